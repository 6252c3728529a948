"""The hidden radar model: what the learned simulator has to imitate.

Per frame: scattering centres on object surfaces (scene.Centres) are moved with their actors,
kept if inside the field of view (azimuth +/-32 deg, elevation +/-15 deg, range <= 50 m), facing
the radar and not occluded (glass does not occlude); a random subset is active. Each gets an
aspect-dependent RCS (material base RCS + 10 log10(cos(incidence)^lobe)), a Swerling-like
fluctuation, an RSS with range fall-off and a detection probability that drops weak returns and
returns with near-zero Doppler. Detections share range-Doppler cells: at most ``per_cell``
strongest centres per cell survive, so a faster ego (static world spread over more Doppler
cells) yields more points. Then angular/range/Doppler noise (clipped at ``noise_clip`` sigma),
multipath ghosts (longer path or mirrored in the ground) and clutter are added.

Doppler is the range rate (m/s, negative approaching, VoD's v_r): v_r = (v_centre - v_radar) . u.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.geometry import cartesian_to_spherical, spherical_to_cartesian
from pipeline.world.materials import material_arrays
from pipeline.world.raycast import first_hit_dense
from pipeline.world.road import ground_material, world_to_road
from pipeline.world.scene import PLANE, ActorStates, Primitives, Scene

UNLABELLED = -1
"""object_id / material of ghosts and clutter."""


@dataclass(frozen=True)
class RadarModel:
    """Parameters of the hidden radar (angles in degrees, ranges in m, Doppler in m/s, powers in dB)."""

    fov_az_deg: float = 32.0
    fov_el_deg: float = 15.0
    max_range_m: float = 50.0
    min_range_m: float = 0.8
    select_prob: float = 0.8
    range_sigma_m: float = 0.05
    az_sigma_deg: float = 0.6
    el_sigma_deg: float = 0.9
    doppler_sigma_mps: float = 0.04
    rss_sigma_db: float = 1.5
    noise_clip: float = 3.0
    rss_offset_db: float = 14.0
    ref_range_m: float = 5.0
    threshold_db: float = -15.0
    threshold_soft_db: float = 2.0
    doppler_notch_mps: float = 0.15
    slow_penalty_db: float = 20.0
    slow_doppler_mps: float = 2.0
    range_bin_m: float = 0.2
    doppler_bin_mps: float = 0.12
    per_cell: int = 1
    ghost_prob: float = 0.05
    clutter_rate: float = 6.0
    max_points: int = 800
    rss_min_db: float = -30.0
    rss_max_db: float = 40.0
    noise: bool = True
    """False: no fluctuation, no noise, no ghosts, no clutter, deterministic detection (P > 0.5)."""


@dataclass
class RadarScan:
    """points_D (M, 3) m in {D}; doppler_mps (M,) range rate; rss_db (M,); object_id (M,) int32 and
    material (M,) int32 (-1 for ghosts and clutter); is_static (M,) bool (centre on a static actor)."""

    points_D: np.ndarray
    doppler_mps: np.ndarray
    rss_db: np.ndarray
    object_id: np.ndarray
    material: np.ndarray
    is_static: np.ndarray


def radar_velocity(T_world_vehicle: np.ndarray, v_vehicle_W: np.ndarray, yaw_rate: float,
                   T_vehicle_radar: np.ndarray) -> np.ndarray:
    """Velocity (3,) m/s of the radar over ground, expressed in {D} (rigid body: v + omega x r)."""
    r_W = T_world_vehicle[:3, :3] @ T_vehicle_radar[:3, 3]
    v_W = v_vehicle_W + np.cross([0.0, 0.0, yaw_rate], r_W)
    return (T_world_vehicle[:3, :3] @ T_vehicle_radar[:3, :3]).T @ v_W


def centres_world(scene: Scene, states: ActorStates) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Scattering centres at the actors' current poses: pos (C, 3), normal (C, 3), velocity (C, 3) in
    {W}, and actor index (C,)."""
    c = scene.centres
    actor = scene.prims.actor[c.prim]
    yaw = states.yaw[actor]
    cs, sn = np.cos(yaw), np.sin(yaw)

    def rot(v: np.ndarray) -> np.ndarray:
        return np.stack([cs * v[:, 0] - sn * v[:, 1], sn * v[:, 0] + cs * v[:, 1], v[:, 2]], axis=1)

    pos = states.pos[actor] + rot(c.pos)
    arm = pos - states.pos[actor]
    vel = states.vel[actor] + states.yaw_rate[actor, None] * np.stack([-arm[:, 1], arm[:, 0], np.zeros(len(arm))], 1)
    return pos, rot(c.normal), vel, actor


