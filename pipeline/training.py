"""Resumable training of Dis-Net, RSS-Net and PlaceNet (torchvision-reference style:
train_one_epoch, evaluate, run), their test metrics and what the best checkpoints add (Dis-Net's
refitted count branch, PlaceNet's count scale, RSS-Net's residual quantiles). Loading and
prediction are in pipeline.inference, the nets' baselines in pipeline.net_baselines.

Data are array-likes (numpy or zarr arrays) indexed by frame / point along axis 0; they are read
one window of batches at a time (pipeline.rows: sorted reads, one chunk-group order per epoch),
never all at once.

Files in ``out_dir`` (one folder per net; a folder holding the other net's checkpoint is refused):
``last.safetensors`` (+ ``last.json`` sidecar): weights, optimizer, RNG, epoch, curves - the
resume point, written last in every epoch; ``best.safetensors`` (+ ``best.json``): weights of the
epoch with the lowest validation loss (with train.count_refit_epochs, Dis-Net's number branch then
refitted on that epoch's backbone; its meta holds the 'count_refit' record); ``curves.csv`` /
``curves.json`` / ``curves.png``.
Resuming is the default: a last checkpoint with the same fingerprint and architecture continues
from its epoch and ends with exactly the weights of an uninterrupted run (same device and threads).
"""

from __future__ import annotations

import csv
import functools
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np
import torch
from torch import Tensor, nn
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from pipeline import augment
from pipeline import checkpoint as ckpt
from pipeline.config import EPOCHS_KEYS, PATIENCE_KEYS, check_limit
from pipeline.continuation import continuation_problem, default_fingerprint, stalled
from pipeline.errors import ConfigError
from pipeline.net_baselines import mean_map_baseline, speed_count_prior
from pipeline.inference import (RESIDUAL_KEY, RESIDUAL_LEVELS, device_of, disnet_inputs, jsonable_arch,
                                model_state, placenet_predict, rss_arrays, rssnet_inputs, select_device)
from pipeline.models.disnet import DisNet, build_disnet, disnet_kwargs, mix_with_prior
from pipeline.models.losses import count_loss, kl_loss, poisson_loss, rss_loss
from pipeline.models.placenet import PlaceNet, build_placenet, placenet_kwargs
from pipeline.models.rssnet import RSSNet, build_rssnet, rssnet_kwargs
from pipeline.patches import input_summaries
from pipeline.progress import EVERY_S, Heartbeat, bar as progress_bar
from pipeline.rows import (WINDOW_BATCHES, Batch, Rows, as_rows, chunk_len, epoch_windows, evenly_spaced,
                           iter_batches, n_rows, take_rows)

log = logging.getLogger(__name__)
TermsFn = Callable[[nn.Module, Batch, torch.device], dict[str, Tensor]]


@dataclass
class DisNetData:
    """Dis-Net training data; arrays indexed by frame along axis 0.

    images (F, H, W, 3) uint8 RGB; heatmaps (F, H, W) float32 summing to 1; counts (F,) radar
    points per frame (> 0 for every listed frame); speeds (F,) ego speed |v_D| m/s;
    train_idx / val_idx: frame indices (frames without radar points already excluded).
    """

    images: Any
    heatmaps: Any
    counts: Any
    speeds: Any
    train_idx: Sequence[int]
    val_idx: Sequence[int]
    prior_map: Any = None
    """(H, W) mean training heatmap for disnet.prior (None: computed from the train frames)."""


@dataclass
class RssNetData:
    """RSS-Net training data; arrays indexed by sampled radar point along axis 0.

    patches (P, ps, ps, 3) uint8 RGB; range_images (P, h, w) float32 0..255 or empty (see
    pipeline.models.rssnet); point_vectors (P, 4) [x, y, z m in {D}, doppler m/s]; rss (P,)
    dataset units; train_idx / val_idx: point indices.
    """

    patches: Any
    range_images: Any
    point_vectors: Any
    rss: Any
    train_idx: Sequence[int]
    val_idx: Sequence[int]


@dataclass
class PlaceNetData:
    """PlaceNet training data; arrays indexed by sampled lidar candidate along axis 0.

    features (P, len(pipeline.placement.FEATURES)) float32; counts (P,) real radar points whose
    nearest candidate this is (pipeline.placement.radar_counts); train_idx / val_idx: row indices.
    Optional, for the count scale (:func:`placenet_count_scale`), per training frame in row order
    (the training rows are the first sum(train_frame_rows)): train_frame_rows (F,) its rows,
    train_frame_candidates () -> (F,) the candidates they were sampled from (called only when the
    scale is computed), train_frame_counts (F,) its real radar points.
    """

    features: Any
    counts: Any
    train_idx: Sequence[int]
    val_idx: Sequence[int]
    train_frame_rows: np.ndarray | None = None
    train_frame_candidates: Callable[[], np.ndarray] | None = None
    train_frame_counts: np.ndarray | None = None


@dataclass
class TrainResult:
    """Outcome of train_disnet / train_rssnet / train_placenet."""

    net: str
    last_path: Path
    best_path: Path
    epoch: int
    """Last finished epoch."""
    resumed_from: int
    """Epoch the run continued from (0 = fresh start)."""
    best_epoch: int
    best_metric: float
    curves: list[dict[str, float]] = field(default_factory=list)
    stopped_early: bool = False
    """Whether the net stopped before its last epoch, its patience having run out (in this run or
    the one it resumed)."""


def _progress(iterable: Iterable, total: int, desc: str, enabled: bool, every_s: float = EVERY_S):
    return progress_bar(iterable, total=total, desc=desc, unit="batch", enabled=enabled, every_s=every_s)


# ------------------------------------------------------------------------------- loop


def _weighted_total(terms: dict[str, Tensor], weights: dict[str, float]) -> Tensor:
    return sum(weights[k] * terms[k] for k in weights)


