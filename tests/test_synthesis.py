"""Tests of pipeline.synthesis: pixel sampling, lidar range estimation (against a brute-force
oracle), placement on the camera ray, Doppler conventions and one synthetic frame end to end."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import chisquare

from pipeline import synthesis
from pipeline.frame import LABEL_COLUMNS, Object3D, box_rotations, label_rows, to_box_frame
from pipeline.geometry import (
    cartesian_to_spherical, invert_transform, pixel_rays_D, project_to_image, spherical_to_cartesian,
)
from pipeline.synthesis import (
    ESTIMATORS, MAX_WIDENINGS, NO_SUPPORT_RULES, REFILL_MAX_FACTOR, REFILL_OVERSAMPLE, SUPPORT_DIRECT, SUPPORT_NONE,
    SUPPORT_WIDENED, LidarAngularIndex, _refill_draws, doppler_for_points, object_velocities_for_points,
    place_on_camera_ray, sample_pixels, synthesize_frame,
)
from pipeline.world.rig import rotation_zyx

# Radar {D}: x fwd, y left, z up. Camera: x right, y down, z fwd. Columns = camera axes in {D}.
R_RADAR_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def make_T_radar_cam(centre_D=(0.3, 0.4, 0.5)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R_RADAR_CAM
    T[:3, 3] = centre_D
    return T


K_SMALL = np.array([[100.0, 0.0, 79.5], [0.0, 100.0, 39.5], [0.0, 0.0, 1.0]])  # 160 x 80 image


# --------------------------------------------------------------------------- sample_pixels


def test_sample_pixels_matches_map_distribution():
    rng = np.random.default_rng(1)
    prob = rng.random((4, 5))
    prob[1, 2] = 0.0
    prob /= prob.sum()
    n = 200_000
    uv = sample_pixels(prob, n, np.random.default_rng(7))
    assert uv.shape == (n, 2) and uv.dtype == np.float64
    cols, rows = np.floor(uv[:, 0] + 0.5).astype(int), np.floor(uv[:, 1] + 0.5).astype(int)
    counts = np.zeros_like(prob)
    np.add.at(counts, (rows, cols), 1)
    assert counts[1, 2] == 0  # zero-probability pixel never drawn
    mask = prob > 0
    _, p_value = chisquare(counts[mask], n * prob[mask])
    assert p_value > 1e-4
    # jitter uniform in [-0.5, 0.5) around integer pixel centres
    frac = uv - np.stack([cols, rows], axis=1)
    assert frac.min() >= -0.5 and frac.max() < 0.5
    assert np.histogram(frac[:, 0], bins=4, range=(-0.5, 0.5))[0].min() > 0.23 * n


def test_sample_pixels_reproducible_and_empty():
    prob = np.random.default_rng(0).random((6, 7))
    a = sample_pixels(prob, 50, np.random.default_rng(3))
    b = sample_pixels(prob, 50, np.random.default_rng(3))
    np.testing.assert_array_equal(a, b)
    assert sample_pixels(prob, 0, np.random.default_rng(3)).shape == (0, 2)


def test_sample_pixels_systematic_follows_the_map_with_less_clumping():
    prob = np.random.default_rng(1).random((4, 5))
    prob[1, 2] = 0.0
    prob /= prob.sum()
    n = 200_000
    uv = sample_pixels(prob, n, np.random.default_rng(7), method="systematic")
    counts = np.zeros_like(prob)
    np.add.at(counts, (np.floor(uv[:, 1] + 0.5).astype(int), np.floor(uv[:, 0] + 0.5).astype(int)), 1)
    assert counts[1, 2] == 0
    # every pixel gets its share to within one sample (iid: binomial spread of ~sqrt(n p))
    assert np.abs(counts - n * prob).max() <= 1.0
    # the top two rows (mass q, one stretch of the row-major order) get floor(n q) or ceil(n q) of
    # 40 samples, every seed; iid draws do not
    top = prob[:2].sum()
    for seed in range(20):
        v = sample_pixels(prob, 40, np.random.default_rng(seed), method="systematic")[:, 1]
        assert abs(np.sum(v < 1.5) - 40 * top) < 1.0 + 1e-9
    iid = [np.sum(sample_pixels(prob, 40, np.random.default_rng(s))[:, 1] < 1.5) for s in range(20)]
    assert max(abs(c - 40 * top) for c in iid) > 1.0
    # returned in random order, not along the rows
    assert not np.all(np.diff(uv[:1000, 1]) >= -1.0)
    with pytest.raises(ValueError, match="method"):
        sample_pixels(prob, 3, np.random.default_rng(0), method="sorted")


def test_sample_pixels_single_pixel_map():
    prob = np.zeros((3, 4))
    prob[2, 1] = 5.0
    uv = sample_pixels(prob, 100, np.random.default_rng(0))
    assert np.all(np.abs(uv - [1.0, 2.0]) <= 0.5)


@pytest.mark.parametrize("bad", [np.full((2, 2), -1.0), np.zeros((2, 2)), np.full((2, 2), np.nan)])
def test_sample_pixels_rejects_bad_maps(bad):
    with pytest.raises(ValueError):
        sample_pixels(bad, 3, np.random.default_rng(0))


# --------------------------------------------------------------------------- range estimation


def lidar_at(rae: list[tuple[float, float, float]]) -> np.ndarray:
    return spherical_to_cartesian(np.array(rae, dtype=np.float64))


def test_mean_rule_on_hand_made_points():
    lidar = lidar_at([(10.0, 0.0, 0.0), (20.0, 0.01, 0.005), (100.0, 0.05, 0.0), (40.0, 0.0, 0.03)])
    index = LidarAngularIndex(lidar)
    az, el = np.array([0.0]), np.array([0.0])
    expected = {"mean": 15.0, "nearest": 10.0, "min": 10.0, "median": 15.0}
    for estimator, want in expected.items():
        r, flag = index.estimate_range(az, el, 0.02, 0.02, estimator)
        assert r[0] == pytest.approx(want) and flag[0] == SUPPORT_DIRECT
    # elevation window is separate: 0.03 rad is inside a 0.04 window
    r, _ = index.estimate_range(az, el, 0.02, 0.04, "mean")
    assert r[0] == pytest.approx((10 + 20 + 40) / 3)


def test_nearest_ties_take_the_first_lidar_point():
    # exactly equal angles (points on the x axis), plus a farther-off point
    index = LidarAngularIndex(np.array([[30.0, 0.0, 0.0], [12.0, 0.0, 0.0], [5.0, 0.0, 0.05]]))
    for method in (index.estimate_range, index.estimate_range_bruteforce):
        r, _ = method(np.array([0.001]), np.array([0.002]), 0.02, 0.02, "nearest", "drop")
        assert r[0] == pytest.approx(30.0)


def test_widening_and_drop():
    index = LidarAngularIndex(lidar_at([(100.0, 0.05, 0.0)]))
    az, el = np.array([0.12, 1.5]), np.array([0.0, 0.0])
    r, flag = index.estimate_range(az, el, 0.02, 0.02, "mean", "widen")
    assert r[0] == pytest.approx(100.0) and flag[0] == SUPPORT_WIDENED  # found at 4x
    assert np.isnan(r[1]) and flag[1] == SUPPORT_NONE  # 16x window (0.32 rad) still empty
    r, flag = index.estimate_range(az, el, 0.02, 0.02, "mean", "drop")
    assert np.all(np.isnan(r)) and np.all(flag == SUPPORT_NONE)


def test_window_across_azimuth_seam():
    index = LidarAngularIndex(lidar_at([(7.0, np.pi - 0.005, 0.0)]))
    r, flag = index.estimate_range(np.array([-np.pi + 0.005]), np.array([0.0]), 0.02, 0.02, "mean", "drop")
    assert r[0] == pytest.approx(7.0) and flag[0] == SUPPORT_DIRECT


def test_wide_windows_count_each_lidar_point_once():
    # 16x a 0.25 rad window exceeds pi: every point is indexed twice; windows must not double count
    index = LidarAngularIndex(np.array([[10.0, 0.0, 0.0], [20.0 * np.cos(0.1), 20.0 * np.sin(0.1), 0.0]]))
    for az in (0.7, 3.0):
        r, flag = index.estimate_range(np.array([az]), np.array([0.0]), 0.25, 0.25, "mean", "widen")
        assert r[0] == pytest.approx(15.0) and flag[0] == SUPPORT_WIDENED


def test_range_empty_inputs_and_errors():
    index = LidarAngularIndex(np.zeros((0, 3)))
    r, flag = index.estimate_range(np.zeros(3), np.zeros(3), 0.02, 0.02)
    assert np.all(np.isnan(r)) and np.all(flag == 0)
    full = LidarAngularIndex(lidar_at([(5.0, 0.0, 0.0)]))
    r, flag = full.estimate_range(np.zeros(0), np.zeros(0), 0.02, 0.02)
    assert r.shape == (0,) and flag.dtype == np.int8
    with pytest.raises(ValueError, match="estimator"):
        full.estimate_range(np.zeros(1), np.zeros(1), 0.02, 0.02, "mode")
    with pytest.raises(ValueError, match="no_support"):
        full.estimate_range(np.zeros(1), np.zeros(1), 0.02, 0.02, "mean", "skip")
    with pytest.raises(ValueError):
        full.estimate_range(np.zeros(1), np.zeros(1), 0.0, 0.02)


@settings(max_examples=100, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    m=st.integers(0, 300),
    n=st.integers(0, 40),
    delta_az=st.floats(0.005, 0.2),
    delta_el=st.floats(0.005, 0.2),
    estimator=st.sampled_from(ESTIMATORS),
    no_support=st.sampled_from(NO_SUPPORT_RULES),
)
def test_estimators_match_bruteforce(seed, m, n, delta_az, delta_el, estimator, no_support):
    rng = np.random.default_rng(seed)
    rae = np.column_stack([rng.uniform(1, 60, m), rng.uniform(-np.pi, np.pi, m), rng.uniform(-0.6, 0.6, m)])
    index = LidarAngularIndex(spherical_to_cartesian(rae))
    az, el = rng.uniform(-np.pi, np.pi, n), rng.uniform(-0.7, 0.7, n)
    got = index.estimate_range(az, el, delta_az, delta_el, estimator, no_support)
    want = index.estimate_range_bruteforce(az, el, delta_az, delta_el, estimator, no_support)
    np.testing.assert_allclose(got[0], want[0], rtol=1e-12, equal_nan=True)
    np.testing.assert_array_equal(got[1], want[1])


@settings(deadline=None, max_examples=40)
@given(seed=st.integers(0, 2**32 - 1), m=st.integers(0, 300), n=st.integers(0, 40),
       delta_az=st.floats(0.005, 0.3), delta_el=st.floats(0.005, 0.3))
def test_closest_range_in_window_matches_a_scan(seed, m, n, delta_az, delta_el):
    rng = np.random.default_rng(seed)
    rae = np.column_stack([rng.uniform(1, 60, m), rng.uniform(-np.pi, np.pi, m), rng.uniform(-0.6, 0.6, m)])
    index = LidarAngularIndex(spherical_to_cartesian(rae))
    az, el, r = rng.uniform(-np.pi, np.pi, n), rng.uniform(-0.7, 0.7, n), rng.uniform(1, 60, n)
    got = index.closest_range_in_window(az, el, r, delta_az, delta_el)
    want = np.full(n, np.nan)
    for k in range(n):  # reference scan over every lidar point (the seam included)
        d_az = np.abs((index.azimuth_rad - az[k] + np.pi) % (2 * np.pi) - np.pi)
        inside = (d_az <= delta_az) & (np.abs(index.elevation_rad - el[k]) <= delta_el)
        if inside.any():
            cand = index.range_m[inside]
            want[k] = cand[np.argmin(np.abs(cand - r[k]))]
    # a tie between two candidates equally far from r may pick either: compare |dr|
    np.testing.assert_allclose(np.abs(got - r), np.abs(want - r), rtol=1e-12, atol=1e-12, equal_nan=True)
    assert np.all(np.isnan(got) == np.isnan(want))


def test_closest_range_in_window_is_never_worse_than_the_rules():
    rng = np.random.default_rng(3)
    rae = np.column_stack([rng.uniform(1, 60, 2000), rng.uniform(-0.5, 0.5, 2000), rng.uniform(-0.2, 0.2, 2000)])
    index = LidarAngularIndex(spherical_to_cartesian(rae))
    az, el, r = rng.uniform(-0.45, 0.45, 200), rng.uniform(-0.15, 0.15, 200), rng.uniform(1, 60, 200)
    best = np.abs(index.closest_range_in_window(az, el, r, 0.03, 0.03) - r)
    for rule in ("nearest", "min"):  # the rules that pick one lidar point (a mean can fall between)
        est, _ = index.estimate_range(az, el, 0.03, 0.03, rule, "drop")
        ok = np.isfinite(est)
        assert np.all(best[ok] <= np.abs(est[ok] - r[ok]) + 1e-9)
    with pytest.raises(ValueError, match="range_m has 3 values for 200 directions"):
        index.closest_range_in_window(az, el, r[:3], 0.03, 0.03)


@pytest.mark.parametrize("layout", ["uniform", "grid", "seam", "clusters"])
@pytest.mark.parametrize("delta_deg", [(1.5, 1.5), (1.0, 2.5), (12.0, 12.0)])
@pytest.mark.parametrize("candidates", [1, 2, 16])
def test_nearest_from_candidates_equals_the_window_passes(monkeypatch, layout, delta_deg, candidates):
    """'nearest' settles most samples from their nearest lidar points (one k-NN query); its answer
    (range and support) must be the one the window passes give, ties on a grid, widened windows,
    no support and the azimuth seam included."""
    rng = np.random.default_rng(len(layout) + int(delta_deg[1]))
    if layout == "grid":  # equal distances everywhere; samples on points, edges and cell centres
        g_az, g_el = np.meshgrid(np.deg2rad(np.arange(-40, 40, 1.0)), np.deg2rad(np.arange(-8, 8, 1.0)))
        az_l, el_l = g_az.ravel(), g_el.ravel()
        pick = rng.integers(0, az_l.size, 300)
        az = az_l[pick] + rng.choice(np.deg2rad([0.0, 0.5, 1.0, 1.5, 3.0]), 300)
        el = el_l[pick] + rng.choice(np.deg2rad([0.0, 0.5, 1.5]), 300)
    else:
        if layout == "uniform":
            az_l, el_l = rng.uniform(-np.pi, np.pi, 2000), rng.uniform(-0.3, 0.3, 2000)
        elif layout == "seam":
            az_l, el_l = np.pi - np.abs(rng.normal(0, 0.1, 1500)) * rng.choice([-1, 1], 1500), rng.uniform(-0.2, 0.2, 1500)
        else:
            centres = rng.uniform(-np.pi, np.pi, 6)
            az_l = np.concatenate([rng.normal(c, 0.03, 200) for c in centres])
            el_l = rng.normal(0, 0.03, az_l.size)
        az_l = np.mod(az_l + np.pi, 2 * np.pi) - np.pi
        az = np.mod(rng.uniform(-np.pi, np.pi, 300) + (np.pi if layout == "seam" else 0), 2 * np.pi) - np.pi
        el = rng.uniform(-0.4, 0.4, 300)
    index = LidarAngularIndex(spherical_to_cartesian(np.column_stack([rng.uniform(1, 80, az_l.size), az_l, el_l])))
    d_az, d_el = np.deg2rad(delta_deg)
    monkeypatch.setattr(synthesis, "NEAREST_CANDIDATES", candidates)  # few: the margins decide more often
    got = {rule: index.estimate_range(az, el, d_az, d_el, "nearest", rule) for rule in NO_SUPPORT_RULES}
    settled = index._nearest_certified(az, el, d_az, d_el, MAX_WIDENINGS + 1, np.full(az.size, np.nan),
                                       np.zeros(az.size, np.int8))
    assert candidates == 1 or settled.size < az.size  # it settles samples (one candidate has no margin)
    monkeypatch.undo()
    monkeypatch.setattr(LidarAngularIndex, "_nearest_certified", lambda self, az, *rest: np.arange(az.size))
    for rule in NO_SUPPORT_RULES:
        want = index.estimate_range(az, el, d_az, d_el, "nearest", rule)
        np.testing.assert_array_equal(got[rule][0], want[0])
        np.testing.assert_array_equal(got[rule][1], want[1])


# --------------------------------------------------------------------------- placement


def test_place_on_camera_ray_distance_and_ray():
    rng = np.random.default_rng(0)
    T = make_T_radar_cam((-0.8, 0.35, 0.6))
    uv = rng.uniform([0, 0], [159, 79], (200, 2))
    range_m = rng.uniform(2.0, 60.0, 200)
    points = place_on_camera_ray(uv, range_m, K_SMALL, T)
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), range_m, rtol=1e-12)
    c, d = T[:3, 3], pixel_rays_D(uv, K_SMALL, T)
    offset = points - c
    np.testing.assert_allclose(np.cross(offset, d), 0.0, atol=1e-9)  # on the ray's line
    assert np.all(np.einsum("ij,ij->i", offset, d) > 0)  # in front of the camera
    # recomputed angles differ from the camera ray's angles (the camera-radar offset matters)
    rae = cartesian_to_spherical(points)
    assert np.abs(rae[:, 1] - cartesian_to_spherical(d)[:, 1]).max() > 1e-3


def test_place_on_camera_ray_fallback_and_nan():
    T = make_T_radar_cam((0.0, 1.0, 0.0))  # camera 1 m to the left of the radar
    uv = np.array([[79.5, 39.5], [79.5, 39.5]])  # principal point: ray along +x of {D}
    points = place_on_camera_ray(uv, np.array([0.5, np.nan]), K_SMALL, T)
    # |c + t x| >= 1 > 0.5 for every t: no solution, fall back to t = r
    np.testing.assert_allclose(points[0], [0.5, 1.0, 0.0], atol=1e-12)
    assert np.all(np.isnan(points[1]))
    assert place_on_camera_ray(np.zeros((0, 2)), np.zeros(0), K_SMALL, T).shape == (0, 3)
    uv = np.array([[3.0, 4.0], [10.5, 2.25]])
    rays = pixel_rays_D(uv, K_SMALL, T)
    np.testing.assert_array_equal(place_on_camera_ray(uv, np.array([4.0, 9.0]), K_SMALL, T, rays),
                                  place_on_camera_ray(uv, np.array([4.0, 9.0]), K_SMALL, T))
    with pytest.raises(ValueError, match="rays_D"):
        place_on_camera_ray(uv, np.array([4.0, 9.0]), K_SMALL, T, rays[:1])


# --------------------------------------------------------------------------- Doppler


def test_doppler_conventions_hand_computed():
    points = np.array([[20.0, 0.0, 0.0], [0.0, 5.0, 0.0], [3.0, 3.0, 0.0]])
    ego = np.array([10.0, 0.0, 0.0])
    vod = doppler_for_points(points, ego, None, +1, 0.0)
    np.testing.assert_allclose(vod, [-10.0, 0.0, -10.0 / np.sqrt(2)], atol=1e-12)  # approaching < 0
    astyx = doppler_for_points(points, ego, None, -1, 10.39)
    # +10 (positive approaching) wraps into [-5.195, 5.195): 10 - 10.39; 7.071 - 10.39
    np.testing.assert_allclose(astyx, [10.0 - 10.39, 0.0, 10.0 / np.sqrt(2) - 10.39], atol=1e-9)
    slow = doppler_for_points(points[:1], np.array([3.0, 0.0, 0.0]), None, -1, 10.39)
    np.testing.assert_allclose(slow, [3.0])
    # an object moving with the ego vehicle has zero range rate
    same = doppler_for_points(points[:1], ego, np.array([[10.0, 0.0, 0.0]]), +1, 0.0)
    np.testing.assert_allclose(same, [0.0], atol=1e-12)
    with pytest.raises(ValueError):
        doppler_for_points(points, ego, None, 2, 0.0)


def test_object_velocities_oriented_boxes():
    car = Object3D("Car", np.array([10.0, 0.0, 0.0]), np.array([4.0, 2.0, 1.5]), np.pi / 2,
                   velocity_D=np.array([0.0, 3.0, 0.0]))
    unknown = Object3D("Car", np.array([30.0, 0.0, 0.0]), np.array([4.0, 2.0, 1.5]), 0.0)
    points = np.array([
        [10.0, 1.9, 0.0],    # along the (rotated) length: inside
        [11.2, 0.0, 0.0],    # 1.2 m across: inside the 1.0 + 0.3 m grown half width
        [11.5, 0.0, 0.0],    # 1.5 m across: outside
        [10.0, 0.0, 1.0],    # 1.0 m up: inside the 0.75 + 0.3 half height
        [30.0, 0.0, 0.0],    # in the box with unknown (NaN) velocity: static
    ])
    vel = object_velocities_for_points(points, [car, unknown])
    np.testing.assert_allclose(vel, [[0, 3, 0], [0, 3, 0], [0, 0, 0], [0, 3, 0], [0, 0, 0]])
    assert object_velocities_for_points(points, []).shape == (5, 3)
    # calibrate's label rows (centre, size, yaw, pitch, roll, velocity, track id) give the same, without objects
    rows = np.array([[*o.center_D, *o.size_lwh_m, o.yaw_rad, 0.0, 0.0, *o.velocity_D, 7.0] for o in (car, unknown)])
    np.testing.assert_array_equal(object_velocities_for_points(points, rows), vel)
    np.testing.assert_array_equal(object_velocities_for_points(points, np.zeros((0, len(LABEL_COLUMNS)))),
                                  np.zeros((5, 3)))
    with pytest.raises(ValueError, match="label rows"):
        object_velocities_for_points(points, rows[:, :6])
    # rows of calibrate's layout before pitch and roll (11 columns, calibrate version 2) are refused,
    # never read with their velocity taken as the tilt
    with pytest.raises(ValueError, match=r"need shape \(L, >= 12\).*got \(2, 11\)"):
        object_velocities_for_points(points, np.delete(rows, [_COL["pitch"], _COL["roll"]], axis=1))


def test_object_velocities_follow_a_tilted_box():
    """A box pitched 20 deg (nose down) and rolled 10 deg: points inside it but outside the upright
    box of the same yaw get its velocity, points of the upright box outside it do not (until
    2026-12-06 every box was taken upright: Astyx's lean 4 deg in {D})."""
    pitch, roll = np.radians(20.0), np.radians(10.0)
    tilted = Object3D("Car", np.array([10.0, 2.0, 0.0]), np.array([4.0, 2.0, 1.0]), 0.6,
                      velocity_D=np.array([1.0, 2.0, 0.0]), pitch_rad=pitch, roll_rad=roll)
    upright = Object3D("Car", tilted.center_D, tilted.size_lwh_m, 0.6, velocity_D=tilted.velocity_D)
    R = rotation_zyx(0.6, pitch, roll)  # the world's rotation (box -> {D}), built independently
    local = np.array([[1.9, 0.0, 0.0], [-1.9, 0.0, 0.0], [0.0, 0.95, 0.45], [0.0, -0.95, -0.45], [0.0, 0.0, 0.0]])
    inside_tilted = tilted.center_D + local @ R.T
    np.testing.assert_array_equal(object_velocities_for_points(inside_tilted, [tilted], margin_m=0.0),
                                  np.tile(tilted.velocity_D, (5, 1)))
    assert (object_velocities_for_points(inside_tilted[:4], [upright], margin_m=0.0) == 0).all()
    corners_upright = upright.center_D + np.array([[1.9, 0.0, 0.45], [-1.9, 0.0, -0.45]]) @ rotation_zyx(0.6, 0, 0).T
    assert (object_velocities_for_points(corners_upright, [tilted], margin_m=0.0) == 0).all()
    np.testing.assert_array_equal(object_velocities_for_points(corners_upright, [upright], margin_m=0.0),
                                  np.tile(tilted.velocity_D, (2, 1)))
    # the same from calibrate's label rows
    np.testing.assert_array_equal(object_velocities_for_points(inside_tilted, label_rows([tilted]), margin_m=0.0),
                                  np.tile(tilted.velocity_D, (5, 1)))


_COL = {name: i for i, name in enumerate(LABEL_COLUMNS)}
_YAW, _VX = _COL["yaw"], _COL["vx"]


def _velocities_every_pair(points: np.ndarray, rows: np.ndarray, margin_m: float = 0.3) -> np.ndarray:
    """Reference: every point tested against every box (its rotation Rz(yaw) Ry(pitch) Rx(roll) from
    the world's rig.rotation_zyx); the nearest centre wins, then the lower index."""
    out = np.zeros((len(points), 3))
    for i, p in enumerate(points):
        best = (np.inf, -1)
        for j, r in enumerate(rows):
            rel = p - r[0:3]
            R = rotation_zyx(r[_YAW], r[_YAW + 1], r[_YAW + 2])
            local = [R[0, k] * rel[0] + R[1, k] * rel[1] + R[2, k] * rel[2] for k in range(3)]
            half = r[3:6] / 2 + margin_m
            if all(abs(local[k]) <= half[k] for k in range(3)) and np.linalg.norm(rel) < best[0]:
                best = (np.linalg.norm(rel), j)
        if best[1] >= 0:
            out[i] = np.nan_to_num(rows[best[1], _VX:_VX + 3], nan=0.0)
    return out


def _velocities_upright_as_before(points: np.ndarray, rows: np.ndarray, margin_m: float = 0.3) -> np.ndarray:
    """object_velocities_for_points as it was before boxes had a tilt (2026-12-06, a93a48f): every
    point against every box, the box's frame from cos and sin of its yaw alone."""
    out = np.zeros((len(points), 3))
    for i, p in enumerate(points):
        best = (np.inf, -1)
        for j, r in enumerate(rows):
            rel = p - r[0:3]
            c, s = np.cos(r[_YAW]), np.sin(r[_YAW])
            half = r[3:6] / 2 + margin_m
            if (abs(c * rel[0] + s * rel[1]) <= half[0] and abs(-s * rel[0] + c * rel[1]) <= half[1]
                    and abs(rel[2]) <= half[2] and np.linalg.norm(rel) < best[0]):
                best = (np.linalg.norm(rel), j)
        if best[1] >= 0:
            out[i] = np.nan_to_num(rows[best[1], _VX:_VX + 3], nan=0.0)
    return out


@pytest.mark.parametrize("tilted", [False, True])
def test_object_velocities_match_every_pair_test(tilted):
    """Overlapping, rotated, coincident boxes and points on their faces: the sorted-x search finds
    the same box for every point as testing every pair; tilted boxes too (their x extent, which
    the search slices the points by, grows with the tilt). Upright boxes give, to the bit, what the
    yaw-only test before the tilt gave, points on the faces included."""
    rng = np.random.default_rng(5)
    for _ in range(20):
        rows = np.zeros((12, len(LABEL_COLUMNS)))
        rows[:, 0:2] = rng.uniform(-8, 8, (12, 2))
        rows[:, 3:6] = rng.uniform(0.5, 6, (12, 3))
        rows[:, _YAW] = rng.uniform(-np.pi, np.pi, 12)
        if tilted:  # box 3 stays upright: its face points below are exact only for it
            rows[:, _YAW + 1:_YAW + 3] = rng.uniform(-0.6, 0.6, (12, 2))
            rows[3, _YAW + 1:_YAW + 3] = 0.0
        rows[:, _VX:_VX + 3] = rng.normal(0, 5, (12, 3))
        rows[1, :_VX] = rows[0, :_VX]    # the same box twice: the lower index wins
        rows[2, _VX] = np.nan            # unknown velocity: static
        points = rng.uniform(-10, 10, (400, 3))
        points[:, 2] *= 0.3
        c, s = np.cos(rows[3, _YAW]), np.sin(rows[3, _YAW])
        edge = rows[3, 3] / 2 + 0.3      # points on box 3's grown +x face
        points[:5, :2] = rows[3, :2] + np.outer([edge] * 5, [c, s]) + np.outer(rng.uniform(-0.2, 0.2, 5), [-s, c])
        points[:5, 2] = 0.0
        got = object_velocities_for_points(points, rows)
        np.testing.assert_array_equal(got, _velocities_every_pair(points, rows))
        if not tilted:
            np.testing.assert_array_equal(got, _velocities_upright_as_before(points, rows))
    # points beside a box (within its x extent) but inside none, as on Astyx frame 000492
    rows = np.array([[50.0, 3.0, 1.0, 3.7, 1.7, 1.4, -3.1, 0.0, 0.0, np.nan, np.nan, np.nan, 0.0]])
    beside = np.array([[50.0, -10.0, 0.0], [49.0, 20.0, 1.0]])
    np.testing.assert_array_equal(object_velocities_for_points(beside, rows), np.zeros((2, 3)))


def _velocities_box_by_box(points: np.ndarray, rows: np.ndarray, margin_m: float = 0.3) -> np.ndarray:
    """object_velocities_for_points as it was until 2026-12-06 (0059618): one loop step per box over
    its slice of the points sorted by x, each box's frame by to_box_frame with its own rotation."""
    boxes = synthesis.label_boxes(rows)
    out = np.zeros((len(points), 3))
    centres, half = boxes[:, 0:3], boxes[:, 3:6] / 2 + margin_m
    rot = box_rotations(boxes[:, _YAW], boxes[:, _YAW + 1], boxes[:, _YAW + 2])
    vel = np.where(np.isnan(boxes[:, _VX:_VX + 3]), 0.0, boxes[:, _VX:_VX + 3])
    order = np.argsort(points[:, 0], kind="stable")
    reach = np.einsum("lk,lk->l", np.abs(rot[:, 0, :]), half) * (1 + 1e-9) + 1e-9
    lo = np.searchsorted(points[order, 0], centres[:, 0] - reach, side="left")
    hi = np.searchsorted(points[order, 0], centres[:, 0] + reach, side="right")
    box_of, point_of, dist_of = [np.zeros(0, int)], [np.zeros(0, int)], [np.zeros(0)]
    for box in np.flatnonzero(hi > lo):
        idx = order[lo[box]:hi[box]]
        rel = points[idx] - centres[box]
        inside = np.all(np.abs(to_box_frame(rel, rot[box])) <= half[box], axis=1)
        box_of.append(np.full(int(inside.sum()), box))
        point_of.append(idx[inside])
        dist_of.append(np.linalg.norm(rel[inside], axis=1))
    box_of, point_of, dist_of = np.concatenate(box_of), np.concatenate(point_of), np.concatenate(dist_of)
    pick = np.lexsort((box_of, dist_of, point_of))
    first = np.r_[True, point_of[pick][1:] != point_of[pick][:-1]]
    out[point_of[pick][first]] = vel[box_of[pick][first]]
    return out


def test_object_velocities_all_boxes_at_once_as_box_by_box():
    """The (box, point) pairs of every box tested at once (x slice, then y) give, to the bit, what
    the loop over boxes gave; to_box_frame with one rotation per offset gives each box's own call."""
    rng = np.random.default_rng(8)
    for _ in range(10):
        rows = np.zeros((25, len(LABEL_COLUMNS)))
        rows[:, 0:3] = rng.uniform([0, -15, -1], [60, 15, 1], (25, 3))
        rows[:, 3:6] = rng.uniform(0.5, 6, (25, 3))
        rows[:, _YAW:_YAW + 3] = rng.uniform([-np.pi, -0.3, -0.3], [np.pi, 0.3, 0.3], (25, 3))
        rows[:5, _YAW + 1:_YAW + 3] = 0.0                                 # upright ones too
        rows[:, _VX:_VX + 3] = rng.normal(0, 5, (25, 3))
        rows[6:8, 0:3] = rows[5, 0:3] + rng.uniform(-1, 1, (2, 3))       # overlapping boxes
        rows[9, _VX] = np.nan
        points = rng.uniform([0, -18, -2], [65, 18, 2], (4000, 3))
        got = object_velocities_for_points(points, rows)
        assert (got != 0).any(axis=1).sum() > 100
        np.testing.assert_array_equal(got, _velocities_box_by_box(points, rows))
    rot = box_rotations(rows[:, _YAW], rows[:, _YAW + 1], rows[:, _YAW + 2])
    which = rng.integers(0, len(rows), len(points))
    each = np.empty_like(points)
    for box in range(len(rows)):
        each[which == box] = to_box_frame(points[which == box], rot[box])
    np.testing.assert_array_equal(to_box_frame(points, rot[which]), each)


# --------------------------------------------------------------------------- one frame


def wall_scene(x_wall: float = 15.0) -> np.ndarray:
    """A dense lidar wall x = x_wall, y in [-15, 15], z in [-2, 2] (5 cm grid)."""
    y, z = np.meshgrid(np.arange(-15, 15, 0.05), np.arange(-2, 2, 0.05))
    return np.column_stack([np.full(y.size, x_wall), y.ravel(), z.ravel()])


RADAR = dict(az_res_deg=1.5, el_res_deg=1.5, fov_az_deg=100.0, fov_el_deg=40.0, max_range_m=50.0,
             doppler_sign=1, doppler_span_mps=0.0)


def assert_range_within_window(out: dict, T: np.ndarray) -> None:
    """Each output range lies between the smallest and largest wall range in the radar-resolution
    window around its camera ray's angles (the first-pass window the range is drawn from)."""
    ray = cartesian_to_spherical(pixel_rays_D(out["uv"].astype(np.float64), K_SMALL, T))
    wall, delta = cartesian_to_spherical(wall_scene()), np.deg2rad(1.5)
    inside = ((np.abs(ray[:, None, 1] - wall[None, :, 1]) <= delta)
              & (np.abs(ray[:, None, 2] - wall[None, :, 2]) <= delta))
    ranges = np.broadcast_to(wall[:, 0], inside.shape)
    low = np.where(inside, ranges, np.inf).min(axis=1)
    high = np.where(inside, ranges, -np.inf).max(axis=1)
    assert np.all(out["rae"][:, 0] >= low - 1e-4) and np.all(out["rae"][:, 0] <= high + 1e-4)


def test_synthesize_frame_on_a_wall():
    T = make_T_radar_cam((0.3, 0.4, 0.5))
    prob = np.zeros((80, 160))
    prob[30:50, 60:100] = 1.0     # wall region
    prob[0:5, 60:100] = 1.0       # above z = 2 m at 15 m: sky, no lidar support
    ego = np.array([5.0, 0.0, 0.0])
    out = synthesize_frame(prob, 300.4, K_SMALL, T, wall_scene(), ego, [], estimator="nearest",
                           no_support="drop", rng=np.random.default_rng(0), **RADAR)
    k = out["points_D"].shape[0]
    assert out["n_requested"] == 300
    assert out["n_no_support"] > 0 and k > 200
    assert k + out["n_no_support"] + out["n_out_of_fov"] + out["n_beyond_range"] == 300
    points = out["points_D"].astype(np.float64)
    assert_range_within_window(out, T)
    # on the wall up to the angular window error (window 1.5 deg, camera-radar offset ~0.6 m)
    assert np.abs(points[:, 0] - 15.0).max() < 0.3
    # r, az, el recomputed from the radar origin
    np.testing.assert_allclose(out["rae"], cartesian_to_spherical(points), atol=1e-5)
    # the points lie on the sampled pixels' camera rays: they project back onto their pixels
    uv, _, valid = project_to_image(points, K_SMALL, invert_transform(T), (160, 80))
    assert valid.all()
    np.testing.assert_allclose(uv, out["uv"], atol=1e-3)
    # static world: VoD Doppler = -(unit . ego)
    unit = points / np.linalg.norm(points, axis=1, keepdims=True)
    np.testing.assert_allclose(out["doppler"], -(unit @ ego), atol=1e-5)
    assert np.all(out["support"] == SUPPORT_DIRECT)
    # the paper's mean rule is less exact but still on the wall within the window's spread
    mean = synthesize_frame(prob, 300, K_SMALL, T, wall_scene(), ego, [], estimator="mean",
                            no_support="drop", rng=np.random.default_rng(0), **RADAR)
    assert_range_within_window(mean, T)
    assert np.abs(mean["points_D"][:, 0] - 15.0).max() < 0.5


def test_refill_draws_oversample_the_keep_rate():
    assert _refill_draws(10, 80, 100) == int(np.ceil(REFILL_OVERSAMPLE * 10 / (81 / 102)))
    assert _refill_draws(10, 0, 100) == REFILL_MAX_FACTOR * 10  # nothing kept: capped, never infinite
    assert _refill_draws(10, 100, 100) == int(np.ceil(REFILL_OVERSAMPLE * 10 * 102 / 101))
    assert _refill_draws(1, 50, 100) >= 1


def test_synthesize_frame_drop_reasons_and_reproducibility():
    T = make_T_radar_cam()
    prob = np.ones((80, 160))
    args = (prob, 100, K_SMALL, T, wall_scene(), np.zeros(3), [])
    a = synthesize_frame(*args, estimator="mean", no_support="widen", rng=np.random.default_rng(5), **RADAR)
    b = synthesize_frame(*args, estimator="mean", no_support="widen", rng=np.random.default_rng(5), **RADAR)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    narrow = dict(RADAR, fov_az_deg=10.0)
    c = synthesize_frame(*args, estimator="mean", no_support="widen", rng=np.random.default_rng(5), **narrow)
    assert c["n_out_of_fov"] > 0 and np.all(np.abs(np.rad2deg(c["rae"][:, 1])) <= 5.0 + 1e-4)
    near = dict(RADAR, max_range_m=14.0)
    d = synthesize_frame(*args, estimator="mean", no_support="widen", rng=np.random.default_rng(5), **near)
    assert d["points_D"].shape[0] == 0 and d["n_beyond_range"] == 100 - d["n_no_support"] - d["n_out_of_fov"]
    e = synthesize_frame(np.ones((80, 160)), 0, K_SMALL, T, wall_scene(), np.zeros(3), [],
                         estimator="mean", no_support="drop", rng=np.random.default_rng(0), **RADAR)
    assert e["points_D"].shape == (0, 3) and e["doppler"].shape == (0,) and e["n_requested"] == 0
    # refill: the dropped samples are drawn again until n points are out (or the rounds run out)
    half = dict(RADAR, fov_az_deg=40.0)
    h = synthesize_frame(*args, estimator="mean", no_support="widen", rng=np.random.default_rng(5), **half)
    f = synthesize_frame(*args, estimator="mean", no_support="widen", rng=np.random.default_rng(5),
                         refill_rounds=30, **half)
    assert h["points_D"].shape[0] < 70 and f["points_D"].shape[0] == 100
    assert np.all(np.abs(np.rad2deg(f["rae"][:, 1])) <= 20.0 + 1e-4)
    assert f["n_out_of_fov"] > h["n_out_of_fov"]  # every round's drops are counted
    once = synthesize_frame(*args, estimator="mean", no_support="widen", rng=np.random.default_rng(5),
                            refill_rounds=1, **half)
    assert once["points_D"].shape[0] == 100  # one oversampled round suffices
    np.testing.assert_array_equal(once["points_D"][:len(h["points_D"])], h["points_D"])  # round 0 as before
    # the drops counted are those of the draws up to the one that completed the frame: at the
    # field of view's keep rate q (round 0: k of 100), about (1 - q) / q per kept point
    q = h["points_D"].shape[0] / 100
    assert 0.7 < once["n_out_of_fov"] / (100 * (1 - q) / q) < 1.2  # all draws counted: about 1.4
    capped = synthesize_frame(*args, estimator="mean", no_support="widen", rng=np.random.default_rng(5),
                              refill_rounds=1, **narrow)  # keep rate ~10%: the draw cap leaves it short
    assert c["points_D"].shape[0] < capped["points_D"].shape[0] < 100
    np.testing.assert_array_equal(capped["points_D"][:len(c["points_D"])], c["points_D"])
    g = synthesize_frame(*args, estimator="mean", no_support="widen", rng=np.random.default_rng(5),
                         refill_rounds=30, **near)
    assert g["points_D"].shape[0] == 0 and g["n_requested"] == 100  # nothing placeable: the rounds end
    with pytest.raises(ValueError, match="refill_rounds"):
        synthesize_frame(*args, estimator="mean", no_support="widen", rng=np.random.default_rng(5),
                         refill_rounds=-1, **RADAR)
    for bad in (np.nan, -3.0):
        with pytest.raises(ValueError, match="n_hat"):
            synthesize_frame(np.ones((80, 160)), bad, K_SMALL, T, wall_scene(), np.zeros(3), [],
                             estimator="mean", no_support="drop", rng=np.random.default_rng(0), **RADAR)


def test_bad_generation_settings_are_config_errors():
    from pipeline.config import load_config
    from pipeline.errors import ConfigError
    from stages.synthesize import check_generation

    check_generation(load_config("synthetic", environ={}))
    for key, value, words in (("synth.sampling", "sorted", "'synth.sampling' must be one of iid, systematic"),
                              ("synth.range_estimator", "far", "synth.range_estimator"),
                              ("synth.no_support", "skip", "synth.no_support"),
                              ("synth.refill_rounds", "-1", "synth.refill_rounds' must be finite and >= 0"),
                              ("synth.placement", "mesh", "'synth.placement' must be one of lidar, ray"),
                              ("placement.voxel_m", "-1", "placement.voxel_m' must be finite and >= 0"),
                              ("placement.map_weight", "1.5", r"placement.map_weight' must be in \[0, 1\]"),
                              ("synth.device", "tpu", "synth.device must be 'auto', 'cpu' or 'cuda', got 'tpu'")):
        with pytest.raises(ConfigError, match=words):  # numeric ones when the configuration is built
            check_generation(load_config("synthetic", {key: value}, environ={}))
    check_generation(load_config("synthetic", {"synth.device": "cpu"}, environ={}))
    import torch

    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="synth.device = 'cuda' but CUDA is not available"):
            check_generation(load_config("synthetic", {"synth.device": "cuda"}, environ={}))


