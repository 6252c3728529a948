"""Nets trained on one dataset synthesizing another (train.nets_from): the radar settings they carry,
a KITTI-layout dataset (no radar) synthesized and exported with the tiny synthetic world's nets."""

from __future__ import annotations

import json
import re
import shutil
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


def _synthetic_only(trained: Path, tmp_path: Path) -> Path:
    """A cache holding a copy of ``trained``'s synthetic dataset only: the other tests write their
    KITTI data (from their own folders) into ``trained``, and a cache refuses another data root."""
    shutil.copytree(trained / "synthetic", tmp_path / "cache" / "synthetic")
    return tmp_path / "cache"


def _pipeline(cfg, cache: Path, dataset: str, data: Path, log=lambda m: None) -> Pipeline:
    env = RunEnv(cfg, str(cache), dataset, str(data))
    return Pipeline(all_stages(), env, Executor(1, progress=False), progress=False, log=log)


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
    # a run (require_trained) goes on where this dataset has no output to lose (refused where it has:
    # below); a misspelt name is refused
    assert with_nets_from(missing, str(trained), require_trained=True) == missing
    with pytest.raises(ConfigError, match="'astyxx' names no dataset profile .*did you mean 'astyx'"):
        with_nets_from(load_config("kitti", {"train.nets_from": "astyxx"}, environ={}), str(trained))
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
    lines: list[str] = []
    pipe = _pipeline(cfg, trained, "kitti", kitti, lines.append)
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
    _check_inputs_outside_training(pipe, trained, reports["synthesize"].notes)
    _check_prior_moved(pipe, trained, reports["train"].summary)
    assert any(f"ego velocity unknown on {KITTI_FRAMES} of {KITTI_FRAMES} frames" in line for line in lines)
    assert f"; {KITTI_FRAMES} of them without a recorded ego motion" in reports["export"].summary["message"]
    assert f"(the RCS column in {cfg.radar.rss_unit}, the unit of the simulated " in reports["export"].summary["message"]
    assert (trained / "kitti" / "export" / "ego_velocity_unknown.txt").read_text().split() == pipe.frame_ids()
    # every frame in OpenPCDet's training/ (the profile's split: train and val about half each; until
    # 2026-12-04 all were test, under testing/, where OpenPCDet reads no label)
    exported = trained / "kitti" / "export" / "radar" / "training"
    assert len(list((exported / "velodyne").glob("*.bin"))) == KITTI_FRAMES
    sets = {name: (exported.parent / "ImageSets" / f"{name}.txt").read_text().split() for name in ("train", "val", "test")}
    assert sorted(sets["train"] + sets["val"]) == pipe.frame_ids() and not sets["test"]
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
    # a dataset taking KITTI's nets takes the world's, from the world's train stage (KITTI's default
    # is View-of-Delft's nets, which may be Astyx's; until 2026-12-04 the prior was moved from the
    # middle dataset's camera, and retraining the first left the last one current)
    from pipeline.transfer import nets_origin
    from stages.train import nets_from_fingerprint

    assert nets_origin(str(trained), "kitti") == "synthetic" and nets_origin(str(trained), "synthetic") == "synthetic"
    chained = load_config("vod", {"train.nets_from": "kitti"}, environ={})
    chain_fp, direct_fp = nets_from_fingerprint(chained, pipe.env), nets_from_fingerprint(_kitti_cfg(trained), pipe.env)
    world_train = trained / "synthetic" / "train"
    assert chain_fp.startswith("kitti>synthetic:") and direct_fp.startswith("synthetic:")  # the form of before
    assert chain_fp.split(":", 1)[1] == direct_fp.split(":", 1)[1]
    # the world's dataset taking KITTI's nets would take its own: refused before its nets are cleared
    own = load_config("synthetic", {**TINY, "train.nets_from": "kitti"}, environ={})
    with pytest.raises(ConfigError, match="its nets are this dataset's own"):
        with_nets_from(own, str(trained))
    with pytest.raises(ConfigError, match="its nets are this dataset's own"):
        _pipeline(own, trained, "synthetic", trained.parent / "world").run("train")
    assert (world_train / "disnet" / "best.safetensors").is_file() and _pipeline(
        load_config("synthetic", TINY, environ={}), trained, "synthetic", trained.parent / "world").is_current("train")
    # the other dataset's nets retrained: this dataset's copy and what it synthesized are stale
    assert pipe.is_current("synthesize")
    _pipeline(load_config("synthetic", TINY, environ={}), trained, "synthetic", trained.parent / "world").run(
        "train", force=True)
    again = _pipeline(_kitti_cfg(trained), trained, "kitti", kitti)
    assert not again.is_current("train") and not again.is_current("synthesize")
    assert nets_from_fingerprint(chained, pipe.env) != chain_fp  # down the chain too
    # two steps for real: a 'vod' train output holding the world's nets (a copy of KITTI's), and
    # KITTI taking vod's: the nets, settings and camera are the world's, from its retrained train stage
    again.run("train")
    shutil.copytree(trained / "kitti" / "train", trained / "vod" / "train")
    via_vod = _pipeline(with_nets_from(load_config("kitti", {"train.nets_from": "vod"}, environ={}), str(trained)),
                        trained, "kitti", kitti)
    report = via_vod.run("train")[-1]
    assert report.summary["message"].startswith("the nets of dataset synthetic (through dataset vod, which took them ")
    direct = json.loads((trained / "vod" / "train" / "metrics.json").read_text())
    record = json.loads((trained / "kitti" / "train" / "metrics.json").read_text())
    assert record["source_camera"] == direct["source_camera"] and record["settings"] == direct["settings"]
    assert record["source_finished"] == (_pipeline(load_config("synthetic", TINY, environ={}), trained, "synthetic",
                                                   trained.parent / "world").env.dir("train").meta()["finished"])
    for net in ("disnet", "rssnet", "placenet"):
        assert (trained / "kitti" / "train" / net / "best.safetensors").read_bytes() == \
            (trained / "synthetic" / "train" / net / "best.safetensors").read_bytes()
    shutil.rmtree(trained / "vod")


