"""Dis-Net training augmentations on batches of (image, target map, count) frames.

All draw from torch's global RNG, whose state every epoch's checkpoint saves, so a resumed run
draws exactly what an uninterrupted one would.

Shapes: images (B, 3, H, W) float; maps (B, H, W) float, each summing to 1 (the radar-point
distribution over pixels); counts (B,) float, radar points per frame.
"""

from __future__ import annotations

import torch
from torch import Tensor

MIN_MIXED_COUNT = 1.0
"""A CutMix frame whose mixed count falls below this many points keeps its own content."""


def mirror(images: Tensor, maps: Tensor) -> tuple[Tensor, Tensor]:
    """Mirror image and map left-right together, each frame with probability 1/2."""
    flipped = (torch.rand(images.shape[0]) < 0.5).to(images.device)
    return (torch.where(flipped[:, None, None, None], images.flip(-1), images),
            torch.where(flipped[:, None, None], maps.flip(-1), maps))


def photometric(images: Tensor, strength: float) -> Tensor:
    """Brightness and contrast jitter: per frame, contrast about the frame's mean grey level and a
    gain, each a factor drawn from U(1 - strength, 1 + strength); clipped to [0, 1]. Hue and
    saturation are kept (a surface's colour may tell its material, which the radar sees)."""
    if strength <= 0.0:
        return images
    factors = 1.0 + strength * (2.0 * torch.rand(images.shape[0], 2) - 1.0)
    contrast, gain = (f.to(images.device, images.dtype)[:, None, None, None] for f in factors.unbind(1))
    grey = images.mean(dim=(1, 2, 3), keepdim=True)
    return (((images - grey) * contrast + grey) * gain).clamp(0.0, 1.0)


def cutmix(images: Tensor, maps: Tensor, counts: Tensor, prob: float) -> tuple[Tensor, Tensor, Tensor]:
    """CutMix (Yun et al., ICCV 2019) for point distributions: with probability ``prob`` per frame,
    a random box of the next frame in the batch (cyclically) is pasted into the frame.

    The box keeps a share lambda ~ U(0, 1) of the frame's area (sides sqrt(1 - lambda) of H and W,
    centre uniform, clipped at the border). The new targets are what the composite scene's radar
    would return if each region kept its own points: expected points n * map outside the box from
    the frame and inside it from the partner; count = their sum, map = their normalised sum. The
    frame keeps its own ego speed (the partner's points came from the partner's speed: an
    approximation, as is ignoring occlusion and blur across the box edge). A frame whose mixed
    count would be below MIN_MIXED_COUNT is left unchanged. Returns new (images, maps, counts).
    """
    b, _, h, w = images.shape
    if prob <= 0.0 or b < 2:
        return images, maps, counts
    u = torch.rand(b, 4)
    side = torch.sqrt(u[:, 1])                                          # sqrt(1 - lambda), lambda ~ U(0, 1)
    box_h, box_w = (side * h).round().long(), (side * w).round().long()
    cy, cx = (u[:, 2] * h).long(), (u[:, 3] * w).long()
    top, left = cy - box_h // 2, cx - box_w // 2
    y0, y1 = top.clamp(0, h), (top + box_h).clamp(0, h)
    x0, x1 = left.clamp(0, w), (left + box_w).clamp(0, w)
    rows, cols = torch.arange(h)[None, :, None], torch.arange(w)[None, None, :]
    inside = ((rows >= y0[:, None, None]) & (rows < y1[:, None, None])
              & (cols >= x0[:, None, None]) & (cols < x1[:, None, None]))            # (B, H, W)
    inside &= (u[:, 0] < prob)[:, None, None]
    partner = torch.roll(torch.arange(b), -1)
    inside = inside.to(maps.device)
    expected = maps * counts[:, None, None]                             # points per pixel (B, H, W)
    mixed = torch.where(inside, expected[partner], expected)
    mixed_count = mixed.sum(dim=(1, 2))
    changed = inside.any(dim=2).any(dim=1) & (mixed_count >= MIN_MIXED_COUNT)  # others keep their exact targets
    inside &= changed[:, None, None]
    return (torch.where(inside[:, None], images[partner], images),
            torch.where(changed[:, None, None], mixed / mixed_count[:, None, None], maps),
            torch.where(changed, mixed_count, counts))
