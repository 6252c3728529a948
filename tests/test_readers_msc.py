"""MSC-Rad4R reader on fixtures written in the documented formats with pypcd4 and rosbags.

No real MSC-Rad4R file exists here: these tests check the reader against the formats as
documented (see pipeline/readers/msc.py), not against the real dataset.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from pypcd4 import PointCloud

from pipeline.config import load_config
from pipeline.errors import ReaderError
from pipeline.geometry import invert_transform, project_to_image
from pipeline.readers import get_reader
from pipeline.readers.msc import MscBagReader, MscFolderReader, pair_nearest
from pipeline.readers.testing import R_CAM_D

K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
DIST = np.array([-0.23, 0.12, 0.0, 0.0, 0.0])
T_CAM_NATIVE_T = np.array([0.1, 0.2, 0.3])
T_CAM_LIDAR_T = np.array([0.0, -0.5, -0.2])
RADAR_FIELDS = ("x", "y", "z", "beta", "alpha", "power", "doppler", "range", "recoveredSpeed", "denoiseFlag")


def _cfg():
    return load_config("msc").with_overrides({"camera.full_size": "64,48"})


def _write_calibration(folder: Path) -> None:
    folder.mkdir(parents=True)
    matlab = K + np.array([[0, 0, 1], [0, 0, 1], [0, 0, 0]])  # MATLAB's pixel centres start at (1, 1)
    kt = "\n".join("  " + " ".join(f"{v:g}" for v in row) for row in matlab.T)  # MATLAB (transposed) form
    (folder / "CALIBRATION_CAMERA.txt").write_text(
        f"Stereo parameters\nLeft camera\nIntrinsic (K)\n{kt}\nRadial Distortion\n  -0.23 0.12\n"
        f"Right camera\nIntrinsic (K)\n  99 0 0\n 0 99 0\n 30 20 1\nRadial Distortion\n -0.1 0.0\n")
    (folder / "CALIBRATION_CAMERA_RADAR.txt").write_text(
        "attitude of RADAR in camera coordinate\n1 0 0\n0 1 0\n0 0 1\n"
        "translation of RADAR in camera coordinate\n" + " ".join(map(str, T_CAM_NATIVE_T)) + "\n")
    (folder / "CALIBRATION_CAMERA_LIDAR.txt").write_text(
        "attitude of LIDAR in camera coordinate\n" + "\n".join(" ".join(map(str, r)) for r in R_CAM_D)
        + "\ntranslation of LIDAR in camera coordinate\n" + " ".join(map(str, T_CAM_LIDAR_T)) + "\n")


def _radar_native(rng: np.random.Generator, n: int = 40) -> np.ndarray:
    """(n, 10) radar rows in the native right-down-forward frame, columns RADAR_FIELDS."""
    xyz = rng.uniform([-8, -1, 5], [8, 1, 40], (n, 3))
    out = np.zeros((n, 10), np.float32)
    out[:, :3] = xyz
    out[:, 5] = rng.uniform(2, 50, n)
    out[:, 6] = rng.uniform(-3, 3, n)
    out[:, 7] = np.linalg.norm(xyz, axis=1)
    return out


def _lidar(rng: np.random.Generator) -> np.ndarray:
    return np.concatenate([rng.uniform([3, -8, -1], [30, 8, 2], (300, 3)), rng.uniform(0, 100, (300, 1))], 1).astype(np.float32)


def _image(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 255, (48, 64, 3), dtype=np.uint8)


def _stamps(path: Path, times: list[float]) -> None:
    path.write_text("".join(f"{k} {int(t)} {int(round((t % 1) * 1e9))}\n" for k, t in enumerate(times)))


def make_folder(root: Path, radar_times=(100.0, 100.0667, 100.1333), image_times=(100.001, 100.068, 100.134),
                lidar_times=(100.01, 100.13)) -> dict:
    rng = np.random.default_rng(0)
    truth = {"radar": [], "image": [], "lidar": []}
    for sub in ("1_IMAGE/LEFT", "2_LIDAR/PCD", "3_RADAR/PCD", "4_NAVIGATION"):
        (root / sub).mkdir(parents=True)
    for k, _ in enumerate(radar_times):
        rows = _radar_native(rng)
        PointCloud.from_points(rows, RADAR_FIELDS, [np.float32] * 10).save(root / "3_RADAR/PCD" / f"{k:06d}.pcd")
        truth["radar"].append(rows)
    for k, _ in enumerate(lidar_times):
        pts = _lidar(rng)
        PointCloud.from_points(pts, ("x", "y", "z", "intensity"), [np.float32] * 4).save(root / "2_LIDAR/PCD" / f"{k:06d}.pcd")
        truth["lidar"].append(pts)
    for k, _ in enumerate(image_times):
        cv2.imwrite(str(root / "1_IMAGE/LEFT" / f"{k:06d}.png"), _image(k))
    _stamps(root / "3_RADAR/timestamp_radar.txt", list(radar_times))
    _stamps(root / "1_IMAGE/timestamp_image_left.txt", list(image_times))
    _stamps(root / "2_LIDAR/timestamp_lidar.txt", list(lidar_times))
    for side, v in (("LEFT", 4.0), ("RIGHT", 6.0)):
        (root / "4_NAVIGATION" / f"WHEEL_{side}.txt").write_text(
            "".join(f"{k} {100 + k // 10} {(k % 10) * 100_000_000} {v + k * 0.1} 0.01\n" for k in range(5)))
    _write_calibration(root / "5_CALIBRATION_URBAN")
    return truth


def test_pair_nearest_matches_brute_force():
    rng = np.random.default_rng(2)
    ref, other = rng.uniform(0, 10, 50), rng.uniform(0, 10, 30)
    got = pair_nearest(ref, other, 0.05)
    for i, t in enumerate(ref):
        j = int(np.argmin(np.abs(other - t)))
        assert got[i] == (j if abs(other[j] - t) <= 0.05 else -1)


def test_folder_layout(tmp_path):
    truth = make_folder(tmp_path)
    reader = get_reader(_cfg(), tmp_path)
    assert isinstance(reader, MscFolderReader)
    # radar scan 1 (100.0667 s) has no lidar scan within 0.05 s
    assert reader.frame_ids() == ["000000", "000002"] and reader.report()["pairs_dropped"] == 1
    rec = reader.read("000002")
    native = truth["radar"][2]
    np.testing.assert_allclose(rec.radar_D[:, :3], np.stack([native[:, 2], -native[:, 0], -native[:, 1]], 1), atol=1e-5)
    np.testing.assert_allclose(rec.radar_D[:, 3], native[:, 6])
    np.testing.assert_allclose(rec.radar_D[:, 4], native[:, 5])
    np.testing.assert_allclose(rec.K, K)
    # projecting {D} points through the record = projecting native points with p_cam = p + t
    uv, _, _ = project_to_image(rec.radar_D[:, :3], rec.K, invert_transform(rec.T_radar_cam), (64, 48))
    p_cam = native[:, :3] + T_CAM_NATIVE_T
    np.testing.assert_allclose(uv, (p_cam @ K.T)[:, :2] / p_cam[:, 2:3], atol=1e-3)
    lidar_cam = truth["lidar"][1][:, :3] @ R_CAM_D.T + T_CAM_LIDAR_T
    lidar_back = rec.lidar_D @ invert_transform(rec.T_radar_cam)[:3, :3].T + invert_transform(rec.T_radar_cam)[:3, 3]
    np.testing.assert_allclose(lidar_back, lidar_cam, atol=1e-4)
    expected = cv2.undistort(_image(2), K, DIST)[:, :, ::-1]
    np.testing.assert_array_equal(rec.image, expected)
    # wheels: left 4 + 0.1 k, right 6 + 0.1 k at t = 100 + k/10 -> mean 5 + t_offset
    np.testing.assert_allclose(rec.ego_velocity_D, [5.0 + 0.1 * 1.333, 0, 0], atol=1e-3)


def test_folder_rejects_radar_not_in_native_frame(tmp_path):
    make_folder(tmp_path)
    rows = _radar_native(np.random.default_rng(5))
    rows[:, 2] *= -1
    PointCloud.from_points(rows, RADAR_FIELDS, [np.float32] * 10).save(tmp_path / "3_RADAR/PCD/000000.pcd")
    with pytest.raises(ReaderError, match="no clear forward axis"):
        get_reader(_cfg(), tmp_path).read("000000")


def test_folder_reads_radar_points_in_the_lidars_axes_and_refuses_them_moved(tmp_path):
    """MSC-Rad4R's page says the published x, y, z are in the lidar's axes (forward-left-up), not
    the Oculii's right-down-forward: either order gives the same {D} points (counted per order);
    points moved into another sensor's frame (their distance no longer their range) are refused."""
    truth = make_folder(tmp_path)
    native = truth["radar"][2]
    expected = get_reader(_cfg(), tmp_path).read("000002").radar_D
    flu = native.copy()
    flu[:, :3] = np.stack([native[:, 2], -native[:, 0], -native[:, 1]], 1)
    PointCloud.from_points(flu, RADAR_FIELDS, [np.float32] * 10).save(tmp_path / "3_RADAR/PCD/000002.pcd")
    reader = get_reader(_cfg(), tmp_path)
    np.testing.assert_array_equal(reader.read("000002").radar_D, expected)
    assert reader.report()["radar_axes_flu"] == 1
    moved = flu.copy()
    moved[:, :3] += [1.5, 0.0, 1.0]          # e.g. radar -> lidar origin
    PointCloud.from_points(moved, RADAR_FIELDS, [np.float32] * 10).save(tmp_path / "3_RADAR/PCD/000002.pcd")
    with pytest.raises(ReaderError, match="not centred on the radar"):
        get_reader(_cfg(), tmp_path).read("000002")