class _Rows:
    """A stage array as summarise reads it (``[:]`` and ``.oindex[indices]``)."""

    def __init__(self, values: np.ndarray) -> None:
        self.values = np.asarray(values)
        self.oindex = self

    def __getitem__(self, index):
        return self.values[index]


class _Store:
    def __init__(self, status, **arrays) -> None:
        self._status, self._arrays = np.asarray(status), {k: _Rows(v) for k, v in arrays.items()}

    def status(self) -> np.ndarray:
        return self._status

    def array(self, name: str) -> _Rows:
        return self._arrays[name]


def test_synthesize_summary_names_the_inputs_outside_placenets_training_range():
    """Shares over the finished frames' candidates, largest first, only above OUTSIDE_NOTE_SHARE; a
    PlaceNet saved without its range (-1) is said to be unchecked; unfinished frames do not count."""
    from pipeline.cache import DONE, PENDING
    from pipeline.config import load_config
    from pipeline.placement import FEATURES
    from stages.synthesize import summarise

    cfg = load_config("synthetic", environ={})
    k_range, k_dist, k_z = FEATURES.index("log_range"), FEATURES.index("log_neighbour_dist"), FEATURES.index("z_m")
    outside = np.zeros((3, len(FEATURES)), np.int32)
    outside[0, [k_range, k_dist, k_z]] = [100, 700, 20]
    outside[1, [k_range, k_dist, k_z]] = [300, 100, 20]
    outside[2, :] = 999                                                         # not finished: ignored
    rss = np.array([[0, 30, 1, 0], [0, 0, 1, 2], [9, 9, 9, 9]], np.int32)           # of 100 + 200 points
    store = _Store([DONE, DONE, PENDING], candidates=np.array([1000, 1000, 5]), outside_training=outside,
                   rss_points=np.array([100, 200, 5]), rss_outside=rss)
    line, rss_line = summarise(store, cfg)
    assert rss_line.startswith("RSS-Net inputs outside") and "(where 1% of its training rows lie): range_m on 10% " \
        "of the 300 synthesized points;" in rss_line and rss_line.endswith("its RSS there is extrapolated"), rss_line
    assert "log_neighbour_dist on 40%, log_range on 20% of the 2,000 lidar candidates;" in line, line
    assert "z_m" not in line                                                    # 2%: below the note's share
    old = _Store([DONE, DONE], candidates=np.array([1000, 0]), outside_training=np.full((2, len(FEATURES)), -1),
                 rss_points=np.array([10, 0]), rss_outside=np.full((2, 4), -1))
    assert summarise(old, cfg) == [f"{net}'s inputs not checked against its training range: its checkpoint was "
                                   f"saved without it, by an earlier version (`pipeline run train --force` saves it)"
                                   for net in ("PlaceNet", "RSS-Net")]
    quiet = _Store([DONE], candidates=np.array([1000]), outside_training=np.zeros((1, len(FEATURES)), np.int32),
                   rss_points=np.array([0]), rss_outside=np.zeros((1, 4), np.int32))
    assert summarise(quiet, cfg) == []


