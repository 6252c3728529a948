"""Crash-resume soak: SIGKILL pipeline runs at random (seeded) moments, re-run them until they
finish, and check the result equals an uninterrupted run.

    python -m tests.soak --kills 30 [--seed 0] [--work DIR] [--keep]      (what `make soak` runs)

Targets (each compared with a clean run of its own):
- ``fake-serial`` / ``fake-dask``: the `pipeline` CLI with the stages of tests/fake_stages.py
  (calibrate -> heatmaps -> train), slowed down by ``SOAK_FRAME_SLEEP`` seconds per frame so that
  kills land mid-stage; serial executor and a 2-worker dask LocalCluster.
- ``mid-write``: a kill injected after the first array of a frame was written (status not yet).
- ``train-direct``: pipeline.training (Dis-Net + RSS-Net) on a tiny random problem; weights,
  optimizer and RNG state compared exactly on CPU.
- ``real:<stage>``: the real stages on the built-in synthetic world, when it can be generated.
- ``real:train-remote``: the real stages from heatmaps to export on a remote cache (a local
  folder behind an fsspec filesystem that is not the local one, each file written whole as an
  object store writes it), train uploading its checkpoints after every epoch; each attempt runs
  as another machine would (the staging folder alternates between two), so kills land in
  downloads, training, the per-epoch uploads and the final ones. The outputs must equal the clean
  local run's.

What "no frame lost or duplicated" means here (checked from the per-frame call log written by the
fake stages and from the frame status read between attempts):
1. within one attempt no frame of a stage is computed twice;
2. a frame that was DONE after attempt k is never computed again in a later attempt;
3. DONE frames stay DONE (the set only grows from one attempt to the next);
4. the attempt that finishes computes exactly the frames still pending before it, once each;
5. the write of a frame completes at most once over all attempts;
6. at the end every frame is DONE and every array equals the clean run's bit for bit.

Subprocess entry points (used by this harness and by tests/test_reliability.py)::

    python -m tests.soak fake-cli ARGS...        the `pipeline` CLI running the fake stages
    python -m tests.soak train-direct OUT_DIR    resumable training on a tiny random problem
    python -m tests.soak lock-holder URL LOG HOLD_S START_AT   take a stage lock, log the interval

Test-only hooks (environment variables, read by the fake stages in whichever process runs them):
``SOAK_FRAME_SLEEP`` seconds per frame, ``SOAK_CALL_LOG`` the call log, ``SOAK_ATTEMPT`` the
attempt number written into it, ``SOAK_N_FRAMES`` the number of fake frames, ``SOAK_FAULT``
``STAGE:INDEX:WHAT`` with WHAT ``kill`` (SIGKILL this process) or an errno name (``ENOSPC``,
``EROFS``: raise that OSError) right after the first array of that frame was written.
"""

from __future__ import annotations

import argparse
import errno
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SLEEP_ENV, LOG_ENV, ATTEMPT_ENV = "SOAK_FRAME_SLEEP", "SOAK_CALL_LOG", "SOAK_ATTEMPT"
N_FRAMES_ENV, FAULT_ENV = "SOAK_N_FRAMES", "SOAK_FAULT"
TRAIN_EPOCHS_ENV, TRAIN_SCALE_ENV = "SOAK_TRAIN_EPOCHS", "SOAK_TRAIN_SCALE"
FAKE_FRAME_STAGES = ("calibrate", "heatmaps")

# ------------------------------------------------------------------------------ fake stages


def fake_frame_ids() -> list[str]:
    """Frame ids of the fake dataset (``SOAK_N_FRAMES``, default 16)."""
    return [f"f{i:03d}" for i in range(int(os.environ.get(N_FRAMES_ENV, "16")))]


def log_event(event: str, stage: str, index: int | str) -> None:
    """Append one line ``event stage index attempt pid`` to the call log (one O_APPEND write)."""
    path = os.environ.get(LOG_ENV)
    if path:
        line = f"{event} {stage} {index} {os.environ.get(ATTEMPT_ENV, '0')} {os.getpid()}\n"
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, line.encode())
        finally:
            os.close(fd)


def _traced(stage: str, inputs, cfg, fn: Callable):
    install_hooks()
    log_event("start", stage, inputs.index)
    time.sleep(float(os.environ.get(SLEEP_ENV, "0") or 0))
    return fn(inputs, cfg)


def fake_calibrate(inputs, cfg):
    """tests/fake_stages.first, logged and slowed down."""
    from tests import fake_stages

    return _traced("calibrate", inputs, cfg, fake_stages.first)


