"""Zarr I/O beneath FrameStore (pipeline.cache): zarr groups and arrays opened cheaply (each array
by its own ``zarr.json``; a local store's once per process while that file holds the same bytes;
s3fs set to read each object in one request), and a local store's chunk files read and written
directly, encoded as zarr's own codecs encode them (zarr's path costs milliseconds a frame in
IO-thread hand-offs)."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import os
import uuid
from collections.abc import Awaitable, Iterable
from dataclasses import dataclass
from typing import Any

import fsspec
import numcodecs
import numpy as np
import zarr
import zarr.api.asynchronous as zarr_async
from zarr.codecs import BytesCodec, VLenUTF8Codec, ZstdCodec
from zarr.core.chunk_key_encodings import DefaultChunkKeyEncoding
from zarr.core.group import get_node
from zarr.storage import LocalStore
from zarr.storage._common import make_store_path

from pipeline.cachefs import join, local_path
from pipeline.errors import cache_error

ZARR_FORMAT = 3
"""The zarr format outputs are written in (every output this project has made) and opened as:
named, so that zarr does not also look for format 2 metadata at each open (.zgroup, .zarray,
.zattrs: a quarter of the requests of a run on an S3 cache, 2026-12-07)."""

DECODE_ERRORS = (RuntimeError, ValueError, MemoryError)
"""What zarr 3.1.6 raises reading a damaged chunk: RuntimeError from zstd for truncated, empty or
random bytes, or a checksum mismatch; without the checksum also ValueError (UnicodeDecodeError)
for bytes that decompress to the wrong size or text, and MemoryError from the string codec for a
wrong length prefix."""


def chunk_key(arr: zarr.Array, index: int) -> str:
    """Key, under the array's path, of frame ``index``'s chunk (one chunk per frame)."""
    return arr.metadata.encode_chunk_key((index,) + (0,) * (arr.ndim - 1))


def chunk_path(arr: zarr.Array, index: int) -> str:
    """The file of frame ``index``'s chunk of ``arr``, an array of a local store."""
    return os.path.join(str(arr.store.root), arr.path, chunk_key(arr, index))


def put_chunk(path: str, data: bytes) -> None:
    """Write one chunk file as zarr's local store does: to a temporary file beside it, renamed over
    it, so that a reader sees the old chunk or the new one, never part of one."""
    tmp = f"{path}.{uuid.uuid4().hex}.partial"
    try:
        try:
            fh = open(tmp, "wb")
        except FileNotFoundError:  # the chunk's folder is not there yet (a mkdir per chunk cost 0.25 ms)
            os.makedirs(os.path.dirname(path), exist_ok=True)
            fh = open(tmp, "wb")
        with fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


async def write_targets(url: str, names: list[str], run: str = "") -> dict[str, Any]:
    """The async arrays ``names`` of the store at ``url``, set to write every chunk (a fill-valued
    one too, pipeline.cache.EVERY_CHUNK: a missing chunk is then damage), each opened by its own
    zarr.json (not the group's too: a request more per frame on an object store); kept (:func:`keep`)
    where they are local or ``run`` is given, else opened for each call (another process may
    re-create the output between two frames)."""
    root = local_path(url)
    stamps = [_metadata_bytes(root, name) for name in names] if root is not None else \
        [("run", run)] * len(names) if run else [None]
    if None not in stamps:
        hits = [kept(url, name, "write", stamp) for name, stamp in zip(names, stamps)]
        if all(found for found, _ in hits):
            return {name: arr for name, (_, arr) in zip(names, hits)}
    arrays = await gather_all(member_async(url, name, "r+") for name in names)  # not the group's zarr.json
    if None in arrays:  # the group's own error when it is gone, else the array's, as group[name] raises
        await zarr_async.open_group(url, mode="r+", zarr_format=ZARR_FORMAT, **zarr_options(url))
        raise KeyError(names[arrays.index(None)])
    targets = {name: arr.with_config({"write_empty_chunks": True}) for name, arr in zip(names, arrays)}
    if None not in stamps:
        for name, stamp in zip(names, stamps):
            keep(url, name, "write", stamp, targets[name])
    return targets


async def gather_all(awaitables: Iterable[Awaitable[Any]]) -> list[Any]:
    """Await every one to its end, then raise the first failure: a failed write must not leave the
    others pending when the event loop closes (asyncio would print them after the error line)."""
    results = await asyncio.gather(*awaitables, return_exceptions=True)
    for result in results:
        if isinstance(result, BaseException):
            raise result
    return results


