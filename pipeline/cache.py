"""The on-disk cache: one zarr group per frame stage, one folder per dataset stage.

Layout under the cache root (a local folder or any fsspec URL)::

    <root>/<dataset>/<stage>.zarr/       frame stage: declared arrays, one chunk per frame,
                                         plus ``status`` (uint8 per frame) and ``reason`` (str)
    <root>/<dataset>/<stage>/            dataset stage: files, and ``_stage.json`` written last
    <root>/<dataset>/locks/<stage>.lock  one writer per stage output

Frame status codes: PENDING 0, DONE 1, FAILED 2, EXCLUDED 3. A frame's arrays are written first,
its status last, so a process killed at any instant leaves either a complete frame or a frame
that will be redone.
"""

from __future__ import annotations

import asyncio
import errno
import hashlib
import json
import time
from collections.abc import Awaitable, Iterable
from dataclasses import dataclass
from typing import Any

import fsspec
import numpy as np
import zarr
import zarr.api.asynchronous as zarr_async
from zarr.core.sync import sync

from pipeline.errors import CacheError
from pipeline.stage import ArraySpec

PENDING, DONE, FAILED, EXCLUDED = 0, 1, 2, 3
STATUS_NAMES = {PENDING: "pending", DONE: "done", FAILED: "failed", EXCLUDED: "excluded"}


def join(root: str, *parts: str) -> str:
    """Join URL or path parts with '/'."""
    return "/".join([root.rstrip("/"), *[p.strip("/") for p in parts]])


def cache_error(exc: OSError, what: str) -> CacheError:
    """A CacheError explaining an OSError in words (read-only cache, disk full, ...)."""
    if exc.errno == errno.ENOSPC:
        return CacheError(f"{what}: the disk holding the cache is full ({exc})")
    if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
        return CacheError(f"{what}: the cache is not writable ({exc}); choose another with --cache")
    return CacheError(f"{what}: {exc}")


@dataclass(frozen=True)
class FrameStore:
    """The zarr output of one frame stage of one dataset."""

    url: str

    def exists(self) -> bool:
        """True when the group has been created."""
        try:
            return "fingerprint" in self._group("r").attrs
        except (FileNotFoundError, KeyError, zarr.errors.GroupNotFoundError, ValueError):
            return False

    def _group(self, mode: str) -> zarr.Group:
        return _open_group(self.url, mode)

    def fingerprint(self) -> str | None:
        """Fingerprint the output was created with (None if absent)."""
        return self._group("r").attrs.get("fingerprint") if self.exists() else None

    def create(self, fingerprint: str, frame_ids: list[str], specs: tuple[ArraySpec, ...],
               shapes: dict[str, tuple[int, ...]], attrs: dict[str, Any]) -> None:
        """(Re)create every output array up front; any previous content is erased."""
        n = len(frame_ids)
        try:
            g = zarr.open_group(self.url, mode="w")
            for spec in specs:
                shape = shapes[spec.name]
                g.create_array(spec.name, shape=(n, *shape), chunks=(1, *shape), dtype=spec.dtype,
                               fill_value=spec.fill, attributes={"units": spec.units})
                if spec.ragged:
                    g.create_array(f"{spec.name}_count", shape=(n,), chunks=(1,), dtype="int32",
                                   fill_value=0, attributes={"units": "rows"})
            g.create_array("status", shape=(n,), chunks=(1,), dtype="uint8", fill_value=PENDING,
                           attributes={"codes": STATUS_NAMES})
            g.create_array("reason", shape=(n,), chunks=(1,), dtype=str, fill_value="")
            g.attrs.update({**attrs, "frame_ids": list(frame_ids), "created": time.time()})
            # The fingerprint goes last: a group without it counts as absent.
            g.attrs["fingerprint"] = fingerprint
        except OSError as exc:
            raise cache_error(exc, f"creating {self.url}") from None

    def invalidate(self) -> None:
        """Make the stored fingerprint match nothing: the next run recomputes the output."""
        try:
            self._group("r+").attrs["fingerprint"] = "stale"
        except OSError as exc:
            raise cache_error(exc, f"invalidating {self.url}") from None

    def frame_ids(self) -> list[str]:
        """Frame ids, in frame-index order."""
        return list(self._group("r").attrs["frame_ids"])

    def status(self) -> np.ndarray:
        """(F,) uint8 status codes."""
        return np.asarray(self._group("r")["status"][:])

    def done_digest(self) -> str:
        """A short digest of which frames are done ('absent' without an output): what a dataset
        stage reading this output records, to notice frames finished (or redone) after it ran."""
        return done_digest(self.status()) if self.exists() else "absent"

    def reasons(self) -> dict[int, str]:
        """Failure reason per failed frame index."""
        status = self.status()
        arr = self._group("r")["reason"]
        return {int(i): str(arr[int(i)]) for i in np.flatnonzero(status == FAILED)}

    def write_frame(self, index: int, arrays: dict[str, np.ndarray], specs: tuple[ArraySpec, ...]) -> None:
        """Write one frame's arrays, then mark it done (the marker last).

        All arrays of the frame are written concurrently in one round trip to zarr's IO loop (one
        call per array costs about 1 ms of thread hand-offs each, which dominated small frames).
        """
        values: list[tuple[str, Any]] = []
        for spec in specs:
            value = np.asarray(arrays[spec.name])
            if spec.ragged:
                values.append((f"{spec.name}_count", np.int32(value.shape[0])))
            values.append((spec.name, value))
        try:
            sync(_write_frame_async(self.url, index, specs, values))
        except OSError as exc:
            raise cache_error(exc, f"writing frame {index} of {self.url}") from None

    def mark(self, index: int, code: int, reason: str = "") -> None:
        """Record a frame as failed or excluded, with the reason."""
        g = self._group("r+")
        try:
            g["reason"][index] = reason[:2000]
            g["status"][index] = code
        except OSError as exc:
            raise cache_error(exc, f"recording frame {index} of {self.url}") from None

    def read(self, name: str, index: int) -> np.ndarray:
        """One frame of an array; ragged arrays are trimmed to the frame's row count."""
        g = self._group("r")
        value = np.asarray(g[name][index])
        if f"{name}_count" in g:
            value = value[: int(g[f"{name}_count"][index])]
        return value

    def array(self, name: str) -> zarr.Array:
        """The whole zarr array (lazy; index it)."""
        return self._group("r")[name]

    def attrs(self) -> dict[str, Any]:
        """Group attributes."""
        return dict(self._group("r").attrs)


