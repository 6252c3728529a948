"""A train on a remote cache killed while its staging folder is being filled from the remote."""

from __future__ import annotations

import shutil
import uuid

import fsspec
import pytest

from pipeline.dirstore import DirStore
from tests.test_remote_cache import _killed_in_the_second_epoch, _real_pipe


def test_a_download_cut_off_midway_is_done_again(tiny_world, tmp_path, monkeypatch):
    """A machine taking over a remote train downloads the last run's files into its staging
    folder. Killed midway (here after the first file), the folder holds part of them; it must not
    then pass for the remote run's staging folder (the download used to copy the run token too,
    first), or the next run resumes from half-written checkpoints. It downloads again and ends with
    the weights of an uninterrupted run."""
    from pipeline.errors import StageInterrupted
    from tests.test_remote_cache import _tensors

    world = tmp_path / "world"
    shutil.copytree(tiny_world, world)
    remote = f"memory://resume-{uuid.uuid4().hex[:8]}"
    settings = {"train.epochs": "3", "train.nets": "disnet", "run.checkpoint_upload_s": "0"}
    first = _real_pipe(remote, world, tmp_path / "machine-a", [], **settings)
    with monkeypatch.context() as patch:
        _killed_in_the_second_epoch(patch)
        with pytest.raises(StageInterrupted):
            first.run("train")
    fs = fsspec.filesystem("memory")
    get = type(fs).get

    def cut_off(self, rpath, lpath, *args, **kwargs):
        get(self, rpath[:1], lpath[:1], *args, **kwargs)
        raise KeyboardInterrupt("simulated kill while downloading")

    logs: list[str] = []
    second = _real_pipe(remote, world, tmp_path / "machine-b", logs, **settings)
    with monkeypatch.context() as patch:
        patch.setattr(type(fs), "get", cut_off)
        with pytest.raises(StageInterrupted):
            second.run("train")
    staging = DirStore(str(next((tmp_path / "machine-b").glob("train-*/staging"))))
    assert staging.run_token() is None
    second.run("train")
    assert sum("resuming from" in line for line in logs) == 1, logs  # the cut-off one never got to say it
    assert second.env.dir("train").summary()["disnet"]["resumed_from"] == 1
    whole = _real_pipe(str(tmp_path / "cache"), world, tmp_path / "unused", [], **settings)
    whole.run("train")
    a = _tensors((tmp_path / "cache" / "synthetic" / "train" / "disnet" / "best.safetensors").read_bytes())
    b = _tensors(fs.cat_file(f"{remote.removeprefix('memory://')}/synthetic/train/disnet/best.safetensors"))
    assert a.keys() == b.keys() and all((a[k] == b[k]).all() for k in a)
    fs.rm(remote.removeprefix("memory://"), recursive=True)


def test_a_run_going_on_in_its_own_staging_folder_keeps_the_run_token(tiny_world, tmp_path, monkeypatch):
    """A run that goes on in this machine's staging folder of the last run keeps that run's token:
    it used to write a new one into the remote folder and then the staging folder, and a kill
    between the two writes left them different, so the next run threw away the staging folder's
    newer epochs for the remote's last upload (here none: training from scratch)."""
    from pipeline.dirstore import RUN_TOKEN
    from pipeline.errors import StageInterrupted

    world = tmp_path / "world"
    shutil.copytree(tiny_world, world)
    remote = f"memory://token-{uuid.uuid4().hex[:8]}"
    settings = {"train.epochs": "2", "train.nets": "disnet", "run.checkpoint_upload_s": "3600"}
    logs: list[str] = []
    pipe = _real_pipe(remote, world, tmp_path / "machine", logs, **settings)
    with monkeypatch.context() as patch:
        _killed_in_the_second_epoch(patch)
        with pytest.raises(StageInterrupted):
            pipe.run("train")
    token = pipe.env.dir("train").run_token()
    write_text = DirStore.write_text

    def killed_writing_the_staging_token(self, name, text):
        if name == RUN_TOKEN and "://" not in self.url:
            raise KeyboardInterrupt("simulated kill between the two token writes")
        return write_text(self, name, text)

    with monkeypatch.context() as patch:
        patch.setattr(DirStore, "write_text", killed_writing_the_staging_token)
        try:
            pipe.run("train")
        except StageInterrupted:  # as before: killed between the remote's token and the staging folder's
            pass
    pipe.run("train")
    assert pipe.env.dir("train").run_token() == token
    assert not any("resuming from" in line for line in logs), logs
    assert pipe.env.dir("train").summary()["disnet"]["resumed_from"] == 1
    fsspec.filesystem("memory").rm(remote.removeprefix("memory://"), recursive=True)


def test_a_partial_local_copy_a_killed_process_left_is_removed_after_a_day(tmp_path, monkeypatch):
    """A process killed while downloading a local copy of a finished remote output leaves its dot
    folder; another process may be downloading into its own right now, so a fresh one is left to
    it, but one untouched for STALE_COPY_S goes with the copies of earlier runs (they piled up:
    checkpoints of 56 MB per killed synthesize on the demo)."""
    import os
    import time

    from pipeline.dirstore import STALE_COPY_S

    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    remote = f"memory://copies-{uuid.uuid4().hex[:8]}"
    out = DirStore(f"{remote}/train")
    out.write_text("disnet/best.safetensors", "one")
    out.finish("fp", {})
    copy = out.local_copy("~/staging")
    fresh, old = copy.parent / ".aaaa-fresh", copy.parent / ".bbbb-old"
    for partial in (fresh, old):
        (partial / "disnet").mkdir(parents=True)
        (partial / "disnet" / "best.safetensors").write_text("half")
    then = time.time() - STALE_COPY_S - 60
    os.utime(old, (then, then))
    out.write_text("disnet/best.safetensors", "two")
    out.finish("fp", {})  # a new run: its copy replaces the first, and the stale partial one goes
    again = out.local_copy("~/staging")
    assert sorted(p.name for p in again.parent.iterdir()) == sorted([again.name, fresh.name])
    fsspec.filesystem("memory").rm(remote.removeprefix("memory://"), recursive=True)
