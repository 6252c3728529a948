"""Dis-Net augmentations (pipeline.augment): CutMix of point distributions, mirroring."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline import augment


def _frames(b: int = 3, h: int = 12, w: int = 20, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    images = torch.rand(b, 3, h, w, generator=g)
    maps = torch.rand(b, h, w, generator=g) ** 4
    maps = maps / maps.sum(dim=(1, 2), keepdim=True)
    counts = torch.tensor([40.0, 70.0, 25.0])[:b]
    return images, maps, counts


def _draws(monkeypatch, rows):
    """Make cutmix's torch.rand(b, 4) return ``rows``: (mix draw, box side^2, centre y, centre x)."""
    monkeypatch.setattr(torch, "rand", lambda *shape: torch.tensor(rows, dtype=torch.float32))


def test_cutmix_pastes_the_partner_box_and_mixes_expected_points(monkeypatch):
    images, maps, counts = _frames()
    # frame 0: box of side 0.5 centred in the image (rows 3..8, cols 5..14); frame 1: not drawn;
    # frame 2: same box shape, centred at the top-left corner (clipped to rows 0..2, cols 0..4)
    _draws(monkeypatch, [[0.1, 0.25, 0.5, 0.5], [0.9, 0.25, 0.5, 0.5], [0.1, 0.25, 0.0, 0.0]])
    out_img, out_map, out_n = augment.cutmix(images, maps, counts, prob=0.5)
    boxes = {0: (slice(3, 9), slice(5, 15)), 2: (slice(0, 3), slice(0, 5))}
    for i, partner in ((0, 1), (2, 0)):
        inside = torch.zeros(12, 20, dtype=torch.bool)
        inside[boxes[i]] = True
        assert torch.equal(out_img[i][:, inside], images[partner][:, inside])
        assert torch.equal(out_img[i][:, ~inside], images[i][:, ~inside])
        expected = torch.where(inside, counts[partner] * maps[partner], counts[i] * maps[i])
        assert out_n[i].item() == pytest.approx(expected.sum().item(), rel=1e-5)
        torch.testing.assert_close(out_map[i], expected / expected.sum())
    # the undrawn frame is returned bit for bit
    assert torch.equal(out_img[1], images[1]) and torch.equal(out_map[1], maps[1]) and out_n[1] == counts[1]
    np.testing.assert_allclose(out_map.sum(dim=(1, 2)).numpy(), 1.0, rtol=1e-5)


def test_cutmix_whole_image_box_gives_the_partner_and_prob_zero_changes_nothing(monkeypatch):
    images, maps, counts = _frames()
    same = augment.cutmix(images, maps, counts, prob=0.0)
    assert all(a is b for a, b in zip(same, (images, maps, counts)))
    _draws(monkeypatch, [[0.0, 1.0, 0.5, 0.5]] * 3)
    out_img, out_map, out_n = augment.cutmix(images, maps, counts, prob=1.0)
    partner = [1, 2, 0]
    assert torch.equal(out_img, images[partner])
    torch.testing.assert_close(out_map, maps[partner])
    torch.testing.assert_close(out_n, counts[partner])


def test_cutmix_keeps_a_frame_whose_mixed_count_would_vanish(monkeypatch):
    images, maps, counts = _frames(b=2)
    maps = torch.zeros_like(maps)
    maps[0, 3:9, 5:15] = 1.0 / 60   # all of frame 0's points inside the box
    maps[1, 0, 0] = 1.0             # all of frame 1's points outside it
    _draws(monkeypatch, [[0.0, 0.25, 0.5, 0.5], [0.9, 0.25, 0.5, 0.5]])
    out_img, out_map, out_n = augment.cutmix(images, maps, counts, prob=0.5)
    assert torch.equal(out_img, images) and torch.equal(out_map, maps) and torch.equal(out_n, counts)


def test_mirror_flips_image_and_map_of_the_drawn_frames(monkeypatch):
    images, maps, _ = _frames()
    monkeypatch.setattr(torch, "rand", lambda n: torch.tensor([0.2, 0.7, 0.4]))
    out_img, out_map = augment.mirror(images, maps)
    for i, flipped in enumerate((True, False, True)):
        assert torch.equal(out_img[i], images[i].flip(-1) if flipped else images[i])
        assert torch.equal(out_map[i], maps[i].flip(-1) if flipped else maps[i])


def test_photometric_is_a_per_frame_contrast_and_gain_within_the_strength(monkeypatch):
    images, _, _ = _frames()
    assert augment.photometric(images, 0.0) is images
    # frame 0: contrast 1.2, gain 0.8; frame 1: both 1; frame 2: contrast 0.8, gain 1.2
    _draws(monkeypatch, [[1.0, 0.0], [0.5, 0.5], [0.0, 1.0]])
    out = augment.photometric(images, 0.2)
    for i, (c, g) in enumerate(((1.2, 0.8), (1.0, 1.0), (0.8, 1.2))):
        grey = images[i].mean()
        torch.testing.assert_close(out[i], (((images[i] - grey) * c + grey) * g).clamp(0, 1))
    torch.testing.assert_close(out[1], images[1])
    assert out.min() >= 0 and out.max() <= 1
