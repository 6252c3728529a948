"""Networks: ResNet-18 trunk, Dis-Net (distribution + count), RSS-Net (per-point RSS), PlaceNet (radar
returns per lidar point), losses."""

from pipeline.models.disnet import DisNet, build_disnet
from pipeline.models.losses import count_loss, kl_loss, poisson_loss, rss_loss
from pipeline.models.placenet import PlaceNet, build_placenet
from pipeline.models.resnet import ResNet18Backbone, resnet18_backbone
from pipeline.models.rssnet import RSSNet, build_rssnet

__all__ = ["DisNet", "build_disnet", "RSSNet", "build_rssnet", "ResNet18Backbone", "resnet18_backbone",
           "PlaceNet", "build_placenet",
           "kl_loss", "count_loss", "rss_loss", "poisson_loss"]
