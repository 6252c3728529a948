"""Astyx HiRes2019 and demo readers, and the alias-aware ego-velocity estimator."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from pipeline.config import load_config
from pipeline.egomotion import estimate_ego_velocity, estimate_yaw_rate, fit_compensation_pair
from pipeline.errors import ReaderError
from pipeline.geometry import invert_transform, project_to_image, radial_velocity, wrap_doppler
from pipeline.readers import get_reader
from pipeline.readers.testing import ASTYX_SPAN_MPS, make_astyx_dataset
from pipeline.synthesis import object_velocities_for_points

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
HIRES = DATA / "astyx_hires2019" / "dataset_astyx_hires2019"
DEMO = DATA / "astyx_demo" / "dataset_astyx_demo"


def _need(path: Path) -> None:
    if not path.is_dir():
        pytest.skip(f"{path} not present")


def _demo_cfg():
    cfg = load_config("astyx")
    return replace(cfg, dataset=replace(cfg.dataset, reader="astyx_demo"))


# -- estimator on generated scans ----------------------------------------------------------------

@pytest.mark.parametrize("v_true", [(0.0, 0.0, 0.0), (3.0, 0.2, 0.0), (7.8, -0.4, 0.1), (15.3, 0.3, 0.3),
                                    (24.0, 1.0, 0.0), (-0.8, 0.0, 0.0)])  # the last: reversing
def test_estimator_resolves_aliasing_with_outliers(v_true):
    rng = np.random.default_rng(3)
    n = 800
    az, el, r = rng.uniform(-0.9, 0.9, n), rng.uniform(-0.3, 0.3, n), rng.uniform(3, 80, n)
    pts = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)
    rate = -(pts / r[:, None]) @ np.asarray(v_true)
    rate[:200] += rng.uniform(-8, 8, 200)  # 25% moving targets
    measured = np.round(wrap_doppler(rate, ASTYX_SPAN_MPS) / 0.0812) * 0.0812  # quantised like the 6455
    fit = estimate_ego_velocity(pts, measured, ASTYX_SPAN_MPS)
    np.testing.assert_allclose(fit.velocity_D[:2], v_true[:2], atol=0.1)
    assert fit.n_used >= 550
    # the RMS is over the inliers only: about the quantisation step / sqrt(12), not the moving targets'
    assert fit.residual_rms_mps < 0.05


def test_compensation_pair_is_exact_and_handles_too_few_points():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3)) + [10, 0, 0]
    v = np.array([4.0, -0.5, 0.2])
    u = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    fit = fit_compensation_pair(pts, -(u @ v) + 1.0, np.full(50, 1.0))
    np.testing.assert_allclose(fit.velocity_D, v, atol=1e-9)
    assert fit.residual_rms_mps < 1e-9 and fit.n_used == 50
    assert np.isnan(fit_compensation_pair(pts[:2], np.zeros(2), np.zeros(2)).velocity_D).all()


def test_compensation_pair_condition_number():
    """The VoD reader falls back to poses when the design's condition number exceeds 1e3."""
    # unit directions x, x, y, z: u^T u = diag(2, 1, 1), singular values sqrt(2), 1, 1
    axes = np.array([[5.0, 0.0, 0.0], [7.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 0.0, 2.0]])
    assert fit_compensation_pair(axes, np.zeros(4), np.zeros(4)).condition == pytest.approx(np.sqrt(2), rel=1e-12)
    # points within 1e-4 rad of one direction: the lateral and vertical speeds are barely observable
    rng = np.random.default_rng(1)
    narrow = np.column_stack([np.full(20, 10.0), rng.uniform(-1e-3, 1e-3, (20, 2))])
    assert fit_compensation_pair(narrow, np.zeros(20), np.zeros(20)).condition > 1e3


def test_estimator_ignores_points_at_the_origin():
    rng = np.random.default_rng(2)
    az = rng.uniform(-0.9, 0.9, 300)
    pts = np.column_stack([20 * np.cos(az), 20 * np.sin(az), np.zeros(300)])
    rate = -(pts / 20.0) @ np.array([5.0, 0.5, 0.0])
    fit = estimate_ego_velocity(pts, rate, ASTYX_SPAN_MPS)
    with_origin = estimate_ego_velocity(np.vstack([pts, np.zeros((10, 3))]), np.r_[rate, np.zeros(10)], ASTYX_SPAN_MPS)
    assert with_origin.n_points == 310 and with_origin.n_used == fit.n_used == 300
    np.testing.assert_allclose(with_origin.velocity_D, fit.velocity_D)


# -- fixture in the exact layout -------------------------------------------------------------------