def _check_prior_moved(pipe: Pipeline, cache: Path, train_summary: dict) -> None:
    """The train stage records the world's camera; synthesize's map is Dis-Net's with its prior
    moved from that camera to KITTI's (not merely resized)."""
    from pipeline.heatmap import resize_distribution
    from pipeline.inference import disnet_predict, load_disnet
    from pipeline.transfer import camera_from_record, prior_in_target, rebase_prior, source_camera

    camera = camera_from_record(train_summary["source_camera"])
    expected_camera = source_camera(str(cache), "synthetic")
    np.testing.assert_allclose(camera.T_radar_cam, expected_camera.T_radar_cam)
    assert camera.working_wh == tuple(load_config("synthetic", TINY, environ={}).camera.working_size)
    cfg, calib = pipe.env.cfg, pipe.env.store("calibrate")
    net = load_disnet(cfg, cache / "kitti" / "train" / "disnet" / "best.safetensors", device="cpu", saved_arch=True)
    maps, _ = disnet_predict(net, calib.read("image", 0)[None], np.zeros(1, np.float32))
    prior = net.prior_logits.double().exp().numpy()
    moved = prior_in_target(prior, camera, calib.read("K", 0), calib.read("T_radar_cam", 0), cfg.camera.working_size)
    got = pipe.env.store("synthesize").read("pred_map", 0)
    want = resize_distribution(rebase_prior(maps[0], prior, moved), cfg.camera.working_size)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-9)
    assert np.abs(got - resize_distribution(maps[0], cfg.camera.working_size)).sum() > 0.05


