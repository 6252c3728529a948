"""Procedural builders of the three scene types (residential, urban, highway).

Each builder lays out a road cross-section, places static objects along it (buildings, trees,
poles, signs, hedges, guard rails, parked cars) and moving actors (cars, trucks, cyclists,
pedestrians) with constant speeds along their lanes, chosen so that nothing collides with the ego
vehicle within the sequence. All randomness comes from the generator passed in.
"""

from __future__ import annotations

import numpy as np

from pipeline.world.materials import MATERIAL_ID, material_arrays
from pipeline.world.road import RoadLayout, ground_material, road_to_world
from pipeline.world.scene import (ACROSS, ALONG, PLANE, SCENE_TYPES, Centres, Ego, Scene, SceneBuilder)

GROUND_CENTRES_PER_M2 = 0.8
"""Density of radar scattering centres on the ground."""
FRAME_DT_S = 0.1
"""Frame period: 10 Hz."""

CAR_COLOURS = ((0.75, 0.08, 0.06), (0.1, 0.2, 0.6), (0.85, 0.85, 0.85), (0.5, 0.5, 0.52),
               (0.12, 0.35, 0.15), (0.9, 0.75, 0.2), (0.35, 0.18, 0.1))
CLOTHES = ((0.1, 0.1, 0.3), (0.5, 0.1, 0.1), (0.2, 0.2, 0.2), (0.8, 0.7, 0.5), (0.1, 0.4, 0.3),
           (0.9, 0.9, 0.85), (0.6, 0.3, 0.6))
EGO_SPEED_RANGE = {"residential": (0.0, 8.0), "urban": (0.0, 12.0), "highway": (9.0, 15.0)}
"""Ego speed range per scene type (m/s); overall 0..15 m/s."""
MAX_EGO_SPEED_MPS = 15.0


def build_scene(scene_type: str, rng: np.random.Generator, frames: int, id_base: int,
                ego_speed_mps: float | None = None) -> Scene:
    """Build one sequence's scene of ``scene_type`` lasting ``frames`` frames at 10 Hz.

    ``ego_speed_mps`` forces a constant ego speed (no acceleration); otherwise speed and
    acceleration are drawn for the scene type. Object ids start at ``id_base``.
    """
    if scene_type not in SCENE_TYPES:
        raise ValueError(f"unknown scene type {scene_type!r}; expected one of {SCENE_TYPES}")
    duration = max(frames - 1, 0) * FRAME_DT_S
    ego_rng = np.random.default_rng(rng.integers(2**63))
    speed0, accel = _ego_speed(ego_rng, scene_type, duration, ego_speed_mps)
    layout, ego_l = _layout(scene_type, rng)
    span = (-45.0, MAX_EGO_SPEED_MPS * duration + 100.0)  # independent of the ego speed: same seed, same scene
    b = SceneBuilder(rng, layout.kappa_1pm, id_base)
    ground = b.actor("ground")
    b.prims.append((ground, PLANE, (0.0, 0.0, 0.0), 0.0, (0.0, 0.0, 0.0), MATERIAL_ID["asphalt"], (1.0, 1.0, 1.0)))
    ego = Ego(0.0, ego_l, speed0, accel)
    {"residential": _residential, "urban": _urban, "highway": _highway}[scene_type](
        b, layout, ego, span, duration)
    return b.finish(scene_type, layout, ego, _ground_centres(layout, span, rng))


def _ego_speed(rng: np.random.Generator, scene_type: str, duration: float,
               forced: float | None) -> tuple[float, float]:
    """Initial ego speed and acceleration, keeping the speed inside the scene type's range."""
    if forced is not None:
        return float(forced), 0.0
    lo, hi = EGO_SPEED_RANGE[scene_type]
    if scene_type != "highway" and rng.uniform() < 0.12:
        return 0.0, 0.0
    v0 = rng.uniform(max(lo, 1.0), hi)
    accel = rng.uniform(-0.8, 0.8)
    v_end = np.clip(v0 + accel * duration, max(lo, 0.5), hi)
    return float(v0), float((v_end - v0) / duration) if duration > 0 else 0.0