def test_fixture_reads_aliased_doppler_and_labels(tmp_path):
    ego = make_astyx_dataset(tmp_path, n_frames=2, speed_mps=8.0)
    reader = get_reader(load_config("astyx").with_overrides({"camera.full_size": "64,48"}), tmp_path)
    assert reader.frame_ids() == ["000000", "000001"]
    rec = reader.read("000001")
    np.testing.assert_allclose(rec.ego_velocity_D, ego, atol=0.05)
    raw = np.loadtxt(tmp_path / "radar_6455/000001.txt", skiprows=2)
    np.testing.assert_allclose(rec.radar_D[:, 3], -raw[:, 3], atol=1e-6)  # sign flipped, still wrapped
    assert np.abs(rec.radar_D[:, 3]).max() <= ASTYX_SPAN_MPS / 2 + 1e-6
    assert rec.labels[0].yaw_rad == pytest.approx(0.5)
    assert rec.lidar_D.shape == (300, 3) and rec.image.shape == (48, 64, 3)



def test_a_data_root_above_the_dataset_names_the_folder_that_holds_its_index(tmp_path):
    """The usual mistake, the folder above dataset_astyx_hires2019/: the error names the folder
    that holds dataset.json (it said only 'missing dataset index file')."""
    make_astyx_dataset(tmp_path / "dataset_astyx_hires2019", n_frames=1)
    cfg = load_config("astyx").with_overrides({"camera.full_size": "64,48"})
    with pytest.raises(ReaderError, match="missing dataset index file; --data-root is the folder that holds it: "
                                          + str(tmp_path / "dataset_astyx_hires2019")):
        get_reader(cfg, tmp_path).frame_ids()
    assert get_reader(cfg, tmp_path / "dataset_astyx_hires2019").frame_ids() == ["000000"]
    with pytest.raises(ReaderError, match="missing dataset index file$"):
        get_reader(cfg, tmp_path / "dataset_astyx_hires2019" / "radar_6455").frame_ids()

# -- real files --------------------------------------------------------------------------------

@pytest.mark.realdata
def test_demo_ego_speed_matches_can_bus(capsys):
    _need(DEMO)
    reader = get_reader(_demo_cfg(), DEMO)
    assert reader.frame_ids() == [f"{i:06d}" for i in range(5)]
    errors = {}
    for fid in reader.frame_ids():
        speed = float(np.linalg.norm(reader.estimate_ego(fid).velocity_D))
        errors[fid] = speed - reader.can_speed_mps(fid)
        print(f"astyx demo {fid}: CAN {reader.can_speed_mps(fid):6.2f} m/s, radar {speed:6.2f} m/s, "
              f"error {errors[fid]:+.2f} m/s")
    assert max(abs(e) for e in errors.values()) < 1.0
    with pytest.raises(ReaderError, match="no camera or lidar"):
        reader.read("000000")


@pytest.fixture(scope="module")
def hires():
    _need(HIRES)
    return get_reader(load_config("astyx"), HIRES)


@pytest.mark.realdata
def test_hires_index_counts(hires):
    assert len(hires.frame_ids()) == 141
    assert hires.report()["skipped_missing"] == 546 - 141


@pytest.mark.realdata
@pytest.mark.slow
def test_hires_every_present_frame_reads(hires):
    speeds = {fid: float(np.linalg.norm(hires.read(fid).ego_velocity_D)) for fid in hires.frame_ids()}
    assert len(speeds) == 141 and max(speeds.values()) < 25.0


@pytest.mark.realdata
def test_hires_calibration_sets_and_geometry(hires):
    """Both calibration sets (frames < 470 and >= 470) differ; labelled cars within 20 m hold lidar
    points, more with the (w, x, y, z) quaternion yaw than with the yaw turned by 90 deg; label
    centres within +/-25 deg of the camera axis project into the image."""
    recs = {f: hires.read(f) for f in ("000000", "000300", "000480", "000545")}
    assert not np.allclose(recs["000000"].T_radar_cam, recs["000480"].T_radar_cam)
    np.testing.assert_allclose(recs["000000"].T_radar_cam, recs["000300"].T_radar_cam)
    ours = turned = 0
    for rec in recs.values():
        for obj in rec.labels:
            if np.linalg.norm(obj.center_D) > 20:
                continue
            ours += _lidar_in_box(rec.lidar_D, obj, obj.yaw_rad)
            turned += _lidar_in_box(rec.lidar_D, obj, obj.yaw_rad + np.pi / 2)
        centres = np.array([o.center_D for o in rec.labels])
        ahead = np.abs(np.arctan2(centres[:, 1], centres[:, 0])) < np.radians(25)
        _, _, valid = project_to_image(centres[ahead], rec.K, invert_transform(rec.T_radar_cam), (2048, 618))
        assert valid.all()
    assert ours > 2 * turned


