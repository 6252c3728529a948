"""Atomic, durable writes (pipeline.fileio) on file systems that cannot flush or fail to."""

from __future__ import annotations

import errno
import os

import pytest
import torch

from pipeline import checkpoint as ckpt
from pipeline.fileio import UNSUPPORTED_FSYNC, atomic_path


def _fsync_failing(monkeypatch, code: int) -> list[str]:
    """Make os.fsync fail with ``code``; returns the list of paths it was asked to flush."""
    asked: list[str] = []

    def failing(fd):
        asked.append(os.readlink(f"/proc/self/fd/{fd}"))
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(os, "fsync", failing)
    return asked


@pytest.mark.parametrize("code", sorted(UNSUPPORTED_FSYNC))
def test_a_file_system_that_cannot_flush_still_gets_its_checkpoint(tmp_path, monkeypatch, code):
    """Some FUSE mounts of object stores and network file systems answer fsync with EINVAL,
    ENOTSUP or ENOSYS (a folder's with EBADF): nothing to flush there, so the checkpoint is
    renamed into place as before instead of training stopping at its first save."""
    path = tmp_path / "net" / "last.safetensors"
    asked = _fsync_failing(monkeypatch, code)
    ckpt.save_checkpoint(path, {"model.w": torch.ones(3)}, {"epoch": 1})
    assert ckpt.read_meta(path)["epoch"] == 1
    assert len(asked) == 2 and asked[1] == str(path.parent)  # the file, then its folder


def test_a_failed_flush_is_an_error_naming_the_file_and_the_old_checkpoint_stays(tmp_path, monkeypatch):
    """EIO from fsync means the new data may not be on the disk: the write fails, naming the file,
    and the last good checkpoint stays in place, with no temporary file left beside it."""
    path = tmp_path / "net" / "last.safetensors"
    ckpt.save_checkpoint(path, {"model.w": torch.ones(3)}, {"epoch": 1})
    _fsync_failing(monkeypatch, errno.EIO)
    with pytest.raises(OSError) as info:
        ckpt.save_checkpoint(path, {"model.w": torch.zeros(3)}, {"epoch": 2})
    assert info.value.errno == errno.EIO and info.value.filename.startswith(str(path.parent / ".last.safetensors."))
    monkeypatch.undo()
    assert ckpt.read_meta(path)["epoch"] == 1
    assert sorted(p.name for p in path.parent.iterdir()) == ["last.json", "last.safetensors"]


def test_an_atomic_write_without_durable_does_not_flush(tmp_path, monkeypatch):
    asked = _fsync_failing(monkeypatch, errno.EIO)
    with atomic_path(tmp_path / "a.txt") as tmp:
        tmp.write_text("x")
    assert (tmp_path / "a.txt").read_text() == "x" and asked == []


def test_flushing_a_file_system_waits_for_that_one_only(tmp_path, monkeypatch):
    """A dataset stage's folder is flushed with syncfs on its own file system: os.sync would wait
    for every mount, a hung network mount too. Where syncfs does not exist, os.sync serves."""
    import ctypes

    from pipeline.fileio import sync_filesystem

    def everything():
        raise AssertionError("os.sync called")

    with monkeypatch.context() as patch:
        patch.setattr(os, "sync", everything)
        sync_filesystem(tmp_path)  # Linux: syncfs
    synced = []
    monkeypatch.setattr(os, "sync", lambda: synced.append(True))
    monkeypatch.setattr(ctypes, "CDLL", lambda *a, **k: type("NoSyncfs", (), {})())
    sync_filesystem(tmp_path)
    assert synced == [True]


def test_a_frame_stage_run_flushes_its_output_when_it_ends(tmp_path, monkeypatch):
    """Frames are not flushed one by one (0.6 ms an fsync per chunk): a run that computed frames
    flushes its output's file system once before it reports them, so that a power loss after a
    finished run loses none; a run with nothing to do flushes nothing."""
    import pipeline.cache
    from tests.test_damaged_cache import _pipe

    flushed: list[str] = []
    monkeypatch.setattr(pipeline.cache, "sync_filesystem", lambda path: flushed.append(str(path)))
    pipe = _pipe(tmp_path)
    pipe.run("calibrate")
    assert flushed == [str(tmp_path / "cache" / "fake" / "calibrate.zarr")]
    pipe.run("calibrate")
    assert len(flushed) == 1
