"""VoD and synthetic-layout readers: real example frames (skipped without ../shared/data) and fixtures."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from pipeline.config import load_config
from pipeline.errors import ConfigError
from pipeline.geometry import invert_transform, project_to_image
from pipeline.readers import get_reader
from pipeline.readers.kitti_format import label_to_object, parse_label_file
from pipeline.readers.testing import T_CAM_RADAR, kitti_label_line, make_vod_dataset, rigid, write_pose

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
VOD = DATA / "vod_example"


def _fixture_cfg(profile: str = "vod"):
    return load_config(profile).with_overrides({"camera.full_size": "64,48"})


@pytest.fixture(scope="module")
def vod_real():
    if not VOD.is_dir():
        pytest.skip("../shared/data/vod_example not present")
    reader = get_reader(load_config("vod"), VOD)
    return reader, {f: reader.read(f) for f in reader.frame_ids()}


@pytest.mark.realdata
def test_real_index(vod_real):
    reader, records = vod_real
    assert reader.frame_ids() == ["00549", "01047"]
    assert reader.report().get("skipped_missing", 0) == 0
    for rec in records.values():
        assert rec.image.shape == (1216, 1936, 3) and rec.radar_D.dtype == np.float32
        assert rec.lidar_D.shape[0] > 150_000


@pytest.mark.realdata
def test_real_labels_project_into_their_2d_boxes(vod_real):
    """Every label's 3D centre, converted to {D} and projected with K and T_cam_radar, lies in the
    label's own 2D box (+5 px): checks the label conversion, intrinsics and radar calibration."""
    _, records = vod_real
    for fid, rec in records.items():
        boxes = np.array([[float(v) for v in line.split()[4:8]]
                          for line in (VOD / "lidar/training/label_2" / f"{fid}.txt").read_text().splitlines()])
        centres = np.array([o.center_D for o in rec.labels])
        uv, _, valid = project_to_image(centres, rec.K, invert_transform(rec.T_radar_cam), (1936, 1216))
        inside = ((uv[:, 0] >= boxes[:, 0] - 5) & (uv[:, 0] <= boxes[:, 2] + 5)
                  & (uv[:, 1] >= boxes[:, 1] - 5) & (uv[:, 1] <= boxes[:, 3] + 5))
        assert valid.all() and inside.all(), fid


@pytest.mark.realdata
def test_real_label_boxes_match_the_raw_lidar_annotations(vod_real):
    """The example set also holds the raw annotations (radar/training/label_2/*.json: boxes in a
    lidar frame). One rigid transform maps their centres onto the reader's within millimetres, and
    their headings onto the reader's yaw: the boxes are upright in the lidar frame, read as the
    devkit reads them (raising the centre along the pitched camera's axis instead left 11-14 mm RMS,
    6-12 cm absolute)."""
    from scipy.spatial.transform import Rotation

    _, records = vod_real
    for fid, rec in records.items():
        raw = json.loads((VOD / "radar/training/label_2" / f"{fid}.json").read_text())
        lines = [line.split() for line in (VOD / "lidar/training/label_2" / f"{fid}.txt").read_text().splitlines()]
        assert len(raw) == len(lines) == len(rec.labels)
        by_size = {(round(b["geometry"]["size"]["length"], 9), round(b["geometry"]["size"]["height"], 9)): b for b in raw}
        boxes = [by_size[(round(float(f[10]), 9), round(float(f[8]), 9))] for f in lines]
        a = np.array([[b["geometry"]["center"][k] for k in "xyz"] for b in boxes])
        d = np.array([o.center_D for o in rec.labels])
        rot, _ = Rotation.align_vectors(d - d.mean(0), a - a.mean(0))
        residual = np.linalg.norm(rot.apply(a - a.mean(0)) - (d - d.mean(0)), axis=1)
        assert np.sqrt(np.mean(residual ** 2)) < 0.005 and residual.max() < 0.01, (fid, residual.max())
        q = [[b["geometry"]["quaternion"][k] for k in "xyzw"] for b in boxes]
        heading = (rot * Rotation.from_quat(q)).apply([1.0, 0.0, 0.0])
        dyaw = np.angle(np.exp(1j * (np.arctan2(heading[:, 1], heading[:, 0]) - [o.yaw_rad for o in rec.labels])))
        assert np.abs(dyaw).max() < 0.01, (fid, np.abs(dyaw).max())


