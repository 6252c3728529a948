"""heatmaps: the ground-truth distribution of radar returns in the image (eqs. 5-7).

Reads: calibrate (radar, K, T_radar_cam).
Writes (heatmaps.zarr): heatmap (h, w) float32, sums to 1 over the working image (all zeros when
the frame has no projected radar point: such frames have no defined target and are skipped by
Dis-Net training); count int32, the number of radar points projected into the working image.
Config: heatmap.sigma_px (std in full-resolution pixels, scaled to the working resolution),
camera.* (through the scaling).
"""

from __future__ import annotations

import numpy as np

from pipeline.config import Config
from pipeline.executor import FrameInputs
from pipeline.geometry import invert_transform, project_to_image
from pipeline.heatmap import gaussian_heatmap
from pipeline.stage import ArraySpec, FrameStage
from pipeline.working import scale_sigma

CONFIG_KEYS = ("heatmap.sigma_px", "camera.full_size", "camera.crop_rows", "camera.working_size")


def outputs(cfg: Config) -> tuple[ArraySpec, ...]:
    w, h = cfg.camera.working_size
    return (ArraySpec("heatmap", (h, w), "float32", "probability per pixel (sums to 1)", finite=True),
            ArraySpec("count", (), "int32", "radar points in the working image"))


def working_sigma(cfg: Config) -> tuple[float, float]:
    """Sigma std (u, v) in working-resolution pixels."""
    c = cfg.camera
    return scale_sigma(tuple(cfg.heatmap.sigma_px), tuple(c.crop_rows), tuple(c.full_size), tuple(c.working_size))


def radar_uv(inputs: FrameInputs, cfg: Config) -> np.ndarray:
    """Pixels (n, 2) at the working resolution of the frame's radar points that project into it."""
    radar = inputs.get("calibrate", "radar")
    if len(radar) == 0:
        return np.zeros((0, 2))
    T_cam_radar = invert_transform(inputs.get("calibrate", "T_radar_cam"))
    uv, _, valid = project_to_image(radar[:, :3], inputs.get("calibrate", "K"), T_cam_radar,
                                    tuple(cfg.camera.working_size))
    return uv[valid]


def process(inputs: FrameInputs, cfg: Config) -> dict[str, np.ndarray]:
    w, h = cfg.camera.working_size
    uv = radar_uv(inputs, cfg)
    if len(uv) == 0:
        return {"heatmap": np.zeros((h, w), np.float32), "count": np.int32(0)}
    return {"heatmap": gaussian_heatmap(uv, (w, h), working_sigma(cfg)), "count": np.int32(len(uv))}


STAGE = FrameStage(name="heatmaps", upstream=("calibrate",), config_keys=CONFIG_KEYS, outputs=outputs,
                   process=process, doc=__doc__)
