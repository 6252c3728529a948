"""train: Dis-Net and RSS-Net on the train split, model selection on val, figures on test.

Reads: calibrate (image, ego_velocity, split; lidar, K, T_radar_cam of the training frames, whose
lidar candidates PlaceNet's count scale needs), heatmaps (heatmap, count), patches (patch,
range_image, point, rss, place_features, place_count).
Writes (train/): disnet/{last,best}.safetensors (+ .json sidecars), rssnet/..., placenet/...,
training curves (CSV, JSON, PNG) per net, metrics.json: held-out test metrics of the best epochs
next to the baselines (mean training map, training mean count, training median RSS, constant
PlaceNet intensity).
Config: disnet.*, rssnet.*, placement.* (PlaceNet), train.*, radar.max_points / rss_min / rss_max.
With train.nets_from = DATASET it trains nothing: it copies that dataset's best checkpoints (from
the same cache) and writes metrics.json with where they came from (pipeline.transfer).
Frames without a projected radar point have no defined heatmap target: they are left out of
Dis-Net and PlaceNet training and counted in the summary.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np

from pipeline import transfer
from pipeline.cache import DONE, RaggedRows
from pipeline.config import (EPOCHS_KEYS, PATIENCE_KEYS, TRAINING_KEYS, Config, check_device, check_profile,
                             named_nets)
from pipeline.errors import ConfigError, PipelineError
from pipeline.stage import DatasetStage

VERSION = 3
"""Bump when the stage's outputs change (3: PlaceNet's checkpoint holds its count scale,
pipeline.training.placenet_count_scale); :data:`NET_VERSIONS` says which nets it retrains."""
NET_VERSIONS = {"disnet": 2, "rssnet": 2, "placenet": 3}
"""Bump a net's when the training code changes what it learns or what its checkpoint holds: its
checkpoints are redone, the other nets' are resumed as they are (a cache trained before the count
scale retrains PlaceNet alone)."""

NETS = ("disnet", "rssnet", "placenet")
"""Values train.nets may list."""
CONFIG_KEYS = tuple(dict.fromkeys(sum((TRAINING_KEYS[n] for n in NETS), TRAINING_KEYS["common"])
                                  + ("train.nets", "disnet.prior_mix", *EPOCHS_KEYS.values(),
                                     *PATIENCE_KEYS.values())))
COPIED = tuple(f"{net}/best.safetensors" for net in NETS)
"""What train.nets_from takes from the other dataset's train output (those of them it has)."""
MEAN_MAP_FILE = "mean_heatmap.npy"
"""The file of the mean training heatmap (H, W) float32, which evaluate's mean-map baseline samples."""


def frame_table(inputs) -> dict[str, np.ndarray]:
    """Per-frame split, count, speed and usability (all upstream stages done)."""
    calib, heat, patches = inputs.store("calibrate"), inputs.store("heatmaps"), inputs.store("patches")
    ok = (calib.status() == DONE) & (heat.status() == DONE) & (patches.status() == DONE)
    split = np.asarray(calib.array("split")[:])
    counts = np.asarray(heat.array("count")[:])
    speeds = np.linalg.norm(np.asarray(calib.array("ego_velocity")[:]), axis=1).astype(np.float32)
    return {"ok": ok, "split": split, "count": counts, "speed": speeds}


def disnet_data(inputs, table):
    from pipeline.training import DisNetData

    usable = table["ok"] & (table["count"] > 0)
    idx = {p: np.flatnonzero(usable & (table["split"] == code)) for p, code in (("train", 0), ("val", 1), ("test", 2))}
    data = DisNetData(images=inputs.store("calibrate").array("image"), heatmaps=inputs.store("heatmaps").array("heatmap"),
                      counts=table["count"], speeds=table["speed"], train_idx=idx["train"], val_idx=idx["val"])
    return data, idx


def rssnet_data(inputs, table, part: int, val_part: int = 1):
    """RSS-Net data over the sampled points of frames in split ``part`` (train) and ``val_part``."""
    from pipeline.training import RssNetData

    store = inputs.store("patches")
    counts = np.asarray(store.array("patch_count")[:])
    frames = {p: np.flatnonzero(table["ok"] & (table["split"] == p)) for p in (part, val_part)}
    allf = np.concatenate([frames[part], frames[val_part]]) if part != val_part else frames[part]
    rows = {name: RaggedRows(store.array(name), counts, allf) for name in ("patch", "range_image", "point", "rss")}
    n_train = int(counts[frames[part]].sum())
    n_all = len(rows["rss"])
    return RssNetData(patches=rows["patch"], range_images=rows["range_image"], point_vectors=rows["point"],
                      rss=rows["rss"], train_idx=range(n_train),
                      val_idx=range(n_train, n_all) if part != val_part else range(0))


