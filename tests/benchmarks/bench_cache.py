"""Re-running a finished stage over 200 frames: no per-frame work, time to return (goal < 2 s).

Prints one line ending in the ratio of the re-run time to the first run's.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from pipeline.config import load_config  # noqa: E402
from pipeline.executor import Executor, RunEnv  # noqa: E402
from pipeline.runner import Pipeline  # noqa: E402
from tests import fake_stages  # noqa: E402


def main() -> None:
    ids = [f"f{i:03d}" for i in range(200)]
    with tempfile.TemporaryDirectory() as tmp:
        calls = Path(tmp) / "calls.txt"
        os.environ[fake_stages.CALLS_FILE_ENV] = str(calls)
        env = RunEnv(load_config("synthetic", environ={}), str(Path(tmp) / "cache"), "bench", tmp)

        def pipe() -> Pipeline:
            return Pipeline(fake_stages.STAGES, env, Executor(1, progress=False), progress=False,
                            log=lambda m: None, frame_lister=lambda: ids)

        t0 = time.perf_counter()
        pipe().run("heatmaps")
        first = time.perf_counter() - t0
        calls.unlink()
        t0 = time.perf_counter()
        pipe().run("heatmaps")
        rerun = time.perf_counter() - t0
        work = len(calls.read_text().splitlines()) if calls.exists() else 0
    print(f"re-run of 2 finished stages over 200 frames: first run {first:.2f} s, re-run {rerun:.3f} s "
          f"({work} per-frame calls; goal < 2 s), re-run/first ratio {rerun / first:.3f}")


if __name__ == "__main__":
    main()