def simulate_radar(scene: Scene, prims: Primitives, states: ActorStates, T_world_radar: np.ndarray,
                   v_radar_D: np.ndarray, rng: np.random.Generator, model: RadarModel) -> RadarScan:
    """One radar frame of the hidden model (see module docstring)."""
    pos, normal, vel, actor = centres_world(scene, states)
    R_rw = T_world_radar[:3, :3].T
    origin = T_world_radar[:3, 3]
    rel = pos - origin
    p_D = rel @ R_rw.T
    rng_m = np.linalg.norm(p_D, axis=1)
    az = np.arctan2(p_D[:, 1], p_D[:, 0])
    el = np.arcsin(np.clip(p_D[:, 2] / np.maximum(rng_m, 1e-9), -1, 1))
    cos_inc = -np.sum(normal * rel, axis=1) / np.maximum(rng_m, 1e-9)
    cand = np.flatnonzero((rng_m > model.min_range_m) & (rng_m <= model.max_range_m)
                          & (np.abs(az) <= np.radians(model.fov_az_deg)) & (np.abs(el) <= np.radians(model.fov_el_deg))
                          & (cos_inc > 0.02))
    cand = cand[rng.random(len(cand)) < model.select_prob]
    cand = cand[~_occluded(prims, origin, rel[cand], rng_m[cand], model.max_range_m)]
    mat = _centre_material(scene, prims, pos, cand)
    lobe = scene.centres.lobe[cand]
    rcs = scene.centres.rcs_dbsm[cand] + 10 * np.log10(cos_inc[cand] ** lobe + 0.01)
    if model.noise:
        rcs = rcs + np.clip(10 * np.log10(rng.exponential(1.0, len(cand)) + 1e-3), -10.0, 5.0)
    r = rng_m[cand]
    u_W = rel[cand] / r[:, None]
    v_radar_W = T_world_radar[:3, :3] @ v_radar_D
    doppler = np.sum((vel[cand] - v_radar_W) * u_W, axis=1)
    rss = rcs + model.rss_offset_db - 20 * np.log10(r / model.ref_range_m)
    p_det = _detection_prob(rss, doppler, model)
    det = rng.random(len(cand)) < p_det if model.noise else p_det > 0.5
    keep = _cell_winners(r[det], doppler[det], rss[det], model)
    sel = np.flatnonzero(det)[keep]
    idx = cand[sel]
    rae = np.stack([r[sel], az[idx], el[idx]], axis=1)
    scan = RadarScan(np.zeros((0, 3)), doppler[sel], rss[sel], scene.object_id[actor[idx]].astype(np.int32),
                     mat[sel].astype(np.int32), scene.mode[actor[idx]] == 0)
    if model.noise:
        rae, scan = _add_noise(rae, scan, rng, model)
        rae, scan = _add_ghosts_and_clutter(rae, scan, T_world_radar, v_radar_D, rng, model)
    return _finish(rae, scan, model)


def _occluded(prims: Primitives, origin: np.ndarray, rel: np.ndarray, rng_m: np.ndarray,
              max_range_m: float) -> np.ndarray:
    """(N,) True where an opaque primitive lies between the radar and the centre (rays rel (N, 3))."""
    near = np.linalg.norm(prims.centre - origin, axis=1) - np.linalg.norm(prims.half, axis=1) < max_range_m + 1
    opaque = ~material_arrays()["transparent"][prims.material] & (prims.kind != PLANE)
    idx = np.flatnonzero(near & opaque)
    t, _ = first_hit_dense(origin, rel, prims, idx)
    return t < 1.0 - 0.03 / np.maximum(rng_m, 1e-3)


def _centre_material(scene: Scene, prims: Primitives, pos: np.ndarray, cand: np.ndarray) -> np.ndarray:
    """Material id per candidate centre (ground centres take the road-layout material)."""
    prim = scene.centres.prim[cand]
    mat = prims.material[prim].copy()
    ground = prims.kind[prim] == PLANE
    if ground.any():
        s_m, l_m = world_to_road(scene.layout.kappa_1pm, pos[cand][ground, :2])
        mat[ground] = ground_material(scene.layout, s_m, l_m)
    return mat


def _detection_prob(rss_db: np.ndarray, doppler_mps: np.ndarray, model: RadarModel) -> np.ndarray:
    """Detection probability: soft power threshold, raised near zero Doppler (stationary clutter
    filter: only strong slow returns survive), times a narrow notch at zero Doppler."""
    raise_db = model.slow_penalty_db * np.exp(-((doppler_mps / model.slow_doppler_mps) ** 2))
    power = 1.0 / (1.0 + np.exp(-(rss_db - model.threshold_db - raise_db) / model.threshold_soft_db))
    notch = 1.0 - np.exp(-((doppler_mps / model.doppler_notch_mps) ** 2))
    return power * notch


