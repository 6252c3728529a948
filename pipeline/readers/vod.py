"""View-of-Delft reader (KITTI layout with ``radar/`` and ``lidar/`` trees) and the synthetic world.

Layout under the data root (frame ids are the file stems, e.g. ``00549``; stems that differ only
by leading zeros, ``549`` beside ``00549``, are one frame number with two sets of files: the frame
is listed once, under the first of its complete ids, and refused on read naming both files):

- ``<radar_folder>/training/velodyne/ID.bin``: 7 float32 per point: x, y, z (m, radar frame =
  {D}), RCS (dBsm), v_r (range rate, m/s), v_r_compensated, time (0 current scan; -1, -2 ... in
  the accumulated ``radar_3frames`` / ``radar_5frames`` folders). ``radar_folder`` is a reader
  option; the single-scan folder keeps only time == 0 points.
- ``lidar/training/velodyne/ID.bin``: 4 float32 per point (x, y, z, reflectance), lidar frame.
- ``{radar,lidar}/training/calib/ID.txt``: ``Tr_velo_to_cam`` is radar->camera in the radar tree
  and lidar->camera in the lidar tree; intrinsics from P2.
- ``{radar,lidar}/training/image_2/ID.jpg`` or ``.png`` (both present is a duplicate frame id).
- ``{lidar,radar}/training/pose/ID.json`` (optional): JSON lines ``odomToCamera`` (camera->odom
  world, row-major 4x4), ``mapToCamera``, ``UTMToCamera``; an optional ``{"timestamp": s}`` line
  gives the frame time, else time = frame number / 10 Hz.
- ``lidar/training/label_2/ID.txt`` (optional): KITTI labels; column 2 is the track id in the
  tracking release (it is treated as a track id only where it is unique within the frame). A
  negative box size is refused, except on ``DontCare`` lines (KITTI gives them -1).
- ``ImageSets/sequences.txt`` (optional): ``name first last`` per line (inclusive frame numbers);
  without it sequences are split where frame numbers jump.
- Synthetic world only: ``radar/training/meta/ID.bin``: int32 pairs (object_id, material_id) per
  radar point -> ``FrameRecord.extras``.

Ego velocity: least squares on ``v_r - v_r_compensated = -(u . v_D)`` over the current scan's
points (exact on the real files); pose differencing (odometry, central difference) when the fit
has fewer than 3 points or is ill-conditioned. Object velocities: the box of the same object in
the neighbouring frames' labels, with their poses (central difference where both neighbours have
it, one-sided where one does), else NaN. The same object is the same track id and class where both
frames hold track ids; otherwise (the detection release) the nearest box of the class, where that
is unambiguous (:func:`pipeline.boxmatch.match_boxes`).
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from functools import cached_property
from pathlib import Path
from typing import Callable, TypeVar

import numpy as np

from pipeline.boxmatch import MAX_OBJECT_SPEED_MPS, differenced_velocities, match_boxes
from pipeline.config import Config
from pipeline.egomotion import fit_compensation_pair
from pipeline.errors import ReaderError
from pipeline.frame import FrameRecord, Object3D
from pipeline.geometry import invert_transform
from pipeline.readers.base import (DetectorFiles, Reader, check_not_empty, check_rigid, read_float32_records,
                                   read_image_rgb, require_file, split_sequences_at_gaps)
from pipeline.readers.kitti_format import (KittiLabel, camera_calib, label_to_object, lidar_box_label_to_object,
                                           parse_label_file)

RADAR_FOLDERS = ("radar", "radar_3frames", "radar_5frames")
FRAME_RATE_HZ = 10.0
MAX_FIT_CONDITION = 1e3
"""Compensation-pair fits with a worse condition number fall back to pose differencing."""
PARSED_FILES_KEPT = 16
"""Parsed label and pose files a reader keeps (:meth:`VodReader._parsed`): a frame reads its
neighbours' too (timestamps, ego and object velocities), so without it each label file was parsed
three times and each pose file about eight."""
_T = TypeVar("_T")


class VodReader(Reader):
    """View-of-Delft in its KITTI layout; see the module docstring for files and conventions."""

    name = "vod"
    version = 3
    """2: a 0 / 1 flag in the second label column is not taken for track ids; a track keeps its class;
    boxes upright in the lidar frame, as the devkit reads them (centres moved 6-12 cm). 3: boxes
    without track ids get velocities by matching them to the neighbouring frames' boxes."""

    def __init__(self, cfg: Config, data_root: str | Path, radar_folder: str = "radar",
                 with_meta: bool = False) -> None:
        super().__init__(cfg, data_root)
        if radar_folder not in RADAR_FOLDERS:
            raise ReaderError(self.root, f"radar_folder must be one of {RADAR_FOLDERS}, got '{radar_folder}'")
        self.radar_folder = radar_folder
        self.with_meta = with_meta
        self._parsed_files: OrderedDict[tuple, object] = OrderedDict()
        self._parsed_lock = threading.Lock()  # a dask worker's threads share one reader

    def _parsed(self, path: Path, parse: Callable[[], _T]) -> _T:
        """``parse()`` of ``path``, kept for the next call while the file keeps its modification time
        and size (the last PARSED_FILES_KEPT files; a worker keeps its reader for one command,
        RunEnv.session, and a reader used longer sees files changed since).
        A file that fails to parse is not kept: its error is raised again each time."""
        st = path.stat()
        key = (str(path), st.st_mtime_ns, st.st_size)
        with self._parsed_lock:
            if key in self._parsed_files:
                self._parsed_files.move_to_end(key)
                return self._parsed_files[key]  # type: ignore[return-value]
        value = parse()
        with self._parsed_lock:
            self._parsed_files[key] = value
            while len(self._parsed_files) > PARSED_FILES_KEPT:
                self._parsed_files.popitem(last=False)
        return value

    def detector_files(self, frame_id: str) -> DetectorFiles:
        """The radar tree's calib (Tr_velo_to_cam: radar -> camera), the lidar tree's labels (whether
        they hold track ids as :meth:`_has_track_ids` decides) and the frame's image file, those that
        exist."""
        calib = self._calib(self.radar_folder, frame_id)
        label = self.root / "lidar" / "training" / "label_2" / f"{frame_id}.txt"
        images = self._image_candidates(frame_id)
        tracked = label.is_file() and self._has_track_ids(
            [lab for lab in parse_label_file(label, frame_id) if lab.class_name != "DontCare"])
        return DetectorFiles(calib=calib if calib.is_file() else None, label=label if label.is_file() else None,
                             image=images[0] if images else None, label_track_ids=tracked)

    def layout_hint(self) -> str:
        return (f"{self.radar_folder}/training/velodyne/ID.bin and lidar/training/velodyne/ID.bin, "
                f"calib/ID.txt in both trees and image_2/ID.jpg or .png")

    # -- paths ---------------------------------------------------------------------------------

    def _radar_bin(self, fid: str) -> Path:
        return self.root / self.radar_folder / "training" / "velodyne" / f"{fid}.bin"

    def _lidar_bin(self, fid: str) -> Path:
        return self.root / "lidar" / "training" / "velodyne" / f"{fid}.bin"

    def _calib(self, tree: str, fid: str) -> Path:
        path = self.root / tree / "training" / "calib" / f"{fid}.txt"
        if tree != "lidar" and not path.is_file():
            path = self.root / "radar" / "training" / "calib" / f"{fid}.txt"
        return path

    def _pose(self, fid: str) -> Path | None:
        for tree in ("lidar", "radar"):
            path = self.root / tree / "training" / "pose" / f"{fid}.json"
            if path.is_file():
                return path
        return None

    def _image_candidates(self, fid: str) -> list[Path]:
        """Image files of the frame in the first image folder that has any."""
        for tree in dict.fromkeys((self.radar_folder, "radar", "lidar")):
            folder = self.root / tree / "training" / "image_2"
            found = [folder / f"{fid}{ext}" for ext in (".jpg", ".png") if (folder / f"{fid}{ext}").is_file()]
            if found:
                return found
        return []

    def _velodyne_file(self, fid: str) -> Path:
        """The radar point file of ``fid``, else its lidar one (the files that list a frame id)."""
        radar = self._radar_bin(fid)
        return radar if radar.is_file() else self._lidar_bin(fid)

    def _required(self, fid: str) -> list[Path]:
        return [self._radar_bin(fid), self._lidar_bin(fid), self._calib(self.radar_folder, fid),
                self._calib("lidar", fid)]

    # -- index ---------------------------------------------------------------------------------

    @cached_property
    def _index(self) -> tuple[list[str], dict[str, str], dict[int, list[str]]]:
        """(sorted frame ids with all required files, {id: sequence name}, {frame number: its stems}
        for the numbers with several, e.g. 549: ['00549', '549']). Such a number is listed once,
        under its first complete stem (counted in ``frame_ids_differing_by_leading_zeros``)."""
        stems: set[str] = set()
        for folder in (self._radar_bin("x").parent, self._lidar_bin("x").parent):
            if folder.is_dir():
                stems |= {p.stem for p in folder.glob("*.bin") if p.stem.isdigit()}
        by_number: dict[int, list[str]] = {}
        for fid in sorted(stems, key=lambda s: (int(s), s)):
            by_number.setdefault(int(fid), []).append(fid)
        ids, clashes = [], {}
        for group in by_number.values():
            complete = [fid for fid in group
                        if all(p.is_file() for p in self._required(fid)) and self._image_candidates(fid)]
            if not complete:
                for fid in group:
                    lacking = [p for p in self._required(fid) if not p.is_file()]
                    self.skip_missing(fid, lacking or [f"{self.radar_folder}/training/image_2/{fid}.jpg or .png"])
                continue
            ids.append(complete[0])
            if len(group) > 1:
                clashes[int(complete[0])] = group
                self._counts["frame_ids_differing_by_leading_zeros"] += len(group) - 1
        return ids, self._sequences(ids), clashes

    def _sequences(self, ids: list[str]) -> dict[str, str]:
        listing = self.root / "ImageSets" / "sequences.txt"
        if not listing.is_file():
            by_number = split_sequences_at_gaps([int(f) for f in ids])
            return {f: by_number[int(f)] for f in ids}
        ranges = []
        for line_no, line in enumerate(listing.read_text().splitlines(), 1):
            parts = line.split()
            if not parts:
                continue
            if len(parts) != 3 or not parts[1].isdigit() or not parts[2].isdigit():
                raise ReaderError(listing, f"line {line_no} is not 'name first last'")
            ranges.append((parts[0], int(parts[1]), int(parts[2])))
        out = {}
        for fid in ids:
            names = [name for name, first, last in ranges if first <= int(fid) <= last]
            out[fid] = names[0] if names else "unlisted"
            self._counts["frames_without_sequence"] += not names
        return out

    def frame_ids(self) -> list[str]:
        return list(self._index[0])

    def sequence_of(self, frame_id: str) -> str:
        seqs = self._index[1]
        if frame_id not in seqs:
            raise ReaderError(self._radar_bin(frame_id), "unknown frame id (not in the index)", frame=frame_id)
        return seqs[frame_id]

    def _neighbour(self, fid: str, step: int) -> str | None:
        """Id of frame number + step if it is indexed and in the same sequence."""
        other = f"{int(fid) + step:0{len(fid)}d}"
        seqs = self._index[1]
        return other if other in seqs and seqs[other] == seqs.get(fid) else None

    # -- reading -------------------------------------------------------------------------------

    def read(self, frame_id: str) -> FrameRecord:
        for path in self._required(frame_id):
            require_file(path, frame_id, "required")
        others = [fid for fid in self._index[2].get(int(frame_id), []) if fid != frame_id]
        if others:
            files = ", ".join(str(self._velodyne_file(other)) for other in others)
            raise ReaderError(self._radar_bin(frame_id), f"frame number {int(frame_id)} has a second set of files, "
                                                         f"named with other leading zeros ({files}): which set is "
                                                         f"the frame is ambiguous; remove or rename one",
                              frame=frame_id)
        images = self._image_candidates(frame_id)
        if not images:
            raise ReaderError(self.root / "lidar" / "training" / "image_2" / f"{frame_id}.jpg",
                              "missing image file (.jpg or .png)", frame=frame_id)
        if len(images) > 1:
            raise ReaderError(images[0], f"duplicate frame id: also {images[1].name}", frame=frame_id)
        radar_cal = camera_calib(self._calib(self.radar_folder, frame_id), frame_id)
        lidar_cal = camera_calib(self._calib("lidar", frame_id), frame_id)
        T_radar_cam = invert_transform(radar_cal.T_cam_sensor)
        T_radar_lidar = check_rigid(T_radar_cam @ lidar_cal.T_cam_sensor, self._calib("lidar", frame_id),
                                    frame_id, "T_radar_lidar")
        radar, current, extras = self._read_radar(frame_id)
        lidar = read_float32_records(self._lidar_bin(frame_id), 4, frame_id, "lidar")
        check_not_empty(lidar, self._lidar_bin(frame_id), frame_id, "lidar")
        image = read_image_rgb(images[0], frame_id, self.cfg.camera.full_size)
        timestamp = self._checked_timestamp(frame_id)
        ego = self._ego_velocity(frame_id, radar[current], radar_cal.T_cam_sensor)
        labels = self._labels(frame_id, T_radar_cam @ radar_cal.T_cam_rect, radar_cal.T_cam_sensor, T_radar_lidar)
        lidar_D = (lidar[:, :3].astype(np.float64) @ T_radar_lidar[:3, :3].T + T_radar_lidar[:3, 3])
        record = FrameRecord(
            frame_id=frame_id, sequence_id=self.sequence_of(frame_id), timestamp_s=timestamp,
            image=image, K=radar_cal.K, lidar_D=lidar_D.astype(np.float32),
            lidar_intensity=lidar[:, 3].copy(), radar_D=radar[:, [0, 1, 2, 4, 3]].copy(),
            T_radar_lidar=T_radar_lidar, T_radar_cam=T_radar_cam, ego_velocity_D=ego,
            has_radar=True, labels=labels, extras=extras)
        return self.finish(record, self._radar_bin(frame_id))

    def _read_radar(self, fid: str) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """(kept points (M, 7), (M,) bool current-scan mask, extras) with the time column checked."""
        path = self._radar_bin(fid)
        radar = read_float32_records(path, 7, fid, "radar")
        time = radar[:, 6]
        if np.any((time != np.round(time)) | (time > 0) | (time < -20)):
            raise ReaderError(path, "radar time column holds values that are not scan offsets "
                                    "(0, -1, -2, ...): wrong record type?", frame=fid)
        keep = time == 0 if self.radar_folder == "radar" else np.ones(len(radar), bool)
        self._counts["radar_points_dropped_time"] += int((~keep).sum())
        extras = self._read_meta(fid, radar.shape[0]) if self.with_meta else {}
        radar = radar[keep]
        extras = {k: v[keep] for k, v in extras.items()}
        check_not_empty(radar, path, fid, "radar")
        return radar, radar[:, 6] == 0, extras

    def _read_meta(self, fid: str, n_points: int) -> dict[str, np.ndarray]:
        path = require_file(self.root / "radar" / "training" / "meta" / f"{fid}.bin", fid, "radar meta")
        size = path.stat().st_size
        if size != 8 * n_points:
            raise ReaderError(path, f"radar meta file has {size} bytes, expected {8 * n_points} "
                                    f"(2 int32 per radar point, {n_points} points)", frame=fid)
        meta = np.fromfile(path, dtype="<i4").reshape(-1, 2)
        return {"object_id": meta[:, 0].copy(), "material": meta[:, 1].copy()}

    # -- poses and time ------------------------------------------------------------------------

    def _pose_lines(self, fid: str) -> dict | None:
        path = self._pose(fid)
        if path is None:
            return None

        def parse() -> dict:
            merged: dict = {}
            try:
                for line in path.read_text().splitlines():
                    if line.strip():
                        merged.update(json.loads(line))
            except (json.JSONDecodeError, AttributeError, TypeError, ValueError):
                raise ReaderError(path, "pose file is not JSON lines of objects", frame=fid) from None
            return merged

        return dict(self._parsed(path, parse))

    def _timestamp(self, fid: str) -> float:
        pose = self._pose_lines(fid)
        if pose is not None and "timestamp" in pose:
            value = pose["timestamp"]
            if not isinstance(value, (int, float)) or not np.isfinite(value):
                raise ReaderError(self._pose(fid), f"timestamp is not a finite number: {value!r}", frame=fid)
            return float(value)
        return int(fid) / FRAME_RATE_HZ

    def _checked_timestamp(self, fid: str) -> float:
        """The frame time; ReaderError if it is not after the previous frame of the sequence."""
        t = self._timestamp(fid)
        prev = self._neighbour(fid, -1)
        if prev is not None:
            t_prev = self._timestamp(prev)
            if t_prev >= t:
                raise ReaderError(self._pose(fid) or self._radar_bin(fid),
                                  f"non-monotonic timestamps: {t:.6f} s is not after the previous "
                                  f"frame {prev} ({t_prev:.6f} s)", frame=fid)
        return t

    def _T_world_cam(self, fid: str) -> np.ndarray | None:
        pose = self._pose_lines(fid)
        if pose is None or "odomToCamera" not in pose:
            return None
        values = np.asarray(pose["odomToCamera"], dtype=np.float64)
        if values.size != 16:
            raise ReaderError(self._pose(fid), f"odomToCamera has {values.size} values, expected 16", frame=fid)
        return check_rigid(values.reshape(4, 4), self._pose(fid), fid, "odomToCamera")

    # -- velocities ----------------------------------------------------------------------------

    def _ego_velocity(self, fid: str, radar_now: np.ndarray, T_cam_radar: np.ndarray) -> np.ndarray:
        fit = fit_compensation_pair(radar_now[:, :3], radar_now[:, 4], radar_now[:, 5])
        if fit.n_used >= 3 and fit.condition <= MAX_FIT_CONDITION:
            self._counts["ego_from_doppler_pair"] += 1
            return fit.velocity_D
        velocity = self._ego_from_poses(fid, T_cam_radar)
        if velocity is None:
            raise ReaderError(self._radar_bin(fid), f"cannot determine ego velocity: Doppler fit unusable "
                                                    f"({fit.n_used} points) and no neighbouring poses", frame=fid)
        self._counts["ego_from_poses"] += 1
        return velocity

    def _ego_from_poses(self, fid: str, T_cam_radar: np.ndarray) -> np.ndarray | None:
        """Radar velocity in {D} by differencing the radar origin in the odometry frame."""
        T_now = self._T_world_cam(fid)
        if T_now is None:
            return None
        origin = {}
        for step in (-1, 1):
            other = self._neighbour(fid, step)
            T = self._T_world_cam(other) if other else None
            if T is not None:
                origin[step] = ((T @ T_cam_radar)[:3, 3], self._timestamp(other))
        if not origin:
            return None
        here = ((T_now @ T_cam_radar)[:3, 3], self._timestamp(fid))
        (p0, t0), (p1, t1) = origin.get(-1, here), origin.get(1, here)
        R_world_radar = (T_now @ T_cam_radar)[:3, :3]
        return R_world_radar.T @ ((p1 - p0) / (t1 - t0))

    def _labels(self, fid: str, T_radar_rect: np.ndarray, T_cam_radar: np.ndarray,
                T_radar_lidar: np.ndarray) -> list[Object3D]:
        """The frame's labels in {D}; ``T_radar_rect`` maps their frame (the rectified reference
        camera) to {D}, ``T_cam_radar`` {D} to the pose's camera (rotations only matter there);
        boxes upright in the lidar frame (``T_radar_lidar``) where :attr:`labels_lidar_boxes`."""
        path = self.root / "lidar" / "training" / "label_2" / f"{fid}.txt"
        if not path.is_file():
            return []
        labels = self._label_lines(path, fid)
        tracked = self._has_track_ids(labels)
        if self.labels_lidar_boxes:
            objects = [lidar_box_label_to_object(lab, T_radar_rect, T_radar_lidar, lab.column2 if tracked else -1)
                       for lab in labels]
        else:
            objects = [label_to_object(lab, T_radar_rect, lab.column2 if tracked else -1) for lab in labels]
        if labels and not tracked:
            self._counts["frames_without_track_ids"] += 1
        self._object_velocities(fid, labels, objects, T_cam_radar)
        return objects

    labels_lidar_boxes = True
    """View-of-Delft's boxes are annotated upright in the lidar frame and read as its devkit reads
    them (:func:`lidar_box_label_to_object`); the generated world's are upright in its level camera."""
    labels_hold_track_ids = False
    """Whether the second label column always holds track ids (the generated world). For VoD it is
    a track id in the tracking release but a 0 / 1 flag in the detection release, so there it
    counts as a track id only where the values are unique within the frame and one exceeds 1 (a
    frame whose ids are all 0 or 1 is read as untracked: its boxes are then matched by position)."""

    def _has_track_ids(self, labels: list[KittiLabel]) -> bool:
        ids = [lab.column2 for lab in labels]
        unique = len(set(ids)) == len(ids) and all(i >= 0 for i in ids)
        return unique and (self.labels_hold_track_ids or max(ids, default=0) > 1)

    def _label_lines(self, path: Path, fid: str) -> list[KittiLabel]:
        return list(self._parsed(path, lambda: [lab for lab in parse_label_file(path, fid)
                                                if lab.class_name != "DontCare"]))  # placeholders, no box

    @staticmethod
    def _centres_world(labels: list[KittiLabel], T_world_cam: np.ndarray) -> np.ndarray:
        """(N, 3) m: the boxes' centres in the odometry world frame (the label frame taken as the
        pose's camera: a constant offset between them cancels in a velocity)."""
        centres = np.array([lab.location_cam - [0.0, lab.size_hwl_m[0] / 2, 0.0] for lab in labels]).reshape(-1, 3)
        return centres @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]

    def _neighbour_boxes(self, fid: str | None) -> tuple[list[KittiLabel], np.ndarray, float] | None:
        """(labels, their centres (N, 3) m in the odometry world, time s) of a neighbouring frame
        with a pose and a label file; None otherwise."""
        if fid is None:
            return None
        path = self.root / "lidar" / "training" / "label_2" / f"{fid}.txt"
        T = self._T_world_cam(fid)
        if T is None or not path.is_file():
            return None
        labels = self._label_lines(path, fid)
        return labels, self._centres_world(labels, T), self._timestamp(fid)

    def _same_objects(self, labels: list[KittiLabel], centres: np.ndarray, t: float,
                      other: tuple[list[KittiLabel], np.ndarray, float]) -> tuple[np.ndarray, bool]:
        """((N,) index of each box's object among ``other``'s boxes or -1, whether by position): by
        track id and class where both frames hold track ids, else by
        :func:`pipeline.boxmatch.match_boxes`."""
        other_labels, other_centres, t_other = other
        if self._has_track_ids(labels) and self._has_track_ids(other_labels):
            where = {(lab.column2, lab.class_name): k for k, lab in enumerate(other_labels)}
            return np.array([where.get((lab.column2, lab.class_name), -1) for lab in labels], np.int64), False
        return match_boxes(centres, [lab.class_name for lab in labels], other_centres,
                           [lab.class_name for lab in other_labels], MAX_OBJECT_SPEED_MPS * abs(t_other - t)), True

    def _object_velocities(self, fid: str, labels: list[KittiLabel], objects: list[Object3D],
                           T_cam_radar: np.ndarray) -> None:
        """Set each object's velocity over ground in {D} from its box in the neighbouring frames
        (central difference where both have it, one-sided where one does); NaN stays where neither
        has it, or the frame has no pose. Counted by how the boxes were associated."""
        T_now = self._T_world_cam(fid)
        if not labels or T_now is None:
            if labels:
                self._counts["objects_velocity_unknown"] += len(labels)
            return
        centres, t = self._centres_world(labels, T_now), self._timestamp(fid)
        neighbours = []
        by_position = np.zeros(len(labels), bool)
        for step in (-1, 1):
            other = self._neighbour_boxes(self._neighbour(fid, step))
            if other is None:
                continue
            same, positional = self._same_objects(labels, centres, t, other)
            neighbours.append((same, other[1], other[2]))
            by_position |= positional & (same >= 0)
        v_world = differenced_velocities(centres, t, neighbours)
        known = ~np.isnan(v_world[:, 0])
        v_D = v_world[known] @ (T_now @ T_cam_radar)[:3, :3]  # R_radar_world @ v for each row
        for obj, v in zip((o for o, k in zip(objects, known) if k), v_D):
            obj.velocity_D = v.astype(np.float32)
        for key, count in (("by_track_id", known & ~by_position), ("by_box_matching", known & by_position),
                           ("unknown", ~known)):
            if count.any():
                self._counts[f"objects_velocity_{key}"] += int(count.sum())


class SyntheticReader(VodReader):
    """The project's generated world: VoD layout with PNG images and per-point radar meta files."""

    name = "synthetic"
    version = 1
    """The world's frames read as before VoD's version 2 (its labels always hold track ids and are
    upright in its level camera)."""
    labels_hold_track_ids = True
    labels_lidar_boxes = False

    def __init__(self, cfg: Config, data_root: str | Path, radar_folder: str = "radar") -> None:
        super().__init__(cfg, data_root, radar_folder=radar_folder, with_meta=True)
