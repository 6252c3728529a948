"""Damaged cache chunks: a chunk file truncated, overwritten with garbage, emptied, bit-flipped or
deleted fails the frame that reads it with a reason naming the array, the frame, the file and
how to recompute it; the other frames finish. A damaged status chunk, and the dataset-level read
paths (`pipeline status`), give one line naming the file. Small pipelines of tests/fake_stages.py.
"""

from __future__ import annotations

import json
import pickle
import re
import struct
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import pipeline.cli as cli
from pipeline.cache import DONE, EVERY_CHUNK, EXCLUDED, FAILED, PENDING, FrameStore
from pipeline.config import load_config
from pipeline.errors import CacheError, ChunkError, MetadataError
from pipeline.executor import Executor, RunEnv
from pipeline.inspection import cache_status, verify_cache
from pipeline.runner import Pipeline
from tests import fake_stages

IDS = [f"f{i:03d}" for i in range(8)]


def _flip_middle_bit(data: bytes) -> bytes:
    mid = len(data) // 2
    return data[:mid] + bytes([data[mid] ^ 0x10]) + data[mid + 1:]


DAMAGES = {
    "truncated": lambda data: data[: len(data) // 2],
    "random bytes": lambda data: np.random.default_rng(0).bytes(len(data)),
    "empty": lambda data: b"",
    "one bit flipped": _flip_middle_bit,  # still a zstd frame: caught by the checksum only
}


def _pipe(tmp_path: Path, name: str = "cache") -> Pipeline:
    cfg = load_config("synthetic", {}, environ={})
    env = RunEnv(cfg=cfg, cache_root=str(tmp_path / name), dataset="fake", data_root=str(tmp_path))
    return Pipeline(fake_stages.STAGES, env, Executor(1), progress=False, log=lambda m: None,
                    frame_lister=lambda: list(IDS))


def _chunk(pipe: Pipeline, stage: str, key: str) -> Path:
    return Path(pipe.env.cache_root) / "fake" / f"{stage}.zarr" / key


def _damage(path: Path, how: str) -> None:
    path.write_bytes(DAMAGES[how](path.read_bytes()))


@pytest.mark.parametrize("how", list(DAMAGES))
def test_damaged_upstream_chunk_fails_only_its_frame_naming_array_frame_and_file(tmp_path, how):
    pipe = _pipe(tmp_path)
    pipe.run("calibrate")
    chunk = _chunk(pipe, "calibrate", "points/c/3/0/0")
    _damage(chunk, how)
    report = pipe.run("heatmaps")[-1]
    heat = pipe.env.store("heatmaps")
    status = heat.status()
    assert status[3] == FAILED and report.failed == 1
    assert (np.delete(status, 3) == DONE).all()  # frames 0 (value = fill 0), 5 and 7 (no points) included
    reason = heat.reasons()[3]
    assert reason.startswith("stage heatmaps, frame f003: calibrate.zarr/points, frame 3 (f003): ")
    assert f"chunk {chunk} cannot be decoded (RuntimeError: Zstd decompression error" in reason
    assert "internal error" not in reason and "\n" not in reason
    if how == "one bit flipped":
        assert "doesn't match checksum" in reason
    assert reason.endswith(f"recompute the frame with `pipeline run calibrate --dataset fake --cache {tmp_path / 'cache'} "
                           f"--force --frames f003` (the frames made from it are recomputed too)")


def _follow(pipe: Pipeline, message: str) -> None:
    """Run the `pipeline run STAGE --force --frames ID` that a ChunkError's message gives."""
    from pipeline.frame_selection import parse_frames

    stage, frame = re.search(r"`pipeline run (\S+) --dataset fake --cache \S+ --force --frames (\S+)`", message).groups()
    pipe.run(stage, frames=parse_frames(frame, pipe.frame_ids()), force=True)


def test_following_the_message_recomputes_the_frame(tmp_path, monkeypatch):
    """The command the reason gives recomputes the damaged frame in place, and the frame of the
    stage that failed on it runs again without --retry-failed (once each); the result equals a
    run that was never damaged."""
    calls = tmp_path / "calls.log"
    monkeypatch.setenv(fake_stages.CALLS_FILE_ENV, str(calls))
    pipe = _pipe(tmp_path)
    pipe.run("calibrate")
    _damage(_chunk(pipe, "calibrate", "points/c/3/0/0"), "truncated")
    pipe.run("heatmaps")
    calls.write_text("")
    _follow(pipe, pipe.env.store("heatmaps").reasons()[3])
    assert pipe.env.store("heatmaps").status()[3] == PENDING  # made from the damaged frame: to redo
    pipe.run("heatmaps")
    assert calls.read_text().split("\n")[:-1] == ["calibrate f003", "heatmaps f003"]
    monkeypatch.delenv(fake_stages.CALLS_FILE_ENV)
    ref = _pipe(tmp_path, "ref")
    ref.run("heatmaps")
    for stage, name in (("calibrate", "points"), ("heatmaps", "total")):
        np.testing.assert_array_equal(pipe.env.store(stage).read(name, 3), ref.env.store(stage).read(name, 3))
    assert (pipe.env.store("heatmaps").status() == DONE).all()


def test_missing_chunk_of_a_done_frame_is_an_error_not_the_fill_value(tmp_path):
    pipe = _pipe(tmp_path)
    pipe.run("calibrate")
    calib = pipe.env.store("calibrate")
    assert calib.read("value", 0) == 0.0  # equal to the fill value, yet written: not taken as missing
    assert calib.read("points", 5).shape == (0, 3)  # no rows (an all-NaN chunk, a count of 0)
    _chunk(pipe, "calibrate", "value/c/2").unlink()
    _chunk(pipe, "calibrate", "points_count/c/6").unlink()
    pipe.run("heatmaps")
    reasons = pipe.env.store("heatmaps").reasons()
    assert sorted(reasons) == [2, 6]
    assert "calibrate.zarr/value, frame 2 (f002): chunk " in reasons[2]
    assert "calibrate.zarr/points_count, frame 6 (f006): chunk " in reasons[6]
    for i in (2, 6):
        assert "is missing although the frame is done" in reasons[i] and "--force --frames" in reasons[i]


def test_missing_chunk_reads_as_fill_value_in_an_output_without_the_marker(tmp_path):
    """Outputs created before every chunk was written (no EVERY_CHUNK attribute) cannot tell a
    deleted chunk from a fill value: zarr reads the fill value, as it always did."""
    pipe = _pipe(tmp_path)
    pipe.run("calibrate")
    calib = pipe.env.store("calibrate")
    calib._group("r+").attrs.pop(EVERY_CHUNK)  # zarr's Attributes: removes the key from zarr.json
    assert EVERY_CHUNK not in calib.attrs()
    _chunk(pipe, "calibrate", "value/c/2").unlink()
    assert calib.read("value", 2) == 0.0


@pytest.mark.parametrize("writer", ["chunk files", "zarr"])
def test_an_array_of_no_elements_per_frame_has_no_chunk_to_miss(tmp_path, monkeypatch, writer):
    """zarr writes no chunk for a frame of an array with a zero-length dimension (a remote cache,
    or an output zarr wrote): reading and verifying such a frame is no damage."""
    from pipeline.stage import ArraySpec
    if writer == "zarr":
        monkeypatch.setattr(FrameStore, "_write_chunk_files", lambda self, *args: False)
    specs = (ArraySpec("empty", (0, 3), "float32", "m", fill=np.nan, ragged=True),
             ArraySpec("value", (2,), "float32", "m"))
    store = FrameStore(str(tmp_path / "out.zarr"))
    store.create("fp", ["a", "b"], specs, {"empty": (0, 3), "value": (2,)}, {})
    for i in range(2):
        store.write_frame(i, {"empty": np.zeros((0, 3), np.float32), "value": np.full(2, i, np.float32)}, specs)
    assert store.read("empty", 1).shape == (0, 3)
    status, errors = store.verify()
    assert status.tolist() == [DONE, DONE] and errors == {}
    (tmp_path / "out.zarr" / "value" / "c" / "1" / "0").unlink()  # a real chunk missing is still found
    assert sorted(store.verify()[1]) == [1]


def test_whole_array_reads_name_the_first_damaged_frame(tmp_path):
    """FrameStore.array (what dataset stages index) raises ChunkError for the frames it reads."""
    pipe = _pipe(tmp_path)
    pipe.run("calibrate")
    calib = pipe.env.store("calibrate")
    _damage(_chunk(pipe, "calibrate", "points/c/4/0/0"), "random bytes")
    _damage(_chunk(pipe, "calibrate", "points/c/6/0/0"), "random bytes")
    points = calib.array("points")
    assert points.shape == (8, 8, 3) and np.asarray(points.oindex[[0, 1, 7]]).shape == (3, 8, 3)
    for read in (lambda: points[:], lambda: points[3:], lambda: points.oindex[[6, 4]], lambda: points[4, :2],
                 lambda: np.asarray(points)):
        with pytest.raises(ChunkError, match=r"^calibrate\.zarr/points, frame 4 \(f004\): chunk .*points/c/4/0/0 "):
            read()
    with pytest.raises(ChunkError, match="frame 6 "):
        points.oindex[[5, 6]]
    again = pickle.loads(pickle.dumps(points))  # like a zarr array, it travels to dask workers
    assert np.asarray(again[0]).shape == (8, 3)
    np.testing.assert_array_equal(np.asarray(calib.array("value")), np.arange(8.0))


def test_whole_frame_reads_come_from_the_chunk_files_and_equal_zarrs(tmp_path):
    """Reads of whole frames (``[:]``, ``[...]``, ``oindex`` by indices or a mask) of a local output
    come from its chunk files: the values, dtypes and shapes zarr reads, fill values where a frame
    was never written."""
    import zarr

    from pipeline.zarr_io import frames_from_chunk_files

    pipe = _pipe(tmp_path)
    pipe.run("calibrate", frames=[0, 2, 3, 5, 6, 7])
    calib = pipe.env.store("calibrate")
    mask = np.array([True, False, True, True, False, False, True, False])
    for name in ("points", "points_count", "value", "status"):
        raw = zarr.open_group(calib.url, mode="r")[name]
        assert frames_from_chunk_files(raw) is not None  # the files were read, not zarr
        checked = calib.array(name)
        for got, want in ((checked[:], raw[:]), (checked[...], raw[...]), (np.asarray(checked), raw[:]),
                          (checked.oindex[[7, 1, 3]], raw.oindex[[7, 1, 3]]), (checked.oindex[mask], raw.oindex[mask]),
                          (checked.oindex[np.array([], int)], raw.oindex[np.array([], int)])):
            assert got.dtype == want.dtype and got.shape == want.shape, name
            np.testing.assert_array_equal(got, want, err_msg=name)
    assert np.isnan(calib.array("points")[1]).all() and np.isnan(calib.array("points").oindex[[4]]).all()


def test_frame_reads_and_writes_reuse_opened_arrays_until_their_metadata_changes(tmp_path):
    """FrameStore.read takes a local output's frame from its chunk files, with the arrays opened
    once per process, and write_frame reuses the arrays it opened: the values zarr reads. An output
    re-created under the same names with other arrays (dtype, capacity, fill) is read and written
    as it now is."""
    import zarr

    from pipeline.stage import ArraySpec

    pipe = _pipe(tmp_path)
    pipe.run("calibrate", frames=[0, 1, 2, 4, 5, 6, 7])
    calib = pipe.env.store("calibrate")
    raw = zarr.open_group(calib.url, mode="r")
    for i in range(8):
        for name in ("points", "value", "status"):
            want = np.asarray(raw[name][i])
            if name == "points":
                want = want[:int(raw["points_count"][i])]
            got = calib.read(name, i)
            assert got.dtype == want.dtype and got.shape == want.shape, (name, i)
            np.testing.assert_array_equal(got, want)
    assert calib._read_chunk_files("points", 5) is not None  # from the files, not zarr
    assert calib._read_chunk_files("points", 3) is None  # never written: zarr's path decides
    specs = (ArraySpec("points", (4, 2), "int16", "-", fill=-1, ragged=True), ArraySpec("value", (), "float32", "-"))
    calib.create("other", IDS, specs, {"points": (4, 2), "value": ()}, {})
    calib.write_frame(1, {"points": np.arange(6, dtype=np.int16).reshape(3, 2), "value": np.float32(2.5)}, specs)
    raw = zarr.open_group(calib.url, mode="r")
    assert raw["points"].dtype == np.int16 and raw["points"].shape == (8, 4, 2) and int(raw["points_count"][1]) == 3
    np.testing.assert_array_equal(raw["points"][1], [[0, 1], [2, 3], [4, 5], [-1, -1]])
    got = calib.read("points", 1)
    assert got.dtype == np.int16 and got.shape == (3, 2)
    np.testing.assert_array_equal(got, np.arange(6).reshape(3, 2))
    value = calib.read("value", 1)
    assert value.dtype == np.float32 and value.shape == () and value == 2.5


def test_frames_are_written_to_their_chunk_files_as_zarr_writes_them(tmp_path, monkeypatch):
    """write_frame, mark and mark_many write a local output's chunk files themselves, strings too:
    the files zarr writes, to the byte, the status last, a failed frame's reason cleared; a row of
    the wrong shape or a frame outside the output is still zarr's error, and nothing of it is written."""
    from pipeline import cache
    from pipeline.stage import ArraySpec

    put, original_put = [], cache.put_chunk
    monkeypatch.setattr(cache, "put_chunk", lambda path, data: (put.append(Path(path)), original_put(path, data)))
    specs = (ArraySpec("points", (4, 2), "float32", "m", fill=np.nan, ragged=True),
             ArraySpec("value", (), "int64", "-"), ArraySpec("name", (), "str", "-", fill=""))
    store = FrameStore(str(tmp_path / "s.zarr"))
    store.create("fp", IDS, specs, {"points": (4, 2), "value": (), "name": ()}, {})
    frame = {"points": np.arange(6.0).reshape(3, 2), "value": np.int64(7), "name": np.asarray("seq-ü 1", dtype=object)}
    store.mark(1, FAILED, "cannot read lidar/\udcff.bin")  # a file name that is no UTF-8
    assert store.reasons() == {1: "cannot read lidar/\\udcff.bin"}
    put.clear()
    store.mark(1, FAILED, "lidar truncated")
    assert [p.relative_to(store.url).as_posix() for p in put] == ["reason/c/1", "status/c/1"]
    assert store.reasons() == {1: "lidar truncated"}
    store.mark_many(np.array([5, 3]), EXCLUDED, "upstream failed")
    store.write_frame(1, frame, specs)
    assert [p.relative_to(store.url).as_posix() for p in put[2:]] == [
        "reason/c/3", "status/c/3", "reason/c/5", "status/c/5",
        "points_count/c/1", "points/c/1/0/0", "value/c/1", "name/c/1", "reason/c/1", "status/c/1"]
    assert store.status()[1] == DONE and store.reasons() == {} and store.read("value", 1) == 7
    assert store.read("name", 1) == "seq-ü 1" and list(store.status()[[3, 5]]) == [EXCLUDED, EXCLUDED]
    assert store._read_chunk_files("name", 1) == "seq-ü 1"  # from the file, not zarr
    np.testing.assert_array_equal(store.read("points", 1), frame["points"])
    assert not list(Path(store.url).rglob("*.partial"))
    direct = {p: p.read_bytes() for p in put}
    monkeypatch.setattr(FrameStore, "_write_chunk_files", lambda self, *args: False)
    store.mark_many(np.array([5, 3]), EXCLUDED, "upstream failed")  # through zarr: the same files
    store.write_frame(1, frame, specs)
    assert {p: p.read_bytes() for p in put} == direct
    store.mark(1, FAILED, "lidar truncated")
    failed = _chunk_files(store)
    monkeypatch.undo()
    store.write_frame(1, frame, specs)
    store.mark(1, FAILED, "lidar truncated")
    assert _chunk_files(store) == failed
    put.clear()
    monkeypatch.setattr(cache, "put_chunk", lambda path, data: (put.append(Path(path)), original_put(path, data)))
    with pytest.raises(ValueError, match="broadcast"):
        store.write_frame(2, {**frame, "points": np.zeros((5, 2))}, specs)  # 5 rows, capacity 4
    with pytest.raises(IndexError):
        store.mark(len(IDS), FAILED, "no such frame")
    assert put == []

    def disk_full(path, data):
        put.append(Path(path))
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(cache, "put_chunk", disk_full)
    with pytest.raises(CacheError, match="writing frame 2"):
        store.write_frame(2, frame, specs)
    assert len(put) == 1 and store.status()[2] == PENDING  # the first chunk failed; not marked done
    with pytest.raises(CacheError, match="recording frame 2"):
        store.mark(2, FAILED, "x")


def _chunk_files(store: FrameStore) -> dict[str, bytes]:
    return {p.relative_to(store.url).as_posix(): p.read_bytes()
            for p in sorted(Path(store.url).rglob("c/*")) if p.is_file()}


def test_frame_ids_are_an_array_not_the_group_metadata_which_every_open_parses(tmp_path):
    """An output's frame ids are an array of their own (one chunk), not in the group's zarr.json
    that every read and write of a frame parses (0.8 MB at 50,000 frames); an output that has them
    in its attributes (created before 2026-12-04) still reads them there; a damaged one is named,
    and is no frame's damage for verify."""
    import shutil

    import zarr

    pipe = _pipe(tmp_path)
    pipe.run("calibrate")
    calib = pipe.env.store("calibrate")
    group = zarr.open_group(calib.url, mode="r+")
    assert list(group["frame_ids"][:]) == IDS and group["frame_ids"].nchunks == 1 and calib.frame_ids() == IDS
    assert "frame_ids" not in group.attrs and len((Path(calib.url) / "zarr.json").read_text()) < 2000
    assert not verify_cache(pipe, ["calibrate"])[0]["damaged"]
    chunk = _chunk(pipe, "calibrate", "frame_ids/c/0")
    saved = chunk.read_bytes()
    chunk.unlink()  # zarr would read the fill value, '', for every id
    with pytest.raises(MetadataError, match=r"calibrate.zarr/frame_ids: the frame ids of stage output calibrate "
                                            r"has empty ids \(its chunk is missing\)"):
        calib.frame_ids()
    chunk.write_bytes(saved)
    meta = Path(calib.url) / "frame_ids" / "zarr.json"
    text = meta.read_text()
    meta.write_text(text[: len(text) // 2])
    with pytest.raises(MetadataError, match=r"frame_ids: the frame ids of stage output calibrate cannot be read "
                                            r"\(JSONDecodeError"):
        calib.frame_ids()
    _damage(_chunk(pipe, "calibrate", "value/c/2"), "random bytes")  # another chunk's error stays its own
    with pytest.raises(ChunkError, match=r"calibrate.zarr/value, frame 2: chunk .*value/c/2 cannot be decoded"):
        calib.read("value", 2)
    meta.write_text(text)
    _damage(chunk, "random bytes")
    with pytest.raises(MetadataError, match=r"calibrate.zarr/frame_ids: the frame ids of stage output calibrate "
                                            r"cannot be read \(.*\); recompute the stage"):
        calib.frame_ids()
    shutil.rmtree(Path(calib.url) / "frame_ids")  # an output of the earlier layout
    group.attrs["frame_ids"] = IDS
    assert calib.frame_ids() == IDS
    assert [r.processed for r in pipe.run("heatmaps")] == [0, len(IDS)]
    del group.attrs["frame_ids"]
    with pytest.raises(MetadataError, match=r"calibrate.zarr/frame_ids: the frame ids of stage output calibrate "
                                            r"is missing; recompute the stage"):
        calib.frame_ids()


def test_damaged_chunk_read_by_a_dataset_stage_stops_it_with_the_chunk_named(tmp_path):
    pipe = _pipe(tmp_path)
    pipe.run("heatmaps")
    _damage(_chunk(pipe, "heatmaps", "total/c/5"), "empty")
    with pytest.raises(ChunkError, match=r"^heatmaps\.zarr/total, frame 5 \(f005\): chunk "):
        pipe.run("train")


def test_damaged_status_chunk_stops_the_run_naming_the_file(tmp_path):
    pipe = _pipe(tmp_path)
    pipe.run("calibrate")
    chunk = _chunk(pipe, "calibrate", "status/c/3")
    _damage(chunk, "random bytes")
    with pytest.raises(ChunkError) as info:
        pipe.run("heatmaps")
    message = str(info.value)
    assert message.startswith(f"calibrate.zarr/status, frame 3 (f003): chunk {chunk} cannot be decoded (")
    assert message.endswith(f"`pipeline run calibrate --dataset fake --cache {tmp_path / 'cache'} --force --frames "
                            f"f003` (the frames made from it are recomputed too)")
    assert not pipe.env.store("heatmaps").exists()  # stopped before any downstream output
    _follow(pipe, message)
    pipe.run("heatmaps")
    assert (pipe.env.store("heatmaps").status() == DONE).all()


@pytest.mark.parametrize("how", list(DAMAGES))
def test_status_read_from_its_chunk_files_is_zarrs_and_a_damaged_chunk_is_left_to_zarr(tmp_path, how):
    """A local output's status is read from its chunk files, not through zarr (which spends about
    0.3 ms per chunk: 7 s for 20,000 frames): the codes zarr reads, a deleted or never written chunk
    pending; a damaged chunk is read by zarr, which names it."""
    import zarr

    from pipeline.cache import EXCLUDED
    from pipeline.zarr_io import frames_from_chunk_files

    pipe = _pipe(tmp_path)
    pipe.run("calibrate", frames=[0, 1, 2, 3, 4, 5])
    store = pipe.env.store("calibrate")
    store.mark(1, PENDING)
    store.mark(4, FAILED, "a reason")
    store.mark(5, EXCLUDED, "another")
    _chunk(pipe, "calibrate", "status/c/2").unlink()
    arr = zarr.open_array(f"{store.url}/status", mode="r")
    direct = frames_from_chunk_files(arr)
    assert direct is not None and direct.dtype == np.uint8
    assert list(direct) == [DONE, PENDING, PENDING, DONE, FAILED, EXCLUDED, PENDING, PENDING]
    np.testing.assert_array_equal(direct, arr[:])
    np.testing.assert_array_equal(store.status(), direct)
    _damage(_chunk(pipe, "calibrate", "status/c/3"), how)
    assert frames_from_chunk_files(arr) is None
    with pytest.raises(ChunkError, match=r"calibrate.zarr/status, frame 3 \(f003\): chunk .* cannot be decoded"):
        store.status()
    # a zstd header claiming 64 TiB: numcodecs raises MemoryError, which must not escape either
    huge = struct.pack("<I", 0xFD2FB528) + bytes([0xE0]) + struct.pack("<Q", 2 ** 46) + bytes([1, 0, 0])
    _chunk(pipe, "calibrate", "status/c/3").write_bytes(huge)
    assert frames_from_chunk_files(arr) is None
    with pytest.raises(ChunkError, match=r"calibrate.zarr/status, frame 3 \(f003\): chunk .* cannot be decoded"):
        store.status()


_READ_STATUS = """
import sys
from pipeline.cache import FrameStore
from pipeline.errors import ChunkError
try:
    FrameStore(sys.argv[1]).status()
except ChunkError as exc:
    print(exc.frame)
"""


def test_a_damaged_chunk_read_through_zarr_leaves_no_reads_running_at_exit(tmp_path):
    """zarr reads an array's chunks concurrently and raises at the first damaged one while the
    others still run; the process then ended with hundreds of 'Task was destroyed but it is
    pending!' lines after the one-line error (in about half the runs: timing)."""
    import subprocess
    import sys

    from pipeline.stage import ArraySpec
    specs = (ArraySpec("value", (2,), "float32", "m"),)
    store = FrameStore(str(tmp_path / "out.zarr"))
    store.create("fp", [f"f{i}" for i in range(2000)], specs, {"value": (2,)}, {})
    store.mark_many(np.arange(2000), EXCLUDED, "not selected")
    (tmp_path / "out.zarr" / "status" / "c" / "0").write_bytes(b"garbage")  # zarr's path, failing early
    runs = [subprocess.Popen([sys.executable, "-c", _READ_STATUS, str(tmp_path / "out.zarr")], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, cwd=Path(__file__).parents[1])
            for _ in range(5)]  # at once: each process spends most of its 3 s importing
    for run in runs:
        stdout, stderr = run.communicate(timeout=120)
        assert stdout == "f0\n" and stderr == "", stderr[-2000:]


def test_damaged_reason_chunk_gives_a_reason_saying_so(tmp_path):
    pipe = _pipe(tmp_path)
    pipe.run("calibrate")
    _damage(_chunk(pipe, "calibrate", "points/c/3/0/0"), "truncated")
    pipe.run("heatmaps")
    chunk = _chunk(pipe, "heatmaps", "reason/c/3")
    _damage(chunk, "truncated")
    reason = pipe.env.store("heatmaps").reasons()[3]
    assert reason.startswith(f"(the frame failed; its reason cannot be read: chunk {chunk} cannot be decoded (")
    assert pipe.run("heatmaps")[-1].failed == 1  # the runner reads it too: the frame stays failed


def test_damaged_array_metadata_is_a_cache_error_naming_its_file(tmp_path):
    pipe = _pipe(tmp_path)
    pipe.run("calibrate")
    meta = _chunk(pipe, "calibrate", "points/zarr.json")
    _damage(meta, "truncated")
    with pytest.raises(CacheError, match=re.escape(f"{meta}: the metadata of array points cannot be read (")):
        pipe.run("heatmaps")


GROUP_DAMAGES = {**{k: v for k, v in DAMAGES.items() if k != "one bit flipped"},  # JSON has no checksum
                 "a JSON list": lambda data: b"[1, 2]"}


@pytest.mark.parametrize("how", [*GROUP_DAMAGES, "deleted"])
def test_damaged_group_metadata_stops_the_run_instead_of_recomputing(tmp_path, how):
    """A group zarr.json that cannot be read (or is gone, the arrays still there) stops every run
    that reads the output, naming the file, what recomputing would lose and the two ways out;
    the arrays are left alone. --force then recomputes it."""
    pipe = _pipe(tmp_path)
    pipe.run("heatmaps")
    meta = _chunk(pipe, "heatmaps", "zarr.json")
    saved = meta.read_bytes()
    if how == "deleted":
        meta.unlink()
    else:
        meta.write_bytes(GROUP_DAMAGES[how](saved))
    chunks = sorted(p.name for p in _chunk(pipe, "heatmaps", "total/c").iterdir())
    problem = "is missing" if how == "deleted" else "cannot be read ("
    for target in ("heatmaps", "train"):
        with pytest.raises(MetadataError) as info:
            pipe.run(target)
        message = str(info.value)
        assert message.startswith(f"{meta}: the metadata of stage output heatmaps {problem}"), message
        assert "(its status array records 8 of 8 frames finished)" in message
        assert message.endswith("Restore the file (from a backup or another copy of the cache), or recompute the "
                                "stage from scratch with `pipeline run heatmaps --force`")
    assert sorted(p.name for p in _chunk(pipe, "heatmaps", "total/c").iterdir()) == chunks  # nothing erased
    assert not pipe.env.store("train").exists() and pipe.env.dir("train").meta() is None
    with pytest.raises(MetadataError):
        pipe.run("heatmaps", frames=[2], force=True)  # in place needs the metadata: only the whole stage
    meta.write_bytes(saved)  # restored: everything is there again, nothing recomputed
    assert pipe.run("heatmaps")[-1].processed == 0
    _damage(meta, "truncated")
    report = pipe.run("heatmaps", force=True)[-1]
    assert report.processed == 8 and (pipe.env.store("heatmaps").status() == DONE).all()


@pytest.mark.parametrize("how", list(GROUP_DAMAGES))
def test_a_damaged_stage_record_of_a_dataset_stage_stops_the_run_instead_of_recomputing(tmp_path, how):
    """A dataset stage's _stage.json that is not a JSON object (written whole by a rename, so
    damaged) stops every run that reads the output, naming the file and the two ways out, as a
    damaged group zarr.json does; its files are left alone (until 2026-12-06 the output was taken
    for unfinished and recomputed without a word). A deleted one still means unfinished; --force
    makes the output again."""
    pipe = _pipe(tmp_path)
    pipe.run("train")
    folder = Path(pipe.env.dir("train").path)
    record = folder / "_stage.json"
    saved, total = record.read_bytes(), (folder / "total.txt").read_bytes()
    record.write_bytes(GROUP_DAMAGES[how](saved))
    command = f"`pipeline run train --dataset fake --cache {tmp_path / 'cache'} --force`"
    problem = "holds a JSON list, not an object" if how == "a JSON list" else "cannot be read ("
    with pytest.raises(MetadataError) as info:
        pipe.run("train")
    message = str(info.value)
    assert message.startswith(f"{record}: the record of stage output train {problem}"), message
    assert message.endswith(f"Restore the file (from a backup or another copy of the cache), or make the output "
                            f"again with {command}") and "\n" not in message, message
    assert record.read_bytes() == GROUP_DAMAGES[how](saved) and (folder / "total.txt").read_bytes() == total
    with pytest.raises(MetadataError):
        pipe.env.dir("train").meta()
    record.write_bytes(saved)  # restored: up to date
    assert pipe.run("train")[-1].summary["message"] == "up to date"
    record.write_bytes(GROUP_DAMAGES[how](saved))
    assert pipe.run("train", force=True)[-1].summary["message"] != "up to date"
    assert pipe.run("train")[-1].summary["message"] == "up to date"
    record.unlink()  # a stage never finished, or killed before its record: not finished, run again
    assert pipe.env.dir("train").meta() is None
    assert pipe.run("train")[-1].summary["message"] != "up to date" and pipe.env.dir("train").meta() is not None


def test_damaged_first_stage_metadata_is_rebuilt_by_force(tmp_path):
    pipe = _pipe(tmp_path)
    pipe.run("heatmaps")
    _damage(_chunk(pipe, "calibrate", "zarr.json"), "empty")
    with pytest.raises(MetadataError, match="`pipeline run calibrate --force`$"):
        pipe.run("calibrate")
    pipe.run("calibrate", force=True)
    assert (pipe.env.store("calibrate").status() == DONE).all()
    assert not pipe.is_current("heatmaps")  # made from the outputs the forced run replaced
    assert pipe.run("heatmaps")[-1].processed == 8


def test_status_lists_every_stage_around_a_damaged_one(tmp_path):
    pipe = _pipe(tmp_path)
    pipe.run("train")
    _damage(_chunk(pipe, "heatmaps", "zarr.json"), "truncated")
    rows = {row["stage"]: row for row in cache_status(pipe)}
    assert rows["calibrate"]["done"] == 8 and rows["calibrate"]["current"] is True
    assert rows["heatmaps"]["damaged"].startswith(f"{_chunk(pipe, 'heatmaps', 'zarr.json')}: the metadata")
    assert rows["heatmaps"]["exists"] and rows["heatmaps"]["current"] is None
    assert rows["train"]["exists"] and rows["train"]["current"] is None  # unknown until heatmaps is readable


# ------------------------------------------------------------------------------ pipeline verify


def test_verify_names_every_damaged_frame_and_nothing_else(tmp_path):
    """verify reads every chunk: the damaged frames of each output, whatever the damage (including
    a deleted chunk of a done frame and a damaged status chunk), and no false alarm."""
    pipe = _pipe(tmp_path)
    pipe.run("train")
    assert [(r["stage"], r.get("checked"), r.get("damaged")) for r in verify_cache(pipe)] == \
        [("calibrate", 8, {}), ("heatmaps", 8, {}), ("train", None, None)]
    for i, how in enumerate(DAMAGES):
        _damage(_chunk(pipe, "calibrate", f"points/c/{i}/0/0"), how)
    _chunk(pipe, "calibrate", "value/c/5").unlink()
    _damage(_chunk(pipe, "heatmaps", "status/c/6"), "random bytes")
    rows = {r["stage"]: r for r in verify_cache(pipe) if "checked" in r}
    assert list(rows["calibrate"]["damaged"]) == [0, 1, 2, 3, 5]
    assert rows["calibrate"]["frame_ids_damaged"] == ["f000", "f001", "f002", "f003", "f005"]
    assert rows["calibrate"]["damaged"][5].startswith("calibrate.zarr/value, frame 5 (f005): chunk ")
    assert "is missing although the frame is done" in rows["calibrate"]["damaged"][5]
    assert rows["calibrate"]["damaged"][3].endswith("--force --frames f003` (the frames made from it are "
                                                    "recomputed too)")
    assert list(rows["heatmaps"]["damaged"]) == [6] and rows["heatmaps"]["checked"] == 7
    assert rows["heatmaps"]["damaged"][6].startswith("heatmaps.zarr/status, frame 6 (f006): chunk ")
    # the commands it gives repair everything
    pipe.run("calibrate", frames=[0, 1, 2, 3, 5], force=True)
    pipe.run("heatmaps", frames=[6], force=True)
    assert all(not r.get("damaged") for r in verify_cache(pipe))


def test_verify_reads_a_cache_this_user_may_not_write(tmp_path, monkeypatch):
    """A cache copied read-only (or archived) was refused by verify ('the cache is not writable')
    because its shared readers' locks opened their files for writing: they are now flocked
    read-only, or not taken where they do not exist; a run that rewrites an output still needs
    to write its lock."""
    import errno
    import os

    from pipeline.lock import reading, rewriting

    pipe = _pipe(tmp_path)
    pipe.run("train")
    real_open = os.open

    def read_only(path, flags, *args):
        if flags & (os.O_CREAT | os.O_WRONLY | os.O_RDWR):
            raise PermissionError(errno.EACCES, "Permission denied", path)
        return real_open(path, flags, *args)

    with monkeypatch.context() as patch:
        patch.setattr(os, "open", read_only)
        rows = verify_cache(pipe)
        assert [(r["stage"], r.get("checked"), r.get("damaged")) for r in rows] == \
            [("calibrate", 8, {}), ("heatmaps", 8, {}), ("train", None, None)]
        lock = str(tmp_path / "no-such-lock")
        with reading([lock], "a read"):  # no lock file, none can be made: no lock taken
            pass
        with pytest.raises(Exception, match="not writable"):
            with rewriting(lock, "a rewrite"):
                pass


def test_verify_reads_arrays_in_blocks_and_names_the_frame_inside_a_block(tmp_path):
    pipe = _pipe(tmp_path)
    pipe.run("calibrate")
    _damage(_chunk(pipe, "calibrate", "points/c/6/0/0"), "one bit flipped")
    store = pipe.env.store("calibrate")
    seen: list[tuple[int, int]] = []
    for block_bytes in (1, 200, 1 << 20):  # a frame per block, a few frames, everything at once
        status, errors = store.verify(lambda n, total: seen.append((n, total)), block_bytes=block_bytes)
        assert (status == DONE).all() and list(errors) == [6]
        assert "checksum" in str(errors[6]).lower() or "cannot be decoded" in str(errors[6])
    assert {total for _, total in seen} == {8 * 5}  # 8 frames x (status, reason, points, points_count, value)
    assert sum(n for n, _ in seen) == 3 * 8 * 5


def test_verify_reports_unreadable_metadata_and_checkpoints(tmp_path):
    import torch

    from pipeline.checkpoint import save_checkpoint

    pipe = _pipe(tmp_path)
    pipe.run("train")
    _damage(_chunk(pipe, "heatmaps", "zarr.json"), "truncated")
    folder = Path(pipe.env.dir("train").path)
    save_checkpoint(folder / "net" / "best.safetensors", {"w": torch.zeros(64)}, {"epoch": 1})
    save_checkpoint(folder / "net" / "last.safetensors", {"w": torch.zeros(64)}, {"epoch": 1})
    _damage(folder / "net" / "last.safetensors", "truncated")
    rows = {r["stage"]: r for r in verify_cache(pipe)}
    assert rows["calibrate"]["damaged"] == {}
    assert rows["heatmaps"]["problem"].startswith(f"{_chunk(pipe, 'heatmaps', 'zarr.json')}: the metadata")
    assert rows["train"]["checkpoints"] == 2
    assert rows["train"]["problem"].startswith(f"{folder / 'net' / 'last.safetensors'}: unreadable checkpoint")
    assert [r["stage"] for r in verify_cache(pipe, ["calibrate"])] == ["calibrate"]
    # a readable file whose weights hold a NaN is damaged too; a NaN buffer that means 'not known' is not
    weights = {"model.fc.weight": torch.zeros(64), "model.feature_low": torch.full((4,), float("nan"))}
    save_checkpoint(folder / "net" / "last.safetensors", weights, {"epoch": 1})
    assert "problem" not in {r["stage"]: r for r in verify_cache(pipe, ["train"])}["train"]
    weights["model.fc.weight"][3] = float("nan")
    save_checkpoint(folder / "net" / "last.safetensors", weights, {"epoch": 1})
    assert {r["stage"]: r for r in verify_cache(pipe, ["train"])}["train"]["problem"] == (
        f"{folder / 'net' / 'last.safetensors'}: 1 of 64 values of fc.weight are not finite (NaN or inf): the "
        f"checkpoint is damaged; retrain it: `pipeline run train --force` (with the same --dataset and --cache)")


def test_cli_verify_prints_the_repair_command_and_exits_2(tmp_path, fake_cli):
    assert fake_cli(tmp_path, "run", "heatmaps", "--workers", "1").exit_code == 0
    clean = fake_cli(tmp_path, "verify")
    assert clean.exit_code == 0 and "calibrate       8 finished frame(s) read: every chunk intact" in clean.stdout
    _damage(tmp_path / "cache" / "synthetic" / "heatmaps.zarr" / "total" / "c" / "2", "empty")
    out = fake_cli(tmp_path, "verify")
    assert out.exit_code == 2 and out.stderr.strip() == "error: 1 stage output(s) damaged (above)"
    assert "heatmaps        8 finished frame(s) read: 1 damaged" in out.stdout
    command = re.search(r"recompute them: pipeline (run heatmaps .*)$", out.stdout, re.M).group(1)
    assert command == f"run heatmaps --dataset synthetic --cache {tmp_path / 'cache'} --force --frames f002"
    # the damaged chunk's line names what is wrong; the repair command is verify's one (with its --set
    # options; until 2026-12-08 the chunk's line named its own, without them)
    assert out.stdout.count("pipeline run") == 1 and "frame 2 (f002): chunk " in out.stdout
    assert fake_cli(tmp_path, *command.split()[:2], *command.split()[6:], "--workers", "1").exit_code == 0
    assert fake_cli(tmp_path, "verify").exit_code == 0
    bad = fake_cli(tmp_path, "verify", "--stage", "heatmap")
    assert bad.exit_code == 2 and "--stage heatmap: no such stage" in bad.stderr


def test_verify_checks_the_files_a_dataset_stage_recorded_when_it_finished(tmp_path, fake_cli):
    """A dataset stage's folder records its files' sizes and SHA-256 (_files.json) when it
    finishes: `pipeline verify` names a file deleted, truncated or changed in place by hand and how
    to make the output again; files added since are not damage. An output finished before files
    were recorded says so."""
    assert fake_cli(tmp_path, "run", "train", "--workers", "1").exit_code == 0
    folder = tmp_path / "cache" / "synthetic" / "train"
    recorded = json.loads((folder / "_files.json").read_text())
    assert list(recorded) == ["total.txt"] and recorded["total.txt"][0] == (folder / "total.txt").stat().st_size
    clean = fake_cli(tmp_path, "verify", "--stage", "train")
    assert clean.exit_code == 0 and "train           1 file(s) intact" in clean.stdout, clean.output
    (folder / "notes.txt").write_text("mine")
    assert fake_cli(tmp_path, "verify", "--stage", "train").exit_code == 0
    text = (folder / "total.txt").read_text()
    changed = {"changed": text[:-1] + ("1" if text[-1] != "1" else "2"), "truncated": text[:-1]}
    for how, damaged in (*changed.items(), ("deleted", None)):
        if damaged is None:
            (folder / "total.txt").unlink()
        else:
            (folder / "total.txt").write_text(damaged)
        out = fake_cli(tmp_path, "verify", "--stage", "train")
        assert out.exit_code == 2, (how, out.output)
        expected = {"changed": "its content changed since the stage finished (SHA-256)",
                    "truncated": f"{len(text) - 1} bytes, {len(text)} when the stage finished", "deleted": "missing"}
        assert f"train           cannot be read: {folder / 'total.txt'}: {expected[how]}" in out.stdout, out.stdout
        command = re.search(r"make it again: pipeline (run train .*)$", out.stdout, re.M).group(1)
        assert command == f"run train --dataset synthetic --cache {tmp_path / 'cache'} --force"
    assert fake_cli(tmp_path, *command.split()[:2], *command.split()[6:], "--workers", "1").exit_code == 0
    assert fake_cli(tmp_path, "verify", "--stage", "train").exit_code == 0
    (folder / "_files.json").write_text("{}")  # a stage that wrote no file: none to check, but recorded
    assert "train           0 file(s) intact" in fake_cli(tmp_path, "verify", "--stage", "train").stdout
    (folder / "_files.json").unlink()  # as an output finished before 2026-12-06
    old = fake_cli(tmp_path, "verify", "--stage", "train")
    assert old.exit_code == 0 and "train           finished (its files are not checked" in old.stdout


def test_verify_repair_commands_carry_its_settings_and_say_when_the_output_is_not_current(tmp_path, fake_cli):
    """A cache made with --set options (e.g. the transfer's train.nets_from=astyx): verify's repair
    line left them out, and pasted it recomputed every stage with the profile's settings, the nets
    trained again and the transferred outputs replaced (found 2026-12-06 on the View-of-Delft frames
    with the Astyx nets). It now carries verify's own --set options and says where the output is not
    current with them."""
    settings = ("--set", "heatmap.sigma_px=5,5")
    assert fake_cli(tmp_path, "run", "train", "--workers", "1", *settings).exit_code == 0
    (tmp_path / "cache" / "synthetic" / "train" / "total.txt").unlink()
    _damage(tmp_path / "cache" / "synthetic" / "heatmaps.zarr" / "total" / "c" / "2", "empty")
    cache = tmp_path / "cache"
    plain = fake_cli(tmp_path, "verify")
    assert plain.exit_code == 2
    assert f"make it again: pipeline run train --dataset synthetic --cache {cache} --force\n" in plain.stdout
    assert ("(not current with this command's settings, with which that run recomputes heatmaps and every stage "
            "after it: add `--set heatmap.sigma_px=5.0,5.0` to both)") in plain.stdout
    assert "(not current with this command's settings, with which that run makes heatmaps anew: " in plain.stdout
    same = fake_cli(tmp_path, "verify", *settings)
    assert same.exit_code == 2 and "not current" not in same.stdout, same.stdout
    for stage, tail in (("train", " --force"), ("heatmaps", " --force --frames f002")):
        command = re.search(rf"(?:make it again|recompute them): pipeline (run {stage} .*)$", same.stdout, re.M).group(1)
        assert command == f"run {stage} --dataset synthetic --cache {cache} --set heatmap.sigma_px=5,5{tail}"
    heatmaps = re.search(r"recompute them: pipeline (run heatmaps .*)$", same.stdout, re.M).group(1).split()
    assert fake_cli(tmp_path, *heatmaps[:2], *heatmaps[6:], "--workers", "1").exit_code == 0
    train = re.search(r"make it again: pipeline (run train .*)$", same.stdout, re.M).group(1).split()
    assert fake_cli(tmp_path, *train[:2], *train[6:], "--workers", "1").exit_code == 0
    assert fake_cli(tmp_path, "verify", *settings).exit_code == 0


def test_verify_names_the_first_five_damaged_files_of_a_stage_and_counts_the_rest(tmp_path):
    """A dataset stage output that lost many files (an export of thousands of frames, half deleted)
    is one problem naming the first five and how many more, not thousands of lines; verify's
    progress counts each file of it that it checks."""
    from pipeline.stage import DatasetStage

    def many(inputs, cfg, out, fingerprint):
        for i in range(7):
            out.write_text(f"frames/{i}.txt", str(i))
        return {"message": "7 files"}

    env = RunEnv(cfg=load_config("synthetic", {}, environ={}), cache_root=str(tmp_path / "cache"), dataset="fake",
                 data_root=str(tmp_path))
    stages = [*fake_stages.STAGES[:2], DatasetStage("train", ("heatmaps",), ("train.epochs",), many)]
    pipe = Pipeline(stages, env, Executor(1), progress=False, log=lambda m: None, frame_lister=lambda: list(IDS))
    pipe.run("train")
    counted: list[tuple[str, int, int]] = []
    row = verify_cache(pipe, ["train"], lambda stage, n, total: counted.append((stage, n, total)))[0]
    assert row["files"] == 7 and "problem" not in row, row
    assert sum(n for _, n, _ in counted) == 7 and {(stage, total) for stage, _, total in counted} == {("train", 7)}
    folder = Path(pipe.env.dir("train").path)
    for path in (folder / "frames").iterdir():
        path.unlink()
    row = verify_cache(pipe, ["train"])[0]
    assert row["problem"] == "; ".join([f"{folder / 'frames'}/{i}.txt: missing" for i in range(5)]
                                       + ["... and 2 more file(s)"]), row


def test_chunk_error_survives_pickling():
    err = ChunkError("a.zarr/x", 3, "f003", "/c/a.zarr/x/c/3", "cannot be decoded (E: e)", "do this")
    again = pickle.loads(pickle.dumps(err))
    assert str(again) == str(err) == "a.zarr/x, frame 3 (f003): chunk /c/a.zarr/x/c/3 cannot be decoded (E: e); do this"
    assert (again.array, again.index, again.chunk) == ("a.zarr/x", 3, "/c/a.zarr/x/c/3")


# ------------------------------------------------------------------------------------- the CLI


@pytest.fixture
def fake_cli(monkeypatch):
    """The real CLI (options, error handling) on the fake stages and frames."""
    return fake_stages.fake_cli(monkeypatch, lambda: IDS)


def test_cli_damaged_status_chunk_is_one_line(tmp_path, fake_cli):
    assert fake_cli(tmp_path, "run", "heatmaps", "--workers", "1").exit_code == 0
    chunk = tmp_path / "cache" / "synthetic" / "calibrate.zarr" / "status" / "c" / "3"
    _damage(chunk, "truncated")
    for args in (("status",), ("run", "heatmaps", "--workers", "1"), ("run", "heatmaps", "--dry-run")):
        out = fake_cli(tmp_path, *args)
        assert out.exit_code == 2, out.output
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in out.output
        assert lines[0].startswith(f"error: calibrate.zarr/status, frame 3 (f003): chunk {chunk} cannot be decoded")
    status = fake_cli(tmp_path, "status").stdout  # the table still lists every stage
    assert re.search(r"^calibrate +unknown +damaged: calibrate.zarr/status, frame 3 ", status, re.M), status
    assert re.search(r"^heatmaps +unknown +done +8 ", status, re.M) and re.search(r"^train +.* not run$", status, re.M)


def test_cli_damaged_group_metadata_names_the_file_and_force(tmp_path, fake_cli):
    assert fake_cli(tmp_path, "run", "heatmaps", "--workers", "1").exit_code == 0
    meta = tmp_path / "cache" / "synthetic" / "heatmaps.zarr" / "zarr.json"
    _damage(meta, "truncated")
    for args in (("status",), ("run", "train", "--workers", "1")):
        out = fake_cli(tmp_path, *args)
        assert out.exit_code == 2 and "Traceback" not in out.output, out.output
        errors = [line for line in out.stderr.splitlines() if line.startswith("error: ")]
        assert len(errors) == 1 and errors[0].startswith(f"error: {meta}: the metadata of stage output heatmaps ")
    assert fake_cli(tmp_path, "run", "heatmaps", "--force", "--workers", "1").exit_code == 0
    assert fake_cli(tmp_path, "status").exit_code == 0


def test_cli_damaged_stage_record_names_the_file_in_status_verify_and_runs(tmp_path, fake_cli):
    """A dataset stage's _stage.json cut short (found by a review, 2026-12-06): verify exited 0 without
    the stage's line, status called it not finished, and a run recomputed it and the stages after it
    without a word. Now each says so in one line naming the file and --force, exit code 2."""
    assert fake_cli(tmp_path, "run", "train", "--workers", "1").exit_code == 0
    record = tmp_path / "cache" / "synthetic" / "train" / "_stage.json"
    record.write_bytes(record.read_bytes()[:40])
    for args in (("status",), ("run", "train", "--workers", "1"), ("run", "train", "--dry-run")):
        out = fake_cli(tmp_path, *args)
        assert out.exit_code == 2 and "Traceback" not in out.output, (args, out.output)
        errors = [line for line in out.stderr.splitlines() if line.startswith("error: ")]
        assert len(errors) == 1 and errors[0].startswith(f"error: {record}: the record of stage output train "
                                                         "cannot be read ("), (args, out.output)
        assert f"`pipeline run train --dataset synthetic --cache {tmp_path / 'cache'} --force`" in errors[0]
    status = fake_cli(tmp_path, "status").stdout  # the other stages are still listed
    assert re.search(r"^calibrate .* done +8", status, re.M) and re.search(r"^heatmaps ", status, re.M), status
    verify = fake_cli(tmp_path, "verify")  # every output checked; the train line names the file and the way out
    assert verify.exit_code == 2 and "Traceback" not in verify.output
    assert re.search(r"^calibrate .* every chunk intact", verify.stdout, re.M), verify.output
    assert f"train           cannot be read: {record}: the record of stage output train cannot be read (" in verify.stdout
    assert f"make it again: pipeline run train --dataset synthetic --cache {tmp_path / 'cache'} --force" in verify.stdout
    assert fake_cli(tmp_path, "run", "train", "--force", "--workers", "1").exit_code == 0  # the way out
    assert fake_cli(tmp_path, "verify").exit_code == 0 and fake_cli(tmp_path, "status").exit_code == 0


@pytest.mark.parametrize("how", ["truncated", "deleted"])
def test_cli_damaged_array_metadata_names_the_file_in_status_verify_and_runs(tmp_path, fake_cli, how):
    """One array's zarr.json truncated or deleted (found by audits, 2026-12-04): verify ended in a
    raw JSONDecodeError or said every chunk was intact, status called the stage current, and a
    resumed or per-frame forced run of the stage ended in a traceback."""
    assert fake_cli(tmp_path, "run", "heatmaps", "--workers", "1", "--frames", "0:4").exit_code == 0
    meta = tmp_path / "cache" / "synthetic" / "heatmaps.zarr" / "total" / "zarr.json"
    if how == "deleted":
        meta.unlink()
    else:
        _damage(meta, how)
    expected = f"{meta}: the metadata of array total " + ("is missing" if how == "deleted" else "cannot be read (")
    for args in (("status",), ("verify",), ("run", "heatmaps", "--workers", "1"),
                 ("run", "heatmaps", "--force", "--frames", "f003", "--workers", "1")):
        out = fake_cli(tmp_path, *args)
        assert out.exit_code == 2 and "Traceback" not in out.output, (args, out.output)
        assert expected in out.output, (args, out.output)
        assert "make it again" not in out.output  # a dataset stage's repair line, not a frame stage's
    assert fake_cli(tmp_path, "run", "heatmaps", "--force", "--workers", "1").exit_code == 0  # the way out
    assert fake_cli(tmp_path, "verify").exit_code == 0


def test_cli_run_and_status_report_the_damaged_chunk_per_frame(tmp_path, fake_cli):
    assert fake_cli(tmp_path, "run", "calibrate", "--workers", "1").exit_code == 0
    _damage(tmp_path / "cache" / "synthetic" / "calibrate.zarr" / "points" / "c" / "3" / "0" / "0", "empty")
    run = fake_cli(tmp_path, "run", "heatmaps", "--workers", "1")
    assert run.exit_code == 0, run.output
    failed = [line for line in run.stderr.splitlines() if line.startswith("  failed: ")]
    assert len(failed) == 1 and failed[0].startswith("  failed: stage heatmaps, frame f003: calibrate.zarr/points, "
                                                     "frame 3 (f003): chunk ")
    status = fake_cli(tmp_path, "status")
    assert status.exit_code == 0
    assert re.search(r"heatmaps .* done +7  failed +1", status.stdout)
    # the reason names the stage and frame itself (until 2026-12-08 under 'frame 3: ', naming the frame twice)
    assert "\n                stage heatmaps, frame f003: calibrate.zarr/points, frame 3 (f003): chunk " in status.stdout


def test_cli_names_relocate_when_the_recorded_data_root_is_gone(tmp_path, fake_cli, monkeypatch):
    """Without --data-root the CLI reads the data where the cache was made; when that place is
    gone it says so and names relocate, instead of a reader error."""
    data = tmp_path / "data"
    data.mkdir()
    assert fake_cli(data.parent, "run", "calibrate", "--workers", "1").exit_code == 0   # --data-root tmp_path
    from pipeline.cache import frame_store

    store = frame_store(str(tmp_path / "cache"), "synthetic", "calibrate")
    store.set_fingerprint(store.fingerprint(), data_root=str(data))   # as if made from tmp_path/data
    data.rmdir()
    out = CliRunner().invoke(cli.main, ["run", "heatmaps", "--dataset", "synthetic", "--cache", str(tmp_path / "cache")])
    assert out.exit_code == 2
    assert f"the cache was made from the data at {data}, which is not there any more" in out.stderr
    assert f"`pipeline relocate --dataset synthetic --cache {tmp_path / 'cache'} --data-root NEW_PLACE`" in out.stderr


def test_cli_takes_a_link_to_the_cache_s_data_root_as_that_data_root(tmp_path, fake_cli, monkeypatch):
    """--data-root through a symbolic link (or another spelling) of the folder the cache was made
    from was refused as moved data, offering relocate; it is the same folder: the outputs stay
    current. A link to another folder with the same frames is still a move."""
    assert fake_cli(tmp_path, "run", "heatmaps", "--workers", "1").exit_code == 0   # --data-root tmp_path
    link = tmp_path.parent / f"{tmp_path.name}-link"
    link.symlink_to(tmp_path)
    for root in (link, f"{tmp_path}/./"):
        out = CliRunner().invoke(cli.main, ["run", "heatmaps", "--workers", "1", "--dataset", "synthetic", "--cache",
                                            str(tmp_path / "cache"), "--data-root", str(root)])
        assert out.exit_code == 0, out.output
        assert "processed 0 frame(s)" in out.stderr and "relocate" not in out.output
    other = tmp_path / "other"
    other.mkdir()
    moved = tmp_path.parent / f"{tmp_path.name}-other"
    moved.symlink_to(other)
    out = CliRunner().invoke(cli.main, ["run", "heatmaps", "--workers", "1", "--dataset", "synthetic", "--cache",
                                        str(tmp_path / "cache"), "--data-root", str(moved)])
    assert out.exit_code == 2 and "pipeline relocate" in out.stderr


def test_cli_counts_each_failed_frame_once_under_the_stage_it_first_failed_in(tmp_path, fake_cli, monkeypatch):
    """Until 2026-12-05 the run printed '2 frame(s) failed across stages' for one bad frame: heatmaps
    marks the frame calibrate failed on failed too, and the counts were summed."""
    import sys

    monkeypatch.setattr(sys.modules[__name__], "IDS", ["bad000", "f001", "f002", "f003"])
    out = fake_cli(tmp_path, "run", "train", "--workers", "1")
    assert out.exit_code == 0, out.output
    assert "1 frame(s) failed (first in calibrate: 1); `pipeline status --dataset synthetic --cache " in out.stderr
    chunk = tmp_path / "cache" / "synthetic" / "calibrate.zarr" / "points" / "c" / "3" / "0" / "0"
    _damage(chunk, "empty")  # frame 3 now fails in heatmaps; frame 0 stays failed from the first run
    out = fake_cli(tmp_path, "run", "heatmaps", "--workers", "1", "--force")
    assert "2 frame(s) failed (first in calibrate: 1, heatmaps: 1)" in out.stderr, out.output


def test_cli_says_which_stages_frames_does_not_limit(tmp_path, fake_cli):
    """Until 2026-12-05 nothing said that train (export, evaluate) used every finished frame after a
    `--frames` run: `run export --frames 0:2` on a finished cache exported every frame."""
    out = fake_cli(tmp_path, "run", "train", "--workers", "1", "--frames", "0:2")
    assert out.exit_code == 0, out.output
    assert ("--frames 0:2: limits the per-frame stages; train uses every finished frame of its inputs, not only "
            "those (they run again when more frames finish)") in out.stderr
    dry = fake_cli(tmp_path, "run", "train", "--dry-run", "--frames", "0:2")
    assert "--frames 0:2: per-frame work would be limited to those frames; train uses every finished" in dry.stdout
    out = fake_cli(tmp_path, "run", "heatmaps", "--workers", "1", "--frames", "0:2")
    assert out.exit_code == 0 and "--frames" not in out.output  # only frame stages: nothing to say


def test_cli_run_exits_1_when_a_stage_made_nothing(tmp_path, fake_cli, monkeypatch):
    """Some failed frames leave the run a success (exit 0; --strict stops at the first); a stage
    whose every frame failed made nothing, which a script must notice (until 2026-12-04: exit 0)."""
    import sys

    monkeypatch.setattr(sys.modules[__name__], "IDS", ["bad000", "f001", "f002"])
    out = fake_cli(tmp_path / "some", "run", "calibrate", "--workers", "1")
    assert out.exit_code == 0 and "1 frame(s) failed" in out.stderr, out.output
    monkeypatch.setattr(sys.modules[__name__], "IDS", ["bad000", "bad001"])
    out = fake_cli(tmp_path / "all", "run", "calibrate", "--workers", "1")
    assert out.exit_code == 1, out.output
    assert "error: stage calibrate has no frame done: all 2 frame(s) it tried in this run failed, e.g. " in out.stderr
    assert "bad000.bin is truncated" in out.stderr
    # the stages after one with no frame done are not run (until 2026-12-04 they were, and failed or
    # refused for want of input), and a rerun with nothing to retry still exits 1, saying why
    out = fake_cli(tmp_path / "all", "run", "heatmaps", "--workers", "1")
    assert out.exit_code == 1 and "no frame of calibrate is done: the stages that need it were not run (heatmaps)" in out.output
    assert "heatmaps " not in out.output and "its 2 failed frame(s) failed in an earlier run" in out.stderr
    assert f"`pipeline status --dataset synthetic --cache {tmp_path / 'all' / 'cache'}`" in out.stderr
    from pipeline.cache import frame_store

    reasons = frame_store(str(tmp_path / "all" / "cache"), "synthetic", "calibrate").reasons().values()
    assert all(r.count("frame bad00") == 1 for r in reasons), reasons   # the frame named once
    # a rerun that tries only the bad frame again while the others are done made its output: exit 0
    monkeypatch.setattr(sys.modules[__name__], "IDS", ["f000", "f001", "bad002"])
    assert fake_cli(tmp_path / "rerun", "run", "calibrate", "--workers", "1", "--frames", "0:2").exit_code == 0
    out = fake_cli(tmp_path / "rerun", "run", "heatmaps", "--workers", "1", "--retry-failed")
    assert out.exit_code == 0, out.output


def test_cli_status_says_unfinished_for_a_current_stage_with_frames_left(tmp_path, fake_cli):
    assert fake_cli(tmp_path, "run", "heatmaps", "--workers", "1", "--frames", "0:4").exit_code == 0
    status = fake_cli(tmp_path, "status").stdout
    assert re.search(r"^heatmaps +current, unfinished +done +4 .* pending +4 ", status, re.M), status
    assert fake_cli(tmp_path, "run", "heatmaps", "--workers", "1").exit_code == 0
    assert re.search(r"^heatmaps +current +done +8 ", fake_cli(tmp_path, "status").stdout, re.M)


def test_relocate_waits_with_wait_as_its_lock_refusal_says(tmp_path, fake_cli):
    """relocate's refusal of a held lock says 'pass --wait SECONDS', as every command's does, but
    relocate had no --wait (until 2026-12-07: click's 'no such option'). Now it waits for the lock."""
    import threading

    from pipeline.cachefs import join
    from pipeline.lock import stage_lock

    assert fake_cli(tmp_path, "run", "heatmaps", "--workers", "1").exit_code == 0
    moved = tmp_path.parent / f"{tmp_path.name}-moved"
    moved.mkdir()  # the fake stages' frames are their ids: the same data at another place
    lock = join(str(tmp_path / "cache"), "synthetic", "locks", "heatmaps.lock")
    args = ["relocate", "--dataset", "synthetic", "--cache", str(tmp_path / "cache"), "--data-root", str(moved)]
    held, release = threading.Event(), threading.Event()

    def hold():
        with stage_lock(lock, "a test run"):
            held.set()
            release.wait(10)

    holder = threading.Thread(target=hold)
    holder.start()
    held.wait(10)
    try:
        refused = CliRunner().invoke(cli.main, args)
        assert refused.exit_code == 2 and "pass --wait SECONDS" in refused.stderr, refused.output
        threading.Timer(0.5, release.set).start()
        waited = CliRunner().invoke(cli.main, [*args, "--wait", "30"])
    finally:
        release.set()
        holder.join()
    assert waited.exit_code == 0 and "relocated dataset synthetic" in waited.stdout, waited.output