def _check_inputs_outside_training(pipe: Pipeline, cache: Path, notes: list[str]) -> None:
    """synthesize counts, per PlaceNet input, the candidates outside the nets' training range (as
    recomputed here for frame 0) and names those above OUTSIDE_NOTE_SHARE after the run."""
    from pipeline.executor import FrameInputs
    from pipeline.placement import FEATURES
    from pipeline.inference import load_placenet
    from stages.patches import candidates, features
    from stages.synthesize import OUTSIDE_NOTE_SHARE

    syn, cfg = pipe.env.store("synthesize"), pipe.env.cfg
    net = load_placenet(cfg, cache / "synthetic" / "train" / "placenet" / "best.safetensors", saved_arch=True)
    f = FrameInputs(pipe.env, 0, pipe.frame_ids()[0])
    points, uv = candidates(f, cfg)
    assert syn.read("candidates", 0) == len(points) > 0
    np.testing.assert_array_equal(syn.read("outside_training", 0), net.outside_range(features(f, points, uv)).sum(0))
    share = np.sum([syn.read("outside_training", i) for i in range(KITTI_FRAMES)], 0) / \
        sum(int(syn.read("candidates", i)) for i in range(KITTI_FRAMES))
    named = [FEATURES[k] for k in np.flatnonzero(share > OUTSIDE_NOTE_SHARE)]
    assert named, share   # a ground plane and a wall under a random image: unlike the world's scenes
    place = [n for n in notes if n.startswith("PlaceNet inputs outside")]
    assert len(place) == 1 and "(nets of 'synthetic')" in place[0], notes
    assert all(f"{name} on {share[FEATURES.index(name)]:.0%}" in place[0] for name in named)
    # RSS-Net's inputs: KITTI without oxts gives every static point Doppler 0, below the 0.5
    # percentile of the world's training points' |Doppler|
    from pipeline.patches import INPUT_SUMMARIES
    rss = np.sum([syn.read("rss_outside", i) for i in range(KITTI_FRAMES)], 0) / \
        sum(int(syn.read("rss_points", i)) for i in range(KITTI_FRAMES))
    assert rss[INPUT_SUMMARIES.index("abs_doppler_mps")] > OUTSIDE_NOTE_SHARE
    (rss_note,) = [n for n in notes if n.startswith("RSS-Net inputs outside")]
    assert f"abs_doppler_mps on {rss[INPUT_SUMMARIES.index('abs_doppler_mps')]:.0%}" in rss_note


def test_the_train_stage_refuses_settings_the_nets_were_not_trained_with(trained, tmp_path):
    kitti = _kitti(tmp_path / "kitti")
    trained = _synthetic_only(trained, tmp_path)
    raw = load_config("kitti", {"train.nets_from": "synthetic"}, environ={})   # not through with_nets_from
    with pytest.raises(ConfigError, match=r"train.nets_from = 'synthetic': this configuration lacks settings .*"
                                          r"radar\.name=synthetic"):
        _pipeline(raw, trained, "kitti", kitti).run("train")
    no_source = load_config("kitti", {"train.nets_from": "astyx"}, environ={})
    with pytest.raises(PipelineError, match=r"no finished train stage at .*astyx/train"):
        _pipeline(no_source, trained, "kitti", kitti).run("train")


