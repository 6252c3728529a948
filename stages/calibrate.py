"""calibrate: raw dataset files -> one consistent frame record per frame at the working resolution.

Reads: the raw dataset through its reader (pipeline.readers).
Writes (calibrate.zarr, one chunk per frame):
  image (h, w, 3) uint8 RGB at camera.working_size (rows camera.crop_rows kept, then resized);
  K (3, 3) float64 intrinsics of that image; T_radar_cam, T_radar_lidar (4, 4) float64;
  lidar (<= lidar.store_max_points, 3) float32 m in {D}: points in the camera view within
  radar.max_range_m + lidar.range_margin_m; radar (<= radar.store_max_points, 5) float32
  [x, y, z m in {D}, range rate m/s, RSS]: points in the common field of view within max range;
  radar_object, radar_material (same rows, int32; -2 when the dataset has no such side data);
  labels (<= 64, 13) float32 [centre xyz, l w h, yaw, pitch, roll, velocity xyz, track id] in {D}
  (pipeline.frame.LABEL_COLUMNS; the rotation Rz(yaw) Ry(pitch) Rx(roll), pipeline.frame.box_rotations);
  ego_velocity (3,) float64 m/s in {D}; ego_velocity_known bool (False: the dataset records no
  motion for the frame, ego_velocity is zero); timestamp float64 s; sequence str; split int8
  (0 train, 1 val, 2 test); has_radar bool; radar_beyond_range int32, the radar points in the
  common field of view but beyond radar.max_range_m (dropped, as the method has it; counted so
  that a run says how many: summarise()); reader_counts (K,) int32, only for a reader that gives
  per-frame counts (Reader.frame_counts: MSC-Rad4R's axis order, Doppler check and lidar beams
  without a return), the frame's own counts in that order, which summarise() sums.
Config: dataset.*, camera.*, radar fov/range/capacity and Doppler convention (the readers read the
recorded radar with its own profile's: pipeline.config.own_radar), lidar.*, split.*.
"""

from __future__ import annotations

import warnings

import numpy as np

from pipeline.cache import DONE
from pipeline.config import Config
from pipeline.errors import FrameError
from pipeline.frame import LABEL_COLUMNS, label_rows
from pipeline.executor import FrameInputs, process_memo
from pipeline.geometry import cartesian_to_spherical, invert_transform
from pipeline.readers import reader_class
from pipeline.split import SplitFallbackWarning, assign_split
from pipeline.stage import ArraySpec, FrameStage
from pipeline.working import common_fov_mask, crop_resize

MAX_LABELS = 64

VERSION = 3
"""Bump when the outputs change for the same inputs (2: ego_velocity_known, radar_beyond_range; 3: labels
gain the pitch and roll columns). Not bumped for reader_counts (2026-12-07): only the MSC-Rad4R reader
gives counts, and its own version (5, in this stage's fingerprint: Pipeline.fingerprint) recomputes
its outputs, while the other datasets' outputs are as before."""

CONFIG_KEYS = (
    "dataset.reader", "dataset.world_frames", "dataset.world_seed", "dataset.world_resolution", "dataset.world_sequence_len",
    "dataset.radar_mount_T_radar_lidar", "dataset.msc_doppler_field",
    "camera.full_size", "camera.crop_rows", "camera.working_size",
    "radar.fov_az_deg", "radar.fov_el_deg", "radar.max_range_m", "radar.store_max_points",
    "radar.doppler_sign", "radar.doppler_span_mps",  # how the readers of Astyx and MSC-Rad4R read Doppler
    "lidar.store_max_points", "lidar.range_margin_m",
    "split.rule", "split.fractions", "split.block_len", "split.seed",
)


def outputs(cfg: Config) -> tuple[ArraySpec, ...]:
    w, h = cfg.camera.working_size
    nr, nl = cfg.radar.store_max_points, cfg.lidar.store_max_points
    return (
        ArraySpec("image", (h, w, 3), "uint8", "RGB 0-255"),
        ArraySpec("K", (3, 3), "float64", "pixels", finite=True),
        ArraySpec("T_radar_cam", (4, 4), "float64", "rigid transform {C}->{D}, m", finite=True),
        ArraySpec("T_radar_lidar", (4, 4), "float64", "rigid transform {L}->{D}, m", finite=True),
        ArraySpec("lidar", (nl, 3), "float32", "m in {D}", fill=np.nan, ragged=True, finite=True),
        ArraySpec("radar", (nr, 5), "float32", "x,y,z m in {D}; range rate m/s; RSS", fill=np.nan, ragged=True,
                  finite=True),
        ArraySpec("radar_object", (nr,), "int32", "object id (-1 ghost/clutter, -2 unknown)", fill=-2, ragged=True),
        ArraySpec("radar_material", (nr,), "int32", "material id (-1 ghost/clutter, -2 unknown)", fill=-2, ragged=True),
        ArraySpec("labels", (MAX_LABELS, len(LABEL_COLUMNS)), "float32", ",".join(LABEL_COLUMNS), fill=np.nan, ragged=True),
        ArraySpec("ego_velocity", (3,), "float64", "m/s in {D}", finite=True),
        ArraySpec("ego_velocity_known", (), "bool", "the dataset records the frame's motion", fill=False),
        ArraySpec("timestamp", (), "float64", "s"),
        ArraySpec("sequence", (), "str", "sequence id", fill=""),
        ArraySpec("split", (), "int8", "0 train, 1 val, 2 test", fill=-1),
        ArraySpec("has_radar", (), "bool", "dataset records radar", fill=False),
        ArraySpec("radar_beyond_range", (), "int32", "radar points in the field of view beyond max range (dropped)",
                  fill=-1),
    ) + _counts_spec(cfg)


