"""Fidelity metrics of a synthesized radar frame against the real one (EVALUATION.md).

Conventions: points are in the radar frame {D} (x forward, y left, z up, metres). A radar point
array (N, 5) has the columns of ``pipeline.frame.RADAR_COLUMNS``: x_m, y_m, z_m, doppler_mps
(range rate, positive receding, wrapped into the radar's span for aliasing radars), rss (dataset
units). A spherical point array (N, 5) has columns range_m, azimuth_rad, elevation_rad,
doppler_mps, rss (see :func:`to_spherical`).

Set metrics (Chamfer, GOSPA, matched F1) treat the **synthetic** points as the estimate and the
**real** points as the truth: "missed" = real points without a synthetic partner, "false" =
synthetic points without a real partner; precision = matches / synthetic, recall = matches / real.
Undefined values (empty sets, zero true count) are NaN, never an exception: the report counts them.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import maximum_bipartite_matching, min_weight_full_bipartite_matching
from scipy.spatial import cKDTree

from pipeline.frame import check_shape
from pipeline.geometry import cartesian_to_spherical, project_to_image, radial_velocity, wrap_doppler

KL_EPS = 1e-12
"""Predicted probabilities are clipped below at this value in :func:`kl_divergence`."""

SPHERICAL_COLUMNS = ("range_m", "azimuth_rad", "elevation_rad", "doppler_mps", "rss")
"""Columns of a spherical radar point array and keys of :func:`distribution_distances`."""

FRAME_METRICS = (
    "kl", "count_rel_err", "count_sq_rel_err", "rss_err", "chamfer_m",
    "gospa", "gospa_localisation", "gospa_missed", "gospa_false",
    "precision", "recall", "f1",
)
"""Keys of the per-frame metric dicts (see :func:`frame_metrics`); ``count_sq_rel_err`` averaged
over frames is L_n."""


def region_mask(points_D: np.ndarray, fov_az_deg: float, fov_el_deg: float, max_range_m: float,
                K: np.ndarray, T_cam_radar: np.ndarray, image_size_wh: tuple[int, int]) -> np.ndarray:
    """(N,) bool: points (N, 3) in {D} inside the evaluated region.

    Inside the radar field of view (|azimuth| <= fov_az / 2, |elevation| <= fov_el / 2, both total
    fields of view in degrees, symmetric about x), 0 < range <= max_range_m, and projecting into
    the image of size (W, H) for intrinsics K (positive camera depth). The lidar's own field of
    view is not modelled: regions without lidar show up as missing range support instead.
    """
    pts = check_shape("points_D", np.asarray(points_D, dtype=np.float64), (None, 3))
    sph = cartesian_to_spherical(pts)
    _, _, in_image = project_to_image(pts, K, T_cam_radar, image_size_wh)
    return (
        in_image & (sph[:, 0] > 0) & (sph[:, 0] <= max_range_m)
        & (np.abs(sph[:, 1]) <= np.deg2rad(fov_az_deg) / 2) & (np.abs(sph[:, 2]) <= np.deg2rad(fov_el_deg) / 2)
    )


def kl_divergence(target: np.ndarray, pred: np.ndarray, eps: float = KL_EPS) -> float:
    """L_KL = sum_x P(x) log(P(x) / P_hat(x)) of two maps (H, W) (KL(target || prediction) >= 0).

    Both maps are normalised to sum 1 first (a no-op for proper distributions; it lets a constant
    or unnormalised baseline map be scored). Pixels with P = 0 contribute 0 (0 log 0 = 0). P_hat is
    clipped below at ``eps`` (1e-12) after normalisation so that a zero prediction under target mass
    gives a large finite value instead of infinity. Returns NaN when the target has no mass (a frame
    with no projected radar point has no defined target). Raises ValueError on negative or
    non-finite entries or mismatched shapes.
    """
    P = check_shape("target", np.asarray(target, dtype=np.float64), (None, None))
    Q = check_shape("pred", np.asarray(pred, dtype=np.float64), P.shape)
    for name, m in (("target", P), ("pred", Q)):
        if not np.all(np.isfinite(m)) or (m.size and m.min() < 0):
            raise ValueError(f"{name}: map must be finite and non-negative")
    p_sum, q_sum = P.sum(), Q.sum()
    if p_sum <= 0:
        return float("nan")
    if q_sum <= 0:
        raise ValueError("pred: map has no mass")
    P = P / p_sum
    Q = np.maximum(Q / q_sum, eps)
    mask = P > 0
    # >= 0 by Gibbs' inequality; a map scored against itself sums to about -1e-11 in float64
    return max(0.0, float(np.sum(P[mask] * (np.log(P[mask]) - np.log(Q[mask])))))


def count_errors(n_hat: float, n: float) -> tuple[float, float]:
    """(|n_hat - n| / n, ((n_hat - n) / n)^2) for one frame; (NaN, NaN) when n == 0 (undefined)."""
    if n <= 0:
        return float("nan"), float("nan")
    rel = (float(n_hat) - float(n)) / float(n)
    return abs(rel), rel * rel


def chamfer_m(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer distance (m) of point sets a (N, 3) and b (M, 3), not squared.

    0.5 * (mean_i min_j |a_i - b_j| + mean_j min_i |a_i - b_j|); NaN if either set is empty.
    """
    a = check_shape("a", np.asarray(a, dtype=np.float64), (None, 3))
    b = check_shape("b", np.asarray(b, dtype=np.float64), (None, 3))
    if len(a) == 0 or len(b) == 0:
        return float("nan")
    d_ab, _ = cKDTree(b).query(a)
    d_ba, _ = cKDTree(a).query(b)
    return float(0.5 * (d_ab.mean() + d_ba.mean()))


