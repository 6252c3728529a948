"""Resumable training of Dis-Net and RSS-Net (torchvision-reference style: train_one_epoch,
evaluate, run), inference helpers and the baselines the models must beat.

Data are array-likes (numpy or zarr arrays) indexed by frame / point along axis 0; they are read
one window of batches at a time (sorted reads, one chunk-group order per epoch), never all at once.

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
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Sequence

import numpy as np
import torch
from torch import Tensor, nn
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

from pipeline import augment
from pipeline import checkpoint as ckpt
from pipeline.config import EPOCHS_KEYS, TRAINING_KEYS
from pipeline.egomotion import STOPPED_MPS
from pipeline.errors import ConfigError
from pipeline.models.disnet import COUNT_PRIOR_KNOTS, DisNet, build_disnet, disnet_kwargs
from pipeline.models.losses import count_loss, kl_loss, poisson_loss, rss_loss
from pipeline.models.placenet import PlaceNet, build_placenet, placenet_kwargs
from pipeline.models.resnet import resnet18_backbone
from pipeline.models.rssnet import RSSNet, build_rssnet, rssnet_kwargs
from pipeline.patches import input_summaries

log = logging.getLogger(__name__)
Batch = dict[str, np.ndarray]
TermsFn = Callable[[nn.Module, Batch, torch.device], dict[str, Tensor]]
WINDOW_BATCHES = 16
"""Batches read from the arrays in one go (one sorted read per array)."""


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


# ----------------------------------------------------------------------------------------- data


def select_device(name: str, key: str = "train.device") -> torch.device:
    """'auto' -> cuda when available else cpu; 'cpu' / 'cuda' as given (ConfigError naming the
    setting ``key`` if unusable)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"{key} = '{name}' but CUDA is not available (use 'auto' or 'cpu')")
    if not (name == "cpu" or name.startswith("cuda")):
        raise ConfigError(f"{key} must be 'auto', 'cpu' or 'cuda', got '{name}'")
    return torch.device(name)


Rows = np.ndarray | range
"""Row indices: an int array, or a ``range`` (step 1) for the contiguous row sets of RSS-Net and
PlaceNet, which are never materialised (8 bytes a row: 390 MB at 24,000 frames of 2,048 rows)."""


def evenly_spaced(idx: Rows, n: int) -> np.ndarray:
    """At most ``n`` of the indices ``idx``, evenly spaced along it (all of them when fewer)."""
    pick = np.unique(np.linspace(0, len(idx) - 1, min(len(idx), n)).astype(np.int64)) if len(idx) else []
    if isinstance(idx, range):
        return idx.start + idx.step * np.asarray(pick, np.int64)
    idx = np.asarray(idx, dtype=np.int64)
    return idx[pick] if len(idx) else idx


def _index_array(idx: Sequence[int]) -> np.ndarray:
    """``idx`` as a flat int64 array (a range by arange: np.asarray of one is 20x slower)."""
    if isinstance(idx, range):
        return np.arange(idx.start, idx.stop, idx.step, dtype=np.int64)
    return np.asarray(idx, np.int64).reshape(-1)


def _rows(idx: Sequence[int]) -> Rows:
    """``idx`` as row indices: a ``range`` (step 1) as it is, else a flat int64 array."""
    return idx if isinstance(idx, range) and idx.step == 1 else _index_array(idx)


def take_rows(array: Any, idx: Rows) -> np.ndarray:
    """Rows ``idx`` (any order, repeats allowed) of a numpy or zarr array, read with sorted indices."""
    idx = _index_array(idx)
    if isinstance(array, np.ndarray):
        return array[idx]
    uniq, inverse = np.unique(idx, return_inverse=True)
    rows = array.oindex[uniq] if hasattr(array, "oindex") else array[uniq]
    return np.asarray(rows)[inverse]


def n_rows(array: Any) -> int:
    """Length of axis 0 of a numpy / zarr array."""
    return int(array.shape[0])


def chunk_len(array: Any) -> int:
    """Rows per storage chunk along axis 0 (1 for in-memory arrays)."""
    chunks = getattr(array, "chunks", None)
    if not chunks:
        return 1
    first = chunks[0]
    return int(first[0] if isinstance(first, tuple) else first)


def epoch_windows(idx: Rows, rows_per_chunk: int, window: int, rng: np.random.Generator) -> Iterator[np.ndarray]:
    """One epoch's shuffled order of the rows ``idx``, in consecutive pieces of ``window`` rows (the
    last may be shorter), each made when it is asked for: with ``rows_per_chunk`` > 1 the storage
    chunks' groups of rows in a random order, then the rows inside each window shuffled (reads stay
    within few chunks); with 1, a plain permutation. For a ``range`` (step 1) only one window is held
    at a time, not an order of every row (8 bytes a row and several times that while sorting: 2.9 GB
    for 49 million rows). The windows and the generator's state after the last one are the same
    whether ``idx`` is a range or an array of the same rows (a resumed training goes on the same)."""
    if window <= 0:
        raise ValueError(f"epoch_windows: window must be > 0, got {window}")
    if len(idx) == 0:
        return iter(())
    if isinstance(idx, range) and idx.step == 1 and rows_per_chunk > 1:
        return _range_windows(idx, rows_per_chunk, window, rng)
    return _array_windows(_index_array(idx), rows_per_chunk, window, rng)