def _counts_spec(cfg: Config) -> tuple[ArraySpec, ...]:
    """reader_counts, for a reader that gives per-frame counts (Reader.frame_counts); none for the
    others, whose outputs and caches stay as they were."""
    keys = reader_class(cfg).frame_counts
    return (ArraySpec("reader_counts", (len(keys),), "int32", "per-frame counts of the reader: " + ", ".join(keys),
                      fill=-1),) if keys else ()


def _split_table(inputs: FrameInputs) -> dict[str, int]:
    """Split of every frame of the dataset (computed once per process and RunEnv.session)."""
    cfg = inputs.cfg

    def build() -> dict[str, int]:
        reader = inputs.reader
        ids = reader.frame_ids()
        seqs = [reader.sequence_of(f) for f in ids]
        s = cfg.split
        with warnings.catch_warnings():  # said once, on the stage's summary (summarise), not per worker
            warnings.simplefilter("ignore", SplitFallbackWarning)
            parts = assign_split(ids, seqs, s.rule, tuple(s.fractions), s.block_len, s.seed)
        return dict(zip(ids, (int(p) for p in parts)))

    return process_memo(("split", inputs.env.data_root, cfg.split, cfg.dataset, inputs.env.session), build)


def _labels_array(labels) -> np.ndarray:
    return label_rows(labels[:MAX_LABELS]).astype(np.float32)


MIN_POINTS_TO_JUDGE = 50
"""A sensor with at least this many points of which none lands in the camera's view points at a
wrong calibration (mirrored, in millimetres, another sensor's matrix): the frame fails."""


def _check_view(frame_id: str, n_lidar: int, n_lidar_kept: int, n_radar: int, n_radar_kept: int) -> None:
    """FrameError when a sensor has points but none inside the camera's view and range."""
    for name, n, kept in (("lidar", n_lidar, n_lidar_kept), ("radar", n_radar, n_radar_kept)):
        if n >= MIN_POINTS_TO_JUDGE and kept == 0:
            raise FrameError("calibrate", frame_id, f"none of the {n} {name} points lies in the camera's view "
                                                    f"and range: the calibration is probably wrong")


def process(inputs: FrameInputs, cfg: Config) -> dict[str, np.ndarray]:
    """Read one frame and bring it to the working resolution and the common field of view."""
    rec = inputs.reader.read(inputs.frame_id)
    full_w, full_h = cfg.camera.full_size
    if rec.image.shape[:2] != (full_h, full_w):
        raise FrameError("calibrate", inputs.frame_id,
                         f"image is {rec.image.shape[1]}x{rec.image.shape[0]}, the profile expects {full_w}x{full_h}")
    image_w, K_w = crop_resize(rec.image, rec.K, tuple(cfg.camera.crop_rows), tuple(cfg.camera.working_size))
    T_cam_radar = invert_transform(rec.T_radar_cam)
    fov = (cfg.radar.fov_az_deg, cfg.radar.fov_el_deg)
    size = tuple(cfg.camera.working_size)
    n = len(rec.radar_D)
    in_view = common_fov_mask(rec.radar_D[:, :3], K_w, T_cam_radar, size, *fov, np.inf) if n else np.zeros(0, bool)
    kept = in_view & (cartesian_to_spherical(rec.radar_D[:, :3])[:, 0] <= cfg.radar.max_range_m)
    radar = rec.radar_D[kept]
    keep_lidar = common_fov_mask(rec.lidar_D, K_w, T_cam_radar, size, 360.0, 180.0,
                                 cfg.radar.max_range_m + cfg.lidar.range_margin_m)
    lidar = rec.lidar_D[keep_lidar]
    _check_view(inputs.frame_id, len(rec.lidar_D), len(lidar), n, int(kept.sum()))
    cap = cfg.lidar.store_max_points
    if len(lidar) > cap:
        lidar = lidar[np.sort(inputs.rng(0, 7).choice(len(lidar), cap, replace=False))]
    obj = rec.extras.get("object_id", np.full(n, -2, np.int32))[kept]
    mat = rec.extras.get("material", np.full(n, -2, np.int32))[kept]
    keys = reader_class(cfg).frame_counts  # as outputs() declared them
    counts = {"reader_counts": np.array([rec.counts[k] for k in keys], np.int32)} if keys else {}
    return {
        "image": image_w, "K": K_w, "T_radar_cam": rec.T_radar_cam, "T_radar_lidar": rec.T_radar_lidar,
        "lidar": lidar.astype(np.float32), "radar": radar.astype(np.float32),
        "radar_object": obj.astype(np.int32), "radar_material": mat.astype(np.int32),
        "labels": _labels_array(rec.labels), "ego_velocity": np.asarray(rec.ego_velocity_D, np.float64),
        "ego_velocity_known": np.bool_(rec.ego_velocity_known),
        "radar_beyond_range": np.int32(in_view.sum() - kept.sum()),
        "timestamp": np.float64(rec.timestamp_s), "sequence": np.asarray(rec.sequence_id, dtype=object),
        "split": np.int8(_split_table(inputs)[inputs.frame_id]), "has_radar": np.bool_(rec.has_radar), **counts,
    }


