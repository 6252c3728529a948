"""Metrics against hand computations and brute-force oracles."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist
from scipy.stats import wasserstein_distance

from pipeline.geometry import wrap_doppler
from pipeline import metrics as M


# ---------------------------------------------------------------- brute-force oracles

def brute_gospa(syn: np.ndarray, real: np.ndarray, c: float, p: float) -> float:
    """GOSPA (alpha = 2) by enumerating every partial assignment of pairs with d < c."""
    n, m = len(syn), len(real)
    best = c ** p / 2 * (n + m)
    d = cdist(syn, real) if n and m else np.zeros((n, m))
    for k in range(1, min(n, m) + 1):
        for rows in itertools.combinations(range(n), k):
            for cols in itertools.permutations(range(m), k):
                dd = d[list(rows), list(cols)]
                if np.all(dd < c):
                    best = min(best, float(np.sum(dd ** p)) + c ** p / 2 * (n + m - 2 * k))
    return best ** (1 / p)


def brute_max_matches(syn: np.ndarray, real: np.ndarray, gates: tuple[float, float, float]) -> int:
    """Maximum number of admissible one-to-one pairs, by enumerating injections."""
    g_m, g_rss, g_dop = gates
    n, m = len(syn), len(real)
    ok = ((cdist(syn[:, :3], real[:, :3]) <= g_m)
          & (np.abs(syn[:, None, 4] - real[None, :, 4]) <= g_rss)
          & (np.abs(syn[:, None, 3] - real[None, :, 3]) <= g_dop))
    if n > m:
        ok, n, m = ok.T, m, n
    best = 0
    for cols in itertools.permutations(range(m), n):
        best = max(best, int(sum(ok[i, j] for i, j in enumerate(cols))))
    return best


def small_points(max_n: int, scale: float, cols: int):
    return st.integers(0, max_n).flatmap(
        lambda n: st.lists(st.lists(st.floats(-scale, scale, allow_nan=False), min_size=cols, max_size=cols),
                           min_size=n, max_size=n)).map(lambda x: np.array(x, dtype=np.float64).reshape(-1, cols))


# ---------------------------------------------------------------- KL and counts

def test_kl_hand_value_and_zero_terms():
    P = np.array([[0.5, 0.5, 0.0]])
    Q = np.array([[0.25, 0.25, 0.5]])
    assert M.kl_divergence(P, Q) == pytest.approx(math.log(2.0))
    assert M.kl_divergence(P, P) == pytest.approx(0.0, abs=1e-12)
    # a heatmap-like map against itself: never the small negative a float64 sum can give
    rng = np.random.default_rng(3)
    for _ in range(20):
        m = rng.random((40, 80)) ** 8
        assert M.kl_divergence(m, m) >= 0.0


def test_kl_normalises_and_clips():
    P = np.array([[2.0, 2.0]])  # unnormalised target
    assert M.kl_divergence(P, np.array([[1.0, 1.0]])) == pytest.approx(0.0, abs=1e-12)
    v = M.kl_divergence(np.array([[1.0, 0.0]]), np.array([[0.0, 1.0]]))
    assert np.isfinite(v) and v == pytest.approx(-math.log(M.KL_EPS))
    assert math.isnan(M.kl_divergence(np.zeros((2, 2)), np.ones((2, 2))))
    with pytest.raises(ValueError):
        M.kl_divergence(np.ones((2, 2)), -np.ones((2, 2)))
    with pytest.raises(ValueError):
        M.kl_divergence(np.ones((2, 2)), np.ones((2, 3)))


def test_count_errors():
    assert M.count_errors(15, 10) == pytest.approx((0.5, 0.25))
    assert M.count_errors(5, 10) == pytest.approx((0.5, 0.25))
    assert all(math.isnan(x) for x in M.count_errors(3, 0))


# ---------------------------------------------------------------- Chamfer

def test_chamfer_hand_value():
    a = np.array([[0.0, 0, 0], [1, 0, 0]])
    b = np.array([[0.0, 0, 2]])
    # a->b: 2 and sqrt(5); b->a: 2
    assert M.chamfer_m(a, b) == pytest.approx(0.5 * ((2 + math.sqrt(5)) / 2 + 2))
    assert M.chamfer_m(a, a) == 0.0
    assert math.isnan(M.chamfer_m(a, np.zeros((0, 3))))


@settings(max_examples=40, deadline=None)
@given(small_points(8, 10.0, 3), small_points(8, 10.0, 3))
def test_chamfer_matches_brute_force(a, b):
    if len(a) == 0 or len(b) == 0:
        assert math.isnan(M.chamfer_m(a, b))
        return
    d = cdist(a, b)
    assert M.chamfer_m(a, b) == pytest.approx(0.5 * (d.min(1).mean() + d.min(0).mean()), abs=1e-9)


# ---------------------------------------------------------------- GOSPA

def test_gospa_hand_values():
    real = np.array([[0.0, 0, 0], [10, 0, 0]])
    syn = np.array([[1.0, 0, 0]])
    g = M.gospa(syn, real)  # c = 2, p = 2: one pair at d = 1, one missed point
    assert g["localisation"] == pytest.approx(1.0)
    assert g["missed"] == pytest.approx(2.0) and g["false"] == 0.0
    assert g["total"] == pytest.approx(math.sqrt(3.0))
    assert (g["n_assigned"], g["n_missed"], g["n_false"]) == (1, 1, 0)
    far = M.gospa(np.array([[0.0, 0, 5]]), np.array([[0.0, 0, 0]]))  # beyond c: missed + false
    assert far["localisation"] == 0.0 and far["missed"] == far["false"] == pytest.approx(2.0)
    assert far["total"] == pytest.approx(2.0)
    assert M.gospa(real, real)["total"] == 0.0
    assert M.gospa(np.zeros((0, 3)), np.zeros((0, 3)))["total"] == 0.0
    assert M.gospa(np.zeros((0, 3)), real)["total"] == pytest.approx(math.sqrt(4.0))


@settings(max_examples=60, deadline=None)
@given(small_points(4, 3.0, 3), small_points(4, 3.0, 3), st.sampled_from([1.0, 2.0]), st.sampled_from([1.0, 2.0]))
def test_gospa_matches_enumeration(syn, real, c, p):
    expected = brute_gospa(syn, real, c, p)
    for density in (0.0, 2.0):  # dense Hungarian, then the sparse formulation
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(M, "DENSE_MATCHING_MIN_DENSITY", density)
            g = M.gospa(syn, real, c=c, p=p)
        assert g["total"] == pytest.approx(expected, rel=1e-9, abs=1e-9)
        assert g["localisation"] + g["missed"] + g["false"] == pytest.approx(g["total"] ** p, rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("box", [3.0, 60.0])  # dense graph (dense solver) and sparse graph
def test_gospa_large_matches_dense_hungarian(box):
    rng = np.random.default_rng(1)
    real = rng.uniform(0, box, (400, 3))
    syn = rng.uniform(0, box, (450, 3))
    C = np.minimum(cdist(syn, real), 2.0) ** 2
    r, c = linear_sum_assignment(C)
    ref = math.sqrt(C[r, c].sum() + 2.0 * (len(syn) - len(real)))
    assert M.gospa(syn, real)["total"] == pytest.approx(ref, rel=1e-9)


def test_gospa_sparse_and_dense_solvers_agree(monkeypatch):
    rng = np.random.default_rng(2)
    real, syn = rng.uniform(0, 8, (200, 3)), rng.uniform(0, 8, (230, 3))
    dense = M.gospa(syn, real)
    monkeypatch.setattr(M, "DENSE_MATCHING_MIN_DENSITY", 2.0)  # force the sparse formulation
    sparse = M.gospa(syn, real)
    assert sparse["total"] == pytest.approx(dense["total"], rel=1e-9)
    assert sparse["n_assigned"] == dense["n_assigned"]


def test_gospa_rejects_other_alpha():
    with pytest.raises(ValueError):
        M.gospa(np.zeros((1, 3)), np.zeros((1, 3)), alpha=1.0)


# ---------------------------------------------------------------- matched F1

def test_f1_identical_and_disjoint():
    rng = np.random.default_rng(0)
    real = np.column_stack([rng.uniform(0, 30, (50, 3)), rng.normal(0, 3, 50), rng.normal(0, 10, 50)])
    f = M.matched_f1(real, real)
    assert (f["precision"], f["recall"], f["f1"], f["matches"]) == (1.0, 1.0, 1.0, 50)
    moved = real.copy()
    moved[:, 0] += 100.0  # beyond the distance gate
    assert M.matched_f1(moved, real)["f1"] == 0.0
    louder = real.copy()
    louder[:, 4] += 8.5  # beyond the RSS gate only
    assert M.matched_f1(louder, real)["matches"] == 0
    faster = real.copy()
    faster[:, 3] += 2.6  # beyond the Doppler gate only
    assert M.matched_f1(faster, real)["matches"] == 0


def test_f1_hand_value_and_empty():
    real = np.array([[0.0, 0, 0, 0, 0], [5, 0, 0, 0, 0]])
    syn = np.array([[0.5, 0, 0, 1, 3], [20, 0, 0, 0, 0], [21, 0, 0, 0, 0]])
    f = M.matched_f1(syn, real)
    assert f["matches"] == 1
    assert f["precision"] == pytest.approx(1 / 3) and f["recall"] == pytest.approx(0.5)
    assert f["f1"] == pytest.approx(2 * (1 / 3) * 0.5 / (1 / 3 + 0.5))
    e = M.matched_f1(np.zeros((0, 5)), real)
    assert math.isnan(e["precision"]) and e["recall"] == 0.0 and e["f1"] == 0.0
    assert math.isnan(M.matched_f1(np.zeros((0, 5)), np.zeros((0, 5)))["f1"])


def test_f1_wrapped_doppler():
    real = np.array([[0.0, 0, 0, 5.0, 0]])
    syn = np.array([[0.0, 0, 0, -5.0, 0]])  # 10 m/s apart, 0.39 m/s apart on a 10.39 m/s circle
    assert M.matched_f1(syn, real)["matches"] == 0
    assert M.matched_f1(syn, real, doppler_span_mps=10.39)["matches"] == 1


@settings(max_examples=100, deadline=None)
@given(small_points(5, 0.7, 5), small_points(5, 0.7, 5))
def test_f1_matches_brute_force_maximum(syn, real):
    gates = (1.0, 1.0, 1.0)  # comparable to the spread: typically 1-4 admissible matches, many borderline pairs
    expected = brute_max_matches(syn, real, gates) if len(syn) and len(real) else 0
    assert M.matched_f1(syn, real, *gates)["matches"] == expected


@pytest.mark.parametrize("seed", range(6))
def test_f1_matches_a_dense_assignment_on_frame_sized_sets(seed):
    """Sets of a real frame's size with many competing admissible pairs (a wrapped Doppler gate
    too): the match count is the dense Hungarian assignment's (admissible pairs cost 0, the others
    1), too large for enumeration."""
    rng = np.random.default_rng(seed)
    n, m = rng.integers(150, 400, size=2)
    syn, real = (np.column_stack([rng.uniform(0, 12, (k, 3)), rng.uniform(-5.2, 5.2, k), rng.uniform(0, 30, k)])
                 for k in (n, m))
    span = 10.39 if seed % 2 else 0.0
    ok = ((cdist(syn[:, :3], real[:, :3]) <= 1.0) & (np.abs(syn[:, None, 4] - real[None, :, 4]) <= 8.0)
          & (np.abs(M.doppler_difference(syn[:, None, 3], real[None, :, 3], span)) <= 2.5))
    r, c = linear_sum_assignment(np.where(ok, 0.0, 1.0))
    expected = int(ok[r, c].sum())
    assert 20 < expected < min(n, m)  # a real contest for the pairs, not all or nothing
    got = M.matched_f1(syn, real, doppler_span_mps=span)
    assert got["matches"] == expected
    assert got["precision"] == pytest.approx(expected / n) and got["recall"] == pytest.approx(expected / m)


# ---------------------------------------------------------------- distributions, region, physics

def test_distribution_distances():
    rng = np.random.default_rng(3)
    real = rng.normal(0, 1, (300, 5))
    shifted = real + np.array([1.0, 0, 0, 0, -2.0])
    d = M.distribution_distances(shifted, real)
    assert set(d) == set(M.SPHERICAL_COLUMNS)
    assert d["range_m"] == pytest.approx(1.0) and d["rss"] == pytest.approx(2.0)
    assert d["azimuth_rad"] == pytest.approx(0.0, abs=1e-12)
    assert all(math.isnan(v) for v in M.distribution_distances(np.zeros((0, 5)), real).values())


def test_circular_wasserstein_on_a_wrapped_doppler():
    """On a circle: point masses delta apart score min(delta, period - delta); samples either side
    of the wrap are near; rotating both changes nothing; the weighted-median shift is the best of
    all shifts (brute force over the CDF differences, where the piecewise-linear minimum lies)."""
    period = 10.3936
    for a, delta in ((1.0, 0.5), (4.9, 0.7), (-5.0, 9.0)):
        got = M.circular_wasserstein(np.array([a]), np.array([a + delta]), period)
        assert got == pytest.approx(min(delta, period - delta))
    rng = np.random.default_rng(0)
    real = rng.uniform(period / 2 - 0.3, period / 2, 500)                  # just below +span/2
    syn = rng.uniform(-period / 2, -period / 2 + 0.3, 400)                  # just above -span/2: wrapped
    assert M.circular_wasserstein(syn, real, period) < 0.35 < 9.5 < wasserstein_distance(syn, real)
    a, b = rng.normal(0, 2, 300), rng.normal(1, 1.5, 200)
    got = M.circular_wasserstein(a, b, period)
    assert M.circular_wasserstein(a + 3.3, b + 3.3, period) == pytest.approx(got)
    wa, wb = np.mod(a, period), np.mod(b, period)
    knots = np.unique(np.concatenate([wa, wb, [0, period]]))
    diff = (np.searchsorted(np.sort(wa), knots[:-1], side="right") / len(wa)
            - np.searchsorted(np.sort(wb), knots[:-1], side="right") / len(wb))
    brute = min(np.sum(np.diff(knots) * np.abs(diff - c)) for c in diff)
    assert got == pytest.approx(brute) and got <= wasserstein_distance(a, b) + 1e-12
    d = M.distribution_distances(np.column_stack([np.ones((400, 3)), syn, np.ones(400)]),
                                 np.column_stack([np.ones((500, 3)), real, np.ones(500)]), doppler_span_mps=period)
    assert d["doppler_mps"] == pytest.approx(M.circular_wasserstein(syn, real, period))


def test_to_spherical():
    s = M.to_spherical(np.array([[0.0, 2.0, 0.0, -1.5, 7.0]]))
    assert s[0] == pytest.approx([2.0, math.pi / 2, 0.0, -1.5, 7.0])


def _camera():
    K = np.array([[100.0, 0, 100], [0, 100.0, 50], [0, 0, 1]])
    T_cam_radar = np.array([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]])
    return K, T_cam_radar, (200, 100)


def test_region_mask():
    K, T, size = _camera()
    pts = np.array([[10.0, 0, 0], [60.0, 0, 0], [10.0, 9, 0], [-10.0, 0, 0], [10.0, 3, 0], [10.0, 0, 4.5],
                    [10.0, 0, -6.0]])
    mask = M.region_mask(pts, fov_az_deg=40.0, fov_el_deg=40.0, max_range_m=50.0, K=K, T_cam_radar=T,
                         image_size_wh=size)
    # in; beyond 50 m; az 42 deg > 20 deg (u = 10, in the image); behind the camera;
    # az 16.7 deg (u = 70) in; el 24 deg > 20 deg (v = 5, in the image); v = 110 below the image
    # although el = -31 deg is also out; the FOV here is narrower than the image except vertically
    assert mask.tolist() == [True, False, False, False, True, False, False]
    wide = M.region_mask(pts, 179.0, 179.0, 100.0, K, T, size)
    # only the image limits the wide-FOV case: [10,9,0] u = 10 in; [60,0,0] in; [10,0,-6] v = 110 out
    assert wide.tolist() == [True, True, True, False, True, True, False]


def test_range_check_with_known_estimator():
    rng = np.random.default_rng(4)
    pts = rng.uniform([5, -5, -1], [40, 5, 2], (100, 3))
    r = np.linalg.norm(pts, axis=1)
    offsets = np.linspace(-2, 2, 100)

    def estimator(az, el):
        est = r + offsets
        est[:10] = np.nan  # no support
        return est

    out = M.range_check(pts, np.ones((5, 3)), estimator)
    assert out["no_support_share"] == pytest.approx(0.1)
    ref = np.abs(offsets[10:])
    assert out["median_abs_dr"] == pytest.approx(np.median(ref))
    assert out["p90_abs_dr"] == pytest.approx(np.percentile(ref, 90))
    tup = M.range_check(pts, np.ones((5, 3)), lambda az, el: (r.copy(), np.arange(100) >= 50))
    assert tup["median_abs_dr"] == pytest.approx(0.0, abs=1e-9) and tup["no_support_share"] == 0.5
    none = M.range_check(pts, np.zeros((0, 3)), estimator)
    assert none["no_support_share"] == 1.0 and math.isnan(none["median_abs_dr"])


def test_doppler_check_static_world_and_wrap():
    rng = np.random.default_rng(5)
    pts = rng.uniform([5, -10, -1], [40, 10, 2], (50, 3))
    ego = np.array([8.0, 0.5, 0.0])
    u = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    true_rr = -(u @ ego)
    static = np.ones(50, bool)
    static[:5] = False
    measured = true_rr.copy()
    measured[:5] += 30.0  # moving objects, excluded by the mask
    out = M.doppler_check(pts, measured, ego, static)
    assert out["median_abs_dv"] == pytest.approx(0.0, abs=1e-9) and out["n_static"] == 45
    span = 10.3936
    wrapped = wrap_doppler(true_rr + 0.2, span)
    w = M.doppler_check(pts, wrapped, ego, static, span_mps=span)
    assert w["median_abs_dv"] == pytest.approx(0.2, abs=1e-9)
    assert math.isnan(M.doppler_check(pts, measured, ego, np.zeros(50, bool))["median_abs_dv"])


def test_rss_loss_and_frame_metrics():
    assert M.rss_loss([0.0, 10.0], [5.0, 10.0], 0.0, 10.0) == pytest.approx(0.125)
    rng = np.random.default_rng(6)
    real = np.column_stack([rng.uniform(0, 30, (40, 3)), rng.normal(0, 3, 40), rng.normal(0, 10, 40)])
    tmap = rng.uniform(0, 1, (8, 12))
    fm = M.frame_metrics(real, real, n_hat=40, target_map=tmap, pred_map=tmap, rss_err=0.01)
    assert set(fm) == set(M.FRAME_METRICS)
    assert fm["kl"] == pytest.approx(0.0, abs=1e-12)
    assert fm["chamfer_m"] == 0.0 and fm["gospa"] == 0.0 and fm["f1"] == 1.0 and fm["count_rel_err"] == 0.0
    assert math.isnan(M.frame_metrics(real[:3], real)["kl"])


# ---------------------------------------------------------------- audit: orientation, gates, units

def test_frame_metrics_orientation_synthetic_is_the_estimate():
    """One real point, three synthetic ones (one 0.5 m from it): by the module's conventions the
    two far synthetic points are 'false' (c^2 / 2 = 2 each), nothing is 'missed', precision =
    1 / 3 (matches / synthetic), recall = 1 (matches / real), and the count error is relative to
    the real count: |3 - 1| / 1 = 2."""
    real = np.array([[0.0, 0, 0, 0, 0]])
    syn = np.array([[0.5, 0, 0, 0, 0], [10.0, 0, 0, 0, 0], [20.0, 0, 0, 0, 0]])
    fm = M.frame_metrics(syn, real)
    assert fm["gospa_missed"] == 0.0 and fm["gospa_false"] == pytest.approx(4.0)
    assert fm["gospa_localisation"] == pytest.approx(0.25)
    assert fm["precision"] == pytest.approx(1 / 3) and fm["recall"] == 1.0
    assert fm["count_rel_err"] == pytest.approx(2.0) and fm["count_sq_rel_err"] == pytest.approx(4.0)
    assert M.frame_metrics(syn, real, n_hat=2)["count_rel_err"] == pytest.approx(1.0)   # n_hat, not len(syn)


def test_frame_metrics_passes_the_doppler_span_to_the_matching():
    real = np.array([[0.0, 0, 0, 5.0, 0]])
    syn = np.array([[0.0, 0, 0, -5.0, 0]])   # 0.39 m/s apart on a 10.39 m/s circle
    assert M.frame_metrics(syn, real)["f1"] == 0.0
    assert M.frame_metrics(syn, real, doppler_span_mps=10.39)["f1"] == 1.0


def test_f1_gates_are_inclusive():
    """EVALUATION.md: a pair counts if distance <= 1.0 m, |d RSS| <= 8 and |d Doppler| <= 2.5 m/s
    (values exact in binary: Astyx RSS comes in 0.5 steps, so a difference of exactly 8 is common)."""
    real = np.array([[0.0, 0, 0, 1.0, 50.0]])
    for syn, want in (([1.0, 0, 0, 1.0, 50.0], 1), ([0.0, 0, 0, 1.0, 58.0], 1), ([0.0, 0, 0, 3.5, 50.0], 1),
                      ([0.0, 0, 0, -1.5, 42.0], 1), ([0.0, 0, 0, 1.0, 58.5], 0), ([0.0, 0, 0, 3.5625, 50.0], 0)):
        assert M.matched_f1(np.array([syn]), real)["matches"] == want, syn


def test_region_mask_half_fields_of_view_and_range_limit():
    """fov_* are TOTAL fields of view: with 40 deg, azimuth 25 deg is out although it projects into
    the image; a point at exactly max_range_m is in ('within 50 m')."""
    from pipeline.geometry import project_to_image

    K, T, size = _camera()
    pts = np.array([[10.0, 10.0 * math.tan(math.radians(25)), 0], [10.0, 10.0 * math.tan(math.radians(15)), 0],
                    [50.0, 0, 0], [50.0 + 1e-6, 0, 0]])
    assert project_to_image(pts, K, T, size)[2].all()
    mask = M.region_mask(pts, fov_az_deg=40.0, fov_el_deg=40.0, max_range_m=50.0, K=K, T_cam_radar=T,
                         image_size_wh=size)
    assert mask.tolist() == [False, True, True, False]


def test_rss_loss_normalises_by_the_span_not_the_maximum():
    # Astyx Mag spans 45..102: a 5-unit error is 5 / 57 of the span
    assert M.rss_loss([45.0, 102.0], [50.0, 102.0], 45.0, 102.0) == pytest.approx(0.5 * (5.0 / 57.0) ** 2)


@pytest.mark.parametrize("gates", [(2.0, 3.0, 0.5), (0.5, 20.0, 6.0)])
def test_f1_gates_other_than_the_defaults(gates):
    """The gates are the caller's (eval.gate_m, gate_rss, gate_doppler), not only the defaults: the
    count is the enumerated maximum under them on sets whose spread is comparable to each gate.
    A distance gate of 1 m is its own square, so only another value tells a metre from a squared metre."""
    rng = np.random.default_rng(7)
    for _ in range(30):
        syn, real = (np.column_stack([rng.uniform(0, 1.5 * gates[0], (k, 3)), rng.uniform(0, 2 * gates[2], k),
                                      rng.uniform(0, 2 * gates[1], k)]) for k in rng.integers(1, 6, size=2))
        assert M.matched_f1(syn, real, *gates)["matches"] == brute_max_matches(syn, real, gates)