def _cell_winners(r: np.ndarray, doppler: np.ndarray, rss: np.ndarray, model: RadarModel) -> np.ndarray:
    """Indices of the ``per_cell`` strongest returns per (range bin, Doppler bin) cell."""
    if len(r) == 0:
        return np.zeros(0, np.int64)
    rb = np.floor(r / model.range_bin_m).astype(np.int64)
    db = np.floor(doppler / model.doppler_bin_mps).astype(np.int64)
    order = np.lexsort((-rss, db, rb))
    key_r, key_d = rb[order], db[order]
    new = np.ones(len(order), bool)
    new[1:] = (key_r[1:] != key_r[:-1]) | (key_d[1:] != key_d[:-1])
    start = np.maximum.accumulate(np.where(new, np.arange(len(order)), 0))
    rank = np.arange(len(order)) - start
    return np.sort(order[rank < model.per_cell])


def _clipped_normal(rng: np.random.Generator, sigma: float, n: int, clip: float) -> np.ndarray:
    return np.clip(rng.normal(0.0, 1.0, n), -clip, clip) * sigma


def _add_noise(rae: np.ndarray, scan: RadarScan, rng: np.random.Generator,
               model: RadarModel) -> tuple[np.ndarray, RadarScan]:
    """Range, angle, Doppler and RSS noise (Gaussian clipped at ``noise_clip`` sigma)."""
    n, k = len(rae), model.noise_clip
    rae = rae + np.stack([_clipped_normal(rng, model.range_sigma_m, n, k),
                          _clipped_normal(rng, np.radians(model.az_sigma_deg), n, k),
                          _clipped_normal(rng, np.radians(model.el_sigma_deg), n, k)], axis=1)
    scan.doppler_mps = scan.doppler_mps + _clipped_normal(rng, model.doppler_sigma_mps, n, k)
    scan.rss_db = scan.rss_db + rng.normal(0.0, model.rss_sigma_db, n)
    return rae, scan


def _add_ghosts_and_clutter(rae: np.ndarray, scan: RadarScan, T_world_radar: np.ndarray, v_radar_D: np.ndarray,
                            rng: np.random.Generator, model: RadarModel) -> tuple[np.ndarray, RadarScan]:
    """Multipath ghosts of strong returns (longer path, or mirror image below the ground) and clutter."""
    strong = np.flatnonzero((scan.rss_db > 5.0) & (rng.random(len(rae)) < model.ghost_prob))
    mirror = rng.random(len(strong)) < 0.5
    g = rae[strong].copy()
    g[~mirror, 0] += rng.uniform(1.0, 5.0, (~mirror).sum())
    if mirror.any():
        p_W = spherical_to_cartesian(g[mirror]) @ T_world_radar[:3, :3].T + T_world_radar[:3, 3]
        p_W[:, 2] = -p_W[:, 2]
        g[mirror] = cartesian_to_spherical((p_W - T_world_radar[:3, 3]) @ T_world_radar[:3, :3])
    g_rss = scan.rss_db[strong] - rng.uniform(5.0, 12.0, len(strong))
    n_c = rng.poisson(model.clutter_rate)
    c = np.stack([rng.uniform(2.0, model.max_range_m, n_c), np.radians(rng.uniform(-1, 1, n_c) * model.fov_az_deg),
                  np.radians(rng.uniform(-1, 1, n_c) * model.fov_el_deg)], axis=1)
    u = np.stack([np.cos(c[:, 2]) * np.cos(c[:, 1]), np.cos(c[:, 2]) * np.sin(c[:, 1]), np.sin(c[:, 2])], axis=1)
    c_dop = -(u @ v_radar_D) + rng.normal(0.0, 0.5, n_c)
    c_rss = model.threshold_db + rng.uniform(0.0, 8.0, n_c)
    n_extra = len(strong) + n_c
    fill = np.full(n_extra, UNLABELLED, np.int32)
    scan = RadarScan(np.zeros((0, 3)), np.concatenate([scan.doppler_mps, scan.doppler_mps[strong], c_dop]),
                     np.concatenate([scan.rss_db, g_rss, c_rss]), np.concatenate([scan.object_id, fill]),
                     np.concatenate([scan.material, fill]), np.concatenate([scan.is_static, np.zeros(n_extra, bool)]))
    return np.concatenate([rae, g, c]), scan


def _finish(rae: np.ndarray, scan: RadarScan, model: RadarModel) -> RadarScan:
    """Apply the field of view and range limits, clip the RSS, cap the count, sort by range."""
    ok = ((rae[:, 0] > model.min_range_m) & (rae[:, 0] <= model.max_range_m)
          & (np.abs(rae[:, 1]) <= np.radians(model.fov_az_deg)) & (np.abs(rae[:, 2]) <= np.radians(model.fov_el_deg)))
    idx = np.flatnonzero(ok)
    if len(idx) > model.max_points:
        idx = np.sort(idx[np.argsort(-scan.rss_db[idx], kind="stable")[:model.max_points]])
    idx = idx[np.argsort(rae[idx, 0], kind="stable")]
    r, az, el = rae[idx, 0], rae[idx, 1], rae[idx, 2]
    pts = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)
    return RadarScan(pts, scan.doppler_mps[idx], np.clip(scan.rss_db[idx], model.rss_min_db, model.rss_max_db),
                     scan.object_id[idx], scan.material[idx], scan.is_static[idx])
