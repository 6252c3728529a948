"""One writer per stage output: a lock file per stage, with stale-lock recovery.

The lock file holds JSON {pid, host, started} naming the holder (for messages). On a local
filesystem the lock itself is an exclusive ``flock`` on that file: the kernel drops it when the
holder exits or is killed, so a lock left by a SIGKILLed run is taken over by the next run, and
two runs recovering the same stale lock cannot both win. The holder deletes the file before it
lets go; a contender that locked a file deleted meanwhile notices (inode changed) and retries.
On remote (fsspec) caches creation is exists-then-write, which is best effort; a lock left by a
dead process on another host is reported with its age and can be removed with ``pipeline unlock``.

Readers: a stage run holds a shared flock on its inputs' ``<stage>.lock.readers`` files (kept,
never deleted), and a run that recreates or replaces an output (forced, or stale) takes that
output's exclusively, so an output is not rewritten while another run reads it. Local caches only.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import shlex
import socket
import time
from contextlib import contextmanager
from typing import Iterator

import fsspec

from pipeline.cachefs import command_options, is_local
from pipeline.errors import LockError, cache_error

_RETRY = -1


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


def _try_flock(path: str, payload: str) -> int | None:
    """Local lock: the held file descriptor, None if another process holds it, _RETRY if the file
    was replaced while we locked it."""
    fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    except BaseException:
        os.close(fd)
        raise
    try:
        current = os.stat(path).st_ino
    except FileNotFoundError:
        current = None
    if current != os.fstat(fd).st_ino:  # the previous holder deleted it between our open and flock
        os.close(fd)
        return _RETRY
    try:
        os.ftruncate(fd, 0)
        os.write(fd, payload.encode())
    except BaseException:
        os.close(fd)
        raise
    return fd


def _try_create_remote(fs: fsspec.AbstractFileSystem, path: str, payload: str) -> bool:
    if fs.exists(path):
        return False
    with fs.open(path, "w") as fh:
        fh.write(payload)
    return True


def _refuse(what: str, info: dict | None, url: str) -> LockError:
    info = info or {}
    age = time.time() - float(info.get("started", time.time()))
    return LockError(
        f"{what} is being written by another run (pid {info.get('pid', '?')} on {info.get('host', '?')}, "
        f"for {age:.0f} s); wait for it to finish (or pass --wait SECONDS). If that run is dead "
        f"on another machine, remove the lock with {unlock_command(url)}.")


def unlock_command(url: str) -> str:
    """The `pipeline unlock` command that removes the lock file ``url``
    (CACHE/DATASET/locks/NAME.lock), quoted for the shell."""
    root, dataset, _, name = url.rstrip("/").rsplit("/", 3)
    return f"`pipeline unlock {shlex.quote(name.removesuffix('.lock'))} {command_options(dataset, root)}`"


@contextmanager
def stage_lock(url: str, what: str, wait_s: float = 0.0) -> Iterator[None]:
    """Hold the lock file ``url`` while the body runs.

    ``what`` names the output in messages. With ``wait_s`` > 0, wait up to that long for another
    run to finish; otherwise raise LockError at once naming the holder. A cache that cannot be
    written (read-only, disk full) raises CacheError.
    """
    fs, path = fsspec.core.url_to_fs(url)
    payload = json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "started": time.time()})
    deadline = time.monotonic() + wait_s
    try:
        fs.makedirs(fs._parent(path), exist_ok=True)
        if is_local(fs):
            fd = _acquire_local(path, payload, what, deadline, url)
        else:
            fd = None
            _acquire_remote(fs, path, payload, what, deadline, url)
    except OSError as exc:
        raise cache_error(exc, f"taking the lock {url}") from None
    try:
        yield
    finally:
        if fd is not None:
            try:
                os.unlink(path)  # while still locked: a waiter that opened it will see the inode change
            except FileNotFoundError:
                pass  # removed by `pipeline unlock`
            finally:
                os.close(fd)
        else:
            info = _read(fs, path)
            if info is not None and info.get("pid") == os.getpid() and info.get("host") == socket.gethostname():
                fs.rm(path)


@contextmanager
def reading(urls: list[str], what: str, wait_s: float = 0.0) -> Iterator[None]:
    """While the body runs, no other run may rewrite the stage outputs whose lock files are ``urls``
    (a shared lock on each one's ``.readers`` file; see :func:`rewriting`). Local caches only: on
    remote ones this does nothing. LockError (naming ``what``) when one is being rewritten and
    ``wait_s`` runs out."""
    with _readers_locks(urls, fcntl.LOCK_SH, wait_s,
                        f"{what}: an input of it is being rewritten by another run; wait for it to finish (or "
                        f"pass --wait SECONDS)"):
        yield


@contextmanager
def rewriting(url: str, what: str, wait_s: float = 0.0) -> Iterator[None]:
    """While the body runs, the output whose lock file is ``url`` is recreated or replaced: no
    other run may be reading it (an exclusive lock on its ``.readers`` file). Taken inside
    stage_lock, only by a run that rewrites the output (appending frames to it needs no more)."""
    with _readers_locks([url], fcntl.LOCK_EX, wait_s,
                        f"{what} is being read by another run (checked, or read by a stage downstream of it); "
                        f"wait for it to finish (or pass --wait SECONDS)"):
        yield


READ_ONLY_ERRNOS = (errno.EACCES, errno.EPERM, errno.EROFS)
"""Errors of creating a file where this user may not write."""


@contextmanager
def _readers_locks(urls: list[str], mode: int, wait_s: float, refusal: str) -> Iterator[None]:
    deadline = time.monotonic() + wait_s
    held = []
    try:
        for url in urls:
            fs, path = fsspec.core.url_to_fs(url)
            if not is_local(fs):
                continue
            try:
                fd = _flock_readers(path, mode, deadline, refusal)
            except OSError as exc:
                raise cache_error(exc, f"taking the lock {url}.readers") from None
            if fd is not None:
                held.append(fd)
        yield
    finally:
        for fd in held:
            os.close(fd)


def _flock_readers(lock_path: str, mode: int, deadline: float, refusal: str) -> int | None:
    """Open ``lock_path``.readers (kept, never deleted) and flock it with ``mode`` (LOCK_SH or LOCK_EX),
    waiting until ``deadline``; the open descriptor (closing it releases the lock). A reader (LOCK_SH)
    of a cache it may not write (a copy made read-only, an archive) flocks the file read-only, or,
    where it does not exist, takes no lock: None (a run that can rewrite the output creates it)."""
    path = lock_path + ".readers"
    try:
        os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
        fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o644)
    except OSError as exc:
        if mode != fcntl.LOCK_SH or exc.errno not in READ_ONLY_ERRNOS:
            raise
        try:
            fd = os.open(path, os.O_RDONLY)
        except FileNotFoundError:
            return None
    while True:
        try:
            fcntl.flock(fd, mode | fcntl.LOCK_NB)
            return fd
        except BlockingIOError:
            if time.monotonic() >= deadline:
                os.close(fd)
                raise LockError(refusal) from None
            time.sleep(0.2)
        except BaseException:
            os.close(fd)
            raise


def _acquire_local(path: str, payload: str, what: str, deadline: float, url: str) -> int:
    while True:
        fd = _try_flock(path, payload)
        if fd is not None and fd != _RETRY:
            return fd
        if fd is None and time.monotonic() >= deadline:
            raise _refuse(what, _read(fsspec.filesystem("file"), path), url)
        if fd is None:
            time.sleep(0.2)


def _acquire_remote(fs: fsspec.AbstractFileSystem, path: str, payload: str, what: str, deadline: float,
                    url: str) -> None:
    while not _try_create_remote(fs, path, payload):
        info = _read(fs, path)
        if _is_stale(info):
            try:
                fs.rm(path)  # the holder is gone: recover
            except FileNotFoundError:
                pass  # another run recovered it first
            continue
        if time.monotonic() >= deadline:
            raise _refuse(what, info, url)
        time.sleep(0.5)


def held(url: str) -> bool:
    """Whether the lock file ``url`` names a holder: a live process of this machine, or any process
    of another machine. Reads the file only; taking the lock to probe it would make a writer's own
    attempt at that moment fail."""
    fs, path = fsspec.core.url_to_fs(url)
    info = _read(fs, path)
    return fs.exists(path) if info is None else not _is_stale(info)  # None: being written, or unreadable


def remove_lock(url: str) -> bool:
    """Remove the lock file ``url`` left by a dead run (``pipeline unlock``); False if there is none.
    LockError when the lock belongs to a process still running on this machine."""
    fs, path = fsspec.core.url_to_fs(url)
    if not fs.exists(path):
        return False
    info = _read(fs, path)
    if info is not None and info.get("host") == socket.gethostname() and _pid_alive(int(info.get("pid", -1))):
        raise LockError(f"{url} is held by pid {info.get('pid')}, still running on this machine: stop that run "
                        f"(or wait for it) instead of removing its lock")
    fs.rm(path)
    return True
