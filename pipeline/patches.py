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
    gathered with one fancy index; only the resize runs per patch.
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
    rows = (y0 + sv)[:, None] + np.arange(sv)[None, :]  # (N, S_v) rows of ``padded``
    cols = (x0 + su)[:, None] + np.arange(su)[None, :]  # (N, S_u)
    windows = padded[rows[:, :, None], cols[:, None, :]]  # (N, S_v, S_u, 3)
    shrink = su * sv >= out_size * out_size
    interp = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    if (su, sv) == (out_size, out_size):
        return np.ascontiguousarray(windows)
    return np.stack([cv2.resize(win, (out_size, out_size), interpolation=interp) for win in windows])


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
