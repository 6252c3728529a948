"""The on-disk cache: one zarr group per frame stage (FrameStore, here), one folder per dataset
stage (pipeline.dirstore.DirStore). The zarr I/O beneath FrameStore is pipeline.zarr_io's.

Layout under the cache root (a local folder or any fsspec URL)::

    <root>/<dataset>/<stage>.zarr/       frame stage: declared arrays, one chunk per frame,
                                         plus ``status`` (uint8 per frame), ``reason`` (str)
                                         and ``frame_ids`` (str, one chunk); on a remote cache
                                         ``status_snapshot``, the status in one object
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
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import os
import shlex
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import fsspec
import numpy as np
import zarr
from zarr.codecs import ZstdCodec
from zarr.core.sync import sync

from pipeline.cachefs import command_options, join, local_path
from pipeline.errors import CacheError, ChunkError, MetadataError, cache_error, one_line
from pipeline.fileio import sync_filesystem
from pipeline.snapshots import (STATUS_SNAPSHOT, StatusSnapshot, column_eligible, column_key, decode_column,
                                decode_status, encode_column, fresh_status, get_objects, put_object)
from pipeline.stage import ArraySpec
from pipeline.zarr_io import (DECODE_ERRORS, ZARR_FORMAT, chunk_key, chunk_path, direct_layout,
                              frames_from_chunk_files, gather_all, keep, kept, member_async, open_group, opened_array,
                              put_chunk, write_targets, zarr_options)

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
            self.save_status_snapshot(np.full(n, PENDING, np.uint8))  # a remote one's: every frame pending, no lineage
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
        """(F,) uint8 status codes; ChunkError naming the lowest damaged chunk when one is. A remote
        output's from its :data:`STATUS_SNAPSHOT` when it has one (one request, not one per frame)."""
        return self.status_and_snapshot()[0]

    def status_and_snapshot(self) -> tuple[np.ndarray, StatusSnapshot | None]:
        """(status, the status snapshot it was read from, None when it was read from the chunks):
        what a run that saves the next snapshot (:meth:`save_status_snapshot`) starts from."""
        arr = self._array("status")
        status = frames_from_chunk_files(arr)
        if status is not None:
            return status, None
        snapshot = None if local_path(self.url) is not None else self._status_snapshot_there(arr)
        if snapshot is not None:
            return snapshot.status, snapshot
        try:
            return np.asarray(arr[:]), None
        except DECODE_ERRORS as exc:
            _settle_io()
            raise self.damaged("status", np.arange(arr.shape[0]), exc) from None

    def _status_snapshot_there(self, arr: zarr.Array) -> StatusSnapshot | None:
        """The :data:`STATUS_SNAPSHOT` of the output whose status array is ``arr``, None when there
        is none that holds its status (pipeline.snapshots.decode_status)."""
        data = sync(get_objects(arr.store_path.store, [STATUS_SNAPSHOT]))[0]
        return decode_status(data, arr.shape[0], STATUS_NAMES)

    def save_status_snapshot(self, status: np.ndarray, keep_unchanged: bool = False,
                             after: StatusSnapshot | None = None, changed: np.ndarray | None = None) -> None:
        """Write ``status`` (F,), the output's whole status array, as its :data:`STATUS_SNAPSHOT`
        with a new token (a remote output only): what the runner knows the status to be, holding
        the stage's lock (when a run of the stage's frames ends: the status it read, the marks and
        frames it wrote). ``keep_unchanged``: leave a snapshot there that holds ``status`` with a
        token (no status chunk was written since it was, so the column snapshots tagged with it
        still hold their arrays: a run with nothing to do keeps them). ``after``: the snapshot the
        status was read from before frames ``changed`` ((F,) bool) were written or marked, and no
        others: the new one succeeds it (pipeline.snapshots, the lineage)."""
        if local_path(self.url) is not None:
            return
        status = np.asarray(status, np.uint8).reshape(-1)
        arr = self._array("status", "r+")
        if len(status) != arr.shape[0]:
            raise ValueError(f"{self.url}: a status snapshot of {len(status)} frames for {arr.shape[0]}")
        if keep_unchanged:
            there = self._status_snapshot_there(arr)
            if there is not None and there.token is not None and np.array_equal(there.status, status):
                return
        snapshot = fresh_status(status) if after is None or changed is None else after.successor(status, changed)
        try:
            sync(put_object(arr.store_path.store, STATUS_SNAPSHOT, snapshot.encode()))
        except OSError as exc:
            raise cache_error(exc, f"writing {join(self.url, STATUS_SNAPSHOT)}") from None

    def column(self, arr: zarr.Array, frames: np.ndarray | None,
               read_chunks: Callable[[np.ndarray | None], np.ndarray]) -> np.ndarray | None:
        """Frames ``frames`` (F',) of this remote output's array ``arr`` (every frame: None), from its
        column snapshot (pipeline.snapshots) when one holds what its chunks hold, or does once the
        chunks of the frames written since it was read are read; else every frame's, read from its
        chunks, kept as the column snapshot for the next reads. ``read_chunks(frames)``: the values
        of frames ``frames`` (every frame: None), read from their chunks. A read makes or brings up
        to date the column when that reads at most twice the chunks it wants, else it reads the
        chunks it wants (the caller does: None, having read nothing). None too where the output is
        local, the array is not small or has no frames, or the output has no status snapshot with
        a token."""
        n = arr.shape[0]
        if not n or arr.basename == "status":  # the status has its own snapshot (reasons and ids are strings)
            return None
        snapshot, values, stale = self._column_snapshot(arr)
        if snapshot is None:
            return None
        wanted = n if frames is None else len(frames)
        if values is not None and len(stale) <= 2 * wanted:
            if len(stale):  # the frames written since the column was read, from their chunks
                values[stale] = read_chunks(stale)
        elif n <= 2 * wanted:
            values, stale = np.asarray(read_chunks(None)), None
        else:
            return None
        if stale is None or len(stale):
            with contextlib.suppress(OSError):  # e.g. read-only credentials: the next read reads the chunks too
                sync(put_object(arr.store_path.store.with_read_only(False), column_key(arr.basename),
                                encode_column(values, snapshot.token)))
        return values if frames is None else values[frames]

    def _drop_local_status_snapshot(self) -> None:
        """Remove a local output's :data:`STATUS_SNAPSHOT`, if any (one copied from an object
        store): before its status chunks are written directly."""
        with contextlib.suppress(FileNotFoundError):
            os.unlink(os.path.join(local_path(self.url), STATUS_SNAPSHOT))

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

    def write_frame(self, index: int, arrays: dict[str, np.ndarray], specs: tuple[ArraySpec, ...],
                    run: str = "") -> None:
        """Write one frame's arrays, then mark it done (the marker last).

        A local output's chunk files are written directly, as zarr's local store writes them (each
        encoded by the array's own codecs, to a temporary file renamed over the chunk): zarr's
        writes cost about 4 ms a frame in IO-thread hand-offs. Otherwise (a remote cache, another
        layout) all arrays of the frame are written concurrently in one round trip to zarr's IO loop,
        their metadata read once per ``run`` (RunEnv.stage_run; zarr_io.write_targets) if given.
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
                sync(_write_frame_async(self.url, index, fills, values, run))
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
        self._drop_local_status_snapshot()
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
            sync(drop_status_snapshot(status))
            if len(indices) == 1:
                reasons[int(indices[0])] = reason
                status[int(indices[0])] = code
                return
            reasons.oindex[indices] = np.full(len(indices), reason, dtype=reasons.dtype)
            status.oindex[indices] = np.full(len(indices), code, np.uint8)
        except OSError as exc:
            what = f"frame {indices[0]}" if len(indices) == 1 else f"{len(indices)} frames"
            raise cache_error(exc, f"recording {what} of {self.url}") from None

    def read(self, name: str, index: int, run: str = "") -> np.ndarray:
        """One frame of an array; ragged arrays are trimmed to the frame's row count. ``run``: as
        for :func:`read_frame`.

        ChunkError when a chunk it reads cannot be decoded, or is missing while the frame is done.
        """
        direct = self._read_chunk_files(name, index)
        if direct is not None:
            return direct
        return self._read_through_zarr(name, index, run)

    def _read_through_zarr(self, name: str, index: int, run: str = "") -> np.ndarray:
        """:meth:`read` through zarr (a remote cache): :meth:`read_many` of the one array, two round
        trips to the store where there were four, one after the other (until 2026-12-07)."""
        value = self.read_many([name], index, run)[name]
        if isinstance(value, Exception):
            raise value
        return value

    def read_many(self, names: Sequence[str], index: int, run: str = "") -> dict[str, np.ndarray | Exception]:
        """Frame ``index`` of each array of ``names``, as :meth:`read` gives it, through zarr, in two
        round trips to a remote store for them all (:func:`read_frame`). Each name's value, or the
        exception its read raised (ChunkError, MetadataError, KeyError, ...), for the caller to
        raise where it uses that array."""
        return read_frame([(self, names)], index, run)[0]

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
        except (ValueError, TypeError) as exc:
            node = exc
        return self._opened(name, node, missing_ok)

    def _opened(self, name: str, node: Any, missing_ok: bool = False) -> Any:
        """:meth:`_array` of what :func:`member_async` gave for array ``name``: its node, None, or the
        exception it raised."""
        if isinstance(node, (ValueError, TypeError)):  # json.JSONDecodeError for a truncated or garbled zarr.json
            raise self._damaged_array(name, node)
        if isinstance(node, BaseException):
            raise node
        if node is None:
            if missing_ok:
                return None
            self._group("r")  # GroupNotFoundError when the group is gone too, as opening it first raised
            raise KeyError(name)
        return zarr.Array(node) if isinstance(node, zarr.AsyncArray) else zarr.Group(node)

    def _decode(self, arr: zarr.Array, index: int, got: Any = None) -> np.ndarray:
        """Frame ``index`` of ``arr`` (or what reading it gave: ``got``, a value or the exception
        raised); ChunkError when its chunk cannot be decoded."""
        try:
            if isinstance(got, BaseException):
                raise got
            return np.asarray(arr[index] if got is None else got)
        except DECODE_ERRORS as exc:
            raise self._chunk_error(arr, index, f"cannot be decoded ({one_line(exc)})") from None

    def _checked(self, arr: zarr.Array, index: int, got: Any = None, run: str = "") -> np.ndarray:
        """:meth:`_decode`, and ChunkError when the value is all fill because the chunk is missing
        although the frame is done and the group has every chunk written (:data:`EVERY_CHUNK`;
        zarr writes no chunk for a frame of no elements, which is never missing). The group's
        metadata (once per process and ``run``, as :func:`read_frame`'s) and the file system are
        asked only for a value that is all fill."""
        value = self._decode(arr, index, got)
        if value.size and _all_fill(value, arr.fill_value) and self._every_chunk(run) \
                and not sync(arr.store.exists(f"{arr.path}/{chunk_key(arr, index)}")) \
                and int(self._decode(self._array("status"), index)) == DONE:
            raise self._chunk_error(arr, index, "is missing although the frame is done (zarr would read the fill "
                                                   "value in its place)")
        return value

    def _every_chunk(self, run: str = "") -> bool:
        """Whether the group has every chunk written (:data:`EVERY_CHUNK`), its metadata read once
        per process and ``run`` (RunEnv.stage_run) where one is given."""
        found, every = kept(self.url, "", "every chunk", ("run", run)) if run else (False, None)
        if not found:
            every = bool(self._group("r").attrs.get(EVERY_CHUNK))
            if run:
                keep(self.url, "", "every chunk", ("run", run), every)
        return every

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
        remedy = (f"recompute the frame with `pipeline run {self.stage} {command_options(dataset, root)} --force "
                  f"--frames {shlex.quote(frame) if frame else index}` (the frames made from it are recomputed too)")
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
        every_chunk = self._every_chunk()
        total = self._array("status").shape[0] * (2 + len(names))
        progress = (lambda n: None) if progress is None else (lambda n, _p=progress: _p(n, total))
        errors: dict[int, ChunkError] = {}
        status = self._scan(every_chunk, "status", None, errors, progress, block_bytes)
        status = np.where(np.isin(np.arange(len(status)), list(errors)), PENDING, status).astype(np.uint8)
        self._check_status_snapshot(status, errors)
        self._scan(every_chunk, "reason", status == FAILED, errors, progress, block_bytes, "failed")
        done = status == DONE
        for name in names:
            arr = self._array(name)
            _, column, stale = self._column_snapshot(arr)
            values = self._scan(every_chunk, name, done, errors, progress, block_bytes, "is done", column is not None)
            if column is not None:  # readers take the column's values but for the frames written since
                taken = done.copy()
                taken[stale] = False
                self._check_column_snapshot(arr, column, values, taken, errors)
        return status, dict(sorted(errors.items()))

    def _column_snapshot(self, arr: zarr.Array) -> tuple[StatusSnapshot | None, np.ndarray | None,
                                                          np.ndarray | None]:
        """(the output's status snapshot, which a column read now would be tagged with: None when it
        has none with a token, or the output is local or the array not small; the values of array
        ``arr``'s column snapshot when it was read under that snapshot or one of its ancestors, else
        None; then the frames (indices) written since, whose values it does not hold: empty when
        tagged with that snapshot, None without values)."""
        if local_path(self.url) is not None or not column_eligible(arr.dtype, arr.shape[1:]):
            return None, None, None
        status_data, column_data = sync(get_objects(arr.store_path.store, [STATUS_SNAPSHOT, column_key(arr.basename)]))
        snapshot = decode_status(status_data, arr.shape[0], STATUS_NAMES)
        if snapshot is None or snapshot.token is None:
            return None, None, None
        column = decode_column(column_data, arr.dtype, arr.shape)
        stale = None if column is None else snapshot.written_since(column[1])
        return snapshot, (None if stale is None else column[0]), stale

    def _check_column_snapshot(self, arr: zarr.Array, column: np.ndarray, values: np.ndarray, done: np.ndarray,
                               errors: dict[int, ChunkError]) -> None:
        """Add to ``errors`` a ChunkError for each frame of ``done`` ((F,) bool: done frames that
        readers take from the column) whose chunk of array ``arr`` holds ``values`` (F, ...) other
        than its column snapshot ``column`` (recomputing the frame removes the status snapshot it
        is tagged with, and the next snapshot has the frame written since)."""
        same = (column == values) | ((column != column) & (values != values))  # NaN where both are NaN
        for i in np.flatnonzero(done & ~same.reshape(len(same), -1).all(axis=1)):
            errors.setdefault(int(i), self._chunk_error(
                arr, int(i), f"holds {values[i].tolist()} where the output's column snapshot "
                             f"({join(self.url, column_key(arr.basename))}) holds {column[i].tolist()}"))

    def _check_status_snapshot(self, status: np.ndarray, errors: dict[int, ChunkError]) -> None:
        """Add to ``errors`` a ChunkError for each frame whose code in a remote output's
        :data:`STATUS_SNAPSHOT` is not its status chunk's, ``status`` (F,): readers would take the
        snapshot's (its repair, recomputing the frame, removes the snapshot and writes it again)."""
        if local_path(self.url) is not None:
            return
        arr = self._array("status")
        there = self._status_snapshot_there(arr)
        if there is None:
            return
        for i in np.flatnonzero(there.status != status):
            errors.setdefault(int(i), self._chunk_error(
                arr, int(i), f"says the frame is {STATUS_NAMES[int(status[i])]} where the output's status snapshot "
                             f"({join(self.url, STATUS_SNAPSHOT)}) says {STATUS_NAMES[int(there.status[i])]}"))

    def _scan(self, every_chunk: bool, name: str, frames: np.ndarray | None, errors: dict[int, ChunkError],
              progress: Callable[[int], None], block_bytes: int, state: str = "",
              values_too: bool = False) -> np.ndarray | None:
        """Decode array ``name`` in blocks, recording in ``errors`` a ChunkError for each frame of
        mask ``frames`` (every frame: None) whose chunk cannot be decoded or, where the group has every
        chunk written (``every_chunk``), is missing (the frames being in ``state``); the values when ``frames`` is None
        (the status array) or ``values_too`` (a frame whose chunk cannot be decoded: undefined)."""
        arr = self._array(name)
        n = arr.shape[0]
        wanted = np.ones(n, bool) if frames is None else frames
        per_frame_size = int(np.prod(arr.shape[1:], dtype=np.int64))
        per_frame = max(1, per_frame_size * arr.dtype.itemsize)
        step = max(1, block_bytes // per_frame)
        values = np.empty(arr.shape, arr.dtype) if frames is None or values_too else None
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
    lowest damaged frame it read instead of the codec's error. Reads of whole frames come from the
    chunk files of a local output, and from the column snapshot of a remote output's small array
    (:meth:`FrameStore.column`)."""

    def __init__(self, store: FrameStore, array: zarr.Array) -> None:
        self._store = store
        self._array = array

    def __getitem__(self, selection: Any) -> Any:
        if selection is Ellipsis or (isinstance(selection, slice) and selection == slice(None)):
            # the whole array, from its chunk files (a local output) or its column snapshot (a remote one)
            value = frames_from_chunk_files(self._array)
            if value is None:
                value = self._store.column(self._array, None, self._chunks)
            if value is not None:
                return value
        return self._read(lambda: self._array[selection], selection)

    def _chunks(self, frames: np.ndarray | None) -> np.ndarray:
        """The values of frames ``frames`` (every frame: None), read from their chunks."""
        if frames is None:
            return self._read(lambda: self._array[...], Ellipsis)
        return self._read(lambda: self._array.oindex[frames], frames)

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
        if frames is not None:  # some whole frames, from their chunk files or the column snapshot
            value = frames_from_chunk_files(self._checked._array, frames)
            if value is None and frames.size and frames.max() < self._checked._array.shape[0]:
                value = self._checked._store.column(self._checked._array, frames, self._checked._chunks)
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


def read_frame(wanted: Sequence[tuple[FrameStore, Sequence[str]]], index: int,
               run: str = "") -> list[dict[str, np.ndarray | Exception]]:
    """Frame ``index`` of the arrays ``names`` of each ``(store, names)`` of ``wanted``, as
    FrameStore.read gives them, through zarr: the ``zarr.json`` of every array and of its row count
    (ragged arrays have one) read concurrently, then every chunk; two round trips to a remote cache
    for a frame's arrays of several stages. With ``run`` (RunEnv.stage_run: the run of a stage's
    frames, which holds the read locks of the finished outputs it reads) each ``zarr.json`` is read
    once per process and run, then only the chunks: one round trip (until 2026-12-07 every frame
    read each ``zarr.json``). Per store, each name's value or the exception its read raised (the
    array's error first, as read reports it)."""
    asked = [(store, list(dict.fromkeys(names))) for store, names in wanted]
    members = [(store, member) for store, names in asked for name in names for member in (name, f"{name}_count")]
    known = {}
    for url, member in {(store.url, member) for store, member in members} if run else ():
        found, node = kept(url, member, "read", ("run", run))
        if found:
            known[(url, member)] = node
    fetch = list(dict.fromkeys((store.url, member) for store, member in members if (store.url, member) not in known))

    async def metadata() -> list[Any]:
        return await asyncio.gather(*(member_async(url, m, "r") for url, m in fetch), return_exceptions=True)

    fetched = dict(zip(fetch, sync(metadata()) if fetch else []))
    for (url, member), node in fetched.items() if run else ():
        if not isinstance(node, BaseException):
            keep(url, member, "read", ("run", run), node)
    nodes = iter({**known, **fetched}[(store.url, member)] for store, member in members)
    results: list[dict[str, np.ndarray | Exception]] = []
    opened: list[tuple[FrameStore, dict[str, np.ndarray | Exception], str, list[zarr.Array]]] = []
    for store, names in asked:
        out: dict[str, np.ndarray | Exception] = {}
        results.append(out)
        for name in names:
            node, count_node = next(nodes), next(nodes)
            try:
                arr = store._opened(name, node)
                counts = store._opened(f"{name}_count", count_node, missing_ok=True)
            except Exception as exc:  # noqa: BLE001 - the caller raises it where it reads the array
                out[name] = exc
            else:
                opened.append((store, out, name, [arr] if counts is None else [arr, counts]))
    chosen = [arr for *_, arrays in opened for arr in arrays]

    async def chunks() -> list[Any]:
        return await asyncio.gather(*(a.async_array.getitem(index) for a in chosen), return_exceptions=True)

    got = iter(sync(chunks()))
    for store, out, name, arrays in opened:
        read = [next(got) for _ in arrays]
        try:
            value, *rows = (store._checked(arr, index, r, run) for arr, r in zip(arrays, read))
            out[name] = value[: int(rows[0])] if rows else value
        except Exception as exc:  # noqa: BLE001 - as above
            out[name] = exc
    return [{name: out[name] for name in names} for (_, names), out in zip(asked, results)]


def done_digest(status: np.ndarray) -> str:
    """Short digest of the indices of the frames whose status (F,) is DONE."""
    done = np.flatnonzero(np.asarray(status) == DONE).astype(np.int64)
    return hashlib.sha256(done.tobytes()).hexdigest()[:16]


async def _write_frame_async(url: str, index: int, fills: dict[str, Any], values: list[tuple[str, Any]],
                             run: str = "") -> None:
    """Write ``values`` into row ``index`` of the group's arrays concurrently, then the status;
    ``fills``: the ragged arrays' padding values, by name; ``run``: as for write_targets."""
    names = [name for name, _ in values] + ["reason", "status"]
    targets = await write_targets(url, names, run)

    def row(name: str, value: Any) -> Any:
        target = targets[name]
        return _frame_row(value, target.dtype, target.shape[1:], name in fills, fills.get(name))

    # the status snapshot goes before the status chunk: once per process and run of the stage's frames
    dropped = bool(run) and kept(url, STATUS_SNAPSHOT, "removed", ("run", run))[0]
    drop = [] if dropped else [drop_status_snapshot(targets["status"])]
    await gather_all([*(targets[name].setitem(index, row(name, v)) for name, v in values),
                       targets["reason"].setitem(index, ""), *drop])
    if run and drop:
        keep(url, STATUS_SNAPSHOT, "removed", ("run", run), True)
    await targets["status"].setitem(index, DONE)


async def drop_status_snapshot(status: Any) -> None:
    """Remove the :data:`STATUS_SNAPSHOT` of the output whose status array (zarr.Array or
    AsyncArray, opened for writing) is ``status``, if it has one."""
    await status.store_path.store.delete(STATUS_SNAPSHOT)


def _frame_row(value: Any, dtype: Any, shape: tuple[int, ...], ragged: bool, fill: Any) -> Any:
    """One frame's row of an array of ``dtype`` and per-frame ``shape``: ``value`` cast, or, for a
    ragged array, its rows padded with ``fill`` to the capacity."""
    if not ragged:
        return np.asarray(value).astype(dtype, copy=False) if dtype != object else value
    padded = np.full(shape, fill, dtype=dtype)
    padded[: value.shape[0]] = value
    return padded


def frame_store(root: str, dataset: str, stage: str) -> FrameStore:
    """The FrameStore of ``stage`` of ``dataset`` under cache ``root``."""
    return FrameStore(join(root, dataset, f"{stage}.zarr"))


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