@pytest.mark.realdata
def test_hires_frame_speeds(hires):
    """Frame 000363 (the shared subset has no 000025) and a standstill frame."""
    assert np.linalg.norm(hires.read("000363").ego_velocity_D) == pytest.approx(6.9, abs=0.3)
    assert np.linalg.norm(hires.read("000482").ego_velocity_D) < 0.2


@pytest.mark.realdata
def test_hires_turn_between_scans_matches_opencv_icp(hires):
    """Frames 000005 -> 000006 (0.1 s apart, the car turning): the yaw rate of the lidar overlay
    agrees with OpenCV's point-to-plane ICP (cv2.ppf_match_3d_ICP, 6 degrees of freedom, measured
    2026-12-06: -0.485 deg, i.e. -0.085 rad/s; 0.3 m voxels: -0.484 deg) within 0.005 rad/s."""
    a, b = hires.read("000005"), hires.read("000006")
    dt = b.timestamp_s - a.timestamp_s
    assert dt == pytest.approx(0.1, abs=0.005)
    rate = estimate_yaw_rate(a.lidar_D, b.lidar_D, (a.ego_velocity_D + b.ego_velocity_D) / 2, dt)
    assert rate == pytest.approx(-0.085, abs=0.005)


@pytest.mark.realdata
def test_hires_box_velocities_do_not_depend_on_the_order_frames_are_read_in():
    """Dask workers read frames in any order: frame 000006's velocities are the same to the bit
    read after 000005, before it, or alone (the turn between two scans is estimated from the
    earlier to the later whichever is read first; the other way round gives -0.0857 rad/s against
    -0.0874 between 000005 and 000006)."""
    _need(HIRES)
    runs = []
    for ids in (["000005", "000006"], ["000007", "000006"], ["000006"]):
        reader = get_reader(load_config("astyx"), HIRES)
        runs.append([reader.read(f) for f in ids][-1])
    v = [np.array([o.velocity_D for o in rec.labels]) for rec in runs]
    assert np.isfinite(v[0]).any()
    np.testing.assert_array_equal(v[0], v[1])
    np.testing.assert_array_equal(v[0], v[2])


@pytest.mark.realdata
def test_hires_box_velocities_agree_with_the_radar():
    """Frames 000240-000314 (30 frames, traffic): the boxes of the neighbouring frames give most
    boxes a velocity (none before 2026-12-06), and the real radar's Doppler on those boxes agrees
    with it far better than with a static box's (measured 2026-12-06: 152 boxes, 0.96 of the points
    within 2.5 m/s of the velocity's Doppler against 0.60 of a static box's)."""
    _need(HIRES)
    reader = get_reader(load_config("astyx"), HIRES)
    ids = [f for f in reader.frame_ids() if 240 <= int(f) <= 314]
    near = {"moving": 0, "static": 0}
    n_points = 0
    for fid in ids:
        rec = reader.read(fid)
        known = [o for o in rec.labels if not np.isnan(o.velocity_D[0])]
        points, doppler = rec.radar_D[:, :3].astype(np.float64), rec.radar_D[:, 3].astype(np.float64)
        v_obj = object_velocities_for_points(points, known)
        marker = object_velocities_for_points(points, [replace(o, velocity_D=np.ones(3, np.float32)) for o in known])
        on_box = np.any(marker != 0, axis=1)
        n_points += int(on_box.sum())
        for key, v in (("moving", v_obj[on_box]), ("static", None)):
            rate = radial_velocity(points[on_box], rec.ego_velocity_D, v)
            near[key] += int((np.abs(wrap_doppler(rate - doppler[on_box], ASTYX_SPAN_MPS)) <= 2.5).sum())
    assert len(ids) == 30 and reader.report()["objects_velocity_by_box_matching"] >= 140
    assert n_points > 3000
    assert near["moving"] / n_points > 0.9 and near["static"] / n_points < 0.7


def _lidar_in_box(lidar_D: np.ndarray, obj, yaw: float) -> int:
    d = lidar_D - obj.center_D
    c, s = np.cos(yaw), np.sin(yaw)
    return int(((np.abs(d[:, 0] * c + d[:, 1] * s) <= obj.size_lwh_m[0] / 2)
                & (np.abs(-d[:, 0] * s + d[:, 1] * c) <= obj.size_lwh_m[1] / 2)
                & (np.abs(d[:, 2]) <= obj.size_lwh_m[2] / 2)).sum())


