"""evaluate: fidelity of the synthesized radar against the real one, next to the baselines.

Reads: synthesize (points, pred_map, n_hat), calibrate (real radar, lidar, image, labels, ego
velocity, split, sequence, timestamp), heatmaps (real heatmap, count), train (mean training
heatmap, training count and RSS statistics, RSS-Net).
Writes (evaluate/): report.json, report.md (one table: model and baselines, mean and median over
frames; Wasserstein distances; the model by ego speed; physics checks), figures/fig8.png,
figures/bev.png, figures/histograms.png.
Config: eval.*, synth.* (baselines use the same generation steps), radar.*.
Every method is evaluated on the same frames: those of eval.split that synthesize finished.
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pipeline.cache import DONE
from pipeline.config import Config
from pipeline.geometry import invert_transform, project_to_image
from pipeline.stage import DatasetStage
from stages.synthesize import check_generation, check_split, generate, models, split_mask

NOMINAL_FRAME_PERIOD_S = 0.1
"""Frame period assumed by the previous-frame baseline where timestamps do not give one (10 Hz)."""
MAX_FRAME_GAP_S = 1.0
"""Consecutive frames further apart than this (or going backwards) use the nominal period."""

VERSION = 7
"""Bump when the report's rows or numbers change for the same inputs (2: model-oracle-map row, one
random stream per method; 3: no-points row; 4: the model by ego speed; 5: physics checks with the
share within 1 m and the best-lidar-point oracle; 6: the baselines follow synth.placement; 7: the
baselines sample their maps at full weight, pipeline.baselines.generation_config)."""

RANGE_CHECK_TOLERANCE_M = 1.0
"""The physics checks report the share of real points whose lidar range is within this of the
measured range (the matched-F1 gate's default)."""

CONFIG_KEYS = ("eval.split", "eval.figure_frames", "eval.gate_m", "eval.gate_rss", "eval.gate_doppler_mps",
               "synth.range_estimator", "synth.no_support", "synth.seed", "synth.sampling", "synth.refill_rounds",
               "synth.placement", "placement.voxel_m", "placement.map_weight", "heatmap.sigma_px",
               "radar.doppler_span_mps", "radar.az_res_deg", "radar.el_res_deg")


def _train_stats(inputs, cfg: Config) -> dict:
    """Training-split statistics the baselines use: mean count, mean map, RSS values."""
    calib, heat, patches = inputs.store("calibrate"), inputs.store("heatmaps"), inputs.store("patches")
    split = np.asarray(calib.array("split")[:])
    ok = (calib.status() == DONE) & (heat.status() == DONE)
    counts = np.asarray(heat.array("count")[:])
    train = np.flatnonzero(ok & (split == 0) & (counts > 0))
    mean_map = np.load(Path(inputs.dir("train").path) / "mean_heatmap.npy", allow_pickle=False)
    pc = np.asarray(patches.array("rss_count")[:])
    rss = np.asarray(patches.array("rss").oindex[train])
    rss_values = np.concatenate([rss[k, :pc[f]] for k, f in enumerate(train)]) if len(train) else np.zeros(0)
    return {"n_bar": int(round(counts[train].mean())) if len(train) else 0, "mean_map": mean_map,
            "train_rss": rss_values, "rss_median": float(np.median(rss_values)) if len(rss_values) else 0.0}


def _real(f) -> np.ndarray:
    """Real radar (M, 5) [x, y, z, range rate, rss] of the frame (already in the evaluated region)."""
    return f.get("calibrate", "radar").astype(np.float64)


def _syn5(points9: np.ndarray) -> np.ndarray:
    """Synthesize rows -> (N, 5) [x, y, z, range rate, rss]."""
    return points9[:, [0, 1, 2, 8, 7]].astype(np.float64)


def _static_mask(real: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Real points outside every labelled box that moves faster than 0.5 m/s."""
    from pipeline.synthesis import object_velocities_for_points

    if len(real) == 0:
        return np.zeros(0, bool)
    vel = object_velocities_for_points(real[:, :3], labels)
    return np.linalg.norm(vel, axis=1) < 0.5


def _previous_index(i: int, inputs, seq: np.ndarray, done: np.ndarray) -> int | None:
    j = i - 1
    return j if j >= 0 and seq[j] == seq[i] and done[j] else None


def _methods_for_frame(i, f, inputs, cfg, stats, syn_store, nets, prev,
                       real_map: np.ndarray) -> dict[str, tuple[np.ndarray, float, np.ndarray | None]]:
    """(points (N, 5), decided count, map or None) of every method on frame ``i``; ``real_map`` is
    the frame's real heatmap (H, W)."""
    from pipeline.baselines import METHODS, choose_count, choose_map, choose_rss, ego_motion_transform, \
        generation_config, lidar_subsample, previous_frame

    out = {}
    n_true = int(f.get("heatmaps", "count"))
    pred_map = syn_store.read("pred_map", i)
    n_hat = float(syn_store.read("n_hat", i))
    size = tuple(cfg.camera.working_size)
    out["model"] = (_syn5(syn_store.read("points", i)), n_hat, pred_map)
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
            pf = inputs.frame(prev)
            dt = float(f.get("calibrate", "timestamp") - pf.get("calibrate", "timestamp"))
            if not 0.0 < dt <= MAX_FRAME_GAP_S:  # clock wrap (Astyx: lidar µs past the hour) or a gap
                dt = NOMINAL_FRAME_PERIOD_S
            T = ego_motion_transform(pf.get("calibrate", "ego_velocity"), dt)
            pts = np.asarray(previous_frame(_real(pf), T), np.float64)
            out[spec.name] = (pts, float(len(pts)), None)
        elif spec.kind == "empty":
            out[spec.name] = (np.zeros((0, 5)), 0.0, None)
    return out


def run(inputs, cfg: Config, out, fingerprint: str) -> dict:
    from pipeline.figures import bev, fig8, histograms
    from pipeline.metrics import distribution_distances, frame_metrics
    from pipeline.report import aggregate, speed_breakdown, write_report
    from pipeline.training import rssnet_predict
    from stages.patches import point_inputs

    check(cfg)
    calib, syn_store = inputs.store("calibrate"), inputs.store("synthesize")
    split = np.asarray(calib.array("split")[:])
    seq = np.asarray(calib.array("sequence")[:])
    calib_done = calib.status() == DONE
    in_split = split_mask(split, cfg.eval.split)
    syn_done = syn_store.status() == DONE
    frames = np.flatnonzero(syn_done & in_split)
    if len(frames) == 0:
        from pipeline.errors import PipelineError
        raise PipelineError(f"evaluate: no synthesized frame in split '{cfg.eval.split}' "
                            f"(synth.split = '{cfg.synth.split}')")
    stats = _train_stats(inputs, cfg)
    nets = models(inputs.frame(int(frames[0])), cfg)
    r = cfg.radar
    per_frame: dict[str, list] = {}
    pooled: dict[str, list] = {}
    real_frames: list[np.ndarray] = []
    speeds, model_counts = [], []
    figure_rows = []
    for i in tqdm(frames, desc="evaluate", unit="frame", disable=not inputs.progress):
        i = int(i)
        f = inputs.frame(i)
        real = _real(f)
        real_frames.append(real)
        target = f.get("heatmaps", "heatmap")
        rss_err = float("nan")
        if len(real):
            patches, ranges = point_inputs(f.get("calibrate", "image"), f.get("calibrate", "K"),
                                           f.get("calibrate", "T_radar_cam"), f.get("calibrate", "lidar"),
                                           real[:, :3], cfg)
            pred = rssnet_predict(nets.rssnet, patches, ranges, real[:, :4].astype(np.float32))
            rss_err = float(np.mean(((real[:, 4] - pred) / (r.rss_max - r.rss_min)) ** 2))
        prev = _previous_index(i, inputs, seq, calib_done)
        methods = _methods_for_frame(i, f, inputs, cfg, stats, syn_store, nets, prev, target)
        speeds.append(float(np.linalg.norm(f.get("calibrate", "ego_velocity"))))
        model_counts.append(methods["model"][1])
        for name, (pts, n, prob) in methods.items():
            m = frame_metrics(pts, real, n_hat=n, target_map=target if prob is not None and len(real) else None,
                              pred_map=prob, rss_err=rss_err if name == "model" else float("nan"),
                              gate_m=cfg.eval.gate_m, gate_rss=cfg.eval.gate_rss,
                              gate_doppler=cfg.eval.gate_doppler_mps, doppler_span_mps=r.doppler_span_mps)
            per_frame.setdefault(name, []).append(m)
            pooled.setdefault(name, []).append(pts)
        if len(figure_rows) < cfg.eval.figure_frames:
            figure_rows.append((i, methods["model"][0], real))
    pooled_real = np.concatenate(real_frames)
    distances = {name: distribution_distances(_sph(np.concatenate(p)), _sph(pooled_real))
                 for name, p in pooled.items() if sum(len(x) for x in p)}
    phys = physics_checks(inputs, cfg, frames)
    root = Path(out.path)
    figs = root / "figures"
    _figures(inputs, cfg, figure_rows, syn_store, figs, pooled["model"], pooled_real, fig8, bev, histograms)
    table = aggregate(per_frame)
    meta = {"frames": int(len(frames)), "split": cfg.eval.split, "range_estimator": cfg.synth.range_estimator,
            "placement": cfg.synth.placement,
            "train_mean_count": stats["n_bar"], "synthesize_counts": _synth_counts(syn_store, frames)}
    missing = int((in_split & calib_done & ~syn_done).sum())
    if missing:  # a partial report must say so (e.g. after `run synthesize --frames ...`)
        meta["frames_not_synthesized"] = f"{missing} of the split's frames are not in this report (synthesize has not finished them)"
    by_speed = speed_breakdown(np.array(speeds), np.array([len(x) for x in real_frames]), np.array(model_counts),
                               per_frame["model"])
    json_path, md_path = write_report(root, inputs.env.dataset, cfg.eval.split, table, distances, phys, meta,
                                      by_speed)
    model = table["model"]
    return {"report": str(md_path), "figures": str(figs),
            "message": (f"{len(frames)} frames{f' ({missing} more not synthesized yet)' if missing else ''}: "
                        f"model chamfer {model['chamfer_m']['mean']:.2f} m, F1 {model['f1']['mean']:.3f}; report {md_path}")}


def _sph(points5: np.ndarray) -> np.ndarray:
    from pipeline.metrics import to_spherical

    return to_spherical(points5)


def physics_checks(inputs, cfg: Config, frames) -> dict:
    """Physics checks on real frames (no learning): (a) lidar range at each real radar point's
    angles vs its measured range, for the paper's mean rule and every other estimator, and for the
    window's lidar point closest to the measured range (an oracle: how often some lidar point of
    the window is right); (b) Doppler of static real points predicted from the ego velocity vs
    measured. Reads calibrate only."""
    from pipeline.metrics import doppler_check, range_check
    from pipeline.synthesis import LidarAngularIndex

    r = cfg.radar
    estimators = ("mean", "nearest", "median", "min")
    physics: dict[str, list] = {"abs_dr_" + e: [] for e in (*estimators, "best")}
    physics["abs_dv"] = []
    for i in frames:
        f = inputs.frame(int(i))
        real = _real(f)
        lidar = f.get("calibrate", "lidar")
        index = LidarAngularIndex(lidar)
        for est in estimators:
            check = range_check(real[:, :3], lidar, lambda az, el, e=est: index.estimate_range(
                az, el, np.radians(r.az_res_deg), np.radians(r.el_res_deg), e, "drop"))
            physics["abs_dr_" + est].append(check["abs_dr"])
        ranges = np.linalg.norm(real[:, :3].astype(np.float64), axis=1)
        check = range_check(real[:, :3], lidar, lambda az, el: index.closest_range_in_window(
            az, el, ranges, np.radians(r.az_res_deg), np.radians(r.el_res_deg)))
        physics["abs_dr_best"].append(check["abs_dr"])
        dv = doppler_check(real[:, :3], real[:, 3], f.get("calibrate", "ego_velocity"),
                           _static_mask(real, f.get("calibrate", "labels")), r.doppler_span_mps)
        physics["abs_dv"].append(dv["abs_dv"])
    return _physics_summary(physics)


def _physics_summary(physics: dict[str, list]) -> dict:
    out = {}
    for key, values in physics.items():
        v = np.concatenate(values) if values else np.zeros(0)
        if key.startswith("abs_dr_"):
            ok = np.isfinite(v)
            within = float(np.mean(v[ok] <= RANGE_CHECK_TOLERANCE_M)) if ok.any() else float("nan")
            name = "best lidar point in the window, an oracle" if key == "abs_dr_best" else f"{key[7:]} rule"
            out[f"range ({name})"] = {
                "median_abs_dr_m": float(np.median(v[ok])) if ok.any() else float("nan"),
                "p90_abs_dr_m": float(np.percentile(v[ok], 90)) if ok.any() else float("nan"),
                f"within_{RANGE_CHECK_TOLERANCE_M:g}m_share": within,
                "no_support_share": float(1 - ok.mean()) if len(v) else float("nan"), "points": int(len(v))}
        elif key == "abs_dv":
            out["doppler (static points)"] = {"median_abs_dv_mps": float(np.median(v)) if len(v) else float("nan"),
                                              "points": int(len(v))}
    return out


def _synth_counts(syn_store, frames) -> dict:
    counts = np.asarray(syn_store.array("counts").oindex[frames]).sum(0)
    names = ("requested", "no_lidar_support", "outside_fov", "beyond_range", "widened")
    return {k: int(v) for k, v in zip(names, counts)}


def _figures(inputs, cfg, rows, syn_store, figs: Path, syn_pooled, real_pooled, fig8, bev, histograms) -> None:
    figs.mkdir(parents=True, exist_ok=True)
    f8, bv = [], []
    for i, syn, real in rows:
        f = inputs.frame(i)
        image = f.get("calibrate", "image")
        T_cam_radar = invert_transform(f.get("calibrate", "T_radar_cam"))
        size = (image.shape[1], image.shape[0])
        K = f.get("calibrate", "K")
        ruv, _, rv = project_to_image(real[:, :3], K, T_cam_radar, size)
        suv, _, sv = project_to_image(syn[:, :3], K, T_cam_radar, size)
        title = f"frame {inputs.frame_ids[i]}: {len(real)} real, {len(syn)} synthetic"
        f8.append({"image": image, "prob_map": syn_store.read("pred_map", i), "real_uv": ruv[rv], "syn_uv": suv[sv],
                   "title": title})
        bv.append({"real_points_D": real, "syn_points_D": syn, "title": title})
    if f8:
        fig8(figs / "fig8.png", f8)
        bev(figs / "bev.png", bv, cfg.radar.max_range_m)
    histograms(figs / "histograms.png", _sph(real_pooled), _sph(np.concatenate(syn_pooled)))


def check(cfg: Config) -> None:
    """ConfigError for an unknown eval.split or generation settings no frame could run with."""
    check_split("eval.split", cfg.eval.split)
    check_generation(cfg)


STAGE = DatasetStage(name="evaluate", upstream=("calibrate", "heatmaps", "patches", "train", "synthesize"),
                     config_keys=CONFIG_KEYS, version=VERSION, run=run, doc=__doc__, check=check)
