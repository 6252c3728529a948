"""RSS-Net (paper Fig. 6): image patch + local range image + point vector -> RSS of one radar point.

Branches (each can be switched off for the Table III ablation; at least one must stay on):
- camera: patch (B, 3, ps, ps) RGB float [0, 1] -> 3x3 convs 8, 8, 16 (strides 2, 2, 1; BN + ReLU)
  -> adaptive average pool to 16 x 8 x 32.
- lidar: local range image (B, 32, 128) raw values -> 2 channels (value scaled to [-1, 1] and an
  occupancy mask, so that an empty pixel differs from "same distance as the radar point") ->
  the same conv stack -> 16 x 8 x 32.
- fusion (when camera or lidar is on): concat (32 channels with both, 16 with one) -> 3x3 convs
  -> 16 -> 8 -> 1 -> flatten 256 -> FC 128 + ReLU.
- radar point: [x, y, z] / 50 m and doppler / 10 m/s -> FC 4 -> 128 + ReLU.
- head: concat of the enabled 128-d embeddings (256 with both, 128 with one) -> MLP 128 -> 64 -> 1.

A dropped branch is not built and not computed: the head input shrinks (no zero filling).
The output is the normalised RSS ``(a - rss_min) / (rss_max - rss_min)``; :meth:`RSSNet.to_rss`
converts it to dataset units.

Range image values: 0..255 are lidar pixels (127 = same distance as the radar point); any other
value (negative, > 255, NaN) is an empty pixel, e.g. :data:`pipeline.rangeimage.EMPTY`.

The 0.5 and 99.5 percentiles of a few summaries of the training inputs (:data:`pipeline.patches.INPUT_SUMMARIES`,
:func:`pipeline.patches.input_summaries`) are saved with the weights (``input_low``, ``input_high``):
:meth:`RSSNet.outside_range` says which inputs of another dataset (train.nets_from) the net never
saw the like of, e.g. the denser local range images of a 64-line lidar.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pipeline.models.disnet import IMAGENET_MEAN, IMAGENET_STD
from pipeline.input_range import outside, training_range
from pipeline.patches import INPUT_SUMMARIES

POINT_XYZ_SCALE_M = 50.0
"""Point coordinates enter the network divided by this, metres."""
POINT_DOPPLER_SCALE_MPS = 10.0
"""Doppler enters the network divided by this, m/s."""
FEATURE_HW = (8, 32)
"""Common feature-map size (h, w) of the patch and range-image branches."""


class RSSNet(nn.Module):
    """RSS regressor; ``forward`` returns normalised RSS (B,) (0 = rss_min, 1 = rss_max)."""

    OPTIONAL_BUFFERS = ("input_low", "input_high")
    """Absent from checkpoints written before 2026-12-04: loaded as unbounded (no range check)."""

    def __init__(self, use_camera: bool = True, use_lidar: bool = True, use_radar_point: bool = True,
                 patch_size: int = 32, range_image_size: tuple[int, int] = (128, 32), *,
                 rss_min: float, rss_max: float) -> None:
        super().__init__()
        if not (use_camera or use_lidar or use_radar_point):
            raise ValueError("RSSNet needs at least one input: use_camera, use_lidar or use_radar_point")
        if not rss_max > rss_min:
            raise ValueError(f"RSSNet needs rss_max > rss_min, got {rss_min} .. {rss_max}")
        self.use_camera, self.use_lidar, self.use_radar_point = use_camera, use_lidar, use_radar_point
        self.patch_size = int(patch_size)
        self.range_image_size = (int(range_image_size[0]), int(range_image_size[1]))  # (w, h)
        self.rss_min, self.rss_max = float(rss_min), float(rss_max)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.patch_branch = _branch(3) if use_camera else None
        self.range_branch = _branch(2) if use_lidar else None
        n_maps = 16 * (int(use_camera) + int(use_lidar))
        self.fusion = _fusion(n_maps) if n_maps else None
        self.point_fc = nn.Linear(4, 128) if use_radar_point else None
        n_embed = 128 * (int(n_maps > 0) + int(use_radar_point))
        self.register_buffer("input_low", torch.full((len(INPUT_SUMMARIES),), -torch.inf, dtype=torch.float64))
        self.register_buffer("input_high", torch.full((len(INPUT_SUMMARIES),), torch.inf, dtype=torch.float64))
        self.head = nn.Sequential(nn.Linear(n_embed, 128), nn.ReLU(inplace=True),
                                  nn.Linear(128, 64), nn.ReLU(inplace=True), nn.Linear(64, 1))

    def forward(self, patch: Tensor | None, range_image: Tensor | None, point: Tensor | None) -> Tensor:
        """patch (B, 3, ps, ps) float [0, 1]; range_image (B, h, w) raw 0..255 / empty;
        point (B, 4) [x, y, z m in {D}, doppler m/s]. Inputs of dropped branches may be None."""
        maps, embeds = [], []
        if self.patch_branch is not None:
            ps = self.patch_size
            x = (_need(patch, "patch", (3, ps, ps)) - self.mean) / self.std
            maps.append(F.adaptive_avg_pool2d(self.patch_branch(x), FEATURE_HW))      # (B, 16, 8, 32)
        if self.range_branch is not None:
            w, h = self.range_image_size
            x = normalise_range_image(_need(range_image, "range_image", (h, w)))              # (B, 2, h, w)
            maps.append(F.adaptive_avg_pool2d(self.range_branch(x), FEATURE_HW))      # (B, 16, 8, 32)
        if self.fusion is not None:
            embeds.append(self.fusion(torch.cat(maps, dim=1)))                        # (B, 128)
        if self.point_fc is not None:
            embeds.append(F.relu(self.point_fc(normalise_point(_need(point, "point", (4,))))))  # (B, 128)
        return self.head(torch.cat(embeds, dim=1)).squeeze(1)                        # (B,)

    def set_input_range(self, summaries: np.ndarray) -> None:
        """pipeline.input_range.RANGE_PERCENTILES of the training points' :func:`input_summaries` (N, 4); a
        summary with no value (its input absent) stays unbounded."""
        low, high = training_range(np.asarray(summaries, np.float64).reshape(-1, len(INPUT_SUMMARIES)))
        self.input_low.copy_(torch.as_tensor(low))
        self.input_high.copy_(torch.as_tensor(high))

    def has_input_range(self) -> bool:
        """Whether the net was saved with its training range (not before 2026-12-04)."""
        return bool(torch.isfinite(self.input_low).any())

    def outside_range(self, summaries: np.ndarray) -> np.ndarray:
        """Bool (N, 4): which :func:`input_summaries` (N, 4) lie outside the training range (NaN:
        never)."""
        return outside(np.asarray(summaries, np.float64).reshape(-1, len(INPUT_SUMMARIES)),
                       self.input_low.cpu().numpy(), self.input_high.cpu().numpy())

    def to_rss(self, a_norm: Tensor) -> Tensor:
        """Normalised RSS -> dataset units (rss_min + a_norm * (rss_max - rss_min))."""
        return self.rss_min + a_norm * (self.rss_max - self.rss_min)

    def normalise_rss(self, rss: Tensor) -> Tensor:
        """Dataset units -> normalised RSS (inverse of :meth:`to_rss`)."""
        return (rss - self.rss_min) / (self.rss_max - self.rss_min)


def normalise_range_image(range_image: Tensor) -> Tensor:
    """(B, h, w) raw values -> (B, 2, h, w): [(v - 127.5) / 127.5 or 0 when empty, occupancy 0/1]."""
    r = range_image.float()
    occupied = torch.isfinite(r) & (r >= 0) & (r <= 255)
    value = torch.where(occupied, (r - 127.5) / 127.5, torch.zeros_like(r))
    return torch.stack([value, occupied.to(r.dtype)], dim=1)


def normalise_point(point: Tensor) -> Tensor:
    """(B, 4) [x, y, z m, doppler m/s] -> (B, 4) scaled to order one."""
    scale = point.new_tensor([POINT_XYZ_SCALE_M] * 3 + [POINT_DOPPLER_SCALE_MPS])
    return point.float() / scale


def _need(x: Tensor | None, name: str, per_item_shape: tuple[int, ...]) -> Tensor:
    """Check that an enabled branch got its input with shape (B, *per_item_shape)."""
    if x is None:
        raise ValueError(f"RSSNet: input '{name}' is required by the enabled branches but is None")
    if tuple(x.shape[1:]) != per_item_shape:
        raise ValueError(f"RSSNet: input '{name}' expected shape (B, {', '.join(map(str, per_item_shape))}), "
                         f"got {tuple(x.shape)}")
    return x


def _conv_bn_relu(in_ch: int, out_ch: int, stride: int) -> list[nn.Module]:
    return [nn.Conv2d(in_ch, out_ch, 3, stride=stride, padding=1, bias=False),
            nn.BatchNorm2d(out_ch), nn.ReLU(inplace=True)]


def _branch(in_ch: int) -> nn.Sequential:
    """3x3 convs in_ch -> 8 -> 8 -> 16, strides 2, 2, 1 (a 32 x 128 range image lands on 8 x 32)."""
    return nn.Sequential(*_conv_bn_relu(in_ch, 8, 2), *_conv_bn_relu(8, 8, 2), *_conv_bn_relu(8, 16, 1))


def _fusion(in_ch: int) -> nn.Sequential:
    """(B, in_ch, 8, 32) -> convs 16, 8, 1 -> flatten 256 -> FC 128 + ReLU."""
    return nn.Sequential(*_conv_bn_relu(in_ch, 16, 1), *_conv_bn_relu(16, 8, 1),
                         nn.Conv2d(8, 1, 3, padding=1), nn.Flatten(),
                         nn.Linear(FEATURE_HW[0] * FEATURE_HW[1], 128), nn.ReLU(inplace=True))


def rssnet_kwargs(cfg) -> dict:
    """Constructor arguments of RSSNet from a Config (rssnet.*, patches.*, radar.rss_min/max)."""
    return {"use_camera": cfg.rssnet.use_camera, "use_lidar": cfg.rssnet.use_lidar,
            "use_radar_point": cfg.rssnet.use_radar_point, "patch_size": cfg.patches.patch_size_px,
            "range_image_size": tuple(cfg.patches.range_image_size),
            "rss_min": cfg.radar.rss_min, "rss_max": cfg.radar.rss_max}


def build_rssnet(cfg) -> RSSNet:
    """RSSNet from a Config."""
    return RSSNet(**rssnet_kwargs(cfg))