def test_calibrate_counts_radar_points_beyond_max_range(tmp_path):
    """Points dropped beyond radar.max_range_m are counted and said after the run: kept + dropped
    at 30 m equals what a 1000 m limit keeps, and the note under calibrate's line gives both."""
    from pipeline.executor import Executor, RunEnv
    from pipeline.runner import Pipeline
    from stages import calibrate

    make_astyx_dataset(tmp_path / "data", n_frames=2, n_radar=400)  # ranges 3-45 m

    def run(max_range: float) -> tuple[int, int, list[str]]:
        cfg = load_config("astyx").with_overrides({"camera.full_size": "64,48", "camera.crop_rows": "0,48",
                                                   "camera.working_size": "64,48", "radar.max_range_m": max_range})
        lines: list[str] = []
        env = RunEnv(cfg=cfg, cache_root=str(tmp_path / f"cache{max_range:g}"), dataset="astyx",
                     data_root=str(tmp_path / "data"))
        Pipeline([calibrate.STAGE], env, Executor(1), progress=False, log=lines.append).run("calibrate")
        store = env.store("calibrate")
        kept = int(np.asarray(store.array("radar_count")[:]).sum())
        return kept, int(np.asarray(store.array("radar_beyond_range")[:]).sum()), lines

    everything, none_beyond, lines_far = run(1000.0)
    kept, beyond, lines = run(30.0)
    assert none_beyond == 0 and not any("dropped" in line for line in lines_far)
    assert 0 < beyond and kept + beyond == everything
    note = [line for line in lines if "dropped" in line]
    assert len(note) == 1 and f"{beyond:,} of {everything:,} in the field of view" in note[0], lines
    assert "radar.max_range_m = 30 m" in note[0] and "on 2 of 2 frames" in note[0]
    # a damaged chunk of another frame: the summary says it cannot be made, the run goes on
    chunk = tmp_path / "cache30" / "astyx" / "calibrate.zarr" / "radar_beyond_range" / "c" / "0"
    chunk.write_bytes(b"garbage")
    lines = []
    cfg = load_config("astyx").with_overrides({"camera.full_size": "64,48", "camera.crop_rows": "0,48",
                                               "camera.working_size": "64,48", "radar.max_range_m": 30.0})
    env = RunEnv(cfg=cfg, cache_root=str(tmp_path / "cache30"), dataset="astyx", data_root=str(tmp_path / "data"))
    report = Pipeline([calibrate.STAGE], env, Executor(1), progress=False, log=lines.append).run(
        "calibrate", frames=[1], force=True)[0]
    assert report.processed == 1 and report.notes[0].startswith("summary unavailable:") and "radar_beyond_range" in \
        report.notes[0], report.notes


def test_calibrate_reads_frames_added_since_a_run_in_the_same_process(tmp_path):
    """A cluster's workers outlive a run and keep what they read of the dataset (its reader, the
    split): frames added since are read as the new index has them, into the split a fresh process
    gives (the kept reader called the new frame unknown and failed it)."""
    from pipeline import executor
    from pipeline.executor import Executor, RunEnv
    from pipeline.runner import Pipeline
    from stages import calibrate

    cfg = load_config("astyx").with_overrides({"camera.full_size": "64,48", "camera.crop_rows": "0,48",
                                               "camera.working_size": "64,48", "split.block_len": "1"})

    def run(cache: str):
        env = RunEnv(cfg=cfg, cache_root=str(tmp_path / cache), dataset="astyx", data_root=str(tmp_path / "data"))
        report = Pipeline([calibrate.STAGE], env, Executor(1), progress=False, log=lambda m: None).run("calibrate")[0]
        return report, env.store("calibrate").array("split")[:]

    make_astyx_dataset(tmp_path / "data", n_frames=4)
    assert run("cache")[0].done == 4
    make_astyx_dataset(tmp_path / "data", n_frames=7)
    report, split = run("cache")
    assert (report.done, report.failed) == (7, 0), report.failures
    executor._MEMO.clear()  # a fresh process
    np.testing.assert_array_equal(split, run("fresh")[1])
    assert len(set(split.tolist())) > 1


