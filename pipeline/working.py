"""Working resolution: row crop + resize of images, matching intrinsics, and field-of-view masks.

Pixel convention: u right, v down, integer values at pixel centres; pixel k covers [k - 0.5, k + 0.5).
Cropping rows [top, bottom) shifts v by -top. Resizing W x H' to w x h (cv2, centre-aligned like
INTER_AREA / INTER_LINEAR) maps u' = (u + 0.5) sx - 0.5 and v' = (v + 0.5) sy - 0.5 with
sx = w / W and sy = h / H' (H' = bottom - top). The intrinsics follow exactly: fx' = sx fx,
cx' = (cx + 0.5) sx - 0.5, fy' = sy fy, cy' = (cy - top + 0.5) sy - 0.5, skew' = sx skew.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from pipeline.frame import check_shape
from pipeline.geometry import cartesian_to_spherical, project_to_image


def _scales(crop_rows: Sequence[int], full_wh: Sequence[int], working_wh: Sequence[int]) -> tuple[int, float, float]:
    """(top, sx, sy) of the full -> working map; ValueError on an invalid crop or size."""
    top, bottom = (int(r) for r in crop_rows)
    full_w, full_h = (int(s) for s in full_wh)
    work_w, work_h = (int(s) for s in working_wh)
    if not 0 <= top < bottom <= full_h:
        raise ValueError(f"crop_rows {tuple(crop_rows)} must satisfy 0 <= top < bottom <= {full_h}")
    if min(full_w, work_w, work_h) <= 0:
        raise ValueError(f"sizes must be positive: full {tuple(full_wh)}, working {tuple(working_wh)}")
    return top, work_w / full_w, work_h / (bottom - top)


def full_to_working_uv(uv: np.ndarray, crop_rows: Sequence[int], full_wh: Sequence[int],
                       working_wh: Sequence[int]) -> np.ndarray:
    """Map pixels (N, 2) of the full image to (N, 2) float64 pixels of the working image."""
    uv = check_shape("uv", np.asarray(uv, dtype=np.float64), (None, 2))
    top, sx, sy = _scales(crop_rows, full_wh, working_wh)
    return np.stack([(uv[:, 0] + 0.5) * sx - 0.5, (uv[:, 1] - top + 0.5) * sy - 0.5], axis=1)


def _pixel_map(crop_rows: Sequence[int], full_wh: Sequence[int], working_wh: Sequence[int]) -> np.ndarray:
    """(3, 3) homogeneous map of full-image pixels to working-image pixels (module docstring)."""
    top, sx, sy = _scales(crop_rows, full_wh, working_wh)
    return np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, (0.5 - top) * sy - 0.5], [0.0, 0.0, 1.0]])


def working_K(K: np.ndarray, crop_rows: Sequence[int], full_wh: Sequence[int], working_wh: Sequence[int]) -> np.ndarray:
    """Intrinsics (3, 3) float64 of the working image from those of the full image (module docstring)."""
    K = check_shape("K", np.asarray(K, dtype=np.float64), (3, 3))
    return _pixel_map(crop_rows, full_wh, working_wh) @ K


def full_K(K_w: np.ndarray, crop_rows: Sequence[int], full_wh: Sequence[int], working_wh: Sequence[int]) -> np.ndarray:
    """Intrinsics (3, 3) float64 of the full image from those of the working image (the inverse of
    :func:`working_K`), e.g. for a calib file that goes with the dataset's own image."""
    K_w = check_shape("K_w", np.asarray(K_w, dtype=np.float64), (3, 3))
    return np.linalg.solve(_pixel_map(crop_rows, full_wh, working_wh), K_w)


def crop_resize(image: np.ndarray, K: np.ndarray, crop_rows: Sequence[int],
                working_wh: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """Crop rows [top, bottom) of ``image`` (H, W, 3) uint8, resize to ``working_wh`` (w, h).

    Returns the working image (h, w, 3) uint8 (cv2 INTER_AREA when shrinking, INTER_LINEAR when
    enlarging) and its intrinsics K_w (3, 3) float64, exact for the pixel-centre convention.
    """
    image = check_shape("image", np.asarray(image), (None, None, 3))
    if image.dtype != np.uint8:
        raise ValueError(f"crop_resize: image must be uint8, got {image.dtype}")
    full_wh = (image.shape[1], image.shape[0])
    top, sx, sy = _scales(crop_rows, full_wh, working_wh)
    cropped = np.ascontiguousarray(image[top:int(crop_rows[1])])
    interp = cv2.INTER_AREA if sx * sy <= 1.0 else cv2.INTER_LINEAR
    resized = cv2.resize(cropped, (int(working_wh[0]), int(working_wh[1])), interpolation=interp)
    return resized, working_K(K, crop_rows, full_wh, working_wh)


def scale_sigma(sigma_full_px: Sequence[float], crop_rows: Sequence[int], full_wh: Sequence[int],
                working_wh: Sequence[int]) -> tuple[float, float]:
    """Heatmap standard deviations (sx, sy) from full-resolution pixels to working pixels."""
    _, sx, sy = _scales(crop_rows, full_wh, working_wh)
    return float(sigma_full_px[0]) * sx, float(sigma_full_px[1]) * sy


def scale_rc(r_c_full_px: float, crop_rows: Sequence[int], full_wh: Sequence[int],
             working_wh: Sequence[int]) -> tuple[float, float]:
    """Patch half side from full-resolution pixels to working pixels, (r_cu, r_cv).

    The two differ when the working image changes the aspect ratio; ``pipeline.patches`` accepts
    the pair (a rectangular working window holding the square full-resolution window).
    """
    _, sx, sy = _scales(crop_rows, full_wh, working_wh)
    return float(r_c_full_px) * sx, float(r_c_full_px) * sy


def fov_mask(points_D: np.ndarray, fov_az_deg: float, fov_el_deg: float, max_range_m: float) -> np.ndarray:
    """Bool (N,): points (N, 3) in {D} inside the radar's field of view and range.

    Total fields of view, symmetric about the x axis: |azimuth| <= fov_az / 2 and
    |elevation| <= fov_el / 2; 0 < range <= max_range_m.
    """
    rae = cartesian_to_spherical(check_shape("points_D", np.asarray(points_D), (None, 3)))
    return (
        (rae[:, 0] > 0.0) & (rae[:, 0] <= max_range_m)
        & (np.abs(rae[:, 1]) <= np.deg2rad(fov_az_deg) / 2.0)
        & (np.abs(rae[:, 2]) <= np.deg2rad(fov_el_deg) / 2.0)
    )


def common_fov_mask(points_D: np.ndarray, K_w: np.ndarray, T_cam_radar: np.ndarray, working_wh: Sequence[int],
                    fov_az_deg: float, fov_el_deg: float, max_range_m: float) -> np.ndarray:
    """Bool (N,): points (N, 3) in {D} in the radar FOV and range that also project into the
    working image (``project_to_image`` with K_w: depth > 0.1 m, pixel inside the image)."""
    points = check_shape("points_D", np.asarray(points_D), (None, 3))
    _, _, in_image = project_to_image(points, K_w, T_cam_radar, tuple(int(s) for s in working_wh))
    return fov_mask(points, fov_az_deg, fov_el_deg, max_range_m) & in_image
