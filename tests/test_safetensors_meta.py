"""pipeline.safetensors_meta: a safetensors file's metadata from a file object, without torch."""

from __future__ import annotations

import io
import json

import fsspec
import numpy as np
import pytest
from safetensors import safe_open
from safetensors.numpy import save, save_file

from pipeline.safetensors_meta import read_metadata


def test_metadata_is_what_safetensors_reads(tmp_path):
    path = tmp_path / "a.safetensors"
    meta = {"meta": json.dumps({"epoch": 3, "curves": [{"loss": 0.5}] * 50}), "other": "x"}
    save_file({"w": np.arange(12, dtype=np.float32).reshape(3, 4), "b": np.zeros(7, np.int64)}, str(path), metadata=meta)
    with safe_open(str(path), framework="numpy") as f:
        expected = f.metadata()
    with open(path, "rb") as fh:
        assert read_metadata(fh) == expected == meta
    fs = fsspec.filesystem("memory")  # a remote file read in small blocks
    fs.pipe("/meta-test/a.safetensors", path.read_bytes())
    with fs.open("/meta-test/a.safetensors", "rb", block_size=64) as fh:
        assert read_metadata(fh) == meta
    fs.rm("/meta-test", recursive=True)


def test_a_file_without_metadata_has_none():
    assert read_metadata(io.BytesIO(save({"w": np.ones(3, np.float32)}))) == {}


@pytest.mark.parametrize("cut", [0, 3, 8, 20])
def test_a_header_cut_short_is_a_value_error(cut):
    data = save({"w": np.ones(3, np.float32)}, metadata={"meta": "{}"})
    with pytest.raises(ValueError, match="short"):
        read_metadata(io.BytesIO(data[:cut]))


def test_a_header_of_another_format_is_a_value_error():
    for header in (b"[1, 2]", b'{"__metadata__": [1]}'):
        with pytest.raises(ValueError, match="not a safetensors"):
            read_metadata(io.BytesIO(len(header).to_bytes(8, "little") + header))
    with pytest.raises(ValueError, match="allows"):
        read_metadata(io.BytesIO((1 << 40).to_bytes(8, "little")))
    with pytest.raises(ValueError):  # json.JSONDecodeError is a ValueError
        read_metadata(io.BytesIO((4).to_bytes(8, "little") + b"{{{{"))