def test_synthesize_summary_of_many_frames_reads_a_sample_of_them(monkeypatch):
    """Above SUMMARY_FRAMES_MAX finished frames the shares are counted over a random sample of
    them (a read of four chunks per frame, a request each on an object store), and the line says
    so; the sample holds finished frames only."""
    import stages.synthesize as synthesize
    from pipeline.cache import DONE, PENDING
    from pipeline.config import load_config
    from pipeline.placement import FEATURES

    monkeypatch.setattr(synthesize, "SUMMARY_FRAMES_MAX", 50)
    n = 400
    status = np.where(np.arange(n) % 4 == 3, PENDING, DONE)  # 300 finished
    outside = np.zeros((n, len(FEATURES)), np.int32)
    outside[:, FEATURES.index("log_range")] = np.where(status == DONE, 30, 10**6)  # 30% where finished
    read: list[np.ndarray] = []

    class Rows(_Rows):
        def __getitem__(self, index):
            read.append(np.asarray(index))
            return self.values[index]

    store = _Store(status, candidates=np.full(n, 100), outside_training=outside, rss_points=np.zeros(n, int),
                   rss_outside=np.zeros((n, 4), np.int32))
    store._arrays = {k: Rows(v.values) for k, v in store._arrays.items()}
    (line,) = synthesize.summarise(store, load_config("synthetic", environ={}))
    assert "log_range on 30% of the 5,000 lidar candidates (in a random sample of 50 of the 300 finished " \
        "frames);" in line, line
    assert all(len(index) == 50 and (status[index] == DONE).all() for index in read) and len(read) == 4


