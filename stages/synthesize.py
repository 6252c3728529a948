"""synthesize: generate the radar frame of a camera + lidar frame (Section IV-B).

Reads: calibrate (image, K, T_radar_cam, lidar, labels, ego_velocity, split), heatmaps (count, for
synth.count = oracle), train (best Dis-Net, RSS-Net and, for synth.placement = lidar, PlaceNet
checkpoints).
Writes (synthesize.zarr) per frame of split synth.split:
  points (<= capacity, 9) float32 in {D}: x, y, z (m), range (m), azimuth (rad), elevation (rad),
  doppler (m/s, in the simulated radar's convention: radar.doppler_sign * range rate, wrapped into
  radar.doppler_span_mps), rss (dataset units: RSS-Net's, plus a drawn residual with
  synth.rss_sampling = residual), range_rate (m/s, internal convention, wrapped);
  pred_map (h, w) float32 Dis-Net's distribution; n_hat float32, the model's count (synth.count
  predicted or disnet; with oracle Dis-Net's, while the real count is drawn); n_parts (2,)
  float32, Dis-Net's count and PlaceNet's (-1 where not computed); counts (5,) int32 [requested,
  no lidar support, outside the field of view, beyond max range, found by widening the window]
  (with lidar placement: points without a candidate left count as without support);
  candidates int32, the frame's lidar candidates (lidar placement; 0 with the ray placement);
  outside_training (len(FEATURES),) int32, how many of them have each PlaceNet input outside the
  range PlaceNet was trained on (pipeline.input_range.RANGE_PERCENTILES; -1 for a PlaceNet
  saved without it): summarise() names
  the inputs where that is far more than on the training data (nets of another dataset);
  rss_points int32 and rss_outside (len(INPUT_SUMMARIES),) int32 the same for RSS-Net's inputs
  (pipeline.patches.input_summaries).
Config: synth.*, radar.* (resolutions, fov, range, Doppler convention), patches.* (RSS-Net inputs),
placement.voxel_m, placement.map_weight and heatmap.sigma_px (lidar placement); with
train.nets_from the nets are another dataset's (pipeline.transfer): built as they were trained,
their map resized to this dataset's working size, Dis-Net's prior (the other dataset's mean map)
moved to the same places around the radar in this dataset's camera (transfer.prior_in_target).
synth.device says where the nets run (the CPU unless set); like train.device it is in no
fingerprint.
"""

from __future__ import annotations

import hashlib
import threading
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from pipeline import transfer
from pipeline.config import Config, check_device, named_nets
from pipeline.errors import PipelineError
from pipeline.executor import FrameInputs, process_memo, run_memo
from pipeline.geometry import wrap_doppler
from pipeline.input_range import RANGE_PERCENTILES
from pipeline.patches import INPUT_SUMMARIES, input_summaries
from pipeline.placement import FEATURES
from pipeline.stage import ArraySpec, FrameStage
from stages.patches import point_inputs

POINT_COLUMNS = ("x_m", "y_m", "z_m", "range_m", "azimuth_rad", "elevation_rad", "doppler_mps", "rss",
                 "range_rate_mps")
CONFIG_KEYS = ("synth.split", "synth.range_estimator", "synth.no_support", "synth.seed", "synth.count",
               "synth.sampling", "synth.rss_sampling", "synth.refill_rounds", "synth.placement", "placement.voxel_m",
               "placement.map_weight",
               "heatmap.sigma_px", "radar.az_res_deg", "radar.el_res_deg", "radar.fov_az_deg", "radar.fov_el_deg",
               "radar.max_range_m", "radar.doppler_sign", "radar.doppler_span_mps", "radar.max_points",
               "radar.store_max_points", "patches.r_c_px", "patches.r_l_m", "patches.range_image_size",
               "patches.patch_size_px")
SPLITS = {"train": 0, "val": 1, "test": 2}
"""Split codes of calibrate's ``split`` array; synth.split and eval.split may also be 'all'."""


def split_mask(split: np.ndarray, name: str) -> np.ndarray:
    """(F,) bool: the frames of split codes ``split`` (F,) in split ``name`` ('all': every frame)."""
    return np.ones(len(split), bool) if name == "all" else np.asarray(split) == SPLITS[name]