def done_digest(status: np.ndarray) -> str:
    """Short digest of the indices of the frames whose status (F,) is DONE."""
    done = np.flatnonzero(np.asarray(status) == DONE).astype(np.int64)
    return hashlib.sha256(done.tobytes()).hexdigest()[:16]


@dataclass(frozen=True)
class DirStore:
    """The folder output of one dataset stage."""

    url: str

    @property
    def fs(self) -> fsspec.AbstractFileSystem:
        return fsspec.core.url_to_fs(self.url)[0]

    @property
    def path(self) -> str:
        """Path inside the filesystem (a local path for a local cache)."""
        return fsspec.core.url_to_fs(self.url)[1]

    def file(self, name: str) -> str:
        """Path of a file of the output (in the filesystem's own terms)."""
        return join(self.path, name)

    def meta(self) -> dict[str, Any] | None:
        """Content of ``_stage.json`` (None if the stage never finished)."""
        try:
            with self.fs.open(self.file("_stage.json"), "r") as fh:
                return json.load(fh)
        except (FileNotFoundError, json.JSONDecodeError):
            return None
        except OSError as exc:  # e.g. the cache path is a file
            raise cache_error(exc, f"reading {self.file('_stage.json')}") from None

    def fingerprint(self) -> str | None:
        meta = self.meta()
        return meta.get("fingerprint") if meta else None

    def ensure(self) -> None:
        """Create the folder."""
        try:
            self.fs.makedirs(self.path, exist_ok=True)
        except OSError as exc:
            raise cache_error(exc, f"creating {self.url}") from None

    def write_text(self, name: str, text: str) -> None:
        """Write a file atomically on local filesystems (temporary name, then rename)."""
        self.write_bytes(name, text.encode())

    def write_bytes(self, name: str, data: bytes) -> None:
        fs, target = self.fs, self.file(name)
        tmp = target + ".tmp"
        try:
            fs.makedirs(fs._parent(target), exist_ok=True)
            with fs.open(tmp, "wb") as fh:
                fh.write(data)
            fs.mv(tmp, target)
        except OSError as exc:
            raise cache_error(exc, f"writing {target}") from None

    def finish(self, fingerprint: str, summary: dict[str, Any], frames: dict[str, str] | None = None) -> None:
        """Mark the stage complete (written last). The folder's path is kept so that
        :meth:`summary` can move the summary's paths along with a moved or copied cache; ``frames``
        (per-frame upstream stage -> :meth:`FrameStore.done_digest`) says which frames it read."""
        self.write_text("_stage.json", json.dumps({"fingerprint": fingerprint, "finished": time.time(),
                                                   "path": self.path, "frames": frames or {}, "summary": summary},
                                                  indent=2, default=str))

    def summary(self) -> dict[str, Any]:
        """The summary the stage finished with ({} if it never did); string values that were paths
        inside the folder are given at its current path (the cache may have been moved since)."""
        meta = self.meta() or {}
        summary, old = dict(meta.get("summary", {})), meta.get("path")
        if old and old != self.path:
            for key, value in summary.items():
                if isinstance(value, str) and (value == old or value.startswith(old.rstrip("/") + "/")):
                    summary[key] = self.path + value[len(old):]
        return summary

    def clear(self) -> None:
        """Remove the folder and everything in it."""
        try:
            if self.fs.exists(self.path):
                self.fs.rm(self.path, recursive=True)
        except OSError as exc:
            raise cache_error(exc, f"removing {self.url}") from None

    def invalidate(self) -> None:
        """Forget completion (the files stay; the stage decides what to reuse)."""
        try:
            if self.fs.exists(self.file("_stage.json")):
                self.fs.rm(self.file("_stage.json"))
        except OSError as exc:
            raise cache_error(exc, f"invalidating {self.url}") from None


