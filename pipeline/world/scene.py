"""Scenes of the synthetic world: actors made of primitives, their motion, and the ego trajectory.

World frame {W}: flat ground z = 0, z up, metres (see road.py). An *actor* is one object with one
identity (a car, a pedestrian, a building, the ground); it is made of *primitives*: upright boxes
(yaw about z only) and vertical cylinders, expressed in the actor's local frame (x forward, y
left, z up, origin on the ground under the actor's centre); the ground is one infinite plane. An
actor is static (its local frame is {W}), drives along the road at constant speed and lane offset,
or walks across it. Radar scattering centres are fixed points on primitive surfaces (local frame)
with a normal and a base RCS.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.world.materials import MATERIAL_ID, material_arrays
from pipeline.world.road import RoadLayout, road_to_world

SCENE_TYPES = ("residential", "urban", "highway")
LABELLED_CLASSES = ("Car", "Truck", "Pedestrian", "Cyclist")
"""Classes written to the KITTI label files; other actors (buildings, poles...) are unlabelled."""

BOX, CYLINDER, PLANE = 0, 1, 2
STATIC, ALONG, ACROSS = 0, 1, 2
EDGE_MATERIALS = ("car_paint", "dark_paint", "guard_rail", "concrete", "sign", "metal_pole", "brick")
"""Materials whose vertical box edges act as strong, broad-lobed scatterers (dihedral corners)."""


@dataclass
class Primitives:
    """Primitives in some frame (local at build time, {W} per frame). P primitives.

    actor (P,) int: owning actor index. kind (P,) int: BOX, CYLINDER or PLANE (z = 0).
    centre (P, 3) m: box centre / cylinder axis midpoint. yaw (P,) rad about z.
    half (P, 3) m: box half extents along its local x, y, z; cylinder (radius, radius, half height).
    material (P,) int; tint (P, 3) colour multiplier.
    """

    actor: np.ndarray
    kind: np.ndarray
    centre: np.ndarray
    yaw: np.ndarray
    half: np.ndarray
    material: np.ndarray
    tint: np.ndarray


@dataclass
class Centres:
    """Radar scattering centres (C), in their actor's local frame.

    prim (C,) int: primitive they lie on. pos (C, 3) m, normal (C, 3) unit, rcs_dbsm (C,) base RCS,
    lobe (C,) aspect exponent.
    """

    prim: np.ndarray
    pos: np.ndarray
    normal: np.ndarray
    rcs_dbsm: np.ndarray
    lobe: np.ndarray


@dataclass
class Ego:
    """Ego trajectory: along the road at lateral offset ``l_m``; s(t) from speed v0 + accel * t."""

    s0_m: float
    l_m: float
    speed0_mps: float
    accel_mps2: float


@dataclass
class Scene:
    """One sequence's world. A actors; ``object_id`` (A,) are globally unique ids (meta, labels).

    Per actor: class name, motion ``mode`` (STATIC/ALONG/ACROSS) with road coordinates s0, l0, signed
    speed (m/s) and yaw offset from the road heading (rad); ``size_lwh_m`` (A, 3) label box size;
    ``static_pose`` (A, 3) world (x, y, yaw) of static labelled actors (parked cars).
    """

    scene_type: str
    layout: RoadLayout
    ego: Ego
    sun_W: np.ndarray
    actor_class: list[str]
    object_id: np.ndarray
    mode: np.ndarray
    s0_m: np.ndarray
    l0_m: np.ndarray
    speed_mps: np.ndarray
    yaw_offset_rad: np.ndarray
    size_lwh_m: np.ndarray
    static_pose: np.ndarray
    prims: Primitives
    centres: Centres


@dataclass
class ActorStates:
    """Actor poses and velocities at one time: pos (A, 3) m in {W}, yaw (A,) rad, vel (A, 3) m/s,
    yaw_rate (A,) rad/s."""

    pos: np.ndarray
    yaw: np.ndarray
    vel: np.ndarray
    yaw_rate: np.ndarray


def actor_states(scene: Scene, t_s: float) -> ActorStates:
    """Poses and velocities of all actors at time ``t_s`` (exact, analytic motion)."""
    kappa = scene.layout.kappa_1pm
    n = len(scene.actor_class)
    pos = np.zeros((n, 3))
    yaw = np.zeros(n)
    vel = np.zeros((n, 3))
    rate = np.zeros(n)
    along = scene.mode == ALONG
    if along.any():
        scale = 1.0 - kappa * scene.l0_m[along]
        s_c = scene.s0_m[along] + scene.speed_mps[along] * t_s / scale
        xy, theta = road_to_world(kappa, s_c, scene.l0_m[along])
        pos[along, :2] = xy
        yaw[along] = theta + scene.yaw_offset_rad[along]
        vel[along, 0] = scene.speed_mps[along] * np.cos(theta)
        vel[along, 1] = scene.speed_mps[along] * np.sin(theta)
        rate[along] = kappa * scene.speed_mps[along] / scale
    across = scene.mode == ACROSS
    if across.any():
        l_t = scene.l0_m[across] + scene.speed_mps[across] * t_s
        xy, theta = road_to_world(kappa, scene.s0_m[across], l_t)
        pos[across, :2] = xy
        yaw[across] = theta + scene.yaw_offset_rad[across]
        vel[across, 0] = -scene.speed_mps[across] * np.sin(theta)
        vel[across, 1] = scene.speed_mps[across] * np.cos(theta)
    return ActorStates(pos, yaw, vel, rate)


def label_poses(scene: Scene, states: ActorStates) -> tuple[np.ndarray, np.ndarray]:
    """Bottom-centre positions (A, 3) in {W} and yaw (A,) of every actor's label box."""
    static = scene.mode == STATIC
    pos = states.pos.copy()
    yaw = states.yaw.copy()
    pos[static, :2] = scene.static_pose[static, :2]
    yaw[static] = scene.static_pose[static, 2]
    return pos, yaw


