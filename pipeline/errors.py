"""Exceptions of the library. The CLI turns these into one-line messages and exit code 2."""

from __future__ import annotations

import contextlib
import errno
import signal
import threading
from typing import Any, Iterator, Literal, get_args


class PipelineError(Exception):
    """Base class of every error the library raises on purpose."""


class ConfigError(PipelineError):
    """A configuration key or value is invalid."""


class ReaderError(PipelineError):
    """A dataset file is missing or malformed.

    The message always names the file, the frame and what is wrong.
    """

    def __init__(self, path: object, problem: str, frame: str | None = None) -> None:
        self.path = str(path)
        self.problem = problem
        self.frame = frame
        where = f"frame {frame}: " if frame is not None else ""
        super().__init__(f"{where}{self.path}: {problem}")


class FrameError(PipelineError):
    """A per-frame computation failed for a reason that concerns only this frame."""

    def __init__(self, stage: str, frame: str, problem: str) -> None:
        self.stage = stage
        self.frame = frame
        self.problem = problem
        super().__init__(f"stage {stage}, frame {frame}: {problem}")


class LockError(PipelineError):
    """Another run holds the lock of a stage output."""


class CacheError(PipelineError):
    """The cache cannot be read or written (read-only, disk full, corrupt layout)."""


class MetadataError(CacheError):
    """The metadata of a stage output (a ``zarr.json``) is damaged or missing while its arrays are
    there: the output cannot be read, and recomputing it from scratch would lose its finished
    frames, so the run stops instead. The message names the file and the two ways out."""


class ChunkError(PipelineError):
    """A chunk of a cached array is damaged: it cannot be decoded, or a finished frame's chunk is
    missing. It concerns one frame: a frame computation that reads it fails alone, the run goes on.

    The message names the array (``<stage>.zarr/<array>``), the frame, the chunk file, what is
    wrong and what recomputes it.
    """

    def __init__(self, array: str, index: int, frame: str | None, chunk: str, problem: str, remedy: str) -> None:
        self.array = array
        self.index = index
        self.frame = frame
        self.chunk = chunk
        self.problem = problem
        self.remedy = remedy
        frame_id = f" ({frame})" if frame is not None and frame != str(index) else ""
        self.finding = f"{array}, frame {index}{frame_id}: chunk {chunk} {problem}"
        """The message without its remedy (where the caller names the command itself, as verify does)."""
        super().__init__(f"{self.finding}; {remedy}")

    def __reduce__(self):  # picklable (raised on dask workers)
        return type(self), (self.array, self.index, self.frame, self.chunk, self.problem, self.remedy)


def from_dask(exc: BaseException) -> bool:
    """Whether ``exc`` is dask's or dask.distributed's own (the cluster failed, not the work)."""
    return type(exc).__module__.startswith(("distributed", "dask"))


InterruptedKind = Literal["frame", "resumes", "dataset"]
"""What an interrupted stage leaves to go on from (:class:`StageInterrupted`)."""


class StageInterrupted(KeyboardInterrupt):
    """Ctrl-C (SIGINT) while a stage ran: says which stage, and so what a new run goes on from.

    ``kind``: 'frame' (finished frames are kept; the world's generation keeps its finished
    sequences, which hold them), 'resumes' (a dataset stage that goes on from what it saved,
    train's per-epoch checkpoints) or 'dataset' (starts over). ``forced``: a recomputation that
    --force asked for had begun, which a repeated --force would start again.
    """

    KINDS = get_args(InterruptedKind)

    def __init__(self, stage: str, kind: InterruptedKind, forced: bool) -> None:
        if kind not in self.KINDS:
            raise ValueError(f"StageInterrupted: kind must be one of {self.KINDS}, got {kind!r}")
        self.stage = stage
        self.kind = kind
        self.forced = forced
        super().__init__(stage)

    def advice(self) -> str:
        """One line for the person who pressed Ctrl-C."""
        return f"interrupted in {self.stage}: {resume_advice(self.stage, self.kind, self.forced)}"


