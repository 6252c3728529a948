"""Cache, runner, executors, lock and CLI: resume, invalidation, distributed equality, locking."""

from __future__ import annotations

import os
import re
import shutil
import time
import types
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from pipeline.cache import DONE, EXCLUDED, FAILED, PENDING, frame_store
from pipeline.config import load_config
from pipeline.dataroot import relocate_cache
from pipeline.dirstore import DirStore
from pipeline.errors import ConfigError, FrameError, LockError, PipelineError
from pipeline.executor import Executor, FrameInputs, RunEnv
from pipeline.frame_selection import parse_frames
from pipeline.inspection import cache_status
from pipeline.lock import stage_lock
from pipeline.runner import Pipeline
from tests import fake_stages

IDS = [f"f{i:03d}" for i in range(12)]


def make_pipeline(tmp_path: Path, ids=IDS, executor=None, **overrides) -> Pipeline:
    cfg = load_config("synthetic", overrides, environ={})
    env = RunEnv(cfg=cfg, cache_root=str(tmp_path / "cache"), dataset="fake", data_root=str(tmp_path))
    return Pipeline(fake_stages.STAGES, env, executor or Executor(1), progress=False, log=lambda m: None,
                    frame_lister=lambda: list(ids))


def read_all(pipe: Pipeline) -> dict[str, np.ndarray]:
    out = {}
    for stage in ("calibrate", "heatmaps"):
        store = pipe.env.store(stage)
        for name in ("points", "points_count", "value") if stage == "calibrate" else ("total",):
            out[f"{stage}/{name}"] = np.asarray(store.array(name)[:])
    return out


def calls(path: Path) -> list[str]:
    return path.read_text().splitlines() if path.exists() else []


def test_resume_after_kill_redoes_only_remaining_frames(tmp_path, monkeypatch):
    log = tmp_path / "calls.txt"
    monkeypatch.setenv(fake_stages.CALLS_FILE_ENV, str(log))
    monkeypatch.setenv("FAKE_STAGE_STOP_AFTER", "5")
    with pytest.raises(KeyboardInterrupt):
        make_pipeline(tmp_path / "a").run("heatmaps")
    status = frame_store(str(tmp_path / "a" / "cache"), "fake", "calibrate").status()
    assert (status == DONE).sum() == 5 and (status == PENDING).sum() == 7
    monkeypatch.delenv("FAKE_STAGE_STOP_AFTER")
    log.unlink()
    resumed = make_pipeline(tmp_path / "a")
    resumed.run("heatmaps")
    first_stage_calls = [c for c in calls(log) if c.startswith("calibrate")]
    assert sorted(first_stage_calls) == sorted(f"calibrate {f}" for f in IDS[5:])
    clean = make_pipeline(tmp_path / "b")
    clean.run("heatmaps")
    a, b = read_all(resumed), read_all(clean)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_rerun_of_finished_stage_does_no_frame_work(tmp_path, monkeypatch):
    log = tmp_path / "calls.txt"
    monkeypatch.setenv(fake_stages.CALLS_FILE_ENV, str(log))
    make_pipeline(tmp_path).run("train")
    log.unlink()
    reports = make_pipeline(tmp_path).run("train")
    assert calls(log) == []
    assert [r.processed for r in reports[:2]] == [0, 0]
    assert reports[2].summary["message"] == "up to date"


def test_a_moved_cache_reports_its_files_where_they_are_now(tmp_path):
    """A dataset stage's summary names files in its folder (the train stage's checkpoints, the
    report); after the cache is copied elsewhere an up-to-date run must name the copies."""
    import json
    import shutil

    old = DirStore(str(tmp_path / "a" / "train"))
    old.ensure()
    summary = {"checkpoints": old.path, "report": f"{old.path}/report.md", "sibling": f"{old.path}2/x",
               "outside": str(tmp_path / "elsewhere"), "note": "a plain string", "epochs": 3,
               "message": f"80 frames; report {old.path}/report.md, figures ({old.path}); not {old.path}2/x"}
    old.finish("fp", summary)
    assert old.summary() == summary
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    moved = DirStore(str(tmp_path / "b" / "train")).summary()
    new = tmp_path / "b" / "train"
    assert moved == {**summary, "checkpoints": str(new), "report": str(new / "report.md"),  # the message since 2026-12-05
                     "message": f"80 frames; report {new}/report.md, figures ({new}); not {old.path}2/x"}
    legacy = tmp_path / "b" / "train" / "_stage.json"   # written before the folder's path was kept
    legacy.write_text(json.dumps({"fingerprint": "fp", "summary": summary}))
    assert DirStore(str(tmp_path / "b" / "train")).summary() == summary
    assert DirStore(str(tmp_path / "never")).summary() == {}


def test_a_local_dataset_stage_output_reaches_the_disk_before_it_is_marked_complete(tmp_path, monkeypatch):
    """After a power loss a folder marked complete must hold whole files: its file system is
    flushed (fileio.sync_filesystem) before ``_stage.json`` is written; a remote folder has no
    local disk to flush."""
    out = DirStore(str(tmp_path / "train"))
    out.write_text("metrics.json", "{}")
    import pipeline.dirstore

    synced: list[bool] = []
    monkeypatch.setattr(pipeline.dirstore, "sync_filesystem",
                        lambda path: synced.append(path == out.path and os.path.exists(out.file("_stage.json"))))
    out.finish("fp", {})
    assert synced == [False] and out.fingerprint() == "fp"
    remote = DirStore(f"memory://sync-{os.getpid()}/train")
    remote.finish("fp", {})
    remote.clear()
    assert synced == [False]


def test_a_dataset_stage_folder_records_its_files_and_each_changed_one_is_named(tmp_path):
    """DirStore.write_manifest records each file of the folder (in subfolders too, by its path in
    the folder) with its size and SHA-256, but the bookkeeping files, and says how many;
    check_files counts the files it checked (those recorded: a file added since is neither checked
    nor a problem), hashes each whole file (a change past the first MiB read is found), and calls an
    unreadable record a problem, not an output finished before files were recorded."""
    import json

    from pipeline.dirstore import FILES_MANIFEST, RUN_TOKEN

    out = DirStore(str(tmp_path / "train"))
    out.write_text("metrics.json", "{}")
    big = np.random.default_rng(0).bytes(3 << 19)  # 1.5 MiB: more than one block read
    out.write_bytes("disnet/best.safetensors", big)
    out.write_text(RUN_TOKEN, "token")
    assert out.write_manifest() == 2
    assert sorted(json.loads(Path(out.file(FILES_MANIFEST)).read_text())) == ["disnet/best.safetensors", "metrics.json"]
    out.write_text("notes.txt", "mine")
    assert out.check_files() == (2, [])
    out.write_bytes("disnet/best.safetensors", big[:-1] + bytes([big[-1] ^ 1]))  # the same size, its last byte
    assert out.check_files() == (2, [f"{out.file('disnet/best.safetensors')}: its content changed since the "
                                     f"stage finished (SHA-256)"])
    Path(out.file(FILES_MANIFEST)).write_text('{"metrics.json": [2,')  # cut off
    checked, problems = out.check_files()
    assert checked == 0 and len(problems) == 1 and problems[0].startswith(f"{out.file(FILES_MANIFEST)}: unreadable")


def test_a_staging_folder_holds_the_last_run_by_its_token_or_where_neither_folder_has_one(tmp_path):
    """DirStore.holds_run_of: the same run token in both folders (files or not); a missing or other
    token in either is no. holds_untokened_run_of: a folder from before tokens holding files, with
    no token in either; a token in either (the remote's last run begun elsewhere, or the remote
    wiped since this folder's run began) or no files is no."""
    from pipeline.dirstore import RUN_TOKEN

    remote, work = DirStore(str(tmp_path / "remote")), DirStore(str(tmp_path / "work"))
    work.write_text("runs/1.txt", "epoch 1")
    assert work.holds_untokened_run_of(remote) and not work.holds_run_of(remote)
    remote.write_text(RUN_TOKEN, "a")
    assert not work.holds_untokened_run_of(remote) and not work.holds_run_of(remote)
    work.write_text(RUN_TOKEN, "a")
    assert work.holds_run_of(remote) and not work.holds_untokened_run_of(remote)
    work.write_text(RUN_TOKEN, "b")
    assert not work.holds_run_of(remote)
    Path(remote.file(RUN_TOKEN)).unlink()
    assert not work.holds_run_of(remote) and not work.holds_untokened_run_of(remote)
    empty = DirStore(str(tmp_path / "empty"))
    assert not empty.holds_untokened_run_of(DirStore(str(tmp_path / "none")))


def test_frame_memo_builds_once_per_frame_and_key():
    """FrameInputs.memo: one build per (frame, key); another key or another frame builds again;
    the memo does not collide with the frame's array reads."""
    builds = []

    def build(tag):
        return lambda: builds.append(tag) or np.full(3, len(builds))

    a, b = FrameInputs(None, 0, "000"), FrameInputs(None, 1, "001")
    first = a.memo(("lidar-candidates", "net"), build("a"))
    again = a.memo(("lidar-candidates", "net"), build("a-again"))
    assert again is first and builds == ["a"]
    a.memo(("lidar-candidates", "other net"), build("a2"))
    b.memo(("lidar-candidates", "net"), build("b"))
    assert builds == ["a", "a2", "b"]
    a._cache[("lidar-candidates", "net")] = "an array read"   # what get() would store for that pair
    assert a.memo(("lidar-candidates", "net"), build("a3")) is first
    a.clear_memo()   # what a benchmark timing the same frame again does: builds again, reads kept
    assert a.memo(("lidar-candidates", "net"), build("a4")) is not first and builds[-1] == "a4"
    assert a._cache[("lidar-candidates", "net")] == "an array read"


