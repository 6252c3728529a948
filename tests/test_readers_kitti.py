"""KITTI object-layout reader (camera + lidar, no radar) on a fixture in the exact layout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.config import load_config
from pipeline.errors import ReaderError
from pipeline.geometry import invert_transform, project_to_image
from pipeline.readers import get_reader
from pipeline.readers.testing import K_FIXTURE, R_CAM_D, kitti_label_line, rigid, write_image, write_kitti_calib

T_CAM_VELO = rigid(R_CAM_D, np.array([0.0, -0.08, -0.27]))


def _make(root: Path, fid: str = "000007", size=(64, 48), oxts: bool = False) -> np.ndarray:
    base = root / "training"
    rng = np.random.default_rng(0)
    velo = np.concatenate([rng.uniform([3, -5, -1.5], [30, 5, 1], (400, 3)), rng.uniform(0, 1, (400, 1))], 1)
    (base / "velodyne").mkdir(parents=True)
    velo.astype("<f4").tofile(base / "velodyne" / f"{fid}.bin")
    write_kitti_calib(base / "calib" / f"{fid}.txt", K_FIXTURE, T_CAM_VELO)
    write_image(base / "image_2" / f"{fid}.png", size)
    (base / "label_2").mkdir()
    line = kitti_label_line("Car", 0, np.array([12.0, 1.0, -0.8]), np.array([4.0, 1.7, 1.5]), 0.3, T_CAM_VELO)
    (base / "label_2" / f"{fid}.txt").write_text(line.rsplit(" ", 1)[0] + "\nDontCare -1 -1 -10 1 1 2 2 -1 -1 -1 -1000 -1000 -1000 -10\n")
    if oxts:
        (base / "oxts").mkdir()
        (base / "oxts" / f"{fid}.txt").write_text("49.0 8.4 110 0 0 0.1 5 5 6.0 0.2 0.0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0\n")
    return velo


def _cfg(mount=(1, 0, 0, 0.76, 0, 1, 0, 0, 0, 0, 1, -1.08, 0, 0, 0, 1)):
    return load_config("kitti").with_overrides({"camera.full_size": "64,48",
                                                "dataset.radar_mount_T_radar_lidar": ",".join(map(str, mount))})


def test_reads_without_radar_and_mounts_lidar(tmp_path):
    velo = _make(tmp_path)
    reader = get_reader(_cfg(), tmp_path)
    assert reader.frame_ids() == ["000007"]
    rec = reader.read("000007")
    assert rec.radar_D.shape == (0, 5) and rec.has_radar is False
    np.testing.assert_allclose(rec.lidar_D, velo[:, :3] + [0.76, 0, -1.08], atol=1e-5)
    np.testing.assert_allclose(rec.ego_velocity_D, 0.0)
    assert reader.report()["ego_velocity_unknown"] == 1 and rec.ego_velocity_known is False
    # T_cam_radar @ T_radar_lidar reproduces the calibration's lidar->camera transform
    np.testing.assert_allclose(invert_transform(rec.T_radar_cam) @ rec.T_radar_lidar, T_CAM_VELO, atol=1e-9)
    assert [o.class_name for o in rec.labels] == ["Car"]
    np.testing.assert_allclose(rec.labels[0].center_D, [12.76, 1.0, -1.88], atol=1e-6)
    # lidar projected from {D} lands where projecting the raw Velodyne points with P2 / Tr lands
    uv, _, valid = project_to_image(rec.lidar_D, rec.K, invert_transform(rec.T_radar_cam), (64, 48))
    p_cam = velo[:, :3] @ T_CAM_VELO[:3, :3].T + T_CAM_VELO[:3, 3]
    uv_ref = (p_cam @ K_FIXTURE.T)[:, :2] / p_cam[:, 2:3]
    np.testing.assert_allclose(uv[valid], uv_ref[valid], atol=1e-3)


def test_oxts_velocity_and_image_padding(tmp_path):
    _make(tmp_path, size=(60, 46), oxts=True)
    reader = get_reader(_cfg(), tmp_path)
    rec = reader.read("000007")
    np.testing.assert_allclose(rec.ego_velocity_D, [6.0, 0.2, 0.0])
    assert rec.ego_velocity_known is True
    assert rec.image.shape == (48, 64, 3) and reader.report()["images_padded_or_cropped"] == 1
    assert reader.detector_files("000007").image is None  # padded: the export writes the reader's image


def test_bad_mount_and_far_wrong_image_size(tmp_path):
    _make(tmp_path, size=(200, 48))
    with pytest.raises(ReaderError, match="image is 200x48"):
        get_reader(_cfg(), tmp_path).read("000007")
    with pytest.raises(ReaderError, match="radar mount"):
        get_reader(_cfg(mount=(2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1)), tmp_path).read("000007")


def _rotation(axis, angle_rad: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1 - np.cos(angle_rad)) * k @ k


def _write_real_kitti_calib(path: Path, P2: np.ndarray, R0: np.ndarray, Tr: np.ndarray) -> None:
    """KITTI's own form: P0..P3 differ (P2 and P3 carry camera 2's and 3's offsets from camera 0),
    R0_rect a rotation, Tr_velo_to_cam velodyne -> unrectified camera 0, Tr_imu_to_velo set."""
    P0 = np.column_stack([P2[:, :3], np.zeros(3)])
    P3 = np.column_stack([P2[:, :3], P2[:, :3] @ [-0.47, 0.002, 0.003]])
    imu = rigid(np.eye(3), np.array([-0.81, 0.32, -0.80]))[:3]
    rows = {"P0": P0, "P1": P0, "P2": P2, "P3": P3, "R0_rect": R0, "Tr_velo_to_cam": Tr[:3], "Tr_imu_to_velo": imu}
    path.write_text("".join(f"{k}: " + " ".join(f"{v:.12e}" for v in m.ravel()) + "\n" for k, m in rows.items()))


def test_labels_are_in_the_rectified_camera_0_and_the_export_keeps_kitti_conventions(tmp_path):
    """KITTI labels live in the rectified camera 0 (P2's 4th column is camera 2's offset from it,
    about 6 cm): the reader's boxes and the exported calib (radar in the Velodyne's place) must put
    a label where OpenPCDet's KITTI calibration does (p_lidar = (R0_rect Tr_velo_to_cam)^-1 p_rect),
    and the exported P2 must project {D} points to the reader's pixels."""
    from pipeline.export import CALIB_KEYS, calib_text
    from pipeline.readers.kitti_format import calib_matrix, parse_calib_file

    _make(tmp_path)
    fid = "000007"
    R0 = _rotation([0.3, 1.0, -0.2], np.deg2rad(0.8))
    P2 = np.column_stack([K_FIXTURE, K_FIXTURE @ [0.0599, -0.0003, 0.0027]])
    _write_real_kitti_calib(tmp_path / "training" / "calib" / f"{fid}.txt", P2, R0, T_CAM_VELO)
    bottom_rect, (h, w, l), ry = np.array([1.5, 1.6, 14.0]), (1.5, 1.7, 4.0), 0.4
    (tmp_path / "training" / "label_2" / f"{fid}.txt").write_text(
        f"Car 0.00 0 0.1 10 10 20 20 {h} {w} {l} {' '.join(map(str, bottom_rect))} {ry}\n")
    cfg = _cfg()
    reader = get_reader(cfg, tmp_path)
    rec = reader.read(fid)
    T_radar_lidar = rec.T_radar_lidar
    R0_4 = rigid(R0, np.zeros(3))
    centre_rect = bottom_rect - [0.0, h / 2, 0.0]
    centre_lidar = invert_transform(R0_4 @ T_CAM_VELO) @ np.append(centre_rect, 1.0)
    expected_D = (T_radar_lidar @ centre_lidar)[:3]
    np.testing.assert_allclose(rec.labels[0].center_D, expected_D, atol=1e-9)
    # the reader's pixels come from P2 as a whole (camera 2, with its offset)
    p_lidar = np.array([[20.0, 2.0, 0.5], [12.0, -3.0, -1.0]])
    p_cam2 = (P2 @ np.column_stack([(R0_4 @ T_CAM_VELO @ np.column_stack([p_lidar, np.ones(2)]).T).T[:, :3], np.ones(2)]).T).T
    uv_ref = p_cam2[:, :2] / p_cam2[:, 2:]
    p_D = (T_radar_lidar @ np.column_stack([p_lidar, np.ones(2)]).T).T[:, :3]
    uv, _, _ = project_to_image(p_D, rec.K, invert_transform(rec.T_radar_cam), (64, 48))
    np.testing.assert_allclose(uv, uv_ref, atol=1e-6)

    files = reader.detector_files(fid)
    assert files.label == tmp_path / "training" / "label_2" / f"{fid}.txt"
    assert files.image == tmp_path / "training" / "image_2" / f"{fid}.png"  # used as it is: copied as it is
    out = tmp_path / "calib_out.txt"
    out.write_text(calib_text(files.calib))
    assert [line.split(":")[0] for line in out.read_text().splitlines()] == list(CALIB_KEYS)
    parsed = parse_calib_file(out, fid)
    Tr_new, R0_new = np.eye(4), np.eye(4)
    Tr_new[:3] = calib_matrix(parsed, "Tr_velo_to_cam", (3, 4), out, fid)
    R0_new[:3, :3] = calib_matrix(parsed, "R0_rect", (3, 3), out, fid)
    P2_new = calib_matrix(parsed, "P2", (3, 4), out, fid)
    # OpenPCDet: rect -> "lidar" (here the radar frame {D}) with (R0_rect Tr_velo_to_cam)^-1
    np.testing.assert_allclose((invert_transform(R0_new @ Tr_new) @ np.append(centre_rect, 1.0))[:3], expected_D,
                               atol=1e-9)
    proj = (P2_new @ np.column_stack([(R0_new @ Tr_new @ np.column_stack([p_D, np.ones(2)]).T).T[:, :3],
                                      np.ones(2)]).T).T
    np.testing.assert_allclose(proj[:, :2] / proj[:, 2:], uv_ref, atol=1e-6)
    np.testing.assert_allclose(calib_matrix(parsed, "P3", (3, 4), out, fid), P2[:, :3] @ np.column_stack(
        [np.eye(3), [-0.47, 0.002, 0.003]]), atol=1e-9)