DENSE_MATCHING_MAX_CELLS = 16_000_000
"""Largest real x synthetic cost matrix (cells) solved densely (128 MB of float64)."""

DENSE_MATCHING_MIN_DENSITY = 0.01
"""Edge density (edges / cells) above which the dense solver is used (it is faster there)."""


def _min_cost_matching(real_idx: np.ndarray, syn_idx: np.ndarray, weight: np.ndarray,
                       n_real: int, n_syn: int, unmatched_cost: float) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-cost one-to-one matching over the edges (real_idx[k], syn_idx[k]) of cost weight[k],
    each unmatched point costing ``unmatched_cost`` (every weight must be < 2 * unmatched_cost).

    Exact either way: a dense rectangular ``linear_sum_assignment`` (non-edges cost
    2 * unmatched_cost, the price of leaving both points unmatched, and are dropped afterwards)
    when the graph is dense and the matrix fits in :data:`DENSE_MATCHING_MAX_CELLS`; otherwise the
    sparse formulation of :func:`_match_with_dummies`. Returns matched (real, syn) indices.
    """
    cells = n_real * n_syn
    if len(weight) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if cells <= DENSE_MATCHING_MAX_CELLS and len(weight) >= DENSE_MATCHING_MIN_DENSITY * cells:
        cost = np.full((n_real, n_syn), 2.0 * unmatched_cost)
        cost[real_idx, syn_idx] = weight
        is_edge = np.zeros((n_real, n_syn), bool)
        is_edge[real_idx, syn_idx] = True
        from scipy.optimize import linear_sum_assignment  # here: importing scipy.optimize takes 0.4 s

        r, s = linear_sum_assignment(cost)
        keep = is_edge[r, s]
        return r[keep].astype(np.int64), s[keep].astype(np.int64)
    return _match_with_dummies(real_idx, syn_idx, weight, n_real, n_syn, unmatched_cost)


def _match_with_dummies(real_idx: np.ndarray, syn_idx: np.ndarray, weight: np.ndarray,
                        n_real: int, n_syn: int, unmatched_cost: float) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-cost one-to-one matching of real to synthetic points over a sparse set of edges.

    Edges (real_idx[k], syn_idx[k]) cost ``weight[k]``; each unmatched point of either set costs
    ``unmatched_cost``. Solved exactly as a full matching of a square (n_real + n_syn) graph:
    rows = real points + one dummy per synthetic point, columns = synthetic points + one dummy per
    real point; real i -- dummy column i and dummy row j -- synthetic j cost ``unmatched_cost``;
    dummy row j -- dummy column i (cost 0) exists wherever edge (i, j) exists, so every partial
    matching of the real edges extends to a full matching of equal cost. All weights are shifted
    by +1 (a full matching has exactly n_real + n_syn edges, so the argmin is unchanged) because
    the sparse solver treats stored zeros as missing edges. Returns matched (real, syn) indices.
    """
    n = n_real + n_syn
    rows = np.concatenate([real_idx, np.arange(n_real), n_real + np.arange(n_syn), n_real + syn_idx])
    cols = np.concatenate([syn_idx, n_syn + np.arange(n_real), np.arange(n_syn), n_syn + real_idx])
    w = np.concatenate([weight, np.full(n, unmatched_cost), np.zeros(len(weight))]) + 1.0
    graph = sp.csr_matrix((w, (rows, cols)), shape=(n, n))
    row_ind, col_ind = min_weight_full_bipartite_matching(graph)
    keep = (row_ind < n_real) & (col_ind < n_syn)
    return np.asarray(row_ind[keep], np.int64), np.asarray(col_ind[keep], np.int64)