def _layout(scene_type: str, rng: np.random.Generator) -> tuple[RoadLayout, float]:
    """Road cross-section and the ego's lateral offset for a scene type."""
    if scene_type == "residential":
        kappa = rng.choice([0.0, 0.0, 1 / 70, -1 / 70, 1 / 120, -1 / 120])
        return RoadLayout(kappa, 5.2, 1.8, "grass", (), (0.0,)), -1.3
    if scene_type == "urban":
        kappa = rng.choice([0.0, 0.0, 1 / 80, -1 / 80, 1 / 150])
        return RoadLayout(kappa, 8.0, 3.5, "paving", (-3.25, 3.25), (0.0,)), float(rng.choice([-1.625, -4.875]))
    kappa = rng.choice([0.0, 1 / 400, -1 / 400, 1 / 800])
    return (RoadLayout(kappa, 12.0, 0.0, "grass", (-5.0, -8.5, 5.0, 8.5), (), edge_lines=True, shoulder_m=2.5),
            float(rng.choice([-3.25, -6.75, -10.25])))


def _ground_centres(layout: RoadLayout, span: tuple[float, float], rng: np.random.Generator) -> Centres:
    """Scattering centres on the ground (z = 0, prim 0) plus kerb-line centres facing the road."""
    width = layout.half_width_m + layout.shoulder_m + layout.sidewalk_m + 5.0
    n = rng.poisson(GROUND_CENTRES_PER_M2 * (span[1] - span[0]) * 2 * width)
    s = rng.uniform(span[0], span[1], n)
    l = rng.uniform(-width, width, n)
    xy, _ = road_to_world(layout.kappa_1pm, s, l)
    mat = ground_material(layout, s, l)
    rcs = material_arrays()["rcs_dbsm"][mat] + rng.normal(0, 3.0, n)
    normal = np.tile([0.0, 0.0, 1.0], (n, 1))
    kerb_s = np.arange(span[0], span[1], 0.6)
    kerb_l = layout.half_width_m + layout.shoulder_m
    ks = np.concatenate([kerb_s, kerb_s])
    kl = np.concatenate([np.full(len(kerb_s), kerb_l), np.full(len(kerb_s), -kerb_l)])
    kxy, kth = road_to_world(layout.kappa_1pm, ks, kl)
    side = -np.sign(kl)
    knormal = np.stack([-np.sin(kth) * side, np.cos(kth) * side, np.zeros(len(ks))], axis=1)
    pos = np.concatenate([np.column_stack([xy, np.zeros(n)]), np.column_stack([kxy, np.zeros(len(ks))])])
    return Centres(np.zeros(len(pos), np.int64), pos, np.concatenate([normal, knormal]),
                   np.concatenate([rcs, rng.normal(-6.0, 3.0, len(ks))]), np.full(len(pos), 1.0))


def _slots(rng: np.random.Generator, lo: float, hi: float, gap: tuple[float, float]) -> np.ndarray:
    """Increasing positions in [lo, hi) separated by random gaps."""
    out, s = [], lo + rng.uniform(0, gap[1])
    while s < hi:
        out.append(s)
        s += rng.uniform(*gap)
    return np.array(out)


def _pick(rng: np.random.Generator, options: tuple) -> tuple:
    return options[int(rng.integers(len(options)))]


def add_car(b: SceneBuilder, s: float, l: float, heading_sign: float, speed: float = 0.0,
            static: bool = True, truck: bool = False) -> None:
    """A car (or truck) at road coordinates; moving ones drive along the road at ``speed`` m/s."""
    rng = b.rng
    if truck:
        L, W, H = rng.uniform(7.0, 11.0), rng.uniform(2.4, 2.55), rng.uniform(3.2, 3.8)
    else:
        L, W, H = rng.uniform(3.8, 4.9), rng.uniform(1.7, 1.95), rng.uniform(1.4, 1.65)
    yaw_off = 0.0 if heading_sign > 0 else np.pi
    cls = "Truck" if truck else "Car"
    if static:
        x, y, th = b.place(s, l)
        pose = (x, y, th + yaw_off + rng.normal(0, 0.03))
        actor = b.actor(cls, size_lwh=(L, W, H), static_pose=pose)
    else:
        pose = None
        actor = b.actor(cls, ALONG, s, l, speed, yaw_off, (L, W, H))
    dark = rng.uniform() < 0.25
    paint = "dark_paint" if dark else "car_paint"
    tint = (1.0, 1.0, 1.0) if dark else _pick(rng, CAR_COLOURS)
    if truck:
        _truck_parts(b, actor, L, W, H, paint, tint, pose)
    else:
        _car_parts(b, actor, L, W, H, paint, tint, pose)