VERSION = 6
"""2: refill rounds oversample (pipeline.synthesis.REFILL_OVERSAMPLE), so the points differ from version 1's.
3: lidar placement (synth.placement). 4: candidates and outside_training (the same points); with
train.nets_from, Dis-Net's prior moved to this dataset's camera. 5: rss_points and rss_outside (the
same points). 6: synth.count = predicted blends Dis-Net's count with PlaceNet's (lidar placement);
n_parts."""
SUMMARY_FRAMES_MAX = 1000
"""summarise() counts the inputs outside the nets' training range over at most this many finished
frames, a random sample above it (each frame's counts are a read of four chunks, a request each
on an object store, after every run: 120,000 at 30,000 frames). A share over 1,000 frames' millions
of candidates moves by well under a percent with the sample."""

OUTSIDE_NOTE_SHARE = 0.05
"""summarise() names a PlaceNet or RSS-Net input outside its training range on more than this share
of the candidates or points (1% by construction on the training data:
pipeline.input_range.RANGE_PERCENTILES)."""
RAY_HINT = " (or set synth.placement=ray, which needs no PlaceNet)"
"""Said where PlaceNet alone is missing."""


def capacity(cfg: Config) -> int:
    return max(cfg.radar.max_points, cfg.radar.store_max_points)


def outputs(cfg: Config) -> tuple[ArraySpec, ...]:
    w, h = cfg.camera.working_size
    return (ArraySpec("points", (capacity(cfg), len(POINT_COLUMNS)), "float32", ",".join(POINT_COLUMNS),
                      fill=np.nan, ragged=True, finite=True),
            ArraySpec("pred_map", (h, w), "float32", "probability per pixel", finite=True),
            ArraySpec("n_hat", (), "float32", "the model's point count", finite=True),
            ArraySpec("n_parts", (2,), "float32", "Dis-Net's count, PlaceNet's count (-1: not computed)",
                      fill=np.nan, finite=True),
            ArraySpec("counts", (5,), "int32", "requested, no support, out of fov, beyond range, widened"),
            ArraySpec("candidates", (), "int32", "lidar candidates (lidar placement)", fill=-1),
            ArraySpec("outside_training", (len(FEATURES),), "int32",
                      f"candidates with the PlaceNet input outside its training range: {','.join(FEATURES)}",
                      fill=-1),
            ArraySpec("rss_points", (), "int32", "points whose RSS RSS-Net gave", fill=-1),
            ArraySpec("rss_outside", (len(INPUT_SUMMARIES),), "int32",
                      f"points with the RSS-Net input summary outside its training range: {','.join(INPUT_SUMMARIES)}",
                      fill=-1))


def check_generation(cfg: Config) -> None:
    """ConfigError for generation settings no frame could run with (before any frame is tried)."""
    from pipeline.errors import ConfigError

    s = cfg.synth
    # the text choices (placement, count, sampling, split, ...) and the numeric settings (refill_rounds,
    # voxel_m, map_weight) are held to pipeline.config.CHOICES and LIMITS where set
    if not cfg.train.nets_from:  # trained here: refused before training, not after it
        left_out = [n for n in needed_nets(cfg) if n not in named_nets(cfg)]
        if left_out:
            hint = RAY_HINT if left_out == ["placenet"] else ""
            raise ConfigError(f"train.nets = '{cfg.train.nets}' leaves out {', '.join(left_out)}, which synthesis "
                              f"with synth.placement = '{s.placement}' needs: add it to train.nets{hint}")
    check_device("synth.device", s.device)


def needed_nets(cfg: Config) -> tuple[str, ...]:
    """The nets generation loads: PlaceNet only for synth.placement = 'lidar'."""
    return ("disnet", "rssnet") + (("placenet",) if cfg.synth.placement == "lidar" else ())


