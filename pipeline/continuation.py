"""Whether training may continue from a net's last checkpoint under the configured epochs.

The epochs are not part of a net's training fingerprint under a constant learning rate, so that
raising train.epochs (or placement.epochs) continues from the last finished epoch instead of
starting over (a schedule that spans the epochs puts them in the fingerprint:
pipeline.training.default_fingerprint). Continuing must still give the nets a fresh run of that
length would, which a checkpoint with more epochs than asked cannot: its best epoch may lie beyond
them. Torch-free: shared by pipeline.training (which then starts the net over) and `pipeline
status` (which says so).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


def continuation_problem(meta: Mapping[str, Any], n_epochs: int) -> str | None:
    """Why training for ``n_epochs`` cannot continue from a last checkpoint whose metadata is
    ``meta`` (its finished 'epoch'), in a few words; None when it can."""
    done = int(meta.get("epoch", 0))
    return f"it has {done} epochs, more than the {n_epochs} asked" if done > n_epochs else None
