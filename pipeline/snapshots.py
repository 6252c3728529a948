"""Snapshots: a remote output's per-frame arrays that are read whole, each in one object.

A frame stage's output holds one chunk per frame and array (so that parallel writers never share
one). On an object store each chunk is a request, so a read of a whole per-frame array is a
request per frame (30,000 at 30,000 frames, minutes at 20 ms a request), and commands read some
whole again and again: every frame's status (each run's checks of its upstream outputs,
`pipeline status`), calibrate's split (each stage's frame selection, in every run that resumes
it), train's and evaluate's tables. Beside a remote output's arrays (pipeline.cache.FrameStore):

- ``status_snapshot``: its status array, with a random token. FrameStore.create writes one of
  pending frames, the runner one when a run of the stage's frames ends (it holds the stage's lock),
  and every write of a status chunk removes it first, so one that is there is the status array
  (but for a frame that a run stopped by --strict was still computing: written after the
  snapshot, it reads as the snapshot has it, pending or failed, and is computed again).
- ``column_snapshot.<array>``: a small array (a fixed shape per frame of numbers or booleans, at
  most COLUMN_FRAME_BYTES_MAX bytes a frame) as a reader read it whole from its chunks, tagged
  with the token of the status snapshot it found before that read. Every write of a frame's chunks
  goes with its status chunk's, which removes that status snapshot first, and no token is used
  twice, so a column tagged with the present status snapshot's token holds what the chunks held
  when it was read (the frames the status snapshot holds as done, at least). A reader that cannot
  write (read-only credentials) reads the chunks each time, as before.
- The lineage: a status snapshot that a run writes when it ends (or ``--force --frames`` once its
  frames are marked) succeeds the one the run read its status from, when it read one; it keeps
  the tokens of up to LINEAGE_MAX snapshots before it and, per frame, how many snapshots ago the
  frame was last written or marked. A column tagged with one of those tokens is brought up to date
  by reading the chunks of the frames written since (a run of 3 frames: 3 chunks, not every
  frame's); one with any other token is read again from every chunk. This holds as the runner's
  own snapshot does: the run holds the stage's lock, and nothing else writes the output meanwhile.

Each object is a header line, ``radarsim status snapshot 3 <frames> <token> <ancestors>`` (the
tokens before it, newest first, joined by commas; ``-`` for none) or ``radarsim column snapshot 1
<token> <dtype> <frames>,<shape...>``, then the values in C order (a status snapshot's status
codes, then each frame's age in snapshots, 255 for older than its oldest ancestor) compressed by
zstd with its content checksum; one that does not parse, decode or fit is not read. Versions 1
(no token) and 2 (no lineage) of the status snapshot, both of 2026-12-07, are still read: as a
status, and as a status and token. A local output keeps none: its chunk files are read directly
(0.4 s for 20,000 frames' status).
"""

from __future__ import annotations

import asyncio
import secrets
from dataclasses import dataclass
from typing import Any

import numcodecs
import numpy as np
from zarr.core.buffer import default_buffer_prototype

STATUS_SNAPSHOT = "status_snapshot"
"""The key of an output's status snapshot, beside its arrays."""
COLUMN_PREFIX = "column_snapshot."
"""Column snapshot keys: this and the array's name."""
COLUMN_FRAME_BYTES_MAX = 4096
"""Largest per-frame value (bytes) of an array kept as a column snapshot: evaluate's metrics of a
frame are about 2 kB; calibrate's labels, images and every ragged array stay in their chunks."""

LINEAGE_MAX = 16
"""Status snapshots before the present one that it keeps the tokens of (and each frame's age in
them): a column snapshot read under one of them is brought up to date from the frames written
since; one older is read again from every chunk."""
OLDER = 255
"""A frame's age in a status snapshot's lineage when it was last written before its oldest ancestor."""

_STATUS_HEADER = b"radarsim status snapshot "
_COLUMN_HEADER = b"radarsim column snapshot 1 "
_CODEC = numcodecs.Zstd(level=0, checksum=True)


def new_token() -> str:
    """A token no other status snapshot has (64 random bits)."""
    return secrets.token_hex(8)


@dataclass(frozen=True, eq=False)
class StatusSnapshot:
    """A remote output's status as a status snapshot holds it, with its token and lineage."""

    status: np.ndarray
    """(F,) uint8 status codes."""
    token: str | None
    """None for version 1, which is read as a status only."""
    ancestors: tuple[str, ...] = ()
    """The tokens of the snapshots it succeeds, newest first (at most LINEAGE_MAX)."""
    age: np.ndarray | None = None
    """(F,) uint8: ``age[i] = d`` (1 <= d <= len(ancestors)): frame i was last written or marked
    after snapshot ``ancestors[d - 1]`` and before the one after it; OLDER: before the oldest, or
    unknown. None (version 2): OLDER for every frame."""

    def written_since(self, token: str) -> np.ndarray | None:
        """The frames (sorted indices) whose chunks may have been written since status snapshot
        ``token`` was the output's: none for this one's own token; None when ``token`` is neither
        it nor one of its ancestors (then any frame may have been)."""
        if self.token is not None and token == self.token:
            return np.empty(0, np.int64)
        if token not in self.ancestors or self.age is None:
            return None
        return np.flatnonzero(self.age <= self.ancestors.index(token) + 1)

    def successor(self, status: np.ndarray, changed: np.ndarray) -> StatusSnapshot:
        """The snapshot of ``status`` (F,) written after this one, with a new token, when frames
        ``changed`` ((F,) bool) were written or marked since it was the output's and nothing else
        was; without a lineage when this one has no token."""
        if self.token is None:
            return fresh_status(status)
        ancestors = (self.token, *self.ancestors)[:LINEAGE_MAX]
        age = np.full(len(status), OLDER, np.uint8) if self.age is None else self.age.astype(np.int64) + 1
        age = np.where((age > len(ancestors)) | (age >= OLDER), OLDER, age).astype(np.uint8)
        age[np.asarray(changed, bool)] = 1
        return StatusSnapshot(np.asarray(status, np.uint8), new_token(), ancestors, age)

    def encode(self) -> bytes:
        """The status snapshot's object (version 3)."""
        status = np.ascontiguousarray(self.status, np.uint8).reshape(-1)
        age = np.full(len(status), OLDER, np.uint8) if self.age is None else np.asarray(self.age, np.uint8)
        head = f"3 {len(status)} {self.token} {','.join(self.ancestors) or '-'}\n".encode()
        return _STATUS_HEADER + head + _CODEC.encode(status.tobytes() + age.tobytes())


