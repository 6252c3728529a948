"""The ego vehicle's sensor rig: camera intrinsics, mountings and the lidar scan pattern.

Vehicle frame {V}: origin on the ground under the rear axle, x forward, y left, z up (metres).
Camera {C}: x right, y down, z forward (level, no tilt, so that KITTI labels' y axis is vertical).
Radar {D}: x forward, y left, z up, at the front bumper ~0.5 m high with small mounting errors.
Lidar {L}: x forward, y left, z up, on the roof ~1.9 m high with small mounting errors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LIDAR_PATTERNS = {16: (15.0, -15.0), 64: (2.0, -24.8), 128: (22.5, -22.5)}
"""Vertical field of view (top, bottom elevation, deg) per number of lidar lines (VLP-16, HDL-64, OS1-128)."""


@dataclass(frozen=True)
class Rig:
    """Sensor rig. K (3, 3); image size (W, H); T_vehicle_* (4, 4) mountings; lidar grid angles (rad)."""

    K: np.ndarray
    size_wh: tuple[int, int]
    T_vehicle_cam: np.ndarray
    T_vehicle_radar: np.ndarray
    T_vehicle_lidar: np.ndarray
    lidar_el_rad: np.ndarray
    lidar_az_rad: np.ndarray

    @property
    def T_cam_radar(self) -> np.ndarray:
        """Radar -> camera (4, 4)."""
        return np.linalg.inv(self.T_vehicle_cam) @ self.T_vehicle_radar

    @property
    def T_cam_lidar(self) -> np.ndarray:
        """Lidar -> camera (4, 4)."""
        return np.linalg.inv(self.T_vehicle_cam) @ self.T_vehicle_lidar


def rotation_zyx(yaw_rad: float, pitch_rad: float, roll_rad: float) -> np.ndarray:
    """Rotation (3, 3) = Rz(yaw) @ Ry(pitch) @ Rx(roll)."""
    cz, sz = np.cos(yaw_rad), np.sin(yaw_rad)
    cy, sy = np.cos(pitch_rad), np.sin(pitch_rad)
    cx, sx = np.cos(roll_rad), np.sin(roll_rad)
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    return Rz @ Ry @ Rx


def _transform(R: np.ndarray, t: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


LIDAR_MAX_RAYS = 40000
"""Rays per scan (lines x columns) at most: keeps a scan within the synthetic profile's
``lidar.store_max_points`` so that no reader has to truncate it."""


def make_rig(resolution_wh: tuple[int, int], lidar_lines: int, lidar_cols: int | None = None,
             lidar_fov_deg: float = 180.0) -> Rig:
    """The rig for an image of ``resolution_wh`` and a lidar of 16, 64 or 128 lines (front half).

    ``lidar_cols`` defaults to min(900, LIDAR_MAX_RAYS // lines) columns (0.2 .. 0.56 deg steps).
    """
    if lidar_lines not in LIDAR_PATTERNS:
        raise ValueError(f"lidar_lines must be one of {sorted(LIDAR_PATTERNS)}, got {lidar_lines}")
    if lidar_cols is None:
        lidar_cols = min(900, LIDAR_MAX_RAYS // lidar_lines)
    w, h = resolution_wh
    f = 0.7725 * w
    K = np.array([[f, 0.0, 0.4966 * w], [0.0, f, 0.5139 * h], [0.0, 0.0, 1.0]])
    R_vc = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    top, bottom = LIDAR_PATTERNS[lidar_lines]
    half = np.radians(lidar_fov_deg) / 2
    step = 2 * half / lidar_cols
    return Rig(
        K=K,
        size_wh=(int(w), int(h)),
        T_vehicle_cam=_transform(R_vc, (1.85, 0.02, 1.50)),
        T_vehicle_radar=_transform(rotation_zyx(np.radians(0.8), np.radians(0.5), 0.0), (3.72, -0.08, 0.50)),
        T_vehicle_lidar=_transform(rotation_zyx(np.radians(-1.2), np.radians(0.3), np.radians(0.2)), (1.30, 0.0, 1.90)),
        lidar_el_rad=np.radians(np.linspace(top, bottom, lidar_lines)),
        lidar_az_rad=half - step * (np.arange(lidar_cols) + 0.5),
    )


def lidar_directions(rig: Rig) -> np.ndarray:
    """Unit ray directions (lines, cols, 3) of the lidar grid in {L}."""
    el = rig.lidar_el_rad[:, None]
    az = rig.lidar_az_rad[None, :]
    return np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), axis=-1)


def camera_directions(rig: Rig) -> np.ndarray:
    """Ray directions (H, W, 3) in {C} through pixel centres, scaled so that z = 1 (t = depth)."""
    w, h = rig.size_wh
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    K = rig.K
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
