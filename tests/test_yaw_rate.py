"""The radar's turn between two lidar scans (pipeline.egomotion.estimate_yaw_rate)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.baselines import ego_motion_transform
from pipeline.egomotion import estimate_yaw_rate


def _street(rng: np.random.Generator, n: int) -> np.ndarray:
    """n points (n, 3) m drawn anew on a street's static surfaces: two house fronts along x at
    y = +/-8 m, a cross wall at x = 45 m, a parked van, the ground."""
    kind = rng.integers(0, 5, n)
    x, y, z = rng.uniform(2, 45, n), rng.uniform(-8, 8, n), rng.uniform(-0.5, 4, n)
    y = np.where(kind == 0, 8.0, np.where(kind == 1, -8.0, y))
    x = np.where(kind == 2, 45.0, x)
    van = kind == 3
    x[van], y[van] = rng.uniform(12, 17, van.sum()), np.where(rng.random(van.sum()) < 0.5, 3.0, 5.0)
    z = np.where(kind == 4, -0.5, z)
    return np.column_stack([x, y, z])


@pytest.mark.parametrize("rate, dt", [(0.2, 0.1), (-0.35, 0.2), (0.0, 0.1), (0.12, -0.3)])
def test_recovers_the_turn_between_scans_of_other_points(rate, dt):
    """Each scan samples other points of the same surfaces (as a lidar does from another place);
    a car crossing the street is in one scan only. The turn comes back within 0.004 rad/s
    (0.02 deg over 0.1 s), for a later or an earlier other scan."""
    rng = np.random.default_rng(1)
    ego = np.array([9.0, 0.2, 0.0])
    now = _street(rng, 12000)
    T_other_now = np.linalg.inv(ego_motion_transform(ego, -dt, rate))   # this frame -> the other's
    other = _street(rng, 12000) @ T_other_now[:3, :3].T + T_other_now[:3, 3]
    crossing = np.column_stack([rng.uniform(20, 24, 1500), rng.uniform(-2, 2, 1500), rng.uniform(-0.5, 1.0, 1500)])
    estimate = estimate_yaw_rate(now, np.vstack([other, crossing]), ego, dt)
    assert estimate == pytest.approx(rate, abs=0.004)


def test_too_few_points_or_no_time_apart_give_no_turn():
    rng = np.random.default_rng(2)
    cloud = _street(rng, 500)
    assert estimate_yaw_rate(cloud[:5], cloud, np.zeros(3), 0.1) == 0.0
    assert estimate_yaw_rate(cloud, np.full((50, 3), np.nan), np.zeros(3), 0.1) == 0.0
    assert estimate_yaw_rate(cloud, cloud, np.zeros(3), 0.0) == 0.0


def test_turning_left_turns_the_later_scan_to_the_right():
    """The sign, without ego_motion_transform: standing still and turning left by 1 deg in
    0.1 s, the later scan sees the street turned 1 deg to the right (clockwise): +0.1745 rad/s."""
    rng = np.random.default_rng(3)
    psi = np.deg2rad(1.0)
    c, s = np.cos(psi), np.sin(psi)
    clockwise = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])
    later = _street(rng, 12000) @ clockwise.T
    assert estimate_yaw_rate(_street(rng, 12000), later, np.zeros(3), 0.1) == pytest.approx(psi / 0.1, abs=0.004)