def _rot(axis: str, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


def test_fixture_calibration_directions_lidar_points_and_time(tmp_path):
    """calib_data.T_to_ref_COS maps sensor -> reference: with a radar entry that is not the
    identity, T_radar_lidar = inv(T_radar) @ T_lidar and T_radar_cam = inv(T_radar) @ T_camera;
    lidar points land at T_radar_lidar @ p_L (rotation and translation both); the frame time is
    the median lidar Timestamp in microseconds; the intensity is the Reflectivity column."""
    import json

    from pipeline.readers.testing import K_FIXTURE, T_CAM_RADAR, rigid

    make_astyx_dataset(tmp_path, n_frames=2, speed_mps=8.0)
    T_ref_radar = rigid(_rot("z", 0.1), np.array([0.2, -0.1, 0.05]))
    T_ref_lidar = rigid(_rot("z", 0.3) @ _rot("x", 0.05), np.array([-0.5, 0.1, 0.8]))
    T_ref_cam = T_ref_radar @ np.linalg.inv(T_CAM_RADAR)
    calib = {"sensors": [
        {"sensor_uid": "radar_6455", "calib_data": {"T_to_ref_COS": T_ref_radar.tolist()}},
        {"sensor_uid": "lidar_vlp16", "calib_data": {"T_to_ref_COS": T_ref_lidar.tolist()}},
        {"sensor_uid": "camera_front", "calib_data": {"T_to_ref_COS": T_ref_cam.tolist(), "K": K_FIXTURE.tolist()}}]}
    (tmp_path / "calibration" / "000001.json").write_text(json.dumps(calib))
    rng = np.random.default_rng(7)
    p_L = rng.uniform([2, -10, -2], [40, 10, 2], (201, 3))
    stamps = 3_000_000 + 1000 * np.arange(201)                      # 3.0 s .. 3.2 s, median 3.1 s
    rows = "\n".join(f"{a:.4f} {b:.4f} {c:.4f} {7 + k % 3} {k % 16} {t}"
                     for k, ((a, b, c), t) in enumerate(zip(p_L, stamps)))
    (tmp_path / "lidar_vlp16" / "000001.txt").write_text("X Y Z Reflectivity LaserID Timestamp \n" + rows + "\n")
    reader = get_reader(load_config("astyx").with_overrides({"camera.full_size": "64,48"}), tmp_path)
    rec = reader.read("000001")
    np.testing.assert_allclose(rec.T_radar_lidar, np.linalg.inv(T_ref_radar) @ T_ref_lidar, atol=1e-9)
    np.testing.assert_allclose(rec.T_radar_cam, np.linalg.inv(T_CAM_RADAR), atol=1e-9)
    homogeneous = np.column_stack([np.round(p_L, 4), np.ones(201)])
    expected = (np.linalg.inv(T_ref_radar) @ T_ref_lidar @ homogeneous.T).T[:, :3]
    np.testing.assert_allclose(rec.lidar_D, expected, atol=1e-4)
    assert rec.timestamp_s == pytest.approx(3.1, abs=1e-9)
    np.testing.assert_array_equal(rec.lidar_intensity, 7 + np.arange(201) % 3)


def test_fixture_ego_velocity_when_every_point_is_aliased(tmp_path):
    """At 8 m/s with every target within 25 deg of the axis, every static range rate (< -7 m/s) is
    aliased into the +/-5.2 m/s span: the record's ego velocity must come from the alias-aware fit."""
    make_astyx_dataset(tmp_path, n_frames=2, speed_mps=8.0)
    rng = np.random.default_rng(2)
    n = 300
    az, el, r = rng.uniform(-0.45, 0.45, n), rng.uniform(-0.2, 0.2, n), rng.uniform(3, 45, n)
    xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)
    rate = -(xyz / r[:, None]) @ np.array([8.0, 0, 0])
    assert rate.max() < -ASTYX_SPAN_MPS / 2
    v_r = -wrap_doppler(rate, ASTYX_SPAN_MPS)                        # Astyx: positive approaching
    rows = "\n".join(f"{a:.6f} {b:.6f} {c:.6f} {d:.4f} 60.0" for (a, b, c), d in zip(xyz, v_r))
    (tmp_path / "radar_6455" / "000001.txt").write_text("\nX Y Z V_r Mag\n" + rows + "\n")
    reader = get_reader(load_config("astyx").with_overrides({"camera.full_size": "64,48"}), tmp_path)
    np.testing.assert_allclose(reader.read("000001").ego_velocity_D, [8.0, 0, 0], atol=0.05)
    np.testing.assert_allclose(reader.estimate_ego("000001").velocity_D, [8.0, 0, 0], atol=0.05)


# -- object velocities from neighbouring frames -------------------------------------------------

def _car_velocities(root, ids):
    reader = get_reader(load_config("astyx").with_overrides({"camera.full_size": "64,48"}), root)
    return [reader.read(f).labels[0].velocity_D for f in ids], reader


def test_fixture_car_velocity_from_neighbouring_boxes(tmp_path):
    """A car overtaking at 12 m/s while the radar drives at 8 m/s: its box moves 0.4 m per 0.1 s
    in {D}; the velocity over ground comes back once the ego's motion is removed, from both
    neighbours in the middle and from one at the ends, the same whatever order the frames are read in."""
    make_astyx_dataset(tmp_path, n_frames=3, speed_mps=8.0, car_velocity_D=(12.0, 1.0, 0.0))
    found = {}
    for ids in (["000000", "000001", "000002"], ["000002", "000000", "000001"], ["000001"]):
        velocities, reader = _car_velocities(tmp_path, ids)
        for fid, v in zip(ids, velocities):
            np.testing.assert_allclose(v, [12.0, 1.0, 0.0], atol=0.1)
            found.setdefault(fid, v)
            np.testing.assert_array_equal(v, found[fid])  # to the bit: dask workers read frames in any order
    assert reader.report()["objects_velocity_by_box_matching"] == 1


