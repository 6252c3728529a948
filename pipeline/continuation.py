"""Whether training may continue from a net's last checkpoint under the configured epochs and
patience.

The epochs are not part of a net's training fingerprint under a constant learning rate, so that
raising train.epochs (or placement.epochs) continues from the last finished epoch instead of
starting over (a schedule that spans the epochs puts them in the fingerprint:
pipeline.training.default_fingerprint). Nor is the patience (train.patience, placement.patience:
stop once that many epochs in a row have not lowered the selection loss), which only says where a
run ends. Continuing must still give the nets a fresh run of those settings would, which a
checkpoint cannot where its best epoch lies beyond where a fresh run would have stopped: beyond the
epochs asked, or after the epoch at which the patience now set would have ended the run. Torch-free:
shared by pipeline.training (which then starts the net over) and `pipeline status` (which says so).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from pipeline.config import EPOCHS_KEYS, TRAINING_KEYS


def default_fingerprint(cfg, net: str) -> str:
    """Fingerprint of the config keys that change what a net learns (not epochs/device/threads);
    torch-free, so that `pipeline status` can tell a checkpoint's settings without loading torch."""
    if net not in TRAINING_KEYS or net == "common":
        raise ValueError(f"default_fingerprint: unknown net {net!r}")
    common = list(TRAINING_KEYS["common"])
    if cfg.train.lr_schedule != "constant":  # the schedule spans the epochs: more epochs, another run
        common.append(EPOCHS_KEYS[net])
    return cfg.fingerprint(list(TRAINING_KEYS[net]) + common)


def continuation_problem(meta: Mapping[str, Any], n_epochs: int, patience: int = 0,
                         select_on: str = "loss") -> str | None:
    """Why training for ``n_epochs`` with ``patience`` (0: none) cannot continue from a last
    checkpoint whose metadata is ``meta`` (its finished 'epoch', 'curves', 'selection' and
    'best_epoch'), in a few words; None when it can. ``select_on`` is train.select_on."""
    done = int(meta.get("epoch", 0))
    if done > n_epochs:
        return f"it has {done} epochs, more than the {n_epochs} asked"
    if patience > 0 and done > 0:
        bests = running_best_epochs(meta.get("curves") or [], str(meta.get("selection", "val")), select_on)
        stop = stop_epoch(bests, patience)
        if stop is not None and stop < done and bests[stop - 1] != bests[-1]:
            return (f"its best epoch, {bests[-1]}, came after epoch {stop}, where a patience of {patience} stops "
                    f"with epoch {bests[stop - 1]} best")
    return None


def running_best_epochs(curves: Sequence[Mapping[str, Any]], selection: str, select_on: str) -> list[int]:
    """The best epoch after each epoch of ``curves`` (a checkpoint's per-epoch records): the first
    epoch with the lowest selection loss so far, the loss being the ``selection`` split's ('val' or
    'train') ``select_on`` term where the curves hold it, else its 'loss' (as
    pipeline.training.selection_key picks it); the comparison the training loop makes."""
    prefix = "val" if selection == "val" else "train"
    key = f"{prefix}_{select_on}" if curves and f"{prefix}_{select_on}" in curves[0] else f"{prefix}_loss"
    out, best, best_metric = [], 0, float("inf")
    for i, row in enumerate(curves, 1):
        metric = float(row[key])
        if metric < best_metric:
            best, best_metric = i, metric
        out.append(best)
    return out


def stop_epoch(best_epochs: Sequence[int], patience: int) -> int | None:
    """The epoch after which a run with ``patience`` (> 0) stops, given the best epoch after each
    epoch (:func:`running_best_epochs`): the first whose best lies ``patience`` epochs back or more;
    None when no epoch of them does (the run goes on)."""
    return next((e for e, b in enumerate(best_epochs, 1) if e - b >= patience), None)


def stalled(state: Mapping[str, Any], patience: int) -> bool:
    """Whether a run with ``patience`` (0: none) ends at a checkpoint or training state ``state``:
    its 'best_epoch' lies ``patience`` epochs or more behind its last finished 'epoch'."""
    return patience > 0 and int(state.get("epoch", 0)) - int(state.get("best_epoch", 0)) >= patience
