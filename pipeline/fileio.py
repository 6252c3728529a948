"""Atomic writes to local files: a reader never sees a half-written file, a crash leaves none."""

from __future__ import annotations

import errno
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


_UMASK = os.umask(0o022)
os.umask(_UMASK)  # read once: os.umask can only be read by setting it
FILE_MODE = 0o666 & ~_UMASK
"""Mode of the files written here: what open() would give (mkstemp alone gives 0600, which other
users, e.g. a training container, cannot read)."""


@contextmanager
def atomic_path(path: str | os.PathLike, durable: bool = False) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s folder; when the body succeeds it is renamed onto
    ``path`` (os.replace), otherwise removed. The folder is created if needed; the file gets the
    mode a plain open() would give (FILE_MODE). With ``durable`` the file's data reach the disk
    before the rename and the rename before the return (:func:`fsync`), so that a power loss too
    leaves the old file or the new one, not an empty one (a rename alone may reach the disk before
    the data on ext4 and XFS)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.fchmod(fd, FILE_MODE)
    os.close(fd)
    try:
        yield Path(tmp)
        if durable:
            fsync(tmp)
        os.replace(tmp, path)
        if durable:
            fsync(path.parent)
    finally:
        Path(tmp).unlink(missing_ok=True)


UNSUPPORTED_FSYNC = frozenset({errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP, errno.ENOSYS, errno.EBADF})
"""fsync errors that mean the file system cannot flush that file or folder (some FUSE mounts of
object stores, network file systems), not that its data are lost: ignored."""


def fsync(path: str | os.PathLike) -> None:
    """Flush the file or folder ``path`` to the disk (a folder: the names in it, e.g. a rename).
    Where the file system does not support it (:data:`UNSUPPORTED_FSYNC`), or a folder cannot be
    opened for reading, nothing is flushed; any other error is an OSError naming ``path``."""
    folder = os.path.isdir(path)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) * folder)
    except PermissionError:
        if folder:  # a folder we may write in but not list
            return
        raise
    try:
        os.fsync(fd)
    except OSError as exc:
        if exc.errno not in UNSUPPORTED_FSYNC:
            raise OSError(exc.errno, exc.strerror, str(path)) from None
    finally:
        os.close(fd)


def write_atomic(path: str | os.PathLike, data: bytes | str) -> Path:
    """Write ``data`` (str as UTF-8) to ``path`` atomically; returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data.encode("utf-8") if isinstance(data, str) else data)
    return Path(path)


def sync_filesystem(path: str | os.PathLike) -> None:
    """Flush every file written on the file system holding ``path`` (Linux ``syncfs``; elsewhere
    ``os.sync``, all file systems). Not ``os.sync`` on Linux: it would also wait for every other
    mount, a hung network mount included."""
    import ctypes

    try:
        syncfs = ctypes.CDLL(None, use_errno=True).syncfs
    except (OSError, AttributeError):  # no such call here
        os.sync()
        return
    fd = os.open(path, os.O_RDONLY)
    try:
        if syncfs(fd) != 0:
            code = ctypes.get_errno()
            if code not in UNSUPPORTED_FSYNC:
                raise OSError(code, os.strerror(code), str(path))
    finally:
        os.close(fd)