def test_fixture_reader_reads_a_neighbour_again_once_its_files_change(tmp_path):
    """A reader used again (one RunEnv over several runs; a worker keeps one per command): a
    neighbour's box moved in its file since the reader last read it gives the velocity a new reader
    gives (the kept copy gave the old one)."""
    import json

    make_astyx_dataset(tmp_path, n_frames=2, speed_mps=8.0, car_velocity_D=(8.0, 0.0, 0.0))
    (v0, _), reader = _car_velocities(tmp_path, ["000000", "000001"])
    np.testing.assert_allclose(v0, [8.0, 0.0, 0.0], atol=0.1)
    path = tmp_path / "groundtruth_obj3d" / "000001.json"
    gt = json.loads(path.read_text())
    gt["objects"][0]["center3d"][0] += 0.5   # 5 m/s faster over the 0.1 s
    path.write_text(json.dumps(gt))
    again = reader.read("000000").labels[0].velocity_D
    (fresh,), _ = _car_velocities(tmp_path, ["000000"])
    np.testing.assert_allclose(fresh, [13.0, 0.0, 0.0], atol=0.1)
    np.testing.assert_array_equal(again, fresh)


def test_fixture_reader_shared_by_threads_reads_what_it_reads_alone(tmp_path):
    """A dask worker's threads share one reader: reads of the same frames from 4 threads at once,
    in any order, give each frame the velocities a reader of its own gives, and none fails."""
    from concurrent.futures import ThreadPoolExecutor

    make_astyx_dataset(tmp_path, n_frames=6, speed_mps=8.0, car_velocity_D=(12.0, 1.0, 0.0))
    ids = [f"{i:06d}" for i in range(6)]
    alone = {f: _car_velocities(tmp_path, [f])[0][0] for f in ids}
    reader = get_reader(load_config("astyx").with_overrides({"camera.full_size": "64,48"}), tmp_path)
    order = [ids[i] for i in np.random.default_rng(0).integers(0, 6, 60)]
    with ThreadPoolExecutor(4) as pool:
        got = list(pool.map(lambda f: reader.read(f).labels[0].velocity_D, order))
    for f, v in zip(order, got):
        np.testing.assert_array_equal(v, alone[f])


def test_fixture_car_velocity_unknown_beyond_the_time_gap(tmp_path):
    """Frames 0.8 s apart (Astyx's ids one apart may be minutes apart): the boxes are not
    differenced; frame 2, 0.1 s after frame 1, is."""
    make_astyx_dataset(tmp_path, n_frames=3, speed_mps=8.0, car_velocity_D=(0.0, 0.0, 0.0), times_s=[0.0, 0.8, 0.9])
    (v0, v1, v2), reader = _car_velocities(tmp_path, ["000000", "000001", "000002"])
    assert np.isnan(v0).all()
    np.testing.assert_allclose(v1, 0.0, atol=0.1)
    np.testing.assert_allclose(v2, 0.0, atol=0.1)
    assert reader.report()["objects_velocity_unknown"] == 1


def test_fixture_unreadable_neighbour_leaves_the_frame_readable(tmp_path):
    """A neighbour whose radar cannot be read gives no velocity; the frame still reads (the
    neighbour's own read names its file)."""
    make_astyx_dataset(tmp_path, n_frames=2, speed_mps=8.0, car_velocity_D=(3.0, 0.0, 0.0))
    (tmp_path / "radar_6455" / "000000.txt").write_text("\nX Y Z V_r Mag\n1 2\n")
    (v1,), _ = _car_velocities(tmp_path, ["000001"])
    assert np.isnan(v1).all()
    with pytest.raises(ReaderError, match="000000"):
        get_reader(load_config("astyx").with_overrides({"camera.full_size": "64,48"}), tmp_path).read("000000")


def test_fixture_box_drawn_longer_in_one_frame_follows_its_seen_face(tmp_path):
    """The car ahead keeps its distance (it drives at the ego's 8 m/s) but frame 1 draws it 1.2 m
    longer, away from the radar, as an annotator may who sees only its rear: its centre moves
    0.6 m and back in 0.1 s, its rear face stays. The velocity follows the rear face."""
    import json

    make_astyx_dataset(tmp_path, n_frames=3, speed_mps=8.0, car_velocity_D=(8.0, 0.0, 0.0))
    path = tmp_path / "groundtruth_obj3d" / "000001.json"
    gt = json.loads(path.read_text())
    obj = gt["objects"][0]
    w, x, y, z = obj["orientation_quat"]
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    obj["dimension3d"][0] += 1.2
    obj["center3d"] = (np.asarray(obj["center3d"]) + 0.6 * np.array([np.cos(yaw), np.sin(yaw), 0.0])).tolist()
    path.write_text(json.dumps(gt))
    velocities, _ = _car_velocities(tmp_path, ["000000", "000001", "000002"])
    for v in velocities:
        np.testing.assert_allclose(v, [8.0, 0.0, 0.0], atol=0.1)


