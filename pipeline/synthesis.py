"""4D signal generation at inference (METHOD.md, Section IV-B): sample pixels from the predicted
map, back-project them, estimate their range from lidar, place them on the camera ray and give
them a Doppler value. RSS is not computed here (RSS-Net runs batched in the stage).

Conventions: radar frame {D} x forward / y left / z up; azimuth atan2(y, x) positive left;
elevation asin(z / r) positive up; pixels (u, v) with u right, v down, integer values at pixel
centres. Doppler outputs follow the simulated radar's convention: ``doppler_sign`` times the range
rate (range rate positive receding), wrapped into ``doppler_span_mps`` when that is > 0.
Pure numpy / scipy.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from pipeline.config import CHOICES
from pipeline.frame import LABEL_COLUMNS, Object3D, box_rotations, check_shape, label_rows, to_box_frame
from pipeline.geometry import cartesian_to_spherical, norms_m, pixel_rays_D, radial_velocity, wrap_doppler

ESTIMATORS = CHOICES["synth.range_estimator"]
"""Range estimators over the angular window: 'mean' is the paper's rule (eqs. 13-15)."""
NO_SUPPORT_RULES = CHOICES["synth.no_support"]
"""What to do when no lidar point lies in the window."""
MAX_WIDENINGS = 4
"""'widen' doubles the window at most this many times (so up to 16x the resolution)."""
SUPPORT_NONE, SUPPORT_DIRECT, SUPPORT_WIDENED = 0, 1, 2
"""Values of the per-sample support flag returned by ``estimate_range``."""
NEAREST_CANDIDATES = 16
"""Nearest lidar points per sample from which 'nearest' settles most samples without the passes."""
KEPT, DROP_NO_SUPPORT, DROP_OUT_OF_FOV, DROP_BEYOND_RANGE = 0, 1, 2, 3
"""Fate of a drawn sample: kept, or the first reason it was dropped."""
REFILL_OVERSAMPLE = 1.5
"""A refill round draws this many times the samples the keep rate so far says it needs (and keeps
the first ones placed), so that one round nearly always completes the frame."""
REFILL_MAX_FACTOR = 8
"""A refill round draws at most this many times the missing samples."""


# --------------------------------------------------------------------------- pixel sampling


SAMPLINGS = CHOICES["synth.sampling"]
"""How ``sample_pixels`` draws: independent draws (the paper) or one stratified (systematic) draw."""


def sample_pixels(prob_map: np.ndarray, n: int, rng: np.random.Generator, method: str = "iid") -> np.ndarray:
    """Draw ``n`` continuous pixel positions from a (H, W) probability map (eq. 11).

    Inverse-transform sampling with replacement (cumulative sum + searchsorted) over the map's
    non-negative weights (need not sum to 1), then a uniform jitter in [-0.5, 0.5) around the
    chosen pixel centre. ``method`` 'iid' draws n independent uniforms (the paper); 'systematic'
    uses (U + k) / n for k = 0..n-1 with one uniform U (systematic resampling): each sample is still
    distributed as the map, but any stretch of the row-major pixel order with mass q receives
    floor(n q) or ceil(n q) samples instead of a binomial count; the samples are returned in random
    order. Returns uv (n, 2) float64, u = column, v = row.
    Raises ValueError for a map with negative or non-finite values, zero total mass (when n > 0)
    or an unknown method.
    """
    return _draw_pixels(_map_cdf(prob_map, n), n, rng, method)


def _map_cdf(prob_map: np.ndarray, n: int) -> tuple[np.ndarray, int, int]:
    """(cumulative weights (H*W,), last pixel with positive weight, W) of a map to draw ``n``
    samples from, with the checks of :func:`sample_pixels` (values and mass only when n > 0)."""
    weights = check_shape("prob_map", np.asarray(prob_map, dtype=np.float64), (None, None))
    if n < 0:
        raise ValueError(f"sample_pixels: n must be >= 0, got {n}")
    if n == 0:
        return np.zeros(0), -1, weights.shape[1]
    if not np.all(np.isfinite(weights)) or weights.min() < 0:
        raise ValueError("prob_map: values must be finite and non-negative")
    cdf = np.cumsum(weights.ravel())
    if cdf[-1] <= 0:
        raise ValueError("prob_map: total probability mass is zero")
    return cdf, int(np.flatnonzero(weights.ravel() > 0)[-1]), weights.shape[1]