def placenet_data(inputs, table, part: int, val_part: int = 1, cfg: Config | None = None):
    """PlaceNet rows of the usable frames (radar points in the image) of split ``part`` (train) and
    ``val_part``; features and counts read per batch (row indices as ranges: nothing per row is
    held in memory). With ``cfg``, the training frames' candidates too (counted when the count scale
    is computed)."""
    from pipeline.training import PlaceNetData

    store = inputs.store("patches")
    per_frame = np.asarray(store.array("place_count_count")[:])
    usable = table["ok"] & (table["count"] > 0)
    frames = {p: np.flatnonzero(usable & (table["split"] == p)) for p in (part, val_part)}
    allf = np.concatenate([frames[part], frames[val_part]]) if part != val_part else frames[part]
    features = RaggedRows(store.array("place_features"), per_frame, allf)
    counts = RaggedRows(store.array("place_count"), per_frame, allf)
    n_train, n_all = int(per_frame[frames[part]].sum()), len(counts)
    return PlaceNetData(features=features, counts=counts, train_idx=range(n_train),
                        val_idx=range(n_train, n_all) if part != val_part else range(0),
                        train_frame_rows=per_frame[frames[part]],
                        train_frame_candidates=(None if cfg is None else
                                                lambda: candidate_counts(inputs, cfg, frames[part])),
                        train_frame_counts=np.asarray(table["count"])[frames[part]])


def candidate_counts(inputs, cfg: Config, frames: np.ndarray) -> np.ndarray:
    """(F,) the lidar candidates of each of ``frames`` (their PlaceNet rows are a sample of them),
    from calibrate's lidar and camera (stages.patches.candidates: a projection, no features)."""
    from pipeline.progress import bar
    from stages.patches import candidates

    return np.array([len(candidates(inputs.frame(int(i)), cfg)[0])
                     for i in bar(frames, total=len(frames), desc="train (PlaceNet's candidates)", unit="frame",
                                  enabled=inputs.progress, every_s=cfg.run.progress_every_s)], np.int64)


def _baselines(inputs, table, idx, cfg: Config, root: Path) -> dict[str, float]:
    """Held-out test losses of the trivial predictors the networks must beat (:func:`held_out_baselines`);
    the mean training map saved under ``root`` (the stage's output folder) for evaluate's baselines."""
    mean_map = training_mean_map(inputs, idx, cfg)
    out = held_out_baselines(inputs, table, idx, cfg, mean_map)
    np.save(root / MEAN_MAP_FILE, mean_map.astype(np.float32), allow_pickle=False)
    return out


def training_mean_map(inputs, idx, cfg: Config) -> np.ndarray:
    """The mean of the training frames' heatmaps (reads every one, with progress lines)."""
    from pipeline.net_baselines import mean_map_baseline

    return mean_map_baseline(inputs.store("heatmaps").array("heatmap"), idx["train"], progress=inputs.progress,
                             every_s=cfg.run.progress_every_s)


def held_out_baselines(inputs, table, idx, cfg: Config, mean_map: np.ndarray) -> dict[str, float]:
    """Test losses of the trivial predictors the networks must beat: the mean training map
    ('mean_map_kl') and count ('mean_count_L_n', with 'train_mean_count'), and the training median
    RSS ('median_rss_L_a', with 'train_rss_median'); a loss is left out where its split is empty."""
    from pipeline.net_baselines import disnet_baseline, rssnet_baseline

    heat = inputs.store("heatmaps").array("heatmap")
    out: dict[str, float] = {}
    if len(idx["test"]):
        d = disnet_baseline(heat, table["count"], idx["train"], idx["test"], mean_map=mean_map)
        out.update(mean_map_kl=d["kl"], mean_count_L_n=d["n"])
    out["train_mean_count"] = float(table["count"][idx["train"]].mean())
    train_rss, test_rss = rssnet_data(inputs, table, 0, 0).rss, rssnet_data(inputs, table, 2, 2).rss
    if len(train_rss) and len(test_rss):
        # one flat array: the training points first, then the test points
        rss = np.concatenate([train_rss[np.arange(len(train_rss))], test_rss[np.arange(len(test_rss))]])
        r = rssnet_baseline(rss, np.arange(len(train_rss)), np.arange(len(train_rss), len(rss)),
                            cfg.radar.rss_min, cfg.radar.rss_max)
        out.update(median_rss_L_a=r["a"], train_rss_median=r["median"])
    return out


