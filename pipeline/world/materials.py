"""Material table of the synthetic world: appearance, lidar response and radar reflectivity.

Every primitive of the world carries one material id. The same material decides how a surface
looks in the camera (base colour + procedural texture), how the lidar sees it (reflectivity,
return probability; glass lets the beam through) and how strongly it scatters the radar (RCS per
scattering centre in dBsm, specular lobe exponent, centre density). Appearance therefore predicts
radar reflectivity, which is what the learned RSS model has to discover.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Material:
    """One surface material.

    rgb: base colour, linear 0..1 (multiplied by a per-object tint where ``tinted``).
    texture: name of the procedural texture (see camera.py).
    rcs_dbsm: mean RCS of one scattering centre seen face-on, dBsm.
    lobe: exponent n of the aspect factor cos(incidence)^n (large = mirror-like metal).
    centres_per_m2: density of radar scattering centres on the surface.
    lidar_reflectivity: 0..1, scaled to VoD's 0..255 reflectance on write.
    lidar_return_prob: probability that a lidar beam hitting the surface returns (dark paint drops).
    transparent: lidar beams and radar occlusion pass through (glass).
    specular: strength of the camera's specular highlight.
    """

    name: str
    rgb: tuple[float, float, float]
    texture: str
    rcs_dbsm: float
    lobe: float
    centres_per_m2: float
    lidar_reflectivity: float
    lidar_return_prob: float = 1.0
    transparent: bool = False
    specular: float = 0.0
    tinted: bool = False


MATERIALS: tuple[Material, ...] = (
    Material("asphalt", (0.30, 0.30, 0.31), "asphalt", -13.0, 1.0, 0.35, 0.08),
    Material("road_marking", (0.86, 0.86, 0.82), "plain", -11.0, 1.0, 0.35, 0.65),
    Material("paving", (0.60, 0.59, 0.56), "tiles", -11.0, 1.0, 0.35, 0.22),
    Material("grass", (0.24, 0.42, 0.16), "grass", -15.0, 1.0, 0.3, 0.30),
    Material("concrete", (0.68, 0.67, 0.64), "concrete", 1.0, 2.0, 1.0, 0.25),
    Material("brick", (0.56, 0.26, 0.19), "brick", 2.0, 2.0, 1.0, 0.20),
    Material("plaster", (0.86, 0.83, 0.74), "concrete", -2.0, 2.0, 0.9, 0.40),
    Material("glass", (0.16, 0.20, 0.25), "glass", 1.0, 8.0, 1.0, 0.0, 0.0, True, 0.9),
    Material("car_paint", (0.85, 0.85, 0.85), "paint", 9.0, 5.0, 5.0, 0.50, 1.0, False, 0.7, True),
    Material("dark_paint", (0.06, 0.06, 0.07), "paint", 9.0, 5.0, 5.0, 0.05, 0.3, False, 0.7),
    Material("rubber", (0.05, 0.05, 0.05), "plain", -2.0, 1.0, 4.0, 0.06, 0.8),
    Material("vegetation", (0.18, 0.36, 0.12), "leaves", -7.0, 1.0, 2.0, 0.35),
    Material("bark", (0.36, 0.26, 0.16), "bark", -4.0, 1.0, 2.0, 0.25),
    Material("clothing", (0.80, 0.80, 0.80), "cloth", -9.0, 1.0, 12.0, 0.30, 1.0, False, 0.0, True),
    Material("skin", (0.80, 0.60, 0.48), "plain", -12.0, 1.0, 8.0, 0.35, 1.0, False, 0.1, True),
    Material("metal_pole", (0.55, 0.56, 0.58), "brushed", 6.0, 2.0, 6.0, 0.45, 1.0, False, 0.5),
    Material("sign", (0.90, 0.90, 0.90), "plain", 11.0, 10.0, 10.0, 0.90, 1.0, False, 0.3, True),
    Material("guard_rail", (0.66, 0.68, 0.70), "rail", 7.0, 4.0, 4.0, 0.60, 1.0, False, 0.5),
    Material("bicycle_metal", (0.60, 0.60, 0.65), "plain", 2.0, 2.0, 10.0, 0.40, 1.0, False, 0.4, True),
)
"""All materials; a material's id is its index in this tuple."""

MATERIAL_ID: dict[str, int] = {m.name: i for i, m in enumerate(MATERIALS)}
"""Material name -> id."""


def material_arrays() -> dict[str, np.ndarray]:
    """Per-material properties as arrays indexed by material id (float64 unless stated)."""
    return {
        "rgb": np.array([m.rgb for m in MATERIALS], np.float64),
        "rcs_dbsm": np.array([m.rcs_dbsm for m in MATERIALS]),
        "lobe": np.array([m.lobe for m in MATERIALS]),
        "density": np.array([m.centres_per_m2 for m in MATERIALS]),
        "lidar_reflectivity": np.array([m.lidar_reflectivity for m in MATERIALS]),
        "lidar_return_prob": np.array([m.lidar_return_prob for m in MATERIALS]),
        "transparent": np.array([m.transparent for m in MATERIALS], bool),
        "specular": np.array([m.specular for m in MATERIALS]),
        "tinted": np.array([m.tinted for m in MATERIALS], bool),
    }
