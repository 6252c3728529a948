"""Ground-truth heatmap of projected radar points (METHOD.md, eqs. 5-7) and an estimate of Sigma.

The target is the normalised Gaussian mixture p(x) = (1/Z) sum_i N(x; p_i, Sigma) evaluated at the
centre of every pixel, with sum_x p(x) = 1. Pixel (u, v): u to the right, v down, integer values at
pixel centres (the convention of ``pipeline.frame``). Sigma is diagonal with standard deviations
``sigma_px = (sx, sy)`` in pixels of the image the points are expressed in.

For a diagonal Sigma every component factorises, N_i(x, y) ~ gx_i(x) gy_i(y), so the whole map is
one matrix product ``Gy^T (H, N) @ Gx (N, W)``: exact at every pixel (sub-pixel positions kept, no
binning), O(N (H + W)) exponentials and one GEMM instead of N * H * W exponentials.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from pipeline.frame import FrameRecord, Object3D, check_shape
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
    sum_i (sum_x gx_i)(sum_y gy_i), folded into the factors before one float32 GEMM. Per-pixel
    relative error vs the float64 per-point sum (``naive_heatmap``) is ~1e-6 wherever the value is
    above ~N * 1e-38 (smaller factors are flushed to 0; tests check < 1e-5 above 1e-28). Memory:
    N * (W + H) float32 factors.
    Raises ValueError for zero points (no defined target: the caller skips the frame), non-finite
    input, or non-positive size / sigma.
    """
    uv, w, h, sx, sy = _check_inputs(uv, size_wh, sigma_px)
    gx, peak_x = _gauss_factors_1d(uv[:, 0], w, sx)  # (N, W) float32, max 1 per point
    gy, peak_y = _gauss_factors_1d(uv[:, 1], h, sy)  # (N, H) float32, max 1 per point
    log_weight = peak_x + peak_y
    weight = np.exp(log_weight - log_weight.max())  # (N,), best point 1
    z = float(np.sum(weight * gx.sum(axis=1, dtype=np.float64) * gy.sum(axis=1, dtype=np.float64)))
    gy *= (weight / z).astype(np.float32)[:, None]  # normalisation folded into the row factors
    gy[gy < _FLUSH] = 0.0
    return gy.T @ gx  # (H, N) @ (N, W) -> (H, W) float32


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
    """Bool (N,): points (N, 3) in {D}, metres, inside the box grown by ``grow_m`` on every side."""
    p = check_shape("points_D", np.asarray(points_D, dtype=np.float64), (None, 3))
    c, s = np.cos(box.yaw_rad), np.sin(box.yaw_rad)
    d = p - np.asarray(box.center_D, dtype=np.float64)[None, :]
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)
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