def primitives_at(scene: Scene, states: ActorStates) -> Primitives:
    """The scene's primitives placed in {W} for the given actor states."""
    p = scene.prims
    a = p.actor
    c, s = np.cos(states.yaw[a]), np.sin(states.yaw[a])
    centre = states.pos[a].copy()
    centre[:, 0] += c * p.centre[:, 0] - s * p.centre[:, 1]
    centre[:, 1] += s * p.centre[:, 0] + c * p.centre[:, 1]
    centre[:, 2] += p.centre[:, 2]
    return Primitives(a, p.kind, centre, states.yaw[a] + p.yaw, p.half, p.material, p.tint)


def ego_pose(scene: Scene, t_s: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Vehicle pose at ``t_s``: T_world_vehicle (4, 4), velocity (3,) m/s in {W}, yaw rate rad/s.

    Vehicle frame: origin on the ground under the rear axle, x forward, y left, z up.
    """
    e = scene.ego
    kappa = scene.layout.kappa_1pm
    scale = 1.0 - kappa * e.l_m
    travelled = e.speed0_mps * t_s + 0.5 * e.accel_mps2 * t_s**2
    speed = e.speed0_mps + e.accel_mps2 * t_s
    xy, theta = road_to_world(kappa, np.array([e.s0_m + travelled / scale]), np.array([e.l_m]))
    T = np.eye(4)
    c, s = np.cos(theta[0]), np.sin(theta[0])
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = xy[0]
    return T, np.array([speed * c, speed * s, 0.0]), kappa * speed / scale


def ego_speed(scene: Scene, t_s: float) -> float:
    """Ego speed (m/s) at ``t_s``."""
    return float(scene.ego.speed0_mps + scene.ego.accel_mps2 * t_s)


class SceneBuilder:
    """Accumulates actors, primitives and scattering centres while a scene is built."""

    def __init__(self, rng: np.random.Generator, kappa: float, id_base: int) -> None:
        self.rng = rng
        self.kappa = kappa
        self.id_base = id_base
        self.actors: list[tuple] = []
        self.prims: list[tuple] = []

    def actor(self, cls: str, mode: int = STATIC, s0: float = 0.0, l0: float = 0.0, speed: float = 0.0,
              yaw_offset: float = 0.0, size_lwh: tuple[float, float, float] = (0.0, 0.0, 0.0),
              static_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> int:
        """Add an actor; returns its index. ``static_pose`` (x, y, yaw) locates a static labelled actor."""
        self.actors.append((cls, mode, s0, l0, speed, yaw_offset, size_lwh, static_pose))
        return len(self.actors) - 1

    def box(self, actor: int, centre: tuple, yaw: float, size_lwh: tuple, material: str,
            tint: tuple = (1.0, 1.0, 1.0), pose: tuple[float, float, float] | None = None) -> None:
        """Box with full sizes (length along its x, width, height) centred at ``centre``.

        ``pose`` (x, y, yaw) places a part given in object coordinates into the actor frame.
        """
        centre, yaw = _apply_pose(centre, yaw, pose)
        half = (size_lwh[0] / 2, size_lwh[1] / 2, size_lwh[2] / 2)
        self.prims.append((actor, BOX, centre, yaw, half, MATERIAL_ID[material], tint))

    def cylinder(self, actor: int, base_xy: tuple, z0: float, radius: float, height: float, material: str,
                 tint: tuple = (1.0, 1.0, 1.0), pose: tuple[float, float, float] | None = None) -> None:
        """Vertical cylinder standing at ``base_xy`` from height z0 to z0 + height."""
        centre, _ = _apply_pose((base_xy[0], base_xy[1], z0 + height / 2), 0.0, pose)
        self.prims.append((actor, CYLINDER, centre, 0.0, (radius, radius, height / 2), MATERIAL_ID[material], tint))

    def place(self, s: float, l: float) -> tuple[float, float, float]:
        """World (x, y) and road heading at road coordinates (s, l)."""
        xy, theta = road_to_world(self.kappa, np.array([s]), np.array([l]))
        return float(xy[0, 0]), float(xy[0, 1]), float(theta[0])

    def finish(self, scene_type: str, layout: RoadLayout, ego: Ego, ground_centres: Centres) -> Scene:
        """Assemble arrays, sample scattering centres and return the Scene."""
        a = self.actors
        prims = Primitives(
            actor=np.array([p[0] for p in self.prims], np.int64),
            kind=np.array([p[1] for p in self.prims], np.int64),
            centre=np.array([p[2] for p in self.prims], np.float64).reshape(-1, 3),
            yaw=np.array([p[3] for p in self.prims], np.float64),
            half=np.array([p[4] for p in self.prims], np.float64).reshape(-1, 3),
            material=np.array([p[5] for p in self.prims], np.int64),
            tint=np.array([p[6] for p in self.prims], np.float64).reshape(-1, 3),
        )
        centres = _concat_centres([ground_centres, sample_centres(prims, self.rng)])
        sun = np.array([np.cos(self.rng.uniform(0, 2 * np.pi)), np.sin(self.rng.uniform(0, 2 * np.pi)), 0.0])
        sun[:2] /= np.linalg.norm(sun[:2])
        sun[:2] *= np.cos(np.radians(self.rng.uniform(25, 60)))
        sun[2] = np.sqrt(1.0 - sun[0] ** 2 - sun[1] ** 2)
        return Scene(
            scene_type=scene_type, layout=layout, ego=ego, sun_W=sun,
            actor_class=[x[0] for x in a],
            object_id=self.id_base + np.arange(len(a), dtype=np.int64),
            mode=np.array([x[1] for x in a], np.int64),
            s0_m=np.array([x[2] for x in a], np.float64),
            l0_m=np.array([x[3] for x in a], np.float64),
            speed_mps=np.array([x[4] for x in a], np.float64),
            yaw_offset_rad=np.array([x[5] for x in a], np.float64),
            size_lwh_m=np.array([x[6] for x in a], np.float64).reshape(-1, 3),
            static_pose=np.array([x[7] for x in a], np.float64).reshape(-1, 3),
            prims=prims, centres=centres,
        )


def _apply_pose(centre: tuple, yaw: float, pose: tuple[float, float, float] | None) -> tuple[tuple, float]:
    """Map a part's centre and yaw from object coordinates through ``pose`` = (x, y, yaw)."""
    if pose is None:
        return tuple(float(c) for c in centre), float(yaw)
    x, y, th = pose
    c, s = np.cos(th), np.sin(th)
    return (x + c * centre[0] - s * centre[1], y + s * centre[0] + c * centre[1], float(centre[2])), yaw + th


def _concat_centres(parts: list[Centres]) -> Centres:
    return Centres(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                     ("prim", "pos", "normal", "rcs_dbsm", "lobe")))


