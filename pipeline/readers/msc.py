"""MSC-Rad4R reader: the extracted-folder layout and the ROS1 bag layout (``MscReader.open`` picks).

VERIFIED ONLY AGAINST DOCUMENTATION (no real MSC-Rad4R file was available; the tests build fixtures
in the documented formats): folder and file names, the MATLAB-style calibration text (an
``Intrinsic`` block of 9 numbers, transposed MATLAB form accepted, a ``Radial Distortion`` line;
extrinsics as a rotation block after a line containing ``attitude`` or ``rotation`` and a
translation after ``translation``, p_cam = R p_sensor + t, metres -- values above 20 are read as
millimetres and counted), the timestamp files ``frame sec nsec``, the wheel files ``frame sec nsec
linear_velocity angular_velocity``, the bag topic names and message types, the radar's axes
(MSC-Rad4R's data page says x, y, z were changed from the Oculii's right-down-forward frame to the
lidar's forward-left-up axes; each frame's order is told from its points, :func:`radar_axes`, and
counted, and points whose distance is not their own ``range`` field are refused), which radar frame
``CALIBRATION_CAMERA_RADAR`` refers to (told from its attitude, :func:`calibration_axes`: the native
right-down-forward one or the published forward-left-up one), which field holds the Doppler
(``doppler``; ``dataset.msc_doppler_field``) and its sign (taken as range rate,
``radar.doppler_sign`` = +1), and that the radar boresight is the vehicle's forward axis (ego
velocity = (speed, 0, 0) in {D}, speed from the wheels or /vel, yaw-rate lever arm ignored).

Doppler checked against the ego motion: a third-party loader of MSC-Rad4R's bags (read, not run;
its repository unknown) reads ``power`` and ``doppler`` from /oculii_radar/point_cloud and notes
that the two are swapped. So each frame from DOPPLER_CHECK_MIN_SPEED_MPS ahead with
DOPPLER_CHECK_MIN_POINTS points compares its Doppler with a static world's range rate, -speed x /
|p| (:func:`static_doppler_shares`); read with a swapped field or a wrong sign it is refused,
naming the ``--set`` that fixes it, where another reading agrees (:meth:`MscReader._check_doppler`;
checked frames counted as ``doppler_checked``). The check only holds the reading that agrees with
the ego speed and the boresight above: slower frames are not checked, and a frame where no reading
agrees (ego-motion-compensated Doppler, say) is read as configured and counted.

What a first run on real data is to be checked by: each record counts its frame's radar axis order,
whether its Doppler was checked and agreed, its lidar beams without a return, and the axes and
units its sequence's calibration was read in (:attr:`MscReader.frame_counts`); calibrate stores
them per frame and its summary, printed under the stage's line, says their sums over the finished
frames (:meth:`MscReader.counts_summary`), e.g. "MSC-Rad4R radar points in forward-left-up axes on
1,180 of 1,180 frames, right-down-forward on 0; lidar beams without a return left out: 3,400,000",
"MSC-Rad4R radar calibration (CALIBRATION_CAMERA_RADAR) in forward-left-up axes on 0 of 1,180
frames, right-down-forward on 1,180; extrinsics read as millimetres on 0" and "MSC-Rad4R Doppler
checked against the ego motion on 1,050 of 1,180 frames: agreed on all". Of the reader's other
counts (:meth:`Reader.report`), ``pairs_dropped`` is said where a run lists the frames.

Folder layout (one sequence per root, e.g. URBAN_D0/):
``1_IMAGE/LEFT/NNNNNN.png`` + ``1_IMAGE/timestamp_image_left.txt``; ``2_LIDAR/PCD/NNNNNN.pcd`` +
``2_LIDAR/timestamp_lidar.txt``; ``3_RADAR/PCD/NNNNNN.pcd`` (fields x y z beta alpha power doppler
range recoveredSpeed denoiseFlag, read with pypcd4) + ``3_RADAR/timestamp_radar.txt``;
``4_NAVIGATION/WHEEL_LEFT.txt``, ``WHEEL_RIGHT.txt``; ``5_CALIBRATION_<SET>/`` (SET: URBAN, RURAL, ...)
with ``CALIBRATION_CAMERA.txt``, ``CALIBRATION_CAMERA_RADAR.txt``, ``CALIBRATION_CAMERA_LIDAR.txt``.
Bag layout: ``*.bag`` in the root (one sequence each; rosbags, no ROS needed) with the radar and
lidar as sensor_msgs/PointCloud2 (numpy dtypes built from each message's ``fields``), the image as
sensor_msgs/Image and /vel as geometry_msgs/TwistStamped; calibration text files as above in
``5_CALIBRATION_<SET>/``. Bag record times are used for pairing. A third-party devkit written for the
dataset (github.com/shubhendu-ranadive/mscrad4r-devkit, read 2026-12-07) agrees with these folder,
file and column names, the six-digit file numbers from 0, a calibration folder per set
(``5_CALIBRATION_{type}``) and the extrinsics' headings ("attitude of RADAR in camera coordinate",
"location of RADAR in camera coordinate": p_cam = R p + t); it projects the published radar points
through CALIBRATION_CAMERA_RADAR as they are.

Frames are the radar scans; each is paired with the nearest image and lidar scan within
``pair_tolerance_s`` (default 0.05 s); radar scans without both partners are dropped and counted
(``pairs_dropped``). Images are undistorted with OpenCV (K unchanged).
"""

