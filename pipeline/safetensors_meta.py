"""The metadata of a safetensors file, read from any binary file object without torch (a remote
cache's fsspec file included: only the header's bytes are read).

The format (https://huggingface.co/docs/safetensors): an 8-byte little-endian header length, then
that many bytes of JSON whose ``"__metadata__"`` maps strings to strings. safetensors' own readers
take a local path only; pipeline.checkpoint keeps its training state there under ``"meta"``.
"""

from __future__ import annotations

import json
from typing import BinaryIO

MAX_HEADER_BYTES = 100_000_000
"""safetensors' own limit on the header."""


def read_metadata(fh: BinaryIO) -> dict[str, str]:
    """The ``__metadata__`` of the safetensors file open in ``fh`` (at its start); {} where it has
    none. ValueError where the header is cut short, too long or not a JSON object."""
    head = fh.read(8)
    if len(head) != 8:
        raise ValueError("shorter than a safetensors header (8 bytes)")
    size = int.from_bytes(head, "little")
    if size > MAX_HEADER_BYTES:
        raise ValueError(f"header of {size} bytes (safetensors allows {MAX_HEADER_BYTES})")
    text = fh.read(size)
    if len(text) != size:
        raise ValueError(f"header cut short: {len(text)} of {size} bytes")
    header = json.loads(text)
    meta = header.get("__metadata__") if isinstance(header, dict) else None
    if not isinstance(header, dict) or not isinstance(meta, (dict, type(None))):
        raise ValueError("header is not a safetensors JSON object")
    return dict(meta or {})
