"""Vectorised ray casting against the world's primitives (upright boxes, vertical cylinders, ground).

All rays of one call start at one origin ``origin_W`` (3,) in {W}; directions need not be unit
length: the returned distance ``t`` is in units of the direction's length (unit directions give
metres; camera rays with z_cam = 1 give depth). A miss is ``inf``.

Sensors whose rays form a regular grid (camera pixels, lidar lines x columns) are cast with
*windows*: each primitive is tested only against the rays of the grid rectangle that can see it,
which keeps the work proportional to the primitives' image area instead of rays x primitives.
``first_hit_dense`` tests every ray against every primitive (used for the radar's occlusion test
and as the brute-force oracle of the windowed caster in tests).
"""

from __future__ import annotations

import numpy as np

from pipeline.world.scene import BOX, CYLINDER, PLANE, Primitives

EPS_T = 1e-4
"""Smallest accepted hit distance (avoids self-hits at the origin)."""

BOX_EDGES = np.array([[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7],
                      [0, 4], [1, 5], [2, 6], [3, 7]])
"""Vertex pairs of the 12 edges of a box whose vertices are numbered by the bits (x, y, z)."""


def ray_box_t(origin_W: np.ndarray, dirs: np.ndarray, centre: np.ndarray, yaw: np.ndarray,
              half: np.ndarray) -> np.ndarray:
    """Entry distances (M, P) of rays (M, 3) into upright boxes (centre (P, 3), yaw (P,), half (P, 3)).

    Slab test in each box's frame; rays starting inside a box do not hit it.
    """
    c, s = np.cos(yaw), np.sin(yaw)
    rel = origin_W[None, :] - centre
    o = (c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2])
    dx, dy = dirs[:, 0:1], dirs[:, 1:2]
    d = (dx * c + dy * s, -dx * s + dy * c, np.broadcast_to(dirs[:, 2:3], (dirs.shape[0], len(yaw))))
    t_near = np.full((dirs.shape[0], len(yaw)), -np.inf, dirs.dtype)
    t_far = np.full_like(t_near, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(3):
            inv = 1.0 / np.where(np.abs(d[k]) < 1e-12, 1e-12, d[k])
            t1 = (-half[:, k] - o[k]) * inv
            t2 = (half[:, k] - o[k]) * inv
            np.maximum(t_near, np.minimum(t1, t2), out=t_near)
            np.minimum(t_far, np.maximum(t1, t2), out=t_far)
    return np.where((t_far >= t_near) & (t_near > EPS_T), t_near, np.inf)


def ray_cylinder_t(origin_W: np.ndarray, dirs: np.ndarray, centre: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Entry distances (M, P) of rays (M, 3) into vertical cylinders (centre (P, 3); half = (r, r, hz))."""
    rel = origin_W[None, :] - centre
    r, hz = half[:, 0], half[:, 2]
    dx, dy, dz = dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3]
    a = dx * dx + dy * dy
    b = 2.0 * (rel[:, 0] * dx + rel[:, 1] * dy)
    cc = rel[:, 0] ** 2 + rel[:, 1] ** 2 - r**2
    disc = b * b - 4.0 * a * cc
    with np.errstate(divide="ignore", invalid="ignore"):
        t_side = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a)
        z_side = rel[:, 2] + t_side * dz
        side_ok = (disc >= 0) & (np.abs(z_side) <= hz) & (t_side > EPS_T)
        t_cap = (np.where(rel[:, 2] > 0, hz, -hz) - rel[:, 2]) / dz
        cx = rel[:, 0] + t_cap * dx
        cy = rel[:, 1] + t_cap * dy
        cap_ok = (cx * cx + cy * cy <= r**2) & (t_cap > EPS_T) & (np.abs(rel[:, 2]) > hz)
    return np.minimum(np.where(side_ok, t_side, np.inf), np.where(cap_ok, t_cap, np.inf))


def ray_plane_t(origin_W: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Distances (M,) to the ground plane z = 0 for rays (M, 3) from above; inf for rays going up."""
    dz = dirs[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -origin_W[2] / dz
    return np.where((dz < 0) & (t > EPS_T), t, np.inf)


def prim_t(origin_W: np.ndarray, dirs: np.ndarray, prims: Primitives, idx: np.ndarray) -> np.ndarray:
    """Entry distances (M, len(idx)) of rays against the primitives ``idx`` of any kind."""
    idx = np.asarray(idx)
    out = np.full((dirs.shape[0], len(idx)), np.inf, dirs.dtype)
    kind = prims.kind[idx]
    for k in (BOX, CYLINDER, PLANE):
        sel = np.flatnonzero(kind == k)
        if len(sel) == 0:
            continue
        j = idx[sel]
        if k == BOX:
            out[:, sel] = ray_box_t(origin_W, dirs, prims.centre[j], prims.yaw[j], prims.half[j])
        elif k == CYLINDER:
            out[:, sel] = ray_cylinder_t(origin_W, dirs, prims.centre[j], prims.half[j])
        else:
            out[:, sel] = ray_plane_t(origin_W, dirs)[:, None]
    return out


def first_hit_dense(origin_W: np.ndarray, dirs: np.ndarray, prims: Primitives, idx: np.ndarray,
                    chunk: int = 1024) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of every ray (M, 3) over primitives ``idx``: distance (M,) and primitive (M,), -1 = miss."""
    idx = np.asarray(idx, np.int64)
    t_best = np.full(dirs.shape[0], np.inf)
    p_best = np.full(dirs.shape[0], -1, np.int64)
    if len(idx) == 0:
        return t_best, p_best
    for start in range(0, dirs.shape[0], chunk):
        t = prim_t(origin_W, dirs[start:start + chunk], prims, idx)
        k = np.argmin(t, axis=1)
        t_min = t[np.arange(len(k)), k]
        t_best[start:start + chunk] = t_min
        p_best[start:start + chunk] = np.where(np.isfinite(t_min), idx[k], -1)
    return t_best, p_best


def box_corners(prims: Primitives) -> np.ndarray:
    """Corners (P, 8, 3) in {W} of the primitives' boxes (cylinders: their bounding boxes)."""
    bits = np.array([[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], np.float64) * 2 - 1
    local = bits[None, :, :] * prims.half[:, None, :]
    c, s = np.cos(prims.yaw)[:, None], np.sin(prims.yaw)[:, None]
    x = c * local[..., 0] - s * local[..., 1]
    y = s * local[..., 0] + c * local[..., 1]
    return np.stack([x, y, local[..., 2]], axis=-1) + prims.centre[:, None, :]


def camera_windows(prims: Primitives, T_cam_world: np.ndarray, K: np.ndarray, size_wh: tuple[int, int],
                   max_depth_m: float, near_m: float = 0.05) -> np.ndarray:
    """Pixel windows (P, 4) int [row0, row1, col0, col1) that can see each primitive (empty: row0 >= row1).

    The box is clipped against the near plane (edges crossing it contribute their crossing points),
    so the window is exact for boxes and conservative for cylinders (bounding box). Planes get none.
    """
    w, h = size_wh
    corners = box_corners(prims) @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    a = corners[:, BOX_EDGES[:, 0]]
    b = corners[:, BOX_EDGES[:, 1]]
    with np.errstate(divide="ignore", invalid="ignore"):
        f = (near_m - a[..., 2]) / (b[..., 2] - a[..., 2])
    crossing = ((a[..., 2] < near_m) != (b[..., 2] < near_m))
    cross_pts = a + np.where(crossing, f, 0.0)[..., None] * (b - a)
    pts = np.concatenate([corners, cross_pts], axis=1)
    ok = np.concatenate([corners[..., 2] >= near_m, crossing], axis=1)
    z = np.where(ok, pts[..., 2], 1.0)
    u = np.where(ok, K[0, 0] * pts[..., 0] / z + K[0, 2], np.nan)
    v = np.where(ok, K[1, 1] * pts[..., 1] / z + K[1, 2], np.nan)
    out = np.zeros((len(prims.kind), 4), np.int64)
    visible = ok.any(axis=1) & (prims.kind != PLANE) & (corners[..., 2].min(axis=1) < max_depth_m)
    if visible.any():
        with np.errstate(invalid="ignore"):
            umin, umax = np.nanmin(u[visible], axis=1), np.nanmax(u[visible], axis=1)
            vmin, vmax = np.nanmin(v[visible], axis=1), np.nanmax(v[visible], axis=1)
        out[visible, 0] = np.clip(np.floor(vmin) - 1, 0, h)
        out[visible, 1] = np.clip(np.floor(vmax) + 2, 0, h)
        out[visible, 2] = np.clip(np.floor(umin) - 1, 0, w)
        out[visible, 3] = np.clip(np.floor(umax) + 2, 0, w)
    return out


def spherical_windows(prims: Primitives, T_world_sensor: np.ndarray, az_left_rad: float, az_step_rad: float,
                      n_cols: int, el_top_rad: float, el_step_rad: float, n_rows: int,
                      max_range_m: float, pad_cells: int = 2) -> np.ndarray:
    """Grid windows (P, 4) [row0, row1, col0, col1) of a spherical ray grid (lidar, radar view).

    Grid: column k looks at azimuth az_left - k * az_step, row i at elevation el_top - i * el_step
    (in the sensor frame). Bounds are computed in the sensor's level frame (its yaw only): exact
    azimuth extremes from the footprint, exact elevation extremes from the nearest and farthest
    footprint points; ``pad_cells`` plus the sensor's tilt cover the difference.
    """
    R = T_world_sensor[:3, :3]
    sensor_yaw = np.arctan2(R[1, 0], R[0, 0])
    tilt = np.arccos(np.clip(R[2, 2], -1.0, 1.0))
    pad = pad_cells + int(np.ceil(tilt / min(az_step_rad, el_step_rad)))
    rel = prims.centre - T_world_sensor[:3, 3]
    c, s = np.cos(sensor_yaw), np.sin(sensor_yaw)
    rx, ry = c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]
    yaw = prims.yaw - sensor_yaw
    az_lo, az_hi, d_min, d_max = _footprint_extent(rx, ry, yaw, prims.half, prims.kind)
    z_top = rel[:, 2] + prims.half[:, 2]
    z_bot = rel[:, 2] - prims.half[:, 2]
    el_hi = np.arctan2(z_top, np.where(z_top > 0, d_min, d_max))
    el_lo = np.arctan2(z_bot, np.where(z_bot < 0, d_min, d_max))
    inside = d_min < 0.3
    el_hi[inside], el_lo[inside] = np.pi / 2, -np.pi / 2
    out = np.zeros((len(prims.kind), 4), np.int64)
    out[:, 0] = np.clip(np.floor((el_top_rad - el_hi) / el_step_rad) - pad, 0, n_rows)
    out[:, 1] = np.clip(np.ceil((el_top_rad - el_lo) / el_step_rad) + 1 + pad, 0, n_rows)
    out[:, 2] = np.clip(np.floor((az_left_rad - az_hi) / az_step_rad) - pad, 0, n_cols)
    out[:, 3] = np.clip(np.ceil((az_left_rad - az_lo) / az_step_rad) + 1 + pad, 0, n_cols)
    far = (d_min > max_range_m) | (prims.kind == PLANE)
    full = inside & ~far
    out[full] = [0, n_rows, 0, n_cols]
    empty = far | (az_lo > az_left_rad + pad * az_step_rad) | (az_hi < az_left_rad - n_cols * az_step_rad - pad * az_step_rad)
    out[empty & ~full] = 0
    return out


def _footprint_extent(rx: np.ndarray, ry: np.ndarray, yaw: np.ndarray, half: np.ndarray,
                      kind: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Azimuth interval (lo, hi, rad, continuous around the centre's azimuth) and nearest / farthest
    horizontal distance of each footprint (box rectangle or cylinder disc) seen from the origin."""
    az_c = np.arctan2(ry, rx)
    dist_c = np.hypot(rx, ry)
    # box: corners relative to the origin
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    sx = np.array([1, 1, -1, -1])[None, :] * half[:, 0:1]
    sy = np.array([1, -1, 1, -1])[None, :] * half[:, 1:2]
    cx = rx[:, None] + c * sx - s * sy
    cy = ry[:, None] + s * sx + c * sy
    daz = np.angle(np.exp(1j * (np.arctan2(cy, cx) - az_c[:, None])))
    box_lo, box_hi = az_c + daz.min(axis=1), az_c + daz.max(axis=1)
    # nearest point of the rectangle: origin in box coordinates, clamped to the rectangle
    ox, oy = -(c[:, 0] * rx + s[:, 0] * ry), -(-s[:, 0] * rx + c[:, 0] * ry)
    qx = np.clip(ox, -half[:, 0], half[:, 0])
    qy = np.clip(oy, -half[:, 1], half[:, 1])
    box_dmin = np.hypot(ox - qx, oy - qy)
    box_dmax = np.hypot(cx, cy).max(axis=1)
    r = half[:, 0]
    with np.errstate(invalid="ignore"):
        spread = np.arcsin(np.clip(r / np.maximum(dist_c, 1e-9), 0.0, 1.0))
    is_box = kind == BOX
    lo = np.where(is_box, box_lo, az_c - spread)
    hi = np.where(is_box, box_hi, az_c + spread)
    d_min = np.where(is_box, box_dmin, np.maximum(dist_c - r, 0.0))
    d_max = np.where(is_box, box_dmax, dist_c + r)
    return lo, hi, d_min, d_max


def cast_grid(origin_W: np.ndarray, dirs_W: np.ndarray, prims: Primitives, windows: np.ndarray,
              skip: np.ndarray | None = None, ground: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of a grid of rays (H, W, 3) using per-primitive windows (P, 4).

    ``skip`` (P,) bool excludes primitives (e.g. glass for the lidar). Returns distance (H, W)
    (inf = miss) and primitive index (H, W) int32 (-1 = miss; the ground plane has its own index).
    """
    h, w, _ = dirs_W.shape
    t_buf = np.full((h, w), np.inf, dirs_W.dtype)
    p_buf = np.full((h, w), -1, np.int32)
    if ground:
        plane = np.flatnonzero(prims.kind == PLANE)
        if len(plane):
            t_buf[:] = ray_plane_t(origin_W, dirs_W.reshape(-1, 3)).reshape(h, w)
            p_buf[np.isfinite(t_buf)] = plane[0]
    todo = (windows[:, 1] > windows[:, 0]) & (windows[:, 3] > windows[:, 2])
    if skip is not None:
        todo &= ~skip
    for i in np.flatnonzero(todo):
        r0, r1, c0, c1 = windows[i]
        sub = dirs_W[r0:r1, c0:c1].reshape(-1, 3)
        if prims.kind[i] == BOX:
            t = ray_box_t(origin_W, sub, prims.centre[i:i + 1], prims.yaw[i:i + 1], prims.half[i:i + 1])
        else:
            t = ray_cylinder_t(origin_W, sub, prims.centre[i:i + 1], prims.half[i:i + 1])
        t = t.reshape(r1 - r0, c1 - c0)
        tv = t_buf[r0:r1, c0:c1]
        closer = t < tv
        tv[closer] = t[closer]
        p_buf[r0:r1, c0:c1][closer] = i
    return t_buf, p_buf


def surface_normals(points_W: np.ndarray, prim_idx: np.ndarray, prims: Primitives) -> np.ndarray:
    """Outward unit normals (N, 3) at hit points (N, 3) on primitives ``prim_idx`` (N,)."""
    return surface_geometry(points_W, prim_idx, prims)[0]


def surface_geometry(points_W: np.ndarray, prim_idx: np.ndarray,
                     prims: Primitives) -> tuple[np.ndarray, np.ndarray]:
    """Outward unit normals (N, 3) in {W} and primitive-local coordinates (N, 3) of hit points.

    Local coordinates are relative to the primitive centre, rotated by -yaw; the ground's normal is
    +z and its local coordinates are the world coordinates.
    """
    dtype = points_W.dtype
    rel = points_W - prims.centre[prim_idx].astype(dtype)
    yaw = prims.yaw[prim_idx].astype(dtype)
    half = prims.half[prim_idx].astype(dtype)
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], axis=1)
    kind = prims.kind[prim_idx]
    n_local = np.zeros_like(local)
    ratio = np.abs(local) / np.maximum(half, 1e-9)
    axis = np.argmax(ratio, axis=1)
    rows = np.arange(len(axis))
    n_local[rows, axis] = np.sign(local[rows, axis])
    cyl = kind == CYLINDER
    if cyl.any():
        radial = local[cyl, :2] / np.maximum(np.linalg.norm(local[cyl, :2], axis=1, keepdims=True), 1e-9)
        on_cap = np.abs(local[cyl, 2]) > half[cyl, 2] - 1e-3
        n_local[cyl, :2] = np.where(on_cap[:, None], 0.0, radial)
        n_local[cyl, 2] = np.where(on_cap, np.sign(local[cyl, 2]), 0.0)
    normal = np.stack([c * n_local[:, 0] - s * n_local[:, 1], s * n_local[:, 0] + c * n_local[:, 1],
                       n_local[:, 2]], axis=1)
    plane = kind == PLANE
    normal[plane] = (0.0, 0.0, 1.0)
    local[plane] = points_W[plane]
    return normal, local
