"""Reliability: SIGKILL at random moments then resume (equal to a clean run, no frame lost or
redone), a kill in the middle of a frame's write, concurrent runs and stale locks, disk full and
read-only caches (simulated inside FrameStore.write_frame, and real ones in a user namespace).

The harness lives in tests/soak.py (its docstring defines the checked properties); `make soak`
runs the long version. Subprocesses run `python -m tests.soak fake-cli ...`: the real `pipeline`
CLI driving the stages of tests/fake_stages.py.
"""

from __future__ import annotations

import asyncio
import errno
import os
import pickle
import random
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest
import zarr

from pipeline.cache import DONE, FAILED, PENDING, FrameStore, frame_store
from pipeline.config import load_config
from pipeline.errors import CacheError
from pipeline.executor import Executor, RunEnv
from pipeline.runner import Pipeline
from pipeline.zarr_io import gather_all
from tests import fake_stages, soak

IDS = [f"f{i:03d}" for i in range(8)]


def test_sigkill_at_random_moments_then_resume_equals_clean_run(tmp_path):
    """3 seeded SIGKILLs of `pipeline run train` (fake stages, serial): properties 1-6 of soak.py."""
    result = soak.soak_fake(tmp_path, workers=1, kills=3, rng=random.Random(7), n_frames=8, sleep_s=0.12)
    assert result.problems == []
    assert result.kills >= 2 and result.attempts == result.kills + 1
    assert result.compared == 3  # calibrate.zarr, heatmaps.zarr, train/total.txt


def test_kill_between_array_writes_leaves_frame_pending(tmp_path):
    """SIGKILL right after a frame's first array is written: status stays PENDING, the next run
    redoes exactly that frame and the rest, and the result equals a clean run."""
    result = soak.soak_mid_write(tmp_path, frames=(3,), n_frames=6)
    assert result.problems == []
    events = soak.read_events(tmp_path / "killed.log")
    assert ("partial", "calibrate", "3", 0) in events  # the fault fired after the first array
    calib_starts = [int(i) for e, s, i, _ in events if e == "start" and s == "calibrate"]
    assert sorted(calib_starts) == [0, 1, 2, 3, 3, 4, 5]  # frame 3 twice: killed, then redone once


def test_train_weights_after_kills_equal_uninterrupted_run(tmp_path):
    """pipeline.training killed once mid-run, resumed: every tensor of every checkpoint (weights,
    optimizer, RNG) equals an uninterrupted run's on CPU with the same seed."""
    result = soak.soak_train_direct(tmp_path, kills=1, rng=random.Random(3), epochs=3, scale=1, startup_s=2.0)
    assert result.problems == [] and result.compared == 4
    assert result.kills == 1 and result.attempts == 2


def _start(cmd, env):
    return subprocess.Popen(cmd, env=env, cwd=soak.ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True, text=True)


def _wait_for(predicate, timeout_s=30.0):
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def _in_process_reference(tmp_path: Path, data: Path, n_frames: int) -> Pipeline:
    cfg = load_config("synthetic", {}, environ={})
    env = RunEnv(cfg=cfg, cache_root=str(tmp_path / "ref"), dataset="synthetic", data_root=str(data))
    pipe = Pipeline(fake_stages.STAGES, env, Executor(1), progress=False, log=lambda m: None,
                    frame_lister=lambda: [f"f{i:03d}" for i in range(n_frames)])
    pipe.run("heatmaps")
    return pipe


