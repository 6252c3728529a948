"""Writing simulated frames in the View-of-Delft (KITTI) on-disk layout.

    lidar/training/{image_2/NNNNN.png, velodyne/NNNNN.bin (x y z reflectance float32, {L}),
                    calib/NNNNN.txt (Tr_velo_to_cam = lidar -> camera), pose/NNNNN.json,
                    label_2/NNNNN.txt (KITTI, track id in the 2nd column)}
    radar/training/{image_2/NNNNN.png, velodyne/NNNNN.bin (x y z RCS v_r v_r_compensated time,
                    float32, {D}), calib/NNNNN.txt (Tr_velo_to_cam = radar -> camera),
                    pose/NNNNN.json, meta/NNNNN.bin (int32 pairs object_id, material_id)}
    ImageSets/{full.txt, sequences.txt}, world.json (written last by generate()).

Text formats copy VoD's: calib keys P0..P3, R0_rect, Tr_velo_to_cam, an empty ``Tr_imu_to_velo:``;
poses are three JSON lines (odomToCamera, mapToCamera, UTMToCamera; row-major 4x4, camera -> world).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from pipeline.world.rig import Rig
from pipeline.world.sim import FrameData, Label

SUBDIRS = ("lidar/training/image_2", "lidar/training/velodyne", "lidar/training/calib", "lidar/training/pose",
           "lidar/training/label_2", "radar/training/image_2", "radar/training/velodyne", "radar/training/calib",
           "radar/training/pose", "radar/training/meta", "ImageSets")


def make_dirs(root: Path) -> None:
    """Create the layout's folders under ``root``."""
    for sub in SUBDIRS:
        (root / sub).mkdir(parents=True, exist_ok=True)


def _numbers(values: np.ndarray) -> str:
    return " ".join(repr(float(v)) for v in np.asarray(values, np.float64).reshape(-1))


def calib_text(K: np.ndarray, T_cam_sensor: np.ndarray) -> str:
    """A VoD/KITTI calibration file: P0..P3 = [K | 0], R0_rect = I, Tr_velo_to_cam = T_cam_sensor[:3]."""
    P = np.concatenate([K, np.zeros((3, 1))], axis=1)
    lines = [f"P{i}: {_numbers(P)}" for i in range(4)]
    lines.append(f"R0_rect: {_numbers(np.eye(3))}")
    lines.append(f"Tr_velo_to_cam: {_numbers(T_cam_sensor[:3, :4])}")
    lines.append("Tr_imu_to_velo: ")
    return "\n".join(lines) + "\n"


def pose_text(T_world_cam: np.ndarray, T_map_world: np.ndarray, T_utm_map: np.ndarray) -> str:
    """Three JSON lines of camera -> odom/map/UTM transforms (row-major 4x4)."""
    T_map_cam = T_map_world @ T_world_cam
    rows = (("odomToCamera", T_world_cam), ("mapToCamera", T_map_cam), ("UTMToCamera", T_utm_map @ T_map_cam))
    return "\n".join(json.dumps({k: [float(v) for v in T.reshape(-1)]}) for k, T in rows)


def label_text(labels: list[Label]) -> str:
    """KITTI label lines: class track_id occluded alpha x1 y1 x2 y2 h w l x y z rotation_y score."""
    out = []
    for lb in labels:
        out.append(f"{lb.class_name} {lb.track_id} 0 {lb.alpha:.6f} "
                   + " ".join(f"{v:.2f}" for v in lb.bbox) + " "
                   + " ".join(f"{v:.6f}" for v in (*lb.hwl, *lb.xyz, lb.rotation_y)) + " 1")
    return "".join(line + "\n" for line in out)


def radar_array(data: FrameData) -> np.ndarray:
    """(M, 7) float32 VoD radar points: x y z RCS v_r v_r_compensated time(=0).

    v_r_compensated = v_r + u . v_radar with u the unit direction of the written (float32) point,
    so v_r - v_r_compensated = -(u . v_radar) holds per point and the ego velocity is recoverable.
    """
    scan = data.radar
    xyz = scan.points_D.astype(np.float32)
    u = xyz.astype(np.float64)
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
    v_r = scan.doppler_mps.astype(np.float32).astype(np.float64)
    out = np.zeros((len(xyz), 7), np.float32)
    out[:, :3] = xyz
    out[:, 3] = scan.rss_db
    out[:, 4] = v_r
    out[:, 5] = v_r + u @ data.v_radar_D
    return out


def write_png(path: Path, image_rgb: np.ndarray) -> None:
    """Lossless PNG of an (H, W, 3) uint8 RGB image."""
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image_rgb[..., ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    path.write_bytes(buf.tobytes())


def _link_or_copy(src: Path, dst: Path) -> None:
    if dst.exists():
        dst.unlink()
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def write_frame(root: Path, frame_id: str, data: FrameData, rig: Rig, T_map_world: np.ndarray,
                T_utm_map: np.ndarray) -> None:
    """Write every file of one frame (all sensors must have been simulated)."""
    lid, rad = root / "lidar" / "training", root / "radar" / "training"
    write_png(lid / "image_2" / f"{frame_id}.png", data.camera)
    _link_or_copy(lid / "image_2" / f"{frame_id}.png", rad / "image_2" / f"{frame_id}.png")
    lidar = np.concatenate([data.lidar.points_L, data.lidar.reflectance[:, None]], axis=1).astype(np.float32)
    (lid / "velodyne" / f"{frame_id}.bin").write_bytes(lidar.tobytes())
    (rad / "velodyne" / f"{frame_id}.bin").write_bytes(radar_array(data).tobytes())
    meta = np.stack([data.radar.object_id, data.radar.material], axis=1).astype(np.int32)
    (rad / "meta" / f"{frame_id}.bin").write_bytes(meta.tobytes())
    (lid / "calib" / f"{frame_id}.txt").write_text(calib_text(rig.K, rig.T_cam_lidar))
    (rad / "calib" / f"{frame_id}.txt").write_text(calib_text(rig.K, rig.T_cam_radar))
    pose = pose_text(data.T_world_cam, T_map_world, T_utm_map)
    (lid / "pose" / f"{frame_id}.json").write_text(pose)
    (rad / "pose" / f"{frame_id}.json").write_text(pose)
    (lid / "label_2" / f"{frame_id}.txt").write_text(label_text(data.labels))
