"""Astyx HiRes2019 reader and the Astyx demo set (radar + CAN bus only).

HiRes2019 layout under the data root (``dataset_astyx_hires2019/``):

- ``dataset.json``: ``data`` -> frame key -> {sensor uid: relative path}. Entries whose files are
  absent are skipped and counted (``skipped_missing``); paths that leave the root, duplicate keys
  and two keys for one frame are errors of that frame (ReaderError on read).
- ``radar_6455/ID.txt``: a blank line, the header ``X Y Z V_r Mag``, then 5 numbers per point;
  radar frame = {D}; ``V_r`` positive when approaching and aliased (wrapped into about
  +/-5.2 m/s). The reader converts it to range rate with ``radar.doppler_sign`` (-1) and keeps it
  wrapped; ``Mag`` is the RSS.
- ``lidar_vlp16/ID.txt``: header ``X Y Z Reflectivity LaserID Timestamp``, then rows (Timestamp
  in microseconds; the frame time is their median).
- ``camera_front/ID.jpg``: 2048x618.
- ``calibration/ID.json``: ``sensors[]`` with ``sensor_uid`` and ``calib_data.T_to_ref_COS``
  (sensor -> reference = radar frame); the camera entry has ``K``. T_radar_cam = T_camera,
  T_radar_lidar = T_lidar (each composed with the inverse of the radar's own entry).
- ``groundtruth_obj3d/ID.json``: ``objects[]`` with ``center3d``, ``dimension3d`` (l, w, h),
  ``orientation_quat`` (w, x, y, z; unit norm), ``classname``, ``object_id``; in the radar frame.
  The boxes are drawn upright in the lidar's frame, which is tilted against the radar's: the
  reader keeps the quaternion's whole rotation as yaw, pitch and roll
  (:func:`quaternion_to_yaw_pitch_roll`, Object3D's Rz(yaw) Ry(pitch) Rx(roll)), so that a box
  holds the points it was drawn around.

Ego velocity is not recorded: it is estimated from the scan's own (aliased) Doppler by
:func:`pipeline.egomotion.estimate_ego_velocity`.

Nor are object velocities or track ids (``object_id`` is -1), nor the ego's pose. A box gets a
velocity over ground from the same object's boxes in the frames one id before and after, where
those are at most MAX_NEIGHBOUR_GAP_S away (the frames are a selection: ids one apart may be
minutes apart): the neighbour's boxes are moved into this frame by the ego's motion in between
(straight at the mean of the two Doppler ego velocities, turning at the yaw rate that overlays the
two lidar scans, :func:`pipeline.egomotion.estimate_yaw_rate`), paired by
:func:`pipeline.boxmatch.match_boxes`, and differenced at the centre of the face each box shows
the radar (:func:`box_reference_points`). Other boxes keep an unknown (NaN) velocity.

The demo set (``dataset_astyx_demo/``: ``dataset_info.json``, ``radar_hires1``, ``canbus`` with
``vehicle_speed`` km/h and bare NaN values, calibration uids radar_hires1 / lidar_os1 /
camera_bfly) has no camera or lidar files: :class:`AstyxDemoReader` exposes the radar and the CAN
speed for checking the ego-speed estimator, and its ``read`` raises ReaderError.
"""

from __future__ import annotations

import json
import threading
import warnings
from collections import Counter, OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from pipeline.baselines import ego_motion_transform
from pipeline.boxmatch import MAX_OBJECT_SPEED_MPS, differenced_velocities, match_boxes
from pipeline.config import Config
from pipeline.egomotion import EgoFit, estimate_ego_velocity, estimate_yaw_rate
from pipeline.errors import ReaderError
from pipeline.frame import FrameRecord, Object3D, box_rotations, from_box_frame
from pipeline.geometry import invert_transform
from pipeline.readers.base import (DetectorFiles, Reader, check_finite, check_intrinsics, check_not_empty,
                                   check_rigid, inside_root, read_image_rgb, require_file, split_sequences_at_gaps)

