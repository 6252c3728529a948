"""A cache on a non-local fsspec filesystem (memory://, standing in for s3:// or gcs://): frames
go through zarr's own path, not the chunk files, and must give what a local cache gives, resume
the same way, and name a damaged chunk. Small pipelines of tests/fake_stages.py."""

from __future__ import annotations

import json
import uuid
from pathlib import Path

import fsspec
import numpy as np
import pytest

from pipeline.cache import DONE, PENDING
from pipeline.config import load_config
from pipeline.errors import ChunkError
from pipeline.executor import Executor, RunEnv
from pipeline.runner import Pipeline
from tests import fake_stages
from tests.test_damaged_cache import IDS


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
    for stage, names in (("calibrate", ("points", "value")), ("heatmaps", ("total",))):
        a, b = local.env.store(stage), far.env.store(stage)
        assert (b.status() == DONE).all()
        for name in names:
            for i in range(len(IDS)):
                np.testing.assert_array_equal(a.read(name, i), b.read(name, i), err_msg=f"{stage}/{name} {i}")
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


def test_the_stages_writing_local_files_stage_and_upload_on_a_remote_cache(tmp_path, remote):
    """train, evaluate and export write with local file APIs: on a remote cache they write into a
    local staging folder (run.staging_dir) that is uploaded when they finish, and synthesize and
    evaluate read the checkpoints through a local copy. Everything equals a local cache's run; a
    second machine (another staging folder) resumes train from what the first uploaded."""
    from pipeline.world import generate

    world = tmp_path / "world"
    generate(world, frames=10, seed=5, resolution_wh=(640, 384), sequence_len=10)
    logs: list[str] = []
    local = _real_pipe(str(tmp_path / "cache"), world, tmp_path / "unused", logs)
    far = _real_pipe(remote, world, tmp_path / "machine-a", logs)
    for pipe in (local, far):
        pipe.run("evaluate")
        pipe.run("export")
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
                      if p.is_file() and p.name != "_stage.json")
    assert len(exported) > 30
    assert sorted(f.removeprefix(f"/{there}/export/") for f in fs.find(f"{there}/export")
                  if not f.endswith(("_stage.json", "_run.token"))) == exported
    for name in exported:
        assert fs.cat_file(f"{there}/export/{name}") == (here / "export" / name).read_bytes(), name
    ours, theirs = (json.loads(p) for p in ((here / "evaluate" / "report.json").read_text(),
                                           fs.cat_file(f"{there}/evaluate/report.json")))
    assert len(ours["metrics"]) > 5
    for key in ("metrics", "distribution_distances", "physics_checks", "by_ego_speed", "meta"):
        assert json.dumps(ours[key], sort_keys=True) == json.dumps(theirs[key], sort_keys=True), key
    figures = sorted(p.name for p in (here / "evaluate" / "figures").iterdir())
    assert len(figures) >= 3 and sorted(f.rsplit("/", 1)[-1] for f in fs.find(f"{there}/evaluate/figures")) == figures
    kept = {p.name.split("-")[0]: sorted(q.name for q in p.iterdir()) for p in (tmp_path / "machine-a").iterdir()}
    # train's staging folder (it resumes from it) and the copy synthesize and evaluate read; the
    # uploaded staging folders of export and evaluate are not kept
    assert kept == {"train": ["copies", "staging"], "export": [], "evaluate": []}, kept
    summary = far.env.dir("train").summary()  # the remote folder, not the staging one, is named
    assert summary["checkpoints"] == f"{remote}/synthetic/train"
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


def test_a_staged_train_killed_mid_run_resumes_from_its_staging_folder(tmp_path, remote, monkeypatch):
    """A train killed after its first epoch on a remote cache has uploaded nothing (the output is
    not done); run again on the same machine it goes on from that epoch in its staging folder,
    without downloading, and uploads the finished nets."""
    import pipeline.training
    from pipeline.errors import StageInterrupted
    from pipeline.world import generate

    world = tmp_path / "world"
    generate(world, frames=10, seed=5, resolution_wh=(640, 384), sequence_len=10)
    original, calls = pipeline.training.train_one_epoch, []

    def killed_in_the_second_epoch(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt("simulated kill")
        return original(*args, **kwargs)

    logs: list[str] = []
    pipe = _real_pipe(remote, world, tmp_path / "machine", logs, **{"train.epochs": "2", "train.nets": "disnet"})
    with monkeypatch.context() as patch:
        patch.setattr(pipeline.training, "train_one_epoch", killed_in_the_second_epoch)
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
