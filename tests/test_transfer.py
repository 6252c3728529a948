"""Nets trained on one dataset synthesizing another (train.nets_from): the radar settings they carry,
a KITTI-layout dataset (no radar) synthesized and exported with the tiny synthetic world's nets."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.cache import DONE, EXCLUDED
from pipeline.config import load_config
from pipeline.errors import ConfigError, PipelineError
from pipeline.executor import Executor, RunEnv
from pipeline.geometry import invert_transform
from pipeline.readers.testing import R_CAM_D, rigid, write_image, write_kitti_calib
from pipeline.runner import Pipeline
from pipeline.transfer import RADAR_SETTINGS, settings, trained_settings, with_nets_from
from pipeline.world import generate
from stages import all_stages

TINY = {"train.epochs": "1", "placement.epochs": "1", "disnet.width": "8", "patches.points_per_frame": "16",
        "split.rule": "random", "train.threads": "1"}
KITTI_FRAMES = 3


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """A cache root whose 'synthetic' dataset (a tiny world) has finished its train stage."""
    root = tmp_path_factory.mktemp("transfer")
    generate(root / "world", frames=8, seed=11, resolution_wh=(640, 384), sequence_len=8)
    _pipeline(load_config("synthetic", TINY, environ={}), root / "cache", "synthetic", root / "world").run("train")
    return root / "cache"


def _pipeline(cfg, cache: Path, dataset: str, data: Path) -> Pipeline:
    env = RunEnv(cfg, str(cache), dataset, str(data))
    return Pipeline(all_stages(), env, Executor(1, progress=False), progress=False, log=lambda m: None)


def _kitti(root: Path) -> Path:
    """KITTI object layout at KITTI's image size: Velodyne points on a ground plane and a wall."""
    base = root / "training"
    for folder in ("velodyne", "calib", "image_2"):
        (base / folder).mkdir(parents=True)
    T_cam_velo = rigid(R_CAM_D, np.array([0.0, -0.08, -0.27]))
    K = np.array([[721.5, 0.0, 609.6], [0.0, 721.5, 172.9], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(0)
    for i in range(KITTI_FRAMES):
        ground = np.column_stack([rng.uniform(3, 45, 6000), rng.uniform(-15, 15, 6000), np.full(6000, -1.7)])
        wall = np.column_stack([np.full(4000, 25.0), rng.uniform(-15, 15, 4000), rng.uniform(-1.7, 3, 4000)])
        velo = np.column_stack([np.concatenate([ground, wall]), rng.uniform(0, 1, 10000)])
        velo.astype("<f4").tofile(base / "velodyne" / f"{i:06d}.bin")
        write_kitti_calib(base / "calib" / f"{i:06d}.txt", K, T_cam_velo)
        write_image(base / "image_2" / f"{i:06d}.png", (1242, 375))
    (base / "label_2").mkdir()
    (base / "label_2" / "000000.txt").write_text(KITTI_LABEL)
    return root


KITTI_LABEL = "Car 0.12 0 -1.58 587.0 173.3 614.1 200.1 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59\n"
"""A KITTI label line (rectified camera 0), carried over by the export as it is."""


def _kitti_cfg(cache: Path, **sets: str):
    return with_nets_from(load_config("kitti", {"train.nets_from": "synthetic", **sets}, environ={}), str(cache),
                          explicit=sets)


def test_the_trained_radar_settings_replace_the_profile_and_are_recorded(trained):
    source = load_config("synthetic", TINY, environ={})
    record = json.loads((trained / "synthetic" / "train" / "_stage.json").read_text())["summary"]["settings"]
    assert record == settings(source) and set(record) == set(RADAR_SETTINGS)
    cfg = _kitti_cfg(trained)
    assert settings(cfg) == settings(source)
    assert cfg.camera.working_size == (608, 192) and cfg.lidar == load_config("kitti", environ={}).lidar
    # a value given explicitly that is not the trained one is refused, naming it
    with pytest.raises(ConfigError, match=r"radar\.fov_az_deg=64.0 \(here: 100.0\)"):
        _kitti_cfg(trained, **{"radar.fov_az_deg": "100"})
    assert _kitti_cfg(trained, **{"radar.fov_az_deg": str(source.radar.fov_az_deg)}) == cfg
    # nothing trained there: the profile as it is (the train stage will say why it cannot run)
    missing = load_config("kitti", {"train.nets_from": "astyx"}, environ={})
    assert with_nets_from(missing, str(trained)) == missing
    with pytest.raises(ConfigError, match="names this dataset itself"):
        with_nets_from(load_config("kitti", {"train.nets_from": "kitti"}, environ={}), str(trained))


def test_settings_of_a_train_output_without_the_record(trained, tmp_path):
    """Train outputs written before the record: the values the source's calibrate and patches
    outputs recorded, the rest from its profile."""
    import shutil

    cache = tmp_path / "cache"
    shutil.copytree(trained, cache)
    meta_path = cache / "synthetic" / "train" / "_stage.json"
    meta = json.loads(meta_path.read_text())
    del meta["summary"]["settings"]
    meta_path.write_text(json.dumps(meta))
    for stage in ("calibrate", "patches"):  # as if both had run with --set radar.fov_az_deg=50
        path = cache / "synthetic" / f"{stage}.zarr" / "zarr.json"
        doc = json.loads(path.read_text())
        doc["attributes"]["config"]["radar.fov_az_deg"] = 50.0
        path.write_text(json.dumps(doc))
    got = trained_settings(str(cache), "synthetic")
    assert got["radar.fov_az_deg"] == 50.0 and got["patches.r_c_px"] == load_config("synthetic", environ={}).patches.r_c_px
    assert got["radar.doppler_span_mps"] == load_config("synthetic", environ={}).radar.doppler_span_mps


def test_a_dataset_without_radar_is_synthesized_with_another_datasets_nets(trained, tmp_path):
    kitti = _kitti(tmp_path / "kitti")
    cfg = _kitti_cfg(trained)
    pipe = _pipeline(cfg, trained, "kitti", kitti)
    reports = {r.stage: r for r in pipe.run("export")}
    assert "the nets of dataset synthetic" in reports["train"].summary["message"]
    for net in ("disnet", "rssnet", "placenet"):
        assert (trained / "kitti" / "train" / net / "best.safetensors").read_bytes() == \
            (trained / "synthetic" / "train" / net / "best.safetensors").read_bytes()
    syn = pipe.env.store("synthesize")
    assert np.all(syn.status() == DONE)
    calib = pipe.env.store("calibrate")
    total = 0
    for i in range(KITTI_FRAMES):
        pred = syn.read("pred_map", i)
        assert pred.shape == (192, 608) and np.isclose(pred.sum(dtype=np.float64), 1.0, atol=1e-4)
        points = syn.read("points", i)
        lidar = {tuple(p) for p in calib.read("lidar", i).astype(np.float32).tolist()}
        assert all(tuple(p) in lidar for p in points[:, :3].tolist())  # on this frame's lidar points
        az = np.degrees(np.abs(points[:, 4]))
        assert np.all(az <= cfg.radar.fov_az_deg / 2 + 1e-3) and np.all(points[:, 3] <= cfg.radar.max_range_m + 1e-3)
        assert np.all((points[:, 7] >= cfg.radar.rss_min - 1e-3) & (points[:, 7] <= cfg.radar.rss_max + 1e-3))
        total += len(points)
    assert total > 0
    exported = trained / "kitti" / "export" / "radar" / "testing"
    assert len(list((exported / "velodyne").glob("*.bin"))) == KITTI_FRAMES
    # KITTI's calib with the radar in the Velodyne's place, and KITTI's labels as they are
    assert (exported / "label_2" / "000000.txt").read_text() == KITTI_LABEL
    assert not (exported / "label_2" / "000001.txt").exists()
    assert (exported / "image_2" / "000001.png").read_bytes() == (kitti / "training/image_2/000001.png").read_bytes()
    calib = {line.split(":")[0]: np.array(line.split(":")[1].split(), float)
             for line in (exported / "calib" / "000001.txt").read_text().splitlines()}
    T_cam_radar = rigid(R_CAM_D, np.array([0.0, -0.08, -0.27])) @ invert_transform(
        np.asarray(cfg.dataset.radar_mount_T_radar_lidar, float).reshape(4, 4))
    np.testing.assert_allclose(calib["Tr_velo_to_cam"].reshape(3, 4), T_cam_radar[:3], atol=1e-9)
    # no radar: nothing to evaluate against, said plainly
    with pytest.raises(PipelineError, match="records no radar"):
        pipe.run("evaluate")
    assert np.all(pipe.env.store("evaluate-frames").status() == EXCLUDED)
    # the other dataset's nets retrained: this dataset's copy and what it synthesized are stale
    assert pipe.is_current("synthesize")
    _pipeline(load_config("synthetic", TINY, environ={}), trained, "synthetic", trained.parent / "world").run(
        "train", force=True)
    again = _pipeline(_kitti_cfg(trained), trained, "kitti", kitti)
    assert not again.is_current("train") and not again.is_current("synthesize")


def test_the_train_stage_refuses_settings_the_nets_were_not_trained_with(trained, tmp_path):
    kitti = _kitti(tmp_path / "kitti")
    raw = load_config("kitti", {"train.nets_from": "synthetic"}, environ={})   # not through with_nets_from
    with pytest.raises(ConfigError, match=r"train.nets_from = 'synthetic': this configuration lacks settings .*"
                                          r"radar\.name=synthetic"):
        _pipeline(raw, trained, "kitti", kitti).run("train")
    no_source = load_config("kitti", {"train.nets_from": "astyx"}, environ={})
    with pytest.raises(PipelineError, match=r"no finished train stage at .*astyx/train"):
        _pipeline(no_source, trained, "kitti", kitti).run("train")
