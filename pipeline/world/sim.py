"""Frame-by-frame simulation of one sequence: ego motion, camera, lidar, hidden radar and labels."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.world.builders import FRAME_DT_S, build_scene
from pipeline.world.camera import render_camera
from pipeline.world.lidar import LidarScan, scan_lidar
from pipeline.world.radar import RadarModel, RadarScan, radar_velocity, simulate_radar
from pipeline.world.rig import Rig, camera_directions, lidar_directions
from pipeline.world.scene import (LABELLED_CLASSES, ActorStates, Primitives, Scene, actor_states, ego_pose,
                                  ego_speed, label_poses, primitives_at)

STREAM_CAMERA, STREAM_LIDAR, STREAM_RADAR, STREAM_SCENE = 1, 2, 3, 4


@dataclass
class Label:
    """One KITTI label: camera-frame box bottom centre xyz (m), size h w l (m), rotation_y and alpha
    (rad), 2-D box (x1, y1, x2, y2) pixels, track id (the actor's object id)."""

    class_name: str
    track_id: int
    alpha: float
    bbox: tuple[float, float, float, float]
    hwl: tuple[float, float, float]
    xyz: tuple[float, float, float]
    rotation_y: float


@dataclass
class FrameData:
    """Everything simulated for one frame; transforms are (4, 4) sensor -> world {W}."""

    t_s: float
    T_world_vehicle: np.ndarray
    T_world_cam: np.ndarray
    T_world_radar: np.ndarray
    T_world_lidar: np.ndarray
    v_radar_D: np.ndarray
    ego_speed_mps: float
    states: ActorStates
    prims: Primitives
    camera: np.ndarray | None = None
    """The camera image (H, W, 3) uint8 RGB."""
    lidar: LidarScan | None = None
    radar: RadarScan | None = None
    labels: list[Label] = field(default_factory=list)


class SequenceSim:
    """Simulates the frames of one scene with one rig; ray grids are computed once."""

    def __init__(self, scene: Scene, rig: Rig, seed_key: tuple[int, ...], radar_model: RadarModel | None = None,
                 noise: bool = True) -> None:
        self.scene = scene
        self.rig = rig
        self.seed_key = tuple(int(k) for k in seed_key)
        self.radar_model = radar_model or RadarModel(noise=noise)
        self.noise = noise
        self.dirs_C = camera_directions(rig).astype(np.float32)
        self.dirs_L = lidar_directions(rig).astype(np.float32)

    def rng(self, frame: int, stream: int) -> np.random.Generator:
        """The random generator of one frame and stream (independent of evaluation order)."""
        return np.random.default_rng([*self.seed_key, frame, stream])

    def frame(self, k: int, sensors: tuple[str, ...] = ("camera", "lidar", "radar")) -> FrameData:
        """Simulate frame ``k`` (time k * 0.1 s) for the requested sensors."""
        t = k * FRAME_DT_S
        T_wv, v_w, yaw_rate = ego_pose(self.scene, t)
        rig = self.rig
        states = actor_states(self.scene, t)
        prims = primitives_at(self.scene, states)
        data = FrameData(t, T_wv, T_wv @ rig.T_vehicle_cam, T_wv @ rig.T_vehicle_radar, T_wv @ rig.T_vehicle_lidar,
                         radar_velocity(T_wv, v_w, yaw_rate, rig.T_vehicle_radar), ego_speed(self.scene, t),
                         states, prims)
        if "camera" in sensors:
            data.camera = render_camera(self.scene, prims, data.T_world_cam, rig.K, self.dirs_C,
                                        self.rng(k, STREAM_CAMERA) if self.noise else None)
            data.labels = make_labels(self.scene, states, data.T_world_cam, rig)
        if "lidar" in sensors:
            data.lidar = scan_lidar(self.scene, prims, data.T_world_lidar, rig.lidar_el_rad, rig.lidar_az_rad,
                                    self.dirs_L, self.rng(k, STREAM_LIDAR) if self.noise else None)
        if "radar" in sensors:
            data.radar = simulate_radar(self.scene, prims, states, data.T_world_radar, data.v_radar_D,
                                        self.rng(k, STREAM_RADAR), self.radar_model)
        return data


def make_sequence(scene_type: str, frames: int, rig: Rig, seed: int, seq_index: int,
                  ego_speed_mps: float | None = None, noise: bool = True,
                  radar_model: RadarModel | None = None) -> SequenceSim:
    """Build the scene of sequence ``seq_index`` of a world with ``seed`` and its simulator.

    Object ids are ``seq_index * 10000 + actor index`` (unique across the world).
    """
    rng = np.random.default_rng([seed, seq_index, STREAM_SCENE])
    scene = build_scene(scene_type, rng, frames, seq_index * 10000, ego_speed_mps)
    return SequenceSim(scene, rig, (seed, seq_index), radar_model, noise)


def make_labels(scene: Scene, states: ActorStates, T_world_cam: np.ndarray, rig: Rig) -> list[Label]:
    """KITTI labels of the labelled actors visible in the image (centre depth 1..80 m)."""
    pos_W, yaw_W = label_poses(scene, states)
    T_cw = np.linalg.inv(T_world_cam)
    w, h = rig.size_wh
    out = []
    for i, cls in enumerate(scene.actor_class):
        if cls not in LABELLED_CLASSES:
            continue
        p_C = T_cw[:3, :3] @ pos_W[i] + T_cw[:3, 3]
        if not 1.0 < p_C[2] < 80.0:
            continue
        l_, w_, h_ = scene.size_lwh_m[i]
        corners = _label_corners(pos_W[i], yaw_W[i], (l_, w_, h_)) @ T_cw[:3, :3].T + T_cw[:3, 3]
        front = corners[corners[:, 2] > 0.1]
        uv = front[:, :2] / front[:, 2:3] * [rig.K[0, 0], rig.K[1, 1]] + rig.K[:2, 2]
        x1, y1 = np.clip(uv.min(axis=0), 0, [w - 1, h - 1])
        x2, y2 = np.clip(uv.max(axis=0), 0, [w - 1, h - 1])
        if x2 - x1 < 2 or y2 - y1 < 2:
            continue
        d_C = T_cw[:3, :3] @ np.array([np.cos(yaw_W[i]), np.sin(yaw_W[i]), 0.0])
        ry = float(np.arctan2(-d_C[2], d_C[0]))
        alpha = float(np.angle(np.exp(1j * (ry - np.arctan2(p_C[0], p_C[2])))))
        out.append(Label(cls, int(scene.object_id[i]), alpha, (float(x1), float(y1), float(x2), float(y2)),
                         (float(h_), float(w_), float(l_)), tuple(float(v) for v in p_C), ry))
    return out


def _label_corners(bottom_W: np.ndarray, yaw: float, lwh: tuple[float, float, float]) -> np.ndarray:
    """Corners (8, 3) in {W} of an upright box with bottom centre ``bottom_W``."""
    l_, w_, h_ = lwh
    x = np.array([1, 1, 1, 1, -1, -1, -1, -1]) * l_ / 2
    y = np.array([1, -1, 1, -1, 1, -1, 1, -1]) * w_ / 2
    z = np.array([0, 0, 1, 1, 0, 0, 1, 1]) * h_
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([bottom_W[0] + c * x - s * y, bottom_W[1] + s * x + c * y, bottom_W[2] + z], axis=1)
