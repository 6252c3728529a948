"""The on-disk cache: one zarr group per frame stage, one folder per dataset stage. The zarr I/O
beneath the frame stages' outputs (FrameStore) is pipeline.zarr_io's.

Layout under the cache root (a local folder or any fsspec URL)::

    <root>/<dataset>/<stage>.zarr/       frame stage: declared arrays, one chunk per frame,
                                         plus ``status`` (uint8 per frame), ``reason`` (str)
                                         and ``frame_ids`` (str, one chunk)
    <root>/<dataset>/<stage>/            dataset stage: files, and ``_stage.json`` written last
    <root>/<dataset>/locks/<stage>.lock  one writer per stage output

Frame status codes: PENDING 0, DONE 1, FAILED 2, EXCLUDED 3. A frame's arrays are written first,
its status last, so a process killed at any instant leaves either a complete frame or a frame
that will be redone.

A damaged chunk (one that cannot be decoded, fails its checksum, or is missing from a done frame)
raises ChunkError naming the array, the frame and the file: it fails only the frame reading it.
A frame whose ``status`` chunk is deleted counts as pending (the fill value) and is recomputed.
A group ``zarr.json`` that cannot be read, or is gone while the arrays are there, raises
MetadataError: the output is not taken for absent (and recomputed, its frames lost) unless forced.
So does a dataset stage's ``_stage.json`` that is there but not a JSON object (written whole by a
rename, such a file is damaged); a missing one means the stage has not finished.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
import re
import shlex
import shutil
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import fsspec
import numpy as np
import zarr
from zarr.codecs import ZstdCodec
from zarr.core.sync import sync

from pipeline.cachefs import is_local, join, local_path, writes_whole_objects
from pipeline.errors import CacheError, ChunkError, MetadataError, cache_error, one_line
from pipeline.fileio import sync_filesystem
from pipeline.stage import ArraySpec
from pipeline.zarr_io import (DECODE_ERRORS, ZARR_FORMAT, chunk_key, chunk_path, direct_layout, frames_from_chunk_files,
                              gather_all, member_async, open_group, opened_array, put_chunk, write_targets,
                              zarr_options)

PENDING, DONE, FAILED, EXCLUDED = 0, 1, 2, 3
STATUS_NAMES = {PENDING: "pending", DONE: "done", FAILED: "failed", EXCLUDED: "excluded"}

FRAME_IDS = "frame_ids"
"""The array of an output's frame ids (strings, one chunk); outputs created before 2026-12-04 hold
them in the group's attributes."""

EVERY_CHUNK = "every_chunk_written"
"""Group attribute: a finished frame has every chunk written, even one equal to the fill value
(which zarr skips by default), so a missing chunk of a done frame is damage, not a fill value.
Outputs created before 2026-12-03 lack it: there a missing chunk still reads as the fill value."""

COMPRESSOR = ZstdCodec(level=0, checksum=True)
"""zarr's default compressor plus zstd's content checksum: a flipped bit in a chunk is then an
error when read instead of a silently wrong value (outputs created before 2026-12-03 have none)."""