def _array_windows(idx: np.ndarray, rows_per_chunk: int, window: int, rng: np.random.Generator) -> Iterator[np.ndarray]:
    """:func:`epoch_windows` of an array: its whole order made first."""
    if rows_per_chunk <= 1:
        order = rng.permutation(idx)
        yield from (order[start:start + window] for start in range(0, len(order), window))
        return
    _, group = np.unique(idx // rows_per_chunk, return_inverse=True)
    rank = rng.permutation(group.max() + 1)
    order = idx[np.argsort(rank[group], kind="stable")]
    for start in range(0, len(order), window):
        yield rng.permutation(order[start:start + window])


def _range_windows(idx: range, rows_per_chunk: int, window: int, rng: np.random.Generator) -> Iterator[np.ndarray]:
    """:func:`epoch_windows` of a range (step 1): each chunk's rows are consecutive numbers, so the
    chunks' order is all that is held."""
    first = idx.start // rows_per_chunk
    rank = rng.permutation((idx.stop - 1) // rows_per_chunk - first + 1)
    pending: list[np.ndarray] = []
    held = 0
    for chunk in first + np.argsort(rank):  # the chunk of rank 0 first, then rank 1, ...
        rows = np.arange(max(chunk * rows_per_chunk, idx.start), min((chunk + 1) * rows_per_chunk, idx.stop))
        pending.append(rows)
        held += len(rows)
        while held >= window:
            rows = np.concatenate(pending)
            yield rng.permutation(rows[:window])
            pending, held = [rows[window:]], held - window
    if held:
        yield rng.permutation(np.concatenate(pending))


def iter_batches(arrays: dict[str, Any], order: Rows | Iterator[np.ndarray], batch_size: int) -> Iterator[Batch]:
    """Yield ``{name: rows}`` batches in ``order``: row indices (an array or a range), or an iterator
    (not a list) of windows of them (:func:`epoch_windows`, WINDOW_BATCHES batches each). A window is
    read in one go per array, the next one in a background thread while the current one is consumed
    (windows are taken from the iterator in this thread)."""
    if isinstance(order, Iterator):
        windows = order
    else:
        window = batch_size * WINDOW_BATCHES
        windows = (order[s:s + window] for s in range(0, len(order), window))

    def read(sel: Rows) -> Batch:
        return {k: take_rows(a, sel) for k, a in arrays.items()}

    with ThreadPoolExecutor(max_workers=1) as pool:
        sel = next(windows, None)
        pending = pool.submit(read, sel) if sel is not None else None
        while pending is not None:
            block = pending.result()
            sel = next(windows, None)
            pending = pool.submit(read, sel) if sel is not None else None
            n = len(next(iter(block.values())))
            for s in range(0, n, batch_size):
                yield {k: v[s:s + batch_size] for k, v in block.items()}


def _progress(iterable: Iterable, total: int, desc: str, enabled: bool):
    from tqdm.auto import tqdm
    return tqdm(iterable, total=total, desc=desc, leave=False,
                disable=not (enabled and sys.stderr.isatty()))


# ------------------------------------------------------------------------------- loop


def _weighted_total(terms: dict[str, Tensor], weights: dict[str, float]) -> Tensor:
    return sum(weights[k] * terms[k] for k in weights)


def train_one_epoch(model: nn.Module, optimizer: torch.optim.Optimizer, batches: Iterable[Batch],
                    terms_fn: TermsFn, weights: dict[str, float], device: torch.device,
                    n_batches: int = 0, desc: str = "train", progress: bool = True,
                    ema: AveragedModel | None = None) -> dict[str, float]:
    """One pass over ``batches``; loss = mean over the batch of sum_k weights[k] * term_k; ``ema``
    (when given) is updated after every optimiser step.

    Returns per-sample means of every term and of the loss (key 'loss'). Raises FloatingPointError
    on a non-finite loss (before any checkpoint of the epoch is written).
    """
    model.train()
    sums: dict[str, float] = {}
    count = 0
    bar = _progress(batches, n_batches, desc, progress)
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
        if step % 10 == 0 and hasattr(bar, "set_postfix"):
            bar.set_postfix(loss=f"{loss.item():.4g}")
    return {k: v / max(count, 1) for k, v in sums.items()}


@torch.no_grad()
def evaluate(model: nn.Module, batches: Iterable[Batch], terms_fn: TermsFn, weights: dict[str, float],
             device: torch.device, n_batches: int = 0, desc: str = "val",
             progress: bool = True) -> dict[str, float]:
    """Per-sample (per-frame / per-point) means of every term and of the weighted loss, eval mode.
    Empty input gives NaN for every key."""
    model.eval()
    sums: dict[str, float] = {}
    count = 0
    for batch in _progress(batches, n_batches, desc, progress):
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


def run(spec: _NetSpec, cfg, out_dir: str | Path, fingerprint: str, progress: bool = True) -> TrainResult:
    """Train ``spec.model`` for the epochs its config key says (EPOCHS_KEYS), resuming from ``out_dir``
    when possible."""
    epochs_key = EPOCHS_KEYS[spec.name]
    n_epochs = int(cfg.get(epochs_key))
    if n_epochs < 0:
        raise ConfigError(f"{epochs_key} must be >= 0, got {n_epochs}")
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
    resumed = _resume(last, best, spec, optimizer, fingerprint, device, ema)
    if resumed is not None:
        state, rng = resumed
    start = state["epoch"]
    rows_per_chunk = chunk_len(next(iter(spec.arrays.values())))
    n_train_batches = math.ceil(len(spec.train_idx) / spec.batch_size)
    n_val_batches = math.ceil(len(spec.val_idx) / spec.batch_size)
    for epoch in range(start + 1, n_epochs + 1):
        t0 = time.perf_counter()
        for group in optimizer.param_groups:  # a function of the epoch alone: resumes exactly
            group["lr"] = epoch_lr(cfg, epoch, base_lr, n_epochs)
        order = epoch_windows(spec.train_idx, rows_per_chunk, spec.batch_size * WINDOW_BATCHES, rng)
        tr = train_one_epoch(spec.model, optimizer, iter_batches(spec.arrays, order, spec.batch_size),
                             spec.terms_fn, spec.weights, device, n_train_batches,
                             f"{spec.name} epoch {epoch}/{n_epochs}", progress, ema)
        va = evaluate(scored, iter_batches(spec.arrays, spec.val_idx, spec.batch_size), spec.terms_fn,
                      spec.weights, device, n_val_batches, f"{spec.name} val", progress)
        metric = va[select_key] if len(spec.val_idx) else tr[select_key]
        state["curves"].append({"epoch": epoch, **{f"train_{k}": v for k, v in tr.items()},
                                **{f"val_{k}": v for k, v in va.items()},
                                "seconds": time.perf_counter() - t0})
        state["epoch"] = epoch
        if metric < state["best_metric"]:
            state["best_epoch"], state["best_metric"] = epoch, metric
            ckpt.save_checkpoint(best, ckpt.model_tensors(scored), _meta(spec, fingerprint, state))
        _save_last(last, spec, optimizer, rng, fingerprint, state, ema)  # the commit point of the epoch
        write_curves(out_dir, spec.name, state["curves"], plot=False)
    write_curves(out_dir, spec.name, state["curves"], plot=True)
    return TrainResult(spec.name, last, best, state["epoch"], start, state["best_epoch"],
                       state["best_metric"], state["curves"])


SELECT_ON = ("loss", "kl")
"""Values of train.select_on."""


def selection_key(select_on: str, weights: dict[str, float]) -> str:
    """The loss term that picks the best epoch: ``select_on`` when the net has that term (Dis-Net's
    'kl'), else the weighted total 'loss' (RSS-Net has one term). ConfigError for unknown values."""
    if select_on not in SELECT_ON:
        raise ConfigError(f"train.select_on must be one of {SELECT_ON}, got {select_on!r}")
    return select_on if select_on in weights else "loss"


def unit_interval(key: str, value: float, include_one: bool = True) -> float:
    """``value`` as a float in [0, 1] ([0, 1) without ``include_one``); ConfigError naming ``key``."""
    x = float(value)
    if not (np.isfinite(x) and 0.0 <= x and (x <= 1.0 if include_one else x < 1.0)):
        raise ConfigError(f"{key} must be in [0, 1{']' if include_one else ')'}, got {x}")
    return x


def check_training(cfg) -> None:
    """ConfigError for training settings no net could train with (the train stage's check, run
    before any output is touched; the same checks also guard the training functions)."""
    # epochs, intervals (cutmix, jitter, ema_decay, ...) are held to pipeline.config.LIMITS where set
    selection_key(cfg.train.select_on, {})
    if cfg.train.lr_schedule not in LR_SCHEDULES:
        raise ConfigError(f"train.lr_schedule must be one of {', '.join(LR_SCHEDULES)}; got '{cfg.train.lr_schedule}'")
    select_device(cfg.train.device)


def make_ema(model: nn.Module, decay: float) -> AveragedModel | None:
    """Exponential moving average of ``model``'s parameters and buffers (BatchNorm statistics
    included) with ``decay`` per update; None when decay is 0 (ConfigError outside [0, 1))."""
    decay = unit_interval("train.ema_decay", decay, include_one=False)
    if decay == 0.0:
        return None
    return AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(decay), use_buffers=True)


LR_SCHEDULES = ("constant", "cosine")


def epoch_lr(cfg, epoch: int, base_lr: float | None = None, epochs: int | None = None) -> float:
    """Learning rate of epoch ``epoch`` (1-based) of ``epochs`` (None: cfg.train.epochs) under
    cfg.train.lr_schedule, starting from ``base_lr`` (None: cfg.train.lr)."""
    t = cfg.train
    lr = t.lr if base_lr is None else base_lr
    if t.lr_schedule not in LR_SCHEDULES:
        raise ConfigError(f"train.lr_schedule must be one of {', '.join(LR_SCHEDULES)}; got '{t.lr_schedule}'")
    if t.lr_schedule == "constant":
        return lr
    return lr * 0.5 * (1.0 + math.cos(math.pi * (epoch - 1) / (t.epochs if epochs is None else epochs)))


def _meta(spec: _NetSpec, fingerprint: str, state: dict[str, Any]) -> dict[str, Any]:
    return {"net": spec.name, "fingerprint": fingerprint, "arch": spec.arch,
            "selection": "val" if len(spec.val_idx) else "train", **state}


def _save_last(path: Path, spec: _NetSpec, optimizer: torch.optim.Optimizer, rng: np.random.Generator,
               fingerprint: str, state: dict[str, Any], ema: AveragedModel | None = None) -> None:
    opt_tensors, opt_json = ckpt.flatten_optimizer(optimizer)
    tensors = {**ckpt.model_tensors(spec.model), **opt_tensors, **ckpt.rng_tensors()}
    if ema is not None:
        tensors.update({f"ema.{k}": v for k, v in ema.state_dict().items()})
    meta = {**_meta(spec, fingerprint, state), "optimizer": opt_json,
            "numpy_rng": ckpt.numpy_rng_state(rng)}
    ckpt.save_checkpoint(path, tensors, meta)


def _resume(last: Path, best: Path, spec: _NetSpec, optimizer: torch.optim.Optimizer, fingerprint: str,
            device: torch.device, ema: AveragedModel | None = None) -> tuple[dict[str, Any], np.random.Generator] | None:
    """Restore model, optimizer, RNGs (and ``ema``) from ``last`` when it matches; else clear stale files."""
    if not last.exists():
        return None
    meta = ckpt.read_meta(last)
    if meta.get("net") != spec.name:
        raise ValueError(f"{last} is a {meta.get('net')!r} checkpoint: train {spec.name} in its own folder")
    if meta.get("fingerprint") != fingerprint or meta.get("arch") != spec.arch:
        log.warning("%s: saved for other settings; training %s from scratch", last, spec.name)
        for p in (last, best, last.with_suffix(".json"), best.with_suffix(".json")):
            p.unlink(missing_ok=True)
        return None
    tensors, meta = ckpt.load_checkpoint(last)
    spec.model.load_state_dict(_model_state(spec.model, tensors), strict=True)
    spec.model.to(device)
    optimizer.load_state_dict(ckpt.unflatten_optimizer(tensors, meta["optimizer"]))
    if ema is not None:
        ema.load_state_dict(ckpt.strip_prefix(tensors, "ema."), strict=True)
    ckpt.restore_rng(tensors)
    state = {k: meta[k] for k in ("epoch", "best_epoch", "best_metric", "curves")}
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


def _disnet_inputs(batch: Batch, device: torch.device) -> tuple[Tensor, Tensor]:
    """uint8 (B, H, W, 3) -> float (B, 3, H, W) in [0, 1] on device; speeds (B,) float32."""
    img = torch.from_numpy(np.ascontiguousarray(batch["images"])).to(device)
    img = img.permute(0, 3, 1, 2).float() / 255.0
    speed = torch.from_numpy(np.asarray(batch["speeds"], np.float32)).to(device)
    return img, speed


def disnet_terms(model: nn.Module, batch: Batch, device: torch.device, flip: bool = False,
                 cutmix: float = 0.0, jitter: float = 0.0) -> dict[str, Tensor]:
    """Per-frame L_KL ('kl') and L_n ('n') of one batch; in training mode, ``flip`` mirrors,
    ``cutmix`` mixes frames and ``jitter`` varies brightness and contrast (pipeline.augment), in
    that order."""
    img, speed = _disnet_inputs(batch, device)
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


def default_fingerprint(cfg, net: str) -> str:
    """Fingerprint of the config keys that change what a net learns (not epochs/device/threads)."""
    if net not in TRAINING_KEYS or net == "common":
        raise ValueError(f"default_fingerprint: unknown net {net!r}")
    common = list(TRAINING_KEYS["common"])
    if cfg.train.lr_schedule != "constant":  # the schedule spans the epochs: more epochs, another run
        common.append(EPOCHS_KEYS[net])
    return cfg.fingerprint(list(TRAINING_KEYS[net]) + common)


def _jsonable_arch(kwargs: dict[str, Any]) -> dict[str, Any]:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in kwargs.items()}


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
    arr = _rows(idx)
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
                 fingerprint: str | None = None) -> TrainResult:
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
        name="disnet", model=model, arch=_jsonable_arch(disnet_kwargs(cfg)), arrays=arrays,
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
    res = run(spec, cfg, out_dir, fingerprint or default_fingerprint(cfg, "disnet"), progress)
    if refit_epochs > 0:
        _refit_best_count(cfg, spec, res.best_path, refit_epochs, progress)
    return res


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
        img, speed = _disnet_inputs(b, device)
        grids.append(model.count_grid_features(img))
        speeds.append(speed)
        counts.append(torch.from_numpy(np.asarray(b["counts"], np.float32)).to(device))
    if not grids:
        raise ValueError("refit_count_branch: no frames to refit on")
    return torch.cat(grids), torch.cat(speeds), torch.cat(counts)