GOSPA_C_M = 2.0
"""GOSPA cut-off c of the report (EVALUATION.md), metres."""
GOSPA_P = 2.0
"""GOSPA order p of the report."""


def gospa(syn_xyz: np.ndarray, real_xyz: np.ndarray, c: float = GOSPA_C_M, p: float = GOSPA_P,
          alpha: float = 2.0) -> dict[str, float]:
    """GOSPA (Rahmathullah, Garcia-Fernandez, Svensson 2017) of synthetic (N, 3) vs real (M, 3) points.

    With alpha = 2 (the only value supported) GOSPA^p = min over partial assignments gamma of
    sum_{(i,j) in gamma} d_ij^p + c^p / 2 * (#unassigned real + #unassigned synthetic), with only
    pairs d < c assignable (a pair at d >= c costs the same as one missed plus one false point).
    Solved exactly by :func:`_min_cost_matching` on the graph of pairs closer than c (found with a
    KD-tree): dense Hungarian when that graph is dense, a sparse full matching otherwise, so
    thousands of points stay cheap (3000 x 3600 points: < 1 s either way on one core).
    Returns ``total`` = GOSPA (m) and its decomposition in the p-th power (m^p), which sums to
    total^p: ``localisation`` (sum of d^p over assigned pairs), ``missed`` (c^p / 2 per real point
    left unassigned), ``false`` (c^p / 2 per synthetic point left unassigned), plus the counts
    ``n_assigned``, ``n_missed``, ``n_false``. Two empty sets give total 0.
    """
    if alpha != 2.0:
        raise ValueError(f"gospa: only alpha = 2 is implemented, got {alpha}")
    if c <= 0 or p < 1:
        raise ValueError(f"gospa: need c > 0 and p >= 1, got c={c}, p={p}")
    syn = check_shape("syn_xyz", np.asarray(syn_xyz, dtype=np.float64), (None, 3))
    real = check_shape("real_xyz", np.asarray(real_xyz, dtype=np.float64), (None, 3))
    half = c ** p / 2.0
    if len(syn) and len(real):
        pairs = cKDTree(real).sparse_distance_matrix(cKDTree(syn), c, output_type="ndarray")
        pairs = pairs[pairs["v"] < c]
        ri, si = _min_cost_matching(pairs["i"], pairs["j"], pairs["v"] ** p, len(real), len(syn), half)
        d_assigned = np.linalg.norm(real[ri] - syn[si], axis=1)
    else:
        d_assigned = np.zeros(0)
    n_assigned = len(d_assigned)
    loc = float(np.sum(d_assigned ** p))
    missed = half * (len(real) - n_assigned)
    false = half * (len(syn) - n_assigned)
    return {
        "total": float((loc + missed + false) ** (1.0 / p)),
        "localisation": loc, "missed": float(missed), "false": float(false),
        "n_assigned": n_assigned, "n_missed": len(real) - n_assigned, "n_false": len(syn) - n_assigned,
    }