def train_one_epoch(model: nn.Module, optimizer: torch.optim.Optimizer, batches: Iterable[Batch],
                    terms_fn: TermsFn, weights: dict[str, float], device: torch.device,
                    n_batches: int = 0, desc: str = "train", progress: bool = True,
                    ema: AveragedModel | None = None, every_s: float = EVERY_S,
                    totals: tuple[dict[str, float], int] | None = None,
                    after_step: Callable[[int, dict[str, float], int], None] | None = None) -> dict[str, float]:
    """One pass over ``batches``; loss = mean over the batch of sum_k weights[k] * term_k; ``ema``
    (when given) is updated after every optimiser step. ``totals``: the per-sample sums and their
    count of the epoch's batches trained before these (a resume inside the epoch); ``after_step``
    is called after each step with its index in ``batches`` and the sums and count so far.

    Returns per-sample means of every term and of the loss (key 'loss'). Raises FloatingPointError
    on a non-finite loss (before any checkpoint of the epoch is written).
    """
    model.train()
    sums: dict[str, float] = dict(totals[0]) if totals else {}
    count = totals[1] if totals else 0
    bar = _progress(batches, n_batches, desc, progress, every_s)
    for step, batch in enumerate(bar):
        terms = terms_fn(model, batch, device)
        total = _weighted_total(terms, weights)                    # (B,)
        loss = total.mean()
        if not torch.isfinite(loss):
            raise FloatingPointError(f"{desc}: non-finite loss at batch {step}")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if ema is not None:
            ema.update_parameters(model)
        count += _accumulate(sums, {**terms, "loss": total})
        if after_step is not None:
            after_step(step, sums, count)
        if step % 10 == 0 and hasattr(bar, "set_postfix"):
            bar.set_postfix(loss=f"{loss.item():.4g}", refresh=False)  # a refresh would write a log line now
    return {k: v / max(count, 1) for k, v in sums.items()}


@torch.no_grad()
def evaluate(model: nn.Module, batches: Iterable[Batch], terms_fn: TermsFn, weights: dict[str, float],
             device: torch.device, n_batches: int = 0, desc: str = "val",
             progress: bool = True, every_s: float = EVERY_S) -> dict[str, float]:
    """Per-sample (per-frame / per-point) means of every term and of the weighted loss, eval mode.
    Empty input gives NaN for every key."""
    model.eval()
    sums: dict[str, float] = {}
    count = 0
    for batch in _progress(batches, n_batches, desc, progress, every_s):
        terms = terms_fn(model, batch, device)
        count += _accumulate(sums, {**terms, "loss": _weighted_total(terms, weights)})
    keys = list(weights) + ["loss"]
    return {k: (sums[k] / count if count else math.nan) for k in keys}


def _accumulate(sums: dict[str, float], terms: dict[str, Tensor]) -> int:
    for k, v in terms.items():
        sums[k] = sums.get(k, 0.0) + float(v.detach().double().sum())
    return int(next(iter(terms.values())).shape[0])


@dataclass
class _NetSpec:
    """Everything run() needs to know about one net."""

    name: str
    model: nn.Module
    arch: dict[str, Any]
    arrays: dict[str, Any]
    train_idx: Rows
    val_idx: Rows
    batch_size: int
    terms_fn: TermsFn
    weights: dict[str, float]
    lr: float | None = None
    """Base learning rate (None: cfg.train.lr)."""


Publish = Callable[[list[Path]], bool]
"""Uploads the given files of a staged output now; False: the upload failed (logged; the run goes
on) (pipeline.runner.DatasetInputs.publish)."""


