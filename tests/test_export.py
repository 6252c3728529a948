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
    write_vod_rows,
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
    path = write_vod_rows(tmp_path / "radar" / "00001.bin", vod_points(points, rss, v_r, ego))
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
    path = write_vod_rows(tmp_path / "e.bin", vod_points(np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(3)))
    assert read_vod_bin(path).shape == (0, 7)
    bad = tmp_path / "bad.bin"
    bad.write_bytes(b"\0" * 30)
    with pytest.raises(ReaderError, match="multiple of 28"):
        read_vod_bin(bad)
    with pytest.raises(ReaderError):
        read_vod_bin(tmp_path / "missing.bin")
    with pytest.raises(ValueError):
        vod_points(np.zeros((3, 3)), np.zeros(2), np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError):
        write_vod_rows(tmp_path / "x.bin", np.zeros((3, 6)))


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


def test_a_box_reaching_behind_the_camera_is_labelled_by_its_part_in_front(tmp_path: Path):
    """An object beside the car whose box reaches behind the camera plane (on Astyx a truck holding
    104 radar points) is written with truncation 1, as label_truncation rates such a box, and the 2D
    box of its part in front of the plane: here checked against points filling the box, kept in
    front, projected and clipped. OpenPCDet's reading gives the 3D box back. Until 2026-12-07 such a
    box was left out, so a detector trained on the export learnt the truck as background. A box
    wholly behind the camera is still left out."""
    from pipeline.export import NEAR_PLANE_M, in_front_of_camera, kitti_label_text
    from pipeline.frame import Object3D
    from pipeline.readers.kitti_format import lidar_box_label_to_object, parse_label_file
    from pipeline.readers.testing import R_CAM_D, rigid

    K = np.array([[600.0, 0, 320], [0, 600.0, 200], [0, 0, 1]])
    T_cam_radar = rigid(R_CAM_D, np.array([0.05, 0.8, -0.4]))
    beside = Object3D("Truck", np.array([1.5, 2.4, 0.8]), np.array([8.0, 2.5, 3.0]), 0.1)
    text = kitti_label_text([beside], T_cam_radar, K, (640, 400))
    fields = text.split()
    assert fields[0] == "Truck" and float(fields[1]) == 1.0
    u = np.linspace(-0.5, 0.5, 41)
    fill = np.stack(np.meshgrid(u, u, u, indexing="ij"), -1).reshape(-1, 3) * beside.size_lwh_m
    cam = (beside.center_D + fill @ beside.rotation.T) @ T_cam_radar[:3, :3].T + T_cam_radar[:3, 3]
    assert (cam[:, 2] <= NEAR_PLANE_M).any() and (cam[:, 2] > 1.0).any()
    cam = cam[cam[:, 2] > NEAR_PLANE_M]
    uv = (cam @ K.T)[:, :2] / cam[:, 2:3]
    brute = [max(uv[:, 0].min(), 0), max(uv[:, 1].min(), 0), min(uv[:, 0].max(), 639), min(uv[:, 1].max(), 399)]
    np.testing.assert_allclose([float(v) for v in fields[4:8]], brute, atol=2.0)
    (tmp_path / "label.txt").write_text(text)
    label = parse_label_file(tmp_path / "label.txt", "x")[0]
    back = lidar_box_label_to_object(label, invert_transform(T_cam_radar), np.eye(4), -1)
    np.testing.assert_allclose(back.center_D, beside.center_D, atol=1e-4)
    np.testing.assert_allclose(back.size_lwh_m, beside.size_lwh_m, atol=1e-5)
    behind = Object3D("Car", np.array([-3.0, 2.4, 0.3]), np.array([4.0, 1.8, 1.5]), 0.0)
    assert kitti_label_text([behind], T_cam_radar, K, (640, 400)) == DONT_CARE_LINE + "\n"
    assert len(in_front_of_camera(np.tile([0.0, 0.0, -1.0], (8, 1)))) == 0


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