@pytest.mark.realdata
def test_real_lidar_fills_labelled_boxes_and_radar_hits_image(vod_real):
    """Lidar (through T_radar_lidar) has points inside every labelled box closer than 30 m; more than
    80% of the radar points project inside the image."""
    _, records = vod_real
    for fid, rec in records.items():
        for obj in rec.labels:
            if np.linalg.norm(obj.center_D) > 30:
                continue
            d = rec.lidar_D - obj.center_D
            c, s = np.cos(obj.yaw_rad), np.sin(obj.yaw_rad)
            inside = ((np.abs(d[:, 0] * c + d[:, 1] * s) <= obj.size_lwh_m[0] / 2)
                      & (np.abs(-d[:, 0] * s + d[:, 1] * c) <= obj.size_lwh_m[1] / 2)
                      & (np.abs(d[:, 2]) <= obj.size_lwh_m[2] / 2))
            assert inside.sum() >= 5, (fid, obj.class_name)
        _, _, valid = project_to_image(rec.radar_D[:, :3], rec.K, invert_transform(rec.T_radar_cam), (1936, 1216))
        assert valid.mean() > 0.8, fid


@pytest.mark.realdata
def test_real_ego_velocity_fit_and_static_doppler(vod_real):
    _, records = vod_real
    np.testing.assert_allclose(records["00549"].ego_velocity_D, [1.92, 0.03, -0.02], atol=0.02)
    for fid, rec in records.items():
        raw = np.fromfile(VOD / "radar/training/velodyne" / f"{fid}.bin", dtype="<f4").reshape(-1, 7)
        u = raw[:, :3] / np.linalg.norm(raw[:, :3], axis=1, keepdims=True)
        residual = -(u @ rec.ego_velocity_D) - (raw[:, 4] - raw[:, 5])
        assert np.sqrt(np.mean(residual**2)) < 0.15, fid
        static = np.abs(raw[:, 5]) < 0.1
        assert static.sum() > 100
        # doppler column is the range rate; static targets: -(u . v_ego)
        np.testing.assert_allclose(rec.radar_D[static, 3], -(u[static] @ rec.ego_velocity_D), atol=0.15)


def test_fixture_ego_object_velocity_and_time(tmp_path):
    truth = make_vod_dataset(tmp_path, n_frames=3, speed_mps=5.0, object_velocity_D=(1.0, 0.5, 0.0))
    reader = get_reader(_fixture_cfg(), tmp_path)
    assert reader.frame_ids() == truth.frame_ids
    for fid in truth.frame_ids:
        rec = reader.read(fid)
        np.testing.assert_allclose(rec.ego_velocity_D, truth.ego_velocity_D, atol=1e-4)
        # central difference for the middle frame, one-sided at the ends; constant motion -> exact
        np.testing.assert_allclose(rec.labels[0].velocity_D, truth.object_velocity_D, atol=1e-4)
        assert rec.labels[0].track_id == 7
        assert rec.timestamp_s == pytest.approx(truth.timestamps_s[fid])
        assert rec.sequence_id == "seq_00010"
    assert reader.report()["ego_from_doppler_pair"] == 3


def test_a_0_1_flag_in_the_second_label_column_is_not_taken_for_track_ids(tmp_path):
    """VoD's detection release writes a 0 / 1 flag where the tracking release writes track ids: a
    frame whose values are all 0 or 1 is untracked (its boxes matched by position, here to none:
    the neighbours' boxes are another class or 3 m away, farther than an object moves in 0.1 s,
    so its velocity stays NaN rather than one between two different objects), and a track id whose
    class changes between frames is not the same track."""
    truth = make_vod_dataset(tmp_path, n_frames=3, speed_mps=5.0, object_velocity_D=(1.0, 0.5, 0.0))
    labels = {fid: tmp_path / "lidar/training/label_2" / f"{fid}.txt" for fid in truth.frame_ids}
    car = {fid: path.read_text().split() for fid, path in labels.items()}
    for k, (fid, cls) in enumerate(zip(truth.frame_ids, ("Pedestrian", "Cyclist", "Cyclist"))):
        fields = [cls, "1", *car[fid][2:11], str(float(car[fid][11]) + 3 * k), *car[fid][12:]]
        labels[fid].write_text(" ".join(fields) + "\n")
    middle = get_reader(_fixture_cfg(), tmp_path).read(truth.frame_ids[1]).labels[0]
    assert middle.track_id == -1 and np.all(np.isnan(middle.velocity_D))
    # track id 7 (tracking release) but the class changes after the middle frame: only the earlier end counts
    for fid, cls, dx in zip(truth.frame_ids, ("Car", "Car", "Van"), (0.0, 0.0, 5.0)):  # the Van elsewhere
        labels[fid].write_text(" ".join([cls, "7", *car[fid][2:11], str(float(car[fid][11]) + dx), *car[fid][12:]]) + "\n")
    middle = get_reader(_fixture_cfg(), tmp_path).read(truth.frame_ids[1]).labels[0]
    assert middle.track_id == 7
    np.testing.assert_allclose(middle.velocity_D, truth.object_velocity_D, atol=1e-4)  # one-sided, still exact
    # KITTI's DontCare placeholder (sizes -1, at -1000 m) is no object
    dont_care = "DontCare -1 -1 -10 0 0 0 0 -1 -1 -1 -1000 -1000 -1000 -10\n"
    labels[truth.frame_ids[1]].write_text(labels[truth.frame_ids[1]].read_text() + dont_care)
    assert [o.class_name for o in get_reader(_fixture_cfg(), tmp_path).read(truth.frame_ids[1]).labels] == ["Car"]


