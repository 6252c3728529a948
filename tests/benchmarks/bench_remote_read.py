"""A frame's read on a remote cache (through zarr's fsspec store), each request to
the store taking LATENCY_S as an object store's does (S3 within a region: about 10-30 ms), against
the sequence read until 2026-12-07: the array's ``zarr.json``, its chunk, the row count's
``zarr.json``, its chunk, one after the other. The values read both ways must be the same, or the
script exits with status 1.

The store holds N_FRAMES frames of a ragged float32 array and a scalar, as the fake stages'; a read
of both arrays of FRAMES_TIMED frames is timed each way, interleaved, best of REPEATS: both at once
(FrameStore.read_many, as a frame stage reads a frame's arrays after its first frame), each with
FrameStore.read (two round trips each), and the old sequence. Prints one line with the requests
per frame each way and the ratios of the old sequence's time to the new ways'.

A second line: the output's status read whole (``FrameStore.status``) from its snapshot, against
its N_FRAMES chunks read as until 2026-12-07 (a request each), best of REPEATS; a third the scalar
array read whole from its column snapshot (pipeline.snapshots; kept by the read before, timed
apart) against its chunks; a fourth the same after each of REPEATS runs that wrote RUN_FRAMES
frames (untimed), the column brought up to date from those frames' chunks, against its chunks.
The same values both ways or exit status 1.
"""

from __future__ import annotations

import sys
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import fsspec
import numpy as np
from fsspec.implementations.memory import MemoryFileSystem

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from pipeline.cache import FrameStore  # noqa: E402
from pipeline.stage import ArraySpec  # noqa: E402

N_FRAMES, FRAMES_TIMED, REPEATS, LATENCY_S, RUN_FRAMES = 200, 40, 3, 0.02, 5
SPECS = (ArraySpec("points", (64, 3), "float32", "m", fill=np.nan, ragged=True), ArraySpec("value", (), "float64", "-"))
PROTOCOL = "latencymem"


class LatencyFileSystem(MemoryFileSystem):
    """fsspec's memory filesystem, each request (a read, a listing, a size) taking :data:`latency`
    seconds and counted in :data:`requests`; the writes take none (the store is filled first)."""

    protocol = PROTOCOL
    latency = 0.0
    requests = 0
    _lock = threading.Lock()

    @classmethod
    def _strip_protocol(cls, path):
        if isinstance(path, str) and path.startswith(f"{PROTOCOL}://"):
            path = path[len(PROTOCOL) + 3:]
        return super()._strip_protocol(path)

    def _request(self) -> None:
        with self._lock:
            type(self).requests += 1
        time.sleep(self.latency)

    def cat_file(self, path, start=None, end=None, **kwargs):
        self._request()
        return super().cat_file(path, start, end, **kwargs)

    def info(self, path, **kwargs):
        self._request()
        return super().info(path, **kwargs)

    def ls(self, path, detail=True, **kwargs):
        self._request()
        return super().ls(path, detail, **kwargs)


def sequential_read(store: FrameStore, name: str, index: int) -> np.ndarray:
    """FrameStore.read through zarr as it was until 2026-12-07: four requests one after the other
    for a ragged array (its zarr.json, its chunk, its row count's zarr.json and chunk)."""
    value = store._checked(store._array(name), index)
    counts = store._array(f"{name}_count", missing_ok=True)
    return value if counts is None else value[: int(store._checked(counts, index))]


def frame_read(store: FrameStore, name: str, index: int) -> np.ndarray:
    """What a frame stage's frame after its first reads (FrameInputs.prefetch): both arrays in one
    FrameStore.read_many, memoised for the second name."""
    key = (id(store), index)
    if key not in _FRAMES:
        _FRAMES.clear()
        _FRAMES[key] = store.read_many(["points", "value"], index)
    return _FRAMES[key][name]


_FRAMES: dict[tuple[int, int], dict] = {}


def reads(store: FrameStore, frames: range, read) -> tuple[float, int, list]:
    """Seconds and requests to read both arrays of ``frames`` with ``read``, and the values."""
    LatencyFileSystem.requests = 0
    t0 = time.perf_counter()
    values = [(read(store, "points", i), read(store, "value", i)) for i in frames]
    return time.perf_counter() - t0, LatencyFileSystem.requests, values


def whole_reads(ways: dict[str, Callable[[], np.ndarray]], what: str,
                before: Callable[[int], None] | None = None) -> tuple[dict[str, float], dict[str, int]]:
    """Best seconds of REPEATS and requests of each of two ``ways`` of reading ``what`` whole, the
    snapshot's ('snapshot') and the chunks' ('chunks', as until 2026-12-07); exits with status 1
    where the two differ. ``before(repeat)``, untimed, before each repeat's reads."""
    best = {way: np.inf for way in ways}
    requests = {}
    for rep in range(REPEATS):
        if before is not None:
            before(rep)
        got = {}
        for way, read in ways.items():
            LatencyFileSystem.requests = 0
            t0 = time.perf_counter()
            got[way] = read()
            best[way] = min(best[way], time.perf_counter() - t0)
            requests[way] = LatencyFileSystem.requests
        if not np.array_equal(got["snapshot"], got["chunks"]):
            print(f"{what} read from its snapshot differs from its chunks'", file=sys.stderr)
            sys.exit(1)
    return best, requests