def _draw_pixels(map_cdf: tuple[np.ndarray, int, int], n: int, rng: np.random.Generator, method: str) -> np.ndarray:
    """``n`` pixel positions (n, 2) from a map prepared by :func:`_map_cdf`."""
    if method not in SAMPLINGS:
        raise ValueError(f"sample_pixels: method {method!r} unknown; choose one of {SAMPLINGS}")
    if n == 0:
        return np.zeros((0, 2), np.float64)
    cdf, last_positive, width = map_cdf
    u = rng.random(n) if method == "iid" else rng.permutation((rng.random() + np.arange(n)) / n)
    flat = np.searchsorted(cdf, u * cdf[-1], side="right")
    flat = np.minimum(flat, last_positive)  # guards the u * total == total rounding case
    rows, cols = np.divmod(flat, width)
    jitter = rng.random((n, 2)) - 0.5
    return np.stack([cols, rows], axis=1).astype(np.float64) + jitter


# --------------------------------------------------------------------------- range from lidar


def _wrap_angle(angle_rad: np.ndarray) -> np.ndarray:
    """Wrap angles into [-pi, pi)."""
    return np.mod(angle_rad + np.pi, 2.0 * np.pi) - np.pi


def _check_estimator(estimator: str, no_support: str) -> None:
    if estimator not in ESTIMATORS:
        raise ValueError(f"range estimator {estimator!r} unknown; choose one of {ESTIMATORS}")
    if no_support not in NO_SUPPORT_RULES:
        raise ValueError(f"no_support rule {no_support!r} unknown; choose one of {NO_SUPPORT_RULES}")