def test_changing_sigma_recomputes_downstream_only(tmp_path, monkeypatch):
    log = tmp_path / "calls.txt"
    monkeypatch.setenv(fake_stages.CALLS_FILE_ENV, str(log))
    make_pipeline(tmp_path).run("train")
    log.unlink()
    pipe = make_pipeline(tmp_path, **{"heatmap.sigma_px": "50,50"})
    reports = {r.stage: r for r in pipe.run("train")}
    assert reports["calibrate"].processed == 0
    assert reports["heatmaps"].processed == len(IDS)
    assert reports["train"].summary["message"] != "up to date"
    assert all(c.startswith("heatmaps") for c in calls(log))


def test_real_stage_declarations_invalidate_as_declared():
    """Sigma is a key of heatmaps: its fingerprint and every downstream one change, calibrate's not."""
    from stages import all_stages

    def fingerprints(**overrides):
        cfg = load_config("synthetic", overrides, environ={})
        pipe = Pipeline(all_stages(), RunEnv(cfg, "/nonexistent", "x", "/data"), frame_lister=lambda: IDS)
        return {name: pipe.fingerprint(name) for name in pipe.order}

    base, changed = fingerprints(), fingerprints(**{"heatmap.sigma_px": "50,50"})
    same = {n for n in base if base[n] == changed[n]}
    assert same == {"calibrate", "patches"}


NOT_IN_FINGERPRINTS = {
    "run.workers": "how many processes run it", "train.threads": "how many threads run it",
    "run.staging_dir": "where a remote cache's output is staged and copied on this machine",
    "run.progress_every_s": "how often a log is told how far the work is",
    "synth.device": "where the nets run (pipeline.config: no fingerprint holds it)",
    "train.device": "where the nets train, checked before a run (pipeline.config.TRAINING_KEYS: not a net's)",
    "train.nets_from": "in the train stage's extra fingerprint, which every stage after it inherits",
    "radar.name": "words of a message", "radar.rss_unit": "words of a message or a figure's label"}
"""Keys a stage's module may read that need not change its fingerprint (and why)."""


def test_every_setting_a_stage_module_reads_is_in_its_fingerprint():
    """ARCHITECTURE.md: a stage's fingerprint hashes the configuration keys it declares and its
    upstream stages' fingerprints, so that changing a setting recomputes what it changes. Every
    ``cfg.section.key`` a stage's module reads must be among those keys (a key left out of a
    declaration leaves stale outputs that look current), unless NOT_IN_FINGERPRINTS says why not."""
    import inspect

    from pipeline.config import all_keys
    from stages import all_stages

    stages = {s.name: s for s in all_stages()}
    report_only = {"evaluate-frames": {"eval.figure_frames", "eval.pooled_rows_max"}}  # the report's (FRAME_KEYS)

    def declared(name):
        stage = stages[name]
        return set(stage.config_keys).union(*(declared(u) for u in stage.upstream))

    keys = set(all_keys())
    for name, stage in stages.items():
        module = inspect.getmodule(getattr(stage, "process", None) or stage.run)
        read = {f"{a}.{b}" for a, b in re.findall(r"cfg\.(\w+)\.(\w+)", Path(module.__file__).read_text())} & keys
        missing = read - declared(name) - set(NOT_IN_FINGERPRINTS) - report_only.get(name, set())
        assert not missing, f"stage {name} reads {sorted(missing)}, which no fingerprint of it holds"


def test_failed_frame_recorded_and_others_continue(tmp_path):
    ids = IDS[:4] + ["bad004"] + IDS[5:8]
    pipe = make_pipeline(tmp_path, ids=ids)
    reports = pipe.run("heatmaps")
    assert reports[0].failed == 1 and reports[0].done == 7
    store = pipe.env.store("calibrate")
    assert "bad004.bin is truncated" in store.reasons()[4]
    assert pipe.env.store("heatmaps").status()[4] == FAILED  # blocked by its upstream
    with pytest.raises(FrameError, match="truncated"):
        make_pipeline(tmp_path / "strict", ids=ids).run("heatmaps", strict=True)


def test_dataset_stage_reruns_when_its_inputs_finish_other_frames(tmp_path, monkeypatch):
    """A dataset stage records which frames its per-frame inputs had done: frames finished by a
    later run, or a failed frame retried, make it stale (before 2026-12-02 it stayed 'up to date'
    and e.g. evaluate's report silently left such frames out)."""
    import json

    first = {r.stage: r for r in make_pipeline(tmp_path).run("train", frames=list(range(4)))}
    assert first["heatmaps"].done == 4 and first["train"].summary["message"] != "up to date"
    assert make_pipeline(tmp_path).is_current("train")    # nothing changed since
    rest = {r.stage: r for r in make_pipeline(tmp_path).run("train")}
    assert rest["heatmaps"].processed == 8
    assert rest["train"].summary["message"] != "up to date"
    assert make_pipeline(tmp_path).run("train")[2].summary["message"] == "up to date"

    ids = IDS[:4] + ["bad004"] + IDS[5:8]
    pipe = make_pipeline(tmp_path / "retry", ids=ids)
    pipe.run("train")
    monkeypatch.setenv("FAKE_STAGE_FIXED", "1")
    assert make_pipeline(tmp_path / "retry", ids=ids).run("train")[2].summary["message"] == "up to date"
    retried = {r.stage: r for r in make_pipeline(tmp_path / "retry", ids=ids).run("train", retry_failed=True)}
    assert retried["calibrate"].processed == 1 and retried["heatmaps"].done == len(ids)
    assert retried["train"].summary["message"] != "up to date"

    # a frame blocked only by its upstream's failure runs once that is fixed, without --retry-failed
    monkeypatch.delenv("FAKE_STAGE_FIXED")
    blocked = make_pipeline(tmp_path / "blocked", ids=ids)
    blocked.run("heatmaps")
    assert blocked.env.store("heatmaps").status()[4] == FAILED
    monkeypatch.setenv("FAKE_STAGE_FIXED", "1")
    make_pipeline(tmp_path / "blocked", ids=ids).run("calibrate", retry_failed=True)
    again = {r.stage: r for r in make_pipeline(tmp_path / "blocked", ids=ids).run("heatmaps")}
    assert again["heatmaps"].processed == 1 and again["heatmaps"].done == len(ids)
    assert make_pipeline(tmp_path / "blocked", ids=ids).run("heatmaps")[1].processed == 0

    # an output written before dataset stages recorded their frames passes on its fingerprint
    meta_path = Path(pipe.env.dir("train").file("_stage.json"))
    meta = json.loads(meta_path.read_text())
    del meta["frames"]
    meta_path.write_text(json.dumps(meta))
    assert make_pipeline(tmp_path / "retry", ids=ids).is_current("train")


def test_frames_option_limits_work(tmp_path):
    pipe = make_pipeline(tmp_path)
    pipe.run("calibrate", frames=parse_frames("0:4", IDS))
    assert (pipe.env.store("calibrate").status() == DONE).sum() == 4
    assert parse_frames("f003,5", IDS) == [3, 5]
    with pytest.raises(ConfigError):
        parse_frames("nope", IDS)


def test_dask_localcluster_over_tcp_equals_serial(tmp_path, monkeypatch):
    distributed = pytest.importorskip("distributed")
    root = str(Path(__file__).resolve().parents[1])
    monkeypatch.setenv("PYTHONPATH", root + os.pathsep + os.environ.get("PYTHONPATH", ""))
    serial = make_pipeline(tmp_path / "serial")
    serial.run("heatmaps")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  protocol="tcp", dashboard_address=None) as cluster:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1")
        with Executor(scheduler=cluster.scheduler_address, progress=False) as ex:
            ex.check_cluster(str(tmp_path))       # the workers run a probe task and see the cache
            first = tmp_path / "first" / "cache"  # a first run's cache, not there yet (refused until 2026-12-04)
            ex.check_cluster(str(first))
            assert first.is_dir() and not list(first.iterdir())  # the probe's marker is gone
            dist = make_pipeline(tmp_path / "dist", executor=ex)
            dist.run("heatmaps")
    a, b = read_all(serial), read_all(dist)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_a_worker_that_does_not_see_the_probe_marker_is_named(tmp_path, monkeypatch):
    """The probe a worker runs looks for the marker the client wrote; a worker of another machine
    that does not share the cache misses it, and the run stops naming the cache."""
    from pipeline import executor as E

    (tmp_path / "marker").write_bytes(b"")
    assert E._worker_probe(str(tmp_path / "marker")) and not E._worker_probe(str(tmp_path / "other"))

    class Client:  # a cluster whose worker sees another filesystem
        def wait_for_workers(self, n, timeout):
            pass

        def __init__(self, blind_task: bool) -> None:
            self.blind_task = blind_task

        def submit(self, fn, url, pure):
            seen = url.replace(str(tmp_path), str(tmp_path / "x")) if self.blind_task else url
            return types.SimpleNamespace(result=lambda timeout: fn(seen))

        def run(self, fn, url):  # two workers: the second on another filesystem
            return {"tcp://a:1": fn(url), "tcp://b:2": fn(url.replace(str(tmp_path), str(tmp_path / "x")))}

    ex = Executor(scheduler="tcp://127.0.0.1:1", progress=False)
    monkeypatch.setattr(ex, "client", lambda: Client(blind_task=True))
    with pytest.raises(PipelineError, match="does not see the cache"):
        ex.check_cluster(str(tmp_path / "cache"))
    # the probe task ran on a worker that sees the cache, another does not (until 2026-12-04 the
    # run went on and stopped at its first frame there, saying the cache's output did not exist)
    monkeypatch.setattr(ex, "client", lambda: Client(blind_task=False))
    with pytest.raises(PipelineError, match=r"a worker \(tcp://b:2\) does not see the cache"):
        ex.check_cluster(str(tmp_path / "cache"))
    assert not list((tmp_path / "cache").iterdir())
    pytest.importorskip("distributed")
    with pytest.raises(PipelineError, match="dask cluster at foo: cannot connect .*missing port"):
        Executor(scheduler="foo", progress=False).check_cluster(str(tmp_path / "cache"))  # a malformed address
    assert not list((tmp_path / "cache").iterdir())


