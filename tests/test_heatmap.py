"""Tests of pipeline.heatmap against the naive float64 per-point sum and hand-made objects."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.frame import FrameRecord, Object3D
from pipeline.heatmap import (
    estimate_sigma_px,
    gaussian_heatmap,
    naive_heatmap,
    object_points_uv,
    points_in_box,
    resize_distribution,
    sigma_from_frames,
)

NORMAL_FLOOR = 1e-28
"""Compare per-pixel relative error where the value is well inside float32's normal range."""


def _max_rel_err(fast: np.ndarray, ref: np.ndarray) -> float:
    mask = ref >= NORMAL_FLOOR
    return float(np.max(np.abs(fast.astype(np.float64) - ref)[mask] / ref[mask]))


@pytest.mark.parametrize(
    "seed, size_wh, sigma, n",
    [
        (0, (64, 48), (5.0, 7.0), 1),
        (1, (80, 40), (3.0, 3.0), 17),
        (2, (33, 71), (12.0, 4.5), 40),
        (3, (120, 90), (25.0, 25.0), 200),
    ],
)
def test_matches_naive_with_subpixel_and_outside_points(seed, size_wh, sigma, n):
    rng = np.random.default_rng(seed)
    w, h = size_wh
    # Sub-pixel positions, some outside the image by up to 10 px, some exactly on the border.
    uv = rng.uniform([-10.0, -10.0], [w + 10.0, h + 10.0], (n, 2))
    uv[0] = [w - 0.5, -0.5]
    fast = gaussian_heatmap(uv, size_wh, sigma)
    ref = naive_heatmap(uv, size_wh, sigma)
    assert fast.shape == (h, w) and fast.dtype == np.float32
    assert _max_rel_err(fast, ref) < 1e-5
    assert abs(float(fast.sum(dtype=np.float64)) - 1.0) < 1e-5


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 25), w=st.integers(1, 40), h=st.integers(1, 40),
       sx=st.floats(0.3, 30.0), sy=st.floats(0.3, 30.0))
def test_property_matches_naive(seed, n, w, h, sx, sy):
    rng = np.random.default_rng(seed)
    uv = rng.uniform([-3 * sx, -3 * sy], [w + 3 * sx, h + 3 * sy], (n, 2))
    fast = gaussian_heatmap(uv, (w, h), (sx, sy))
    assert fast.shape == (h, w) and np.all(fast >= 0)
    assert _max_rel_err(fast, naive_heatmap(uv, (w, h), (sx, sy))) < 1e-5


def test_point_far_outside_does_not_underflow_the_map():
    # 60 sigma away: every in-image density underflows in the naive float64 form, but the
    # normalised map is still defined (the in-image tail of the Gaussian, renormalised).
    uv = np.array([[-300.0, 20.0]])
    fast = gaussian_heatmap(uv, (40, 30), (5.0, 5.0))
    assert np.isfinite(fast).all() and abs(float(fast.sum()) - 1.0) < 1e-5
    # The in-image shape along u is exp(-0.5((u+300)/5)^2) renormalised: decreasing in u.
    row = fast[20].astype(np.float64)
    held = row[row > NORMAL_FLOOR]  # columns far down the tail underflow float32
    assert len(held) >= 2 and np.all(np.diff(held) < 0)
    # Columns follow the exact ratio of Gaussians between neighbours where float32 is normal.
    ratio = row[1] / row[0]
    assert ratio == pytest.approx(np.exp(-0.5 * ((301.0 / 5) ** 2 - (300.0 / 5) ** 2)), rel=1e-5)


def test_far_point_mixed_with_near_point_is_negligible_not_dominant():
    near = np.array([[10.0, 10.0]])
    both = np.array([[10.0, 10.0], [5000.0, 10.0]])
    a = gaussian_heatmap(near, (32, 24), (3.0, 3.0))
    b = gaussian_heatmap(both, (32, 24), (3.0, 3.0))
    np.testing.assert_allclose(a, b, rtol=1e-6, atol=0)


def test_single_point_at_pixel_centre_peaks_there_and_is_symmetric():
    m = gaussian_heatmap(np.array([[20.0, 15.0]]), (41, 31), (4.0, 2.0))
    assert np.unravel_index(np.argmax(m), m.shape) == (15, 20)
    np.testing.assert_allclose(m, m[:, ::-1], rtol=1e-6)
    np.testing.assert_allclose(m, m[::-1, :], rtol=1e-6)


