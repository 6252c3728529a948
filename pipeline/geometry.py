"""Rigid transforms, projections and spherical coordinates.

Frames: radar {D} x forward / y left / z up; camera {C} x right / y down / z forward; lidar {L}
as the dataset defines it. A transform ``T_dst_src`` (4, 4) maps points in src to dst, so
``T_cam_radar @ T_radar_lidar == T_cam_lidar``. Points are (N, 3) arrays in metres, pixels (N, 2)
with u to the right and v down, integer coordinates at pixel centres.
"""

from __future__ import annotations

import numpy as np

from pipeline.frame import check_shape


def invert_transform(T_dst_src: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (4, 4): returns T_src_dst.

    Raises ValueError if the rotation block is not orthonormal (|R^T R - I| > 1e-3) or a mirror
    (determinant -1), or the last row is not [0, 0, 0, 1]: such a matrix is not a rigid transform.
    """
    T = check_shape("T", np.asarray(T_dst_src, dtype=np.float64), (4, 4))
    if not np.all(np.isfinite(T)):
        raise ValueError("transform has non-finite entries")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise ValueError(f"transform last row is {T[3].tolist()}, expected [0, 0, 0, 1]")
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-3:
        raise ValueError("transform rotation block is not orthonormal (not invertible as a rigid transform)")
    if np.linalg.det(R) < 0:
        raise ValueError("transform rotation block has determinant -1: a mirror image, not a rotation")
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def transform_points(T_dst_src: np.ndarray, points_src: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to points (N, 3); returns (N, 3) in the dtype of ``points_src``."""
    points = check_shape("points", np.asarray(points_src), (None, 3))
    T = np.asarray(T_dst_src, dtype=np.float64)
    out = points.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    return out.astype(points.dtype if points.dtype.kind == "f" else np.float64)


def project_to_image(
    points_D: np.ndarray, K: np.ndarray, T_cam_radar: np.ndarray, image_size_wh: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project points in {D} into the image (eq. 4).

    Returns ``uv`` (N, 2) float64 pixel coordinates, ``depth_m`` (N,) camera z, and ``valid`` (N,)
    bool: depth > 0.1 m and the pixel inside [-0.5, W - 0.5) x [-0.5, H - 0.5).
    """
    points = check_shape("points_D", np.asarray(points_D, dtype=np.float64), (None, 3))
    p_cam = transform_points(T_cam_radar, points)
    depth = p_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uvw = p_cam @ np.asarray(K, dtype=np.float64).T
        uv = uvw[:, :2] / uvw[:, 2:3]
    w, h = image_size_wh
    valid = (
        (depth > 0.1)
        & (uv[:, 0] >= -0.5) & (uv[:, 0] < w - 0.5)
        & (uv[:, 1] >= -0.5) & (uv[:, 1] < h - 0.5)
    )
    uv[~np.isfinite(uv)] = -1.0
    return uv, depth, valid


def pixel_rays_D(uv: np.ndarray, K: np.ndarray, T_radar_cam: np.ndarray) -> np.ndarray:
    """Unit ray directions in {D} (N, 3) of pixels (N, 2) (eq. 12); rays start at the camera centre."""
    uv = check_shape("uv", np.asarray(uv, dtype=np.float64), (None, 2))
    homog = np.concatenate([uv, np.ones((uv.shape[0], 1))], axis=1)
    d_cam = homog @ np.linalg.inv(np.asarray(K, dtype=np.float64)).T
    d_D = d_cam @ np.asarray(T_radar_cam, dtype=np.float64)[:3, :3].T
    return d_D / np.linalg.norm(d_D, axis=1, keepdims=True)


def norms_m(points: np.ndarray) -> np.ndarray:
    """|p| (N,) of points (N, 3) float64: the values np.linalg.norm(axis=1) gives (same sum order),
    without its overhead."""
    return norms_xyz_m(points[:, 0], points[:, 1], points[:, 2])


def norms_xyz_m(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """|(x, y, z)| (N,) of coordinates given as three (N,) arrays, metres (``norms_m``'s sum order)."""
    return np.sqrt(x * x + y * y + z * z)


def cartesian_to_spherical(points_D: np.ndarray) -> np.ndarray:
    """(N, 3) xyz in {D} -> (N, 3) [range_m, azimuth_rad, elevation_rad] (eq. 3 inverted).

    azimuth = atan2(y, x) (positive left), elevation = asin(z / r) (positive up); a point at the
    origin maps to (0, 0, 0).
    """
    p = check_shape("points_D", np.asarray(points_D, dtype=np.float64), (None, 3))
    r = norms_m(p)
    az = np.arctan2(p[:, 1], p[:, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        el = np.where(r > 0, np.arcsin(np.clip(p[:, 2] / np.where(r > 0, r, 1.0), -1.0, 1.0)), 0.0)
    return np.stack([r, az, el], axis=1)


def spherical_to_cartesian(rae: np.ndarray) -> np.ndarray:
    """(N, 3) [range_m, azimuth_rad, elevation_rad] -> (N, 3) xyz in {D} (eq. 3)."""
    s = check_shape("rae", np.asarray(rae, dtype=np.float64), (None, 3))
    r, az, el = s[:, 0], s[:, 1], s[:, 2]
    return np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)


def radial_velocity(directions_D: np.ndarray, ego_velocity_D: np.ndarray,
                    object_velocity_D: np.ndarray | None = None) -> np.ndarray:
    """Range rate (m/s, positive receding) of targets along ``directions_D`` (N, 3) (eq. 16).

    v = ((v_O - v_D) . d) / |d|; ``object_velocity_D`` (N, 3) or None for the static world.
    """
    d = check_shape("directions_D", np.asarray(directions_D, dtype=np.float64), (None, 3))
    rel = -np.asarray(ego_velocity_D, dtype=np.float64)[None, :]
    if object_velocity_D is not None:
        rel = rel + check_shape("object_velocity_D", np.asarray(object_velocity_D, np.float64), (d.shape[0], 3))
    norm = norms_m(d)
    norm = np.where(norm > 0, norm, 1.0)
    return np.einsum("ij,ij->i", rel, d) / norm


def wrap_doppler(doppler_mps: np.ndarray, span_mps: float, low_mps: float | None = None) -> np.ndarray:
    """Wrap velocities into an aliasing radar's unambiguous interval [low, low + span).

    ``span_mps`` <= 0 means the radar does not alias: values are returned unchanged. ``low_mps``
    defaults to -span / 2.
    """
    v = np.asarray(doppler_mps, dtype=np.float64)
    if span_mps <= 0:
        return v
    low = -span_mps / 2.0 if low_mps is None else low_mps
    return np.mod(v - low, span_mps) + low
