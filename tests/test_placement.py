"""Lidar-point placement (pipeline.placement) and PlaceNet: candidates, features, the training
target, the placement weights against a brute-force sum, the voxel-limited draw, and PlaceNet's
standardisation, loss, training and resume."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from pipeline import inference as Inf
from pipeline import net_baselines as B
from pipeline import placement as P
from pipeline import training as T
from pipeline.config import load_config
from pipeline.errors import ConfigError
from pipeline.frame import Object3D
from pipeline.geometry import cartesian_to_spherical, invert_transform, project_to_image
from pipeline.models import PlaceNet, poisson_loss

torch.set_num_threads(1)

# Radar {D}: x fwd, y left, z up. Camera: x right, y down, z fwd. Columns = camera axes in {D}.
T_RADAR_CAM = np.eye(4)
T_RADAR_CAM[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
T_RADAR_CAM[:3, 3] = (0.3, 0.4, 0.5)
K_SMALL = np.array([[100.0, 0.0, 79.5], [0.0, 100.0, 39.5], [0.0, 0.0, 1.0]])  # 160 x 80 image


def wall(x_m: float = 10.0, step: float = 0.1) -> np.ndarray:
    """Lidar wall x = x_m, y in [-3, 3), z in [-1, 1) on a ``step`` grid, (N, 3) m."""
    y, z = np.meshgrid(np.arange(-3, 3, step), np.arange(-1, 1, step))
    return np.column_stack([np.full(y.size, x_m), y.ravel(), z.ravel()])


# --------------------------------------------------------------------------- candidates


def test_lidar_candidates_keep_only_points_the_radar_and_camera_both_see():
    points = np.array([
        [10.0, 0.0, 0.0],     # ahead: kept
        [0.3, 0.0, 0.0],      # nearer than MIN_RANGE_M
        [60.0, 0.0, 0.0],     # beyond max range
        [10.0, 2.5, 0.0],     # azimuth 14 deg > 20 / 2, inside the image
        [10.0, 0.0, 4.0],     # elevation 21.8 deg > 20 / 2, inside the image
        [-10.0, 0.0, 0.0],    # behind
        [10.0, 9.0, 0.0],     # azimuth 42 deg: outside the 160 px image
        [np.nan, 0.0, 0.0],
        [20.0, -1.0, 0.5],    # kept
        [10.0, 0.0, -2.2],    # elevation -12.4 deg < -20 / 2, inside the image (row 67)
    ])
    idx, uv = P.lidar_candidates(points, K_SMALL, T_RADAR_CAM, (160, 80), fov_az_deg=20.0, fov_el_deg=20.0,
                                 max_range_m=50.0)
    np.testing.assert_array_equal(idx, [0, 8])
    wide, _ = P.lidar_candidates(points, K_SMALL, T_RADAR_CAM, (160, 80), 100.0, 20.0, 50.0)
    np.testing.assert_array_equal(wide, [0, 3, 8])    # the radar sees 42 deg, the camera does not
    tall, _ = P.lidar_candidates(points, K_SMALL, T_RADAR_CAM, (160, 80), 20.0, 30.0, 50.0)
    np.testing.assert_array_equal(tall, [0, 8, 9])
    expect, _, _ = project_to_image(points[idx], K_SMALL, invert_transform(T_RADAR_CAM), (160, 80))
    np.testing.assert_allclose(uv, expect)
    with pytest.raises(ValueError, match="lidar_D"):
        P.lidar_candidates(points[:, :2], K_SMALL, T_RADAR_CAM, (160, 80), 80.0, 20.0, 50.0)


def test_candidate_features_hand_computed():
    gx, gy = np.meshgrid(np.arange(-3, 3, 0.1), np.arange(4, 6, 0.1))
    ground = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, -1.5)])
    lidar = np.vstack([wall(10.0), ground])
    cand = np.array([[10.0, 0.0, 0.0], [0.5, 5.0, -1.5], [10.0, 2.0, 0.5]])
    uv = np.array([[80.0, 40.0], [0.0, 0.0], [159.0, 79.0]])
    image = np.zeros((80, 160, 3), np.uint8)
    image[40, 80] = (255, 0, 51)                                # one coloured pixel under the first candidate
    ego = np.array([4.0, 0.0, 0.0])
    box = Object3D("Car", np.array([10.0, 2.0, 0.5]), np.array([1.0, 1.0, 1.0]), 0.0,
                   velocity_D=np.array([4.0, 0.0, 0.0]))    # moves with the ego: range rate 0
    f = P.candidate_features(cand, uv, image, lidar, ego, [box])
    assert f.shape == (3, len(P.FEATURES)) and f.dtype == np.float32 and np.all(np.isfinite(f))
    col = {name: f[:, k] for k, name in enumerate(P.FEATURES)}
    rae = cartesian_to_spherical(cand)
    np.testing.assert_allclose(col["log_range"], np.log(rae[:, 0]), rtol=1e-6)
    np.testing.assert_allclose(col["z_m"], cand[:, 2])
    np.testing.assert_allclose(col["azimuth"], rae[:, 1], atol=1e-6)
    np.testing.assert_allclose(col["elevation"], rae[:, 2], atol=1e-6)
    rate = np.abs(cand @ ego / rae[:, 0]) * [1, 1, 0]           # static: |unit . ego|; in the box: 0
    np.testing.assert_allclose(col["abs_range_rate"], rate, atol=1e-5)
    np.testing.assert_allclose(col["abs_range_rate_clip3"], np.minimum(rate, 3), atol=1e-5)
    np.testing.assert_allclose(col["abs_range_rate_clip05"], np.minimum(rate, 0.5), atol=1e-5)
    np.testing.assert_array_equal(col["on_object"], [0, 0, 1])
    np.testing.assert_allclose(col["ego_speed"], 4.0)
    np.testing.assert_allclose([col["red"][0], col["green"][0], col["blue"][0]], [1.0, 0.0, 0.2], atol=1e-6)
    np.testing.assert_allclose(col["red_mean"][0], 1 / 25, atol=1e-6)
    np.testing.assert_allclose(col["red_std"][0], np.sqrt(1 / 25 - 1 / 625), atol=1e-5)
    # the wall's normal is x: seen head on from the origin at (10, 0, 0); the ground's is z
    assert col["cos_incidence"][0] == pytest.approx(1.0, abs=1e-6)
    assert col["normal_z2"][0] == pytest.approx(0.0, abs=1e-6) and col["normal_z2"][1] == pytest.approx(1.0)
    np.testing.assert_allclose(col["cos_incidence"][1], 1.5 / rae[1, 0], rtol=1e-5)
    assert np.all(col["planarity"] < 1e-6)
    # the 10th nearest point of a 10 cm grid is 0.2 m away (plus the 1 mm floor)
    np.testing.assert_allclose(np.exp(col["log_neighbour_dist"][:2]), 0.201, rtol=1e-5)
    empty = P.candidate_features(np.zeros((0, 3)), np.zeros((0, 2)), image, lidar, ego, [])
    assert empty.shape == (0, len(P.FEATURES))
    # too few lidar points for a normal: the geometry columns are zeros, not NaN
    few = P.candidate_features(cand, uv, image, lidar[:2], ego, [])
    assert np.all(np.isfinite(few)) and np.all(few[:, -4:] == 0)
    # the threads of the neighbour query and the normals change nothing (synthesize gives them the nets'
    # threads; the candidates are split into blocks of at least MIN_BLOCK_ROWS)
    cloud = np.random.default_rng(2).uniform(-5, 5, (3 * 3 * P.MIN_BLOCK_ROWS, 3)) + [20.0, 0.0, 0.0]
    many = cloud[::3]
    pixels = np.zeros((len(many), 2))
    for workers in (2, 3):
        np.testing.assert_array_equal(P.candidate_features(many, pixels, image, cloud, ego, [], workers=workers),
                                      P.candidate_features(many, pixels, image, cloud, ego, []))


def test_planarity_is_the_smallest_share_of_the_spread():
    """Ten neighbours spread equally along x, y and z (covariance 2 a^2 I): planarity 1/3 whatever a;
    flattened to a disc in z: 0."""
    for a in (0.1, 2.0):
        cloud = np.vstack([a * np.vstack([np.eye(3), -np.eye(3)]), np.zeros((4, 3))]) + [10.0, 0.0, 0.0]
        f = P.candidate_features(cloud[:1], np.zeros((1, 2)), np.zeros((4, 4, 3), np.uint8), cloud,
                                 np.zeros(3), [])
        assert f[0, P.FEATURES.index("planarity")] == pytest.approx(1 / 3, rel=1e-5)
        disc = cloud * [1.0, 1.0, 0.0]
        f = P.candidate_features(disc[:1], np.zeros((1, 2)), np.zeros((4, 4, 3), np.uint8), disc, np.zeros(3), [])
        assert f[0, P.FEATURES.index("planarity")] == pytest.approx(0.0, abs=1e-9)


def test_smallest_eigenpair_matches_eigh_and_handles_degenerate_matrices():
    rng = np.random.default_rng(4)
    # covariances of 10-point patches: planes, lines and blobs in random orientations
    pts = rng.normal(size=(3000, 10, 3)) * rng.uniform(0, 1, (3000, 1, 3)) ** 3
    pts = pts @ np.linalg.qr(rng.normal(size=(3000, 3, 3)))[0]
    nb = pts - pts.mean(axis=1, keepdims=True)
    cov = nb.transpose(0, 2, 1) @ nb
    value, vector = P.smallest_eigenpair_sym3(cov)
    w, v = np.linalg.eigh(cov)
    trace = w.sum(axis=1)
    np.testing.assert_allclose(value, w[:, 0], rtol=0, atol=1e-7 * trace.max())
    assert np.max(np.abs(value - w[:, 0]) / trace) < 1e-7
    np.testing.assert_allclose(np.linalg.norm(vector, axis=1), 1.0, atol=1e-12)
    separated = (w[:, 1] - w[:, 0]) > 1e-6 * trace  # the eigenvector is unique up to sign
    assert separated.mean() > 0.9
    np.testing.assert_allclose(np.abs(np.sum(vector * v[:, :, 0], axis=1))[separated], 1.0, atol=1e-8)
    # (nearly) repeated smallest eigenvalue: any unit vector of its eigenspace; isotropic: z
    value, vector = P.smallest_eigenpair_sym3(np.stack([np.diag([0.0, 0.0, 1.0]), np.diag([2.0, 0.0, 0.0]),
                                                       np.eye(3), np.zeros((3, 3))]))
    np.testing.assert_allclose(value, [0, 0, 1, 0], atol=1e-7)
    assert abs(vector[0, 2]) < 1e-6 and abs(vector[1, 0]) < 1e-6
    np.testing.assert_allclose(np.linalg.norm(vector, axis=1), 1.0)
    np.testing.assert_allclose(vector[2:], [[0, 0, 1], [0, 0, 1]])


def _reference_colour_and_geometry(points_D, uv, image, lidar_D):
    """Columns 9: of candidate_features as computed until 2026-12-06, whole-array numpy steps: the
    faster steps since (std at the pixels only, neighbour-major sums, the eigenpair on (9, C) rows)
    must give the same bits."""
    img = image.astype(np.float32) / 255.0
    mean = cv2.blur(img, (P.COLOUR_WINDOW_PX, P.COLOUR_WINDOW_PX))
    std = np.sqrt(np.maximum(cv2.blur(img * img, (P.COLOUR_WINDOW_PX, P.COLOUR_WINDOW_PX)) - mean * mean, 0.0))
    px = np.clip(np.rint(uv).astype(np.int64), 0, [img.shape[1] - 1, img.shape[0] - 1])
    colour = np.concatenate([a[px[:, 1], px[:, 0]] for a in (img, mean, std)], axis=1)
    cloud = np.asarray(lidar_D, np.float64)
    cloud = cloud[np.all(np.isfinite(cloud), axis=1)]
    dist, idx = cKDTree(cloud, balanced_tree=False, compact_nodes=False).query(points_D, k=P.NORMAL_NEIGHBOURS)
    nb = cloud[idx]
    nb -= nb.mean(axis=1, keepdims=True)
    cov = np.matmul(nb.transpose(0, 2, 1), nb)
    smallest, normal = _reference_eigenpair(cov)
    r = np.linalg.norm(points_D, axis=1)
    geometry = np.column_stack([np.abs(np.sum(normal * points_D, axis=1)) / np.maximum(r, 1e-9),
                                np.maximum(smallest, 0.0) / np.maximum(np.trace(cov, axis1=1, axis2=2), 1e-12),
                                np.log(dist[:, -1] + 1e-3), normal[:, 2] ** 2])
    return np.column_stack([colour, geometry]).astype(np.float32)


def _reference_eigenpair(a):
    """smallest_eigenpair_sym3 as computed until 2026-12-06, on (C, 3, 3) arrays."""
    xx, yy, zz, xy, xz, yz = a[:, 0, 0], a[:, 1, 1], a[:, 2, 2], a[:, 0, 1], a[:, 0, 2], a[:, 1, 2]
    q = (xx + yy + zz) / 3
    dx, dy, dz = xx - q, yy - q, zz - q
    p = np.sqrt((dx * dx + dy * dy + dz * dz + 2 * (xy * xy + xz * xz + yz * yz)) / 6)
    safe = np.where(p > 0, p, 1.0)
    det = dx * (dy * dz - yz * yz) - xy * (xy * dz - yz * xz) + xz * (xy * yz - dy * xz)
    phi = np.arccos(np.clip(det / safe ** 3 / 2, -1.0, 1.0)) / 3
    smallest = np.where(p > 0, q + 2 * p * np.cos(phi + 2 * np.pi / 3), q)
    m = a - smallest[:, None, None] * np.eye(3)
    crosses = np.stack([np.cross(m[:, 0], m[:, 1]), np.cross(m[:, 0], m[:, 2]), np.cross(m[:, 1], m[:, 2])], axis=1)
    size = np.einsum("cij,cij->ci", crosses, crosses)
    rows = np.arange(len(a))
    best = np.argmax(size, axis=1)
    vec = crosses[rows, best]
    scale = np.max(np.abs(m), axis=(1, 2))
    degenerate = size[rows, best] <= (1e-10 * scale * scale) ** 2
    if np.any(degenerate):
        m = m[degenerate]
        row = m[np.arange(len(m)), np.argmax(np.einsum("cij,cij->ci", m, m), axis=1)]
        other = np.cross(row, np.eye(3)[np.argmin(np.abs(row), axis=1)])
        vec[degenerate] = np.where(np.any(row != 0, axis=1)[:, None], other, [0.0, 0.0, 1.0])
    return smallest, vec / np.linalg.norm(vec, axis=1, keepdims=True)


def test_features_keep_the_bits_of_the_whole_array_steps():
    """A scene of planes, a pole (a line: rank-1 neighbourhoods), a repeated point and noise; lidar
    stored as float32 as calibrate stores it; the frame's tree passed in or built: the same bits."""
    rng = np.random.default_rng(8)
    ground = np.column_stack([rng.uniform(2, 40, 4000), rng.uniform(-15, 15, 4000), np.full(4000, -1.6)])
    walls = np.column_stack([np.full(2000, 25.0), rng.uniform(-10, 10, 2000), rng.uniform(-1.6, 3, 2000)])
    pole = np.column_stack([np.full(40, 12.0), np.full(40, 3.0), np.linspace(-1.6, 2.4, 40)])
    blob = rng.normal(size=(1500, 3)) * 0.4 + [15.0, -4.0, 0.5]
    lidar = np.vstack([ground, walls, pole, blob, np.repeat([[8.0, 1.0, 0.0]], 12, axis=0)]).astype(np.float32)
    lidar += rng.normal(size=lidar.shape).astype(np.float32) * np.float32(0.01) * (rng.random((len(lidar), 1)) < 0.5)
    cand = lidar[::2].astype(np.float64)
    uv = rng.uniform(-0.5, [159.4, 79.4], (len(cand), 2))
    image = rng.integers(0, 256, (80, 160, 3), dtype=np.uint8)
    expect = _reference_colour_and_geometry(cand, uv, image, lidar)
    for tree in (None, P.neighbour_tree(lidar)):
        got = P.candidate_features(cand, uv, image, lidar, np.array([3.0, 0.5, 0.0]), [], tree=tree)
        np.testing.assert_array_equal(got[:, 9:], expect)
    cov = rng.normal(size=(20000, 3, 3))
    cov = np.concatenate([cov @ cov.transpose(0, 2, 1), cov, np.round(cov) * 0.5, -np.eye(3)[None], np.zeros((1, 3, 3))])
    for got, want in zip(P.smallest_eigenpair_sym3(cov), _reference_eigenpair(cov)):
        np.testing.assert_array_equal(got, want)


