"""KITTI camera + lidar reader (object layout), the target the trained radar is synthesized for.

Layout under the data root (``split`` option, default ``training``):
``<split>/velodyne/ID.bin`` (4 float32: x, y, z, reflectance; Velodyne frame x fwd, y left, z up),
``<split>/image_2/ID.png``, ``<split>/calib/ID.txt`` (P2, R0_rect, Tr_velo_to_cam), optional
``<split>/label_2/ID.txt`` (KITTI labels, no track ids) and optional ``<split>/oxts/ID.txt`` (the raw
layout's OXTS line: lat lon alt roll pitch yaw vn ve vf vl vu ...).

There is no radar: ``radar_D`` is (0, 5) and ``has_radar`` False. The simulated radar's mounting is
``dataset.radar_mount_T_radar_lidar`` (row-major 4x4, lidar -> {D}).
Ego velocity: from the OXTS forward/left/up speeds (vf, vl, vu; IMU axes taken as parallel to the
Velodyne's, lever arm ignored) rotated into {D} when an oxts file is present, else zeros with
``ego_velocity_known`` False (the object layout records no motion; calibrate counts those frames).
KITTI object images are not all exactly 1242x375; images within 20 pixels of ``camera.full_size``
are cropped / zero-padded at the right and bottom (K is unchanged), larger differences are errors.
Each object frame is its own sequence; time = frame number / 10 Hz. The raw (drive) layout is not
read by this module.
"""

from __future__ import annotations

from functools import cached_property
from pathlib import Path

import numpy as np

from pipeline.config import Config
from pipeline.errors import ReaderError
from pipeline.frame import FrameRecord
from pipeline.geometry import invert_transform
from pipeline.readers.base import (DetectorFiles, Reader, check_not_empty, check_rigid, read_float32_records,
                                   read_image_rgb, require_file)
from pipeline.readers.kitti_format import (calib_matrix, camera_calib, label_to_object, parse_calib_file,
                                           parse_label_file)

SIZE_TOLERANCE_PX = 20


