"""Tests of pipeline.working: exact intrinsics after crop + resize, scaling helpers, FOV masks."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pipeline.geometry import project_to_image
from pipeline.working import (
    common_fov_mask,
    crop_resize,
    fov_mask,
    full_K,
    full_to_working_uv,
    scale_rc,
    scale_sigma,
    working_K,
)

K_FULL = np.array([[1500.0, 0.3, 960.0], [0.0, 1480.0, 610.0], [0.0, 0.0, 1.0]])
FULL_WH = (1936, 1216)
CROP = (571, 1215)
WORK_WH = (320, 160)
# Camera looking along +x of {D}: cam x = -y_D, cam y = -z_D, cam z = x_D, offset 0.2 m.
T_CAM_RADAR = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.2], [1.0, 0.0, 0.0, 0.1], [0, 0, 0, 1.0]])


def test_projection_with_working_K_equals_mapped_full_pixel():
    rng = np.random.default_rng(0)
    pts = rng.uniform([5, -10, -2], [60, 10, 3], (200, 3))
    uv_full, _, _ = project_to_image(pts, K_FULL, T_CAM_RADAR, FULL_WH)
    Kw = working_K(K_FULL, CROP, FULL_WH, WORK_WH)
    uv_work, _, _ = project_to_image(pts, Kw, T_CAM_RADAR, WORK_WH)
    np.testing.assert_allclose(uv_work, full_to_working_uv(uv_full, CROP, FULL_WH, WORK_WH), atol=1e-9)


def test_pixel_centre_convention_on_corners():
    # Full-image pixel area [-0.5, W - 0.5) x [top - 0.5, bottom - 0.5) maps onto the working area.
    corners = np.array([[-0.5, CROP[0] - 0.5], [FULL_WH[0] - 0.5, CROP[1] - 0.5]])
    np.testing.assert_allclose(full_to_working_uv(corners, CROP, FULL_WH, WORK_WH),
                               [[-0.5, -0.5], [WORK_WH[0] - 0.5, WORK_WH[1] - 0.5]])


def test_crop_resize_matches_cv2_and_tracks_a_feature():
    img = np.zeros((120, 200, 3), np.uint8)
    img[70:74, 100:104] = 255  # bright 4x4 square centred on full pixel (101.5, 71.5)
    out, Kw = crop_resize(img, np.eye(3), (40, 120), (100, 40))
    assert out.shape == (40, 100, 3) and out.dtype == np.uint8
    np.testing.assert_array_equal(out, cv2.resize(img[40:120], (100, 40), interpolation=cv2.INTER_AREA))
    # Centre of mass of the square in the working image equals the mapped full-res centre.
    weight = out[..., 0].astype(np.float64)
    rows, cols = np.mgrid[0:40, 0:100]
    com = np.array([(cols * weight).sum(), (rows * weight).sum()]) / weight.sum()
    expected = full_to_working_uv(np.array([[101.5, 71.5]]), (40, 120), (200, 120), (100, 40))[0]
    np.testing.assert_allclose(com, expected, atol=1e-9)
    np.testing.assert_allclose(Kw, working_K(np.eye(3), (40, 120), (200, 120), (100, 40)))


def test_shrinking_averages_whole_pixel_blocks():
    # A 4x shrink must average each 4 x 4 block (area interpolation), not sample a few pixels of it.
    img = np.random.default_rng(2).integers(0, 256, (16, 24, 3), dtype=np.uint8)
    out, _ = crop_resize(img, np.eye(3), (0, 16), (6, 4))
    block_mean = img.astype(np.float64).reshape(4, 4, 6, 4, 3).mean(axis=(1, 3))
    assert np.abs(out - block_mean).max() <= 0.5 + 1e-9


def test_enlarging_uses_linear_and_shapes():
    img = np.random.default_rng(1).integers(0, 255, (10, 12, 3), dtype=np.uint8)
    out, _ = crop_resize(img, K_FULL, (0, 10), (24, 20))
    np.testing.assert_array_equal(out, cv2.resize(img, (24, 20), interpolation=cv2.INTER_LINEAR))


def test_crop_errors():
    img = np.zeros((10, 10, 3), np.uint8)
    with pytest.raises(ValueError, match="crop_rows"):
        crop_resize(img, np.eye(3), (5, 5), (4, 4))
    with pytest.raises(ValueError, match="crop_rows"):
        crop_resize(img, np.eye(3), (0, 11), (4, 4))
    with pytest.raises(ValueError, match="uint8"):
        crop_resize(img.astype(np.float32), np.eye(3), (0, 10), (4, 4))
    with pytest.raises(ValueError, match="sizes"):
        crop_resize(img, np.eye(3), (0, 10), (0, 4))


def test_scale_sigma_and_rc():
    sx, sy = scale_sigma((100.0, 100.0), CROP, FULL_WH, WORK_WH)
    assert sx == pytest.approx(100 * 320 / 1936) and sy == pytest.approx(100 * 160 / 644)
    # A length of 2 r_c full-res pixels maps to the distance between the mapped end points.
    rcu, rcv = scale_rc(50.0, CROP, FULL_WH, WORK_WH)
    ends = full_to_working_uv(np.array([[900.0, 800.0], [1000.0, 900.0]]), CROP, FULL_WH, WORK_WH)
    np.testing.assert_allclose(ends[1] - ends[0], [2 * rcu, 2 * rcv])


def test_fov_mask():
    pts = np.array([
        [10.0, 0.0, 0.0],                                    # inside
        [10.0, 10.0 * np.tan(np.deg2rad(31.0)), 0.0],        # az 31 < 32: inside
        [10.0, 10.0 * np.tan(np.deg2rad(33.0)), 0.0],        # az 33 > 32: out
        [10.0, 0.0, 10.0 * np.tan(np.deg2rad(21.0))],        # el 21 > 20: out
        [-10.0, 0.0, 0.0],                                   # behind
        [49.9, 0.0, 0.0], [50.1, 0.0, 0.0],                  # range limit
        [0.0, 0.0, 0.0],                                     # origin
        [10.0, -10.0 * np.tan(np.deg2rad(31.0)), 0.0],       # az -31: inside
        [10.0, -10.0 * np.tan(np.deg2rad(33.0)), 0.0],       # az -33: out
        [10.0, 0.0, -10.0 * np.tan(np.deg2rad(19.0))],       # el -19: inside
        [10.0, 0.0, -10.0 * np.tan(np.deg2rad(21.0))],       # el -21: out
    ])
    np.testing.assert_array_equal(fov_mask(pts, 64.0, 40.0, 50.0), [1, 1, 0, 0, 0, 1, 0, 0, 1, 0, 1, 0])
    assert fov_mask(np.zeros((0, 3)), 64.0, 40.0, 50.0).shape == (0,)


def test_common_fov_mask_requires_projection_inside_working_image():
    Kw = working_K(K_FULL, CROP, FULL_WH, WORK_WH)
    pts = np.array([[20.0, 0.0, 0.0], [20.0, 0.0, 5.0], [20.0, 0.0, -1.0], [60.0, 0.0, -1.0]])
    _, _, in_image = project_to_image(pts, Kw, T_CAM_RADAR, WORK_WH)
    mask = common_fov_mask(pts, Kw, T_CAM_RADAR, WORK_WH, 64.0, 40.0, 50.0)
    np.testing.assert_array_equal(mask, in_image & fov_mask(pts, 64.0, 40.0, 50.0))
    # Row of (20, 0, 0): 610 + 1480 * 0.2 / 20 = 624.8, inside the crop 571..1214 -> in.
    # Above the crop (z = 5 m at 20 m projects to row ~250) -> out; beyond range (60 m) -> out.
    assert mask[0] and not mask[1] and mask[2] and not mask[3]
    # The image is 320 wide and 160 high (not 160 wide): a point 12 m to the right at 20 m (camera
    # depth 20.1 m) lands at full column 960 + (1500 * 12 + 0.3 * 0.2) / 20.1 = 1855.5, working
    # column (1855.5 + 0.5) * 320 / 1936 - 0.5 = 306.3; full row 610 + 1480 * 0.2 / 20.1 = 624.7,
    # working row (624.7 - 571 + 0.5) * 160 / 644 - 0.5 = 13.0.
    right = np.array([[20.0, -12.0, 0.0]])
    uv, _, _ = project_to_image(right, Kw, T_CAM_RADAR, WORK_WH)
    np.testing.assert_allclose(uv[0], [306.28, 12.97], atol=0.01)
    assert common_fov_mask(right, Kw, T_CAM_RADAR, WORK_WH, 90.0, 40.0, 50.0).tolist() == [True]


def test_full_K_inverts_working_K():
    """A calib generated for the dataset's own image needs the full-resolution intrinsics back."""
    Kw = working_K(K_FULL, CROP, FULL_WH, WORK_WH)
    np.testing.assert_allclose(full_K(Kw, CROP, FULL_WH, WORK_WH), K_FULL, rtol=1e-12, atol=1e-9)
    assert not np.allclose(Kw, K_FULL)
