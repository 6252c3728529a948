"""Lidar-point placement: put the synthetic radar points on lidar points instead of on camera rays.

The paper places each sampled pixel on its camera ray at a lidar range estimated in an angular
window, which lands on the wrong surface for most points (README, physics checks). Here the points
are lidar points themselves. Every lidar point y of the radar's field of view that projects into
the image (a *candidate*) gets an intensity lambda(y) >= 0 from PlaceNet: the expected number of
real radar points whose nearest candidate it is (learned from the training frames). With G the
heatmap's Gaussian blur and M the predicted map, a map sample x picks candidate y with probability
G(x - pix(y)) lambda(y) / Z(x), Z = G * splat(lambda); summed over x ~ M that is

    q(y) = lambda(y) * (G * (M / Z))(pix(y)),

two blurs of the map-sized image per frame. The map weight beta (``placement.map_weight``) raises
the second factor to the power beta: 1 (the above) lets the map decide each image region's share
of the points and PlaceNet only which candidates inside it; 0 ignores the map (q = lambda / sum
lambda). n points are then drawn from q without replacement (Gumbel top-k). With ``voxel_m`` > 0
(off by default: it lowered F1 on Astyx) they are spread over voxels of that side (random grid
offset): a voxel gets a second point only once every voxel holding a candidate has one.

Frames and units: points in {D} (x forward, y left, z up), metres; pixels (u right, v down) at the
working resolution; azimuth / elevation in radians. Pure numpy / scipy / OpenCV.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
from scipy.spatial import cKDTree

from pipeline.frame import Object3D, check_shape
from pipeline.geometry import cartesian_to_spherical, invert_transform, norms_m, project_to_image, radial_velocity

MIN_RANGE_M = 0.5
"""Candidates nearer than this to the radar are ignored (sensor housing, the ego vehicle)."""
NORMAL_NEIGHBOURS = 10
"""Lidar neighbours of a candidate whose covariance gives its surface normal."""
COLOUR_WINDOW_PX = 5
"""Side of the window of the local colour mean and standard deviation, working pixels."""
FEATURES = ("log_range", "z_m", "abs_range_rate", "abs_range_rate_clip3", "abs_range_rate_clip05", "on_object",
            "ego_speed", "azimuth", "elevation", "red", "green", "blue", "red_mean", "green_mean", "blue_mean",
            "red_std", "green_std", "blue_std", "cos_incidence", "planarity", "log_neighbour_dist", "normal_z2")
"""Columns of :func:`candidate_features`, in order."""
_RED, _COS_INCIDENCE = FEATURES.index("red"), FEATURES.index("cos_incidence")  # the colour and geometry blocks


def lidar_candidates(
    lidar_D: np.ndarray, K_w: np.ndarray, T_radar_cam: np.ndarray, image_wh: tuple[int, int],
    fov_az_deg: float, fov_el_deg: float, max_range_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Indices (C,) of the lidar points (M, 3) m in {D} that can carry a radar point: inside the
    radar's TOTAL fields of view ``fov_*_deg`` (symmetric about x), between MIN_RANGE_M and
    ``max_range_m``, projecting into the working image (size ``image_wh``, intrinsics ``K_w``);
    and their pixels (C, 2)."""
    points = check_shape("lidar_D", np.asarray(lidar_D, np.float64), (None, 3))
    rae = cartesian_to_spherical(points)
    with np.errstate(invalid="ignore"):
        ok = ((rae[:, 0] > MIN_RANGE_M) & (rae[:, 0] <= max_range_m)
              & (np.abs(rae[:, 1]) <= np.deg2rad(fov_az_deg) / 2) & (np.abs(rae[:, 2]) <= np.deg2rad(fov_el_deg) / 2))
    idx = np.flatnonzero(ok)
    uv, _, valid = project_to_image(points[idx], K_w, invert_transform(T_radar_cam), image_wh)
    return idx[valid], uv[valid]