def test_a_radar_of_other_rss_units_is_evaluated_on_position_and_doppler(trained, tmp_path):
    """The tiny world's nets (dBsm, no Doppler wrap) evaluated on an Astyx-layout dataset (dB(Mag),
    Doppler wrapped into 10.39 m/s): the RSS gate would match nothing, so matched F1 gates position
    and Doppler (modulo Astyx's span) only, RSS distances are empty, and the report says so."""
    from pipeline.executor import FrameInputs
    from pipeline.metrics import frame_metrics
    from pipeline.readers.testing import ASTYX_SPAN_MPS, make_astyx_dataset
    from pipeline.transfer import Comparison, comparison

    make_astyx_dataset(tmp_path / "astyx", n_frames=6, n_radar=300)
    sets = {"camera.full_size": "64,48", "camera.crop_rows": "0,48", "camera.working_size": "64,48",
            "split.rule": "random", "split.fractions": "0.5,0,0.5", "synth.split": "all", "eval.figure_frames": "1"}
    cfg = with_nets_from(load_config("astyx", {"train.nets_from": "synthetic", **sets}, environ={}), str(trained),
                         explicit=sets)
    compared = comparison(cfg)
    assert not compared.rss and compared.doppler_span_mps == compared.real_doppler_span_mps == ASTYX_SPAN_MPS
    # the recorded radar is read with Astyx's own Doppler sign and span, not the nets' radar's
    from pipeline.readers import get_reader
    assert cfg.radar.doppler_span_mps == 0.0
    own, theirs = (get_reader(c, tmp_path / "astyx").read("000001")
                   for c in (load_config("astyx", sets, environ={}), cfg))
    np.testing.assert_array_equal(theirs.radar_D, own.radar_D)
    np.testing.assert_allclose(theirs.ego_velocity_D, [8.0, 0.0, 0.0], atol=0.05)
    assert comparison(load_config("astyx", environ={})) == Comparison(True, ASTYX_SPAN_MPS, ASTYX_SPAN_MPS, ())
    astyx_on_vod = load_config("vod", {"train.nets_from": "astyx"}, environ={}).with_overrides(
        settings(load_config("astyx", environ={})))
    got = comparison(astyx_on_vod)
    assert (got.rss, got.doppler_span_mps, got.real_doppler_span_mps) == (False, ASTYX_SPAN_MPS, 0.0)
    assert "synthesized radar's span 10.3936 m/s (the real radar does not wrap)" in got.notes[1]
    assert got.notes[2].startswith("the baselines' counts and maps come from this dataset's own radar on its train "
                                   "split, which the nets of 'astyx' never saw")
    pipe = _pipeline(cfg, trained, "astyx", tmp_path / "astyx")
    pipe.run("evaluate")
    report = json.loads((trained / "astyx" / "evaluate" / "report.json").read_text())
    assert "RSS not compared" in report["meta"]["compared"] and "10.3936 m/s" in report["meta"]["compared"]
    assert "RSS not compared" in (trained / "astyx" / "evaluate" / "report.md").read_text()
    assert "(with eval.split = all, the evaluated frames among them)" not in report["meta"]["compared"]  # test split
    assert report["distribution_distances"]["model"]["rss"] is None and report["distribution_distances"]["model"]["range_m"] is not None
    part = pipe.env.store("evaluate-frames")
    test = np.flatnonzero(part.status() == DONE)
    assert len(test)
    f1_rss_gated, f1 = [], []
    for i in test:
        f = FrameInputs(pipe.env, int(i), pipe.frame_ids()[int(i)])
        syn = f.get("synthesize", "points")[:, [0, 1, 2, 8, 7]].astype(np.float64)
        real = f.get("calibrate", "radar").astype(np.float64)
        ours = frame_metrics(syn, real, gate_rss=np.inf, doppler_span_mps=ASTYX_SPAN_MPS)
        np.testing.assert_allclose(part.read("metrics", int(i))[0, -1], ours["f1"])   # model row, F1 column
        f1.append(ours["f1"])
        f1_rss_gated.append(frame_metrics(syn, real, doppler_span_mps=ASTYX_SPAN_MPS)["f1"])
    assert max(f1) > 0 and max(f1_rss_gated) == 0