def test_a_scheduler_address_where_something_else_answers_is_an_error_not_a_hang(tmp_path, monkeypatch):
    """--scheduler at a port where another server listens (the scheduler's dashboard, 8787 instead
    of 8786) never answers dask's handshake: dask's Client waited for it forever until 2026-12-04."""
    import http.server
    import threading

    pytest.importorskip("distributed")
    from pipeline import executor as E

    server = http.server.HTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    address = f"tcp://127.0.0.1:{server.server_address[1]}"
    monkeypatch.setattr(E, "HANDSHAKE_TIMEOUT_S", 1.0)
    try:
        t0 = time.monotonic()
        with pytest.raises(PipelineError, match=f"dask cluster at {address}: something listens there but does not "
                                                f"answer as a dask scheduler \\(no answer within 1 s\\).*dashboard"):
            Executor(scheduler=address, progress=False).check_cluster(str(tmp_path / "cache"))
        assert time.monotonic() - t0 < 30
    finally:
        server.shutdown()
        server.server_close()
    E.check_scheduler_answers(address)  # nothing listens there now: left to the Client, which says so
    E.check_scheduler_answers("foo")    # malformed: the same
    for port in (0, 65536, 99999):      # no TCP port: the Client tried it for 30 s until 2026-12-06
        with pytest.raises(PipelineError, match=f"port {port} is not a TCP port"):
            E.check_scheduler_answers(f"tcp://127.0.0.1:{port}")


def test_second_writer_refused_and_stale_lock_recovered(tmp_path):
    pipe = make_pipeline(tmp_path)
    lock = Path(pipe.env.cache_root) / "fake" / "locks" / "calibrate.lock"
    with stage_lock(str(lock), "stage 'calibrate' of dataset 'fake'"):
        with pytest.raises(LockError, match="being written by another run"):
            pipe.run("calibrate")
    lock.write_text('{"pid": 999999999, "host": "%s", "started": 0}' % os.uname().nodename)
    pipe.run("calibrate")  # the holder is dead: the lock is recovered
    assert not lock.exists()


def test_runs_checking_an_up_to_date_stage_do_not_refuse_each_other(tmp_path):
    """A stage up to date with nothing to run is checked under a shared lock, which runs checking
    it at the same moment all hold. Until 2026-12-04 checking took the exclusive lock, so two runs
    started together could refuse each other on an upstream stage. A stage another run is writing
    (its exclusive lock held: appending frames, retrying failed ones) still stops this run, up to
    date or not, as does one with frames left to compute."""
    from pipeline.lock import held, reading

    pipe = make_pipeline(tmp_path)
    pipe.run("calibrate")
    pipe.run("heatmaps", frames=[0, 1])
    locks = Path(pipe.env.cache_root) / "fake" / "locks"
    calibrate_lock, heatmaps_lock = str(locks / "calibrate.lock"), str(locks / "heatmaps.lock")
    with stage_lock(heatmaps_lock, "stage 'heatmaps' of dataset 'fake'"):
        assert held(heatmaps_lock) and not held(calibrate_lock)
        with pytest.raises(LockError, match="'heatmaps' of dataset 'fake' is being written by another run") as exc:
            make_pipeline(tmp_path).run("heatmaps")
        # the whole command (until 2026-12-08 `pipeline unlock`, which needs the stage, dataset and cache)
        assert f"`pipeline unlock heatmaps --dataset fake --cache {pipe.env.cache_root}`" in str(exc.value)
        assert make_pipeline(tmp_path).run("calibrate")[0].processed == 0
    with reading([calibrate_lock, heatmaps_lock], "another run checking both"):
        calibrate, heatmaps = make_pipeline(tmp_path).run("heatmaps")
        assert [r.processed for r in make_pipeline(tmp_path).run("heatmaps")] == [0, 0]
    assert (calibrate.processed, calibrate.done) == (0, len(IDS))
    assert (heatmaps.processed, heatmaps.done) == (len(IDS) - 2, len(IDS))
    with stage_lock(calibrate_lock, "stage 'calibrate' of dataset 'fake'"):  # up to date, and being written
        with pytest.raises(LockError, match="'calibrate' of dataset 'fake' is being written by another run"):
            make_pipeline(tmp_path).run("heatmaps")
    with reading([calibrate_lock], "another run checking calibrate"):  # and a forced run says so
        with pytest.raises(LockError, match="'calibrate' of dataset 'fake' is being read by another run "
                                            "\\(checked, or read by a stage downstream of it\\)"):
            make_pipeline(tmp_path).run("calibrate", force=True)
    assert not held(calibrate_lock)
    Path(calibrate_lock).write_text('{"pid": 999999999, "host": "%s", "started": 0}' % os.uname().nodename)
    assert not held(calibrate_lock)  # its holder is dead
    Path(calibrate_lock).write_text('{"pid": 1, "host": "another-machine", "started": 0}')
    assert held(calibrate_lock)


def test_many_failed_frames_are_marked_in_one_write_logged_up_to_a_limit_and_their_reasons_read_on_demand(tmp_path):
    """Frames blocked by a failed upstream frame are marked in one write per array (mark() per
    frame re-opened the group), the same codes and reasons; a run logs the first FAILURES_LOGGED
    failures and counts the rest; reasons are read only for the frames asked for."""
    from pipeline import runner as R
    from pipeline.cache import EXCLUDED

    ids = [f"bad{i:03d}" if i % 2 else f"f{i:03d}" for i in range(2 * R.FAILURES_LOGGED + 6)]
    lines = []
    pipe = make_pipeline(tmp_path, ids=ids)
    pipe.log = lines.append
    calibrate, heatmaps = pipe.run("heatmaps")
    bad = [i for i, f in enumerate(ids) if f.startswith("bad")]
    assert calibrate.failed == heatmaps.failed == len(bad)
    failed_lines = [line for line in lines if line.startswith("  failed: ")]
    assert len(failed_lines) == R.FAILURES_LOGGED
    assert f"  ... and {len(bad) - R.FAILURES_LOGGED} more failed frame(s) of calibrate in this run: `pipeline " \
           f"status --reasons N` lists their reasons" in lines
    store = pipe.env.store("heatmaps")
    reasons = store.reasons()
    assert sorted(reasons) == bad and set(reasons.values()) == {"upstream stage calibrate failed for this frame"}
    assert list(store.reasons(limit=2)) == bad[:2] and list(store.reasons(frames=np.array([bad[3], 0]))) == [bad[3]]
    loose = pipe.env.store("calibrate")  # per frame and in one write: the same
    loose.mark_many(np.array([0, 2]), EXCLUDED, "not selected")
    loose.mark(4, EXCLUDED, "not selected")
    assert list(loose.status()[[0, 2, 4]]) == [EXCLUDED] * 3
    assert [loose.read("reason", i) for i in (0, 2, 4)] == ["not selected"] * 3
    rows = {r["stage"]: r for r in cache_status(pipe, reasons=3)}
    assert list(rows["heatmaps"]["reasons"]) == bad[:3]


def test_cli_help_and_errors(tmp_path):
    from pipeline.cli import main

    runner = CliRunner()
    out = runner.invoke(main, ["run", "--help"]).output
    for option in ("--dataset", "--data-root", "--cache", "--workers", "--scheduler", "--frames", "--set",
                   "--strict", "--force"):
        assert option in out
    assert "synthetic" in runner.invoke(main, ["datasets"]).output
    bad = runner.invoke(main, ["run", "heatmaps", "--set", "heatmap.sigma=3"])
    assert bad.exit_code == 2 and "did you mean 'heatmap.sigma_px'" in bad.output
    # a cache of its own: the working tree's cache/vod, where one exists, remembers its data root
    missing = runner.invoke(main, ["run", "heatmaps", "--dataset", "vod", "--cache", str(tmp_path / "cache")])
    assert missing.exit_code == 2 and "--data-root" in missing.output


def test_cli_datasets_columns_line_up_for_every_profile():
    """`pipeline datasets` is a table: each column starts at the same place on every line, and a
    long radar name ('synthetic FMCW (hidden model)') widens its column instead of pushing the
    rest of its line to the right."""
    from pipeline.cli import main
    from pipeline.config import profile_names

    lines = CliRunner().invoke(main, ["datasets"]).output.splitlines()
    names = profile_names()
    assert len(lines) == len(names)
    starts = set()
    for name, line in zip(names, lines):
        cfg = load_config(name, environ={})
        width, height = cfg.camera.working_size
        fields = [name, cfg.radar.name, f"working {width}x{height}", cfg.dataset.description]
        columns, at = [], 0
        for field in fields:
            at = line.index(field, at)
            assert at == 0 or line[at - 2:at] == "  ", (name, line)  # two spaces between columns
            columns.append(at)
            at += len(field)
        starts.add(tuple(columns))
    assert len(starts) == 1, lines


