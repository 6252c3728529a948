"""Reader-level bad input: each case raises ReaderError whose one-line message names file and problem."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.config import load_config
from pipeline.errors import ReaderError
from pipeline.readers import get_reader
from pipeline.readers.testing import T_CAM_RADAR, make_astyx_dataset, make_vod_dataset, rigid, write_image, write_pose

FID = "00011"


@pytest.fixture()
def vod(tmp_path):
    make_vod_dataset(tmp_path, n_frames=3, first=10)
    return tmp_path


@pytest.fixture()
def astyx(tmp_path):
    make_astyx_dataset(tmp_path, n_frames=2, n_radar=200)
    return tmp_path


def _vod_reader(root: Path):
    return get_reader(load_config("vod").with_overrides({"camera.full_size": "64,48"}), root)


def _astyx_reader(root: Path):
    return get_reader(load_config("astyx").with_overrides({"camera.full_size": "64,48"}), root)


def _expect(reader, fid: str, path: Path, problem: str) -> ReaderError:
    with pytest.raises(ReaderError) as info:
        reader.read(fid)
    message = str(info.value)
    assert "\n" not in message
    assert str(path) in message, message
    assert problem in message, message
    assert info.value.frame == fid
    return info.value


def _radar(root: Path, fid: str = FID) -> Path:
    return root / "radar/training/velodyne" / f"{fid}.bin"


def _lidar(root: Path, fid: str = FID) -> Path:
    return root / "lidar/training/velodyne" / f"{fid}.bin"


def _calib(root: Path, fid: str = FID) -> Path:
    return root / "radar/training/calib" / f"{fid}.txt"


def _image(root: Path, fid: str = FID) -> Path:
    return root / "lidar/training/image_2" / f"{fid}.jpg"


def test_truncated_radar_bin(vod):
    with open(_radar(vod), "ab") as f:
        f.write(b"\x00\x01\x02")
    _expect(_vod_reader(vod), FID, _radar(vod), "not a multiple of 28")


def test_radar_records_saved_as_lidar_have_wrong_length(vod):
    np.zeros((3, 7), "<f4").tofile(_lidar(vod))  # 84 bytes: not 4-float records
    _expect(_vod_reader(vod), FID, _lidar(vod), "not a multiple of 16")


def test_lidar_records_saved_as_radar_are_rejected_by_time_column(vod):
    lidar = np.random.default_rng(0).uniform(1, 30, (14, 4)).astype("<f4")  # 224 bytes = 8 x 28
    lidar.tofile(_radar(vod))
    _expect(_vod_reader(vod), FID, _radar(vod), "wrong record type")


def test_nan_radar_points(vod):
    radar = np.fromfile(_radar(vod), "<f4").reshape(-1, 7)
    radar[3, 1] = np.nan
    radar.tofile(_radar(vod))
    _expect(_vod_reader(vod), FID, _radar(vod), "NaN or inf")


def test_inf_lidar_points_astyx(astyx):
    path = astyx / "lidar_vlp16/000001.txt"
    lines = path.read_text().splitlines()
    lines[5] = "inf 0.0 0.0 5 0 1000"
    path.write_text("\n".join(lines) + "\n")
    _expect(_astyx_reader(astyx), "000001", path, "NaN or inf")


def test_empty_radar_frame(vod):
    _radar(vod).write_bytes(b"")
    _expect(_vod_reader(vod), FID, _radar(vod), "no points")


def test_empty_lidar_frame(vod):
    _lidar(vod).write_bytes(b"")
    _expect(_vod_reader(vod), FID, _lidar(vod), "no points")


def test_missing_calibration_key(vod):
    text = "\n".join(l for l in _calib(vod).read_text().splitlines() if not l.startswith("P2"))
    _calib(vod).write_text(text)
    _expect(_vod_reader(vod), FID, _calib(vod), "'P2' is missing")


def test_malformed_calibration_values(vod):
    text = _calib(vod).read_text().replace("R0_rect: 1 0 0", "R0_rect: 1 zero 0")
    _calib(vod).write_text(text)
    _expect(_vod_reader(vod), FID, _calib(vod), "malformed calibration values for key 'R0_rect'")


def test_non_invertible_transform(vod):
    lines = [("Tr_velo_to_cam: " + " ".join(["0"] * 12)) if l.startswith("Tr_velo_to_cam") else l
             for l in _calib(vod).read_text().splitlines()]
    _calib(vod).write_text("\n".join(lines))
    _expect(_vod_reader(vod), FID, _calib(vod), "not an invertible rigid transform")


def test_astyx_missing_intrinsics_and_scaled_transform(astyx):
    path = astyx / "calibration/000001.json"
    calib = json.loads(path.read_text())
    del calib["sensors"][2]["calib_data"]["K"]
    path.write_text(json.dumps(calib))
    _expect(_astyx_reader(astyx), "000001", path, "'K' of sensor 'camera_front' is missing")
    calib["sensors"][1]["calib_data"]["T_to_ref_COS"] = (2 * np.eye(4)).tolist()
    path.write_text(json.dumps(calib))
    _expect(_astyx_reader(astyx), "000001", path, "not an invertible rigid transform")


def test_corrupt_image(vod):
    _image(vod).write_bytes(b"\xff\xd8 this is not a jpeg")
    _expect(_vod_reader(vod), FID, _image(vod), "cannot be decoded")


def test_image_of_wrong_size(vod):
    write_image(_image(vod), (80, 48))
    _expect(_vod_reader(vod), FID, _image(vod), "image is 80x48 pixels, expected 64x48")


def test_index_entry_outside_dataset_root(astyx):
    index = json.loads((astyx / "dataset.json").read_text())
    index["data"]["1"]["radar_6455"] = "../../outside/000001.txt"
    (astyx / "dataset.json").write_text(json.dumps(index))
    reader = _astyx_reader(astyx)
    assert "000001" in reader.frame_ids()
    _expect(reader, "000001", astyx / "dataset.json", "points outside the dataset root")


def test_astyx_sensor_folders_linked_elsewhere_are_read_with_follow_links(astyx, tmp_path_factory):
    """A data root assembled from links to other storage (a cluster's usual layout): refused by
    default, naming the setting that reads through them; read with dataset.follow_links, the same
    values as from the real folders (until 2026-12-06 every frame failed, with no way out but a
    copy). '..' and absolute entries stay refused."""
    before = _astyx_reader(astyx).read("000001")
    storage = tmp_path_factory.mktemp("storage")
    for folder in ("camera_front", "lidar_vlp16"):
        (astyx / folder).rename(storage / folder)
        (astyx / folder).symlink_to(storage / folder, target_is_directory=True)
    error = _expect(_astyx_reader(astyx), "000001", astyx / "dataset.json", "points outside the dataset root")
    assert "dataset.follow_links=true" in str(error) and "--retry-failed" in str(error)
    cfg = load_config("astyx").with_overrides({"camera.full_size": "64,48", "dataset.follow_links": "true"})
    after = get_reader(cfg, astyx).read("000001")
    assert np.array_equal(after.lidar_D, before.lidar_D) and np.array_equal(after.image, before.image)
    index = json.loads((astyx / "dataset.json").read_text())
    index["data"]["1"]["radar_6455"] = "radar_6455/../../outside/000001.txt"
    (astyx / "dataset.json").write_text(json.dumps(index))
    _expect(get_reader(cfg, astyx), "000001", astyx / "dataset.json", "points outside the dataset root")


def test_missing_files_are_skipped_counted_and_raise_on_read(vod):
    _lidar(vod).unlink()
    reader = _vod_reader(vod)
    assert reader.frame_ids() == ["00010", "00012"]
    assert reader.report()["skipped_missing"] == 1
    _expect(reader, FID, _lidar(vod), "missing")
    # the skipped frame is named with the file it lacks (until 2026-12-06 only counted:
    # 'reader skipped missing: 1', which of 10,000 frames not said)
    assert reader.skipped_examples() == [f"{FID}: no lidar/training/velodyne/{FID}.bin"]


def test_astyx_missing_files_are_skipped_and_counted(astyx):
    (astyx / "camera_front/000000.jpg").unlink()
    reader = _astyx_reader(astyx)
    assert reader.frame_ids() == ["000001"] and reader.report()["skipped_missing"] == 1
    _expect(reader, "000000", astyx / "dataset.json", "missing")
    # named with the file it lacks, as the other readers do (until 2026-12-06 only counted)
    assert reader.skipped_examples() == ["000000: no camera_front/000000.jpg"]


def test_duplicate_frame_id_jpg_and_png(vod):
    write_image(_image(vod).with_suffix(".png"), (64, 48))
    _expect(_vod_reader(vod), FID, _image(vod), "duplicate frame id")


def test_frame_ids_differing_only_by_leading_zeros_are_one_refused_frame(vod):
    """`11.bin` beside `00011.bin`: one frame number with two sets of files. It is listed once
    (not as two frames), counted in report(), and refused naming both files."""
    for path in list(vod.rglob(f"{FID}.*")):
        shutil.copy(path, path.with_name("11" + path.suffix))
    reader = _vod_reader(vod)
    assert reader.frame_ids() == ["00010", FID, "00012"]
    assert reader.report()["frame_ids_differing_by_leading_zeros"] == 1
    err = _expect(reader, FID, _radar(vod), "frame number 11 has a second set of files")
    assert str(_radar(vod, "11")) in str(err)
    with pytest.raises(ReaderError, match=re.escape(str(_radar(vod, FID)))):
        reader.read("11")  # the other name is refused too, naming the listed one
    for path in vod.rglob("11.*"):  # a stray point file alone is enough to make the frame ambiguous
        if path.parent.name != "velodyne" or path.parent.parent.parent.name != "lidar":
            path.unlink()
    reader = _vod_reader(vod)
    assert reader.frame_ids() == ["00010", FID, "00012"]
    assert str(_lidar(vod, "11")) in str(_expect(reader, FID, _radar(vod), "second set of files"))
    _lidar(vod, "11").unlink()
    _vod_reader(vod).read(FID)  # one set of files again: read as before


def test_negative_box_size_in_a_label_is_refused(vod):
    path = vod / "lidar/training/label_2" / f"{FID}.txt"
    line = path.read_text().splitlines()[0]
    parts = line.split()
    for column, name in ((8, "h"), (9, "w"), (10, "l")):
        bad = parts.copy()
        bad[column] = "-" + bad[column]
        path.write_text(line + "\n\n" + " ".join(bad) + "\n")  # the blank line still counts
        _expect(_vod_reader(vod), FID, path, f"label line 3 has a negative box {name} (-{float(parts[column]):g} m)")
    # KITTI's DontCare lines carry -1 sizes: not an error, and no object
    path.write_text(line + "\nDontCare -1 -1 -10 1 1 2 2 -1 -1 -1 -1000 -1000 -1000 -10\n")
    assert [o.class_name for o in _vod_reader(vod).read(FID).labels] == [parts[0]]
    # a neighbour's label file is read for the object velocities: its bad line is named too
    path.write_text(line + "\n")
    neighbour = vod / "lidar/training/label_2" / "00012.txt"
    parts = neighbour.read_text().split()
    parts[8] = "-2"
    neighbour.write_text(" ".join(parts) + "\n")
    with pytest.raises(ReaderError, match=re.escape(f"{neighbour}: label line 1 has a negative box h (-2 m)")):
        _vod_reader(vod).read(FID)


def test_duplicate_index_entries(astyx):
    text = (astyx / "dataset.json").read_text()
    entry = json.dumps(json.loads(text)["data"]["1"])
    (astyx / "dataset.json").write_text(text.replace('"data": {', f'"data": {{"01": {entry}, ', 1))
    _expect(_astyx_reader(astyx), "000001", astyx / "dataset.json", "duplicate index entries '01' and '1'")
    # the same key twice (json would silently keep the last one)
    (astyx / "dataset.json").write_text(text.replace('"data": {', f'"data": {{"0": {entry}, ', 1))
    _expect(_astyx_reader(astyx), "000000", astyx / "dataset.json", "duplicate index entr")


def test_non_monotonic_timestamps(vod):
    for fid, t in (("00010", 5.0), ("00011", 4.9)):
        write_pose(vod / "lidar/training/pose" / f"{fid}.json", np.linalg.inv(T_CAM_RADAR), t)
    _expect(_vod_reader(vod), FID, vod / "lidar/training/pose" / f"{FID}.json", "non-monotonic timestamps")


def test_absurd_ego_speed(vod):
    radar = np.fromfile(_radar(vod), "<f4").reshape(-1, 7)
    u = radar[:, :3] / np.linalg.norm(radar[:, :3], axis=1, keepdims=True)
    radar[:, 4] = -(u @ np.array([100.0, 0, 0]))
    radar[:, 5] = 0.0
    radar.tofile(_radar(vod))
    _expect(_vod_reader(vod), FID, _radar(vod), "absurd ego speed 100.0 m/s")


def test_radar_points_all_outside_field_of_view(vod):
    radar = np.fromfile(_radar(vod), "<f4").reshape(-1, 7)
    radar[:, 0] *= -1  # behind the sensor: wrong axis convention
    radar.tofile(_radar(vod))
    _expect(_vod_reader(vod), FID, _radar(vod), "outside the field of view")


def test_astyx_radar_row_with_missing_value(astyx):
    path = astyx / "radar_6455/000001.txt"
    lines = path.read_text().splitlines()
    lines[4] = "1.0 2.0 0.5 48"
    path.write_text("\n".join(lines) + "\n")
    _expect(_astyx_reader(astyx), "000001", path, "has 4 values, expected 5")


def test_malformed_pose_file(vod):
    path = vod / "lidar/training/pose" / f"{FID}.json"
    path.write_text('{"odomToCamera": [1, 2,')
    _expect(_vod_reader(vod), FID, path, "not JSON lines")


def test_pose_that_is_not_rigid(vod):
    write_pose(vod / "lidar/training/pose" / f"{FID}.json", rigid(3 * np.eye(3), np.zeros(3)))
    radar = np.fromfile(_radar(vod), "<f4").reshape(-1, 7)[:2]  # too few points: poses are needed
    radar.tofile(_radar(vod))
    _expect(_vod_reader(vod), FID, vod / "lidar/training/pose" / f"{FID}.json", "odomToCamera")


def test_mirrored_and_doubled_calibrations_are_refused(vod, astyx):
    """A reflection passes an orthonormality test but mirrors the lidar; two values for one key
    leave the reader guessing (found by the 2026-12-02 audit: both gave silently wrong frames)."""
    text = _calib(vod).read_text()
    _calib(vod).write_text(text.replace("R0_rect: 1 0 0", "R0_rect: -1 0 0"))
    _expect(_vod_reader(vod), FID, _calib(vod), "determinant -1")
    tr = next(line for line in text.splitlines() if line.startswith("Tr_velo_to_cam"))
    _calib(vod).write_text(text + "\n" + tr + "\n")
    _expect(_vod_reader(vod), FID, _calib(vod), "'Tr_velo_to_cam' appears twice")
    path = astyx / "calibration/000001.json"
    calib = json.loads(path.read_text())
    mirrored = np.asarray(calib["sensors"][1]["calib_data"]["T_to_ref_COS"])
    mirrored[:3, 0] *= -1
    calib["sensors"][1]["calib_data"]["T_to_ref_COS"] = mirrored.tolist()
    path.write_text(json.dumps(calib))
    _expect(_astyx_reader(astyx), "000001", path, "determinant -1")
    calib["sensors"][1]["calib_data"] = None
    path.write_text(json.dumps(calib))
    _expect(_astyx_reader(astyx), "000001", path, "'T_to_ref_COS' of sensor 'lidar_vlp16' is missing")


def test_astyx_radar_columns_by_name_and_doppler_span(astyx):
    path = astyx / "radar_6455/000000.txt"
    text = path.read_text()
    path.write_text(text.replace("X Y Z V_r Mag", "X Y Z Mag V_r"))
    _expect(_astyx_reader(astyx), "000000", path, "columns X Y Z Mag V_r, expected X Y Z V_r Mag")
    lines = text.splitlines()
    first = next(i for i, line in enumerate(lines) if line.strip() and line.split()[0] != "X")
    values = lines[first].split()
    values[3] = "48.0"   # a magnitude where V_r belongs
    lines[first] = " ".join(values)
    path.write_text("\n".join(lines) + "\n")
    _expect(_astyx_reader(astyx), "000000", path, "outside the sensor's unambiguous span")


def test_astyx_ground_truth_with_nan_is_refused(astyx):
    path = next((astyx / "groundtruth_obj3d").glob("*.json"))
    fid = path.stem
    gt = json.loads(path.read_text())
    gt["objects"][0]["center3d"][0] = float("nan")
    path.write_text(json.dumps(gt))
    _expect(_astyx_reader(astyx), fid, path, "NaN or inf")


def test_calibrate_fails_a_frame_whose_points_all_miss_the_camera():
    """A wrong calibration (in millimetres, another sensor's matrix) can pass every reader check and
    put every lidar or radar point outside the camera's view: the frame fails instead of being
    stored empty."""
    from pipeline.errors import FrameError
    from stages.calibrate import _check_view

    _check_view("f", n_lidar=20000, n_lidar_kept=9000, n_radar=300, n_radar_kept=120)
    _check_view("f", n_lidar=20000, n_lidar_kept=9000, n_radar=5, n_radar_kept=0)     # too few to judge
    with pytest.raises(FrameError, match="none of the 20000 lidar points"):
        _check_view("f", n_lidar=20000, n_lidar_kept=0, n_radar=300, n_radar_kept=120)
    with pytest.raises(FrameError, match="none of the 300 radar points"):
        _check_view("f", n_lidar=20000, n_lidar_kept=9000, n_radar=300, n_radar_kept=0)
