"""export: synthesized radar in detector-ready layouts.

Reads: synthesize (points), calibrate (image, K, T_radar_cam, ego_velocity, split), the raw
dataset's calib and label files where it has KITTI-layout ones (VoD, the synthetic world).
Writes (export/): radar/training/velodyne/<id>.bin (7 float32: x, y, z, RCS, v_r,
v_r_compensated, time = 0, the View-of-Delft radar layout that OpenPCDet's VoD configuration
reads), radar/training/calib/<id>.txt and label_2/<id>.txt carried over (calib generated from K and
T_radar_cam when the dataset has none), radar/ImageSets/{train,val,test}.txt, optional
pcd/<id>.pcd and preview/<id>.png (image with the points coloured by range).
Config: export.* (noise_fraction: the paper's 5% uniform noise points), radar.* (noise bounds).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from pipeline.cache import DONE
from pipeline.config import Config
from pipeline.geometry import invert_transform, project_to_image
from pipeline.stage import DatasetStage

CONFIG_KEYS = ("export.noise_fraction", "export.pcd", "export.previews", "radar.fov_az_deg", "radar.fov_el_deg",
               "radar.max_range_m", "radar.rss_min", "radar.rss_max", "radar.doppler_sign")
SPLIT_NAMES = {0: "train", 1: "val", 2: "test"}


def _source_file(data_root: str, *parts: str) -> Path | None:
    path = Path(data_root, *parts)
    return path if path.is_file() else None


def run(inputs, cfg: Config, out, fingerprint: str) -> dict:
    from pipeline.export import (add_uniform_noise, kitti_calib_text, preview_png, vod_points, write_image_sets,
                                 write_kitti_layout, write_pcd)

    syn, calib = inputs.store("synthesize"), inputs.store("calibrate")
    done = np.flatnonzero(syn.status() == DONE)
    split = np.asarray(calib.array("split")[:])
    root = Path(out.path)
    radar_root = root / "radar"
    lists: dict[str, list[str]] = {name: [] for name in SPLIT_NAMES.values()}
    n_points = n_noise = 0
    for i in tqdm(done, desc="export", unit="frame", disable=not inputs.progress):
        i = int(i)
        fid = inputs.frame_ids[i]
        f = inputs.frame(i)
        pts = syn.read("points", i)
        ego = f.get("calibrate", "ego_velocity")
        rows = vod_points(pts[:, :3], pts[:, 7], pts[:, 8], ego)
        if cfg.export.noise_fraction > 0:
            r = cfg.radar
            before = len(rows)
            rows = add_uniform_noise(rows, cfg.export.noise_fraction, f.rng(cfg.synth.seed, 31),
                                     fov_az_deg=r.fov_az_deg, fov_el_deg=r.fov_el_deg, max_range_m=r.max_range_m,
                                     rss_range=(r.rss_min, r.rss_max), doppler_range_mps=(-15.0, 15.0),
                                     ego_velocity_D=ego)
            n_noise += len(rows) - before
        K, T_radar_cam = f.get("calibrate", "K"), f.get("calibrate", "T_radar_cam")
        T_cam_radar = invert_transform(T_radar_cam)
        calib_src = _source_file(inputs.env.data_root, "radar", "training", "calib", f"{fid}.txt")
        label_src = _source_file(inputs.env.data_root, "lidar", "training", "label_2", f"{fid}.txt")
        write_kitti_layout(radar_root, fid, rows,
                           calib=calib_src or kitti_calib_text(np.column_stack([K, np.zeros(3)]), T_cam_radar),
                           label=label_src)
        if cfg.export.pcd:
            write_pcd(root / "pcd" / f"{fid}.pcd", pts[:, :3], pts[:, 7], pts[:, 6])
        if cfg.export.previews:
            image = f.get("calibrate", "image")
            uv, _, valid = project_to_image(pts[:, :3], K, T_cam_radar, (image.shape[1], image.shape[0]))
            preview_png(root / "preview" / f"{fid}.png", image, uv[valid], pts[valid, 3], cfg.radar.max_range_m)
        lists[SPLIT_NAMES.get(int(split[i]), "test")].append(fid)
        n_points += len(pts)
    write_image_sets(radar_root, lists)
    return {"frames": int(len(done)), "points": int(n_points), "noise_points": int(n_noise), "output": str(root),
            "message": f"exported {len(done)} frame(s), {n_points} points (+{n_noise} noise) to {root}"}


STAGE = DatasetStage(name="export", upstream=("calibrate", "synthesize"), config_keys=CONFIG_KEYS, run=run,
                     doc=__doc__)
