"""The Reader base class and the checks every reader applies to raw files.

A reader turns one dataset layout into :class:`pipeline.frame.FrameRecord` s in the conventions of
``pipeline/frame.py``. Everything wrong with an input file is a :class:`ReaderError` whose one-line
message names the file, the frame and the problem; readers never return partial records silently.
"""

from __future__ import annotations

import os
import stat
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.config import Config, RadarSection, own_radar
from pipeline.errors import PipelineError, ReaderError
from pipeline.frame import FrameRecord
from pipeline.geometry import cartesian_to_spherical, invert_transform

MAX_EGO_SPEED_MPS = 70.0
"""Ego speeds above this (252 km/h) are treated as a corrupt input, m/s."""


@dataclass(frozen=True)
class DetectorFiles:
    """What the export stage carries over from the raw dataset for one frame (None: not in the
    dataset; the export generates the calib and writes the reader's image).

    ``calib``: a KITTI calib file to copy, or its matrices ({key: matrix}, the keys of
    ``pipeline.export.CALIB_KEYS``) with ``Tr_velo_to_cam`` mapping the radar frame {D} to camera 0
    (before R0_rect); ``label``: a KITTI label file (boxes in the rectified camera 0); ``image``:
    the image file, when it is the reader's image as it is; ``label_track_ids``: the label's second
    column holds track ids, not KITTI's truncation; ``objects_labelled``: without a label file, the
    frame's annotation is the reader's ``labels`` (its own format: the export writes them as KITTI
    labels for the generated calib).
    """

    calib: Path | dict[str, np.ndarray] | None = None
    label: Path | None = None
    image: Path | None = None
    label_track_ids: bool = False
    objects_labelled: bool = False


class Reader:
    """Base class of the dataset readers.

    Subclasses implement :meth:`frame_ids`, :meth:`sequence_of` and :meth:`read`; they count what
    they skip in ``self._counts`` (reported by :meth:`report`: the running totals of this instance,
    which a worker process shares over its frames). What a run is to say per frame they give in
    each record's ``counts`` (:attr:`frame_counts`). Construction does no heavy work: the index is
    built lazily on first use.
    """

    name = "base"
    version = 1
    """Bumped when what the reader returns for the same files changes: part of the first stage's
    fingerprint from 2 on (so caches made by an earlier version are recomputed)."""
    frame_counts: tuple[str, ...] = ()
    """The keys of each record's ``counts`` (FrameRecord), in this order: calibrate stores them per
    frame (its ``reader_counts`` array, declared only for a reader that gives some) and its summary
    says their sums over the finished frames (:meth:`counts_summary`)."""

    def __init__(self, cfg: Config, data_root: str | Path) -> None:
        self.cfg = cfg
        self.radar = own_radar(cfg)
        """The recorded radar's settings (with train.nets_from the dataset's own, not the nets')."""
        self.root = Path(data_root)
        self._counts: Counter[str] = Counter()
        self._missing: list[str] = []

    SKIPPED_SHOWN = 3
    """How many skipped frames :meth:`skipped_examples` names."""

    def frame_ids(self) -> list[str]:
        """Sorted ids of all frames whose files are present (absent ones are skipped and counted)."""
        raise NotImplementedError

    def sequence_of(self, frame_id: str) -> str:
        """Name of the sequence (continuous recording) the frame belongs to."""
        raise NotImplementedError

    def read(self, frame_id: str) -> FrameRecord:
        """The validated record of one frame; ReaderError for anything wrong with its files."""
        raise NotImplementedError

    def report(self) -> dict:
        """Counters of what the reader skipped or dropped, e.g. ``{"skipped_missing": 3}``."""
        return dict(self._counts)

    @classmethod
    def counts_summary(cls, totals: dict[str, int], n_frames: int) -> list[str]:
        """Lines for calibrate's summary from ``totals``, the sums of the :attr:`frame_counts` over
        ``n_frames`` finished frames; none for a reader without per-frame counts."""
        return []

    def skip_missing(self, frame_id: str, missing: list[Path | str]) -> None:
        """Count a frame skipped for want of files, and keep the first few as examples."""
        self._counts["skipped_missing"] += 1
        if len(self._missing) < self.SKIPPED_SHOWN:
            names = [os.path.relpath(p, self.root) if os.path.isabs(p) else str(p) for p in missing]
            self._missing.append(f"{frame_id}: no {' or '.join(names)}" if names else frame_id)

    def skipped_examples(self) -> list[str]:
        """The first frames skipped for want of files, each with what it lacks ('01047: no
        lidar/training/velodyne/01047.bin'); empty where the reader does not say."""
        return list(self._missing)

    def detector_files(self, frame_id: str) -> DetectorFiles:
        """The frame's calib, label and image files for a detector's KITTI layout (export stage)."""
        return DetectorFiles()

    def layout_hint(self) -> str:
        """The files one frame needs, relative to the data root (said when no frame is found);
        empty when the reader says more itself."""
        return ""

    def skipped_text(self) -> str:
        """' (e.g. 01047: no lidar/training/velodyne/01047.bin; ...)': the frames of
        :meth:`skipped_examples`, or '' when none was skipped for want of files."""
        examples = "; ".join(self.skipped_examples())
        return f" (e.g. {examples})" if examples else ""

    def no_frames_error(self, data_root: str) -> PipelineError:
        """The error for ``data_root`` (as the user gave it) where :meth:`frame_ids` lists no frame:
        what a frame needs (:meth:`layout_hint`) and the frames skipped for want of files."""
        hint, examples = self.layout_hint(), self.skipped_text()
        return PipelineError(f"dataset at {data_root}: no frames found" + (f" (a frame needs {hint})" if hint else "")
                             + (f"; frames skipped for want of files{examples}" if examples else ""))

    # -- helpers shared by the subclasses -------------------------------------------------------

    def finish(self, record: FrameRecord, path: Path) -> FrameRecord:
        """Run the record's own validation and the physical plausibility checks; return it."""
        try:
            record.validate()
        except ValueError as exc:
            raise ReaderError(path, f"invalid frame record: {exc}", frame=record.frame_id) from None
        check_ego_speed(record.ego_velocity_D, path, record.frame_id)
        if record.has_radar:
            check_radar_fov(record.radar_D[:, :3], self.radar, path, record.frame_id)
        return record


