"""Networks: ResNet-18 trunk, Dis-Net (distribution + count), RSS-Net (per-point RSS), losses."""

from pipeline.models.disnet import DisNet, build_disnet
from pipeline.models.losses import count_loss, kl_loss, rss_loss
from pipeline.models.resnet import ResNet18Backbone, resnet18_backbone
from pipeline.models.rssnet import RSSNet, build_rssnet

__all__ = ["DisNet", "build_disnet", "RSSNet", "build_rssnet", "ResNet18Backbone", "resnet18_backbone",
           "kl_loss", "count_loss", "rss_loss"]