# ------------------------------------------------------------------------------- RSS-Net


def _rssnet_inputs(model: RSSNet, batch: Batch, device: torch.device) -> tuple[Tensor | None, ...]:
    patch = range_image = point = None
    if model.use_camera:
        patch = torch.from_numpy(np.ascontiguousarray(batch["patches"])).to(device)
        patch = patch.permute(0, 3, 1, 2).float() / 255.0                 # (B, 3, ps, ps)
    if model.use_lidar:
        range_image = torch.from_numpy(np.asarray(batch["range_images"], np.float32)).to(device)
    if model.use_radar_point:
        point = torch.from_numpy(np.asarray(batch["point_vectors"], np.float32)).to(device)
    return patch, range_image, point


def rssnet_terms(model: nn.Module, batch: Batch, device: torch.device) -> dict[str, Tensor]:
    """Per-point L_a ('a') of one batch, in normalised RSS units (eq. 22)."""
    a_hat = model(*_rssnet_inputs(model, batch, device))
    rss = torch.from_numpy(np.asarray(batch["rss"], np.float32)).to(device)
    return {"a": rss_loss(a_hat, model.normalise_rss(rss))}


def _rss_arrays(model: RSSNet, patches: Any, range_images: Any, point_vectors: Any) -> dict[str, Any]:
    """The arrays the enabled branches read (dropped branches read nothing)."""
    named = {"patches": (model.use_camera, patches), "range_images": (model.use_lidar, range_images),
             "point_vectors": (model.use_radar_point, point_vectors)}
    out = {}
    for name, (used, array) in named.items():
        if used:
            if array is None:
                raise ValueError(f"RSS-Net uses '{name}' (see rssnet.*) but no array was given")
            out[name] = array
    return out