KMH_TO_MPS = 1.0 / 3.6
RADAR_COLUMNS = ("X", "Y", "Z", "V_r", "Mag")
"""Header of an Astyx radar_6455 file, in this order."""
MAX_NEIGHBOUR_GAP_S = 0.5
"""A neighbouring frame further apart in time gives its boxes no velocity. HiRes2019's frames are a
selection: ids one apart are 0.1 s to minutes apart. Over the 141 frames in ../shared/data
(2026-12-06), 499 of 888 boxes get a velocity (matching centres without the turn: 186 / 290 / 498 /
520 within 0.12 / 0.25 / 0.5 / 1 s)."""
MOTIONS_KEPT = 4
"""Frames (time, ego velocity, boxes, lidar) and frame pairs (yaw rate) a reader keeps for the
frames it reads next: a frame's neighbours are read next, as the neighbour or the frame itself.
Each is kept with the modification time and size of the files it was read from, and read again
once one of them changes. A worker keeps its reader for one command (RunEnv.session); this covers a
reader used longer (the Python API: one RunEnv, several runs) or files rewritten during a run."""
MOTION_FILES = ("radar_6455", "lidar_vlp16", "groundtruth_obj3d", "calibration")
"""The files of a frame its FrameMotion is read from."""


def load_json(path: Path, frame: str | None, what: str, pairs_hook=None) -> object:
    """Parse a JSON file (bare NaN accepted); ReaderError if missing or malformed."""
    require_file(path, frame, what)
    try:
        return json.loads(path.read_text(errors="replace"), object_pairs_hook=pairs_hook)
    except json.JSONDecodeError as exc:
        raise ReaderError(path, f"{what} is not valid JSON ({exc.msg} at line {exc.lineno})", frame=frame) from None


def read_text_table(path: Path, n_cols: int, frame: str | None, what: str, header_start: str) -> np.ndarray:
    """Rows of ``n_cols`` numbers after a header line starting with ``header_start`` -> (N, n_cols) float64."""
    require_file(path, frame, what)
    lines = path.read_text(errors="replace").splitlines()
    header = next((i for i, line in enumerate(lines) if line.strip()), None)
    if header is None or not lines[header].strip().startswith(header_start):
        raise ReaderError(path, f"{what}: header line '{header_start} ...' not found", frame=frame)
    try:  # numpy's C parser: half the time of splitting the text in Python
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # a table without rows
            data = np.loadtxt(lines[header + 1:], dtype=np.float64, comments=None, ndmin=2)
    except ValueError:
        data = None
    if data is None or data.shape[1] != n_cols:  # no rows, or a problem to name by the row
        data = _text_rows(path, lines[header + 1:], n_cols, frame, what)
    check_finite(data, path, frame, what)
    return data


def _text_rows(path: Path, lines: list[str], n_cols: int, frame: str | None, what: str) -> np.ndarray:
    """The non-blank ``lines`` of ``n_cols`` numbers each -> (N, n_cols) float64; ReaderError naming
    the first row of another length or a malformed number."""
    rows = [line for line in lines if line.strip()]
    tokens = " ".join(rows).split()
    if len(tokens) != n_cols * len(rows):
        bad = next(i for i, row in enumerate(rows) if len(row.split()) != n_cols)
        raise ReaderError(path, f"{what}: row {bad + 1} has {len(rows[bad].split())} values, expected {n_cols}",
                          frame=frame)
    try:
        return np.array(tokens, dtype=np.float64).reshape(len(rows), n_cols)
    except ValueError as exc:
        raise ReaderError(path, f"{what}: malformed number ({exc})", frame=frame) from None


def _reject_duplicate_keys(pairs: list[tuple[str, object]]) -> dict:
    counts = Counter(k for k, _ in pairs)
    out = dict(pairs)
    dup = [k for k, n in counts.items() if n > 1]
    if dup:
        out["__duplicate_keys__"] = dup
    return out