def test_cli_says_where_it_looked_when_a_data_root_holds_no_frames(tmp_path):
    """A wrong --data-root is one line: a missing folder is named as such, an empty one with the
    files a frame of that dataset needs (a user pointing at the folder above the right one)."""
    from pipeline.cli import main
    from pipeline.readers.testing import make_vod_dataset

    runner = CliRunner()
    cache = str(tmp_path / "cache")
    gone = runner.invoke(main, ["run", "calibrate", "--dataset", "vod", "--cache", cache,
                                "--data-root", str(tmp_path / "nowhere")])
    assert gone.exit_code == 2 and f"{tmp_path / 'nowhere'} is not a folder" in gone.output, gone.output
    make_vod_dataset(tmp_path / "data" / "vod", n_frames=2)
    for dataset, needs in (("vod", "radar/training/velodyne/ID.bin and lidar/training/velodyne/ID.bin"),
                           ("kitti", "training/velodyne/ID.bin, training/image_2/ID.png")):
        above = runner.invoke(main, ["run", "calibrate", "--dataset", dataset, "--cache", cache,
                                     "--data-root", str(tmp_path / "data")])
        assert above.exit_code == 2 and "no frames found" in above.output and needs in above.output, above.output
        assert len(above.output.strip().splitlines()) == 1 and "Traceback" not in above.output
    # one sensor's folder missing: the line says what the frames lack, not only what a frame needs
    shutil.rmtree(tmp_path / "data" / "vod" / "lidar" / "training" / "velodyne")
    partial = runner.invoke(main, ["run", "calibrate", "--dataset", "vod", "--cache", cache,
                                   "--data-root", str(tmp_path / "data" / "vod")])
    assert partial.exit_code == 2 and "Traceback" not in partial.output
    assert "reader          skipped missing: 2 (e.g. 00010: no lidar/training/velodyne/00010.bin; 00011: no " in partial.output
    assert partial.output.strip().splitlines()[-1].endswith(
        "frames skipped for want of files (e.g. 00010: no lidar/training/velodyne/00010.bin; "
        "00011: no lidar/training/velodyne/00011.bin)"), partial.output
    assert not (tmp_path / "cache" / "vod").exists()


def test_cli_never_generates_a_world_into_a_folder_the_user_named(tmp_path):
    """A mistyped --data-root for the synthetic dataset is an error, not a new 240-frame world."""
    from pipeline.cli import main

    runner = CliRunner()
    target = tmp_path / "typo"
    out = runner.invoke(main, ["run", "calibrate", "--cache", str(tmp_path / "cache"), "--data-root", str(target)])
    assert out.exit_code == 2 and "no synthetic world there" in out.output and "generate-world" in out.output
    assert not target.exists()
    for args in (["--workers", "0"], ["--wait", "-5"]):
        bad = runner.invoke(main, ["run", "calibrate", "--cache", str(tmp_path / "cache"), *args])
        assert bad.exit_code == 2 and args[0] in bad.output
    assert not (tmp_path / "cache").exists()
    from pipeline.cli import _absolute   # a relative cache would be another folder on a dask worker
    assert _absolute("cache") == os.path.join(os.getcwd(), "cache")
    assert _absolute("s3://bucket/cache") == "s3://bucket/cache" and _absolute("") == ""


def test_a_stage_rebuilt_after_its_output_was_deleted_marks_downstream_stale(tmp_path, monkeypatch):
    """Deleting a stage's output by hand and running again rebuilds it under the same fingerprint;
    the outputs made from the old one must not pass as current (they did before 2026-12-01)."""
    import shutil

    log = tmp_path / "calls.txt"
    monkeypatch.setenv(fake_stages.CALLS_FILE_ENV, str(log))
    pipe = make_pipeline(tmp_path)
    pipe.run("train")
    shutil.rmtree(pipe.env.store("heatmaps").url)
    assert pipe.env.dir("train").fingerprint() == make_pipeline(tmp_path).fingerprint("train")  # looks current
    assert not make_pipeline(tmp_path).is_current("train")  # but its input now has no frame done
    reports = {r.stage: r for r in make_pipeline(tmp_path).run("train")}
    assert reports["calibrate"].processed == 0
    assert reports["heatmaps"].processed == len(IDS)
    assert reports["train"].summary["message"] != "up to date"
    again = {r.stage: r for r in make_pipeline(tmp_path).run("train")}  # and then all is current
    assert again["heatmaps"].processed == 0 and again["train"].summary["message"] == "up to date"


def test_force_recompute_marks_downstream_stale(tmp_path, monkeypatch):
    log = tmp_path / "calls.txt"
    monkeypatch.setenv(fake_stages.CALLS_FILE_ENV, str(log))
    make_pipeline(tmp_path).run("train")
    log.unlink()
    make_pipeline(tmp_path).run("calibrate", force=True)
    assert not make_pipeline(tmp_path).is_current("heatmaps")
    reports = {r.stage: r for r in make_pipeline(tmp_path).run("train")}
    assert reports["calibrate"].processed == 0          # forced once, now current
    assert reports["heatmaps"].processed == len(IDS)    # recomputed from the new calibrate
    assert reports["train"].summary["message"] != "up to date"


def test_force_with_frames_recomputes_those_frames_in_place(tmp_path, monkeypatch):
    """--force --frames on a current frame stage: only those frames are recomputed (the others
    stay done), the same frames of the frame stages after it are to be recomputed, and the dataset
    stages after it are stale; a killed such run leaves them so."""
    log = tmp_path / "calls.txt"
    monkeypatch.setenv(fake_stages.CALLS_FILE_ENV, str(log))
    make_pipeline(tmp_path).run("train")
    before = read_all(make_pipeline(tmp_path))
    log.unlink()
    reports = {r.stage: r for r in make_pipeline(tmp_path).run("calibrate", frames=[2, 5], force=True)}
    assert log.read_text().split() == ["calibrate", IDS[2], "calibrate", IDS[5]]
    assert reports["calibrate"].done == len(IDS)
    pipe = make_pipeline(tmp_path)
    heat = pipe.env.store("heatmaps").status()
    assert list(np.flatnonzero(heat == PENDING)) == [2, 5] and pipe.is_current("heatmaps")
    assert not pipe.is_current("train")
    log.unlink()
    reports = {r.stage: r for r in make_pipeline(tmp_path).run("train")}
    assert reports["heatmaps"].processed == 2 and reports["train"].summary["message"] != "up to date"
    assert sorted(log.read_text().split()[1::2]) == [IDS[2], IDS[5]]
    after = read_all(make_pipeline(tmp_path))
    for key in before:
        np.testing.assert_array_equal(before[key], after[key], err_msg=key)
    # killed after the first recomputed frame: the stages after it still have both frames to redo
    log.unlink()
    monkeypatch.setenv("FAKE_STAGE_STOP_AFTER", "1")
    with pytest.raises(KeyboardInterrupt):
        make_pipeline(tmp_path).run("calibrate", frames=[2, 5], force=True)
    monkeypatch.delenv("FAKE_STAGE_STOP_AFTER")
    pipe = make_pipeline(tmp_path)
    assert list(np.flatnonzero(pipe.env.store("heatmaps").status() == PENDING)) == [2, 5]
    assert not pipe.is_current("train")
    pipe.run("train")
    assert (pipe.env.store("calibrate").status() == DONE).all() and (pipe.env.store("heatmaps").status() == DONE).all()


def test_force_frames_on_a_stage_made_with_other_settings_is_refused_keeping_its_frames(tmp_path, monkeypatch):
    """--force --frames means 'those frames, in place': where a stage the run needs was made with
    other settings (a repair command run without the cache's --set options) it would be made anew
    with only those frames. Refused, naming the stage, with every frame kept (until 2026-12-06 the
    heatmaps below were rebuilt with frames 2 and 5 alone, the other finished frames discarded)."""
    make_pipeline(tmp_path).run("heatmaps")
    other = {"heatmap.sigma_px": "50,50"}  # heatmaps' own setting: calibrate stays current
    for target in ("heatmaps", "train"):  # the stage itself, or one the target needs
        with pytest.raises(ConfigError, match=rf"heatmaps holds {len(IDS)} finished frame\(s\) made with other settings"):
            make_pipeline(tmp_path, **other).run(target, frames=[2, 5], force=True)
    pipe = make_pipeline(tmp_path)
    assert pipe.is_current("heatmaps") and (pipe.env.store("heatmaps").status() == DONE).all()
    # with the settings it was made with, in place as before; without --frames, made anew
    reports = {r.stage: r for r in make_pipeline(tmp_path).run("heatmaps", frames=[2, 5], force=True)}
    assert reports["heatmaps"].processed == 2 and reports["heatmaps"].done == len(IDS)
    reports = {r.stage: r for r in make_pipeline(tmp_path, **other).run("heatmaps", force=True)}
    assert reports["heatmaps"].processed == len(IDS)
    # no output yet: nothing to lose, no refusal
    shutil.rmtree(tmp_path / "cache")
    reports = {r.stage: r for r in make_pipeline(tmp_path).run("heatmaps", frames=[0], force=True)}
    assert reports["heatmaps"].done == 1


