"""A cache on a non-local fsspec filesystem (memory://, standing in for s3:// or gcs://): frames
go through zarr's own path, not the chunk files, and must give what a local cache gives, resume
the same way, and name a damaged chunk. Small pipelines of tests/fake_stages.py."""

from __future__ import annotations

import json
import re
import shutil
import time
import uuid
from pathlib import Path

import fsspec
import numpy as np
import pytest

from pipeline.cache import DONE, FAILED, PENDING
from pipeline.dirstore import RUN_TOKEN, DirStore
from pipeline.config import load_config
from pipeline.errors import CacheError, ChunkError
from pipeline.executor import Executor, RunEnv
from pipeline.inspection import cache_status, verify_cache
from pipeline.runner import Pipeline, StagedUploads
from tests import fake_stages
from tests.test_damaged_cache import IDS


def _assert_same_frames(local: Pipeline, far: Pipeline) -> None:
    """Every frame of ``far``'s fake stages is done and equal to ``local``'s."""
    for stage, names in (("calibrate", ("points", "value")), ("heatmaps", ("total",))):
        a, b = local.env.store(stage), far.env.store(stage)
        assert (b.status() == DONE).all()
        for name in names:
            for i in range(len(IDS)):
                np.testing.assert_array_equal(a.read(name, i), b.read(name, i), err_msg=f"{stage}/{name} {i}")


def _pipe(cache_root: str, data_root: Path) -> Pipeline:
    env = RunEnv(cfg=load_config("synthetic", {}, environ={}), cache_root=cache_root, dataset="fake",
                 data_root=str(data_root))
    return Pipeline(fake_stages.STAGES, env, Executor(1), progress=False, log=lambda m: None,
                    frame_lister=lambda: list(IDS))


@pytest.fixture
def remote():
    name = f"remote-{uuid.uuid4().hex[:8]}"
    yield f"memory://{name}"
    fs = fsspec.filesystem("memory")
    if fs.exists(f"/{name}"):
        fs.rm(f"/{name}", recursive=True)


def test_a_remote_cache_gives_what_a_local_one_gives_and_resumes(tmp_path, remote):
    local, far = _pipe(str(tmp_path / "cache"), tmp_path), _pipe(remote, tmp_path)
    local.run("train")
    reports = far.run("train")
    assert [r.processed for r in reports if r.stage in ("calibrate", "heatmaps")] == [len(IDS), len(IDS)]
    _assert_same_frames(local, far)
    texts = [d.fs.cat_file(d.file("total.txt")) for d in (far.env.dir("train"), local.env.dir("train"))]
    assert texts[0] == texts[1] and float(texts[0]) > 0
    again = far.run("train")  # resumed: nothing recomputed
    assert [(r.action, r.processed) for r in again[:2]] == [("resumed", 0), ("resumed", 0)]
    assert again[2].summary["message"] == "up to date"
    status, errors = far.env.store("heatmaps").verify()
    assert (status == DONE).all() and errors == {}


def test_a_damaged_chunk_of_a_remote_cache_is_named(tmp_path, remote):
    pipe = _pipe(remote, tmp_path)
    pipe.run("calibrate")
    fs = fsspec.filesystem("memory")
    chunk = f"{remote.removeprefix('memory://')}/fake/calibrate.zarr/value/c/3"
    fs.pipe_file(f"/{chunk}", b"garbage")
    with pytest.raises(ChunkError) as exc:
        pipe.env.store("calibrate").read("value", 3)
    assert exc.value.frame == IDS[3] and "calibrate.zarr/value" in str(exc.value)
    errors = pipe.env.store("calibrate").verify()[1]
    assert list(errors) == [3]
    pipe.run("heatmaps")  # the frame reading it fails, naming it; the others finish
    reasons = pipe.env.store("heatmaps").reasons()
    assert list(reasons) == [3] and "calibrate.zarr/value, frame 3" in reasons[3]


def test_a_damaged_stage_record_of_a_remote_cache_stops_the_run(tmp_path, remote):
    """A remote dataset stage's _stage.json cut short is a MetadataError naming it, as on a local
    cache (before, the output was taken for unfinished and recomputed without a word); deleted, it
    means unfinished."""
    from pipeline.errors import MetadataError

    pipe = _pipe(remote, tmp_path)
    pipe.run("train")
    out = pipe.env.dir("train")
    saved = out.fs.cat_file(out.file("_stage.json"))
    out.fs.pipe_file(out.file("_stage.json"), saved[:40])
    with pytest.raises(MetadataError, match=re.escape(f"{out.url}/_stage.json: the record of stage output train "
                                                      "cannot be read (")):
        pipe.run("train")
    with pytest.raises(MetadataError, match="`pipeline run train --dataset fake --cache memory://"):
        out.meta()
    assert pipe.run("train", force=True)[-1].summary["message"] != "up to date"
    assert pipe.run("train")[-1].summary["message"] == "up to date"
    out.fs.rm(out.file("_stage.json"))
    assert out.meta() is None


def test_a_failed_array_write_on_a_remote_cache_leaves_the_frame_pending(tmp_path, remote, monkeypatch):
    """On zarr's path a frame's arrays are written concurrently and its status after them all: one
    array whose write fails leaves the frame pending (to be redone), never done without its data."""
    import errno

    import zarr

    from pipeline.errors import CacheError

    original = zarr.AsyncArray.setitem

    async def setitem(self, key, value):
        if self.path.endswith("points") and key == 3:
            raise OSError(errno.EIO, "Input/output error")
        return await original(self, key, value)

    pipe = _pipe(remote, tmp_path)
    with monkeypatch.context() as patch:
        patch.setattr(zarr.AsyncArray, "setitem", setitem)
        with pytest.raises(CacheError, match="writing frame 3 of"):
            pipe.run("calibrate")
    assert pipe.env.store("calibrate").status()[3] == PENDING
    pipe.run("calibrate")
    assert (pipe.env.store("calibrate").status() == DONE).all()


def _real_pipe(cache: str, world: Path, staging: Path, logs: list[str], **overrides: str) -> Pipeline:
    from stages import all_stages
    from tests.test_pipeline_e2e import TINY

    cfg = load_config("synthetic", {**TINY, "run.staging_dir": str(staging), **overrides}, environ={})
    return Pipeline(all_stages(), RunEnv(cfg, cache, "synthetic", str(world)), Executor(1), progress=False,
                    log=logs.append)


def _tensors(data: bytes) -> dict[str, np.ndarray]:
    from safetensors.numpy import load

    return load(data)


def test_the_stages_writing_local_files_stage_and_upload_on_a_remote_cache(tiny_world, tmp_path, remote, monkeypatch):
    """train, evaluate and export write with local file APIs: on a remote cache they write into a
    local staging folder (run.staging_dir) that is uploaded when they finish, and synthesize and
    evaluate read the checkpoints through a local copy. Everything equals a local cache's run; a
    second machine (another staging folder) resumes train from what the first uploaded. While
    training, every net's checkpoints are uploaded (here after every epoch), not only Dis-Net's."""
    world = tmp_path / "world"
    shutil.copytree(tiny_world, world)
    logs: list[str] = []
    local = _real_pipe(str(tmp_path / "cache"), world, tmp_path / "unused", logs)
    far = _real_pipe(remote, world, tmp_path / "machine-a", logs, **{"run.checkpoint_upload_s": "0"})
    published: set[str] = set()
    finals: dict[str, list[str]] = {}
    publish, left = StagedUploads.publish, StagedUploads.left

    def recorded(self, paths):
        published.update(Path(f).relative_to(self.work.path).as_posix() for f in paths)
        return publish(self, paths)

    def final(self):
        files = left(self)
        finals[self.name] = [Path(f).relative_to(self.work.path).as_posix() for f in files]
        return files

    with monkeypatch.context() as patch:
        patch.setattr(StagedUploads, "publish", recorded)
        patch.setattr(StagedUploads, "left", final)
        for pipe in (local, far):
            pipe.run("evaluate")
            pipe.run("export")
    assert published == {f"{net}/{name}" for net in ("disnet", "rssnet", "placenet")
                         for name in ("best.safetensors", "best.json", "last.safetensors", "last.json")}, published
    # the upload at its end sends what was not uploaded as it trained (until 2026-12-07 every file
    # again): not the last epoch's resume points; the best checkpoints, which got their input ranges
    # and quantiles after training, and the rest
    lasts = {f"{net}/last.{ext}" for net in ("disnet", "rssnet", "placenet") for ext in ("safetensors", "json")}
    assert "metrics.json" in finals["train"] and "disnet/best.safetensors" in finals["train"], finals
    assert not lasts & set(finals["train"]), finals
    fs = fsspec.filesystem("memory")
    here, there = tmp_path / "cache" / "synthetic", remote.removeprefix("memory://") + "/synthetic"
    for net in ("disnet", "rssnet", "placenet"):  # the same training, the same weights
        a = _tensors((here / "train" / net / "best.safetensors").read_bytes())
        b = _tensors(fs.cat_file(f"{there}/train/{net}/best.safetensors"))
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a), net
    for i in range(10):
        np.testing.assert_array_equal(local.env.store("synthesize").read("points", i),
                                      far.env.store("synthesize").read("points", i))
    exported = sorted(p.relative_to(here / "export").as_posix() for p in (here / "export").rglob("*")
                      if p.is_file() and p.name not in ("_stage.json", "_files.json"))
    assert len(exported) > 30
    assert sorted(f.removeprefix(f"/{there}/export/") for f in fs.find(f"{there}/export")
                  if not f.endswith(("_stage.json", "_run.token", "_files.json"))) == exported
    for name in exported:
        assert fs.cat_file(f"{there}/export/{name}") == (here / "export" / name).read_bytes(), name
    ours, theirs = (json.loads(p) for p in ((here / "evaluate" / "report.json").read_text(),
                                           fs.cat_file(f"{there}/evaluate/report.json")))
    assert len(ours["metrics"]) > 5
    for key in ("metrics", "distribution_distances", "physics_checks", "by_ego_speed", "meta"):
        assert json.dumps(ours[key], sort_keys=True) == json.dumps(theirs[key], sort_keys=True), key
    figures = sorted(p.name for p in (here / "evaluate" / "figures").iterdir())
    assert len(figures) >= 3 and sorted(f.rsplit("/", 1)[-1] for f in fs.find(f"{there}/evaluate/figures")) == figures
    uploading = [line for line in logs if "uploading" in line]  # the remote pipe's three staged stages say so
    assert [line.split()[0] for line in uploading] == ["train", "evaluate", "export"], logs
    assert re.search(rf"^export +uploading {len(exported)} file\(s\), [0-9.]+ MB, to {remote}/synthetic/export$",
                     uploading[-1]), uploading
    # every file the dataset stages wrote is recorded, the same on both, and reads back intact
    checked = [{r["stage"]: (r.get("files"), r.get("checkpoints"), r.get("problem")) for r in verify_cache(pipe)
                if "checkpoints" in r} for pipe in (local, far)]
    assert checked[0] == checked[1] and checked[0]["export"][0] == len(exported), checked
    assert checked[0]["train"][1] >= 6 and not any(problem for *_, problem in checked[0].values())
    kept = {p.name.split("-")[0]: sorted(q.name for q in p.iterdir()) for p in (tmp_path / "machine-a").iterdir()}
    # train's staging folder (it resumes from it) and the copy synthesize and evaluate read; the
    # uploaded staging folders of export and evaluate are not kept
    assert kept == {"train": ["copies", "staging"], "export": [], "evaluate": []}, kept
    summary = far.env.dir("train").summary()  # the remote folder, not the staging one, is named
    assert summary["checkpoints"] == f"{remote}/synthetic/train"
    assert json.loads(fs.cat_file(f"{there}/train/metrics.json"))["checkpoints"] == f"{remote}/synthetic/train"
    assert not [f for f in fs.find(there) if f.endswith((".json", ".md", ".csv"))  # nor in a file (metrics.json
                and str(tmp_path / "machine-a").encode() in fs.cat_file(f)]   # did until 2026-12-07)
    assert str(tmp_path / "machine-a") not in json.dumps(far.env.dir("export").summary())

    # another machine: more epochs resume from the uploaded checkpoints, and the others read them anew
    logs.clear()
    other = _real_pipe(remote, world, tmp_path / "machine-b", logs, **{"train.epochs": "2"})
    other.run("evaluate")
    assert any("resuming from" in line and remote in line for line in logs), logs
    assert other.env.dir("train").summary()["disnet"]["resumed_from"] == 1
    b = _tensors(fs.cat_file(f"{there}/train/disnet/best.safetensors"))
    copies = list((tmp_path / "machine-b").glob("train-*/copies/*/disnet/best.safetensors"))
    assert len(copies) == 1 and all(np.array_equal(v, _tensors(copies[0].read_bytes())[k]) for k, v in b.items())
    # the first machine's staging folder is now an older run's: it takes the remote's files
    logs.clear()
    again = _real_pipe(remote, world, tmp_path / "machine-a", logs, **{"train.epochs": "3"})
    again.run("train")
    assert any("resuming from" in line for line in logs), logs
    assert again.env.dir("train").summary()["disnet"]["resumed_from"] == 2
    again.run("synthesize")  # reads the new run's checkpoints: a new copy replaces the first run's
    copies = list((tmp_path / "machine-a").glob("train-*/copies/*"))
    assert len(copies) == 1 and (copies[0] / "_stage.json").read_bytes() == fs.cat_file(f"{there}/train/_stage.json")


