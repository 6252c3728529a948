"""Benchmark of the range step (METHOD.md 4D signal generation, step 3): 2000 samples against
100k lidar points, spatial index (cKDTree on angles) vs the brute-force n x M scan.

Run: ``python tests/benchmarks/bench_range.py`` (``make bench``). Not collected by pytest. Prints
one line ending in the speed-up ratio (brute force time / index time); the index time includes
building the index. Both methods must give the same ranges, or the script exits with status 1.
"""

from __future__ import annotations

import os
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from pipeline.geometry import spherical_to_cartesian  # noqa: E402
from pipeline.synthesis import LidarAngularIndex  # noqa: E402

N_SAMPLES, N_LIDAR = 2000, 100_000
DELTA_RAD = np.deg2rad(1.5)


def scene(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 64-ring lidar over 360 deg (ranges 2-80 m) and sample directions inside a 64 x 40 deg FOV."""
    rings = np.deg2rad(np.linspace(-25.0, 3.0, 64))
    rae = np.column_stack([
        rng.uniform(2.0, 80.0, N_LIDAR),
        rng.uniform(-np.pi, np.pi, N_LIDAR),
        rings[rng.integers(0, 64, N_LIDAR)],
    ])
    az = rng.uniform(-np.deg2rad(32.0), np.deg2rad(32.0), N_SAMPLES)
    el = rng.uniform(-np.deg2rad(20.0), np.deg2rad(20.0), N_SAMPLES)
    return spherical_to_cartesian(rae), az, el


def best_of(repeats: int, fn) -> tuple[float, object]:
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return min(times), result


def main() -> int:
    lidar, az, el = scene(np.random.default_rng(0))
    def indexed():
        return LidarAngularIndex(lidar).estimate_range(az, el, DELTA_RAD, DELTA_RAD, "mean", "widen")

    t_index, fast = best_of(3, indexed)
    index = LidarAngularIndex(lidar)
    t_brute, slow = best_of(1, lambda: index.estimate_range_bruteforce(az, el, DELTA_RAD, DELTA_RAD, "mean", "widen"))
    if not (np.allclose(fast[0], slow[0], equal_nan=True) and np.array_equal(fast[1], slow[1])):
        print("bench_range: index and brute force disagree", file=sys.stderr)
        return 1
    print(f"range step ({N_SAMPLES} samples, {N_LIDAR} lidar points, mean rule, +/-1.5 deg): "
          f"kd-tree index {t_index * 1e3:.1f} ms (build included), brute force {t_brute * 1e3:.1f} ms, "
          f"ratio {t_brute / t_index:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
