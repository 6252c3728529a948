"""Where the cache's files are: cache paths and URLs joined, and what kind of file system holds
them (the local one, or one on which a file appears whole or not at all)."""

from __future__ import annotations

import functools
import shlex

import fsspec


def command_options(dataset: str, cache_root: str) -> str:
    """'--dataset D --cache C', quoted for the shell: what a command named in a message takes, so
    that pasted in any folder it acts on this dataset's cache."""
    return f"--dataset {shlex.quote(dataset)} --cache {shlex.quote(cache_root)}"


def join(root: str, *parts: str) -> str:
    """Join URL or path parts with '/'."""
    return "/".join([root.rstrip("/"), *[p.strip("/") for p in parts]])


def is_local(fs: fsspec.AbstractFileSystem) -> bool:
    """Whether ``fs`` is the local file system."""
    protocol = fs.protocol if isinstance(fs.protocol, (tuple, list)) else (fs.protocol,)
    return "file" in protocol or "local" in protocol


WHOLE_OBJECT_PROTOCOLS = frozenset({"s3", "s3a", "gs", "gcs", "abfs", "abfss", "az", "adl", "memory"})
"""Filesystems on which a file appears whole or not at all (object stores: an object is written by
one request, or a multipart upload completed at its end)."""


def writes_whole_objects(fs: fsspec.AbstractFileSystem) -> bool:
    """Whether a file ``put`` on ``fs`` appears whole or not at all (:data:`WHOLE_OBJECT_PROTOCOLS`).
    Other filesystems (sftp, smb, ftp, hdfs, webdav) write a file as its bytes arrive, so an upload
    cut off midway leaves a damaged file under its name."""
    protocol = fs.protocol if isinstance(fs.protocol, (tuple, list)) else (fs.protocol,)
    return any(p in WHOLE_OBJECT_PROTOCOLS for p in protocol)


@functools.lru_cache(maxsize=1024)
def local_path(url: str) -> str | None:
    """The local folder of cache URL ``url``; None when it is not on the local file system."""
    fs, path = fsspec.core.url_to_fs(url)
    return path if is_local(fs) else None