def doppler_difference(a_mps: np.ndarray, b_mps: np.ndarray, span_mps: float = 0.0) -> np.ndarray:
    """a - b (m/s); for an aliasing radar (span > 0) the circular difference in [-span/2, span/2)."""
    return wrap_doppler(np.asarray(a_mps, np.float64) - np.asarray(b_mps, np.float64), span_mps)


def matched_f1(syn: np.ndarray, real: np.ndarray, gate_m: float = 1.0, gate_rss: float = 8.0,
               gate_doppler: float = 2.5, doppler_span_mps: float = 0.0) -> dict[str, float]:
    """Precision / recall / F1 of a one-to-one matching of synthetic (N, 5) to real (M, 5) points.

    A pair is admissible only if |dxyz| <= gate_m, |d rss| <= gate_rss and |d doppler| <=
    gate_doppler (the circular difference when ``doppler_span_mps`` > 0). The matching maximises
    the number of admissible pairs (as the Hungarian assignment with cost = distance for admissible
    pairs and a large constant otherwise does, whose tie-break by distance leaves the number
    unchanged): a maximum bipartite matching of the admissible graph (Hopcroft-Karp, scipy's
    ``maximum_bipartite_matching``; until 2026-12-06 a minimum-cost matching, 60 ms a call on
    Astyx frames). precision = matches / N,
    recall = matches / M (NaN for an empty set), F1 = harmonic mean; F1 = 0 when there is no match
    and at least one set is non-empty (e.g. no synthetic point at all), NaN when both are empty.
    """
    syn = check_shape("syn", np.asarray(syn, dtype=np.float64), (None, 5))
    real = check_shape("real", np.asarray(real, dtype=np.float64), (None, 5))
    matches = 0
    if len(syn) and len(real):
        pairs = cKDTree(real[:, :3]).sparse_distance_matrix(cKDTree(syn[:, :3]), gate_m, output_type="ndarray")
        ri, si = pairs["i"], pairs["j"]
        ok = (np.abs(real[ri, 4] - syn[si, 4]) <= gate_rss) & (
            np.abs(doppler_difference(real[ri, 3], syn[si, 3], doppler_span_mps)) <= gate_doppler)
        if ok.any():
            graph = sp.csr_matrix((np.ones(int(ok.sum())), (ri[ok], si[ok])), shape=(len(real), len(syn)))
            matches = int(np.count_nonzero(maximum_bipartite_matching(graph, perm_type="column") >= 0))
    precision = matches / len(syn) if len(syn) else float("nan")
    recall = matches / len(real) if len(real) else float("nan")
    if matches > 0:
        f1 = 2.0 * precision * recall / (precision + recall)
    else:
        f1 = 0.0 if len(syn) or len(real) else float("nan")
    return {"precision": float(precision), "recall": float(recall), "f1": float(f1), "matches": int(matches)}


def to_spherical(points: np.ndarray) -> np.ndarray:
    """Radar points (N, 5) [x, y, z, doppler, rss] -> (N, 5) [range_m, azimuth_rad, elevation_rad,
    doppler_mps, rss] (azimuth positive left, elevation positive up)."""
    pts = check_shape("points", np.asarray(points, dtype=np.float64), (None, 5))
    return np.concatenate([cartesian_to_spherical(pts[:, :3]), pts[:, 3:]], axis=1)


def circular_wasserstein(a: np.ndarray, b: np.ndarray, period: float) -> float:
    """1-D Wasserstein distance between samples ``a`` (N,) and ``b`` (M,) of a circle of length
    ``period`` (e.g. Doppler of a radar that wraps it): min over c of the integral over one period
    of |F_a - F_b - c|, the minimiser a weighted median (Rabin, Delon and Gousseau, 2011)."""
    a = np.mod(np.asarray(a, np.float64), period)
    b = np.mod(np.asarray(b, np.float64), period)
    knots = np.unique(np.concatenate([a, b, [0.0, period]]))
    lengths = np.diff(knots)
    cdf = np.searchsorted(np.sort(a), knots[:-1], side="right") / len(a) - \
        np.searchsorted(np.sort(b), knots[:-1], side="right") / len(b)
    order = np.argsort(cdf)
    cum = np.cumsum(lengths[order])
    c = cdf[order][np.searchsorted(cum, cum[-1] / 2)]
    return float(np.sum(lengths * np.abs(cdf - c)))