INPUT_RANGE_ROWS = 20_000
"""Training points (evenly spaced) from which RSS-Net's input range is computed."""


def train_rssnet(cfg, data: RssNetData, out_dir: str | Path, progress: bool = True,
                 fingerprint: str | None = None) -> TrainResult:
    """Train RSS-Net with L_a (Adam, cfg.train.*, batch cfg.train.rss_batch_size); resumes. The best
    checkpoint keeps the quantiles of its residuals on the validation points
    (:func:`rssnet_residual_quantiles`; none without validation points)."""
    _setup(cfg)
    model = build_rssnet(cfg)
    arrays = {**_rss_arrays(model, data.patches, data.range_images, data.point_vectors), "rss": data.rss}
    train_idx = _checked_idx(data.train_idx, "train_idx", arrays, False)
    if len(train_idx):
        rows = evenly_spaced(train_idx, INPUT_RANGE_ROWS)
        model.set_input_range(input_summaries(
            None if data.patches is None else take_rows(data.patches, rows),
            None if data.range_images is None else take_rows(data.range_images, rows),
            take_rows(data.point_vectors, rows)))
    spec = _NetSpec(
        name="rssnet", model=model, arch=_jsonable_arch(rssnet_kwargs(cfg)), arrays=arrays,
        train_idx=train_idx,
        val_idx=_checked_idx(data.val_idx, "val_idx", arrays, True),
        batch_size=cfg.train.rss_batch_size, terms_fn=rssnet_terms, weights={"a": 1.0})
    res = run(spec, cfg, out_dir, fingerprint or default_fingerprint(cfg, "rssnet"), progress)
    if len(data.val_idx):
        _add_to_best_meta(res, model, RESIDUAL_KEY, lambda best: rssnet_residual_quantiles(best, data, data.val_idx))
    return res