def _group_statistic(
    sample_idx: np.ndarray, lidar_idx: np.ndarray, ang_dist2: np.ndarray | None, range_m: np.ndarray,
    n: int, estimator: str,
) -> np.ndarray:
    """Per-sample statistic of the lidar ranges of (sample, lidar) pairs; NaN for empty samples.

    ``sample_idx`` (P,) sample of each pair, in non-decreasing order (pairs grouped by sample);
    ``lidar_idx`` (P,) its lidar point; ``ang_dist2`` (P,) the key 'nearest' minimises (the
    squared angular distance, rad^2; the oracle passes |dr| instead), needed by 'nearest' only
    (ties: the lower lidar index). O(P) except 'median' (one sort).
    """
    out = np.full(n, np.nan)
    if sample_idx.size == 0:
        return out
    r = range_m[lidar_idx]
    starts = np.flatnonzero(np.r_[True, sample_idx[1:] != sample_idx[:-1]])
    counts = np.diff(np.r_[starts, sample_idx.size])
    owners = sample_idx[starts]
    if estimator == "mean":
        out[owners] = np.add.reduceat(r, starts) / counts
    elif estimator == "min":
        out[owners] = np.minimum.reduceat(r, starts)
    elif estimator == "nearest":
        group_min = np.repeat(np.minimum.reduceat(ang_dist2, starts), counts)
        candidate = np.where(ang_dist2 == group_min, lidar_idx, np.iinfo(np.intp).max)
        out[owners] = range_m[np.minimum.reduceat(candidate, starts)]
    else:  # median: sort ranges within each group (one argsort on group offset + range)
        span = float(r.max() - r.min()) + 1.0
        r_sorted = r[np.argsort(sample_idx * span + (r - r.min()), kind="stable")]
        out[owners] = 0.5 * (r_sorted[starts + (counts - 1) // 2] + r_sorted[starts + counts // 2])
    return out


class LidarAngularIndex:
    """Lidar points of one frame indexed by angle for the range step (eqs. 13-15).

    Built from ``lidar_D`` (M, 3) metres in {D}; points at the origin or non-finite are ignored.
    The window of a sample at (theta, phi) holds the lidar points with |wrap(theta - theta_j)| <=
    delta_az and |phi - phi_j| <= delta_el (azimuth wraps at +/- pi). A cKDTree on (azimuth,
    elevation * delta_az / delta_el) makes the window a square of half side delta_az, queried with
    ``query_ball_point(p=inf)``; one tree per aspect ratio, built on first use. Points near the
    azimuth seam are indexed twice (shifted by -/+ 2 pi) so windows across it are complete.
    """

    def __init__(self, lidar_D: np.ndarray) -> None:
        points = check_shape("lidar_D", np.asarray(lidar_D, dtype=np.float64), (None, 3))
        rae = cartesian_to_spherical(points)
        keep = np.isfinite(rae[:, 0]) & (rae[:, 0] > 0)  # a non-finite coordinate gives a non-finite range
        self.range_m: np.ndarray = rae[keep, 0]
        """(M',) ranges of the kept lidar points, metres."""
        self.azimuth_rad: np.ndarray = rae[keep, 1]
        self.elevation_rad: np.ndarray = rae[keep, 2]
        self._trees: dict[tuple[float, float], tuple[cKDTree, np.ndarray]] = {}

    def __len__(self) -> int:
        return int(self.range_m.size)

    def _tree(self, el_scale: float, seam_margin_rad: float) -> tuple[cKDTree, np.ndarray]:
        """Tree over (azimuth, elevation * el_scale) with seam copies, and the copies' lidar index."""
        key = (el_scale, seam_margin_rad)
        if key not in self._trees:
            az, el = self.azimuth_rad, self.elevation_rad * el_scale
            seam = np.flatnonzero(np.abs(az) >= np.pi - seam_margin_rad)
            az_all = np.concatenate([az, np.where(az[seam] > 0, az[seam] - 2.0 * np.pi, az[seam] + 2.0 * np.pi)])
            el_all = np.concatenate([el, el[seam]])
            owner = np.concatenate([np.arange(az.size), seam])
            tree = cKDTree(np.stack([az_all, el_all], axis=1), balanced_tree=False, compact_nodes=False)  # quick build
            self._trees[key] = (tree, owner)
        return self._trees[key]

    def _pairs(
        self, az: np.ndarray, el: np.ndarray, half_az: float, half_el: float, max_half_az: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """(sample, lidar) index pairs of every lidar point in each sample's window."""
        el_scale = half_az / half_el
        tree, owner = self._tree(el_scale, min(np.pi, max_half_az))
        hits = tree.query_ball_point(
            np.stack([az, el * el_scale], axis=1), r=half_az, p=np.inf, return_sorted=False
        )
        counts = np.fromiter((len(h) for h in hits), dtype=np.intp, count=len(hits))
        flat = np.fromiter(itertools.chain.from_iterable(hits), dtype=np.intp, count=int(counts.sum()))
        sample_idx, lidar_idx = np.repeat(np.arange(az.size), counts), owner[flat]  # grouped by sample
        if half_az >= np.pi and sample_idx.size:  # a point and its seam copy can both match
            pairs = np.unique(np.stack([sample_idx, lidar_idx], axis=1), axis=0)
            sample_idx, lidar_idx = pairs[:, 0], pairs[:, 1]
        return sample_idx, lidar_idx

    def estimate_range(
        self, az_rad: np.ndarray, el_rad: np.ndarray, delta_az_rad: float, delta_el_rad: float,
        estimator: str = "mean", no_support: str = "widen",
    ) -> tuple[np.ndarray, np.ndarray]:
        """Range of each sample direction from the lidar points in its angular window.

        ``az_rad``, ``el_rad`` (n,): sample directions in {D}. ``delta_*_rad``: half sides of the
        window (the radar's angular resolutions delta_1, delta_2). ``estimator``: 'mean' (the
        paper), 'nearest' (range of the angularly nearest point, Euclidean in (az, el) radians),
        'median' or 'min' over the window. ``no_support``: 'widen' doubles both half sides up to
        MAX_WIDENINGS times for samples with an empty window; 'drop' gives up at once.
        Returns ``range_m`` (n,) float64 (NaN without support) and ``support`` (n,) int8
        (SUPPORT_NONE / SUPPORT_DIRECT / SUPPORT_WIDENED).
        """
        _check_estimator(estimator, no_support)
        az, el = _check_directions(az_rad, el_rad)
        _check_deltas(delta_az_rad, delta_el_rad)
        n = az.size
        range_m, support = np.full(n, np.nan), np.zeros(n, np.int8)
        if n == 0 or len(self) == 0:
            return range_m, support
        passes = MAX_WIDENINGS + 1 if no_support == "widen" else 1
        max_half_az = delta_az_rad * 2 ** (passes - 1)
        todo = np.arange(n)
        if estimator == "nearest":
            todo = self._nearest_certified(az, el, delta_az_rad, delta_el_rad, passes, range_m, support)
        for k in range(passes):
            half_az, half_el = delta_az_rad * 2**k, delta_el_rad * 2**k
            s_idx, l_idx = self._pairs(az[todo], el[todo], half_az, half_el, max_half_az)
            d2 = None
            if estimator == "nearest":
                d2 = (_wrap_angle(az[todo][s_idx] - self.azimuth_rad[l_idx]) ** 2
                      + (el[todo][s_idx] - self.elevation_rad[l_idx]) ** 2)
            values = _group_statistic(s_idx, l_idx, d2, self.range_m, todo.size, estimator)
            found = np.isfinite(values)
            range_m[todo[found]] = values[found]
            support[todo[found]] = SUPPORT_DIRECT if k == 0 else SUPPORT_WIDENED
            todo = todo[~found]
            if todo.size == 0:
                break
        return range_m, support

    def _nearest_certified(
        self, az: np.ndarray, el: np.ndarray, delta_az: float, delta_el: float, passes: int,
        range_m: np.ndarray, support: np.ndarray,
    ) -> np.ndarray:
        """'nearest' from the NEAREST_CANDIDATES angularly nearest lidar points of each sample
        (one k-nearest-neighbour query) instead of gathering every point of its windows.

        The answer of the window passes is the point nearest the sample (Euclidean in (az, el)
        radians; ties: lower lidar index) within its first non-empty window m (half sides
        2^m delta). Every lidar point nearer than the last candidate, d_K, is a candidate, and
        every point that can lie in a window is in the tree at its wrapped distance (seam copies).
        So with m the first window holding a candidate, the candidates give the passes' answer
        when no point can hide in window m - 1 (its half diagonal below d_K) and the best
        candidate of window m is nearer than d_K; with no candidate in any window and the largest
        window's half diagonal below d_K there is no support. Where window m - 1 could hide a
        point, the passes' own tree counts its points (no pairs): none, and the candidates decide.
        Samples with a candidate within 1e-9 of a window border, or a margin under 1e-9, are left
        to the passes. Fills ``range_m`` and ``support`` of the settled samples; returns the
        indices of the others.
        """
        half_diag = float(np.hypot(delta_az, delta_el))
        reach = half_diag * 2 ** (passes - 1)  # half diagonal of the largest window
        seam_margin = min(np.pi, delta_az * 2 ** (passes - 1))  # as the passes' trees
        tree, owner = self._tree(1.0, seam_margin)
        k = min(NEAREST_CANDIDATES, tree.n)
        dist, idx = tree.query(np.stack([az, el], axis=1), k=[*range(1, k + 1)],
                               distance_upper_bound=reach * (1 + 1e-6))  # (n, k), inf beyond
        valid = np.isfinite(dist)
        j = owner[np.where(valid, idx, 0)]  # lidar index of each candidate
        d_az, d_el = _wrap_angle(az[:, None] - self.azimuth_rad[j]), el[:, None] - self.elevation_rad[j]
        with np.errstate(divide="ignore", invalid="ignore"):  # a candidate on the sample: log2(0)
            log2_ratio = np.log2(np.maximum(np.abs(d_az) / delta_az, np.abs(d_el) / delta_el))
            on_power_of_two = np.abs(log2_ratio - np.rint(log2_ratio)) <= 1e-9
        border = valid & (log2_ratio > -0.5) & (log2_ratio < passes) & on_power_of_two
        window = np.where(valid, np.maximum(0.0, np.ceil(log2_ratio)), np.inf)  # first window holding it
        first = window.min(axis=1)  # the sample's first non-empty window, if the rest hold
        d_k = np.where(valid[:, -1], dist[:, -1], reach * (1 + 1e-6))  # every nearer point is a candidate
        d2 = d_az**2 + d_el**2  # the passes' metric
        in_first = window == first[:, None]
        best = np.where(in_first, d2, np.inf).min(axis=1)
        choice = np.where(in_first & (d2 == best[:, None]), j, np.iinfo(np.intp).max).min(axis=1)
        # the answer if window first - 1 (the largest window when no candidate is in one) is empty:
        decided = ~border.any(axis=1) & ((first >= passes) | (np.sqrt(best) < d_k * (1 - 1e-9)))
        level = np.minimum(first, passes) - 1.0  # that window
        shut = d_k > half_diag * np.exp2(level) * (first > 0) * (1 + 1e-9)  # a hidden point would be a candidate
        ask = np.flatnonzero(decided & ~shut & (first > 0))
        if ask.size:  # else count that window's points in the passes' own tree (no pairs)
            el_scale = delta_az / delta_el
            tree_w, _ = self._tree(el_scale, seam_margin)
            inside = tree_w.query_ball_point(np.stack([az[ask], el[ask] * el_scale], axis=1),
                                             r=delta_az * np.exp2(level[ask]), p=np.inf, return_length=True)
            shut[ask[inside == 0]] = True
        settled = decided & shut
        hit = settled & (first < passes)
        range_m[hit] = self.range_m[choice[hit]]
        support[hit] = np.where(first[hit] == 0, SUPPORT_DIRECT, SUPPORT_WIDENED)
        return np.flatnonzero(~settled)

    def closest_range_in_window(
        self, az_rad: np.ndarray, el_rad: np.ndarray, range_m: np.ndarray, delta_az_rad: float,
        delta_el_rad: float,
    ) -> np.ndarray:
        """Range (n,) of the lidar point in each direction's window whose range is closest to
        ``range_m`` (n,) m; NaN where the window is empty (no widening).

        An oracle, for the physics checks: it needs the measured range and shows how often *some*
        lidar point of the window is at the radar's range, i.e. what a better choice than
        ``estimate_range``'s rules could reach.
        """
        az, el = _check_directions(az_rad, el_rad)
        _check_deltas(delta_az_rad, delta_el_rad)
        target = np.asarray(range_m, np.float64).ravel()
        if target.size != az.size:
            raise ValueError(f"range_m has {target.size} values for {az.size} directions")
        if az.size == 0 or len(self) == 0:
            return np.full(az.size, np.nan)
        s_idx, l_idx = self._pairs(az, el, delta_az_rad, delta_el_rad, delta_az_rad)
        abs_dr = np.abs(self.range_m[l_idx] - target[s_idx])
        return _group_statistic(s_idx, l_idx, abs_dr, self.range_m, az.size, "nearest")

    def estimate_range_bruteforce(
        self, az_rad: np.ndarray, el_rad: np.ndarray, delta_az_rad: float, delta_el_rad: float,
        estimator: str = "mean", no_support: str = "widen", chunk: int = 64,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Reference for ``estimate_range``: an n x M scan in chunks of ``chunk`` samples (tests,
        benchmark). Same arguments, same results."""
        _check_estimator(estimator, no_support)
        az, el = _check_directions(az_rad, el_rad)
        _check_deltas(delta_az_rad, delta_el_rad)
        n = az.size
        range_m, support = np.full(n, np.nan), np.zeros(n, np.int8)
        passes = MAX_WIDENINGS + 1 if no_support == "widen" else 1
        for start in range(0, n, chunk):
            sl = slice(start, min(n, start + chunk))
            daz = np.abs(_wrap_angle(az[sl, None] - self.azimuth_rad[None, :]))      # (c, M)
            dl = np.abs(el[sl, None] - self.elevation_rad[None, :])
            for k in range(passes):
                inside = (daz <= delta_az_rad * 2**k) & (dl <= delta_el_rad * 2**k)
                rows = np.isnan(range_m[sl]) & inside.any(axis=1)
                if not rows.any():
                    continue
                values = _window_values(self.range_m, daz[rows] ** 2 + dl[rows] ** 2, inside[rows], estimator)
                range_m[start + np.flatnonzero(rows)] = values
                support[start + np.flatnonzero(rows)] = SUPPORT_DIRECT if k == 0 else SUPPORT_WIDENED
        return range_m, support


def _window_values(range_m: np.ndarray, d2: np.ndarray, inside: np.ndarray, estimator: str) -> np.ndarray:
    """Statistic of each row's window (brute-force reference); ``d2``, ``inside`` (c, M), every
    row non-empty."""
    r = np.broadcast_to(range_m, inside.shape)
    if estimator == "mean":
        return np.where(inside, r, 0.0).sum(axis=1) / inside.sum(axis=1)
    if estimator == "min":
        return np.where(inside, r, np.inf).min(axis=1)
    if estimator == "median":
        return np.nanmedian(np.where(inside, r, np.nan), axis=1)
    return range_m[np.argmin(np.where(inside, d2, np.inf), axis=1)]  # first index wins ties


def _check_directions(az_rad: np.ndarray, el_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    az = np.asarray(az_rad, dtype=np.float64).ravel()
    el = check_shape("el_rad", np.asarray(el_rad, dtype=np.float64).ravel(), (az.size,))
    if not (np.all(np.isfinite(az)) and np.all(np.isfinite(el))):
        raise ValueError("estimate_range: sample angles must be finite")
    return az, el


def _check_deltas(delta_az_rad: float, delta_el_rad: float) -> None:
    if not (delta_az_rad > 0 and delta_el_rad > 0):
        raise ValueError(f"angular window half sides must be > 0, got {delta_az_rad}, {delta_el_rad}")


# --------------------------------------------------------------------------- placement, Doppler


def place_on_camera_ray(
    uv: np.ndarray, range_m: np.ndarray, K: np.ndarray, T_radar_cam: np.ndarray,
    rays_D: np.ndarray | None = None,
) -> np.ndarray:
    """Points (n, 3) in {D} on the camera rays of pixels ``uv`` (n, 2) at ``range_m`` (n,) from the
    RADAR origin (the method's improvement over eq. 12, which ignores the camera-radar offset).

    With c the camera centre in {D} and d the unit ray, solves |c + t d| = r for the larger root
    t = -(c.d) + sqrt((c.d)^2 - |c|^2 + r^2). Fallback, where that root is not real or not
    positive (only possible when r < |c|, i.e. closer to the radar than the camera is): t = r,
    the point at distance r from the camera along the ray. NaN ranges give NaN points.
    ``K`` (3, 3) intrinsics of the image ``uv`` refers to; ``T_radar_cam`` (4, 4). ``rays_D``:
    ``pixel_rays_D(uv, K, T_radar_cam)`` when the caller has it already.
    """
    uv = check_shape("uv", np.asarray(uv, dtype=np.float64), (None, 2))
    r = check_shape("range_m", np.asarray(range_m, dtype=np.float64), (uv.shape[0],))
    if uv.shape[0] == 0:
        return np.zeros((0, 3), np.float64)
    d = pixel_rays_D(uv, K, T_radar_cam) if rays_D is None else check_shape("rays_D", rays_D, (uv.shape[0], 3))
    c = np.asarray(T_radar_cam, dtype=np.float64)[:3, 3]
    cd = d @ c
    disc = cd**2 - c @ c + r**2
    with np.errstate(invalid="ignore"):
        t = -cd + np.sqrt(np.where(disc >= 0, disc, np.nan))
    t = np.where(np.isfinite(t) & (t > 0), t, r)
    return c[None, :] + t[:, None] * d


BOX_COLUMNS = LABEL_COLUMNS.index("vz") + 1
"""Leading columns of a label row (pipeline.frame.LABEL_COLUMNS) that describe the moving box:
centre, size, yaw, pitch, roll, velocity; the track id is not needed."""
_YAW, _VX = LABEL_COLUMNS.index("yaw"), LABEL_COLUMNS.index("vx")


def label_boxes(labels: Sequence[Object3D] | np.ndarray) -> np.ndarray:
    """(L, BOX_COLUMNS) float64 rows of ``labels``: Object3D objects, or label rows (L, >= BOX_COLUMNS)
    as calibrate stores them (taken as they are, without building objects)."""
    rows = np.asarray(labels, np.float64) if isinstance(labels, np.ndarray) else label_rows(labels)
    if rows.size == 0:
        return np.zeros((0, BOX_COLUMNS))
    if rows.ndim != 2 or rows.shape[1] < BOX_COLUMNS:
        raise ValueError(f"label rows: need shape (L, >= {BOX_COLUMNS}) ({', '.join(LABEL_COLUMNS[:BOX_COLUMNS])}), "
                         f"got {rows.shape}")
    return rows[:, :BOX_COLUMNS]


def object_velocities_for_points(
    points_D: np.ndarray, labels: Sequence[Object3D] | np.ndarray, margin_m: float = 0.3, unknown: float = 0.0
) -> np.ndarray:
    """Velocity over ground (n, 3) m/s in {D} of the labelled object containing each point.

    ``labels``: Object3D objects or calibrate's label rows (see ``label_boxes``). A point belongs
    to a box when it lies inside the oriented box (centre, size l/w/h, rotation from yaw, pitch and
    roll: pipeline.frame.box_rotations) grown by ``margin_m`` on every face; where boxes overlap,
    the one with the nearest centre wins. Points in no box (the static world) get 0. Labels whose
    velocity is unknown (NaN) give their points ``unknown`` (0: static, so a dataset without
    velocities gives a static-world Doppler for its objects; NaN marks them as not known).
    """
    points = check_shape("points_D", np.asarray(points_D, dtype=np.float64), (None, 3))
    out = np.zeros((points.shape[0], 3))
    boxes = label_boxes(labels)
    if points.shape[0] == 0 or len(boxes) == 0:
        return out
    centres, half = boxes[:, 0:3], boxes[:, 3:6] / 2 + margin_m                        # (L, 3), (L, 3)
    rot = box_rotations(boxes[:, _YAW], boxes[:, _YAW + 1], boxes[:, _YAW + 2])      # (L, 3, 3) box -> {D}
    vel = np.where(np.isnan(boxes[:, _VX:_VX + 3]), unknown, boxes[:, _VX:_VX + 3])
    # A point inside box l lies within its x extent |dx| <= sum_k |R[0, k]| half_k (and its y extent
    # likewise): each box tests only the points of that slice of the points sorted by x whose y is
    # near, all boxes' (box, point) pairs at once. Each pair is tested alone and the winners are
    # sorted by (point, distance, box) below, so the pairs' order, and the sort's among equal x,
    # changes nothing (an unstable sort: 0.25 against 0.6 ms for a demo frame's 8,400 candidates)
    order = np.argsort(points[:, 0])
    xs = points[order, 0]
    reach = np.einsum("lik,lk->li", np.abs(rot[:, :2, :]), half) * (1 + 1e-9) + 1e-9    # (L, 2): slack for rounding
    lo = np.searchsorted(xs, centres[:, 0] - reach[:, 0], side="left")
    hi = np.searchsorted(xs, centres[:, 0] + reach[:, 0], side="right")
    counts = np.maximum(hi - lo, 0)
    box_of = np.repeat(np.arange(len(boxes)), counts)
    point_of = order[np.arange(len(box_of)) + np.repeat(lo - (np.cumsum(counts) - counts), counts)]
    near = np.abs(points[point_of, 1] - centres[box_of, 1]) <= reach[box_of, 1]
    box_of, point_of = box_of[near], point_of[near]
    rel = points[point_of] - centres[box_of]                                             # (P, 3)
    local, h = np.abs(to_box_frame(rel, rot[box_of])), half[box_of]                      # (P, 3) each
    inside = (local[:, 0] <= h[:, 0]) & (local[:, 1] <= h[:, 1]) & (local[:, 2] <= h[:, 2])
    if not inside.any():  # no point inside any box
        return out
    box_of, point_of, dist_of = box_of[inside], point_of[inside], norms_m(rel[inside])
    # where boxes overlap the nearest centre wins (the lower box index on a tie)
    pick = np.lexsort((box_of, dist_of, point_of))
    first = np.r_[True, point_of[pick][1:] != point_of[pick][:-1]]
    out[point_of[pick][first]] = vel[box_of[pick][first]]
    return out


def on_objects_of_unknown_velocity(points_D: np.ndarray, labels: Sequence[Object3D] | np.ndarray) -> np.ndarray:
    """(N,) bool: the points (N, 3) m in {D} on a labelled object whose velocity is unknown (NaN),
    found as :func:`object_velocities_for_points` finds them: their Doppler is a static object's."""
    return np.isnan(object_velocities_for_points(points_D, labels, unknown=np.nan)[:, 0])


def doppler_for_points(
    points_D: np.ndarray, ego_velocity_D: np.ndarray, object_velocity_D: np.ndarray | None,
    doppler_sign: int, span_mps: float,
) -> np.ndarray:
    """Doppler (n,) m/s of points (n, 3) in {D} in the simulated radar's convention (eq. 16).

    Range rate ((v_O - v_D) . d) / |d| along the line of sight d from the radar origin, times
    ``doppler_sign`` (+1: range rate as VoD; -1: positive approaching as Astyx), wrapped into
    [-span/2, span/2) when ``span_mps`` > 0 (aliasing radar). ``object_velocity_D`` (n, 3) or None
    for the static world.
    """
    if doppler_sign not in (1, -1):
        raise ValueError(f"doppler_sign must be +1 or -1, got {doppler_sign}")
    points = check_shape("points_D", np.asarray(points_D, dtype=np.float64), (None, 3))
    ego = check_shape("ego_velocity_D", np.asarray(ego_velocity_D, dtype=np.float64), (3,))
    range_rate = radial_velocity(points, ego, object_velocity_D)
    return wrap_doppler(doppler_sign * range_rate, span_mps)


# --------------------------------------------------------------------------- one frame


def _place_samples(
    uv: np.ndarray, K_w: np.ndarray, T_radar_cam: np.ndarray, index: LidarAngularIndex, *,
    az_res_deg: float, el_res_deg: float, fov_az_deg: float, fov_el_deg: float, max_range_m: float,
    estimator: str, no_support: str,
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Steps 2-3 of :func:`synthesize_frame` for pixels ``uv`` (n, 2): the kept samples (points_D,
    rae, uv, support; in draw order) and the fate (n,) int8 of every sample: KEPT, or the first
    reason it was dropped (DROP_NO_SUPPORT, DROP_OUT_OF_FOV, DROP_BEYOND_RANGE)."""
    rays = pixel_rays_D(uv, K_w, T_radar_cam)
    ray_rae = cartesian_to_spherical(rays)
    range_m, support = index.estimate_range(
        ray_rae[:, 1], ray_rae[:, 2], np.deg2rad(az_res_deg), np.deg2rad(el_res_deg),
        estimator=estimator, no_support=no_support,
    )
    points = place_on_camera_ray(uv, range_m, K_w, T_radar_cam, rays)
    rae = cartesian_to_spherical(np.nan_to_num(points))
    in_fov = (np.abs(rae[:, 1]) <= np.deg2rad(fov_az_deg) / 2) & (np.abs(rae[:, 2]) <= np.deg2rad(fov_el_deg) / 2)
    in_range = (rae[:, 0] > 0) & (rae[:, 0] <= max_range_m)
    fate = np.select([support == SUPPORT_NONE, ~in_fov, ~in_range],
                     [DROP_NO_SUPPORT, DROP_OUT_OF_FOV, DROP_BEYOND_RANGE], KEPT).astype(np.int8)
    keep = fate == KEPT
    return {"points_D": points[keep], "rae": rae[keep], "uv": uv[keep], "support": support[keep]}, fate


def _refill_draws(missing: int, kept: int, drawn: int) -> int:
    """Samples to draw in a refill round for ``missing`` more points after ``kept`` of ``drawn``
    samples were kept: REFILL_OVERSAMPLE times what the keep rate so far predicts, at most
    REFILL_MAX_FACTOR times ``missing``."""
    rate = (kept + 1) / (drawn + 2)  # Laplace's rule: never 0, even when nothing was kept
    return int(min(np.ceil(REFILL_OVERSAMPLE * missing / rate), REFILL_MAX_FACTOR * missing))


def synthesize_frame(
    prob_map: np.ndarray, n_hat: float, K_w: np.ndarray, T_radar_cam: np.ndarray,
    lidar_D: np.ndarray, ego_velocity_D: np.ndarray, labels: Sequence[Object3D] | np.ndarray, *,
    az_res_deg: float, el_res_deg: float, fov_az_deg: float, fov_el_deg: float,
    max_range_m: float, doppler_sign: int, doppler_span_mps: float,
    estimator: str, no_support: str, rng: np.random.Generator,
    index: LidarAngularIndex | None = None, sampling: str = "iid", refill_rounds: int = 0,
) -> dict[str, np.ndarray | int]:
    """Synthesize one frame's radar points except RSS (Section IV-B, steps 1-4).

    ``prob_map`` (H, W) at working resolution with intrinsics ``K_w``; ``n_hat`` rounded to the
    number of samples; ``lidar_D`` (M, 3) m in {D} (or a prebuilt ``index``); radar profile values
    in degrees / metres; ``fov_*_deg`` are TOTAL fields of view, symmetric about x.
    Steps: sample pixels (``sampling``: see :func:`sample_pixels`) -> camera rays -> their (az, el)
    -> lidar range in the window of those angles -> point on the camera ray at that range from the
    radar origin -> r/az/el recomputed from the radar origin -> drop samples without support, then
    outside the FOV, then beyond ``max_range_m`` (each dropped sample counted under its first
    reason) -> Doppler. ``refill_rounds`` > 0 draws replacements for the dropped samples up to that
    many more times (sampling the map restricted to where the radar can return a point): each
    round draws REFILL_OVERSAMPLE times what the keep rate so far says it needs and keeps the
    first samples placed, so one round nearly always suffices; 0 keeps the paper's single draw, so
    fewer than n points may come out.
    Returns points_D (k, 3) float32, rae (k, 3) float32 [range_m, azimuth_rad, elevation_rad],
    doppler (k,) float32, uv (k, 2) float32, support (k,) int8, and the int counts n_requested,
    n_no_support, n_out_of_fov, n_beyond_range (dropped samples of all rounds, up to the draw
    that completed the frame), n_widened (kept samples found by widening).
    """
    if not (np.isfinite(n_hat) and n_hat >= 0):
        raise ValueError(f"n_hat must be finite and >= 0, got {n_hat}")
    if int(refill_rounds) < 0:
        raise ValueError(f"refill_rounds must be >= 0, got {refill_rounds}")
    n = int(round(float(n_hat)))
    index = LidarAngularIndex(lidar_D) if index is None else index
    map_cdf = _map_cdf(prob_map, n)  # once for all rounds
    parts: list[dict[str, np.ndarray]] = []
    dropped = np.zeros(4, np.int64)  # samples per fate code, over the draws used
    missing, kept_total, drawn_total = n, 0, 0
    for round_ in range(1 + int(refill_rounds)):
        draws = missing if round_ == 0 else _refill_draws(missing, kept_total, drawn_total)
        kept, fate = _place_samples(
            _draw_pixels(map_cdf, draws, rng, sampling), K_w, T_radar_cam, index, az_res_deg=az_res_deg,
            el_res_deg=el_res_deg, fov_az_deg=fov_az_deg, fov_el_deg=fov_el_deg, max_range_m=max_range_m,
            estimator=estimator, no_support=no_support)
        used = fate.size  # draws up to the one that completes the frame: the rest are unused
        if len(kept["uv"]) > missing:
            used = int(np.flatnonzero(fate == KEPT)[missing - 1]) + 1
            kept = {k: v[:missing] for k, v in kept.items()}
        parts.append(kept)
        dropped += np.bincount(fate[:used], minlength=len(dropped))
        kept_total, drawn_total = kept_total + len(kept["uv"]), drawn_total + used
        missing -= len(kept["uv"])
        if missing == 0:
            break
    points, rae, uv, support = (np.concatenate([p[k] for p in parts]) for k in ("points_D", "rae", "uv", "support"))
    object_velocity = object_velocities_for_points(points, labels)
    doppler = doppler_for_points(points, ego_velocity_D, object_velocity, doppler_sign, doppler_span_mps)
    return {
        "points_D": points.astype(np.float32),
        "rae": rae.astype(np.float32),
        "doppler": doppler.astype(np.float32),
        "uv": uv.astype(np.float32),
        "support": support,
        "n_requested": n,
        "n_no_support": int(dropped[DROP_NO_SUPPORT]),
        "n_out_of_fov": int(dropped[DROP_OUT_OF_FOV]),
        "n_beyond_range": int(dropped[DROP_BEYOND_RANGE]),
        "n_widened": int((support == SUPPORT_WIDENED).sum()),
    }