def training_fingerprint(inputs, cfg: Config, net: str) -> str:
    """What a net's checkpoints depend on: its config keys (not epochs) and the training data (the
    upstream outputs and which of their frames are done: a frame retried or finished later starts
    training afresh instead of resuming checkpoints that never saw it).

    Raising train.epochs (placement.epochs for PlaceNet) re-runs the stage but continues from the
    last finished epoch; lowering them below it trains the net again (pipeline.continuation).
    """
    from pipeline.continuation import default_fingerprint

    stores = ("calibrate", "heatmaps") if net == "disnet" else ("calibrate", "heatmaps", "patches")
    data = [f"{inputs.store(s).fingerprint()}:{inputs.store(s).done_digest()}" for s in stores]  # Dis-Net reads no patches
    return f"v{NET_VERSIONS[net]}-{default_fingerprint(cfg, net)}-" + "-".join(str(d) for d in data)


def run(inputs, cfg: Config, out, fingerprint: str) -> dict:
    """Train the configured nets; returns the summary (test metrics next to baselines)."""
    from pipeline.checkpoint import read_meta
    from pipeline.inference import load_disnet, load_rssnet
    from pipeline.training import disnet_metrics, rssnet_metrics, train_disnet, train_rssnet

    check(cfg)
    if cfg.train.nets_from:
        return _take_nets(inputs, cfg, out)
    nets = named_nets(cfg)
    table = frame_table(inputs)
    d_data, idx = disnet_data(inputs, table)
    if len(idx["train"]) == 0:
        raise PipelineError("train: no usable training frame (all failed, or no radar point in the train split); a "
                            "dataset without radar takes the nets of another: --set train.nets_from=DATASET")
    root = Path(out.path)
    summary: dict = {"frames": {k: int(len(v)) for k, v in idx.items()},
                     "frames_without_radar_points": int((table["ok"] & (table["count"] == 0)).sum()),
                     "checkpoints": _final_place(inputs, out), "settings": transfer.settings(cfg)}
    summary["baselines_test"] = _baselines(inputs, table, idx, cfg, root)
    shown = {"progress": inputs.progress, "every_s": cfg.run.progress_every_s}  # the test passes' progress
    if "disnet" in nets:
        res = train_disnet(cfg, d_data, root / "disnet", progress=inputs.progress,
                           fingerprint=training_fingerprint(inputs, cfg, "disnet"), publish=inputs.publish)
        model = load_disnet(cfg, res.best_path, device="cpu")
        summary["disnet"] = {**_epochs(res), "val": res.best_metric,
                             "test": disnet_metrics(model, d_data, idx["test"], cfg.train.alpha, **shown) if len(idx["test"]) else {}}
        best_meta = read_meta(res.best_path)
        refit = best_meta.get("count_refit")
        if refit:
            summary["disnet"]["count_refit"] = {k: v for k, v in refit.items() if k != "curve"}
        summary["disnet"]["prior_mix"] = best_meta.get("prior_mix")
    if "rssnet" in nets:
        r_data = rssnet_data(inputs, table, 0, 1)
        res = train_rssnet(cfg, r_data, root / "rssnet", progress=inputs.progress,
                           fingerprint=training_fingerprint(inputs, cfg, "rssnet"), publish=inputs.publish)
        model = load_rssnet(cfg, res.best_path, device="cpu")
        test = rssnet_data(inputs, table, 2, 2)
        summary["rssnet"] = {**_epochs(res), "val": res.best_metric,
                             "test": rssnet_metrics(model, test, test.train_idx, **shown) if len(test.rss) else {}}
    if "placenet" in nets:
        summary["placenet"] = _train_placenet(inputs, cfg, table, root)
    (root / "metrics.json").write_text(json.dumps(summary, indent=2, default=float))
    summary["message"] = _headline(summary)
    return summary