def _add_to_best_meta(res: TrainResult, model: nn.Module, key: str, compute: Callable[[nn.Module], Any]) -> None:
    """Give the best checkpoint's metadata ``key`` = ``compute(model)``, the best weights loaded into
    ``model`` on the CPU, where it lacks the key (a new best is written without it; a resumed,
    finished run's best keeps it)."""
    if key in ckpt.read_meta(res.best_path):
        return
    tensors, meta = ckpt.load_checkpoint(res.best_path)
    model.load_state_dict(_model_state(model, tensors), strict=True)
    model = model.to("cpu")
    ckpt.save_checkpoint(res.best_path, ckpt.model_tensors(model), {**meta, key: compute(model)})


RESIDUAL_KEY = "rss_residual_quantiles"
"""RSS-Net checkpoint metadata: the quantiles of its validation residuals (synth.rss_sampling)."""
RESIDUAL_LEVELS = np.linspace(0.0, 1.0, 101)
"""Levels of the residual quantiles a checkpoint keeps (0 and 1: the smallest and largest)."""


@torch.no_grad()
def rssnet_residual_quantiles(model: RSSNet, data: RssNetData, idx: Sequence[int], batch: int = 256) -> list[float]:
    """Quantiles at RESIDUAL_LEVELS of real minus predicted RSS (dataset units) over rows ``idx``
    of ``data`` (RSS-Net's validation points): the spread its prediction, a conditional mean, leaves
    out."""
    model.eval()
    device = _device_of(model)
    arrays = {**_rss_arrays(model, data.patches, data.range_images, data.point_vectors), "rss": data.rss}
    residuals = [np.asarray(b["rss"], np.float64) - model.to_rss(model(*_rssnet_inputs(model, b, device))).double()
                 .cpu().numpy() for b in iter_batches(arrays, _rows(idx), batch)]
    return np.quantile(np.concatenate(residuals), RESIDUAL_LEVELS).tolist()


def saved_residual_quantiles(meta: dict) -> np.ndarray | None:
    """RSS-Net's residual quantiles (len(RESIDUAL_LEVELS),) from its checkpoint's metadata; None
    where it holds none (saved before 2026-12-06, or trained without validation points) or not
    finite, non-decreasing numbers."""
    q = meta.get(RESIDUAL_KEY)
    try:
        q = np.asarray(q, np.float64)
    except (TypeError, ValueError):
        return None
    ok = q.shape == RESIDUAL_LEVELS.shape and np.all(np.isfinite(q)) and np.all(np.diff(q) >= 0)
    return q if ok else None