def test_second_concurrent_run_stops_or_waits_and_cache_stays_consistent(tmp_path):
    n = 8
    data = tmp_path / "data"
    data.mkdir()
    log = tmp_path / "calls.log"
    env = soak.subprocess_env(SOAK_N_FRAMES=str(n), SOAK_FRAME_SLEEP="0.3", SOAK_CALL_LOG=str(log))
    cmd = soak.python_cmd(*soak.fake_run_args(tmp_path / "cache", data, 1, "heatmaps"))
    first = _start(cmd, env)
    try:
        _wait_for(lambda: log.exists() and "start calibrate" in log.read_text())
        second = subprocess.run(cmd, env=env, cwd=soak.ROOT, capture_output=True, text=True, timeout=60)
        waiter = _start(cmd + ["--wait", "120"], env)
        waiter_out = waiter.communicate(timeout=120)
        first_out = first.communicate(timeout=120)
    finally:
        for p in (first,):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
    assert second.returncode == 2
    lines = second.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in second.stderr
    assert lines[0].startswith("error: stage 'calibrate' of dataset 'synthetic' is being written by another run")
    assert f"pid {first.pid} " in lines[0] and "--wait" in lines[0]
    assert first.returncode == 0, first_out[1]
    assert waiter.returncode == 0, waiter_out[1]
    # Every frame of every stage computed exactly once over the three runs: the waiter reused all.
    starts = [(s, i) for e, s, i, _ in soak.read_events(log) if e == "start"]
    assert sorted(starts) == sorted((s, str(i)) for s in ("calibrate", "heatmaps") for i in range(n))
    assert "processed 0 frame(s)" in waiter_out[1]
    ref = _in_process_reference(tmp_path, data, n)
    for stage in ("calibrate", "heatmaps"):
        assert soak.compare_zarr_groups(str(tmp_path / "cache" / "synthetic" / f"{stage}.zarr"),
                                        ref.env.store(stage).url) == []


