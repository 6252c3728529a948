"""One writer per stage output: a lock file created exclusively, with stale-lock recovery.

The lock file holds JSON {pid, host, started}. On a local filesystem creation is atomic
(O_CREAT | O_EXCL). A lock whose process is gone (same host, pid not alive) is stale and is taken
over. On remote (fsspec) caches creation is exists-then-write, which is best effort; a lock left by
a dead process on another host is reported with its age and can be removed with
``pipeline unlock``.
"""

from __future__ import annotations

import json
import os
import socket
import time
from contextlib import contextmanager
from typing import Iterator

import fsspec

from pipeline.errors import LockError


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _read(fs: fsspec.AbstractFileSystem, path: str) -> dict | None:
    try:
        with fs.open(path, "r") as fh:
            return json.load(fh)
    except (FileNotFoundError, json.JSONDecodeError, OSError):
        return None


def _is_stale(info: dict | None) -> bool:
    if info is None:
        return True  # unreadable or half-written lock: its writer died while creating it
    return info.get("host") == socket.gethostname() and not _pid_alive(int(info.get("pid", -1)))


def _try_create(fs: fsspec.AbstractFileSystem, path: str, payload: str) -> bool:
    if fs.protocol in ("file", ("file", "local")) or "file" in fs.protocol:
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            return False
        with os.fdopen(fd, "w") as fh:
            fh.write(payload)
        return True
    if fs.exists(path):
        return False
    with fs.open(path, "w") as fh:
        fh.write(payload)
    return True


@contextmanager
def stage_lock(url: str, what: str, wait_s: float = 0.0) -> Iterator[None]:
    """Hold the lock file ``url`` while the body runs.

    ``what`` names the output in messages. With ``wait_s`` > 0, wait up to that long for another
    run to finish; otherwise raise LockError at once naming the holder.
    """
    fs, path = fsspec.core.url_to_fs(url)
    fs.makedirs(fs._parent(path), exist_ok=True)
    payload = json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "started": time.time()})
    deadline = time.monotonic() + wait_s
    while not _try_create(fs, path, payload):
        info = _read(fs, path)
        if _is_stale(info):
            fs.rm(path)  # the holder is gone: recover
            continue
        if time.monotonic() >= deadline:
            age = time.time() - float(info.get("started", time.time()))
            raise LockError(
                f"{what} is being written by another run (pid {info.get('pid')} on {info.get('host')}, "
                f"for {age:.0f} s); wait for it to finish (or pass --wait SECONDS). If that run is dead "
                f"on another machine, remove the lock with `pipeline unlock`.")
        time.sleep(0.5)
    try:
        yield
    finally:
        info = _read(fs, path)
        if info is not None and info.get("pid") == os.getpid() and info.get("host") == socket.gethostname():
            fs.rm(path)
