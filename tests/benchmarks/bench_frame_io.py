"""A frame's read and write through FrameStore (what every frame stage does per frame): the chunk
files read with the arrays opened once per process, and writes through arrays opened once,
against zarr's path for the same calls (the group and its arrays opened for every call, as until
2026-12-04). Both must read the same values, or the script exits with status 1.

The store has N_FRAMES frames of a ragged float32 array and a scalar, as the fake stages'; each way
is timed over FRAMES_TIMED frames, interleaved, best of REPEATS. Prints one line ending in the
ratio of zarr's path to FrameStore's for a read of both arrays and for a write.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from pipeline import cache  # noqa: E402
from pipeline.cache import FrameStore  # noqa: E402
from pipeline.stage import ArraySpec  # noqa: E402

N_FRAMES, FRAMES_TIMED, REPEATS = 20_000, 300, 3
SPECS = (ArraySpec("points", (64, 3), "float32", "m", fill=np.nan, ragged=True), ArraySpec("value", (), "float64", "-"))


def frame(i: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(i)
    return {"points": rng.normal(size=(int(rng.integers(1, 64)), 3)).astype(np.float32), "value": np.float64(i)}


def reads(store: FrameStore, frames: range, direct: bool) -> tuple[float, list]:
    """Seconds to read both arrays of ``frames``, and the values."""
    original = FrameStore._read_chunk_files
    if not direct:
        FrameStore._read_chunk_files = lambda self, name, index: None  # zarr's path
    try:
        t0 = time.perf_counter()
        values = [(store.read("points", i), store.read("value", i)) for i in frames]
        return time.perf_counter() - t0, values
    finally:
        FrameStore._read_chunk_files = original


def writes(store: FrameStore, frames: range, reuse: bool) -> float:
    """Seconds to write ``frames``; without ``reuse`` the opened arrays are forgotten before each."""
    data = [frame(i) for i in frames]
    t0 = time.perf_counter()
    for i, arrays in zip(frames, data):
        if not reuse:
            cache._WRITABLE.clear()
        store.write_frame(i, arrays, SPECS)
    return time.perf_counter() - t0


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        store = FrameStore(str(Path(tmp) / "stage.zarr"))
        store.create("bench", [f"{i:05d}" for i in range(N_FRAMES)], SPECS, {"points": (64, 3), "value": ()}, {})
        times = {"read direct": [], "read zarr": [], "write reuse": [], "write zarr": []}
        for rep in range(REPEATS):  # interleaved: the machine is shared and noisy
            start = 2 * rep * FRAMES_TIMED
            times["write reuse"].append(writes(store, range(start, start + FRAMES_TIMED), True))
            times["write zarr"].append(writes(store, range(start + FRAMES_TIMED, start + 2 * FRAMES_TIMED), False))
            frames = range(start, start + 2 * FRAMES_TIMED)
            t_direct, direct = reads(store, frames, True)
            t_zarr, through_zarr = reads(store, frames, False)
            times["read direct"].append(t_direct)
            times["read zarr"].append(t_zarr)
            for (p, v), (q, w) in zip(direct, through_zarr):
                if not (p.dtype == q.dtype and np.array_equal(p, q) and v.shape == w.shape and v == w):
                    print("a frame read from the chunk files differs from zarr's read", file=sys.stderr)
                    sys.exit(1)
    ms = {k: 1e3 * min(v) / (2 * FRAMES_TIMED if k.startswith("read") else FRAMES_TIMED) for k, v in times.items()}
    print(f"a frame of a {N_FRAMES:,}-frame output (2 arrays; best of {REPEATS}): read {ms['read direct']:.2f} ms "
          f"against zarr's path {ms['read zarr']:.2f} ms, write {ms['write reuse']:.2f} ms against "
          f"{ms['write zarr']:.2f} ms (identical values); zarr/FrameStore ratio read "
          f"{ms['read zarr'] / ms['read direct']:.1f}x, write {ms['write zarr'] / ms['write reuse']:.1f}x")


if __name__ == "__main__":
    main()