def test_kitti_label_text_projects_a_tilted_box_with_its_tilt():
    """A box pitched 10 deg and rolled -6 deg (Astyx keeps its boxes' tilt since 2026-12-06): its 2D
    box is the clipped projection of its own 8 corners, not of the upright box's; location, size,
    rotation_y and alpha are the upright box's (OpenPCDet's boxes are upright in {D}, the yaw the
    heading of the length axis on {D}'s x-y plane). Upright boxes are written to the byte as the
    yaw-only corners (cos and sin of the yaw, before 2026-12-06) give them."""
    from pipeline.export import _clipped_box, kitti_label_text
    from pipeline.frame import Object3D
    from pipeline.readers.testing import R_CAM_D, rigid
    from pipeline.world.rig import rotation_zyx

    K = np.array([[600.0, 0, 320], [0, 600.0, 200], [0, 0, 1]])
    T_cam_radar = rigid(R_CAM_D, np.array([0.05, 0.8, -0.4])) @ rigid(
        np.array([[1, 0, 0], [0, np.cos(0.05), -np.sin(0.05)], [0, np.sin(0.05), np.cos(0.05)]]), np.zeros(3))
    pitch, roll = np.radians(10.0), np.radians(-6.0)
    upright = Object3D("Car", np.array([12.0, 1.5, 0.3]), np.array([4.2, 1.8, 1.5]), 0.7)
    tilted = Object3D("Car", upright.center_D, upright.size_lwh_m, 0.7, pitch_rad=pitch, roll_rad=roll)
    a, b = (kitti_label_text([o], T_cam_radar, K, (640, 400)).split() for o in (upright, tilted))
    assert a[:4] == b[:4] and a[8:] == b[8:] and a[4:8] != b[4:8]
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
    for obj, fields, R in ((tilted, b, rotation_zyx(0.7, pitch, roll)), (upright, a, rotation_zyx(0.7, 0.0, 0.0))):
        corners_cam = (obj.center_D + 0.5 * signs * obj.size_lwh_m @ R.T) @ T_cam_radar[:3, :3].T + T_cam_radar[:3, 3]
        (box, _) = _clipped_box((corners_cam @ K.T)[:, :2] / corners_cam[:, 2:3], (640, 400))
        np.testing.assert_allclose([float(v) for v in fields[4:8]], box, rtol=1e-5)

    rng, checked = np.random.default_rng(6), 0
    for _ in range(30):
        obj = Object3D("Car", np.array([rng.uniform(5, 40), rng.uniform(-10, 10), rng.uniform(-1, 1)]),
                       rng.uniform(0.5, 5, 3), rng.uniform(-np.pi, np.pi))
        (length, width, height), (c, s) = obj.size_lwh_m, (np.cos(obj.yaw_rad), np.sin(obj.yaw_rad))
        dx, dy, dz = np.meshgrid([-length / 2, length / 2], [-width / 2, width / 2], [-height / 2, height / 2],
                                 indexing="ij")
        corners_D = obj.center_D + np.stack([c * dx.ravel() - s * dy.ravel(), s * dx.ravel() + c * dy.ravel(),
                                             dz.ravel()], axis=1)
        corners_cam = corners_D @ T_cam_radar[:3, :3].T + T_cam_radar[:3, 3]
        text = kitti_label_text([obj], T_cam_radar, K, (640, 400))
        if np.any(corners_cam[:, 2] <= 0.1) or text == DONT_CARE_LINE + "\n":
            continue
        (box, truncation) = _clipped_box((corners_cam @ K.T)[:, :2] / corners_cam[:, 2:3], (640, 400))
        fields = text.split()
        assert fields[1] == f"{truncation:.6g}" and fields[4:8] == [f"{v:.6g}" for v in box]
        checked += 1
    assert checked > 10


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


# ---------------------------------------------------------------- the export stage on fixture datasets

def _calibrated(tmp_path: Path, profile: str, overrides: dict[str, str]):
    """The calibrate stage run on a fixture dataset under tmp_path / 'data' (64 x 48 images); its RunEnv."""
    from pipeline.config import load_config
    from pipeline.executor import Executor, RunEnv
    from pipeline.runner import Pipeline
    from stages import calibrate

    cfg = load_config(profile, environ={}).with_overrides({"camera.full_size": "64,48", "camera.crop_rows": "0,48",
                                                           **overrides})
    env = RunEnv(cfg=cfg, cache_root=str(tmp_path / "cache"), dataset=profile, data_root=str(tmp_path / "data"))
    report, = Pipeline([calibrate.STAGE], env, Executor(1), progress=False, log=lambda m: None).run("calibrate")
    assert report.failed == 0
    return env


def _export(env, points: list[np.ndarray], out: Path) -> dict:
    """The export stage's run over frames whose synthesized points (n, 9, synthesize's columns) are
    ``points``, written into synthesize's store as that stage writes them; its summary."""
    from types import SimpleNamespace

    from pipeline.runner import DatasetInputs
    from stages import export
    from stages.synthesize import outputs

    ids = env.store("calibrate").frame_ids()
    spec = next(s for s in outputs(env.cfg) if s.name == "points")
    syn = env.store("synthesize")
    syn.create("fixture", ids, (spec,), {"points": spec.shape}, {})
    for i, pts in enumerate(points):
        syn.write_frame(i, {"points": np.asarray(pts, np.float32)}, (spec,))
    return export.run(DatasetInputs(env, ids), env.cfg, SimpleNamespace(path=str(out)), "fixture")