class KittiReader(Reader):
    """KITTI object layout (camera + Velodyne, no radar); see the module docstring."""

    name = "kitti"
    version = 2
    """2: labels taken in the rectified camera 0 (KITTI's label frame), not camera 2 (6 cm apart)."""

    def __init__(self, cfg: Config, data_root: str | Path, split: str = "training") -> None:
        super().__init__(cfg, data_root)
        self.base = self.root / split

    def detector_files(self, frame_id: str) -> DetectorFiles:
        """KITTI's own calib with the simulated radar in the Velodyne's place (Tr_velo_to_cam maps
        {D} to camera 0: Tr_velo_to_cam @ T_lidar_radar; Tr_imu_to_velo ends in {D} too), so that
        KITTI's labels (rectified camera 0) are carried over as they are; the label file; the image
        file where the reader uses it as it is (not padded or cropped to camera.full_size)."""
        path = self._path("calib", frame_id, ".txt")
        calib = parse_calib_file(path, frame_id)
        P2 = calib_matrix(calib, "P2", (3, 4), path, frame_id)
        T_lidar_radar = invert_transform(self.mount())
        Tr = np.eye(4)
        Tr[:3] = calib_matrix(calib, "Tr_velo_to_cam", (3, 4), path, frame_id)
        imu = np.eye(4)
        if calib.get("Tr_imu_to_velo", np.zeros(0)).size:
            imu[:3] = calib_matrix(calib, "Tr_imu_to_velo", (3, 4), path, frame_id)
        matrices = {key: calib_matrix(calib, key, (3, 4), path, frame_id) if key in calib else P2
                    for key in ("P0", "P1", "P2", "P3")}
        matrices["R0_rect"] = calib_matrix(calib, "R0_rect", (3, 3), path, frame_id) if "R0_rect" in calib else np.eye(3)
        matrices["Tr_velo_to_cam"] = (Tr @ T_lidar_radar)[:3]
        matrices["Tr_imu_to_velo"] = (invert_transform(T_lidar_radar) @ imu)[:3]
        label = self._path("label_2", frame_id, ".txt")
        image = self._path("image_2", frame_id, ".png")
        shape = read_image_rgb(image, frame_id, None).shape if image.is_file() else None
        as_is = shape is not None and (shape[1], shape[0]) == tuple(self.cfg.camera.full_size)
        return DetectorFiles(calib=matrices, label=label if label.is_file() else None, image=image if as_is else None)

    def layout_hint(self) -> str:
        split = self.base.name
        return f"{split}/velodyne/ID.bin, {split}/image_2/ID.png and {split}/calib/ID.txt"

    def _path(self, folder: str, fid: str, ext: str) -> Path:
        return self.base / folder / f"{fid}{ext}"

    @cached_property
    def _ids(self) -> list[str]:
        folder = self.base / "velodyne"
        stems = sorted(p.stem for p in folder.glob("*.bin")) if folder.is_dir() else []
        ids = []
        for fid in stems:
            needed = [self._path("image_2", fid, ".png"), self._path("calib", fid, ".txt")]
            if all(p.is_file() for p in needed):
                ids.append(fid)
            else:
                self.skip_missing(fid, [p for p in needed if not p.is_file()])
        return ids

    def frame_ids(self) -> list[str]:
        return list(self._ids)

    def sequence_of(self, frame_id: str) -> str:
        return frame_id

    def mount(self) -> np.ndarray:
        """T_radar_lidar (4, 4) from ``dataset.radar_mount_T_radar_lidar``."""
        values = np.asarray(self.cfg.dataset.radar_mount_T_radar_lidar, dtype=np.float64)
        if values.size != 16:
            raise ReaderError("dataset.radar_mount_T_radar_lidar", f"has {values.size} values, expected 16")
        return check_rigid(values.reshape(4, 4), "dataset.radar_mount_T_radar_lidar", None, "radar mount")

    def read(self, frame_id: str) -> FrameRecord:
        calib = camera_calib(self._path("calib", frame_id, ".txt"), frame_id)
        T_radar_lidar = self.mount()
        T_radar_cam = T_radar_lidar @ invert_transform(calib.T_cam_sensor)
        lidar = read_float32_records(self._path("velodyne", frame_id, ".bin"), 4, frame_id, "lidar")
        check_not_empty(lidar, self._path("velodyne", frame_id, ".bin"), frame_id, "lidar")
        image = self._image(frame_id)
        labels = []
        label_path = self._path("label_2", frame_id, ".txt")
        if label_path.is_file():
            T_radar_rect = T_radar_cam @ calib.T_cam_rect  # labels are in the rectified camera 0
            labels = [label_to_object(lab, T_radar_rect, -1) for lab in parse_label_file(label_path, frame_id)
                      if lab.class_name != "DontCare"]
        lidar_D = lidar[:, :3].astype(np.float64) @ T_radar_lidar[:3, :3].T + T_radar_lidar[:3, 3]
        ego = self._ego(frame_id, T_radar_lidar)
        record = FrameRecord(
            frame_id=frame_id, sequence_id=frame_id, timestamp_s=int(frame_id) / 10.0 if frame_id.isdigit() else 0.0,
            image=image, K=calib.K, lidar_D=lidar_D.astype(np.float32), lidar_intensity=lidar[:, 3].copy(),
            radar_D=np.zeros((0, 5), np.float32), T_radar_lidar=T_radar_lidar, T_radar_cam=T_radar_cam,
            ego_velocity_D=np.zeros(3) if ego is None else ego, ego_velocity_known=ego is not None,
            has_radar=False, labels=labels)
        return self.finish(record, self._path("velodyne", frame_id, ".bin"))

    def _image(self, fid: str) -> np.ndarray:
        path = self._path("image_2", fid, ".png")
        image = read_image_rgb(path, fid, None)
        want_w, want_h = self.cfg.camera.full_size
        h, w = image.shape[:2]
        if (w, h) == (want_w, want_h):
            return image
        if abs(w - want_w) > SIZE_TOLERANCE_PX or abs(h - want_h) > SIZE_TOLERANCE_PX:
            raise ReaderError(path, f"image is {w}x{h} pixels, expected about {want_w}x{want_h} "
                                    "(camera.full_size)", frame=fid)
        out = np.zeros((want_h, want_w, 3), np.uint8)
        out[:min(h, want_h), :min(w, want_w)] = image[:want_h, :want_w]
        self._counts["images_padded_or_cropped"] += 1
        return out

    def _ego(self, fid: str, T_radar_lidar: np.ndarray) -> np.ndarray | None:
        """Ego velocity (3,) m/s in {D} from the frame's oxts record, None without one."""
        path = self._path("oxts", fid, ".txt")
        if not path.is_file():
            self._counts["ego_velocity_unknown"] += 1
            return None
        require_file(path, fid, "oxts")
        try:
            values = np.array(path.read_text().split()[:11], dtype=np.float64)
        except ValueError:
            raise ReaderError(path, "oxts line has non-numeric values", frame=fid) from None
        if values.size < 11:
            raise ReaderError(path, f"oxts line has {values.size} values, expected at least 11", frame=fid)
        return T_radar_lidar[:3, :3] @ values[8:11]