@dataclass(frozen=True)
class _ChunkCodec:
    """How the chunk files of a FrameStore array (one frame per chunk) are encoded, as zarr's
    codecs do it: bytes (``stored``: the dtype with its byte order) or vlen-utf8 strings
    (``stored`` None), then zstd."""

    dtype: Any
    shape: tuple[int, ...]
    stored: np.dtype | None
    zstd: numcodecs.Zstd

    def encode(self, row: Any) -> bytes:
        """One frame's chunk file for ``row`` (a value of the per-frame shape)."""
        if self.stored is None:
            return self.zstd.encode(_VLEN_UTF8.encode(np.asarray(row, dtype=object).reshape(-1)))
        return self.zstd.encode(np.ascontiguousarray(row, dtype=self.stored).tobytes())

    def decode(self, data: bytes) -> np.ndarray | None:
        """The frame of chunk file bytes ``data``; None when they do not decode to one frame."""
        raw = self.zstd.decode(data)
        size = int(np.prod(self.shape, dtype=np.int64))
        if self.stored is None:
            items = _VLEN_UTF8.decode(raw)
            return items.reshape(self.shape).astype(self.dtype) if items.size == size else None
        if len(raw) != size * self.stored.itemsize:
            return None
        return np.frombuffer(raw, self.stored).reshape(self.shape)


_VLEN_UTF8 = numcodecs.VLenUTF8()
"""zarr 3's vlen-utf8 codec encodes with numcodecs' VLenUTF8 (zarr.codecs.vlen_utf8)."""


def direct_layout(arr: zarr.Array) -> _ChunkCodec | None:
    """The codec of the chunk files of an array of a local store laid out as ``FrameStore.create``
    makes it (one chunk per frame, zarr's default chunk keys, zarr format 3, bytes of a fixed-size
    dtype or vlen-utf8 strings, then zstd); None for any other."""
    meta = arr.metadata
    codecs = getattr(meta, "codecs", None)  # None: zarr format 2
    if codecs is None or not isinstance(arr.store, LocalStore) or \
            meta.chunk_grid.chunk_shape != (1, *arr.shape[1:]) or \
            meta.chunk_key_encoding != DefaultChunkKeyEncoding(separator="/"):
        return None
    kinds = [type(c) for c in codecs]
    zstd = numcodecs.Zstd(level=codecs[-1].level, checksum=codecs[-1].checksum) if kinds[-1:] == [ZstdCodec] else None
    if kinds == [BytesCodec, ZstdCodec] and arr.dtype.kind in "biuf":
        stored = np.dtype(arr.dtype).newbyteorder(">" if getattr(codecs[0].endian, "value", "") == "big" else "<")
        return _ChunkCodec(arr.dtype, tuple(arr.shape[1:]), stored, zstd)
    if kinds == [VLenUTF8Codec, ZstdCodec] and arr.dtype.kind in "TU":
        return _ChunkCodec(arr.dtype, tuple(arr.shape[1:]), None, zstd)
    return None


def frames_from_chunk_files(arr: zarr.Array, frames: np.ndarray | None = None,
                             missing_is_fill: bool = True) -> np.ndarray | None:
    """Frames ``frames`` (indices; default all) of array ``arr`` of a FrameStore, read straight from
    their chunk files (zarr's default chunk keys; a missing one is the fill value, as zarr reads
    it, unless not ``missing_is_fill``): zarr spends about 0.3 ms per chunk, 6 s on the status of
    20,000 frames, against 0.4 s here. None, for zarr to read them (and name a damaged chunk), when
    the cache is not local, the array is not laid out as ``FrameStore.create`` makes it (a
    ``direct_layout``), a chunk file does not decode to one frame, or one
    is missing and not ``missing_is_fill``."""
    layout = direct_layout(arr)
    if layout is None:
        return None
    frames = np.arange(arr.shape[0]) if frames is None else np.asarray(frames, np.int64).reshape(-1)
    if frames.size and not (0 <= frames.min() and frames.max() < arr.shape[0]):
        return None
    out = np.full((len(frames), *arr.shape[1:]), arr.metadata.fill_value, arr.dtype)
    try:
        for row, index in enumerate(frames):
            try:
                with open(chunk_path(arr, int(index)), "rb") as fh:
                    value = layout.decode(fh.read())
            except FileNotFoundError:
                if missing_is_fill:
                    continue
                return None
            if value is None:
                return None
            out[row] = value
    except (OSError, *DECODE_ERRORS):  # unreadable, not zstd, checksum mismatch, a huge claimed size
        return None
    return out


