"""What the train stage holds per training row of RSS-Net and PlaceNet (PlaceNet has 2,048 rows a
frame: 49 million at 24,000 frames): the memory of one epoch's row order and of the PlaceNet
counts' baseline, on a generated ``place_count`` array in the patches stage's layout (N_FRAMES
frames of 1,500 to 2,048 rows, a chunk per frame).

The stage now keeps row sets as ranges, reads the counts per batch window like the features, and
makes an epoch's order one window at a time (``epoch_windows``). The reference is the same work
done with an array per row, as the stage did until 2026-12-05: the counts read into memory
through one index of every row, the order of every row made at once
(``tests.test_training.reference_epoch_order``) and the baseline computed over arrays. Each runs
in a child process that reports its peak resident memory above what it held before; both must
give the same order and the same baseline. Prints one line ending in the ratio of the
reference's memory to the stage's.
"""

from __future__ import annotations

import hashlib
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

N_FRAMES = 8_000
CAPACITY = 2_048
WINDOW = 4_096 * 16
"""PlaceNet's batch (placement.batch_size) times training.WINDOW_BATCHES."""


def build(path: Path) -> None:
    """A FrameStore holding ``place_count`` as the patches stage writes it."""
    from pipeline.cache import FrameStore
    from pipeline.stage import ArraySpec

    specs = (ArraySpec("place_count", (CAPACITY,), "float32", "real radar points per candidate", fill=np.nan,
                       ragged=True),)
    store = FrameStore(str(path))
    store.create("bench", [f"{i:06d}" for i in range(N_FRAMES)], specs, {"place_count": (CAPACITY,)}, {})
    rng = np.random.default_rng(0)
    for i in range(N_FRAMES):
        rows = int(rng.integers(1500, CAPACITY + 1))
        store.write_frame(i, {"place_count": rng.poisson(0.05, rows).astype(np.float32)}, specs)


def child(path: str, how: str) -> None:
    """One way of holding the rows: prints its peak memory above the start, the order's digest and
    the baseline."""
    from pipeline.cache import FrameStore, RaggedRows
    from pipeline.net_baselines import placenet_baseline
    from pipeline.rows import epoch_windows
    from tests.test_training import reference_epoch_order  # the order of every row at once, as before

    store = FrameStore(path)
    per_frame = np.asarray(store.array("place_count_count")[:])
    train, test = np.arange(0, N_FRAMES, 2), np.arange(1, N_FRAMES, 2)  # the stage: one view per split
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    train_rows = RaggedRows(store.array("place_count"), per_frame, train)
    test_rows = RaggedRows(store.array("place_count"), per_frame, test)
    digest = hashlib.sha256()
    if how == "rows":  # until 2026-12-05
        counts = train_rows[np.arange(len(train_rows))]
        test_counts = test_rows[np.arange(len(test_rows))]
        order = reference_epoch_order(np.arange(len(counts)), CAPACITY, WINDOW, np.random.default_rng(7))
        digest.update(order.tobytes())
        both = np.concatenate([counts, test_counts])
        base = placenet_baseline(both, np.arange(len(counts)), np.arange(len(counts), len(both)))
    else:
        for window in epoch_windows(range(len(train_rows)), CAPACITY, WINDOW, np.random.default_rng(7)):
            digest.update(window.tobytes())
        base = placenet_baseline(train_rows, range(len(train_rows)), range(len(test_rows)), test_rows)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"mb": (peak - before) / 1024, "s": time.perf_counter() - t0, "rows": len(train_rows),
                      "order": digest.hexdigest()[:16], "nll": base["nll"]}))


def measure(path: Path, how: str) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", str(path), how], capture_output=True, text=True,
                         check=True, cwd=ROOT)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "patches.zarr"
        build(path)
        rows, windows = measure(path, "rows"), measure(path, "windows")
    if rows["order"] != windows["order"] or not np.isclose(rows["nll"], windows["nll"], rtol=1e-12):
        sys.exit(f"bench_train_rows.py: the two ways differ: {rows} against {windows}")
    print(f"train rows, {N_FRAMES} frames ({windows['rows']:,} PlaceNet training rows), an epoch's order and the "
          f"counts' baseline: peak +{windows['mb']:.0f} MB in {windows['s']:.1f} s (ranges, windows) against "
          f"+{rows['mb']:.0f} MB in {rows['s']:.1f} s (an array per row), the same order and baseline: "
          f"{rows['mb'] / max(windows['mb'], 1.0):.1f}x less memory")


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--child":
        child(sys.argv[2], sys.argv[3])
    else:
        main()
