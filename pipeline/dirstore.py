"""The folder output of one dataset stage (DirStore), ``<root>/<dataset>/<stage>/`` (the whole
cache's layout: pipeline.cache): its files, ``_stage.json`` written last (the record of the run
that finished it), the run token and the files' manifest, and for a remote folder the local
staging folder a stage writes into and the local copies its readers take.

A ``_stage.json`` that is there but not a JSON object raises MetadataError (written whole by a
rename, such a file is damaged); a missing one means the stage has not finished.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import fsspec

from pipeline.cachefs import command_options, is_local, join, writes_whole_objects
from pipeline.errors import CacheError, MetadataError, cache_error, one_line
from pipeline.fileio import sync_filesystem

RUN_TOKEN = "_run.token"
"""File of a staged stage's output folder (remote and staging alike) naming the run that began
last: a staging folder whose token differs from the remote's is another run's (an older one, or
this machine's while another ran the stage since) and is replaced by the remote's files."""

FILES_MANIFEST = "_files.json"
"""File of a finished dataset stage's output folder recording each of its files' size and SHA-256
({path: [bytes, hex digest]}; DirStore.write_manifest), which `pipeline verify` checks."""

UNRECORDED = frozenset({"_stage.json", RUN_TOKEN, FILES_MANIFEST})
"""Bookkeeping files of a dataset stage's folder, left out of its manifest."""


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
        where = f" {command_options(parts[1], parts[0])}" if len(parts) == 3 else ""
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

    def holds_files(self) -> bool:
        """Whether the folder holds anything: where no run finished (no ``_stage.json``), the files
        of a run cut off, or of a finished one marked stale since (:meth:`invalidate` keeps them)."""
        try:
            return bool(self.fs.ls(self.path, detail=False))
        except (FileNotFoundError, NotADirectoryError):
            return False
        except OSError as exc:
            raise cache_error(exc, f"listing {self.url}") from None

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
        (per-frame upstream stage -> pipeline.cache.FrameStore.done_digest) says which frames it
        read; ``record``: what it was made with (pipeline.runner.Pipeline.record), kept beside. On a
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

    def holds_untokened_run_of(self, other: DirStore) -> bool:
        """Whether this (staging) folder holds the files of a run in ``other`` begun before run
        tokens were written (2026-12-07): it holds files and neither folder has a :data:`RUN_TOKEN`.
        Kept, as :meth:`holds_run_of`'s are, rather than replaced by ``other``'s."""
        return self.holds_files() and self.run_token() is None and other.run_token() is None

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


STALE_COPY_S = 86400.0
"""Age (s, by mtime) after which a partial local copy (a ``.``-folder of DirStore.local_copy) is
taken for one a killed process left, and removed with the copies of earlier runs."""


def _stale(path: Path) -> bool:
    """Whether ``path`` was last modified more than STALE_COPY_S ago (False if it is gone)."""
    try:
        return time.time() - path.stat().st_mtime > STALE_COPY_S
    except OSError:
        return False


def _mirror_root(url: str, staging_dir: str) -> Path:
    """Where the local staging folder and copies of the remote folder ``url`` live: under
    ``staging_dir`` (``~`` expanded), named by the URL's last part and a digest of the whole URL."""
    name = url.rstrip("/").rsplit("/", 1)[-1] or "folder"
    return Path(os.path.expanduser(staging_dir)) / f"{name}-{hashlib.sha256(url.encode()).hexdigest()[:16]}"


def dir_store(root: str, dataset: str, stage: str) -> DirStore:
    """The DirStore of ``stage`` of ``dataset`` under cache ``root``."""
    return DirStore(join(root, dataset, stage))
