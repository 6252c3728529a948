"""evaluate's per-frame part (evaluate-frames): resumable like any frame stage, recomputed when
what it read was recomputed, a failed frame left out of the report and said so."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.baselines import mean_count
from pipeline.cache import DONE, FAILED, PENDING
from pipeline.config import load_config
from pipeline.executor import Executor, RunEnv
from pipeline.runner import Pipeline
from pipeline.world import generate
from stages import all_stages, evaluate

TINY = {"train.epochs": "1", "placement.epochs": "1", "disnet.width": "8", "patches.points_per_frame": "16",
        "split.rule": "random", "synth.split": "all", "eval.split": "all", "eval.figure_frames": "1",
        "train.threads": "1"}
FRAMES = 8


@pytest.fixture(scope="module")
def synthesized(tmp_path_factory) -> tuple[Path, Path]:
    """A tiny world and a cache with every stage up to synthesize done (trained once per module)."""
    root = tmp_path_factory.mktemp("eval-frames")
    world, cache = root / "world", root / "cache"
    generate(world, frames=FRAMES, seed=7, resolution_wh=(640, 384), sequence_len=FRAMES)
    _pipeline(world, cache).run("synthesize")
    return world, cache


def _pipeline(world: Path, cache: Path, **settings: str) -> Pipeline:
    env = RunEnv(load_config("synthetic", {**TINY, **settings}, environ={}), str(cache), "synthetic", str(world))
    return Pipeline(all_stages(), env, Executor(1, progress=False), progress=False, log=lambda m: None)


def _copy(synthesized, tmp_path) -> Pipeline:
    world, cache = synthesized
    shutil.copytree(cache, tmp_path / "cache")
    return _pipeline(world, tmp_path / "cache")


def _report(pipe: Pipeline) -> dict:
    return json.loads((Path(pipe.env.cache_root) / "synthetic" / "evaluate" / "report.json").read_text())


def test_a_run_stopped_part_way_resumes_and_gives_the_same_report(synthesized, tmp_path):
    pipe = _copy(synthesized, tmp_path)
    first = {r.stage: r for r in pipe.run("evaluate", frames=[0, 1, 2])}
    assert first["evaluate-frames"].processed == 3
    status = pipe.env.store("evaluate-frames").status()
    assert list(status[:3]) == [DONE] * 3 and np.all(status[3:] == PENDING)
    partial = _report(pipe)
    assert partial["meta"]["frames"] == 3 and "5 of the split's synthesized frames" in partial["meta"]["frames_not_evaluated"]
    assert "5 more not evaluated" in first["evaluate"].summary["message"]
    second = {r.stage: r for r in _pipeline(*synthesized[:1], tmp_path / "cache").run("evaluate")}
    assert second["evaluate-frames"].processed == FRAMES - 3   # only the frames left
    resumed = _report(pipe)
    assert resumed["meta"]["frames"] == FRAMES and "frames_not_evaluated" not in resumed["meta"]
    # the by-speed table's counts: the real radar's points and the model's predicted count (n_hat)
    by_speed = resumed["by_ego_speed"]
    assert sum(r["frames"] for r in by_speed) == FRAMES
    real = np.asarray(pipe.env.store("calibrate").array("radar_count")[:FRAMES], np.float64)
    n_hat = np.asarray(pipe.env.store("synthesize").array("n_hat")[:FRAMES], np.float64)
    assert sum(r["frames"] * r["real_count"] for r in by_speed) == pytest.approx(real.sum())
    assert sum(r["frames"] * r["model_count"] for r in by_speed) == pytest.approx(n_hat.sum(), rel=1e-6)
    whole = _copy(synthesized, tmp_path / "whole")
    assert {r.stage: r for r in whole.run("evaluate")}["evaluate-frames"].processed == FRAMES
    assert resumed == _report(whole)
    # up to date: no frame is evaluated again
    again = {r.stage: r for r in pipe.run("evaluate")}
    assert again["evaluate-frames"].processed == 0 and again["evaluate"].summary["message"] == "up to date"


def test_recomputed_inputs_and_force_recompute_every_frame(synthesized, tmp_path):
    pipe = _copy(synthesized, tmp_path)
    pipe.run("evaluate")
    # synthesize forced under the same fingerprint: the stored per-frame results were made from its
    # old points, so none of them may be reused
    pipe.run("synthesize", force=True)
    reports = {r.stage: r for r in pipe.run("evaluate")}
    assert reports["evaluate-frames"].processed == FRAMES
    # --force on evaluate recomputes its per-frame part too
    reports = {r.stage: r for r in pipe.run("evaluate", force=True)}
    assert reports["evaluate-frames"].processed == FRAMES


def test_a_failed_frame_is_left_out_and_said(synthesized, tmp_path, monkeypatch):
    pipe = _copy(synthesized, tmp_path)
    physics = evaluate.physics_frame

    def broken(f, cfg):
        if f.index == 4:
            raise ValueError("lidar of frame 4 is broken")
        return physics(f, cfg)

    monkeypatch.setattr(evaluate, "physics_frame", broken)
    reports = {r.stage: r for r in pipe.run("evaluate")}
    assert reports["evaluate-frames"].failed == 1
    status = pipe.env.store("evaluate-frames").status()
    assert status[4] == FAILED and np.sum(status == DONE) == FRAMES - 1
    assert "lidar of frame 4 is broken" in pipe.env.store("evaluate-frames").reasons()[4]
    report = _report(pipe)
    assert report["meta"]["frames"] == FRAMES - 1 and "1 failed" in report["meta"]["frames_not_evaluated"]
    assert "1 of them failed" in reports["evaluate"].summary["message"]
    with pytest.raises(Exception, match=r"stage evaluate-frames, frame \S+: ValueError: lidar of frame 4"):
        pipe.run("evaluate", strict=True)
    monkeypatch.setattr(evaluate, "physics_frame", physics)
    reports = {r.stage: r for r in pipe.run("evaluate", retry_failed=True)}
    assert reports["evaluate-frames"].processed == 1 and _report(pipe)["meta"]["frames"] == FRAMES


def test_a_method_s_distribution_distances_use_the_real_points_of_its_own_frames(synthesized, tmp_path):
    """previous-frame has no points on a sequence's first frame: its distribution distances compare
    it with the real points of the frames it has, as its metrics are (before, with every frame's)."""
    from pipeline.baselines import METHODS
    from pipeline.metrics import distribution_distances

    pipe = _copy(synthesized, tmp_path)
    pipe.run("evaluate")
    part = pipe.env.store("evaluate-frames")
    frames = np.flatnonzero(part.status() == DONE)
    names = [spec.name for spec in METHODS]
    present = np.asarray(part.array("present").oindex[frames], bool)
    counts = np.asarray(part.array("points_count")[:])[frames]
    rows = [np.asarray(part.array("points")[int(i), :n]) for i, n in zip(frames, counts)]
    summary = evaluate.summarise(part, frames, 0.0, True, 10**9, False)
    previous, model = names.index("previous-frame"), names.index("model")
    assert present[:, previous].any() and not present[:, previous].all()

    def pooled(method: int, only: np.ndarray) -> np.ndarray:
        return np.concatenate([r[r[:, 0] == method, 1:] for r, keep in zip(rows, only) if keep])

    everywhere = np.ones(len(frames), bool)
    mine = distribution_distances(pooled(previous, everywhere), pooled(-1, present[:, previous]), 0.0)
    assert summary.distances["previous-frame"] == mine
    assert mine != distribution_distances(pooled(previous, everywhere), pooled(-1, everywhere), 0.0)
    assert summary.distances["model"] == distribution_distances(pooled(model, everywhere), pooled(-1, everywhere), 0.0)
    assert "real points of the frames it has" in (Path(pipe.env.cache_root) / "synthetic" / "evaluate" /
                                                  "report.md").read_text()


def test_the_report_pools_a_random_sample_above_eval_pooled_rows_max(synthesized, tmp_path, monkeypatch):
    """Above eval.pooled_rows_max the report's pooled rows are a random sample of the rows of every
    frame, the same however the frames are read; the per-frame metrics are untouched, and the
    report says what was sampled."""
    from tqdm import tqdm

    pipe = _copy(synthesized, tmp_path)
    pipe.run("evaluate")
    part = pipe.env.store("evaluate-frames")
    frames = np.flatnonzero(part.status() == DONE)
    counts = np.asarray(part.array("points_count")[:])[frames]
    full, total, row_frame = evaluate._pooled(part, "points", frames, 10**9, tqdm(disable=True))
    assert total == len(full) == counts.sum()
    assert np.array_equal(row_frame, np.repeat(np.arange(len(frames)), counts))
    assert np.array_equal(full, np.concatenate([np.asarray(part.array("points")[int(i), :n]) for i, n in
                                                zip(frames, counts)]))
    k = total // 3
    sample, sampled_total, sample_frame = evaluate._pooled(part, "points", frames, k, tqdm(disable=True))
    assert len(sample_frame) == len(sample) and np.all(np.diff(sample_frame) >= 0)
    assert all(tuple(r) in {tuple(x) for x in full[row_frame == f]} for r, f in zip(sample[:50], sample_frame[:50]))
    assert sampled_total == total and abs(len(sample) - k) < 4 * np.sqrt(k)  # each row kept with probability k / total
    full_rows = {tuple(r) for r in full}
    assert all(tuple(r) in full_rows for r in sample) and len({tuple(r) for r in sample}) > 0.95 * len(sample)
    monkeypatch.setattr(evaluate, "READ_BYTES", 1)  # one frame per read: the same sample
    assert np.array_equal(evaluate._pooled(part, "points", frames, k, tqdm(disable=True))[0], sample)

    exact = evaluate.summarise(part, frames, 0.0, True, 10**9, False)
    thinned = evaluate.summarise(part, frames, 0.0, True, k, False)
    assert exact.sampled == "" and "physics" not in thinned.sampled  # fewer real points than k: all pooled
    assert f"distribution distances and histograms from a random sample of {len(sample):,} of the {total:,} pooled " \
        f"points" in thinned.sampled
    assert json.dumps(thinned.table) == json.dumps(exact.table)
    assert json.dumps(thinned.by_speed) == json.dumps(exact.by_speed)
    real_points = int(np.asarray(part.array("abs_dr_count")[:])[frames].sum())
    assert {v["points"] for k_, v in thinned.physics.items() if k_.startswith("range")} == {real_points}
    assert len(thinned.real_sph) < real_points == len(exact.real_sph)

    report = {r.stage: r for r in _pipeline(*synthesized[:1], tmp_path / "cache", **{"eval.pooled_rows_max": str(k)})
              .run("evaluate")}
    assert report["evaluate-frames"].processed == 0  # the pooling is the report's alone
    assert f"random sample of {len(sample):,} of the {total:,} pooled points" in _report(pipe)["meta"]["sampled"]
    assert "random sample" in (Path(pipe.env.cache_root) / "synthetic" / "evaluate" / "report.md").read_text()

    import zarr

    from pipeline.errors import CacheError

    zarr.open_array(f"{part.url}/points_count", mode="r+")[int(frames[2])] = part.array("points").shape[1] + 1
    with pytest.raises(CacheError, match=rf"points_count, frame {int(frames[2])}: \d+ rows, outside 0\.\.\d+"):
        evaluate.summarise(part, frames, 0.0, True, 10**9, False)


def test_nets_retrained_under_the_same_fingerprint_are_loaded_again(synthesized, tmp_path):
    """The per-process memo of the trained nets (synthesize, evaluate-frames) is keyed by the train
    run, not only its fingerprint: after `train --force` a process (a cluster's worker, or this one)
    must not go on with the old nets."""
    from pipeline.executor import FrameInputs
    from stages.synthesize import models

    pipe = _copy(synthesized, tmp_path)
    frame = FrameInputs(pipe.env, 0, pipe.frame_ids()[0])
    before = models(frame, pipe.env.cfg)
    assert models(frame, pipe.env.cfg) is before
    fingerprint = pipe.env.dir("train").fingerprint()
    pipe.run("train", force=True)
    assert pipe.env.dir("train").fingerprint() == fingerprint
    assert models(frame, pipe.env.cfg) is not before


def test_a_damaged_mean_map_stops_the_run_naming_the_file_and_the_command(synthesized, tmp_path):
    """A damaged train/mean_heatmap.npy is one error naming the file, that it is damaged and the
    command that writes it again; it stops the run before any frame (before, every frame failed with
    numpy's advice to load the file with allow_pickle), and a frame that meets it stops the run too."""
    from pipeline.errors import CacheError
    from pipeline.executor import process_frame

    pipe = _copy(synthesized, tmp_path)
    path = Path(pipe.env.dir("train").path) / "mean_heatmap.npy"
    path.write_text("garbage\n")
    command = f"pipeline run train --dataset synthetic --cache {tmp_path / 'cache'} --force"
    with pytest.raises(CacheError) as info:
        pipe.run("evaluate")
    text = str(info.value)
    assert text.startswith(f"{path} is damaged") and command in text, text
    assert "pickle" not in text and "\n" not in text, text
    assert not (tmp_path / "cache" / "synthetic" / "evaluate-frames.zarr").exists()  # stopped before any frame
    with pytest.raises(CacheError, match="is damaged"):   # met by a frame (a run that resumes)
        process_frame(evaluate.FRAMES, pipe.env, 0, pipe.frame_ids()[0])
    good = np.load(Path(synthesized[1]) / "synthetic" / "train" / "mean_heatmap.npy")
    for damaged, problem in ((good.tobytes()[:40], "cannot be read"), (b"", "cannot be read"),
                             (None, "not a finite 2-D map")):
        if damaged is None:
            np.save(path, good.reshape(-1), allow_pickle=False)
        else:
            path.write_bytes(damaged)
        with pytest.raises(CacheError, match=problem):
            evaluate.read_mean_map(pipe.env, pipe.env.cfg)
    path.unlink()
    with pytest.raises(CacheError, match=f"is missing; write it again with `{command}`"):
        evaluate.read_mean_map(pipe.env, pipe.env.cfg)
    np.save(path, good, allow_pickle=False)
    assert np.array_equal(evaluate.read_mean_map(pipe.env, pipe.env.cfg), good)


def test_previous_frame_needs_consecutive_frames_and_keeps_to_the_evaluated_region():
    """EVALUATION.md: previous-frame 'where consecutive frames exist'. A previous frame 5 s back
    (Astyx's subset skips seconds between neighbouring ids) gives no points rather than points moved
    by 0.1 s of ego motion; a clock that wraps at the hour still counts as 0.1 s; moved points
    outside the evaluated region are dropped, as the real points were."""
    prev = np.array([[10.0, 0.0, 0.0, -5.0, 1.0], [20.0, 9.5, 0.0, -4.0, 2.0]])
    ego = np.array([5.0, 0.0, 0.0])
    everything = lambda xyz: np.ones(len(xyz), bool)                               # noqa: E731
    assert evaluate.moved_previous_frame(prev, ego, 5.0, everything) is None
    assert evaluate.moved_previous_frame(prev, ego, -1.0, everything) is None     # backwards, no wrap
    moved = evaluate.moved_previous_frame(prev, ego, 0.1, everything)
    np.testing.assert_allclose(moved[:, :3], prev[:, :3] - [0.5, 0.0, 0.0], atol=1e-9)
    np.testing.assert_array_equal(moved[:, 3:], prev[:, 3:])                       # Doppler and RSS as measured
    wrapped = evaluate.moved_previous_frame(prev, ego, 0.1 - evaluate.CLOCK_WRAP_S, everything)
    np.testing.assert_allclose(wrapped, moved, atol=1e-6)
    within_25deg = lambda xyz: np.abs(np.arctan2(xyz[:, 1], xyz[:, 0])) <= np.deg2rad(25)   # noqa: E731
    np.testing.assert_allclose(evaluate.moved_previous_frame(prev, ego, 0.1, within_25deg), moved[:1])


def test_static_points_leave_out_boxes_of_unknown_velocity():
    """Astyx labels carry no velocity: points inside its boxes may move and are no static points
    for the Doppler check (they counted as static, a quarter of Astyx's points, before)."""
    from pipeline.frame import Object3D, label_rows

    real = np.array([[10.0, 0.0, 0.0, 0.0, 0.0], [30.0, 5.0, 0.0, 0.0, 0.0], [20.0, -3.0, 0.0, 0.0, 0.0]])
    unknown = Object3D("Car", np.array([10.0, 0.0, 0.0]), np.array([4.0, 2.0, 1.5]), 0.0)
    parked = Object3D("Car", np.array([30.0, 5.0, 0.0]), np.array([4.0, 2.0, 1.5]), 0.0,
                      velocity_D=np.zeros(3, np.float32))
    moving = Object3D("Car", np.array([20.0, -3.0, 0.0]), np.array([4.0, 2.0, 1.5]), 0.0,
                      velocity_D=np.array([3.0, 0.0, 0.0], np.float32))
    np.testing.assert_array_equal(evaluate._static_mask(real, label_rows([unknown, parked, moving])),
                                  [False, True, False])
    np.testing.assert_array_equal(evaluate._static_mask(real, label_rows([])), [True, True, True])


class _FakeStore:
    """A frame store of whole arrays (status, split, ...) for the functions that read one (a local
    one: nothing is read ahead)."""

    url = "/fake/calibrate.zarr"

    def __init__(self, status, **arrays):
        self._status, self._arrays = np.asarray(status), {k: np.asarray(v) for k, v in arrays.items()}
        self._arrays["status"] = self._status

    def status(self):
        return self._status

    def array(self, name):
        return self._status if name == "status" else self._arrays[name]

    def read(self, name, index, run=""):
        return self._arrays[name][index]


class _FakeEnv:
    stage_run = ""

    def __init__(self, **stores):
        self.stores = stores

    def store(self, name):
        return self.stores[name]


def test_baseline_statistics_come_from_the_train_split_only():
    """The baselines' mean count and map are 'training-split statistics' (EVALUATION.md): frames of
    the val and test splits (codes 1, 2), frames without points and unfinished ones are left out."""
    split = [0, 1, 2, 0, 0, 2]
    calib = _FakeStore([DONE, DONE, DONE, DONE, PENDING, DONE], split=split)
    heat = _FakeStore([DONE] * 6, count=[10, 50, 70, 0, 30, 90])
    train, counts = evaluate._train_counts(_FakeEnv(calibrate=calib, heatmaps=heat))
    assert list(train) == [0] and list(counts) == [10, 50, 70, 0, 30, 90]
    assert mean_count(counts[train]) == 10


def test_evaluate_frames_selects_eval_split_not_synth_split():
    """evaluate-frames works on eval.split's frames that record radar, whatever synth.split is."""
    calib = _FakeStore([DONE] * 4, split=[0, 2, 2, 1], has_radar=[True, True, False, True])
    cfg = load_config("synthetic", {"synth.split": "all", "eval.split": "test"}, environ={})
    assert list(evaluate.select_frames(_FakeEnv(calibrate=calib), cfg)) == [False, True, False, False]
    cfg = load_config("synthetic", {"synth.split": "test", "eval.split": "val"}, environ={})
    assert list(evaluate.select_frames(_FakeEnv(calibrate=calib), cfg)) == [False, False, False, True]


def test_an_empty_split_is_told_apart_from_frames_without_radar():
    """evaluate with nothing to compare: a split the split's settings left empty (12 Astyx frames in
    blocks of 15 all land in train) says so with the frames per split and the way out (before, it
    said the dataset records no radar in that split); frames of the split that record no radar, and
    a dataset without radar, say that."""
    from types import SimpleNamespace

    from pipeline.cache import EXCLUDED
    from pipeline.errors import PipelineError

    def message(split, has_radar, **settings) -> str:
        n = len(split)
        calib = _FakeStore([DONE] * n, split=split, has_radar=has_radar)
        env = _FakeEnv(calibrate=calib, synthesize=_FakeStore([DONE] * n),
                       **{"evaluate-frames": _FakeStore([EXCLUDED] * n)})
        env.env = SimpleNamespace(dataset="astyx")
        cfg = load_config("astyx", settings, environ={})
        with pytest.raises(PipelineError) as info:
            evaluate.run(env, cfg, None, "")
        return str(info.value)

    text = message([0] * 12, [True] * 12)
    assert "split 'test' of dataset astyx has no frames (12 calibrated frames: 12 in train, 0 in val, 0 in test; " \
           "split.rule=block, split.block_len=15)" in text and "--set eval.split=all" in text, text
    assert "records no radar" not in text
    text = message([0, 0, 1, 2, 2], [True, True, True, False, False])
    assert "the 2 frames of split 'test' of dataset astyx record no radar" in text, text
    assert "records no radar" in message([0, 1, 2], [False] * 3, **{"eval.split": "all"})


def test_previous_frame_is_none_across_a_sequence_boundary_or_before_a_frame_not_calibrated():
    from pipeline.executor import FrameInputs

    calib = _FakeStore([DONE, DONE, DONE, FAILED, DONE], sequence=["a", "a", "b", "b", "b"])
    env = _FakeEnv(calibrate=calib)
    ids = [f"{i:06d}" for i in range(5)]
    prev = evaluate._previous(FrameInputs(env, 1, ids[1]), ids)
    assert prev is not None and prev.index == 0
    assert evaluate._previous(FrameInputs(env, 0, ids[0]), ids) is None       # the first frame
    assert evaluate._previous(FrameInputs(env, 2, ids[2]), ids) is None       # frame 1 is of sequence a
    assert evaluate._previous(FrameInputs(env, 4, ids[4]), ids) is None       # frame 3 failed in calibrate


def test_the_report_gives_the_counts_parts_errors():
    """Mean relative error and L_n of Dis-Net's count, PlaceNet's and the model's, over the frames
    with real points; PlaceNet's left out where it was not computed (-1)."""
    from stages.evaluate import count_parts

    parts = np.array([[12.0, 8.0], [5.0, 5.0], [3.0, 3.0]])
    real = np.array([10.0, 5.0, 0.0])  # the third frame has no real point: left out
    n_hat = np.sqrt(parts.prod(axis=1))
    line = count_parts(parts, n_hat, real)
    assert line.startswith("mean relative error of Dis-Net's count 0.1 (L_n 0.02), PlaceNet's 0.1 (L_n 0.02), ")
    assert f"their geometric mean (the model's) {abs(np.sqrt(96) - 10) / 20:.3g}" in line
    assert line.endswith("over 2 frames with real points")
    parts[0, 1] = 0.0  # a frame without a lidar candidate: PlaceNet's count is 0, computed
    assert "PlaceNet's 0.5 (L_n 0.5)" in count_parts(parts, n_hat, real)
    parts[0, 1] = -1
    assert "PlaceNet" not in count_parts(parts, n_hat, real)
    assert count_parts(parts, n_hat, np.zeros(3)) == ""
