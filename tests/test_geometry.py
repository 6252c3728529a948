"""Frame and pixel conventions of pipeline.geometry: angles in {D} (x forward, y left, z up), the
pixel area [-0.5, W - 0.5), depths, transforms and Doppler wrapping."""

import numpy as np
import pytest

from pipeline.geometry import (cartesian_to_spherical, invert_transform, norms_m, project_to_image, radial_velocity,
                               spherical_to_cartesian, wrap_doppler)


def test_spherical_angles_follow_the_radar_frame_and_round_trip():
    # {D}: x forward, y left, z up; azimuth positive to the left, elevation positive up.
    pts = np.array([[1.0, 1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 2.0, 0.0], [3.0, 0.0, -3.0], [0.0, 0.0, 5.0]])
    rae = cartesian_to_spherical(pts)
    np.testing.assert_allclose(rae[:, 0], [np.sqrt(2), np.sqrt(2), 2.0, np.sqrt(18), 5.0], rtol=1e-12)
    np.testing.assert_allclose(rae[:, 1], [np.pi / 4, -np.pi / 4, np.pi / 2, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(rae[:, 2], [0.0, 0.0, 0.0, -np.pi / 4, np.pi / 2], atol=1e-12)
    cloud = np.random.default_rng(0).uniform(-50, 50, (100, 3))
    np.testing.assert_allclose(spherical_to_cartesian(cartesian_to_spherical(cloud)), cloud, atol=1e-9)


def test_projection_keeps_exactly_the_pixel_area_in_front_of_the_camera():
    # Identity extrinsics, unit focal length: a point (x, y, 1) projects to (cx + x, cy + y).
    K = np.array([[1.0, 0.0, 2.0], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])
    w, h = 6, 4                                    # pixel area [-0.5, 5.5) x [-0.5, 3.5)
    uv = np.array([[-0.5, 0.0], [-0.5625, 0.0], [5.4375, 0.0], [5.5, 0.0],
                   [0.0, -0.5], [0.0, -0.5625], [0.0, 3.4375], [0.0, 3.5]])
    pts = np.column_stack([uv - [2.0, 1.0], np.ones(len(uv))])
    got, depth, valid = project_to_image(pts, K, np.eye(4), (w, h))
    np.testing.assert_allclose(got, uv, atol=1e-12)
    np.testing.assert_array_equal(valid, [1, 0, 1, 0, 1, 0, 1, 0])
    # depth must exceed 0.1 m: on the axis at 0.05 m and behind the camera (pixel inside) are invalid
    near_behind = np.array([[0.0, 0.0, 0.05], [0.0, 0.0, 0.2], [1.0, 0.5, -2.0]])
    _, depth, valid = project_to_image(near_behind, K, np.eye(4), (w, h))
    np.testing.assert_array_equal(valid, [0, 1, 0])
    np.testing.assert_allclose(depth, [0.05, 0.2, -2.0])


def test_invert_transform_refuses_a_mirror():
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="determinant"):
        invert_transform(mirror)


def test_wrap_doppler_into_a_given_interval():
    np.testing.assert_allclose(wrap_doppler(np.array([-1.0, 5.0, 0.0, 3.9]), 4.0, low_mps=0.0), [3.0, 1.0, 0.0, 3.9])
    np.testing.assert_allclose(wrap_doppler(np.array([-1.0, 5.0, 2.0]), 4.0), [-1.0, 1.0, -2.0])


def test_norms_and_range_rates_keep_the_bits_of_numpys_row_reductions():
    """norms_m, and radial_velocity through it, give np.linalg.norm(axis=1)'s values to the bit
    (its sum order over the three columns), signed zeros, infinities, NaN and subnormals included."""
    import itertools

    special = [0.0, -0.0, 1.0, -3.5, 1e-320, 1e154, 1e308, np.inf, -np.inf, np.nan]
    rows = np.array(list(itertools.product(special, repeat=3)))
    rng = np.random.default_rng(0)
    rows = np.vstack([rows, rng.normal(size=(5000, 3)) * 10.0 ** rng.integers(-150, 150, (5000, 3))])
    with np.errstate(all="ignore"):
        assert norms_m(rows).tobytes() == np.linalg.norm(rows, axis=1).tobytes()
        finite = rows[np.isfinite(rows).all(axis=1)]
        ego, obj = np.array([3.0, -0.5, 0.1]), rng.normal(size=finite.shape)
        norm = np.linalg.norm(finite, axis=1)
        want = np.einsum("ij,ij->i", obj - ego, finite) / np.where(norm > 0, norm, 1.0)
        assert radial_velocity(finite, ego, obj).tobytes() == want.tobytes()