def run(spec: _NetSpec, cfg, out_dir: str | Path, fingerprint: str, progress: bool = True,
        publish: Publish | None = None) -> TrainResult:
    """Train ``spec.model`` for the epochs its config key says (EPOCHS_KEYS), or until as many epochs
    as its patience (PATIENCE_KEYS; 0: none) have passed since its best one, resuming from ``out_dir``
    when possible: from the last epoch's end, or from a resume point inside the next epoch (saved
    after a window of batches every cfg.train.checkpoint_every_s), skipping the windows it trained.
    With ``publish`` (an output staged for a remote cache), a save at least
    cfg.run.checkpoint_upload_s after the last upload hands the checkpoints to it
    (:func:`publish_checkpoints`)."""
    epochs_key = EPOCHS_KEYS[spec.name]
    n_epochs = int(cfg.get(epochs_key))
    if n_epochs < 0:
        raise ConfigError(f"{epochs_key} must be >= 0, got {n_epochs}")
    patience = int(cfg.get(PATIENCE_KEYS[spec.name]))
    if patience < 0:
        raise ConfigError(f"{PATIENCE_KEYS[spec.name]} must be >= 0, got {patience}")
    out_dir = Path(out_dir)
    last, best = out_dir / "last.safetensors", out_dir / "best.safetensors"
    device = select_device(cfg.train.device)
    spec.model.to(device)
    base_lr = cfg.train.lr if spec.lr is None else spec.lr
    if cfg.train.weight_decay > 0:
        optimizer = torch.optim.AdamW(spec.model.parameters(), lr=base_lr, weight_decay=cfg.train.weight_decay)
    else:
        optimizer = torch.optim.Adam(spec.model.parameters(), lr=base_lr)
    select_key = selection_key(cfg.train.select_on, spec.weights)
    ema = make_ema(spec.model, cfg.train.ema_decay)
    scored = ema.module if ema is not None else spec.model  # the weights validated and saved as best
    rng = np.random.default_rng(cfg.train.seed)
    state = {"epoch": 0, "best_epoch": 0, "best_metric": math.inf, "curves": []}
    resumed = _resume(last, best, spec, optimizer, fingerprint, device, n_epochs, ema, patience,
                      cfg.train.select_on)
    if resumed is not None:
        state, rng = resumed
    start = state["epoch"]
    rows_per_chunk = chunk_len(next(iter(spec.arrays.values())))
    n_train_batches = math.ceil(len(spec.train_idx) / spec.batch_size)
    n_val_batches = math.ceil(len(spec.val_idx) / spec.batch_size)
    partial = state.pop("partial", None)  # a resume point inside epoch start + 1
    save_every_s = float(cfg.train.checkpoint_every_s)
    uploaded_at, uploaded_best = time.monotonic(), None
    every_s = cfg.run.progress_every_s
    heartbeat = Heartbeat(progress, every_s)

    def upload() -> None:
        nonlocal uploaded_at, uploaded_best
        if publish is not None and time.monotonic() - uploaded_at >= cfg.run.checkpoint_upload_s:
            if publish_checkpoints(publish, best, last, with_best=state["best_epoch"] != uploaded_best):
                uploaded_best = state["best_epoch"]  # else a best that failed is sent again next time
            uploaded_at = time.monotonic()

    for epoch in range(start + 1, n_epochs + 1):
        if stalled(state, patience):
            break  # stopped early, in this run or the one resumed
        t0 = time.perf_counter()
        for group in optimizer.param_groups:  # a function of the epoch alone: resumes exactly
            group["lr"] = epoch_lr(cfg, epoch, base_lr, n_epochs)
        epoch_rng = ckpt.numpy_rng_state(rng)  # the epoch's windows are drawn from this state
        order = epoch_windows(spec.train_idx, rows_per_chunk, spec.batch_size * WINDOW_BATCHES, rng)
        skipped, totals = 0, None
        if partial is not None:
            skipped, totals, t0 = partial["windows"], (partial["sums"], partial["count"]), t0 - partial["seconds"]
            for _ in range(skipped):
                next(order)  # drawn as the run that trained them drew them, not read again
            partial = None
        saved_at = time.monotonic()

        def save_inside_epoch(step: int, sums: dict[str, float], count: int) -> None:
            """After a batch window that ends at least train.checkpoint_every_s after the last save
            (not the epoch's last: the epoch's end saves), a resume point inside the epoch."""
            nonlocal saved_at
            batches = skipped * WINDOW_BATCHES + step + 1
            if batches % WINDOW_BATCHES or batches >= n_train_batches or time.monotonic() - saved_at < save_every_s:
                return
            inside = {"epoch": epoch, "windows": batches // WINDOW_BATCHES, "batches": batches,
                      "of_batches": n_train_batches, "sums": sums, "count": count,
                      "seconds": time.perf_counter() - t0}
            _save_last(last, spec, optimizer, epoch_rng, fingerprint, {**state, "partial": inside}, ema)
            saved_at = time.monotonic()
            upload()

        tr = train_one_epoch(spec.model, optimizer, iter_batches(spec.arrays, order, spec.batch_size),
                             spec.terms_fn, spec.weights, device, n_train_batches - skipped * WINDOW_BATCHES,
                             f"{spec.name} epoch {epoch}/{n_epochs}", progress, ema, every_s, totals,
                             save_inside_epoch if save_every_s > 0 else None)
        va = evaluate(scored, iter_batches(spec.arrays, spec.val_idx, spec.batch_size), spec.terms_fn,
                      spec.weights, device, n_val_batches, f"{spec.name} val", progress, every_s)
        metric = va[select_key] if len(spec.val_idx) else tr[select_key]
        state["curves"].append({"epoch": epoch, **{f"train_{k}": v for k, v in tr.items()},
                                **{f"val_{k}": v for k, v in va.items()},
                                "seconds": time.perf_counter() - t0})
        state["epoch"] = epoch
        if metric < state["best_metric"]:
            state["best_epoch"], state["best_metric"] = epoch, metric
            ckpt.save_checkpoint(best, ckpt.model_tensors(scored), _meta(spec, fingerprint, state))
        _save_last(last, spec, optimizer, ckpt.numpy_rng_state(rng), fingerprint, state, ema)  # the epoch's commit
        heartbeat.maybe(epoch_line(spec.name, epoch, n_epochs, tr, va if len(spec.val_idx) else None, select_key,
                                   state["best_epoch"], state["curves"][-1]["seconds"]))
        write_curves(out_dir, spec.name, state["curves"], plot=False)
        upload()
    write_curves(out_dir, spec.name, state["curves"], plot=True)
    return TrainResult(spec.name, last, best, state["epoch"], start, state["best_epoch"], state["best_metric"],
                       state["curves"], stopped_early=state["epoch"] < n_epochs and stalled(state, patience))


def epoch_line(net: str, epoch: int, n_epochs: int, train: dict[str, float], val: dict[str, float] | None,
               select_key: str, best_epoch: int, seconds: float) -> str:
    """One line on a finished epoch for a log: 'disnet epoch 3/12: train loss 0.4123, val loss
    0.3987 kl 0.2510 (best so far), 52 s' (no val part without a validation split)."""
    where = f"val loss {val['loss']:.4g}" + (f" {select_key} {val[select_key]:.4g}" if select_key != "loss" else "") \
        if val is not None else "no val split"
    best = " (best so far)" if best_epoch == epoch else f" (best: epoch {best_epoch})"
    return f"{net} epoch {epoch}/{n_epochs}: train loss {train['loss']:.4g}, {where}{best}, {seconds:.0f} s"


def publish_checkpoints(publish: Publish, best: Path, last: Path, with_best: bool = True) -> bool:
    """Hand a finished epoch's checkpoints (each with its JSON sidecar) to ``publish``: ``best``
    (when ``with_best`` and it exists), then ``last``, in two calls, in the order the epoch wrote
    them; so an upload cut off between the two leaves what a run killed between the writes leaves,
    from which training resumes exactly. When the upload of ``best`` fails, ``last`` (which names
    that best epoch) is not sent without it. Whether both were uploaded."""
    if with_best and best.exists() and not publish([best, best.with_suffix(".json")]):
        return False
    return bool(publish([last, last.with_suffix(".json")]))


