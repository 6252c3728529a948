"""Lidar simulation: a spinning multi-line scanner (front half) cast against the world.

Glass is transparent to the beam (no return; the beam continues to what lies behind), dark paint
returns only part of the time, every return has range noise; reflectance is 0..255 as in VoD.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.world.materials import material_arrays
from pipeline.world.raycast import cast_grid, spherical_windows, surface_normals
from pipeline.world.road import ground_material, world_to_road
from pipeline.world.scene import PLANE, Primitives, Scene

MAX_RANGE_M = 100.0
RANGE_SIGMA_M = 0.02
RANDOM_DROPOUT = 0.01


@dataclass
class LidarScan:
    """points_L (N, 3) float32 in {L}; reflectance (N,) float32 0..255; prim (N,) int primitive hit;
    material (N,) int32."""

    points_L: np.ndarray
    reflectance: np.ndarray
    prim: np.ndarray
    material: np.ndarray


def scan_lidar(scene: Scene, prims: Primitives, T_world_lidar: np.ndarray, el_rad: np.ndarray,
               az_rad: np.ndarray, dirs_L: np.ndarray, rng: np.random.Generator | None) -> LidarScan:
    """One scan. dirs_L (lines, cols, 3) unit rays in {L} at elevations el_rad and azimuths az_rad
    (uniform steps, az decreasing with the column). ``rng`` None = no range noise and no random dropout."""
    props = material_arrays()
    R = T_world_lidar[:3, :3]
    origin = T_world_lidar[:3, 3]
    lines, cols, _ = dirs_L.shape
    dirs_W = (dirs_L.reshape(-1, 3) @ R.T).reshape(lines, cols, 3)
    az_step = float(az_rad[0] - az_rad[1])
    el_step = float(el_rad[0] - el_rad[1]) if lines > 1 else 1.0
    windows = spherical_windows(prims, T_world_lidar, float(az_rad[0]) + az_step / 2, az_step, cols,
                                float(el_rad[0]) + el_step / 2, el_step, lines, MAX_RANGE_M)
    glass = props["transparent"][prims.material] & (prims.kind != PLANE)
    t, pid = cast_grid(origin, dirs_W, prims, windows, skip=glass)
    t, pid = t.reshape(-1), pid.reshape(-1)
    keep = np.flatnonzero(np.isfinite(t) & (t < MAX_RANGE_M))
    t, pid = t[keep], pid[keep]
    d_W = dirs_W.reshape(-1, 3)[keep]
    pts_W = origin + t[:, None] * d_W
    mat = prims.material[pid].astype(np.int32)
    ground = prims.kind[pid] == PLANE
    if ground.any():
        s_m, l_m = world_to_road(scene.layout.kappa_1pm, pts_W[ground, :2])
        mat[ground] = ground_material(scene.layout, s_m, l_m)
    cos_inc = np.abs(np.sum(surface_normals(pts_W, pid, prims) * d_W, axis=1))
    refl = 255.0 * props["lidar_reflectivity"][mat] * (0.35 + 0.65 * cos_inc)
    returns = props["lidar_return_prob"][mat]
    if rng is not None:
        t = t + np.clip(rng.normal(0.0, RANGE_SIGMA_M, len(t)), -3 * RANGE_SIGMA_M, 3 * RANGE_SIGMA_M)
        refl = refl * (1.0 + rng.normal(0.0, 0.08, len(t)))
        ok = rng.random(len(t)) < returns * (1.0 - RANDOM_DROPOUT)
    else:
        ok = returns >= 0.5
    points_L = t[ok, None] * dirs_L.reshape(-1, 3)[keep][ok]
    return LidarScan(points_L.astype(np.float32), np.clip(refl[ok], 0, 255).astype(np.float32), pid[ok], mat[ok])