class _AstyxIndex(Reader):
    """Index handling shared by the HiRes2019 and demo readers."""

    index_name = "dataset.json"
    radar_uid = "radar_6455"
    required_uids: tuple[str, ...] = ()

    @cached_property
    def _index(self) -> tuple[dict[str, dict[str, Path]], dict[str, str]]:
        """({frame id: {uid: path}} for present frames, {frame id: problem} for broken entries)."""
        index_file = self.root / self.index_name
        if not index_file.is_file() and self.root.is_dir():  # the usual mistake: the folder above the dataset's
            below = sorted(str(f.parent) for f in self.root.glob(f"*/{self.index_name}"))
            if below:
                raise ReaderError(index_file, f"missing dataset index file; --data-root is the folder that holds "
                                              f"it: {' or '.join(below)}")
        data = load_json(index_file, None, "dataset index", _reject_duplicate_keys)
        entries = data.get("data") if isinstance(data, dict) else None
        if not isinstance(entries, dict):
            raise ReaderError(index_file, "index has no 'data' object")
        problems: dict[str, str] = {f"{int(k):06d}" if k.isdigit() else k: f"duplicate index entry '{k}'"
                                    for k in entries.pop("__duplicate_keys__", [])}
        frames: dict[str, dict[str, Path]] = {}
        seen_radar: dict[Path, str] = {}
        seen_keys: dict[str, str] = {}
        resolved: dict[Path, Path] = {}  # inside_root's resolved folders
        for key, entry in entries.items():
            fid = f"{int(key):06d}" if key.isdigit() else key
            if fid in seen_keys:
                problems[fid] = f"duplicate index entries '{seen_keys[fid]}' and '{key}' for frame {fid}"
                continue
            seen_keys[fid] = key
            try:
                paths = self._entry_paths(entry, fid, index_file, resolved)
            except ReaderError as exc:
                problems[fid] = exc.problem
                continue
            if paths.get(self.radar_uid) in seen_radar:
                other = seen_radar.get(paths[self.radar_uid], fid)
                problems[fid] = problems[other] = f"duplicate index entries for frame {fid} ({other})"
                continue
            lacking = [paths[uid] for uid in self.required_uids if not paths[uid].is_file()]
            if lacking:
                self.skip_missing(fid, lacking)
                continue
            frames[fid] = paths
            seen_radar[paths[self.radar_uid]] = fid
        return frames, problems

    def _entry_paths(self, entry: object, fid: str, index_file: Path, resolved: dict[Path, Path]) -> dict[str, Path]:
        if not isinstance(entry, dict):
            raise ReaderError(index_file, f"index entry of frame {fid} is not an object", frame=fid)
        missing = [uid for uid in self.required_uids if uid not in entry]
        if missing:
            raise ReaderError(index_file, f"index entry lacks {', '.join(missing)}", frame=fid)
        follow = self.cfg.dataset.follow_links
        return {uid: inside_root(self.root, str(rel), fid, index_file, resolved, follow) for uid, rel in entry.items()}

    def layout_hint(self) -> str:
        return (f"an entry in {self.index_name} whose {', '.join(self.required_uids)} files exist "
                "(paths relative to the data root)")

    def frame_ids(self) -> list[str]:
        frames, problems = self._index
        return sorted(set(frames) | set(problems), key=lambda s: (len(s), s))

    def sequence_of(self, frame_id: str) -> str:
        sequence = self._sequences.get(frame_id)
        if sequence is None:
            raise ReaderError(self.root / self.index_name, "unknown frame id", frame=frame_id)
        return sequence

    @cached_property
    def _sequences(self) -> dict[str, str]:
        """Frame id -> sequence, once per reader (it was found anew per frame: O(F log F) each):
        numbered frames split where the numbers jump, any other id a sequence of its own."""
        ids = self.frame_ids()
        numbered = split_sequences_at_gaps([int(f) for f in ids if f.isdigit()])
        return {f: numbered[int(f)] if f.isdigit() else f for f in ids}

    def _paths(self, frame_id: str) -> dict[str, Path]:
        frames, problems = self._index
        if frame_id in problems:
            raise ReaderError(self.root / self.index_name, problems[frame_id], frame=frame_id)
        if frame_id not in frames:
            raise ReaderError(self.root / self.index_name, "frame not in the index or its files are missing",
                              frame=frame_id)
        return frames[frame_id]

    def _calibration(self, frame_id: str, uids: tuple[str, str, str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(T_radar_lidar, T_radar_cam, K) from the calibration JSON; uids = (radar, lidar, camera)."""
        path = self._paths(frame_id)["calibration"]
        data = load_json(path, frame_id, "calibration")
        sensors = {s.get("sensor_uid"): s["calib_data"] if isinstance(s.get("calib_data"), dict) else {}
                   for s in data.get("sensors", []) if isinstance(s, dict)} if isinstance(data, dict) else {}
        T = {}
        for uid in uids:
            if uid not in sensors or "T_to_ref_COS" not in sensors[uid]:
                raise ReaderError(path, f"calibration key 'T_to_ref_COS' of sensor '{uid}' is missing", frame=frame_id)
            T[uid] = check_rigid(_matrix(sensors[uid]["T_to_ref_COS"], (4, 4), path, frame_id, uid),
                                 path, frame_id, f"T_to_ref_COS of {uid}")
        if "K" not in sensors[uids[2]]:
            raise ReaderError(path, f"calibration key 'K' of sensor '{uids[2]}' is missing", frame=frame_id)
        K = check_intrinsics(_matrix(sensors[uids[2]]["K"], (3, 3), path, frame_id, uids[2]), path, frame_id)
        T_radar_ref = invert_transform(T[uids[0]])
        return T_radar_ref @ T[uids[1]], T_radar_ref @ T[uids[2]], K

    def read_radar(self, frame_id: str) -> np.ndarray:
        """(M, 5) float32 radar points in {D}: x, y, z (m), range rate (m/s, wrapped), Mag."""
        path = self._paths(frame_id)[self.radar_uid]
        raw = read_text_table(path, 5, frame_id, "radar", "X")
        check_not_empty(raw, path, frame_id, "radar")
        header = next(line.split() for line in path.read_text(errors="replace").splitlines() if line.strip())
        if header != list(RADAR_COLUMNS):
            raise ReaderError(path, f"radar: columns {' '.join(header)}, expected {' '.join(RADAR_COLUMNS)}",
                              frame=frame_id)
        span = self.radar.doppler_span_mps
        if span > 0 and np.abs(raw[:, 3]).max() > 0.55 * span:
            raise ReaderError(path, f"radar: V_r up to {np.abs(raw[:, 3]).max():.2f} m/s, outside the sensor's "
                                    f"unambiguous span of +/-{span / 2:.2f} m/s (wrong column or unit?)",
                              frame=frame_id)
        out = raw.astype(np.float32)
        out[:, 3] = raw[:, 3] * self.radar.doppler_sign
        return out

    def estimate_ego(self, frame_id: str) -> EgoFit:
        """Ego velocity of the radar from the frame's own Doppler (alias-aware robust fit)."""
        radar = self.read_radar(frame_id)
        return estimate_ego_velocity(radar[:, :3], radar[:, 3], self.radar.doppler_span_mps)


def _matrix(values: object, shape: tuple[int, int], path: Path, frame: str, uid: str) -> np.ndarray:
    try:
        out = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ReaderError(path, f"malformed calibration values of sensor '{uid}'", frame=frame) from None
    if out.shape != shape or not np.all(np.isfinite(out)):
        raise ReaderError(path, f"calibration matrix of sensor '{uid}' has shape {out.shape} or non-finite "
                                f"values, expected finite {shape}", frame=frame)
    return out


@dataclass
class FrameMotion:
    """What a box's velocity needs of a frame: its time (s), its Doppler ego-velocity fit, its
    labelled boxes and its lidar file's rows (N, 6) with the lidar's pose T_radar_lidar (4, 4)."""

    time_s: float
    fit: EgoFit
    labels: list[Object3D]
    lidar: np.ndarray
    T_radar_lidar: np.ndarray

    @property
    def ego_velocity_D(self) -> np.ndarray:
        """(3,) m/s in {D}."""
        return self.fit.velocity_D

    @cached_property
    def lidar_D(self) -> np.ndarray:
        """(N, 3) m in {D}, float64."""
        return self.lidar[:, :3] @ self.T_radar_lidar[:3, :3].T + self.T_radar_lidar[:3, 3]


QUATERNION_NORM_TOLERANCE = 1e-3
"""A box's ``orientation_quat`` further than this from unit norm is an error of its file (the 888
boxes in ../shared/data are unit to 1.2e-16)."""


def quaternion_to_yaw_pitch_roll(w: float, x: float, y: float, z: float) -> tuple[float, float, float]:
    """(yaw, pitch, roll) rad of the unit quaternion (w, x, y, z), such that
    pipeline.frame.box_rotations(yaw, pitch, roll) is its rotation matrix (Rz(yaw) Ry(pitch) Rx(roll)).

    Astyx's boxes are upright in the lidar's frame, which is tilted against the radar's (about -3.6
    deg roll, -2.2 deg pitch): in {D} their z axes lean a median 4.2 deg (0.6 deg against the
    lidar's z; the 888 boxes in ../shared/data, 2026-12-06). Keeping only the yaw, as the reader did
    until then, made the boxes upright in {D}: of the 141 frames' lidar points, 1,462 were in or out
    of a box (grown 0.3 m, as :func:`pipeline.synthesis.object_velocities_for_points` has it) that
    should not have been (78,165 in boxes upright, 78,541 tilted), and 1,012 radar points (24,298)."""
    yaw = float(np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)))
    pitch = float(np.arcsin(np.clip(2.0 * (w * y - x * z), -1.0, 1.0)))
    roll = float(np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y)))
    return yaw, pitch, roll


