"""What a run reports: one StageReport per stage it ran (its line, the frames it left failed), and
the line that counts a run's failed frames once each (failed_frames_line)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.cache import DONE, EXCLUDED, FAILED, PENDING

NAME_WIDTH = 15
"""Width of the stage-name column of progress lines (the longest name, evaluate-frames)."""


@dataclass
class StageReport:
    """What one stage did in a run."""

    stage: str
    action: str
    done: int = 0
    failed: int = 0
    pending: int = 0
    excluded: int = 0
    processed: int = 0
    seconds: float = 0.0
    failures: list[tuple[int, str]] = field(default_factory=list)
    """(frame index, reason) of the frames that failed in this run."""
    failed_frames: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    """Indices of the frames failed in the output after the run (``failed`` of them), this run's or
    earlier, their own failures or an upstream stage's (a frame stage)."""
    summary: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    """Lines printed under the stage's line (FrameStage.summarise)."""

    def set_counts(self, status: np.ndarray) -> "StageReport":
        """Take the frame counts (and the failed frames) from the output's (F,) status after the run."""
        self.done, self.pending, self.excluded = (int((status == code).sum()) for code in (DONE, PENDING, EXCLUDED))
        self.failed_frames = np.flatnonzero(status == FAILED)
        self.failed = len(self.failed_frames)
        return self

    def line(self) -> str:
        if self.action == "dataset":
            return f"{self.stage:<{NAME_WIDTH}} {self.summary.get('message', 'done')} ({self.seconds:.1f} s)"
        return (f"{self.stage:<{NAME_WIDTH}} processed {self.processed} frame(s) in {self.seconds:.1f} s; "
                f"done {self.done}, failed {self.failed}, pending {self.pending}, excluded {self.excluded}")


def failed_frames_line(reports: list[StageReport]) -> str:
    """'N frame(s) failed (first in calibrate: 3, synthesize: 1)': each failed frame counted once,
    under the first stage of ``reports`` (in run order) where it failed; the stages after that one
    mark it failed too (blocked), which summing their counts would count again. '' if none failed."""
    seen = np.zeros(0, np.int64)
    parts = []
    for r in reports:
        new = np.setdiff1d(r.failed_frames, seen)
        if len(new):
            parts.append(f"{r.stage}: {len(new)}")
            seen = np.union1d(seen, new)
    return f"{len(seen)} frame(s) failed (first in {', '.join(parts)})" if len(seen) else ""
