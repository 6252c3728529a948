"""Train / val / test assignment of frames (METHOD.md, "Experiments to reproduce").

Rules:
- 'sequence': whole sequences go to one part (no leakage). Sequences are shuffled with the seed and
  assigned greedily, each to the part furthest below its target share (relative deficit), so the
  parts' frame shares approximate ``fractions``. With fewer sequences than parts of positive share,
  it falls back to 'block' and emits a ``SplitFallbackWarning`` saying so.
- 'block': blocks of ``block_len`` consecutive frames inside each sequence (the last block of a
  sequence may be shorter) are the units, assigned like sequences. Only frames at block edges
  neighbour another part.
- 'random': the paper's split: inside each sequence, frames are shuffled and cut by ``fractions``
  (neighbouring frames land in different parts: leaky; for comparison only).

Frames of one sequence are taken in the order given (the caller passes them in time order).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np

from pipeline.config import CHOICES

TRAIN, VAL, TEST = 0, 1, 2
RULES = CHOICES["split.rule"]


class SplitFallbackWarning(UserWarning):
    """The requested rule could not be applied as asked; the message says what was done instead."""


def _check_fractions(fractions: Sequence[float]) -> np.ndarray:
    f = np.asarray(fractions, dtype=np.float64)
    if f.shape != (3,) or not np.all(np.isfinite(f)) or np.any(f < 0) or abs(f.sum() - 1.0) > 1e-6:
        raise ValueError(f"split fractions must be 3 non-negative numbers summing to 1, got {tuple(fractions)}")
    return f / f.sum()


def _sequence_groups(sequence_ids: Sequence[str]) -> list[np.ndarray]:
    """Frame indices of each sequence, sequences in order of first appearance, frames in given order."""
    _, first, inverse = np.unique(np.asarray(sequence_ids, dtype=object), return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    by_sequence = np.argsort(inverse, kind="stable")  # frames grouped by sequence, in given order within
    groups = np.split(by_sequence, np.cumsum(np.bincount(inverse, minlength=len(first)))[:-1])
    return [groups[k] for k in np.argsort(first)]


def _assign_units(units: list[np.ndarray], fractions: np.ndarray, rng: np.random.Generator,
                  n_frames: int) -> np.ndarray:
    """Give each unit (frame indices) to one part; shuffled order, part with largest relative deficit."""
    parts = np.zeros(n_frames, dtype=np.int8)
    target = fractions * sum(len(u) for u in units)
    assigned = np.zeros(3)
    positive = fractions > 0
    for k in rng.permutation(len(units)):
        deficit = np.where(positive, (target - assigned) / np.where(positive, target, 1.0), -np.inf)
        part = int(np.argmax(deficit + 1e-9 * fractions))  # ties: the larger share first
        parts[units[k]] = part
        assigned[part] += len(units[k])
    return parts


def _blocks(groups: list[np.ndarray], block_len: int) -> list[np.ndarray]:
    return [g[s:s + block_len] for g in groups for s in range(0, len(g), block_len)]


def _random_within(groups: list[np.ndarray], fractions: np.ndarray, rng: np.random.Generator,
                   n_frames: int) -> np.ndarray:
    parts = np.zeros(n_frames, dtype=np.int8)
    for g in groups:
        cut = np.rint(np.cumsum(fractions)[:2] * len(g)).astype(int)
        shuffled = rng.permutation(g)
        parts[shuffled[cut[0]:cut[1]]] = VAL
        parts[shuffled[cut[1]:]] = TEST
    return parts


def assign_split(frame_ids: Sequence[str], sequence_ids: Sequence[str], rule: str,
                 fractions: Sequence[float] = (0.6, 0.1, 0.3), block_len: int = 15, seed: int = 0) -> np.ndarray:
    """Part of every frame: (F,) int8, 0 train, 1 val, 2 test (rules in the module docstring).

    frame_ids, sequence_ids: (F,) one entry per frame (frame ids must be unique). Deterministic for
    a given seed and input order. Raises ValueError on an unknown rule, mismatched lengths,
    duplicate frame ids, bad fractions or block_len < 1.
    """
    if rule not in RULES:
        raise ValueError(f"split rule {rule!r} unknown; expected one of {RULES}")
    if len(frame_ids) != len(sequence_ids):
        raise ValueError(f"split: {len(frame_ids)} frame ids but {len(sequence_ids)} sequence ids")
    if len(set(frame_ids)) != len(frame_ids):
        raise ValueError("split: frame ids are not unique")
    if int(block_len) < 1:
        raise ValueError(f"split: block_len must be >= 1, got {block_len}")
    f = _check_fractions(fractions)
    n = len(frame_ids)
    if n == 0:
        return np.zeros(0, dtype=np.int8)
    rng = np.random.default_rng(seed)
    groups = _sequence_groups(sequence_ids)
    if rule == "random":
        return _random_within(groups, f, rng, n)
    if rule == "sequence":
        if len(groups) >= int(np.count_nonzero(f)):
            return _assign_units(groups, f, rng, n)
        warnings.warn(f"split: {len(groups)} sequence(s) for {np.count_nonzero(f)} parts; "
                      f"falling back to blocks of {block_len} frames inside sequences",
                      SplitFallbackWarning, stacklevel=2)
    return _assign_units(_blocks(groups, int(block_len)), f, rng, n)