def test_radar_counts_against_brute_force():
    rng = np.random.default_rng(3)
    cand, radar = rng.uniform(0, 20, (300, 3)), rng.uniform(0, 20, (80, 3))
    got = P.radar_counts(cand, radar, gate_m=1.5)
    d = np.linalg.norm(radar[:, None] - cand[None], axis=2)
    nearest = d.argmin(axis=1)
    expect = np.bincount(nearest[d.min(axis=1) <= 1.5], minlength=300)
    np.testing.assert_array_equal(got, expect)
    assert 0 < got.sum() < 80  # some gated out
    assert P.radar_counts(cand, np.zeros((0, 3)), 1.0).tolist() == [0] * 300
    assert P.radar_counts(np.zeros((0, 3)), radar, 1.0).shape == (0,)


# --------------------------------------------------------------------------- placement weights


def gaussian(d: np.ndarray, sigma: float) -> np.ndarray:
    return np.exp(-0.5 * (d / sigma) ** 2)


def test_placement_weights_equal_the_sum_over_map_pixels():
    """q(y) = sum_x M(x) G(x - y) lambda(y) / sum_y' G(x - y') lambda(y'). The image (12 x 10) is
    smaller than the blur kernel's half width at sigma 3, so OpenCV's truncated kernel is the full
    Gaussian here."""
    rng = np.random.default_rng(0)
    w, h, sigma = 12, 10, (3.0, 2.5)
    m = rng.random((h, w))
    uv = rng.uniform(0, [w - 1, h - 1], (15, 2))
    lam = rng.gamma(1.0, 1.0, 15)
    lam[4] = 0.0
    q = P.placement_weights(m, uv, lam, (w, h), sigma)
    px = np.rint(uv).astype(int)
    yy, xx = np.mgrid[0:h, 0:w]
    g = gaussian(xx[..., None] - px[:, 0], sigma[0]) * gaussian(yy[..., None] - px[:, 1], sigma[1])  # (h, w, C)
    brute = lam * np.einsum("hw,hwc->c", m / (g @ lam), g)
    np.testing.assert_allclose(q, brute / brute.sum(), rtol=1e-6)
    assert q[4] == 0 and q.sum() == pytest.approx(1.0)
    # a map at half the resolution: the candidates' pixels (pixel centres: u' = (u + 0.5) / 2 - 0.5)
    # and the blur scale with it
    half = P.placement_weights(m[::2, ::2], uv, lam, (2 * w, 2 * h), (2 * sigma[0], 2 * sigma[1]))
    np.testing.assert_allclose(half, P.placement_weights(m[::2, ::2], (uv + 0.5) / 2 - 0.5, lam, (w, h), sigma),
                               rtol=1e-9)


