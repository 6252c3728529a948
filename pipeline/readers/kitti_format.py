"""KITTI text formats shared by the VoD, synthetic and KITTI readers: calibration and labels.

Calibration files hold ``key: numbers`` lines (``P0..P3`` 3x4, ``R0_rect`` 3x3, ``Tr_velo_to_cam``
3x4, possibly ``Tr_imu_to_velo:`` with no numbers). They are parsed by key, never by line number.
Labels are KITTI object lines in the rectified camera frame: class, (track id | truncation),
occlusion, alpha, 2D box (4), h w l (m), x y z of the box's bottom centre (m), rotation_y (rad)
[, score].
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import ReaderError
from pipeline.frame import Object3D
from pipeline.readers.base import check_intrinsics, check_rigid, require_file


def parse_calib_file(path: Path, frame: str | None) -> dict[str, np.ndarray]:
    """Parse a KITTI calibration text file -> {key: 1-D float64 array} (keys without numbers are kept empty)."""
    require_file(path, frame, "calibration")
    out: dict[str, np.ndarray] = {}
    for line_no, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        if not line.strip():
            continue
        if ":" not in line:
            raise ReaderError(path, f"line {line_no} is not 'key: values': {line.strip()[:40]!r}", frame=frame)
        key, values = line.split(":", 1)
        if key.strip() in out:  # two values for one key: which one is meant cannot be known
            raise ReaderError(path, f"calibration key '{key.strip()}' appears twice (line {line_no})", frame=frame)
        try:
            out[key.strip()] = np.array([float(v) for v in values.split()], dtype=np.float64)
        except ValueError:
            raise ReaderError(path, f"malformed calibration values for key '{key.strip()}' "
                                    f"(line {line_no})", frame=frame) from None
    return out


def calib_matrix(calib: dict[str, np.ndarray], key: str, shape: tuple[int, int], path: Path,
                 frame: str | None) -> np.ndarray:
    """The matrix of ``key`` reshaped to ``shape`` (row-major); ReaderError if missing or wrong length."""
    if key not in calib:
        raise ReaderError(path, f"calibration key '{key}' is missing", frame=frame)
    values = calib[key]
    if values.size != shape[0] * shape[1]:
        raise ReaderError(path, f"calibration key '{key}' has {values.size} values, expected "
                                f"{shape[0] * shape[1]}", frame=frame)
    if not np.all(np.isfinite(values)):
        raise ReaderError(path, f"calibration key '{key}' has non-finite values", frame=frame)
    return values.reshape(shape)


@dataclass(frozen=True)
class CameraCalib:
    """Intrinsics ``K`` (3, 3), ``T_cam_sensor`` (4, 4): sensor -> rectified camera-2 frame, and
    ``T_cam_rect`` (4, 4): the rectified reference camera (camera 0, the frame of KITTI labels) ->
    rectified camera 2, the translation K^-1 P2[:, 3] (identity where P2 has no 4th column, as in
    View-of-Delft)."""

    K: np.ndarray
    T_cam_sensor: np.ndarray
    T_cam_rect: np.ndarray


def camera_calib(path: Path, frame: str | None) -> CameraCalib:
    """K and T_cam_sensor from P2, R0_rect and Tr_velo_to_cam of one KITTI calibration file.

    P2 = K [I | K^-1 P2[:, 3]] (the 4th column is a translation of the rectified camera 2);
    T_cam_sensor = [I | K^-1 P2[:, 3]] @ R0_rect @ Tr_velo_to_cam.
    """
    calib = parse_calib_file(path, frame)
    P2 = calib_matrix(calib, "P2", (3, 4), path, frame)
    K = check_intrinsics(P2[:, :3], path, frame)
    R0 = np.eye(4)
    R0[:3, :3] = calib_matrix(calib, "R0_rect", (3, 3), path, frame) if "R0_rect" in calib else np.eye(3)
    Tr = np.eye(4)
    Tr[:3, :] = calib_matrix(calib, "Tr_velo_to_cam", (3, 4), path, frame)
    check_rigid(Tr, path, frame, "Tr_velo_to_cam")
    check_rigid(R0, path, frame, "R0_rect")
    offset = np.eye(4)
    offset[:3, 3] = np.linalg.solve(K, P2[:, 3])
    return CameraCalib(K=K, T_cam_sensor=offset @ R0 @ Tr, T_cam_rect=offset)


@dataclass(frozen=True)
class KittiLabel:
    """One KITTI label line in the camera frame (bottom-centre location, rotation_y about camera y)."""

    class_name: str
    column2: int
    size_hwl_m: np.ndarray
    location_cam: np.ndarray
    rotation_y: float


def parse_label_file(path: Path, frame: str | None) -> list[KittiLabel]:
    """Parse a KITTI label file (15 or 16 columns per line); ReaderError on a malformed line or a
    negative box size (h, w, l m; ``DontCare`` lines, which KITTI writes with -1, excepted)."""
    labels = []
    for line_no, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) not in (15, 16):
            raise ReaderError(path, f"label line {line_no} has {len(parts)} columns, expected 15 or 16", frame=frame)
        try:
            values = np.array([float(v) for v in parts[1:15]], dtype=np.float64)
        except ValueError:
            raise ReaderError(path, f"label line {line_no} has non-numeric values", frame=frame) from None
        if not np.all(np.isfinite(values)):
            raise ReaderError(path, f"label line {line_no} has non-finite values", frame=frame)
        negative = np.flatnonzero(values[7:10] < 0)
        if len(negative) and parts[0] != "DontCare":  # KITTI writes DontCare boxes with -1 sizes
            axis = negative[0]
            raise ReaderError(path, f"label line {line_no} has a negative box {'hwl'[axis]} ({values[7 + axis]:g} m)",
                              frame=frame)
        labels.append(KittiLabel(parts[0], int(values[0]), values[7:10], values[10:13], float(values[13])))
    return labels


def label_to_object(label: KittiLabel, T_radar_cam: np.ndarray, track_id: int) -> Object3D:
    """Convert a camera-frame KITTI label to an Object3D in {D}; ``T_radar_cam`` maps the label's
    frame, the rectified reference camera (``T_radar_cam2 @ CameraCalib.T_cam_rect``), to {D}.

    The box centre is the bottom centre raised by h/2 (camera y points down); the heading in the
    camera frame is (cos ry, 0, -sin ry), rotated into {D} and measured about its z axis.
    """
    h, w, l = label.size_hwl_m
    centre_cam = label.location_cam + np.array([0.0, -h / 2.0, 0.0])
    heading_cam = np.array([np.cos(label.rotation_y), 0.0, -np.sin(label.rotation_y)])
    centre_D = T_radar_cam[:3, :3] @ centre_cam + T_radar_cam[:3, 3]
    heading_D = T_radar_cam[:3, :3] @ heading_cam
    return Object3D(class_name=label.class_name, center_D=centre_D.astype(np.float64),
                    size_lwh_m=np.array([l, w, h], dtype=np.float64),
                    yaw_rad=float(np.arctan2(heading_D[1], heading_D[0])), track_id=track_id)


def lidar_box_label_to_object(label: KittiLabel, T_radar_rect: np.ndarray, T_radar_lidar: np.ndarray,
                              track_id: int) -> Object3D:
    """Convert a label of a box annotated in the lidar frame and written in KITTI's camera form (View-of-Delft)
    to an Object3D in {D}, as the View-of-Delft devkit reads it: the bottom centre ``location``
    (camera frame, mapped by ``T_radar_rect``) raised by h/2 along the lidar's z axis, the heading at
    yaw -(rotation_y + pi/2) about the lidar's z axis (``T_radar_lidar``). Where the camera is level
    with the lidar this is :func:`label_to_object`; VoD's camera is pitched about 7 deg, which moves a
    box centre about 0.06 h along the camera's axis."""
    h, w, l = label.size_hwl_m
    R_radar_lidar = T_radar_lidar[:3, :3]
    bottom_D = T_radar_rect[:3, :3] @ label.location_cam + T_radar_rect[:3, 3]
    centre_D = bottom_D + R_radar_lidar @ np.array([0.0, 0.0, h / 2.0])
    yaw_lidar = -(label.rotation_y + np.pi / 2.0)
    heading_D = R_radar_lidar @ np.array([np.cos(yaw_lidar), np.sin(yaw_lidar), 0.0])
    return Object3D(class_name=label.class_name, center_D=centre_D.astype(np.float64),
                    size_lwh_m=np.array([l, w, h], dtype=np.float64),
                    yaw_rad=float(np.arctan2(heading_D[1], heading_D[0])), track_id=track_id)
