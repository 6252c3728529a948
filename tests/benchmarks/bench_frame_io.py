"""A frame's read and write through FrameStore (what every frame stage does per frame): the chunk
files read and written directly, with the arrays opened once per process, against zarr's path
for the same calls (the group and its arrays opened for every call, as until 2026-12-04). The
values read both ways, and the chunk files written both ways, must be the same, or the script
exits with status 1.

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

from pipeline import zarr_io  # noqa: E402
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


def writes(store: FrameStore, frames: range, direct: bool) -> float:
    """Seconds to write ``frames``; without ``direct`` through zarr, the arrays opened for each."""
    data = [frame(i) for i in frames]
    original = FrameStore._write_chunk_files
    if not direct:
        FrameStore._write_chunk_files = lambda self, *args: False  # zarr's path
    try:
        t0 = time.perf_counter()
        for i, arrays in zip(frames, data):
            if not direct:
                zarr_io._KEPT.clear()
            store.write_frame(i, arrays, SPECS)
        return time.perf_counter() - t0
    finally:
        FrameStore._write_chunk_files = original


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        store = FrameStore(str(Path(tmp) / "stage.zarr"))
        store.create("bench", [f"{i:05d}" for i in range(N_FRAMES)], SPECS, {"points": (64, 3), "value": ()}, {})
        times = {"read direct": [], "read zarr": [], "write direct": [], "write zarr": []}
        for rep in range(REPEATS):  # interleaved: the machine is shared and noisy
            start = 2 * rep * FRAMES_TIMED
            times["write direct"].append(writes(store, range(start, start + FRAMES_TIMED), True))
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
        for i in range(3):  # the same frame written both ways: the same files
            written = []
            for direct in (True, False):
                writes(store, range(i, i + 1), direct)
                tops = [t for t in Path(store.url).glob(f"*/c/{i}") if t.parts[-3] != "frame_ids"]  # c/<frame>[/0/...]
                files = [t for t in tops if t.is_file()] + [f for t in tops if t.is_dir() for f in t.rglob("*")]
                written.append({f.relative_to(store.url).as_posix(): f.read_bytes() for f in files if f.is_file()})
                if not direct and sorted(written[-1]) != ["points/c/%d/0/0" % i, "points_count/c/%d" % i,
                                                          "reason/c/%d" % i, "status/c/%d" % i, "value/c/%d" % i]:
                    print(f"frame {i}'s chunk files are not the five expected: {sorted(written[-1])}", file=sys.stderr)
                    sys.exit(1)
            if written[0] != written[1] or not written[0]:
                print("a frame's chunk files written directly differ from zarr's", file=sys.stderr)
                sys.exit(1)
    ms = {k: 1e3 * min(v) / (2 * FRAMES_TIMED if k.startswith("read") else FRAMES_TIMED) for k, v in times.items()}
    print(f"a frame of a {N_FRAMES:,}-frame output (2 arrays; best of {REPEATS}): read {ms['read direct']:.2f} ms "
          f"against zarr's path {ms['read zarr']:.2f} ms, write {ms['write direct']:.2f} ms against "
          f"{ms['write zarr']:.2f} ms (identical values and files); zarr/FrameStore ratio read "
          f"{ms['read zarr'] / ms['read direct']:.1f}x, write {ms['write zarr'] / ms['write direct']:.1f}x")


if __name__ == "__main__":
    main()
