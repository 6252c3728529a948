"""Baselines: counts, field of view, sampling, ego motion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline import baselines as B
from pipeline.geometry import (
    cartesian_to_spherical,
    invert_transform,
    project_to_image,
    transform_points,
)
from pipeline.synthesis import sample_pixels


def _camera():
    """Camera looking along radar x, 200 x 100 pixels, 90 deg horizontal field of view."""
    K = np.array([[100.0, 0, 99.5], [0, 100.0, 49.5], [0, 0, 1]])
    T_cam_radar = np.array([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]])
    return K, T_cam_radar, (200, 100)


def test_methods_table():
    names = [s.name for s in B.METHODS]
    assert names[0] == "model" and len(set(names)) == len(names)
    for required in ("uniform", "mean-map", "lidar-subsample", "model-oracle-count", "mean-map-oracle-count",
                     "previous-frame"):
        assert required in names
    assert B.method_by_name("mean-map").rss_source == "train-dist"
    assert B.method_by_name("uniform").rss_source == "median"
    assert [s.name for s in B.METHODS if s.is_model] == ["model", "model-oracle-count", "model-oracle-map"]
    assert B.REFERENCE_ROWS == ("no-points",) and B.method_by_name("no-points").kind == "empty"
    real = np.arange(12.0).reshape(3, 4) / 66.0
    assert B.choose_map(B.method_by_name("model-oracle-map"), (4, 3), real_map_hw=real) is real
    with pytest.raises(ValueError, match="real heatmap"):
        B.choose_map(B.method_by_name("model-oracle-map"), (4, 3))
    with pytest.raises(ValueError):
        B.method_by_name("nope")
    with pytest.raises(ValueError):
        B.BaselineSpec("x", "bogus", "mean", "median")


def test_baselines_sample_their_maps_at_full_weight():
    """The model's rows generate with the configured map weight; a baseline that samples a map
    always with weight 1 (it samples that map), the rest of the configuration untouched."""
    from pipeline.config import load_config

    cfg = load_config("synthetic", {"placement.map_weight": "0.3", "placement.voxel_m": "0.5"}, environ={})
    for spec in B.METHODS:
        got = B.generation_config(spec, cfg)
        if spec.is_model:
            assert got is cfg
        else:
            assert got.placement.map_weight == 1.0 and got.placement.voxel_m == 0.5
            assert got.synth == cfg.synth and got.radar == cfg.radar
    assert cfg.placement.map_weight == 0.3   # not changed in place


def test_choose_count_map_rss():
    rng = np.random.default_rng(0)
    assert B.choose_count(B.method_by_name("uniform"), n_bar=7, n_true=3) == 7
    assert B.choose_count(B.method_by_name("mean-map-oracle-count"), n_bar=7, n_true=3) == 3
    assert B.choose_count(B.method_by_name("model"), n_bar=7, n_true=3, n_hat=4.6) == 5
    with pytest.raises(ValueError):
        B.choose_count(B.method_by_name("model"), 7, 3)
    m = B.choose_map(B.method_by_name("uniform"), (4, 3))
    assert m.shape == (3, 4) and m.sum() == pytest.approx(1.0) and np.ptp(m) == 0
    assert B.choose_map(B.method_by_name("lidar-subsample"), (4, 3)) is None
    train = np.array([1.0, 2.0, 10.0])
    r = B.choose_rss(B.method_by_name("mean-map"), 500, rng, 2.0, train)
    assert r.shape == (500,) and set(np.unique(r)) <= set(train) and len(np.unique(r)) == 3
    assert np.all(B.choose_rss(B.method_by_name("uniform"), 4, rng, 2.5) == 2.5)
    assert B.choose_rss(B.method_by_name("model"), 4, rng, 2.5) is None


def test_uniform_map_sampling_covers_image():
    prob = B.choose_map(B.method_by_name("uniform"), (200, 100))
    uv = sample_pixels(prob, 5000, np.random.default_rng(1))
    assert uv.shape == (5000, 2)
    assert uv[:, 0].min() >= -0.5 and uv[:, 0].max() < 199.5 and uv[:, 1].min() >= -0.5 and uv[:, 1].max() < 99.5
    assert abs(uv[:, 0].mean() - 99.5) < 3 and abs(uv[:, 1].mean() - 49.5) < 1.5


def test_mean_map_sampling_follows_map():
    m = np.zeros((4, 5))
    m[1, 3] = 3.0
    m[2, 0] = 1.0
    prob = B.choose_map(B.method_by_name("mean-map"), (5, 4), mean_map_hw=m)
    uv = sample_pixels(prob, 8000, np.random.default_rng(2))
    px = np.round(uv).astype(int)
    assert np.all(np.abs(uv - px) <= 0.5)
    hits = {(u, v) for u, v in px}
    assert hits == {(3, 1), (0, 2)}
    share = np.mean((px[:, 0] == 3) & (px[:, 1] == 1))
    assert share == pytest.approx(0.75, abs=0.02)


def test_lidar_subsample_fov_count_doppler():
    K, T, size = _camera()
    rng = np.random.default_rng(3)
    lidar = rng.uniform([-60, -60, -5], [60, 60, 5], (20000, 3))
    ego = np.array([10.0, 0.0, 0.0])
    pts = B.lidar_subsample(lidar, 300, 60.0, 30.0, 50.0, K, T, size, rng, ego_velocity_D=ego, rss_value=3.5)
    assert pts.shape == (300, 5) and pts.dtype == np.float32
    sph = cartesian_to_spherical(pts[:, :3])
    assert np.all(sph[:, 0] <= 50.0 + 1e-4)
    assert np.all(np.abs(np.rad2deg(sph[:, 1])) <= 30.0 + 1e-4)
    assert np.all(np.abs(np.rad2deg(sph[:, 2])) <= 15.0 + 1e-4)
    assert project_to_image(pts[:, :3], K, T, size)[2].all()
    assert np.all(pts[:, 4] == 3.5)
    u = pts[:, :3] / np.linalg.norm(pts[:, :3], axis=1, keepdims=True)
    assert np.allclose(pts[:, 3], -(u @ ego), atol=1e-4)
    assert len(np.unique(pts[:, :3], axis=0)) == 300  # without replacement
    few = B.lidar_subsample(lidar[:50], 300, 60.0, 30.0, 50.0, K, T, size, rng, ego_velocity_D=ego, rss_value=0)
    inside = B.region_mask(lidar[:50], 60.0, 30.0, 50.0, K, T, size).sum()
    assert len(few) == inside < 50
    empty = B.lidar_subsample(np.zeros((0, 3)), 10, 60.0, 30.0, 50.0, K, T, size, rng, ego_velocity_D=ego,
                              rss_value=0)
    assert empty.shape == (0, 5)


def test_lidar_subsample_wraps_doppler():
    K, T, size = _camera()
    rng = np.random.default_rng(4)
    lidar = rng.uniform([5, -5, -1], [40, 5, 1], (500, 3))
    pts = B.lidar_subsample(lidar, 100, 90.0, 40.0, 50.0, K, T, size, rng, ego_velocity_D=np.array([20.0, 0, 0]),
                            rss_value=0.0, doppler_span_mps=10.0)
    assert pts[:, 3].min() >= -5.0 and pts[:, 3].max() < 5.0


def test_ego_motion_straight_and_turning():
    v = np.array([10.0, 1.0, 0.2])
    T = B.ego_motion_transform(v, 0.1)
    p_prev = np.array([[20.0, 3.0, 1.0]])
    assert transform_points(T, p_prev) == pytest.approx(p_prev - v * 0.1)
    # turning: half steps composed equal the full step, and a tiny yaw rate tends to straight motion
    full = B.ego_motion_transform(v, 0.2, yaw_rate_rps=0.5)
    half = B.ego_motion_transform(v, 0.1, yaw_rate_rps=0.5)
    assert half @ half == pytest.approx(full, abs=1e-12)
    assert B.ego_motion_transform(v, 0.1, 1e-7) == pytest.approx(T, abs=1e-7)
    assert invert_transform(full) @ full == pytest.approx(np.eye(4), abs=1e-12)
    # a static point ahead appears rotated to the right when the car turns left
    q = transform_points(B.ego_motion_transform(np.zeros(3), 1.0, math.radians(10)), np.array([[10.0, 0, 0]]))
    assert math.degrees(math.atan2(q[0, 1], q[0, 0])) == pytest.approx(-10.0)


def test_previous_frame_moves_points_keeps_columns():
    prev = np.array([[10.0, 2.0, 0.5, -1.0, 12.0], [30.0, -4.0, 1.0, 0.5, 3.0]], np.float32)
    T = B.ego_motion_transform(np.array([5.0, 0, 0]), 0.1)
    out = B.previous_frame(prev, T)
    assert out.shape == (2, 5)
    assert out[:, 0] == pytest.approx(prev[:, 0] - 0.5)
    assert np.array_equal(out[:, 1:], prev[:, 1:])
    assert B.previous_frame(np.zeros((0, 5)), T).shape == (0, 5)


def test_mean_count_rounds_to_the_nearest_count():
    """n_bar is the training mean rounded (not truncated), and at least 1."""
    assert B.mean_count([10, 20, 31]) == 20          # mean 20.33
    assert B.mean_count([10, 20, 32]) == 21          # mean 20.67
    assert B.mean_count([3, 4, 4]) == 4              # mean 3.67
    assert B.mean_count([0, 0, 0, 1]) == 1           # mean 0.25, but never 0 points
    assert B.mean_count([]) == 0                     # no training frame: nothing to draw