def test_many_points_chunked_path_matches_naive(monkeypatch):
    import pipeline.heatmap as hm

    monkeypatch.setattr(hm, "_FACTOR_CHUNK", 7)  # 30 points: 4 full blocks and a remainder
    rng = np.random.default_rng(5)
    uv = rng.uniform(0, 30, (30, 2))
    assert _max_rel_err(hm.gaussian_heatmap(uv, (30, 30), (4.0, 6.0)), naive_heatmap(uv, (30, 30), (4.0, 6.0))) < 1e-5


@pytest.mark.parametrize(
    "uv, size, sigma, match",
    [
        (np.zeros((0, 2)), (10, 10), (1.0, 1.0), "no points"),
        (np.zeros((3, 3)), (10, 10), (1.0, 1.0), "expected shape"),
        (np.array([[np.nan, 1.0]]), (10, 10), (1.0, 1.0), "non-finite"),
        (np.zeros((1, 2)), (0, 10), (1.0, 1.0), "size_wh"),
        (np.zeros((1, 2)), (10, 10), (0.0, 1.0), "sigma_px"),
    ],
)
def test_errors(uv, size, sigma, match):
    with pytest.raises(ValueError, match=match):
        gaussian_heatmap(uv, size, sigma)
    with pytest.raises(ValueError, match=match):
        naive_heatmap(uv, size, sigma)


def test_estimate_sigma_recovers_known_spread():
    rng = np.random.default_rng(0)
    objects = [rng.normal(rng.uniform(0, 1000, 2), [30.0, 12.0], (60, 2)) for _ in range(40)]
    objects.append(np.array([[0.0, 0.0]]))  # too few points: skipped
    sx, sy = estimate_sigma_px(objects)
    assert sx == pytest.approx(30.0, rel=0.08) and sy == pytest.approx(12.0, rel=0.08)


def test_estimate_sigma_is_robust_to_outliers():
    rng = np.random.default_rng(1)
    objects = [rng.normal(500.0, 10.0, (100, 2)) for _ in range(10)]
    for obj in objects:
        obj[:5] = 1e5  # 5 % stray points
    sx, sy = estimate_sigma_px(objects)
    assert 9.0 < sx < 11.5 and 9.0 < sy < 11.5


def test_estimate_sigma_counts_an_object_with_exactly_min_points():
    # deviations from the median (1, 1): (-1, 0, 2) per axis, median |dev| = 1
    sx, sy = estimate_sigma_px([np.array([[0.0, 0.0], [1.0, 1.0], [3.0, 3.0]])], min_points=3)
    assert sx == pytest.approx(1.4826) and sy == pytest.approx(1.4826)


def test_estimate_sigma_errors():
    with pytest.raises(ValueError, match="no object"):
        estimate_sigma_px([np.zeros((2, 2))])
    with pytest.raises(ValueError, match="expected shape"):
        estimate_sigma_px([np.zeros((5, 3))])


def test_points_in_box_rotated_and_grown():
    box = Object3D("car", np.array([10.0, 0.0, 0.0]), np.array([4.0, 2.0, 1.5]), np.pi / 2)
    # Rotated by 90 deg: length along y of {D}.
    pts = np.array([[10.0, 1.9, 0.0], [11.4, 0.0, 0.0], [10.0, 0.0, 0.74], [10.0, 2.3, 0.0]])
    np.testing.assert_array_equal(points_in_box(pts, box), [True, False, True, False])
    np.testing.assert_array_equal(points_in_box(pts, box, grow_m=0.5), [True, True, True, True])


def test_points_in_box_follows_the_yaw_direction():
    # yaw 45 deg (counter-clockwise seen from above, towards +y): the long axis points along (1, 1)
    box = Object3D("car", np.array([10.0, 0.0, 0.0]), np.array([4.0, 1.0, 1.0]), np.pi / 4)
    along, across = np.array([1.0, 1.0, 0.0]) / np.sqrt(2), np.array([-1.0, 1.0, 0.0]) / np.sqrt(2)
    pts = box.center_D + np.array([1.8 * along, -1.8 * along, 1.8 * across, 0.4 * across])
    np.testing.assert_array_equal(points_in_box(pts, box), [True, True, False, True])


