"""Local range images around radar points for RSS-Net (METHOD.md, eqs. 18-21).

For a radar point p_i in {D} (x forward, y left, z up, metres), the lidar points l_j with
|l_j - p_i| < r_l are translated by -p_i and mapped to a w x h grid (default 128 x 32):

    u_j = floor(0.5 (1 - dy_j / r_l) w)              dy_j = y_j - y_i   (u grows to the right,
    v_j = floor((1 - (dz_j + r_l) / (2 r_l)) h)      dz_j = z_j - z_i    i.e. towards -y; v down)

clipped to [0, w - 1] x [0, h - 1]. Pixel value 127 + s_j * round(255 |l_j - p_i| / (2 r_l)), with
s_j = +1 when the lidar point is farther from the radar origin than p_i (|l_j| > |p_i|), else -1;
``round`` is half away from zero. Several points in one pixel are averaged.

Neighbours are taken strictly inside the ball (distance < r_l), so occupied pixels hold values in
[0, 254] (127 = "same distance from the radar as p_i"); empty pixels hold ``EMPTY = -1.0``, just
outside that range so that no average can equal it while the input scale stays compact.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from pipeline.frame import check_shape
from pipeline.geometry import norms_m, norms_xyz_m

EMPTY = -1.0
"""Value of pixels without lidar points (occupied pixels are in [0, 254])."""

INT32_KEY_PIXELS = 2**23
"""Below this many pixels in all (2047 images of 128 x 32), the pixel << 8 | value sort keys are
32-bit integers: they sort about twice as fast as 64-bit ones."""

_BRUTE_CHUNK = 8
"""Radar points per distance matrix in the brute-force version (bounds memory to 8 x M)."""


def _check_args(lidar_D: np.ndarray, points_D: np.ndarray, r_l: float,
                size_wh: Sequence[int]) -> tuple[np.ndarray, np.ndarray, int, int]:
    lidar = check_shape("lidar_D", np.asarray(lidar_D, dtype=np.float64), (None, 3))
    points = check_shape("points_D", np.asarray(points_D, dtype=np.float64), (None, 3))
    if not (np.isfinite(r_l) and r_l > 0):
        raise ValueError(f"range image: r_l must be positive, got {r_l}")
    w, h = (int(s) for s in size_wh)
    if w <= 0 or h <= 0:
        raise ValueError(f"range image: size_wh must be positive, got {tuple(size_wh)}")
    return lidar, points, w, h


def _render(lidar: np.ndarray, points: np.ndarray, owner: np.ndarray, neighbour: np.ndarray,
            r_l: float, w: int, h: int) -> np.ndarray:
    """Images (N, h, w) float32 from (owner point index, lidar index) pairs, one pair per neighbour,
    in any order: pixel values are averages of integers, so the sums are exact in any order."""
    n = points.shape[0]
    # per coordinate: 1-D gathers are faster than gathering (K, 3) rows
    dx, dy, dz = (lidar[:, k][neighbour] - points[:, k][owner] for k in range(3))
    dist = norms_xyz_m(dx, dy, dz)
    keep = dist < r_l
    if not keep.all():
        owner, neighbour, dy, dz, dist = owner[keep], neighbour[keep], dy[keep], dz[keep], dist[keep]
    u = np.clip(np.floor(0.5 * (1.0 - dy / r_l) * w), 0, w - 1).astype(np.int64)
    v = np.clip(np.floor((1.0 - (dz + r_l) / (2.0 * r_l)) * h), 0, h - 1).astype(np.int64)
    # |l_j| and |p_i| once per point rather than per pair
    farther = norms_m(lidar)[neighbour] > norms_m(points)[owner]
    level = np.floor(255.0 * dist / (2.0 * r_l) + 0.5).astype(np.int64)  # 0..127 inside the ball
    value = 127 + np.where(farther, level, -level)  # an integer in 0..254: 8 bits
    # Average per occupied pixel: sort keys (pixel << 8 | value), a plain sort of integers, and
    # sum the runs of equal pixels; O(K log K) in the pairs rather than O(N h w) accumulators.
    key = (((owner * h + v) * w + u) << 8) | value
    key = np.sort(key.astype(np.int32) if n * h * w < INT32_KEY_PIXELS else key)
    flat, value = key >> 8, key & 255
    starts = np.flatnonzero(np.r_[True, flat[1:] != flat[:-1]]) if flat.size else np.zeros(0, np.intp)
    image = np.full(n * h * w, EMPTY, dtype=np.float32)
    if starts.size:
        counts = np.diff(np.r_[starts, flat.size])
        image[flat[starts]] = np.add.reduceat(value, starts) / counts
    return image.reshape(n, h, w)


def lidar_tree(lidar_D: np.ndarray) -> cKDTree:
    """A cKDTree of lidar points (M, 3) in {D}, built for one query per frame: sliding-midpoint
    splits without compaction (quick to build) and 32-point leaves."""
    return cKDTree(lidar_D, leafsize=32, balanced_tree=False, compact_nodes=False)


def local_range_images(lidar_D: np.ndarray, points_D: np.ndarray, r_l: float,
                       size_wh: Sequence[int] = (128, 32), tree: cKDTree | None = None) -> np.ndarray:
    """Local range images (N, h, w) float32 of radar points ``points_D`` (N, 3) in {D}, metres.

    lidar_D: (M, 3) lidar points in {D}, metres. r_l: neighbourhood radius, metres.
    size_wh: (w, h) of each image. tree: a ``cKDTree`` of ``lidar_D`` to reuse (built here if None).
    Neighbours come from one ``sparse_distance_matrix`` between a tree of the points and the
    lidar's; pixel values as in the module docstring, ``EMPTY`` where no lidar point falls. Empty
    lidar or N = 0 are handled.
    """
    lidar, points, w, h = _check_args(lidar_D, points_D, r_l, size_wh)
    n = points.shape[0]
    if n == 0 or lidar.shape[0] == 0:
        return np.full((n, h, w), EMPTY, dtype=np.float32)
    tree = lidar_tree(lidar) if tree is None else tree
    if tree.n != lidar.shape[0]:  # its indices are rows of lidar_D (a tree of its finite points only is not)
        raise ValueError(f"range image: the tree holds {tree.n} points, lidar_D {lidar.shape[0]}: "
                         "not a tree of lidar_D")
    # all (point, lidar) pairs within r_l as arrays, in the trees' order (any order: see _render)
    pairs = cKDTree(points).sparse_distance_matrix(tree, r_l, output_type="ndarray")
    return _render(lidar, points, pairs["i"].astype(np.int64), pairs["j"].astype(np.int64), r_l, w, h)


def local_range_image(lidar_D: np.ndarray, point_D: np.ndarray, r_l: float,
                      size_wh: Sequence[int] = (128, 32), tree: cKDTree | None = None) -> np.ndarray:
    """Local range image (h, w) float32 of one radar point ``point_D`` (3,) in {D}, metres.

    Same conventions as ``local_range_images`` (eqs. 18-21; ``EMPTY`` for empty pixels).
    """
    point = check_shape("point_D", np.asarray(point_D, dtype=np.float64), (3,))
    return local_range_images(lidar_D, point[None, :], r_l, size_wh, tree)[0]


def local_range_images_brute(lidar_D: np.ndarray, points_D: np.ndarray, r_l: float,
                             size_wh: Sequence[int] = (128, 32)) -> np.ndarray:
    """Same result as ``local_range_images`` from the full point-to-lidar distance matrix.

    O(N M) distances (in chunks of a few radar points); the reference for tests and the benchmark.
    """
    lidar, points, w, h = _check_args(lidar_D, points_D, r_l, size_wh)
    owners, neighbours = [], []
    for start in range(0, points.shape[0], _BRUTE_CHUNK):
        block = points[start:start + _BRUTE_CHUNK]
        dist = np.linalg.norm(block[:, None, :] - lidar[None, :, :], axis=2)  # (n, M)
        i, j = np.nonzero(dist < r_l)
        owners.append(i + start)
        neighbours.append(j)
    owner = np.concatenate(owners) if owners else np.zeros(0, np.int64)
    neighbour = np.concatenate(neighbours) if neighbours else np.zeros(0, np.int64)
    return _render(lidar, points, owner.astype(np.int64), neighbour.astype(np.int64), r_l, w, h)
