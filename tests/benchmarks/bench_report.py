"""evaluate's report over many frames (after `make demo`): the memory and time of its summary
(stages.evaluate.summarise: the metrics aggregated, the pooled points' distribution distances,
the physics checks) on evaluate-frames outputs of N_SMALL and N_LARGE frames made by linking the
demo's finished chunks in turn (nothing is copied; the demo's cache is only read). Each summary
runs in a child process that reports its peak resident memory above what it held before.

At N_LARGE the pooled rows pass eval.pooled_rows_max, so the summary works from a random sample;
it runs once more with no limit (every row pooled, as before the limit), the reference. The linked
frames repeat the demo's test frames, so the pooled points have the distribution of the demo
report's: the script prints how far the sample's distances are from that report's exact ones.
Prints one line ending in the ratio of the memory without the limit to that with it, at N_LARGE.
Skips without the demo.
"""

from __future__ import annotations

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

from pipeline.cache import DONE, FrameStore  # noqa: E402
from pipeline.config import load_config  # noqa: E402

N_SMALL, N_LARGE = 2_000, 20_000
NO_LIMIT = 10**12
DEMO = ROOT / "cache" / "synthetic"
SOURCE = DEMO / "evaluate-frames.zarr"
REPORT = DEMO / "evaluate" / "report.json"


def build(path: Path, n_frames: int) -> None:
    """An evaluate-frames output of ``n_frames`` frames whose chunks link to the demo's finished ones
    in turn."""
    from stages.evaluate import FRAMES

    cfg = load_config("synthetic", environ={})
    specs = FRAMES.outputs(cfg)
    done = np.flatnonzero(FrameStore(str(SOURCE)).status() == DONE)
    store = FrameStore(str(path))
    store.create("bench", [f"{i:06d}" for i in range(n_frames)], specs, {s.name: s.frame_shape(cfg) for s in specs}, {})
    for name in [s.name for s in specs] + [f"{s.name}_count" for s in specs if s.ragged] + ["status"]:
        for i in range(n_frames):
            src = SOURCE / name / "c" / str(int(done[i % len(done)]))
            target = path / name / "c" / str(i)
            if src.is_file():  # one axis: c/<frame>
                target.parent.mkdir(parents=True, exist_ok=True)
                target.symlink_to(src)
                continue
            for chunk in (c for c in src.rglob("*") if c.is_file()):  # c/<frame>/0/...
                (target / chunk.relative_to(src)).parent.mkdir(parents=True, exist_ok=True)
                (target / chunk.relative_to(src)).symlink_to(chunk)


def child(path: str, rows_max: int) -> None:
    """Summarise the output at ``path``; print JSON: peak MB above the start, seconds, distances."""
    from stages.evaluate import summarise

    store = FrameStore(path)
    frames = np.flatnonzero(store.status() == DONE)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    summary = summarise(store, frames, 0.0, True, rows_max, progress=False)
    seconds = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"mb": (peak - before) / 1024, "s": seconds, "distances": summary.distances,
                      "sampled": summary.sampled}))


def measure(path: Path, rows_max: int) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", str(path), str(rows_max)], capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    if not (SOURCE.exists() and REPORT.exists()):
        print("report: skipped (run `make demo` first: it needs the demo's evaluate-frames output and report)")
        return
    rows_max = load_config("synthetic", environ={}).eval.pooled_rows_max
    with tempfile.TemporaryDirectory() as tmp:
        build(Path(tmp) / "small.zarr", N_SMALL)
        small = measure(Path(tmp) / "small.zarr", rows_max)
        build(Path(tmp) / "large.zarr", N_LARGE)
        large, unlimited = measure(Path(tmp) / "large.zarr", rows_max), measure(Path(tmp) / "large.zarr", NO_LIMIT)
    exact = json.loads(REPORT.read_text())["distribution_distances"]
    errors = np.array([abs(d[c] - exact[m][c]) / abs(exact[m][c]) for m, d in large["distances"].items()
                       for c in d if exact[m][c]])
    print(f"report summary over {N_SMALL:,} / {N_LARGE:,} frames (the demo's linked in turn): "
          f"{small['mb']:.0f} MB, {small['s']:.1f} s / {large['mb']:.0f} MB, {large['s']:.1f} s "
          f"({large['sampled'] or 'nothing sampled'}; its distances off the demo report's exact ones by "
          f"{100 * np.median(errors):.1f}% median, {100 * errors.max():.1f}% at most); every row pooled at "
          f"{N_LARGE:,}: {unlimited['mb']:.0f} MB, {unlimited['s']:.1f} s; memory ratio "
          f"{unlimited['mb'] / max(large['mb'], 1e-9):.2f}x")


if __name__ == "__main__":
    if sys.argv[1:2] == ["--child"]:
        child(sys.argv[2], int(sys.argv[3]))
    else:
        main()
