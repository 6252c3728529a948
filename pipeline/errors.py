"""Exceptions of the library. The CLI turns these into one-line messages and exit code 2."""

from __future__ import annotations


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