def test_moved_data_is_refused_then_relocated_keeping_every_output(tmp_path, monkeypatch):
    """The same frames at another data root would recompute everything: the run stops and says how
    to relocate; relocate checks frames computed from the new place against the cache (other data
    is refused, nothing changed) and keeps every output current."""
    import dataclasses

    def at(root: Path, stages=fake_stages.STAGES) -> Pipeline:
        env = RunEnv(cfg=load_config("synthetic", {}, environ={}), cache_root=str(tmp_path / "cache"),
                     dataset="fake", data_root=str(root))
        return Pipeline(stages, env, Executor(1), progress=False, log=lambda m: None, frame_lister=lambda: list(IDS))

    log = tmp_path / "calls.txt"
    monkeypatch.setenv(fake_stages.CALLS_FILE_ENV, str(log))
    make_pipeline(tmp_path).run("train")
    moved = tmp_path / "moved"
    # the commands it names carry --dataset and --cache: pasted in another folder they act on this cache
    with pytest.raises(PipelineError, match=f"pipeline relocate --dataset fake --cache {tmp_path / 'cache'} "
                                            f"--data-root {moved}`"):
        at(moved).run("train")
    assert "pipeline relocate" in {r["stage"]: r for r in cache_status(at(moved))}["calibrate"]["note"]

    def other_data(inputs, cfg):
        return {**fake_stages.first(inputs, cfg), "value": np.float64(-1.0)}

    other = [dataclasses.replace(fake_stages.STAGES[0], process=other_data), *fake_stages.STAGES[1:]]
    with pytest.raises(PipelineError, match=r"not the data the cache was made from: frame f000 gives another 'value'"):
        relocate_cache(at(moved, other))
    assert make_pipeline(tmp_path).is_current("train")  # nothing changed
    result = relocate_cache(at(moved))
    assert result["stages"] == ["calibrate", "heatmaps", "train"] and result["checked_frames"] == [IDS[0], IDS[6], IDS[-1]]
    log.unlink()
    reports = {r.stage: r for r in at(moved).run("train")}
    assert reports["heatmaps"].processed == 0 and reports["train"].summary["message"] == "up to date"
    assert not log.exists()  # no frame computed again
    with pytest.raises(PipelineError, match="nothing to relocate"):
        relocate_cache(at(moved))
    # going back is a move too; forcing the first stage instead recomputes from the named place
    with pytest.raises(PipelineError, match="pipeline relocate"):
        make_pipeline(tmp_path).run("train")
    reports = {r.stage: r for r in make_pipeline(tmp_path).run("calibrate", force=True)}
    assert reports["calibrate"].processed == len(IDS) and not make_pipeline(tmp_path).is_current("heatmaps")


def test_relocate_without_the_settings_an_output_was_made_with_is_refused(tmp_path, monkeypatch):
    """A relocate given other settings than an output was made with (a --set left out) kept the
    outputs current under its own and moved the first stage, so that no later relocate found the
    others, and the next run recomputed them, the trained nets included (until 2026-12-07). It is
    refused, naming the options, with nothing changed; with them it keeps every output."""
    def at(root: Path, overrides: dict | None = None) -> Pipeline:
        env = RunEnv(cfg=load_config("synthetic", overrides or {}, environ={}), cache_root=str(tmp_path / "cache"),
                     dataset="fake", data_root=str(root))
        return Pipeline(fake_stages.STAGES, env, Executor(1), progress=False, log=lambda m: None,
                        frame_lister=lambda: list(IDS))

    monkeypatch.setenv(fake_stages.CALLS_FILE_ENV, str(tmp_path / "calls.txt"))
    at(tmp_path, {"train.epochs": "3"}).run("train")
    moved = tmp_path / "moved"
    with pytest.raises(PipelineError, match=re.escape("the outputs of train were made with other settings than this command's") +
                       ".*" + re.escape("`--set train.epochs=3`; nothing was changed")):
        relocate_cache(at(moved))
    assert at(tmp_path, {"train.epochs": "3"}).is_current("train")  # still current where it was made
    result = relocate_cache(at(moved, {"train.epochs": "3"}))
    assert result["stages"] == ["calibrate", "heatmaps", "train"]
    assert at(moved, {"train.epochs": "3"}).is_current("train")


def test_another_data_root_with_other_frames_or_settings_is_refused_until_forced(tmp_path, monkeypatch):
    """Until 2026-12-05 a --data-root listing other frames (a mistyped path, a subset of the data) made
    every stage stale and recomputed it without a word, the trained nets included; only a root with
    the same frames and settings (moved data) was refused."""
    def at(root: Path, ids: list[str], overrides: dict | None = None) -> Pipeline:
        env = RunEnv(cfg=load_config("synthetic", overrides or {}, environ={}), cache_root=str(tmp_path / "cache"),
                     dataset="fake", data_root=str(root))
        return Pipeline(fake_stages.STAGES, env, Executor(1), progress=False, log=lambda m: None,
                        frame_lister=lambda: list(ids))

    log = tmp_path / "calls.txt"
    monkeypatch.setenv(fake_stages.CALLS_FILE_ENV, str(log))
    at(tmp_path, IDS).run("train")
    trained = (tmp_path / "cache" / "fake" / "train" / "_stage.json").read_bytes()
    log.unlink()
    other = tmp_path / "other"
    cases = [(IDS[:5] + ["x001"], {}, f"the data root {other} lists 6 frame(s), 5 of them among the cache's {len(IDS)}"),
             (IDS, {"split.seed": "7"}, f"lists the same {len(IDS)} frame(s), but calibrate's settings or code differ "
                                        f"from those of the cache's output, so `pipeline relocate` cannot keep it: made "
                                        f"with split.seed=0 (this command: 7), and `--set split.seed=0` gives this "
                                        f"command the cache's settings")]
    for ids, overrides, frames in cases:
        for target in ("train", "heatmaps"):
            with pytest.raises(PipelineError, match=re.escape(frames)) as exc:
                at(other, ids, overrides).run(target)
            assert f"`pipeline run calibrate --dataset fake --cache {tmp_path / 'cache'} --force --data-root {other}`" \
                in str(exc.value)
            assert "to keep this cache, use another --cache" in str(exc.value)
            with pytest.raises(PipelineError):
                at(other, ids, overrides).run(target, force=True)  # forcing another stage is no answer
        assert frames in {r["stage"]: r for r in cache_status(at(other, ids, overrides))}["calibrate"]["note"]
        # relocate names why it cannot keep the outputs (it said 'nothing to relocate', as if the
        # cache were made from this root already)
        with pytest.raises(PipelineError, match=re.escape(f"cannot relocate the cache, made from the data at "
                                                          f"{tmp_path}, to {other}: it {frames[frames.index('lists'):]}")):
            relocate_cache(at(other, ids, overrides))
    with pytest.raises(PipelineError, match=re.escape(f"lists {len(IDS) - 1} frame(s), {len(IDS) - 1} of them among "
                                                      f"the cache's {len(IDS)} (not listed here: {IDS[3]})")):
        relocate_cache(at(other, IDS[:3] + IDS[4:]))
    assert not log.exists()  # nothing computed, nothing replaced
    assert (tmp_path / "cache" / "fake" / "train" / "_stage.json").read_bytes() == trained
    assert at(tmp_path, IDS).is_current("train")
    reports = {r.stage: r for r in at(other, IDS[:5] + ["x001"]).run("calibrate", force=True)}
    assert reports["calibrate"].processed == 6 and at(other, IDS[:5] + ["x001"]).env.store("calibrate").frame_ids()[-1] == "x001"


def test_invalid_settings_are_refused_before_any_output_is_touched(tmp_path):
    """A stage's check runs for the whole run before any stage recreates or invalidates anything."""
    import dataclasses

    from pipeline.runner import Pipeline as P
    from stages import all_stages

    make_pipeline(tmp_path).run("train")

    def refuse(cfg):
        raise ConfigError("heatmap.sigma_px: refused by the check")

    stages = [dataclasses.replace(s, check=refuse) if s.name == "heatmaps" else s for s in fake_stages.STAGES]
    cfg = load_config("synthetic", {"heatmap.sigma_px": "11,11"}, environ={})
    env = RunEnv(cfg=cfg, cache_root=str(tmp_path / "cache"), dataset="fake", data_root=str(tmp_path))
    pipe = P(stages, env, Executor(1), progress=False, log=lambda m: None, frame_lister=lambda: list(IDS))
    with pytest.raises(ConfigError, match="refused"):
        pipe.run("train")
    assert (pipe.env.store("heatmaps").status() == DONE).all()          # not recreated
    assert make_pipeline(tmp_path).is_current("train")                   # not invalidated
    # the real stages' checks: bad values name their key, with no cache at all
    real = {"synth.placement": "foo", "placement.map_weight": "-1", "train.epochs": "-3", "eval.split": "tset",
            "train.nets": "disnet,bogus", "train.ema_decay": "1"}
    for key, value in real.items():  # refused when the configuration is built (limits) or by the stage's check
        with pytest.raises(ConfigError, match=key.split(".")[-1]):
            cfg = load_config("synthetic", {key: value}, environ={})
            env = RunEnv(cfg=cfg, cache_root=str(tmp_path / "none"), dataset="synthetic", data_root=str(tmp_path))
            P(all_stages(), env, Executor(1), progress=False, log=lambda m: None,
              frame_lister=lambda: list(IDS)).check_config("evaluate")
    assert not (tmp_path / "none").exists()


