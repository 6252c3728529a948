"""Benchmark: separable-GEMM heatmap vs the naive per-point sum (run by `make bench`, not pytest).

Prints one line: fast and naive times, the time to write a float32 array of the map's size (the
memory floor), speed-up, ratio to the floor, and the max per-pixel relative error vs the naive
float64 map (over pixels >= 1e-28, i.e. well inside float32's normal range). Single-threaded BLAS.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from pipeline.heatmap import gaussian_heatmap, naive_heatmap  # noqa: E402


def best_ms(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--size", type=int, nargs=2, default=(1936, 1216), metavar=("W", "H"))
    parser.add_argument("--points", type=int, default=1000)
    parser.add_argument("--sigma", type=float, default=100.0)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    w, h = args.size
    rng = np.random.default_rng(args.seed)
    uv = rng.uniform([-0.5, -0.5], [w - 0.5, h - 0.5], (args.points, 2))
    sigma = (args.sigma, args.sigma)
    fast_ms = best_ms(lambda: gaussian_heatmap(uv, (w, h), sigma), 10)
    floor_ms = best_ms(lambda: np.full((h, w), 1.0, dtype=np.float32), 20)
    start = time.perf_counter()
    ref = naive_heatmap(uv, (w, h), sigma)
    naive_ms = (time.perf_counter() - start) * 1e3
    fast = gaussian_heatmap(uv, (w, h), sigma).astype(np.float64)
    held = ref >= 1e-28
    rel = float(np.max(np.abs(fast - ref)[held] / ref[held]))
    print(f"heatmap {w}x{h}, {args.points} pts, sigma {args.sigma:g} px: fast {fast_ms:.1f} ms, "
          f"naive {naive_ms:.0f} ms, write-floor {floor_ms:.2f} ms, speed-up {naive_ms / fast_ms:.0f}x, "
          f"floor ratio {fast_ms / floor_ms:.0f}x, max rel err {rel:.1e}")


if __name__ == "__main__":
    main()
