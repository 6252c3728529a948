"""A cache on a non-local fsspec filesystem (memory://, standing in for s3:// or gcs://): frames
go through zarr's own path, not the chunk files, and must give what a local cache gives, resume
the same way, and name a damaged chunk. Small pipelines of tests/fake_stages.py."""

from __future__ import annotations

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