@pytest.mark.parametrize("key, value", [
    ("camera.working_size", "0,0"), ("radar.max_range_m", "-1"), ("heatmap.sigma_px", "-5,-5"),
    ("heatmap.sigma_px", "nan,nan"), ("patches.r_c_px", "-1"), ("patches.points_per_frame", "-1"),
    ("placement.gate_m", "inf"), ("radar.doppler_sign", "2"), ("train.ema_decay", "1"), ("run.workers", "0"),
    ("run.checkpoint_upload_s", "-1"),
    ("split.fractions", "0.5,0.5,0.5"), ("split.seed", "-1"), ("camera.crop_rows", "300,100"),
    ("camera.crop_rows", "0,5000"), ("radar.rss_max", "nan"), ("radar.rss_min", "100"),
    ("dataset.radar_mount_T_radar_lidar", "1,0,0"),                 # the mount: refused since the 27th session
    ("dataset.radar_mount_T_radar_lidar", "1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,2"),
    ("dataset.radar_mount_T_radar_lidar", "2,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1")])
def test_values_no_stage_could_run_with_are_refused_with_the_key_before_anything_runs(tmp_path, key, value):
    """Until 2026-12-04 these were accepted: calibrate, heatmaps and patches then failed every frame
    (exit 0), after discarding the outputs made with the old settings."""
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config("synthetic", {key: value}, environ={})
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):  # from the environment too
        load_config("synthetic", environ={"PIPELINE__" + key.replace(".", "__").upper(): value})
    from pipeline.cli import main
    out = CliRunner().invoke(main, ["run", "heatmaps", "--dataset", "synthetic", "--cache", str(tmp_path / "c"),
                                    "--set", f"{key}={value}"])
    assert out.exit_code != 0 and key in out.output and "Traceback" not in out.output
    assert not (tmp_path / "c").exists()
    load_config("synthetic", {"radar.doppler_sign": "-1", "train.ema_decay": "0.99", "placement.map_weight": "0",
                              "eval.gate_rss": "inf"}, environ={})  # values at the limits pass; inf: no gate


def test_values_are_parsed_by_their_type_and_each_item_of_a_tuple_is_held_to_its_limit():
    """pipeline.config: a bool reads 1/0, true/false, yes/no, on/off; a whole number is refused a
    fraction (not truncated: 2.5 epochs is no setting); every item of a tuple is checked ('each
    value'); split.fractions sum to 1. The same from --set and from the environment."""
    for text, want in (("0", False), ("1", True), ("off", False), ("yes", True), ("False", False)):
        assert load_config("synthetic", {"export.pcd": text}, environ={}).export.pcd is want
        assert load_config("synthetic", environ={"PIPELINE__EXPORT__PCD": text}).export.pcd is want
    epochs = load_config("synthetic", {"train.epochs": "3"}, environ={}).train.epochs
    assert epochs == 3 and isinstance(epochs, int)
    for bad in ({"train.epochs": "2.5"}, {"heatmap.sigma_px": "5,-5"}, {"split.fractions": "0.5,0.3,0.15"}):
        key = next(iter(bad))
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            load_config("synthetic", bad, environ={})
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            load_config("synthetic", environ={"PIPELINE__" + key.replace(".", "__").upper(): bad[key]})
    with pytest.raises(ConfigError, match="train.epochs"):  # a TOML float where a whole number goes
        load_config("synthetic", environ={}).with_overrides({"train.epochs": 2.5})


def test_environment_errors_name_the_variable_and_a_malformed_variable_is_refused(tmp_path):
    """Until 2026-12-05 a bad value was reported under the key alone ('train.epochs'), which the user
    never typed, and PIPELINE__TRAIN_EPOCHS (one underscore) was ignored without a word."""
    with pytest.raises(ConfigError, match=r"environment variable PIPELINE__TRAIN__EPOCHS='abc': .*train\.epochs"):
        load_config("synthetic", environ={"PIPELINE__TRAIN__EPOCHS": "abc"})
    for var, meant in [("PIPELINE__TRAIN_EPOCHS", "PIPELINE__TRAIN__EPOCHS"),
                       ("PIPELINE__TRAIN__EPOCH", "PIPELINE__TRAIN__EPOCHS"),
                       ("PIPELINE__HEATMAP__SIGMA", "PIPELINE__HEATMAP__SIGMA_PX"),
                       ("PIPELINE__COUNT_GRAD_SCALE", "PIPELINE__TRAIN__COUNT_GRAD_SCALE"), ("PIPELINE__XYZ", None)]:
        with pytest.raises(ConfigError, match=f"environment variable {var} names no configuration key") as exc:
            load_config("synthetic", environ={var: "3"})
        assert (f"did you mean {meant}?" in str(exc.value)) if meant else "did you mean" not in str(exc.value)
    assert load_config("synthetic", environ={"PIPELINE__TRAIN__EPOCHS": "3"}).train.epochs == 3
    assert load_config("synthetic", environ={"pipeline__train__epochs": "5"}).train.epochs == 5  # was ignored
    assert load_config("synthetic", environ={"PIPELINE__TRAIN__COUNT_GRAD_SCALE": "0.5"}).train.count_grad_scale == 0.5
    load_config("synthetic", environ={"PIPELINE_CACHE": "x"})  # the CLI's own variable (one underscore) is no key
    # --set wins over the environment, so a bad variable it overrides is never read
    assert load_config("synthetic", {"train.epochs": "4"}, environ={"PIPELINE__TRAIN__EPOCHS": "abc"}).train.epochs == 4
    with pytest.raises(ConfigError, match=r"^unknown configuration key 'train.Epochs'; did you mean 'train.epochs'"):
        load_config("synthetic", {"train.Epochs": "4"}, environ={"PIPELINE__TRAIN__EPOCHS": "abc"})  # the --set named
    with pytest.raises(ConfigError, match="environment variables PIPELINE__TRAIN__EPOCHS and pipeline__train__epochs "
                                          "both set train.epochs"):
        load_config("synthetic", environ={"PIPELINE__TRAIN__EPOCHS": "3", "pipeline__train__epochs": "5"})
    from pipeline.cli import main
    out = CliRunner().invoke(main, ["run", "heatmaps", "--dataset", "synthetic", "--cache", str(tmp_path / "c")],
                             env={"PIPELINE__TRAIN_EPOCHS": "3"})
    assert out.exit_code != 0 and "PIPELINE__TRAIN__EPOCHS?" in out.output and "Traceback" not in out.output
    assert not (tmp_path / "c").exists()


def test_cli_names_a_cache_url_fsspec_cannot_open_and_an_unknown_stage_to_unlock(tmp_path):
    """Until 2026-12-04: a raw ImportError or ValueError traceback for the URL; `unlock heatmap`
    (a typo) said there was no lock and exited 0."""
    from pipeline.cli import main

    for url, words in (("s3x://bucket/cache", "Protocol not known"), ("nosuchfs://b/c", "not known")):
        for args in (["status"], ["run", "calibrate"], ["unlock", "heatmaps"]):
            out = CliRunner().invoke(main, [*args, "--dataset", "vod", "--cache", url, "--data-root", str(tmp_path)])
            assert out.exit_code == 2 and "Traceback" not in out.output, (args, out.output)
            assert f"--cache {url}: fsspec cannot open it" in out.output and words in out.output
            assert "e.g. s3:// with `pip install s3fs`" in out.output
    import importlib.util
    if importlib.util.find_spec("gcsfs") is None:  # a known protocol whose package is missing: fsspec names it
        out = CliRunner().invoke(main, ["status", "--dataset", "vod", "--cache", "gs://b/c"])
        assert out.exit_code == 2 and "gcsfs" in out.output and out.output.rstrip().endswith("install the package it names")
    out = CliRunner().invoke(main, ["unlock", "heatmap", "--dataset", "synthetic", "--cache", str(tmp_path)])
    assert out.exit_code == 2 and "did you mean 'heatmaps'" in out.output
    out = CliRunner().invoke(main, ["unlock", "heatmaps", "--dataset", "synthetic", "--cache", str(tmp_path)])
    assert out.exit_code == 0 and "no lock at" in out.output


def test_a_killed_forced_rebuild_leaves_downstream_stale(tmp_path, monkeypatch):
    """Downstream outputs are marked stale before the rebuild starts, not after it ends."""
    log = tmp_path / "calls.txt"
    monkeypatch.setenv(fake_stages.CALLS_FILE_ENV, str(log))
    make_pipeline(tmp_path).run("train")
    log.unlink()
    monkeypatch.setenv("FAKE_STAGE_STOP_AFTER", "3")
    with pytest.raises(KeyboardInterrupt):
        make_pipeline(tmp_path).run("calibrate", force=True)
    assert not make_pipeline(tmp_path).is_current("heatmaps")
    assert not make_pipeline(tmp_path).is_current("train")


def test_the_stale_marks_of_a_rebuild_say_it_is_under_way(tmp_path):
    """The downstream stages are marked stale as the rebuild starts, above its progress and its own
    line: until 2026-12-07 the log said 'upstream calibrate was recomputed' there, also where the
    rebuild was then cut off."""
    make_pipeline(tmp_path).run("train")
    lines: list[str] = []
    pipe = make_pipeline(tmp_path)
    pipe.log = lines.append
    pipe.run("calibrate", force=True)
    marks = [line for line in lines if "marked stale" in line]
    assert marks and all(line.endswith("marked stale (upstream calibrate is being recomputed)") for line in marks)
    assert lines.index(marks[-1]) < next(i for i, line in enumerate(lines) if line.startswith("calibrate "))


