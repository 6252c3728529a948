"""Tests of pipeline.export: VoD .bin round trip and its v_r_compensated definition, noise points,
PCD round trip, preview images and the KITTI/VoD folder layout."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.errors import ReaderError
from pipeline.export import (
    DONT_CARE_LINE, add_uniform_noise, detector_label_text, kitti_calib_text, label_classes, parse_class_map, preview_png,
    read_pcd, read_vod_bin, rename_classes, vod_points, write_image, write_image_sets, write_kitti_layout, write_pcd,
    write_vod_bin,
)
from pipeline.geometry import cartesian_to_spherical, invert_transform, project_to_image
from pipeline.synthesis import doppler_for_points


def random_points(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    points = rng.uniform([1, -20, -2], [50, 20, 5], (n, 3))
    return points, rng.uniform(-70, 40, n), rng.uniform(-10, 10, n)


def test_vod_bin_round_trip(tmp_path: Path):
    points, rss, v_r = random_points(50)
    ego = np.array([4.0, 0.5, -0.1])
    path = write_vod_bin(tmp_path / "radar" / "00001.bin", points, rss, v_r, ego)
    assert path.stat().st_size == 50 * 28
    rows = read_vod_bin(path)
    assert rows.shape == (50, 7) and rows.dtype == np.float32
    np.testing.assert_array_equal(rows[:, :3], points.astype(np.float32))
    np.testing.assert_array_equal(rows[:, 3], rss.astype(np.float32))
    np.testing.assert_array_equal(rows[:, 4], v_r.astype(np.float32))
    np.testing.assert_array_equal(rows[:, 6], 0.0)
    # VoD: v_r - v_r_compensated = -(u . v_ego)
    unit = points / np.linalg.norm(points, axis=1, keepdims=True)
    np.testing.assert_allclose(rows[:, 4] - rows[:, 5], -(unit @ ego), atol=1e-5)
    assert [p.name for p in path.parent.iterdir()] == ["00001.bin"]  # no temporary files left


def test_static_world_compensates_to_zero():
    points, rss, _ = random_points(20, seed=1)
    ego = np.array([7.0, -0.3, 0.05])
    v_r = doppler_for_points(points, ego, None, +1, 0.0)  # range rate of static targets
    rows = vod_points(points, rss, v_r, ego)
    np.testing.assert_allclose(rows[:, 5], 0.0, atol=1e-5)


def test_vod_bin_empty_and_bad_files(tmp_path: Path):
    path = write_vod_bin(tmp_path / "e.bin", np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(3))
    assert read_vod_bin(path).shape == (0, 7)
    bad = tmp_path / "bad.bin"
    bad.write_bytes(b"\0" * 30)
    with pytest.raises(ReaderError, match="multiple of 28"):
        read_vod_bin(bad)
    with pytest.raises(ReaderError):
        read_vod_bin(tmp_path / "missing.bin")
    with pytest.raises(ValueError):
        write_vod_bin(tmp_path / "x.bin", np.zeros((3, 3)), np.zeros(2), np.zeros(3), np.zeros(3))


def test_v_r_compensated_of_an_aliasing_radar_is_wrapped_into_its_span():
    """Astyx's radar wraps v_r into 10.39 m/s: a static point's compensated velocity is 0, not a
    multiple of the span (56% of the Astyx export's points had +10.4 m/s before); a moving one keeps
    its own while it lies within the span; noise points too."""
    from pipeline.geometry import wrap_doppler

    span, ego = 10.3936, np.array([12.0, 0.5, 0.0])
    rng = np.random.default_rng(3)
    points = rng.uniform([5, -20, -1], [60, 20, 2], (300, 3))
    unit = points / np.linalg.norm(points, axis=1, keepdims=True)
    own = np.where(np.arange(300) < 200, 0.0, rng.uniform(-4.5, 4.5, 300))   # static, then movers
    v_r = wrap_doppler(own - unit @ ego, span)                                 # what the radar reports
    rows = vod_points(points, np.zeros(300), v_r, ego, span)
    np.testing.assert_allclose(rows[:, 5], own, atol=1e-4)
    assert np.abs(vod_points(points, np.zeros(300), v_r, ego)[:200, 5]).max() > 5   # unwrapped: off by the span
    noisy = add_uniform_noise(rows, 0.5, rng, fov_az_deg=110, fov_el_deg=39, max_range_m=100, rss_range=(45, 95),
                              doppler_range_mps=(-span / 2, span / 2), ego_velocity_D=ego, doppler_span_mps=span)
    assert np.all(np.abs(noisy[:, 4:6]) <= span / 2 + 1e-4)


def test_uniform_noise_count_and_bounds():
    points, rss, v_r = random_points(200)
    ego = np.array([3.0, 0.0, 0.0])
    rows = vod_points(points, rss, v_r, ego)
    out = add_uniform_noise(rows, 0.05, np.random.default_rng(0), fov_az_deg=64.0, fov_el_deg=40.0,
                            max_range_m=50.0, rss_range=(-74.0, 39.8), doppler_range_mps=(-20.0, 20.0),
                            ego_velocity_D=ego)
    assert out.shape == (210, 7) and out.dtype == np.float32
    np.testing.assert_array_equal(out[:200], rows)
    noise = out[200:].astype(np.float64)
    rae = cartesian_to_spherical(noise[:, :3])
    assert np.all((rae[:, 0] >= 0.5 - 1e-4) & (rae[:, 0] <= 50.0 + 1e-4))
    assert np.all(np.abs(np.rad2deg(rae[:, 1])) <= 32.0 + 1e-3)
    assert np.all(np.abs(np.rad2deg(rae[:, 2])) <= 20.0 + 1e-3)
    assert np.all((noise[:, 3] >= -74.0) & (noise[:, 3] <= 39.8))
    assert np.all((noise[:, 4] >= -20.0) & (noise[:, 4] <= 20.0))
    unit = noise[:, :3] / rae[:, :1]
    np.testing.assert_allclose(noise[:, 4] - noise[:, 5], -(unit @ ego), atol=1e-4)
    assert add_uniform_noise(rows, 0.0, np.random.default_rng(0), fov_az_deg=64, fov_el_deg=40,
                             max_range_m=50, rss_range=(0, 1), doppler_range_mps=(0, 1)).shape == (200, 7)
    with pytest.raises(ValueError):
        add_uniform_noise(rows, -0.1, np.random.default_rng(0), fov_az_deg=64, fov_el_deg=40,
                          max_range_m=50, rss_range=(0, 1), doppler_range_mps=(0, 1))


def test_pcd_round_trip(tmp_path: Path):
    points, rss, doppler = random_points(30)
    path = write_pcd(tmp_path / "pcd" / "00001.pcd", points, rss, doppler)
    back = read_pcd(path)
    assert back.shape == (30, 5)
    np.testing.assert_array_equal(back, np.column_stack([points, rss, doppler]).astype(np.float32))
    empty = write_pcd(tmp_path / "empty.pcd", np.zeros((0, 3)), np.zeros(0), np.zeros(0))
    assert read_pcd(empty).shape == (0, 5)


def test_preview_png(tmp_path: Path):
    h, w = 120, 200
    image = np.zeros((h, w, 3), np.uint8)
    image[..., 0] = 200  # red in RGB
    uv = np.array([[150.0, 90.0], [60.0, 100.0]])
    path = preview_png(tmp_path / "prev" / "00001.png", image, uv, np.array([10.0, 45.0]), 50.0)
    out = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert out.shape == (h, w, 3)
    np.testing.assert_array_equal(out[110, 10], [0, 0, 200])  # untouched pixel, BGR order
    expected = cv2.applyColorMap(np.array([[int(10 / 50 * 255)]], np.uint8), cv2.COLORMAP_TURBO)[0, 0]
    np.testing.assert_array_equal(out[90, 150], expected)  # point centre coloured by its range
    assert not np.array_equal(out[100, 60], out[90, 150])  # farther point, other colour
    # no point in view (until 2026-12-04 cv2's None for no points crashed the export): the image and the bar
    empty = cv2.imread(str(preview_png(tmp_path / "prev" / "00002.png", image, np.zeros((0, 2)), np.zeros(0), 50.0)))
    yy, xx = np.mgrid[0:h, 0:w]
    away = np.min([(xx - u) ** 2 + (yy - v) ** 2 for u, v in uv], axis=0) > 8 ** 2
    np.testing.assert_array_equal(empty[away], out[away])
    np.testing.assert_array_equal(empty[90, 150], [0, 0, 200])


def test_kitti_layout_and_image_sets(tmp_path: Path):
    root = tmp_path / "radar"
    calib_src = tmp_path / "src_calib.txt"
    calib_src.write_text("P2: 1 0 0 0 0 1 0 0 0 0 1 0\nTr_imu_to_velo:\n")
    image_src = tmp_path / "img.jpg"
    image_src.write_bytes(b"jpegbytes")
    points, rss, v_r = random_points(5)
    rows = vod_points(points, rss, v_r, np.zeros(3))
    label = "Car 0 0 0 0 0 10 10 1.5 1.8 4.0 1 1.6 10 0\n"
    written = write_kitti_layout(root, "00042", rows, calib=calib_src, label=label, image=image_src)
    assert written["velodyne"] == root / "training" / "velodyne" / "00042.bin"
    np.testing.assert_array_equal(read_vod_bin(written["velodyne"]), rows)
    assert (root / "training" / "calib" / "00042.txt").read_text() == calib_src.read_text()
    assert (root / "training" / "label_2" / "00042.txt").read_text() == label
    assert (root / "training" / "image_2" / "00042.jpg").read_bytes() == b"jpegbytes"
    sets = write_image_sets(root, {"train": ["00001", "00002"], "val": [], "test": ["00042"]})
    assert (root / "ImageSets" / "train.txt").read_text() == "00001\n00002\n"
    assert sets["val"].read_text() == ""
    assert (root / "ImageSets" / "test.txt").read_text() == "00042\n"
    with pytest.raises(ValueError):
        write_kitti_layout(root, "../evil", rows)
    with pytest.raises(ReaderError):
        write_kitti_layout(root, "00043", rows, calib=tmp_path / "missing.txt")


def test_kitti_calib_text_parses_back():
    P2 = np.array([[500.0, 0, 320, 1.5], [0, 500, 240, 0], [0, 0, 1, 0]])
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]
    T[:3, 3] = [0.1, -0.2, 0.3]
    parsed = {}
    for line in kitti_calib_text(P2, T).splitlines():
        key, _, values = line.partition(":")
        parsed[key] = np.array(values.split(), dtype=np.float64)
    assert set(parsed) == {"P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo"}
    np.testing.assert_allclose(parsed["P2"].reshape(3, 4), P2)
    np.testing.assert_allclose(parsed["Tr_velo_to_cam"].reshape(3, 4), T[:3])
    np.testing.assert_allclose(parsed["R0_rect"].reshape(3, 3), np.eye(3))


def test_detector_labels_keep_truncation_and_drop_track_ids():
    vod = "Car 0 0 -1.7 1232.0 764.3 1357.1 941.7 1.2 0.7 2.0 2.8 2.5 12.8 -1.4 1\n"
    tracked = "Pedestrian 10035 0 -1.98 526.56 195.84 547.44 235.96 1.55 0.6 0.5 8.61 1.5 19.44 -1.57 1\n"
    half = "Cyclist 0.5 1 0.1 1 2 3 4 1.5 0.6 1.7 1.0 1.5 10.0 0.2\n"
    out = detector_label_text(vod + tracked + half + "short line\n")
    assert out.splitlines()[0] == vod.strip() and out.splitlines()[2] == half.strip()
    assert out.splitlines()[1].split()[:3] == ["Pedestrian", "0", "0"]
    assert out.splitlines()[1].split()[3:] == tracked.split()[3:]
    assert out.splitlines()[3] == "short line" and out.endswith("\n")
    # the reader knows the column holds track ids: 0 everywhere (a track id of 1 is no truncation)
    track_one = "Car 1 0 -1.7 1232.0 764.3 1357.1 941.7 1.2 0.7 2.0 2.8 2.5 12.8 -1.4\n"
    assert detector_label_text(track_one).split()[1] == "1"
    assert detector_label_text(track_one, track_ids=True).split()[1] == "0"
    # one space between fields (OpenPCDet splits on ' '), no blank lines, never an empty file
    assert detector_label_text("Car  0 0 -1.7 1 2 3 4 1.2 0.7 2.0 2.8 2.5 12.8 -1.4\n\n") == \
        "Car 0 0 -1.7 1 2 3 4 1.2 0.7 2.0 2.8 2.5 12.8 -1.4\n"
    assert detector_label_text("") == detector_label_text("\n \n") == DONT_CARE_LINE + "\n"
    assert len(DONT_CARE_LINE.split(" ")) == 15


def test_exported_files_are_readable_by_others(tmp_path: Path):
    """Atomic writes go through mkstemp (mode 0600); the files must get the mode open() gives."""
    mask = os.umask(0o022)
    os.umask(mask)
    image = np.zeros((4, 6, 3), np.uint8)
    image[1, 2] = (255, 0, 0)
    path = write_image(tmp_path / "image_2" / "00001.png", image)
    assert path.stat().st_mode & 0o777 == 0o666 & ~mask
    np.testing.assert_array_equal(cv2.imread(str(path))[:, :, ::-1], image)   # RGB in, RGB back
    smooth = np.full((16, 16, 3), (200, 40, 90), np.uint8)
    jpg = write_image(tmp_path / "image_2" / "00002.jpg", smooth)
    assert jpg.read_bytes()[:3] == b"\xff\xd8\xff"                          # a JPEG, by its suffix
    assert np.abs(cv2.imread(str(jpg))[:, :, ::-1].astype(int) - smooth).max() <= 3
    with pytest.raises(ValueError, match="png or .jpg"):
        write_image(tmp_path / "x.bmp", smooth)


def test_kitti_label_text_round_trips_through_openpcdets_reading(tmp_path: Path):
    """Boxes in {D} written as KITTI labels for a generated calib come back, read the way OpenPCDet
    reads them (bottom centre raised along the point cloud's z, yaw = -(rotation_y + pi/2)), to
    the same centres, sizes and yaws; their 2D boxes enclose the projected centres; a box behind the
    camera is left out; a frame without boxes gets DontCare."""
    from pipeline.export import kitti_label_text
    from pipeline.frame import Object3D
    from pipeline.readers.kitti_format import lidar_box_label_to_object, parse_label_file
    from pipeline.readers.testing import R_CAM_D, rigid

    K = np.array([[600.0, 0, 320], [0, 600.0, 200], [0, 0, 1]])
    T_cam_radar = rigid(R_CAM_D, np.array([0.05, 0.8, -0.4])) @ rigid(
        np.array([[1, 0, 0], [0, np.cos(0.05), -np.sin(0.05)], [0, np.sin(0.05), np.cos(0.05)]]), np.zeros(3))
    objects = [Object3D("Car", np.array([15.0, 2.0, 0.3]), np.array([4.2, 1.8, 1.5]), 0.4),
               Object3D("Towed Object", np.array([30.0, -4.0, 0.5]), np.array([3.0, 2.0, 2.5]), -2.9),
               Object3D("Person", np.array([6.0, 3.5, 0.4]), np.array([0.6, 0.6, 1.8]), 3.0),   # half out of view
               Object3D("Car", np.array([-8.0, 0.0, 0.3]), np.array([4.0, 1.8, 1.5]), 0.0)]     # behind
    path = tmp_path / "label.txt"
    path.write_text(kitti_label_text(objects, T_cam_radar, K, (640, 400)))
    labels = parse_label_file(path, "x")
    assert [lab.class_name for lab in labels] == ["Car", "Towed_Object", "Person"]
    lines = [line.split() for line in path.read_text().splitlines()]
    for obj, lab, fields in zip(objects, labels, lines):
        back = lidar_box_label_to_object(lab, invert_transform(T_cam_radar), np.eye(4), -1)
        np.testing.assert_allclose(back.center_D, obj.center_D, atol=1e-4)
        np.testing.assert_allclose(back.size_lwh_m, obj.size_lwh_m, atol=1e-5)
        assert abs(np.angle(np.exp(1j * (back.yaw_rad - obj.yaw_rad)))) < 1e-5
        u0, v0, u1, v1 = map(float, fields[4:8])
        uv, _, _ = project_to_image(obj.center_D[None], K, T_cam_radar, (640, 400))
        assert 0 <= u0 < u1 <= 639 and 0 <= v0 < v1 <= 399 and (u0 <= uv[0, 0] <= u1 or obj.class_name == "Person")
    assert float(lines[0][1]) == 0.0 and 0.05 < float(lines[2][1]) < 0.95    # truncation: in view, partly out
    assert kitti_label_text([objects[3]], T_cam_radar, K, (640, 400)) == DONT_CARE_LINE + "\n"


def test_track_id_labels_get_the_truncation_of_their_box():
    """With the camera's P2 and image size, a track id's column gets the box's truncation, the value
    kitti_label_text writes for the same box from {D} (the synthetic world's and View-of-Delft's
    tracking labels had 0 everywhere until 2026-12-04, so OpenPCDet rated boxes cut by the image
    edge 'Easy'); a box reaching behind the camera gets 1; without P2 the column becomes 0."""
    from pipeline.export import calib_P2, kitti_label_text, label_truncation
    from pipeline.frame import Object3D
    from pipeline.readers.testing import R_CAM_D, rigid

    K = np.array([[600.0, 0, 320], [0, 600.0, 200], [0, 0, 1]])
    T_cam_radar = rigid(R_CAM_D, np.array([0.05, 0.8, -0.4]))
    objects = [Object3D("Car", np.array([15.0, 2.0, 0.3]), np.array([4.2, 1.8, 1.5]), 0.4),      # in view
               Object3D("Car", np.array([20.0, 10.0, 0.3]), np.array([4.2, 1.8, 1.5]), 0.4),    # a third out
               Object3D("Car", np.array([10.0, 6.0, 0.3]), np.array([4.2, 1.8, 1.5]), 0.4)]     # mostly out
    truth = [line.split() for line in kitti_label_text(objects, T_cam_radar, K, (640, 400)).splitlines()]
    assert len(truth) == 3 and float(truth[0][1]) == 0.0 and 0.05 < float(truth[1][1]) < float(truth[2][1]) < 1
    P2 = calib_P2(kitti_calib_text(np.column_stack([K, np.zeros(3)]), T_cam_radar))
    tracked = "".join(" ".join([f[0], str(7 + i), *f[2:]]) + "\n" for i, f in enumerate(truth))
    out = [line.split() for line in detector_label_text(tracked, True, P2, (640, 400)).splitlines()]
    for got, want in zip(out, truth, strict=True):
        assert float(got[1]) == pytest.approx(float(want[1]), abs=0.005) and got[2:] == want[2:]
    behind = "Car 3 0 0 0 0 10 10 1.5 1.8 4.0 0.0 1.5 1.0 0.0\n"    # 4 m long, centred 1 m ahead
    assert detector_label_text(behind, True, P2, (640, 400)).split()[1] == "1.00"
    assert label_truncation(behind.split(), P2, (640, 400)) == 1.0
    assert detector_label_text(behind, True).split()[1] == "0"
    assert detector_label_text(behind.replace("4.0", "x"), True, P2, (640, 400)).split()[1] == "0"
    with pytest.raises(ValueError, match="P2"):
        calib_P2("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")


def test_class_names_rename_label_classes():
    assert parse_class_map("") == {} and parse_class_map(" Person = Pedestrian , Other_Vehicle=Car,") == {
        "Person": "Pedestrian", "Other_Vehicle": "Car"}
    for bad, words in (("Person", "not From=To"), ("Person=", "not From=To"), ("a=b=c", "not From=To"),
                       ("Towed Object=Car", "not From=To"), ("Car=Truck,Car=Van", "'Car' is renamed twice")):
        with pytest.raises(ValueError, match=words):
            parse_class_map(bad)
    text = ("Person 0.00 0 -1.9 526.5 195.8 547.4 235.9 1.5 0.6 0.5 8.6 1.5 19.4 -1.5\n"
            "Car 0.50 1 0.3 100 100 200 200 1.5 1.8 4.0 2.0 1.6 10.0 0.1\n" + DONT_CARE_LINE + "\n")
    out = rename_classes(text, {"Person": "Pedestrian"})
    lines = out.splitlines()
    assert lines[0] == "Pedestrian " + text.splitlines()[0].split(" ", 1)[1]   # the other fields untouched
    assert lines[1:] == text.splitlines()[1:] and out.endswith("\n")
    assert rename_classes(text, {}) == text
    assert label_classes(out) == {"Pedestrian": 1, "Car": 1}                      # DontCare is no box
    assert label_classes(DONT_CARE_LINE + "\n") == {}


def test_points_on_objects_of_unknown_velocity_are_counted():
    """Until 2026-12-05 nothing said that points on a labelled object without a recorded velocity
    (the View-of-Delft example frames, Astyx) got a static object's Doppler: a moving cyclist's
    points were exported as parked."""
    from pipeline.frame import Object3D, label_rows
    from pipeline.synthesis import on_objects_of_unknown_velocity

    unknown = Object3D("Car", np.array([10.0, 0.0, 0.0]), np.array([4.0, 2.0, 1.5]), 0.0)  # velocity NaN
    known = Object3D("Car", np.array([20.0, 5.0, 0.0]), np.array([4.0, 2.0, 1.5]), 0.0,
                     velocity_D=np.array([3.0, 0.0, 0.0]))
    points = np.array([[10.0, 0.0, 0.0], [11.9, 0.9, 0.5], [12.2, 0.0, 0.0],   # in the unknown box (margin 0.3)
                       [20.0, 5.0, 0.0],                                         # in the moving box
                       [30.0, -5.0, 0.0], [12.5, 0.0, 0.0]])                     # in none
    rows = label_rows([unknown, known]).astype(np.float32)
    assert on_objects_of_unknown_velocity(points, rows).tolist() == [True, True, True, False, False, False]
    assert not on_objects_of_unknown_velocity(points, label_rows([known]).astype(np.float32)).any()
    assert on_objects_of_unknown_velocity(np.zeros((0, 3)), rows).shape == (0,)


def test_uniform_noise_fills_the_field_of_view_and_range_shell():
    """Noise is uniform over the TOTAL fields of view and [min_range_m, max_range_m]: with many
    points both angles reach near their limits and no range falls below min_range_m; the count is
    round(fraction * n), not truncated."""
    points, rss, v_r = random_points(200)
    rows = vod_points(points, rss, v_r, np.zeros(3))
    out = add_uniform_noise(rows, 2.0, np.random.default_rng(1), fov_az_deg=64.0, fov_el_deg=20.0,
                            max_range_m=50.0, min_range_m=20.0, rss_range=(0, 1), doppler_range_mps=(0, 1))
    rae = cartesian_to_spherical(out[200:].astype(np.float64)[:, :3])
    az, el = np.abs(np.rad2deg(rae[:, 1])), np.abs(np.rad2deg(rae[:, 2]))
    assert 30.0 < az.max() <= 32.0 + 1e-3 and 9.0 < el.max() <= 10.0 + 1e-3
    assert rae[:, 0].min() >= 20.0 - 1e-4 and rae[:, 0].max() <= 50.0 + 1e-4
    assert np.mean(rae[:, 0] < 35.0) == pytest.approx(0.5, abs=0.1)       # uniform in range, not in volume
    few = add_uniform_noise(rows[:199], 0.05, np.random.default_rng(0), fov_az_deg=64, fov_el_deg=40,
                            max_range_m=50, rss_range=(0, 1), doppler_range_mps=(0, 1))
    assert few.shape == (199 + 10, 7)                                        # round(9.95) = 10


def test_kitti_label_alpha_is_the_observation_angle():
    """alpha = rotation_y - atan2(x, z): a car driving straight away from the camera has alpha =
    -pi/2 wherever it is in the image (KITTI's observation angle), although its rotation_y differs."""
    from pipeline.export import kitti_label_text
    from pipeline.frame import Object3D
    from pipeline.readers.testing import R_CAM_D, rigid

    K = np.array([[600.0, 0, 320], [0, 600.0, 200], [0, 0, 1]])
    T_cam_radar = rigid(R_CAM_D, np.zeros(3))
    objects = [Object3D("Car", np.array([25.0, 25.0 * np.tan(a), 0.3]), np.array([4.2, 1.8, 1.5]), a)
               for a in np.radians([-20.0, -8.0, 0.0, 12.0, 20.0])]
    lines = [line.split() for line in kitti_label_text(objects, T_cam_radar, K, (640, 400)).splitlines()]
    assert len(lines) == 5
    alphas, rys = np.array([float(f[3]) for f in lines]), np.array([float(f[14]) for f in lines])
    np.testing.assert_allclose(alphas, -np.pi / 2, atol=1e-4)
    assert np.ptp(rys) > 0.6


def test_exported_v_r_is_the_range_rate_whatever_the_radars_doppler_convention():
    """synthesize's column 6 is the Doppler in the simulated radar's convention (Astyx: positive
    approaching, aliased), column 8 the range rate; VoD's v_r is a range rate (positive receding).
    A static world seen at 8 m/s: v_r = -(u . v_ego) wrapped, v_r_compensated 0."""
    from pipeline.export import radar_rows

    span = 10.3936
    ego = np.array([8.0, 0.0, 0.0])
    xyz = np.array([[10.0, 0.0, 0.0], [10.0, 10.0, 0.0], [3.0, -4.0, 1.0], [0.0, 7.0, 0.0]])
    unit = xyz / np.linalg.norm(xyz, axis=1, keepdims=True)
    rate = np.mod(-(unit @ ego) + span / 2, span) - span / 2
    points = np.zeros((4, 9), np.float32)
    points[:, :3] = xyz
    points[:, 6] = np.mod(-rate + span / 2, span) - span / 2       # Astyx's sign -1
    points[:, 7] = [50.0, 60.0, 70.0, 80.0]
    points[:, 8] = rate
    rows = radar_rows(points, ego, span)
    np.testing.assert_allclose(rows[:, 3], points[:, 7])
    np.testing.assert_allclose(rows[:, 4], rate, atol=1e-6)
    assert rows[0, 4] == pytest.approx(-8.0 + span, abs=1e-5)      # approaching at 8 m/s, aliased once
    np.testing.assert_allclose(rows[:, 5], 0.0, atol=1e-5)


def test_a_generated_calib_holds_the_full_resolution_camera():
    """Astyx has no calib files: the generated P2 goes with the exported full-size image, so it is
    the dataset's own camera, not the cropped, resized working camera the stages use."""
    from pipeline.config import load_config
    from pipeline.export import calib_P2, generated_calib
    from pipeline.working import working_K

    cfg = load_config("astyx", environ={})
    c = cfg.camera
    K = np.array([[1200.0, 0.0, 1010.0], [0.0, 1190.0, 300.0], [0.0, 0.0, 1.0]])
    K_w = working_K(K, c.crop_rows, c.full_size, c.working_size)
    assert not np.allclose(K_w, K)
    T_cam_radar = np.array([[0.0, -1.0, 0.0, 0.1], [0.0, 0.0, -1.0, 0.2], [1.0, 0.0, 0.0, -0.3], [0, 0, 0, 1.0]])
    P2 = calib_P2(generated_calib(K_w, T_cam_radar, c.crop_rows, c.full_size, c.working_size))
    np.testing.assert_allclose(P2[:, :3], K, atol=1e-9)
    np.testing.assert_allclose(P2[:, 3], 0.0)