def distribution_distances(syn_sph: np.ndarray, real_sph: np.ndarray, doppler_span_mps: float = 0.0) -> dict[str, float]:
    """1-D Wasserstein distance per column of spherical point arrays (N, 5) and (M, 5); Doppler on
    the circle of ``doppler_span_mps`` when the radar wraps it (> 0: :func:`circular_wasserstein`,
    so that values either side of the wrap are near).

    Keys are :data:`SPHERICAL_COLUMNS` (units of the column: m, rad, rad, m/s, RSS units); NaN for
    a column when either set is empty or the column has no finite value.
    """
    from scipy.stats import wasserstein_distance  # here: importing scipy.stats takes 0.5 s

    syn = check_shape("syn_sph", np.asarray(syn_sph, dtype=np.float64), (None, 5))
    real = check_shape("real_sph", np.asarray(real_sph, dtype=np.float64), (None, 5))
    out: dict[str, float] = {}
    for k, name in enumerate(SPHERICAL_COLUMNS):
        s, r = syn[:, k], real[:, k]
        s, r = s[np.isfinite(s)], r[np.isfinite(r)]
        if not (len(s) and len(r)):
            out[name] = float("nan")
        elif name == "doppler_mps" and doppler_span_mps > 0:
            out[name] = circular_wasserstein(s, r, doppler_span_mps)
        else:
            out[name] = float(wasserstein_distance(s, r))
    return out


def range_check(real_points_D: np.ndarray, lidar_D: np.ndarray,
                estimate_range: Callable[[np.ndarray, np.ndarray], object]) -> dict[str, float]:
    """Physics check (a): lidar-based range at each real radar point's angles vs its measured range.

    ``real_points_D`` (N, 3) m; ``lidar_D`` (L, 3) m, the frame's lidar (an empty cloud means no
    point has support; the estimator is not called); ``estimate_range(azimuth_rad (N,),
    elevation_rad (N,))`` returns range_m (N,) with NaN where no lidar supports the direction, or a
    tuple (range_m, supported (N,) bool) -- e.g. the bound ``estimate_range`` of the synthesis
    module's lidar angular index built on this frame's lidar.
    Returns median_abs_dr and p90_abs_dr (m, over supported points; NaN if none), no_support_share,
    n_points, and abs_dr (N,) float64 (NaN where unsupported) so that callers can pool frames.
    """
    pts = check_shape("real_points_D", np.asarray(real_points_D, dtype=np.float64), (None, 3))
    check_shape("lidar_D", np.asarray(lidar_D), (None, 3))
    n = len(pts)
    if n == 0:
        return {"median_abs_dr": float("nan"), "p90_abs_dr": float("nan"),
                "no_support_share": float("nan"), "n_points": 0, "abs_dr": np.zeros(0)}
    sph = cartesian_to_spherical(pts)
    if len(lidar_D) == 0:
        est = np.full(n, np.nan)
    else:
        res = estimate_range(sph[:, 1], sph[:, 2])
        if isinstance(res, tuple):
            est = np.where(np.asarray(res[1], bool), np.asarray(res[0], np.float64), np.nan)
        else:
            est = np.asarray(res, np.float64)
    check_shape("estimate_range result", est, (n,))
    abs_dr = np.abs(est - sph[:, 0])
    ok = np.isfinite(abs_dr)
    return {
        "median_abs_dr": float(np.median(abs_dr[ok])) if ok.any() else float("nan"),
        "p90_abs_dr": float(np.percentile(abs_dr[ok], 90)) if ok.any() else float("nan"),
        "no_support_share": float(1.0 - ok.mean()), "n_points": n, "abs_dr": abs_dr,
    }


