"""Reading array-likes by rows: numpy or zarr arrays indexed along axis 0 (frames, points or
lidar candidates), read one window of batches at a time with sorted indices, never all at once;
an epoch's shuffled order made one window at a time (the chunks' groups of rows in a random order).
Used by training, inference and the baselines."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Any, Iterator, Sequence

import numpy as np


Batch = dict[str, np.ndarray]


WINDOW_BATCHES = 16
"""Batches read from the arrays in one go (one sorted read per array)."""


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


def index_array(idx: Sequence[int]) -> np.ndarray:
    """``idx`` as a flat int64 array (a range by arange: np.asarray of one is 20x slower)."""
    if isinstance(idx, range):
        return np.arange(idx.start, idx.stop, idx.step, dtype=np.int64)
    return np.asarray(idx, np.int64).reshape(-1)


def as_rows(idx: Sequence[int]) -> Rows:
    """``idx`` as row indices: a ``range`` (step 1) as it is, else a flat int64 array."""
    return idx if isinstance(idx, range) and idx.step == 1 else index_array(idx)


def take_rows(array: Any, idx: Rows) -> np.ndarray:
    """Rows ``idx`` (any order, repeats allowed) of a numpy or zarr array, read with sorted indices."""
    idx = index_array(idx)
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
    return _array_windows(index_array(idx), rows_per_chunk, window, rng)


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