@dataclass(frozen=True)
class FrameStore:
    """The zarr output of one frame stage of one dataset."""

    url: str

    def exists(self) -> bool:
        """True when the group has been created (its fingerprint is written last). MetadataError
        when the group's ``zarr.json`` cannot be read, or is gone while its arrays are there: the
        output would otherwise count as absent and be recomputed, its finished frames lost."""
        return self._created_attrs() is not None

    def _created_attrs(self) -> dict[str, Any] | None:
        """The group's attributes when it has been created (they hold its fingerprint), else None;
        MetadataError as :meth:`exists` says."""
        try:
            attrs = dict(self._group("r").attrs)
        except (FileNotFoundError, KeyError, zarr.errors.GroupNotFoundError):
            if self._has_status_array():
                raise self._damaged_group("is missing") from None
            return None
        except (ValueError, TypeError) as exc:  # json.JSONDecodeError, UnicodeDecodeError, a JSON list
            raise self._damaged_group(f"cannot be read ({one_line(exc)})") from None
        return attrs if "fingerprint" in attrs else None

    @property
    def stage(self) -> str:
        """The stage's name, from the folder's (``<stage>.zarr``)."""
        return self.url.rstrip("/").rsplit("/", 1)[-1].removesuffix(".zarr")

    def _has_status_array(self) -> bool:
        """Whether the status array's ``zarr.json`` is there (readable or not): one read of it, as
        zarr reads it (on an object store an existence check asked twice for a missing one)."""
        try:
            return sync(member_async(self.url, "status", "r")) is not None
        except (ValueError, TypeError):  # there, but damaged
            return True
        except OSError:
            return False

    def _damaged_group(self, problem: str) -> MetadataError:
        """MetadataError for the group's ``zarr.json``, with how many frames its status array
        says are finished (what recomputing would lose) when that array can be read."""
        try:
            status = np.asarray(self._array("status")[:])
            finished = f" (its status array records {int((status == DONE).sum())} of {len(status)} frames finished)"
        except Exception:  # noqa: BLE001 - only words: the status array may be damaged too
            finished = ""
        return MetadataError(
            f"{join(self.url, 'zarr.json')}: the metadata of stage output {self.stage} {problem}, so the settings "
            f"and frame ids its arrays were made with are unknown{finished}. Restore the file (from a backup or "
            f"another copy of the cache), or recompute the stage from scratch with `pipeline run {self.stage} "
            f"--force`")

    def _group(self, mode: str) -> zarr.Group:
        return open_group(self.url, mode)

    def fingerprint(self) -> str | None:
        """Fingerprint the output was created with (None if absent); the group's metadata read once."""
        attrs = self._created_attrs()
        return None if attrs is None else attrs["fingerprint"]

    def create(self, fingerprint: str, frame_ids: list[str], specs: tuple[ArraySpec, ...],
               shapes: dict[str, tuple[int, ...]], attrs: dict[str, Any]) -> None:
        """(Re)create every output array up front; any previous content is erased."""
        n = len(frame_ids)
        try:
            g = zarr.open_group(self.url, mode="w", zarr_format=ZARR_FORMAT, **zarr_options(self.url))
            for spec in specs:
                shape = shapes[spec.name]
                g.create_array(spec.name, shape=(n, *shape), chunks=(1, *shape), dtype=spec.dtype,
                               fill_value=spec.fill, compressors=COMPRESSOR, attributes={"units": spec.units})
                if spec.ragged:
                    g.create_array(f"{spec.name}_count", shape=(n,), chunks=(1,), dtype="int32",
                                   fill_value=0, compressors=COMPRESSOR, attributes={"units": "rows"})
            g.create_array("status", shape=(n,), chunks=(1,), dtype="uint8", fill_value=PENDING,
                           compressors=COMPRESSOR, attributes={"codes": STATUS_NAMES})
            g.create_array("reason", shape=(n,), chunks=(1,), dtype=str, fill_value="", compressors=COMPRESSOR)
            # an array of one chunk, not the group's attributes: every open of the group (several
            # per frame read or written until 2026-12-07) parses its zarr.json, 0.8 MB of ids at 50,000 frames
            ids = g.create_array(FRAME_IDS, shape=(n,), chunks=(max(n, 1),), dtype=str, fill_value="",
                                 compressors=COMPRESSOR)
            ids[:] = np.asarray(list(frame_ids), dtype=str)
            g.attrs.update({**attrs, "created": time.time(), EVERY_CHUNK: True})
            # The fingerprint goes last: a group without it counts as absent.
            g.attrs["fingerprint"] = fingerprint
        except OSError as exc:
            raise cache_error(exc, f"creating {self.url}") from None

    def invalidate(self) -> None:
        """Make the stored fingerprint match nothing: the next run recomputes the output."""
        self.set_fingerprint("stale")

    def set_fingerprint(self, fingerprint: str, **attrs: Any) -> None:
        """Store another fingerprint (and ``attrs``) for the output as it is (stale, or relocated)."""
        try:
            group = self._group("r+")
            group.attrs.update(attrs)
            group.attrs["fingerprint"] = fingerprint
        except OSError as exc:
            raise cache_error(exc, f"updating the fingerprint of {self.url}") from None

    def frame_ids(self) -> list[str]:
        """Frame ids, in frame-index order. MetadataError naming the array when it cannot be read."""
        try:
            arr = sync(member_async(self.url, FRAME_IDS, "r"))  # not the group's zarr.json too
            ids = None if arr is None else [str(i) for i in np.asarray(zarr.Array(arr)[:])]
        except (*DECODE_ERRORS, TypeError) as exc:  # a damaged chunk, or zarr.json (json.JSONDecodeError)
            _settle_io()
            problem = f"cannot be read ({one_line(exc)})"
        else:
            if ids is None:  # outputs created before 2026-12-04 hold them in the group's attributes
                attrs = self._group("r").attrs
                if "frame_ids" in attrs:
                    return list(attrs["frame_ids"])
                problem = "is missing"
            elif all(ids):
                return ids
            else:
                problem = "has empty ids (its chunk is missing)"  # zarr reads a missing chunk as the fill, ''
        raise MetadataError(f"{join(self.url, FRAME_IDS)}: the frame ids of stage output {self.stage} {problem}; "
                            f"recompute the stage: delete {self.url} or run it with --force")

    def status(self) -> np.ndarray:
        """(F,) uint8 status codes; ChunkError naming the lowest damaged chunk when one is."""
        arr = self._array("status")
        status = frames_from_chunk_files(arr)
        if status is not None:
            return status
        try:
            return np.asarray(arr[:])
        except DECODE_ERRORS as exc:
            _settle_io()
            raise self.damaged("status", np.arange(arr.shape[0]), exc) from None

    def done_digest(self) -> str:
        """A short digest of which frames are done ('absent' without an output): what a dataset
        stage reading this output records, to notice frames finished (or redone) after it ran."""
        return done_digest(self.status()) if self.exists() else "absent"

    def reasons(self, frames: np.ndarray | None = None, limit: int | None = None,
                status: np.ndarray | None = None) -> dict[int, str]:
        """Failure reason per failed frame index (a damaged reason chunk gives a reason saying so):
        of the frames ``frames`` only when given, of the first ``limit`` failed ones when given
        (each costs a read of its own). ``status``: the output's status when the caller has it."""
        failed = (self.status() if status is None else status) == FAILED
        if frames is not None:
            failed &= np.isin(np.arange(len(failed)), frames)
        arr = self._array("reason")
        out = {}
        for i in np.flatnonzero(failed)[:limit]:
            try:
                out[int(i)] = str(self._decode(arr, int(i)))
            except ChunkError as exc:  # only words: a retry rewrites them
                out[int(i)] = (f"(the frame failed; its reason cannot be read: chunk {exc.chunk} {exc.problem}; "
                               f"--retry-failed runs the frame again)")
        return out

    def write_frame(self, index: int, arrays: dict[str, np.ndarray], specs: tuple[ArraySpec, ...]) -> None:
        """Write one frame's arrays, then mark it done (the marker last).

        A local output's chunk files are written directly, as zarr's local store writes them (each
        encoded by the array's own codecs, to a temporary file renamed over the chunk): zarr's
        writes cost about 4 ms a frame in IO-thread hand-offs. Otherwise (a remote cache, another
        layout) all arrays of the frame are written concurrently in one round trip to zarr's IO loop.
        """
        values: list[tuple[str, Any]] = []
        for spec in specs:
            value = np.asarray(arrays[spec.name])
            if spec.ragged:
                values.append((f"{spec.name}_count", np.int32(value.shape[0])))
            values.append((spec.name, value))
        fills = {spec.name: spec.fill for spec in specs if spec.ragged}
        try:
            if not self._write_chunk_files([index], [*values, ("reason", "")], fills, DONE):
                sync(_write_frame_async(self.url, index, fills, values))
        except OSError as exc:
            raise cache_error(exc, f"writing frame {index} of {self.url}") from None

    def _write_chunk_files(self, indices: Sequence[int] | np.ndarray, values: list[tuple[str, Any]], fills: dict[str, Any],
                           code: int) -> bool:
        """Write ``values`` (the same for each frame) straight to the chunk files of frames
        ``indices`` of a local output, each frame's status ``code`` after its other chunks; False,
        having written nothing, when that cannot be done: not local, an array not laid out as
        :meth:`create` makes it, or a row of another shape (zarr's path raises the error)."""
        indices = np.asarray(indices, np.int64).reshape(-1)
        chunks = []
        for name, value in (*values, ("status", np.uint8(code))):
            arr = opened_array(self.url, name)[1]
            layout = None if arr is None else direct_layout(arr)
            if layout is None or (indices.size and not (indices.min() >= 0 and indices.max() < arr.shape[0])):
                return False
            row = _frame_row(value, arr.dtype, arr.shape[1:], name in fills, fills.get(name))
            if np.shape(row) != layout.shape:
                return False
            chunks.append((arr, layout.encode(row)))
        for index in indices:
            for arr, data in chunks:  # the status last: the frame is done only once the rest is written
                put_chunk(chunk_path(arr, int(index)), data)
        return True

    def flush(self) -> None:
        """Make every chunk written so far reach the disk (a local store: fileio.sync_filesystem;
        an object store's writes are durable when they return). The runner calls it when a run of
        the stage ends: its frames are not flushed one by one (an fsync per chunk cost 0.6 ms)."""
        path = local_path(self.url)
        if path is None or not os.path.isdir(path):
            return
        try:
            sync_filesystem(path)
        except OSError as exc:
            raise cache_error(exc, f"flushing {self.url} to the disk") from None

    def mark(self, index: int, code: int, reason: str = "") -> None:
        """Record a frame as failed or excluded, with the reason (overwriting a damaged chunk)."""
        self.mark_many(np.array([index]), code, reason)

    def mark_many(self, indices: np.ndarray, code: int, reason: str = "") -> None:
        """Record frames ``indices`` (F',) as failed or excluded, with one reason: a local output's
        chunk files written directly, as :meth:`write_frame` does, else by zarr, one write per array
        (a single frame written alone: zarr's orthogonal write reads the chunks it replaces, and
        :meth:`mark` must overwrite a damaged one)."""
        indices = np.unique(np.asarray(indices, np.int64))
        if not indices.size:
            return
        # a reason naming a file whose name is no UTF-8 holds lone surrogates, which no string array stores
        reason = reason[:2000].encode("utf-8", "backslashreplace").decode("utf-8")
        try:
            if self._write_chunk_files(indices, [("reason", reason)], {}, code):
                return
            reasons, status = self._array("reason", "r+"), self._array("status", "r+")
            if len(indices) == 1:
                reasons[int(indices[0])] = reason
                status[int(indices[0])] = code
                return
            reasons.oindex[indices] = np.full(len(indices), reason, dtype=reasons.dtype)
            status.oindex[indices] = np.full(len(indices), code, np.uint8)
        except OSError as exc:
            what = f"frame {indices[0]}" if len(indices) == 1 else f"{len(indices)} frames"
            raise cache_error(exc, f"recording {what} of {self.url}") from None

    def read(self, name: str, index: int) -> np.ndarray:
        """One frame of an array; ragged arrays are trimmed to the frame's row count.

        ChunkError when a chunk it reads cannot be decoded, or is missing while the frame is done.
        """
        direct = self._read_chunk_files(name, index)
        if direct is not None:
            return direct
        value = self._checked(self._array(name), index)
        counts = self._array(f"{name}_count", missing_ok=True)  # ragged arrays have one
        if counts is not None:
            value = value[: int(self._checked(counts, index))]
        return value

    def _read_chunk_files(self, name: str, index: int) -> np.ndarray | None:
        """:meth:`read` from the frame's chunk files (a local cache, the arrays opened once per
        process); None, for zarr's path, when that cannot be done or a chunk is missing or damaged
        (zarr's path then raises the ChunkError)."""
        arr = opened_array(self.url, name)[1]
        if arr is None:
            return None
        value = frames_from_chunk_files(arr, [index], missing_is_fill=False)
        if value is None:
            return None
        ragged, counts = opened_array(self.url, f"{name}_count")
        if not ragged:
            return value[0, ...]
        rows = None if counts is None else frames_from_chunk_files(counts, [index], missing_is_fill=False)
        return None if rows is None else value[0, :int(rows[0])]

    def array(self, name: str) -> "CheckedArray":
        """The whole array (lazy; index it like a zarr array); a read that meets a damaged chunk
        raises ChunkError naming it."""
        return CheckedArray(self, self._array(name))

    def damaged(self, name: str, frames: np.ndarray, exc: BaseException) -> BaseException:
        """After a read of frame indices ``frames`` (F',) of array ``name`` raised ``exc``: the
        ChunkError of the lowest of them whose chunk cannot be decoded, or ``exc`` itself when each
        decodes alone (it was then no damaged chunk). Reads the frames concurrently."""
        frames = np.unique(np.asarray(frames, dtype=np.int64))
        arr = self._array(name)

        async def results() -> list[Any]:
            return await asyncio.gather(*(arr.async_array.getitem(int(i)) for i in frames), return_exceptions=True)

        for index, result in zip(frames, sync(results())):
            if isinstance(result, DECODE_ERRORS):
                return self._chunk_error(arr, int(index), f"cannot be decoded ({one_line(result)})")
        return exc

    def _array_folders(self) -> list[str]:
        """The names of the output's array folders (every folder of the group is an array's), from
        the file system: zarr's own listing stops on an array whose metadata cannot be read, and
        leaves out one whose metadata is gone."""
        fs, path = fsspec.core.url_to_fs(self.url)
        try:
            entries = fs.ls(path, detail=True)
        except OSError as exc:
            raise cache_error(exc, f"listing {self.url}") from None
        return sorted(e["name"].rstrip("/").rsplit("/", 1)[-1] for e in entries if e.get("type") == "directory")

    def check_metadata(self) -> list[str]:
        """The output's array names; MetadataError naming the first array whose ``zarr.json`` is
        gone or cannot be read (every frame of it would be unreadable): a run that resumes the
        output, ``status`` and ``verify`` ask first. Each ``zarr.json`` is read once (no existence
        check before: its read says it is gone)."""
        folders = self._array_folders()
        for name in folders:
            if self._array(name, missing_ok=True) is None:
                raise MetadataError(f"{join(self.url, name, 'zarr.json')}: the metadata of array {name} is missing; "
                                    f"recompute the stage: delete {self.url} or run it with --force")
        return folders

    def _damaged_array(self, name: str, exc: BaseException) -> MetadataError:
        meta = join(self.url, name, "zarr.json")
        return MetadataError(f"{meta}: the metadata of array {name} cannot be read ({one_line(exc)}); recompute "
                             f"the stage: delete {self.url} or run it with --force")

    def _array(self, name: str, mode: str = "r", missing_ok: bool = False) -> Any:
        """Array ``name`` as ``group[name]`` gives it, its ``zarr.json`` read alone: not the group's
        too (a request of its own on an object store, made several times per frame until
        2026-12-07; the local path reads none either). Not there: None when ``missing_ok``, else
        KeyError, or the group's own error when the group is gone too. MetadataError naming the
        file when it cannot be read (every frame of the array is then unreadable)."""
        try:
            node = sync(member_async(self.url, name, mode))
        except (ValueError, TypeError) as exc:  # json.JSONDecodeError for a truncated or garbled zarr.json
            raise self._damaged_array(name, exc) from None
        if node is None:
            if missing_ok:
                return None
            self._group("r")  # GroupNotFoundError when the group is gone too, as opening it first raised
            raise KeyError(name)
        return zarr.Array(node) if isinstance(node, zarr.AsyncArray) else zarr.Group(node)

    def _decode(self, arr: zarr.Array, index: int) -> np.ndarray:
        """Frame ``index`` of ``arr``; ChunkError when its chunk cannot be decoded."""
        try:
            return np.asarray(arr[index])
        except DECODE_ERRORS as exc:
            raise self._chunk_error(arr, index, f"cannot be decoded ({one_line(exc)})") from None

    def _checked(self, arr: zarr.Array, index: int) -> np.ndarray:
        """:meth:`_decode`, and ChunkError when the value is all fill because the chunk is missing
        although the frame is done and the group has every chunk written (:data:`EVERY_CHUNK`;
        zarr writes no chunk for a frame of no elements, which is never missing). The group's
        metadata and the file system are asked only for a value that is all fill."""
        value = self._decode(arr, index)
        if value.size and _all_fill(value, arr.fill_value) and self._group("r").attrs.get(EVERY_CHUNK) \
                and not sync(arr.store.exists(f"{arr.path}/{chunk_key(arr, index)}")) \
                and int(self._decode(self._array("status"), index)) == DONE:
            raise self._chunk_error(arr, index, "is missing although the frame is done (zarr would read the fill "
                                                   "value in its place)")
        return value

    def _chunk_error(self, arr: zarr.Array, index: int, problem: str) -> ChunkError:
        """ChunkError for frame ``index`` of ``arr``, with the command that
        recomputes the frame."""
        chunk = join(self.url, arr.path, chunk_key(arr, index))
        try:
            ids = self.frame_ids()
        except Exception:  # noqa: BLE001 - only words: the chunk's own error must not be lost
            ids = []
        frame = str(ids[index]) if 0 <= index < len(ids) else None
        folder = self.url.rstrip("/").rsplit("/", 1)[-1]
        root, dataset, _ = self.url.rstrip("/").rsplit("/", 2)  # <cache root>/<dataset>/<stage>.zarr
        remedy = (f"recompute the frame with `pipeline run {self.stage} --dataset {shlex.quote(dataset)} --cache "
                  f"{shlex.quote(root)} --force --frames {shlex.quote(frame) if frame else index}` (the frames made "
                  f"from it are recomputed too)")
        return ChunkError(f"{folder}/{arr.basename}", index, frame, chunk, problem, remedy)

    def verify(self, progress: Callable[[int, int], None] | None = None,
               block_bytes: int = 64 << 20) -> tuple[np.ndarray, dict[int, ChunkError]]:
        """Read every chunk the output holds for its frames: (status (F,) uint8, {frame index: the
        first ChunkError met in that frame}). A done frame's chunks of every array are decoded
        (checksums included) and, where the group has every chunk written, must exist; a failed
        frame's reason chunk must decode; every status chunk must (a frame whose status chunk is
        damaged reads as pending in the status returned). Arrays are read in blocks of about
        ``block_bytes``; a block that fails is read frame by frame to name the damaged frames.
        ``progress(n, total)`` after each block of n frames of one array (total: frames times
        arrays). MetadataError when the group's or an array's metadata cannot be read."""
        if not self.exists():
            raise CacheError(f"{self.url}: no output to verify")
        names = sorted(set(self.check_metadata()) - {"status", "reason", FRAME_IDS})
        every_chunk = bool(self._group("r").attrs.get(EVERY_CHUNK))
        total = self._array("status").shape[0] * (2 + len(names))
        progress = (lambda n: None) if progress is None else (lambda n, _p=progress: _p(n, total))
        errors: dict[int, ChunkError] = {}
        status = self._scan(every_chunk, "status", None, errors, progress, block_bytes)
        status = np.where(np.isin(np.arange(len(status)), list(errors)), PENDING, status).astype(np.uint8)
        self._scan(every_chunk, "reason", status == FAILED, errors, progress, block_bytes, "failed")
        done = status == DONE
        for name in names:
            self._scan(every_chunk, name, done, errors, progress, block_bytes, "is done")
        return status, dict(sorted(errors.items()))

    def _scan(self, every_chunk: bool, name: str, frames: np.ndarray | None, errors: dict[int, ChunkError],
              progress: Callable[[int], None], block_bytes: int, state: str = "") -> np.ndarray | None:
        """Decode array ``name`` in blocks, recording in ``errors`` a ChunkError for each frame of
        mask ``frames`` (every frame: None) whose chunk cannot be decoded or, where the group has every
        chunk written (``every_chunk``), is missing (the frames being in ``state``); the values when ``frames`` is None
        (the status array)."""
        arr = self._array(name)
        n = arr.shape[0]
        wanted = np.ones(n, bool) if frames is None else frames
        per_frame_size = int(np.prod(arr.shape[1:], dtype=np.int64))
        per_frame = max(1, per_frame_size * arr.dtype.itemsize)
        step = max(1, block_bytes // per_frame)
        values = np.empty(n, arr.dtype) if frames is None else None
        for start in range(0, n, step):
            stop = min(n, start + step)
            if not wanted[start:stop].any():
                progress(stop - start)
                continue
            try:
                block = np.asarray(arr[start:stop])
            except DECODE_ERRORS:  # find the damaged frames of the block
                _settle_io()
                block = None
                for i in range(start, stop):
                    try:
                        value = self._decode(arr, i)
                        if values is not None:
                            values[i] = value
                    except ChunkError as exc:
                        if wanted[i]:
                            errors.setdefault(i, exc)
            if block is not None and values is not None:
                values[start:stop] = block
            progress(stop - start)
        if every_chunk and frames is not None and per_frame_size:  # zarr writes no chunk holding nothing
            present = set(sync(_keys(arr.store, f"{arr.path}/c/")))
            for i in np.flatnonzero(wanted):
                if i not in errors and f"{arr.path}/{chunk_key(arr, int(i))}" not in present:
                    errors[int(i)] = self._chunk_error(arr, int(i), f"is missing although the frame {state}")
        return values

    def attrs(self) -> dict[str, Any]:
        """Group attributes."""
        return dict(self._group("r").attrs)


class CheckedArray:
    """A FrameStore's zarr array: index it (``[sel]``, ``oindex[sel]``) like the zarr array, whose
    other attributes it passes on; a read that meets a damaged chunk raises the ChunkError of the
    lowest damaged frame it read instead of the codec's error."""

    def __init__(self, store: FrameStore, array: zarr.Array) -> None:
        self._store = store
        self._array = array

    def __getitem__(self, selection: Any) -> Any:
        if selection is Ellipsis or (isinstance(selection, slice) and selection == slice(None)):
            # the whole array, from its chunk files
            value = frames_from_chunk_files(self._array)
            if value is not None:
                return value
        return self._read(lambda: self._array[selection], selection)

    @property
    def oindex(self) -> "_CheckedOIndex":
        return _CheckedOIndex(self)

    def __len__(self) -> int:
        return len(self._array)

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> np.ndarray:
        """The whole array read (np.asarray of it), as a zarr array allows."""
        return np.asarray(self[...], dtype=dtype)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):  # e.g. while unpickling, before __init__ set them
            raise AttributeError(name)
        return getattr(self._array, name)

    def _read(self, read: Callable[[], Any], selection: Any) -> Any:
        """``read()`` of ``selection``; on a decoding error, the ChunkError of the lowest damaged
        frame the selection reads (its first item selects the frames)."""
        try:
            return read()
        except DECODE_ERRORS as exc:
            _settle_io()
            first = selection[0] if isinstance(selection, tuple) else selection
            try:
                frames = np.arange(self._array.shape[0])[first]
            except (IndexError, TypeError, ValueError):  # not a frame selection: no chunk to blame
                raise exc from None
            raise self._store.damaged(self._array.basename, frames, exc) from None