def box_reference_points(labels: Sequence[Object3D]) -> np.ndarray:
    """(N, 3) m in {D}: the point of each box followed from frame to frame, the centre of its
    side face nearest the radar (the face the sensors see).

    The four side faces' centres are centre + R (+/-l/2, 0, 0) and centre + R (0, +/-w/2, 0), R
    the box's whole rotation (:attr:`Object3D.rotation`): Astyx's boxes lean about 4 deg in {D},
    which moves a face centre up to about 0.15 m in height from the box centre's. Nearest is by
    the distance in {D}'s x-y plane, as it was when the faces shared the centre's height: which face
    the radar sees is a matter of the box's footprint, not of the radar's height above the box's
    centre (by 3D distance, the height would tip the choice towards the face that leans down). An
    upright box gives the same bits as before the tilt was used (the yaw alone).

    Astyx's boxes are drawn anew in each frame; their extent away from the sensors, which no
    sensor sees, varies from frame to frame, and so does the centre. Over the 141 frames in
    ../shared/data (2026-12-06, the boxes tilted), the real radar points on boxes with a
    differenced velocity are within 2.5 m/s of the Doppler it gives for 95.6% of the points
    (14,446 of 15,118), against 92.0% with the centres (73.3% with static boxes). The yaw-only
    face centres gave the same 14,446: the chosen face centres sit a median 0.07 m (90th
    percentile 0.13 m) above or below the box centre, which moves the velocities' z (90th
    percentile 0.16 m/s) and barely their x-y (0.008 m/s), and the same face is chosen for all 888
    boxes (by 3D distance too)."""
    if not labels:
        return np.zeros((0, 3))
    centre = np.array([o.center_D for o in labels], np.float64)
    half = np.array([o.size_lwh_m for o in labels], np.float64)[:, :2] / 2
    rotation = box_rotations(*np.array([(o.yaw_rad, o.pitch_rad, o.roll_rad) for o in labels], np.float64).T)
    local = np.zeros((len(labels), 4, 3))  # faces: +length, +width, -length, -width (the order ties are broken in)
    local[:, 0, 0], local[:, 1, 1] = half[:, 0], half[:, 1]
    local[:, 2, 0], local[:, 3, 1] = -half[:, 0], -half[:, 1]
    faces = centre[:, None, :] + from_box_frame(local, rotation[:, None])                              # (N, 4, 3)
    nearest = np.argmin(faces[..., 0] * faces[..., 0] + faces[..., 1] * faces[..., 1], axis=1)
    return faces[np.arange(len(labels)), nearest]