def doppler_check(real_points_D: np.ndarray, real_doppler_rangerate: np.ndarray,
                  ego_velocity_D: np.ndarray, static_mask: np.ndarray,
                  span_mps: float = 0.0) -> dict[str, float]:
    """Physics check (b): Doppler of static real points predicted from the ego velocity vs measured.

    ``real_points_D`` (N, 3) m; ``real_doppler_rangerate`` (N,) m/s in the internal convention
    (range rate, positive receding, wrapped when the radar aliases); ``ego_velocity_D`` (3,) m/s;
    ``static_mask`` (N,) bool, points on the static world. The prediction is eq. 16 with v_O = 0;
    for span > 0 the difference is taken circularly (wrapped into [-span/2, span/2)).
    Returns median_abs_dv and p90_abs_dv (m/s; NaN when no static point), n_static and abs_dv
    (n_static,) for pooling over frames.
    """
    pts = check_shape("real_points_D", np.asarray(real_points_D, dtype=np.float64), (None, 3))
    v = check_shape("real_doppler_rangerate", np.asarray(real_doppler_rangerate, np.float64), (len(pts),))
    mask = check_shape("static_mask", np.asarray(static_mask, bool), (len(pts),))
    ego = check_shape("ego_velocity_D", np.asarray(ego_velocity_D, np.float64), (3,))
    pts, v = pts[mask], v[mask]
    ok = np.linalg.norm(pts, axis=1) > 0
    pts, v = pts[ok], v[ok]
    if len(pts) == 0:
        return {"median_abs_dv": float("nan"), "p90_abs_dv": float("nan"), "n_static": 0, "abs_dv": np.zeros(0)}
    abs_dv = np.abs(doppler_difference(radial_velocity(pts, ego), v, span_mps))
    return {"median_abs_dv": float(np.median(abs_dv)), "p90_abs_dv": float(np.percentile(abs_dv, 90)),
            "n_static": int(len(pts)), "abs_dv": abs_dv}


def rss_loss(rss_true: np.ndarray, rss_pred: np.ndarray, rss_min: float, rss_max: float) -> float:
    """L_a (eq. 22) = mean(((a - a_hat) / (a_max - a_min))^2) over points (N,); NaN when N = 0."""
    a = np.asarray(rss_true, np.float64).ravel()
    b = check_shape("rss_pred", np.asarray(rss_pred, np.float64).ravel(), a.shape)
    if rss_max <= rss_min:
        raise ValueError(f"rss_loss: need rss_max > rss_min, got {rss_min}..{rss_max}")
    return float(np.mean(((a - b) / (rss_max - rss_min)) ** 2)) if len(a) else float("nan")


def frame_metrics(syn: np.ndarray, real: np.ndarray, n_hat: float | None = None,
                  target_map: np.ndarray | None = None, pred_map: np.ndarray | None = None,
                  rss_err: float = float("nan"), gate_m: float = 1.0, gate_rss: float = 8.0,
                  gate_doppler: float = 2.5, doppler_span_mps: float = 0.0) -> dict[str, float]:
    """All per-frame metrics of one method (keys :data:`FRAME_METRICS`).

    ``syn`` (N, 5) and ``real`` (M, 5) radar points restricted to the evaluated region; ``n_hat``
    the count the method decided (defaults to N); ``target_map``/``pred_map`` (H, W) for ``kl``
    (NaN when either is None: a method without a map); ``rss_err`` is L_a computed by the caller
    (RSS-Net on the real points), NaN for methods without RSS-Net.
    """
    syn = check_shape("syn", np.asarray(syn, dtype=np.float64), (None, 5))
    real = check_shape("real", np.asarray(real, dtype=np.float64), (None, 5))
    rel, sq = count_errors(len(syn) if n_hat is None else n_hat, len(real))
    kl = kl_divergence(target_map, pred_map) if target_map is not None and pred_map is not None else float("nan")
    g = gospa(syn[:, :3], real[:, :3])
    f = matched_f1(syn, real, gate_m, gate_rss, gate_doppler, doppler_span_mps)
    return {
        "kl": kl, "count_rel_err": rel, "count_sq_rel_err": sq, "rss_err": float(rss_err),
        "chamfer_m": chamfer_m(syn[:, :3], real[:, :3]),
        "gospa": g["total"], "gospa_localisation": g["localisation"],
        "gospa_missed": g["missed"], "gospa_false": g["false"],
        "precision": f["precision"], "recall": f["recall"], "f1": f["f1"],
    }