_KEPT: dict[tuple[str, str, str], tuple[Any, Any]] = {}
"""Arrays a process keeps open, by (store URL, array name, use: 'chunk files' (:func:`opened_array`),
'read' (pipeline.cache.read_frame) or 'write' (:func:`write_targets`)), each with the stamp under
which it holds: a local array's ``zarr.json`` bytes (zarr replaces that file by a rename, inode
numbers are reused and a file time may not change within a clock tick, so the metadata itself),
or on a remote store the token of the run of a stage's frames that opened it (RunEnv.stage_run:
that run created its output before its frames, or reads finished ones, and holds the locks that
keep others from re-creating them). Opening the group and its arrays for every frame's read or
write cost about 2 ms of zarr's IO-thread hand-offs per array locally, and on an object store a
request per ``zarr.json`` per frame (until 2026-12-07). None for an array that is not there or
that zarr could not open. Also the snapshots of status a run's process has removed ('removed',
pipeline.snapshots.STATUS_SNAPSHOT)."""
_KEPT_MAX = 2048


def kept(url: str, name: str, use: str, stamp: Any) -> tuple[bool, Any]:
    """(True, the array or None) where array ``name`` of the store at ``url`` is kept for ``use``
    under ``stamp`` (:data:`_KEPT`), else (False, None)."""
    hit = _KEPT.get((url, name, use))
    return (True, hit[1]) if hit is not None and hit[0] == stamp else (False, None)


def keep(url: str, name: str, use: str, stamp: Any, node: Any) -> None:
    """Keep ``node``, array ``name`` of the store at ``url`` opened for ``use``, under ``stamp``."""
    if len(_KEPT) >= _KEPT_MAX:
        _KEPT.clear()
    _KEPT[(url, name, use)] = (stamp, node)


def _metadata_bytes(root: str, name: str) -> bytes | None:
    """The bytes of array ``name``'s zarr.json under local folder ``root``; None when unreadable."""
    try:
        with open(os.path.join(root, name, "zarr.json"), "rb") as fh:
            return fh.read()
    except OSError:
        return None


def opened_array(url: str, name: str) -> tuple[bool, zarr.Array | None]:
    """(whether it exists, the array or None) for array ``name`` of the local store at ``url``,
    opened once per process while its ``zarr.json`` holds the same bytes; (False, None) when that
    file cannot be read or the store is not local, (True, None) when zarr cannot open the array
    (zarr's own path then names the problem)."""
    root = local_path(url)
    meta = None if root is None else _metadata_bytes(root, name)
    if meta is None:
        return False, None
    found, arr = kept(url, name, "chunk files", meta)
    if found:
        return True, arr
    try:
        arr: zarr.Array | None = zarr.open_array(join(url, name), mode="r", zarr_format=ZARR_FORMAT)
        if json.dumps(arr.metadata.to_dict(), sort_keys=True, default=str) != \
                json.dumps(json.loads(meta), sort_keys=True, default=str):
            arr = None  # the file was replaced between the two reads: zarr's path this time
    except Exception:  # noqa: BLE001 - damaged or racing metadata: left to zarr's path, which names it
        arr = None
    keep(url, name, "chunk files", meta, arr)
    return True, arr


def open_group(url: str, mode: str) -> zarr.Group:
    """The zarr group at ``url`` opened in ``mode``; FileNotFoundError as zarr raises it, a
    CacheError for any other OSError."""
    try:
        return zarr.open_group(url, mode=mode, zarr_format=ZARR_FORMAT, **zarr_options(url))
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise cache_error(exc, f"opening {url}") from None


async def member_async(url: str, name: str, mode: str) -> Any:
    """Member ``name`` of the group at ``url`` (an AsyncArray) as ``group.getitem(name)`` reads it,
    with the same errors, without reading the group's own ``zarr.json``; None when it is not there."""
    node_path = await make_store_path(url, mode=mode, **zarr_options(url)) / name
    try:
        return await get_node(node_path.store, node_path.path, ZARR_FORMAT)
    except FileNotFoundError:  # zarr's NodeNotFoundError, or a local store's missing folder
        return None


def zarr_options(url: str) -> dict[str, Any]:
    """Keyword arguments for zarr's functions opening the store at ``url``: on s3fs one GET per
    read. s3fs (2026.9.0) asks an object's size (a HEAD) before reading it whole, to read a large
    one in concurrent parts (``max_concurrency`` above 1, its default 10): a request more for each
    zarr.json and chunk read, a frame's chunks being far smaller than the 50 MiB s3fs splits at
    (a missing chunk: a HEAD and a listing instead of one GET)."""
    return {"storage_options": {"max_concurrency": 1}} if _sizes_before_reads(url) else {}


@functools.lru_cache(maxsize=1024)
def _sizes_before_reads(url: str) -> bool:
    """Whether ``url`` is on s3fs reading each whole object after a HEAD (:func:`zarr_options`)."""
    if local_path(url) is not None:
        return False
    fs = fsspec.core.url_to_fs(url)[0]
    protocol = fs.protocol if isinstance(fs.protocol, (tuple, list)) else (fs.protocol,)
    return "s3" in protocol and getattr(fs, "max_concurrency", 1) > 1