def _epochs(res) -> dict:
    """A net's epochs in the summary: its best, the one this run resumed from (0: a fresh start), the
    last it trained, and whether its patience ran out before its last epoch (train.patience)."""
    return {"best_epoch": res.best_epoch, "resumed_from": res.resumed_from, "epochs": res.epoch,
            "stopped_early": res.stopped_early}


def _final_place(inputs, out) -> str:
    """Where the checkpoints are kept: the output folder ``out``, or on a remote cache the remote
    folder that ``out`` (a local staging folder) is uploaded to; metrics.json named the staging
    folder on the machine that trained until 2026-12-07."""
    final = inputs.dir("train")
    return str(Path(out.path)) if final.is_local else final.url


def _take_nets(inputs, cfg: Config, out) -> dict:
    """train.nets_from: the checkpoints of the other dataset's finished train stage, copied (so that
    this cache keeps what its synthesis used), after checking that this configuration has the
    settings they were trained with (pipeline.transfer); this dataset's mean training map; the other
    dataset's camera (transfer.source_camera; in the summary as source_camera, None with the reason
    in the message when its calibrate output is gone), from which synthesize moves Dis-Net's prior."""
    named = cfg.train.nets_from
    source = transfer.checked_origin(cfg, inputs.env.cache_root)  # named may itself hold another's nets
    via = f" (through dataset {named}, which took them from it)" if source != named else ""
    try:
        trained = transfer.trained_settings(inputs.env.cache_root, source)
    except PipelineError as exc:
        raise type(exc)(f"{exc}{via}") from None
    wrong = transfer.mismatches(cfg, trained)
    if wrong:
        raise ConfigError(f"train.nets_from = '{source}': this configuration lacks settings the nets were trained "
                          f"with: {'; '.join(wrong)} (the CLI sets them itself; set them with --set)")
    src = transfer.source_train(inputs.env.cache_root, source)
    root, src_files = Path(out.path), src.local_copy(cfg.run.staging_dir)
    taken = [name for name in COPIED if (src_files / name).is_file()]
    for name in taken:
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src_files / name, root / name)
    _save_mean_map(inputs, root)
    meta = src.meta() or {}
    try:  # where the source radar's returns lay in its camera: Dis-Net's prior is moved from there
        camera, unmoved = transfer.camera_record(transfer.source_camera(inputs.env.cache_root, source)), ""
    except PipelineError as exc:
        camera, unmoved = None, (f"; Dis-Net's prior is not moved to this camera: {exc}, then `pipeline run train "
                                 f"--force --dataset {cfg.profile} ...` to take the nets again with its camera")
    record = {"nets_from": source, "source": src.path, "source_fingerprint": meta.get("fingerprint"),
              "source_finished": meta.get("finished"), "taken": taken, "settings": trained,
              "source_camera": camera, "source_metrics": meta.get("summary", {})}
    (root / "metrics.json").write_text(json.dumps(record, indent=2, default=float))
    nets = [n for n in NETS if f"{n}/best.safetensors" in taken]
    when = time.strftime("%Y-%m-%d %H:%M", time.gmtime(meta["finished"])) if meta.get("finished") else "?"
    return {"checkpoints": _final_place(inputs, out), "nets_from": source, "settings": trained, "source_camera": camera,
            "message": f"the nets of dataset {source}{via} ({', '.join(nets)}; trained {when} UTC): "
                       f"radar {trained.get('radar.name', '?')}{unmoved}"}


def _save_mean_map(inputs, root: Path) -> None:
    """The mean training heatmap of this dataset, for evaluate's baselines, where its train split has
    radar (a dataset without radar has nothing to evaluate against)."""
    from pipeline.net_baselines import mean_map_baseline

    table = frame_table(inputs)
    train = np.flatnonzero(table["ok"] & (table["count"] > 0) & (table["split"] == 0))
    if len(train):
        mean_map = mean_map_baseline(inputs.store("heatmaps").array("heatmap"), train, progress=inputs.progress,
                                     every_s=inputs.cfg.run.progress_every_s).astype(np.float32)
        np.save(root / MEAN_MAP_FILE, mean_map, allow_pickle=False)