def test_the_kitti_profile_mounts_the_radar_in_the_front_bumper():
    """The profile's radar sits ahead of and below the Velodyne (1.73 m up on KITTI's car), about
    bumper height: the road under the Velodyne (z_velo = -1.73 m) is 0.4-0.8 m below {D}'s origin.
    Until 2026-12-04 the translation's signs were reversed (radar behind and 1.08 m above)."""
    from pipeline.readers.kitti import KittiReader

    mount = KittiReader(load_config("kitti", environ={}), "/nonexistent").mount()
    radar_in_velo = invert_transform(mount)[:3, 3]
    assert radar_in_velo[0] > 0.5 and abs(radar_in_velo[1]) < 0.5
    road_D = (mount @ [10.0, 0.0, -1.73, 1.0])[:3]
    assert -0.8 < road_D[2] < -0.4


def test_calibrate_says_how_many_frames_have_no_ego_motion(tmp_path):
    """A KITTI frame without oxts is synthesized as if stopped: the calibrate run says on how many."""
    from pipeline.executor import Executor, RunEnv
    from pipeline.runner import Pipeline
    from stages import calibrate

    _make(tmp_path / "data")
    cfg = _cfg().with_overrides({"camera.crop_rows": "0,48", "camera.working_size": "64,48"})
    lines: list[str] = []
    env = RunEnv(cfg=cfg, cache_root=str(tmp_path / "cache"), dataset="kitti", data_root=str(tmp_path / "data"))
    Pipeline([calibrate.STAGE], env, Executor(1), progress=False, log=lines.append).run("calibrate")
    assert not np.asarray(env.store("calibrate").array("ego_velocity_known")[:]).any()
    assert any("ego velocity unknown on 1 of 1 frames" in line and "stopped car" in line for line in lines), lines
    # KITTI's object set records no object motion either: the run says how many objects that leaves
    n_labels = int(np.asarray(env.store("calibrate").array("labels_count")[:]).sum())
    assert n_labels > 0
    assert any(f"labelled objects of unknown velocity: {n_labels} of {n_labels}" in line for line in lines), lines