def test_force_on_a_dataset_stage_starts_from_scratch_and_status_follows_upstream(tmp_path):
    pipe = make_pipeline(tmp_path)
    pipe.run("train")
    leftover = Path(pipe.env.dir("train").file("checkpoint.safetensors"))
    leftover.write_bytes(b"an earlier run's state")
    make_pipeline(tmp_path).run("train", force=True)
    assert not leftover.exists() and (leftover.parent / "total.txt").exists()
    # status: a stage whose upstream would be rebuilt is not current, whatever its own record says
    changed = make_pipeline(tmp_path, **{"heatmap.sigma_px": "12,12"})
    rows = {r["stage"]: r for r in cache_status(changed)}
    assert rows["calibrate"]["current"] and not rows["heatmaps"]["current"] and not rows["train"]["current"]


def test_frames_that_select_nothing_and_bad_steps_are_errors():
    for spec in ("999:1000", "5:1", "0:10:0", "1:2:3:4"):
        with pytest.raises(ConfigError, match="--frames"):
            parse_frames(spec, IDS)


def test_unlock_refuses_a_lock_of_a_running_process(tmp_path):
    import json
    import socket

    from pipeline.lock import remove_lock

    lock = tmp_path / "x.lock"
    lock.write_text(json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "started": 0}))
    with pytest.raises(LockError, match="still running"):
        remove_lock(str(lock))
    assert lock.exists()
    lock.write_text(json.dumps({"pid": 2 ** 22 + 12345, "host": socket.gethostname(), "started": 0}))
    assert remove_lock(str(lock)) and not lock.exists()
    assert remove_lock(str(lock)) is False



def _even_frames_only(tmp_path, stage: str) -> Pipeline:
    """The fake stages over IDS, ``stage`` selecting the even frames only."""
    import dataclasses

    def even(inputs, cfg):
        return np.arange(len(inputs.frame_ids)) % 2 == 0

    stages = [dataclasses.replace(s, select=even) if s.name == stage else s for s in fake_stages.STAGES]
    env = RunEnv(cfg=load_config("synthetic", environ={}), cache_root=str(tmp_path / "cache"), dataset="fake",
                 data_root=str(tmp_path))
    return Pipeline(stages, env, Executor(1), progress=False, log=lambda m: None, frame_lister=lambda: list(IDS))

def test_frames_the_configuration_leaves_out_are_excluded_whatever_frames_says(tmp_path):
    """With --frames the pending count is still what is left to do: frames the stage's select
    leaves out are excluded at once, not left pending."""
    report = _even_frames_only(tmp_path, "heatmaps").run("heatmaps", frames=[0, 1])[1]
    assert (report.done, report.excluded, report.pending) == (1, 6, 5)


def test_an_output_being_read_is_not_rewritten_and_the_other_way_round(tmp_path):
    """A run reading a stage's output (a stage downstream of it) holds off a run that would rewrite
    it, e.g. `run synthesize --force` while `run evaluate` reads synthesize; and a run does not read
    an output another run is writing. Both stop with a message, or wait with --wait."""
    import threading

    from pipeline.lock import reading, rewriting

    url = str(tmp_path / "locks" / "synthesize.lock")
    with reading([url], "stage 'evaluate'"):
        with stage_lock(url, "stage 'synthesize'"):   # checking it, or appending frames: allowed
            with pytest.raises(LockError, match="being read by another run"):
                with rewriting(url, "stage 'synthesize'"):
                    pass
        with reading([url], "stage 'export'"):   # readers share
            pass
    with rewriting(url, "stage 'synthesize'"):
        with pytest.raises(LockError, match="'evaluate': an input of it is being rewritten"):
            with reading([url], "stage 'evaluate'"):
                pass
    done = threading.Event()

    def read_briefly():
        with reading([url], "stage 'evaluate'"):
            done.set()
            time.sleep(0.6)

    reader = threading.Thread(target=read_briefly)
    reader.start()
    done.wait(5)
    t0 = time.monotonic()
    with rewriting(url, "stage 'synthesize'", wait_s=10):   # waits for the reader, then rewrites
        assert time.monotonic() - t0 > 0.3
    reader.join()


def test_failed_frames_are_retried_only_when_asked(tmp_path, monkeypatch):
    """A failed frame keeps its failure (and is not tried again) when a later run finishes the
    frames still pending; --retry-failed runs it again, and only it."""
    log = tmp_path / "calls.txt"
    monkeypatch.setenv(fake_stages.CALLS_FILE_ENV, str(log))
    ids = IDS[:2] + ["bad002"] + IDS[3:6]
    make_pipeline(tmp_path, ids=ids).run("calibrate", frames=[0, 1, 2])
    assert make_pipeline(tmp_path, ids=ids).env.store("calibrate").status()[2] == FAILED
    log.unlink()
    monkeypatch.setenv("FAKE_STAGE_FIXED", "1")  # the file was replaced, but nobody asked for a retry
    report = make_pipeline(tmp_path, ids=ids).run("calibrate")[0]
    assert sorted(calls(log)) == sorted(f"calibrate {f}" for f in ids[3:])
    assert (report.processed, report.failed, report.done) == (3, 1, 5)
    log.unlink()
    report = make_pipeline(tmp_path, ids=ids).run("calibrate", retry_failed=True)[0]
    assert calls(log) == ["calibrate bad002"] and (report.failed, report.done) == (0, len(ids))