def test_boxes_without_track_ids_get_velocities_by_matching_across_frames(tmp_path):
    """VoD's detection release: no track ids (a 0 / 1 flag in their place). A moving car, a parked
    car and a walking pedestrian, listed in a different order in each frame, get their velocities
    over ground in {D} by matching each box to its nearest box of the class in the neighbouring
    frames (exact for constant motion), the parked car 0; a box with no partner stays NaN."""
    truth = make_vod_dataset(tmp_path, n_frames=4, speed_mps=5.0, object_velocity_D=(1.0, 0.5, 0.0))
    t0 = int(truth.frame_ids[0]) / 10.0
    movers = {"car": ("Car", np.array([15.0, -2.0, 0.0]), truth.object_velocity_D),
              "parked": ("Car", np.array([20.0, 4.0, 0.0]), np.zeros(3)),
              "walker": ("Pedestrian", np.array([12.0, -6.0, 0.0]), np.array([0.0, 1.2, 0.0]))}
    rng = np.random.default_rng(1)
    for fid in truth.frame_ids:
        dt = int(fid) / 10.0 - t0
        lines = [kitti_label_line(cls, 0, start + v * dt - truth.ego_velocity_D * dt, np.array([4.0, 1.8, 1.5]),
                                  0.2, T_CAM_RADAR) for cls, start, v in movers.values()]
        order = rng.permutation(len(lines))
        (tmp_path / "lidar/training/label_2" / f"{fid}.txt").write_text("\n".join(lines[k] for k in order) + "\n")
    reader = get_reader(_fixture_cfg(), tmp_path)
    for fid in truth.frame_ids:
        rec = reader.read(fid)
        dt = int(fid) / 10.0 - t0
        for cls, start, v in movers.values():
            here = start + v * dt - truth.ego_velocity_D * dt
            obj = min(rec.labels, key=lambda o: np.linalg.norm(o.center_D - here))
            assert obj.class_name == cls and obj.track_id == -1
            np.testing.assert_allclose(obj.velocity_D, v, atol=1e-4)
    assert reader.report()["objects_velocity_by_box_matching"] == 12
    # the walker turns into a Cyclist in the last frame: no partner there, one-sided before it
    last = tmp_path / "lidar/training/label_2" / f"{truth.frame_ids[-1]}.txt"
    last.write_text(last.read_text().replace("Pedestrian ", "Cyclist "))
    reader = get_reader(_fixture_cfg(), tmp_path)
    cyclist = [o for o in reader.read(truth.frame_ids[-1]).labels if o.class_name == "Cyclist"]
    assert len(cyclist) == 1 and np.all(np.isnan(cyclist[0].velocity_D))
    walker = [o for o in reader.read(truth.frame_ids[-2]).labels if o.class_name == "Pedestrian"]
    np.testing.assert_allclose(walker[0].velocity_D, [0.0, 1.2, 0.0], atol=1e-4)
    assert reader.report()["objects_velocity_unknown"] == 1
    # the calibrate run says how many labelled objects that leaves with a static object's Doppler
    from pipeline.executor import Executor, RunEnv
    from pipeline.runner import Pipeline
    from stages import calibrate

    cfg = _fixture_cfg().with_overrides({"camera.crop_rows": "0,48", "camera.working_size": "64,48"})
    lines: list[str] = []
    env = RunEnv(cfg=cfg, cache_root=str(tmp_path / "cache"), dataset="vod", data_root=str(tmp_path))
    Pipeline([calibrate.STAGE], env, Executor(1), progress=False, log=lines.append).run("calibrate")
    assert any("labelled objects of unknown velocity: 1 of 12:" in line and "static" in line for line in lines), lines


