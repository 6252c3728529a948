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
  when it was read (the frames the status snapshot holds as done, at least); one with another
  token is not read, and the next whole read replaces it. A reader that cannot write (read-only
  credentials) reads the chunks each time, as before.

Each object is a header line, ``radarsim status snapshot 2 <frames> <token>`` or ``radarsim
column snapshot 1 <token> <dtype> <frames>,<shape...>``, then the values in C order compressed by
zstd with its content checksum; one that does not parse, decode or fit is not read. Version 1 of
the status snapshot (2026-12-07, no token) is still read as a status, never as a token. A local
output keeps none: its chunk files are read directly (0.4 s for 20,000 frames' status).
"""

from __future__ import annotations

import asyncio
import secrets
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

_STATUS_HEADER = b"radarsim status snapshot "
_COLUMN_HEADER = b"radarsim column snapshot 1 "
_CODEC = numcodecs.Zstd(level=0, checksum=True)


def new_token() -> str:
    """A token no other status snapshot has (64 random bits)."""
    return secrets.token_hex(8)


def encode_status(status: np.ndarray, token: str) -> bytes:
    """The object of status snapshot ``status`` (F,) uint8 with ``token``."""
    status = np.ascontiguousarray(status, np.uint8).reshape(-1)
    return _STATUS_HEADER + f"2 {len(status)} {token}\n".encode() + _CODEC.encode(status.tobytes())


def decode_status(data: bytes | None, frames: int, codes: Any) -> tuple[np.ndarray, str | None] | None:
    """(status (``frames``,) uint8, its token or None for version 1) from a status snapshot's bytes
    ``data``; None when there are none or they do not hold one of ``codes`` per frame."""
    if not data:
        return None
    head, _, body = data.partition(b"\n")
    if not head.startswith(_STATUS_HEADER):
        return None
    fields = head[len(_STATUS_HEADER):].split(b" ")
    if fields[0] == b"1" and len(fields) == 2:
        token = None
    elif fields[0] == b"2" and len(fields) == 3 and fields[2]:
        token = fields[2].decode("ascii", "replace")
    else:
        return None
    if fields[1] != str(frames).encode():
        return None
    try:
        status = np.frombuffer(_CODEC.decode(body), np.uint8)
    except (RuntimeError, ValueError):  # truncated, or not zstd: numcodecs raises RuntimeError
        return None
    if len(status) != frames or not np.isin(status, list(codes)).all():
        return None
    return status.copy(), token


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


def decode_column(data: bytes | None, token: str, dtype: Any, shape: tuple[int, ...]) -> np.ndarray | None:
    """The values (``shape``, frames first) of a column snapshot's bytes ``data`` when it was
    read under status snapshot ``token`` and holds ``dtype`` in that shape; else None."""
    if not data:
        return None
    head, _, body = data.partition(b"\n")
    dtype = np.dtype(dtype)
    want = f"{token} {dtype.str} {','.join(str(d) for d in shape)}".encode()
    if not head.startswith(_COLUMN_HEADER) or head[len(_COLUMN_HEADER):] != want:
        return None
    try:
        raw = _CODEC.decode(body)
    except (RuntimeError, ValueError):
        return None
    if len(raw) != dtype.itemsize * int(np.prod(shape, dtype=np.int64)):
        return None
    return np.frombuffer(raw, dtype).reshape(shape).copy()


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
