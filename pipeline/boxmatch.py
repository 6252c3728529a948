"""Associating the labelled boxes of two neighbouring frames that carry no track ids.

View-of-Delft's detection release labels every frame of its 10 Hz sequences but gives a box no
identity across frames, so an object's velocity cannot be differenced along its track. Over 0.1 s
an object moves little against the spacing of objects of its class (a cyclist at 5 m/s: 0.5 m; two
cyclists side by side: about 1 m apart), so the box of the same object in the neighbouring frame is
the nearest box of its class there, once both frames' centres are in one world frame (the ego's
own motion removed). :func:`match_boxes` keeps only the pairs where that is unambiguous; the rest
stay unmatched (their velocity unknown) rather than risk a velocity between two different objects.

Units: centres (N, 3) in metres, in one frame for both sets (the odometry world).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.distance import cdist

from pipeline.frame import check_shape

MAX_OBJECT_SPEED_MPS = 20.0
"""Fastest object speed over ground that a match may imply (72 km/h; the boxes of a neighbouring
frame dt seconds away are searched within this speed times dt of a box)."""
AMBIGUITY_RATIO = 2.0
"""A match stands only if every other box of the class, in either frame, is at least this many
times farther from the pair's boxes than they are from each other."""


def match_boxes(centres_a: np.ndarray, classes_a: Sequence[str], centres_b: np.ndarray, classes_b: Sequence[str],
                max_shift_m: float, ambiguity_ratio: float = AMBIGUITY_RATIO) -> np.ndarray:
    """(N,) int64: for each box i of frame a (centres (N, 3) m, class names), the index of the same
    object's box in frame b (centres (M, 3) m in the same world frame), or -1.

    Boxes i and j are matched when they have the same class, lie within ``max_shift_m`` of each
    other, each is the other's nearest box of that class (mutual nearest neighbours) and no other
    box of the class in b is nearer to i, nor any other in a nearer to j, than ``ambiguity_ratio``
    times their distance. A box of a class absent from b, or without an unambiguous partner, gets -1.
    """
    a = check_shape("centres_a", np.asarray(centres_a, np.float64), (None, 3))
    b = check_shape("centres_b", np.asarray(centres_b, np.float64), (None, 3))
    if len(classes_a) != len(a) or len(classes_b) != len(b):
        raise ValueError(f"{len(classes_a)} and {len(classes_b)} class names for {len(a)} and {len(b)} boxes")
    out = np.full(len(a), -1, np.int64)
    if len(a) == 0 or len(b) == 0:
        return out
    d = cdist(a, b)
    d[np.asarray(classes_a, object)[:, None] != np.asarray(classes_b, object)[None, :]] = np.inf
    rows = np.arange(len(a))
    j = np.argmin(d, axis=1)
    nearest = d[rows, j]
    mutual = np.argmin(d, axis=0)[j] == rows
    second_in_b = np.partition(d, 1, axis=1)[:, 1] if d.shape[1] > 1 else np.full(len(a), np.inf)
    second_in_a = np.partition(d, 1, axis=0)[1] if d.shape[0] > 1 else np.full(len(b), np.inf)
    margin = ambiguity_ratio * nearest
    ok = (np.isfinite(nearest) & (nearest <= max_shift_m) & mutual
          & (second_in_b >= margin) & (second_in_a[j] >= margin))
    out[ok] = j[ok]
    return out


def differenced_velocities(centres: np.ndarray, t_s: float,
                           neighbours: Sequence[tuple[np.ndarray, np.ndarray, float]]) -> np.ndarray:
    """(N, 3) m/s: each box's velocity from its positions in neighbouring frames, NaN where no
    neighbour holds it.

    ``centres`` (N, 3) m: the boxes at time ``t_s``; ``neighbours``: (same (N,) int64, centres
    (M, 3) m, time s) per neighbouring frame, ``same[i]`` the index of box i's object among that
    frame's centres or -1, all centres in one frame (a world frame, or the ego's at ``t_s`` with
    its motion removed). The velocity is the difference between the box's earliest and latest
    known positions over their time apart: a central difference where frames before and after hold
    it, one-sided where one does.
    """
    c = check_shape("centres", np.asarray(centres, np.float64), (None, 3))
    first, t_first = c.copy(), np.full(len(c), float(t_s))
    last, t_last = c.copy(), np.full(len(c), float(t_s))
    for same, other, t_other in neighbours:
        held = np.asarray(same) >= 0
        for ends, times, later in ((first, t_first, False), (last, t_last, True)):
            take = held & ((t_other > times) if later else (t_other < times))
            ends[take] = np.asarray(other, np.float64)[np.asarray(same)[take]]
            times[take] = t_other
    out = np.full((len(c), 3), np.nan)
    known = t_first != t_last
    out[known] = (last - first)[known] / (t_last - t_first)[known, None]
    return out
