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
    assert reader.report()["ego_velocity_unknown"] == 1
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
    assert rec.image.shape == (48, 64, 3) and reader.report()["images_padded_or_cropped"] == 1


def test_bad_mount_and_far_wrong_image_size(tmp_path):
    _make(tmp_path, size=(200, 48))
    with pytest.raises(ReaderError, match="image is 200x48"):
        get_reader(_cfg(), tmp_path).read("000007")
    with pytest.raises(ReaderError, match="radar mount"):
        get_reader(_cfg(mount=(2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1)), tmp_path).read("000007")