def test_box_reference_point_is_the_nearest_face_centre():
    from pipeline.frame import Object3D
    from pipeline.readers.astyx import box_reference_points

    boxes = [Object3D(class_name="Car", center_D=np.array([20.0, 0.0, -0.5]), size_lwh_m=np.array([4.0, 2.0, 1.5]),
                      yaw_rad=0.0),                                                        # ahead: its rear face
             Object3D(class_name="Car", center_D=np.array([2.0, 6.0, 0.0]), size_lwh_m=np.array([4.0, 2.0, 1.5]),
                      yaw_rad=0.0),                                                        # beside, to the left: its right side
             Object3D(class_name="Car", center_D=np.array([0.0, -9.0, 0.0]), size_lwh_m=np.array([4.0, 2.0, 1.5]),
                      yaw_rad=np.pi / 2)]                                                  # turned: its rear, towards y
    np.testing.assert_allclose(box_reference_points(boxes), [[18.0, 0.0, -0.5], [2.0, 5.0, 0.0], [0.0, -7.0, 0.0]],
                               atol=1e-12)
    assert box_reference_points([]).shape == (0, 3)


def test_box_reference_point_of_a_tilted_box_is_where_its_rotation_puts_the_face():
    """Astyx's boxes lean about 4 deg in {D}: the face centre is centre + R (+/-l/2, 0, 0) or
    centre + R (0, +/-w/2, 0) with the box's whole rotation (before 2026-12-06 the yaw alone and the
    centre's height: 0.14 m too low for the rear face of this car pitched 4 deg)."""
    from pipeline.frame import Object3D
    from pipeline.readers.astyx import box_reference_points

    pitch, roll = np.radians(4.0), np.radians(-3.5)
    boxes = [Object3D(class_name="Car", center_D=np.array([20.0, 0.0, -0.5]), size_lwh_m=np.array([4.0, 2.0, 1.5]),
                      yaw_rad=0.0, pitch_rad=pitch),                                       # ahead: its rear face
             Object3D(class_name="Car", center_D=np.array([2.0, 6.0, 0.0]), size_lwh_m=np.array([4.0, 2.0, 1.5]),
                      yaw_rad=0.1, pitch_rad=pitch, roll_rad=roll)]                        # to the left: its right side
    expected = [boxes[0].center_D + boxes[0].rotation @ [-2.0, 0.0, 0.0],
                boxes[1].center_D + boxes[1].rotation @ [0.0, -1.0, 0.0]]
    np.testing.assert_allclose(box_reference_points(boxes), expected, atol=1e-12)
    np.testing.assert_allclose(expected[0], [20.0 - 2.0 * np.cos(pitch), 0.0, -0.5 + 2.0 * np.sin(pitch)], atol=1e-12)


def test_box_reference_points_of_upright_boxes_are_the_yaw_only_ones_to_the_bit():
    """Boxes without pitch or roll give the bits of the yaw-only face centres (the code until
    2026-12-06, written out here), every face and heading among them."""
    from pipeline.frame import Object3D
    from pipeline.readers.astyx import box_reference_points

    rng = np.random.default_rng(7)
    n = 2000
    centre, size, yaw = rng.uniform(-60, 60, (n, 3)), rng.uniform(0.3, 15, (n, 3)), rng.uniform(-7, 7, n)
    boxes = [Object3D(class_name="Car", center_D=c, size_lwh_m=s, yaw_rad=float(y)) for c, s, y in zip(centre, size, yaw)]
    half = size[:, :2] / 2
    axes = np.stack([np.cos(yaw), np.sin(yaw), -np.sin(yaw), np.cos(yaw)], axis=1).reshape(-1, 2, 2)
    offsets = np.concatenate([axes[:, :1] * half[:, :1, None], axes[:, 1:] * half[:, 1:, None]], axis=1)
    faces = centre[:, None, :2] + np.concatenate([offsets, -offsets], axis=1)
    nearest = np.argmin(np.einsum("nfk,nfk->nf", faces, faces), axis=1)
    np.testing.assert_array_equal(box_reference_points(boxes),
                                  np.column_stack([faces[np.arange(n), nearest], centre[:, 2]]))