def test_placement_weights_with_a_map_of_another_aspect_ratio():
    """A 12 x 10 map for a 24 x 40 working image: u scales by 1/2, v by 1/4, and so do the blur's
    standard deviations (6, 10) working pixels -> (3, 2.5) map pixels; brute force at map pixels."""
    rng = np.random.default_rng(2)
    (w, h), (mw, mh), sigma = (24, 40), (12, 10), (6.0, 10.0)
    m = rng.random((mh, mw))
    uv = rng.uniform(0, [w - 1, h - 1], (15, 2))
    lam = rng.gamma(1.0, 1.0, 15)
    q = P.placement_weights(m, uv, lam, (w, h), sigma)
    px = np.floor((uv + 0.5) * [mw / w, mh / h]).astype(int)
    yy, xx = np.mgrid[0:mh, 0:mw]
    g = gaussian(xx[..., None] - px[:, 0], 3.0) * gaussian(yy[..., None] - px[:, 1], 2.5)
    brute = lam * np.einsum("hw,hwc->c", m / (g @ lam), g)
    np.testing.assert_allclose(q, brute / brute.sum(), rtol=1e-6)


def test_placement_weights_take_each_candidate_from_its_own_pixel_of_a_smaller_map():
    """Working pixel 3 lies in pixel 1 of a half-size map and pixel 5 in pixel 2 (pixel k covers
    [k - 0.5, k + 0.5)): the map's mass at pixel 1 goes mostly to the candidate at working pixel 3,
    as it does with the same map at the working size."""
    full = np.zeros((32, 64))
    full[10:12, 2:4] = 1.0                     # working pixels 2..3 = half-size pixel 1
    uv = np.array([[3.0, 10.0], [5.0, 10.0]])
    at_size = P.placement_weights(full, uv, np.ones(2), (64, 32), (1.0, 1.0))
    half = P.placement_weights(full[::2, ::2], uv, np.ones(2), (64, 32), (1.0, 1.0))
    assert at_size[0] > 0.85 and half[0] > 0.75