def _car_parts(b: SceneBuilder, a: int, L: float, W: float, H: float, paint: str, tint: tuple, pose) -> None:
    z_body = 0.95 * H / 1.5
    b.box(a, (0.0, 0.0, (0.28 + z_body) / 2), 0.0, (L, W, z_body - 0.28), paint, tint, pose)
    cab_h = H - 0.06 - z_body
    b.box(a, (-0.06 * L, 0.0, z_body + cab_h / 2), 0.0, (0.5 * L, W - 0.12, cab_h), "glass", pose=pose)
    b.box(a, (-0.07 * L, 0.0, H - 0.03), 0.0, (0.46 * L, W - 0.16, 0.06), paint, tint, pose)
    for x in (0.31 * L, -0.31 * L):
        b.box(a, (x, 0.0, 0.31), 0.0, (0.62, W - 0.04, 0.62), "rubber", pose=pose)


def _truck_parts(b: SceneBuilder, a: int, L: float, W: float, H: float, paint: str, tint: tuple, pose) -> None:
    cab_l = 2.3
    b.box(a, (L / 2 - cab_l / 2, 0.0, 0.5 + 1.0), 0.0, (cab_l, W, 2.0), paint, tint, pose)
    b.box(a, (L / 2 - 0.05, 0.0, 2.0 + 0.4), 0.0, (0.1, W - 0.2, 0.7), "glass", pose=pose)
    cargo_l = L - cab_l - 0.3
    b.box(a, (-L / 2 + cargo_l / 2, 0.0, 0.9 + (H - 0.9) / 2), 0.0, (cargo_l, W, H - 0.9), "car_paint",
          (0.9, 0.9, 0.9), pose)
    for x in (L / 2 - 1.2, -L / 2 + 1.5, -L / 2 + 2.8):
        b.box(a, (x, 0.0, 0.5), 0.0, (1.0, W - 0.05, 1.0), "rubber", pose=pose)


def add_pedestrian(b: SceneBuilder, s: float, l: float, speed: float, across: bool = False) -> None:
    """A pedestrian walking along the sidewalk (or across the road) at ``speed`` m/s (0 = standing)."""
    rng = b.rng
    h = rng.uniform(1.55, 1.9)
    if across:
        actor = b.actor("Pedestrian", ACROSS, s, l, speed, np.pi / 2 if speed >= 0 else -np.pi / 2, (0.5, 0.6, h))
    else:
        actor = b.actor("Pedestrian", ALONG, s, l, speed, 0.0 if speed >= 0 else np.pi, (0.5, 0.6, h))
    legs, torso = _pick(rng, CLOTHES), _pick(rng, CLOTHES)
    skin = (rng.uniform(0.45, 1.1),) * 3
    k = h / 1.75
    b.box(actor, (0.0, 0.0, 0.45 * k), 0.0, (0.25, 0.34, 0.9 * k), "clothing", legs)
    b.box(actor, (0.0, 0.0, 1.19 * k), 0.0, (0.28, 0.46, 0.58 * k), "clothing", torso)
    b.box(actor, (0.0, 0.0, 1.615 * k), 0.0, (0.21, 0.18, 0.25 * k), "skin", skin)


def add_cyclist(b: SceneBuilder, s: float, l: float, speed: float) -> None:
    """A cyclist riding along the road at ``speed`` m/s (negative = against increasing s)."""
    rng = b.rng
    actor = b.actor("Cyclist", ALONG, s, l, speed, 0.0 if speed >= 0 else np.pi, (1.8, 0.6, 1.85))
    b.box(actor, (0.0, 0.0, 0.6), 0.0, (1.1, 0.06, 0.45), "bicycle_metal", _pick(rng, CAR_COLOURS))
    for x in (0.55, -0.55):
        b.box(actor, (x, 0.0, 0.34), 0.0, (0.66, 0.05, 0.66), "rubber")
    b.box(actor, (-0.05, 0.0, 0.8), 0.0, (0.35, 0.32, 0.5), "clothing", _pick(rng, CLOTHES))
    b.box(actor, (-0.05, 0.0, 1.32), 0.0, (0.32, 0.42, 0.55), "clothing", _pick(rng, CLOTHES))
    b.box(actor, (0.0, 0.0, 1.72), 0.0, (0.21, 0.18, 0.24), "skin", (rng.uniform(0.45, 1.1),) * 3)


def add_building(b: SceneBuilder, s: float, side: float, l_front: float, width: float, depth: float,
                 height: float, material: str, shopfront: bool) -> None:
    """A building whose facade faces the road at |l| = l_front, with glass window bands."""
    x, y, th = b.place(s, side * (l_front + depth / 2))
    a = b.actor("building")
    pose = (x, y, th)
    b.box(a, (0.0, 0.0, height / 2), 0.0, (width, depth, height), material, pose=pose)
    facade = -side * depth / 2 - side * 0.03
    if shopfront:
        b.box(a, (0.0, facade, 1.7), 0.0, (0.8 * width, 0.12, 2.6), "glass", pose=pose)
    for z in np.arange(4.2 if shopfront else 1.2, height - 1.2, 3.2):
        b.box(a, (0.0, facade, z + 0.7), 0.0, (0.85 * width, 0.1, 1.3), "glass", pose=pose)