def test_points_in_box_follows_the_tilt():
    """A box pitched 15 deg and rolled -8 deg (Astyx's boxes lean about 4 deg in {D}): its corners,
    shrunk a little, are inside, the upright box's are not; an upright box gives, to the bit, the
    yaw-only test it had before boxes had a tilt (2026-12-06, a93a48f), points on its faces included."""
    from pipeline.world.rig import rotation_zyx

    box = Object3D("car", np.array([12.0, -3.0, 0.5]), np.array([4.0, 2.0, 1.5]), 0.7,
                   pitch_rad=np.radians(15.0), roll_rad=np.radians(-8.0))
    upright = Object3D("car", box.center_D, box.size_lwh_m, 0.7)
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
    local = 0.49 * signs * box.size_lwh_m
    inside = box.center_D + local @ rotation_zyx(0.7, np.radians(15.0), np.radians(-8.0)).T
    assert points_in_box(inside, box).all()
    assert not points_in_box(inside, upright).any()
    assert not points_in_box(upright.center_D + local @ rotation_zyx(0.7, 0.0, 0.0).T, box).any()

    rng = np.random.default_rng(2)
    for _ in range(20):
        obj = Object3D("car", rng.uniform(-5, 5, 3), rng.uniform(0.5, 5, 3), rng.uniform(-np.pi, np.pi))
        c, s = np.cos(obj.yaw_rad), np.sin(obj.yaw_rad)
        pts = obj.center_D + rng.uniform(-4, 4, (300, 3))
        pts[:4] = obj.center_D + np.outer([-0.5, 0.5, -0.5, 0.5], obj.size_lwh_m[0]) * [c, s, 0]  # on the end faces
        d = pts - obj.center_D
        for grow in (0.0, 0.2):
            before = ((np.abs(c * d[:, 0] + s * d[:, 1]) <= obj.size_lwh_m[0] / 2 + grow)
                      & (np.abs(-s * d[:, 0] + c * d[:, 1]) <= obj.size_lwh_m[1] / 2 + grow)
                      & (np.abs(d[:, 2]) <= obj.size_lwh_m[2] / 2 + grow))
            np.testing.assert_array_equal(points_in_box(pts, obj, grow), before)


def _frame_with_objects(rng: np.random.Generator) -> tuple[FrameRecord, np.ndarray]:
    """Camera looking along +x of {D}; two boxes with radar points; a stray point outside boxes."""
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    R_radar_cam = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # cam z -> D x
    T_radar_cam = np.eye(4)
    T_radar_cam[:3, :3] = R_radar_cam
    labels = [
        Object3D("car", np.array([20.0, 2.0, 0.0]), np.array([4.0, 2.0, 1.5]), 0.0),
        Object3D("car", np.array([30.0, -3.0, 0.5]), np.array([4.0, 2.0, 1.5]), 0.3),
    ]
    radar = [np.c_[obj.center_D + rng.uniform(-0.8, 0.8, (20, 3)), np.zeros((20, 2))] for obj in labels]
    radar.append(np.array([[15.0, -8.0, 0.0, 0.0, 0.0]]))
    frame = FrameRecord(
        frame_id="f0", sequence_id="s0", timestamp_s=0.0, image=np.zeros((480, 640, 3), np.uint8), K=K,
        lidar_D=np.zeros((0, 3), np.float32), lidar_intensity=np.zeros(0, np.float32),
        radar_D=np.concatenate(radar).astype(np.float32), T_radar_lidar=np.eye(4), T_radar_cam=T_radar_cam,
        ego_velocity_D=np.zeros(3), labels=labels,
    )
    return frame.validate(), K


def test_object_points_uv_projects_each_objects_points():
    frame, K = _frame_with_objects(np.random.default_rng(2))
    per_object = object_points_uv(frame)
    assert [len(p) for p in per_object] == [20, 20]
    # Hand projection of the first object's points: u = cx + f (-y / x), v = cy + f (-z / x).
    p = frame.radar_D[:20, :3].astype(np.float64)
    expected = np.c_[320.0 + 500.0 * (-p[:, 1] / p[:, 0]), 240.0 + 500.0 * (-p[:, 2] / p[:, 0])]
    np.testing.assert_allclose(per_object[0], expected, rtol=1e-6)


def test_object_points_uv_keeps_only_points_inside_the_image():
    frame, _ = _frame_with_objects(np.random.default_rng(4))
    # a third object 6 m to the left at 5 m: u = 320 + 500 * 6 / 5 < 0, left of the image
    side = Object3D("car", np.array([5.0, 6.0, 0.0]), np.array([2.0, 2.0, 1.5]), 0.0)
    pts = np.c_[side.center_D + np.random.default_rng(5).uniform(-0.5, 0.5, (10, 3)), np.zeros((10, 2))]
    frame = FrameRecord(**{**frame.__dict__, "labels": [*frame.labels, side],
                           "radar_D": np.vstack([frame.radar_D, pts]).astype(np.float32)})
    assert [len(p) for p in object_points_uv(frame)] == [20, 20, 0]