def require_file(path: Path, frame: str | None, what: str) -> Path:
    """Return ``path`` if it is a file, else raise ReaderError('missing <what>')."""
    if not path.is_file():
        raise ReaderError(path, f"missing {what} file", frame=frame)
    return path


def inside_root(root: Path, relative: str, frame: str | None, index_file: Path,
                resolved: dict[Path, Path] | None = None, follow_links: bool = False) -> Path:
    """Resolve ``relative`` under ``root``; ReaderError if it is absolute or leaves the root, also
    through a symlink (an index may come from an untrusted source), or runs into a symlink loop.
    With ``follow_links`` (``dataset.follow_links``: the root's folders are links the user made to
    storage elsewhere) only an absolute entry or one whose '..' parts climb out of the root is
    refused; links are followed wherever they lead.

    ``resolved``: the resolved folders of the calls so far ({folder: resolved}), for an index of
    many entries in a few folders: only the file itself is then looked at (the folders of 546
    Astyx entries resolved anew each time took 1 ms an entry; a missing file is no link, and
    its folder's resolution decides too). An entry with a '..' part, or whose file is a link or
    cannot be looked at for another reason than its absence, is resolved whole; a folder
    replaced by a link while one index is read is not noticed (as a file replaced between this
    check and its read)."""
    rel = Path(relative)
    if follow_links:
        if rel.is_absolute() or os.path.normpath(rel).split(os.sep)[0] == "..":
            raise ReaderError(index_file, f"index entry '{relative}' points outside the dataset root {root}",
                              frame=frame)
        return root / rel
    cache = {} if resolved is None else resolved
    try:
        path = root / rel
        whole = ".." in rel.parts or rel.name in ("", ".")
        if not whole:
            try:
                whole = stat.S_ISLNK(os.lstat(path).st_mode)
            except FileNotFoundError:  # a missing file is no link: its folder decides, as for a file
                pass
            except OSError:  # a part of the path is no folder, a loop: resolve() decides
                whole = True
        if whole:
            target = path.resolve()
        else:
            if path.parent not in cache:
                cache[path.parent] = path.parent.resolve()
            target = cache[path.parent] / rel.name
        if root not in cache:
            cache[root] = root.resolve()
    except (RuntimeError, OSError) as exc:  # RuntimeError: a symlink loop (Python 3.11)
        raise ReaderError(index_file, f"index entry '{relative}' cannot be resolved ({exc})", frame=frame) from None
    if rel.is_absolute() or not target.is_relative_to(cache[root]):
        raise ReaderError(index_file, f"index entry '{relative}' points outside the dataset root {root} "
                                      f"(symlinks followed); if the root's folders are links you made to storage "
                                      f"elsewhere, `--set dataset.follow_links=true` reads through them (with "
                                      f"--retry-failed for the frames refused before)", frame=frame)
    return root / rel


def read_float32_records(path: Path, n_cols: int, frame: str | None, what: str) -> np.ndarray:
    """Read a little-endian float32 .bin file of ``n_cols`` values per record -> (N, n_cols) float32.

    Raises ReaderError if the file is missing, its size is not a multiple of the record size,
    or it holds non-finite values.
    """
    require_file(path, frame, what)
    size = path.stat().st_size
    record = 4 * n_cols
    if size % record:
        raise ReaderError(path, f"{what}: file size {size} bytes is not a multiple of {record} "
                                f"({n_cols} float32 per point): truncated or wrong record type", frame=frame)
    data = np.fromfile(path, dtype="<f4").reshape(-1, n_cols)
    check_finite(data, path, frame, what)
    return data