def fake_heatmaps(inputs, cfg):
    """tests/fake_stages.second, logged and slowed down."""
    from tests import fake_stages

    return _traced("heatmaps", inputs, cfg, fake_stages.second)


def fake_train(inputs, cfg, out, fingerprint):
    """tests/fake_stages.summarise (a dataset stage), logged and slowed down."""
    from tests import fake_stages

    log_event("start", "train", "-")
    time.sleep(4 * float(os.environ.get(SLEEP_ENV, "0") or 0))
    return fake_stages.summarise(inputs, cfg, out, fingerprint)


def fake_pipeline_stages() -> list:
    """The stages of tests/fake_stages.py with their functions replaced by the traced ones."""
    from dataclasses import replace

    from tests import fake_stages

    calib, heat, train = fake_stages.STAGES
    return [replace(calib, process=fake_calibrate), replace(heat, process=fake_heatmaps),
            replace(train, run=fake_train)]


_HOOKED: list[bool] = []
_WRITING: list = []  # [stage, index, arrays written so far] while FrameStore.write_frame runs


def install_hooks() -> None:
    """Wrap FrameStore.write_frame, zarr.AsyncArray.setitem and put_chunk as pipeline.cache calls it
    (pipeline.zarr_io's: a chunk file written directly) in this process (once): log completed frame
    writes and inject the ``SOAK_FAULT`` fault after a frame's first array write completes (the
    frame's other arrays are being written, concurrently through zarr; its status is not yet)."""
    if _HOOKED:
        return
    _HOOKED.append(True)
    import zarr

    from pipeline import cache
    from pipeline.cache import FrameStore

    original_write, original_setitem, original_put = FrameStore.write_frame, zarr.AsyncArray.setitem, cache.put_chunk

    def write_frame(self, index, arrays, specs, run=""):
        stage = self.url.rstrip("/").rsplit("/", 1)[-1].removesuffix(".zarr")
        _WRITING[:] = [stage, int(index), 0]
        try:
            original_write(self, index, arrays, specs, run)
        finally:
            _WRITING.clear()
        log_event("written", stage, index)

    def written() -> None:
        if _WRITING:
            _WRITING[2] += 1
            if _WRITING[2] == 1:
                _inject_fault(_WRITING[0], _WRITING[1])

    async def setitem(self, key, value):
        await original_setitem(self, key, value)
        written()

    def put_chunk(path, data):
        original_put(path, data)
        written()

    FrameStore.write_frame = write_frame
    zarr.AsyncArray.setitem = setitem
    cache.put_chunk = put_chunk


def _inject_fault(stage: str, index: int) -> None:
    spec = os.environ.get(FAULT_ENV, "")
    if not spec:
        return
    f_stage, f_index, what = spec.split(":")
    if f_stage != stage or int(f_index) != index:
        return
    log_event("partial", stage, index)
    if what == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    code = getattr(errno, what)
    raise OSError(code, os.strerror(code))


def fake_cli(argv: list[str]) -> None:
    """The real `pipeline` CLI (option parsing, locks, error handling) running the fake stages."""
    import pipeline.cli as cli
    from pipeline.executor import Executor
    from pipeline.runner import Pipeline

    def _pipeline(env, workers, scheduler, progress=None):
        return Pipeline(fake_pipeline_stages(), env, Executor(workers, scheduler, progress), progress,
                        frame_lister=fake_frame_ids)

    cli._pipeline = _pipeline
    cli._ensure_world = lambda env, progress: None
    install_hooks()
    cli.main(argv, prog_name="pipeline")


# ---------------------------------------------------------------------- train entry point


def train_direct_config():
    """A tiny CPU configuration for pipeline.training (single thread, fixed seed)."""
    from pipeline.config import load_config

    return load_config("synthetic", {
        "disnet.width": "8", "camera.working_size": "64,32", "radar.max_points": "64",
        "train.batch_size": "8", "train.lr": "3e-3", "train.threads": "1", "train.device": "cpu",
        "patches.patch_size_px": "16", "train.rss_batch_size": "32",
        "train.epochs": os.environ.get(TRAIN_EPOCHS_ENV, "6"),
        "train.checkpoint_every_s": "1e-9",  # a resume point after every window of batches inside an epoch
        "train.seed": "3"}, environ={})