def nets_from_fingerprint(cfg: Config, env) -> str:
    """train.nets_from: its value, the dataset that trained the nets (transfer.nets_origin) where
    that is another, and its train output (fingerprint and finishing time), so that retraining that
    one makes this train stage, and what was synthesized with its nets, stale, also through a
    dataset that took them from it; '' without (not a config key: train outputs made before it
    stay current)."""
    named = cfg.train.nets_from
    if not named:
        return ""
    origin = transfer.checked_origin(cfg, env.cache_root)  # before this stage's output is judged stale and cleared
    meta = transfer.source_train(env.cache_root, origin).meta()
    through = f">{origin}" if origin != named else ""  # the form of before chains for a direct source
    return f"{named}{through}:" + (f"{meta.get('fingerprint')}:{meta.get('finished')}" if meta else "absent")


def _train_placenet(inputs, cfg: Config, table, root: Path) -> dict:
    """Train PlaceNet; its summary with the test NLL next to the constant intensity's."""
    from pipeline.net_baselines import placenet_baseline
    from pipeline.inference import load_placenet
    from pipeline.training import placenet_metrics, train_placenet

    data = placenet_data(inputs, table, 0, 1, cfg)
    if len(data.train_idx) == 0:
        raise PipelineError("train: PlaceNet has no training row (no lidar point in the radar's field of view "
                            "of any usable training frame)")
    res = train_placenet(cfg, data, root / "placenet", progress=inputs.progress,
                         fingerprint=training_fingerprint(inputs, cfg, "placenet"), publish=inputs.publish)
    model = load_placenet(cfg, res.best_path, device="cpu")
    test = placenet_data(inputs, table, 2, 2)
    out = {**_epochs(res), "val": res.best_metric,
           "count_scale": model.count_scale,
           "rows": {"train": int(len(data.train_idx)), "val": int(len(data.val_idx)), "test": int(len(test.train_idx))},
           "test": {}}
    if len(test.train_idx):
        out["test"] = placenet_metrics(model, test, test.train_idx, progress=inputs.progress,
                                       every_s=cfg.run.progress_every_s)
        out["constant_intensity_test_nll"] = placenet_baseline(data.counts, data.train_idx, test.train_idx,
                                                               test.counts)["nll"]
    return out


FEW_TRAIN_FRAMES = 20
"""Fewer training frames than this: the train stage's line says the nets learn little from them
(the two View-of-Delft example frames split 1 / 0 / 1 trained nets equal to the baselines)."""


def _headline(s: dict) -> str:
    b = s["baselines_test"]
    nan = float("nan")
    parts = []
    if "disnet" in s and s["disnet"]["test"]:
        t = s["disnet"]["test"]
        w = (s["disnet"].get("prior_mix") or {}).get("w", 0.0)
        mixed = f", the mean map's share {w:g} chosen on val" if w else ""
        parts.append(f"Dis-Net test L_KL {t['kl']:.4f} (mean map {b.get('mean_map_kl', nan):.4f}{mixed}), "
                     f"L_n {t['n']:.4f} (mean count {b.get('mean_count_L_n', nan):.4f})")
    if "rssnet" in s and s["rssnet"]["test"]:
        parts.append(f"RSS-Net test L_a {s['rssnet']['test']['a']:.2e} (median {b.get('median_rss_L_a', float('nan')):.2e})")
    if "placenet" in s and s["placenet"]["test"]:
        parts.append(f"PlaceNet test NLL {s['placenet']['test']['nll']:.4f} "
                     f"(constant intensity {s['placenet'].get('constant_intensity_test_nll', nan):.4f})")
    stopped = [f"{net} after epoch {s[net]['epochs']} (best {s[net]['best_epoch']})"
               for net in NETS if s.get(net, {}).get("stopped_early")]
    if stopped:
        parts.append(f"stopped early: {', '.join(stopped)}")
    frames = s.get("frames", {})
    if frames.get("train", FEW_TRAIN_FRAMES) < FEW_TRAIN_FRAMES:
        parts.append(f"only {frames['train']} training frame(s) and {frames.get('val', 0)} val: from so few the nets "
                     f"learn little beyond the training means (enough to check the pipeline, not to simulate a radar)")
    return "; ".join(parts) or "trained"


def check(cfg: Config) -> None:
    """ConfigError for train.nets or training settings the stage cannot run with (epochs,
    intervals and text choices are held to pipeline.config.LIMITS and CHOICES where set)."""
    unknown = named_nets(cfg) - set(NETS)
    if unknown:
        raise ConfigError(f"train.nets: unknown net(s) {sorted(unknown)} (use {', '.join(NETS)})")
    if cfg.train.nets_from == cfg.profile:
        raise ConfigError(f"train.nets_from = '{cfg.train.nets_from}' names this dataset itself; leave it empty to "
                          f"train here")
    if cfg.train.nets_from:
        check_profile(cfg.train.nets_from, "train.nets_from")
    check_device("train.device", cfg.train.device)