class _CheckedOIndex:
    """``CheckedArray.oindex``: orthogonal selection with the same error translation."""

    def __init__(self, checked: CheckedArray) -> None:
        self._checked = checked

    def __getitem__(self, selection: Any) -> Any:
        frames = _frame_indices(selection, self._checked._array.shape[0])
        if frames is not None:  # some whole frames, from their chunk files
            value = frames_from_chunk_files(self._checked._array, frames)
            if value is not None:
                return value
        return self._checked._read(lambda: self._checked._array.oindex[selection], selection)


def _frame_indices(selection: Any, n: int) -> np.ndarray | None:
    """The frame indices an orthogonal selection ``selection`` of an array of ``n`` frames picks
    when it picks whole frames by a 1-D list or array of indices or a boolean mask, in order;
    None for any other selection (slices, negative indices, a selection along other axes)."""
    if isinstance(selection, tuple) or not isinstance(selection, (list, np.ndarray)):
        return None
    picked = np.asarray(selection)
    if picked.ndim != 1:
        return None
    if picked.dtype == bool:
        return np.flatnonzero(picked) if len(picked) == n else None
    if picked.dtype.kind not in "iu" or (picked.size and picked.min() < 0):
        return None
    return picked.astype(np.int64)


async def _others_finished(timeout_s: float) -> None:
    others = asyncio.all_tasks() - {asyncio.current_task()}
    if others:
        await asyncio.wait(others, timeout=timeout_s)