def _count_label_parses(monkeypatch) -> list[str]:
    """The ids of the label files the VoD reader parses from now on, in order (parse_label_file
    wrapped)."""
    import pipeline.readers.vod as vod

    parsed: list[str] = []

    def counting(path, frame):
        parsed.append(Path(path).stem)
        return parse_label_file(path, frame)

    monkeypatch.setattr(vod, "parse_label_file", counting)
    return parsed


def test_each_label_file_is_parsed_once_per_reader_until_it_changes(tmp_path, monkeypatch):
    """A frame's velocities read its neighbours' labels and poses: the reader keeps what it parsed
    (each label file was parsed three times), parses a file again once it changes, and raises a
    malformed file's error on each read instead of keeping it."""
    from pipeline.errors import ReaderError

    truth = make_vod_dataset(tmp_path, n_frames=4, speed_mps=5.0, object_velocity_D=(1.0, 0.5, 0.0))
    parsed = _count_label_parses(monkeypatch)
    reader = get_reader(_fixture_cfg(), tmp_path)
    first = [reader.read(fid).labels[0].velocity_D for fid in truth.frame_ids]
    assert sorted(parsed) == sorted(truth.frame_ids)  # each once, though each frame reads its neighbours'
    np.testing.assert_allclose(first, [truth.object_velocity_D] * 4, atol=1e-4)
    # the next frame's box moved 1 m along the camera's x (another size on disk): the middle frame sees it
    path = tmp_path / "lidar/training/label_2" / f"{truth.frame_ids[2]}.txt"
    fields = path.read_text().split()
    path.write_text(" ".join([*fields[:11], f"{float(fields[11]) + 1.0:.6f}", *fields[12:]]) + "\n")
    parsed.clear()
    moved = reader.read(truth.frame_ids[1]).labels[0].velocity_D
    assert parsed == [truth.frame_ids[2]]
    assert np.linalg.norm(moved - truth.object_velocity_D) == pytest.approx(1.0 / 0.2, abs=1e-3)  # central, over 0.2 s
    path.write_text("Car 7 0 0\n")  # malformed: raised on every read, never kept
    for _ in range(2):
        with pytest.raises(ReaderError, match="label line 1 has 4 columns"):
            reader.read(truth.frame_ids[2])


def test_fixture_pose_fallback_with_too_few_radar_points(tmp_path):
    truth = make_vod_dataset(tmp_path, n_frames=3, speed_mps=7.0, n_radar=2)
    reader = get_reader(_fixture_cfg(), tmp_path)
    np.testing.assert_allclose(reader.read("00011").ego_velocity_D, truth.ego_velocity_D, atol=1e-6)
    assert reader.report()["ego_from_poses"] == 1


def test_label_round_trip_matches_kitti_definition(tmp_path):
    """A KITTI line built from a {D} box converts back to that box (centre, size, yaw)."""
    from pipeline.readers.testing import kitti_label_line
    rng = np.random.default_rng(1)
    lines, truth = [], []
    for k in range(20):
        centre = rng.uniform([3, -10, -1], [40, 10, 1])
        lwh, yaw = rng.uniform(0.5, 5, 3), rng.uniform(-np.pi, np.pi)
        lines.append(kitti_label_line("Car", k, centre, lwh, yaw, T_CAM_RADAR))
        truth.append((centre, lwh, yaw))
    (tmp_path / "l.txt").write_text("\n".join(lines))
    for lab, (centre, lwh, yaw) in zip(parse_label_file(tmp_path / "l.txt", "x"), truth):
        obj = label_to_object(lab, invert_transform(T_CAM_RADAR), lab.column2)
        np.testing.assert_allclose(obj.center_D, centre, atol=1e-6)
        np.testing.assert_allclose(obj.size_lwh_m, lwh, atol=1e-6)
        assert np.cos(obj.yaw_rad - yaw) == pytest.approx(1.0, abs=1e-9)


def test_sequences_file_and_gap_split(tmp_path):
    make_vod_dataset(tmp_path / "a", n_frames=2, first=10)
    make_vod_dataset(tmp_path / "a", n_frames=2, first=20)
    reader = get_reader(_fixture_cfg(), tmp_path / "a")
    assert [reader.sequence_of(f) for f in reader.frame_ids()] == ["seq_00010"] * 2 + ["seq_00020"] * 2
    (tmp_path / "a/ImageSets").mkdir()
    (tmp_path / "a/ImageSets/sequences.txt").write_text("delft_1 0 10\ndelft_2 11 30\n")
    reader = get_reader(_fixture_cfg(), tmp_path / "a")
    assert [reader.sequence_of(f) for f in reader.frame_ids()] == ["delft_1", "delft_2", "delft_2", "delft_2"]


