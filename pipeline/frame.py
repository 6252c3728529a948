"""The typed frame record every reader returns, and the shape-check helper used at boundaries.

Conventions (all readers convert to these):
- Radar frame {D}: x forward, y left, z up, metres. Azimuth theta = atan2(y, x), positive to the
  left; elevation phi = asin(z / r), positive up.
- Camera frame {C}: x right, y down, z forward (OpenCV). Pixel (u, v): u to the right, v down,
  integer values at pixel centres.
- Internal Doppler convention: range rate in m/s, positive when the target recedes, negative when
  it approaches (View-of-Delft's v_r). A radar that aliases reports values wrapped into its
  unambiguous span; readers keep them wrapped (they convert the sign only).
- Ego velocity ``ego_velocity_D``: velocity of the radar relative to the static world, expressed in
  {D}, m/s. For a static point with unit direction u (in {D}) the range rate is -(u . v).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

RADAR_COLUMNS = ("x_m", "y_m", "z_m", "doppler_mps", "rss")
"""Columns of ``FrameRecord.radar_D``: position in {D} (m), range rate (m/s), signal strength."""


def check_shape(name: str, array: np.ndarray, shape: tuple[int | None, ...]) -> np.ndarray:
    """Raise ValueError unless ``array`` has ``shape`` (None matches any length).

    Returns the array so that it can be used inline.
    """
    array = np.asarray(array)
    if array.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, array.shape)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name}: expected shape {want}, got {tuple(array.shape)}")
    return array


def box_rotations(yaw_rad, pitch_rad, roll_rad) -> np.ndarray:
    """Rotations (..., 3, 3) R = Rz(yaw) @ Ry(pitch) @ Rx(roll), box frame -> {D}, of boxes with
    these angles (rad, arrays of one shape or scalars). Column k is the box's axis k in {D}: x along
    the length, y along the width, z along the height. With pitch = roll = 0 the entries are
    exactly cos(yaw), -sin(yaw), sin(yaw), cos(yaw), 0 and 1 (no rounding)."""
    cz, sz = np.cos(yaw_rad), np.sin(yaw_rad)
    cy, sy = np.cos(pitch_rad), np.sin(pitch_rad)
    cx, sx = np.cos(roll_rad), np.sin(roll_rad)
    return np.stack([np.stack([cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx], axis=-1),
                     np.stack([sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx], axis=-1),
                     np.stack([-sy, cy * sx, cy * cx], axis=-1)], axis=-2).astype(np.float64)


def to_box_frame(offsets_D: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """(N, 3) m: offsets (N, 3) in {D} from a box's centre, in the box's frame (``offsets_D @
    rotation``, ``rotation`` (3, 3) as :func:`box_rotations` gives it, or (N, 3, 3): each offset's
    own box, the same values). Written out term by term, not through BLAS, so that an upright box
    gives the bits of cos/sin(yaw) alone."""
    d, r = offsets_D, rotation
    return np.stack([r[..., 0, k] * d[:, 0] + r[..., 1, k] * d[:, 1] + r[..., 2, k] * d[:, 2] for k in range(3)],
                    axis=1)


def from_box_frame(local: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """(..., 3) m: offsets (..., 3) in a box's frame, in {D} (``rotation @ local``, the inverse of
    :func:`to_box_frame`), written out term by term as it is. ``rotation`` (3, 3) for one box, or
    (..., 3, 3) broadcasting against ``local``'s leading axes (several boxes at once: offsets
    (B, F, 3) with rotations (B, 1, 3, 3))."""
    p, r = local, rotation
    return np.stack([r[..., k, 0] * p[..., 0] + r[..., k, 1] * p[..., 1] + r[..., k, 2] * p[..., 2]
                     for k in range(3)], axis=-1)


@dataclass
class Object3D:
    """One annotated object, expressed in the radar frame {D}.

    ``center_D`` (3,) m: box centre. ``size_lwh_m`` (3,): length (along heading), width, height.
    ``yaw_rad``: heading about the z axis of {D}, 0 = pointing along +x, positive to the left.
    ``pitch_rad``, ``roll_rad``: the box's tilt, 0 for a box upright in {D}. Only the Astyx reader
    sets them (its boxes are upright in its lidar's frame, 4.2 deg from {D}'s z); the others read
    their boxes upright in {D} (View-of-Delft's are upright in its lidar's frame too, whose z is
    0.5 deg from {D}'s in vod_example, 2026-12-06: kept upright in {D}). The box's orientation is
    ``rotation`` = Rz(yaw) @ Ry(pitch) @ Rx(roll), box frame -> {D} (:func:`box_rotations`), so
    that ``yaw_rad`` is the heading of the box's length axis projected on the x-y plane of {D}.
    ``velocity_D`` (3,) m/s over ground in {D}; NaN where unknown.
    ``track_id``: identity across frames, -1 where the dataset has none.
    """

    class_name: str
    center_D: np.ndarray
    size_lwh_m: np.ndarray
    yaw_rad: float
    track_id: int = -1
    velocity_D: np.ndarray = field(default_factory=lambda: np.full(3, np.nan, np.float32))
    pitch_rad: float = 0.0
    roll_rad: float = 0.0

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) box frame -> {D}, :func:`box_rotations` of the box's yaw, pitch and roll."""
        return box_rotations(self.yaw_rad, self.pitch_rad, self.roll_rad)


LABEL_COLUMNS = ("cx", "cy", "cz", "length", "width", "height", "yaw", "pitch", "roll", "vx", "vy", "vz", "track_id")
"""Columns of a label row (calibrate's ``labels`` array): an Object3D's centre_D, size_lwh_m,
yaw_rad, pitch_rad, roll_rad, velocity_D and track_id."""


def label_rows(labels: Sequence[Object3D]) -> np.ndarray:
    """(L, len(LABEL_COLUMNS)) float64 rows of ``labels`` in LABEL_COLUMNS order."""
    return np.array([[*o.center_D, *o.size_lwh_m, o.yaw_rad, o.pitch_rad, o.roll_rad, *o.velocity_D, o.track_id]
                     for o in labels], np.float64).reshape(-1, len(LABEL_COLUMNS))


@dataclass
class FrameRecord:
    """Everything one frame of any dataset provides, in the conventions of this module.

    image: (H, W, 3) uint8 RGB at the reader's native resolution, undistorted/rectified.
    K: (3, 3) float64 camera intrinsics for ``image``.
    lidar_D: (N, 3) float32 lidar points in {D}, metres.
    lidar_intensity: (N,) float32 reflectance/intensity, sensor units.
    radar_D: (M, 5) float32 radar points, columns RADAR_COLUMNS; (0, 5) for a dataset without
        radar (KITTI camera + lidar).
    T_radar_lidar: (4, 4) float64, maps lidar coordinates to {D}.
    T_radar_cam: (4, 4) float64, maps camera coordinates {C} to {D}.
    ego_velocity_D: (3,) float64 m/s, radar velocity relative to the static world in {D}.
    ego_velocity_known: False when the dataset records no motion for the frame (KITTI without
        ``oxts``): ``ego_velocity_D`` is then zero, and every Doppler derived from it a stopped car's.
    has_radar: False for camera + lidar datasets.
    labels: annotated objects in {D} (empty when the dataset has none).
    extras: per-radar-point side information some datasets have (synthetic world: ``object_id``
        (M,) int32, ``material`` (M,) int32; -1 for ghosts and clutter).
    counts: this frame's own counts of what its reader found or left out, under the keys of the
        reader's ``frame_counts`` (MSC-Rad4R: the radar points' axis order, the Doppler checked,
        lidar beams without a return); empty for readers that give none. Calibrate stores them
        per frame and says their sums.
    """

    frame_id: str
    sequence_id: str
    timestamp_s: float
    image: np.ndarray
    K: np.ndarray
    lidar_D: np.ndarray
    lidar_intensity: np.ndarray
    radar_D: np.ndarray
    T_radar_lidar: np.ndarray
    T_radar_cam: np.ndarray
    ego_velocity_D: np.ndarray
    has_radar: bool = True
    ego_velocity_known: bool = True
    labels: list[Object3D] = field(default_factory=list)
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)

    def validate(self) -> "FrameRecord":
        """Check shapes and dtypes; raise ValueError naming the field that is wrong."""
        check_shape("image", self.image, (None, None, 3))
        check_shape("K", self.K, (3, 3))
        check_shape("lidar_D", self.lidar_D, (None, 3))
        check_shape("lidar_intensity", self.lidar_intensity, (self.lidar_D.shape[0],))
        check_shape("radar_D", self.radar_D, (None, 5))
        check_shape("T_radar_lidar", self.T_radar_lidar, (4, 4))
        check_shape("T_radar_cam", self.T_radar_cam, (4, 4))
        check_shape("ego_velocity_D", self.ego_velocity_D, (3,))
        if self.image.dtype != np.uint8:
            raise ValueError(f"image: expected uint8, got {self.image.dtype}")
        return self