def draw_residuals(quantiles: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n,) residuals drawn from the distribution whose quantiles at RESIDUAL_LEVELS are
    ``quantiles`` (inverse transform, linear between the levels)."""
    return np.interp(rng.random(n), RESIDUAL_LEVELS, np.asarray(quantiles, np.float64))


# ------------------------------------------------------------------------------- PlaceNet


def placenet_terms(model: nn.Module, batch: Batch, device: torch.device) -> dict[str, Tensor]:
    """Per-candidate Poisson negative log-likelihood ('nll') of one batch."""
    log_rate = model(torch.from_numpy(np.asarray(batch["features"], np.float32)).to(device))
    counts = torch.from_numpy(np.asarray(batch["counts"], np.float32)).to(device)
    return {"nll": poisson_loss(log_rate, counts)}


STANDARDISATION_ROWS = 200_000
"""Training rows (evenly spaced) from which PlaceNet's feature standardisation is computed."""


def train_placenet(cfg, data: PlaceNetData, out_dir: str | Path, progress: bool = True,
                   fingerprint: str | None = None) -> TrainResult:
    """Train PlaceNet with the Poisson NLL (Adam at placement.lr, batch placement.batch_size,
    placement.epochs); the features are standardised with the training rows' statistics; resumes."""
    _setup(cfg)
    model = build_placenet(cfg)
    arrays = {"features": data.features, "counts": data.counts}
    train_idx = _checked_idx(data.train_idx, "train_idx", arrays, False)
    model.set_standardisation(take_rows(data.features, evenly_spaced(train_idx, STANDARDISATION_ROWS)))
    spec = _NetSpec(
        name="placenet", model=model, arch=_jsonable_arch(placenet_kwargs(cfg)), arrays=arrays,
        train_idx=train_idx, val_idx=_checked_idx(data.val_idx, "val_idx", arrays, True),
        batch_size=cfg.placement.batch_size, terms_fn=placenet_terms, weights={"nll": 1.0}, lr=cfg.placement.lr)
    res = run(spec, cfg, out_dir, fingerprint or default_fingerprint(cfg, "placenet"), progress)
    if data.train_frame_candidates is not None:
        _add_to_best_meta(res, model, "count_scale", lambda best: placenet_count_scale(
            best, data.features, data.train_frame_rows, data.train_frame_candidates(), data.train_frame_counts))
    return res


def saved_count_scale(meta: dict) -> float | None:
    """PlaceNet's count scale from its checkpoint's metadata; None where it holds none (saved
    before 2026-12-05) or not a finite number."""
    scale = meta.get("count_scale")
    return float(scale) if isinstance(scale, (int, float)) and math.isfinite(scale) else None


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


# ------------------------------------------------------------------------------- inference


