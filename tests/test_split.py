"""Tests of pipeline.split: no leakage for sequence/block rules, fractions, determinism, fallback."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from pipeline.split import TEST, TRAIN, VAL, SplitFallbackWarning, assign_split


def _frames(lengths: list[int]) -> tuple[list[str], list[str]]:
    frame_ids, seq_ids = [], []
    for s, n in enumerate(lengths):
        frame_ids += [f"s{s}_{k:05d}" for k in range(n)]
        seq_ids += [f"s{s}"] * n
    return frame_ids, seq_ids


LENGTHS = [120, 80, 200, 45, 60, 150, 90, 30, 110, 70, 95, 140]


def _shares(parts: np.ndarray) -> np.ndarray:
    return np.bincount(parts, minlength=3) / len(parts)


def test_sequence_rule_keeps_sequences_whole_and_meets_fractions():
    fids, sids = _frames(LENGTHS)
    parts = assign_split(fids, sids, "sequence", (0.6, 0.1, 0.3), seed=0)
    assert parts.dtype == np.int8 and parts.shape == (len(fids),)
    for s in set(sids):
        assert len(set(parts[np.array(sids) == s].tolist())) == 1
    assert set(parts.tolist()) == {TRAIN, VAL, TEST}
    np.testing.assert_allclose(_shares(parts), [0.6, 0.1, 0.3], atol=0.12)


def test_block_rule_keeps_blocks_whole_and_meets_fractions():
    fids, sids = _frames(LENGTHS)
    parts = assign_split(fids, sids, "block", (0.6, 0.1, 0.3), block_len=15, seed=3)
    sids_a = np.array(sids)
    for s in set(sids):
        seq_parts = parts[sids_a == s]
        for start in range(0, len(seq_parts), 15):
            assert len(set(seq_parts[start:start + 15].tolist())) == 1
    np.testing.assert_allclose(_shares(parts), [0.6, 0.1, 0.3], atol=15 / len(fids) + 0.01)


def test_block_rule_is_not_a_trivial_assignment():
    fids, sids = _frames([300])
    parts = assign_split(fids, sids, "block", (0.6, 0.1, 0.3), block_len=10, seed=0)
    # Blocks of one sequence are spread over all parts, and parts change only at block edges.
    assert set(parts.tolist()) == {0, 1, 2}
    changes = np.flatnonzero(np.diff(parts)) + 1
    assert np.all(changes % 10 == 0)


def test_random_rule_cuts_every_sequence_by_fractions():
    fids, sids = _frames([100, 50])
    parts = assign_split(fids, sids, "random", (0.6, 0.1, 0.3), seed=1)
    np.testing.assert_array_equal(np.bincount(parts[:100], minlength=3), [60, 10, 30])
    np.testing.assert_array_equal(np.bincount(parts[100:], minlength=3), [30, 5, 15])
    # Leaky by design: neighbouring frames land in different parts.
    assert np.count_nonzero(np.diff(parts[:100])) > 10


@pytest.mark.parametrize("rule", ["sequence", "block", "random"])
def test_deterministic_with_seed(rule):
    fids, sids = _frames(LENGTHS)
    a = assign_split(fids, sids, rule, (0.6, 0.1, 0.3), 15, seed=7)
    b = assign_split(fids, sids, rule, (0.6, 0.1, 0.3), 15, seed=7)
    c = assign_split(fids, sids, rule, (0.6, 0.1, 0.3), 15, seed=8)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_sequence_rule_falls_back_to_blocks_with_a_warning():
    fids, sids = _frames([200, 100])
    with pytest.warns(SplitFallbackWarning, match="falling back"):
        parts = assign_split(fids, sids, "sequence", (0.6, 0.1, 0.3), block_len=10, seed=0)
    np.testing.assert_array_equal(parts, assign_split(fids, sids, "block", (0.6, 0.1, 0.3), 10, seed=0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assign_split(fids, sids, "sequence", (0.7, 0.0, 0.3), seed=0)  # two parts, two sequences


def test_zero_fraction_part_stays_empty_and_interleaved_sequences():
    fids, sids = _frames([40, 40, 40, 40])
    order = np.random.default_rng(0).permutation(len(fids))  # sequences interleaved in the input
    parts = assign_split([fids[i] for i in order], [sids[i] for i in order], "sequence", (0.75, 0.0, 0.25))
    assert VAL not in parts.tolist()
    shuffled_sids = np.array(sids)[order]
    for s in set(sids):
        assert len(set(parts[shuffled_sids == s].tolist())) == 1


def test_empty_and_errors():
    assert assign_split([], [], "block").shape == (0,)
    with pytest.raises(ValueError, match="unknown"):
        assign_split(["a"], ["s"], "scene")
    with pytest.raises(ValueError, match="sequence ids"):
        assign_split(["a", "b"], ["s"], "block")
    with pytest.raises(ValueError, match="unique"):
        assign_split(["a", "a"], ["s", "s"], "block")
    with pytest.raises(ValueError, match="fractions"):
        assign_split(["a"], ["s"], "block", (0.5, 0.2, 0.2))
    with pytest.raises(ValueError, match="block_len"):
        assign_split(["a"], ["s"], "block", block_len=0)


@pytest.mark.parametrize("lengths", [[50, 50, 50], [100, 20, 60], [30, 200, 45, 80]])
def test_each_part_gets_a_unit_before_any_part_gets_a_second(lengths):
    """Units go to the part furthest below its target *relative* to that target: a part without a
    unit is 100% short, so with as many sequences as parts each part gets one (the small
    validation share is not left empty while train and test take them all)."""
    fids, sids = _frames(lengths)
    for seed in range(5):
        parts = assign_split(fids, sids, "sequence", (0.6, 0.1, 0.3), seed=seed)
        assert set(parts.tolist()) == {TRAIN, VAL, TEST}, seed


def test_a_run_says_the_fallback_once_on_calibrates_summary(tmp_path):
    """A run on too few sequences printed the SplitFallbackWarning as Python shows warnings (the
    source file and line of calibrate under it), from every worker process, until 2026-12-07; the
    calibrate summary says it now, once."""
    from click.testing import CliRunner

    from pipeline.cli import main

    sets = ["--set", "dataset.world_frames=4", "--set", "dataset.world_sequence_len=2", "--set", "split.block_len=1",
            "--set", "split.rule=sequence"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = CliRunner().invoke(main, ["run", "calibrate", "--workers", "1", "--cache", str(tmp_path), *sets])
    assert out.exit_code == 0, out.output
    assert not [w for w in caught if issubclass(w.category, SplitFallbackWarning)]
    notes = [line.strip() for line in out.stderr.splitlines() if "split.rule = 'sequence'" in line]
    assert notes == ["split.rule = 'sequence': too few sequences for the 3 parts, so blocks of 1 frames inside "
                     "sequences were assigned instead (sequences here that lie in several parts: 1 of 2)"], out.stderr
