"""Every stage end to end on a tiny synthetic world, through the serial and the dask executor:
identical caches, a complete report, and an export that the VoD reader reads back unchanged."""

from __future__ import annotations

import json
import os
import re
import shutil
from dataclasses import replace
from pathlib import Path

import cv2

import numpy as np
import pytest
import zarr

from pipeline.cache import DONE, EXCLUDED
from pipeline.config import load_config
from pipeline.errors import ConfigError
from pipeline.executor import Executor, RunEnv
from pipeline.readers.vod import VodReader
from pipeline.runner import Pipeline
from stages import all_stages

TINY = {"train.epochs": "1", "placement.epochs": "1", "disnet.width": "8", "patches.points_per_frame": "16",
        "split.rule": "random", "synth.split": "all", "eval.split": "all", "eval.figure_frames": "2",
        "train.threads": "1", "train.device": "cpu"}
"""train.device: the tests compare runs that each train, bit for bit; on a GPU two trainings differ
(README, "On a GPU"), which failed the serial-against-dask comparison on an H200 (2026-12-04)."""
FRAME_STAGES = ("calibrate", "heatmaps", "patches", "synthesize", "evaluate-frames")


@pytest.fixture(scope="module")
def world(tiny_world, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("world") / "world"
    shutil.copytree(tiny_world, root)
    return root


def run_pipeline(world: Path, cache: Path, workers: int, target: str = "evaluate") -> Pipeline:
    cfg = load_config("synthetic", TINY, environ={})
    env = RunEnv(cfg, str(cache), "synthetic", str(world))
    with Executor(workers, progress=False) as ex:
        pipe = Pipeline(all_stages(), env, ex, progress=False, log=lambda m: None)
        pipe.run(target)
        pipe.run("export")
    return pipe


def arrays(cache: Path, stage: str) -> dict[str, np.ndarray]:
    group = zarr.open_group(str(cache / "synthetic" / f"{stage}.zarr"), mode="r")
    return {name: np.asarray(arr[:]) for name, arr in group.arrays()}


def test_all_stages_serial_equals_dask_and_export_round_trips(world, tmp_path, monkeypatch):
    # No OMP_NUM_THREADS=1 here: the executor itself must make serial and dask agree bit for bit.
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    serial = run_pipeline(world, tmp_path / "serial", 1)
    run_pipeline(world, tmp_path / "dask", 2)
    for stage in FRAME_STAGES:
        a, b = arrays(tmp_path / "serial", stage), arrays(tmp_path / "dask", stage)
        assert a.keys() == b.keys()
        for name in a:
            np.testing.assert_array_equal(a[name], b[name], err_msg=f"{stage}/{name}")
        assert np.all(np.isin(a["status"], (DONE, EXCLUDED))), stage
    # PlaceNet was trained on the patches stage's candidate rows and scored on the test frames
    placenet = json.loads((tmp_path / "serial" / "synthetic" / "train" / "metrics.json").read_text())["placenet"]
    assert min(placenet["rows"].values()) > 0 and np.isfinite(placenet["test"]["nll"])
    patches = arrays(tmp_path / "serial", "patches")
    assert patches["place_count"][np.isfinite(patches["place_count"])].sum() > 0
    # its count scale (saved with it) turns the summed intensity into a count; the frames' count is
    # the geometric mean of Dis-Net's and PlaceNet's (synth.count = predicted, lidar placement)
    from pipeline.checkpoint import read_meta

    best = tmp_path / "serial" / "synthetic" / "train" / "placenet" / "best.safetensors"
    assert placenet["count_scale"] == read_meta(best)["count_scale"] > 0
    synthesized = arrays(tmp_path / "serial", "synthesize")
    parts = synthesized["n_parts"][synthesized["status"] == DONE]
    assert np.all(parts > 0)
    np.testing.assert_allclose(synthesized["n_hat"][synthesized["status"] == DONE], np.sqrt(parts.prod(axis=1)),
                               rtol=1e-5)
    report_meta = json.loads((tmp_path / "serial" / "synthetic" / "evaluate" / "report.json").read_text())["meta"]
    assert "PlaceNet's" in report_meta["count_parts"] and "geometric mean (the model's)" in report_meta["count_parts"]
    from stages.evaluate import count_parts

    evaluated = arrays(tmp_path / "serial", "evaluate-frames")["status"] == DONE
    assert int(evaluated.sum()) == report_meta["frames"]
    assert report_meta["count_parts"] == count_parts(synthesized["n_parts"][evaluated], synthesized["n_hat"][evaluated],
                                                     arrays(tmp_path / "serial", "heatmaps")["count"][evaluated])
    # the synthesized points are lidar points of their frame (lidar placement, the default)
    syn, calib = serial.env.store("synthesize"), serial.env.store("calibrate")
    done = [int(i) for i in np.flatnonzero(syn.status() == DONE)]
    for i in done:
        lidar = {tuple(p) for p in calib.read("lidar", i).astype(np.float32).tolist()}
        assert all(tuple(p) in lidar for p in syn.read("points", i)[:, :3].tolist()), i
    assert sum(len(syn.read("points", i)) for i in done) > 0
    # synth.rss_sampling = residual (on the dask run's cache, which nothing reads after this): the
    # same points, RSS-Net's RSS plus a residual drawn from its validation residuals' quantiles
    from pipeline.inference import RESIDUAL_KEY

    quantiles = read_meta(tmp_path / "dask" / "synthetic" / "train" / "rssnet" / "best.safetensors")[RESIDUAL_KEY]
    residual_env = RunEnv(serial.env.cfg.with_overrides({"synth.rss_sampling": "residual"}), str(tmp_path / "dask"),
                          "synthetic", str(world))
    Pipeline(all_stages(), residual_env, Executor(1, progress=False), progress=False,
             log=lambda m: None).run("synthesize")
    mean_rows, drawn_rows = synthesized["points"], arrays(tmp_path / "dask", "synthesize")["points"]
    np.testing.assert_array_equal(np.delete(drawn_rows, 7, axis=-1), np.delete(mean_rows, 7, axis=-1))
    rss = np.isfinite(mean_rows[..., 7])
    added = drawn_rows[..., 7][rss] - mean_rows[..., 7][rss]
    r = serial.env.cfg.radar
    clipped = np.isin(drawn_rows[..., 7][rss], np.float32([r.rss_min, r.rss_max]))
    assert np.all(clipped | ((added >= quantiles[0] - 1e-3) & (added <= quantiles[-1] + 1e-3)))
    assert np.mean(added != 0) > 0.9 and drawn_rows[..., 7][rss].std() > mean_rows[..., 7][rss].std()
    # evaluate wrote a report with every method and the figures
    report = json.loads((tmp_path / "serial" / "synthetic" / "evaluate" / "report.json").read_text())
    assert "model" in json.dumps(report) and "mean-map" in json.dumps(report)
    # the ceiling row samples the frame's own real heatmap with the real count
    ceiling = report["metrics"]["model-oracle-map"]
    assert ceiling["kl"]["mean"] == 0.0 and ceiling["count_rel_err"]["mean"] == 0.0
    # the empty yardstick: GOSPA from the missed points alone, no matches
    empty = report["metrics"]["no-points"]
    assert empty["gospa_missed"]["mean"] > 0 and empty["gospa_false"]["mean"] == empty["gospa_localisation"]["mean"] == 0
    assert empty["f1"]["mean"] == 0.0 and "no-points" not in json.dumps(report["model_does_not_beat"])
    # the by-speed rows cover every evaluated frame once, and their counts are the model row's
    by_speed = report["by_ego_speed"]
    assert sum(r["frames"] for r in by_speed) == report["meta"]["frames"]
    model_rel = sum(r["frames"] * r["count_rel_err"] for r in by_speed) / report["meta"]["frames"]
    assert np.isclose(model_rel, report["metrics"]["model"]["count_rel_err"]["mean"])
    for fig in ("fig8.png", "bev.png", "histograms.png"):
        assert (tmp_path / "serial" / "synthetic" / "evaluate" / "figures" / fig).stat().st_size > 10_000
    check_export_round_trip(serial, world, tmp_path / "serial")
    assert not (tmp_path / "serial" / "synthetic" / "export" / "ego_velocity_unknown.txt").exists()  # all known
    # export.image_format=jpg: every image_2 file a JPEG of the frame's image
    jpg_env = replace(serial.env, cfg=serial.env.cfg.with_overrides({"export.image_format": "jpg"}))
    Pipeline(all_stages(), jpg_env, Executor(1, progress=False), progress=False, log=lambda m: None).run("export")
    images = sorted((tmp_path / "serial" / "synthetic" / "export" / "radar").glob("*/image_2/*"))
    assert len(images) == len(done) and {p.suffix for p in images} == {".jpg"}
    source = cv2.imread(str(next((world / "lidar" / "training" / "image_2").glob(f"{images[0].stem}.*"))))
    assert np.abs(cv2.imread(str(images[0])).astype(int) - source).mean() < 3
    with pytest.raises(ConfigError, match="export.image_format"):
        Pipeline(all_stages(), replace(serial.env, cfg=serial.env.cfg.with_overrides({"export.image_format": "bmp"})),
                 Executor(1, progress=False), progress=False, log=lambda m: None).run("export")
    # export.class_names renames classes in every label file; the summary counts the boxes per class
    renamed = {r.stage: r for r in Pipeline(all_stages(), replace(serial.env, cfg=serial.env.cfg.with_overrides(
        {"export.class_names": "Car=Vehicle,Carr=Auto"})), Executor(1, progress=False), progress=False,
        log=lambda m: None).run("export")}["export"].summary
    written: dict[str, dict[str, int]] = {"training": {}, "testing": {}}
    for path in (tmp_path / "serial" / "synthetic" / "export" / "radar").glob("*/label_2/*.txt"):
        for line in path.read_text().splitlines():
            kind = line.split()[0]
            if kind != "DontCare":
                written[path.parent.parent.name][kind] = written[path.parent.parent.name].get(kind, 0) + 1
    assert renamed["classes"] == written and "Car" not in str(written) and written["training"]["Vehicle"] > 0
    assert f"Vehicle {written['training']['Vehicle']}" in renamed["message"]
    assert renamed["classes_not_found"] == ["Carr"] and "renames Carr, which no written label holds" in renamed["message"]
    with pytest.raises(ConfigError, match="export.class_names: 'Car' is not From=To"):
        Pipeline(all_stages(), replace(serial.env, cfg=serial.env.cfg.with_overrides({"export.class_names": "Car"})),
                 Executor(1, progress=False), progress=False, log=lambda m: None).run("export")
    # a frame synthesized without a point is exported as an empty .bin, and the message names it
    from stages.synthesize import outputs as synthesize_outputs

    spec = next(s for s in synthesize_outputs(serial.env.cfg) if s.name == "points")
    syn.write_frame(done[0], {"points": np.zeros((0, spec.shape[1]), np.float32)}, (spec,))
    summary = {r.stage: r for r in Pipeline(all_stages(), serial.env, Executor(1, progress=False), progress=False,
                                            log=lambda m: None).run("export", force=True)}["export"].summary
    fid = serial.frame_ids()[done[0]]
    assert summary["empty_frames"] == [fid] and "1 of them without a point (an empty .bin" in summary["message"]
    bins = list((tmp_path / "serial" / "synthetic" / "export" / "radar").glob(f"*/velodyne/{fid}.bin"))
    assert len(bins) == 1 and bins[0].stat().st_size == 0
    # a report over part of the split says so (here synthesize deleted and redone for 3 frames only)
    partial = Pipeline(all_stages(), serial.env, Executor(1, progress=False), progress=False, log=lambda m: None)
    shutil.rmtree(tmp_path / "serial" / "synthetic" / "synthesize.zarr")
    reports = {r.stage: r for r in partial.run("evaluate", frames=[0, 1, 2])}
    report = json.loads((tmp_path / "serial" / "synthetic" / "evaluate" / "report.json").read_text())
    assert report["meta"]["frames"] == 3 and "7 of the split's frames" in report["meta"]["frames_not_synthesized"]
    assert "7 more not synthesized" in reports["evaluate"].summary["message"]


def check_export_round_trip(pipe: Pipeline, world: Path, cache: Path) -> None:
    """The exported radar, read by the VoD reader beside the world's lidar and images, gives back
    the synthesized points, RSS, range rate, and the ego velocity."""
    export = cache / "synthetic" / "export"
    readers = {}
    for subset in ("training", "testing"):  # a VoD view of each subset: its radar beside the world's lidar
        root = cache / f"vod_view_{subset}"
        (root / "radar").mkdir(parents=True)
        os.symlink(export / "radar" / subset, root / "radar" / "training")
        os.symlink(world / "lidar", root / "lidar")
        readers[subset] = VodReader(pipe.env.cfg, root)
    syn = pipe.env.store("synthesize")
    calib = pipe.env.store("calibrate")
    split = calib.array("split")[:]
    ids = pipe.frame_ids()
    mode = 0o666 & ~_umask()
    checked = 0
    for i in np.flatnonzero(syn.status() == DONE):
        subset = "testing" if split[int(i)] == 2 else "training"
        frame = export / "radar" / subset
        fid = ids[int(i)]
        source = next((world / "lidar" / "training" / "image_2").glob(f"{fid}.*"))
        assert (frame / "image_2" / source.name).read_bytes() == source.read_bytes()
        assert (frame / "velodyne" / f"{fid}.bin").stat().st_mode & 0o777 == mode   # readable as open() makes them
        labels = [line.split() for line in (frame / "label_2" / f"{fid}.txt").read_text().splitlines()]
        # the world's track ids become each box's truncation (pipeline.export.label_truncation)
        assert labels and all(re.fullmatch(r"[01]\.\d\d", fields[1]) for fields in labels)
        pts = syn.read("points", int(i))
        if len(pts) < 3:
            continue
        rec = readers[subset].read(fid)
        np.testing.assert_allclose(rec.radar_D[:, :3], pts[:, :3], atol=1e-6)
        np.testing.assert_allclose(rec.radar_D[:, 3], pts[:, 8], atol=1e-5)   # range rate
        np.testing.assert_allclose(rec.radar_D[:, 4], pts[:, 7], atol=1e-5)   # RSS
        np.testing.assert_allclose(rec.ego_velocity_D, calib.read("ego_velocity", int(i)), atol=1e-3)
        checked += 1
    assert checked >= 3
    sets = {p.stem: p.read_text().split() for p in (export / "radar" / "ImageSets").glob("*.txt")}
    assert sorted(sum(sets.values(), [])) == sorted(ids[int(i)] for i in np.flatnonzero(syn.status() == DONE))
    assert sets["test"] and sets["train"]
    assert sorted(sets["test"]) == sorted(p.stem for p in (export / "radar" / "testing" / "velodyne").glob("*.bin"))


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def test_train_stage_reports_the_count_refit(world, tmp_path):
    """With train.count_refit_epochs the train stage's metrics.json says what the refit did
    (the per-pass curve stays in the checkpoint's meta), and its test L_n is the refitted model's."""
    cfg = load_config("synthetic", {**TINY, "train.nets": "disnet", "train.count_refit_epochs": "3"}, environ={})
    env = RunEnv(cfg, str(tmp_path / "cache"), "synthetic", str(world))
    with Executor(1, progress=False) as ex:
        Pipeline(all_stages(), env, ex, progress=False, log=lambda m: None).run("train")
    summary = json.loads((tmp_path / "cache" / "synthetic" / "train" / "metrics.json").read_text())
    refit = summary["disnet"]["count_refit"]
    assert refit["epochs"] == 3 and 0 <= refit["best_pass"] <= 3 and "curve" not in refit
    assert refit["select_n_after"] <= refit["select_n_before"]
    assert refit["selection"] in ("val", "train")
    assert "rssnet" not in summary


def test_lidar_placement_without_placenet_is_a_clear_error_and_ray_placement_works(world, tmp_path):
    """Nets trained without PlaceNet: synthesize with the default lidar placement is refused before
    anything runs (until 2026-12-05 only after training), a train output without PlaceNet's checkpoint
    names it; synth.placement=ray generates from Dis-Net and RSS-Net."""
    from pipeline.errors import ConfigError, PipelineError
    from stages.synthesize import check_checkpoints

    def pipeline(**extra: str) -> Pipeline:
        cfg = load_config("synthetic", {**TINY, "train.nets": "disnet,rssnet", **extra}, environ={})
        env = RunEnv(cfg, str(tmp_path / "cache"), "synthetic", str(world))
        return Pipeline(all_stages(), env, Executor(1, progress=False), progress=False, log=lambda m: None)

    with pytest.raises(ConfigError, match=r"train.nets = 'disnet,rssnet' leaves out placenet.*synth.placement=ray"):
        pipeline().run("synthesize")
    assert not (tmp_path / "cache" / "synthetic" / "calibrate.zarr").exists()  # nothing ran
    pipe = pipeline(**{"synth.placement": "ray"})
    assert not pipe.env.store("synthesize").exists()  # stopped before its output was created (ready)
    pipe.run("synthesize")
    syn = pipe.env.store("synthesize")
    assert np.all(syn.status() == DONE)
    counts = np.stack([syn.read("counts", i) for i in range(len(syn.status()))])
    assert counts[:, 0].sum() > 0 and counts[:, 4].sum() >= 0
    points = np.concatenate([syn.read("points", i) for i in range(len(syn.status()))])
    assert len(points) > 0 and np.all(np.isfinite(points))
    with pytest.raises(PipelineError, match="no placenet checkpoint.*synth.placement=ray"):
        check_checkpoints(pipe.env.dir("train"), load_config("synthetic", TINY, environ={}))


def test_train_stage_records_the_prior_mix_and_takes_a_changed_setting(world, tmp_path):
    """disnet.prior_mix: the train stage's metrics.json holds the best checkpoint's record of the
    share. The setting is one of the stage's keys: switched to 'off' it reruns the stage, whose
    resumed, finished training sets the share to 0 and records so."""
    from pipeline.checkpoint import read_meta
    from pipeline.training import PRIOR_MIX_KEY

    best = tmp_path / "cache" / "synthetic" / "train" / "disnet" / "best.safetensors"

    def train(setting: str) -> dict:
        cfg = load_config("synthetic", {**TINY, "train.nets": "disnet", "disnet.prior_mix": setting}, environ={})
        with Executor(1, progress=False) as ex:
            Pipeline(all_stages(), RunEnv(cfg, str(tmp_path / "cache"), "synthetic", str(world)), ex, progress=False,
                     log=lambda m: None).run("train")
        record = json.loads((tmp_path / "cache" / "synthetic" / "train" / "metrics.json").read_text())["disnet"]
        return record["prior_mix"]

    mix = train("val")
    assert mix == read_meta(best)[PRIOR_MIX_KEY] and mix["setting"] == "val" and mix["val_frames"] > 0
    assert train("off") == {"w": 0.0, "setting": "off"} == read_meta(best)[PRIOR_MIX_KEY]


def test_train_headline_names_a_chosen_prior_share():
    """The train stage's message names the prior's share when one was chosen on val, and says
    nothing of it for a share of 0 or a summary without the record (written before 2026-12-06)."""
    from stages.train import _headline

    base = {"baselines_test": {"mean_map_kl": 0.31, "mean_count_L_n": 0.2}}
    test = {"kl": 0.29, "n": 0.1}
    for mix, said in (({"w": 0.35, "setting": "val"}, True), ({"w": 0.0, "setting": "val"}, False),
                      ({"w": 0.0, "setting": "off"}, False), (None, False)):
        message = _headline({**base, "disnet": {"test": test, "prior_mix": mix}})
        assert ("the mean map's share 0.35 chosen on val" in message) == said, message
        assert message.startswith("Dis-Net test L_KL 0.2900 (mean map 0.3100")
    assert "share" not in _headline({**base, "disnet": {"test": test}})



def test_train_headline_says_when_the_nets_had_few_training_frames():
    """On the two View-of-Delft example frames (1 train, 0 val, 1 test) the nets equal the baselines
    (Dis-Net L_KL 0.2777 against the mean map's 0.2777) and the line said nothing of why."""
    from stages.train import FEW_TRAIN_FRAMES, _headline

    base = {"baselines_test": {"mean_map_kl": 0.31, "mean_count_L_n": 0.2}, "disnet": {"test": {"kl": 0.29, "n": 0.1}}}
    few = _headline({**base, "frames": {"train": 1, "val": 0, "test": 1}})
    assert few.endswith("; only 1 training frame(s) and 0 val: from so few the nets learn little beyond the training "
                        "means (enough to check the pipeline, not to simulate a radar)"), few
    for frames in ({"train": FEW_TRAIN_FRAMES, "val": 2, "test": 5}, {}):
        assert "training frame(s)" not in _headline({**base, "frames": frames})

def test_train_headline_names_the_nets_stopped_early():
    """train.patience: the train stage's message says which nets stopped early, after which epoch
    and with which best; not for nets that ran all their epochs or summaries without the record."""
    from stages.train import _headline

    base = {"baselines_test": {"median_rss_L_a": 0.02}}
    rss = {"test": {"a": 0.018}, "best_epoch": 3, "epochs": 6, "stopped_early": True}
    assert _headline({**base, "rssnet": rss}).endswith("; stopped early: rssnet after epoch 6 (best 3)")
    assert _headline({**base, "rssnet": rss, "placenet": {"test": {}, "best_epoch": 9, "epochs": 13,
                                                         "stopped_early": True}}).endswith(
        "stopped early: rssnet after epoch 6 (best 3), placenet after epoch 13 (best 9)")
    for record in ({**rss, "stopped_early": False}, {"test": {"a": 0.018}}):
        assert "stopped" not in _headline({**base, "rssnet": record})