def selection_key(select_on: str, weights: dict[str, float]) -> str:
    """The loss term that picks the best epoch: ``select_on`` when the net has that term (Dis-Net's
    'kl'), else the weighted total 'loss' (RSS-Net has one term). ConfigError for unknown values."""
    check_limit("train.select_on", select_on)
    return select_on if select_on in weights else "loss"


def unit_interval(key: str, value: float, include_one: bool = True) -> float:
    """``value`` as a float in [0, 1] ([0, 1) without ``include_one``); ConfigError naming ``key``."""
    x = float(value)
    if not (np.isfinite(x) and 0.0 <= x and (x <= 1.0 if include_one else x < 1.0)):
        raise ConfigError(f"{key} must be in [0, 1{']' if include_one else ')'}, got {x}")
    return x


def make_ema(model: nn.Module, decay: float) -> AveragedModel | None:
    """Exponential moving average of ``model``'s parameters and buffers (BatchNorm statistics
    included) with ``decay`` per update; None when decay is 0 (ConfigError outside [0, 1))."""
    decay = unit_interval("train.ema_decay", decay, include_one=False)
    if decay == 0.0:
        return None
    return AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(decay), use_buffers=True)


def epoch_lr(cfg, epoch: int, base_lr: float | None = None, epochs: int | None = None) -> float:
    """Learning rate of epoch ``epoch`` (1-based) of ``epochs`` (None: cfg.train.epochs) under
    cfg.train.lr_schedule, starting from ``base_lr`` (None: cfg.train.lr)."""
    t = cfg.train
    lr = t.lr if base_lr is None else base_lr
    check_limit("train.lr_schedule", t.lr_schedule)
    if t.lr_schedule == "constant":
        return lr
    return lr * 0.5 * (1.0 + math.cos(math.pi * (epoch - 1) / (t.epochs if epochs is None else epochs)))


def _meta(spec: _NetSpec, fingerprint: str, state: dict[str, Any]) -> dict[str, Any]:
    return {"net": spec.name, "fingerprint": fingerprint, "arch": spec.arch,
            "selection": "val" if len(spec.val_idx) else "train", **state}


def _save_last(path: Path, spec: _NetSpec, optimizer: torch.optim.Optimizer, rng_state: dict[str, Any],
               fingerprint: str, state: dict[str, Any], ema: AveragedModel | None = None) -> None:
    """The resume point: weights, optimizer, torch RNGs (and ``ema``) as they are now, the numpy
    generator's ``rng_state`` (the next epoch's windows are drawn from it; for a point inside an
    epoch, state['partial'], that epoch's), and ``state``."""
    opt_tensors, opt_json = ckpt.flatten_optimizer(optimizer)
    tensors = {**ckpt.model_tensors(spec.model), **opt_tensors, **ckpt.rng_tensors()}
    if ema is not None:
        tensors.update({f"ema.{k}": v for k, v in ema.state_dict().items()})
    meta = {**_meta(spec, fingerprint, state), "optimizer": opt_json, "numpy_rng": rng_state}
    ckpt.save_checkpoint(path, tensors, meta)


def _resume(last: Path, best: Path, spec: _NetSpec, optimizer: torch.optim.Optimizer, fingerprint: str,
            device: torch.device, n_epochs: int, ema: AveragedModel | None = None, patience: int = 0,
            select_on: str = "loss") -> tuple[dict[str, Any], np.random.Generator] | None:
    """Restore model, optimizer, RNGs (and ``ema``) from ``last`` when it matches and a run of
    ``n_epochs`` with ``patience`` may continue it (pipeline.continuation); else clear the net's
    checkpoints, so that it trains from scratch."""
    if not last.exists():
        return None
    meta = ckpt.read_meta(last)
    if meta.get("net") != spec.name:
        raise ValueError(f"{last} is a {meta.get('net')!r} checkpoint: train {spec.name} in its own folder")
    problem = ("saved for other settings" if meta.get("fingerprint") != fingerprint or meta.get("arch") != spec.arch
               else continuation_problem(meta, n_epochs, patience, select_on))
    if problem:
        log.warning("%s: %s; training %s from scratch", last, problem, spec.name)
        for p in (last, best, last.with_suffix(".json"), best.with_suffix(".json")):
            p.unlink(missing_ok=True)
        return None
    tensors, meta = ckpt.load_checkpoint(last)
    spec.model.load_state_dict(model_state(spec.model, tensors), strict=True)
    spec.model.to(device)
    optimizer.load_state_dict(ckpt.unflatten_optimizer(tensors, meta["optimizer"]))
    if ema is not None:
        ema.load_state_dict(ckpt.strip_prefix(tensors, "ema."), strict=True)
    ckpt.restore_rng(tensors)
    state = {k: meta[k] for k in ("epoch", "best_epoch", "best_metric", "curves")}
    if meta.get("partial") and meta["partial"].get("epoch") == meta["epoch"] + 1:
        state["partial"] = meta["partial"]  # weights and optimizer from inside that epoch
    return state, ckpt.numpy_rng_from_state(meta["numpy_rng"])


def write_curves(out_dir: str | Path, net: str, curves: list[dict[str, float]], plot: bool = True) -> None:
    """``curves.csv`` / ``.json`` and, with ``plot``, ``.png`` (train vs val per metric of ``net``,
    matplotlib Agg; drawn once at the end of a run because drawing costs more than a tiny epoch)."""
    out_dir = Path(out_dir)
    ckpt.write_json_atomic(out_dir / "curves.json", curves)
    if not curves:
        return
    keys = list(curves[0])
    tmp = out_dir / "curves.csv.tmp"
    with open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys)
        writer.writeheader()
        writer.writerows(curves)
    tmp.replace(out_dir / "curves.csv")
    if plot:
        _plot_curves(out_dir / "curves.png", net, curves)