def test_frames_whose_upstream_frame_is_excluded_are_excluded_not_failed(tmp_path):
    """A frame the first stage's configuration leaves out is excluded downstream too: not counted
    as failed (a --strict run would stop on it) nor retried."""
    pipe = _even_frames_only(tmp_path, "calibrate")
    calibrate, heatmaps = pipe.run("heatmaps", strict=True)
    odd = np.arange(len(IDS)) % 2 == 1
    for report in (calibrate, heatmaps):
        assert (report.done, report.excluded, report.failed) == (len(IDS) // 2, len(IDS) // 2, 0), report.stage
    assert (pipe.env.store("heatmaps").status()[odd] == EXCLUDED).all()


def test_a_run_does_not_read_an_input_another_run_is_rewriting(tmp_path):
    """The frames of a stage read its upstream outputs: while another run recreates one of them
    (`run calibrate --force`), a run that would compute frames from it stops instead of reading
    half-rewritten inputs."""
    from pipeline.lock import rewriting

    pipe = make_pipeline(tmp_path)
    pipe.run("calibrate")
    calibrate_lock = str(Path(pipe.env.cache_root) / "fake" / "locks" / "calibrate.lock")
    with rewriting(calibrate_lock, "stage 'calibrate' of dataset 'fake'"):
        with pytest.raises(LockError, match="an input of it is being rewritten"):
            make_pipeline(tmp_path).run("heatmaps")
    store = pipe.env.store("heatmaps")
    assert not store.exists() or not (store.status() == DONE).any()


def test_force_recomputes_the_target_only_not_its_current_upstream_stages(tmp_path, monkeypatch):
    log = tmp_path / "calls.txt"
    monkeypatch.setenv(fake_stages.CALLS_FILE_ENV, str(log))
    make_pipeline(tmp_path).run("heatmaps")
    log.unlink()
    calibrate, heatmaps = make_pipeline(tmp_path).run("heatmaps", force=True)
    assert (calibrate.processed, heatmaps.processed) == (0, len(IDS))
    assert sorted(calls(log)) == sorted(f"heatmaps {f}" for f in IDS)


@pytest.mark.parametrize("n", [1, 5, 7, 8, 9, 31, 33, 100])
@pytest.mark.parametrize("slots", [1, 2, 3])
def test_dask_batches_hold_every_frame_once_in_order(n, slots):
    """A frame left out of every batch would stay pending after a run that reports no error."""
    from pipeline.executor import MAX_BATCH, _batches

    todo = [(i, f"f{i:03d}") for i in range(n)]
    batches = _batches(todo, slots)
    assert [item for batch in batches for item in batch] == todo
    sizes = [len(b) for b in batches]
    assert all(sizes) and max(sizes) <= MAX_BATCH
    # they shrink (large ones are handed out first) down to one frame per worker at the end, so
    # that no worker idles while another finishes a large batch
    assert sizes == sorted(sizes, reverse=True)
    assert sizes[-min(n, slots):] == [1] * min(n, slots)
    if n >= 100:
        assert len(batches) <= n / 3  # still batched: one task per frame scheduled too slowly


def test_dask_batches_of_a_long_run_are_large_until_its_end():
    from pipeline.executor import MAX_BATCH, _batches

    sizes = [len(b) for b in _batches([(i, str(i)) for i in range(20_000)], 2)]
    assert sizes.count(MAX_BATCH) > 20_000 // MAX_BATCH - 20 and len(sizes) < 20_000 / MAX_BATCH + 20


def test_frame_random_streams_depend_on_seed_salt_and_frame_only():
    """FrameInputs.rng: the same stream on any worker for (seed, salt, frame), another for another
    salt (e.g. patches' point sampling against its placement rows) or another frame."""
    a, b = FrameInputs(None, 3, "003"), FrameInputs(None, 4, "004")
    draw = lambda f, seed, salt: f.rng(seed, salt).random(4)  # noqa: E731
    np.testing.assert_array_equal(draw(a, 1, 11), draw(FrameInputs(None, 3, "other id"), 1, 11))
    assert not np.array_equal(draw(a, 1, 11), draw(a, 1, 12))
    assert not np.array_equal(draw(a, 1, 11), draw(b, 1, 11))
    assert not np.array_equal(draw(a, 1, 11), draw(a, 2, 11))


def test_a_frames_arrays_of_the_same_name_from_two_stages_are_told_apart(tmp_path):
    """FrameInputs.get caches each (stage, array) read once per frame: an array of one stage must
    not be served for the array of the same name of another (e.g. 'points' of calibrate and of
    synthesize)."""
    from pipeline.stage import ArraySpec

    pipe = make_pipeline(tmp_path)
    spec = (ArraySpec("points", (2,), "float32", "-"),)
    for stage, value in (("calibrate", 1.0), ("synthesize", 2.0)):
        pipe.env.store(stage).create("fp", IDS, spec, {"points": (2,)}, {})
        pipe.env.store(stage).write_frame(0, {"points": np.full(2, value, np.float32)}, spec)
    frame = FrameInputs(pipe.env, 0, IDS[0])
    assert frame.get("calibrate", "points").tolist() == [1.0, 1.0]
    assert frame.get("synthesize", "points").tolist() == [2.0, 2.0]
    assert frame.get("calibrate", "points").tolist() == [1.0, 1.0]


def test_a_frame_function_output_is_checked_before_it_is_written():
    """A missing array, a wrong shape, too many rows, and a NaN or inf in an array declared finite
    each fail the frame with the array's name; NaN elsewhere (a metric that does not apply) is kept."""
    from pipeline.executor import _check_outputs
    from pipeline.stage import ArraySpec, FrameStage

    specs = (ArraySpec("points", (4, 3), "float32", "m", fill=np.nan, ragged=True, finite=True),
             ArraySpec("metric", (2,), "float64", "m", fill=np.nan))
    stage = FrameStage(name="s", upstream=(), config_keys=(), outputs=lambda cfg: specs, process=None)
    cfg = load_config("synthetic", environ={})

    def check(points, metric=np.zeros(2)):
        _check_outputs(stage, cfg, specs, {"points": points, "metric": metric})

    check(np.zeros((2, 3)), np.array([np.nan, 1.0]))
    with pytest.raises(FrameError, match="no 'metric'"):
        _check_outputs(stage, cfg, specs, {"points": np.zeros((2, 3))})
    with pytest.raises(ValueError, match=r"points: expected per-frame shape \(4, 3\), got \(2, 2\)"):
        check(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="points: 5 rows exceed the capacity 4"):
        check(np.zeros((5, 3)))
    for bad in (np.nan, np.inf, -np.inf):
        points = np.zeros((3, 3))
        points[1, 2] = bad
        with pytest.raises(ValueError, match=r"points: 1 of 9 values are not finite .* at index \(1, 2\)"):
            check(points)
    points = np.zeros((3, 3))
    points[2] = np.nan
    with pytest.raises(ValueError, match=r"points: 3 of 9 values are not finite .* at index \(2, 0\)"):
        check(points)


def test_the_outputs_the_next_stages_and_the_export_read_are_declared_finite():
    """Those a NaN would reach a detector through (points, RSS, maps, PlaceNet's rows); calibrate's
    labels are not (NaN is an unknown object velocity), nor evaluate's metrics (a metric that does
    not apply)."""
    from stages import all_stages

    cfg = load_config("synthetic", environ={})
    finite = {(s.name, a.name) for s in all_stages() if hasattr(s, "outputs") for a in s.outputs(cfg) if a.finite}
    assert {("calibrate", "lidar"), ("calibrate", "radar"), ("calibrate", "K"), ("calibrate", "T_radar_cam"),
            ("calibrate", "T_radar_lidar"), ("calibrate", "ego_velocity"), ("heatmaps", "heatmap"),
            ("patches", "point"), ("patches", "rss"), ("patches", "range_image"), ("patches", "place_features"),
            ("patches", "place_count"), ("synthesize", "points"), ("synthesize", "pred_map"),
            ("synthesize", "n_hat")} <= finite
    assert ("calibrate", "labels") not in finite and not any(stage == "evaluate-frames" for stage, _ in finite)


def test_a_key_added_later_is_left_out_of_fingerprints_at_its_old_value():
    """synth.rss_sampling joined synthesize's and evaluate's fingerprints on 2026-12-06: at 'mean'
    (what every earlier output was made with) the fingerprint is the one without the key, so no
    output recomputes; at 'residual' it differs."""
    from pipeline.config import ADDED_KEYS

    from stages.evaluate import CONFIG_KEYS as EVALUATE_KEYS
    from stages.synthesize import CONFIG_KEYS as SYNTHESIZE_KEYS

    cfg = load_config("synthetic", {}, environ={})
    residual = cfg.with_overrides({"synth.rss_sampling": "residual"})
    assert ADDED_KEYS["synth.rss_sampling"] == cfg.synth.rss_sampling == "mean"
    for keys in (SYNTHESIZE_KEYS, EVALUATE_KEYS):
        assert "synth.rss_sampling" in keys
        without = tuple(k for k in keys if k != "synth.rss_sampling")
        assert cfg.fingerprint(keys) == cfg.fingerprint(without)
        assert residual.fingerprint(keys) != cfg.fingerprint(keys)
        assert residual.fingerprint(without) == cfg.fingerprint(without)


def test_the_patience_keys_leave_trained_caches_current_at_zero():
    """train.patience and placement.patience joined the train stage's fingerprint on 2026-12-07: at
    0 (no early stop, as every earlier train ran) it is the fingerprint without them, so an upgraded
    cache does not retrain, nor recompute what was synthesized from its nets; another value differs."""
    from stages.train import CONFIG_KEYS

    patience = ("train.patience", "placement.patience")
    without = tuple(k for k in CONFIG_KEYS if k not in patience)
    assert set(patience) <= set(CONFIG_KEYS)
    for profile in ("astyx", "synthetic"):
        cfg = load_config(profile, {}, environ={})
        assert cfg.fingerprint(CONFIG_KEYS) == cfg.fingerprint(without)
        for key in patience:
            assert cfg.with_overrides({key: "3"}).fingerprint(CONFIG_KEYS) != cfg.fingerprint(CONFIG_KEYS)


def test_a_key_of_another_reader_leaves_a_dataset_s_fingerprints_alone():
    """dataset.world_* only shape the synthetic world, dataset.radar_mount_T_radar_lidar only
    KITTI's radar: set for another dataset (PIPELINE__DATASET__WORLD_FRAMES=2400 from `make
    demo-large` left in a shell, say) they recomputed its whole cache from calibrate on until
    2026-12-06; now its fingerprints stay those of before, and the reader that uses a key still
    sees it change."""
    import hashlib
    import json

    from pipeline.config import READER_KEYS, jsonable
    from stages.calibrate import CONFIG_KEYS

    world = {"dataset.world_frames": "40", "dataset.world_seed": "3", "dataset.world_resolution": "320,192",
             "dataset.world_sequence_len": "10"}
    mount = {"dataset.radar_mount_T_radar_lidar": "1,0,0,-1.5,0,1,0,0,0,0,1,1.0,0,0,0,1"}
    doppler_field = {"dataset.msc_doppler_field": "power"}
    assert set(world) | set(mount) | set(doppler_field) == set(READER_KEYS) <= set(CONFIG_KEYS)
    for profile in ("astyx", "vod", "msc", "kitti", "synthetic"):
        cfg = load_config(profile, {}, environ={})
        for overrides in (world, mount, doppler_field):
            changed = cfg.with_overrides(overrides).fingerprint(CONFIG_KEYS) != cfg.fingerprint(CONFIG_KEYS)
            assert changed == (READER_KEYS[next(iter(overrides))] == cfg.dataset.reader), (profile, overrides)
        # the profiles as they are keep the fingerprint of before the rule: every key at its value
        # (dataset.msc_doppler_field joined on 2026-12-07, in ADDED_KEYS: left out at its default)
        before = json.dumps({k: jsonable(cfg.get(k)) for k in sorted(CONFIG_KEYS) if k != "dataset.msc_doppler_field"},
                            sort_keys=True)
        assert cfg.fingerprint(CONFIG_KEYS) == hashlib.sha256(before.encode()).hexdigest()[:16]


def test_the_stages_and_the_cli_load_without_torch():
    """`pipeline status` and every command that only lists the stages took 0.8 s longer (1.9 s
    against 1.1 s on the demo's cache) while stages.train imported torch through pipeline.checkpoint
    at module level; a stage imports torch when it runs a net. A net's training fingerprint, which
    status compares with a checkpoint's (an unfinished train, the ablations' runs), is torch-free
    too (until 2026-12-07 it imported torch through pipeline.training), and so are the stages'
    checks of the configuration with the devices 'auto' and 'cpu', which every `pipeline run`
    makes (until 2026-12-08 train's imported torch). Nor do these import scipy.stats and
    scipy.optimize (about 1 s together; until 2026-12-08 pipeline.metrics imported them)."""
    import subprocess
    import sys

    code = ("import sys; from stages import all_stages; stages = all_stages(); import pipeline.cli; "
            "from pipeline.config import load_config; from pipeline.continuation import default_fingerprint; "
            "[default_fingerprint(load_config('synthetic', {}, environ={}), n) for n in ('disnet', 'rssnet')]; "
            "checks = [s.check for s in stages if getattr(s, 'check', None)]; assert len(checks) >= 3, checks; "
            "[c(load_config('synthetic', {'train.device': d, 'synth.device': d}, environ={})) for c in checks "
            "for d in ('auto', 'cpu')]; "
            "import stages.ablations; assert 'torch' not in sys.modules, 'torch imported'; "
            "assert not {'scipy.stats', 'scipy.optimize'} & set(sys.modules), 'scipy.stats or scipy.optimize imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(__file__).resolve().parents[1])