async def _write_frame_async(url: str, index: int, specs: tuple[ArraySpec, ...],
                             values: list[tuple[str, Any]]) -> None:
    """Write ``values`` into row ``index`` of the group's arrays concurrently, then the status."""
    group = await zarr_async.open_group(url, mode="r+")
    names = [name for name, _ in values] + ["reason", "status"]
    targets = dict(zip(names, await _gather_all(group.getitem(name) for name in names)))
    ragged = {spec.name: spec.fill for spec in specs if spec.ragged}

    def row(name: str, value: Any) -> np.ndarray:
        target = targets[name]
        if name not in ragged:
            return np.asarray(value).astype(target.dtype, copy=False) if target.dtype != object else value
        padded = np.full(target.shape[1:], ragged[name], dtype=target.dtype)
        padded[: value.shape[0]] = value
        return padded

    await _gather_all([*(targets[name].setitem(index, row(name, v)) for name, v in values),
                       targets["reason"].setitem(index, "")])
    await targets["status"].setitem(index, DONE)


async def _gather_all(awaitables: Iterable[Awaitable[Any]]) -> list[Any]:
    """Await every one to its end, then raise the first failure: a failed write must not leave the
    others pending when the event loop closes (asyncio would print them after the error line)."""
    results = await asyncio.gather(*awaitables, return_exceptions=True)
    for result in results:
        if isinstance(result, BaseException):
            raise result
    return results


def _open_group(url: str, mode: str) -> zarr.Group:
    try:
        return zarr.open_group(url, mode=mode)
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise cache_error(exc, f"opening {url}") from None


def frame_store(root: str, dataset: str, stage: str) -> FrameStore:
    """The FrameStore of ``stage`` of ``dataset`` under cache ``root``."""
    return FrameStore(join(root, dataset, f"{stage}.zarr"))


def dir_store(root: str, dataset: str, stage: str) -> DirStore:
    """The DirStore of ``stage`` of ``dataset`` under cache ``root``."""
    return DirStore(join(root, dataset, stage))


class RaggedRows:
    """Flat row view of a ragged per-frame array: row k is ``array[frame[k], row[k]]``.

    Lets training iterate over the sampled points of many frames without loading them all: it
    offers ``len``, ``oindex[rows]`` and ``chunks`` (rows per frame chunk) like a zarr array.
    """

    def __init__(self, array: zarr.Array, counts: np.ndarray, frames: np.ndarray) -> None:
        counts = np.asarray(counts, dtype=np.int64)
        frames = np.asarray(frames, dtype=np.int64)
        self.array = array
        self.frame = np.repeat(frames, counts[frames])
        self.row = np.concatenate([np.arange(counts[f]) for f in frames]) if len(frames) else np.zeros(0, np.int64)
        self.shape = (len(self.frame), *array.shape[2:])
        self.chunks = (max(1, int(array.shape[1])),)

    def __len__(self) -> int:
        return len(self.frame)

    @property
    def oindex(self) -> "RaggedRows":
        return self

    def __getitem__(self, rows) -> np.ndarray:
        rows = np.asarray(rows, dtype=np.int64)
        frames = self.frame[rows]
        uniq, inverse = np.unique(frames, return_inverse=True)
        block = np.asarray(self.array.oindex[uniq])  # (u, capacity, ...)
        return block[inverse, self.row[rows]]