def candidate_features(
    points_D: np.ndarray, uv: np.ndarray, image: np.ndarray, lidar_D: np.ndarray, ego_velocity_D: np.ndarray,
    labels: Sequence[Object3D] | np.ndarray, workers: int = 1, tree: cKDTree | None = None,
) -> np.ndarray:
    """PlaceNet inputs (C, len(FEATURES)) float32 of candidates ``points_D`` (C, 3) at pixels ``uv``.

    Per candidate: log range; height z; |range rate| from the ego velocity (3,) m/s and the
    velocity of the labelled box holding it (also clipped at 3 and 0.5 m/s: a radar's static
    filter acts near 0); whether it lies in a moving labelled box; the ego speed;
    azimuth, elevation; the working image's RGB (0..1) at its pixel and the mean and standard
    deviation over COLOUR_WINDOW_PX (material); from its NORMAL_NEIGHBOURS nearest points of the
    whole lidar cloud ``lidar_D``: |cos| of the angle between the surface normal and the line of
    sight, planarity (smallest / summed covariance eigenvalue), log distance of the farthest
    neighbour (lidar density) and the normal's squared z (ground or wall). ``workers``: threads of
    the neighbour query and the normals (the features do not depend on it). ``tree``: :func:`neighbour_tree` of
    ``lidar_D`` when the caller has it (a frame's range images can use the same tree).
    """
    from pipeline.synthesis import object_velocities_for_points

    pts = check_shape("points_D", np.asarray(points_D, np.float64), (None, 3))
    uv = check_shape("uv", np.asarray(uv, np.float64), (pts.shape[0], 2))
    if pts.shape[0] == 0:
        return np.zeros((0, len(FEATURES)), np.float32)
    rae = cartesian_to_spherical(pts)
    ego = check_shape("ego_velocity_D", np.asarray(ego_velocity_D, np.float64), (3,))
    v_obj = object_velocities_for_points(pts, labels)
    rate = np.abs(radial_velocity(pts, ego, v_obj))
    # each column written once into the float32 rows (the values column_stack(...).astype gave)
    out = np.empty((len(pts), len(FEATURES)), np.float32)
    for k, col in enumerate((np.log(rae[:, 0]), pts[:, 2], rate, np.minimum(rate, 3.0), np.minimum(rate, 0.5),
                             (v_obj[:, 0] != 0) | (v_obj[:, 1] != 0) | (v_obj[:, 2] != 0), np.linalg.norm(ego),
                             rae[:, 1], rae[:, 2])):
        out[:, k] = col
    out[:, _RED:_COS_INCIDENCE] = _colour_features(image, uv)
    tree = neighbour_tree(lidar_D) if tree is None else tree
    out[:, _COS_INCIDENCE:] = _geometry_features(pts, rae[:, 0], tree, workers)
    return out


def _colour_features(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(C, 9): RGB at the nearest pixel, window mean, window standard deviation (0..1)."""
    img = check_shape("image", np.asarray(image), (None, None, 3)).astype(np.float32) / 255.0
    h, w = img.shape[:2]
    k = (COLOUR_WINDOW_PX, COLOUR_WINDOW_PX)
    px = np.clip(np.rint(uv).astype(np.int64), 0, [w - 1, h - 1])
    at = px[:, 1] * w + px[:, 0]                                   # the pixels' rows of the (h w, 3) images
    rgb, mean, mean_sq = (a.reshape(-1, 3)[at] for a in (img, cv2.blur(img, k), cv2.blur(img * img, k)))
    std = np.sqrt(np.maximum(mean_sq - mean * mean, 0.0))          # at the pixels only
    return np.concatenate([rgb, mean, std], axis=1)


def neighbour_tree(lidar_D: np.ndarray) -> cKDTree:
    """The cKDTree of the finite lidar points (M, 3) in which :func:`candidate_features` finds the
    candidates' neighbours. Built unbalanced (median splits cost more than they save for one query
    of each candidate: 11.6 against 12.3 ms for a demo frame's 8,800, the same neighbours)."""
    cloud = np.asarray(lidar_D, np.float64).reshape(-1, 3)
    if not np.isfinite(cloud).all():  # the rows test only where needed (calibrate's lidar is finite)
        cloud = cloud[np.isfinite(cloud).all(axis=1)]
    return cKDTree(cloud, balanced_tree=False, compact_nodes=False)


def _geometry_features(points_D: np.ndarray, range_m: np.ndarray, tree: cKDTree, workers: int = 1) -> np.ndarray:
    """(C, 4): |cos incidence|, planarity, log neighbour distance, normal z^2 from the neighbours in
    ``tree`` (:func:`neighbour_tree`; zeros with too few lidar points). With ``workers`` > 1 the
    candidates are split into that many blocks, each on a thread of its own (the query and numpy's
    loops release the GIL); every row is computed alone, so the values do not depend on it."""
    if workers <= 1 or len(points_D) < workers * MIN_BLOCK_ROWS:
        return _geometry_rows(points_D, range_m, tree)
    ends = np.linspace(0, len(points_D), workers + 1).astype(int)
    with ThreadPoolExecutor(workers) as pool:
        blocks = pool.map(lambda s, e: _geometry_rows(points_D[s:e], range_m[s:e], tree), ends[:-1], ends[1:])
        return np.concatenate(list(blocks))


MIN_BLOCK_ROWS = 1000
"""Fewest candidates per thread of :func:`_geometry_features` (fewer: one thread does them all)."""


def _geometry_rows(points_D: np.ndarray, range_m: np.ndarray, tree: cKDTree) -> np.ndarray:
    """:func:`_geometry_features` of some candidates, on the calling thread."""
    cloud = tree.data
    k = min(NORMAL_NEIGHBOURS, len(cloud))
    if k < 3:
        return np.zeros((len(points_D), 4))
    dist, idx = tree.query(points_D, k=k)
    # neighbour-major (k, C, 3): each neighbour's rows are contiguous, so the sums and the centring run
    # over long rows; summed neighbour by neighbour as nb.mean(axis=1) sums (the same bits)
    nb = np.take(cloud, idx.T, axis=0)
    centre = nb[0].copy()
    for j in range(1, k):
        centre += nb[j]
    centre /= k
    nb -= centre
    nb = nb.transpose(1, 0, 2)                                     # (C, k, 3), a view
    cov = np.matmul(nb.transpose(0, 2, 1), nb)
    smallest, normal = smallest_eigenpair_sym3(cov)
    dot = normal * points_D
    cos_inc = np.abs(_sum3(dot[:, 0], dot[:, 1], dot[:, 2])) / np.maximum(range_m, 1e-9)
    trace = _sum3(cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2])                       # np.trace(cov, axis1=1, axis2=2)
    planarity = np.maximum(smallest, 0.0) / np.maximum(trace, 1e-12)
    return np.column_stack([cos_inc, planarity, np.log(dist[:, -1] + 1e-3), normal[:, 2] ** 2])