def _rotate_z(v: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Rotate vectors (N, 3) about z by yaw (N,)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]], axis=1)


def sample_centres(prims: Primitives, rng: np.random.Generator) -> Centres:
    """Scattering centres on box faces (not the bottom), vertical box edges and cylinder sides.

    Positions and normals are returned in the actor frame of each primitive.
    """
    mats = material_arrays()
    edge_mat = np.isin(prims.material, [MATERIAL_ID[m] for m in EDGE_MATERIALS])
    out_prim, out_pos, out_nrm, out_rcs, out_lobe = [], [], [], [], []
    for i in np.flatnonzero(prims.kind != PLANE):
        h = prims.half[i]
        dens = mats["density"][prims.material[i]]
        if prims.kind[i] == BOX:
            pos, nrm, lobe = _box_surface_points(h, dens, edge_mat[i], rng)
        else:
            pos, nrm, lobe = _cylinder_surface_points(h, dens, rng)
        lobe = np.where(np.isnan(lobe), mats["lobe"][prims.material[i]], lobe)
        rcs = mats["rcs_dbsm"][prims.material[i]] + rng.normal(0.0, 2.5, len(pos))
        rcs = rcs + np.where(np.abs(nrm[:, 0] * nrm[:, 1]) > 0.4, 4.0, 0.0)  # dihedral edges
        out_prim.append(np.full(len(pos), i))
        out_pos.append(_rotate_z(pos, np.full(len(pos), prims.yaw[i])) + prims.centre[i])
        out_nrm.append(_rotate_z(nrm, np.full(len(pos), prims.yaw[i])))
        out_rcs.append(rcs)
        out_lobe.append(lobe)
    if not out_prim:
        return Centres(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0))
    return Centres(np.concatenate(out_prim), np.concatenate(out_pos), np.concatenate(out_nrm),
                   np.concatenate(out_rcs), np.concatenate(out_lobe))


