"""calibrate + heatmaps + patches over the Astyx frames in ../shared/data: frames per second with
1 and 2 dask workers (goal: 2 workers at least 1.6x faster); best of REPEATS alternating runs
each. What a long run pays once per process is left out of both: the serial run's process has
imported the stages before timing, and the workers are started and import them too (0.2-0.4 s
each, 5-10% of these 141 frames' time with 2 workers). Skips when the data is absent."""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from pipeline.config import load_config  # noqa: E402
from pipeline.executor import Executor, RunEnv  # noqa: E402
from pipeline.runner import Pipeline  # noqa: E402
from stages import all_stages  # noqa: E402

REPEATS = 3
DATA = ROOT.parent / "shared" / "data" / "astyx_hires2019" / "dataset_astyx_hires2019"


def _import_stages() -> None:
    import stages.calibrate  # noqa: F401
    import stages.heatmaps  # noqa: F401
    import stages.patches  # noqa: F401


def fps(workers: int, cache: str) -> tuple[float, int]:
    env = RunEnv(load_config("astyx", environ={}), cache, "astyx", str(DATA))
    with Executor(workers, progress=False) as ex:
        pipe = Pipeline(all_stages(), env, ex, progress=False, log=lambda m: None)
        n = len(pipe.frame_ids())
        if workers > 1:  # start the cluster and import the stages on its workers before timing: a
            ex.client().run(_import_stages)  # long run amortises it
        t0 = time.perf_counter()
        pipe.run("heatmaps")
        pipe.run("patches")
        return n / (time.perf_counter() - t0), n


def main() -> None:
    if not DATA.is_dir():
        print("stages: skipped (../shared/data/astyx_hires2019 absent)")
        return
    best = {1: 0.0, 2: 0.0}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(REPEATS):  # alternate, keep the best of each: the machine is shared and noisy
            for workers in (1, 2):
                rate, n = fps(workers, f"{tmp}/{workers}-{rep}")
                best[workers] = max(best[workers], rate)
    one, two = best[1], best[2]
    print(f"calibrate+heatmaps+patches, {n} Astyx frames: 1 worker {one:.2f} frames/s, "
          f"2 workers {two:.2f} frames/s, speed-up {two / one:.2f}x (goal 1.6x)")


if __name__ == "__main__":
    main()