def _killed_in_the_second_epoch(patch) -> None:
    """Make pipeline.training's second call of train_one_epoch raise KeyboardInterrupt (a kill)."""
    import pipeline.training

    original, calls = pipeline.training.train_one_epoch, []

    def killed(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt("simulated kill")
        return original(*args, **kwargs)

    patch.setattr(pipeline.training, "train_one_epoch", killed)


def test_a_staged_train_killed_mid_run_resumes_from_its_staging_folder(tiny_world, tmp_path, remote, monkeypatch):
    """A train killed after its first epoch on a remote cache, before its first upload of
    checkpoints was due (run.checkpoint_upload_s), has uploaded none (the output is not done); run
    again on the same machine it goes on from that epoch in its staging folder, without
    downloading, and uploads the finished nets."""
    from pipeline.errors import StageInterrupted

    world = tmp_path / "world"
    shutil.copytree(tiny_world, world)
    logs: list[str] = []
    pipe = _real_pipe(remote, world, tmp_path / "machine", logs, **{"train.epochs": "2", "train.nets": "disnet",
                                                                    "run.checkpoint_upload_s": "3600"})
    with monkeypatch.context() as patch:
        _killed_in_the_second_epoch(patch)
        with pytest.raises(StageInterrupted):
            pipe.run("train")
    fs = fsspec.filesystem("memory")
    there = remote.removeprefix("memory://") + "/synthetic/train"
    assert pipe.env.dir("train").meta() is None and not fs.exists(f"{there}/disnet/last.safetensors")
    staged = list((tmp_path / "machine").glob("train-*/staging/disnet/last.safetensors"))
    assert len(staged) == 1
    logs.clear()
    pipe.run("train")
    assert not any("resuming from" in line for line in logs), logs
    summary = pipe.env.dir("train").summary()
    assert summary["disnet"]["resumed_from"] == 1 and summary["checkpoints"] == f"{remote}/synthetic/train"
    assert fs.cat_file(f"{there}/disnet/best.safetensors") == \
        (staged[0].parent / "best.safetensors").read_bytes()


def test_a_staged_train_killed_mid_run_resumes_on_another_machine_from_its_last_upload(tiny_world, tmp_path, remote, monkeypatch):
    """While training, a staged train uploads each finished epoch's checkpoints (here after every
    epoch: run.checkpoint_upload_s 0), best before last, so that a train killed in its second
    epoch on one machine resumes on another from the first epoch, not from scratch, and ends with
    the weights of an uninterrupted run."""
    from pipeline.errors import StageInterrupted

    world = tmp_path / "world"
    shutil.copytree(tiny_world, world)
    settings = {"train.epochs": "3", "train.nets": "disnet", "run.checkpoint_upload_s": "0"}
    logs: list[str] = []
    uploads: list[list[str]] = []
    upload = DirStore.upload

    def recorded(self, staged, files=None):
        if files is not None:
            uploads.append([Path(f).relative_to(staged.path).as_posix() for f in files])
        return upload(self, staged, files)

    first = _real_pipe(remote, world, tmp_path / "machine-a", logs, **settings)
    with monkeypatch.context() as patch:
        _killed_in_the_second_epoch(patch)
        patch.setattr(DirStore, "upload", recorded)
        with pytest.raises(StageInterrupted):
            first.run("train")
    # epoch 1 wrote best then last (its val loss is the best so far): uploaded in that order
    assert uploads == [["disnet/best.safetensors", "disnet/best.json"], ["disnet/last.safetensors", "disnet/last.json"]]
    fs = fsspec.filesystem("memory")
    there = remote.removeprefix("memory://") + "/synthetic/train"
    staged = next((tmp_path / "machine-a").glob("train-*/staging"))
    for name in ("best.safetensors", "last.safetensors"):
        assert fs.cat_file(f"{there}/disnet/{name}") == (staged / "disnet" / name).read_bytes(), name
    assert first.env.dir("train").meta() is None
    logs.clear()
    second = _real_pipe(remote, world, tmp_path / "machine-b", logs, **settings)
    second.run("train")
    assert any("resuming from" in line and remote in line for line in logs), logs
    assert second.env.dir("train").summary()["disnet"]["resumed_from"] == 1
    whole = _real_pipe(str(tmp_path / "cache"), world, tmp_path / "unused", [], **settings)
    whole.run("train")
    a = _tensors((tmp_path / "cache" / "synthetic" / "train" / "disnet" / "best.safetensors").read_bytes())
    b = _tensors(fs.cat_file(f"{there}/disnet/best.safetensors"))
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def test_a_failed_upload_while_a_stage_runs_is_logged_and_the_run_goes_on(tmp_path, remote, monkeypatch):
    """DatasetInputs.publish uploads files of the staging folder while the stage runs; a failure
    there is one log line naming the staging folder, and publish says it failed (train then sends
    a best checkpoint that failed again), and the stage's final upload still takes everything.
    Without a staging folder (a local cache) there is nothing to publish."""
    from pipeline.errors import CacheError
    from pipeline.stage import DatasetStage

    published: list[bool] = []
    uploaded: list[bool] = []
    running: list[bool] = []

    def run(inputs, cfg, out, fingerprint):
        running.append(True)
        (Path(out.path) / "part.txt").write_bytes(bytes(1_500_000))
        published.append(inputs.publish is not None)
        if inputs.publish is not None:
            uploaded.append(inputs.publish([Path(out.path) / "part.txt"]))
        running.clear()
        return {"message": "done"}

    stage = DatasetStage("train", ("heatmaps",), ("train.epochs",), run, local_files=True, resumes=True)
    logs: list[str] = []
    pipe = _staged_pipe(remote, tmp_path, tmp_path / "staging", stage)
    pipe.log = logs.append
    upload = DirStore.upload

    def fails_while_running(self, staged, files=None):
        if running:
            raise CacheError(f"uploading to {self.url}: Connection reset by peer")
        logs.append("(the final upload)")
        return upload(self, staged, files)

    with monkeypatch.context() as patch:
        patch.setattr(DirStore, "upload", fails_while_running)
        pipe.run("train")
    staging = str(next((tmp_path / "staging").glob("train-*/staging")))
    assert [line for line in logs if "Connection reset" in line and "going on" in line and staging in line], logs
    assert pipe.is_current("train") and "part.txt" in _remote_files(pipe.env.dir("train").url)
    # the final upload is announced before it begins, with what it sends (the bookkeeping files aside)
    at = logs.index("(the final upload)")
    assert logs[at - 1] == f"train           uploading 1 file(s), 1.5 MB, to {pipe.env.dir('train').url}", logs
    _staged_pipe(str(tmp_path / "cache"), tmp_path, tmp_path / "staging", stage).run("train")
    assert published == [True, False] and uploaded == [False]
    _staged_pipe(remote, tmp_path, tmp_path / "staging", stage).run("train", force=True)  # nothing fails now
    assert uploaded == [False, True]


def _folder_stage():
    """A dataset stage 'train' writing with local file APIs, like train, export and evaluate: it
    reports the files it found in its folder when it began (what it resumes from) and adds one,
    ``runs/<n>.txt`` (n: its runs so far in that folder), holding the folder it wrote into."""
    from pipeline.stage import DatasetStage

    def run(inputs, cfg, out, fingerprint):
        root = Path(out.path)
        found = sorted(p.relative_to(root).as_posix() for p in root.rglob("*")
                       if p.is_file() and not p.name.startswith("_"))
        (root / "runs").mkdir(parents=True, exist_ok=True)
        (root / "runs" / f"{len(list((root / 'runs').glob('*.txt'))) + 1}.txt").write_text(str(root))
        return {"found": found, "output": str(root), "message": f"wrote into {root}"}

    return DatasetStage("train", ("heatmaps",), ("train.epochs",), run, local_files=True, resumes=True)


def _staged_pipe(cache_root: str, data_root: Path, staging: Path, stage=None, epochs: int = 1) -> Pipeline:
    """:func:`_pipe` with ``stage`` for its train stage and the staging folder ``staging``."""
    cfg = load_config("synthetic", {"run.staging_dir": str(staging), "train.epochs": str(epochs)}, environ={})
    env = RunEnv(cfg=cfg, cache_root=cache_root, dataset="fake", data_root=str(data_root))
    stages = [*fake_stages.STAGES[:2], stage or fake_stages.STAGES[2]]
    return Pipeline(stages, env, Executor(1), progress=False, log=lambda m: None, frame_lister=lambda: list(IDS))


def _remote_files(url: str) -> list[str]:
    """The files under the remote folder ``url``, relative to it."""
    fs, path = fsspec.core.url_to_fs(url)
    return sorted(f.removeprefix(path.rstrip("/") + "/") for f in fs.find(path))


def test_only_stages_writing_local_files_on_a_remote_cache_are_staged(tmp_path, remote):
    """A stage writing through its DirStore (fsspec) writes straight into a remote cache, and a stage
    writing local files on a local cache into its folder there: neither makes a staging folder (nor
    a run token), and a local output is read where it is, not copied."""
    staging = tmp_path / "staging"
    far = _staged_pipe(remote, tmp_path, staging)  # fake_stages' train writes with out.write_text
    far.run("train")
    assert float(far.env.dir("train").fs.cat_file(far.env.dir("train").file("total.txt"))) > 0
    assert _remote_files(far.env.dir("train").url) == ["_files.json", "_stage.json", "total.txt"]
    local = _staged_pipe(str(tmp_path / "cache"), tmp_path, staging, _folder_stage())
    summary = local.run("train")[-1].summary
    folder = tmp_path / "cache" / "fake" / "train"
    assert summary["output"] == str(folder) and (folder / "runs" / "1.txt").read_text() == str(folder)
    assert local.env.dir("train").local_copy(str(staging)) == folder
    assert not staging.exists()


def test_a_staging_folder_holds_only_what_the_run_resumes_from(tmp_path, remote):
    """A staged stage that resumes goes on from its staging folder, but a forced run starts from an
    empty one, a killed run's temporary files are neither read nor uploaded, and a staging folder
    that another machine's run has replaced on the remote is emptied before the remote's files are
    taken: files of this machine's older runs would otherwise be read, and uploaded again."""
    a, b = tmp_path / "machine-a", tmp_path / "machine-b"
    out = _staged_pipe(remote, tmp_path, a).env.dir("train")

    def run(staging: Path, epochs: int, force: bool = False) -> list[str]:
        pipe = _staged_pipe(remote, tmp_path, staging, _folder_stage(), epochs)
        return pipe.run("train", force=force)[-1].summary["found"]

    assert run(a, 1) == []
    assert run(a, 2) == ["runs/1.txt"]  # resumed in its staging folder
    assert _remote_files(out.url) == ["_files.json", "_run.token", "_stage.json", "runs/1.txt", "runs/2.txt"]
    assert run(a, 2, force=True) == []  # forced: from scratch, here and on the remote
    assert _remote_files(out.url) == ["_files.json", "_run.token", "_stage.json", "runs/1.txt"]
    assert run(a, 3) == ["runs/1.txt"]
    staged = next(a.glob("train-*/staging"))
    (staged / "runs" / "9.txt.tmp").write_text("half-written")  # a killed run's
    assert run(a, 4) == ["runs/1.txt", "runs/2.txt"]
    assert not (staged / "runs" / "9.txt.tmp").exists() and "runs/9.txt.tmp" not in _remote_files(out.url)
    out.write_text("runs/3.txt.tmp", "half-uploaded")  # a killed upload's, on a filesystem that writes in place
    assert run(a, 41) == ["runs/1.txt", "runs/2.txt", "runs/3.txt"]
    assert "runs/3.txt.tmp" not in _remote_files(out.url)
    out.write_text("runs/4.txt.tmp", "half-uploaded")
    shutil.rmtree(staged)                                   # resumed on a machine without the staging folder
    assert run(a, 42) == ["runs/1.txt", "runs/2.txt", "runs/3.txt", "runs/4.txt"]
    assert "runs/4.txt.tmp" not in _remote_files(out.url) and not (staged / "runs" / "4.txt.tmp").exists()
    # another machine runs it from scratch since: this one's three files are an older run's
    assert run(b, 5, force=True) == []
    assert run(a, 6) == ["runs/1.txt"]
    assert out.fs.cat_file(out.file("runs/1.txt")).decode() == str(next(b.glob("train-*/staging")))
    assert sorted(p.name for p in (staged / "runs").iterdir()) == ["1.txt", "2.txt"]
    assert _remote_files(out.url) == ["_files.json", "_run.token", "_stage.json", "runs/1.txt", "runs/2.txt"]


def test_a_failed_upload_leaves_the_stage_unfinished(tmp_path, remote, monkeypatch):
    """The remote folder loses its completion mark when a staged run begins and gets it back only
    after the staging folder is uploaded: an upload that fails (or a run killed while uploading)
    leaves the stage to be run again, not the last run's mark over partly replaced files."""
    from pipeline.errors import CacheError

    def pipe(epochs: int) -> Pipeline:
        return _staged_pipe(remote, tmp_path, tmp_path / "staging", _folder_stage(), epochs)

    pipe(1).run("train")

    def fails(self, staged, files=None):
        raise CacheError(f"uploading to {self.url}: Input/output error")

    with monkeypatch.context() as patch:
        patch.setattr(DirStore, "upload", fails)
        with pytest.raises(CacheError, match="uploading"):
            pipe(2).run("train")
    assert pipe(2).env.dir("train").meta() is None and not pipe(2).is_current("train")
    assert pipe(2).run("train")[-1].summary["found"] == ["runs/1.txt", "runs/2.txt"]  # resumed here
    assert pipe(2).is_current("train")
    assert _remote_files(pipe(2).env.dir("train").url) == ["_files.json", "_run.token", "_stage.json", "runs/1.txt",
                                                           "runs/2.txt", "runs/3.txt"]


def test_a_write_error_in_the_staging_folder_is_a_cache_error(tmp_path, remote):
    """An OSError naming a file of the staging folder is the stage's output failing to be written
    (a CacheError naming the folder), not a stage's bug or a read error, as on a local cache."""
    import errno

    from pipeline.errors import CacheError
    from pipeline.stage import DatasetStage

    def run(inputs, cfg, out, fingerprint):
        raise OSError(errno.EIO, "Input/output error", str(Path(out.path) / "disnet" / "last.safetensors"))

    stage = DatasetStage("train", ("heatmaps",), ("train.epochs",), run, local_files=True, resumes=True)
    pipe = _staged_pipe(remote, tmp_path, tmp_path / "staging", stage)
    with pytest.raises(CacheError, match=r"train: writing into .*staging.*Input/output error"):
        pipe.run("train")


def _finished(url: str, files: dict[str, str]) -> DirStore:
    """A finished dataset stage output at ``url`` holding ``files`` (name -> text)."""
    out = DirStore(url)
    for name, text in files.items():
        out.write_text(name, text)
    out.finish("fp", {})
    return out


def test_a_local_copy_is_downloaded_once_per_run_and_each_remote_folder_has_its_own(tmp_path, remote, monkeypatch):
    """local_copy downloads a finished output once per run (its _stage.json), also when the staging
    folder is given with '~'; the same stage of two datasets (same last part of the URL) has two
    copies, neither removing the other's; a copy another process is still downloading (a dot
    folder) is left to it; an output that has not finished has no copy, and one finished without a
    file (until 2026-12-06 a FileNotFoundError) a copy of its _stage.json alone."""
    from pipeline.errors import CacheError

    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    first = _finished(f"{remote}/one/train", {"disnet/best.safetensors": "one"})
    second = _finished(f"{remote}/two/train", {"disnet/best.safetensors": "two"})
    downloads = []
    original = DirStore.download

    def counted(self, staged):
        downloads.append(self.url)
        return original(self, staged)

    monkeypatch.setattr(DirStore, "download", counted)
    copy = first.local_copy("~/staging")
    assert copy.is_relative_to(tmp_path / "home" / "staging")
    assert (copy / "disnet" / "best.safetensors").read_text() == "one"
    assert (copy / "_stage.json").read_bytes() == first.fs.cat_file(first.file("_stage.json"))
    other = second.local_copy("~/staging")
    assert (other / "disnet" / "best.safetensors").read_text() == "two" and other.parent != copy.parent
    partial = copy.parent / ".0123456789abcdef-0badc0de"
    partial.mkdir()
    assert first.local_copy("~/staging") == copy and second.local_copy("~/staging") == other
    assert downloads == [first.url, second.url]  # reused
    first.write_text("disnet/best.safetensors", "one, retrained")
    first.finish("fp", {})  # another run: a new copy replaces the old one
    again = first.local_copy("~/staging")
    assert again != copy and (again / "disnet" / "best.safetensors").read_text() == "one, retrained"
    assert sorted(p.name for p in again.parent.iterdir()) == sorted([again.name, partial.name])
    assert other.is_dir()
    with pytest.raises(CacheError, match="the stage has not finished"):
        DirStore(f"{remote}/three/train").local_copy("~/staging")
    empty = _finished(f"{remote}/four/train", {})
    assert [p.name for p in empty.local_copy("~/staging").iterdir()] == ["_stage.json"]


def test_two_processes_making_the_same_local_copy_both_get_it(tmp_path, remote, monkeypatch):
    """Two processes on one machine that find no copy both download one; the second to finish
    finds the first's in place (its rename fails), takes it and removes its own download."""
    out = _finished(f"{remote}/race/train", {"disnet/best.safetensors": "weights"})
    original = DirStore.download

    def beaten(self, staged):  # the other process finishes its copy while this one downloads
        taken = original(self, staged)
        monkeypatch.setattr(DirStore, "download", original)
        out.local_copy(str(tmp_path))
        return taken

    monkeypatch.setattr(DirStore, "download", beaten)
    copy = out.local_copy(str(tmp_path))
    assert (copy / "disnet" / "best.safetensors").read_text() == "weights"
    assert [p.name for p in copy.parent.iterdir()] == [copy.name]  # no download left behind


def test_synthesis_on_a_remote_cache_names_the_missing_checkpoints_before_train_finished(tmp_path, remote):
    """The train stage's remote folder without its _stage.json (never finished, or running) holds
    no checkpoint synthesis may read: the error names the nets to train, as on a local cache."""
    from pipeline.errors import PipelineError
    from stages.synthesize import check_checkpoints

    cfg = load_config("synthetic", {"run.staging_dir": str(tmp_path / "staging")}, environ={})
    train = _finished(f"{remote}/synthetic/train", {"disnet/best.safetensors": "weights"})
    train.invalidate()
    with pytest.raises(PipelineError, match="no disnet, rssnet, placenet checkpoint; synthesis needs it"):
        check_checkpoints(train, cfg)
    assert not (tmp_path / "staging").exists()


def test_upload_and_download_make_the_folders_of_a_filesystem_that_has_them(tmp_path):
    """Object stores (s3://, gcs://, memory://) need no folders, but a remote filesystem with real
    ones (sftp://, smb://, hdfs://; here the local one under another protocol) writes no file into
    a folder that is not there: upload creates the staging folder's subfolders on the remote, and
    download those of the remote folder here."""
    from fsspec.implementations.local import LocalFileSystem

    class Folders(LocalFileSystem):
        protocol = ("folders",)

        @classmethod
        def _strip_protocol(cls, path):
            return super()._strip_protocol(str(path).removeprefix("folders://"))

    fsspec.register_implementation("folders", Folders, clobber=True)
    staged = tmp_path / "staging"
    for name in ("metrics.json", "disnet/best.safetensors", "evaluate/figures/bev/000001.png"):
        (staged / name).parent.mkdir(parents=True, exist_ok=True)
        (staged / name).write_text(name)
    out = DirStore(f"folders://{tmp_path / 'remote' / 'train'}")
    assert not out.is_local
    out.upload(DirStore(str(staged)))
    uploaded = sorted(p.relative_to(tmp_path / "remote" / "train").as_posix()
                      for p in (tmp_path / "remote" / "train").rglob("*") if p.is_file())
    assert uploaded == ["disnet/best.safetensors", "evaluate/figures/bev/000001.png", "metrics.json"]
    assert out.download(DirStore(str(tmp_path / "back"))) == 3
    assert all((tmp_path / "back" / name).read_text() == name for name in uploaded)


def test_verify_reads_the_checkpoints_of_a_remote_cache(tmp_path, remote, monkeypatch):
    """`pipeline verify` downloads each checkpoint of a remote dataset stage output and reads it: a
    damaged one is named by its remote URL (until 2026-12-06 a remote cache's were not read), and
    so is one that cannot be downloaded (not counted as read, nor read from the one before)."""
    import errno

    import torch

    from pipeline.checkpoint import save_checkpoint

    pipe = _staged_pipe(remote, tmp_path, tmp_path / "staging")
    pipe.run("train")
    out = pipe.env.dir("train")
    save_checkpoint(tmp_path / "good.safetensors", {"model.fc.weight": torch.zeros(64)}, {"epoch": 1})
    good = (tmp_path / "good.safetensors").read_bytes()
    out.write_bytes("net/best.safetensors", good)
    out.write_bytes("net/last.safetensors", good[: len(good) // 2])
    row = {r["stage"]: r for r in verify_cache(pipe, ["train"])}["train"]
    assert row["checkpoints"] == 2
    assert row["problem"].startswith(f"{remote}/fake/train/net/last.safetensors: unreadable checkpoint"), row
    out.write_bytes("net/last.safetensors", good)
    row = {r["stage"]: r for r in verify_cache(pipe, ["train"])}["train"]
    assert row["checkpoints"] == 2 and "problem" not in row
    get = type(out.fs).get

    def fails_for_last(self, rpath, lpath, *args, **kwargs):
        if str(rpath).endswith("last.safetensors"):
            raise OSError(errno.EIO, "Input/output error")
        return get(self, rpath, lpath, *args, **kwargs)

    with monkeypatch.context() as patch:
        patch.setattr(type(out.fs), "get", fails_for_last)
        row = {r["stage"]: r for r in verify_cache(pipe, ["train"])}["train"]
    assert row["problem"].startswith(f"downloading {remote}/fake/train/net/last.safetensors: "), row
    assert "Input/output error" in row["problem"] and ";" not in row["problem"], row


def test_an_upload_of_given_files_takes_those_only(tmp_path, remote):
    """DirStore.upload(staged, files), which DatasetInputs.publish calls while a stage runs, uploads
    only the given files of the staging folder, named by their path there or inside it, each to
    its path in the remote folder; an empty list uploads nothing, not the whole folder."""
    staged = DirStore(str(tmp_path / "staging"))
    for name in ("disnet/best.safetensors", "disnet/last.safetensors", "metrics.json"):
        staged.write_text(name, name)
    out = DirStore(f"{remote}/train")
    out.upload(staged, [])
    assert _remote_files(out.url) == []
    out.upload(staged, ["disnet/last.safetensors", Path(staged.path) / "metrics.json"])
    assert _remote_files(out.url) == ["disnet/last.safetensors", "metrics.json"]
    assert out.fs.cat_file(out.file("disnet/last.safetensors")) == b"disnet/last.safetensors"


def test_an_upload_cut_off_midway_leaves_no_part_of_a_file_on_a_filesystem_that_writes_in_place(tmp_path, remote):
    """sftp or smb write a file as its bytes arrive: an upload cut off in the middle of the last
    checkpoint left half of it under its name, and the next run stopped on it. Each file now goes
    to a ``.tmp`` name and is renamed when whole: the remote keeps the checkpoint before (or none),
    and the killed run's ``.tmp`` is what remove_temporaries clears. An object store (memory://)
    is written in place, without renames."""
    from fsspec.implementations.local import LocalFileSystem

    from pipeline.cachefs import writes_whole_objects

    class InPlace(LocalFileSystem):
        protocol = ("inplace",)
        cut = ""

        @classmethod
        def _strip_protocol(cls, path):
            return super()._strip_protocol(str(path).removeprefix("inplace://"))

        def put_file(self, lpath, rpath, callback=None, **kwargs):
            data = Path(lpath).read_bytes()
            rpath = self._strip_protocol(rpath)
            if InPlace.cut and rpath.startswith(self._strip_protocol(InPlace.cut)):
                Path(rpath).write_bytes(data[: len(data) // 2])
                raise OSError(104, "Connection reset by peer")
            Path(rpath).write_bytes(data)

    fsspec.register_implementation("inplace", InPlace, clobber=True)
    staged = DirStore(str(tmp_path / "staging"))
    out = DirStore(f"inplace://{tmp_path / 'remote' / 'train'}")
    assert not writes_whole_objects(out.fs) and writes_whole_objects(fsspec.filesystem("memory"))
    last = tmp_path / "remote" / "train" / "disnet" / "last.safetensors"
    staged.write_bytes("disnet/last.safetensors", b"epoch 1" * 1000)
    out.upload(staged, ["disnet/last.safetensors"])
    assert last.read_bytes() == b"epoch 1" * 1000
    staged.write_bytes("disnet/last.safetensors", b"epoch 2" * 1000)
    InPlace.cut = str(last)
    with pytest.raises(CacheError, match="Connection reset by peer"):
        out.upload(staged, ["disnet/last.safetensors"])
    assert last.read_bytes() == b"epoch 1" * 1000               # the checkpoint before, whole
    assert Path(str(last) + ".tmp").stat().st_size == 3500      # the half that arrived
    assert out.remove_temporaries() == [str(last) + ".tmp"]
    InPlace.cut = ""
    out.upload(staged, ["disnet/last.safetensors"])
    assert last.read_bytes() == b"epoch 2" * 1000
    assert sorted(p.name for p in last.parent.iterdir()) == ["last.safetensors"]

    memory = DirStore(f"{remote}/train")
    moved = []
    mv = type(memory.fs).mv
    try:
        type(memory.fs).mv = lambda self, *a, **k: moved.append(a)
        memory.upload(staged)
    finally:
        type(memory.fs).mv = mv
    assert moved == [] and _remote_files(memory.url) == ["disnet/last.safetensors"]


def _listing_filesystem():
    """A filesystem (the local one under protocol listed://) that caches its listings as s3fs and
    gcsfs do: ``ls``, ``find`` and ``glob`` keep what they list, ``info`` (hence ``open``) answers
    from a cached listing, and opening a file that another process rewrote since it was listed
    fails as s3fs's does (``[Errno 16] ... no longer exists``: its ETag changed). ``find`` lists
    afresh but keeps the folders it had listed before; ``cat_file`` is one request, as s3fs's GET;
    this process's own writes drop its listings."""
    import errno

    from fsspec.implementations.local import LocalFileSystem

    class Listed(LocalFileSystem):
        protocol = ("listed",)

        @classmethod
        def _strip_protocol(cls, path):
            return super()._strip_protocol(str(path).removeprefix("listed://"))

        def ls(self, path, detail=True, **kwargs):
            path = self._strip_protocol(path)
            if path not in self.dircache:
                self.dircache[path] = LocalFileSystem().ls(path, detail=True, **kwargs)
            return self.dircache[path] if detail else [e["name"] for e in self.dircache[path]]

        def find(self, path, maxdepth=None, withdirs=False, detail=False, **kwargs):
            found = LocalFileSystem().find(self._strip_protocol(path), maxdepth, withdirs, detail=True, **kwargs)
            for folder in {self._parent(name) for name in found}:
                if folder not in self.dircache:
                    self.dircache[folder] = LocalFileSystem().ls(folder, detail=True)
            return found if detail else sorted(found)

        def info(self, path, **kwargs):
            path = self._strip_protocol(path)
            listed = self._ls_from_cache(path)  # FileNotFoundError when a listing of its folder lacks it
            if listed:
                named = [e for e in listed if e["name"] == path]
                return named[0] if named else {"name": path, "size": 0, "type": "directory"}
            return LocalFileSystem().info(path, **kwargs)

        def _open(self, path, mode="rb", **kwargs):
            path = self._strip_protocol(path)
            if "r" in mode:
                listed, now = self.info(path), LocalFileSystem().info(path)
                if (listed["size"], listed.get("mtime")) != (now["size"], now.get("mtime")):
                    raise OSError(errno.EBUSY, f"The remote file corresponding to filename {path} and Etag "
                                               f"\"{listed.get('mtime')}\" no longer exists.")
            else:
                self.invalidate_cache()
            return super()._open(path, mode, **kwargs)

        def cat_file(self, path, start=None, end=None, **kwargs):
            return Path(self._strip_protocol(path)).read_bytes()[start:end]

        def invalidate_cache(self, path=None):
            self.dircache.clear()

        def mv(self, *args, **kwargs):
            self.invalidate_cache()
            return super().mv(*args, **kwargs)

        def rm(self, *args, **kwargs):
            self.invalidate_cache()
            return super().rm(*args, **kwargs)

        def put_file(self, *args, **kwargs):
            self.invalidate_cache()
            return super().put_file(*args, **kwargs)

    fsspec.register_implementation("listed", Listed, clobber=True)
    return Listed


def _rewritten_by_another_run(root: Path, token: str, weights: str, message: str) -> None:
    """The files a run of another process (a train on another machine) leaves in ``root``."""
    (root / "disnet").mkdir(parents=True, exist_ok=True)
    (root / "disnet" / "best.safetensors").write_text(weights)
    (root / RUN_TOKEN).write_text(token)
    (root / "_files.json").write_text(json.dumps({"disnet/best.safetensors": [len(weights), "x"]}))
    (root / "_stage.json").write_text(json.dumps({"fingerprint": token, "finished": 1.0, "summary": {"message": message}}))


def test_a_process_that_outlives_runs_reads_the_records_another_run_rewrote(tmp_path):
    """A worker of a dask cluster outlives runs: one that made a local copy of train's remote
    output (listing the folder) read the stage's record afresh when train ran again elsewhere
    only on a filesystem without a listing cache. On s3fs it stopped every frame of the next
    synthesize with `[Errno 16] The remote file corresponding to filename .../train/_stage.json and
    Etag ... no longer exists` (checked with moto's S3 server, 2026-12-07) until the worker was
    restarted. The record, the run token and the files' manifest are now read in one request."""
    _listing_filesystem()
    root = tmp_path / "remote" / "train"
    _rewritten_by_another_run(root, "run-1", "weights 1", "first")
    out = DirStore(f"listed://{root}")
    first = out.local_copy(str(tmp_path / "staging"))  # the download lists the folder
    assert (first / "disnet" / "best.safetensors").read_text() == "weights 1"
    assert out.run_token() == "run-1" and out.check_files()[0] == 1
    time.sleep(0.01)  # another mtime, as another ETag
    _rewritten_by_another_run(root, "run-two", "weights 2", "the second run, a longer record")
    assert out.meta()["fingerprint"] == "run-two"
    assert out.run_token() == "run-two"
    again = out.local_copy(str(tmp_path / "staging"))
    assert again != first and (again / "disnet" / "best.safetensors").read_text() == "weights 2"
    assert json.loads((again / "_stage.json").read_text())["summary"]["message"] == "the second run, a longer record"
    assert out.check_files()[0] == 1


def test_the_listing_filesystem_of_the_tests_fails_as_s3fs_does(tmp_path):
    """The test above's filesystem reproduces the failure: opening the record rewritten since the
    listing fails (errno 16), a one-request read does not."""
    import errno

    fs = _listing_filesystem()()
    root = tmp_path / "remote"
    _rewritten_by_another_run(root, "run-1", "weights 1", "first")
    fs.find(str(root))
    time.sleep(0.01)
    _rewritten_by_another_run(root, "run-two", "weights 2", "a longer record")
    with pytest.raises(OSError) as exc:
        fs.open(str(root / "_stage.json"), "rb").read()
    assert exc.value.errno == errno.EBUSY
    assert b"a longer record" in fs.cat_file(str(root / "_stage.json"))


@pytest.fixture
def s3(monkeypatch):
    """An s3:// bucket on moto's S3 server (a thread, a free port) through s3fs, the protocol of a
    real bucket; skipped where they are not installed (neither is a dependency of the package:
    `pip install s3fs "moto[server]"`)."""
    pytest.importorskip("s3fs")
    moto_server = pytest.importorskip("moto.server")
    from s3fs import S3FileSystem

    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    monkeypatch.setenv("AWS_DEFAULT_REGION", "us-east-1")
    monkeypatch.setitem(fsspec.config.conf, "s3", {"endpoint_url": f"http://{host}:{port}", "key": "testing",
                                                   "secret": "testing"})
    S3FileSystem.clear_instance_cache()
    bucket = f"test-{uuid.uuid4().hex[:8]}"
    S3FileSystem().mkdir(bucket)
    yield f"s3://{bucket}"
    S3FileSystem.clear_instance_cache()
    server.stop()


def test_an_s3_cache_gives_what_a_local_one_gives_and_names_a_damaged_chunk(tmp_path, s3):
    """The first tests of this file on the S3 protocol (moto's server, s3fs) instead of memory://."""
    local, far = _pipe(str(tmp_path / "cache"), tmp_path), _pipe(f"{s3}/cache", tmp_path)
    local.run("train")
    far.run("train")
    _assert_same_frames(local, far)
    again = far.run("train")
    assert [(r.action, r.processed) for r in again[:2]] == [("resumed", 0), ("resumed", 0)]
    far.env.dir("train").fs.pipe_file(f"{s3.removeprefix('s3://')}/cache/fake/calibrate.zarr/value/c/3", b"garbage")
    errors = far.env.store("calibrate").verify()[1]
    assert list(errors) == [3] and "calibrate.zarr/value" in str(errors[3])


def test_on_s3_a_process_that_outlives_runs_reads_the_records_another_run_rewrote(tmp_path, s3):
    """test_a_process_that_outlives_runs_reads_the_records_another_run_rewrote on s3fs itself: the
    other run writes through another s3fs instance (another process's)."""
    from s3fs import S3FileSystem

    other = S3FileSystem(skip_instance_cache=True)
    root = f"{s3.removeprefix('s3://')}/cache/synthetic/train"

    def rewritten(token: str, weights: str, message: str) -> None:
        other.pipe({f"{root}/disnet/best.safetensors": weights.encode(), f"{root}/{RUN_TOKEN}": token.encode(),
                    f"{root}/_stage.json": json.dumps({"fingerprint": token, "summary": {"message": message}}).encode()})

    rewritten("run-1", "weights 1", "first")
    out = DirStore(f"{s3}/cache/synthetic/train")
    first = out.local_copy(str(tmp_path / "staging"))
    assert (first / "disnet" / "best.safetensors").read_text() == "weights 1" and out.run_token() == "run-1"
    rewritten("run-two", "weights 2", "the second run, a longer record")
    assert out.meta()["fingerprint"] == "run-two" and out.run_token() == "run-two"
    again = out.local_copy(str(tmp_path / "staging"))
    assert (again / "disnet" / "best.safetensors").read_text() == "weights 2"


def _object_store(protocol: str) -> type:
    """The local filesystem under ``protocol``:// as an object store (no folders to make; the
    pipeline does not take it for the local one), for a test to subclass and register."""
    from fsspec.implementations.local import LocalFileSystem

    class ObjectStore(LocalFileSystem):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **{**kwargs, "auto_mkdir": True})

        @classmethod
        def _strip_protocol(cls, path):
            return super()._strip_protocol(str(path).removeprefix(f"{protocol}://"))

    ObjectStore.protocol = (protocol,)
    return ObjectStore


def test_a_remote_cache_never_asks_for_zarr_format_2_metadata(tmp_path):
    """Every output is zarr format 3; opened without saying so, zarr also asks for .zgroup, .zarray
    and .zattrs at each open, a request each on an object store (246 of 1,043 requests of the fake
    pipeline's run on moto's S3 server, 2026-12-07; none with the format named: 737 in all)."""
    asked: list[str] = []

    class Asked(_object_store("asked")):
        def cat_file(self, path, *args, **kwargs):
            asked.append(str(path))
            return super().cat_file(path, *args, **kwargs)

        def info(self, path, *args, **kwargs):
            asked.append(str(path))
            return super().info(path, *args, **kwargs)

    fsspec.register_implementation("asked", Asked, clobber=True)
    pipe = _pipe(f"asked://{tmp_path / 'cache'}", tmp_path)
    pipe.run("train")
    cache_status(_pipe(f"asked://{tmp_path / 'cache'}", tmp_path))
    assert any(p.endswith("zarr.json") for p in asked)  # the store was read through this filesystem
    probes = [p for p in asked if p.endswith((".zgroup", ".zarray", ".zattrs", ".zmetadata"))]
    assert not probes, probes[:5]


def _counting_filesystem(asked: list[tuple[str, str]]):
    """The local filesystem under protocol counted://, as an object store (no folders to make),
    recording each request zarr or the cache makes (cat_file, info, exists, ls) in ``asked``."""
    base = _object_store("counted")

    class Counted(base):
        pass

    for name in ("cat_file", "info", "exists", "ls"):
        def asking(self, path, *args, _name=name, **kwargs):
            asked.append((_name, str(path)))
            return getattr(base, _name)(self, path, *args, **kwargs)
        setattr(Counted, name, asking)
    fsspec.register_implementation("counted", Counted, clobber=True)


def test_a_frame_s_read_and_write_on_a_remote_cache_read_each_array_s_metadata_once(tmp_path):
    """On an object store each read of a zarr.json is a request: a frame's read or write opened
    the group (its zarr.json) and then each array, and a read asked whether the ragged array's
    ``_count`` array was there before reading it (`name in group`), so that a frame of the fake
    pipeline's heatmaps read 11 zarr.json files, against 7 now (2026-12-07). Nothing read is kept
    beyond the call (another process may re-create the output in between)."""
    from pipeline.cache import FrameStore
    from pipeline.stage import ArraySpec

    asked: list[tuple[str, str]] = []
    _counting_filesystem(asked)
    root = tmp_path / "out.zarr"
    store = FrameStore(f"counted://{root}")
    specs = (ArraySpec("points", (4, 3), "float32", "m", fill=np.nan, ragged=True),
             ArraySpec("value", (), "float64", "-"))
    store.create("fp", ["a", "b"], specs, {"points": (4, 3), "value": ()}, {})

    def metadata_read(operation) -> list[str]:
        asked.clear()
        operation()
        assert all(what == "cat_file" for what, _ in asked), asked  # no existence check, no listing
        names = [path.removeprefix(f"{root}").strip("/") for _, path in asked]
        return sorted(name.removesuffix("zarr.json").strip("/") for name in names if name.endswith("zarr.json"))

    points = np.arange(6, dtype=np.float32).reshape(2, 3)
    for _ in range(2):  # the same again: nothing kept from the call before
        assert metadata_read(lambda: store.write_frame(1, {"points": points, "value": np.float64(5)}, specs)) \
            == ["points", "points_count", "reason", "status", "value"]
        assert metadata_read(lambda: np.testing.assert_array_equal(store.read("points", 1), points)) \
            == ["points", "points_count"]
        assert metadata_read(lambda: store.read("value", 1) == 5) == ["value", "value_count"]  # not there: one read
        assert metadata_read(lambda: store.status().tolist() == [PENDING, DONE]) == ["status"]
        assert metadata_read(lambda: store.fingerprint() == "fp") == [""]
    assert metadata_read(lambda: store.mark(0, 2, "bad")) == ["reason", "status"]
    assert store.reasons() == {0: "bad"}


def test_on_s3_a_frame_s_read_is_one_get_per_object(tmp_path, s3, monkeypatch):
    """s3fs (2026.9.0) reads a whole object with a HEAD (its size, to read a large one in parts)
    and then a GET; a missing one with a HEAD and a listing. The cache's zarr store reads each
    zarr.json and chunk with one GET: a frame of points (a ragged array: its rows and their count),
    its value (and the one request saying it has no count) and the status of the output are
    4, 3 and 1 + 8 GETs (40 requests before 2026-12-07, the group's zarr.json read by each); the
    status 2 GETs where the run left its snapshot (since 2026-12-07), 1 + 1 + 8 once a frame's
    status is written (the snapshot asked for, gone)."""
    import s3fs.core

    calls: list[str] = []
    original = s3fs.core.S3FileSystem._call_s3

    async def counting(self, method, *args, **kwargs):
        calls.append(method)
        return await original(self, method, *args, **kwargs)

    pipe = _pipe(f"{s3}/cache", tmp_path)
    pipe.run("calibrate")
    store = pipe.env.store("calibrate")
    monkeypatch.setattr(s3fs.core.S3FileSystem, "_call_s3", counting)
    store.read("points", 3)
    store.read("value", 3)
    assert (store.status() == DONE).all()
    assert calls == ["get_object"] * (4 + 3 + 2), calls
    store.mark(2, FAILED, "bad")
    calls.clear()
    assert (store.status() == FAILED).sum() == 1
    assert calls == ["get_object"] * (2 + len(IDS)), calls


def test_a_frame_s_arrays_on_a_remote_cache_are_read_in_two_round_trips(tmp_path):
    """FrameStore.read_many (and read_frame, of several outputs) reads the zarr.json of every array
    asked and of its row count concurrently, then every chunk: each read below waits at a barrier until all of its round trip
    are in flight (one after the other, as until 2026-12-07, the first would wait alone and the
    barrier break). A damaged chunk or a missing array is that name's value, an exception with
    read's own message, and the other arrays are read all the same."""
    import threading

    from pipeline.cache import FrameStore, read_frame
    from pipeline.stage import ArraySpec

    barriers: dict[str, threading.Barrier] = {}

    class Together(_object_store("together")):
        def cat_file(self, path, *args, **kwargs):
            barrier = barriers.get("metadata" if str(path).endswith("zarr.json") else "chunks")
            if barrier is not None:
                barrier.wait(timeout=20)
            return super().cat_file(path, *args, **kwargs)

    fsspec.register_implementation("together", Together, clobber=True)
    store = FrameStore(f"together://{tmp_path / 'out.zarr'}")
    specs = (ArraySpec("points", (4, 3), "float32", "m", fill=np.nan, ragged=True),
             ArraySpec("value", (), "float64", "-"))
    store.create("fp", ["a", "b"], specs, {"points": (4, 3), "value": ()}, {})
    points = np.arange(6, dtype=np.float32).reshape(2, 3)
    store.write_frame(1, {"points": points, "value": np.float64(5)}, specs)
    # points, points_count, value, value_count (not there); then the chunks of the three that are
    barriers.update(metadata=threading.Barrier(4), chunks=threading.Barrier(3))
    got = store.read_many(["points", "value"], 1)
    np.testing.assert_array_equal(got["points"], points)
    assert got["value"] == 5 and not any(b.broken for b in barriers.values())
    barriers.clear()
    other = FrameStore(f"together://{tmp_path / 'other.zarr'}")  # another stage's output: the same round trips
    other.create("fp", ["a", "b"], specs, {"points": (4, 3), "value": ()}, {})
    other.write_frame(1, {"points": points[:1], "value": np.float64(7)}, specs)
    barriers.update(metadata=threading.Barrier(4), chunks=threading.Barrier(3))
    mine, theirs = read_frame([(store, ["points"]), (other, ["value"])], 1)
    np.testing.assert_array_equal(mine["points"], points)
    assert theirs == {"value": 7} and not any(b.broken for b in barriers.values())
    barriers.clear()
    (tmp_path / "out.zarr" / "value" / "c" / "1").write_bytes(b"garbage")
    got = store.read_many(["value", "nothing", "points"], 1)
    with pytest.raises(ChunkError) as damaged:
        store.read("value", 1)
    assert isinstance(got["value"], ChunkError) and str(got["value"]) == str(damaged.value)
    assert isinstance(got["nothing"], KeyError)
    np.testing.assert_array_equal(got["points"], points)


def test_a_frame_stage_on_a_remote_cache_reads_a_frame_s_arrays_at_once(tmp_path, remote, monkeypatch):
    """On a remote cache each frame after a process's first of the stage reads at once
    (FrameInputs.prefetch, pipeline.cache.read_frame) the arrays that frame read: the fake heatmaps
    frame's points and value in one read_frame, not one after the other; the results equal a local
    cache's, and the frame whose chunk is damaged fails naming it. On a local cache nothing is
    read ahead (its chunk files are read directly)."""
    import pipeline.executor as executor
    from pipeline.cache import FrameStore

    calls: list[tuple[str, ...]] = []
    read_frame, read_many = executor.read_frame, FrameStore.read_many
    monkeypatch.setattr(executor, "read_frame", lambda wanted, *args: calls.append(
        tuple(f"{s.stage}:{n}" for s, names in wanted for n in names)) or read_frame(wanted, *args))
    monkeypatch.setattr(FrameStore, "read_many", lambda self, names, *args: calls.append(
        tuple(f"{self.stage}:{n}" for n in names)) or read_many(self, names, *args))
    local, far = _pipe(str(tmp_path / "cache"), tmp_path), _pipe(remote, tmp_path)
    for pipe in (local, far):
        pipe.run("calibrate")
    calls.clear()
    local.run("heatmaps")
    assert calls == []
    far.run("heatmaps")
    frame_reads = [c for c in calls if c != ("heatmaps:status",) and c != ("calibrate:status",)]
    assert frame_reads[:2] == [("calibrate:points",), ("calibrate:value",)], frame_reads  # the first frame
    assert frame_reads[2:] == [("calibrate:points", "calibrate:value")] * (len(IDS) - 1), frame_reads
    _assert_same_frames(local, far)
    chunk = f"{remote.removeprefix('memory://')}/fake/calibrate.zarr/value/c/3"
    fsspec.filesystem("memory").pipe_file(f"/{chunk}", b"garbage")
    far.run("heatmaps", force=True)
    reasons = far.env.store("heatmaps").reasons()
    assert list(reasons) == [3] and "calibrate.zarr/value, frame 3" in reasons[3], reasons


def test_each_run_of_a_stage_s_frames_keeps_what_it_reads_of_finished_outputs_for_itself(tmp_path, monkeypatch):
    """The runner gives each run of a frame stage's frames a token of its own (RunEnv.stage_run),
    the same for all its frames; run_memo builds once per process and token (the records a frame
    function reads of finished upstream outputs: a request per frame on a remote cache until
    2026-12-07), and each time where there is none: synthesize run again after a retraining, by the
    same Pipeline in the same process, reads the new train record and so loads the new nets."""
    import dataclasses

    import pipeline.executor as executor

    tokens: list[tuple[str, str]] = []
    process_frame = executor.process_frame

    def recording(stage, env, index, frame_id):
        tokens.append((stage.name, env.stage_run))
        return process_frame(stage, env, index, frame_id)

    monkeypatch.setattr(executor, "process_frame", recording)
    pipe = _pipe(str(tmp_path / "cache"), tmp_path)
    pipe.run("heatmaps")
    pipe.run("heatmaps", force=True)
    runs = [token for stage, token in tokens if stage == "heatmaps"]
    assert len(runs) == 2 * len(IDS) and all(runs)
    assert len(set(runs[:len(IDS)])) == len(set(runs[len(IDS):])) == 1 and runs[0] != runs[-1]
    assert pipe.env.stage_run == ""  # the pipeline's own environment keeps none
    built: list[int] = []
    env = pipe.env
    for token in ("a", "a", "b", "", ""):
        executor.run_memo(dataclasses.replace(env, stage_run=token) if token else env, ("test", tmp_path),
                          lambda: built.append(1) or len(built))
    assert len(built) == 4  # a once, b once, and each call without a token


def test_a_run_of_a_stage_s_frames_on_a_remote_cache_opens_its_arrays_once(tmp_path):
    """Each frame's write on a remote cache read the zarr.json of every array it writes, and each
    frame's read that of every array it reads (until 2026-12-07): on an object store a request
    each, every frame. Within one run of a stage's frames (RunEnv.stage_run; the run created its
    output before and holds its lock and the read locks of the outputs it reads) they are read once
    per process; another run reads them again, and the frames equal a local cache's."""
    asked: list[tuple[str, str]] = []
    _counting_filesystem(asked)
    far = _pipe(f"counted://{tmp_path / 'remote'}", tmp_path)
    local = _pipe(str(tmp_path / "cache"), tmp_path)
    local.run("heatmaps")
    far.run("calibrate")

    def metadata_reads(run) -> tuple[int, int]:
        asked.clear()
        run()
        reads = [path for what, path in asked if what == "cat_file"]
        return (sum(p.endswith("heatmaps.zarr/total/zarr.json") for p in reads),
                sum(p.endswith("calibrate.zarr/points/zarr.json") for p in reads))

    first = metadata_reads(lambda: far.run("heatmaps"))
    again = metadata_reads(lambda: far.run("heatmaps", force=True))
    assert first == again and max(first) <= 3, (first, again)  # (2, 1); before, (9, 9): one per frame
    _assert_same_frames(local, far)


def test_a_cache_error_reading_a_frames_inputs_on_a_remote_cache_stops_the_run(tmp_path, remote, monkeypatch):
    """As on a local cache (test_reliability): a cache problem reading an input array is no bad
    input of one frame, on the first frame (read alone) and on those read at once after it
    (FrameInputs.prefetch keeps the error for the stage's read to raise): the run stops at once,
    no frame failed, and a run after the problem is gone finishes every frame."""
    from pipeline.cache import FrameStore

    pipe = _pipe(remote, tmp_path)
    pipe.run("calibrate")
    checked, reads = FrameStore._checked, []

    def failing_at(n: int):
        def reading(self, arr, index, got=None, run=""):
            if self.url.endswith("/calibrate.zarr") and arr.path in ("points", "value"):
                reads.append(arr.path)
                if len(reads) > n:
                    raise CacheError(f"reading {self.url}: [Errno 5] Input/output error")
            return checked(self, arr, index, got, run)
        return reading

    for n in (0, 3):  # the first frame's read; the second frame's, read at once
        reads.clear()
        with monkeypatch.context() as patch:
            patch.setattr(FrameStore, "_checked", failing_at(n))
            with pytest.raises(CacheError, match="Input/output error"):
                pipe.run("heatmaps", force=True)
        status = pipe.env.store("heatmaps").status()
        assert not (status == FAILED).any() and pipe.env.store("heatmaps").reasons() == {}, n
        assert (status == DONE).sum() == (0 if n == 0 else 1), (n, status)
    pipe.run("heatmaps")
    assert (pipe.env.store("heatmaps").status() == DONE).all()


def _chunks_status(store) -> np.ndarray:
    """The status array as its chunks hold it (zarr's read, not the snapshot)."""
    return np.asarray(store._array("status")[:])


def _snapshot(store) -> np.ndarray | None:
    """The status as the output's status snapshot holds it (None: it has none)."""
    there = store._status_snapshot_there(store._array("status"))
    return None if there is None else there.status


def test_each_run_of_a_stage_s_frames_on_a_remote_cache_leaves_a_snapshot_equal_to_its_status(tmp_path, remote,
                                                                                           monkeypatch):
    """The runner writes a remote output's status snapshot from what it read and wrote, not from a
    read of every chunk: after runs that fail, block, exclude, retry, redo and stop at a failure
    (--strict), the snapshot is the status array's chunks, code for code."""
    from dataclasses import replace

    from pipeline.errors import FrameError

    ids = [*IDS[:3], "bad003", *IDS[4:]]
    picked = [i for i in range(len(ids)) if i != 5]  # heatmaps leaves frame 5 out (excluded)
    stages = [fake_stages.STAGES[0], replace(fake_stages.STAGES[1], select=lambda inputs, cfg: np.isin(
        np.arange(len(ids)), picked)), fake_stages.STAGES[2]]
    env = RunEnv(cfg=load_config("synthetic", {}, environ={}), cache_root=remote, dataset="fake",
                 data_root=str(tmp_path))
    pipe = Pipeline(stages, env, Executor(1), progress=False, log=lambda m: None, frame_lister=lambda: list(ids))

    def snapshots_hold_the_chunks() -> dict[str, list[int]]:
        out = {}
        for name in ("calibrate", "heatmaps"):
            store = pipe.env.store(name)
            if store.exists():
                chunks = _chunks_status(store)
                assert _snapshot(store) is not None, name
                np.testing.assert_array_equal(_snapshot(store), chunks, err_msg=name)
                np.testing.assert_array_equal(store.status(), chunks, err_msg=name)
                out[name] = chunks.tolist()
        return out

    pipe.run("heatmaps")
    assert snapshots_hold_the_chunks() == {"calibrate": [DONE] * 3 + [FAILED] + [DONE] * 4,
                                           "heatmaps": [DONE] * 3 + [FAILED, DONE, 3, DONE, DONE]}
    monkeypatch.setenv("FAKE_STAGE_FIXED", "1")
    pipe.run("calibrate", retry_failed=True)
    pipe.run("heatmaps")  # the frame its upstream blocked is tried now
    assert snapshots_hold_the_chunks()["heatmaps"] == [DONE] * 5 + [3, DONE, DONE]
    pipe.run("heatmaps", frames=[1, 6], force=True)  # redone: marked pending, then done again
    assert snapshots_hold_the_chunks()["heatmaps"] == [DONE] * 5 + [3, DONE, DONE]
    monkeypatch.delenv("FAKE_STAGE_FIXED")
    with pytest.raises(FrameError):
        pipe.run("calibrate", force=True, strict=True)  # stops at bad003: the frames after stay pending
    assert snapshots_hold_the_chunks()["calibrate"] == [DONE] * 3 + [FAILED] + [PENDING] * 4


def test_a_remote_output_s_status_comes_from_its_snapshot_until_a_status_chunk_is_written(tmp_path):
    """status() reads the snapshot, one object, where there is one (2 requests, not one per frame);
    writing a frame or marking one removes it first, so what status() then reads is the chunks
    again; creating the output writes one of pending frames. A local output reads its chunk files and keeps no snapshot (one
    copied there is removed by its first write)."""
    from pipeline.cache import STATUS_SNAPSHOT, FrameStore
    from pipeline.stage import ArraySpec

    asked: list[tuple[str, str]] = []
    _counting_filesystem(asked)
    specs = (ArraySpec("value", (), "float64", "-"),)
    ids = [f"f{i}" for i in range(40)]
    store = FrameStore(f"counted://{tmp_path / 'out.zarr'}")
    store.create("fp", ids, specs, {"value": ()}, {})
    store.write_frame(0, {"value": np.float64(1)}, specs)
    asked.clear()
    assert store.status().tolist() == [DONE] + [PENDING] * 39
    assert len(asked) == 2 + 40  # the status array's zarr.json, the missing snapshot, each chunk
    claimed = np.full(40, DONE, np.uint8)  # not what the chunks hold: tells which one status() read
    store.save_status_snapshot(claimed)
    asked.clear()
    assert store.status().tolist() == claimed.tolist() and len(asked) == 2

    for write in (lambda: store.write_frame(3, {"value": np.float64(2)}, specs),
                  lambda: store.write_frame(4, {"value": np.float64(2)}, specs, run="run-a"),
                  lambda: store.write_frame(5, {"value": np.float64(2)}, specs, run="run-b"),
                  lambda: store.mark(6, FAILED, "bad"),
                  lambda: store.mark_many(np.array([7, 8]), 3, "left out")):
        store.save_status_snapshot(claimed)
        write()
        assert not (tmp_path / "out.zarr" / STATUS_SNAPSHOT).exists()
        np.testing.assert_array_equal(store.status(), _chunks_status(store))
    store.save_status_snapshot(claimed)
    store.create("fp", ids, specs, {"value": ()}, {})  # re-created: its snapshot says every frame is pending
    assert _snapshot(store).tolist() == _chunks_status(store).tolist() == [PENDING] * 40

    local = FrameStore(str(tmp_path / "local.zarr"))
    local.create("fp", ids, specs, {"value": ()}, {})
    local.save_status_snapshot(claimed)  # nothing on a local cache
    assert not (tmp_path / "local.zarr" / STATUS_SNAPSHOT).exists()
    shutil.copy(tmp_path / "out.zarr" / "zarr.json", tmp_path / "local.zarr" / STATUS_SNAPSHOT)
    assert local.status().tolist() == [PENDING] * 40  # the chunk files, not the copied file
    local.write_frame(2, {"value": np.float64(1)}, specs)
    assert not (tmp_path / "local.zarr" / STATUS_SNAPSHOT).exists()


@pytest.mark.parametrize("damage", ["another frame count", "truncated", "not zstd", "an unknown code", "empty",
                                    "no token", "an unknown version", "no ages", "an age beyond its ancestors",
                                    "an age of 0", "an empty ancestor"])
def test_a_status_snapshot_that_does_not_hold_the_output_s_status_is_not_read(tmp_path, remote, damage):
    from pipeline.cache import STATUS_SNAPSHOT, FrameStore
    from pipeline.snapshots import _CODEC
    from pipeline.stage import ArraySpec

    specs = (ArraySpec("value", (), "float64", "-"),)
    store = FrameStore(f"{remote}/out.zarr")
    store.create("fp", [f"f{i}" for i in range(6)], specs, {"value": ()}, {})
    store.write_frame(1, {"value": np.float64(1)}, specs)
    body = _CODEC.encode(np.full(6, DONE, np.uint8).tobytes())
    head = b"radarsim status snapshot "
    data = {"another frame count": head + b"2 5 abc\n" + _CODEC.encode(bytes(5)),
            "truncated": head + b"2 6 abc\n" + body[:-3],
            "not zstd": head + b"2 6 abc\n" + bytes(6),
            "an unknown code": head + b"2 6 abc\n" + _CODEC.encode(bytes([1, 1, 1, 1, 1, 9])),
            "empty": b"",
            "no token": head + b"2 6\n" + body,
            "an unknown version": head + b"4 6 abc\n" + body,
            "no ages": head + b"3 6 abc def\n" + body,
            "an age beyond its ancestors": head + b"3 6 abc def\n" + _CODEC.encode(bytes([1] * 6 + [1, 2, 255] * 2)),
            "an age of 0": head + b"3 6 abc def\n" + _CODEC.encode(bytes([1] * 6 + [1, 0, 255] * 2)),
            "an empty ancestor": head + b"3 6 abc def,\n" + _CODEC.encode(bytes([1] * 6 + [1] * 6))}[damage]
    fsspec.filesystem("memory").pipe_file(f"{remote}/out.zarr/{STATUS_SNAPSHOT}", data)
    assert store.status().tolist() == [PENDING, DONE, PENDING, PENDING, PENDING, PENDING]
    fsspec.filesystem("memory").pipe_file(f"{remote}/out.zarr/{STATUS_SNAPSHOT}", head + b"2 6 abc\n" + body)
    assert store.status().tolist() == [DONE] * 6  # the same, whole: read
    fsspec.filesystem("memory").pipe_file(f"{remote}/out.zarr/{STATUS_SNAPSHOT}", head + b"1 6\n" + body)
    assert store.status().tolist() == [DONE] * 6  # 2026-12-07's first version, without a token: read too
    fsspec.filesystem("memory").pipe_file(f"{remote}/out.zarr/{STATUS_SNAPSHOT}", head + b"3 6 abc def,ghi\n" +
                                          _CODEC.encode(bytes([1] * 6 + [1, 2, 255, 1, 1, 2])))
    assert store.status().tolist() == [DONE] * 6  # a lineage that fits


def test_the_upload_at_the_end_of_a_staged_run_sends_what_was_not_uploaded_as_it_now_is(tmp_path, remote,
                                                                                         monkeypatch):
    """StagedUploads: a file published while the stage ran is not sent again at its end unless it
    was written again since (checkpoints are renamed over: another inode), nor is _stage.json; a
    file whose upload failed is."""
    from pipeline.errors import CacheError

    out = DirStore(f"{remote}/train")
    work = DirStore(str(tmp_path / "staging"))
    logs: list[str] = []
    uploads = StagedUploads(out, work, "train", logs.append)
    root = tmp_path / "staging"
    for name in ("a.bin", "b.bin", "c.bin", "_stage.json"):
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(name.encode())
    assert uploads.publish([root / "a.bin", root / "b.bin"]) and out.fs.cat_file(out.file("a.bin")) == b"a.bin"
    (root / "b.tmp").write_bytes(b"b, again")
    (root / "b.tmp").replace(root / "b.bin")
    assert [p.name for p in uploads.left()] == ["b.bin", "c.bin"]
    assert uploads.publish(["b.bin"]) and [p.name for p in uploads.left()] == ["c.bin"]  # a path inside the folder

    def fails(self, staged, files=None):
        raise CacheError(f"uploading to {self.url}: Connection reset by peer")

    monkeypatch.setattr(DirStore, "upload", fails)
    assert not uploads.publish([root / "c.bin"]) and "going on" in logs[-1]
    assert [p.name for p in uploads.left()] == ["c.bin"]


def test_a_run_reads_the_group_metadata_once_for_values_that_are_all_fill(tmp_path):
    """A value that is all fill (a stopped ego's velocity) is checked against a missing chunk,
    which zarr reads as the fill: whether the output has every chunk written is in its group's
    zarr.json, read for each such value, a request each on an object store; within a run of a
    stage's frames once per process. A missing chunk of a done frame is still named."""
    from pipeline.cache import FrameStore, read_frame
    from pipeline.stage import ArraySpec

    asked: list[tuple[str, str]] = []
    _counting_filesystem(asked)
    root = tmp_path / "out.zarr"
    store = FrameStore(f"counted://{root}")
    specs = (ArraySpec("ego", (3,), "float32", "m/s"),)
    store.create("fp", [f"f{i}" for i in range(6)], specs, {"ego": (3,)}, {})
    for i in range(6):
        store.write_frame(i, {"ego": np.zeros(3, np.float32)}, specs)

    def group_reads(run: str) -> int:
        asked.clear()
        for i in range(5):
            assert read_frame([(store, ["ego"])], i, run)[0]["ego"].tolist() == [0, 0, 0]
        return sum(path == f"{root}/zarr.json" for _, path in asked)

    assert group_reads("") == 5 and group_reads("run-a") == 1 and group_reads("run-a") == 0
    (root / "ego" / "c" / "5" / "0").unlink()
    got = read_frame([(store, ["ego"])], 5, "run-a")[0]["ego"]
    assert isinstance(got, ChunkError) and "is missing although the frame is done" in str(got)


def test_verify_names_the_frames_whose_status_snapshot_disagrees_with_their_status_chunks(tmp_path, remote):
    """Readers of a remote output's status take its snapshot: verify, which reads every status
    chunk, names each frame where the two disagree (the status chunk, with the command that
    recomputes the frame), and that command leaves them agreeing."""
    pipe = _pipe(remote, tmp_path)
    pipe.run("heatmaps")
    assert all(not r.get("damaged") for r in verify_cache(pipe))
    store = pipe.env.store("calibrate")
    claimed = _chunks_status(store)
    claimed[[2, 5]] = [PENDING, FAILED]
    store.save_status_snapshot(claimed)
    damaged = {r["stage"]: r.get("damaged") for r in verify_cache(pipe)}
    assert sorted(damaged["calibrate"]) == [2, 5] and not damaged["heatmaps"], damaged
    assert "calibrate.zarr/status/c/5" in damaged["calibrate"][5] and "says the frame is done where the output's " \
        "status snapshot" in damaged["calibrate"][5] and "says failed" in damaged["calibrate"][5], damaged
    assert "--force --frames f005" in damaged["calibrate"][5], damaged
    pipe.run("calibrate", frames=[2, 5], force=True)
    assert all(not r.get("damaged") for r in verify_cache(pipe))
    assert _snapshot(store).tolist() == _chunks_status(store).tolist() == [DONE] * len(IDS)


def _small_output(url: str, n: int):
    """A FrameStore at ``url`` of ``n`` frames with a scalar, a vector and a ragged array, every
    frame written (value i, vector i + (0, 1, 2)) and its status snapshot saved."""
    from pipeline.cache import FrameStore
    from pipeline.stage import ArraySpec

    specs = (ArraySpec("value", (), "float64", "-", fill=np.nan), ArraySpec("vec", (3,), "int32", "-"),
             ArraySpec("rows", (64, 32), "float32", "-", fill=np.nan, ragged=True))
    store = FrameStore(url)
    store.create("fp", [f"f{i}" for i in range(n)], specs, {"value": (), "vec": (3,), "rows": (64, 32)}, {})
    for i in range(n):
        store.write_frame(i, {"value": np.float64(i), "vec": np.arange(3, dtype=np.int32) + i,
                              "rows": np.ones((i % 3, 32), np.float32)}, specs)
    store.save_status_snapshot(np.full(n, DONE, np.uint8))
    return store, specs


def test_a_remote_output_s_small_arrays_are_read_whole_from_their_column_snapshot(tmp_path):
    """A whole read of a small per-frame array (numbers, at most 4 kB a frame) of a remote output
    reads its chunks once, a request per frame, and keeps them in one object that the next whole
    reads take (2 requests and the array's zarr.json), while the status snapshot it was read under
    is there: a frame written or marked since, or the output re-created, and the chunks are read
    again, also when the status snapshot is written again with the same codes (a forced frame
    goes back to done). A read of some frames takes the column too; it reads all the chunks to
    make one only when it wants at least half of them. Larger arrays are always read from their chunks."""
    from pipeline.cache import FAILED

    asked: list[tuple[str, str]] = []
    _counting_filesystem(asked)
    root = tmp_path / "out.zarr"
    store, specs = _small_output(f"counted://{root}", 40)

    def read(name: str, frames=None) -> tuple[np.ndarray, int]:
        """The values and how many chunks the read asked for."""
        asked.clear()
        got = store.array(name)[:] if frames is None else store.array(name).oindex[frames]
        return np.asarray(got), sum("/c/" in path for _, path in asked)

    values, chunks = read("value")
    assert values.tolist() == list(range(40)) and chunks == 40
    values, chunks = read("value")
    assert values.tolist() == list(range(40)) and chunks == 0 and len(asked) == 3
    assert read("vec", [3, 5])[1] == 2  # 2 of 40 frames: their chunks, no column made
    assert read("vec", np.arange(20))[1] == 40  # half: the column is made
    vec, chunks = read("vec", [3, 5])
    assert vec.tolist() == [[3, 4, 5], [5, 6, 7]] and chunks == 0
    rows, chunks = read("rows_count")
    assert rows.tolist() == [i % 3 for i in range(40)] and chunks == 40
    assert read("rows")[1] == 40 and read("rows")[1] == 40  # 8 kB a frame: no column
    assert sorted(p.name for p in root.glob("column_snapshot.*")) == \
        ["column_snapshot.rows_count", "column_snapshot.value", "column_snapshot.vec"]

    store.write_frame(5, {"value": np.float64(-5), "vec": np.zeros(3, np.int32), "rows": np.ones((0, 32))}, specs)
    values, chunks = read("value")  # no status snapshot: the chunks, and no column made
    assert values[5] == -5 and chunks == 40 and read("value")[1] == 40
    store.save_status_snapshot(np.full(40, DONE, np.uint8))  # the same codes, another token
    values, chunks = read("value")
    assert values[5] == -5 and chunks == 40
    values, chunks = read("value")
    assert values[5] == -5 and chunks == 0
    assert read("vec", [5])[0].tolist() == [[0, 0, 0]]
    store.mark(6, FAILED, "bad")
    assert read("value")[1] == 40

    store.save_status_snapshot(np.full(40, DONE, np.uint8))
    assert read("value")[1] == 40 and read("value")[1] == 0
    store.create("fp", [f"f{i}" for i in range(40)], specs, {"value": (), "vec": (3,), "rows": (64, 32)}, {})
    values, chunks = read("value")  # re-created: nothing written yet
    assert np.isnan(values).all() and chunks == 40

    local, _ = _small_output(str(tmp_path / "local.zarr"), 6)
    assert np.asarray(local.array("value")[:]).tolist() == list(range(6))
    assert not list((tmp_path / "local.zarr").glob("column_snapshot.*"))


@pytest.mark.parametrize("damage", ["another token", "another dtype", "another shape", "truncated", "not zstd",
                                    "empty", "a status snapshot without a token"])
def test_a_column_snapshot_that_does_not_hold_the_array_is_not_read(tmp_path, remote, damage):
    from pipeline.cache import STATUS_SNAPSHOT
    from pipeline.snapshots import _CODEC, decode_status, encode_column

    store, _ = _small_output(f"{remote}/out.zarr", 6)
    fs = fsspec.filesystem("memory")
    snapshot = decode_status(fs.cat_file(f"{remote}/out.zarr/{STATUS_SNAPSHOT}"), 6, (0, 1, 2, 3))
    status, token = snapshot.status, snapshot.token
    lie = np.full(6, 7.0)  # not what the chunks hold
    good = encode_column(lie, token)
    head = b"radarsim column snapshot 1 "
    data = {"another token": encode_column(lie, "0123456789abcdef"),
            "another dtype": encode_column(lie.astype(np.float32), token),
            "another shape": encode_column(lie[:5], token),
            "truncated": good[:-3],
            "not zstd": head + f"{token} <f8 6\n".encode() + lie.tobytes(),
            "empty": b"",
            "a status snapshot without a token": good}[damage]
    if damage == "a status snapshot without a token":
        fs.pipe_file(f"{remote}/out.zarr/{STATUS_SNAPSHOT}", b"radarsim status snapshot 1 6\n" +
                     _CODEC.encode(status.tobytes()))
    fs.pipe_file(f"{remote}/out.zarr/column_snapshot.value", data)
    assert np.asarray(store.array("value")[:]).tolist() == list(range(6))
    if damage != "a status snapshot without a token":  # the column is made again, holding the chunks
        assert np.asarray(store.array("value")[:]).tolist() == list(range(6))
        fs.pipe_file(f"{remote}/out.zarr/column_snapshot.value", good)  # and the check tells them apart
    assert np.asarray(store.array("value")[:]).tolist() == (lie.tolist() if damage != "a status snapshot without a "
                                                            "token" else list(range(6)))


def test_a_reader_that_cannot_write_the_column_snapshot_reads_the_chunks(tmp_path, remote, monkeypatch):
    """Read-only credentials: the column cannot be kept, so each whole read reads the chunks (the
    read does not fail)."""
    import pipeline.cache

    store, _ = _small_output(f"{remote}/out.zarr", 6)

    async def refused(*args, **kwargs):
        raise PermissionError("Access Denied")

    monkeypatch.setattr(pipeline.cache, "put_object", refused)
    for _ in range(2):
        assert np.asarray(store.array("value")[:]).tolist() == list(range(6))
    assert not fsspec.filesystem("memory").exists(f"{remote}/out.zarr/column_snapshot.value")


def test_verify_names_the_frames_whose_column_snapshot_disagrees_with_their_chunks(tmp_path, remote):
    """Readers take a remote output's column snapshot where it is tagged with the status snapshot
    there: verify, which reads every chunk, names each done frame whose chunk holds another value."""
    from pipeline.cache import STATUS_SNAPSHOT
    from pipeline.snapshots import decode_status, encode_column

    store, _ = _small_output(f"{remote}/out.zarr", 6)
    assert store.verify()[1] == {}
    fs = fsspec.filesystem("memory")
    token = decode_status(fs.cat_file(f"{remote}/out.zarr/{STATUS_SNAPSHOT}"), 6, (0, 1, 2, 3)).token
    vec = np.asarray(store.array("vec")[:])
    vec[4, 1] = 99
    fs.pipe_file(f"{remote}/out.zarr/column_snapshot.vec", encode_column(vec, token))
    errors = store.verify()[1]
    assert list(errors) == [4] and "out.zarr/vec" in str(errors[4]) and "holds [4, 5, 6] where the output's column " \
        "snapshot" in str(errors[4]) and "column_snapshot.vec) holds [4, 99, 6]" in str(errors[4]), errors
    store.save_status_snapshot(np.full(6, DONE, np.uint8))  # what recomputing the frame does to it
    assert store.verify()[1] == {}


def test_a_run_with_nothing_to_do_keeps_the_status_snapshot_and_the_columns_read_under_it(tmp_path, remote):
    """On a remote cache every command runs the stages before its target under their locks; one
    with nothing to do leaves the status snapshot there, token and all, so that the column
    snapshots read under it stay (calibrate's split, read by each later stage's frame selection,
    is read once, not once per command). Frames forced again change the token; the forced stage's
    snapshot is written again once its frames are marked pending, so that its run reads one
    object rather than every status chunk."""
    from pipeline.cache import STATUS_SNAPSHOT
    from pipeline.snapshots import decode_status

    pipe = _pipe(remote, tmp_path)
    pipe.run("heatmaps")
    fs = fsspec.filesystem("memory")

    def token(stage: str) -> str | None:
        path = f"{remote}/fake/{stage}.zarr/{STATUS_SNAPSHOT}"
        parsed = decode_status(fs.cat_file(path) if fs.exists(path) else None, len(IDS), (0, 1, 2, 3))
        return None if parsed is None else parsed.token

    calibrate = pipe.env.store("calibrate")
    values = np.asarray(calibrate.array("value")[:])
    column = fs.cat_file(f"{remote}/fake/calibrate.zarr/column_snapshot.value")
    before = {stage: token(stage) for stage in ("calibrate", "heatmaps")}
    assert all(before.values())
    pipe.run("heatmaps")
    assert {stage: token(stage) for stage in ("calibrate", "heatmaps")} == before
    assert before["calibrate"].encode() in column

    pipe.redo_frames("heatmaps", [2])
    assert token("heatmaps") not in (None, before["heatmaps"])
    heatmaps = pipe.env.store("heatmaps")
    assert _snapshot(heatmaps).tolist() == _chunks_status(heatmaps).tolist() == [DONE] * 2 + [PENDING] + [DONE] * 5
    pipe.run("heatmaps")
    assert token("calibrate") == before["calibrate"] and (heatmaps.status() == DONE).all()
    pipe.run("calibrate", frames=[1], force=True)
    assert token("calibrate") not in (None, before["calibrate"])
    np.testing.assert_array_equal(calibrate.array("value")[:], values)  # read again from the chunks
    assert fs.cat_file(f"{remote}/fake/calibrate.zarr/column_snapshot.value") != column


def test_a_column_read_before_runs_is_brought_up_to_date_from_the_frames_they_wrote(tmp_path, monkeypatch):
    """Each run's status snapshot succeeds the one it read its status from and says which frames
    it wrote: a column read under one of the last LINEAGE_MAX snapshots is brought up to date by
    reading those frames' chunks (3 frames recomputed: 3 chunks, not every frame's; by a read that
    wants at least half as many frames), over several runs too, a frame that a run alone made done
    (retried, no marks before it) included; a column older than that, or read before a snapshot
    written without a lineage (a frame written outside a run, so the next run read its status
    from the chunks), is read again from every chunk. verify checks the frames that readers take
    from such a column."""
    from dataclasses import replace

    import pipeline.snapshots

    asked: list[tuple[str, str]] = []
    _counting_filesystem(asked)
    now: dict[str, float] = {}  # frame id -> the value calibrate writes for it from now on

    def process(inputs, cfg):
        out = fake_stages.first(inputs, cfg)
        return {**out, "value": np.float64(now.get(inputs.frame_id, out["value"]))}

    ids = [*IDS[:3], "bad003", *IDS[4:]]
    stages = [replace(fake_stages.STAGES[0], process=process), *fake_stages.STAGES[1:]]
    env = RunEnv(cfg=load_config("synthetic", {}, environ={}), cache_root=f"counted://{tmp_path / 'cache'}",
                 dataset="fake", data_root=str(tmp_path))
    pipe = Pipeline(stages, env, Executor(1), progress=False, log=lambda m: None, frame_lister=lambda: list(ids))
    pipe.run("calibrate")  # bad003 fails
    calibrate = pipe.env.store("calibrate")

    def read() -> int:
        """How many chunks a whole read of calibrate's value asked for (its done frames' values
        checked against their chunks)."""
        asked.clear()
        got = np.asarray(calibrate.array("value")[:])
        chunks = sum("/c/" in path for _, path in asked)
        done = calibrate.status() == DONE
        np.testing.assert_array_equal(got[done], np.asarray(calibrate._array("value")[:])[done])
        return chunks

    def recompute(frame: int, value: float) -> None:
        now[ids[frame]] = value
        pipe.run("calibrate", frames=[frame], force=True)

    assert read() == len(ids) and read() == 0
    monkeypatch.setenv("FAKE_STAGE_FIXED", "1")
    pipe.run("calibrate", retry_failed=True)  # frame 3 done in the run's own snapshot only
    assert read() == 1 and read() == 0
    now.update({ids[1]: -1.0, ids[5]: -5.0, ids[6]: -6.0})
    pipe.run("calibrate", frames=[1, 5, 6], force=True)

    def some(frames: list[int]) -> tuple[list[float], int]:
        asked.clear()
        return np.asarray(calibrate.array("value").oindex[frames]).tolist(), sum("/c/" in p for _, p in asked)

    # a read brings the column up to date when that reads at most twice the chunks it wants
    assert some([0]) == ([0.0], 1)  # 3 frames written since: the frame's own chunk
    assert some([0, 6]) == ([0.0, -6.0], 3) and some([0]) == ([0.0], 0)
    assert read() == 0
    recompute(2, -2.0)
    recompute(3, -3.0)
    assert read() == 2 and read() == 0
    assert np.asarray(calibrate.array("value")[:]).tolist() == [0, -1, -2, -3, 4, -5, -6, 7]

    errors = calibrate.verify()[1]
    assert errors == {}, errors
    recompute(4, -4.0)  # the column holds frame 4's old value until a read brings it up to date
    fs = fsspec.filesystem("file")
    column = tmp_path / "cache" / "fake" / "calibrate.zarr" / "column_snapshot.value"
    data = fs.cat_file(str(column))
    values, token = pipeline.snapshots.decode_column(data, np.float64, (len(ids),))
    values[5] = 99.0  # a value readers would take (frame 5 was not written since)
    fs.pipe_file(str(column), pipeline.snapshots.encode_column(values, token))
    errors = calibrate.verify()[1]
    assert list(errors) == [5] and "holds -5.0 where the output's column snapshot" in str(errors[5]), errors
    fs.pipe_file(str(column), data)
    assert read() == 1

    calibrate.write_frame(0, {"value": np.float64(0), "points": np.zeros((0, 3), np.float32)},
                          stages[0].outputs(env.cfg))  # outside a run: the next one reads the chunks' status
    recompute(7, -7.0)
    assert read() == len(ids) and read() == 0
    monkeypatch.setattr(pipeline.snapshots, "LINEAGE_MAX", 3)  # a forced run writes two: marked, and at its end
    recompute(1, 11.0)
    assert read() == 1
    recompute(2, 12.0)
    recompute(3, 13.0)
    assert read() == len(ids)  # read under the fourth snapshot before the present one