from __future__ import annotations

import re
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np

from pipeline.config import Config
from pipeline.errors import ReaderError
from pipeline.frame import FrameRecord
from pipeline.geometry import invert_transform, radial_velocity
from pipeline.readers.base import (Reader, check_finite, check_intrinsics, check_not_empty, check_rigid,
                                   require_file)

R_NATIVE_D = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
"""Rotation {D} (x fwd, y left, z up) -> the radar's native right-down-forward frame."""
RANGE_TOLERANCE_M = 0.5
"""Largest median difference between |x, y, z| and the radar's own range field, metres."""
FORWARD_DOMINANCE = 2.0
"""The forward axis's median must be positive and this many times the other two medians' magnitudes."""
DOPPLER_CHECK_MIN_SPEED_MPS = 1.0
"""Ego speed from which each frame's Doppler is checked against the ego motion, m/s (MSC-Rad4R's
platform drove at 5 km/h = 1.39 m/s)."""
DOPPLER_CHECK_MIN_POINTS = 20
"""Fewest radar points a frame needs for its Doppler to be checked."""
DOPPLER_TOLERANCE_MPS = 0.5
"""A point agrees with a static world when its Doppler is within this of a static point's range rate, m/s."""
DOPPLER_LOW_SHARE, DOPPLER_HIGH_SHARE = 0.25, 0.5
"""A frame is refused when the share of agreeing points is below LOW as read and at least HIGH (and
twice the share as read) for another reading of the fields (:func:`static_doppler_shares`)."""
RADAR_TOPIC = "/oculii_radar/point_cloud"
LIDAR_TOPIC = "/ouster/points"
IMAGE_TOPIC = "/camera_array/left/image_raw"
VEL_TOPIC = "/vel"
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


def _forward_order(ahead: np.ndarray) -> str | None:
    """'rdf' or 'flu': the axis order in which the vector (3,) ``ahead``, a direction in front of
    the radar, has its forward axis: positive and FORWARD_DOMINANCE times the other two; None for
    neither order."""
    for axes, fwd, others in (("rdf", 2, [0, 1]), ("flu", 0, [1, 2])):
        if ahead[fwd] > 0 and ahead[fwd] >= FORWARD_DOMINANCE * np.max(np.abs(ahead[others])):
            return axes
    return None


def radar_axes(xyz: np.ndarray, path: Path, frame: str | None) -> str:
    """'rdf' or 'flu': the axis order of an Oculii point cloud (M, 3). The sensor's native frame is
    right-down-forward; MSC-Rad4R's data page says its x, y, z were changed to the lidar's axes
    (forward-left-up) for ROS viewing. A forward-looking radar's points lie ahead, so the forward
    axis is the one whose median is positive and dominates the other two (lateral and vertical);
    ReaderError when no axis does (the points are in neither order)."""
    med = np.median(xyz, axis=0)
    axes = _forward_order(med)
    if axes is None:
        raise ReaderError(path, f"radar points have no clear forward axis (median x, y, z = {med[0]:.2f}, "
                                f"{med[1]:.2f}, {med[2]:.2f} m): neither right-down-forward (z ahead) nor "
                                f"forward-left-up (x ahead)", frame=frame)
    return axes


def calibration_axes(R_cam_radar: np.ndarray, path: Path) -> str:
    """'rdf' or 'flu': the axis order of the radar frame whose attitude in the camera a
    ``CALIBRATION_CAMERA_RADAR`` file gives (``R_cam_radar`` (3, 3), p_cam = R p_radar + t): the
    native right-down-forward one, or the forward-left-up one MSC-Rad4R's published points use (its
    page does not say which, and a devkit projects the published points through it directly).
    Camera and radar both look ahead, so the camera's optical axis in the radar frame, R's third
    row, lies along that frame's forward axis; ReaderError when it lies along neither."""
    ahead = np.asarray(R_cam_radar, np.float64)[2]
    axes = _forward_order(ahead)
    if axes is None:
        raise ReaderError(path, f"the radar's attitude in the camera frame puts the camera's view along "
                                f"({ahead[0]:.2f}, {ahead[1]:.2f}, {ahead[2]:.2f}) in the radar's axes: neither "
                                f"right-down-forward (z ahead) nor forward-left-up (x ahead)")
    return axes


def static_doppler_shares(radar_D: np.ndarray, speed_mps: float) -> np.ndarray:
    """(4,) shares of the points of ``radar_D`` (M, 5: x, y, z m in {D}, Doppler m/s, RSS; M > 0)
    whose reading is within DOPPLER_TOLERANCE_MPS of the range rate of a static point seen from a
    radar moving at (speed_mps, 0, 0) in {D} (:func:`pipeline.geometry.radial_velocity`: -speed * x /
    |p|), for four readings of the last two columns: the Doppler as read, its opposite, the RSS
    column, its opposite; points at the origin left out. Most points of a street scene are static:
    the right reading has a large share."""
    xyz = radar_D[:, :3].astype(np.float64)
    seen = np.any(xyz != 0, axis=1)
    static_mps = radial_velocity(xyz[seen], np.array([speed_mps, 0.0, 0.0]))
    readings = radar_D[seen][:, [3, 3, 4, 4]].astype(np.float64) * np.array([1.0, -1.0, 1.0, -1.0])
    return np.mean(np.abs(readings - static_mps[:, None]) <= DOPPLER_TOLERANCE_MPS, axis=0)