def check_checkpoints(train_dir, cfg: Config, weights: bool = False) -> Path:
    """PipelineError naming what is missing or damaged unless the train stage's output
    ``train_dir`` holds every checkpoint generation needs (:func:`needed_nets`), readable; with
    ``weights`` their weights are read and must be finite too (the demo's 14 MB Dis-Net checkpoint
    in 15-16 ms; once per run, before the output is recreated: the nets' loaders check them again
    when they load). Returns the local folder it checked (:func:`checkpoint_folder`)."""
    nets = needed_nets(cfg)
    folder = checkpoint_folder(train_dir, cfg)
    missing = [n for n in nets if folder is None or not (folder / n / "best.safetensors").is_file()]
    if missing:
        hint = RAY_HINT if missing == ["placenet"] else ""
        raise PipelineError(f"{train_dir.url}: no {', '.join(missing)} checkpoint; synthesis needs it: run the "
                            f"train stage with {', '.join(missing)} in train.nets{hint}")
    from pipeline.checkpoint import load_checkpoint, read_meta
    from pipeline.inference import saved_count_scale, saved_residual_quantiles

    read = load_checkpoint if weights else read_meta
    for net in nets:  # a truncated, overwritten or otherwise damaged file fails here, not in every frame
        path = str(folder / net / "best.safetensors")
        try:
            meta = read(path)
        except PipelineError as exc:
            retrain = "retrain it: `pipeline run train --force`"
            raise PipelineError(str(exc) if retrain in str(exc) else
                                f"{exc}; {retrain} (with the same --dataset and --cache)") from None
        meta = meta[1] if weights else meta
        if net == "placenet" and uses_placenet_count(cfg) and saved_count_scale(meta) is None:
            raise PipelineError(f"{path}: PlaceNet's checkpoint holds no count scale (trained before 2026-12-05), "
                                f"which synth.count = predicted needs: retrain it, `pipeline run train --force` "
                                f"(with the same --dataset and --cache), or set synth.count=disnet")
        if net == "rssnet" and cfg.synth.rss_sampling == "residual" and saved_residual_quantiles(meta) is None:
            raise PipelineError(f"{path}: RSS-Net's checkpoint holds no residual quantiles (trained before 2026-12-06, "
                                f"or without validation points), which synth.rss_sampling = residual needs: retrain "
                                f"it, `pipeline run train --force` (with the same --dataset and --cache), or set "
                                f"synth.rss_sampling=mean")
    return folder


def checkpoint_folder(train_dir, cfg: Config) -> Path | None:
    """A local folder holding the train stage's output ``train_dir`` (a DirStore): the folder itself
    on a local cache; on a remote one, a local copy of its finished run (run.staging_dir), or None
    while it has not finished."""
    if train_dir.is_local:
        return Path(train_dir.path)
    return train_dir.local_copy(cfg.run.staging_dir) if train_dir.meta() is not None else None


def uses_placenet_count(cfg: Config) -> bool:
    """Whether the frames' count blends in PlaceNet's: synth.count = predicted, the lidar placement
    and nets trained on this dataset. PlaceNet's count is a sum over the lidar's points, so it
    carries the density of the lidar it was trained with: the Astyx nets (16-line lidar) on the two
    View-of-Delft frames (64 lines, about 23,700 candidates a frame against Astyx's 1,200) gave
    3,482 and 3,402 points where the radar has 208 and 195 (Dis-Net: 575 and 558)."""
    return cfg.synth.count == "predicted" and cfg.synth.placement == "lidar" and not cfg.train.nets_from


def frame_count(n_disnet: float, intensity: np.ndarray, count_scale: float) -> tuple[float, float]:
    """(the count a frame's points are drawn to, PlaceNet's count): the geometric mean of Dis-Net's
    count ``n_disnet`` (from the image and the ego speed) and PlaceNet's, ``count_scale`` times its
    intensity (C,) summed over the frame's candidates (from the lidar, whose objects and surfaces it
    sees). Their errors differ: on the held-out frames of the synthetic world and of Astyx the
    mean's is lower than either's (README, "The count")."""
    n_placenet = float(count_scale) * float(np.sum(intensity))
    return float(np.sqrt(max(n_disnet, 0.0) * n_placenet)), n_placenet


def ready(inputs, cfg: Config) -> None:
    """Before synthesize's output is recreated: the train stage's checkpoints are there, readable and
    with finite weights."""
    check_checkpoints(inputs.dir("train"), cfg, weights=True)


def select(inputs, cfg: Config) -> np.ndarray:
    check_generation(cfg)
    check_checkpoints(inputs.dir("train"), cfg)
    return split_mask(inputs.store("calibrate").array("split")[:], cfg.synth.split)


class Nets(NamedTuple):
    """The train stage's best networks (on synth.device); placenet is None with synth.placement = 'ray'."""

    disnet: Any
    rssnet: Any
    placenet: Any
    source_camera: Any = None
    """With train.nets_from: the other dataset's camera (pipeline.transfer.SourceCamera), or None."""