def test_folder_non_monotonic_radar_timestamps(tmp_path):
    make_folder(tmp_path, radar_times=(100.0, 100.0667, 99.9), image_times=(99.9, 100.0, 100.068),
                lidar_times=(99.91, 100.01, 100.07))
    with pytest.raises(ReaderError, match="non-monotonic") as info:
        get_reader(_cfg(), tmp_path).read("000002")
    assert "timestamp_radar.txt" in str(info.value)


def _write_bag(path: Path, radar_rows: np.ndarray | None = None, vel_xy: tuple[float, float] = (3.0, 4.0)) -> list[np.ndarray]:
    """Two frames; ``radar_rows`` (RADAR_FIELDS columns): every frame's radar points (default:
    _radar_native's); ``vel_xy``: the /vel twist's linear x and y, m/s."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    PointField = T["sensor_msgs/msg/PointField"]
    rng = np.random.default_rng(1)

    def header(ns: int) -> object:
        return Header(seq=0, stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="f")

    def cloud(ns: int, names: tuple[str, ...], rows: np.ndarray, pad: int) -> object:
        # float32 fields with `pad` unused bytes after each point: offsets must come from the fields
        step = 4 * len(names) + pad
        buf = np.zeros((rows.shape[0], step), np.uint8)
        buf[:, :4 * len(names)] = rows.astype("<f4").view(np.uint8).reshape(rows.shape[0], -1)
        fields = [PointField(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate(names)]
        return T["sensor_msgs/msg/PointCloud2"](header=header(ns), height=1, width=rows.shape[0], fields=fields,
                                                is_bigendian=False, point_step=step, row_step=step * rows.shape[0],
                                                data=buf.ravel(), is_dense=True)

    radars = []
    with Writer(path) as writer:
        conns = {topic: writer.add_connection(topic, msgtype, typestore=ts) for topic, msgtype in (
            ("/oculii_radar/point_cloud", "sensor_msgs/msg/PointCloud2"), ("/ouster/points", "sensor_msgs/msg/PointCloud2"),
            ("/camera_array/left/image_raw", "sensor_msgs/msg/Image"), ("/vel", "geometry_msgs/msg/TwistStamped"))}
        for k in range(2):
            t0 = 10**10 + k * 100_000_000
            rows = _radar_native(rng)
            rows = rows if radar_rows is None else radar_rows
            radars.append(rows)
            msgs = [("/oculii_radar/point_cloud", t0, cloud(t0, RADAR_FIELDS, rows, 6)),
                    ("/ouster/points", t0 + 5_000_000, cloud(t0, ("x", "y", "z", "intensity"), _lidar(rng), 4)),
                    ("/camera_array/left/image_raw", t0 + 2_000_000, T["sensor_msgs/msg/Image"](
                        header=header(t0), height=48, width=64, encoding="rgb8", is_bigendian=0, step=64 * 3,
                        data=_image(k).ravel())),
                    ("/vel", t0, T["geometry_msgs/msg/TwistStamped"](header=header(t0), twist=T["geometry_msgs/msg/Twist"](
                        linear=T["geometry_msgs/msg/Vector3"](x=vel_xy[0], y=vel_xy[1], z=0.0),
                        angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0))))]
            for topic, stamp, msg in sorted(msgs, key=lambda m: m[1]):
                writer.write(conns[topic], stamp, ts.serialize_ros1(msg, conns[topic].msgtype))
    return radars


def test_bag_layout(tmp_path):
    radars = _write_bag(tmp_path / "URBAN_D0.bag")
    _write_calibration(tmp_path / "5_CALIBRATION_URBAN")
    reader = get_reader(_cfg(), tmp_path)
    assert isinstance(reader, MscBagReader)
    assert reader.frame_ids() == ["URBAN_D0_000000", "URBAN_D0_000001"]
    rec = reader.read("URBAN_D0_000001")
    native = radars[1]
    np.testing.assert_allclose(rec.radar_D[:, :3], np.stack([native[:, 2], -native[:, 0], -native[:, 1]], 1), atol=1e-5)
    np.testing.assert_allclose(rec.radar_D[:, 3], native[:, 6])
    np.testing.assert_allclose(rec.ego_velocity_D, [5.0, 0, 0])
    np.testing.assert_array_equal(rec.image, cv2.undistort(_image(1)[:, :, ::-1], K, DIST)[:, :, ::-1])
    assert rec.lidar_D.shape == (300, 3) and rec.sequence_id == "URBAN_D0"


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis, np.float64) / np.linalg.norm(axis) * angle)[0]


def test_folder_turned_extrinsics_millimetres_and_three_radial_terms(tmp_path):
    """p_cam = R p_sensor + t with rotations that are not the identity and the radar translation in
    millimetres: radar and lidar points through the record land where the calibration text puts them
    in the camera; a third radial coefficient is k3 (OpenCV's 5th distortion term, not p1)."""
    truth = make_folder(tmp_path)
    R_radar = _rot([0.2, 1.0, 0.1], 0.15)
    t_radar_mm = np.array([120.0, -80.0, 40.0])
    R_lidar = R_CAM_D @ _rot([0.0, 0.0, 1.0], 0.3) @ _rot([1.0, 0.0, 0.0], 0.05)
    calib = tmp_path / "5_CALIBRATION_URBAN"
    rows = lambda R: "\n".join(" ".join(f"{v:.12g}" for v in r) for r in R)  # noqa: E731
    (calib / "CALIBRATION_CAMERA_RADAR.txt").write_text(
        f"attitude of RADAR in camera coordinate\n{rows(R_radar)}\n"
        "translation of RADAR in camera coordinate\n" + " ".join(map(str, t_radar_mm)) + "\n")
    (calib / "CALIBRATION_CAMERA_LIDAR.txt").write_text(
        f"attitude of LIDAR in camera coordinate\n{rows(R_lidar)}\n"
        "translation of LIDAR in camera coordinate\n" + " ".join(map(str, T_CAM_LIDAR_T)) + "\n")
    text = (calib / "CALIBRATION_CAMERA.txt").read_text()
    (calib / "CALIBRATION_CAMERA.txt").write_text(text.replace("-0.23 0.12\n", "-0.23 0.12 -0.05\n", 1))
    reader = get_reader(_cfg(), tmp_path)
    rec = reader.read("000002")
    assert reader.report()["extrinsics_in_millimetres"] == 1
    T_cam_radar = invert_transform(rec.T_radar_cam)
    radar_cam = rec.radar_D[:, :3].astype(np.float64) @ T_cam_radar[:3, :3].T + T_cam_radar[:3, 3]
    np.testing.assert_allclose(radar_cam, truth["radar"][2][:, :3] @ R_radar.T + t_radar_mm / 1000.0, atol=1e-4)
    lidar_cam = rec.lidar_D.astype(np.float64) @ T_cam_radar[:3, :3].T + T_cam_radar[:3, 3]
    np.testing.assert_allclose(lidar_cam, truth["lidar"][1][:, :3] @ R_lidar.T + T_CAM_LIDAR_T, atol=1e-4)
    expected = cv2.undistort(_image(2), K, np.array([-0.23, 0.12, 0.0, 0.0, -0.05]))[:, :, ::-1]
    np.testing.assert_array_equal(rec.image, expected)


def test_camera_calibration_moves_matlabs_one_based_principal_point(tmp_path):
    """MATLAB's export puts the centre of a 720 x 540 image at (360.5, 270.5), OpenCV at (359.5,
    269.5): K comes back in OpenCV's convention, in either orientation of the matrix (before
    2026-12-06 it kept MATLAB's, one pixel off)."""
    from pipeline.readers.msc import read_camera_calibration

    for text in ("700 0 0\n0 700 0\n360.5 270.5 1", "700 0 360.5\n0 700 270.5\n0 0 1"):
        path = tmp_path / "CALIBRATION_CAMERA.txt"
        path.write_text(f"Left camera\nIntrinsic (K)\n{text}\nRadial Distortion\n-0.23 0.12\n")
        K, dist = read_camera_calibration(path)
        np.testing.assert_allclose(K, [[700, 0, 359.5], [0, 700, 269.5], [0, 0, 1]])
        np.testing.assert_allclose(dist, [-0.23, 0.12, 0, 0, 0])


def test_lidar_beams_without_a_return_are_left_out(tmp_path):
    """An organized Ouster scan keeps beams without a return as NaN or (0, 0, 0): they are left out
    and counted (before 2026-12-06 a NaN refused the whole frame, and zeros became a cluster of
    points at the lidar's mount)."""
    truth = make_folder(tmp_path)
    pts = truth["lidar"][1].copy()
    pts[::7, :3] = np.nan
    pts[3::7, :3] = 0.0
    PointCloud.from_points(pts, ("x", "y", "z", "intensity"), [np.float32] * 4).save(tmp_path / "2_LIDAR/PCD/000001.pcd")
    reader = get_reader(_cfg(), tmp_path)
    rec = reader.read("000002")
    kept = np.isfinite(pts[:, 0]) & np.any(pts[:, :3] != 0, axis=1)
    assert len(rec.lidar_D) == kept.sum() < len(pts) and np.all(np.isfinite(rec.lidar_D))
    lidar_cam = pts[kept, :3] @ R_CAM_D.T + T_CAM_LIDAR_T
    T_cam_radar = invert_transform(rec.T_radar_cam)
    np.testing.assert_allclose(rec.lidar_D @ T_cam_radar[:3, :3].T + T_cam_radar[:3, 3], lidar_cam, atol=1e-4)
    np.testing.assert_array_equal(rec.lidar_intensity, pts[kept, 3])
    assert reader.report()["lidar_points_without_return"] == len(pts) - kept.sum()


def test_a_radar_calibration_in_the_lidars_axes_is_read_as_such(tmp_path):
    """CALIBRATION_CAMERA_RADAR may give the attitude of the radar's native right-down-forward frame
    or of the forward-left-up one MSC-Rad4R's published points use (a devkit projects those points
    through it directly); the reader tells which from the attitude (the camera looks along the
    radar's forward axis). The same mounting written either way gives the same record, whichever
    order the points are in; an attitude whose camera view lies along neither forward axis is
    refused naming the file. Until 2026-12-07 every attitude was taken as right-down-forward."""
    from pipeline.readers.msc import R_NATIVE_D

    truth = make_folder(tmp_path)
    R_native = _rot([0.2, 1.0, 0.1], 0.15)
    calib = tmp_path / "5_CALIBRATION_URBAN" / "CALIBRATION_CAMERA_RADAR.txt"
    rows = lambda R: "\n".join(" ".join(f"{v:.12g}" for v in r) for r in R)  # noqa: E731
    translation = "translation of RADAR in camera coordinate\n" + " ".join(map(str, T_CAM_NATIVE_T)) + "\n"
    calib.write_text(f"attitude of RADAR in camera coordinate\n{rows(R_native)}\n{translation}")
    reader = get_reader(_cfg(), tmp_path)
    native = reader.read("000002")
    assert reader.report()["radar_calibration_in_lidar_axes"] == 0
    calib.write_text(f"attitude of RADAR in camera coordinate\n{rows(R_native @ R_NATIVE_D)}\n{translation}")
    native_rows = truth["radar"][2]
    flu = native_rows.copy()
    flu[:, :3] = np.stack([native_rows[:, 2], -native_rows[:, 0], -native_rows[:, 1]], 1)
    for points in ("native", "flu"):
        if points == "flu":
            PointCloud.from_points(flu, RADAR_FIELDS, [np.float32] * 10).save(tmp_path / "3_RADAR/PCD/000002.pcd")
        reader = get_reader(_cfg(), tmp_path)
        rec = reader.read("000002")
        assert reader.report()["radar_calibration_in_lidar_axes"] == 1
        np.testing.assert_allclose(rec.T_radar_cam, native.T_radar_cam, atol=1e-9)
        np.testing.assert_allclose(rec.radar_D, native.radar_D, atol=1e-5)
        np.testing.assert_allclose(rec.lidar_D, native.lidar_D, atol=1e-4)
    sideways = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # the camera looking along the radar's y
    calib.write_text(f"attitude of RADAR in camera coordinate\n{rows(sideways)}\n{translation}")
    with pytest.raises(ReaderError, match="CALIBRATION_CAMERA_RADAR.txt.*neither right-down-forward"):
        get_reader(_cfg(), tmp_path).read("000002")


def test_the_calibration_folder_of_any_set_is_found_and_a_missing_or_second_one_named(tmp_path):
    """Each set of sequences (URBAN, RURAL, ...) has its own 5_CALIBRATION_<SET>/; until
    2026-12-07 the reader looked for 5_CALIBRATION_URBAN/ alone and refused every other sequence."""
    make_folder(tmp_path)
    urban = get_reader(_cfg(), tmp_path).read("000002")
    (tmp_path / "5_CALIBRATION_URBAN").rename(tmp_path / "5_CALIBRATION_RURAL")
    rural = get_reader(_cfg(), tmp_path).read("000002")
    np.testing.assert_array_equal(rural.T_radar_cam, urban.T_radar_cam)
    (tmp_path / "5_CALIBRATION_SMOKE").mkdir()
    with pytest.raises(ReaderError, match="2 calibration folders .5_CALIBRATION_RURAL, 5_CALIBRATION_SMOKE."):
        get_reader(_cfg(), tmp_path).read("000002")
    for folder in ("5_CALIBRATION_RURAL", "5_CALIBRATION_SMOKE"):
        shutil.rmtree(tmp_path / folder)
    with pytest.raises(ReaderError, match="no calibration folder: an MSC-Rad4R sequence holds one 5_CALIBRATION_<SET>/"):
        get_reader(_cfg(), tmp_path).read("000002")


STREET_SPEED_MPS = 1.4
"""MSC-Rad4R's platform drove at 5 km/h = 1.39 m/s."""


def _street_native(seed: int = 7, n: int = 60, movers: int = 6) -> np.ndarray:
    """(n, 10) radar rows (RADAR_FIELDS, native right-down-forward frame) of a street scene seen from
    a radar moving ahead at STREET_SPEED_MPS: points at azimuths within +-50 deg, static but for the
    first ``movers``; ``doppler`` the range rate (-speed * forward / distance for a static point),
    ``power`` an RSS of 2..50 dB."""
    rng = np.random.default_rng(seed)
    azimuth, elevation = rng.uniform(-0.87, 0.87, n), rng.uniform(-0.1, 0.1, n)
    range_m = rng.uniform(3.0, 40.0, n)
    forward = range_m * np.cos(elevation) * np.cos(azimuth)
    left, up = range_m * np.cos(elevation) * np.sin(azimuth), range_m * np.sin(elevation)
    rows = np.zeros((n, 10), np.float32)
    rows[:, :3] = np.stack([-left, -up, forward], 1)
    rows[:, 6] = -STREET_SPEED_MPS * forward / range_m
    rows[:movers, 6] += rng.choice([-1.0, 1.0], movers) * rng.uniform(3.0, 8.0, movers)
    rows[:, 5] = rng.uniform(2.0, 50.0, n)
    rows[:, 7] = range_m
    return rows


def _save_radar(root: Path, frame: int, rows: np.ndarray) -> None:
    PointCloud.from_points(rows, RADAR_FIELDS, [np.float32] * 10).save(root / "3_RADAR/PCD" / f"{frame:06d}.pcd")


def _set_wheels(root: Path, speed_mps: float) -> None:
    for side in ("LEFT", "RIGHT"):
        (root / "4_NAVIGATION" / f"WHEEL_{side}.txt").write_text(
            "".join(f"{k} {100 + k // 10} {(k % 10) * 100_000_000} {speed_mps} 0.0\n" for k in range(5)))


def _swapped(rows: np.ndarray) -> np.ndarray:
    """``rows`` with the power and doppler columns swapped (as a third-party loader says the bags hold them)."""
    out = rows.copy()
    out[:, [5, 6]] = rows[:, [6, 5]]
    return out


def test_the_doppler_as_read_is_checked_against_the_ego_motion(tmp_path):
    """A moving platform sees most points of a street scene at a static world's range rate
    (-speed * x / |p| in {D}): a frame whose Doppler agrees is read and counted as checked; until
    2026-12-07 nothing compared them."""
    make_folder(tmp_path)
    _set_wheels(tmp_path, STREET_SPEED_MPS)
    street = _street_native()
    _save_radar(tmp_path, 2, street)
    reader = get_reader(_cfg(), tmp_path)
    rec = reader.read("000002")
    np.testing.assert_allclose(rec.radar_D[:, 3], street[:, 6])
    np.testing.assert_allclose(rec.radar_D[:, 4], street[:, 5])
    np.testing.assert_allclose(rec.ego_velocity_D, [STREET_SPEED_MPS, 0, 0])
    assert reader.report()["doppler_checked"] == 1
    assert "doppler_disagrees_with_every_reading" not in reader.report()


def test_a_doppler_of_the_other_sign_is_refused_naming_radar_doppler_sign(tmp_path):
    """The sign of MSC-Rad4R's ``doppler`` is not documented (taken as range rate): with the sign
    flipped in the data, a moving frame is refused naming the file, the frame and the setting that
    fixes it, which then reads it; a stopped ego (or one below 1 m/s) tells nothing and is not
    checked. Until 2026-12-07 such frames were read with every Doppler of the wrong sign."""
    make_folder(tmp_path)
    flipped = _street_native()
    flipped[:, 6] *= -1
    _save_radar(tmp_path, 2, flipped)
    for stopped in (0.0, 0.5):
        _set_wheels(tmp_path, stopped)
        reader = get_reader(_cfg(), tmp_path)
        reader.read("000002")
        assert "doppler_checked" not in reader.report()
    _set_wheels(tmp_path, STREET_SPEED_MPS)
    # 54 of the 60 points are static
    with pytest.raises(ReaderError, match=r"frame 000002: .*/3_RADAR/PCD/000002.pcd: radar Doppler disagrees with the "
                                          r"ego motion \(1.40 m/s ahead\).*90% with the opposite sign.*"
                                          r"--set radar.doppler_sign=-1$"):
        get_reader(_cfg(), tmp_path).read("000002")
    reader = get_reader(_cfg().with_overrides({"radar.doppler_sign": "-1"}), tmp_path)
    np.testing.assert_allclose(reader.read("000002").radar_D[:, 3], -flipped[:, 6])
    assert reader.report()["doppler_checked"] == 1


def test_swapped_power_and_doppler_fields_are_refused_and_read_with_dataset_msc_doppler_field(tmp_path):
    """A third-party loader of MSC-Rad4R's bags (read, not run) says their ``power`` and ``doppler``
    fields are swapped: such a frame is refused naming dataset.msc_doppler_field, and read with it
    set, the Doppler from ``power`` and the RSS from ``doppler``; in both layouts. Until 2026-12-07
    the RSS was read as the Doppler without a word."""
    street = _street_native()
    make_folder(tmp_path / "folder")
    _set_wheels(tmp_path / "folder", STREET_SPEED_MPS)
    _save_radar(tmp_path / "folder", 2, _swapped(street))
    (tmp_path / "bag").mkdir()
    _write_bag(tmp_path / "bag" / "URBAN_D0.bag", radar_rows=_swapped(street), vel_xy=(STREET_SPEED_MPS, 0.0))
    _write_calibration(tmp_path / "bag" / "5_CALIBRATION_URBAN")
    swapped_cfg = _cfg().with_overrides({"dataset.msc_doppler_field": "power"})
    for root, fid, name in ((tmp_path / "folder", "000002", "000002.pcd"),
                            (tmp_path / "bag", "URBAN_D0_000001", "URBAN_D0.bag")):
        with pytest.raises(ReaderError, match=f"frame {fid}: .*/{name}: radar Doppler disagrees with the ego motion.*"
                                              r"90% and \d+% from field 'power'.*--set dataset.msc_doppler_field=power$"):
            get_reader(_cfg(), root).read(fid)
        reader = get_reader(swapped_cfg, root)
        rec = reader.read(fid)
        np.testing.assert_allclose(rec.radar_D[:, 3], street[:, 6])
        np.testing.assert_allclose(rec.radar_D[:, 4], street[:, 5])
        assert reader.report()["doppler_checked"] == 1


def test_a_bag_frame_whose_doppler_agrees_is_checked_and_one_of_either_sign_and_field_named(tmp_path):
    """The bag layout checks as the folder one does (speed from /vel): agreeing -> read and
    counted; the swapped fields with the sign flipped as well -> both settings named."""
    street = _street_native()
    _write_calibration(tmp_path / "5_CALIBRATION_URBAN")
    _write_bag(tmp_path / "URBAN_D0.bag", radar_rows=street, vel_xy=(STREET_SPEED_MPS, 0.0))
    reader = get_reader(_cfg(), tmp_path)
    np.testing.assert_allclose(reader.read("URBAN_D0_000000").radar_D[:, 3], street[:, 6])
    assert reader.report()["doppler_checked"] == 1
    both = _swapped(street)
    both[:, 5] *= -1
    (tmp_path / "URBAN_D0.bag").unlink()
    _write_bag(tmp_path / "URBAN_D0.bag", radar_rows=both, vel_xy=(STREET_SPEED_MPS, 0.0))
    with pytest.raises(ReaderError, match=r"--set dataset.msc_doppler_field=power --set radar.doppler_sign=-1$"):
        get_reader(_cfg(), tmp_path).read("URBAN_D0_000000")


def test_dataset_msc_doppler_field_takes_doppler_or_power():
    from pipeline.errors import ConfigError

    assert _cfg().dataset.msc_doppler_field == "doppler"
    with pytest.raises(ConfigError, match="'dataset.msc_doppler_field' must be one of doppler, power, got 'range'"):
        _cfg().with_overrides({"dataset.msc_doppler_field": "range"})


def _flu(native: np.ndarray) -> np.ndarray:
    """Radar rows of the native right-down-forward frame with x, y, z in forward-left-up order."""
    out = native.copy()
    out[:, :3] = np.stack([native[:, 2], -native[:, 0], -native[:, 1]], 1)
    return out


def _counted_folder(root: Path) -> int:
    """Three frames: 000000 with the ego stopped (its Doppler not checked) and its radar points in the
    native right-down-forward axes; 000001 and 000002 at STREET_SPEED_MPS with the points in the
    forward-left-up axes, 000001's Doppler a static world's range rate (agrees), 000002's zero on
    every point (an ego-motion-compensated Doppler: no reading agrees), 000001's lidar with beams
    without a return. Returns how many."""
    make_folder(root, lidar_times=(100.01, 100.07, 100.13))
    for side in ("LEFT", "RIGHT"):
        (root / "4_NAVIGATION" / f"WHEEL_{side}.txt").write_text(
            f"0 100 0 0.0 0.0\n1 100 30000000 {STREET_SPEED_MPS} 0.0\n2 100 500000000 {STREET_SPEED_MPS} 0.0\n")
    _save_radar(root, 1, _flu(_street_native()))
    compensated = _flu(_street_native(seed=8))
    compensated[:, 6] = 0.0
    _save_radar(root, 2, compensated)
    pts = _lidar(np.random.default_rng(3))
    pts[::7, :3] = np.nan
    pts[3::7, :3] = 0.0
    PointCloud.from_points(pts, ("x", "y", "z", "intensity"), [np.float32] * 4).save(root / "2_LIDAR/PCD/000001.pcd")
    return int((~np.isfinite(pts[:, 0]) | np.all(pts[:, :3] == 0, axis=1)).sum())


def test_calibrate_says_the_readers_counts_summed_over_its_frames_serial_and_on_dask(tmp_path):
    """The axis order, the Doppler check and the lidar beams without a return are how a first run on
    real MSC-Rad4R data tells that the reader's unverified assumptions held: each frame's own counts
    are stored with its calibrate outputs (reader_counts) and calibrate's summary says their sums,
    the same through the serial and the dask executor. Until 2026-12-07 they stayed in the reader
    instances of the worker processes, never said."""
    import zarr

    from pipeline.executor import Executor, RunEnv
    from pipeline.runner import Pipeline
    from stages import calibrate

    from pipeline.readers.msc import R_NATIVE_D

    without_return = _counted_folder(tmp_path / "data")
    # the same mounting as the fixture's, its attitude given for the forward-left-up frame and its
    # translation in millimetres (both read as such, and counted per frame)
    (tmp_path / "data" / "5_CALIBRATION_URBAN" / "CALIBRATION_CAMERA_RADAR.txt").write_text(
        "attitude of RADAR in camera coordinate\n" + "\n".join(" ".join(f"{v:g}" for v in r) for r in R_NATIVE_D)
        + "\ntranslation of RADAR in camera coordinate\n" + " ".join(str(1000 * v) for v in T_CAM_NATIVE_T) + "\n")
    cfg = _cfg().with_overrides({"camera.crop_rows": "0,48", "camera.working_size": "64,48"})
    keys = ("radar_axes_flu", "radar_axes_rdf", "doppler_checked", "doppler_disagrees_with_every_reading",
            "lidar_points_without_return", "radar_calibration_in_lidar_axes", "calibration_in_millimetres")
    notes, counts = {}, {}
    for workers in (1, 2):
        cache = tmp_path / f"cache{workers}"
        env = RunEnv(cfg=cfg, cache_root=str(cache), dataset="msc", data_root=str(tmp_path / "data"))
        with Executor(workers, progress=False) as ex:
            report = Pipeline([calibrate.STAGE], env, ex, progress=False, log=lambda m: None).run("calibrate")[0]
        assert report.done == 3 and not report.failures, report.failures
        notes[workers] = report.notes
        group = zarr.open_group(str(cache / "msc" / "calibrate.zarr"), mode="r")
        counts[workers] = np.asarray(group["reader_counts"][:])
        assert keys == tuple(get_reader(cfg, tmp_path / "data").frame_counts) and ", ".join(keys) in \
            group["reader_counts"].attrs["units"]
    np.testing.assert_array_equal(counts[1], [[0, 1, 0, 0, 0, 1, 1], [1, 0, 1, 0, without_return, 1, 1],
                                              [1, 0, 1, 1, 0, 1, 1]])
    np.testing.assert_array_equal(counts[1], counts[2])
    assert notes[1] == notes[2] == [
        f"MSC-Rad4R radar points in forward-left-up axes on 2 of 3 frames, right-down-forward on 1; lidar beams "
        f"without a return left out: {without_return}",
        "MSC-Rad4R radar calibration (CALIBRATION_CAMERA_RADAR) in forward-left-up axes on 3 of 3 frames, "
        "right-down-forward on 0; extrinsics read as millimetres on 3",
        "MSC-Rad4R Doppler checked against the ego motion on 2 of 3 frames: agreed on all but 1, where no reading "
        "of the fields agreed (read as configured)"], notes[1]


def test_only_the_msc_reader_adds_an_output_to_calibrate():
    """reader_counts is declared for the reader that gives per-frame counts only: the other
    datasets' calibrate outputs, and so their caches, stay as they were."""
    from stages import calibrate

    for profile in ("astyx", "vod", "kitti", "synthetic", "msc"):
        names = [spec.name for spec in calibrate.outputs(load_config(profile, {}, environ={}))]
        assert ("reader_counts" in names) == (profile == "msc"), profile
        assert names[:-1 if profile == "msc" else None][-1] == "radar_beyond_range", profile


def test_the_counts_summary_says_when_no_frame_s_doppler_was_checked():
    totals = dict.fromkeys(MscFolderReader.frame_counts, 0) | {"radar_axes_flu": 1180,
                                                               "lidar_points_without_return": 3_400_000}
    lines = MscFolderReader.counts_summary(totals, 1180)
    assert lines == ["MSC-Rad4R radar points in forward-left-up axes on 1,180 of 1,180 frames, right-down-forward "
                     "on 0; lidar beams without a return left out: 3,400,000",
                     "MSC-Rad4R radar calibration (CALIBRATION_CAMERA_RADAR) in forward-left-up axes on 0 of 1,180 "
                     "frames, right-down-forward on 1,180; extrinsics read as millimetres on 0",
                     "MSC-Rad4R Doppler checked against the ego motion on none of 1,180 frames (checked from 1 m/s "
                     "ahead and 20 points): its field and sign are as configured, unchecked"]