# -- text formats ----------------------------------------------------------------------------------

def _numbers_after(lines: list[str], keyword: str, count: int, path: Path, start: int = 0,
                   one_line: bool = False) -> np.ndarray:
    """The first ``count`` numbers after the first line (from ``start``) containing ``keyword``."""
    pattern = re.compile(keyword, re.IGNORECASE)
    hit = next((i for i in range(start, len(lines)) if pattern.search(lines[i])), None)
    if hit is None:
        raise ReaderError(path, f"calibration block '{keyword}' is missing")
    found: list[float] = []
    for line in lines[hit + 1:]:
        numbers = _NUMBER.findall(line)
        if not numbers and found:
            break
        found += [float(v) for v in numbers]
        if len(found) >= count or (one_line and found):
            break
    if len(found) < count:
        raise ReaderError(path, f"calibration block '{keyword}' has {len(found)} numbers, expected {count}")
    return np.array(found if one_line else found[:count])


MATLAB_PIXEL_ORIGIN = 1.0
"""MATLAB's pixel coordinates put the top-left pixel's centre at (1, 1), OpenCV's (and {D}'s
projections') at (0, 0): a MATLAB principal point is this much larger (MathWorks'
cameraIntrinsicsToOpenCV subtracts it)."""


def read_camera_calibration(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(K (3, 3) in OpenCV's pixel convention, distortion (5,) k1 k2 p1 p2 k3) of the left camera
    from the MATLAB stereo export (its principal point moved by MATLAB_PIXEL_ORIGIN)."""
    lines = require_file(path, None, "camera calibration").read_text(errors="replace").splitlines()
    start = next((i for i, line in enumerate(lines) if "left" in line.lower()), 0)
    K = _numbers_after(lines, r"intrinsic", 9, path, start).reshape(3, 3)
    if np.allclose(K[:2, 2], 0) and not np.allclose(K[2, :2], 0):
        K = K.T  # MATLAB IntrinsicMatrix is the transpose of the OpenCV K
    K[:2, 2] -= MATLAB_PIXEL_ORIGIN * K[2, 2]
    radial = _numbers_after(lines, r"radial\s*distortion", 1, path, start, one_line=True)
    dist = np.zeros(5)
    dist[[0, 1, 4][:min(3, radial.size)]] = radial[:3]
    return check_intrinsics(K, path, None), dist


def read_extrinsics(path: Path) -> tuple[np.ndarray, bool]:
    """(T_cam_sensor (4, 4), translation was in millimetres) from a camera-sensor calibration file."""
    lines = require_file(path, None, "extrinsic calibration").read_text(errors="replace").splitlines()
    R = _numbers_after(lines, r"attitude|rotation", 9, path).reshape(3, 3)
    t = _numbers_after(lines, r"translation", 3, path)
    millimetres = bool(np.linalg.norm(t) > 20.0)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t / 1000.0 if millimetres else t
    return check_rigid(T, path, None, "camera extrinsics"), millimetres


def read_stamp_file(path: Path, n_values: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``frame sec nsec [values...]`` lines -> (frames (N,) int, times (N,) s, values (N, n_values))."""
    require_file(path, None, "timestamp")
    rows = [line.split() for line in path.read_text(errors="replace").splitlines() if line.strip()]
    if any(len(r) < 3 + n_values for r in rows):
        raise ReaderError(path, f"a line has fewer than {3 + n_values} values (frame sec nsec ...)")
    try:
        table = np.array([r[:3 + n_values] for r in rows], dtype=np.float64).reshape(-1, 3 + n_values)
    except ValueError:
        raise ReaderError(path, "non-numeric timestamp line") from None
    return table[:, 0].astype(np.int64), table[:, 1] + table[:, 2] * 1e-9, table[:, 3:]


def pair_nearest(ref_s: np.ndarray, other_s: np.ndarray, tolerance_s: float) -> np.ndarray:
    """Index into ``other_s`` of the nearest time to each ``ref_s`` (N,), -1 where none within tolerance."""
    if other_s.size == 0:
        return np.full(ref_s.shape, -1)
    order = np.argsort(other_s, kind="stable")
    sorted_s = other_s[order]
    pos = np.clip(np.searchsorted(sorted_s, ref_s), 1, max(len(sorted_s) - 1, 1))
    left = np.clip(pos - 1, 0, len(sorted_s) - 1)
    right = np.clip(pos, 0, len(sorted_s) - 1)
    pick = np.where(np.abs(sorted_s[left] - ref_s) <= np.abs(sorted_s[right] - ref_s), left, right)
    return np.where(np.abs(sorted_s[pick] - ref_s) <= tolerance_s, order[pick], -1)


# -- shared reader logic -----------------------------------------------------------------------------

class MscReader(Reader):
    """Common calibration, conversion and record building; use ``MscReader.open`` to get a reader."""

    name = "msc"
    version = 5
    """2 (2026-12-06): K's principal point in OpenCV's pixel convention (MATLAB_PIXEL_ORIGIN); lidar
    beams without a return (NaN or the origin in an organized scan) left out, counted in the report's
    lidar_points_without_return. 3 (2026-12-07): a radar calibration in the forward-left-up axes is
    read as such (:func:`calibration_axes`; before, every one was taken as right-down-forward). 4
    (2026-12-07): a frame whose Doppler disagrees with the ego motion where another reading of the
    fields agrees is refused (:meth:`_check_doppler`); dataset.msc_doppler_field. 5 (2026-12-07):
    each record gives its frame's counts (:attr:`frame_counts`), which calibrate stores in an
    output array of its own (reader_counts) and sums in its summary: an MSC-Rad4R calibrate output
    made before lacks that array."""
    frame_counts = ("radar_axes_flu", "radar_axes_rdf", "doppler_checked", "doppler_disagrees_with_every_reading",
                    "lidar_points_without_return", "radar_calibration_in_lidar_axes", "calibration_in_millimetres")
    """Per frame: 1 where the radar points are in the forward-left-up axes (as MSC-Rad4R's data page
    says), 1 where in the Oculii's own right-down-forward ones (:func:`radar_axes`); 1 where the
    Doppler was checked against the ego motion, 1 where it was but no reading of the fields agreed
    (:meth:`_check_doppler`); the lidar beams without a return left out; 1 where the sequence's
    CALIBRATION_CAMERA_RADAR gives the forward-left-up frame's attitude (:func:`calibration_axes`;
    0: the native one's), 1 where its extrinsics were read as millimetres (:func:`read_extrinsics`)."""

    @classmethod
    def counts_summary(cls, totals: dict[str, int], n_frames: int) -> list[str]:
        """What calibrate's summary says of the unverified assumptions (module docstring), e.g.
        'MSC-Rad4R radar points in forward-left-up axes on 1,180 of 1,180 frames, right-down-forward
        on 0; lidar beams without a return left out: 3,400,000' and a line on the Doppler check."""
        checked, none_agreed = totals["doppler_checked"], totals["doppler_disagrees_with_every_reading"]
        in_lidar_axes = totals["radar_calibration_in_lidar_axes"]
        lines = [f"MSC-Rad4R radar points in forward-left-up axes on {totals['radar_axes_flu']:,} of {n_frames:,} "
                 f"frames, right-down-forward on {totals['radar_axes_rdf']:,}; lidar beams without a return left "
                 f"out: {totals['lidar_points_without_return']:,}",
                 f"MSC-Rad4R radar calibration (CALIBRATION_CAMERA_RADAR) in forward-left-up axes on "
                 f"{in_lidar_axes:,} of {n_frames:,} frames, right-down-forward on {n_frames - in_lidar_axes:,}; "
                 f"extrinsics read as millimetres on {totals['calibration_in_millimetres']:,}"]
        if not checked:
            lines.append(f"MSC-Rad4R Doppler checked against the ego motion on none of {n_frames:,} frames (checked "
                         f"from {DOPPLER_CHECK_MIN_SPEED_MPS:g} m/s ahead and {DOPPLER_CHECK_MIN_POINTS} points): "
                         f"its field and sign are as configured, unchecked")
            return lines
        agreed = f"all but {none_agreed:,}, where no reading of the fields agreed (read as configured)" \
            if none_agreed else "all"
        lines.append(f"MSC-Rad4R Doppler checked against the ego motion on {checked:,} of {n_frames:,} frames: "
                     f"agreed on {agreed}")
        return lines

    def __init__(self, cfg: Config, data_root: str | Path, pair_tolerance_s: float = 0.05,
                 calib_dir: str | Path | None = None) -> None:
        super().__init__(cfg, data_root)
        self.tolerance_s = float(pair_tolerance_s)
        self._calib_dir = Path(calib_dir) if calib_dir else None

    @cached_property
    def calib_dir(self) -> Path:
        """The sequence's calibration folder: the one given, else its one ``5_CALIBRATION_<SET>/``
        (URBAN, RURAL, ...: each set of sequences has its own calibration)."""
        if self._calib_dir is not None:
            return self._calib_dir
        found = sorted(p for p in self.root.glob("5_CALIBRATION_*") if p.is_dir())
        if len(found) != 1:
            what = "no calibration folder" if not found else f"{len(found)} calibration folders " \
                f"({', '.join(p.name for p in found)})"
            raise ReaderError(self.root, f"{what}: an MSC-Rad4R sequence holds one 5_CALIBRATION_<SET>/ "
                                         f"(e.g. 5_CALIBRATION_URBAN/ with CALIBRATION_CAMERA.txt, "
                                         f"CALIBRATION_CAMERA_RADAR.txt and CALIBRATION_CAMERA_LIDAR.txt)")
        return found[0]

    @classmethod
    def open(cls, cfg: Config, data_root: str | Path, **options: object) -> "MscReader":
        """The folder reader if ``3_RADAR/`` exists, the bag reader if ``*.bag`` files do."""
        root = Path(data_root)
        if (root / "3_RADAR").is_dir():
            return MscFolderReader(cfg, root, **options)
        if any(root.glob("*.bag")):
            return MscBagReader(cfg, root, **options)
        raise ReaderError(root, "neither an extracted MSC-Rad4R folder (3_RADAR/) nor ROS1 bags (*.bag)")

    @cached_property
    def calibration(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(K, distortion, T_radar_cam, T_radar_lidar), {D} being the radar frame of the radar
        calibration (:func:`calibration_axes`) in forward-left-up order."""
        K, dist = read_camera_calibration(self.calib_dir / "CALIBRATION_CAMERA.txt")
        radar_file = self.calib_dir / "CALIBRATION_CAMERA_RADAR.txt"
        T_cam_calib, mm_r = read_extrinsics(radar_file)
        T_cam_lidar, mm_l = read_extrinsics(self.calib_dir / "CALIBRATION_CAMERA_LIDAR.txt")
        self._counts["extrinsics_in_millimetres"] = int(mm_r) + int(mm_l)
        axes = calibration_axes(T_cam_calib[:3, :3], radar_file)
        self._counts["radar_calibration_in_lidar_axes"] = int(axes == "flu")
        self._calibration_counts = {"radar_calibration_in_lidar_axes": int(axes == "flu"),
                                    "calibration_in_millimetres": int(mm_r or mm_l)}  # each frame's
        T_calib_D = np.eye(4)
        if axes == "rdf":
            T_calib_D[:3, :3] = R_NATIVE_D
        T_radar_cam = invert_transform(T_cam_calib @ T_calib_D)
        return K, dist, T_radar_cam, T_radar_cam @ T_cam_lidar

    @property
    def _doppler_fields(self) -> tuple[str, str]:
        """(the field read as the Doppler, the one read as the RSS): dataset.msc_doppler_field."""
        field = self.cfg.dataset.msc_doppler_field
        return field, "power" if field == "doppler" else "doppler"

    def _radar_D(self, fields: dict[str, np.ndarray], path: Path, fid: str) -> tuple[np.ndarray, str]:
        """((M, 5) float32 in {D} from the radar fields: xyz (in either axis order), radar.doppler_sign
        times the Doppler field, the RSS field (:attr:`_doppler_fields`); the points' axis order as
        read, 'rdf' or 'flu' (:func:`radar_axes`))."""
        missing = [k for k in ("x", "y", "z", "doppler", "power") if k not in fields]
        if missing:
            raise ReaderError(path, f"radar point fields {missing} are missing", frame=fid)
        doppler, rss = self._doppler_fields
        xyz = np.stack([fields["x"], fields["y"], fields["z"]], axis=1).astype(np.float64)
        out = np.column_stack([xyz, np.asarray(fields[doppler], np.float64) * self.radar.doppler_sign,
                               fields[rss]]).astype(np.float32)
        check_finite(out, path, fid, "radar")
        check_not_empty(out, path, fid, "radar")
        axes = radar_axes(xyz, path, fid)
        if axes == "rdf":
            out[:, :3] = xyz @ R_NATIVE_D  # = (R_NATIVE_D.T @ p)^T
        if "range" in fields:  # xyz must be centred on the radar, not moved into another sensor's frame
            off = float(np.median(np.abs(np.linalg.norm(xyz, axis=1) - np.asarray(fields["range"], np.float64))))
            if off > RANGE_TOLERANCE_M:
                raise ReaderError(path, f"radar x, y, z are not centred on the radar: their distance differs from "
                                        f"the range field by {off:.2f} m (median); points in another sensor's frame "
                                        "are not supported", frame=fid)
        return out, axes

    def _check_doppler(self, radar_D: np.ndarray, speed_mps: float, path: Path, fid: str) -> dict[str, int]:
        """The frame's counts doppler_checked and doppler_disagrees_with_every_reading (0 or 1 each);
        ReaderError when the frame's Doppler as read disagrees with the ego motion and another
        reading of the two fields agrees (:func:`static_doppler_shares`), naming the ``--set`` that
        fixes it. Checked from DOPPLER_CHECK_MIN_SPEED_MPS and DOPPLER_CHECK_MIN_POINTS on."""
        off_origin = np.count_nonzero(radar_D[:, :3].any(axis=1))
        if speed_mps < DOPPLER_CHECK_MIN_SPEED_MPS or off_origin < DOPPLER_CHECK_MIN_POINTS:
            return {"doppler_checked": 0, "doppler_disagrees_with_every_reading": 0}
        shares = static_doppler_shares(radar_D, speed_mps)
        best = 1 + int(np.argmax(shares[1:]))
        if shares[0] >= DOPPLER_LOW_SHARE:
            return {"doppler_checked": 1, "doppler_disagrees_with_every_reading": 0}
        if shares[best] < DOPPLER_HIGH_SHARE or shares[best] < 2 * shares[0]:
            return {"doppler_checked": 1, "doppler_disagrees_with_every_reading": 1}
        field, other = self._doppler_fields
        sign = self.radar.doppler_sign
        if best == 1:
            fix = f"--set radar.doppler_sign={-sign}"
        else:
            new_sign = 1 if best == 2 else -1
            fix = f"--set dataset.msc_doppler_field={other}" + (f" --set radar.doppler_sign={new_sign}"
                                                                 if new_sign != sign else "")
        raise ReaderError(path, f"radar Doppler disagrees with the ego motion ({speed_mps:.2f} m/s ahead): "
                                f"{shares[0]:.0%} of the points are within {DOPPLER_TOLERANCE_MPS} m/s of a static "
                                f"world's range rate as read (field '{field}', radar.doppler_sign = {sign:+d}), "
                                f"{shares[1]:.0%} with the opposite sign, {shares[2]:.0%} and {shares[3]:.0%} from "
                                f"field '{other}' with sign +1 and -1: the fields or the sign are read wrongly; "
                                f"run again with {fix}", frame=fid)

    def _record(self, fid: str, seq: str, t: float, image_bgr: np.ndarray, image_path: Path,
                lidar_xyzi: np.ndarray, lidar_path: Path, radar_D: np.ndarray, axes: str,
                speed: float, radar_path: Path) -> FrameRecord:
        """The frame's record with its counts (:attr:`frame_counts`; also added to :meth:`report`'s);
        ``radar_D`` and ``axes`` as :meth:`_radar_D` gives them."""
        K, dist, T_radar_cam, T_radar_lidar = self.calibration
        h, w = image_bgr.shape[:2]
        if (w, h) != tuple(self.cfg.camera.full_size):
            raise ReaderError(image_path, f"image is {w}x{h} pixels, expected "
                                          f"{self.cfg.camera.full_size[0]}x{self.cfg.camera.full_size[1]}", frame=fid)
        image = cv2.undistort(image_bgr, K, dist)[:, :, ::-1]
        xyz = lidar_xyzi[:, :3]
        no_return = ~np.all(np.isfinite(xyz), axis=1) | np.all(xyz == 0, axis=1)
        if no_return.any():  # an organized Ouster scan keeps its beams without a return, as NaN or (0, 0, 0)
            lidar_xyzi = lidar_xyzi[~no_return]
        check_finite(lidar_xyzi, lidar_path, fid, "lidar")
        check_not_empty(lidar_xyzi, lidar_path, fid, "lidar")
        lidar_D = lidar_xyzi[:, :3] @ T_radar_lidar[:3, :3].T + T_radar_lidar[:3, 3]
        counts = {"radar_axes_flu": int(axes == "flu"), "radar_axes_rdf": int(axes == "rdf"),
                  **self._check_doppler(radar_D, speed, radar_path, fid),
                  "lidar_points_without_return": int(no_return.sum()), **self._calibration_counts}
        record = self.finish(FrameRecord(
            frame_id=fid, sequence_id=seq, timestamp_s=t, image=np.ascontiguousarray(image), K=K,
            lidar_D=lidar_D.astype(np.float32), lidar_intensity=lidar_xyzi[:, 3].astype(np.float32),
            radar_D=radar_D, T_radar_lidar=T_radar_lidar, T_radar_cam=T_radar_cam,
            ego_velocity_D=np.array([speed, 0.0, 0.0]), has_radar=True,
            counts={k: counts[k] for k in self.frame_counts}), radar_path)
        self._counts.update({k: v for k, v in counts.items() if v and k not in self._calibration_counts})  # once
        return record


# -- extracted folders -------------------------------------------------------------------------------

def _files_by_number(folder: Path, ext: str) -> dict[int, Path]:
    return {int(p.stem): p for p in folder.glob(f"*{ext}") if p.stem.isdigit()} if folder.is_dir() else {}


def _stamp_path(folder: Path, hint: str) -> Path:
    files = sorted(folder.glob("**/timestamp*.txt"))
    preferred = [p for p in files if hint in p.name.lower()]
    if not (preferred or files):
        raise ReaderError(folder, "no timestamp*.txt file")
    return (preferred or files)[0]


def _pcd_fields(path: Path, fid: str) -> dict[str, np.ndarray]:
    from pypcd4 import PointCloud

    require_file(path, fid, "point cloud")
    try:
        cloud = PointCloud.from_path(path)
    except Exception as exc:  # pypcd4 raises several types on malformed files
        raise ReaderError(path, f"cannot parse PCD file ({type(exc).__name__}: {exc})", frame=fid) from None
    return {name: cloud.pc_data[name] for name in cloud.fields}


class MscFolderReader(MscReader):
    """MSC-Rad4R extracted folders; see the module docstring."""

    @cached_property
    def _index(self) -> dict[str, tuple[int, float, Path, Path, Path]]:
        """{frame id: (radar row, time s, radar pcd, image png, lidar pcd)}."""
        r_frames, r_times, _ = read_stamp_file(_stamp_path(self.root / "3_RADAR", "radar"))
        i_frames, i_times, _ = read_stamp_file(_stamp_path(self.root / "1_IMAGE", "left"))
        l_frames, l_times, _ = read_stamp_file(_stamp_path(self.root / "2_LIDAR", "lidar"))
        radar_files = _files_by_number(self.root / "3_RADAR" / "PCD", ".pcd")
        image_files = _files_by_number(self.root / "1_IMAGE" / "LEFT", ".png")
        lidar_files = _files_by_number(self.root / "2_LIDAR" / "PCD", ".pcd")
        img_idx = pair_nearest(r_times, i_times, self.tolerance_s)
        lid_idx = pair_nearest(r_times, l_times, self.tolerance_s)
        index = {}
        for row, (frame, t) in enumerate(zip(r_frames, r_times)):
            if img_idx[row] < 0 or lid_idx[row] < 0:
                self._counts["pairs_dropped"] += 1
                continue
            paths = (radar_files.get(int(frame)), image_files.get(int(i_frames[img_idx[row]])),
                     lidar_files.get(int(l_frames[lid_idx[row]])))
            if any(p is None for p in paths):
                wanted = (f"3_RADAR/PCD file of frame {int(frame)}", f"1_IMAGE/LEFT file of frame {int(i_frames[img_idx[row]])}",
                          f"2_LIDAR/PCD file of frame {int(l_frames[lid_idx[row]])}")
                self.skip_missing(f"{int(frame):06d}", [w for w, p in zip(wanted, paths) if p is None])
                continue
            index[f"{int(frame):06d}"] = (row, float(t), *paths)
        return index

    @cached_property
    def _stamps(self) -> np.ndarray:
        return read_stamp_file(_stamp_path(self.root / "3_RADAR", "radar"))[1]

    def frame_ids(self) -> list[str]:
        return sorted(self._index)

    def layout_hint(self) -> str:
        return ("a row of 3_RADAR/timestamp_radar.txt with its 3_RADAR/PCD/NNNNNN.pcd and, within the pairing "
                "tolerance, a 1_IMAGE/LEFT/NNNNNN.png and a 2_LIDAR/PCD/NNNNNN.pcd (their timestamp files)")

    def sequence_of(self, frame_id: str) -> str:
        return self.root.name

    def _speed(self, t: float) -> float:
        speeds = []
        for side in ("WHEEL_LEFT.txt", "WHEEL_RIGHT.txt"):
            _, times, values = read_stamp_file(self.root / "4_NAVIGATION" / side, 2)
            order = np.argsort(times)
            speeds.append(float(np.interp(t, times[order], values[order, 0])))
        return float(np.mean(speeds))

    def read(self, frame_id: str) -> FrameRecord:
        if frame_id not in self._index:
            raise ReaderError(self.root / "3_RADAR", "unknown frame id or frame without paired image/lidar",
                              frame=frame_id)
        row, t, radar_path, image_path, lidar_path = self._index[frame_id]
        if row > 0 and self._stamps[row - 1] >= t:
            raise ReaderError(_stamp_path(self.root / "3_RADAR", "radar"), f"non-monotonic timestamps: "
                              f"{t:.6f} s is not after the previous scan ({self._stamps[row - 1]:.6f} s)", frame=frame_id)
        radar_D, axes = self._radar_D(_pcd_fields(radar_path, frame_id), radar_path, frame_id)
        lidar = _pcd_fields(lidar_path, frame_id)
        intensity = lidar.get("intensity", lidar.get("reflectivity", np.zeros_like(lidar["x"])))
        lidar_xyzi = np.stack([lidar["x"], lidar["y"], lidar["z"], intensity], axis=1).astype(np.float64)
        image = cv2.imread(str(require_file(image_path, frame_id, "image")), cv2.IMREAD_COLOR)
        if image is None:
            raise ReaderError(image_path, "image cannot be decoded (corrupt or not an image)", frame=frame_id)
        return self._record(frame_id, self.root.name, t, image, image_path, lidar_xyzi, lidar_path, radar_D, axes,
                            self._speed(t), radar_path)


# -- ROS1 bags -----------------------------------------------------------------------------------

_PC2_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def pointcloud2_fields(msg: object) -> dict[str, np.ndarray]:
    """sensor_msgs/PointCloud2 -> {field name: (N,) array}, dtype built from the message's fields."""
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for f in msg.fields:
        if f.datatype not in _PC2_TYPES:
            raise ValueError(f"unsupported PointField datatype {f.datatype} for '{f.name}'")
        names.append(f.name)
        formats.append((order + _PC2_TYPES[f.datatype], (f.count,)) if f.count > 1 else order + _PC2_TYPES[f.datatype])
        offsets.append(f.offset)
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": msg.point_step})
    n = msg.width * msg.height
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    if msg.row_step * msg.height > data.size or msg.point_step * msg.width > msg.row_step:
        raise ValueError(f"data has {data.size} bytes, too few for {n} points of {msg.point_step} bytes")
    rows = data[:msg.row_step * msg.height].reshape(msg.height, msg.row_step)[:, :msg.point_step * msg.width]
    points = np.frombuffer(np.ascontiguousarray(rows).tobytes(), dtype=dtype, count=n)
    return {name: points[name].astype(np.float64) for name in names}


def image_msg_to_bgr(msg: object) -> np.ndarray:
    """sensor_msgs/Image (rgb8, bgr8, mono8, bayer_*8) -> (H, W, 3) uint8 BGR."""
    raw = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    channels = {"rgb8": 3, "bgr8": 3, "mono8": 1}.get(msg.encoding, 1 if msg.encoding.startswith("bayer") else 0)
    if channels == 0:
        raise ValueError(f"unsupported image encoding '{msg.encoding}'")
    image = raw[:msg.step * msg.height].reshape(msg.height, msg.step)[:, :msg.width * channels]
    image = image.reshape(msg.height, msg.width, channels)
    if msg.encoding == "rgb8":
        return np.ascontiguousarray(image[:, :, ::-1])
    if msg.encoding == "bgr8":
        return np.ascontiguousarray(image)
    if msg.encoding == "mono8":
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    codes = {"bayer_rggb8": cv2.COLOR_BayerRG2BGR, "bayer_bggr8": cv2.COLOR_BayerBG2BGR,
             "bayer_gbrg8": cv2.COLOR_BayerGB2BGR, "bayer_grbg8": cv2.COLOR_BayerGR2BGR}
    if msg.encoding not in codes:
        raise ValueError(f"unsupported image encoding '{msg.encoding}'")
    return cv2.cvtColor(image[:, :, 0], codes[msg.encoding])


class MscBagReader(MscReader):
    """MSC-Rad4R ROS1 bags read with rosbags; see the module docstring."""

    def __init__(self, cfg: Config, data_root: str | Path, pair_tolerance_s: float = 0.05,
                 calib_dir: str | Path | None = None, radar_topic: str = RADAR_TOPIC,
                 lidar_topic: str = LIDAR_TOPIC, image_topic: str = IMAGE_TOPIC, vel_topic: str = VEL_TOPIC) -> None:
        super().__init__(cfg, data_root, pair_tolerance_s, calib_dir)
        self.topics = {"radar": radar_topic, "lidar": lidar_topic, "image": image_topic, "vel": vel_topic}

    @cached_property
    def _typestore(self):
        from rosbags.typesys import Stores, get_typestore
        return get_typestore(Stores.ROS1_NOETIC)

    def _messages(self, bag: Path, topic: str, start: int | None = None, stop: int | None = None):
        from rosbags.rosbag1 import Reader as BagReader

        with BagReader(bag) as reader:
            conns = [c for c in reader.connections if c.topic == topic]
            for conn, stamp, raw in reader.messages(connections=conns, start=start, stop=stop):
                yield stamp, self._typestore.deserialize_ros1(raw, conn.msgtype)

    def _stamps(self, bag: Path, topic: str) -> np.ndarray:
        from rosbags.rosbag1 import Reader as BagReader

        with BagReader(bag) as reader:
            conns = [c for c in reader.connections if c.topic == topic]
            return np.array([stamp for _, stamp, _ in reader.messages(connections=conns)], dtype=np.int64)

    @cached_property
    def _index(self) -> dict[str, tuple[Path, int, int, int, float, np.ndarray, np.ndarray]]:
        """{frame id: (bag, radar ns, image ns, lidar ns, time s, vel times s, vel speeds)}."""
        index = {}
        for bag in sorted(self.root.glob("*.bag")):
            radar, image, lidar = (self._stamps(bag, self.topics[k]) for k in ("radar", "image", "lidar"))
            vel = [(s * 1e-9, float(np.linalg.norm([m.twist.linear.x, m.twist.linear.y, m.twist.linear.z])))
                   for s, m in self._messages(bag, self.topics["vel"])]
            vel_t, vel_v = (np.array(c, dtype=np.float64) for c in zip(*vel)) if vel else (np.zeros(0), np.zeros(0))
            img_idx = pair_nearest(radar * 1e-9, image * 1e-9, self.tolerance_s)
            lid_idx = pair_nearest(radar * 1e-9, lidar * 1e-9, self.tolerance_s)
            for k, stamp in enumerate(radar):
                if img_idx[k] < 0 or lid_idx[k] < 0 or vel_t.size == 0:
                    self._counts["pairs_dropped"] += 1
                    continue
                index[f"{bag.stem}_{k:06d}"] = (bag, int(stamp), int(image[img_idx[k]]), int(lidar[lid_idx[k]]),
                                                stamp * 1e-9, vel_t, vel_v)
        return index

    def frame_ids(self) -> list[str]:
        return sorted(self._index)

    def sequence_of(self, frame_id: str) -> str:
        if frame_id not in self._index:
            raise ReaderError(self.root, "unknown frame id", frame=frame_id)
        return self._index[frame_id][0].stem

    def _one(self, bag: Path, kind: str, stamp: int, fid: str) -> object:
        for _, msg in self._messages(bag, self.topics[kind], stamp, stamp + 1):
            return msg
        raise ReaderError(bag, f"no {self.topics[kind]} message at {stamp} ns", frame=fid)

    def read(self, frame_id: str) -> FrameRecord:
        if frame_id not in self._index:
            raise ReaderError(self.root, "unknown frame id or frame without paired image/lidar/vel", frame=frame_id)
        bag, t_radar, t_image, t_lidar, t, vel_t, vel_v = self._index[frame_id]
        try:
            radar = pointcloud2_fields(self._one(bag, "radar", t_radar, frame_id))
            lidar = pointcloud2_fields(self._one(bag, "lidar", t_lidar, frame_id))
            image = image_msg_to_bgr(self._one(bag, "image", t_image, frame_id))
        except ValueError as exc:
            raise ReaderError(bag, f"malformed message: {exc}", frame=frame_id) from None
        radar_D, axes = self._radar_D(radar, bag, frame_id)
        intensity = lidar.get("intensity", lidar.get("reflectivity", np.zeros_like(lidar["x"])))
        lidar_xyzi = np.stack([lidar["x"], lidar["y"], lidar["z"], intensity], axis=1)
        order = np.argsort(vel_t)
        speed = float(np.interp(t, vel_t[order], vel_v[order]))
        return self._record(frame_id, bag.stem, t, image, bag, lidar_xyzi, bag, radar_D, axes, speed, bag)