def _settle_io(timeout_s: float = 60.0) -> None:
    """After a zarr read of several chunks raised: wait (at most ``timeout_s``) for the reads of its
    other chunks, still running on zarr's IO loop (asyncio.gather does not cancel them at the first
    error). Left running, the process's exit destroys them with a warning and a traceback each,
    hundreds of lines after the one-line error."""
    sync(_others_finished(timeout_s))


async def _keys(store: Any, prefix: str) -> list[str]:
    return [key async for key in store.list_prefix(prefix)]


def _all_fill(value: np.ndarray, fill: Any) -> bool:
    """True when every element of ``value`` equals the fill value (NaN equals NaN); most values
    are told apart by their first element."""
    value = np.asarray(value).reshape(-1)
    nan = isinstance(fill, (float, np.floating)) and bool(np.isnan(fill))

    def same(v: np.ndarray) -> np.ndarray:
        return np.isnan(v) if nan else v == fill

    return value.size == 0 or (bool(same(value[:1]).all()) and bool(same(value).all()))


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
        """Content of ``_stage.json`` (None if the stage never finished, or its last run did not).
        MetadataError when the file is there but is not a JSON object: :meth:`finish` writes it
        whole (a temporary file renamed into place), so a kill cannot leave part of it, and such a
        file is damaged; taken for absent, the output would pass as unfinished and be recomputed
        without a word (until 2026-12-06).

        Read in one request (``cat_file``), as are the run token and the files' manifest: opening
        the file takes its size and ETag from the filesystem's listing cache (s3fs, gcsfs) where a
        listing of the folder (a download's ``find``) put them, and in a process that outlives runs
        (a worker of a dask cluster) a record rewritten since by another run could not be read
        (s3fs: ``[Errno 16] The remote file ... no longer exists``) until 2026-12-07."""
        try:
            meta = json.loads(self.fs.cat_file(self.file("_stage.json")))
        except FileNotFoundError:
            return None
        except ValueError as exc:  # json.JSONDecodeError, UnicodeDecodeError
            raise self._damaged_meta(f"cannot be read ({one_line(exc)})") from None
        except OSError as exc:  # e.g. the cache path is a file
            raise cache_error(exc, f"reading {self.file('_stage.json')}") from None
        if not isinstance(meta, dict):
            raise self._damaged_meta(f"holds a JSON {type(meta).__name__}, not an object")
        return meta

    def _damaged_meta(self, problem: str) -> MetadataError:
        """MetadataError for a damaged ``_stage.json`` (:meth:`meta`), with the two ways out."""
        parts = self.url.rstrip("/").rsplit("/", 2)  # <cache root>/<dataset>/<stage>
        stage = parts[-1]
        where = f" --dataset {shlex.quote(parts[1])} --cache {shlex.quote(parts[0])}" if len(parts) == 3 else ""
        return MetadataError(
            f"{join(self.url, '_stage.json')}: the record of stage output {stage} {problem}, so whether it finished, "
            f"and with which settings, is unknown (the file is written whole, so it is damaged). Restore the file "
            f"(from a backup or another copy of the cache), or make the output again with `pipeline run {stage}"
            f"{where} --force`" + (" (or delete the file: the next run resumes from the checkpoints there, which it "
                                   "checks, instead of training again)" if self._holds_checkpoints() else ""))

    def _holds_checkpoints(self) -> bool:
        """Whether the folder holds a training checkpoint (``<net>/last.safetensors``) a run resumes from."""
        try:
            return bool(self.fs.glob(self.path.rstrip("/") + "/*/last.safetensors"))
        except OSError:
            return False

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

    def finish(self, fingerprint: str, summary: dict[str, Any], frames: dict[str, str] | None = None,
               record: dict[str, Any] | None = None) -> None:
        """Mark the stage complete (written last). The folder's path is kept so that
        :meth:`summary` can move the summary's paths along with a moved or copied cache; ``frames``
        (per-frame upstream stage -> :meth:`FrameStore.done_digest`) says which frames it read;
        ``record``: what it was made with (pipeline.runner.Pipeline.record), kept beside. On a
        local file system every file written reaches the disk first (fileio.sync_filesystem), so
        that after a power loss too a folder marked complete holds whole files."""
        if self.is_local:
            self.ensure()
            try:
                sync_filesystem(self.path)
            except OSError as exc:
                raise cache_error(exc, f"flushing {self.url} to the disk") from None
        self.write_text("_stage.json", json.dumps({**(record or {}), "fingerprint": fingerprint, "finished": time.time(),
                                                   "path": self.path, "frames": frames or {}, "summary": summary},
                                                  indent=2, default=str))

    def summary(self) -> dict[str, Any]:
        """The summary the stage finished with ({} if it never did); paths inside the folder, as
        string values or within one (the message), are given at its current path (the cache may
        have been moved since)."""
        meta = self.meta() or {}
        summary, old = dict(meta.get("summary", {})), meta.get("path")
        if old and old != self.path:
            # the folder itself or a path under it: not a sibling whose name merely starts the same
            inside = re.compile(re.escape(old.rstrip("/")) + r"(?=$|[/\s,;:)\]'\"`])")
            for key, value in summary.items():
                if isinstance(value, str):
                    summary[key] = inside.sub(lambda _: self.path.rstrip("/"), value)
        return summary

    def clear(self) -> None:
        """Remove the folder and everything in it."""
        try:
            if self.fs.exists(self.path):
                self.fs.rm(self.path, recursive=True)
        except OSError as exc:
            raise cache_error(exc, f"removing {self.url}") from None

    def remove_temporaries(self) -> list[str]:
        """Remove the ``*.tmp`` files a killed run left (atomic writes that never reached their
        rename, e.g. a half-written checkpoint); call only while holding the output's exclusive
        lock. Returns the paths removed."""
        try:
            found = self.fs.glob(join(self.path, "**", "*.tmp")) if self.fs.exists(self.path) else []
            for name in found:
                self.fs.rm(name)
        except OSError as exc:
            raise cache_error(exc, f"removing temporary files of {self.url}") from None
        return found

    def set_fingerprint(self, fingerprint: str, **_: Any) -> None:
        """Store another fingerprint for the finished output as it is (relocated data); its other
        fields are kept."""
        meta = self.meta()
        if meta is not None:
            self.write_text("_stage.json", json.dumps({**meta, "fingerprint": fingerprint}, indent=2, default=str))

    @property
    def is_local(self) -> bool:
        """Whether the folder is on the local file system (else an fsspec URL: s3://, gcs://, memory://)."""
        return is_local(self.fs)

    def staging(self, staging_dir: str) -> DirStore:
        """The local folder a stage writing with local file APIs writes into when this folder is
        remote (:meth:`upload` then copies it here): under ``staging_dir`` (run.staging_dir), one per
        remote folder, kept between runs so that a killed run resumes from it on this machine."""
        return DirStore(str(_mirror_root(self.url, staging_dir) / "staging"))

    def work_folder(self, staging_dir: str) -> DirStore:
        """Where a writer with local file APIs writes this folder's files: the folder itself on the
        local file system, else its :meth:`staging` folder (then uploaded)."""
        return self if self.is_local else self.staging(staging_dir)

    def holds_run_of(self, other: DirStore) -> bool:
        """Whether this (staging) folder holds the files of the last run begun in ``other``: both
        carry the same :data:`RUN_TOKEN` (a folder without one holds no run's)."""
        token = self.run_token()
        return token is not None and token == other.run_token()

    def run_token(self) -> str | None:
        """The token of the last run begun in this folder (:data:`RUN_TOKEN`; a staged stage writes
        one into its staging folder and the remote one when it begins), None if none was."""
        try:
            return self.fs.cat_file(self.file(RUN_TOKEN)).decode().strip() or None  # in one request, as meta
        except FileNotFoundError:
            return None
        except OSError as exc:
            raise cache_error(exc, f"reading {self.file(RUN_TOKEN)}") from None

    def upload(self, staged: DirStore, files: Sequence[str | os.PathLike] | None = None) -> None:
        """Copy every file of the local folder ``staged`` but ``_stage.json`` into this one (which
        :meth:`finish` then marks complete), or only ``files`` (paths inside ``staged``), in one call.
        On a filesystem that writes files in place (:func:`writes_whole_objects` False: sftp, smb)
        each file goes to a temporary ``*.tmp`` name first and is renamed once whole, so that an
        upload cut off midway leaves the file before it, or none, never a part of it (a killed
        run's ``*.tmp`` files are removed by :meth:`remove_temporaries`)."""
        root = Path(staged.path)
        if files is None:
            local = sorted(p for p in root.rglob("*") if p.is_file() and p.name != "_stage.json")
        else:
            local = [Path(p) if Path(p).is_absolute() else root / p for p in files]
        targets = [self.file(path.relative_to(root).as_posix()) for path in local]
        fs = self.fs
        whole = writes_whole_objects(fs)
        try:
            for parent in sorted({fs._parent(t) for t in targets}):
                fs.makedirs(parent, exist_ok=True)
            if local:  # one call: an object store's filesystem (s3fs, gcsfs) sends the files concurrently
                fs.put([str(path) for path in local], targets if whole else [t + ".tmp" for t in targets])
            if not whole:
                for target in targets:
                    fs.mv(target + ".tmp", target)
        except OSError as exc:
            raise cache_error(exc, f"uploading {root} to {self.url}") from None

    def download(self, staged: DirStore) -> int:
        """Copy every file of this (remote) folder but ``_stage.json`` and :data:`RUN_TOKEN` into
        the local folder ``staged``; returns how many (a resumable stage's checkpoints, when it
        resumes on another machine than the one that began it). The token stays behind: a download
        cut off midway must not leave a staging folder that claims to hold the remote's run."""
        try:
            files = [f for f in self.fs.find(self.path) if f.rsplit("/", 1)[-1] not in ("_stage.json", RUN_TOKEN)] \
                if self.fs.exists(self.path) else []
            targets = [Path(staged.path) / os.path.relpath(name, self.path) for name in files]
            for parent in {t.parent for t in targets}:
                parent.mkdir(parents=True, exist_ok=True)
            if files:  # one call, as in upload
                self.fs.get(files, [str(t) for t in targets])
        except OSError as exc:
            raise cache_error(exc, f"downloading {self.url} to {staged.path}") from None
        return len(files)

    def local_copy(self, staging_dir: str) -> Path:
        """A local folder holding this finished output's files, for readers that need local files
        (checkpoints, the mean map): the folder itself on a local cache; on a remote one a copy under
        ``staging_dir`` (run.staging_dir), downloaded once per finished run of the stage (its
        ``_stage.json``): a process, or another on this machine, that finds it reuses it."""
        if self.is_local:
            return Path(self.path)
        try:
            stamp = self.fs.cat_file(self.file("_stage.json"))  # in one request, as meta
        except FileNotFoundError:
            raise CacheError(f"{self.url}: the stage has not finished (no _stage.json)") from None
        except OSError as exc:
            raise cache_error(exc, f"reading {self.file('_stage.json')}") from None
        copy = _mirror_root(self.url, staging_dir) / "copies" / hashlib.sha256(stamp).hexdigest()[:16]
        if not copy.is_dir():
            tmp = copy.parent / f".{copy.name}-{uuid.uuid4().hex[:8]}"
            tmp.mkdir(parents=True)  # also for an output of no file but its _stage.json
            self.download(DirStore(str(tmp)))
            (tmp / "_stage.json").write_bytes(stamp)
            try:
                tmp.rename(copy)  # atomic: a reader sees the whole copy or none
            except OSError:  # another process renamed its copy of the same run first
                if not copy.is_dir():
                    raise
                shutil.rmtree(tmp, ignore_errors=True)
            for old in copy.parent.iterdir():  # copies of earlier runs (readers load a run's files once)
                if old != copy and (not old.name.startswith(".") or _stale(old)):
                    shutil.rmtree(old, ignore_errors=True)
        return copy

    def write_manifest(self, sizes: dict[str, int] | None = None) -> int:
        """Record every file of the folder (but the bookkeeping files, :data:`UNRECORDED`) with its
        size and SHA-256 in :data:`FILES_MANIFEST`, for :meth:`check_files`; the runner calls it
        when the stage has written everything, before the upload and :meth:`finish`. ``sizes``: the
        folder's :meth:`sizes` when the caller has them. Returns how many files. Kept out of
        ``_stage.json``, which every run reads (an export of 24,000 frames has about 150,000 files)."""
        try:
            files = {name: [size, self._digest(name)] for name, size in (self.sizes() if sizes is None else sizes).items()}
        except OSError as exc:
            raise cache_error(exc, f"reading the files of {self.url}") from None
        self.write_text(FILES_MANIFEST, json.dumps(files, separators=(",", ":"), sort_keys=True))
        return len(files)

    def check_files(self, progress: Callable[[int, int], None] | None = None) -> tuple[int | None, list[str]]:
        """(files checked, one problem per file that is missing or whose size or SHA-256 differs
        from :data:`FILES_MANIFEST`'s record); (None, []) for an output finished without one (before
        2026-12-06). Files added since are not problems. ``progress(n, total)`` per file."""
        try:
            recorded = json.loads(self.fs.cat_file(self.file(FILES_MANIFEST)))  # in one request, as meta
        except FileNotFoundError:
            return None, []
        except (OSError, ValueError) as exc:
            return 0, [f"{self.file(FILES_MANIFEST)}: unreadable ({one_line(exc)})"]
        problems = []
        try:
            sizes = self.sizes()
        except OSError as exc:
            return 0, [str(cache_error(exc, f"listing {self.url}"))]
        for name, (size, digest) in recorded.items():
            shown = join(self.url, name)
            if name not in sizes:
                problems.append(f"{shown}: missing")
            elif sizes[name] != size:
                problems.append(f"{shown}: {sizes[name]} bytes, {size} when the stage finished")
            else:
                try:
                    if self._digest(name) != digest:
                        problems.append(f"{shown}: its content changed since the stage finished (SHA-256)")
                except OSError as exc:
                    problems.append(f"{shown}: unreadable ({one_line(exc)})")
            if progress:
                progress(1, len(recorded))
        return len(recorded), problems

    def sizes(self) -> dict[str, int]:
        """{path relative to the folder: size in bytes} of its files but :data:`UNRECORDED`."""
        if not self.fs.exists(self.path):
            return {}
        found = self.fs.find(self.path, detail=True)
        root = self.path.rstrip("/") + "/"
        return {name.removeprefix(root): int(info["size"]) for name, info in found.items()
                if info.get("type", "file") == "file" and name.rsplit("/", 1)[-1] not in UNRECORDED}

    def _digest(self, name: str) -> str:
        """SHA-256 (hex) of the folder's file ``name``."""
        digest = hashlib.sha256()
        with self.fs.open(self.file(name), "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                digest.update(block)
        return digest.hexdigest()

    def invalidate(self) -> None:
        """Forget completion (the files stay; the stage decides what to reuse)."""
        try:
            if self.fs.exists(self.file("_stage.json")):
                self.fs.rm(self.file("_stage.json"))
        except OSError as exc:
            raise cache_error(exc, f"invalidating {self.url}") from None


async def _write_frame_async(url: str, index: int, fills: dict[str, Any], values: list[tuple[str, Any]]) -> None:
    """Write ``values`` into row ``index`` of the group's arrays concurrently, then the status;
    ``fills``: the ragged arrays' padding values, by name."""
    names = [name for name, _ in values] + ["reason", "status"]
    targets = await write_targets(url, names)

    def row(name: str, value: Any) -> Any:
        target = targets[name]
        return _frame_row(value, target.dtype, target.shape[1:], name in fills, fills.get(name))

    await gather_all([*(targets[name].setitem(index, row(name, v)) for name, v in values),
                       targets["reason"].setitem(index, "")])
    await targets["status"].setitem(index, DONE)


def _frame_row(value: Any, dtype: Any, shape: tuple[int, ...], ragged: bool, fill: Any) -> Any:
    """One frame's row of an array of ``dtype`` and per-frame ``shape``: ``value`` cast, or, for a
    ragged array, its rows padded with ``fill`` to the capacity."""
    if not ragged:
        return np.asarray(value).astype(dtype, copy=False) if dtype != object else value
    padded = np.full(shape, fill, dtype=dtype)
    padded[: value.shape[0]] = value
    return padded


STALE_COPY_S = 86400.0
"""Age (s, by mtime) after which a partial local copy (a ``.``-folder of DirStore.local_copy) is
taken for one a killed process left, and removed with the copies of earlier runs."""


def _stale(path: Path) -> bool:
    """Whether ``path`` was last modified more than STALE_COPY_S ago (False if it is gone)."""
    try:
        return time.time() - path.stat().st_mtime > STALE_COPY_S
    except OSError:
        return False


def frame_store(root: str, dataset: str, stage: str) -> FrameStore:
    """The FrameStore of ``stage`` of ``dataset`` under cache ``root``."""
    return FrameStore(join(root, dataset, f"{stage}.zarr"))


RUN_TOKEN = "_run.token"
"""File of a staged stage's output folder (remote and staging alike) naming the run that began
last: a staging folder whose token differs from the remote's is another run's (an older one, or
this machine's while another ran the stage since) and is replaced by the remote's files."""

FILES_MANIFEST = "_files.json"
"""File of a finished dataset stage's output folder recording each of its files' size and SHA-256
({path: [bytes, hex digest]}; DirStore.write_manifest), which `pipeline verify` checks."""

UNRECORDED = frozenset({"_stage.json", RUN_TOKEN, FILES_MANIFEST})
"""Bookkeeping files of a dataset stage's folder, left out of its manifest."""


def _mirror_root(url: str, staging_dir: str) -> Path:
    """Where the local staging folder and copies of the remote folder ``url`` live: under
    ``staging_dir`` (``~`` expanded), named by the URL's last part and a digest of the whole URL."""
    name = url.rstrip("/").rsplit("/", 1)[-1] or "folder"
    return Path(os.path.expanduser(staging_dir)) / f"{name}-{hashlib.sha256(url.encode()).hexdigest()[:16]}"


def dir_store(root: str, dataset: str, stage: str) -> DirStore:
    """The DirStore of ``stage`` of ``dataset`` under cache ``root``."""
    return DirStore(join(root, dataset, stage))


class RaggedRows:
    """Flat row view of a ragged per-frame array: the rows of frame ``frames[i]`` are rows
    ``offsets[i]`` to ``offsets[i + 1]`` of the view.

    Lets training iterate over the sampled points of many frames without loading them all: it
    offers ``len``, ``oindex[rows]`` and ``chunks`` (rows per frame chunk) like a zarr array. A
    read of rows holds at most ``FRAMES_PER_READ`` frames' chunks at once (a sample spread over
    every training frame read all of them together: 3 GB of PlaceNet features at 16,000 frames).
    """

    FRAMES_PER_READ = 256

    def __init__(self, array: zarr.Array, counts: np.ndarray, frames: np.ndarray) -> None:
        counts = np.asarray(counts, dtype=np.int64)
        self.array = array
        self.frames = np.asarray(frames, dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(counts[self.frames])]).astype(np.int64)
        self.shape = (int(self.offsets[-1]), *array.shape[2:])
        self.chunks = (max(1, int(array.shape[1])),)

    def __len__(self) -> int:
        return self.shape[0]

    @property
    def oindex(self) -> "RaggedRows":
        return self

    def __getitem__(self, rows) -> np.ndarray:
        rows = np.asarray(rows, dtype=np.int64)
        if rows.size and not (0 <= rows.min() and rows.max() < len(self)):
            raise IndexError(f"rows out of range 0..{len(self) - 1}")
        position = np.searchsorted(self.offsets, rows, side="right") - 1
        within = rows - self.offsets[position]
        uniq, inverse = np.unique(self.frames[position], return_inverse=True)
        out = np.empty((len(rows), *self.shape[1:]), dtype=self.array.dtype)
        order = np.argsort(inverse, kind="stable")  # the rows grouped by frame, frames ascending
        bounds = np.searchsorted(inverse[order], np.arange(0, len(uniq) + self.FRAMES_PER_READ, self.FRAMES_PER_READ))
        for w, start in enumerate(range(0, len(uniq), self.FRAMES_PER_READ)):
            block = np.asarray(self.array.oindex[uniq[start:start + self.FRAMES_PER_READ]])  # (w, capacity, ...)
            picked = order[bounds[w]:bounds[w + 1]]
            out[picked] = block[inverse[picked] - start, within[picked]]
        return out