def check_finite(values: np.ndarray, path: Path, frame: str | None, what: str) -> None:
    """ReaderError if ``values`` has NaN or inf entries (names how many rows)."""
    bad = ~np.isfinite(np.asarray(values, dtype=np.float64))
    if bad.any():
        rows = int(bad.reshape(bad.shape[0], -1).any(axis=1).sum()) if bad.ndim > 1 else int(bad.sum())
        raise ReaderError(path, f"{what}: {rows} point(s) with NaN or inf values", frame=frame)


def check_not_empty(points: np.ndarray, path: Path, frame: str | None, what: str) -> None:
    """ReaderError if ``points`` has no rows."""
    if points.shape[0] == 0:
        raise ReaderError(path, f"{what}: frame has no points", frame=frame)


def check_rigid(T_dst_src: np.ndarray, path: Path, frame: str | None, what: str) -> np.ndarray:
    """Return ``T_dst_src`` (4, 4) float64 if it is an invertible rigid transform, else ReaderError."""
    T = np.asarray(T_dst_src, dtype=np.float64)
    try:
        invert_transform(T)
    except ValueError as exc:
        raise ReaderError(path, f"{what}: not an invertible rigid transform ({exc})", frame=frame) from None
    return T


def check_intrinsics(K: np.ndarray, path: Path, frame: str | None) -> np.ndarray:
    """Return K (3, 3) float64 if it is a finite pinhole matrix with positive focal lengths."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 \
            or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise ReaderError(path, f"camera intrinsics are not a valid pinhole matrix: {K.tolist()}", frame=frame)
    return K


def read_image_rgb(path: Path, frame: str | None, expected_wh: tuple[int, int] | None) -> np.ndarray:
    """Decode an image file with OpenCV -> (H, W, 3) uint8 RGB.

    ReaderError if the file is missing, cannot be decoded, or is not ``expected_wh`` (W, H) pixels.
    """
    require_file(path, frame, "image")
    buffer = np.fromfile(path, dtype=np.uint8)
    image = cv2.imdecode(buffer, cv2.IMREAD_COLOR) if buffer.size else None
    if image is None:
        raise ReaderError(path, "image cannot be decoded (corrupt or not an image)", frame=frame)
    height, width = image.shape[:2]
    if expected_wh is not None and (width, height) != tuple(expected_wh):
        raise ReaderError(path, f"image is {width}x{height} pixels, expected {expected_wh[0]}x{expected_wh[1]} "
                                "(camera.full_size)", frame=frame)
    return np.ascontiguousarray(image[:, :, ::-1])


def check_ego_speed(ego_velocity_D: np.ndarray, path: Path, frame: str | None) -> None:
    """ReaderError if the ego velocity is non-finite or faster than MAX_EGO_SPEED_MPS."""
    v = np.asarray(ego_velocity_D, dtype=np.float64)
    if not np.all(np.isfinite(v)):
        raise ReaderError(path, f"ego velocity is not finite: {v.tolist()}", frame=frame)
    speed = float(np.linalg.norm(v))
    if speed > MAX_EGO_SPEED_MPS:
        raise ReaderError(path, f"absurd ego speed {speed:.1f} m/s (> {MAX_EGO_SPEED_MPS:.0f} m/s)", frame=frame)


def fov_mask(points_D: np.ndarray, radar: RadarSection) -> np.ndarray:
    """(N,) bool: points (N, 3) in {D} inside the radar's azimuth/elevation FOV and range."""
    rae = cartesian_to_spherical(points_D)
    return ((np.abs(np.degrees(rae[:, 1])) <= radar.fov_az_deg / 2.0)
            & (np.abs(np.degrees(rae[:, 2])) <= radar.fov_el_deg / 2.0)
            & (rae[:, 0] <= radar.max_range_m) & (rae[:, 0] > 0))


def check_radar_fov(points_D: np.ndarray, radar: RadarSection, path: Path, frame: str | None) -> None:
    """ReaderError if a non-empty radar frame has no point inside the radar's field of view."""
    if points_D.shape[0] and not fov_mask(points_D, radar).any():
        raise ReaderError(path, f"all {points_D.shape[0]} radar points lie outside the field of view "
                                f"(az +/-{radar.fov_az_deg / 2:g} deg, el +/-{radar.fov_el_deg / 2:g} deg, "
                                f"range <= {radar.max_range_m:g} m): wrong axes or units?", frame=frame)


def split_sequences_at_gaps(numbers: list[int]) -> dict[int, str]:
    """Map sorted frame numbers to sequence names ``seq_<first>``, splitting where numbers jump."""
    out: dict[int, str] = {}
    name = ""
    prev = None
    for n in sorted(numbers):
        if prev is None or n != prev + 1:
            name = f"seq_{n:05d}"
        out[n] = name
        prev = n
    return out