class AstyxReader(_AstyxIndex):
    """Astyx HiRes2019: radar 6455, VLP-16 lidar, front camera; see the module docstring."""

    name = "astyx"
    version = 4
    """2: labelled boxes get a velocity from the neighbouring frames' boxes (before: none).
    3: boxes keep their pitch and roll from ``orientation_quat`` (before: the yaw only).
    4: the velocities are differenced at face centres placed by the box's whole rotation
    (:func:`box_reference_points`; before: the yaw only, at the centre's height)."""
    required_uids = ("radar_6455", "lidar_vlp16", "camera_front", "calibration")
    calib_uids = ("radar_6455", "lidar_vlp16", "camera_front")

    def __init__(self, cfg: Config, data_root: str | Path) -> None:
        super().__init__(cfg, data_root)
        self._motions: OrderedDict[tuple, FrameMotion] = OrderedDict()
        self._yaw_rates: OrderedDict[tuple, float] = OrderedDict()
        self._kept_lock = threading.Lock()  # a dask worker's threads share one reader

    def detector_files(self, frame_id: str) -> DetectorFiles:
        """No KITTI files; the frame's objects are its annotation where its ground-truth file exists."""
        path = self._paths(frame_id).get("groundtruth_obj3d")
        return DetectorFiles(objects_labelled=path is not None and path.is_file())

    def read(self, frame_id: str) -> FrameRecord:
        paths = self._paths(frame_id)
        T_radar_lidar, T_radar_cam, K = self._calibration(frame_id, self.calib_uids)
        key = self._files_key(frame_id)
        radar = self.read_radar(frame_id)
        seen = self._recall(self._motions, key)  # read already as the neighbour of the frame before
        if seen is not None:
            lidar, fit = seen.lidar, seen.fit
        else:
            lidar = read_text_table(paths["lidar_vlp16"], 6, frame_id, "lidar", "X")
            check_not_empty(lidar, paths["lidar_vlp16"], frame_id, "lidar")
            fit = estimate_ego_velocity(radar[:, :3], radar[:, 3], self.radar.doppler_span_mps)
        image = read_image_rgb(paths["camera_front"], frame_id, self.cfg.camera.full_size)
        if fit.n_used < 3:
            raise ReaderError(paths[self.radar_uid], "cannot estimate ego velocity: fewer than 3 static "
                                                     "points agree", frame=frame_id)
        motion = FrameMotion(float(np.median(lidar[:, 5])) * 1e-6, fit, self._labels(frame_id), lidar, T_radar_lidar)
        self._keep(self._motions, key, motion)
        self._object_velocities(key, motion)
        record = FrameRecord(
            frame_id=frame_id, sequence_id=self.sequence_of(frame_id),
            timestamp_s=motion.time_s, image=image, K=K,
            lidar_D=motion.lidar_D.astype(np.float32), lidar_intensity=lidar[:, 3].astype(np.float32),
            radar_D=radar, T_radar_lidar=T_radar_lidar, T_radar_cam=T_radar_cam,
            ego_velocity_D=fit.velocity_D, has_radar=True, labels=motion.labels)
        return self.finish(record, paths[self.radar_uid])

    # -- object velocities ---------------------------------------------------------------------

    def _files_key(self, frame_id: str) -> tuple:
        """(frame id, (modification time ns, size) of each of its MOTION_FILES, None where absent)."""
        paths, stats = self._paths(frame_id), []
        for uid in MOTION_FILES:
            try:
                st = paths[uid].stat()
                stats.append((st.st_mtime_ns, st.st_size))
            except (KeyError, OSError):
                stats.append(None)
        return frame_id, tuple(stats)

    def _recall(self, kept: OrderedDict, key: tuple):
        with self._kept_lock:
            return kept.get(key)

    def _keep(self, kept: OrderedDict, key: tuple, value: object) -> None:
        """Keep ``value`` of the last few frames or pairs read: a frame's neighbours are read next."""
        with self._kept_lock:
            kept[key] = value
            kept.move_to_end(key)
            while len(kept) > MOTIONS_KEPT:
                kept.popitem(last=False)

    def _motion(self, key: tuple) -> FrameMotion | None:
        """Time, ego velocity and boxes of a neighbouring frame (its :meth:`_files_key`); None where
        it has no boxes or its files do not give them (its own read names what is wrong)."""
        frame_id = key[0]
        seen = self._recall(self._motions, key)
        if seen is not None:
            return seen
        try:
            labels = self._labels(frame_id)
            if not labels:
                return None
            lidar = read_text_table(self._paths(frame_id)["lidar_vlp16"], 6, frame_id, "lidar", "X")
            T_radar_lidar = self._calibration(frame_id, self.calib_uids)[0]
            fit = self.estimate_ego(frame_id)
        except (ReaderError, KeyError, OSError):
            return None
        if fit.n_used < 3 or len(lidar) == 0:
            return None
        motion = FrameMotion(float(np.median(lidar[:, 5])) * 1e-6, fit, labels, lidar, T_radar_lidar)
        self._keep(self._motions, key, motion)
        return motion

    def _object_velocities(self, key: tuple, motion: FrameMotion) -> None:
        """Set each box's velocity over ground (in {D}) from the same object's boxes in the
        neighbouring frames (ids one apart in the sequence, at most MAX_NEIGHBOUR_GAP_S away),
        associated by :func:`pipeline.boxmatch.match_boxes` once the ego's motion between the two
        scans is removed: straight at the mean of their Doppler ego velocities, turning at the
        yaw rate that overlays their lidar scans (:func:`pipeline.egomotion.estimate_yaw_rate`).
        Boxes held by no neighbour keep a NaN velocity.

        The turn moves a box across the line of sight only, so it leaves the box's Doppler as it
        is, but not its speed: on the 141 frames in ../shared/data (2026-12-06), boxes the radar
        sees standing still (90% of their points within 0.5 m/s of a static Doppler, the ego
        moving) get a median speed of 0.87 m/s (90th percentile 4.0) with it and 1.52 m/s (5.5)
        without; beyond 25 m 1.47 against 3.3 m/s. What is left is the boxes' own jitter."""
        if not motion.labels:
            return
        frame_id = key[0]
        centres = box_reference_points(motion.labels)
        classes = [o.class_name for o in motion.labels]
        neighbours = []
        for step in (-1, 1):
            other_id = self._neighbour(frame_id, step)
            other_key = self._files_key(other_id) if other_id is not None else None
            other = self._motion(other_key) if other_key is not None else None
            if other is None or not 0 < abs(other.time_s - motion.time_s) <= MAX_NEIGHBOUR_GAP_S:
                continue
            dt = other.time_s - motion.time_s
            ego = (motion.ego_velocity_D + other.ego_velocity_D) / 2
            pair = tuple(sorted((key, other_key)))
            yaw_rate = self._recall(self._yaw_rates, pair)
            if yaw_rate is None:  # from the first frame of the pair to the second, whichever is read
                first, second = (motion, other) if pair[0] == key else (other, motion)
                yaw_rate = estimate_yaw_rate(first.lidar_D, second.lidar_D, ego, second.time_s - first.time_s)
                self._keep(self._yaw_rates, pair, yaw_rate)
            T_now_other = ego_motion_transform(ego, -dt, yaw_rate)
            other_centres = (box_reference_points(other.labels) @ T_now_other[:3, :3].T
                             + T_now_other[:3, 3])
            same = match_boxes(centres, classes, other_centres, [o.class_name for o in other.labels],
                               MAX_OBJECT_SPEED_MPS * abs(dt))
            neighbours.append((same, other_centres, other.time_s))
        velocity = differenced_velocities(centres, motion.time_s, neighbours)
        known = ~np.isnan(velocity[:, 0])
        for obj, v, k in zip(motion.labels, velocity, known):
            if k:
                obj.velocity_D = v.astype(np.float32)
        self._counts["objects_velocity_by_box_matching"] += int(known.sum())
        self._counts["objects_velocity_unknown"] += int((~known).sum())

    def _neighbour(self, frame_id: str, step: int) -> str | None:
        """Id of frame number + step in the same sequence, or None."""
        if not frame_id.isdigit():
            return None
        other = f"{int(frame_id) + step:0{len(frame_id)}d}"
        return other if self._sequences.get(other) == self._sequences.get(frame_id) else None

    def _labels(self, frame_id: str) -> list[Object3D]:
        path = self._paths(frame_id).get("groundtruth_obj3d")
        if path is None or not path.is_file():
            return []
        data = load_json(path, frame_id, "ground truth")
        objects = []
        for i, obj in enumerate(data.get("objects", []) if isinstance(data, dict) else []):
            try:
                centre = np.asarray(obj["center3d"], np.float64).reshape(3)
                size = np.asarray(obj["dimension3d"], np.float64).reshape(3)
                w, x, y, z = np.asarray(obj["orientation_quat"], np.float64).reshape(4)
                name = str(obj["classname"])
                track_id = int(obj.get("object_id", -1))
            except (KeyError, TypeError, ValueError):
                raise ReaderError(path, f"object {i} lacks center3d/dimension3d/orientation_quat/classname "
                                        "or has malformed values", frame=frame_id) from None
            if not np.all(np.isfinite(np.r_[centre, size, w, x, y, z])):
                raise ReaderError(path, f"object {i} has NaN or inf in its box", frame=frame_id)
            norm = np.sqrt(w * w + x * x + y * y + z * z)
            if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
                raise ReaderError(path, f"object {i}: orientation_quat has norm {norm:.6g}, expected a unit "
                                        "quaternion (w, x, y, z)", frame=frame_id)
            yaw, pitch, roll = quaternion_to_yaw_pitch_roll(w, x, y, z)
            objects.append(Object3D(class_name=name, center_D=centre, size_lwh_m=size, yaw_rad=yaw,
                                    track_id=track_id, pitch_rad=pitch, roll_rad=roll))
        return objects


class AstyxDemoReader(_AstyxIndex):
    """The Astyx demo set: radar_hires1 scans and CAN-bus speed, no camera or lidar files."""

    name = "astyx_demo"
    index_name = "dataset_info.json"
    radar_uid = "radar_hires1"
    required_uids = ("radar_hires1", "calibration", "canbus")

    def read(self, frame_id: str) -> FrameRecord:
        raise ReaderError(self.root / self.index_name, "the Astyx demo set has no camera or lidar files; "
                                                      "use read_radar() and can_speed_mps()", frame=frame_id)

    def can_speed_mps(self, frame_id: str) -> float:
        """CAN-bus ``vehicle_speed`` of the frame converted from km/h to m/s."""
        path = self._paths(frame_id)["canbus"]
        data = load_json(path, frame_id, "CAN bus")
        speed = data.get("vehicle_speed") if isinstance(data, dict) else None
        if not isinstance(speed, (int, float)) or not np.isfinite(speed):
            raise ReaderError(path, f"vehicle_speed missing or not a finite number: {speed!r}", frame=frame_id)
        return float(speed) * KMH_TO_MPS
