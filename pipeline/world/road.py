"""Road geometry: a constant-curvature centreline with road coordinates (s, l).

World frame {W}: x, y on the flat ground (z = 0), z up, metres. The road centreline starts at the
origin heading along +x and bends with constant curvature ``kappa_1pm`` (1/m, positive = turning
left). A point is addressed by arc length ``s_m`` along the centreline and lateral offset ``l_m``
(positive to the left of the direction of travel).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.world.materials import MATERIAL_ID

STRAIGHT_EPS = 1e-9
"""|kappa| below which the road is treated as straight."""


@dataclass(frozen=True)
class RoadLayout:
    """Cross-section of the road (all offsets in metres from the centreline, left positive).

    kappa_1pm: curvature (1/m). half_width_m: kerb line |l| of the carriageway.
    sidewalk_m: width of the paved strip beyond the kerb. verge: ground material name beyond it.
    lane_bounds_m: lateral offsets of painted lane separators (dashed), centre_lines_m: solid lines.
    edge_lines: paint solid edge lines 0.3 m inside the kerb (highways).
    shoulder_m: asphalt shoulder beyond the kerb line before the sidewalk/verge (highways).
    """

    kappa_1pm: float
    half_width_m: float
    sidewalk_m: float
    verge: str
    lane_bounds_m: tuple[float, ...]
    centre_lines_m: tuple[float, ...]
    edge_lines: bool = False
    shoulder_m: float = 0.0


def road_to_world(kappa_1pm: float, s_m: np.ndarray, l_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Road coordinates (N,) -> world xy (N, 2) metres and road heading (N,) rad (0 = +x)."""
    s = np.asarray(s_m, np.float64)
    l = np.asarray(l_m, np.float64)
    if abs(kappa_1pm) < STRAIGHT_EPS:
        theta = np.zeros(np.broadcast(s, l).shape)
        return np.stack(np.broadcast_arrays(s, l), axis=-1).astype(np.float64), theta
    theta = kappa_1pm * s
    x = np.sin(theta) / kappa_1pm - l * np.sin(theta)
    y = (1.0 - np.cos(theta)) / kappa_1pm + l * np.cos(theta)
    return np.stack(np.broadcast_arrays(x, y), axis=-1), np.broadcast_to(theta, np.shape(x)).copy()


def world_to_road(kappa_1pm: float, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World xy (..., 2) -> road coordinates (s_m, l_m), each (...). Valid for |kappa s| < pi."""
    x = xy[..., 0]
    y = xy[..., 1]
    if abs(kappa_1pm) < STRAIGHT_EPS:
        return x.copy(), y.copy()
    radius = 1.0 / kappa_1pm
    sign = np.sign(kappa_1pm)
    dy = y - radius
    rho = np.hypot(x, dy)
    l = radius - sign * rho
    theta = np.arctan2(sign * x, -sign * dy)
    return theta / kappa_1pm, l


def ground_material(layout: RoadLayout, s_m: np.ndarray, l_m: np.ndarray) -> np.ndarray:
    """Material id (N,) int32 of the ground at road coordinates (asphalt, markings, paving, verge)."""
    a = np.abs(l_m)
    mat = np.full(np.shape(l_m), MATERIAL_ID[layout.verge], np.int32)
    paved = a < layout.half_width_m + layout.shoulder_m + layout.sidewalk_m
    mat[paved] = MATERIAL_ID["paving"]
    mat[a < layout.half_width_m + layout.shoulder_m] = MATERIAL_ID["asphalt"]
    marking = np.zeros(np.shape(l_m), bool)
    dashed = np.mod(s_m, 9.0) < 3.0
    for b in layout.lane_bounds_m:
        marking |= (np.abs(l_m - b) < 0.075) & dashed
    for b in layout.centre_lines_m:
        marking |= np.abs(l_m - b) < 0.08
    if layout.edge_lines:
        marking |= np.abs(a - (layout.half_width_m - 0.3)) < 0.1
    mat[marking] = MATERIAL_ID["road_marking"]
    return mat