def train_direct(out_dir: str) -> None:
    """Train Dis-Net and RSS-Net on seeded random arrays into ``out_dir`` (resuming from it)."""
    from pipeline import training as T

    cfg = train_direct_config()
    T.WINDOW_BATCHES = 1  # one batch a window: kills land between resume points inside the epochs too
    rng = np.random.default_rng(0)
    scale = int(os.environ.get(TRAIN_SCALE_ENV, "2"))
    n, h, w, p = 12 * scale, 32, 64, 160 * scale
    heat = rng.random((n, h, w)).astype(np.float32)
    heat /= heat.sum(axis=(1, 2), keepdims=True)
    dis = T.DisNetData(rng.integers(0, 256, (n, h, w, 3)).astype(np.uint8), heat,
                       rng.integers(5, 40, n), rng.uniform(0, 15, n).astype(np.float32),
                       list(range(n * 3 // 4)), list(range(n * 3 // 4, n)))
    rss = T.RssNetData(rng.integers(0, 256, (p, 16, 16, 3)).astype(np.uint8),
                       rng.uniform(-1, 255, (p, 32, 128)).astype(np.float32),
                       rng.normal(size=(p, 4)).astype(np.float32), rng.uniform(-30, 40, p).astype(np.float32),
                       list(range(p * 4 // 5)), list(range(p * 4 // 5, p)))
    T.train_disnet(cfg, dis, Path(out_dir) / "disnet", progress=False)
    T.train_rssnet(cfg, rss, Path(out_dir) / "rssnet", progress=False)


def lock_holder(url: str, log: str, hold_s: str, start_at: str) -> None:
    """Wait until ``start_at`` (epoch s), take the stage lock (waiting up to 60 s), hold it
    ``hold_s`` seconds and append ``enter exit pid`` (monotonic-free wall times) to ``log``."""
    from pipeline.lock import stage_lock

    time.sleep(max(0.0, float(start_at) - time.time()))
    with stage_lock(url, "stage 'x' of dataset 'soak'", wait_s=60):
        enter = time.time()
        time.sleep(float(hold_s))
        leave = time.time()
    with open(log, "a") as fh:
        fh.write(f"{enter:.6f} {leave:.6f} {os.getpid()}\n")


# ------------------------------------------------------------------------------ the harness


def subprocess_env(**extra: str) -> dict[str, str]:
    """Environment for child runs: the project importable, one thread, no config overrides."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PIPELINE_", "SOAK_"))}
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    env.update(extra)
    return env


def python_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "tests.soak", *args]


@dataclass
class Attempt:
    """One run of a command: killed or finished with ``rc``."""

    killed: bool
    rc: int | None
    seconds: float
    snapshot: Any = None
    stderr: str = ""


def run_once(cmd: list[str], env: dict[str, str], kill_after_s: float | None, timeout_s: float = 600) -> Attempt:
    """Run ``cmd`` in its own process group; SIGKILL the whole group after ``kill_after_s`` if it is
    still running (workers included). Returns whether the kill landed."""
    with tempfile.TemporaryFile() as err:
        t0 = time.monotonic()
        proc = subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=err,
                                start_new_session=True)
        try:
            rc = proc.wait(timeout=kill_after_s if kill_after_s is not None else timeout_s)
            killed = False
        except subprocess.TimeoutExpired:
            if kill_after_s is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
                raise RuntimeError(f"{' '.join(cmd)} did not finish in {timeout_s} s") from None
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()  # reap: a zombie's pid would look alive to the lock's stale check
            _wait_group_gone(proc.pid)
            rc, killed = None, True
        seconds = time.monotonic() - t0
        err.seek(0)
        return Attempt(killed, rc, seconds, stderr=err.read().decode(errors="replace"))


def _wait_group_gone(pgid: int, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.05)


def run_with_kills(cmd: list[str] | Callable[[int], list[str]], env: dict[str, str], kills: int, startup_s: float,
                   work_s: float, rng: random.Random, snapshot: Callable[[], Any] = lambda: None) -> list[Attempt]:
    """Run ``cmd`` (or ``cmd(attempt number)``); up to ``kills`` times SIGKILL it at a random moment,
    re-run until it exits 0.

    A kill lands ``startup_s + u * work_s / kills`` seconds after the start, u ~ U(-0.2, 1): mostly
    mid-work, sometimes during start-up. ``snapshot()`` is recorded after every attempt.
    """
    attempts: list[Attempt] = []
    landed = 0
    while True:
        delay = None
        if landed < kills:
            delay = max(0.05, startup_s + rng.uniform(-0.2, 1.0) * work_s / kills)
        att = run_once(cmd(len(attempts)) if callable(cmd) else cmd, {**env, ATTEMPT_ENV: str(len(attempts))}, delay)
        att.snapshot = snapshot()
        attempts.append(att)
        if att.killed:
            landed += 1
            continue
        if att.rc != 0:
            raise RuntimeError(f"{' '.join(cmd[-6:])} exited {att.rc} after {landed} kill(s):\n{att.stderr[-3000:]}")
        return attempts


# ------------------------------------------------------------------------------ comparisons


def compare_zarr_groups(a: str, b: str) -> list[str]:
    """Names of the arrays that differ (or exist in one group only); NaN equals NaN."""
    import zarr

    ga, gb = zarr.open_group(a, mode="r"), zarr.open_group(b, mode="r")
    names = sorted(set(ga.array_keys()) | set(gb.array_keys()))
    bad = []
    for name in names:
        if name not in ga or name not in gb:
            bad.append(f"{name} (missing)")
            continue
        try:
            np.testing.assert_array_equal(np.asarray(ga[name][:]), np.asarray(gb[name][:]))
        except AssertionError:
            bad.append(name)
    for key in ("fingerprint", "frame_ids"):
        if ga.attrs.get(key) != gb.attrs.get(key):
            bad.append(f"attrs.{key}")
    return bad


def compare_safetensors(a: Path, b: Path) -> list[str]:
    """Tensors that differ between two safetensors files (exact comparison)."""
    from safetensors.torch import load_file

    ta, tb = load_file(str(a)), load_file(str(b))
    bad = sorted(set(ta) ^ set(tb))
    bad += [k for k in sorted(set(ta) & set(tb)) if not (ta[k].dtype == tb[k].dtype and ta[k].shape == tb[k].shape
                                                        and bool((ta[k] == tb[k]).all()))]
    return bad


def compare_trees(a: Path, b: Path) -> tuple[list[str], int]:
    """Compare two output folders: zarr groups array by array, safetensors tensor by tensor, .bin
    and .txt files byte by byte (JSON/CSV/PNG/MD carry timings and are skipped). Returns (problems,
    number of items compared)."""
    problems, compared = [], 0
    for path in sorted(a.rglob("*")):
        rel = path.relative_to(a)
        other = b / rel
        if path.suffix == ".zarr" and path.is_dir():
            compared += 1
            problems += [f"{rel}/{n}" for n in compare_zarr_groups(str(path), str(other))]
        elif ".zarr" in str(rel) or not path.is_file() or "locks" in rel.parts or "world" in rel.parts:
            continue
        elif path.suffix == ".safetensors":
            compared += 1
            problems += [f"{rel}:{n}" for n in (compare_safetensors(path, other) if other.exists() else ["missing"])]
        elif path.suffix in (".bin", ".txt", ".npy"):
            compared += 1
            if not other.exists() or path.read_bytes() != other.read_bytes():
                problems.append(str(rel))
    return problems, compared


# --------------------------------------------------------------------------- fake targets


def read_events(log: Path) -> list[tuple[str, str, str, int]]:
    """Call-log lines as (event, stage, index, attempt)."""
    if not log.exists():
        return []
    out = []
    for line in log.read_text().splitlines():
        event, stage, index, attempt, _pid = line.split()
        out.append((event, stage, index, int(attempt)))
    return out


def fake_snapshot(cache: Path, dataset: str = "synthetic") -> dict[str, set[int]]:
    """DONE frame indices per fake frame stage (empty when the store does not exist yet)."""
    from pipeline.cache import DONE, frame_store

    out = {}
    for stage in FAKE_FRAME_STAGES:
        store = frame_store(str(cache), dataset, stage)
        out[stage] = set(np.flatnonzero(store.status() == DONE).tolist()) if store.exists() else set()
    return out


def check_call_log(attempts: list[Attempt], events, n_frames: int, workers: int) -> tuple[list[str], dict[str, int]]:
    """Check properties 1-5 of the module docstring; returns (problems, redone frames per stage)."""
    problems: list[str] = []
    redone = {}
    for stage in FAKE_FRAME_STAGES:
        before: set[int] = set()
        total = 0
        written = Counter(int(i) for e, s, i, _ in events if e == "written" and s == stage)
        for k, att in enumerate(attempts):
            started = [int(i) for e, s, i, a in events if e == "start" and s == stage and a == k]
            total += len(started)
            after = att.snapshot[stage]
            dup = [i for i, c in Counter(started).items() if c > 1]
            if dup:
                problems.append(f"{stage}: attempt {k} computed frame(s) {dup} twice")
            if set(started) & before:
                problems.append(f"{stage}: attempt {k} recomputed finished frame(s) {sorted(set(started) & before)}")
            if not before <= after:
                problems.append(f"{stage}: attempt {k} lost finished frame(s) {sorted(before - after)}")
            if not att.killed and sorted(started) != sorted(set(range(n_frames)) - before):
                problems.append(f"{stage}: the finishing attempt {k} computed {sorted(started)}, "
                                f"pending were {sorted(set(range(n_frames)) - before)}")
            before = after
        if before != set(range(n_frames)):
            problems.append(f"{stage}: frames {sorted(set(range(n_frames)) - before)} not done at the end")
        if any(c > 1 for c in written.values()):
            problems.append(f"{stage}: frame writes completed more than once: {[i for i, c in written.items() if c > 1]}")
        redone[stage] = total - n_frames
        kills = sum(a.killed for a in attempts)
        if redone[stage] > kills * workers:
            problems.append(f"{stage}: {redone[stage]} frames redone after {kills} kills with {workers} worker(s)")
    return problems, redone


def fake_run_args(cache: Path, data: Path, workers: int, target: str = "train") -> list[str]:
    return ["fake-cli", "run", target, "--dataset", "synthetic", "--cache", str(cache), "--data-root", str(data),
            "--workers", str(workers)]


@dataclass
class TargetResult:
    """One row of the summary table."""

    name: str
    kills: int
    attempts: int
    redone: str
    seconds: float
    compared: int
    problems: list[str] = field(default_factory=list)


def soak_fake(work: Path, workers: int, kills: int, rng: random.Random, n_frames: int = 16,
              sleep_s: float = 0.15, name: str | None = None) -> TargetResult:
    """Clean fake run, then the same under ``kills`` random SIGKILLs; compare everything."""
    work.mkdir(parents=True, exist_ok=True)
    data = work / "data"
    data.mkdir(exist_ok=True)
    base = {N_FRAMES_ENV: str(n_frames), SLEEP_ENV: str(sleep_s)}
    clean_log, killed_log = work / "clean.log", work / "killed.log"
    clean = run_once(python_cmd(*fake_run_args(work / "clean", data, workers)),
                     subprocess_env(**base, **{LOG_ENV: str(clean_log)}), None)
    if clean.rc != 0:
        raise RuntimeError(f"clean fake run failed:\n{clean.stderr[-3000:]}")
    noop = run_once(python_cmd(*fake_run_args(work / "clean", data, workers)), subprocess_env(**base), None)
    t0 = time.monotonic()
    attempts = run_with_kills(python_cmd(*fake_run_args(work / "killed", data, workers)),
                              subprocess_env(**base, **{LOG_ENV: str(killed_log)}), kills, noop.seconds,
                              max(0.5, clean.seconds - noop.seconds), rng,
                              lambda: fake_snapshot(work / "killed"))
    seconds = time.monotonic() - t0
    problems, redone = check_call_log(attempts, read_events(killed_log), n_frames, workers)
    tree_problems, compared = compare_trees(work / "clean", work / "killed")
    return TargetResult(name or f"fake-{'serial' if workers == 1 else 'dask'}", sum(a.killed for a in attempts),
                        len(attempts), ", ".join(f"{s} {n}" for s, n in redone.items()), seconds, compared,
                        problems + tree_problems)


def soak_mid_write(work: Path, frames: tuple[int, ...], n_frames: int = 12) -> TargetResult:
    """Kill a run right after the first array of frame i was written, for each i in ``frames``:
    the frame must stay PENDING, and the resumed run must equal a clean one."""
    from pipeline.cache import PENDING, frame_store

    work.mkdir(parents=True, exist_ok=True)
    data = work / "data"
    data.mkdir(exist_ok=True)
    base = {N_FRAMES_ENV: str(n_frames)}
    clean = run_once(python_cmd(*fake_run_args(work / "clean", data, 1, "heatmaps")), subprocess_env(**base), None)
    if clean.rc != 0:
        raise RuntimeError(f"clean fake run failed:\n{clean.stderr[-3000:]}")
    problems, attempts, t0 = [], 0, time.monotonic()
    log = work / "killed.log"
    cmd = python_cmd(*fake_run_args(work / "killed", data, 1, "heatmaps"))
    for index in frames:
        att = run_once(cmd, subprocess_env(**base, **{LOG_ENV: str(log), FAULT_ENV: f"calibrate:{index}:kill"}), None)
        attempts += 1
        if att.rc != -signal.SIGKILL:
            problems.append(f"frame {index}: the injected kill did not happen (rc {att.rc})")
            continue
        store = frame_store(str(work / "killed"), "synthetic", "calibrate")
        if store.status()[index] != PENDING:
            problems.append(f"frame {index}: status {store.status()[index]} after a kill mid-write (want PENDING)")
    final = run_once(cmd, subprocess_env(**base, **{LOG_ENV: str(log), ATTEMPT_ENV: str(attempts)}), None)
    attempts += 1
    if final.rc != 0:
        problems.append(f"resume failed: {final.stderr[-2000:]}")
    tree_problems, compared = compare_trees(work / "clean", work / "killed")
    return TargetResult("mid-write", len(frames), attempts, "-", time.monotonic() - t0, compared,
                        problems + tree_problems)


def soak_train_direct(work: Path, kills: int, rng: random.Random, epochs: int = 6, scale: int = 2,
                      startup_s: float | None = None) -> TargetResult:
    """Resumable training killed at random moments vs an uninterrupted run: tensors equal exactly.
    ``startup_s``: seconds before training starts (measured when None)."""
    work.mkdir(parents=True, exist_ok=True)
    env = subprocess_env(**{TRAIN_EPOCHS_ENV: str(epochs), TRAIN_SCALE_ENV: str(scale)})
    clean = run_once(python_cmd("train-direct", str(work / "clean")), env, None)
    if clean.rc != 0:
        raise RuntimeError(f"clean training failed:\n{clean.stderr[-3000:]}")
    startup = startup_s if startup_s is not None else \
        run_once([sys.executable, "-c", "import pipeline.training"], env, None).seconds
    t0 = time.monotonic()
    attempts = run_with_kills(python_cmd("train-direct", str(work / "killed")), env, kills, startup,
                              max(0.5, clean.seconds - startup), rng)
    problems, compared = compare_trees(work / "clean", work / "killed")
    if compared < 4:
        problems.append(f"only {compared} checkpoint files compared")
    return TargetResult("train-direct", sum(a.killed for a in attempts), len(attempts), "-",
                        time.monotonic() - t0, compared, problems)


# --------------------------------------------------------------------------- real stages

REAL_STAGES = ("calibrate", "heatmaps", "patches", "train", "synthesize", "export")
REAL_SETTINGS = ("train.epochs=3", "placement.epochs=3", "train.threads=1", "train.device=cpu", "synth.device=cpu")


def real_stage_cmd(stage: str, cache: Path, world: Path, workers: int) -> list[str]:
    cmd = [sys.executable, "-m", "pipeline.cli", "run", stage, "--dataset", "synthetic", "--cache", str(cache),
           "--data-root", str(world), "--workers", str(workers)]
    for s in REAL_SETTINGS:
        cmd += ["--set", s]
    return cmd


def real_pipeline_available(work: Path, frames: int = 24) -> tuple[bool, str]:
    """Generate the synthetic world into ``work/world``; (False, why) if it cannot be done yet."""
    att = run_once([sys.executable, "-m", "pipeline.cli", "generate-world", "--frames", str(frames), "--seed", "0",
                    "--out", str(work / "world")], subprocess_env(), None)
    if att.rc != 0:
        return False, (att.stderr.strip().splitlines() or ["?"])[-1]
    return True, ""


def soak_real(work: Path, kills: dict[str, int], rng: random.Random, workers: int = 1) -> list[TargetResult]:
    """Each real stage: a clean run (upstream already done), then the same stage under kills."""
    results = []
    env = subprocess_env()
    for stage in REAL_STAGES:
        clean = run_once(real_stage_cmd(stage, work / "clean", work / "world", workers), env, None)
        if clean.rc != 0:
            results.append(TargetResult(f"real:{stage}", 0, 0, "-", 0, 0, [f"clean run failed: {clean.stderr[-1500:]}"]))
            return results
        noop = run_once(real_stage_cmd(stage, work / "clean", work / "world", workers), env, None)
        t0 = time.monotonic()
        try:
            attempts = run_with_kills(real_stage_cmd(stage, work / "killed", work / "world", workers), env,
                                      kills.get(stage, 0), noop.seconds, max(0.5, clean.seconds - noop.seconds), rng)
        except RuntimeError as exc:
            results.append(TargetResult(f"real:{stage}", 0, 0, "-", 0, 0, [str(exc)]))
            return results
        after = run_once(real_stage_cmd(stage, work / "killed", work / "world", workers), env, None)
        problems = [] if "processed 0 frame" in after.stderr or "up to date" in after.stderr or stage == "train" \
            else [f"re-run after completion did work: {after.stderr[-500:]}"]
        results.append(TargetResult(f"real:{stage}", sum(a.killed for a in attempts), len(attempts), "-",
                                    time.monotonic() - t0, 0, problems))
    tree_problems, compared = compare_trees(work / "clean", work / "killed")
    results.append(TargetResult("real:all outputs", 0, 0, "-", 0, compared, tree_problems))
    return results


# ------------------------------------------------------------------------- a remote cache

REMOTE_PROTOCOL, REMOTE_TMP_ENV = "soakremote", "SOAK_REMOTE_TMP"


def remote_filesystem() -> type:
    """``soakremote://PATH``: the local PATH as a remote cache. pipeline.cachefs.is_local does not take
    it for the local file system (so stages stage their output and upload it, and frames go through
    zarr's fsspec store), and every file written to it appears whole, as an object of S3 or GCS
    does: written under ``SOAK_REMOTE_TMP`` (on the same disk) and renamed into place."""
    import uuid

    from fsspec.implementations.local import LocalFileSystem

    def temporary() -> str:
        folder = os.environ[REMOTE_TMP_ENV]
        os.makedirs(folder, exist_ok=True)
        return os.path.join(folder, uuid.uuid4().hex)

    class Whole:
        """A file opened for writing that appears at its path only when closed without an error."""

        def __init__(self, path: str, mode: str) -> None:
            self.path, self.tmp = path, temporary()
            self.fh = open(self.tmp, mode)

        def __enter__(self):
            return self

        def __exit__(self, kind, *_):
            if kind is None:
                self.close()
            else:
                self.fh.close()
                os.unlink(self.tmp)

        def close(self) -> None:
            if not self.fh.closed:
                self.fh.close()
                os.makedirs(os.path.dirname(self.path), exist_ok=True)  # an object store has no folders to make
                os.replace(self.tmp, self.path)

        def __getattr__(self, name: str):
            return getattr(self.fh, name)

    class SoakRemoteFileSystem(LocalFileSystem):
        protocol = (REMOTE_PROTOCOL,)

        def unstrip_protocol(self, name: str) -> str:
            return f"{REMOTE_PROTOCOL}://{self._strip_protocol(name)}"

        def _open(self, path, mode="rb", block_size=None, **kwargs):
            if "w" not in mode:
                return super()._open(path, mode, block_size, **kwargs)
            return Whole(self._strip_protocol(path), mode)

        def put_file(self, path1, path2, callback=None, **kwargs):
            path2 = self._strip_protocol(path2)
            self.makedirs(self._parent(path2), exist_ok=True)
            tmp = temporary()
            shutil.copyfile(path1, tmp)
            os.replace(tmp, path2)

    return SoakRemoteFileSystem


def remote_cli(argv: list[str]) -> None:
    """The real `pipeline` CLI with ``soakremote://`` registered (see :func:`remote_filesystem`)."""
    import fsspec

    import pipeline.cli as cli

    fsspec.register_implementation(REMOTE_PROTOCOL, remote_filesystem(), clobber=True)
    cli.main(argv, prog_name="pipeline")


def soak_remote_train(work: Path, clean: Path, kills: int, rng: random.Random) -> TargetResult:
    """The real stages from heatmaps to export on a ``soakremote://`` cache of the world of
    :func:`soak_real`, train uploading after every epoch, each attempt on the other of two staging
    folders ('machines'), under ``kills`` SIGKILLs in all; the outputs are compared with those of
    ``clean`` (the dataset folder of soak_real's clean cache)."""
    remote, world = work / "remote", work.parent / "real" / "world"
    env = subprocess_env(**{REMOTE_TMP_ENV: str(work / "remote-tmp")})

    def cmd(stage: str, machine: int) -> list[str]:
        run = real_stage_cmd(stage, remote, world, 1)
        run[run.index("--cache") + 1] = f"{REMOTE_PROTOCOL}://{remote}"
        return [*python_cmd("remote-cli"), *run[3:], "--set", f"run.staging_dir={work / f'machine-{machine}'}",
                "--set", "run.checkpoint_upload_s=0"]

    upstream = run_once(cmd("calibrate", 0), env, None)
    if upstream.rc != 0:
        return TargetResult("real:train-remote", 0, 0, "-", 0, 0, [f"upstream run failed: {upstream.stderr[-1500:]}"])
    noop = run_once(cmd("calibrate", 0), env, None)
    t0 = time.monotonic()
    attempts: list[Attempt] = []
    try:  # frames through zarr's fsspec store; train resuming across 'machines'; export staged, starting over
        for stage, n_kills, work_s in (("heatmaps", 1, 3.0), ("patches", 1, 3.0), ("train", max(1, kills - 3), 12.0),
                                       ("synthesize", 1, 6.0), ("export", 1, 4.0)):
            attempts += run_with_kills(lambda attempt, _s=stage: cmd(_s, attempt % 2), env, n_kills, noop.seconds,
                                       work_s, rng)
    except RuntimeError as exc:
        return TargetResult("real:train-remote", 0, 0, "-", 0, 0, [str(exc)])
    problems, compared = [], 0
    for name in ("calibrate.zarr", "heatmaps.zarr", "patches.zarr", "train", "synthesize.zarr", "export"):
        if name.endswith(".zarr"):
            found, n = compare_zarr_groups(str(clean / name), str(remote / "synthetic" / name)), 1
        else:
            found, n = compare_trees(clean / name, remote / "synthetic" / name)
        problems += [f"{name}/{p}" for p in found] + [f"nothing compared under {clean / name}"] * (n == 0)
        compared += n
    return TargetResult("real:train-remote", sum(a.killed for a in attempts), len(attempts), "-",
                        time.monotonic() - t0, compared, problems)


# ------------------------------------------------------------------------------- main


def split_kills(total: int, weights: dict[str, float]) -> dict[str, int]:
    """Distribute ``total`` kills over targets in proportion to ``weights`` (at least 1 each)."""
    s = sum(weights.values())
    out = {k: max(1, int(total * w / s)) for k, w in weights.items()}
    keys = list(weights)
    i = 0
    while sum(out.values()) < total:
        out[keys[i % len(keys)]] += 1
        i += 1
    return out


def print_table(rows: list[TargetResult]) -> None:
    print(f"{'target':<20} {'kills':>5} {'runs':>5} {'redone frames':<26} {'compared':>8} {'s':>7}  result")
    for r in rows:
        verdict = "ok" if not r.problems else "FAIL: " + "; ".join(r.problems)[:300]
        print(f"{r.name:<20} {r.kills:>5} {r.attempts:>5} {r.redone:<26} {r.compared:>8} {r.seconds:>7.1f}  {verdict}")
    print(f"{'total':<20} {sum(r.kills for r in rows):>5} {sum(r.attempts for r in rows):>5}")


def soak(kills: int, seed: int, work: Path, real: bool = True) -> list[TargetResult]:
    """The whole soak; returns one row per target."""
    rng = random.Random(seed)
    rows: list[TargetResult] = []
    ok, why = real_pipeline_available(work / "real") if real else (False, "disabled with --fake-only")
    mid_write = (0, 5, 11)
    budget = kills - len(mid_write)
    if ok:
        plan = split_kills(budget, {"fake-serial": 2, "fake-dask": 2, "train-direct": 2, "calibrate": 2,
                                    "heatmaps": 2, "patches": 2, "train": 3, "synthesize": 2, "export": 1,
                                    "train-remote": 7})
    else:
        print(f"real stages skipped: {why}", flush=True)
        plan = split_kills(budget, {"fake-serial": 4, "fake-dask": 3, "train-direct": 3})
    for name, fn in (("fake-serial", lambda: soak_fake(work / "fake-serial", 1, plan["fake-serial"], rng)),
                     ("fake-dask", lambda: soak_fake(work / "fake-dask", 2, plan["fake-dask"], rng, sleep_s=0.3)),
                     ("mid-write", lambda: soak_mid_write(work / "mid-write", mid_write)),
                     ("train-direct", lambda: soak_train_direct(work / "train-direct", plan["train-direct"], rng))):
        print(f"... {name}", flush=True)
        rows.append(fn())
    if ok:
        print("... real stages", flush=True)
        rows += soak_real(work / "real", plan, rng)
        print("... real train on a remote cache", flush=True)
        rows.append(soak_remote_train(work / "remote", work / "real" / "clean" / "synthetic", plan["train-remote"], rng))
    return rows


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "fake-cli":
        fake_cli(argv[1:])
        return 0
    if argv and argv[0] == "remote-cli":
        remote_cli(argv[1:])
        return 0
    if argv and argv[0] == "train-direct":
        train_direct(argv[1])
        return 0
    if argv and argv[0] == "lock-holder":
        lock_holder(*argv[1:5])
        return 0
    parser = argparse.ArgumentParser(prog="python -m tests.soak", description=__doc__.split("\n\n")[0])
    parser.add_argument("--kills", type=int, default=30, help="SIGKILLs to aim for across all targets")
    parser.add_argument("--seed", type=int, default=0, help="seed of the kill moments")
    parser.add_argument("--work", type=Path, default=None, help="work folder (default: a temporary one)")
    parser.add_argument("--keep", action="store_true", help="keep the work folder")
    parser.add_argument("--fake-only", action="store_true", help="skip the real stages")
    args = parser.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="soak-"))
    t0 = time.monotonic()
    try:
        rows = soak(args.kills, args.seed, work, real=not args.fake_only)
    finally:
        if not args.keep and args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    print_table(rows)
    print(f"soak finished in {time.monotonic() - t0:.0f} s (seed {args.seed})")
    return 1 if any(r.problems for r in rows) else 0


if __name__ == "__main__":
    from tests import soak as _module  # run the importable module, so dask workers can unpickle its functions

    sys.exit(_module.main())