def _rot_x(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def _T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def test_dis_nets_prior_moves_to_the_same_directions_in_another_camera():
    """The source's prior, a blob in one direction from the radar, lands where that direction
    projects in a target camera of another focal length, size and pitch; the same camera leaves
    it as it is; its spread follows the focal length."""
    from pipeline.transfer import SourceCamera, prior_in_target, rebase_prior

    h, w = 40, 80
    K_s = np.array([[100.0, 0, 79.5], [0, 100.0, 19.5], [0, 0, 1]])     # working 160 x 40 pixels
    R_s = R_CAM_D.T                                                      # camera -> {D}: x fwd, y left, z up
    source = SourceCamera(K_s, _T(R_s, np.zeros(3)), (160, 40), 20.0)
    direction_D = np.array([1.0, 0.15, 0.05])                           # slightly left and up

    def cell_of(K, R, d, size):
        """The (h, w) grid cell over a working image of ``size`` pixels that direction d projects to."""
        ray = K @ (R.T @ d)
        u, v = ray[:2] / ray[2]
        return (u + 0.5) * w / size[0] - 0.5, (v + 0.5) * h / size[1] - 0.5

    cx, cy = cell_of(K_s, R_s, direction_D, (160, 40))
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    prior = np.exp(-((jj - cx) ** 2 + (ii - cy) ** 2) / (2 * 1.5 ** 2)) + 1e-9
    prior /= prior.sum()
    same = prior_in_target(prior, source, K_s, _T(R_s, np.zeros(3)), (160, 40))
    np.testing.assert_allclose(same, prior, rtol=1e-4, atol=1e-12)
    # another camera: twice the focal length, 200 x 60 pixels, pitched 4 degrees down
    K_t = np.array([[200.0, 0, 99.5], [0, 200.0, 29.5], [0, 0, 1]])
    R_t = R_s @ _rot_x(4.0)
    moved = prior_in_target(prior, source, K_t, _T(R_t, np.zeros(3)), (200, 60))
    assert moved.shape == (h, w) and moved.sum() == pytest.approx(1.0)
    mx, my = (moved * jj).sum(), (moved * ii).sum()
    tx, ty = cell_of(K_t, R_t, direction_D, (200, 60))
    assert abs(mx - tx) < 0.3 and abs(my - ty) < 0.3, ((mx, my), (tx, ty))
    assert np.hypot(tx - cx, ty - cy) > 5   # a plain resize would leave it at (cx, cy)
    spread = np.sqrt((moved * (jj - mx) ** 2).sum())                            # focal x 2 * (80/200) / (80/160)
    assert spread == pytest.approx(1.5 * 2 * (w / 200) / (w / 160), rel=0.1)
    # a camera 1 m above and 1.5 m behind the radar: the blob's place 20 m from the radar (range_m)
    # seen from there, not its direction
    offset = np.array([-1.5, 0.0, 1.0])
    raised = prior_in_target(prior, source, K_t, _T(R_t, offset), (200, 60))
    far_point = 20.0 * direction_D / np.linalg.norm(direction_D)
    tx, ty = cell_of(K_t, R_t, far_point - offset, (200, 60))
    mx, my = (raised * jj).sum(), (raised * ii).sum()
    assert abs(mx - tx) < 0.3 and abs(my - ty) < 0.3, ((mx, my), (tx, ty))
    assert ty - cell_of(K_t, R_t, direction_D, (200, 60))[1] > 1.5   # lower in the image than its direction
    # the map made with the source prior, as made with the moved one
    rebased = rebase_prior(prior * 0 + 1.0 / prior.size, prior, moved)
    np.testing.assert_allclose(rebased, moved / prior / (moved / prior).sum(), rtol=1e-5)


def test_a_run_naming_untrained_nets_leaves_the_outputs_made_with_trained_ones(trained, tmp_path):
    """KITTI's calibrate made with the synthetic nets' radar settings: a run naming nets not trained
    in this cache (or a misspelt dataset) is refused before any stage, the output untouched (until
    2026-12-04 the profile's settings first replaced calibrate, heatmaps and patches). Where this
    dataset has no output yet, nothing is lost: the run goes on with the profile's settings."""
    from click.testing import CliRunner

    from pipeline.cli import main

    cache = _synthetic_only(trained, tmp_path)
    kitti = _kitti(tmp_path / "kitti")
    args = ["run", "calibrate", "--workers", "1", "--dataset", "kitti", "--data-root", str(kitti), "--cache", str(cache)]
    assert CliRunner().invoke(main, [*args, "--set", "train.nets_from=synthetic"]).exit_code == 0
    calib = cache / "kitti" / "calibrate.zarr" / "zarr.json"
    before = calib.read_bytes()
    for name, words in (("msc", "no finished train stage at .*msc/train.*nothing was run"),
                        ("synthetik", "names no dataset profile .*did you mean 'synthetic'")):
        out = CliRunner().invoke(main, [*args, "--set", f"train.nets_from={name}"])
        assert out.exit_code == 2 and re.search(words, out.output), out.output
    assert calib.read_bytes() == before
    for _ in range(2):  # nor where its outputs were made with the profile's settings (nothing to lose)
        fresh = CliRunner().invoke(main, [*args[:-1], str(tmp_path / "other"), "--set", "train.nets_from=msc"])
        assert fresh.exit_code == 0, fresh.output


@pytest.mark.realdata
def test_export_counts_points_on_objects_of_unknown_velocity_on_real_vod_frames(trained, tmp_path):
    """The View-of-Delft example frames hold no tracks, so no label has a velocity: their points get
    a static object's Doppler. Until 2026-12-05 the export said nothing of it (the audit found a
    quarter of the points on such objects, cyclists among them)."""
    from pipeline.frame import LABEL_COLUMNS
    from stages.export import UNKNOWN_OBJECT_MOTION_LIST

    col = {name: i for i, name in enumerate(LABEL_COLUMNS)}

    def inside_any_box(points: np.ndarray, rows: np.ndarray, margin_m: float = 0.3) -> int:
        """Points inside a box grown by the margin, every (point, box) pair tested: by other means
        than the stage's slices of the points sorted by x."""
        rel = points[:, None, :] - rows[None, :, [col["cx"], col["cy"], col["cz"]]]        # (N, L, 3)
        cos, sin = np.cos(rows[:, col["yaw"]]), np.sin(rows[:, col["yaw"]])
        local = np.stack([cos * rel[..., 0] + sin * rel[..., 1], -sin * rel[..., 0] + cos * rel[..., 1],
                          rel[..., 2]], axis=-1)
        half = rows[:, [col["length"], col["width"], col["height"]]] / 2 + margin_m
        return int(np.all(np.abs(local) <= half, axis=-1).any(axis=1).sum())

    vod = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "vod_example"
    if not vod.is_dir():
        pytest.skip("../shared/data/vod_example not present")
    cache = _synthetic_only(trained, tmp_path)
    sets = {"synth.split": "all", "synth.count": "oracle"}
    cfg = with_nets_from(load_config("vod", {"train.nets_from": "synthetic", **sets}, environ={}), str(cache),
                         explicit=sets)
    pipe = _pipeline(cfg, cache, "vod", vod)
    summary = pipe.run("export")[-1].summary
    syn, calib = pipe.env.store("synthesize"), pipe.env.store("calibrate")
    ids = pipe.frame_ids()
    for i in range(len(ids)):
        assert np.isnan(calib.read("labels", i)[:, col["vx"]]).all()  # no velocity recorded: every box counts
    per_frame = {fid: inside_any_box(syn.read("points", i)[:, :3].astype(np.float64),
                                     calib.read("labels", i).astype(np.float64)) for i, fid in enumerate(ids)}
    assert summary["object_motion_unknown"] == {"frames": 2, "points": sum(per_frame.values())}
    assert sum(per_frame.values()) > 0 and all(per_frame.values())
    assert (cache / "vod" / "export" / UNKNOWN_OBJECT_MOTION_LIST).read_text().split() == ids
    assert f"; {sum(per_frame.values())} of the points (" in summary["message"]
    assert "lie on labelled objects whose velocity the dataset does not record" in summary["message"]


def test_the_moved_prior_keeps_the_mass_of_each_part_of_the_source_view():
    """A uniform source prior seen by a target camera yawed 15 degrees (twice the focal length,
    inside the source's view): a target region's share is the share of the source image its
    directions cover there (the cells of the source grid per target cell), hand-computed as the
    area of the region's corners carried to the source image (a rotation: a homography)."""
    from pipeline.transfer import SourceCamera, prior_in_target

    h, w = 40, 80
    K_s = np.array([[100.0, 0, 79.5], [0, 100.0, 19.5], [0, 0, 1]])
    R_s = R_CAM_D.T
    source = SourceCamera(K_s, _T(R_s, np.zeros(3)), (160, 40), 20.0)
    a = np.radians(15.0)
    R_t = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]) @ R_s
    K_t = np.array([[200.0, 0, 79.5], [0, 200.0, 19.5], [0, 0, 1]])
    moved = prior_in_target(np.full((h, w), 1.0 / (h * w)), source, K_t, _T(R_t, np.zeros(3)), (160, 40))

    def source_area(corners):
        pts = []
        for u, v in corners:
            p = K_s @ (R_s.T @ (R_t @ np.linalg.solve(K_t, [u, v, 1.0])))
            pts.append(p[:2] / p[2])
        x, y = np.array(pts).T
        return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))

    left = source_area([(-0.5, -0.5), (79.5, -0.5), (79.5, 39.5), (-0.5, 39.5)])
    right = source_area([(79.5, -0.5), (159.5, -0.5), (159.5, 39.5), (79.5, 39.5)])
    assert left / (left + right) > 0.55                       # the yaw stretches one side
    assert moved[:, :w // 2].sum() == pytest.approx(left / (left + right), abs=2e-3)


def test_doppler_is_compared_modulo_the_synthesized_radars_span_when_both_wrap():
    """comparison(): 'modulo the simulated radar's span when it aliases, else modulo the real
    radar's'. Astyx's own radar wraps into 10.39 m/s; nets of a radar that wraps into 20 m/s:
    compared modulo 20, and the note says that the real radar's span differs. With eval.split =
    train the baselines' training frames are evaluated ones too, and the note says so."""
    from pipeline.readers.testing import ASTYX_SPAN_MPS
    from pipeline.transfer import comparison

    cfg = load_config("astyx", {"train.nets_from": "vod", "radar.doppler_span_mps": "20"}, environ={})
    got = comparison(cfg)
    assert (got.doppler_span_mps, got.real_doppler_span_mps) == (20.0, ASTYX_SPAN_MPS)
    assert any("modulo the synthesized radar's span 20 m/s" in n for n in got.notes)
    train = comparison(load_config("vod", {"train.nets_from": "astyx", "eval.split": "train"}, environ={}))
    assert "(with eval.split = train, the evaluated frames among them)" in train.notes[-1]


def test_a_mixed_map_keeps_its_prior_share_when_the_prior_is_moved():
    """With disnet.prior_mix the network's map already holds a share w of the source prior: moved
    to another camera, the network's part is rebased and the target prior mixed in at the same w
    (rebasing the mixed map as a whole would change the share frame by frame)."""
    from pipeline.transfer import rebase_mixed_prior, rebase_prior

    rng = np.random.default_rng(4)
    net, source, target = (rng.gamma(0.5, size=(12, 20)) + 1e-3 for _ in range(3))
    net, source, target = net / net.sum(), source / source.sum(), target / target.sum()
    for w in (0.0, 0.3, 0.8):
        mixed = (1 - w) * rebase_prior(net, np.ones_like(net), np.ones_like(net)) + w * source
        got = rebase_mixed_prior(mixed, source, target, w)
        want = (1 - w) * rebase_prior(net, source, target) + w * target
        assert got.dtype == np.float32 and abs(float(got.sum()) - 1) < 1e-5
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(rebase_mixed_prior(source, source, target, 1.0), target, rtol=1e-6)
    whole = rebase_prior((1 - 0.5) * net + 0.5 * source, source, target)  # what rebasing the mix would give
    assert not np.allclose(whole, rebase_mixed_prior((1 - 0.5) * net + 0.5 * source, source, target, 0.5), rtol=1e-3)


def test_the_nets_of_a_dataset_on_a_remote_cache_are_taken_through_a_local_copy(trained, tmp_path):
    """train.nets_from on a remote (fsspec) cache: the other dataset's checkpoints are read from a
    local copy of its finished train output (its remote path is no local folder) and uploaded with
    this dataset's train output, the same bytes as on a local cache."""
    import uuid

    import fsspec

    name = f"remote-{uuid.uuid4().hex[:8]}"
    fs = fsspec.filesystem("memory")
    fs.put(str(trained / "synthetic"), f"/{name}/synthetic", recursive=True)
    try:
        cache = f"memory://{name}"
        cfg = with_nets_from(load_config("kitti", {"train.nets_from": "synthetic",
                                                   "run.staging_dir": str(tmp_path / "staging")}, environ={}), cache)
        report = _pipeline(cfg, cache, "kitti", _kitti(tmp_path / "kitti")).run("train")[-1]
        assert report.summary["message"].startswith("the nets of dataset synthetic (disnet, rssnet, placenet;")
        for net in ("disnet", "rssnet", "placenet"):
            assert fs.cat_file(f"/{name}/kitti/train/{net}/best.safetensors") == \
                (trained / "synthetic" / "train" / net / "best.safetensors").read_bytes(), net
        assert len(list((tmp_path / "staging").glob("train-*/copies/*/disnet/best.safetensors"))) == 1
    finally:
        fs.rm(f"/{name}", recursive=True)


def test_a_run_leaving_out_the_nets_a_dataset_was_made_with_is_refused(trained, tmp_path, monkeypatch):
    """A target made with `--set train.nets_from=...` and a later command without it (found
    2026-12-06 on the View-of-Delft frames with the Astyx nets): the profile's train.nets_from
    (empty for VoD: train its own; 'vod' for KITTI) made every output stale, and the run recomputed
    them from calibrate with the profile's radar, replacing the transferred outputs without a word.
    It is now refused, naming the --set that goes on; an explicit train.nets_from changes the nets."""
    from click.testing import CliRunner

    from pipeline.cli import main

    cache = _synthetic_only(trained, tmp_path)
    kitti = _kitti(tmp_path / "kitti")
    args = ["run", "train", "--workers", "1", "--dataset", "kitti", "--data-root", str(kitti), "--cache", str(cache)]
    assert CliRunner().invoke(main, [*args, "--set", "train.nets_from=synthetic"]).exit_code == 0
    record = (cache / "kitti" / "train" / "_stage.json").read_bytes()
    for extra in ((), ("--dry-run",)):
        out = CliRunner().invoke(main, [*args, *extra])
        assert out.exit_code == 2 and "Traceback" not in out.output, out.output
        assert ("error: dataset 'kitti': its outputs in this cache were made with the nets of 'synthetic' "
                "(train.nets_from = synthetic); without train.nets_from this run would take those of 'vod' (the "
                "profile's train.nets_from)") in out.output, out.output
        assert "Add `--set train.nets_from=synthetic` to go on with them" in out.output
    assert (cache / "kitti" / "train" / "_stage.json").read_bytes() == record  # nothing was run
    status = CliRunner().invoke(main, ["status", *args[4:]])  # says why every stage reads stale
    assert status.exit_code == 0 and status.output.splitlines()[1] == (
        "(made with the nets of 'synthetic', which this command leaves out: the stages below are as a run without "
        "them would find them; add --set train.nets_from=synthetic)"), status.output
    assert "made with the nets" not in CliRunner().invoke(main, ["status", *args[4:], "--set",
                                                                 "train.nets_from=synthetic"]).output
    again = CliRunner().invoke(main, [*args, "--set", "train.nets_from=synthetic"])
    assert again.exit_code == 0 and "train           up to date" in again.output, again.output
    monkeypatch.setenv("PIPELINE__TRAIN__NETS_FROM", "synthetic")
    assert CliRunner().invoke(main, args).exit_code == 0
    # set explicitly to other nets, the run goes on with them (here: none trained in this cache)
    monkeypatch.delenv("PIPELINE__TRAIN__NETS_FROM")
    other = CliRunner().invoke(main, [*args, "--set", "train.nets_from=msc"])
    assert other.exit_code == 2 and "no finished train stage at" in other.output, other.output
