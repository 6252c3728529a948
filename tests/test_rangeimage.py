"""Tests of pipeline.rangeimage: hand-made points with known pixels, averaging, empty, oracles."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from pipeline.rangeimage import (
    EMPTY, INT32_KEY_PIXELS, local_range_image, local_range_images, local_range_images_brute,
)

P = np.array([10.0, 0.0, 0.0])  # radar point, 10 m straight ahead


def test_hand_made_points_land_on_known_pixels():
    # r_l = 1 m, w x h = 128 x 32.
    lidar = np.array([
        [10.5, 0.0, 0.0],   # dy=0, dz=0 -> u=floor(0.5*128)=64, v=floor(0.5*32)=16; d=0.5 farther
        [9.8, 0.5, 0.0],    # dy=+0.5 -> u=floor(0.25*128)=32, v=16; d=sqrt(0.04+0.25), |l|<10: nearer
        [10.0, -0.5, 0.5],  # dy=-0.5 -> u=floor(0.75*128)=96; dz=+0.5 -> v=floor(0.25*32)=8; d=sqrt(.5)
        [10.0, 0.0, -0.9],  # dz=-0.9 -> v=floor((1-0.1/2)*32)=floor(30.4)=30, u=64; d=0.9
        [10.0, 0.0, 2.0],   # outside r_l: ignored
    ])
    img = local_range_image(lidar, P, 1.0)
    assert img.shape == (32, 128) and img.dtype == np.float32

    def val(l: np.ndarray) -> float:
        d = np.linalg.norm(l - P)
        s = 1.0 if np.linalg.norm(l) > np.linalg.norm(P) else -1.0
        return 127.0 + s * math.floor(255.0 * d / 2.0 + 0.5)

    # Hand values: 0.5 m farther -> 127 + round(63.75) = 191.
    assert val(lidar[0]) == 191.0
    expected = {(16, 64): 191.0, (16, 32): val(lidar[1]), (8, 96): val(lidar[2]), (30, 64): val(lidar[3])}
    # |(9.8, 0.5, 0)| = 9.8127 < 10 -> nearer: 127 - round(255*0.5385/2) = 127 - 69 = 58.
    assert expected[(16, 32)] == 58.0
    # |(10, 0, -0.9)| = 10.04 > 10 -> farther: 127 + round(114.75) = 242.
    assert expected[(30, 64)] == 242.0
    # |(10, -0.5, 0.5)| > 10 -> farther: 127 + round(255 * 0.7071 / 2 = 90.16) = 217.
    assert expected[(8, 96)] == 217.0
    for (v, u), value in expected.items():
        assert img[v, u] == value
    mask = np.ones_like(img, dtype=bool)
    for v, u in expected:
        mask[v, u] = False
    assert np.all(img[mask] == EMPTY)


def test_extreme_offsets_reach_the_corner_pixels():
    # dy = -0.7, dz = -0.7 (d = 0.99 < 1): u = floor(0.5 * 1.7 * 128) = 108, v = floor(0.85 * 32) = 27.
    # dy = +0.999: u = floor(0.0005 * 128) = 0;  dy = -0.999: u = floor(0.9995 * 128) = 127.
    # dz = +0.999: v = 0;  dz = -0.999: v = floor(0.9995 * 32) = 31.
    lidar = P + np.array([[0.0, -0.7, -0.7], [0.0, 0.999, 0.0], [0.0, -0.999, 0.0], [0.0, 0.0, 0.999],
                          [0.0, 0.0, -0.999]])
    img = local_range_image(lidar, P, 1.0)
    for v, u in [(27, 108), (16, 0), (16, 127), (0, 64), (31, 64)]:
        assert img[v, u] != EMPTY
    assert np.count_nonzero(img != EMPTY) == 5


def test_shared_pixel_is_averaged():
    # Two points in pixel (16, 64): 0.24 m farther (127 + round(30.6) = 158) and 0.3 m nearer with
    # dy = dz = -0.001 (u = floor(64.064) = 64, v = floor(16.016) = 16; 127 - round(38.25) = 89).
    lidar = np.array([[10.24, 0.0, 0.0], [9.7, -0.001, -0.001]])
    img = local_range_image(lidar, P, 1.0)
    assert img[16, 64] == pytest.approx((158.0 + 89.0) / 2.0)
    assert np.count_nonzero(img != EMPTY) == 1


def test_point_exactly_at_radius_is_excluded_and_values_stay_in_range():
    lidar = np.array([[11.0, 0.0, 0.0], [9.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    img = local_range_image(lidar, P, 1.0)
    assert np.count_nonzero(img != EMPTY) == 1
    # The coincident point: distance 0, |l| == |p| -> s = -1, 127 - 0 = 127.
    assert img[16, 64] == 127.0


def test_equal_distance_from_the_radar_counts_as_nearer_and_levels_round_half_up():
    # |(4, 3, 0)| == |(3, 4, 0)| == 5 exactly: s = -1. d = sqrt(2), r_l = 2: level round(90.16) = 90.
    img = local_range_image(np.array([[4.0, 3.0, 0.0]]), np.array([3.0, 4.0, 0.0]), 2.0)
    assert img[img != EMPTY].tolist() == [127.0 - 90.0]
    # r_l = 127.5: level = round(d), with d = 0.5 and 2.5 exactly: halves go up (1 and 3), not to even
    for d, level in [(0.5, 1), (2.5, 3)]:
        img = local_range_image(P + [[d, 0.0, 0.0]], P, 127.5)
        assert img[img != EMPTY].tolist() == [127.0 + level]


def test_int32_sort_keys_cannot_overflow():
    """Below INT32_KEY_PIXELS pixels in all, (pixel << 8) | value must fit a signed 32-bit key."""
    assert ((INT32_KEY_PIXELS - 1) << 8) | 255 <= np.iinfo(np.int32).max


def test_empty_inputs():
    assert np.all(local_range_image(np.zeros((0, 3)), P, 1.0) == EMPTY)
    assert local_range_images(np.ones((5, 3)), np.zeros((0, 3)), 1.0).shape == (0, 32, 128)
    assert np.all(local_range_image(np.array([[50.0, 0, 0]]), P, 1.0, size_wh=(16, 8)) == EMPTY)
    assert local_range_images_brute(np.zeros((0, 3)), P[None], 1.0).shape == (1, 32, 128)


def test_errors():
    with pytest.raises(ValueError, match="expected shape"):
        local_range_image(np.zeros((4, 2)), P, 1.0)
    with pytest.raises(ValueError, match="r_l"):
        local_range_image(np.zeros((4, 3)), P, 0.0)
    with pytest.raises(ValueError, match="size_wh"):
        local_range_image(np.zeros((4, 3)), P, 1.0, size_wh=(0, 4))


def _reference(lidar: np.ndarray, p: np.ndarray, r_l: float, w: int, h: int) -> np.ndarray:
    """Straight per-point loop over eqs. 18-21 (test oracle)."""
    sums = np.zeros((h, w))
    counts = np.zeros((h, w))
    for l in lidar:
        d = np.linalg.norm(l - p)
        if d >= r_l:
            continue
        u = min(max(math.floor(0.5 * (1 - (l[1] - p[1]) / r_l) * w), 0), w - 1)
        v = min(max(math.floor((1 - (l[2] - p[2] + r_l) / (2 * r_l)) * h), 0), h - 1)
        s = 1.0 if np.linalg.norm(l) > np.linalg.norm(p) else -1.0
        sums[v, u] += 127 + s * math.floor(255 * d / (2 * r_l) + 0.5)
        counts[v, u] += 1
    return np.where(counts > 0, sums / np.maximum(counts, 1), EMPTY)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_lidar=st.integers(0, 300), n_points=st.integers(1, 4),
       r_l=st.sampled_from([0.5, 1.0, 2.0]), size=st.sampled_from([(128, 32), (16, 8), (5, 3)]))
def test_batched_kdtree_and_brute_match_reference(seed, n_lidar, n_points, r_l, size):
    rng = np.random.default_rng(seed)
    points = rng.uniform([2, -5, -1], [20, 5, 1], (n_points, 3))
    owner = rng.integers(0, n_points, n_lidar)
    lidar = points[owner] + rng.uniform(-1.5 * r_l, 1.5 * r_l, (n_lidar, 3))
    lidar = np.round(lidar, 2)  # duplicates / shared pixels happen
    fast = local_range_images(lidar, points, r_l, size)
    brute = local_range_images_brute(lidar, points, r_l, size)
    np.testing.assert_array_equal(fast, brute)
    for i in range(n_points):
        np.testing.assert_allclose(fast[i], _reference(lidar, points[i], r_l, *size), rtol=1e-6)
        occupied = fast[i][fast[i] != EMPTY]
        assert np.all((occupied >= 0) & (occupied <= 254))


def test_reuses_given_tree_and_matches_single():
    rng = np.random.default_rng(0)
    lidar = rng.uniform(-3, 3, (2000, 3)) + P
    points = P + rng.uniform(-1, 1, (3, 3))
    tree = cKDTree(lidar)
    batch = local_range_images(lidar, points, 1.0, tree=tree)
    for i in range(3):
        np.testing.assert_array_equal(batch[i], local_range_image(lidar, points[i], 1.0, tree=tree))


def test_any_tree_of_the_lidar_gives_the_same_images():
    """synthesize passes the tree its candidates' neighbours came from (pipeline.placement's, other
    leaves): the pairs come in another order, the images are the same to the bit."""
    from pipeline.placement import neighbour_tree
    from pipeline.rangeimage import lidar_tree

    rng = np.random.default_rng(1)
    lidar = (rng.uniform(-3, 3, (3000, 3)) + P).astype(np.float32)
    points = lidar[:200].astype(np.float64) + rng.normal(size=(200, 3)) * 0.05
    expect = local_range_images(lidar, points, 1.0, tree=lidar_tree(lidar.astype(np.float64)))
    np.testing.assert_array_equal(local_range_images(lidar, points, 1.0, tree=neighbour_tree(lidar)), expect)


def test_a_tree_of_other_points_is_refused():
    """The tree's indices are taken as rows of lidar_D: pipeline.placement.neighbour_tree of a cloud
    with a NaN row holds its finite points only, whose indices would pick the wrong lidar points."""
    from pipeline.placement import neighbour_tree

    rng = np.random.default_rng(2)
    lidar = rng.uniform(-3, 3, (500, 3)) + P
    lidar[10] = np.nan
    with pytest.raises(ValueError, match="the tree holds 499 points, lidar_D 500"):
        local_range_images(lidar, lidar[20:30], 1.0, tree=neighbour_tree(lidar))


def test_64_bit_sort_keys_give_the_same_images(monkeypatch):
    """Large batches sort 64-bit keys (32-bit ones would overflow): same images as 32-bit keys."""
    import pipeline.rangeimage as R

    rng = np.random.default_rng(1)
    points = P + rng.uniform(-2, 2, (20, 3))
    lidar = np.round(points[rng.integers(0, 20, 3000)] + rng.uniform(-1, 1, (3000, 3)), 2)
    small = local_range_images(lidar, points, 1.0)
    monkeypatch.setattr(R, "INT32_KEY_PIXELS", 0)
    large = local_range_images(lidar, points, 1.0)
    np.testing.assert_array_equal(large, small)
    assert (small != EMPTY).sum() > 1000