def test_placement_weights_edge_cases():
    m = np.zeros((8, 8))
    m[0, 0] = 1.0
    uv = np.array([[7.0, 7.0], [7.0, 7.0], [0.0, 7.0]])
    # two candidates on one pixel share its mass in proportion to their intensity
    q = P.placement_weights(m, uv, np.array([1.0, 3.0, 0.0]), (8, 8), (2.0, 2.0))
    np.testing.assert_allclose(q, [0.25, 0.75, 0.0])
    # map mass far beyond the blur's reach is lost, not blown up: nothing can be placed
    far = np.zeros((8, 200))
    far[0, 0] = 1.0
    assert P.placement_weights(far, np.array([[199.0, 7.0]]), np.ones(1), (200, 8), (1.0, 1.0)).tolist() == [0.0]
    assert P.placement_weights(m, uv, np.zeros(3), (8, 8), (2.0, 2.0)).tolist() == [0, 0, 0]
    assert P.placement_weights(np.zeros((8, 8)), uv, np.ones(3), (8, 8), (2.0, 2.0)).tolist() == [0, 0, 0]
    assert P.placement_weights(m, np.zeros((0, 2)), np.zeros(0), (8, 8), (2.0, 2.0)).shape == (0,)
    for bad in (np.array([1.0, -1.0, 0.0]), np.array([1.0, np.nan, 0.0])):
        with pytest.raises(ValueError, match="intensity"):
            P.placement_weights(m, uv, bad, (8, 8), (2.0, 2.0))