def add_tree(b: SceneBuilder, s: float, l: float) -> None:
    """A tree: bark trunk and a vegetation crown (both cylinders)."""
    rng = b.rng
    x, y, _ = b.place(s, l)
    a = b.actor("vegetation")
    trunk_h = rng.uniform(2.0, 3.0)
    b.cylinder(a, (x, y), 0.0, rng.uniform(0.12, 0.25), trunk_h + 0.3, "bark")
    b.cylinder(a, (x, y), trunk_h, rng.uniform(1.2, 2.3), rng.uniform(2.5, 4.5), "vegetation")


def add_pole(b: SceneBuilder, s: float, l: float, sign: bool) -> None:
    """A lamp pole, or a short pole carrying a traffic sign facing the traffic."""
    rng = b.rng
    x, y, th = b.place(s, l)
    if sign:
        a = b.actor("sign")
        b.cylinder(a, (x, y), 0.0, 0.04, 2.7, "metal_pole")
        colour = _pick(rng, ((0.9, 0.1, 0.1), (0.1, 0.3, 0.9), (1.0, 1.0, 1.0), (1.0, 0.85, 0.1)))
        b.box(a, (0.0, 0.0, 2.35), 0.0, (0.05, 0.7, 0.7), "sign", colour, pose=(x + 0.06 * np.cos(th), y + 0.06 * np.sin(th), th))
    else:
        a = b.actor("pole")
        b.cylinder(a, (x, y), 0.0, 0.08, rng.uniform(5.5, 8.0), "metal_pole")


def add_segments(b: SceneBuilder, cls: str, span: tuple[float, float], l: float, seg_len: float, width: float,
                 z0: float, height: float, material: str, posts_every: float = 0.0) -> None:
    """A chain of straight boxes following the road (walls, guard rails, hedges, barriers)."""
    a = b.actor(cls)
    for s in np.arange(span[0], span[1], seg_len):
        x, y, th = b.place(s + seg_len / 2, l)
        b.box(a, (0.0, 0.0, z0 + height / 2), 0.0, (seg_len - 0.02, width, height), material, pose=(x, y, th))
        for sp in np.arange(0.0, seg_len, posts_every) if posts_every > 0 else ():
            px, py, pth = b.place(s + sp, l + np.sign(l) * (width / 2 + 0.06))
            b.box(a, (0.0, 0.0, (z0 + height) / 2), 0.0, (0.1, 0.1, z0 + height), "guard_rail", pose=(px, py, pth))


def _traffic(b: SceneBuilder, lanes: list[tuple[float, float]], span: tuple[float, float], duration: float,
             ego: Ego, speed_range: tuple[float, float], truck_prob: float) -> None:
    """Moving cars on lanes (offset, direction); the ego's lane gets cars ahead at the ego's pace."""
    rng = b.rng
    ego_mean = ego.speed0_mps + 0.5 * ego.accel_mps2 * duration
    for l, direction in lanes:
        if abs(l - ego.l_m) < 0.5:
            speed = ego_mean
            starts = _slots(rng, 14.0, span[1], (14.0, 35.0))
        else:
            speed = rng.uniform(*speed_range)
            reach = speed * duration
            lo, hi = (span[0] - reach, span[1]) if direction > 0 else (span[0], span[1] + reach)
            starts = _slots(rng, lo, hi, (12.0, 40.0))
        for s in starts:
            add_car(b, float(s), l, direction, direction * speed, static=False, truck=rng.uniform() < truck_prob)