def test_lock_of_sigkilled_run_is_recovered(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    env = soak.subprocess_env(SOAK_N_FRAMES="8", SOAK_FRAME_SLEEP="0.5")
    cmd = soak.python_cmd(*soak.fake_run_args(tmp_path / "cache", data, 1, "heatmaps"))
    lock = tmp_path / "cache" / "synthetic" / "locks" / "calibrate.lock"
    proc = _start(cmd, env)
    _wait_for(lambda: lock.exists() and lock.stat().st_size > 0)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert f'"pid": {proc.pid}' in lock.read_text()  # left behind by the dead run
    rerun = subprocess.run(cmd, env=soak.subprocess_env(SOAK_N_FRAMES="8"), cwd=soak.ROOT, capture_output=True, text=True, timeout=60)
    assert rerun.returncode == 0, rerun.stderr
    assert not lock.exists()
    assert (frame_store(str(tmp_path / "cache"), "synthetic", "heatmaps").status() == DONE).all()


def test_many_runs_recovering_one_stale_lock_never_overlap(tmp_path):
    """Five processes start at the same instant on a stale lock: they hold it one at a time."""
    lock, log = tmp_path / "locks" / "x.lock", tmp_path / "intervals.txt"
    lock.parent.mkdir()
    lock.write_text('{"pid": 999999999, "host": "%s", "started": 0}' % os.uname().nodename)
    start_at = time.time() + 2.0
    procs = [_start(soak.python_cmd("lock-holder", str(lock), str(log), "0.15", f"{start_at:.3f}"),
                    soak.subprocess_env()) for _ in range(5)]
    errs = [p.communicate(timeout=60)[1] for p in procs]
    assert [p.returncode for p in procs] == [0] * 5, errs
    intervals = sorted(tuple(map(float, line.split()[:2])) for line in log.read_text().splitlines())
    assert len(intervals) == 5
    assert all(b[0] >= a[1] for a, b in zip(intervals, intervals[1:])), intervals


# ---------------------------------------------------------------- disk full, read-only cache


def _fault_after_first_array(monkeypatch, stage: str, index: int, code: int) -> None:
    """Make writes of frame ``index`` of ``stage`` (through zarr, or a chunk file written directly)
    fail with OSError(code) after one array."""
    from pipeline import cache

    original_write, original_setitem, original_put = FrameStore.write_frame, zarr.AsyncArray.setitem, cache.put_chunk
    state: list = []

    def write_frame(self, i, arrays, specs, run=""):
        state[:] = [self.url.endswith(f"/{stage}.zarr") and i == index, 0]
        try:
            original_write(self, i, arrays, specs, run)
        finally:
            state.clear()

    def fail_after_one() -> None:
        if state and state[0] and state[1] >= 1:
            raise OSError(code, os.strerror(code))

    def wrote_one() -> None:
        if state:
            state[1] += 1

    async def setitem(self, key, value):
        fail_after_one()
        await original_setitem(self, key, value)
        wrote_one()

    def put_chunk(path, data):
        fail_after_one()
        original_put(path, data)
        wrote_one()

    monkeypatch.setattr(FrameStore, "write_frame", write_frame)
    monkeypatch.setattr(zarr.AsyncArray, "setitem", setitem)
    monkeypatch.setattr(cache, "put_chunk", put_chunk)


@pytest.mark.parametrize("code, words", [(errno.ENOSPC, "disk holding the cache is full"),
                                         (errno.EROFS, "cache is not writable")])
def test_cache_write_error_aborts_run_and_leaves_frame_pending(tmp_path, monkeypatch, code, words):
    _fault_after_first_array(monkeypatch, "calibrate", 3, code)
    cfg = load_config("synthetic", {}, environ={})
    env = RunEnv(cfg=cfg, cache_root=str(tmp_path / "cache"), dataset="fake", data_root=str(tmp_path))
    pipe = Pipeline(fake_stages.STAGES, env, Executor(1), progress=False, log=lambda m: None,
                    frame_lister=lambda: list(IDS))
    with pytest.raises(CacheError, match=words) as info:
        pipe.run("heatmaps")
    assert "writing frame 3 of" in str(info.value) and "calibrate.zarr" in str(info.value)
    status = pipe.env.store("calibrate").status()
    assert status.tolist() == [DONE] * 3 + [PENDING] * 5  # frame 3 not marked, the run stopped there
    assert pipe.env.store("calibrate").reasons() == {}  # not recorded as a bad-input failure
    assert not pipe.env.store("heatmaps").exists()  # downstream never started
    assert not (Path(env.cache_root) / "fake" / "locks" / "calibrate.lock").exists()  # released
    monkeypatch.undo()
    pipe.run("heatmaps")  # once the cache is writable again, the run resumes and completes
    assert (pipe.env.store("heatmaps").status() == DONE).all()


def _cli_with_write_fault(tmp_path: Path, workers: int, fault: str) -> subprocess.CompletedProcess:
    data = tmp_path / "data"
    data.mkdir()
    env = soak.subprocess_env(SOAK_N_FRAMES="6", SOAK_FAULT=f"calibrate:4:{fault}")
    cmd = soak.python_cmd(*soak.fake_run_args(tmp_path / "cache", data, workers, "heatmaps"))
    return subprocess.run(cmd, env=env, cwd=soak.ROOT, capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def dask_enospc_run(tmp_path_factory):
    """One CLI run with 2 dask workers where frame 4's write fails with ENOSPC (shared by 2 tests)."""
    path = tmp_path_factory.mktemp("dask_enospc")
    return path, _cli_with_write_fault(path, 2, "ENOSPC")


def test_failed_array_write_waits_for_the_other_writes_of_the_frame():
    """When one of a frame's concurrent array writes fails, the others still run to their end before
    the error propagates: none is left pending for asyncio to print after the `error:` line."""
    finished = []

    async def fails():
        raise OSError(errno.EROFS, "Read-only file system")

    async def slow(name):
        await asyncio.sleep(0.05)
        finished.append(name)

    with pytest.raises(OSError, match="Read-only"):
        asyncio.run(gather_all([fails(), slow("points"), slow("reason")]))
    assert sorted(finished) == ["points", "reason"]


@pytest.mark.parametrize("workers, fault, words", [(1, "EROFS", "the cache is not writable"),
                                                   (2, "ENOSPC", "the disk holding the cache is full")])
def test_cli_reports_cache_write_error(tmp_path, workers, fault, words, request):
    """The same CacheError reaches the user from the serial loop and from a dask worker process:
    exit code 2, the last stderr line is the one `error:` line, the frame stays pending."""
    if workers == 1:
        out = _cli_with_write_fault(tmp_path, workers, fault)
    else:
        tmp_path, out = request.getfixturevalue("dask_enospc_run")
    assert out.returncode == 2, out.stderr
    errors = [ln for ln in out.stderr.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and words in errors[0] and "writing frame 4 of" in errors[0], out.stderr
    assert out.stderr.strip().splitlines()[-1] == errors[0]
    if workers == 1:
        assert "Traceback" not in out.stderr
    status = frame_store(str(tmp_path / "cache"), "synthetic", "calibrate").status()
    assert status[4] == PENDING


def test_cli_dask_cache_error_is_the_only_output(dask_enospc_run):
    _, out = dask_enospc_run
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [ln for ln in out.stderr.splitlines() if ln.startswith("error:")]


def _unshare_ok() -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "-rm", "true"], capture_output=True)
    return probe.returncode == 0


@pytest.mark.skipif(not _unshare_ok(), reason="needs user+mount namespaces (unshare -rm)")
def test_real_read_only_and_full_filesystems(tmp_path):
    """Real kernel errors: a read-only tmpfs as cache (works even as root), and a 1 MiB tmpfs
    filled up after two frames (once before the lock is taken, once inside zarr's chunk write);
    each gives one `error:` line and exit code 2, and after freeing space the run resumes to the
    same result as a clean run."""
    data, mnt, out = tmp_path / "data", tmp_path / "mnt", tmp_path / "copy"
    for d in (data, mnt):
        d.mkdir()
    run = " ".join(soak.python_cmd(*soak.fake_run_args(mnt, data, 1, "heatmaps")))
    fill = f"dd if=/dev/zero of={mnt}/fill bs=4k 2>/dev/null"
    stale = '{"pid": 999999999, "host": "elsewhere", "started": 0}'
    script = (f"mount -t tmpfs -o ro none {mnt} && {{ {run}; echo rc=$?; umount {mnt}; }}; "
              f"mount -t tmpfs -o size=1m none {mnt} && {run} --frames 0:2 >/dev/null 2>&1 && "
              f"{{ {fill}; {run}; echo rc=$?; rm {mnt}/fill; "  # full before the lock file is written
              # a lock file left by a killed run: its page is reused, so the disk fills up in zarr's write
              f"echo '{stale}' > {mnt}/synthetic/locks/calibrate.lock; {fill}; {run}; echo rc=$?; rm {mnt}/fill; "
              f"{run} 2>/dev/null; echo rc=$?; cp -r {mnt} {out}; }}")
    res = subprocess.run(["unshare", "-rm", "sh", "-c", script], env=soak.subprocess_env(SOAK_N_FRAMES="6"),
                         cwd=soak.ROOT, capture_output=True, text=True, timeout=120)
    assert res.stdout.split() == ["rc=2", "rc=2", "rc=2", "rc=0"], res.stdout + res.stderr
    errors = [ln for ln in res.stderr.splitlines() if ln.startswith("error:")]
    assert "Traceback" not in res.stderr and len(errors) == 3, res.stderr
    assert "not writable" in errors[0] and "Read-only file system" in errors[0]
    assert "taking the lock" in errors[1] and "disk holding the cache is full" in errors[1]
    assert "writing frame 2 of" in errors[2] and "disk holding the cache is full" in errors[2]
    ref = _in_process_reference(tmp_path, data, 6)
    for stage in ("calibrate", "heatmaps"):
        assert soak.compare_zarr_groups(str(out / "synthetic" / f"{stage}.zarr"), ref.env.store(stage).url) == []


def test_real_stage_kill_resume_on_synthetic_world(tmp_path):
    """`pipeline run heatmaps` (real calibrate + heatmaps) on an 8-frame synthetic world, killed
    twice at random moments, then equal to a clean run. Skipped while the world cannot be made."""
    ok, why = soak.real_pipeline_available(tmp_path, frames=8)
    if not ok:
        pytest.skip(f"real pipeline not available yet: {why}")
    clean = soak.run_once(soak.real_stage_cmd("heatmaps", tmp_path / "clean", tmp_path / "world", 1),
                          soak.subprocess_env(), None)
    assert clean.rc == 0, clean.stderr
    attempts = soak.run_with_kills(soak.real_stage_cmd("heatmaps", tmp_path / "killed", tmp_path / "world", 1),
                                   soak.subprocess_env(), 2, 2.0, max(0.5, clean.seconds - 2.0), random.Random(5))
    assert attempts[-1].rc == 0 and len(attempts) <= 3
    problems, compared = soak.compare_trees(tmp_path / "clean", tmp_path / "killed")
    assert problems == [] and compared >= 2
    status = frame_store(str(tmp_path / "killed"), "synthetic", "heatmaps").status()
    assert (status != PENDING).all()


def test_an_error_stopping_a_dask_task_reaches_the_client_as_itself(monkeypatch):
    """dask pickles an exception with the ones it was raised from; zarr's GroupNotFoundError (as
    botocore's errors) cannot be unpickled, and the client then got a bare Exception that the CLI
    showed as a traceback instead of the one `error:` line."""
    import distributed.protocol.pickle as dask_pickle
    from zarr.errors import GroupNotFoundError

    from pipeline import executor
    from pipeline.errors import CacheError

    def write_fails(stage, env, index, frame_id):
        if index == 1:
            try:
                raise GroupNotFoundError("memory://x/calibrate.zarr", "")
            except GroupNotFoundError as exc:
                raise CacheError(f"writing frame {index}: {exc}") from None
        return index, DONE, ""

    with pytest.raises(Exception) as chained:  # what dask did with it before
        write_fails(None, None, 1, "f1")
    with pytest.raises(TypeError):
        dask_pickle.loads(dask_pickle.dumps(chained.value))
    monkeypatch.setattr(executor, "process_frame", write_fails)
    with pytest.raises(CacheError) as raised:
        executor.process_frames(None, None, [(0, "f0"), (1, "f1"), (2, "f2")])
    back = dask_pickle.loads(dask_pickle.dumps(raised.value))
    assert type(back) is CacheError and str(back) == str(raised.value) and "writing frame 1" in str(back)


def test_local_cluster_workers_start_with_ctrl_c_ignored():
    """Ctrl-C reaches the terminal's whole process group: each local worker printed its
    KeyboardInterrupt traceback (68 lines on Astyx calibrate with 2 workers) before the run's one
    'interrupted' line. Workers started inside the guard take no SIGINT (since 2026-12-06 it is
    blocked for them, no longer ignored: an ignored one was lost to the run too); the run's own
    handler is back after. The probe sends itself a SIGINT."""
    import signal
    import subprocess
    import sys

    from pipeline.executor import _workers_without_sigint

    probe = [sys.executable, "-c", "import os, signal, time; os.kill(os.getpid(), signal.SIGINT); time.sleep(0.2); "
                                   "print('survived')"]
    before = signal.getsignal(signal.SIGINT)
    with _workers_without_sigint():
        inside = subprocess.run(probe, capture_output=True, text=True)
    assert (inside.returncode, inside.stdout.strip(), inside.stderr) == (0, "survived", "")
    assert signal.getsignal(signal.SIGINT) is before
    outside = subprocess.run(probe, capture_output=True, text=True)
    assert outside.returncode != 0 and "KeyboardInterrupt" in outside.stderr and "survived" not in outside.stdout


def _pipe_with_dataset_stage(tmp_path: Path, run, resumes: bool = False) -> Pipeline:
    """The fake frame stages, then a dataset stage 'train' running ``run(inputs, cfg, out, fingerprint)``."""
    from pipeline.stage import DatasetStage

    (tmp_path / "data").mkdir(parents=True, exist_ok=True)
    stages = [*fake_stages.STAGES[:2], DatasetStage("train", ("heatmaps",), ("train.epochs",), run, resumes=resumes)]
    env = RunEnv(cfg=load_config("synthetic", {}, environ={}), cache_root=str(tmp_path / "cache"),
                 dataset="synthetic", data_root=str(tmp_path / "data"))
    return Pipeline(stages, env, Executor(1), progress=False, log=lambda m: None, frame_lister=lambda: IDS)


def test_cluster_failure_names_the_stage_and_whether_to_drop_force(tmp_path, capsys):
    """A lost cluster's message said 'run the same command again' (the executor's) or added
    'without --force' whenever --force was given (the CLI's), whether or not the forced rebuild
    had begun; a repeated --force starts the stage again."""
    from pipeline.cli import _handle_errors
    from pipeline.errors import ClusterFailed

    lost = type("CommClosedError", (Exception,), {"__module__": "distributed.comm.core"})

    def no_worker(inputs, cfg, out, fingerprint):
        raise ClusterFailed("dask cluster at tcp://x:1 has had no worker for 2 s", after=" (once it has workers)")

    def closed(inputs, cfg, out, fingerprint):
        raise lost("in <TCP (closed)>: Stream is closed\nmore")

    with pytest.raises(ClusterFailed) as raised:
        _pipe_with_dataset_stage(tmp_path / "a", no_worker, resumes=True).run("train", force=True)
    assert str(raised.value) == ("train: dask cluster at tcp://x:1 has had no worker for 2 s; what it saved is kept; "
                                 "run the same command again without --force to resume from its last checkpoint "
                                 "(once it has workers)")
    with pytest.raises(ClusterFailed) as raised:
        _pipe_with_dataset_stage(tmp_path / "b", closed, resumes=True).run("train")
    assert str(raised.value) == ("train: the dask cluster failed (CommClosedError: in <TCP (closed)>: Stream is "
                                 "closed); what it saved is kept; run the same command again to resume from its last "
                                 "checkpoint")
    assert isinstance(raised.value.__cause__, lost)
    assert str(ClusterFailed("lost", "heatmaps", "frame", True)) == (
        "heatmaps: lost; its finished frames are kept; run the same command again without --force to resume")
    assert pickle.loads(pickle.dumps(ClusterFailed("lost", "heatmaps", "frame", True))).forced

    @_handle_errors
    def command(force):  # lost while closing it after the stages (a probe's failure is a PipelineError)
        raise lost("Stream is closed")

    with pytest.raises(SystemExit) as exit_:
        command(force=True)
    assert exit_.value.code == 2
    assert capsys.readouterr().err == ("error: the dask cluster failed (CommClosedError: Stream is closed); its "
                                       "finished frames are kept; run the same command again without --force to "
                                       "resume\n")


def test_disk_full_in_a_dataset_stage_names_the_stage_and_its_folder(tmp_path):
    """A failing write(2) raises an OSError without a file name: the message said only
    '[Errno 28] No space left on device'. An error naming a file outside the output is left as is."""
    def full(inputs, cfg, out, fingerprint):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    pipe = _pipe_with_dataset_stage(tmp_path, full)
    with pytest.raises(CacheError) as raised:
        pipe.run("train")
    folder = pipe.env.dir("train").path
    assert str(raised.value).startswith(f"train: writing into {folder}: the disk holding the cache is full")

    for error in (PermissionError(errno.EACCES, "Permission denied", str(tmp_path / "data" / "labels.txt")),
                  PermissionError(errno.EACCES, "Permission denied", folder + "_old/x"),  # a sibling's
                  OSError(errno.EIO, os.strerror(errno.EIO))):  # a read(2) that fails names no file either
        def fails(inputs, cfg, out, fingerprint, error=error):
            raise error

        with pytest.raises(type(error)) as raised:
            _pipe_with_dataset_stage(tmp_path, fails).run("train")
        assert raised.value is error


def test_a_dataset_stage_output_holds_one_runs_files(tmp_path):
    """A stage that does not resume starts from an empty folder: a failed run's files (and the
    report of the run before) are gone. One that resumes keeps its files but not the temporary files
    a killed run left (a half-written checkpoint of 42 MB stayed on the demo)."""
    calls = []

    def writes(inputs, cfg, out, fingerprint):
        calls.append(sorted(p.name for p in Path(out.path).iterdir()))
        out.write_text("report.json", f"run {len(calls)}")
        if len(calls) == 1:
            out.write_text("report.md", "run 1")
            (Path(out.path) / "disnet").mkdir()
            (Path(out.path) / "disnet" / ".last.safetensors.x1y2.tmp").write_bytes(b"half")
            raise ValueError("failed between the two files")
        return {"message": "ok"}

    with pytest.raises(ValueError):
        _pipe_with_dataset_stage(tmp_path / "plain", writes).run("train")
    _pipe_with_dataset_stage(tmp_path / "plain", writes).run("train")
    assert calls[1] == []

    calls.clear()
    with pytest.raises(ValueError):
        _pipe_with_dataset_stage(tmp_path / "resumes", writes, resumes=True).run("train")
    pipe = _pipe_with_dataset_stage(tmp_path / "resumes", writes, resumes=True)
    logged = []
    pipe.log = logged.append
    pipe.run("train")
    assert calls[1] == ["disnet", "report.json", "report.md"]  # kept for it to resume from
    assert not (Path(pipe.env.dir("train").path) / "disnet" / ".last.safetensors.x1y2.tmp").exists()
    assert any(line.startswith("train") and "removed 1 temporary file a killed run left: "
               "disnet/.last.safetensors.x1y2.tmp" in line for line in logged), logged


def test_ctrl_c_says_which_stage_and_whether_to_drop_force(tmp_path, monkeypatch, capsys):
    """The message was 'run the same command again to resume' everywhere, but a repeated --force
    starts the stage again, and a stage without checkpoints (export, evaluate) starts over anyway."""
    from pipeline.cli import _handle_errors
    from pipeline.errors import StageInterrupted

    def interrupted(inputs, cfg, out, fingerprint):
        raise KeyboardInterrupt

    with pytest.raises(StageInterrupted) as raised:
        _pipe_with_dataset_stage(tmp_path / "a", interrupted, resumes=True).run("train", force=True)
    assert (raised.value.stage, raised.value.kind, raised.value.forced) == ("train", "resumes", True)
    assert "without --force to resume from its last checkpoint" in raised.value.advice()
    with pytest.raises(StageInterrupted) as raised:
        _pipe_with_dataset_stage(tmp_path / "b", interrupted).run("train")
    assert (raised.value.kind, raised.value.forced) == ("dataset", False)
    assert "train starts over" in raised.value.advice() and "--force" not in raised.value.advice()

    # stopped before a forced rebuild began (waiting for a lock, checking the output): nothing is
    # discarded yet, so the same command, --force and all, is the way on
    pipe = _pipe_with_dataset_stage(tmp_path / "a", interrupted, resumes=True)
    real_is_current = Pipeline.is_current

    def stopped_in_train_check(self, name):
        if name == "train":
            raise KeyboardInterrupt
        return real_is_current(self, name)

    with monkeypatch.context() as patch:
        patch.setattr(Pipeline, "is_current", stopped_in_train_check)
        with pytest.raises(StageInterrupted) as raised:
            pipe.run("train", force=True)
    assert (raised.value.stage, raised.value.forced) == ("train", False)

    monkeypatch.setenv(fake_stages.CALLS_FILE_ENV, str(tmp_path / "calls.log"))
    monkeypatch.setenv("FAKE_STAGE_STOP_AFTER", "2")
    with pytest.raises(StageInterrupted) as raised:
        _pipe_with_dataset_stage(tmp_path / "c", interrupted).run("heatmaps", force=True)
    assert (raised.value.stage, raised.value.kind, raised.value.forced) == ("calibrate", "frame", False)

    @_handle_errors
    def command(force):
        raise StageInterrupted("heatmaps", "frame", force)

    with pytest.raises(SystemExit) as exit_:
        command(force=True)
    assert exit_.value.code == 130
    assert capsys.readouterr().err == ("interrupted in heatmaps: its finished frames are kept; "
                                       "run the same command again without --force to resume\n")


def test_a_forced_run_of_a_resuming_dataset_stage_starts_from_an_empty_folder(tmp_path):
    """--force on a stage that resumes from its files (train's checkpoints) must not resume: the
    forced run sees none of the files the earlier run left."""
    seen = []

    def writes(inputs, cfg, out, fingerprint):
        seen.append(sorted(p.name for p in Path(out.path).iterdir()))
        out.write_text("last.json", f"epoch {len(seen)}")
        return {"message": "ok"}

    _pipe_with_dataset_stage(tmp_path, writes, resumes=True).run("train")
    _pipe_with_dataset_stage(tmp_path, writes, resumes=True).run("train", force=True)
    assert seen == [[], []]


def test_a_run_killed_while_creating_an_output_leaves_it_to_be_created_again(tmp_path, monkeypatch):
    """The output's fingerprint is written after its arrays: a run killed between the two leaves an
    output that is not taken for current, and the next run recreates it and computes every frame."""
    original = zarr.Group.create_array

    def killed_at_status(self, name, *args, **kwargs):
        if name == "status":
            raise KeyboardInterrupt("killed while creating the output")
        return original(self, name, *args, **kwargs)

    cfg = load_config("synthetic", {}, environ={})
    env = RunEnv(cfg=cfg, cache_root=str(tmp_path / "cache"), dataset="fake", data_root=str(tmp_path))
    pipe = Pipeline(fake_stages.STAGES, env, Executor(1), progress=False, log=lambda m: None,
                    frame_lister=lambda: list(IDS))
    with monkeypatch.context() as patch:
        patch.setattr(zarr.Group, "create_array", killed_at_status)
        with pytest.raises(KeyboardInterrupt):
            pipe.run("calibrate")
    assert pipe.env.store("calibrate").fingerprint() is None
    report = Pipeline(fake_stages.STAGES, env, Executor(1), progress=False, log=lambda m: None,
                      frame_lister=lambda: list(IDS)).run("calibrate")[0]
    assert (report.processed, report.done) == (len(IDS), len(IDS))


def test_a_cache_error_reading_a_frames_input_stops_the_run_and_fails_no_frame(tmp_path, monkeypatch):
    """A cache problem (here: an input that cannot be opened) is no bad input of one frame: the run
    stops at once and the frames stay pending, not every one recorded as failed with it."""
    cfg = load_config("synthetic", {}, environ={})
    env = RunEnv(cfg=cfg, cache_root=str(tmp_path / "cache"), dataset="fake", data_root=str(tmp_path))
    pipe = Pipeline(fake_stages.STAGES, env, Executor(1), progress=False, log=lambda m: None,
                    frame_lister=lambda: list(IDS))
    pipe.run("calibrate")
    original = FrameStore.read

    def unreadable(self, name, index, run=""):
        if self.url.endswith("/calibrate.zarr"):
            raise CacheError(f"opening {self.url}: [Errno 5] Input/output error")
        return original(self, name, index, run)

    with monkeypatch.context() as patch:
        patch.setattr(FrameStore, "read", unreadable)
        with pytest.raises(CacheError, match="Input/output error"):
            pipe.run("heatmaps")
    status = pipe.env.store("heatmaps").status()
    assert not (status == FAILED).any() and pipe.env.store("heatmaps").reasons() == {}
    pipe.run("heatmaps")
    assert (pipe.env.store("heatmaps").status() == DONE).all()