def test_map_weight_scales_the_maps_say_from_full_to_none():
    """beta = 1 is the map-sample rule; beta = 0 ignores the map (q = lambda / sum lambda, whatever
    the map); in between q = lambda * b ** beta with b the blurred map ratio of beta = 1."""
    rng = np.random.default_rng(1)
    w, h, sigma = 40, 30, (3.0, 2.5)
    uv = rng.uniform(0, [w - 1, h - 1], (60, 2))
    lam = rng.gamma(1.0, 1.0, 60)
    m = np.full((h, w), 1e-4)
    m[:, : w // 4] = 1.0                       # the map puts nearly everything on the left quarter
    full = P.placement_weights(m, uv, lam, (w, h), sigma)
    np.testing.assert_allclose(P.placement_weights(m, uv, lam, (w, h), sigma, map_weight=1.0), full)
    for other in (m, rng.random((h, w))):
        np.testing.assert_allclose(P.placement_weights(other, uv, lam, (w, h), sigma, map_weight=0.0),
                                   lam / lam.sum(), rtol=1e-12)
    b = full / lam                             # the map's factor at beta = 1 (up to the normaliser)
    half = P.placement_weights(m, uv, lam, (w, h), sigma, map_weight=0.5)
    expected = lam * np.sqrt(b)
    np.testing.assert_allclose(half, expected / expected.sum(), rtol=1e-9)
    right = uv[:, 0] > w / 4 + 6 * sigma[0]
    assert right.sum() > 10
    shares = [P.placement_weights(m, uv, lam, (w, h), sigma, map_weight=beta)[right].sum() for beta in (1.0, 0.5, 0.0)]
    assert shares[0] < 0.01 < shares[1] < shares[2]   # the less the map weighs, the more goes where it says not
    for bad in (-0.1, 1.5, np.nan):
        with pytest.raises(ValueError, match="map_weight"):
            P.placement_weights(m, uv, lam, (w, h), sigma, map_weight=bad)


def _placement_weights_as_before(m, uv, lam, image_wh, sigma_px, map_weight):
    """placement_weights' blurs as computed until 2026-12-07 (float64 arrays converted to and from
    float32 around each blur), for maps with mass and candidates with intensity."""
    m, uv, lam = np.asarray(m, np.float64), np.asarray(uv, np.float64), np.asarray(lam, np.float64)
    (mh, mw), (w, h) = m.shape, image_wh
    px = np.clip(np.floor((uv + 0.5) * [mw / w, mh / h]).astype(np.int64), 0, [mw - 1, mh - 1])
    sx, sy = sigma_px[0] * mw / w, sigma_px[1] * mh / h

    def blur(a):
        return cv2.GaussianBlur(a.astype(np.float32), (0, 0), sigmaX=sx, sigmaY=sy,
                                borderType=cv2.BORDER_CONSTANT).astype(np.float64)

    z = blur(np.bincount(px[:, 1] * mw + px[:, 0], lam, minlength=mh * mw).reshape(mh, mw))
    ratio = np.zeros_like(z)
    reached = z > 1e-12 * z.max()
    ratio[reached] = m[reached] / z[reached]
    q = lam * np.maximum(blur(ratio)[px[:, 1], px[:, 0]], 0.0) ** map_weight
    return q / q.sum() if q.sum() > 0 else np.zeros(len(lam))


def test_placement_weights_keep_the_bits_of_the_float64_steps():
    """The blurs' float32 in and out without float64 copies (the ratio divided in float64 and stored
    in float32, as the copy gave it): the same weights to the bit, maps of other sizes, sparse
    intensities spanning 30 decades and partial map weights included."""
    rng = np.random.default_rng(4)
    for trial in range(60):
        w, h = rng.integers(8, 170, 2)
        mh, mw = (h, w) if trial % 3 else rng.integers(5, 170, 2)
        m = (rng.random((mh, mw)) * (rng.random((mh, mw)) < rng.random())).astype(np.float32)
        m[0, 0] = 1.0
        c = int(rng.integers(1, 3000))
        uv = rng.uniform(-0.5, [w - 0.51, h - 0.51], (c, 2))
        lam = rng.random(c) * (rng.random(c) < 0.8) * 10.0 ** rng.integers(-30, 5)
        lam[0] = 1.0
        sigma, beta = tuple(rng.uniform(0.5, 20, 2)), [1.0, 0.5, rng.random()][trial % 3]
        np.testing.assert_array_equal(P.placement_weights(m, uv, lam, (w, h), sigma, beta),
                                      _placement_weights_as_before(m, uv, lam, (w, h), sigma, beta))


# --------------------------------------------------------------------------- the draw


def test_choose_candidates_fill_every_voxel_before_doubling_up():
    rng = np.random.default_rng(1)
    sites = np.array([[10.0, 0, 0], [10, 5, 0], [20, 0, 0], [30, -5, 1], [40, 3, 0]])
    points = np.repeat(sites, 3, axis=0)                 # three candidates on each site
    q = np.full(15, 1 / 15)
    q[0] = 0.9                                           # one heavy candidate does not crowd its site
    q[12:] = 0.0                                         # the last site cannot be drawn
    for _ in range(20):
        first = P.choose_candidates(q, points, 4, rng, voxel_m=1.0)
        assert sorted(points[first].tolist()) == sorted(sites[:4].tolist())  # one per site
        got = P.choose_candidates(q, points, 9, rng, voxel_m=1.0)
        assert len(np.unique(got)) == 9 and np.all(q[got] > 0)
        per_site = np.bincount(got // 3, minlength=5)
        assert sorted(per_site.tolist()) == [0, 2, 2, 2, 3]   # seconds everywhere before a third
        assert per_site[4] == 0
    assert len(P.choose_candidates(q, points, 100, rng, voxel_m=1.0)) == 12
    free = P.choose_candidates(q, points, 10, rng, voxel_m=0.0)   # no spreading
    assert len(free) == 10 and len(np.unique(free)) == 10 and np.all(free < 12)
    assert P.choose_candidates(q, points, 0, rng, 1.0).shape == (0,)
    assert P.choose_candidates(np.zeros(15), points, 3, rng, 1.0).shape == (0,)
    with pytest.raises(ValueError, match="n must be"):
        P.choose_candidates(q, points, -1, rng, 1.0)
    with pytest.raises(ValueError, match="points_D"):
        P.choose_candidates(q, points[:3], 1, rng, 1.0)


@settings(max_examples=300, deadline=None)
@given(values=st.lists(st.sampled_from([0.0, -0.0, 1.0, -1.0, 2.5, np.inf, -np.inf, np.nan, 1e-300, 7.0]) |
                       st.floats(allow_nan=True, allow_infinity=True), max_size=60),
       n=st.integers(0, 70))
def test_smallest_first_is_the_head_of_the_stable_argsort(values, n):
    """The partition and the sort of the n kept give what sorting all gives: ties (-0.0 and 0.0
    among them) in index order, NaNs last."""
    values = np.array(values, np.float64)
    np.testing.assert_array_equal(P.smallest_first(values, n), np.argsort(values, kind="stable")[:n])


def test_choose_candidates_without_voxels_draw_as_the_lexsort_did():
    """voxel_m = 0: the n best Gumbel keys, as the lexsort over (-key, rank 0) took them until
    2026-12-07 (the same generator draws; the keys tied by rounding q, and zeros in q)."""
    for seed in range(30):
        rng = np.random.default_rng(seed)
        q = np.round(rng.random(3000), 1) * (rng.random(3000) < 0.9)
        points = rng.normal(size=(3000, 3))
        n = int(rng.integers(0, 3100))
        live = np.flatnonzero(q > 0)
        draw = np.random.default_rng([seed, 1])
        keys = np.log(q[live]) + draw.gumbel(size=live.size)
        want = live[np.lexsort((-keys, np.zeros(live.size, np.int64)))[:n]] if n else np.zeros(0, np.int64)
        np.testing.assert_array_equal(P.choose_candidates(q, points, n, np.random.default_rng([seed, 1]), 0.0), want)


def test_choose_candidates_voxel_grid_has_a_random_offset():
    """Two candidates 0.1 m apart on either side of x = 1 share a 1 m cube unless a cube face falls
    between them (probability 0.1 with a random offset; always without one). With a third, far
    candidate and two draws, both near ones come out only when they are in different cubes."""
    rng = np.random.default_rng(3)
    points = np.array([[0.95, 0.2, 0.2], [1.05, 0.2, 0.2], [30.0, 0.2, 0.2]])
    q = np.full(3, 1 / 3)
    both = np.mean([set(P.choose_candidates(q, points, 2, rng, voxel_m=1.0).tolist()) == {0, 1}
                    for _ in range(400)])
    assert both < 0.1  # ~0.1 * 1/3 with the offset; 1/3 with a fixed grid


def test_choose_candidates_single_draw_follows_q():
    rng = np.random.default_rng(2)
    q = np.array([0.5, 0.3, 0.2])
    points = np.array([[0.0, 0, 0], [5, 0, 0], [10, 0, 0]])
    draws = np.array([P.choose_candidates(q, points, 1, rng, 1.0)[0] for _ in range(4000)])
    freq = np.bincount(draws, minlength=3) / len(draws)
    np.testing.assert_allclose(freq, q, atol=4 * np.sqrt(0.25 / 4000))


def test_place_on_lidar_puts_points_on_candidates():
    cand = wall(10.0, 0.5)
    uv, _, valid = project_to_image(cand, K_SMALL, invert_transform(T_RADAR_CAM), (160, 80))
    cand, uv = cand[valid], uv[valid]
    m = np.ones((40, 80))
    ego = np.array([5.0, 0.0, 0.0])
    out = P.place_on_lidar(m, 20.4, cand, uv, np.ones(len(cand)), image_wh=(160, 80), sigma_px=(4.0, 4.0),
                           voxel_m=1.0, ego_velocity_D=ego, labels=[], doppler_span_mps=0.0,
                           rng=np.random.default_rng(0))
    assert out["n_requested"] == 20 and len(out["points_D"]) == 20 and out["n_no_support"] == 0
    rows = {tuple(p) for p in cand.astype(np.float32).tolist()}
    assert all(tuple(p) in rows for p in out["points_D"].tolist())
    # each point's pixel is its own projection
    expect_uv, _, _ = project_to_image(out["points_D"].astype(np.float64), K_SMALL, invert_transform(T_RADAR_CAM),
                                       (160, 80))
    np.testing.assert_allclose(out["uv"], expect_uv, atol=1e-3)
    # n_hat is rounded to the nearest count, not truncated
    three = P.place_on_lidar(m, 2.6, cand, uv, np.ones(len(cand)), image_wh=(160, 80), sigma_px=(4.0, 4.0),
                             voxel_m=1.0, ego_velocity_D=ego, labels=[], doppler_span_mps=0.0,
                             rng=np.random.default_rng(0))
    assert three["n_requested"] == 3 and len(three["points_D"]) == 3
    np.testing.assert_allclose(out["rae"], cartesian_to_spherical(out["points_D"].astype(np.float64)), atol=1e-5)
    unit = out["points_D"] / np.linalg.norm(out["points_D"], axis=1, keepdims=True)
    np.testing.assert_allclose(out["doppler"], -(unit @ ego), atol=1e-5)      # static world: range rate
    # more points than candidates: the rest count as without support
    many = P.place_on_lidar(m, 500, cand, uv, np.ones(len(cand)), image_wh=(160, 80), sigma_px=(4.0, 4.0),
                            voxel_m=1.0, ego_velocity_D=ego, labels=[], doppler_span_mps=0.0,
                            rng=np.random.default_rng(0))
    assert len(cand) < 500 and len(many["points_D"]) == len(cand) and many["n_no_support"] == 500 - len(cand)
    with pytest.raises(ValueError, match="n_hat"):
        P.place_on_lidar(m, np.nan, cand, uv, np.ones(len(cand)), image_wh=(160, 80), sigma_px=(4.0, 4.0),
                         voxel_m=1.0, ego_velocity_D=ego, labels=[], doppler_span_mps=0.0,
                         rng=np.random.default_rng(0))


# --------------------------------------------------------------------------- PlaceNet


def test_placenet_standardisation_and_loss():
    net = PlaceNet(n_features=3, width=4, depth=1)
    x = np.array([[1.0, 5.0, 2.0], [3.0, 5.0, 4.0]])
    net.set_standardisation(x)
    np.testing.assert_allclose(net.feature_mean.numpy(), [2.0, 5.0, 3.0])
    np.testing.assert_allclose(net.feature_std.numpy(), [1.0, 1.0, 1.0])   # the constant column: 1, not 0
    assert net(torch.tensor(x, dtype=torch.float32)).shape == (2,)
    with pytest.raises(ValueError, match="expected features"):
        net(torch.zeros(2, 4))
    with pytest.raises(ValueError, match="no training features"):
        net.set_standardisation(np.zeros((0, 3)))
    log_rate, count = torch.tensor([0.0, np.log(2.0), -1.0]), torch.tensor([0.0, 3.0, 1.0])
    expect = torch.exp(log_rate) - count * log_rate
    torch.testing.assert_close(poisson_loss(log_rate, count), expect)
    with pytest.raises(ValueError, match="shapes"):
        poisson_loss(log_rate, count[:2])


def test_placenet_training_range_and_the_inputs_outside_it():
    """The 0.5 and 99.5 percentiles of the training features are kept; outside_range marks the
    features of a candidate below or above them, per feature."""
    rng = np.random.default_rng(0)
    x = np.column_stack([rng.uniform(0, 1, 20001), rng.normal(10, 2, 20001), np.full(20001, 3.0)])
    net = PlaceNet(n_features=3, width=4, depth=1)
    assert not net.outside_range(np.array([[1e9, -1e9, 0.0]])).any()     # no training range yet: unbounded
    net.set_standardisation(x)
    np.testing.assert_allclose(net.feature_low.numpy(), [np.quantile(x[:, 0], 0.005), np.quantile(x[:, 1], 0.005), 3.0])
    np.testing.assert_allclose(net.feature_high.numpy(), [np.quantile(x[:, 0], 0.995), np.quantile(x[:, 1], 0.995), 3.0])
    assert net.outside_range(x).any(axis=1).mean() == pytest.approx(0.02, abs=0.002)   # 1% per varying feature
    got = net.outside_range(np.array([[0.5, 10.0, 3.0], [1.5, 10.0, 3.0], [0.5, -5.0, 3.5]]))
    np.testing.assert_array_equal(got, [[False, False, False], [True, False, False], [False, True, True]])


def test_a_placenet_saved_without_its_training_range_loads_unbounded(tmp_path):
    """Checkpoints written before the range was saved still load; nothing is marked outside."""
    from pipeline import checkpoint as ckpt
    from pipeline.models.placenet import placenet_kwargs

    cfg = tiny_cfg()
    net = PlaceNet(**placenet_kwargs(cfg))
    net.set_standardisation(np.random.default_rng(0).normal(0, 1, (100, net.n_features)))
    state = {f"model.{k}": v for k, v in net.state_dict().items() if k not in PlaceNet.OPTIONAL_BUFFERS}
    ckpt.save_checkpoint(tmp_path / "old.safetensors", state, {"net": "placenet", "arch": Inf.jsonable_arch(placenet_kwargs(cfg))})
    old = Inf.load_placenet(cfg, tmp_path / "old.safetensors")
    torch.testing.assert_close(old.feature_mean, net.feature_mean)
    assert not old.outside_range(np.full((2, net.n_features), 1e6)).any() and not old.has_training_range()
    state = {f"model.{k}": v for k, v in net.state_dict().items()}
    ckpt.save_checkpoint(tmp_path / "new.safetensors", state, {"net": "placenet", "arch": Inf.jsonable_arch(placenet_kwargs(cfg))})
    assert Inf.load_placenet(cfg, tmp_path / "new.safetensors").outside_range(np.full((2, net.n_features), 1e6)).all()


def make_place_data(p: int = 3000, seed: int = 0) -> T.PlaceNetData:
    """Counts ~ Poisson(exp(1.5 x0 - 1)) with x0 on a scale PlaceNet must standardise (mean 50)."""
    rng = np.random.default_rng(seed)
    x = rng.normal(0, 1, (p, len(P.FEATURES)))
    counts = rng.poisson(np.exp(1.5 * x[:, 0] - 1.0))
    x[:, 0] = 50 + 10 * x[:, 0]
    idx = rng.permutation(p)
    return T.PlaceNetData(x.astype(np.float32), counts.astype(np.int32), idx[: p * 3 // 4], idx[p * 3 // 4:])


def tiny_cfg(**overrides: str):
    base = {"train.threads": "1", "train.device": "cpu", "placement.width": "8", "placement.batch_size": "256",
            "placement.lr": "1e-2", "placement.epochs": "4"}
    return load_config("synthetic", {**base, **overrides}, environ={})


def test_placenet_learns_beats_the_constant_rate_and_resumes(tmp_path):
    data = make_place_data()
    cfg = tiny_cfg()
    ref = T.train_placenet(cfg, data, tmp_path / "a", progress=False)
    model = Inf.load_placenet(cfg, ref.best_path)
    got = T.placenet_metrics(model, data, data.val_idx)["nll"]
    const = B.placenet_baseline(data.counts, data.train_idx, data.val_idx)
    assert const["rate"] == pytest.approx(data.counts[data.train_idx].mean())
    truth = np.exp(1.5 * (data.features[:, 0] - 50) / 10 - 1.0)[data.val_idx]
    c = data.counts[data.val_idx]
    oracle = np.mean(truth - c * np.log(truth))
    assert got < const["nll"] - 0.5 * (const["nll"] - oracle)   # more than half of the way to the truth
    lam = Inf.placenet_predict(model, data.features[:10], batch=3)
    assert lam.shape == (10,) and np.all(lam > 0)
    np.testing.assert_allclose(model.feature_mean.numpy()[0], data.features[data.train_idx, 0].mean(), rtol=1e-4)
    np.testing.assert_allclose(model.feature_high.numpy()[0], np.percentile(data.features[data.train_idx, 0], 99.5),
                               rtol=1e-6)   # the training range is saved with the best weights
    assert ref.epoch == 4 and len(ref.curves) == 4   # placement.epochs, not train.epochs (8 here)
    # killed after two epochs and resumed: the same weights and optimizer state as one run
    T.train_placenet(tiny_cfg(**{"placement.epochs": "2"}), data, tmp_path / "b", progress=False)
    res = T.train_placenet(cfg, data, tmp_path / "b", progress=False)
    assert res.resumed_from == 2 and res.epoch == 4
    from safetensors.torch import load_file
    a, b = load_file(ref.last_path), load_file(res.last_path)
    assert all(torch.equal(a[k], b[k]) for k in a if k.startswith(("model.", "optim.")))


def test_placenet_epochs_are_its_own(tmp_path):
    """placement.epochs sets PlaceNet's epochs whatever train.epochs says; a negative value is a
    ConfigError naming the key; under a cosine schedule it is part of PlaceNet's fingerprint (and
    train.epochs is not), so that changing it starts a new run."""
    data = make_place_data(p=400)
    res = T.train_placenet(tiny_cfg(**{"placement.epochs": "3", "train.epochs": "1"}), data, tmp_path / "a",
                           progress=False)
    assert res.epoch == 3 and [c["epoch"] for c in res.curves] == [1, 2, 3]
    with pytest.raises(ConfigError, match="placement.epochs"):
        T.train_placenet(tiny_cfg(**{"placement.epochs": "-1"}), data, tmp_path / "b", progress=False)
    cos = {"train.lr_schedule": "cosine"}
    fp = T.default_fingerprint
    assert fp(tiny_cfg(**cos, **{"placement.epochs": "3"}), "placenet") != fp(tiny_cfg(**cos), "placenet")
    assert fp(tiny_cfg(**cos, **{"train.epochs": "3"}), "placenet") == fp(tiny_cfg(**cos), "placenet")
    assert fp(tiny_cfg(**cos, **{"placement.epochs": "3"}), "disnet") == fp(tiny_cfg(**cos), "disnet")
    assert fp(tiny_cfg(**{"placement.epochs": "3"}), "placenet") == fp(tiny_cfg(), "placenet")  # constant: resumes


def test_placenet_output_does_not_depend_on_the_features_units():
    """Standardised with its training statistics, the net sees the same input whatever the
    features' units: a * x + b (per feature, a > 0) with the statistics recomputed on it gives the
    same output as x."""
    rng = np.random.default_rng(0)
    x = rng.normal(0, 1, (50, 3)) * [1.0, 3.0, 0.2] + [0.0, 10.0, -4.0]
    torch.manual_seed(0)
    net = PlaceNet(n_features=3, width=4, depth=1)
    net.set_standardisation(x)
    before = net(torch.tensor(x, dtype=torch.float32))
    rescaled = x * [100.0, 0.01, 7.0] + [5.0, -3.0, 1000.0]
    net.set_standardisation(rescaled)
    torch.testing.assert_close(net(torch.tensor(rescaled, dtype=torch.float32)), before, rtol=1e-4, atol=1e-4)


def test_placenet_cosine_schedule_spans_placement_epochs(tmp_path):
    """Under a cosine schedule PlaceNet's learning rate in epoch e of placement.epochs E is
    lr * (1 + cos(pi (e - 1) / E)) / 2, whatever train.epochs says."""
    import math

    from pipeline import checkpoint as ckpt

    data = make_place_data(p=400)
    cfg = tiny_cfg(**{"train.lr_schedule": "cosine", "placement.epochs": "3", "train.epochs": "8"})
    T.train_placenet(cfg, data, tmp_path, progress=False)
    groups = ckpt.read_meta(tmp_path / "last.safetensors")["optimizer"]["param_groups"]
    assert groups[0]["lr"] == pytest.approx(1e-2 * 0.5 * (1 + math.cos(math.pi * 2 / 3)))  # epoch 3 of 3
