"""Box association across frames without track ids (pipeline.boxmatch)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.boxmatch import differenced_velocities, match_boxes


def test_recovers_a_shuffled_frame_of_moving_boxes():
    """30 boxes of three classes on a 4 m grid, each moved by up to 1 m and listed in another
    order: every box finds its own."""
    rng = np.random.default_rng(0)
    grid = np.stack(np.meshgrid(np.arange(6) * 4.0, np.arange(5) * 4.0, indexing="ij"), -1).reshape(-1, 2)
    a = np.column_stack([grid, rng.uniform(-1, 1, 30)])
    classes = list(rng.choice(["Car", "Pedestrian", "Cyclist"], 30))
    order = rng.permutation(30)
    b = (a + rng.uniform(-0.55, 0.55, a.shape))[order]
    match = match_boxes(a, classes, b, [classes[k] for k in order], max_shift_m=2.0)
    np.testing.assert_array_equal(order[match], np.arange(30))


def test_class_gate_and_empty_frames():
    a = np.array([[0.0, 0, 0], [10.0, 0, 0]])
    b = np.array([[0.1, 0, 0], [13.0, 0, 0]])
    # another class at the same place, and a box beyond the gate: no partner
    np.testing.assert_array_equal(match_boxes(a, ["Car", "Car"], b, ["Pedestrian", "Car"], 2.0), [-1, -1])
    np.testing.assert_array_equal(match_boxes(a, ["Car", "Car"], b, ["Car", "Car"], 2.0), [0, -1])
    np.testing.assert_array_equal(match_boxes(a, ["Car", "Car"], b, ["Car", "Car"], 3.5), [0, 1])
    assert match_boxes(a, ["Car", "Car"], np.zeros((0, 3)), [], 2.0).tolist() == [-1, -1]
    assert match_boxes(np.zeros((0, 3)), [], b, ["Car", "Car"], 2.0).shape == (0,)
    with pytest.raises(ValueError, match="class names"):
        match_boxes(a, ["Car"], b, ["Car", "Car"], 2.0)


def test_ambiguous_or_one_sided_nearest_boxes_stay_unmatched():
    """Two boxes of the class almost as near as the nearest: unknown rather than a guess. A box
    whose nearest box in b is nearer to another box of a is not matched either."""
    a = np.array([[0.0, 0, 0]])
    b = np.array([[0.4, 0, 0], [-0.6, 0, 0]])
    assert match_boxes(a, ["Car"], b, ["Car", "Car"], 2.0).tolist() == [-1]
    assert match_boxes(a, ["Car"], b, ["Car", "Car"], 2.0, ambiguity_ratio=1.4).tolist() == [0]
    assert match_boxes(a, ["Car"], b, ["Car", "Truck"], 2.0).tolist() == [0]  # the other is another class
    a = np.array([[0.0, 0, 0], [0.3, 0, 0]])
    b = np.array([[0.25, 0, 0]])
    assert match_boxes(a, ["Car", "Car"], b, ["Car"], 2.0).tolist() == [-1, 0]
    # the same from b's side: the pair (a1, b0) stands only if a0 is far enough from b0 as well
    a = np.array([[0.0, 0, 0], [0.3, 0, 0]])
    b = np.array([[0.18, 0, 0]])
    assert match_boxes(a, ["Car", "Car"], b, ["Car"], 2.0).tolist() == [-1, -1]


def test_the_gate_and_the_ambiguity_margin_are_inclusive():
    """A partner exactly ``max_shift_m`` away is within the gate; another box exactly
    ``ambiguity_ratio`` (default 2) times farther, in b or in a, leaves the match standing."""
    a = np.array([[0.0, 0, 0]])
    assert match_boxes(a, ["Car"], np.array([[2.0, 0, 0]]), ["Car"], 2.0).tolist() == [0]
    assert match_boxes(a, ["Car"], np.array([[2.0, 0, 0]]), ["Car"], 1.999).tolist() == [-1]
    b = np.array([[0.5, 0, 0], [-1.0, 0, 0]])  # the other box of b exactly twice as far from a0
    assert match_boxes(a, ["Car"], b, ["Car", "Car"], 1.0).tolist() == [0]
    assert match_boxes(a, ["Car"], b + [0.01, 0, 0], ["Car", "Car"], 1.0).tolist() == [-1]
    a2 = np.array([[0.0, 0, 0], [1.5, 0, 0]])  # the other box of a exactly twice as far from b0
    assert match_boxes(a2, ["Car", "Car"], np.array([[0.5, 0, 0]]), ["Car"], 1.0).tolist() == [0, -1]
    assert match_boxes(a2, ["Car", "Car"], np.array([[0.51, 0, 0]]), ["Car"], 1.0).tolist() == [-1, -1]


def test_without_a_gate_a_class_absent_from_b_stays_unmatched():
    a = np.array([[0.0, 0, 0], [5.0, 0, 0]])
    b = np.array([[0.2, 0, 0]])
    assert match_boxes(a, ["Car", "Pedestrian"], b, ["Car"], np.inf).tolist() == [0, -1]
    assert match_boxes(a[1:], ["Pedestrian"], b, ["Car"], np.inf).tolist() == [-1]


def test_each_box_of_b_goes_to_one_box_of_a_even_without_a_margin():
    """With ambiguity_ratio 1 (no margin asked) the pair must still be mutual nearest neighbours:
    a0's nearest box, b0, is nearer to a1, so only a1 gets it."""
    a = np.array([[0.0, 0, 0], [0.3, 0, 0]])
    b = np.array([[0.25, 0, 0]])
    assert match_boxes(a, ["Car", "Car"], b, ["Car"], 2.0, ambiguity_ratio=1.0).tolist() == [-1, 0]


def test_differenced_velocities_central_one_sided_and_unknown():
    """Box 0 is held before and after (central difference over 0.3 s), box 1 only after
    (one-sided), box 2 by no neighbour (NaN); the neighbours' order does not matter."""
    now = np.array([[0.0, 0, 0], [10.0, 0, 0], [20.0, 0, 0]])
    before = (np.array([0, -1, -1]), np.array([[-1.0, 0.5, 0]]), 0.9)           # t = 0.9 s
    after = (np.array([1, 0, -1]), np.array([[11.0, 0, 0], [2.0, 0.0, 0.2]]), 1.2)  # t = 1.2 s
    for neighbours in ([before, after], [after, before]):
        v = differenced_velocities(now, 1.0, neighbours)
        np.testing.assert_allclose(v[0], [(2.0 + 1.0) / 0.3, -0.5 / 0.3, 0.2 / 0.3])
        np.testing.assert_allclose(v[1], [(11.0 - 10.0) / 0.2, 0, 0])
        assert np.isnan(v[2]).all()
    assert np.isnan(differenced_velocities(now, 1.0, [])).all()
    assert differenced_velocities(np.zeros((0, 3)), 1.0, [(np.zeros(0, np.int64), np.zeros((0, 3)), 2.0)]).shape == (0, 3)
