"""Reading the status of a 20,000-frame output (one chunk per frame): FrameStore.status, which reads
the chunk files itself, against zarr's read of the same array. Both must give the same codes, or
the script exits with status 1.

Prints one line ending in the ratio of zarr's time to FrameStore.status's.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import zarr

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from pipeline.cache import DONE, EXCLUDED, FAILED, FrameStore  # noqa: E402
from pipeline.stage import ArraySpec  # noqa: E402

N_FRAMES = 20_000


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        store = FrameStore(str(Path(tmp) / "stage.zarr"))
        spec = ArraySpec("value", (), "float32", units="1")
        store.create("fp", [f"{i:05d}" for i in range(N_FRAMES)], (spec,), {"value": ()}, {})
        codes = np.random.default_rng(0).choice([DONE, FAILED, EXCLUDED, 0], N_FRAMES, p=[0.9, 0.03, 0.02, 0.05])
        t0 = time.perf_counter()
        zarr.open_array(f"{store.url}/status", mode="r+")[:] = codes.astype(np.uint8)
        written = time.perf_counter() - t0
        times = {"direct": [], "zarr": []}
        for _ in range(3):  # interleaved
            t0 = time.perf_counter()
            direct = store.status()
            times["direct"].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            through_zarr = np.asarray(zarr.open_array(f"{store.url}/status", mode="r")[:])
            times["zarr"].append(time.perf_counter() - t0)
            if not np.array_equal(direct, through_zarr) or not np.array_equal(direct, codes):
                print("status of the chunk files differs from zarr's read", file=sys.stderr)
                sys.exit(1)
    a, b = min(times["direct"]), min(times["zarr"])
    print(f"status of {N_FRAMES:,} frames (written in {written:.1f} s): FrameStore.status {a:.2f} s, zarr's read "
          f"{b:.2f} s (best of 3, identical codes), zarr/direct ratio {b / a:.1f}x")


if __name__ == "__main__":
    main()