def resume_advice(stage: str | None, kind: InterruptedKind, forced: bool) -> str:
    """What a stopped run of ``stage`` leaves and how to go on (the kinds of
    :class:`StageInterrupted`); ``forced``: a recomputation --force asked for had begun, so the
    rerun must leave --force out."""
    again = "run the same command again" + (" without --force" if forced else "")
    if kind == "frame":
        return f"its finished frames are kept; {again} to resume"
    if kind == "resumes":
        return f"what it saved is kept; {again} to resume from its last checkpoint"
    return f"the stages before it are kept, {stage} starts over when you run the same command again"


@contextlib.contextmanager
def sigint_deferred() -> Iterator[None]:
    """Hold a Ctrl-C (SIGINT) that comes during the body until it ends, then deliver it to the
    handler there was (KeyboardInterrupt by default), also when the body raised.

    For library calls that turn the KeyboardInterrupt a SIGINT raises in the Python code they call
    into another error: torch, making the tensors of a safetensors file (safetensors 0.8, torch
    2.13), calls UntypedStorage.__getitem__ and reports any error there as ValueError ('could not
    determine the shape of object type UntypedStorage'), and a Ctrl-C that fell in a checkpoint's
    load was reported as a damaged checkpoint (a third of them for a checkpoint of many small
    tensors). A load is milliseconds; this costs 9 us. Only the main thread runs signal handlers:
    elsewhere, or with a handler not set from Python, a no-op."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is None:
        yield
        return
    caught: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught:
            signal.raise_signal(signal.SIGINT)


class ClusterFailed(PipelineError):
    """The dask cluster failed while a stage ran (no worker left, the scheduler lost, workers
    killed). ``what``: what failed; ``stage``: the stage it failed in (None: not known where it is
    raised, the runner adds it) and ``kind``, ``forced`` as for :class:`StageInterrupted`;
    ``after``: a condition for the rerun."""

    def __init__(self, what: str, stage: str | None = None, kind: InterruptedKind = "frame", forced: bool = False,
                 after: str = "") -> None:
        self.what, self.stage, self.kind, self.forced, self.after = what, stage, kind, forced, after
        where = f"{stage}: " if stage else ""
        super().__init__(f"{where}{what}; {resume_advice(stage, kind, forced)}{after}")

    @classmethod
    def from_dask(cls, exc: BaseException, **kwargs: Any) -> "ClusterFailed":
        """The failure dask's own error ``exc`` reports (its type and first line); ``kwargs`` as
        for the constructor."""
        return cls(f"the dask cluster failed ({exception_line(exc)})", **kwargs)

    def in_stage(self, stage: str, kind: InterruptedKind, forced: bool) -> "ClusterFailed":
        """The same failure, placed in ``stage`` (of ``kind``, ``forced`` as for the constructor)."""
        return ClusterFailed(self.what, stage, kind, forced, self.after)

    def __reduce__(self):
        return type(self), (self.what, self.stage, self.kind, self.forced, self.after)


def exception_line(exc: BaseException) -> str:
    """'Type: the first line of the message' of ``exc`` ('Type: ' for an empty message)."""
    text = str(exc)
    return f"{type(exc).__name__}: {text.splitlines()[0] if text else ''}"


def first_sentence(exc: BaseException, limit: int = 120) -> str:
    """The first sentence of ``exc``'s message on one line, at most ``limit`` characters (its type
    for an empty message): a library's reason without the advice it appends."""
    text = " ".join(str(exc).split())
    return text.split(". ")[0][:limit] if text else type(exc).__name__


def one_line(exc: BaseException) -> str:
    """:func:`exception_line`, at most 200 characters."""
    return exception_line(exc)[:200]


def cache_error(exc: OSError, what: str) -> CacheError:
    """A CacheError explaining an OSError in words (read-only cache, disk full, ...)."""
    if exc.errno == errno.ENOSPC:
        return CacheError(f"{what}: the disk holding the cache is full ({exc})")
    if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
        return CacheError(f"{what}: the cache is not writable ({exc}); choose another with --cache")
    return CacheError(f"{what}: {exc}")
