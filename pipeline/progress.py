"""Progress of long work on stderr: a tqdm bar on a terminal; elsewhere (a log file, a batch job's
output) plain lines, at most one every ``every_s`` seconds (run.progress_every_s), so that a run
redirected to a file shows how far it is and how long it has left. Work shorter than ``every_s``
writes nothing there."""

from __future__ import annotations

import sys
import time
from typing import Any, Iterable, TextIO

from tqdm import tqdm

EVERY_S = 60.0
"""Default seconds between progress lines when stderr is not a terminal (run.progress_every_s)."""

LINE_FORMAT = "{desc}: {n_fmt}/{total_fmt} ({percentage:.0f}%), {elapsed} elapsed, about {remaining} left, {rate_fmt}{postfix}"
"""A progress line: 'synthesize: 1200/50000 (2%), 02:01 elapsed, about 1:22:03 left, 9.92frame/s' (or
'5.91s/frame' where a frame takes longer than a second), then what the caller last gave
``set_postfix`` (', loss=0.4123'). Callers pass ``refresh=False`` to it: a refresh writes a line at
once, whatever the interval."""


class _Lines:
    """A file for tqdm that turns its carriage-return redraws into lines (blank redraws dropped,
    tqdm's padding of the rate squeezed out)."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream

    def write(self, text: str) -> None:
        line = " ".join(text.replace("\r", "").split())
        if line:
            self.stream.write(line + "\n")

    def flush(self) -> None:
        self.stream.flush()


def bar(iterable: Iterable | None = None, *, total: int | None = None, desc: str = "", unit: str = "it",
        enabled: bool = True, every_s: float = EVERY_S, initial: int = 0, stream: TextIO | None = None) -> tqdm:
    """A tqdm over ``iterable`` (or updated by hand up to ``total``). ``enabled`` False: silent. On a
    terminal ``stream`` (default stderr): the usual bar, cleared when done. Elsewhere: a line once
    ``every_s`` seconds have passed, then at most one every ``every_s`` seconds (nothing for work
    shorter than ``every_s``; nothing at all when ``every_s`` is 0; the caller says when it is done)."""
    stream = sys.stderr if stream is None else stream
    if enabled and _is_terminal(stream):
        return tqdm(iterable, total=total, desc=desc, unit=unit, initial=initial, leave=False, file=stream)
    if not _writes_lines(enabled, every_s, stream):
        return tqdm(iterable, total=total, disable=True)
    # miniters=1: every update checks the interval itself. With tqdm's dynamic miniters (above 1)
    # its monitor thread redraws a bar that has not printed for maxinterval, and over an iterable
    # that redraw shows the count of the last line (the loop syncs its count only when it prints):
    # a log got a line with a stale count and time left, and the loop's own line a second later
    return tqdm(iterable, total=total, desc=desc, unit=unit, initial=initial, file=_Lines(stream), leave=False,
                mininterval=every_s, maxinterval=every_s, miniters=1, delay=every_s, bar_format=LINE_FORMAT,
                ascii=True, dynamic_ncols=False)


class Heartbeat:
    """Lines that are worth a log only now and then (an epoch's losses): :meth:`maybe` writes one
    when ``every_s`` seconds have passed since the last (or since the start), and only where
    :func:`bar` writes lines (stderr not a terminal, ``every_s`` > 0, ``enabled``)."""

    def __init__(self, enabled: bool = True, every_s: float = EVERY_S, stream: TextIO | None = None) -> None:
        self.stream = sys.stderr if stream is None else stream
        self.active = _writes_lines(enabled, every_s, self.stream)
        self.every_s = every_s
        self.last = time.monotonic()

    def maybe(self, line: str) -> bool:
        """Write ``line`` if it is time; whether it was written."""
        if not self.active or time.monotonic() - self.last < self.every_s:
            return False
        self.stream.write(line + "\n")
        self.stream.flush()
        self.last = time.monotonic()
        return True


def _writes_lines(enabled: bool, every_s: float, stream: Any) -> bool:
    """Whether progress goes to ``stream`` as lines: enabled, an interval, and no terminal."""
    return enabled and every_s > 0 and not _is_terminal(stream)


def _is_terminal(stream: Any) -> bool:
    isatty = getattr(stream, "isatty", None)
    try:
        return bool(isatty and isatty())
    except (OSError, ValueError):  # a closed stream
        return False
