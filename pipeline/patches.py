"""Image patches around projected radar points (eq. 17) and the per-frame point sampling.

Pixel convention: u right, v down, integer values at pixel centres. A patch of half side r_c
covers the pixel window of ``S = max(1, round(2 r_c))`` pixels whose centre is nearest to the point:
columns x0 .. x0 + S - 1 with x0 = round(u - (S - 1) / 2) (likewise rows). Pixels outside the image
are 0 (constant padding: the window is never shifted to stay inside). The window is then resized to
out_size x out_size (cv2 INTER_AREA when shrinking, INTER_LINEAR when enlarging).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from pipeline.frame import check_shape


def _window_sides(r_c: float | Sequence[float]) -> tuple[int, int]:
    """(S_u, S_v) window sides in pixels from a half side r_c (scalar or (r_cu, r_cv))."""
    r = np.broadcast_to(np.asarray(r_c, dtype=np.float64), (2,))
    if not np.all(np.isfinite(r)) or np.any(r <= 0):
        raise ValueError(f"patch: r_c must be positive, got {r_c}")
    s = np.maximum(1, np.rint(2.0 * r)).astype(int)
    return int(s[0]), int(s[1])


def image_patches(image: np.ndarray, uv: np.ndarray, r_c: float | Sequence[float], out_size: int) -> np.ndarray:
    """Patches (N, out_size, out_size, 3) uint8 around pixels ``uv`` (N, 2) of ``image`` (H, W, 3) uint8.

    r_c: half side of the window in pixels of ``image``; a pair (r_cu, r_cv) gives a rectangular
    window (a square full-resolution window seen at an anisotropic working resolution), still
    resized to a square. The image is padded once (cv2.copyMakeBorder, constant 0) and the windows
    gathered from a sliding-window view; enlargements by powers of two run as one resize of all
    windows, other sizes per patch.
    """
    image = check_shape("image", np.asarray(image), (None, None, 3))
    if image.dtype != np.uint8:
        raise ValueError(f"patch: image must be uint8, got {image.dtype}")
    uv = check_shape("uv", np.asarray(uv, dtype=np.float64), (None, 2))
    if not np.all(np.isfinite(uv)):
        raise ValueError("patch: uv has non-finite coordinates")
    if int(out_size) <= 0:
        raise ValueError(f"patch: out_size must be positive, got {out_size}")
    out_size = int(out_size)
    su, sv = _window_sides(r_c)
    if uv.shape[0] == 0:
        return np.zeros((0, out_size, out_size, 3), dtype=np.uint8)
    h, w = image.shape[:2]
    x0 = np.rint(uv[:, 0] - (su - 1) / 2.0).astype(np.int64)
    y0 = np.rint(uv[:, 1] - (sv - 1) / 2.0).astype(np.int64)
    # Pad enough for every window, far-away points included: clip window starts to [-S, W] (a
    # window starting beyond that is all padding either way).
    x0 = np.clip(x0, -su, w)
    y0 = np.clip(y0, -sv, h)
    padded = cv2.copyMakeBorder(np.ascontiguousarray(image), sv, sv, su, su, cv2.BORDER_CONSTANT, value=0)
    # every window of ``padded`` as a view (H', W', S_v, S_u, 3); indexing it copies N windows
    windows = sliding_window_view(padded, (sv, su, 3))[:, :, 0][y0 + sv, x0 + su]  # (N, S_v, S_u, 3)
    if (su, sv) == (out_size, out_size):
        return windows
    if _power_of_two(out_size // su) and _power_of_two(out_size // sv) and out_size % su == out_size % sv == 0:
        return _enlarge_stacked(windows, out_size)
    interp = cv2.INTER_AREA if su * sv >= out_size * out_size else cv2.INTER_LINEAR
    return np.stack([cv2.resize(win, (out_size, out_size), interpolation=interp) for win in windows])


def _power_of_two(k: int) -> bool:
    return k > 0 and k & (k - 1) == 0


def _enlarge_stacked(windows: np.ndarray, out_size: int) -> np.ndarray:
    """``windows`` (N, S_v, S_u, 3) enlarged by powers of two to out_size x out_size with ONE cv2
    INTER_LINEAR resize of the windows stacked vertically: the same bytes as resizing each alone.

    Each window gets its first and last row repeated above and below it. cv2 (half-pixel centres,
    fixed-point weights from the fractional source position, exact in binary for factors 2^k) then
    samples output row i of a window at the source row (i + 0.5) / f - 0.5 of that window, as it
    would alone, and the repeated rows give what cv2's border clamping gives at the window's edges;
    the output rows that land on the repeats are dropped. (Other factors round those positions
    differently and go through the per-window loop.)
    """
    n, sv, su, _ = windows.shape
    fv = out_size // sv
    stacked = np.concatenate([windows[:, :1], windows, windows[:, -1:]], axis=1).reshape(-1, su, 3)
    big = cv2.resize(stacked, (out_size, stacked.shape[0] * fv), interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray(big.reshape(n, (sv + 2) * fv, out_size, 3)[:, fv:fv + out_size])


def image_patch(image: np.ndarray, center_uv: np.ndarray, r_c: float | Sequence[float], out_size: int) -> np.ndarray:
    """One patch (out_size, out_size, 3) uint8 around ``center_uv`` (2,); see ``image_patches``."""
    center = check_shape("center_uv", np.asarray(center_uv, dtype=np.float64), (2,))
    return image_patches(image, center[None, :], r_c, out_size)[0]


def sample_points(rng: np.random.Generator, n_available: int, n: int) -> np.ndarray:
    """Indices (k,) int64, sorted, of the radar points used as RSS-Net samples of one frame.

    ``n`` distinct indices drawn without replacement from range(n_available) when n_available >= n;
    otherwise all n_available points (k = n_available; no point is repeated to pad the count). The
    caller passes one generator seeded once per run, so frames get different draws.
    """
    if n_available < 0 or n < 0:
        raise ValueError(f"sample_points: counts must be >= 0, got n_available={n_available}, n={n}")
    if n_available <= n:
        return np.arange(n_available, dtype=np.int64)
    return np.sort(rng.choice(n_available, size=n, replace=False)).astype(np.int64)


INPUT_SUMMARIES = ("range_image_occupancy", "range_m", "abs_doppler_mps", "patch_brightness")
"""Per point: share of occupied range-image pixels, the point's range, |Doppler|, the patch's mean
RGB (0..255)."""


def input_summaries(patches: np.ndarray | None, range_images: np.ndarray | None,
                    points: np.ndarray) -> np.ndarray:
    """(N, 4) float64 :data:`INPUT_SUMMARIES` of N points' inputs: patches (N, s, s, 3) RGB 0..255,
    range images (N, h, w) raw (pipeline.models.rssnet: 0..255 occupied), points (N, 4) [x, y, z m,
    doppler m/s]; a column is NaN where its input is None."""
    pts = np.asarray(points, np.float64).reshape(-1, 4)
    out = np.full((len(pts), len(INPUT_SUMMARIES)), np.nan)
    if len(pts) == 0:
        return out
    if range_images is not None:
        r = np.asarray(range_images, np.float32).reshape(len(pts), -1)
        with np.errstate(invalid="ignore"):
            out[:, 0] = ((r >= 0) & (r <= 255)).mean(axis=1)
    out[:, 1] = np.linalg.norm(pts[:, :3], axis=1)
    out[:, 2] = np.abs(pts[:, 3])
    if patches is not None:
        out[:, 3] = np.asarray(patches, np.float64).reshape(len(pts), -1).mean(axis=1)
    return out