def test_synthesize_frame_doppler_uses_labels_sign_and_span():
    """The frame's Doppler is eq. 16 with each point's object velocity, in the simulated radar's
    convention: an Astyx-like radar (sign -1: positive approaching, wrapped into 10.39 m/s) seeing a
    static wall at 8 m/s reports wrap(+8 cos) < 0, and points on a box moving with the ego vehicle
    report 0. n_hat is rounded to the nearest count."""
    span = 10.39
    T = make_T_radar_cam((0.3, 0.4, 0.5))
    prob = np.zeros((80, 160))
    prob[30:50, 60:100] = 1.0
    ego = np.array([8.0, 0.0, 0.0])
    box = Object3D("Car", np.array([15.0, 5.0, 0.0]), np.array([2.0, 10.0, 6.0]), 0.0, velocity_D=ego.copy())
    radar = dict(RADAR, doppler_sign=-1, doppler_span_mps=span)
    out = synthesize_frame(prob, 120.6, K_SMALL, T, wall_scene(), ego, [box], estimator="nearest",
                           no_support="drop", rng=np.random.default_rng(1), **radar)
    assert out["n_requested"] == 121
    points = out["points_D"].astype(np.float64)
    on_box = (np.abs(points[:, 0] - 15.0) <= 1.3) & (np.abs(points[:, 1] - 5.0) <= 5.3) & (np.abs(points[:, 2]) <= 3.3)
    assert 10 < on_box.sum() < len(points) - 10
    unit = points / np.linalg.norm(points, axis=1, keepdims=True)
    range_rate = -(unit @ ego) * ~on_box                   # static world: -(u . v_ego); on the box: 0
    expected = np.mod(-range_rate + span / 2, span) - span / 2
    np.testing.assert_allclose(out["doppler"], expected, atol=1e-4)
    assert np.all(out["doppler"][~on_box] < -1.0)           # +8 m/s approaching, aliased
