"""The range of a net's training inputs, saved with its weights, so that inputs from another dataset
(train.nets_from) the net never saw the like of can be counted (PlaceNet's features, summaries of
RSS-Net's inputs). numpy only: the stages that report on it need no torch."""

from __future__ import annotations

import numpy as np

RANGE_PERCENTILES = (0.5, 99.5)
"""The training range of each column: outside it lie 1% of the training rows."""


def training_range(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) (C,): the RANGE_PERCENTILES of each column of training rows (N, C), NaN left out;
    a column without a value is unbounded (-inf, inf)."""
    x = np.asarray(x, np.float64)
    known = np.isfinite(x).any(axis=0)
    low, high = np.full(x.shape[1], -np.inf), np.full(x.shape[1], np.inf)
    if known.any():
        low[known], high[known] = np.nanpercentile(x[:, known], RANGE_PERCENTILES, axis=0)
    return low, high


def outside(x: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Bool (N, C): which values of rows (N, C) lie outside [low, high] (C,) (NaN: never)."""
    x = np.asarray(x, np.float64)
    with np.errstate(invalid="ignore"):
        return (x < low) | (x > high)
