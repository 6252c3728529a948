"""Tests of pipeline.patches: window placement, zero padding, resizing, sampling."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pipeline.patches import image_patch, image_patches, input_summaries, sample_points


def _coded_image(h: int = 40, w: int = 60) -> np.ndarray:
    """Each pixel encodes its own (row, col): channel 0 = row + 1, channel 1 = col + 1, channel 2 = 7."""
    rows, cols = np.mgrid[0:h, 0:w]
    return np.stack([rows + 1, cols + 1, np.full_like(rows, 7)], axis=2).astype(np.uint8)


def test_window_is_centred_on_the_point_without_resize():
    img = _coded_image()
    # r_c = 3 -> S = 6 pixels; centre u = 20.5 -> x0 = round(20.5 - 2.5) = 18: columns 18..23.
    patch = image_patch(img, np.array([20.5, 10.0]), 3.0, 6)
    assert patch.shape == (6, 6, 3) and patch.dtype == np.uint8
    np.testing.assert_array_equal(patch[0, :, 1], np.arange(18, 24) + 1)
    # v = 10 -> y0 = round(7.5) = 8 (round half to even): rows 8..13.
    np.testing.assert_array_equal(patch[:, 0, 0], np.arange(8, 14) + 1)


def test_odd_window_centre_pixel_is_the_point():
    img = _coded_image()
    patch = image_patch(img, np.array([30.0, 20.0]), 2.5, 5)  # S = 5
    assert tuple(patch[2, 2]) == (21, 31, 7)


def test_window_side_is_the_nearest_integer_to_twice_r_c():
    img = _coded_image()
    # r_c = 3.3 -> 2 r_c = 6.6 -> S = 7 (not 6): columns 27..33 around u = 30, no resize at out 7
    patch = image_patch(img, np.array([30.0, 20.0]), 3.3, 7)
    np.testing.assert_array_equal(patch[0, :, 1], np.arange(27, 34) + 1)
    np.testing.assert_array_equal(patch[:, 0, 0], np.arange(17, 24) + 1)
    # r_c = 3.2 -> 6.4 -> S = 6: x0 = round(30 - 2.5) = 28 (half to even)
    np.testing.assert_array_equal(image_patch(img, np.array([30.0, 20.0]), 3.2, 6)[0, :, 1], np.arange(28, 34) + 1)


def test_border_is_zero_padded_not_shifted():
    img = _coded_image()
    patch = image_patch(img, np.array([0.0, 0.0]), 2.5, 5)  # window rows/cols -2..2
    assert np.all(patch[:2] == 0) and np.all(patch[:, :2] == 0)
    assert tuple(patch[2, 2]) == (1, 1, 7)
    far = image_patch(img, np.array([500.0, -300.0]), 4.0, 8)
    assert np.all(far == 0)


def test_batch_matches_single_and_resize_matches_cv2():
    img = np.random.default_rng(0).integers(0, 256, (50, 70, 3), dtype=np.uint8)
    uv = np.array([[10.2, 12.7], [69.0, 49.0], [35.0, 25.0], [-3.0, 4.0]])
    batch = image_patches(img, uv, 8.0, 4)  # S = 16 -> shrink with INTER_AREA
    assert batch.shape == (4, 4, 4, 3)
    for i in range(4):
        np.testing.assert_array_equal(batch[i], image_patch(img, uv[i], 8.0, 4))
    x0 = int(np.rint(35 - 7.5))
    y0 = int(np.rint(25 - 7.5))
    window = img[y0:y0 + 16, x0:x0 + 16]
    np.testing.assert_array_equal(batch[2], cv2.resize(window, (4, 4), interpolation=cv2.INTER_AREA))
    up = image_patches(img, uv[2:3], 2.0, 9)  # S = 4 -> enlarge with INTER_LINEAR
    np.testing.assert_array_equal(up[0], cv2.resize(img[y0 + 6:y0 + 10, x0 + 6:x0 + 10], (9, 9),
                                                    interpolation=cv2.INTER_LINEAR))


def _window_by_hand(img: np.ndarray, u: float, v: float, su: int, sv: int) -> np.ndarray:
    """The S_v x S_u window of the module docstring, zero outside the image, cut out pixel by pixel."""
    x0, y0 = int(np.rint(u - (su - 1) / 2)), int(np.rint(v - (sv - 1) / 2))
    out = np.zeros((sv, su, 3), np.uint8)
    for r in range(sv):
        for c in range(su):
            if 0 <= y0 + r < img.shape[0] and 0 <= x0 + c < img.shape[1]:
                out[r, c] = img[y0 + r, x0 + c]
    return out


@pytest.mark.parametrize("r_c, out", [(8.0, 32), (4.0, 32), ((8.0, 4.0), 32), ((4.0, 8.0), 16), (2.0, 32),
                                      (8.0, 48), (5.0, 30), (6.0, 32), (16.0, 12), (8.0, 16)])
def test_many_windows_equal_each_window_resized_alone(r_c, out):
    """Enlargements by powers of two run as one resize of all windows stacked; the bytes must be
    those of cv2.resize on each window alone (no bleeding between neighbouring windows, cv2's edge
    clamping at each window's border), for every factor and shape, points off the image included."""
    rng = np.random.default_rng(7)
    img = rng.integers(0, 256, (48, 80, 3), dtype=np.uint8)
    uv = np.column_stack([rng.uniform(-12, 92, 40), rng.uniform(-12, 60, 40)])
    su, sv = (int(round(2 * r)) for r in np.broadcast_to(r_c, (2,)))
    interp = cv2.INTER_AREA if su * sv >= out * out else cv2.INTER_LINEAR
    expected = np.stack([cv2.resize(_window_by_hand(img, u, v, su, sv), (out, out), interpolation=interp)
                         for u, v in uv])
    np.testing.assert_array_equal(image_patches(img, uv, r_c, out), expected)


def test_rectangular_window():
    img = _coded_image()
    patch = image_patches(img, np.array([[30.0, 20.0]]), (3.0, 1.5), 6)[0]  # 6 wide x 3 high -> 6 x 6
    assert patch.shape == (6, 6, 3)
    # S_u = 6: x0 = round(30 - 2.5) = 28 (half to even); S_v = 3: y0 = round(20 - 1) = 19.
    src = img[19:22, 28:34]
    np.testing.assert_array_equal(patch, cv2.resize(src, (6, 6), interpolation=cv2.INTER_LINEAR))


def test_empty_and_errors():
    img = _coded_image()
    assert image_patches(img, np.zeros((0, 2)), 3.0, 5).shape == (0, 5, 5, 3)
    with pytest.raises(ValueError, match="uint8"):
        image_patches(img.astype(np.float32), np.zeros((1, 2)), 3.0, 5)
    with pytest.raises(ValueError, match="r_c"):
        image_patches(img, np.zeros((1, 2)), 0.0, 5)
    with pytest.raises(ValueError, match="out_size"):
        image_patches(img, np.zeros((1, 2)), 3.0, 0)
    with pytest.raises(ValueError, match="expected shape"):
        image_patch(img, np.zeros(3), 3.0, 5)
    with pytest.raises(ValueError, match="non-finite"):
        image_patches(img, np.array([[np.nan, 0.0]]), 3.0, 5)


def test_sample_points():
    rng = np.random.default_rng(0)
    idx = sample_points(rng, 100, 10)
    assert idx.shape == (10,) and len(set(idx.tolist())) == 10 and np.all(np.diff(idx) > 0)
    assert idx.min() >= 0 and idx.max() < 100
    np.testing.assert_array_equal(sample_points(rng, 7, 10), np.arange(7))
    assert sample_points(rng, 0, 5).shape == (0,)
    a = sample_points(np.random.default_rng(3), 50, 5)
    b = sample_points(np.random.default_rng(3), 50, 5)
    np.testing.assert_array_equal(a, b)
    # One generator across frames: consecutive frames get different draws.
    g = np.random.default_rng(4)
    assert not np.array_equal(sample_points(g, 1000, 5), sample_points(g, 1000, 5))
    with pytest.raises(ValueError):
        sample_points(rng, -1, 5)
    # most of the points: still no point drawn twice
    assert len(np.unique(sample_points(np.random.default_rng(5), 100, 90))) == 90


def test_input_summaries_hand_computed():
    # range images: EMPTY (-1) is unoccupied, 0 (a neighbour nearer by r_l) is occupied
    ranges = np.array([[[-1.0, 0.0], [127.0, -1.0]], [[254.0, 3.5], [0.0, 1.0]]])
    patches = np.zeros((2, 2, 2, 3))
    patches[1] = 51.0
    points = np.array([[3.0, 4.0, 0.0, -2.5], [0.0, 0.0, 2.0, 1.5]])
    out = input_summaries(patches, ranges, points)
    np.testing.assert_allclose(out, [[0.5, 5.0, 2.5, 0.0], [1.0, 2.0, 1.5, 51.0]])
    assert np.isnan(input_summaries(None, None, points)[:, [0, 3]]).all()
