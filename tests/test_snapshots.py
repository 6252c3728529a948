"""pipeline.snapshots: the status snapshot's lineage, which says which frames a column snapshot
read under an earlier status snapshot misses, and its encoding."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.snapshots import LINEAGE_MAX, OLDER, StatusSnapshot, decode_status, fresh_status

CODES = (0, 1, 2, 3)


@settings(max_examples=200, deadline=None)
@given(frames=st.integers(1, 40), runs=st.lists(st.lists(st.integers(0, 39), max_size=8), min_size=1, max_size=24),
       seed=st.integers(0, 2**32 - 1))
def test_a_snapshot_names_every_frame_written_since_each_of_its_ancestors(frames, runs, seed):
    """Over a chain of runs, each writing some frames: the frames a snapshot says were written
    since an earlier one are exactly those some run in between wrote, for each of the last
    LINEAGE_MAX snapshots before it, and unknown (None) for older ones and for tokens it never
    had; a snapshot's lineage survives its encoding."""
    rng = np.random.default_rng(seed)
    status = rng.integers(0, 4, frames).astype(np.uint8)
    chain = [fresh_status(status)]
    writes: list[set[int]] = []  # writes[k]: the frames written between chain[k] and chain[k + 1]
    for written in runs:
        changed = np.zeros(frames, bool)
        changed[[i for i in written if i < frames]] = True
        status = np.where(changed, rng.integers(0, 4, frames), status).astype(np.uint8)
        after = chain[-1].successor(status, changed)
        decoded = decode_status(after.encode(), frames, CODES)
        assert decoded is not None and decoded.token == after.token and decoded.ancestors == after.ancestors
        np.testing.assert_array_equal(decoded.status, status)
        np.testing.assert_array_equal(decoded.age, after.age)
        chain.append(decoded)
        writes.append(set(np.flatnonzero(changed).tolist()))
    last = chain[-1]
    assert len(last.ancestors) == min(len(runs), LINEAGE_MAX) and len({s.token for s in chain}) == len(chain)
    for k, earlier in enumerate(chain):
        since = last.written_since(earlier.token)
        back = len(chain) - 1 - k  # snapshots between: 0 for the last itself
        if back > LINEAGE_MAX:
            assert since is None, (k, back)
        else:
            assert since is not None and set(since.tolist()) == set().union(*writes[k:]), (k, back)
    assert last.written_since("0123456789abcdef") is None
    assert set(np.unique(last.age)) <= set(range(1, LINEAGE_MAX + 1)) | {OLDER}


def test_a_snapshot_without_a_token_or_a_lineage():
    """Version 1 (no token) has no successor with a lineage; version 2 (a token, no ages) starts
    one: the frames written since it are known, nothing before it."""
    status = np.array([1, 0, 2], np.uint8)
    v1 = StatusSnapshot(status, None)
    assert v1.successor(status, np.ones(3, bool)).ancestors == ()
    v2 = StatusSnapshot(status, "a" * 16)
    after = v2.successor(status, np.array([False, True, False]))
    assert after.ancestors == ("a" * 16,) and after.written_since("a" * 16).tolist() == [1]
    assert after.age.tolist() == [OLDER, 1, OLDER] and v2.written_since("a" * 16).tolist() == []