HEADER_READ_BYTES = 1 << 16
"""Bytes a read of a checkpoint's header fetches at a time (s3fs would fetch 5 MB)."""


def resume_point(inputs, cfg: Config, out) -> str | None:
    """What an unfinished train left in ``out`` (a DirStore) for `pipeline status`: each net's last
    finished epoch, or that it was saved for other settings or data or has more epochs than now
    asked (pipeline.continuation), from which a run starts that net over; None when no net has a
    checkpoint. The epoch is the last checkpoint's own (its
    header, without torch), the one a run resumes from: on a remote cache the JSON sidecar beside
    it may arrive before it, and named one epoch more."""
    from pipeline.continuation import continuation_problem, stalled

    said = []
    for net in (n for n in NETS if n in named_nets(cfg)):
        try:
            meta = checkpoint_meta(out, f"{net}/last.safetensors")
        except ValueError:
            said.append(f"{net}: an unreadable checkpoint")
            continue
        if meta is None:
            continue
        n_epochs, patience = int(cfg.get(EPOCHS_KEYS[net])), int(cfg.get(PATIENCE_KEYS[net]))
        problem = continuation_problem(meta, n_epochs, patience, cfg.train.select_on)
        if meta.get("fingerprint") != training_fingerprint(inputs, cfg, net):
            said.append(f"{net} epoch {meta.get('epoch')} for other settings or data (trains again)")
        elif int(meta.get("epoch", 0)) > n_epochs:
            said.append(f"{net} epoch {meta.get('epoch')}, more than the {n_epochs} now asked (trains again)")
        elif problem:
            said.append(f"{net} epoch {meta.get('epoch')}: {problem} (trains again)")
        elif stalled(meta, patience) and int(meta.get("epoch", 0)) < n_epochs:
            said.append(f"{net} done, stopped early after epoch {meta.get('epoch')} of {n_epochs}")
        else:
            inside = meta.get("partial") or {}
            more = (f" and {inside['batches']} of {inside['of_batches']} batches of epoch {inside['epoch']}"
                    if inside.get("epoch") == int(meta.get("epoch", 0)) + 1 and "batches" in inside else "")
            said.append(f"{net} epoch {meta.get('epoch')} of {n_epochs}{more}")
    return ", ".join(said) or None


def checkpoint_meta(out, name: str) -> dict | None:
    """The metadata of the checkpoint ``name`` in the folder ``out`` (a DirStore), read from its
    header without torch; None when there is none; ValueError when it cannot be read."""
    from pipeline.safetensors_meta import read_metadata

    try:
        with out.fs.open(out.file(name), "rb", block_size=HEADER_READ_BYTES) as fh:
            meta = json.loads(read_metadata(fh).get("meta", "{}"))
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        raise ValueError(f"{out.file(name)}: {exc}") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{out.file(name)}: its metadata is not a JSON object")
    return meta


def net_state(inputs, cfg: Config, net: str, meta: dict) -> str:
    """Where a net whose last checkpoint has metadata ``meta`` stands under ``cfg``: 'trained' (its
    epochs done, or its patience run out), 'part-trained' (a run goes on from its epoch) or
    'retrains' (saved for other settings or data, or past where these settings stop:
    pipeline.continuation)."""
    from pipeline.continuation import continuation_problem, stalled

    n_epochs, patience = int(cfg.get(EPOCHS_KEYS[net])), int(cfg.get(PATIENCE_KEYS[net]))
    if (meta.get("fingerprint") != training_fingerprint(inputs, cfg, net)
            or continuation_problem(meta, n_epochs, patience, cfg.train.select_on)):
        return "retrains"
    return "trained" if int(meta.get("epoch", 0)) == n_epochs or stalled(meta, patience) else "part-trained"


STAGE = DatasetStage(name="train", upstream=("calibrate", "heatmaps", "patches"), config_keys=CONFIG_KEYS, version=VERSION,
                     run=run, doc=__doc__, check=check, extra_fingerprint=nets_from_fingerprint, local_files=True,
                     resumes=True, resume_point=resume_point)