def _model_state(model: nn.Module, tensors: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The ``model.`` tensors of a checkpoint as ``model``'s state dict; buffers that later versions
    added (``OPTIONAL_BUFFERS``, absent from older checkpoints) keep the model's defaults."""
    state = ckpt.strip_prefix(tensors, "model.")
    for name in getattr(model, "OPTIONAL_BUFFERS", ()):
        state.setdefault(name, model.state_dict()[name])
    return state


def _load_into(model: nn.Module, arch: dict[str, Any], path: str | Path, device: torch.device) -> nn.Module:
    tensors, meta = ckpt.load_checkpoint(path, prefix="model.")
    if meta.get("arch") != arch:
        diff = {k: (meta.get("arch", {}).get(k), v) for k, v in arch.items()
                if meta.get("arch", {}).get(k) != v}
        raise ConfigError(f"{path}: checkpoint architecture differs from the configuration "
                          f"(saved, configured): {diff}")
    try:
        model.load_state_dict(_model_state(model, tensors), strict=True)
    except RuntimeError as exc:  # e.g. a checkpoint of an older version of the network
        raise ConfigError(f"{path}: the checkpoint does not fit this version's network (written by an "
                          f"older version? run the train stage again): {exc}") from exc
    return model.to(device).eval()


def _arch(cfg, kwargs, path: str | Path, saved: bool) -> dict[str, Any]:
    """A net's constructor arguments: ``kwargs(cfg)``, or with ``saved`` those its checkpoint
    ``path`` was written with (nets trained on another dataset, train.nets_from)."""
    if not saved:
        return _jsonable_arch(kwargs(cfg))
    arch = ckpt.read_meta(path).get("arch")
    if not isinstance(arch, dict):
        raise ConfigError(f"{path}: the checkpoint records no architecture (written by an older version?)")
    return arch


def load_disnet(cfg, path: str | Path, device: str | None = None, saved_arch: bool = False) -> DisNet:
    """Dis-Net from a checkpoint (best or last), eval mode, on cfg.train.device (or ``device``);
    ``saved_arch``: built as the checkpoint says, not as ``cfg`` (its map then has the size it was
    trained at, the working size of its dataset)."""
    arch = _arch(cfg, disnet_kwargs, path, saved_arch)
    model = DisNet(backbone=resnet18_backbone(None, width=arch["width"]), **arch)
    return _load_into(model, arch, path, select_device(device or cfg.train.device))


def load_rssnet(cfg, path: str | Path, device: str | None = None, saved_arch: bool = False) -> RSSNet:
    """RSS-Net from a checkpoint (best or last), eval mode, on cfg.train.device (or ``device``);
    ``saved_arch`` as for :func:`load_disnet`."""
    arch = _arch(cfg, rssnet_kwargs, path, saved_arch)
    model = _load_into(RSSNet(**arch), arch, path, select_device(device or cfg.train.device))
    model.residual_quantiles = saved_residual_quantiles(ckpt.read_meta(path))
    return model


def load_placenet(cfg, path: str | Path, device: str | None = None, saved_arch: bool = False) -> PlaceNet:
    """PlaceNet from a checkpoint (best or last), eval mode, on cfg.train.device (or ``device``);
    ``saved_arch`` as for :func:`load_disnet`."""
    arch = _arch(cfg, placenet_kwargs, path, saved_arch)
    model = _load_into(PlaceNet(**arch), arch, path, select_device(device or cfg.train.device))
    model.count_scale = saved_count_scale(ckpt.read_meta(path))
    return model


def _device_of(model: nn.Module) -> torch.device:
    return next(model.parameters()).device


@torch.no_grad()
def disnet_predict(model: DisNet, images: Any, speeds: Any, batch: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """images (B, H, W, 3) uint8 RGB, speeds (B,) m/s -> (prob_map (B, h, w) float32 summing to 1
    per frame at the model's out_hw, n_hat (B,) float32 expected point count)."""
    model.eval()
    device = _device_of(model)
    n = n_rows(images)
    maps = np.empty((n, *model.out_hw), np.float32)
    counts = np.empty(n, np.float32)
    arrays = {"images": images, "speeds": np.asarray(speeds, np.float32).reshape(-1)}
    for s, b in zip(range(0, n, batch), iter_batches(arrays, np.arange(n), batch)):
        log_map, n_hat = model(*_disnet_inputs(b, device))
        maps[s:s + len(n_hat)] = log_map.exp().cpu().numpy()
        counts[s:s + len(n_hat)] = n_hat.cpu().numpy()
    return maps, counts


@torch.no_grad()
def rssnet_predict(model: RSSNet, patches: Any, range_images: Any, point_vectors: Any,
                   batch: int = 256) -> np.ndarray:
    """RSS (N,) float32 in dataset units for N points; inputs of dropped branches may be None."""
    model.eval()
    device = _device_of(model)
    arrays = _rss_arrays(model, patches, range_images, point_vectors)
    n = n_rows(next(iter(arrays.values())))
    out = np.empty(n, np.float32)
    for s, b in zip(range(0, n, batch), iter_batches(arrays, np.arange(n), batch)):
        a_hat = model(*_rssnet_inputs(model, b, device))
        out[s:s + len(a_hat)] = model.to_rss(a_hat).cpu().numpy()
    return out


@torch.no_grad()
def placenet_predict(model: PlaceNet, features: np.ndarray, batch: int = 65536) -> np.ndarray:
    """Intensity lambda (C,) float64 >= 0 of candidates with features (C, n_features)."""
    model.eval()
    x = np.asarray(features, np.float32)
    out = np.empty(len(x), np.float64)
    for s in range(0, len(x), batch):
        out[s:s + batch] = model(torch.from_numpy(x[s:s + batch]).to(_device_of(model))).exp().double().cpu().numpy()
    return out


def disnet_metrics(model: DisNet, data: DisNetData, idx: Sequence[int], alpha: float,
                   batch: int = 8) -> dict[str, float]:
    """Per-frame mean L_KL ('kl'), L_n ('n') and L_KL + alpha L_n ('loss') on frames ``idx``."""
    arrays = {"images": data.images, "heatmaps": data.heatmaps, "counts": data.counts, "speeds": data.speeds}
    return evaluate(model, iter_batches(arrays, np.asarray(idx, np.int64), batch), disnet_terms,
                    {"kl": 1.0, "n": alpha}, _device_of(model), progress=False)


def rssnet_metrics(model: RSSNet, data: RssNetData, idx: Sequence[int], batch: int = 256) -> dict[str, float]:
    """Per-point mean L_a ('a', = 'loss') on points ``idx``."""
    arrays = {**_rss_arrays(model, data.patches, data.range_images, data.point_vectors), "rss": data.rss}
    return evaluate(model, iter_batches(arrays, _rows(idx), batch), rssnet_terms,
                    {"a": 1.0}, _device_of(model), progress=False)


def placenet_metrics(model: PlaceNet, data: PlaceNetData, idx: Sequence[int], batch: int = 4096) -> dict[str, float]:
    """Per-candidate mean Poisson NLL ('nll', = 'loss') on rows ``idx``."""
    arrays = {"features": data.features, "counts": data.counts}
    return evaluate(model, iter_batches(arrays, _rows(idx), batch), placenet_terms,
                    {"nll": 1.0}, _device_of(model), progress=False)


def placenet_baseline(counts: Any, train_idx: Sequence[int], eval_idx: Sequence[int],
                      eval_counts: Any = None, batch: int = 1 << 14) -> dict[str, float]:
    """The constant-intensity PlaceNet: the training mean count for every candidate; its mean
    Poisson NLL ('nll') on rows ``eval_idx`` of ``eval_counts`` (default ``counts``) and the rate
    ('rate'). The counts are read WINDOW_BATCHES * ``batch`` rows at a time."""
    def total(values: Any, idx: Sequence[int]) -> tuple[float, int]:  # (sum of counts, rows)
        sums = [float(np.asarray(b["c"], np.float64).sum()) for b in iter_batches({"c": values}, _rows(idx), batch)]
        return math.fsum(sums), len(idx)

    train_sum, n_train = total(counts, train_idx)
    rate = train_sum / n_train if n_train else math.nan
    eval_sum, n_eval = total(counts if eval_counts is None else eval_counts, eval_idx)
    log_rate = math.log(rate) if rate > 0 else -30.0
    return {"nll": math.exp(log_rate) - eval_sum / n_eval * log_rate if n_eval else math.nan, "rate": rate}


# ------------------------------------------------------------------------------- baselines

BASELINE_UNIFORM_MIX = 1e-6
"""Share of a uniform map mixed into the mean map so that its KL stays finite where it is 0."""


def mean_map_baseline(heatmaps: Any, train_idx: Sequence[int], batch: int = 64) -> np.ndarray:
    """Average training heatmap (H, W) float64, summing to 1 (with a 1e-6 uniform share mixed in)."""
    idx = np.asarray(train_idx, np.int64)
    if idx.size == 0:
        raise ValueError("mean_map_baseline: train_idx is empty")
    total = None
    for b in iter_batches({"h": heatmaps}, idx, batch):
        part = b["h"].astype(np.float64).sum(axis=0)
        total = part if total is None else total + part
    mean = total / total.sum()
    return (1 - BASELINE_UNIFORM_MIX) * mean + BASELINE_UNIFORM_MIX / mean.size


MIN_FRAMES_PER_KNOT = 30
"""Fewest training frames behind one knot of the count prior."""


def speed_count_prior(speeds_mps: Any, counts: Any, n_knots: int = COUNT_PRIOR_KNOTS,
                      stopped_mps: float = STOPPED_MPS, min_frames: int = MIN_FRAMES_PER_KNOT
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The mean radar point count as a function of the ego speed, from training frames' speeds
    (F,) m/s and counts (F,): (knot speeds (K,) m/s strictly increasing, mean counts (K,)), K <=
    ``n_knots``. Frames below ``stopped_mps`` get a knot of their own when there are
    ``min_frames`` of them (a stopped radar sees its static world at zero Doppler); the others
    are cut into speed quantiles of at least ``min_frames`` frames each (fewer bins when frames are
    few). A knot sits at its frames' mean speed with their mean count. Too few frames for two
    knots give one: the mean count.
    """
    v = np.asarray(speeds_mps, np.float64).ravel()
    n = np.asarray(counts, np.float64).ravel()
    if v.size == 0 or v.shape != n.shape or not (np.all(np.isfinite(v)) and np.all(np.isfinite(n))):
        raise ValueError(f"speed_count_prior: need as many finite speeds as counts, got {v.size} and {n.size}")
    if n_knots < 1 or min_frames < 1:
        raise ValueError(f"speed_count_prior: n_knots and min_frames must be >= 1, got {n_knots}, {min_frames}")
    stopped = v < stopped_mps
    groups = [np.flatnonzero(stopped)] if stopped.sum() >= min_frames and n_knots > 1 else []
    moving = np.flatnonzero(~stopped) if groups else np.arange(v.size)
    bins = max(1, min(n_knots - len(groups), moving.size // min_frames))
    groups += [g for g in np.array_split(moving[np.argsort(v[moving], kind="stable")], bins) if g.size]
    merged = [groups[0]]  # groups with the same mean speed (e.g. a constant speed) become one knot
    for g in groups[1:]:
        if v[g].mean() - v[merged[-1]].mean() > 1e-6:
            merged.append(g)
        else:
            merged[-1] = np.concatenate([merged[-1], g])
    return np.array([v[g].mean() for g in merged]), np.array([n[g].mean() for g in merged])


def disnet_baseline(heatmaps: Any, counts: Any, train_idx: Sequence[int], eval_idx: Sequence[int],
                    batch: int = 64, mean_map: np.ndarray | None = None) -> dict[str, float]:
    """Per-frame mean L_KL of the mean training map ('kl') and L_n of the mean training count ('n')
    on frames ``eval_idx``. ``mean_map``: mean_map_baseline's, when the caller has it (it reads
    every training heatmap)."""
    mean_map = mean_map_baseline(heatmaps, train_idx, batch) if mean_map is None else mean_map
    n_bar = float(np.mean(take_rows(counts, np.asarray(train_idx, np.int64))))
    log_q = np.log(mean_map)
    kl_sum, n_sum, m = 0.0, 0.0, 0
    for b in iter_batches({"h": heatmaps, "n": counts}, np.asarray(eval_idx, np.int64), batch):
        p = b["h"].astype(np.float64)
        kl = (np.where(p > 0, p * np.log(np.where(p > 0, p, 1.0)), 0.0) - p * log_q).sum(axis=(1, 2))
        n = b["n"].astype(np.float64)
        kl_sum += kl.sum()
        n_sum += (((n_bar - n) / n) ** 2).sum()
        m += len(n)
    return {"kl": kl_sum / m if m else math.nan, "n": n_sum / m if m else math.nan, "n_bar": n_bar}


def rssnet_baseline(rss: Any, train_idx: Sequence[int], eval_idx: Sequence[int],
                    rss_min: float, rss_max: float) -> dict[str, float]:
    """L_a ('a') of predicting the training median RSS for every point of ``eval_idx``."""
    median = float(np.median(take_rows(rss, np.asarray(train_idx, np.int64))))
    a = take_rows(rss, np.asarray(eval_idx, np.int64)).astype(np.float64)
    err = ((a - median) / (rss_max - rss_min)) ** 2
    return {"a": float(err.mean()) if err.size else math.nan, "median": median}