def test_sigma_from_frames_pools_objects():
    frame, _ = _frame_with_objects(np.random.default_rng(3))
    sx, sy = sigma_from_frames([frame, frame])
    ref = estimate_sigma_px(object_points_uv(frame) * 2)
    assert (sx, sy) == pytest.approx(ref)
    no_labels = FrameRecord(**{**frame.__dict__, "labels": []})
    with pytest.raises(ValueError, match="no object"):
        sigma_from_frames([no_labels])


# ------------------------------------------------------- interpolated (Chebyshev) path, many points


def test_chebyshev_bound_covers_the_observed_interpolation_error():
    import pipeline.heatmap as hm

    rng = np.random.default_rng(5)
    centres = np.sort(rng.uniform(-0.5, 399.5, 300))
    plan = hm._chebyshev_plan(centres, 400, 20.0)
    assert plan is not None
    exact = np.exp(-0.5 * ((np.arange(400)[None, :] - centres[:, None]) / 20.0) ** 2)
    observed = np.abs(plan.basis @ plan.at_nodes - exact).max()
    assert observed <= plan.eps <= hm._EPS_TARGET
    # The bound is not vacuous: the interpolant one degree-step lower is measurably worse.
    degree = len(plan.nodes) - 1
    assert hm.chebyshev_error_bound(degree - 24, 10.0) > 1e3 * plan.eps


@pytest.mark.parametrize("clustered", [False, True])
def test_interpolated_path_matches_naive_and_certifies_the_tails(clustered, monkeypatch):
    """Many points inside the image take the interpolated path; where the certified bound is not
    small against a pixel (far tails of a cluster), that row is recomputed exactly."""
    import pipeline.heatmap as hm

    rng = np.random.default_rng(7)
    w, h, sigma = 300, 200, (12.0, 9.0)
    if clustered:  # a band of rows at the top: the bottom rows hold only far tails
        uv = np.column_stack([rng.uniform(-0.5, w - 0.5, 400), rng.uniform(0, 130, 400)])
    else:
        uv = rng.uniform([-0.5, -0.5], [w - 0.5, h - 0.5], (400, 2))
    assert hm._chebyshev_plan(uv[:, 0], w, sigma[0]) is not None
    assert hm._chebyshev_plan(uv[:, 1], h, sigma[1]) is not None
    exact_rows = []
    original_exp = np.exp

    def spy_exp(x, *args, **kwargs):  # the exact fallback is the only exp over (N, rows)
        if isinstance(x, np.ndarray) and x.ndim == 2 and x.shape[0] == len(uv) and x.shape[1] < h:
            exact_rows.append(x.shape[1])
        return original_exp(x, *args, **kwargs)

    monkeypatch.setattr(hm.np, "exp", spy_exp)
    fast = hm.gaussian_heatmap(uv, (w, h), sigma)
    monkeypatch.undo()
    ref = naive_heatmap(uv, (w, h), sigma)
    assert _max_rel_err(fast, ref) < 1e-5
    assert abs(float(fast.sum(dtype=np.float64)) - 1.0) < 1e-5
    assert bool(exact_rows) == clustered  # uniform points: every row certified; cluster: tails redone


def test_interpolated_path_is_close_to_the_exact_product(monkeypatch):
    import pipeline.heatmap as hm

    rng = np.random.default_rng(9)
    uv = rng.uniform([-0.5, -0.5], [399.5, 249.5], (500, 2))
    fast = hm.gaussian_heatmap(uv, (400, 250), (30.0, 30.0))
    monkeypatch.setattr(hm, "_chebyshev_plan", lambda *a: None)
    exact = hm.gaussian_heatmap(uv, (400, 250), (30.0, 30.0))
    np.testing.assert_allclose(fast, exact, rtol=3e-6)


def test_resize_distribution_area_averages_when_shrinking_and_interpolates_when_growing():
    rng = np.random.default_rng(0)
    prob = rng.random((8, 12))
    prob /= prob.sum()
    small = resize_distribution(prob, (3, 2))  # 4 x 4 blocks: each block's mass, nothing lost
    np.testing.assert_allclose(small, prob.reshape(2, 4, 3, 4).sum(axis=(1, 3)), rtol=1e-5)
    # 2 x 2 -> 4 x 4 bilinear with pixel-centre alignment: 1-D [a, b] -> [a, (3a + b) / 4, (a + 3b) / 4, b]
    coarse = np.array([[0.1, 0.2], [0.3, 0.4]])
    up = np.array([[1.0, 0.0], [0.75, 0.25], [0.25, 0.75], [0.0, 1.0]])
    expected = up @ coarse @ up.T
    np.testing.assert_allclose(resize_distribution(coarse, (4, 4)), expected / expected.sum(), rtol=1e-5)
