"""Ground-truth heatmap of projected radar points (METHOD.md, eqs. 5-7) and an estimate of Sigma.

The target is the normalised Gaussian mixture p(x) = (1/Z) sum_i N(x; p_i, Sigma) evaluated at the
centre of every pixel, with sum_x p(x) = 1. Pixel (u, v): u to the right, v down, integer values at
pixel centres (the convention of ``pipeline.frame``). Sigma is diagonal with standard deviations
``sigma_px = (sx, sy)`` in pixels of the image the points are expressed in.

For a diagonal Sigma every component factorises, N_i(x, y) ~ gx_i(x) gy_i(y), so the whole map is
one matrix product ``Gy^T (H, N) @ Gx (N, W)``: exact at every pixel (sub-pixel positions kept, no
binning), O(N (H + W)) exponentials and one GEMM instead of N * H * W exponentials.

With many points the GEMM itself (H N W) dominates. A 1-D factor exp(-(x - c)^2 / 2 s^2), as a
function of the centre c, is entire, so its Chebyshev interpolant through n + 1 nodes t_k,
sum_k l_k(c) exp(-(x - t_k)^2 / 2 s^2), is uniformly accurate to a bound eps_n known a priori
(Trefethen, Approximation Theory and Approximation Practice, Thm 8.2). When every centre lies in
the image, both factors are interpolated and the map is the rank-(n+1) product
``Gy^T (H, ny+1) @ (Ly^T Lx / Z) @ Gx (nx+1, W)`` in float64: H W n work with n ~ 85 instead of
N = 1000. Each pixel's error (interpolation and rounding) is bounded; rows where the bound is not
below 1e-7 of every pixel's value are recomputed exactly, so the result stays exact per pixel.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from pipeline.frame import FrameRecord, Object3D, check_shape, to_box_frame
from pipeline.geometry import invert_transform, project_to_image

_FACTOR_CHUNK = 128
"""Points per block when computing the 1-D factors (keeps the float64 temporaries in cache)."""

_FLUSH = np.finfo(np.float32).tiny
"""Factors below this are set to 0 before the float32 GEMM: they are below float32's normal range
(1.2e-38) after products, would only add denormals (slow), and cannot change any pixel whose value
float32 can hold to full precision."""

_MAD_TO_STD = 1.4826
"""Scale from the median absolute deviation to the standard deviation of a normal distribution."""


def _check_inputs(uv: np.ndarray, size_wh: Sequence[int],
                  sigma_px: Sequence[float]) -> tuple[np.ndarray, int, int, float, float]:
    uv = check_shape("uv", np.asarray(uv, dtype=np.float64), (None, 2))
    if uv.shape[0] == 0:
        raise ValueError("heatmap: no points (a frame with zero projected radar points has no target)")
    if not np.all(np.isfinite(uv)):
        raise ValueError("heatmap: uv has non-finite coordinates")
    w, h = (int(s) for s in size_wh)
    if w <= 0 or h <= 0:
        raise ValueError(f"heatmap: size_wh must be positive, got {tuple(size_wh)}")
    sx, sy = (float(s) for s in sigma_px)
    if not (np.isfinite(sx) and np.isfinite(sy) and sx > 0 and sy > 0):
        raise ValueError(f"heatmap: sigma_px must be positive and finite, got {tuple(sigma_px)}")
    return uv, w, h, sx, sy


def _gauss_factors_1d(centres: np.ndarray, n_pixels: int, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """1-D Gaussian factors at the pixel centres 0 .. n_pixels - 1, each scaled to its in-image peak.

    centres: (N,) float64 pixel coordinates. Returns ``g`` (N, n_pixels) float32 with
    g[i, x] = exp(-0.5 ((x - c_i) / sigma)^2 - log_peak_i) (max 1 per row), values below float32's
    normal range set to 0, and ``log_peak`` (N,) float64, the largest in-image exponent of each row
    (at the pixel nearest to c_i). The exponent e is formed in float64 and the exponential taken in
    float32 as exp(e32) * (1 + (e - e32)), so g is accurate to a few float32 ulps (~3e-7 relative)
    even far down the tails, where a plain float32 exponent would lose |e| * 6e-8.
    """
    nearest = np.clip(np.rint(centres), 0, n_pixels - 1)
    log_peak = -0.5 * ((nearest - centres) / sigma) ** 2
    pixels = np.arange(n_pixels, dtype=np.float64)
    g = np.empty((centres.shape[0], n_pixels), dtype=np.float32)
    expo = np.empty((_FACTOR_CHUNK, n_pixels), dtype=np.float64)
    corr = np.empty((_FACTOR_CHUNK, n_pixels), dtype=np.float32)
    for start in range(0, centres.shape[0], _FACTOR_CHUNK):
        c = centres[start:start + _FACTOR_CHUNK]
        e, k, out = expo[:c.shape[0]], corr[:c.shape[0]], g[start:start + c.shape[0]]
        np.subtract.outer(c, pixels, out=e)
        e *= 1.0 / sigma
        np.square(e, out=e)
        e *= -0.5
        e -= log_peak[start:start + c.shape[0], None]  # exponent, <= 0
        out[...] = e  # e32
        e -= out  # rounding error of e32
        k[...] = e
        k += 1.0
        np.exp(out, out=out)
        out *= k
    g[g < _FLUSH] = 0.0
    return g, log_peak


def gaussian_heatmap(uv: np.ndarray, size_wh: Sequence[int], sigma_px: Sequence[float]) -> np.ndarray:
    """Normalised Gaussian-mixture heatmap of projected points (eqs. 5-7, diagonal Sigma).

    uv: (N, 2) float pixel coordinates (u right, v down, integer values at pixel centres) at the
        resolution of the map; points may lie outside the image (their in-image tails count).
    size_wh: (W, H) of the map, pixels.
    sigma_px: (sx, sy) standard deviations of Sigma, pixels at this resolution.
    Returns (H, W) float32, non-negative, summing to 1 (to float32 rounding).

    Exact separable evaluation: each point's 1-D factors are scaled by their in-image maximum and
    the point weighted by exp(its in-image log-peak - the best point's), so points far outside the
    image neither underflow the whole map nor dominate it wrongly; Z is the float64 sum
    sum_i (sum_x gx_i)(sum_y gy_i), folded into the factors before one float32 GEMM. With many
    points inside the image the certified interpolated product replaces the GEMM. Per-pixel
    relative error vs the float64 per-point sum (``naive_heatmap``) is ~1e-6 wherever the value is
    above ~N * 1e-38 (smaller factors are flushed to 0; tests check < 1e-5 above 1e-28). Memory:
    N * (W + H) float32 factors.
    Raises ValueError for zero points (no defined target: the caller skips the frame), non-finite
    input, or non-positive size / sigma.
    """
    uv, w, h, sx, sy = _check_inputs(uv, size_wh, sigma_px)
    plan_x = _chebyshev_plan(uv[:, 0], w, sx)
    plan_y = _chebyshev_plan(uv[:, 1], h, sy) if plan_x is not None else None
    if plan_y is not None:
        result = _interpolated_heatmap(uv, w, h, sx, sy, plan_x, plan_y)
        if result is not None:
            return result
    gx, peak_x = _gauss_factors_1d(uv[:, 0], w, sx)  # (N, W) float32, max 1 per point
    gy, peak_y = _gauss_factors_1d(uv[:, 1], h, sy)  # (N, H) float32, max 1 per point
    log_weight = peak_x + peak_y
    weight = np.exp(log_weight - log_weight.max())  # (N,), best point 1
    z = float(np.sum(weight * gx.sum(axis=1, dtype=np.float64) * gy.sum(axis=1, dtype=np.float64)))
    gy *= (weight / z).astype(np.float32)[:, None]  # normalisation folded into the row factors
    gy[gy < _FLUSH] = 0.0
    return gy.T @ gx  # (H, N) @ (N, W) -> (H, W) float32


_CERTIFY_REL = 1e-7
"""Largest interpolation error, relative to the pixel's value, accepted without recomputing."""

_EPS_TARGET = 1e-13
"""Uniform interpolation error aimed for (relative to a factor's peak of 1)."""


def chebyshev_error_bound(degree: int, half_width_over_sigma: float) -> float:
    """A priori bound on max |f - p_n| for f(t) = exp(-(d - h t)^2 / 2 sigma^2) on t in [-1, 1]
    (any d), p_n its interpolant in the degree + 1 Chebyshev points of the second kind.

    f is entire and on the Bernstein ellipse E_rho |f| <= exp(h^2 b^2 / 2 sigma^2), b the ellipse's
    semi-minor axis (rho - 1/rho) / 2, so ||f - p_n|| <= 4 M rho^-n / (rho - 1) for every rho > 1
    (Trefethen, ATAP, Thm 8.2); this returns the smallest over a fine grid of rho.
    """
    rho = np.geomspace(1.0005, 100.0, 4000)
    b = 0.5 * (rho - 1.0 / rho)
    log_bound = np.log(4.0) + 0.5 * (half_width_over_sigma * b) ** 2 - degree * np.log(rho) - np.log(rho - 1.0)
    return float(np.exp(log_bound.min()))


@functools.lru_cache(maxsize=1024)
def _degree_for(ratio_sixteenths: int) -> tuple[int, float] | None:
    """Smallest degree (step 4, <= 400) whose bound meets _EPS_TARGET for half-width / sigma
    <= ratio_sixteenths / 16, with that bound; None if none does."""
    ratio = ratio_sixteenths / 16.0
    for degree in range(8, 401, 4):
        bound = chebyshev_error_bound(degree, ratio)
        if bound <= _EPS_TARGET:
            return degree, bound
    return None


@dataclass(frozen=True)
class _ChebyshevPlan:
    nodes: np.ndarray  # (n+1,) pixel coordinates of the Chebyshev points
    basis: np.ndarray  # (N, n+1) Lagrange basis at each centre
    at_nodes: np.ndarray  # (n+1, W) exp(-(x - t_k)^2 / 2 sx^2)
    eps: float  # uniform error bound of the interpolant (a factor's peak is 1)


def _chebyshev_plan(centres: np.ndarray, n_pixels: int, sigma: float) -> _ChebyshevPlan | None:
    """The interpolant of the x factors, or None for the exact product: when it would not be
    clearly cheaper (degree above N / 3), or when a centre lies outside the image (its factor is
    rescaled by its in-image peak, which the uniform bound does not cover)."""
    lo, hi = float(centres.min()), float(centres.max())
    if lo < -0.5 or hi > n_pixels - 0.5 or len(centres) < 24:
        return None
    half = max(0.5 * (hi - lo), 0.25)
    found = _degree_for(int(np.ceil(half / sigma * 16.0)))  # ratio rounded up: the bound only grows
    if found is None or found[0] > len(centres) // 3:
        return None
    degree, eps = found
    j = np.arange(degree + 1)
    nodes = 0.5 * (lo + hi) + half * np.cos(np.pi * j / degree)
    bary = (-1.0) ** j
    bary[[0, -1]] *= 0.5
    diff = centres[:, None] - nodes[None, :]
    exact = diff == 0.0
    diff[exact] = 1.0
    basis = bary / diff  # barycentric formula (second kind), numerically stable
    basis /= basis.sum(axis=1, keepdims=True)
    on_node = exact.any(axis=1)
    basis[on_node] = exact[on_node]  # a centre on a node: that basis function is 1, the rest 0
    pixels = np.arange(n_pixels, dtype=np.float64)
    at_nodes = np.exp(-0.5 * ((pixels[None, :] - nodes[:, None]) / sigma) ** 2)
    return _ChebyshevPlan(nodes, basis, at_nodes, eps)


def _interpolated_heatmap(uv: np.ndarray, w: int, h: int, sx: float, sy: float, px: _ChebyshevPlan,
                          py: _ChebyshevPlan) -> np.ndarray | None:
    """``gaussian_heatmap`` with both 1-D factors interpolated (every centre inside the image, so
    every point has the same weight), in float64: Gy^T (Ly^T Lx / Z) Gx. Each pixel's error is
    bounded a priori; rows where the bound is not below _CERTIFY_REL of every pixel are
    recomputed exactly. Returns (H, W) float32, or None when more than a quarter of the rows are
    uncertified (points in a tight cluster, far tails in every row): the exact product is then
    cheaper."""
    n = uv.shape[0]
    sum_x = px.basis @ px.at_nodes.sum(axis=1)  # (N,) sum over columns of each x factor
    sum_y = py.basis @ py.at_nodes.sum(axis=1)
    scale = 1.0 / float(sum_x @ sum_y)  # 1 / Z
    core = (py.basis.T * scale) @ px.basis  # (ny+1, nx+1)
    out = (py.at_nodes.T @ core) @ px.at_nodes  # (H, W)
    # Bound: |Ex Ey - Px Py| <= ex Ey + ey (Ex + ex) for factors E interpolated by P (errors ex,
    # ey), and the float64 products add at most gamma * Lambda_x * sum_i sum_j |Ly_ij| Gy_j(y)
    # (the standard |A||B| GEMM bound with |Px| <= Lambda_x), all times 1 / Z.
    ex, ey = px.eps, py.eps
    sum_rows_y = py.at_nodes.T @ py.basis.sum(axis=0)  # (H,) sum_i Py_i(y)
    sum_cols_x = px.at_nodes.T @ px.basis.sum(axis=0)  # (W,) sum_i Px_i(x)
    abs_rows_y = py.at_nodes.T @ np.abs(py.basis).sum(axis=0)
    gamma = (n + len(px.nodes) + len(py.nodes)) * 1.2e-16
    lebesgue_x = float(np.abs(px.basis).sum(axis=1).max())
    a = scale * (ex * (sum_rows_y + n * ey) + gamma * lebesgue_x * abs_rows_y)  # (H,)
    b = scale * (ey * (sum_cols_x + n * ex) + n * ex * ey)  # (W,)
    suspect = np.flatnonzero(out.min(axis=1) * _CERTIFY_REL < a + b.max())
    bad = suspect[(out[suspect] * _CERTIFY_REL < a[suspect, None] + b[None, :]).any(axis=1)]
    if 4 * bad.size > h:
        return None
    result = out.astype(np.float32)
    if bad.size:
        gy = np.exp(-0.5 * ((bad[None, :] - uv[:, 1:2]) / sy) ** 2)  # (N, rows)
        gx = np.exp(-0.5 * ((np.arange(w)[None, :] - uv[:, 0:1]) / sx) ** 2)  # (N, W)
        result[bad] = (gy.T * scale) @ gx
    return result


def naive_heatmap(uv: np.ndarray, size_wh: Sequence[int], sigma_px: Sequence[float]) -> np.ndarray:
    """Reference (H, W) float64 heatmap: the density of eq. 5 summed point by point over every pixel.

    Same arguments and conventions as ``gaussian_heatmap``; O(N H W) exponentials (tests and
    benchmarks only). Raises ValueError for zero points or when every pixel underflows to 0.
    """
    uv, w, h, sx, sy = _check_inputs(uv, size_wh, sigma_px)
    xs = np.arange(w, dtype=np.float64)
    ys = np.arange(h, dtype=np.float64)
    total = np.zeros((h, w), dtype=np.float64)
    norm = 1.0 / (2.0 * np.pi * sx * sy)
    for u, v in uv:
        dx2 = ((xs - u) / sx) ** 2
        dy2 = ((ys - v) / sy) ** 2
        total += norm * np.exp(-0.5 * (dy2[:, None] + dx2[None, :]))
    z = total.sum()
    if z <= 0:
        raise ValueError("naive heatmap: every pixel underflows (points too far outside the image)")
    return total / z


def estimate_sigma_px(points_uv_per_object: Sequence[np.ndarray], min_points: int = 3) -> tuple[float, float]:
    """Pooled robust spread (sx, sy) of projected radar points around their object's centre, pixels.

    points_uv_per_object: one (n_i, 2) array of pixel coordinates per annotated object.
    Each object's centre is the per-axis median of its points; the deviations of all objects are
    pooled and each axis' standard deviation estimated as 1.4826 * median(|deviation|) (MAD, robust
    to stray points). Objects with fewer than ``min_points`` points carry almost no spread
    information (the median point has deviation 0) and are skipped. Small objects bias the estimate
    somewhat low (the median is fitted to the points); use it as a data-driven starting value.
    Raises ValueError when no object has enough points.
    """
    deviations = []
    for k, pts in enumerate(points_uv_per_object):
        pts = check_shape(f"points_uv_per_object[{k}]", np.asarray(pts, dtype=np.float64), (None, 2))
        if pts.shape[0] >= max(min_points, 2):
            deviations.append(pts - np.median(pts, axis=0))
    if not deviations:
        raise ValueError(f"estimate_sigma_px: no object with at least {min_points} projected points")
    dev = np.concatenate(deviations)
    sx, sy = _MAD_TO_STD * np.median(np.abs(dev), axis=0)
    return float(sx), float(sy)


def points_in_box(points_D: np.ndarray, box: Object3D, grow_m: float = 0.0) -> np.ndarray:
    """Bool (N,): points (N, 3) in {D}, metres, inside the box (its full rotation,
    ``Object3D.rotation``) grown by ``grow_m`` on every side."""
    p = check_shape("points_D", np.asarray(points_D, dtype=np.float64), (None, 3))
    local = to_box_frame(p - np.asarray(box.center_D, dtype=np.float64)[None, :], box.rotation)
    half = 0.5 * np.asarray(box.size_lwh_m, dtype=np.float64) + grow_m
    return np.all(np.abs(local) <= half[None, :], axis=1)


def object_points_uv(frame: FrameRecord, grow_m: float = 0.5) -> list[np.ndarray]:
    """Per labelled object of ``frame``: (n_i, 2) pixels (native image) of its radar points.

    A radar point belongs to an object when it lies inside the object's 3D box grown by ``grow_m``
    metres; only points that project inside the image (``project_to_image``) are kept.
    """
    if not frame.has_radar or frame.radar_D.shape[0] == 0 or not frame.labels:
        return []
    xyz = frame.radar_D[:, :3]
    h, w = frame.image.shape[:2]
    uv, _, valid = project_to_image(xyz, frame.K, invert_transform(frame.T_radar_cam), (w, h))
    return [uv[valid & points_in_box(xyz, obj, grow_m)] for obj in frame.labels]


def sigma_from_frames(frames: Iterable[FrameRecord], grow_m: float = 0.5, min_points: int = 3) -> tuple[float, float]:
    """Estimate Sigma's (sx, sy) in native-image pixels from annotated frames.

    Collects, for every labelled object of every frame, the radar points inside its 3D box grown by
    ``grow_m`` metres, projects them with the frame's K and T_radar_cam, and pools them with
    ``estimate_sigma_px``. The result is in pixels of the frames' own images (full resolution, the
    unit of the config key heatmap.sigma_px); scale it with ``pipeline.working.scale_sigma``.
    Raises ValueError when no object has ``min_points`` projected radar points.
    """
    per_object: list[np.ndarray] = []
    for frame in frames:
        per_object.extend(object_points_uv(frame, grow_m))
    return estimate_sigma_px(per_object, min_points=min_points)


def resize_distribution(prob_hw: np.ndarray, size_wh: Sequence[int]) -> np.ndarray:
    """A per-pixel probability map (h, w) >= 0 at another size (W, H): float32 (H, W) summing to 1
    (all zeros when ``prob_hw`` has no mass). Area-averaged where it shrinks, bilinear where it
    grows (a map predicted at another dataset's working size, train.nets_from). A map already of
    that size is returned as it is, not normalised again (Dis-Net's maps sum to 1)."""
    import cv2

    prob = check_shape("prob_hw", np.asarray(prob_hw, np.float32), (None, None))
    w, h = int(size_wh[0]), int(size_wh[1])
    if prob.shape == (h, w):
        return prob
    shrink = h * w < prob.size
    out = np.maximum(cv2.resize(prob, (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR), 0.0)
    total = float(out.sum(dtype=np.float64))
    return (out / total).astype(np.float32) if total > 0 else np.zeros((h, w), np.float32)