def test_a_failed_frame_is_named_once_in_its_reason(tmp_path):
    """A reader error names its frame; the recorded reason adds the stage without naming the frame
    a second time (until 2026-12-04: 'stage calibrate, frame 000007: frame 000007: ...')."""
    from pipeline.executor import Executor, RunEnv
    from pipeline.runner import Pipeline
    from stages import calibrate

    _make(tmp_path / "data", size=(200, 150))       # far from camera.full_size: the frame fails
    cfg = _cfg().with_overrides({"camera.crop_rows": "0,48", "camera.working_size": "64,48"})
    env = RunEnv(cfg=cfg, cache_root=str(tmp_path / "cache"), dataset="kitti", data_root=str(tmp_path / "data"))
    report, = Pipeline([calibrate.STAGE], env, Executor(1), progress=False, log=lambda m: None).run("calibrate")
    (_, reason), = report.failures
    assert reason.startswith("stage calibrate, frame 000007: ") and reason.count("000007") == 2, reason  # + the file
    assert "image is 200x150 pixels" in reason


def test_the_kitti_profile_describes_the_only_layout_its_reader_reads():
    """`pipeline datasets` called it 'KITTI object/raw layout', but the reader reads the object layout
    only (training/velodyne, image_2, calib; an oxts/ID.txt per frame at most): a raw drive folder
    finds no frame."""
    description = load_config("kitti").dataset.description
    assert "object layout" in description and "raw" not in description