def _plot_curves(path: Path, net: str, curves: list[dict[str, float]]) -> None:
    from matplotlib.figure import Figure

    terms = [k[len("train_"):] for k in curves[0] if k.startswith("train_")]
    fig = Figure(figsize=(4 * len(terms), 3.2))
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.16, top=0.88, wspace=0.3)
    epochs = [c["epoch"] for c in curves]
    for i, term in enumerate(terms):
        ax = fig.add_subplot(1, len(terms), i + 1)
        for split in ("train", "val"):
            ax.plot(epochs, [c[f"{split}_{term}"] for c in curves], marker="o", label=split)
        ax.set_title(f"{net} {term}")
        ax.set_xlabel("epoch")
        ax.legend()
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=100)
    tmp.replace(path)


# ------------------------------------------------------------------------------- Dis-Net


def disnet_terms(model: nn.Module, batch: Batch, device: torch.device, flip: bool = False,
                 cutmix: float = 0.0, jitter: float = 0.0) -> dict[str, Tensor]:
    """Per-frame L_KL ('kl') and L_n ('n') of one batch; in training mode, ``flip`` mirrors,
    ``cutmix`` mixes frames and ``jitter`` varies brightness and contrast (pipeline.augment), in
    that order."""
    img, speed = disnet_inputs(batch, device)
    target = torch.from_numpy(np.asarray(batch["heatmaps"], np.float32)).to(device)
    counts = torch.from_numpy(np.asarray(batch["counts"], np.float32)).to(device)
    if model.training and flip:
        img, target = augment.mirror(img, target)
    if model.training and cutmix > 0:
        img, target, counts = augment.cutmix(img, target, counts, cutmix)
    if model.training and jitter > 0:
        img = augment.photometric(img, jitter)
    log_map, n_hat = model(img, speed)
    return {"kl": kl_loss(log_map, target), "n": count_loss(n_hat, counts)}


def _setup(cfg) -> None:
    torch.set_num_threads(max(1, int(cfg.train.threads)))
    torch.manual_seed(cfg.train.seed)


