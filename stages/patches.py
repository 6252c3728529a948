"""patches: RSS-Net training samples (eqs. 17-21).

Also PlaceNet's training rows (pipeline.placement).

Reads: calibrate (image, radar, lidar, K, T_radar_cam, ego_velocity, labels).
Writes (patches.zarr), for up to patches.points_per_frame radar points per frame sampled with a
generator seeded by (patches.seed, frame index) (identical on any worker):
  patch (n, s, s, 3) uint8: the 2 r_c x 2 r_c window around the point's projection (padded at the
  borders), resized to s = patches.patch_size_px; range_image (n, h, w) float32 local range image
  (eqs. 18-21, values 0..255, empty pixels pipeline.rangeimage.EMPTY); point (n, 4) float32
  [x, y, z m in {D}, range rate m/s]; rss (n,) float32 in dataset units;
and for up to placement.points_per_frame lidar candidates sampled uniformly the same way:
  place_features (c, len(pipeline.placement.FEATURES)) float32; place_count (c,) float32, the real
  radar points whose nearest candidate (among all of the frame's) it is, within placement.gate_m.
Config: patches.*, placement.points_per_frame / gate_m, radar field of view and range, camera.*
(r_c is scaled to the working resolution).
"""

from __future__ import annotations

import numpy as np

from pipeline.config import Config
from pipeline.executor import FrameInputs
from pipeline.geometry import invert_transform, project_to_image
from pipeline.patches import image_patches, sample_points
from pipeline.placement import FEATURES, candidate_features, lidar_candidates, radar_counts
from pipeline.rangeimage import local_range_images
from pipeline.stage import ArraySpec, FrameStage
from pipeline.working import scale_rc

CONFIG_KEYS = ("patches.points_per_frame", "patches.r_c_px", "patches.r_l_m", "patches.range_image_size",
               "patches.patch_size_px", "patches.seed", "camera.full_size", "camera.crop_rows",
               "camera.working_size", "placement.points_per_frame", "placement.gate_m", "radar.fov_az_deg",
               "radar.fov_el_deg", "radar.max_range_m")
VERSION = 2
"""2: PlaceNet's training rows (place_features, place_count). Not bumped when their surface normal
moved to closed form (pipeline.placement.smallest_eigenpair_sym3): the same values to about 1e-8,
and a bump would retrain RSS-Net, whose rows did not change."""


def outputs(cfg: Config) -> tuple[ArraySpec, ...]:
    n, s, c = cfg.patches.points_per_frame, cfg.patches.patch_size_px, cfg.placement.points_per_frame
    rw, rh = cfg.patches.range_image_size
    return (ArraySpec("patch", (n, s, s, 3), "uint8", "RGB 0-255", ragged=True),
            ArraySpec("range_image", (n, rh, rw), "float32", "local range image 0..255", ragged=True, finite=True),
            ArraySpec("point", (n, 4), "float32", "x,y,z m in {D}; range rate m/s", fill=np.nan, ragged=True,
                      finite=True),
            ArraySpec("rss", (n,), "float32", "dataset RSS units", fill=np.nan, ragged=True, finite=True),
            ArraySpec("place_features", (c, len(FEATURES)), "float32", ",".join(FEATURES), fill=np.nan, ragged=True,
                      finite=True),
            ArraySpec("place_count", (c,), "float32", "real radar points per candidate", fill=np.nan, ragged=True,
                      finite=True))


def point_inputs(image: np.ndarray, K: np.ndarray, T_radar_cam: np.ndarray, lidar_D: np.ndarray,
                 points_D: np.ndarray, cfg: Config, tree=None) -> tuple[np.ndarray, np.ndarray]:
    """Image patches (n, s, s, 3) and local range images (n, h, w) of points (n, 3) in {D}.

    Shared by training-sample extraction and by synthesis (RSS-Net inputs for generated points).
    ``tree``: a cKDTree of ``lidar_D`` the caller has already (synthesize: the one its candidates'
    neighbours came from), else one is built.
    """
    c = cfg.camera
    r_c = scale_rc(cfg.patches.r_c_px, tuple(c.crop_rows), tuple(c.full_size), tuple(c.working_size))
    uv, _, _ = project_to_image(points_D, K, invert_transform(T_radar_cam), tuple(c.working_size))
    patches = image_patches(image, uv, r_c, cfg.patches.patch_size_px)
    ranges = local_range_images(lidar_D, points_D, cfg.patches.r_l_m, tuple(cfg.patches.range_image_size), tree)
    return patches, ranges


def process(inputs: FrameInputs, cfg: Config) -> dict[str, np.ndarray]:
    radar = inputs.get("calibrate", "radar")
    idx = sample_points(inputs.rng(cfg.patches.seed, 11), len(radar), cfg.patches.points_per_frame)
    chosen = radar[idx]
    patches, ranges = point_inputs(inputs.get("calibrate", "image"), inputs.get("calibrate", "K"),
                                   inputs.get("calibrate", "T_radar_cam"), inputs.get("calibrate", "lidar"),
                                   chosen[:, :3].astype(np.float64), cfg)
    if inputs.get("calibrate", "has_radar"):
        features, counts = placement_rows(inputs, cfg, inputs.rng(cfg.patches.seed, 12))
    else:  # no radar, nothing to learn where it returns (a dataset that takes another's nets)
        features, counts = np.zeros((0, len(FEATURES)), np.float32), np.zeros(0, np.float32)
    return {"patch": patches, "range_image": ranges, "point": chosen[:, :4].astype(np.float32),
            "rss": chosen[:, 4].astype(np.float32), "place_features": features, "place_count": counts}


def candidates(inputs: FrameInputs, cfg: Config) -> tuple[np.ndarray, np.ndarray]:
    """The frame's lidar candidates (C, 3) m in {D} and their working pixels (C, 2) (shared with
    synthesis)."""
    r = cfg.radar
    lidar = inputs.get("calibrate", "lidar").astype(np.float64)
    idx, uv = lidar_candidates(lidar, inputs.get("calibrate", "K"), inputs.get("calibrate", "T_radar_cam"),
                               tuple(cfg.camera.working_size), r.fov_az_deg, r.fov_el_deg, r.max_range_m)
    return lidar[idx], uv


def features(inputs: FrameInputs, points_D: np.ndarray, uv: np.ndarray, workers: int = 1, tree=None) -> np.ndarray:
    """PlaceNet features of candidates (shared with synthesis; ``workers`` threads for the neighbour
    query; ``tree``: the frame's pipeline.placement.neighbour_tree when the caller keeps it)."""
    return candidate_features(points_D, uv, inputs.get("calibrate", "image"), inputs.get("calibrate", "lidar"),
                              inputs.get("calibrate", "ego_velocity"), inputs.get("calibrate", "labels"), workers,
                              tree)


def placement_rows(inputs: FrameInputs, cfg: Config, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """PlaceNet training rows of one frame: features (c, F) float32 and counts (c,) float32 of up to
    placement.points_per_frame candidates drawn uniformly without replacement."""
    points, uv = candidates(inputs, cfg)
    counts = radar_counts(points, inputs.get("calibrate", "radar")[:, :3], cfg.placement.gate_m)
    keep = sample_points(rng, len(points), cfg.placement.points_per_frame)
    return features(inputs, points[keep], uv[keep]), counts[keep].astype(np.float32)


STAGE = FrameStage(name="patches", upstream=("calibrate",), config_keys=CONFIG_KEYS, outputs=outputs,
                   process=process, version=VERSION, doc=__doc__)