def fresh_status(status: np.ndarray) -> StatusSnapshot:
    """A status snapshot of ``status`` (F,) with a new token and no lineage."""
    return StatusSnapshot(np.asarray(status, np.uint8).reshape(-1), new_token())


def decode_status(data: bytes | None, frames: int, codes: Any) -> StatusSnapshot | None:
    """The status snapshot in bytes ``data``; None when there are none or they do not hold one of
    ``codes`` per frame (and, version 3, a lineage that fits it)."""
    if not data:
        return None
    head, _, body = data.partition(b"\n")
    if not head.startswith(_STATUS_HEADER):
        return None
    version, *fields = head[len(_STATUS_HEADER):].decode("ascii", "replace").split(" ")
    if not fields or fields[0] != str(frames) or len(fields) != {"1": 1, "2": 2, "3": 3}.get(version):
        return None
    token = fields[1] if version != "1" else None
    ancestors = tuple(fields[2].split(",")) if version == "3" and fields[2] != "-" else ()
    if token == "" or "" in ancestors or len(ancestors) > LINEAGE_MAX:
        return None
    try:
        raw = np.frombuffer(_CODEC.decode(body), np.uint8)
    except (RuntimeError, ValueError):  # truncated, or not zstd: numcodecs raises RuntimeError
        return None
    if len(raw) != (2 if version == "3" else 1) * frames:
        return None
    status, age = raw[:frames].copy(), (raw[frames:].copy() if version == "3" else None)
    if not np.isin(status, list(codes)).all():
        return None
    if age is not None and (((age < 1) | (age > len(ancestors))) & (age != OLDER)).any():
        return None
    return StatusSnapshot(status, token, ancestors, age)


def column_key(name: str) -> str:
    """The key of array ``name``'s column snapshot."""
    return COLUMN_PREFIX + name


def column_eligible(dtype: Any, frame_shape: tuple[int, ...]) -> bool:
    """Whether an array of ``dtype`` and per-frame shape ``frame_shape`` is kept as a column
    snapshot: numbers or booleans of at most COLUMN_FRAME_BYTES_MAX bytes a frame."""
    dtype = np.dtype(dtype)
    return dtype.kind in "biuf" and dtype.itemsize * int(np.prod(frame_shape, dtype=np.int64)) <= COLUMN_FRAME_BYTES_MAX


def encode_column(values: np.ndarray, token: str) -> bytes:
    """The object of column snapshot ``values`` (F, ...) read under status snapshot ``token``."""
    values = np.ascontiguousarray(values)
    shape = ",".join(str(d) for d in values.shape)
    return _COLUMN_HEADER + f"{token} {values.dtype.str} {shape}\n".encode() + _CODEC.encode(values.tobytes())


def decode_column(data: bytes | None, dtype: Any, shape: tuple[int, ...]) -> tuple[np.ndarray, str] | None:
    """(the values (``shape``, frames first), the token of the status snapshot they were read under)
    of a column snapshot's bytes ``data`` when it holds ``dtype`` in that shape; else None."""
    if not data:
        return None
    head, _, body = data.partition(b"\n")
    dtype = np.dtype(dtype)
    token, _, rest = head[len(_COLUMN_HEADER):].partition(b" ")
    if not head.startswith(_COLUMN_HEADER) or not token or \
            rest != f"{dtype.str} {','.join(str(d) for d in shape)}".encode():
        return None
    try:
        raw = _CODEC.decode(body)
    except (RuntimeError, ValueError):
        return None
    if len(raw) != dtype.itemsize * int(np.prod(shape, dtype=np.int64)):
        return None
    return np.frombuffer(raw, dtype).reshape(shape).copy(), token.decode("ascii", "replace")


async def get_objects(store: Any, keys: list[str]) -> list[bytes | None]:
    """The bytes of objects ``keys`` of zarr store ``store``, read concurrently; None for one that
    is not there or cannot be read (its reader then reads the chunks, whose read names the problem)."""
    got = await asyncio.gather(*(store.get(key, default_buffer_prototype()) for key in keys),
                               return_exceptions=True)
    for g in got:
        if isinstance(g, BaseException) and not isinstance(g, (OSError, ValueError)):
            raise g
    return [None if g is None or isinstance(g, BaseException) else g.to_bytes() for g in got]


async def put_object(store: Any, key: str, data: bytes) -> None:
    """Write object ``key`` of zarr store ``store``."""
    await store.set(key, default_buffer_prototype().buffer.from_bytes(data))
