"""patches: RSS-Net training samples (eqs. 17-21).

Reads: calibrate (image, radar, lidar, K, T_radar_cam).
Writes (patches.zarr), for up to patches.points_per_frame radar points per frame sampled with a
generator seeded by (patches.seed, frame index) (identical on any worker):
  patch (n, s, s, 3) uint8: the 2 r_c x 2 r_c window around the point's projection (padded at the
  borders), resized to s = patches.patch_size_px; range_image (n, h, w) float32 local range image
  (eqs. 18-21, values 0..255, empty pixels pipeline.rangeimage.EMPTY); point (n, 4) float32
  [x, y, z m in {D}, range rate m/s]; rss (n,) float32 in dataset units.
Config: patches.*, camera.* (r_c is scaled to the working resolution).
"""

from __future__ import annotations

import numpy as np

from pipeline.config import Config
from pipeline.executor import FrameInputs
from pipeline.geometry import invert_transform, project_to_image
from pipeline.patches import image_patches, sample_points
from pipeline.rangeimage import local_range_images
from pipeline.stage import ArraySpec, FrameStage
from pipeline.working import scale_rc

CONFIG_KEYS = ("patches.points_per_frame", "patches.r_c_px", "patches.r_l_m", "patches.range_image_size",
               "patches.patch_size_px", "patches.seed", "camera.full_size", "camera.crop_rows",
               "camera.working_size")


def outputs(cfg: Config) -> tuple[ArraySpec, ...]:
    n, s = cfg.patches.points_per_frame, cfg.patches.patch_size_px
    rw, rh = cfg.patches.range_image_size
    return (ArraySpec("patch", (n, s, s, 3), "uint8", "RGB 0-255", ragged=True),
            ArraySpec("range_image", (n, rh, rw), "float32", "local range image 0..255", ragged=True),
            ArraySpec("point", (n, 4), "float32", "x,y,z m in {D}; range rate m/s", fill=np.nan, ragged=True),
            ArraySpec("rss", (n,), "float32", "dataset RSS units", fill=np.nan, ragged=True))


def point_inputs(image: np.ndarray, K: np.ndarray, T_radar_cam: np.ndarray, lidar_D: np.ndarray,
                 points_D: np.ndarray, cfg: Config) -> tuple[np.ndarray, np.ndarray]:
    """Image patches (n, s, s, 3) and local range images (n, h, w) of points (n, 3) in {D}.

    Shared by training-sample extraction and by synthesis (RSS-Net inputs for generated points).
    """
    c = cfg.camera
    r_c = scale_rc(cfg.patches.r_c_px, tuple(c.crop_rows), tuple(c.full_size), tuple(c.working_size))
    uv, _, _ = project_to_image(points_D, K, invert_transform(T_radar_cam), tuple(c.working_size))
    patches = image_patches(image, uv, r_c, cfg.patches.patch_size_px)
    ranges = local_range_images(lidar_D, points_D, cfg.patches.r_l_m, tuple(cfg.patches.range_image_size))
    return patches, ranges


def process(inputs: FrameInputs, cfg: Config) -> dict[str, np.ndarray]:
    radar = inputs.get("calibrate", "radar")
    idx = sample_points(inputs.rng(cfg.patches.seed, 11), len(radar), cfg.patches.points_per_frame)
    chosen = radar[idx]
    patches, ranges = point_inputs(inputs.get("calibrate", "image"), inputs.get("calibrate", "K"),
                                   inputs.get("calibrate", "T_radar_cam"), inputs.get("calibrate", "lidar"),
                                   chosen[:, :3].astype(np.float64), cfg)
    return {"patch": patches, "range_image": ranges, "point": chosen[:, :4].astype(np.float32),
            "rss": chosen[:, 4].astype(np.float32)}


STAGE = FrameStage(name="patches", upstream=("calibrate",), config_keys=CONFIG_KEYS, outputs=outputs,
                   process=process, doc=__doc__)