def test_accumulated_radar_folder_and_single_scan_time_filter(tmp_path):
    make_vod_dataset(tmp_path, n_frames=1, n_radar=10)
    single = np.fromfile(tmp_path / "radar/training/velodyne/00010.bin", dtype="<f4").reshape(-1, 7)
    older = single.copy()
    older[:, 6] = -1
    both = np.concatenate([single, older])
    both.tofile(tmp_path / "radar/training/velodyne/00010.bin")
    (tmp_path / "radar_3frames/training/velodyne").mkdir(parents=True)
    both.tofile(tmp_path / "radar_3frames/training/velodyne/00010.bin")
    assert get_reader(_fixture_cfg(), tmp_path).read("00010").radar_D.shape == (10, 5)
    acc = get_reader(_fixture_cfg(), tmp_path, radar_folder="radar_3frames").read("00010")
    assert acc.radar_D.shape == (20, 5)


def test_png_images_timestamps_from_pose_and_synthetic_meta(tmp_path):
    truth = make_vod_dataset(tmp_path, n_frames=2, image_ext=".png", n_radar=12)
    for k, fid in enumerate(truth.frame_ids):
        write_pose(tmp_path / "lidar/training/pose" / f"{fid}.json",
                   rigid(np.eye(3), np.array([0.5 * k, 0, 0])) @ np.linalg.inv(T_CAM_RADAR), 100.0 + 0.1 * k)
        meta = np.stack([np.arange(12), np.full(12, 3)], axis=1).astype("<i4")
        meta.tofile(_mkdir(tmp_path / "radar/training/meta") / f"{fid}.bin")
    reader = get_reader(_fixture_cfg("synthetic").with_overrides({"camera.full_size": "64,48"}), tmp_path)
    rec = reader.read(truth.frame_ids[1])
    assert rec.timestamp_s == pytest.approx(100.1)
    np.testing.assert_array_equal(rec.extras["object_id"], np.arange(12))
    np.testing.assert_array_equal(rec.extras["material"], np.full(12, 3))


def test_unknown_reader_name_is_a_config_error(tmp_path):
    cfg = load_config("vod").with_overrides({"dataset.reader": "nuscenes"})
    with pytest.raises(ConfigError, match="nuscenes"):
        get_reader(cfg, tmp_path)


def _mkdir(path: Path) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    return path