def _checked_idx(idx: Sequence[int], name: str, arrays: dict[str, Any], allow_empty: bool) -> Rows:
    """Indices as int64 (a ``range`` of step 1 stays one), checked against the arrays (which must
    all have the same length)."""
    lengths = {k: n_rows(a) for k, a in arrays.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(f"training arrays differ in length along axis 0: {lengths}")
    n = next(iter(lengths.values()))
    arr = as_rows(idx)
    if not allow_empty and len(arr) == 0:
        raise ValueError(f"{name} is empty: nothing to train on")
    if len(arr):
        lo, hi = (arr.start, arr.stop - 1) if isinstance(arr, range) else (int(arr.min()), int(arr.max()))
        if lo < 0 or hi >= n:
            raise ValueError(f"{name} holds indices outside 0..{n - 1}: {lo}..{hi}")
    return arr


def _check_disnet_data(cfg, data: DisNetData, idx: np.ndarray) -> None:
    """Shapes against camera.working_size and positive counts on every listed frame."""
    w, h = cfg.camera.working_size
    if tuple(data.heatmaps.shape[1:]) != (h, w) or tuple(data.images.shape[1:]) != (h, w, 3):
        raise ValueError(f"Dis-Net data: images {tuple(data.images.shape)} / heatmaps "
                         f"{tuple(data.heatmaps.shape)} do not match camera.working_size {w}x{h}")
    counts = take_rows(data.counts, idx)
    if (counts <= 0).any():
        raise ValueError(f"Dis-Net data: frames {idx[counts <= 0][:10].tolist()} have no radar points "
                         "(no heatmap target): leave them out of train_idx / val_idx")


def train_disnet(cfg, data: DisNetData, out_dir: str | Path, progress: bool = True,
                 fingerprint: str | None = None, publish: Publish | None = None) -> TrainResult:
    """Train Dis-Net with L = L_KL + alpha L_n (Adam, cfg.train.*); resumes from ``out_dir``."""
    _setup(cfg)
    model = build_disnet(cfg)
    model.count_grad_scale = unit_interval("train.count_grad_scale", cfg.train.count_grad_scale)
    mix = unit_interval("train.cutmix", cfg.train.cutmix)
    jitter = unit_interval("train.jitter", cfg.train.jitter)
    model.map_dropout = unit_interval("train.map_dropout", cfg.train.map_dropout, include_one=False)
    refit_epochs = int(cfg.train.count_refit_epochs)
    if refit_epochs < 0:
        raise ConfigError(f"train.count_refit_epochs must be >= 0, got {refit_epochs}")
    arrays = {"images": data.images, "heatmaps": data.heatmaps, "counts": data.counts, "speeds": data.speeds}
    spec = _NetSpec(
        name="disnet", model=model, arch=jsonable_arch(disnet_kwargs(cfg)), arrays=arrays,
        train_idx=_checked_idx(data.train_idx, "train_idx", arrays, False),
        val_idx=_checked_idx(data.val_idx, "val_idx", arrays, True),
        batch_size=cfg.train.batch_size,
        terms_fn=functools.partial(disnet_terms, flip=bool(cfg.train.flip), cutmix=mix, jitter=jitter),
        weights={"kl": 1.0, "n": float(cfg.train.alpha)})
    _check_disnet_data(cfg, data, np.concatenate([spec.train_idx, spec.val_idx]))
    if cfg.disnet.prior:
        prior = data.prior_map if data.prior_map is not None else mean_map_baseline(data.heatmaps, spec.train_idx)
        model.set_prior(prior)
        counts = np.asarray(take_rows(data.counts, spec.train_idx), np.float64)
        if cfg.disnet.use_speed and cfg.disnet.speed_count_prior:
            knots, means = speed_count_prior(take_rows(data.speeds, spec.train_idx), counts)
            model.set_count_prior(means, knots)
            log.info("disnet: count prior %s at %s m/s", np.round(means, 1).tolist(), np.round(knots, 2).tolist())
        else:
            model.set_count_prior(float(counts.mean()))
    res = run(spec, cfg, out_dir, fingerprint or default_fingerprint(cfg, "disnet"), progress, publish)
    if refit_epochs > 0:
        _refit_best_count(cfg, spec, res.best_path, refit_epochs, progress)
    # every run: the setting may have changed since the checkpoint was written (it is no training key)
    _add_to_best_meta(res, model, PRIOR_MIX_KEY, lambda m: choose_prior_mix(m, data, spec.val_idx,
                                                                            cfg.disnet.prior_mix), again=True)
    return res


PRIOR_MIX_KEY = "prior_mix"
"""Dis-Net checkpoint metadata: how its prior share was chosen (:func:`choose_prior_mix`)."""
PRIOR_MIX_GRID = np.round(np.linspace(0.0, 1.0, 21), 2)
"""The prior shares w disnet.prior_mix = 'val' tries."""


def choose_prior_mix(model: DisNet, data: DisNetData, idx: Sequence[int], setting: str) -> dict[str, Any]:
    """Set Dis-Net's prior share (DisNet.set_prior_mix): with ``setting`` 'val', the w of
    PRIOR_MIX_GRID with the lowest mean L_KL of its mixed map over frames ``idx`` (the val split);
    else, without a prior or without frames, 0. Returns the record the checkpoint keeps: w, the
    setting and (with 'val') the val L_KL with and without the mixture."""
    model.set_prior_mix(0.0)
    check_limit("disnet.prior_mix", setting)
    if setting == "off" or not model.use_prior or len(idx) == 0:
        return {"w": 0.0, "setting": setting}
    kl = prior_mix_kl(model, data, idx)
    best = int(np.argmin(kl))
    model.set_prior_mix(float(PRIOR_MIX_GRID[best]))
    return {"w": float(PRIOR_MIX_GRID[best]), "setting": setting, "val_kl": float(kl[best]),
            "val_kl_unmixed": float(kl[0]), "val_frames": int(len(idx))}


@torch.no_grad()
def prior_mix_kl(model: DisNet, data: DisNetData, idx: Sequence[int], grid: np.ndarray = PRIOR_MIX_GRID,
                 batch: int = 8) -> np.ndarray:
    """Mean L_KL (len(grid),) over frames ``idx`` of Dis-Net's map mixed with its prior,
    (1 - w) map + w prior for each w of ``grid`` (the model's own share set to 0 meanwhile)."""
    model.eval()
    device, kept = device_of(model), float(model.prior_mix)
    model.set_prior_mix(0.0)
    sums, n = np.zeros(len(grid)), 0
    arrays = {"images": data.images, "heatmaps": data.heatmaps, "speeds": data.speeds}
    for b in iter_batches(arrays, np.asarray(idx, np.int64), batch):
        log_map, _ = model(*disnet_inputs(b, device))
        target = torch.from_numpy(np.asarray(b["heatmaps"], np.float32)).to(device)
        for k, w in enumerate(grid):
            mixed = log_map if w == 0 else mix_with_prior(log_map, model.prior_logits, float(w))
            sums[k] += float(kl_loss(mixed, target).double().sum())
        n += len(log_map)
    model.set_prior_mix(kept)
    return sums / max(n, 1)


def _refit_best_count(cfg, spec: _NetSpec, best: Path, epochs: int, progress: bool) -> None:
    """Refit the number branch of the best checkpoint (refit_count_branch) unless it already was:
    a new best epoch writes a checkpoint without the 'count_refit' record. The checkpoint is
    replaced atomically, so a kill during the refit leaves the trained weights to refit again."""
    tensors, meta = ckpt.load_checkpoint(best)
    if "count_refit" in meta:
        return
    model = spec.model
    model.load_state_dict(ckpt.strip_prefix(tensors, "model."), strict=True)
    device = select_device(cfg.train.device)
    select_idx = spec.val_idx if len(spec.val_idx) else spec.train_idx
    record = refit_count_branch(model, spec.arrays, spec.train_idx, select_idx, epochs, cfg.train.lr,
                                cfg.train.batch_size, cfg.train.seed, device, progress)
    record["selection"] = "val" if len(spec.val_idx) else "train"
    log.info("disnet: number branch refit, %s L_n %.4f -> %.4f (pass %d of %d)", record["selection"],
             record["select_n_before"], record["select_n_after"], record["best_pass"], epochs)
    ckpt.save_checkpoint(best, ckpt.model_tensors(model), {**meta, "count_refit": record})


def refit_count_branch(model: DisNet, arrays: dict[str, Any], train_idx: Rows, select_idx: Rows,
                       epochs: int, lr: float, batch_size: int, seed: int, device: torch.device,
                       progress: bool = False) -> dict[str, Any]:
    """Train ``model``'s number branch alone (DisNet.count_parameters) on L_n over ``train_idx``
    for ``epochs`` passes, on the frozen backbone's pooled features (computed once, eval mode), and
    leave it at the pass with the lowest mean L_n over ``select_idx`` (pass 0: as given).

    ``arrays`` holds 'images' (N, H, W, 3) uint8, 'counts' (N,) and 'speeds' (N,) m/s. Returns the
    record: best_pass, select_n_before / _after and the per-pass curve of the selection L_n.
    """
    model.to(device).eval()
    sets = {name: _count_inputs(model, arrays, np.asarray(idx, np.int64), device)
            for name, idx in (("train", train_idx), ("select", select_idx))}
    params = model.count_parameters()
    saved = [p.detach().clone() for p in params]
    optimizer = torch.optim.Adam(params, lr=lr)
    rng = np.random.default_rng(seed)

    def select_n() -> float:
        with torch.no_grad():
            grid, speed, counts = sets["select"]
            return float(count_loss(model.count_from_grid(grid, speed), counts).mean())

    curve = [select_n()]
    best_pass = 0
    n_train = len(sets["train"][2])
    for k in _progress(range(1, epochs + 1), epochs, "disnet count refit", progress):
        order = torch.from_numpy(rng.permutation(n_train))
        for start in range(0, n_train, batch_size):
            rows = order[start:start + batch_size]
            grid, speed, counts = (t[rows] for t in sets["train"])
            loss = count_loss(model.count_from_grid(grid, speed), counts).mean()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        curve.append(select_n())
        if curve[-1] < curve[best_pass]:
            best_pass = k
            saved = [p.detach().clone() for p in params]
    with torch.no_grad():
        for p, best in zip(params, saved):
            p.copy_(best)
    return {"epochs": epochs, "best_pass": best_pass, "select_n_before": curve[0],
            "select_n_after": curve[best_pass], "curve": curve}


@torch.no_grad()
def _count_inputs(model: DisNet, arrays: dict[str, Any], idx: Rows, device: torch.device,
                  batch: int = 8) -> tuple[Tensor, Tensor, Tensor]:
    """(pooled features (N, C, 5, 18), speeds (N,), counts (N,)) of frames ``idx`` on ``device``."""
    grids, speeds, counts = [], [], []
    sub = {k: arrays[k] for k in ("images", "speeds", "counts")}
    for b in iter_batches(sub, idx, batch):
        img, speed = disnet_inputs(b, device)
        grids.append(model.count_grid_features(img))
        speeds.append(speed)
        counts.append(torch.from_numpy(np.asarray(b["counts"], np.float32)).to(device))
    if not grids:
        raise ValueError("refit_count_branch: no frames to refit on")
    return torch.cat(grids), torch.cat(speeds), torch.cat(counts)


# ------------------------------------------------------------------------------- RSS-Net


def rssnet_terms(model: nn.Module, batch: Batch, device: torch.device) -> dict[str, Tensor]:
    """Per-point L_a ('a') of one batch, in normalised RSS units (eq. 22)."""
    a_hat = model(*rssnet_inputs(model, batch, device))
    rss = torch.from_numpy(np.asarray(batch["rss"], np.float32)).to(device)
    return {"a": rss_loss(a_hat, model.normalise_rss(rss))}


INPUT_RANGE_ROWS = 20_000
"""Training points (evenly spaced) from which RSS-Net's input range is computed."""


def train_rssnet(cfg, data: RssNetData, out_dir: str | Path, progress: bool = True,
                 fingerprint: str | None = None, publish: Publish | None = None) -> TrainResult:
    """Train RSS-Net with L_a (Adam, cfg.train.*, batch cfg.train.rss_batch_size); resumes. The best
    checkpoint keeps the quantiles of its residuals on the validation points
    (:func:`rssnet_residual_quantiles`; none without validation points)."""
    _setup(cfg)
    model = build_rssnet(cfg)
    arrays = {**rss_arrays(model, data.patches, data.range_images, data.point_vectors), "rss": data.rss}
    train_idx = _checked_idx(data.train_idx, "train_idx", arrays, False)
    if len(train_idx):
        rows = evenly_spaced(train_idx, INPUT_RANGE_ROWS)
        model.set_input_range(input_summaries(
            None if data.patches is None else take_rows(data.patches, rows),
            None if data.range_images is None else take_rows(data.range_images, rows),
            take_rows(data.point_vectors, rows)))
    spec = _NetSpec(
        name="rssnet", model=model, arch=jsonable_arch(rssnet_kwargs(cfg)), arrays=arrays,
        train_idx=train_idx,
        val_idx=_checked_idx(data.val_idx, "val_idx", arrays, True),
        batch_size=cfg.train.rss_batch_size, terms_fn=rssnet_terms, weights={"a": 1.0})
    res = run(spec, cfg, out_dir, fingerprint or default_fingerprint(cfg, "rssnet"), progress, publish)
    if len(data.val_idx):
        _add_to_best_meta(res, model, RESIDUAL_KEY, lambda best: rssnet_residual_quantiles(best, data, data.val_idx))
    return res


def _add_to_best_meta(res: TrainResult, model: nn.Module, key: str, compute: Callable[[nn.Module], Any],
                      again: bool = False) -> None:
    """Give the best checkpoint's metadata ``key`` = ``compute(model)``, the best weights loaded into
    ``model`` on the CPU, where it lacks the key (a new best is written without it; a resumed,
    finished run's best keeps it) or, with ``again``, holds another value; the weights and buffers
    are saved as ``compute`` leaves them."""
    if not Path(res.best_path).is_file() or (key in ckpt.read_meta(res.best_path) and not again):
        return  # no epoch trained (train.epochs = 0), or done
    tensors, meta = ckpt.load_checkpoint(res.best_path)
    model.load_state_dict(model_state(model, tensors), strict=True)
    model = model.to("cpu")
    value = compute(model)
    if meta.get(key) != value:  # computed again to the same value: the file stays as it is
        ckpt.save_checkpoint(res.best_path, ckpt.model_tensors(model), {**meta, key: value})


@torch.no_grad()
def rssnet_residual_quantiles(model: RSSNet, data: RssNetData, idx: Sequence[int], batch: int = 256) -> list[float]:
    """Quantiles at RESIDUAL_LEVELS of real minus predicted RSS (dataset units) over rows ``idx``
    of ``data`` (RSS-Net's validation points): the spread its prediction, a conditional mean, leaves
    out."""
    model.eval()
    device = device_of(model)
    arrays = {**rss_arrays(model, data.patches, data.range_images, data.point_vectors), "rss": data.rss}
    residuals = [np.asarray(b["rss"], np.float64) - model.to_rss(model(*rssnet_inputs(model, b, device))).double()
                 .cpu().numpy() for b in iter_batches(arrays, as_rows(idx), batch)]
    return np.quantile(np.concatenate(residuals), RESIDUAL_LEVELS).tolist()


# ------------------------------------------------------------------------------- PlaceNet


def placenet_terms(model: nn.Module, batch: Batch, device: torch.device) -> dict[str, Tensor]:
    """Per-candidate Poisson negative log-likelihood ('nll') of one batch."""
    log_rate = model(torch.from_numpy(np.asarray(batch["features"], np.float32)).to(device))
    counts = torch.from_numpy(np.asarray(batch["counts"], np.float32)).to(device)
    return {"nll": poisson_loss(log_rate, counts)}


STANDARDISATION_ROWS = 200_000
"""Training rows (evenly spaced) from which PlaceNet's feature standardisation is computed."""


def train_placenet(cfg, data: PlaceNetData, out_dir: str | Path, progress: bool = True,
                   fingerprint: str | None = None, publish: Publish | None = None) -> TrainResult:
    """Train PlaceNet with the Poisson NLL (Adam at placement.lr, batch placement.batch_size,
    placement.epochs); the features are standardised with the training rows' statistics; resumes."""
    _setup(cfg)
    model = build_placenet(cfg)
    arrays = {"features": data.features, "counts": data.counts}
    train_idx = _checked_idx(data.train_idx, "train_idx", arrays, False)
    model.set_standardisation(take_rows(data.features, evenly_spaced(train_idx, STANDARDISATION_ROWS)))
    spec = _NetSpec(
        name="placenet", model=model, arch=jsonable_arch(placenet_kwargs(cfg)), arrays=arrays,
        train_idx=train_idx, val_idx=_checked_idx(data.val_idx, "val_idx", arrays, True),
        batch_size=cfg.placement.batch_size, terms_fn=placenet_terms, weights={"nll": 1.0}, lr=cfg.placement.lr)
    res = run(spec, cfg, out_dir, fingerprint or default_fingerprint(cfg, "placenet"), progress, publish)
    if data.train_frame_candidates is not None:
        _add_to_best_meta(res, model, "count_scale", lambda best: placenet_count_scale(
            best, data.features, data.train_frame_rows, data.train_frame_candidates(), data.train_frame_counts))
    return res


COUNT_SCALE_ROWS = 1 << 18
"""Rows whose intensities :func:`placenet_count_scale` computes at a time."""


def placenet_count_scale(model: PlaceNet, features: Any, frame_rows: np.ndarray, frame_candidates: np.ndarray,
                         frame_counts: np.ndarray) -> float:
    """The factor s that turns PlaceNet's intensity summed over a frame's candidates into an
    estimate of the frame's real point count: sum of the counts over sum of the estimates of the
    frames. A frame's estimate is its rows' summed intensity times candidates / rows (its rows, the
    first ``frame_rows`` (F,) of ``features`` in frame order, are a uniform sample of its
    ``frame_candidates`` (F,)); ``frame_counts`` (F,) its real radar points. The intensity alone
    counts only the real points with a candidate within placement.gate_m (76% of them on the
    synthetic world, 59% on Astyx). NaN when no frame has rows or the estimates sum to 0."""
    rows = np.asarray(frame_rows, np.int64)
    frame_of_row = np.repeat(np.arange(len(rows)), rows)
    sums = np.zeros(len(rows))
    for start in range(0, len(frame_of_row), COUNT_SCALE_ROWS):
        stop = min(len(frame_of_row), start + COUNT_SCALE_ROWS)
        lam = placenet_predict(model, take_rows(features, np.arange(start, stop)))
        sums += np.bincount(frame_of_row[start:stop], lam, minlength=len(rows))
    has = rows > 0
    estimate = float((sums[has] * np.asarray(frame_candidates, np.float64)[has] / rows[has]).sum())
    real = float(np.asarray(frame_counts, np.float64)[has].sum())
    return real / estimate if estimate > 0 else float("nan")


# ------------------------------------------------------------------------------- test metrics


def disnet_metrics(model: DisNet, data: DisNetData, idx: Sequence[int], alpha: float,
                   batch: int = 8, progress: bool = False, every_s: float = EVERY_S) -> dict[str, float]:
    """Per-frame mean L_KL ('kl'), L_n ('n') and L_KL + alpha L_n ('loss') on frames ``idx``;
    ``progress``: a 'disnet test' bar (pipeline.progress, a line every ``every_s`` in a log)."""
    arrays = {"images": data.images, "heatmaps": data.heatmaps, "counts": data.counts, "speeds": data.speeds}
    return evaluate(model, iter_batches(arrays, np.asarray(idx, np.int64), batch), disnet_terms,
                    {"kl": 1.0, "n": alpha}, device_of(model), math.ceil(len(idx) / batch), "disnet test",
                    progress, every_s)


def rssnet_metrics(model: RSSNet, data: RssNetData, idx: Sequence[int], batch: int = 256,
                   progress: bool = False, every_s: float = EVERY_S) -> dict[str, float]:
    """Per-point mean L_a ('a', = 'loss') on points ``idx``; ``progress`` as for disnet_metrics."""
    arrays = {**rss_arrays(model, data.patches, data.range_images, data.point_vectors), "rss": data.rss}
    return evaluate(model, iter_batches(arrays, as_rows(idx), batch), rssnet_terms,
                    {"a": 1.0}, device_of(model), math.ceil(len(idx) / batch), "rssnet test", progress, every_s)


def placenet_metrics(model: PlaceNet, data: PlaceNetData, idx: Sequence[int], batch: int = 4096,
                     progress: bool = False, every_s: float = EVERY_S) -> dict[str, float]:
    """Per-candidate mean Poisson NLL ('nll', = 'loss') on rows ``idx``; ``progress`` as for
    disnet_metrics."""
    arrays = {"features": data.features, "counts": data.counts}
    return evaluate(model, iter_batches(arrays, as_rows(idx), batch), placenet_terms,
                    {"nll": 1.0}, device_of(model), math.ceil(len(idx) / batch), "placenet test", progress, every_s)
