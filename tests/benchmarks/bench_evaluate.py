"""evaluate on the demo's test split (after `make demo`): the per-frame part (evaluate-frames: every
method's generation and metrics, the physics checks) with 1 and 2 dask workers, best of REPEATS
alternating runs each, and the report built from it. The demo's finished stages are read in
place (linked into a temporary cache); nothing of the demo's cache is written. Skips without it."""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from pipeline.config import load_config  # noqa: E402
from pipeline.executor import Executor, RunEnv  # noqa: E402
from pipeline.runner import Pipeline  # noqa: E402
from stages import all_stages  # noqa: E402

REPEATS = 2
DEMO = ROOT / "cache" / "synthetic"
READ = ("calibrate.zarr", "heatmaps.zarr", "patches.zarr", "synthesize.zarr", "train")
STAGES_READ = ("calibrate", "heatmaps", "patches", "synthesize", "train")


def _stale_stages() -> list[str]:
    """The demo's stages that this code would make again (another stage version or setting since the
    demo ran): linked into the temporary cache they would be rebuilt there, through the links."""
    env = RunEnv(load_config("synthetic", environ={}), str(DEMO.parent), "synthetic", str(DEMO / "world"))
    with Executor(1, progress=False) as ex:
        pipe = Pipeline(all_stages(), env, ex, progress=False, log=lambda m: None)
        return [name for name in STAGES_READ if not pipe.is_current(name)]


def _import_stages() -> None:
    import stages.evaluate  # noqa: F401  (torch, the nets' modules)


def run(workers: int, cache: Path) -> tuple[float, float, int]:
    """(frames/s of evaluate-frames, seconds of the report, frames) of one forced evaluate."""
    (cache / "synthetic").mkdir(parents=True)
    for name in READ:
        (cache / "synthetic" / name).symlink_to(DEMO / name)
    env = RunEnv(load_config("synthetic", environ={}), str(cache), "synthetic", str(DEMO / "world"))
    with Executor(workers, progress=False) as ex:
        pipe = Pipeline(all_stages(), env, ex, progress=False, log=lambda m: None)
        if workers > 1:  # start the cluster and import the stages on its workers before timing (about 5 s:
            ex.client().run(_import_stages)  # a long run amortises it)
        reports = {r.stage: r for r in pipe.run("evaluate", force=True)}
    part = reports["evaluate-frames"]
    return part.processed / part.seconds, reports["evaluate"].seconds, part.processed


def main() -> None:
    if not all((DEMO / name).exists() for name in READ):
        print("evaluate: skipped (run `make demo` first: it needs the demo's trained networks and synthesized frames)")
        return
    stale = _stale_stages()
    if stale:
        print(f"evaluate: skipped (the demo's {', '.join(stale)} would be made again by this code: run `make demo` "
              "first to bring its cache up to date)")
        return
    best = {1: (0.0, float("inf")), 2: (0.0, float("inf"))}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(REPEATS):  # alternate, keep the best of each: the machine is shared and noisy
            for workers in (1, 2):
                rate, report_s, n = run(workers, Path(tmp) / f"{workers}-{rep}")
                best[workers] = (max(best[workers][0], rate), min(best[workers][1], report_s))
    (one, report_one), (two, report_two) = best[1], best[2]
    print(f"evaluate, {n} demo test frames: per-frame part 1 worker {one:.2f} frames/s, 2 workers {two:.2f} "
          f"frames/s, speed-up {two / one:.2f}x; report from it {min(report_one, report_two):.1f} s")


if __name__ == "__main__":
    main()