def _box_surface_points(h: np.ndarray, density: float, edges: bool,
                        rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points (N, 3), normals (N, 3) and lobe override (N,; NaN = material lobe) in box coordinates."""
    pos, nrm = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            if axis == 2 and sign < 0:
                continue
            u, v = [k for k in range(3) if k != axis]
            area = 4.0 * h[u] * h[v]
            n = min(int(rng.poisson(area * density)), 150)
            p = np.zeros((n, 3))
            p[:, axis] = sign * h[axis]
            p[:, u] = rng.uniform(-h[u], h[u], n)
            p[:, v] = rng.uniform(-h[v], h[v], n)
            q = np.zeros((n, 3))
            q[:, axis] = sign
            pos.append(p)
            nrm.append(q)
    lobe = [np.full(sum(len(p) for p in pos), np.nan)]
    if edges:
        n_z = max(1, int(round(2 * h[2] / 0.4)))
        z = rng.uniform(-h[2], h[2], (4, n_z))
        for k, (sx, sy) in enumerate(((1, 1), (1, -1), (-1, 1), (-1, -1))):
            pos.append(np.stack([np.full(n_z, sx * h[0]), np.full(n_z, sy * h[1]), z[k]], axis=1))
            nrm.append(np.tile([sx / np.sqrt(2), sy / np.sqrt(2), 0.0], (n_z, 1)))
            lobe.append(np.full(n_z, 1.0))
    return np.concatenate(pos), np.concatenate(nrm), np.concatenate(lobe)


def _cylinder_surface_points(h: np.ndarray, density: float,
                             rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points, normals and lobe override on the side of a vertical cylinder (cylinder coordinates)."""
    r, hz = h[0], h[2]
    n = max(1, min(int(rng.poisson(2 * np.pi * r * 2 * hz * density)), 60))
    ang = rng.uniform(0, 2 * np.pi, n)
    nrm = np.stack([np.cos(ang), np.sin(ang), np.zeros(n)], axis=1)
    pos = nrm * r
    pos[:, 2] = rng.uniform(-hz, hz, n)
    return pos, nrm, np.full(n, np.nan)