def summarise(store, cfg: Config) -> list[str]:
    """What the finished frames lost or lack, one line each (none when nothing): radar points
    dropped beyond radar.max_range_m, frames without a recorded ego motion, labelled objects of
    unknown velocity, a 'sequence' split that fell back to blocks; and the sums of the reader's
    per-frame counts in its own words (Reader.counts_summary: MSC-Rad4R's radar axis order, Doppler
    check and lidar beams without a return), said on every run."""
    done = store.status() == DONE
    n_done = int(done.sum())
    if not n_done:
        return []
    lines = _split_fallback(store, cfg, done)
    beyond = np.asarray(store.array("radar_beyond_range")[:])[done].astype(np.int64)
    kept = np.asarray(store.array("radar_count")[:])[done].astype(np.int64)
    known = np.asarray(store.array("ego_velocity_known")[:], bool)[done]
    if beyond.sum():
        share = beyond.sum() / (beyond.sum() + kept.sum())
        lines.append(f"radar points beyond radar.max_range_m = {cfg.radar.max_range_m:g} m dropped: {beyond.sum():,} of "
                     f"{beyond.sum() + kept.sum():,} in the field of view ({share:.0%}), on "
                     f"{np.count_nonzero(beyond)} of {n_done} frames")
    if not known.all():
        lines.append(f"ego velocity unknown on {np.count_nonzero(~known)} of {n_done} frames (the dataset records no "
                     f"motion for them): their Doppler is synthesized as for a stopped car")
    labels = np.asarray(store.array("labels")[:])[done]  # (F, MAX_LABELS, len(LABEL_COLUMNS)), NaN beyond each frame's count
    real = np.arange(labels.shape[1])[None, :] < np.asarray(store.array("labels_count")[:])[done][:, None]
    unknown = real & ~np.isfinite(labels[..., LABEL_COLUMNS.index("vx")])
    if unknown.any():
        lines.append(f"labelled objects of unknown velocity: {int(unknown.sum()):,} of {int(real.sum()):,}: their "
                     f"points get a static object's Doppler (the export lists their frames)")
    return lines + _reader_counts(store, cfg, done)


def _reader_counts(store, cfg: Config, done: np.ndarray) -> list[str]:
    """The reader's lines on its per-frame counts summed over the ``done`` frames (none for a
    reader without counts)."""
    reader = reader_class(cfg)
    if not reader.frame_counts:
        return []
    totals = np.asarray(store.array("reader_counts")[:])[done].astype(np.int64).sum(axis=0)
    return reader.counts_summary(dict(zip(reader.frame_counts, (int(v) for v in totals))), int(done.sum()))


def _split_fallback(store, cfg: Config, done: np.ndarray) -> list[str]:
    """The line saying that split.rule 'sequence' fell back to blocks (too few sequences for the
    parts: pipeline.split), where a sequence of the ``done`` frames lies in several parts (the rule
    itself never splits one); until 2026-12-07 a Python warning with its source line, from every
    worker process."""
    if cfg.split.rule != "sequence":
        return []
    seqs = np.asarray(store.array("sequence")[:], dtype=object)[done].astype(str)
    split = np.asarray(store.array("split")[:])[done]
    pairs = np.unique(np.stack([seqs, split.astype(str)]), axis=1)  # (2, distinct sequence-part pairs)
    names, parts_per_seq = np.unique(pairs[0], return_counts=True)
    n_split = int((parts_per_seq > 1).sum())
    if not n_split:
        return []
    return [f"split.rule = 'sequence': too few sequences for the {np.count_nonzero(cfg.split.fractions)} parts, so "
            f"blocks of {cfg.split.block_len} frames inside sequences were assigned instead (sequences here that "
            f"lie in several parts: {n_split} of {len(names)})"]


STAGE = FrameStage(name="calibrate", upstream=(), config_keys=CONFIG_KEYS, outputs=outputs, process=process,
                   version=VERSION, doc=__doc__, summarise=summarise)
