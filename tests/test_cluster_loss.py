"""An existing dask cluster that loses every worker mid-run: the run stops with a message instead
of waiting forever, keeps the frames finished before, and a rerun on a new worker resumes; a
cancelled batch stops before its next frame."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.cache import DONE, FAILED, PENDING
from pipeline.config import load_config
from pipeline.errors import FrameError, PipelineError
from pipeline.executor import Executor, RunEnv, _batches
from pipeline.runner import Pipeline
from pipeline.stage import ArraySpec, FrameStage

distributed = pytest.importorskip("distributed")

IDS = [f"f{i:03d}" for i in range(12)]
ROOT = str(Path(__file__).resolve().parents[1])


def _frame(inputs, cfg):
    """Per-frame function, configured by the environment of the worker that runs it."""
    log = os.environ.get("LOSS_CALLS")
    if log:
        with open(log, "a") as fh:
            fh.write(f"{inputs.frame_id}\n")
    if inputs.frame_id in os.environ.get("LOSS_FAIL", "").split(","):
        raise ValueError("bad frame")
    if inputs.index >= int(os.environ.get("LOSS_BLOCK_FROM", "1000000")):
        time.sleep(120)  # the worker is killed meanwhile
    hold = os.environ.get("LOSS_HOLD")
    deadline = time.monotonic() + 60
    while hold and not os.path.exists(hold) and time.monotonic() < deadline:
        time.sleep(0.05)  # until the test lets frames go on
    return {"value": np.float64(inputs.index)}


STAGE = FrameStage("calibrate", (), ("split.seed",), lambda cfg: (ArraySpec("value", (), "float64", "-"),), _frame)


def _pipeline(tmp_path: Path, executor: Executor) -> Pipeline:
    cfg = load_config("synthetic", {}, environ={})
    env = RunEnv(cfg=cfg, cache_root=str(tmp_path / "cache"), dataset="fake", data_root=str(tmp_path))
    return Pipeline([STAGE], env, executor, progress=False, log=lambda m: None, frame_lister=lambda: list(IDS))


def _status(tmp_path: Path) -> np.ndarray:
    return _pipeline(tmp_path, Executor(1)).env.store("calibrate").status()


def _wait_for(cond, what: str, limit_s: float = 60.0) -> None:
    deadline = time.monotonic() + limit_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.1)


@pytest.fixture
def cluster():
    """A scheduler in this process and a way to start worker processes (killed at the end)."""
    procs = []
    with distributed.LocalCluster(n_workers=0, processes=True, host="127.0.0.1", protocol="tcp",
                                  dashboard_address=":0") as cl:
        def start_worker(**env):
            penv = {**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""),
                    "OMP_NUM_THREADS": "1", **env}
            proc = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", cl.scheduler_address,
                                     "--nthreads", "1", "--no-nanny", "--no-dashboard"],
                                    env=penv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            procs.append(proc)
            return proc

        try:
            yield cl.scheduler_address, start_worker
        finally:
            for proc in procs:
                if proc.poll() is None:
                    proc.kill()
                proc.wait(timeout=30)


def test_run_stops_when_every_worker_is_gone_and_a_rerun_resumes(tmp_path, cluster):
    address, start_worker = cluster
    first_calls, rerun_calls = tmp_path / "first.txt", tmp_path / "rerun.txt"
    worker = start_worker(LOSS_BLOCK_FROM="4", LOSS_CALLS=str(first_calls))
    outcome: dict = {}
    with Executor(scheduler=address, progress=False, no_worker_timeout_s=1.5) as ex:
        ex.check_cluster(str(tmp_path))
        pipe = _pipeline(tmp_path, ex)

        def run():
            try:
                outcome["reports"] = pipe.run("calibrate")
            except BaseException as exc:  # noqa: BLE001 - the test looks at it
                outcome["error"] = exc

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        # frames 0-3 finish (one of them in a batch that never comes back), frame 4 hangs
        _wait_for(lambda: first_calls.exists() and "f004" in first_calls.read_text().split(), "frame f004 to start")
        _wait_for(lambda: (_status(tmp_path)[:4] == DONE).all(), "frames 0-3 to be done")
        worker.send_signal(signal.SIGKILL)
        worker.wait(timeout=30)
        thread.join(timeout=60)  # 1.5 s without a worker, plus the checks' period; generous here
        assert not thread.is_alive(), "the run kept waiting for a worker"
    error = outcome.get("error")
    assert isinstance(error, PipelineError), outcome
    message = str(error)
    assert address in message and "no worker for 1.5 s" in message
    assert "finished frames are kept" in message and "run the same command again" in message
    status = _status(tmp_path)
    assert (status[:4] == DONE).all() and (status[4:] == PENDING).all(), status

    start_worker(LOSS_CALLS=str(rerun_calls))
    with Executor(scheduler=address, progress=False, no_worker_timeout_s=1.5) as ex:
        ex.check_cluster(str(tmp_path))
        report = _pipeline(tmp_path, ex).run("calibrate")[0]
    assert report.done == len(IDS) and report.processed == len(IDS) - 4
    assert sorted(rerun_calls.read_text().split()) == IDS[4:]
    assert (_status(tmp_path) == DONE).all()


def _batch_states(dask_worker) -> list[str]:
    """Run by client.run on the worker's event loop: the states of this test's batch tasks there."""
    return [ts.state for key, ts in dask_worker.state.tasks.items() if str(key).startswith("calibrate-")]


def test_a_cancelled_batch_stops_before_its_next_frame(tmp_path, cluster):
    """--strict stops at frame 0's failure; the next batch, running then, is cancelled: it
    finishes the frame it is on and computes no other (dask lets a running task run to its end)."""
    address, start_worker = cluster
    calls, release = tmp_path / "calls.txt", tmp_path / "release"
    start_worker(LOSS_CALLS=str(calls), LOSS_FAIL="f000", LOSS_HOLD=str(release))
    with Executor(scheduler=address, progress=False) as ex:
        ex.check_cluster(str(tmp_path))
        with pytest.raises(FrameError, match="1 frame"):
            _pipeline(tmp_path, ex).run("calibrate", strict=True)
        client = ex.client()
        # every batch on the worker cancelled (the one running included) before frames may go on
        _wait_for(lambda: all(s == "cancelled" for states in client.run(_batch_states).values() for s in states),
                  "the worker to cancel its batches")
        release.touch()
        # the worker's one thread runs this only once the cancelled batch has returned
        assert client.submit(int, "7", pure=False).result(timeout=60) == 7
    ran = calls.read_text().split()
    first, second = _batches([(i, f) for i, f in enumerate(IDS)], 1)[:2]  # 12 frames on one thread
    assert len(second) > 1  # the test needs a second frame in the cancelled batch
    assert ran in (["f000"], ["f000", second[0][1]]), ran
    status = _status(tmp_path)
    assert status[0] == FAILED and (status[1:] == PENDING).sum() >= len(IDS) - 2, status
    assert (status[second[0][0] + 1:] == PENDING).all(), status