def models(inputs: FrameInputs, cfg: Config) -> Nets:
    """Best Dis-Net, RSS-Net and (lidar placement) PlaceNet of the train stage, loaded once per
    process onto synth.device and per train run: the key holds the run's finishing time, since nets
    retrained under the same fingerprint (``--force``) are other nets (a cluster's workers outlive a
    run)."""
    import torch

    from pipeline.inference import load_disnet, load_placenet, load_rssnet, select_device

    out = inputs.env.dir("train")
    meta = run_memo(inputs.env, ("train record", out.url), lambda: out.meta() or {})  # once a run, not a frame
    key = ("models", out.url, meta.get("fingerprint"), meta.get("finished"), cfg.synth.placement, cfg.train.nets_from,
           cfg.synth.device)

    def build():
        torch.set_num_threads(max(1, cfg.train.threads // max(1, cfg.run.workers)))
        folder = check_checkpoints(out, cfg)  # the local folder: one copy of a remote train's output
        device = str(select_device(cfg.synth.device, "synth.device"))
        saved = bool(cfg.train.nets_from)  # another dataset's nets: built as trained (pipeline.transfer)
        placenet = (load_placenet(cfg, folder / "placenet" / "best.safetensors", device=device, saved_arch=saved)
                    if cfg.synth.placement == "lidar" else None)
        camera = meta.get("summary", {}).get("source_camera") if saved else None
        return Nets(load_disnet(cfg, folder / "disnet" / "best.safetensors", device=device, saved_arch=saved),
                    load_rssnet(cfg, folder / "rssnet" / "best.safetensors", device=device, saved_arch=saved), placenet,
                    transfer.camera_from_record(camera) if camera else None)

    return process_memo(key, build)


def lidar_tree(inputs: FrameInputs, cfg: Config):
    """With synth.placement = lidar, the frame's lidar (finite: calibrate's spec) in one cKDTree
    (pipeline.placement.neighbour_tree), built once per frame: the candidates' neighbours and the
    range images of the points placed on them (RSS-Net's inputs) are found in it. None with the ray
    placement, whose range images alone build the tree made for them (pipeline.rangeimage.lidar_tree)."""
    from pipeline.placement import neighbour_tree

    if cfg.synth.placement != "lidar":
        return None
    return inputs.memo(("lidar-tree",), lambda: neighbour_tree(inputs.get("calibrate", "lidar")))


def lidar_candidates(inputs: FrameInputs, cfg: Config,
                     placenet) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The frame's lidar candidates (C, 3) m in {D}, their pixels (C, 2), PlaceNet's intensities
    (C,) and how many of them have each input outside PlaceNet's training range (len(FEATURES),):
    computed once per frame and PlaceNet (the count, and evaluate's several maps, use them again)."""
    import torch

    from pipeline.inference import placenet_predict
    from stages.patches import candidates, features

    def build() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        points, uv = candidates(inputs, cfg)
        # the neighbour query gets the threads the nets get (one per dask worker on a full machine)
        x = (features(inputs, points, uv, torch.get_num_threads(), lidar_tree(inputs, cfg)) if len(points)
             else np.zeros((0, len(FEATURES)), np.float32))
        intensity = placenet_predict(placenet, x) if len(points) else np.zeros(0)
        outside = (placenet.outside_range(x).sum(0) if placenet.has_training_range()
                   else np.full(len(FEATURES), -1))  # -1: saved without its range, not checked
        return points, uv, intensity, outside.astype(np.int32)

    return inputs.memo(("lidar-candidates", placenet), build)


def _place(inputs: FrameInputs, cfg: Config, prob_map: np.ndarray, n: float, placenet, rng) -> dict:
    """synth.placement = 'lidar': points on the frame's lidar candidates (pipeline.placement)."""
    from pipeline.placement import place_on_lidar
    from stages.heatmaps import working_sigma

    points, uv, intensity, outside = lidar_candidates(inputs, cfg, placenet)
    placed = place_on_lidar(prob_map, float(n), points, uv, intensity, image_wh=tuple(cfg.camera.working_size),
                            sigma_px=working_sigma(cfg), voxel_m=cfg.placement.voxel_m,
                            map_weight=cfg.placement.map_weight,
                            ego_velocity_D=inputs.get("calibrate", "ego_velocity"),
                            labels=inputs.get("calibrate", "labels"), doppler_span_mps=cfg.radar.doppler_span_mps,
                            rng=rng)
    return {**placed, "candidates": len(points), "outside_training": outside}


def generate(inputs: FrameInputs, cfg: Config, prob_map: np.ndarray, n: float, nets: Nets, rng,
             rss: bool = True) -> dict:
    """Points of one frame from a map and a count (shared with evaluate's baselines): placed as
    synth.placement says, RSS from RSS-Net, with a drawn residual where synth.rss_sampling says
    (``rss`` False: zeros, for a caller that sets its own)."""
    from pipeline.synthesis import synthesize_frame
    from pipeline.inference import draw_residuals, rssnet_predict

    r = cfg.radar
    image, K = inputs.get("calibrate", "image"), inputs.get("calibrate", "K")
    T_radar_cam, lidar = inputs.get("calibrate", "T_radar_cam"), inputs.get("calibrate", "lidar")
    ego = inputs.get("calibrate", "ego_velocity")
    if cfg.synth.placement == "lidar":
        syn = _place(inputs, cfg, prob_map, n, nets.placenet, rng)
    else:
        syn = synthesize_frame(prob_map, float(n), K, T_radar_cam, lidar, ego,
                               inputs.get("calibrate", "labels"),
                               az_res_deg=r.az_res_deg, el_res_deg=r.el_res_deg, fov_az_deg=r.fov_az_deg,
                               fov_el_deg=r.fov_el_deg, max_range_m=r.max_range_m, doppler_sign=1,
                               doppler_span_mps=r.doppler_span_mps, estimator=cfg.synth.range_estimator,
                               no_support=cfg.synth.no_support, rng=rng, sampling=cfg.synth.sampling,
                               refill_rounds=cfg.synth.refill_rounds)
    pts = np.asarray(syn["points_D"], np.float64).reshape(-1, 3)
    range_rate = np.asarray(syn["doppler"], np.float64)
    rss_outside = np.zeros(len(INPUT_SUMMARIES), np.int32)
    if len(pts) and rss:
        patches, ranges = point_inputs(image, K, T_radar_cam, lidar, pts, cfg, lidar_tree(inputs, cfg))
        vectors = np.column_stack([pts, range_rate]).astype(np.float32)
        values = rssnet_predict(nets.rssnet, patches, ranges, vectors)
        if cfg.synth.rss_sampling == "residual":  # the checkpoint's quantiles were checked before any frame
            values = np.clip(values + draw_residuals(nets.rssnet.residual_quantiles, len(values), rng),
                             r.rss_min, r.rss_max)
        if nets.rssnet.has_input_range():
            rss_outside = nets.rssnet.outside_range(input_summaries(patches, ranges, vectors)).sum(0).astype(np.int32)
        else:  # saved without its training range: not checked
            rss_outside[:] = -1
    else:
        values = np.zeros(len(pts), np.float32)
    doppler = wrap_doppler(r.doppler_sign * range_rate, r.doppler_span_mps)
    rows = np.column_stack([pts, np.asarray(syn["rae"], np.float64).reshape(-1, 3), doppler, values, range_rate])
    counts = np.array([syn["n_requested"], syn["n_no_support"], syn["n_out_of_fov"], syn["n_beyond_range"],
                       syn["n_widened"]], np.int32)
    return {"points": rows.astype(np.float32), "uv": np.asarray(syn["uv"]), "counts": counts,
            "rss_points": np.int32(len(pts) if rss else 0), "rss_outside": rss_outside,
            "candidates": np.int32(syn.get("candidates", 0)),
            "outside_training": np.asarray(syn.get("outside_training", np.zeros(len(FEATURES))), np.int32)}


def process(inputs: FrameInputs, cfg: Config) -> dict[str, np.ndarray]:
    from pipeline.heatmap import resize_distribution
    from pipeline.inference import disnet_predict

    nets = models(inputs, cfg)
    speed = np.float32(np.linalg.norm(inputs.get("calibrate", "ego_velocity")))
    maps, n_hat = disnet_predict(nets.disnet, inputs.get("calibrate", "image")[None], np.array([speed], np.float32))
    pred_map = resize_distribution(_with_own_camera(inputs, cfg, nets, maps[0]), cfg.camera.working_size)
    n, n_placenet = float(n_hat[0]), -1.0
    if uses_placenet_count(cfg):
        n, n_placenet = frame_count(n, lidar_candidates(inputs, cfg, nets.placenet)[2], nets.placenet.count_scale)
    drawn = float(inputs.get("heatmaps", "count")) if cfg.synth.count == "oracle" else n
    out = generate(inputs, cfg, pred_map, min(drawn, capacity(cfg)), nets, inputs.rng(cfg.synth.seed, 21))
    return {"points": out["points"], "pred_map": pred_map, "n_hat": np.float32(n),
            "n_parts": np.array([n_hat[0], n_placenet], np.float32), "counts": out["counts"],
            "candidates": out["candidates"], "outside_training": out["outside_training"],
            "rss_points": out["rss_points"], "rss_outside": out["rss_outside"]}


def _with_own_camera(inputs: FrameInputs, cfg: Config, nets: Nets, prob_map: np.ndarray) -> np.ndarray:
    """Dis-Net's map (h, w) of this frame; with another dataset's nets (train.nets_from), a prior
    and that dataset's camera (recorded by the train stage), the prior moved from that camera to
    this frame's (pipeline.transfer.prior_in_target; a mixed-in share of it, disnet.prior_mix, too)."""
    if not (cfg.train.nets_from and nets.disnet.use_prior and nets.source_camera is not None):
        return prob_map
    camera = nets.source_camera
    prior = nets.disnet.prior_logits.double().exp().cpu().numpy()
    K, T = inputs.get("calibrate", "K"), inputs.get("calibrate", "T_radar_cam")
    size = tuple(cfg.camera.working_size)
    key = (hashlib.sha1(prior.tobytes()).hexdigest(), repr(transfer.camera_record(camera)), K.tobytes(), T.tobytes(),
           size)
    moved = _MOVED_PRIORS.get(key)
    if moved is None:  # a few calibrations per dataset; KITTI's differ by drive
        moved = transfer.prior_in_target(prior, camera, K, T, size)
        with _MOVED_PRIORS_LOCK:  # a dask worker's threads share it
            while len(_MOVED_PRIORS) >= MOVED_PRIORS_KEPT:
                _MOVED_PRIORS.pop(next(iter(_MOVED_PRIORS)))
            _MOVED_PRIORS[key] = moved
    return transfer.rebase_mixed_prior(prob_map, prior, moved, float(nets.disnet.prior_mix))


MOVED_PRIORS_KEPT = 8
"""Moved priors a process keeps (one per distinct calibration, oldest dropped first)."""
_MOVED_PRIORS: dict[tuple, np.ndarray] = {}
_MOVED_PRIORS_LOCK = threading.Lock()


def summarise(store, cfg: Config) -> list[str]:
    """Lines naming the PlaceNet and RSS-Net inputs outside their training range on more than
    OUTSIDE_NOTE_SHARE of the finished frames' lidar candidates and synthesized points (none when
    none is): there the nets extrapolate, as with nets of a dataset whose lidar or camera differs
    (train.nets_from); nets saved without their range are said to be unchecked."""
    from pipeline.cache import DONE

    low, high = RANGE_PERCENTILES
    done = np.flatnonzero(store.status() == DONE)
    sampled = ""
    if len(done) > SUMMARY_FRAMES_MAX:
        sampled = f" (in a random sample of {SUMMARY_FRAMES_MAX:,} of the {len(done):,} finished frames)"
        done = np.sort(np.random.default_rng(0).choice(done, SUMMARY_FRAMES_MAX, replace=False))
    source = f" (nets of '{cfg.train.nets_from}')" if cfg.train.nets_from else ""
    lines = []
    for net, count, outside, names, rows, effect in (
            ("PlaceNet", "candidates", "outside_training", FEATURES, "lidar candidates",
             "its intensities there are extrapolated"),
            ("RSS-Net", "rss_points", "rss_outside", INPUT_SUMMARIES, "synthesized points",
             "its RSS there is extrapolated")):
        n_rows = np.asarray(store.array(count).oindex[done]).clip(0)
        out = np.asarray(store.array(outside).oindex[done]).reshape(len(done), len(names))
        if ((out < 0).any(axis=1) & (n_rows > 0)).any():
            lines.append(f"{net}'s inputs not checked against its training range: its checkpoint was saved without "
                         f"it, by an earlier version (`pipeline run train --force` saves it)")
        checked = (out >= 0).all(axis=1) & (n_rows > 0)
        n = int(n_rows[checked].sum())
        share = out[checked].sum(0) / max(n, 1)
        order = [k for k in np.argsort(-share, kind="stable") if share[k] > OUTSIDE_NOTE_SHARE]
        if n and order:
            listed = ", ".join(f"{names[k]} on {share[k]:.0%}" for k in order)
            lines.append(f"{net} inputs outside the {low:g}-{high:g} percentiles of its training data{source} (where "
                         f"1% of its training rows lie): {listed} of the {n:,} {rows}{sampled}; {effect}")
    return lines


STAGE = FrameStage(name="synthesize", upstream=("calibrate", "heatmaps", "train"), config_keys=CONFIG_KEYS,
                   outputs=outputs, process=process, select=select, version=VERSION, doc=__doc__,
                   check=check_generation, summarise=summarise, ready=ready)
