"""evaluate: fidelity of the synthesized radar against the real one, next to the baselines.

Two declarations, run in this order:

- ``evaluate-frames`` (FRAMES, a frame stage: resumable, on the executor like any frame stage)
  reads synthesize (points, pred_map, n_hat), calibrate (real radar, lidar, image, labels, ego
  velocity, sequence, timestamp; the previous frame's radar for ``previous-frame``), heatmaps
  (real heatmap, count) and train (mean training heatmap, training count and RSS statistics,
  RSS-Net, PlaceNet), and writes per frame of eval.split that synthesize finished (evaluate-frames.zarr):
  metrics (len(METHODS), len(FRAME_METRICS)) float64, every method's per-frame metrics (rows in
  pipeline.baselines.METHODS order, columns pipeline.metrics.FRAME_METRICS; NaN where absent);
  present (len(METHODS),) bool, whether the method has a result on the frame (``previous-frame``
  needs a previous frame of the same sequence); count (len(METHODS),) float64, the count each
  method decided; ego_speed () m/s; points (ragged, 7 columns) float64, every method's points and
  the real ones in spherical coordinates [method row (-1: real), range m, azimuth rad, elevation
  rad, range rate m/s, RSS] for the distribution distances and histograms; abs_dr (ragged, 5) m
  and abs_dv (ragged) m/s, the physics checks' per-point residuals (no learning).
- ``evaluate`` (STAGE, a dataset stage) reads evaluate-frames (and synthesize, calibrate for the
  figures) and writes (evaluate/) report.json, report.md (one table: model and baselines, mean and
  median over frames; Wasserstein distances; the model by ego speed; physics checks),
  figures/fig8.png, figures/bev.png, figures/histograms.png.

Config: eval.*, synth.* (baselines use the same generation steps), radar.*; with train.nets_from
the real radar is compared with another dataset's as pipeline.transfer.comparison says (the report
says what is left out).
Every method is evaluated on the same frames: those of eval.split that evaluate-frames finished
(``previous-frame`` on those of them with a previous frame).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.baselines import mean_count
from pipeline.cache import DONE, FAILED
from pipeline.cachefs import command_options
from pipeline.config import Config
from pipeline.errors import CacheError, PipelineError, first_sentence
from pipeline.executor import FrameInputs, process_memo, run_memo
from pipeline.geometry import invert_transform, project_to_image
from pipeline.metrics import region_mask
from pipeline.progress import EVERY_S, bar as progress_bar
from pipeline.stage import ArraySpec, DatasetStage, FrameStage
from stages.synthesize import (SPLITS, capacity, check_generation, generate, lidar_tree, models,
                               split_mask)
from stages.train import MEAN_MAP_FILE

MAX_FRAME_GAP_S = 1.0
"""The previous-frame baseline needs consecutive frames: a previous frame further back than this
(Astyx's subset skips seconds to a minute between many neighbouring ids) gives it no points for
the frame (absent, like a first frame)."""
CLOCK_WRAP_S = 3600.0
"""Timestamps that wrap (Astyx: the lidar's microseconds past the hour): a negative gap is taken
modulo this."""

VERSION = 11
"""Bump when the report's rows or numbers change for the same inputs (2: model-oracle-map row, one
random stream per method; 3: no-points row; 4: the model by ego speed; 5: physics checks with the
share within 1 m and the best-lidar-point oracle; 6: the baselines follow synth.placement; 7: the
baselines sample their maps at full weight, pipeline.baselines.generation_config; 8: per-frame
results in evaluate-frames.zarr; 9: previous-frame only from consecutive frames (gap <= 1 s) and
restricted to the evaluated region; the static-point Doppler check leaves out points in boxes of
unknown velocity; 10: nets of another dataset (train.nets_from) compared as pipeline.transfer.comparison
says: no RSS across RSS units, Doppler modulo the span of the radar that wraps; the physics checks
with the real radar's own span; 11: the Doppler distribution distance on the circle of a radar that
wraps Doppler). The report (STAGE) has its own REPORT_VERSION from 12 on (13: with another dataset's
nets the report says that the baselines know this dataset's own radar)."""
REPORT_VERSION = 19
"""The evaluate report's version (12: the RSS histogram bins each set apart when the units differ;
14: the model compared with a baseline on the frames both have, the frames per row in the table;
15: not compared with one that has none of its frames; 16: the count's parts, count_parts; 17: a
method's distribution distances against the real points of the frames it has, not of every frame;
18: the histograms' axes labelled with their units, the RSS panel's with the radar's RSS unit;
19: the bird's-eye view sized to its panels, one legend above them); evaluate-frames keeps VERSION."""

RANGE_CHECK_TOLERANCE_M = 1.0
"""The physics checks report the share of real points whose lidar range is within this of the
measured range (the matched-F1 gate's default)."""
RANGE_ESTIMATORS = ("mean", "nearest", "median", "min")
"""Range rules of the physics check (a); a fifth column, 'best', is the oracle (the window's lidar
point closest to the measured range)."""

READ_BYTES = 64 << 20
"""The report reads about this many bytes of one ragged array's chunks at a time, at least one
frame's (a frame's chunk holds the array's whole capacity: about 1 MB of points on the demo
world); the read's peak is 2-4 times as much (the block, the decoded bytes, the rows taken)."""

CONFIG_KEYS = ("eval.split", "eval.figure_frames", "eval.pooled_rows_max", "eval.gate_m", "eval.gate_rss",
               "eval.gate_doppler_mps", "synth.range_estimator", "synth.no_support", "synth.seed", "synth.sampling",
               "synth.rss_sampling", "synth.refill_rounds",
               "synth.placement", "placement.voxel_m", "placement.map_weight", "heatmap.sigma_px",
               "radar.doppler_span_mps", "radar.az_res_deg", "radar.el_res_deg")
FRAME_KEYS = tuple(k for k in CONFIG_KEYS if k not in ("eval.figure_frames", "eval.pooled_rows_max"))
"""Configuration of the per-frame results (the figures and the pooling are the report's)."""


def _train_counts(inputs) -> tuple[np.ndarray, np.ndarray]:
    """The training frames with radar points in the image (indices) and every frame's count."""
    calib, heat = inputs.store("calibrate"), inputs.store("heatmaps")
    split = np.asarray(calib.array("split")[:])
    ok = (calib.status() == DONE) & (heat.status() == DONE)
    counts = np.asarray(heat.array("count")[:])
    return np.flatnonzero(ok & (split == 0) & (counts > 0)), counts


def _train_stats(inputs, cfg: Config) -> dict:
    """Training-split statistics the baselines use: mean count, mean map, RSS values."""
    patches = inputs.store("patches")
    train, counts = _train_counts(inputs)
    mean_map = read_mean_map(inputs, cfg)
    pc = np.asarray(patches.array("rss_count")[:])
    rss = np.asarray(patches.array("rss").oindex[train])
    rss_values = np.concatenate([rss[k, :pc[f]] for k, f in enumerate(train)]) if len(train) else np.zeros(0)
    return {"n_bar": mean_count(counts[train]), "mean_map": mean_map,
            "train_rss": rss_values, "rss_median": float(np.median(rss_values)) if len(rss_values) else 0.0}


def read_mean_map(inputs, cfg: Config) -> np.ndarray:
    """The train stage's mean training heatmap (H, W) float32 (``inputs``: a RunEnv or the inputs of
    a stage). CacheError naming the file, what is wrong and the command that writes it again when it
    is missing or damaged (cannot be read as a plain .npy array, or is not a finite 2-D float map)."""
    train = inputs.dir("train")
    name = f"{train.url.rstrip('/')}/{MEAN_MAP_FILE}"
    try:
        mean_map = np.load(train.local_copy(cfg.run.staging_dir) / MEAN_MAP_FILE, allow_pickle=False)
    except FileNotFoundError:
        if not len(_train_counts(inputs)[0]):
            raise CacheError(f"{name} is not there: split 'train' has no finished frame with radar, whose mean "
                             "map the mean-map baseline needs (use more frames, or other split.* settings)") from None
        problem = "is missing"
    except (ValueError, EOFError, OSError) as exc:  # numpy's words for a damaged file end in pickle advice
        problem = f"is damaged: it cannot be read as a .npy array ({_npy_problem(exc)})"
    else:
        if mean_map.ndim == 2 and mean_map.dtype.kind == "f" and bool(np.isfinite(mean_map).all()):
            return mean_map
        problem = (f"is damaged: it holds a {mean_map.dtype} array of shape {mean_map.shape}, "
                   "not a finite 2-D map")
    env = getattr(inputs, "env", inputs)
    raise CacheError(f"{name} {problem}; write it again with `pipeline run train "
                     f"{command_options(env.dataset, env.cache_root)} --force` "
                     "(which trains the nets again), or restore the file from a copy of the cache")


def _npy_problem(exc: BaseException) -> str:
    """numpy's reason, in a few words (its advice to load pickled data is wrong here)."""
    text = " ".join(str(exc).split())
    if "pickled" in text or not text:
        return "not an .npy array header" if text else f"{type(exc).__name__}: the file ends early"
    return first_sentence(exc, 100)


def _shared(inputs: FrameInputs, cfg: Config) -> tuple[dict, list[str]]:
    """The training statistics and the frame ids, computed once per process and train run (the
    key holds the train stage's finishing time: a retrained net under the same fingerprint is
    another run)."""
    train = inputs.env.dir("train")

    def records() -> tuple:  # once a run (three requests a frame on a remote cache until 2026-12-07)
        meta = train.meta() or {}
        return (meta.get("fingerprint"), meta.get("finished"), inputs.env.store("calibrate").fingerprint(),
                inputs.env.store("patches").fingerprint())

    key = ("evaluate-shared", train.url, *run_memo(inputs.env, ("evaluate records", train.url), records))
    return process_memo(key, lambda: (_train_stats(inputs.env, cfg), inputs.env.store("calibrate").frame_ids()))


def _real(f) -> np.ndarray:
    """Real radar (M, 5) [x, y, z, range rate, rss] of the frame (already in the evaluated region)."""
    return f.get("calibrate", "radar").astype(np.float64)


def _syn5(points9: np.ndarray) -> np.ndarray:
    """Synthesize rows -> (N, 5) [x, y, z, range rate, rss]."""
    return points9[:, [0, 1, 2, 8, 7]].astype(np.float64)


def _static_mask(real: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Real points outside every labelled box that moves faster than 0.5 m/s or whose velocity is
    unknown (Astyx labels have none: its objects may move)."""
    from pipeline.synthesis import object_velocities_for_points

    if len(real) == 0:
        return np.zeros(0, bool)
    vel = object_velocities_for_points(real[:, :3], labels, unknown=np.nan)
    return np.linalg.norm(vel, axis=1) < 0.5   # False for NaN: inside a box of unknown velocity


def moved_previous_frame(prev_real: np.ndarray, prev_ego_velocity_D: np.ndarray, dt_s: float,
                         in_region) -> np.ndarray | None:
    """The previous-frame baseline: the previous frame's real points (M, 5) [x, y, z, range rate,
    rss], moved by the ego motion over ``dt_s`` (its ego velocity (3,) m/s) and kept where
    ``in_region`` ((N, 3) -> (N,) bool: the evaluated region, as the real points are); None when the
    frames are not consecutive (more than MAX_FRAME_GAP_S apart, after a clock wrap)."""
    from pipeline.baselines import ego_motion_transform, previous_frame

    dt = dt_s % CLOCK_WRAP_S if dt_s <= 0 else dt_s
    if not 0.0 < dt <= MAX_FRAME_GAP_S:
        return None
    pts = np.asarray(previous_frame(prev_real, ego_motion_transform(prev_ego_velocity_D, dt)), np.float64)
    return pts[in_region(pts[:, :3])]


PREVIOUS_READS = ("status", "sequence", "radar", "ego_velocity", "timestamp")
"""What the previous-frame baseline reads of the frame before (calibrate's arrays)."""


def _previous(f: FrameInputs, frame_ids: list[str]) -> FrameInputs | None:
    """The frame before ``f`` when calibrate finished it and it is of the same sequence, else None."""
    j = f.index - 1
    if j < 0:
        return None
    prev = FrameInputs(f.env, j, frame_ids[j])
    prev.prefetch([("calibrate", name) for name in PREVIOUS_READS])  # on a remote cache: at once
    if prev.get("calibrate", "status") != DONE:
        return None
    return prev if prev.get("calibrate", "sequence") == f.get("calibrate", "sequence") else None


def _methods_for_frame(f: FrameInputs, cfg: Config, stats: dict, nets, prev: FrameInputs | None,
                       real_map: np.ndarray) -> dict[str, tuple[np.ndarray, float, np.ndarray | None]]:
    """(points (N, 5), decided count, map or None) of every method on frame ``f``; ``real_map`` is
    the frame's real heatmap (H, W); ``prev`` the previous frame of its sequence (or None)."""
    from pipeline.baselines import METHODS, choose_count, choose_map, choose_rss, generation_config, lidar_subsample

    out = {}
    n_true = int(f.get("heatmaps", "count"))
    pred_map = f.get("synthesize", "pred_map")
    n_hat = float(f.get("synthesize", "n_hat"))
    size = tuple(cfg.camera.working_size)
    out["model"] = (_syn5(f.get("synthesize", "points")), n_hat, pred_map)
    for spec in METHODS:
        if spec.name == "model":
            continue
        rng = f.rng(cfg.synth.seed, zlib.crc32(spec.name.encode()))  # one stream per method
        if spec.kind == "map":
            n = choose_count(spec, stats["n_bar"], n_true, n_hat)
            prob = choose_map(spec, size, stats["mean_map"], pred_map, real_map)
            if prob is not None and not prob.sum() > 0:  # no real point in the image: nothing to sample
                out[spec.name] = (np.zeros((0, 5)), float(n), None)
                continue
            gen = generate(f, generation_config(spec, cfg), prob, n, nets, rng, rss=spec.rss_source == "model")
            pts = _syn5(gen["points"])
            rss = choose_rss(spec, len(pts), rng, stats["rss_median"], stats["train_rss"])
            if rss is not None:
                pts[:, 4] = rss
            out[spec.name] = (pts, float(n), prob)
        elif spec.kind == "lidar-subsample":
            T_cam_radar = invert_transform(f.get("calibrate", "T_radar_cam"))
            pts = lidar_subsample(f.get("calibrate", "lidar"), stats["n_bar"], cfg.radar.fov_az_deg,
                                  cfg.radar.fov_el_deg, cfg.radar.max_range_m, f.get("calibrate", "K"), T_cam_radar,
                                  size, rng, ego_velocity_D=f.get("calibrate", "ego_velocity"),
                                  rss_value=stats["rss_median"], doppler_span_mps=cfg.radar.doppler_span_mps)
            out[spec.name] = (np.asarray(pts, np.float64), float(stats["n_bar"]), None)
        elif spec.kind == "previous-frame" and prev is not None:
            pts = moved_previous_frame(
                _real(prev), prev.get("calibrate", "ego_velocity"),
                float(f.get("calibrate", "timestamp") - prev.get("calibrate", "timestamp")),
                lambda xyz: region_mask(xyz, cfg.radar.fov_az_deg, cfg.radar.fov_el_deg, cfg.radar.max_range_m,
                                        f.get("calibrate", "K"), invert_transform(f.get("calibrate", "T_radar_cam")),
                                        size))
            if pts is not None:
                out[spec.name] = (pts, float(len(pts)), None)
        elif spec.kind == "empty":
            out[spec.name] = (np.zeros((0, 5)), 0.0, None)
    return out


def frame_outputs(cfg: Config) -> tuple[ArraySpec, ...]:
    """evaluate-frames' arrays (module docstring)."""
    from pipeline.baselines import METHODS
    from pipeline.metrics import FRAME_METRICS

    m, real_cap = len(METHODS), cfg.radar.store_max_points
    points_cap = m * max(capacity(cfg), real_cap) + real_cap
    return (ArraySpec("metrics", (m, len(FRAME_METRICS)), "float64", "rows: METHODS, columns: FRAME_METRICS",
                      fill=np.nan),
            ArraySpec("present", (m,), "bool", "the method has a result on this frame", fill=False),
            ArraySpec("count", (m,), "float64", "points the method decided on", fill=np.nan),
            ArraySpec("ego_speed", (), "float64", "m/s", fill=np.nan),
            ArraySpec("points", (points_cap, 6), "float64",
                      "method row (-1 real), range m, azimuth rad, elevation rad, range rate m/s, rss",
                      fill=np.nan, ragged=True),
            ArraySpec("abs_dr", (real_cap, len(RANGE_ESTIMATORS) + 1), "float64",
                      f"m, |lidar range - radar range| per real point, rules {', '.join(RANGE_ESTIMATORS)}, best "
                      f"(NaN: no lidar support)", fill=np.nan, ragged=True),
            ArraySpec("abs_dv", (real_cap,), "float64", "m/s, |predicted - measured| Doppler of static real points",
                      fill=np.nan, ragged=True))


def evaluate_frame(f: FrameInputs, cfg: Config) -> dict[str, np.ndarray]:
    """Every method's metrics, points and the physics residuals of one frame (FRAMES' arrays)."""
    from pipeline.baselines import METHODS
    from pipeline.metrics import FRAME_METRICS, frame_metrics, rss_loss, to_spherical
    from pipeline.inference import rssnet_predict
    from stages.patches import point_inputs

    from pipeline.transfer import comparison

    stats, frame_ids = _shared(f, cfg)
    nets = models(f, cfg)
    compared = comparison(cfg)
    real = _real(f)
    target = f.get("heatmaps", "heatmap")
    rss_err = float("nan")
    if len(real) and compared.rss:
        patches, ranges = point_inputs(f.get("calibrate", "image"), f.get("calibrate", "K"),
                                       f.get("calibrate", "T_radar_cam"), f.get("calibrate", "lidar"), real[:, :3], cfg,
                                       lidar_tree(f, cfg))  # the frame's tree, which the model's placement uses too
        pred = rssnet_predict(nets.rssnet, patches, ranges, real[:, :4].astype(np.float32))
        rss_err = rss_loss(real[:, 4], pred, cfg.radar.rss_min, cfg.radar.rss_max)
    methods = _methods_for_frame(f, cfg, stats, nets, _previous(f, frame_ids), target)
    table = np.full((len(METHODS), len(FRAME_METRICS)), np.nan)
    present, count = np.zeros(len(METHODS), bool), np.full(len(METHODS), np.nan)
    points = [np.column_stack([np.full(len(real), -1.0), to_spherical(real)])]
    for row, spec in enumerate(METHODS):
        if spec.name not in methods:
            continue
        pts, n, prob = methods[spec.name]
        m = frame_metrics(pts, real, n_hat=n, target_map=target if prob is not None and len(real) else None,
                          pred_map=prob, rss_err=rss_err if spec.name == "model" else float("nan"),
                          gate_m=cfg.eval.gate_m, gate_rss=cfg.eval.gate_rss if compared.rss else np.inf,
                          gate_doppler=cfg.eval.gate_doppler_mps, doppler_span_mps=compared.doppler_span_mps)
        table[row] = [m[k] for k in FRAME_METRICS]
        present[row], count[row] = True, n
        points.append(np.column_stack([np.full(len(pts), float(row)), to_spherical(pts)]))
    abs_dr, abs_dv = physics_frame(f, cfg)
    return {"metrics": table, "present": present, "count": count,
            "ego_speed": np.float64(np.linalg.norm(f.get("calibrate", "ego_velocity"))),
            "points": np.concatenate(points), "abs_dr": abs_dr, "abs_dv": abs_dv}


def physics_frame(f: FrameInputs, cfg: Config) -> tuple[np.ndarray, np.ndarray]:
    """Physics checks of one real frame (no learning; reads calibrate only): abs_dr (M, 5) m, for
    each real radar point |lidar range at its angles - measured range| by each of RANGE_ESTIMATORS
    and by the window's lidar point closest to the measured range (an oracle: how often some lidar
    point of the window is right), NaN without lidar support; abs_dv (S,) m/s, |Doppler predicted
    from the ego velocity - measured| of the S static real points."""
    from pipeline.metrics import doppler_check, range_check
    from pipeline.synthesis import LidarAngularIndex
    from pipeline.transfer import comparison

    r = cfg.radar
    az_res, el_res = np.radians(r.az_res_deg), np.radians(r.el_res_deg)
    real = _real(f)
    lidar = f.get("calibrate", "lidar")
    index = LidarAngularIndex(lidar)
    columns = [range_check(real[:, :3], lidar, lambda az, el, e=est: index.estimate_range(
        az, el, az_res, el_res, e, "drop"))["abs_dr"] for est in RANGE_ESTIMATORS]
    ranges = np.linalg.norm(real[:, :3], axis=1)
    columns.append(range_check(real[:, :3], lidar, lambda az, el: index.closest_range_in_window(
        az, el, ranges, az_res, el_res))["abs_dr"])
    dv = doppler_check(real[:, :3], real[:, 3], f.get("calibrate", "ego_velocity"),
                       _static_mask(real, f.get("calibrate", "labels")), comparison(cfg).real_doppler_span_mps)
    return np.column_stack(columns).reshape(len(real), len(columns)), np.asarray(dv["abs_dv"], np.float64)


def physics_checks(inputs, cfg: Config, frames) -> dict:
    """The physics checks over ``frames`` (indices of calibrated frames): :func:`physics_frame`
    pooled and summarised (``pipeline check-physics``), with progress on stderr."""
    rows = [physics_frame(inputs.frame(int(i)), cfg)
            for i in progress_bar(frames, total=len(frames), desc="check-physics", unit="frame",
                                  enabled=inputs.progress, every_s=cfg.run.progress_every_s)]
    width = len(RANGE_ESTIMATORS) + 1
    return _physics_summary(np.concatenate([a for a, _ in rows]) if rows else np.zeros((0, width)),
                            np.concatenate([b for _, b in rows]) if rows else np.zeros(0))


def _physics_summary(abs_dr: np.ndarray, abs_dv: np.ndarray, n_dr: int | None = None, n_dv: int | None = None) -> dict:
    """The report's physics section from pooled residuals abs_dr (M, 5) m and abs_dv (S,) m/s, which
    may be samples of ``n_dr`` and ``n_dv`` rows (the points counted; default: all of them)."""
    n_dr = len(abs_dr) if n_dr is None else n_dr
    n_dv = len(abs_dv) if n_dv is None else n_dv
    out = {}
    for k, key in enumerate((*RANGE_ESTIMATORS, "best")):
        v = abs_dr[:, k]
        ok = np.isfinite(v)
        within = float(np.mean(v[ok] <= RANGE_CHECK_TOLERANCE_M)) if ok.any() else float("nan")
        name = "best lidar point in the window, an oracle" if key == "best" else f"{key} rule"
        out[f"range ({name})"] = {
            "median_abs_dr_m": float(np.median(v[ok])) if ok.any() else float("nan"),
            "p90_abs_dr_m": float(np.percentile(v[ok], 90)) if ok.any() else float("nan"),
            f"within_{RANGE_CHECK_TOLERANCE_M:g}m_share": within,
            "no_support_share": float(1 - ok.mean()) if len(v) else float("nan"), "points": int(n_dr)}
    out["doppler (static points)"] = {"median_abs_dv_mps": float(np.median(abs_dv)) if len(abs_dv) else float("nan"),
                                      "points": int(n_dv)}
    return out


def select_frames(inputs, cfg: Config) -> np.ndarray:
    """evaluate-frames works on the frames of eval.split that record radar (a camera + lidar
    dataset, e.g. KITTI with train.nets_from, has nothing to compare the synthetic radar with)."""
    calib = inputs.store("calibrate")
    return split_mask(calib.array("split")[:], cfg.eval.split) & np.asarray(calib.array("has_radar")[:], bool)


def ready(inputs, cfg: Config) -> None:
    """Before evaluate-frames' output is recreated: the train stage's mean map is readable, where a
    frame is to be evaluated (a damaged one stops the run here; met by a frame, it stops the run too)."""
    if select_frames(inputs, cfg).any():
        read_mean_map(inputs, cfg)


def run(inputs, cfg: Config, out, fingerprint: str) -> dict:
    """The report over the frames evaluate-frames finished (module docstring)."""
    from pipeline.figures import bev, fig8, histograms
    from pipeline.report import write_report
    from pipeline.transfer import comparison

    check_generation(cfg)
    calib, syn_store, part = inputs.store("calibrate"), inputs.store("synthesize"), inputs.store(FRAMES.name)
    has_radar = np.asarray(calib.array("has_radar")[:], bool)
    in_split = split_mask(np.asarray(calib.array("split")[:]), cfg.eval.split) & has_radar
    calib_done, syn_done, part_status = calib.status() == DONE, syn_store.status() == DONE, part.status()
    frames = np.flatnonzero((part_status == DONE) & in_split)
    failed = int((in_split & (part_status == FAILED)).sum())
    if len(frames) == 0:
        if not (in_split & calib_done).any():
            raise PipelineError(_nothing_to_compare(inputs.env.dataset, cfg, np.asarray(calib.array("split")[:]),
                                                    has_radar, calib_done))
        why = f"; {failed} failed (`pipeline status` lists why)" if failed else ""
        raise PipelineError(f"evaluate: no evaluated frame in split '{cfg.eval.split}' "
                            f"(synth.split = '{cfg.synth.split}'{why})")
    compared = comparison(cfg)
    summary = summarise(part, frames, compared.doppler_span_mps, compared.rss, cfg.eval.pooled_rows_max,
                        inputs.progress, cfg.run.progress_every_s)
    root = Path(out.path)
    figs = root / "figures"
    _figures(inputs, cfg, frames[:cfg.eval.figure_frames], figs, summary.model_sph, summary.real_sph, fig8, bev,
             histograms)
    train, counts = _train_counts(inputs)
    meta = {"frames": int(len(frames)), "split": cfg.eval.split, "range_estimator": cfg.synth.range_estimator,
            "placement": cfg.synth.placement, "train_mean_count": mean_count(counts[train]),
            "synthesize_counts": _synth_counts(syn_store, frames)}
    parts = count_parts(np.asarray(syn_store.array("n_parts").oindex[frames]),
                        np.asarray(syn_store.array("n_hat").oindex[frames]),
                        np.asarray(inputs.store("heatmaps").array("count").oindex[frames]))
    if parts:
        meta["count_parts"] = parts
    if compared.notes:
        meta["compared"] = "; ".join(compared.notes)
    if summary.sampled:
        meta["sampled"] = summary.sampled
    if compared.doppler_span_mps > 0:
        meta["doppler_distance"] = (f"Doppler's Wasserstein distance on the circle of the radar's wrap span "
                                    f"({compared.doppler_span_mps:g} m/s)")
    left_out = _left_out(meta, in_split & calib_done & ~syn_done, in_split & syn_done & (part_status != DONE),
                         failed)
    json_path, md_path = write_report(root, inputs.env.dataset, cfg.eval.split, summary.table, summary.distances,
                                      summary.physics, meta, summary.by_speed)
    model = summary.table["model"]
    tail = f" ({'; '.join(left_out)})" if left_out else ""
    return {"report": str(md_path), "figures": str(figs),
            "message": (f"{len(frames)} frames{tail}: model chamfer {model['chamfer_m']['mean']:.2f} m, "
                        f"F1 {model['f1']['mean']:.3f}; report {md_path}")}


def _nothing_to_compare(dataset: str, cfg: Config, split: np.ndarray, has_radar: np.ndarray,
                        calibrated: np.ndarray) -> str:
    """Why split eval.split holds no frame with real radar, of split codes ``split`` (F,), which
    frames record radar ``has_radar`` (F,) and which calibrate finished ``calibrated`` (F,): the
    dataset records none, the split has no frame (the split's settings left it empty), or its
    frames record none."""
    name = cfg.eval.split
    real = "there is no real radar to compare the synthetic one with"
    if not (has_radar & calibrated).any():
        return f"evaluate: dataset {dataset} records no radar: {real}"
    in_split = split_mask(split, name) & calibrated
    if not in_split.any():
        shares = ", ".join(f"{int((split[calibrated] == code).sum())} in {part}" for part, code in SPLITS.items())
        rule = cfg.split.rule + (f", split.block_len={cfg.split.block_len}" if cfg.split.rule == "block" else "")
        return (f"evaluate: split '{name}' of dataset {dataset} has no frames ({int(calibrated.sum())} calibrated "
                f"frames: {shares}; split.rule={rule}): use more frames, other split settings (split.fractions, "
                f"split.block_len) or --set eval.split=all")
    return (f"evaluate: the {int(in_split.sum())} frames of split '{name}' of dataset {dataset} record no radar: "
            f"{real}; --set eval.split=all compares the frames that record it")


def _left_out(meta: dict, not_synthesized: np.ndarray, not_evaluated: np.ndarray, failed: int) -> list[str]:
    """A report over part of its split says so (e.g. after `run evaluate --frames ...`): the
    split's frames (F,) bool that synthesize or evaluate-frames has not finished, ``failed`` of
    them failed in evaluate-frames, said in ``meta`` and returned for the summary line."""
    left_out = []
    if not_synthesized.any():
        n = int(not_synthesized.sum())
        meta["frames_not_synthesized"] = f"{n} of the split's frames are not in this report (synthesize has not finished them)"
        left_out.append(f"{n} more not synthesized yet")
    if not_evaluated.any():
        n = int(not_evaluated.sum())
        meta["frames_not_evaluated"] = (f"{n} of the split's synthesized frames are not in this report ({failed} failed "
                                        f"in evaluate-frames, the rest not run yet)")
        left_out.append(f"{n} more not evaluated" + (f", {failed} of them failed" if failed else ""))
    return left_out


@dataclass(frozen=True)
class Summary:
    """The report's numbers from evaluate-frames (:func:`summarise`)."""

    table: dict
    """method -> metric -> {mean, median, n, n_nan} (pipeline.report.aggregate_columns)."""
    distances: dict
    """method -> spherical column -> 1-D Wasserstein distance to the real points."""
    physics: dict
    """The physics checks (:func:`_physics_summary`)."""
    by_speed: list
    """The model by ego speed (pipeline.report.speed_breakdown)."""
    real_sph: np.ndarray
    """(P, 5) the pooled real points, spherical [range m, azimuth rad, elevation rad, range rate m/s, RSS]."""
    model_sph: np.ndarray
    """(Q, 5) the model's, the same columns."""
    sampled: str
    """What was pooled from a sample (eval.pooled_rows_max), '' when nothing."""


def summarise(part, frames: np.ndarray, doppler_span_mps: float, with_rss: bool, rows_max: int,
              progress: bool, every_s: float = EVERY_S) -> Summary:
    """The report's numbers over ``frames`` (F,) finished in evaluate-frames' store ``part``:
    metrics aggregated per method, the distribution distances of the pooled points (Doppler on the
    circle of ``doppler_span_mps`` when > 0; RSS left out unless ``with_rss``), the physics checks
    and the model by ego speed. Memory grows with F by the metrics (about 2 kB a frame); the pooled
    per-point rows of each kind stop growing at ``rows_max`` (eval.pooled_rows_max): a random sample
    above it, said in ``Summary.sampled``."""
    from pipeline.baselines import METHODS
    from pipeline.metrics import FRAME_METRICS, distribution_distances
    from pipeline.report import aggregate_columns, speed_breakdown

    metrics = np.asarray(part.array("metrics").oindex[frames])  # (F, methods, FRAME_METRICS)
    present = np.asarray(part.array("present").oindex[frames], bool)
    count = np.asarray(part.array("count").oindex[frames])
    speeds = np.asarray(part.array("ego_speed").oindex[frames])
    columns = {spec.name: {key: np.where(present[:, row], metrics[:, row, k], np.nan)  # aligned: frames paired
                           for k, key in enumerate(FRAME_METRICS)}
               for row, spec in enumerate(METHODS) if present[:, row].any()}
    real_counts = np.asarray(part.array("abs_dr_count").oindex[frames], np.float64)  # one row per real point
    bar = progress_bar(total=3 * len(frames), desc="evaluate (report)", unit="frame", enabled=progress,
                       every_s=every_s)
    with bar:
        (points, n_points, point_frame), (abs_dr, n_dr, _), (abs_dv, n_dv, _) = (
            _pooled(part, name, frames, rows_max, bar) for name in ("points", "abs_dr", "abs_dv"))
    is_real = points[:, 0] == -1
    real = points[is_real, 1:]
    distances = {}
    for row, spec in enumerate(METHODS):
        sph = points[points[:, 0] == row, 1:]
        if spec.name in columns and len(sph):  # against the real points of the frames the method has
            own_real = real if present[:, row].all() else points[is_real & present[point_frame, row], 1:]
            distances[spec.name] = distribution_distances(sph, own_real, doppler_span_mps)
            if not with_rss:
                distances[spec.name]["rss"] = float("nan")
    model_row = [spec.name for spec in METHODS].index("model")
    sampled = "; ".join(f"{what} from a random sample of {len(kept):,} of the {total:,} pooled {rows}"
                        for what, rows, kept, total in (
                            ("distribution distances and histograms", "points (every method's and the real ones)",
                             points, n_points),
                            ("physics checks of range", "real points' residuals", abs_dr, n_dr),
                            ("physics check of static Doppler", "residuals", abs_dv, n_dv)) if len(kept) < total)
    if sampled:
        sampled += " (eval.pooled_rows_max)"
    return Summary(table=aggregate_columns(columns), distances=distances,
                   physics=_physics_summary(abs_dr, abs_dv, n_dr, n_dv),
                   by_speed=speed_breakdown(speeds, real_counts, count[:, model_row],
                                            {key: metrics[:, model_row, k] for k, key in enumerate(FRAME_METRICS)}),
                   real_sph=real, model_sph=points[points[:, 0] == model_row, 1:], sampled=sampled)


def _pooled(part, name: str, frames: np.ndarray, rows_max: int, bar) -> tuple[np.ndarray, int, np.ndarray]:
    """The rows of ragged array ``name`` of ``frames`` (F,), in order, how many there are, and the
    position in ``frames`` of each row's frame (int, one per row returned); above
    ``rows_max`` rows a random sample of about that many: each row kept with probability
    rows_max / rows (each frame's count drawn from the binomial, then that many of its rows without
    replacement; one stream, from the array's name, in frame order: the sample does not depend on
    how the frames are read, and memory stays within the sample and the frames' counts). Reads
    about READ_BYTES of chunks at a time (at least one frame's chunk). CacheError when a frame's
    row count is outside 0..the array's capacity."""
    array = part.array(name)
    rows = np.asarray(part.array(f"{name}_count").oindex[frames], np.int64)
    bad = np.flatnonzero((rows < 0) | (rows > array.shape[1]))
    if bad.size:
        j = int(bad[0])
        raise CacheError(f"{part.url}/{name}_count, frame {int(frames[j])}: {int(rows[j])} rows, outside "
                         f"0..{array.shape[1]} (the array's capacity): the output is damaged; recompute it with "
                         f"`pipeline run {part.stage} --force`")
    total = int(rows.sum())
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    keep = rng.binomial(rows, rows_max / total) if total > rows_max else rows
    offsets = np.concatenate([[0], np.cumsum(keep)])
    out = np.empty((int(offsets[-1]), *array.shape[2:]), array.dtype)
    frame_bytes = int(np.prod(array.shape[1:], dtype=np.int64)) * array.dtype.itemsize
    step = max(1, READ_BYTES // max(frame_bytes, 1))
    for start in range(0, len(frames), step):
        block = np.asarray(array.oindex[frames[start:start + step]])
        for k in range(len(block)):
            j = start + k
            values = block[k, :rows[j]]
            if keep[j] < rows[j]:
                values = values[np.sort(rng.choice(rows[j], keep[j], replace=False))]
            out[offsets[j]:offsets[j + 1]] = values
        bar.update(len(block))
    return out, total, np.repeat(np.arange(len(frames)), keep)


def count_parts(parts: np.ndarray, n_hat: np.ndarray, real: np.ndarray) -> str:
    """The model's count and its parts against the real counts, one line: mean relative error and
    L_n (mean squared relative error) of Dis-Net's count, PlaceNet's and the geometric mean used
    (synthesize's n_parts (F, 2), n_hat (F,); PlaceNet's only where every frame has it), over the
    frames with real points (F,); '' without any."""
    real = np.asarray(real, np.float64)
    has = real > 0
    if not has.any():
        return ""

    def errors(n: np.ndarray) -> str:
        rel = (np.asarray(n, np.float64)[has] - real[has]) / real[has]
        return f"{np.mean(np.abs(rel)):.3g} (L_n {np.mean(rel ** 2):.3g})"

    disnet, placenet = parts[:, 0], parts[:, 1]
    line = f"mean relative error of Dis-Net's count {errors(disnet)}"
    if np.all(placenet[has] >= 0):
        line += f", PlaceNet's {errors(placenet)}, their geometric mean (the model's) {errors(n_hat)}"
    return line + f", over {int(has.sum())} frames with real points"


def _synth_counts(syn_store, frames) -> dict:
    counts = np.asarray(syn_store.array("counts").oindex[frames]).sum(0)
    names = ("requested", "no_lidar_support", "outside_fov", "beyond_range", "widened")
    return {k: int(v) for k, v in zip(names, counts)}


def _figures(inputs, cfg, frames, figs: Path, syn_sph, real_sph, fig8, bev, histograms) -> None:
    """Fig. 8 and bird's-eye views of ``frames`` (the model's points and the real ones), and the
    histograms of the pooled spherical points ``syn_sph`` and ``real_sph`` (N, 5)."""
    figs.mkdir(parents=True, exist_ok=True)
    f8, bv = [], []
    for i in frames:
        f = inputs.frame(int(i))
        syn, real = _syn5(f.get("synthesize", "points")), _real(f)
        image = f.get("calibrate", "image")
        T_cam_radar = invert_transform(f.get("calibrate", "T_radar_cam"))
        size = (image.shape[1], image.shape[0])
        K = f.get("calibrate", "K")
        ruv, _, rv = project_to_image(real[:, :3], K, T_cam_radar, size)
        suv, _, sv = project_to_image(syn[:, :3], K, T_cam_radar, size)
        title = f"frame {f.frame_id}: {len(real)} real, {len(syn)} synthetic"
        f8.append({"image": image, "prob_map": f.get("synthesize", "pred_map"), "real_uv": ruv[rv], "syn_uv": suv[sv],
                   "title": title})
        bv.append({"real_points_D": real, "syn_points_D": syn, "title": title})
    if f8:
        fig8(figs / "fig8.png", f8)
        bev(figs / "bev.png", bv, cfg.radar.max_range_m, cfg.radar.fov_az_deg)
    apart, labels = histogram_units(cfg)
    histograms(figs / "histograms.png", real_sph, syn_sph, apart=apart, labels=labels)


def histogram_units(cfg) -> tuple[dict[str, str], dict[str, str]]:
    """(apart, labels) of the histograms (pipeline.figures.histograms): the RSS panel's x-axis label
    names the radar's RSS unit; where the real and the synthesized radar measure RSS in different
    units (nets of another dataset), each set is binned apart and both units are named."""
    from pipeline.config import own_radar
    from pipeline.transfer import comparison

    real_unit, syn_unit = own_radar(cfg).rss_unit, cfg.radar.rss_unit
    if comparison(cfg).rss:
        return {}, {"rss": f"RSS ({syn_unit})"}
    return ({"rss": f"real {real_unit}, synthetic {syn_unit} (not comparable)"},
            {"rss": f"RSS (real {real_unit}, synthetic {syn_unit})"})


FRAMES = FrameStage(name="evaluate-frames", upstream=("calibrate", "heatmaps", "patches", "train", "synthesize"),
                    config_keys=FRAME_KEYS, outputs=frame_outputs, process=evaluate_frame, select=select_frames,
                    version=VERSION, doc=__doc__, check=check_generation, part_of="evaluate", ready=ready)
STAGE = DatasetStage(name="evaluate", upstream=("calibrate", "heatmaps", "patches", "train", "synthesize", FRAMES.name),
                     config_keys=CONFIG_KEYS, version=REPORT_VERSION, run=run, doc=__doc__, check=check_generation,
                     local_files=True)
