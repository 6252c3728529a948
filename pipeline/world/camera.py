"""Camera rendering: per-pixel ray casting, procedural textures, shading, sky, fog and sensor noise.

Output images are (H, W, 3) uint8 RGB.
"""

from __future__ import annotations

import numpy as np

from pipeline.world.materials import MATERIALS, material_arrays
from pipeline.world.raycast import camera_windows, cast_grid, surface_geometry
from pipeline.world.road import ground_material, world_to_road
from pipeline.world.scene import CYLINDER, PLANE, Primitives, Scene

MAX_DEPTH_M = 160.0
"""Primitives farther than this are not drawn (fog hides them)."""


def hash01(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random values in [0, 1) for integer lattice points (any shape)."""
    h = (ix.astype(np.int64) * 374761393 + iy.astype(np.int64) * 668265263 + seed * 1442695041) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return h.astype(np.float64) / 4294967296.0


def value_noise(a: np.ndarray, b: np.ndarray, seed: int) -> np.ndarray:
    """Smooth 2-D value noise in [0, 1) at continuous coordinates (lattice spacing 1)."""
    ia, ib = np.floor(a), np.floor(b)
    fa, fb = a - ia, b - ib
    fa, fb = fa * fa * (3 - 2 * fa), fb * fb * (3 - 2 * fb)
    ia, ib = ia.astype(np.int64), ib.astype(np.int64)
    n00, n10 = hash01(ia, ib, seed), hash01(ia + 1, ib, seed)
    n01, n11 = hash01(ia, ib + 1, seed), hash01(ia + 1, ib + 1, seed)
    return (n00 * (1 - fa) + n10 * fa) * (1 - fb) + (n01 * (1 - fa) + n11 * fa) * fb


def texture_factor(kind: str, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Brightness multiplier (N,) of a procedural texture at surface coordinates a, b (m)."""
    if kind == "asphalt":
        return 0.85 + 0.35 * (value_noise(a / 0.12, b / 0.12, 1) - 0.5) + 0.2 * (value_noise(a / 3, b / 3, 2) - 0.5)
    if kind == "tiles":
        line = (np.mod(a, 0.5) < 0.025) | (np.mod(b, 0.5) < 0.025)
        return np.where(line, 0.7, 0.95 + 0.12 * (value_noise(a / 0.2, b / 0.2, 3) - 0.5))
    if kind == "grass":
        return (0.65 + 0.7 * value_noise(a / 0.05, b / 0.05, 4)) * (0.85 + 0.3 * value_noise(a / 2, b / 2, 5))
    if kind == "concrete":
        return 0.9 + 0.2 * value_noise(a / 0.4, b / 0.4, 6) + 0.08 * (value_noise(a / 0.03, b / 0.03, 7) - 0.5)
    if kind == "brick":
        row = np.floor(b / 0.075)
        col = np.floor((a + 0.11 * np.mod(row, 2)) / 0.22)
        mortar = (np.mod(b, 0.075) < 0.012) | (np.mod(a + 0.11 * np.mod(row, 2), 0.22) < 0.012)
        return np.where(mortar, 1.45, 0.8 + 0.35 * hash01(col, row, 8))
    if kind == "glass":
        frame = (np.mod(a, 1.5) < 0.06) | (np.mod(b, 1.3) < 0.06)
        return np.where(frame, 0.35, 1.0)
    if kind == "leaves":
        return 0.55 + 0.9 * value_noise(a / 0.07, b / 0.07, 9) * value_noise(a / 0.3, b / 0.3, 10)
    if kind == "bark":
        return 0.75 + 0.5 * value_noise(a / 0.03, b / 0.4, 11)
    if kind == "cloth":
        return 0.9 + 0.2 * value_noise(a / 0.05, b / 0.05, 12)
    if kind == "brushed":
        return 0.9 + 0.2 * value_noise(a / 0.6, b / 0.02, 13)
    if kind == "rail":
        return 0.85 + 0.25 * np.cos(2 * np.pi * b / 0.1)
    return 0.97 + 0.06 * (value_noise(a / 0.5, b / 0.5, 14) - 0.5)


def sky_colour(dirs_W: np.ndarray, sun_W: np.ndarray) -> np.ndarray:
    """Linear RGB (N, 3) float32 of the sky seen along directions (N, 3)."""
    inv_norm = 1.0 / np.sqrt(np.einsum("ij,ij->i", dirs_W, dirs_W))
    up = np.sqrt(np.clip(dirs_W[:, 2] * inv_norm, 0.0, 1.0))[:, None]
    horizon = np.array([0.78, 0.84, 0.92], np.float32)
    zenith = np.array([0.28, 0.48, 0.85], np.float32)
    glow = np.clip((dirs_W @ sun_W.astype(np.float32)) * inv_norm, 0.0, 1.0)
    for _ in range(6):  # glow ** 64
        glow *= glow
    return (horizon + (zenith - horizon) * up + glow[:, None] * np.array([1.0, 0.95, 0.8], np.float32)).astype(np.float32)


def render_camera(scene: Scene, prims: Primitives, T_world_cam: np.ndarray, K: np.ndarray,
                  dirs_C: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
    """Render one image (H, W, 3) uint8 RGB. dirs_C (H, W, 3) are pixel rays in {C} with z = 1;
    ``rng`` None = no noise."""
    h, w, _ = dirs_C.shape
    R = T_world_cam[:3, :3].astype(np.float32)
    origin = T_world_cam[:3, 3]
    dirs_W = (dirs_C.reshape(-1, 3) @ R.T).reshape(h, w, 3)
    T_cam_world = np.linalg.inv(T_world_cam)
    windows = camera_windows(prims, T_cam_world, K, (w, h), MAX_DEPTH_M)
    t, pid = cast_grid(origin, dirs_W, prims, windows)
    flat_t, flat_p = t.reshape(-1), pid.reshape(-1)
    d = dirs_W.reshape(-1, 3)
    hit = np.flatnonzero(flat_p >= 0)
    colour = sky_colour(d, scene.sun_W)
    if len(hit):
        dist = flat_t[hit, None] * d[hit]
        pts = (origin + dist).astype(np.float32)
        rgb = _shade(scene, prims, pts, flat_p[hit], d[hit])
        fog = (1.0 - np.exp(-np.linalg.norm(dist, axis=1) / 450.0))[:, None]
        colour[hit] = rgb * (1 - fog) + colour[hit] * fog
    return _sensor(colour.reshape(h, w, 3), rng)


def _texture_coords(local: np.ndarray, normals: np.ndarray, kind: np.ndarray,
                    half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Texture coordinates (a, b) in metres: face coordinates for boxes, (arc, z) for cylinders,
    world (x, y) for the ground. ``local`` (N, 3) primitive-local hit points, ``half`` (N, 3)."""
    horizontal = np.abs(normals[:, 2]) > 0.5
    a = np.where(horizontal, local[:, 0], local[:, 0] + local[:, 1])
    b = np.where(horizontal, local[:, 1], local[:, 2] + half[:, 2])
    cyl = kind == CYLINDER
    if cyl.any():
        a[cyl] = np.arctan2(local[cyl, 1], local[cyl, 0]) * half[cyl, 0]
    ground = kind == PLANE
    a[ground] = local[ground, 0]
    b[ground] = local[ground, 1]
    return a, b


def _shade(scene: Scene, prims: Primitives, pts: np.ndarray, pid: np.ndarray,
           dirs: np.ndarray) -> np.ndarray:
    """Linear RGB (N, 3) float32 of hit points (N, 3) on primitives ``pid`` (N,)."""
    props = material_arrays()
    normals, local = surface_geometry(pts, pid, prims)
    kind = prims.kind[pid]
    mat = prims.material[pid].astype(np.int32)
    ground = kind == PLANE
    if ground.any():
        s_m, l_m = world_to_road(scene.layout.kappa_1pm, pts[ground, :2].astype(np.float64))
        mat[ground] = ground_material(scene.layout, s_m, l_m)
    a, b = _texture_coords(local, normals, kind, prims.half[pid])
    base = props["rgb"].astype(np.float32)[mat]
    tinted = props["tinted"][mat]
    base[tinted] *= prims.tint[pid[tinted]].astype(np.float32)
    factor = np.ones(len(pid), np.float32)
    for m in np.unique(mat):
        sel = mat == m
        factor[sel] = texture_factor(MATERIALS[m].texture, a[sel].astype(np.float64), b[sel].astype(np.float64))
    view = -dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    sun = scene.sun_W.astype(np.float32)
    light = 0.32 + 0.12 * normals[:, 2] + 0.75 * np.clip(normals @ sun, 0.0, None)
    rgb = base * (factor * light)[:, None]
    shiny = np.flatnonzero(props["specular"][mat] > 0)
    if len(shiny):
        hv = view[shiny] + sun
        hv /= np.linalg.norm(hv, axis=1, keepdims=True)
        rgb[shiny] += (props["specular"][mat[shiny]] * np.clip(np.sum(normals[shiny] * hv, 1), 0, 1) ** 40)[:, None]
    glass = np.flatnonzero(props["transparent"][mat])
    if len(glass):
        v, n = view[glass], normals[glass]
        cos_v = np.sum(v * n, 1, keepdims=True)
        fresnel = 0.25 + 0.6 * (1 - np.abs(cos_v)) ** 3
        rgb[glass] = rgb[glass] * (1 - fresnel) + 0.8 * sky_colour(2 * cos_v * n - v, sun) * fresnel
    return rgb.astype(np.float32)


def _sensor(colour: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
    """Linear RGB (H, W, 3) -> uint8 with vignetting, gamma, slight blur and (optional) noise."""
    import cv2

    h, w, _ = colour.shape
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - w / 2) / (w / 2)) ** 2 + ((yy - h / 2) / (h / 2)) ** 2
    img = colour * (1.0 - 0.12 * r2).astype(np.float32)[..., None]
    img = np.clip(img, 0.0, 1.0) ** np.float32(1 / 2.2) * np.float32(255.0)
    img = cv2.GaussianBlur(img, (3, 3), 0.6)
    if rng is not None:
        img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(2.0)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