def _synthesized(xyz: np.ndarray, rng: np.random.Generator, cfg) -> np.ndarray:
    """Synthesize's point rows (n, 9) at ``xyz`` (n, 3) {D}: range, azimuth, elevation, a Doppler,
    an RSS in the radar's range and a range rate."""
    rae = cartesian_to_spherical(xyz)
    n = len(xyz)
    return np.column_stack([xyz, rae, rng.uniform(-2, 2, n), rng.uniform(cfg.radar.rss_min, cfg.radar.rss_max, n),
                            rng.uniform(-2, 2, n)]).astype(np.float32)


def test_the_export_stage_writes_noise_pcd_previews_and_counts_what_it_wrote(tmp_path: Path):
    """The export stage on a View-of-Delft fixture (its calib and labels carried over) with
    export.noise_fraction, PCD and previews: each .bin holds the frame's VoD rows, then
    round(fraction * n) noise rows drawn per frame within the radar's Doppler span; the summary
    counts the synthesized points and the noise apart; the PCD holds the synthesized points with
    their RSS and Doppler, the preview colours them by range. Points on a box of unknown velocity
    (a pedestrian seen once) are counted in their frame alone; an empty frame is named; with no
    frame in the train split the message says how to get one; no image unless export.images; the
    reader's image where the dataset's file is not in export.image_format."""
    from dataclasses import replace

    from pipeline.export import radar_rows
    from pipeline.readers import get_reader
    from pipeline.readers.testing import T_CAM_RADAR, kitti_label_line, make_vod_dataset
    from stages.export import UNKNOWN_OBJECT_MOTION_LIST

    truth = make_vod_dataset(tmp_path / "data", n_frames=3, speed_mps=5.0)
    ids = truth.frame_ids
    walker = np.array([12.0, 3.0, 0.0])  # a pedestrian (track 9) in the second frame alone: velocity unknown
    second = tmp_path / "data/lidar/training/label_2" / f"{ids[1]}.txt"
    second.write_text(second.read_text() + kitti_label_line("Pedestrian", 9, walker, np.array([0.6, 0.6, 1.7]),
                                                            0.0, T_CAM_RADAR) + "\n")
    env = _calibrated(tmp_path, "vod", {"camera.working_size": "64,48", "radar.doppler_span_mps": "6",
                                        "export.noise_fraction": "0.2", "export.images": "false",
                                        "split.rule": "random", "split.fractions": "0,1,0", "synth.split": "all"})
    cfg, calib = env.cfg, env.store("calibrate")
    rng = np.random.default_rng(3)
    points = []
    for i in range(2):  # frames of 30 points each, away from the pedestrian; the last frame empty
        lidar = calib.read("lidar", i).astype(np.float64)
        lidar = lidar[np.linalg.norm(lidar - walker, axis=1) > 3.0]
        points.append(_synthesized(lidar[rng.choice(len(lidar), 30, replace=False)], rng, cfg))
    on_walker = 4
    points[1][:on_walker] = _synthesized(walker + rng.uniform(-0.2, 0.2, (on_walker, 3)), rng, cfg)
    points.append(np.zeros((0, 9), np.float32))
    summary = _export(env, points, tmp_path / "out")
    radar = tmp_path / "out" / "radar" / "training"

    n = [len(p) for p in points]
    n_noise = [int(round(cfg.export.noise_fraction * k)) for k in n]
    assert summary["points"] == sum(n) and summary["noise_points"] == sum(n_noise) > 0
    assert f"{sum(n)} points (+{sum(n_noise)} noise)" in summary["message"]
    noise = []
    for i, fid in enumerate(ids):
        rows = read_vod_bin(radar / "velodyne" / f"{fid}.bin")
        assert len(rows) == n[i] + n_noise[i]
        np.testing.assert_array_equal(rows[:n[i]], radar_rows(points[i], calib.read("ego_velocity", i),
                                                              cfg.radar.doppler_span_mps))
        noise.append(rows[n[i]:])
        assert np.all(np.abs(noise[i][:, 4]) <= cfg.radar.doppler_span_mps / 2)  # v_r within the span
        pcd = read_pcd(tmp_path / "out" / "pcd" / f"{fid}.pcd")
        np.testing.assert_array_equal(pcd, points[i][:, [0, 1, 2, 7, 6]])
        image, T_cam_radar = calib.read("image", i), invert_transform(calib.read("T_radar_cam", i))
        uv, _, valid = project_to_image(points[i][:, :3], calib.read("K", i), T_cam_radar, image.shape[1::-1])
        preview_png(tmp_path / "expected.png", image, uv[valid], points[i][valid, 3], cfg.radar.max_range_m)
        np.testing.assert_array_equal(cv2.imread(str(tmp_path / "out" / "preview" / f"{fid}.png")),
                                      cv2.imread(str(tmp_path / "expected.png")))
    assert not np.isin(noise[0][:, :3], noise[1][:, :3]).any()  # drawn per frame, not the same points twice
    assert not (radar / "image_2").exists() and (radar / "calib" / f"{ids[0]}.txt").is_file()
    # the pedestrian's points in their frame; the ego motion is known everywhere
    assert summary["object_motion_unknown"] == {"frames": 1, "points": on_walker}
    assert (tmp_path / "out" / UNKNOWN_OBJECT_MOTION_LIST).read_text().split() == [ids[1]]
    share = f"{on_walker / sum(n):.0%}"
    assert f"; {on_walker} of the points ({share}), in 1 frame(s), lie on labelled objects" in summary["message"]
    assert summary["no_ego_motion"] == 0 and "without a recorded ego motion" not in summary["message"]
    assert summary["empty_frames"] == [ids[2]] and f"1 of them without a point (an empty .bin, on which a detector's " \
        f"voxelisation may fail): {ids[2]}" in summary["message"]
    # every frame in val: OpenPCDet trains on none, and the message says how to change that
    sets = {name: (radar.parent / "ImageSets" / f"{name}.txt").read_text().split() for name in ("train", "val", "test")}
    assert sets == {"train": [], "val": ids, "test": []}
    assert "no frame is in the train split" in summary["message"]

    # export.images with a format the dataset's .jpg is not: the reader's image, as PNG; no noise
    png = replace(env, cfg=cfg.with_overrides({"export.images": "true", "export.image_format": "png",
                                               "export.noise_fraction": "0", "export.pcd": "false",
                                               "export.previews": "false"}))
    summary = _export(png, points, tmp_path / "png")
    radar = tmp_path / "png" / "radar" / "training"
    assert summary["noise_points"] == 0 and not (tmp_path / "png" / "pcd").exists()
    reader = get_reader(png.cfg, tmp_path / "data")
    for i, fid in enumerate(ids):
        assert len(read_vod_bin(radar / "velodyne" / f"{fid}.bin")) == n[i]
        written = cv2.imread(str(radar / "image_2" / f"{fid}.png"))[:, :, ::-1]
        np.testing.assert_array_equal(written, reader.read(fid).image)

    # two classes renamed to one: the counts are those of the written labels (before 2026-12-06 the
    # renamed class's count replaced the other's)
    merged = replace(env, cfg=cfg.with_overrides({"export.class_names": "Pedestrian=Car", "export.pcd": "false",
                                                  "export.previews": "false"}))
    written = label_classes("".join((radar / "label_2" / f"{fid}.txt").read_text() for fid in ids))
    summary = _export(merged, points, tmp_path / "merged")
    labels = label_classes("".join((tmp_path / "merged/radar/training/label_2" / f"{fid}.txt").read_text()
                                   for fid in ids))
    assert written["Pedestrian"] >= 1 and written["Car"] >= 1
    assert summary["classes"]["training"] == dict(labels) and labels["Car"] == written["Car"] + written["Pedestrian"]