def _residential(b: SceneBuilder, layout: RoadLayout, ego: Ego, span: tuple[float, float], duration: float) -> None:
    rng = b.rng
    for side in (-1.0, 1.0):
        for s in _slots(rng, span[0], span[1], (6.0, 9.0)):
            if rng.uniform() < 0.45:
                add_car(b, float(s), side * 4.2, -side, static=True)
        for s in _slots(rng, span[0], span[1], (12.0, 22.0)):
            w = rng.uniform(8.0, 13.0)
            add_building(b, float(s), side, rng.uniform(11.0, 15.0), w, rng.uniform(8.0, 11.0),
                         rng.uniform(5.0, 8.0), _pick(rng, ("brick", "plaster", "brick")), False)
        for s in _slots(rng, span[0], span[1], (9.0, 20.0)):
            add_tree(b, float(s), side * rng.uniform(7.8, 9.5))
        for s in _slots(rng, span[0], span[1], (25.0, 40.0)):
            add_pole(b, float(s), side * 5.5, sign=rng.uniform() < 0.4)
        if rng.uniform() < 0.7:
            add_segments(b, "vegetation", span, side * 7.4, 4.0, 0.7, 0.0, rng.uniform(0.9, 1.4), "vegetation")
        for s in _slots(rng, span[0] - 10, span[1] + 10, (8.0, 25.0)):
            speed = 0.0 if rng.uniform() < 0.2 else rng.choice([-1.0, 1.0]) * rng.uniform(0.8, 1.6)
            add_pedestrian(b, float(s), side * rng.uniform(6.0, 6.6), speed)
    _traffic(b, [(-1.5, 1.0), (1.5, -1.0)], span, duration, ego,
             (5.0, 9.0), 0.05)
    for s in _slots(rng, span[0], span[1] + 20, (25.0, 60.0)):
        d = rng.choice([-1.0, 1.0])
        add_cyclist(b, float(s), -d * 2.75, d * rng.uniform(3.0, 6.0))


def _urban(b: SceneBuilder, layout: RoadLayout, ego: Ego, span: tuple[float, float], duration: float) -> None:
    rng = b.rng
    front = layout.half_width_m + layout.sidewalk_m
    for side in (-1.0, 1.0):
        s = span[0]
        while s < span[1]:
            w = rng.uniform(10.0, 24.0)
            add_building(b, s + w / 2, side, front + rng.uniform(0.0, 0.4), w - rng.uniform(0.0, 1.0),
                         12.0, rng.uniform(9.0, 24.0), _pick(rng, ("concrete", "brick", "plaster")), True)
            s += w
        for s in _slots(rng, span[0], span[1], (15.0, 30.0)):
            add_pole(b, float(s), side * (layout.half_width_m + 0.6), sign=rng.uniform() < 0.5)
        for s in _slots(rng, span[0], span[1], (12.0, 30.0)):
            add_tree(b, float(s), side * (layout.half_width_m + 0.9))
        for s in _slots(rng, span[0] - 10, span[1] + 10, (4.0, 14.0)):
            speed = 0.0 if rng.uniform() < 0.2 else rng.choice([-1.0, 1.0]) * rng.uniform(0.8, 1.6)
            add_pedestrian(b, float(s), side * rng.uniform(9.8, 10.9), speed)
        for s in _slots(rng, span[0], span[1] + 20, (30.0, 70.0)):
            add_cyclist(b, float(s), side * 7.25, -side * rng.uniform(3.0, 6.0))
    _traffic(b, [(-4.875, 1.0), (-1.625, 1.0), (1.625, -1.0), (4.875, -1.0)], span, duration, ego, (3.0, 11.0), 0.1)
    ego_end = ego.speed0_mps * duration + 0.5 * ego.accel_mps2 * duration**2
    if rng.uniform() < 0.6:
        d = rng.choice([-1.0, 1.0])
        add_pedestrian(b, float(ego_end + rng.uniform(18.0, 40.0)), -d * 8.5, d * rng.uniform(1.0, 1.5), across=True)


def _highway(b: SceneBuilder, layout: RoadLayout, ego: Ego, span: tuple[float, float], duration: float) -> None:
    rng = b.rng
    add_segments(b, "concrete_barrier", span, 0.0, 12.0, 0.5, 0.0, 0.85, "concrete")
    for side in (-1.0, 1.0):
        add_segments(b, "guard_rail", span, side * 14.8, 12.0, 0.1, 0.45, 0.32, "guard_rail", posts_every=6.0)
        for s in _slots(rng, span[0], span[1], (6.0, 18.0)):
            add_tree(b, float(s), side * rng.uniform(18.0, 30.0))
        for s in _slots(rng, span[0], span[1], (45.0, 80.0)):
            add_pole(b, float(s), side * 15.6, sign=rng.uniform() < 0.5)
        if rng.uniform() < 0.4:
            add_segments(b, "wall", span, side * rng.uniform(20.0, 24.0), 15.0, 0.4, 0.0, rng.uniform(3.0, 4.5),
                         "concrete")
    lanes = [(-3.25, 1.0), (-6.75, 1.0), (-10.25, 1.0), (3.25, -1.0), (6.75, -1.0), (10.25, -1.0)]
    _traffic(b, lanes, span, duration, ego, (10.0, 16.0), 0.2)