def _sum3(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """a + b + c as numpy's reduction over the rows of a (C, 3) array adds them, ((0 + a) + b) + c
    (the same bits, signed zeros included), column by column: a reduction over rows of three costs
    0.15 ms on a demo frame's candidates, the columns 0.03."""
    return ((0.0 + a) + b) + c


def smallest_eigenpair_sym3(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest eigenvalue (C,) and a unit eigenvector (C, 3) of symmetric matrices ``a`` (C, 3, 3)
    float64, in closed form (numpy's batched eigh spends about 1 us per 3x3 matrix, 8 ms per frame).

    Eigenvalues by the trigonometric solution of the characteristic cubic (absolute error about
    1e-8 of the trace); the vector is the largest cross product of two rows of a - lambda I. Where
    the smallest eigenvalue is (nearly) repeated, any unit vector of its eigenspace is returned (as
    eigh would); an isotropic matrix gives z.
    """
    a = check_shape("a", np.asarray(a, np.float64), (None, 3, 3))
    e = a.reshape(-1, 9).T.copy()                  # (9, C): row 3 i + j holds the entries (i, j), contiguous
    xx, yy, zz, xy, xz, yz = e[0], e[4], e[8], e[1], e[2], e[5]
    q = (xx + yy + zz) / 3
    dx, dy, dz = xx - q, yy - q, zz - q
    p = np.sqrt((dx * dx + dy * dy + dz * dz + 2 * (xy * xy + xz * xz + yz * yz)) / 6)
    safe = np.where(p > 0, p, 1.0)
    det = dx * (dy * dz - yz * yz) - xy * (xy * dz - yz * xz) + xz * (xy * yz - dy * xz)
    phi = np.arccos(np.clip(det / safe ** 3 / 2, -1.0, 1.0)) / 3
    smallest = np.where(p > 0, q + 2 * p * np.cos(phi + 2 * np.pi / 3), q)
    m = e - smallest * 0.0                         # a - lambda I, entry by entry (9, C): rows r0, r1, r2
    m[[0, 4, 8]] = e[[0, 4, 8]] - smallest
    r0, r1, r2 = m[0:3], m[3:6], m[6:9]
    crosses = np.stack([_cross(r0, r1), _cross(r0, r2), _cross(r1, r2)])          # (3 pairs, 3, C)
    # squared lengths summed as np.einsum sums three terms ((x^2 + z^2) + y^2): the bits it gave
    size = (crosses[:, 0] * crosses[:, 0] + crosses[:, 2] * crosses[:, 2]) + crosses[:, 1] * crosses[:, 1]
    best = np.argmax(size, axis=0)
    cols = np.arange(len(a))
    vec = crosses[best, :, cols]                                                   # (C, 3)
    scale = np.max(np.abs(m), axis=0)
    degenerate = size[best, cols] <= (1e-10 * scale * scale) ** 2
    if np.any(degenerate):  # a - lambda I has rank <= 1: its largest row spans the other eigenspace
        md = m[:, degenerate].T.reshape(-1, 3, 3)
        row = md[np.arange(len(md)), np.argmax(np.einsum("cij,cij->ci", md, md), axis=1)]
        other = np.cross(row, np.eye(3)[np.argmin(np.abs(row), axis=1)])
        vec[degenerate] = np.where(np.any(row != 0, axis=1)[:, None], other, [0.0, 0.0, 1.0])
    return smallest, vec / norms_m(vec)[:, None]                                  # np.linalg.norm(vec, axis=1)


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Cross products (3, C) of vectors given as rows (3, C): np.cross's formula and order."""
    return np.stack([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])


def radar_counts(candidates_D: np.ndarray, radar_D: np.ndarray, gate_m: float) -> np.ndarray:
    """PlaceNet target (C,) int: the real radar points (R, 3) whose nearest candidate (C, 3) is this
    one, counting only those within ``gate_m`` metres of it."""
    cand = check_shape("candidates_D", np.asarray(candidates_D, np.float64), (None, 3))
    radar = check_shape("radar_D", np.asarray(radar_D, np.float64), (None, 3))
    if len(cand) == 0 or len(radar) == 0:
        return np.zeros(len(cand), np.int64)
    dist, idx = cKDTree(cand).query(radar)
    return np.bincount(idx[dist <= gate_m], minlength=len(cand))


def placement_weights(
    prob_map: np.ndarray, uv: np.ndarray, intensity: np.ndarray, image_wh: tuple[int, int],
    sigma_px: tuple[float, float], map_weight: float = 1.0,
) -> np.ndarray:
    """q (C,) summing to 1 (zeros when nothing can be placed): the probability that a point goes to
    each candidate (module docstring). ``prob_map`` (H, W) >= 0 at any resolution; ``uv`` (C, 2)
    working pixels of an image ``image_wh``; ``intensity`` (C,) >= 0; ``sigma_px`` (u, v) the
    blur's standard deviations in working pixels; ``map_weight`` in [0, 1] the map's exponent
    beta (1: a map sample picks a candidate near it; 0: the map is ignored)."""
    m = check_shape("prob_map", np.asarray(prob_map, np.float64), (None, None))
    uv = check_shape("uv", np.asarray(uv, np.float64), (None, 2))
    lam = check_shape("intensity", np.asarray(intensity, np.float64), (uv.shape[0],))
    if not (np.all(np.isfinite(lam)) and np.all(lam >= 0)):
        raise ValueError("intensity: values must be finite and >= 0")
    if not 0.0 <= map_weight <= 1.0:
        raise ValueError(f"map_weight must be in [0, 1], got {map_weight}")
    if len(lam) == 0 or not lam.sum() > 0 or not m.sum() > 0:
        return np.zeros(len(lam))
    if map_weight == 0:  # the map's factor ** 0 is 1 everywhere: no blur needed
        return lam / lam.sum()
    (mh, mw), (w, h) = m.shape, image_wh
    # the map pixel holding each candidate: pixel k of the working image covers [k - 0.5, k + 0.5)
    # (pipeline.working), so a map of another size holds it at floor((u + 0.5) * mw / w)
    px = np.clip(np.floor((uv + 0.5) * [mw / w, mh / h]).astype(np.int64), 0, [mw - 1, mh - 1])
    sx, sy = sigma_px[0] * mw / w, sigma_px[1] * mh / h

    def blur(a32: np.ndarray) -> np.ndarray:  # in float32, a third of float64's time; terms are >= 0
        return cv2.GaussianBlur(a32, (0, 0), sigmaX=sx, sigmaY=sy, borderType=cv2.BORDER_CONSTANT)

    splat = np.bincount(px[:, 1] * mw + px[:, 0], lam, minlength=mh * mw).reshape(mh, mw)  # summed in order
    z = blur(splat.astype(np.float32))
    # the ratio in float64 (z's float32 values widened exactly), stored in float32 for the blur
    reached = z > np.float64(1e-12 * float(z.max()))  # map mass no candidate can take is lost, not blown up
    ratio = np.zeros(z.shape, np.float32)
    np.divide(m, z, out=ratio, where=reached, dtype=np.float64, casting="same_kind")
    q = lam * np.maximum(blur(ratio)[px[:, 1], px[:, 0]].astype(np.float64), 0.0) ** map_weight
    total = q.sum()
    return q / total if total > 0 else np.zeros(len(lam))


def choose_candidates(q: np.ndarray, points_D: np.ndarray, n: int, rng: np.random.Generator,
                      voxel_m: float) -> np.ndarray:
    """Indices of up to ``n`` candidates drawn from weights ``q`` (C,) without replacement, spread
    over cubes of side ``voxel_m`` (grid with a random offset; 0: no such limit), in draw order.

    Gumbel top-k: keys log q + Gumbel noise. Each cube's best key is drawn first, then each
    cube's second best, and so on, so a second point goes into a cube only once every cube that
    holds a candidate has one. Fewer than n come out only when fewer candidates have q > 0.
    """
    q = np.asarray(q, np.float64).ravel()
    points = check_shape("points_D", np.asarray(points_D, np.float64), (q.size, 3))
    if n < 0:
        raise ValueError(f"choose_candidates: n must be >= 0, got {n}")
    live = np.flatnonzero(q > 0)
    if n == 0 or live.size == 0:
        return np.zeros(0, np.int64)
    keys = np.log(q[live]) + rng.gumbel(size=live.size)
    if voxel_m <= 0:
        return live[smallest_first(-keys, n)]
    rank = np.zeros(live.size, np.int64)
    cell = np.floor(points[live] / voxel_m + rng.random(3)).astype(np.int64)
    order = np.lexsort((-keys, cell[:, 2], cell[:, 1], cell[:, 0]))
    new = np.r_[True, np.any(cell[order][1:] != cell[order][:-1], axis=1)]
    start = np.maximum.accumulate(np.where(new, np.arange(live.size), 0))
    rank[order] = np.arange(live.size) - start      # 0 for each cube's best key, 1 for the next...
    best = np.lexsort((-keys, rank))[:n]
    return live[best]


def smallest_first(values: np.ndarray, n: int) -> np.ndarray:
    """Indices of the ``n`` smallest of ``values`` (V,) float, in increasing order of value, ties
    (and NaNs, last) in index order: ``np.argsort(values, kind="stable")[:n]``, found by a partition
    and a sort of those n alone (O(V + n log n); a demo frame's 150 of 8,400 keys in 0.06 ms against
    0.6 ms)."""
    values = np.asarray(values)
    if n <= 0:
        return np.zeros(0, np.intp)
    if n >= values.size or np.isnan(values).any():
        return np.argsort(values, kind="stable")[:n]
    cut = np.partition(values, n - 1)[n - 1]        # the n-th smallest value
    below = np.flatnonzero(values < cut)
    ties = np.flatnonzero(values == cut)[:n - below.size]  # the n-th value's first occurrences
    chosen = np.concatenate([below, ties])
    return chosen[np.argsort(values[chosen], kind="stable")]


def place_on_lidar(
    prob_map: np.ndarray, n_hat: float, candidates_D: np.ndarray, uv: np.ndarray, intensity: np.ndarray, *,
    image_wh: tuple[int, int], sigma_px: tuple[float, float], voxel_m: float, ego_velocity_D: np.ndarray,
    labels: Sequence[Object3D] | np.ndarray, doppler_span_mps: float, rng: np.random.Generator,
    map_weight: float = 1.0,
) -> dict[str, np.ndarray | int]:
    """One frame's radar points except RSS, placed on lidar candidates (module docstring): the same
    keys as :func:`pipeline.synthesis.synthesize_frame` (Doppler as the range rate, wrapped into
    ``doppler_span_mps``). ``candidates_D`` (C, 3), ``uv`` (C, 2) and ``intensity`` (C,) describe
    the frame's candidates; ``n_hat`` is rounded. Points that cannot be placed (fewer candidates
    with q > 0 than points) are counted as without support."""
    from pipeline.synthesis import SUPPORT_DIRECT, doppler_for_points, object_velocities_for_points

    if not (np.isfinite(n_hat) and n_hat >= 0):
        raise ValueError(f"n_hat must be finite and >= 0, got {n_hat}")
    n = int(round(float(n_hat)))
    cand = check_shape("candidates_D", np.asarray(candidates_D, np.float64), (None, 3))
    q = placement_weights(prob_map, uv, intensity, image_wh, sigma_px, map_weight) if n else np.zeros(len(cand))
    idx = choose_candidates(q, cand, n, rng, voxel_m)
    points = cand[idx]
    doppler = doppler_for_points(points, ego_velocity_D, object_velocities_for_points(points, labels), 1,
                                 doppler_span_mps)
    return {"points_D": points.astype(np.float32), "rae": cartesian_to_spherical(points).astype(np.float32),
            "doppler": doppler.astype(np.float32), "uv": np.asarray(uv, np.float32).reshape(-1, 2)[idx],
            "support": np.full(len(idx), SUPPORT_DIRECT, np.int8), "n_requested": n,
            "n_no_support": n - len(idx), "n_out_of_fov": 0, "n_beyond_range": 0, "n_widened": 0}
