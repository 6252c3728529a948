"""Small on-disk datasets in the exact VoD and Astyx layouts, for tests of readers and stages.

Everything is seeded and known: a radar moving along +x of {D} at ``speed_mps`` through a static
world of random points, one labelled object with a track id moving at a known velocity.
Nothing here runs at import time; the functions write only under the folder they are given.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

IMAGE_WH = (64, 48)
"""Image size (W, H) of the fixtures; tests set ``camera.full_size`` to it."""
K_FIXTURE = np.array([[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]])
R_CAM_D = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
"""Rotation {D} (x fwd, y left, z up) -> camera (x right, y down, z fwd)."""


def rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) transform from a rotation (3, 3) and a translation (3,)."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


T_CAM_RADAR = rigid(R_CAM_D, np.array([0.05, 0.3, -0.4]))
T_RADAR_LIDAR = rigid(np.eye(3), np.array([-0.5, 0.1, 0.8]))


@dataclass
class FixtureTruth:
    """What the fixture was built from: per frame ego velocity in {D}, object velocity in {D}."""

    frame_ids: list[str]
    ego_velocity_D: np.ndarray
    object_velocity_D: np.ndarray
    timestamps_s: dict[str, float] = field(default_factory=dict)


def static_radar_points(rng: np.random.Generator, n: int, ego_velocity_D: np.ndarray) -> np.ndarray:
    """(n, 7) VoD radar records of static targets in front: x y z RCS v_r v_r_comp time."""
    az = rng.uniform(-0.5, 0.5, n)
    el = rng.uniform(-0.15, 0.15, n)
    r = rng.uniform(4.0, 40.0, n)
    xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)
    u = xyz / np.linalg.norm(xyz, axis=1, keepdims=True)
    v_r = -(u @ ego_velocity_D)
    out = np.zeros((n, 7), np.float32)
    out[:, :3], out[:, 3], out[:, 4] = xyz, rng.uniform(-10, 20, n), v_r
    return out


def write_kitti_calib(path: Path, K: np.ndarray, T_cam_sensor: np.ndarray) -> None:
    """A KITTI calibration file with P0..P3 = [K | 0], R0_rect = I, Tr_velo_to_cam, empty Tr_imu_to_velo."""
    P = np.hstack([K, np.zeros((3, 1))]).ravel()
    lines = [f"P{i}: " + " ".join(f"{v:.9g}" for v in P) for i in range(4)]
    lines += ["R0_rect: 1 0 0 0 1 0 0 0 1",
              "Tr_velo_to_cam: " + " ".join(f"{v:.12g}" for v in T_cam_sensor[:3].ravel()),
              "Tr_imu_to_velo:"]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def write_image(path: Path, size_wh: tuple[int, int], seed: int = 0) -> None:
    """A random RGB image of ``size_wh`` (W, H) written with OpenCV (format from the suffix)."""
    rng = np.random.default_rng(seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), rng.integers(0, 255, (size_wh[1], size_wh[0], 3), dtype=np.uint8)):
        raise OSError(f"cannot write {path}")


def kitti_label_line(name: str, track: int, centre_D: np.ndarray, lwh: np.ndarray, yaw_D: float,
                     T_cam_radar: np.ndarray) -> str:
    """A KITTI label line (camera frame, bottom centre, rotation_y) of a box given in {D}."""
    centre_cam = T_cam_radar[:3, :3] @ centre_D + T_cam_radar[:3, 3]
    bottom = centre_cam + np.array([0.0, lwh[2] / 2.0, 0.0])
    heading_cam = T_cam_radar[:3, :3] @ np.array([np.cos(yaw_D), np.sin(yaw_D), 0.0])
    ry = float(np.arctan2(-heading_cam[2], heading_cam[0]))
    vals = [0, 0.0, 10, 10, 20, 20, lwh[2], lwh[1], lwh[0], *bottom, ry]
    return f"{name} {track} " + " ".join(f"{v:.9g}" for v in vals) + " 1"


def make_vod_dataset(root: Path, n_frames: int = 3, first: int = 10, speed_mps: float = 5.0,
                     object_velocity_D: tuple[float, float, float] = (1.0, 0.5, 0.0),
                     image_ext: str = ".jpg", with_poses: bool = True, n_radar: int = 60,
                     seed: int = 0) -> FixtureTruth:
    """Write a VoD-layout dataset of consecutive frames ``first..first+n_frames-1`` under ``root``.

    The radar moves along +x of {D} (= odometry world at t=0) at ``speed_mps``; the frame time is
    number / 10 Hz; one Car with track id 7 starts at (15, -2, 0) in the world and moves at
    ``object_velocity_D`` (world = {D} axes since the ego does not rotate).
    """
    rng = np.random.default_rng(seed)
    ego = np.array([speed_mps, 0.0, 0.0])
    obj_v = np.asarray(object_velocity_D, float)
    T_cam_lidar = T_CAM_RADAR @ T_RADAR_LIDAR
    ids = [f"{n:05d}" for n in range(first, first + n_frames)]
    for i, fid in enumerate(ids):
        t = int(fid) / 10.0
        radar = static_radar_points(rng, n_radar, ego)
        radar.tofile(_mk(root / "radar/training/velodyne" / f"{fid}.bin"))
        lidar = np.concatenate([rng.uniform([2, -10, -2], [40, 10, 2], (500, 3)), rng.uniform(0, 1, (500, 1))], 1)
        lidar[:, :3] = (lidar[:, :3] - T_RADAR_LIDAR[:3, 3]) @ T_RADAR_LIDAR[:3, :3]
        lidar.astype(np.float32).tofile(_mk(root / "lidar/training/velodyne" / f"{fid}.bin"))
        write_kitti_calib(root / "radar/training/calib" / f"{fid}.txt", K_FIXTURE, T_CAM_RADAR)
        write_kitti_calib(root / "lidar/training/calib" / f"{fid}.txt", K_FIXTURE, T_cam_lidar)
        write_image(root / "lidar/training/image_2" / f"{fid}{image_ext}", IMAGE_WH, seed=i)
        ego_x = speed_mps * (t - int(first) / 10.0)
        centre_D = np.array([15.0, -2.0, 0.0]) + obj_v * (t - first / 10.0) - np.array([ego_x, 0, 0])
        line = kitti_label_line("Car", 7, centre_D, np.array([4.0, 1.8, 1.5]), 0.2, T_CAM_RADAR)
        _mk(root / "lidar/training/label_2" / f"{fid}.txt").write_text(line + "\n")
        if with_poses:
            T_world_cam = rigid(np.eye(3), np.array([ego_x, 0.0, 0.0])) @ np.linalg.inv(T_CAM_RADAR)
            write_pose(root / "lidar/training/pose" / f"{fid}.json", T_world_cam)
    return FixtureTruth(ids, ego, obj_v, {f: int(f) / 10.0 for f in ids})


def write_pose(path: Path, T_world_cam: np.ndarray, timestamp_s: float | None = None) -> None:
    """VoD pose JSON lines (odomToCamera, mapToCamera, UTMToCamera; optional timestamp line)."""
    flat = [float(v) for v in T_world_cam.ravel()]
    lines = [json.dumps({"odomToCamera": flat}), json.dumps({"mapToCamera": flat}),
             json.dumps({"UTMToCamera": flat})]
    if timestamp_s is not None:
        lines.append(json.dumps({"timestamp": timestamp_s}))
    _mk(path).write_text("\n".join(lines) + "\n")


def _mk(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


ASTYX_SPAN_MPS = 10.3936


def make_astyx_dataset(root: Path, n_frames: int = 2, speed_mps: float = 8.0, n_radar: int = 400,
                       seed: int = 0, car_velocity_D: tuple[float, float, float] = (8.0, 0.0, 0.0),
                       times_s: Sequence[float] | None = None) -> np.ndarray:
    """Write an Astyx HiRes2019-layout dataset (frames 000000.. with ``dataset.json``) under ``root``.

    The radar moves at (speed, 0, 0) in {D}; V_r = wrap(-(range rate)) (positive approaching,
    aliased with span 10.3936 m/s) of static points; its lidar sees one static cloud of 300 points
    (in {D} at time 0: x 2-40 m, y +/-10 m, z +/-2 m). Each frame labels one car, at (15, 2, -0.5) m
    at time 0 and moving at ``car_velocity_D`` m/s over ground (by default as the ego: it stays
    where it is in {D}); frame i is at ``times_s[i]`` (default 0.1 s apart), the median of its
    lidar Timestamps. Returns the ego velocity (3,).
    """
    rng = np.random.default_rng(seed)
    ego = np.array([speed_mps, 0.0, 0.0])
    times = [0.1 * i for i in range(n_frames)] if times_s is None else list(times_s)
    T_radar_cam = np.linalg.inv(T_CAM_RADAR)
    calib = {"sensors": [
        {"sensor_uid": "radar_6455", "calib_data": {"T_to_ref_COS": np.eye(4).tolist()}},
        {"sensor_uid": "lidar_vlp16", "calib_data": {"T_to_ref_COS": T_RADAR_LIDAR.tolist()}},
        {"sensor_uid": "camera_front", "calib_data": {"T_to_ref_COS": T_radar_cam.tolist(),
                                                      "K": K_FIXTURE.tolist()}}]}
    index = {}
    world = rng.uniform([2, -10, -2], [40, 10, 2], (300, 3))   # a static lidar world, seen from the radar at time 0
    for i in range(n_frames):
        fid = f"{i:06d}"
        az = rng.uniform(-0.9, 0.9, n_radar)
        el = rng.uniform(-0.2, 0.2, n_radar)
        r = rng.uniform(3.0, 45.0, n_radar)
        xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)
        rate = -(xyz / r[:, None]) @ ego
        v_r = -(np.mod(rate + ASTYX_SPAN_MPS / 2, ASTYX_SPAN_MPS) - ASTYX_SPAN_MPS / 2)
        rows = "\n".join(f"{a:.6f} {b:.6f} {c:.6f} {d:.4f} {m:.1f}" for (a, b, c), d, m
                         in zip(xyz, v_r, rng.uniform(45, 90, n_radar)))
        _mk(root / "radar_6455" / f"{fid}.txt").write_text("\nX Y Z V_r Mag\n" + rows + "\n")
        lid = world - ego * times[i]
        stamps = round(times[i] * 1e6) + 2 * np.arange(len(lid)) - (len(lid) - 1)   # median: the frame time
        lrows = "\n".join(f"{a:.3f} {b:.3f} {c:.3f} 5 0 {t}" for (a, b, c), t in zip(lid, stamps))
        _mk(root / "lidar_vlp16" / f"{fid}.txt").write_text("X Y Z Reflectivity LaserID Timestamp \n" + lrows + "\n")
        write_image(root / "camera_front" / f"{fid}.jpg", IMAGE_WH, seed=i)
        _mk(root / "calibration" / f"{fid}.json").write_text(json.dumps(calib, indent=1))
        centre = np.array([15.0, 2.0, -0.5]) + (np.asarray(car_velocity_D) - ego) * times[i]
        gt = {"objects": [{"center3d": centre.tolist(), "dimension3d": [4.0, 1.8, 1.5], "classname": "Car",
                           "orientation_quat": [np.cos(0.25), 0.0, 0.0, np.sin(0.25)], "object_id": -1}]}
        _mk(root / "groundtruth_obj3d" / f"{fid}.json").write_text(json.dumps(gt))
        index[str(i)] = {"calibration": f"calibration/{fid}.json", "camera_front": f"camera_front/{fid}.jpg",
                         "groundtruth_obj3d": f"groundtruth_obj3d/{fid}.json",
                         "lidar_vlp16": f"lidar_vlp16/{fid}.txt", "radar_6455": f"radar_6455/{fid}.txt"}
    _mk(root / "dataset.json").write_text(json.dumps({"data": index, "dataset_type": "Astyx_HiRes"}, indent=1))
    return ego