def test_from_box_frame_of_several_boxes_is_each_box_s_to_the_bit():
    """from_box_frame with rotations (B, 1, 3, 3) and offsets (B, F, 3) gives each box's own call's bits."""
    from pipeline.frame import box_rotations, from_box_frame

    rng = np.random.default_rng(8)
    rot = box_rotations(*rng.uniform(-1, 1, (3, 5)))
    local = rng.normal(size=(5, 4, 3))
    together = from_box_frame(local, rot[:, None])
    assert together.shape == (5, 4, 3)
    for b in range(5):
        np.testing.assert_array_equal(together[b], from_box_frame(local[b], rot[b]))
        np.testing.assert_allclose(together[b], local[b] @ rot[b].T, atol=1e-12)


def test_quaternion_to_yaw_pitch_roll_rebuilds_the_rotation():
    """Random unit quaternions (w, x, y, z), pitch within +/-80 deg: box_rotations of the angles is
    the quaternion's rotation matrix (scipy's, scalar last); the yaw is the one the reader took
    alone before 2026-12-06, to the bit."""
    from scipy.spatial.transform import Rotation

    from pipeline.frame import box_rotations
    from pipeline.readers.astyx import quaternion_to_yaw_pitch_roll

    rng = np.random.default_rng(4)
    quats = rng.normal(size=(400, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    for w, x, y, z in quats:
        yaw, pitch, roll = quaternion_to_yaw_pitch_roll(w, x, y, z)
        if abs(pitch) > np.radians(80):
            continue
        np.testing.assert_allclose(box_rotations(yaw, pitch, roll), Rotation.from_quat([x, y, z, w]).as_matrix(),
                                   atol=1e-12)
        assert yaw == float(np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)))
    assert quaternion_to_yaw_pitch_roll(np.cos(0.25), 0.0, 0.0, np.sin(0.25)) == (pytest.approx(0.5), 0.0, 0.0)


def test_fixture_box_keeps_its_tilt(tmp_path):
    """A box whose quaternion tilts it (pitch 3 deg, roll -4 deg, as Astyx's lean in {D}) is read
    with that rotation: Object3D.rotation is the quaternion's matrix (before 2026-12-06 the box was
    upright, the yaw alone); a quaternion far from unit norm is an error naming the file and object."""
    import json

    from scipy.spatial.transform import Rotation

    make_astyx_dataset(tmp_path, n_frames=2, speed_mps=8.0)
    path = tmp_path / "groundtruth_obj3d" / "000001.json"
    gt = json.loads(path.read_text())
    turn = Rotation.from_euler("ZYX", [0.5, np.radians(3.0), np.radians(-4.0)])
    x, y, z, w = turn.as_quat()
    gt["objects"][0]["orientation_quat"] = [w, x, y, z]
    path.write_text(json.dumps(gt))
    reader = get_reader(load_config("astyx").with_overrides({"camera.full_size": "64,48"}), tmp_path)
    obj = reader.read("000001").labels[0]
    assert (obj.yaw_rad, obj.pitch_rad, obj.roll_rad) == (pytest.approx(0.5), pytest.approx(np.radians(3.0)),
                                                          pytest.approx(np.radians(-4.0)))
    np.testing.assert_allclose(obj.rotation, turn.as_matrix(), atol=1e-12)
    gt["objects"][0]["orientation_quat"] = [2 * w, 2 * x, 2 * y, 2 * z]
    path.write_text(json.dumps(gt))
    reader = get_reader(load_config("astyx").with_overrides({"camera.full_size": "64,48"}), tmp_path)
    with pytest.raises(ReaderError, match="000001.json.*object 0: orientation_quat has norm 2"):
        reader.read("000001")


@pytest.mark.realdata
def test_hires_boxes_are_upright_in_the_lidar_frame(hires):
    """Astyx's boxes are drawn upright in the lidar's frame, which is tilted against the radar's:
    with their pitch and roll kept, their z axes lean a median 0.6 deg from the lidar's z and 4.2
    deg from the radar's (measured 2026-12-06 on the 888 boxes of the 141 frames; upright in {D},
    as the reader had them before, they leaned the lidar's 4.2 deg from its z)."""
    to_lidar, to_radar = [], []
    for fid in hires.frame_ids()[::10]:
        rec = hires.read(fid)
        for obj in rec.labels:
            z_box = obj.rotation[:, 2]
            to_lidar.append(np.degrees(np.arccos(np.clip(z_box @ rec.T_radar_lidar[:3, 2], -1, 1))))
            to_radar.append(np.degrees(np.arccos(np.clip(z_box[2], -1, 1))))
    assert len(to_lidar) > 50
    assert np.median(to_lidar) < 1.0 and np.median(to_radar) > 3.5