def whole_line(what: str, seconds: dict[str, float], requests: dict[str, int], note: str = "") -> str:
    """The benchmark's line for a whole read of ``what`` (:func:`whole_reads`)."""
    return (f"{what} read whole on a remote cache, {1e3 * LATENCY_S:.0f} ms a request (best of {REPEATS}): from its "
            f"snapshot {1e3 * seconds['snapshot']:.0f} ms ({requests['snapshot']} requests{note}), from its chunks as "
            f"until 2026-12-07 {1e3 * seconds['chunks']:.0f} ms ({requests['chunks']}; the same values); old/new ratio "
            f"{seconds['chunks'] / seconds['snapshot']:.1f}x")


def main() -> None:
    fsspec.register_implementation(PROTOCOL, LatencyFileSystem, clobber=True)
    root = f"bench-{uuid.uuid4().hex[:8]}"
    store = FrameStore(f"{PROTOCOL}://{root}/stage.zarr")
    store.create("bench", [f"{i:05d}" for i in range(N_FRAMES)], SPECS, {"points": (64, 3), "value": ()}, {})
    rng = np.random.default_rng(0)
    for i in range(N_FRAMES):
        store.write_frame(i, {"points": rng.normal(size=(int(rng.integers(1, 64)), 3)).astype(np.float32),
                              "value": np.float64(i)}, SPECS)
    LatencyFileSystem.latency = LATENCY_S
    ways = {"frame": frame_read, "read": FrameStore.read, "until 2026-12-07": sequential_read}
    times: dict[str, list[float]] = {way: [] for way in ways}
    requests: dict[str, int] = {}
    try:
        for rep in range(REPEATS):  # interleaved: the machine is shared and noisy
            frames = range(rep * FRAMES_TIMED, (rep + 1) * FRAMES_TIMED)
            got = {}
            for way, read in ways.items():
                seconds, requests[way], got[way] = reads(store, frames, read)
                times[way].append(seconds)
            for way in ("frame", "read"):
                for (p, v), (q, w) in zip(got[way], got["until 2026-12-07"]):
                    if not (p.dtype == q.dtype and np.array_equal(p, q) and v.shape == w.shape and v == w):
                        print(f"a frame read by {way} differs from the old sequence's read", file=sys.stderr)
                        sys.exit(1)
        store.save_status_snapshot(np.asarray(store._array("status")[:]))
        status = whole_reads({"snapshot": store.status, "chunks": lambda: np.asarray(store._array("status")[:])},
                             "the status")
        LatencyFileSystem.requests = 0
        t0 = time.perf_counter()
        store.array("value")[:]  # reads the chunks and keeps the column snapshot
        first = (time.perf_counter() - t0, LatencyFileSystem.requests)
        column = whole_reads({"snapshot": lambda: np.asarray(store.array("value")[:]),
                              "chunks": lambda: np.asarray(store._array("value")[:])}, "a scalar array")

        def a_run(rep: int) -> None:
            """What a run of the stage's frames leaves: RUN_FRAMES frames written again, and a
            status snapshot that succeeds the one it read (the column was read under that one);
            untimed, without latency."""
            LatencyFileSystem.latency = 0.0
            status, snapshot = store.status_and_snapshot()
            frames = np.arange(RUN_FRAMES) * (N_FRAMES // RUN_FRAMES) + rep
            for i in frames:
                store.write_frame(int(i), {"points": np.zeros((1, 3), np.float32), "value": np.float64(-rep)}, SPECS)
            store.save_status_snapshot(status, after=snapshot, changed=np.isin(np.arange(N_FRAMES), frames))
            LatencyFileSystem.latency = LATENCY_S

        later = whole_reads({"snapshot": lambda: np.asarray(store.array("value")[:]),
                             "chunks": lambda: np.asarray(store._array("value")[:])}, "a scalar array after a run",
                            before=a_run)
    finally:
        LatencyFileSystem.latency = 0.0
        LatencyFileSystem().rm(f"/{root}", recursive=True)
    ms = {way: 1e3 * min(t) / FRAMES_TIMED for way, t in times.items()}
    per = {way: n / FRAMES_TIMED for way, n in requests.items()}
    old = ms["until 2026-12-07"]
    print(f"a frame's 2 arrays (one ragged) read on a remote cache, {1e3 * LATENCY_S:.0f} ms a request (best of "
          f"{REPEATS}): at once as a frame stage reads them {ms['frame']:.0f} ms ({per['frame']:.0f} requests), "
          f"each with FrameStore.read {ms['read']:.0f} ms ({per['read']:.0f}), one request after the other as until "
          f"2026-12-07 {old:.0f} ms ({per['until 2026-12-07']:.0f}; identical values); old/new ratio "
          f"{old / ms['frame']:.2f}x at once, {old / ms['read']:.2f}x each")
    print(whole_line(f"the status of {N_FRAMES} frames", *status))
    print(whole_line(f"a scalar array of {N_FRAMES} frames", *column,
                     f"; the read before, which keeps it, {1e3 * first[0]:.0f} ms, {first[1]} requests"))
    print(whole_line(f"after a run that wrote {RUN_FRAMES} of its frames, the same array", *later,
                     ", bringing it up to date from the frames the run wrote"))

if __name__ == "__main__":
    main()
