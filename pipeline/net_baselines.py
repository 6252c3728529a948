"""The baselines the train stage measures each net against, on the same frames and points: the
mean training map and count (Dis-Net), the training median RSS (RSS-Net), the constant intensity
(PlaceNet); and the count prior Dis-Net's number branch starts from (the mean count as a function
of the ego speed). Evaluate's baseline methods are in pipeline.baselines."""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from pipeline.egomotion import STOPPED_MPS
from pipeline.metrics import rss_loss
from pipeline.models.disnet import COUNT_PRIOR_KNOTS
from pipeline.progress import EVERY_S, bar as progress_bar
from pipeline.rows import as_rows, iter_batches, take_rows


def placenet_baseline(counts: Any, train_idx: Sequence[int], eval_idx: Sequence[int],
                      eval_counts: Any = None, batch: int = 1 << 14) -> dict[str, float]:
    """The constant-intensity PlaceNet: the training mean count for every candidate; its mean
    Poisson NLL ('nll') on rows ``eval_idx`` of ``eval_counts`` (default ``counts``) and the rate
    ('rate'). The counts are read WINDOW_BATCHES * ``batch`` rows at a time."""
    def total(values: Any, idx: Sequence[int]) -> tuple[float, int]:  # (sum of counts, rows)
        sums = [float(np.asarray(b["c"], np.float64).sum()) for b in iter_batches({"c": values}, as_rows(idx), batch)]
        return math.fsum(sums), len(idx)

    train_sum, n_train = total(counts, train_idx)
    rate = train_sum / n_train if n_train else math.nan
    eval_sum, n_eval = total(counts if eval_counts is None else eval_counts, eval_idx)
    log_rate = math.log(rate) if rate > 0 else -30.0
    return {"nll": math.exp(log_rate) - eval_sum / n_eval * log_rate if n_eval else math.nan, "rate": rate}


BASELINE_UNIFORM_MIX = 1e-6
"""Share of a uniform map mixed into the mean map so that its KL stays finite where it is 0."""


def mean_map_baseline(heatmaps: Any, train_idx: Sequence[int], batch: int = 64, progress: bool = False,
                      every_s: float = EVERY_S) -> np.ndarray:
    """Average training heatmap (H, W) float64, summing to 1 (with a 1e-6 uniform share mixed in).
    ``progress``: a 'mean training map' bar on stderr (pipeline.progress; a line every ``every_s``
    in a log: every training heatmap is read, about 2 minutes on 25,000 Astyx frames)."""
    idx = np.asarray(train_idx, np.int64)
    if idx.size == 0:
        raise ValueError("mean_map_baseline: train_idx is empty")
    total = None
    for b in progress_bar(iter_batches({"h": heatmaps}, idx, batch), total=math.ceil(idx.size / batch),
                          desc="mean training map", unit="batch", enabled=progress, every_s=every_s):
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
    a = take_rows(rss, np.asarray(eval_idx, np.int64))
    return {"a": rss_loss(a, np.full(len(a), median), rss_min, rss_max), "median": median}