def test_the_export_stage_generates_calib_labels_and_images_for_a_dataset_without_kitti_files(tmp_path: Path):
    """Astyx has no KITTI files: the export writes a calib generated for the full-resolution
    camera, the reader's objects as KITTI labels for that camera (each box's 2D rectangle holds its
    centre projected with the written P2, at a working size other than the full one) and the
    reader's image as PNG; a frame without a ground-truth file gets no label file (its objects are
    unknown, not absent). With every frame in the test split the message counts the boxes under
    testing/ and says that no frame is in the train split. No point on the (velocity-less) box: no
    list of frames with such points."""
    from pipeline.export import calib_P2
    from pipeline.readers import get_reader
    from pipeline.readers.testing import make_astyx_dataset
    from stages.export import UNKNOWN_OBJECT_MOTION_LIST

    make_astyx_dataset(tmp_path / "data", n_frames=2)
    (tmp_path / "data" / "groundtruth_obj3d" / "000001.json").unlink()
    env = _calibrated(tmp_path, "astyx", {"camera.working_size": "32,24", "split.rule": "random",
                                          "split.fractions": "0,0,1", "synth.split": "all"})
    calib, rng = env.store("calibrate"), np.random.default_rng(0)
    points = []
    for i in range(2):  # lidar points away from the fixture's car at (15, 2, -0.5)
        lidar = calib.read("lidar", i).astype(np.float64)
        points.append(_synthesized(lidar[np.linalg.norm(lidar - [15.0, 2.0, -0.5], axis=1) > 4.0][:20], rng, env.cfg))
    summary = _export(env, points, tmp_path / "out")
    testing = tmp_path / "out" / "radar" / "testing"
    reader = get_reader(env.cfg, tmp_path / "data")
    record = reader.read("000000")
    P2 = calib_P2((testing / "calib" / "000000.txt").read_text())
    np.testing.assert_allclose(P2[:, :3], record.K, atol=1e-6)
    (line,) = (testing / "label_2" / "000000.txt").read_text().splitlines()
    fields = line.split()
    assert fields[0] == "Car"
    left, top, right, bottom = (float(v) for v in fields[4:8])
    h, location = float(fields[8]), np.array([float(v) for v in fields[11:14]])
    u, v, w = P2 @ np.append(location - [0.0, h / 2, 0.0], 1.0)   # the box centre (camera y points down)
    assert left <= u / w <= right and top <= v / w <= bottom and right - left > 2
    assert not (testing / "label_2" / "000001.txt").exists()
    for fid in ("000000", "000001"):
        written = cv2.imread(str(testing / "image_2" / f"{fid}.png"))[:, :, ::-1]
        np.testing.assert_array_equal(written, reader.read(fid).image)
    assert summary["classes"] == {"training": {}, "testing": {"Car": 1}}
    assert "labelled boxes under testing/ by class: Car 1" in summary["message"]
    assert "no frame is in the train split" in summary["message"]
    assert summary["object_motion_unknown"] == {"frames": 0, "points": 0}
    assert not (tmp_path / "out" / UNKNOWN_OBJECT_MOTION_LIST).exists() and "lie on labelled" not in summary["message"]


