"""Benchmark: local range images via one KD-tree query vs brute-force distances (`make bench`).

Cloud: M points uniform in a 50 m x 50 m x 3 m slab in front of the radar (~13 points per m^3,
~55 lidar points per 1 m ball); radar points are lidar points moved by up to 0.3 m. Times are best
of a few runs, single-threaded; the KD-tree time includes building the tree. Prints one line.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from scipy.spatial import cKDTree  # noqa: E402

from pipeline.rangeimage import local_range_images, local_range_images_brute  # noqa: E402


def best_ms(fn, repeats: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best * 1e3, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--lidar", type=int, default=100_000)
    parser.add_argument("--points", type=int, default=100)
    parser.add_argument("--r-l", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    lidar = rng.uniform([0.0, -25.0, -1.5], [50.0, 25.0, 1.5], (args.lidar, 3))
    points = lidar[rng.choice(args.lidar, args.points, replace=False)]
    points = points + rng.uniform(-0.3, 0.3, (args.points, 3))
    fast_ms, fast = best_ms(lambda: local_range_images(lidar, points, args.r_l), 5)
    build_ms, tree = best_ms(lambda: cKDTree(lidar), 5)
    query_ms, _ = best_ms(lambda: local_range_images(lidar, points, args.r_l, tree=tree), 5)
    brute_ms, brute = best_ms(lambda: local_range_images_brute(lidar, points, args.r_l), 2)
    same = bool(np.array_equal(fast, brute))
    print(f"range images {args.points} pts, {args.lidar}-pt cloud, r_l {args.r_l:g} m: kd-tree {fast_ms:.1f} ms "
          f"(build {build_ms:.1f} + query/render {query_ms:.1f}), brute {brute_ms:.0f} ms, identical {same}, "
          f"speed-up {brute_ms / fast_ms:.0f}x")


if __name__ == "__main__":
    main()