def _rz(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_fixture_rotated_odometry_world_and_lidar_mounting(tmp_path):
    """Velocities in {D} do not depend on how the odometry world is oriented: with every pose
    turned by 0.7 rad about z and shifted, the pose-differenced ego velocity (2 radar points: the
    Doppler fit is unusable) and the tracked object's velocity are still the fixture's, in {D}.
    A lidar mounted turned by 0.2 rad about z: its points land at T_radar_lidar @ p_L with
    T_radar_lidar = inv(T_cam_radar) @ T_cam_lidar. The Doppler column is v_r (not
    v_r_compensated), the RSS column the RCS."""
    truth = make_vod_dataset(tmp_path, n_frames=3, speed_mps=5.0, object_velocity_D=(1.0, 0.5, 0.0), n_radar=2)
    T_turned = rigid(_rz(0.7), np.array([100.0, -50.0, 3.0]))
    for fid in truth.frame_ids:
        path = tmp_path / "lidar/training/pose" / f"{fid}.json"
        T_world_cam = np.array(json.loads(path.read_text().splitlines()[0])["odomToCamera"]).reshape(4, 4)
        write_pose(path, T_turned @ T_world_cam)
    fid = truth.frame_ids[1]
    T_radar_lidar = rigid(_rz(0.2), np.array([-0.5, 0.1, 0.8]))
    from pipeline.readers.testing import K_FIXTURE, write_kitti_calib
    write_kitti_calib(tmp_path / "lidar/training/calib" / f"{fid}.txt", K_FIXTURE, T_CAM_RADAR @ T_radar_lidar)
    p_L = np.random.default_rng(4).uniform([2, -10, -2], [40, 10, 2], (300, 3))
    np.column_stack([p_L, np.full(300, 0.5)]).astype("<f4").tofile(tmp_path / "lidar/training/velodyne" / f"{fid}.bin")
    reader = get_reader(_fixture_cfg(), tmp_path)
    rec = reader.read(fid)
    assert reader.report()["ego_from_poses"] == 1
    np.testing.assert_allclose(rec.ego_velocity_D, truth.ego_velocity_D, atol=1e-6)
    np.testing.assert_allclose(rec.labels[0].velocity_D, truth.object_velocity_D, atol=1e-4)
    np.testing.assert_allclose(rec.T_radar_lidar, T_radar_lidar, atol=1e-6)
    expected = p_L.astype(np.float32).astype(np.float64) @ T_radar_lidar[:3, :3].T + T_radar_lidar[:3, 3]
    np.testing.assert_allclose(rec.lidar_D, expected, atol=1e-4)
    raw = np.fromfile(tmp_path / "radar/training/velodyne" / f"{fid}.bin", dtype="<f4").reshape(-1, 7)
    np.testing.assert_array_equal(rec.radar_D[:, 3], raw[:, 4])
    np.testing.assert_array_equal(rec.radar_D[:, 4], raw[:, 3])


def test_lidar_box_labels_are_upright_in_a_tilted_lidar(tmp_path):
    """View-of-Delft's devkit: a box is upright in the LIDAR frame, its KITTI location the bottom
    centre (centre lowered h/2 along the lidar's z) in the camera frame, rotation_y = -(yaw_L + pi/2).
    With a lidar pitched 8 deg and yawed 25 deg against the radar, the reader's box has the lidar
    centre mapped into {D} and the heading of the lidar's yaw mapped into {D}."""
    from pipeline.readers.kitti_format import KittiLabel, lidar_box_label_to_object

    cp, sp, cy, sy = np.cos(0.14), np.sin(0.14), np.cos(0.44), np.sin(0.44)
    R_radar_lidar = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    T_radar_lidar = rigid(R_radar_lidar, np.array([-0.6, 0.1, 0.9]))
    T_cam_lidar = T_CAM_RADAR @ T_radar_lidar
    h, w, l, yaw_L = 1.8, 0.7, 1.9, 0.6
    centre_L = np.array([12.0, -3.0, -0.4])
    bottom_cam = (T_cam_lidar @ np.append(centre_L - [0.0, 0.0, h / 2], 1.0))[:3]
    label = KittiLabel("Cyclist", 3, np.array([h, w, l]), bottom_cam, -(yaw_L + np.pi / 2))
    obj = lidar_box_label_to_object(label, invert_transform(T_CAM_RADAR), T_radar_lidar, 3)
    np.testing.assert_allclose(obj.center_D, (T_radar_lidar @ np.append(centre_L, 1.0))[:3], atol=1e-9)
    heading_D = R_radar_lidar @ [np.cos(yaw_L), np.sin(yaw_L), 0.0]
    assert obj.yaw_rad == pytest.approx(np.arctan2(heading_D[1], heading_D[0]), abs=1e-9)
    np.testing.assert_allclose(obj.size_lwh_m, [l, w, h])


def _relabel(path: Path, cls: str | None = None, column2: str | None = None, dx_cam: float = 0.0) -> None:
    """Rewrite a one-line label file with fixed-width numbers (class, second column or the box
    moved ``dx_cam`` m along the camera's x changed)."""
    f = path.read_text().split()
    values = [float(v) for v in f[2:]]
    values[9] += dx_cam
    path.write_text(" ".join([cls or f[0], column2 or f[1], *(f"{v:.6f}" for v in values)]) + "\n")


def test_a_kept_parse_is_keyed_by_path_modification_time_and_size(tmp_path):
    """The reader parses a label file again when its modification time changes at the same size
    (an edited coordinate), or its size changes at the same modification time (a coarse clock),
    and never takes one file's parse for another's of the same size and time (an unpacked archive)."""
    truth = make_vod_dataset(tmp_path, n_frames=3, speed_mps=5.0, object_velocity_D=(1.0, 0.5, 0.0))
    labels = [tmp_path / "lidar/training/label_2" / f"{fid}.txt" for fid in truth.frame_ids]
    for path in labels:
        _relabel(path)
    middle = truth.frame_ids[1]
    # three files of one size and one modification time: each is still its own
    assert len({p.stat().st_size for p in labels}) == 1
    stamp = labels[0].stat().st_mtime_ns
    for path in labels:
        os.utime(path, ns=(stamp, stamp))
    reader = get_reader(_fixture_cfg(), tmp_path)
    np.testing.assert_allclose(reader.read(middle).labels[0].velocity_D, truth.object_velocity_D, atol=1e-4)
    # the next frame's box moved 1 m (same size on disk), its modification time later: seen
    size = labels[2].stat().st_size
    _relabel(labels[2], dx_cam=1.0)
    assert labels[2].stat().st_size == size
    os.utime(labels[2], ns=(stamp + 10**9, stamp + 10**9))
    moved = reader.read(middle).labels[0].velocity_D
    assert np.linalg.norm(moved - truth.object_velocity_D) == pytest.approx(1.0 / 0.2, abs=1e-3)
    # moved back 1 m and written longer, with the same modification time as before: seen too
    _relabel(labels[2], dx_cam=-1.0)
    labels[2].write_text(labels[2].read_text() + "\n")
    assert labels[2].stat().st_size != size
    os.utime(labels[2], ns=(stamp + 10**9, stamp + 10**9))
    np.testing.assert_allclose(reader.read(middle).labels[0].velocity_D, truth.object_velocity_D, atol=1e-4)


def test_a_reader_keeps_only_the_last_parsed_files(tmp_path, monkeypatch):
    """After a pass over 12 frames (24 label and pose files) the first frame's label file is no
    longer kept (parsed again) and the last frame's still is (not parsed again)."""
    import pipeline.readers.vod as vod

    truth = make_vod_dataset(tmp_path, n_frames=12, speed_mps=5.0, n_radar=10)
    parsed = _count_label_parses(monkeypatch)
    reader = get_reader(_fixture_cfg(), tmp_path)
    for fid in truth.frame_ids:
        reader.read(fid)
    assert sorted(parsed) == sorted(truth.frame_ids)
    parsed.clear()
    reader.read(truth.frame_ids[-1])
    assert parsed == []
    reader.read(truth.frame_ids[0])
    assert sorted(parsed) == sorted(truth.frame_ids[:2])
    assert len(reader._parsed_files) <= vod.PARSED_FILES_KEPT


def test_frames_with_and_without_track_ids_side_by_side_are_matched_by_position(tmp_path):
    """The tracking release reads a frame whose ids are all 0 or 1 as untracked: a tracked frame
    beside it (and it beside the tracked one) matches its boxes by position, not by an id that
    the other frame lacks."""
    truth = make_vod_dataset(tmp_path, n_frames=3, speed_mps=5.0, object_velocity_D=(1.0, 0.5, 0.0))
    for fid, column2 in zip(truth.frame_ids, ("1", "7", "1")):
        _relabel(tmp_path / "lidar/training/label_2" / f"{fid}.txt", column2=column2)
    reader = get_reader(_fixture_cfg(), tmp_path)
    for fid, track in zip(truth.frame_ids, (-1, 7, -1)):
        obj = reader.read(fid).labels[0]
        assert obj.track_id == track
        np.testing.assert_allclose(obj.velocity_D, truth.object_velocity_D, atol=1e-4)
    assert reader.report()["objects_velocity_by_box_matching"] == 3
    assert "objects_velocity_by_track_id" not in reader.report()


def test_a_fast_car_in_frames_further_apart_is_matched_within_its_time_gap(tmp_path):
    """Detection release (no track ids), frames 0.2 s apart by their poses' timestamps (a dropped
    scan): a car at 15 m/s (3 m per frame) is searched within 20 m/s times the frames' own time
    gap and gets its velocity over that gap."""
    truth = make_vod_dataset(tmp_path, n_frames=3, speed_mps=5.0)
    v_car, start = np.array([15.0, 0.0, 0.0]), np.array([15.0, -2.0, 0.0])
    for k, fid in enumerate(truth.frame_ids):
        ego_x, t = 0.5 * k, 0.2 * k
        write_pose(tmp_path / "lidar/training/pose" / f"{fid}.json",
                   rigid(np.eye(3), np.array([ego_x, 0.0, 0.0])) @ np.linalg.inv(T_CAM_RADAR), 100.0 + t)
        line = kitti_label_line("Car", 0, start + v_car * t - [ego_x, 0.0, 0.0], np.array([4.0, 1.8, 1.5]), 0.0,
                                T_CAM_RADAR)
        (tmp_path / "lidar/training/label_2" / f"{fid}.txt").write_text(line + "\n")
    reader = get_reader(_fixture_cfg(), tmp_path)
    for fid in truth.frame_ids:
        obj = reader.read(fid).labels[0]
        assert obj.track_id == -1
        np.testing.assert_allclose(obj.velocity_D, v_car, atol=1e-4)
    assert reader.report()["objects_velocity_by_box_matching"] == 3


def test_a_neighbour_without_a_pose_is_left_out_of_the_velocity(tmp_path):
    """The next frame has a label file but no pose: the middle frame's velocity is the one-sided
    difference with the previous frame (exact for constant motion), with or without track ids."""
    truth = make_vod_dataset(tmp_path, n_frames=3, speed_mps=5.0, object_velocity_D=(1.0, 0.5, 0.0))
    (tmp_path / "lidar/training/pose" / f"{truth.frame_ids[2]}.json").unlink()
    for column2 in ("7", "0"):
        for fid in truth.frame_ids:
            _relabel(tmp_path / "lidar/training/label_2" / f"{fid}.txt", column2=column2)
        reader = get_reader(_fixture_cfg(), tmp_path)
        np.testing.assert_allclose(reader.read(truth.frame_ids[1]).labels[0].velocity_D, truth.object_velocity_D,
                                   atol=1e-4)


def test_object_velocity_counts_say_how_each_box_was_associated(tmp_path):
    """The reader's report counts each labelled object once: by track id, by box matching or of
    unknown velocity, and the frames with labels but no track ids."""
    def dataset(name: str, **kw):
        return make_vod_dataset(tmp_path / name, n_frames=3, speed_mps=5.0, object_velocity_D=(1.0, 0.5, 0.0), **kw)

    def label(root: Path, fid: str) -> Path:
        return root / "lidar/training/label_2" / f"{fid}.txt"

    def report(root: Path, fids: list[str]) -> dict:
        reader = get_reader(_fixture_cfg(), root)
        for fid in fids:
            reader.read(fid)
        return {k: v for k, v in reader.report().items() if k.startswith(("objects_velocity", "frames_without"))}

    truth = dataset("tracked")
    assert report(tmp_path / "tracked", truth.frame_ids) == {"objects_velocity_by_track_id": 3}
    # the next frame's box has a 0 / 1 flag and lies 5 m away: the earlier end, by track id, alone counts
    truth = dataset("next_untracked")
    _relabel(label(tmp_path / "next_untracked", truth.frame_ids[2]), column2="1", dx_cam=5.0)
    assert report(tmp_path / "next_untracked", truth.frame_ids[1:2]) == {"objects_velocity_by_track_id": 1}
    # no track ids; the box turns into a Van in the next frame: matched by position to the earlier one
    truth = dataset("untracked")
    for fid, cls in zip(truth.frame_ids, ("Car", "Car", "Van")):
        _relabel(label(tmp_path / "untracked", fid), cls=cls, column2="1")
    assert report(tmp_path / "untracked", truth.frame_ids[1:2]) == {"objects_velocity_by_box_matching": 1,
                                                                     "frames_without_track_ids": 1}
    # no poses: every object's velocity is unknown; an empty label file is no frame without track ids
    truth = dataset("no_poses", with_poses=False)
    label(tmp_path / "no_poses", truth.frame_ids[2]).write_text("")
    assert report(tmp_path / "no_poses", truth.frame_ids) == {"objects_velocity_unknown": 2}


def test_calibrate_counts_unknown_velocities_on_finished_frames_only(tmp_path):
    """The calibrate summary's count of labelled objects of unknown velocity covers the frames
    that finished (a frame whose radar file is cut short fails and is left out), and says
    nothing when every object's velocity is known."""
    from pipeline.executor import Executor, RunEnv
    from pipeline.runner import Pipeline
    from stages import calibrate

    cfg = _fixture_cfg().with_overrides({"camera.crop_rows": "0,48", "camera.working_size": "64,48"})

    def run(root: Path) -> tuple[list[str], object]:
        lines: list[str] = []
        env = RunEnv(cfg=cfg, cache_root=str(root / "cache"), dataset="vod", data_root=str(root / "data"))
        report, = Pipeline([calibrate.STAGE], env, Executor(1), progress=False, log=lines.append).run("calibrate")
        return lines, report

    make_vod_dataset(tmp_path / "known/data", n_frames=3, speed_mps=5.0, object_velocity_D=(1.0, 0.5, 0.0))
    lines, report = run(tmp_path / "known")
    assert report.done == 3 and not any("velocity" in note for note in report.notes), report.notes
    assert not any("unknown velocity" in line for line in lines), lines
    # a pedestrian (track 9) in the second frame alone, and the last frame's radar cut short
    data = tmp_path / "mixed/data"
    truth = make_vod_dataset(data, n_frames=4, speed_mps=5.0, object_velocity_D=(1.0, 0.5, 0.0))
    second = data / "lidar/training/label_2" / f"{truth.frame_ids[1]}.txt"
    second.write_text(second.read_text() + kitti_label_line("Pedestrian", 9, np.array([12.0, 3.0, 0.0]),
                                                            np.array([0.6, 0.6, 1.7]), 0.0, T_CAM_RADAR) + "\n")
    (data / "radar/training/velodyne" / f"{truth.frame_ids[3]}.bin").write_bytes(b"\0" * 10)
    lines, report = run(tmp_path / "mixed")
    assert report.done == 3 and report.failed == 1
    assert any("labelled objects of unknown velocity: 1 of 4:" in line for line in lines), (lines, report.notes)