def test_the_export_message_names_five_empty_frames_and_marks_more():
    """The message names the first five frames without a point, with ' ...' only when there are
    more than five."""
    from pipeline.config import load_config
    from stages.export import _message, _Tally

    cfg = load_config("vod", environ={})
    for k in (5, 6):
        tally = _Tally(empty=[f"{i:05d}" for i in range(k)], points=10)
        tally.lists["train"] = ["00000"]
        message = _message(tally, k, Path("out"), cfg)
        listed = message.split("voxelisation may fail): ")[1]
        assert listed == ", ".join(tally.empty[:5]) + (" ..." if k > 5 else "")


def test_the_export_names_training_frames_without_a_label_file(tmp_path: Path):
    """A View-of-Delft frame of the train split without its label file is written without label_2,
    which OpenPCDet's info generation asserts on: the message says so and lists it (before
    2026-12-06 nothing did); a test frame without one is no problem (OpenPCDet reads no test label)."""
    from pipeline.readers.testing import make_vod_dataset
    from stages.export import UNLABELLED_LIST

    ids = make_vod_dataset(tmp_path / "data", n_frames=3, speed_mps=5.0).frame_ids
    (tmp_path / "data/lidar/training/label_2" / f"{ids[1]}.txt").unlink()
    overrides = {"camera.working_size": "64,48", "export.images": "false", "export.pcd": "false",
                 "export.previews": "false", "split.rule": "random", "split.fractions": "1,0,0", "synth.split": "all"}
    env = _calibrated(tmp_path, "vod", overrides)
    rng = np.random.default_rng(0)
    points = [_synthesized(env.store("calibrate").read("lidar", i)[:5].astype(np.float64), rng, env.cfg)
              for i in range(3)]
    summary = _export(env, points, tmp_path / "out")
    labels = tmp_path / "out" / "radar" / "training" / "label_2"
    assert sorted(p.stem for p in labels.iterdir()) == sorted([ids[0], ids[2]])
    assert summary["training_frames_without_label"] == 1
    assert (tmp_path / "out" / UNLABELLED_LIST).read_text().split() == [ids[1]]
    assert "1 of the frames under training/ have no label_2 file" in summary["message"]
    assert str(tmp_path / "out" / UNLABELLED_LIST) in summary["message"]

    (tmp_path / "test").mkdir()
    (tmp_path / "test" / "data").symlink_to(tmp_path / "data")
    tested = _calibrated(tmp_path / "test", "vod", {**overrides, "split.fractions": "0,0,1"})
    summary = _export(tested, points, tmp_path / "test" / "out")
    assert summary["training_frames_without_label"] == 0 and "label_2 file" not in summary["message"]
    assert not (tmp_path / "test" / "out" / UNLABELLED_LIST).exists()
