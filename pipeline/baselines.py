"""Baselines of the fidelity evaluation (EVALUATION.md), described as data and built from small parts.

Most methods differ only in *which map* pixels are sampled from, *which count* is drawn and *where
RSS comes from*; the evaluate stage feeds the map and count of a :class:`BaselineSpec` into the
same generation function as the model (pixel sampling, range from lidar, Doppler from the ego
velocity) and then sets RSS as the spec says; a baseline samples its map at full weight
(:func:`generation_config`). Two baselines do not sample pixels:
``lidar-subsample`` (lidar points in the radar field of view) and ``previous-frame`` (the previous
real radar frame moved by the ego motion). One row is a yardstick, not a method: ``no-points``
(an empty output) shows what GOSPA charges for the misses alone.

Radar point arrays (k, 5) have columns x_m, y_m, z_m, doppler_mps, rss in {D} (x forward, y left,
z up); Doppler in the internal convention (range rate, positive receding, wrapped into the radar's
span when it aliases). Pixels (k, 2) are continuous (u right, v down, integer values at pixel
centres, the image covering [-0.5, W - 0.5) x [-0.5, H - 0.5)). Every sampler takes a numpy
``Generator`` so results are reproducible.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Iterable

import numpy as np

from pipeline.frame import check_shape
from pipeline.geometry import radial_velocity, transform_points, wrap_doppler
from pipeline.metrics import region_mask

if TYPE_CHECKING:
    from pipeline.config import Config

MAP_SOURCES = ("model", "uniform", "mean", "real", "none")
COUNT_SOURCES = ("model", "mean", "oracle", "previous", "none")
RSS_SOURCES = ("model", "median", "train-dist", "previous", "none")
KINDS = ("map", "lidar-subsample", "previous-frame", "empty")


@dataclass(frozen=True)
class BaselineSpec:
    """One evaluated method: where its map, count and RSS come from."""

    name: str
    """Row name in the report."""
    map_source: str
    """'model' (Dis-Net map), 'uniform' (constant map), 'mean' (average training heatmap), 'real' (the
    frame's own real-radar heatmap: a ceiling, not a method), 'none'."""
    count_source: str
    """'model' (n_hat), 'mean' (training mean count n_bar), 'oracle' (the real count n), 'previous',
    'none' (no points)."""
    rss_source: str
    """'model' (RSS-Net), 'median' (training median), 'train-dist' (drawn from training RSS values),
    'previous' (kept from the previous frame), 'none' (no points)."""
    kind: str = "map"
    """'map' (sample the map, then the model's generation steps), 'lidar-subsample',
    'previous-frame', 'empty' (no points at all)."""
    description: str = ""
    """One line for the report."""
    reference: bool = False
    """A yardstick row, not a competitor: left out of the "does the model beat every baseline"
    comparison (the ``model-*`` variants are left out by their names)."""

    def __post_init__(self) -> None:
        for field_name, allowed in (("map_source", MAP_SOURCES), ("count_source", COUNT_SOURCES),
                                    ("rss_source", RSS_SOURCES), ("kind", KINDS)):
            if getattr(self, field_name) not in allowed:
                raise ValueError(f"BaselineSpec {self.name}: {field_name} must be one of {allowed}, "
                                 f"got {getattr(self, field_name)!r}")

    @property
    def is_model(self) -> bool:
        """True for the learned model and its variants (not competitors of the model): their names
        start with 'model'."""
        return self.name.startswith("model")


METHODS: tuple[BaselineSpec, ...] = (
    BaselineSpec("model", "model", "model", "model", description="Dis-Net map and count, RSS-Net"),
    BaselineSpec("model-oracle-count", "model", "oracle", "model",
                 description="model given the true count n"),
    BaselineSpec("model-oracle-map", "real", "oracle", "model",
                 description="the model's generation from the frame's real heatmap and count: what a perfect "
                             "Dis-Net would reach (a ceiling, not a method)"),
    BaselineSpec("uniform", "uniform", "mean", "median",
                 description="n_bar pixels uniform over the image, RSS = training median"),
    BaselineSpec("mean-map", "mean", "mean", "train-dist",
                 description="n_bar pixels from the mean training heatmap, RSS from the training distribution"),
    BaselineSpec("mean-map-oracle-count", "mean", "oracle", "train-dist",
                 description="mean-map given the true count n"),
    BaselineSpec("lidar-subsample", "none", "mean", "median", kind="lidar-subsample",
                 description="n_bar lidar points in the radar field of view, RSS = training median"),
    BaselineSpec("previous-frame", "none", "previous", "previous", kind="previous-frame",
                 description="previous real radar frame moved by the ego motion"),
    BaselineSpec("no-points", "none", "none", "none", kind="empty", reference=True,
                 description="an empty output: what GOSPA charges for missing every real point (a yardstick, "
                             "not a method)"),
)
"""Every method of the report, model first; ``previous-frame`` only where consecutive frames exist."""

REFERENCE_ROWS: tuple[str, ...] = tuple(s.name for s in METHODS if s.reference)
"""Rows of :data:`METHODS` that are yardsticks, not baselines the model has to beat."""


def generation_config(spec: BaselineSpec, cfg: Config) -> Config:
    """The configuration a 'map' method generates with: the model's rows take ``cfg`` as it is; a
    baseline samples its map (EVALUATION.md: "sample n_bar points from the average training
    heatmap"), so with the lidar placement its map weighs fully (placement.map_weight = 1) whatever
    weight the model's generation uses."""
    if spec.is_model:
        return cfg
    return replace(cfg, placement=replace(cfg.placement, map_weight=1.0))


def method_by_name(name: str) -> BaselineSpec:
    """The spec in :data:`METHODS` called ``name``; ValueError listing the valid names otherwise."""
    for spec in METHODS:
        if spec.name == name:
            return spec
    raise ValueError(f"unknown method {name!r}; valid: {[s.name for s in METHODS]}")


def mean_count(train_counts: Iterable[int]) -> int:
    """n_bar: the training mean of per-frame radar counts (evaluated region), rounded; >= 1, and 0
    without training frames (nothing to average)."""
    counts = np.asarray(list(train_counts), dtype=np.float64)
    if counts.size == 0:
        return 0
    return max(1, int(round(float(counts.mean()))))


def uniform_map(image_size_wh: tuple[int, int]) -> np.ndarray:
    """Constant probability map (H, W) float64 summing to 1 (the ``uniform`` baseline's map)."""
    w, h = image_size_wh
    return np.full((h, w), 1.0 / (w * h))


def choose_count(spec: BaselineSpec, n_bar: int, n_true: int, n_hat: float | None = None) -> int:
    """The number of points a map-kind method generates: n_hat, n_bar or the real count n."""
    if spec.count_source == "model":
        if n_hat is None:
            raise ValueError(f"{spec.name}: needs the model count n_hat")
        return max(0, int(round(float(n_hat))))
    if spec.count_source == "mean":
        return int(n_bar)
    if spec.count_source == "oracle":
        return int(n_true)
    raise ValueError(f"{spec.name}: count source {spec.count_source!r} is not a sampled count")


def choose_map(spec: BaselineSpec, image_size_wh: tuple[int, int], mean_map_hw: np.ndarray | None = None,
               model_map_hw: np.ndarray | None = None, real_map_hw: np.ndarray | None = None) -> np.ndarray | None:
    """The (H, W) map a method samples from (None for kinds that do not sample pixels)."""
    if spec.map_source == "real":
        if real_map_hw is None:
            raise ValueError(f"{spec.name}: needs the frame's real heatmap")
        return real_map_hw
    if spec.map_source == "uniform":
        return uniform_map(image_size_wh)
    if spec.map_source == "mean":
        if mean_map_hw is None:
            raise ValueError(f"{spec.name}: needs the mean training heatmap")
        return mean_map_hw
    if spec.map_source == "model":
        if model_map_hw is None:
            raise ValueError(f"{spec.name}: needs the model map")
        return model_map_hw
    return None


def choose_rss(spec: BaselineSpec, n: int, rng: np.random.Generator, rss_median: float,
               train_rss: np.ndarray | None = None) -> np.ndarray | None:
    """RSS (n,) float32 for a baseline: the training median or draws (with replacement) from the
    training RSS values; None when the method keeps its own RSS ('model', 'previous')."""
    if spec.rss_source == "median":
        return np.full(int(n), rss_median, np.float32)
    if spec.rss_source == "train-dist":
        values = np.asarray(train_rss if train_rss is not None else [], np.float32).ravel()
        if values.size == 0:
            raise ValueError(f"{spec.name}: needs training RSS values")
        return rng.choice(values, size=int(n), replace=True)
    return None


def static_doppler(points_D: np.ndarray, ego_velocity_D: np.ndarray, doppler_span_mps: float = 0.0) -> np.ndarray:
    """Doppler (N,) m/s of static points (N, 3): range rate from the ego velocity (eq. 16, v_O = 0),
    wrapped into [-span/2, span/2) when the radar aliases (span > 0)."""
    pts = check_shape("points_D", np.asarray(points_D, dtype=np.float64), (None, 3))
    return wrap_doppler(radial_velocity(pts, ego_velocity_D), doppler_span_mps)


def lidar_subsample(lidar_D: np.ndarray, n_bar: int, fov_az_deg: float, fov_el_deg: float,
                    max_range_m: float, K_w: np.ndarray, T_cam_radar: np.ndarray,
                    working_size_wh: tuple[int, int], rng: np.random.Generator, *,
                    ego_velocity_D: np.ndarray, rss_value: float, doppler_span_mps: float = 0.0) -> np.ndarray:
    """The ``lidar-subsample`` baseline: (k, 5) float32 radar points.

    Keeps lidar points (L, 3) in {D} inside the evaluated region (radar field of view, range <=
    max_range_m, projecting into the working image of size (W, H) with intrinsics ``K_w``), picks
    k = min(n_bar, available) of them without replacement, Doppler from the ego velocity (static
    world), RSS = ``rss_value`` (training median).
    """
    lidar = check_shape("lidar_D", np.asarray(lidar_D, dtype=np.float64), (None, 3))
    if len(lidar) == 0:
        return np.zeros((0, 5), np.float32)
    keep = np.flatnonzero(region_mask(lidar, fov_az_deg, fov_el_deg, max_range_m, K_w, T_cam_radar,
                                      working_size_wh))
    k = min(int(n_bar), len(keep))
    xyz = lidar[rng.choice(keep, size=k, replace=False)] if k else np.zeros((0, 3))
    doppler = static_doppler(xyz, ego_velocity_D, doppler_span_mps)
    return np.column_stack([xyz, doppler, np.full(k, rss_value)]).astype(np.float32)


def ego_motion_transform(ego_velocity_D: np.ndarray, dt_s: float, yaw_rate_rps: float = 0.0) -> np.ndarray:
    """T_curr_prev (4, 4): maps static points from the radar frame at t - dt to the frame at t.

    The radar moves with constant velocity ``ego_velocity_D`` (3,) m/s expressed in its own frame
    and turns at ``yaw_rate_rps`` about z (positive to the left). Straight motion gives
    p_curr = p_prev - v * dt; with a yaw rate the planar displacement is integrated exactly along
    the arc (velocity constant in the rotating body frame).
    """
    v = check_shape("ego_velocity_D", np.asarray(ego_velocity_D, dtype=np.float64), (3,))
    psi = float(yaw_rate_rps) * float(dt_s)
    if abs(psi) < 1e-9:
        t_xy = v[:2] * dt_s
    else:
        a, b = np.sin(psi) / yaw_rate_rps, (1.0 - np.cos(psi)) / yaw_rate_rps
        t_xy = np.array([[a, -b], [b, a]]) @ v[:2]
    T_prev_curr = np.eye(4)
    c, s = np.cos(psi), np.sin(psi)
    T_prev_curr[:2, :2] = [[c, -s], [s, c]]
    T_prev_curr[:3, 3] = [t_xy[0], t_xy[1], v[2] * dt_s]
    T_curr_prev = np.eye(4)
    T_curr_prev[:3, :3] = T_prev_curr[:3, :3].T
    T_curr_prev[:3, 3] = -T_prev_curr[:3, :3].T @ T_prev_curr[:3, 3]
    return T_curr_prev


def previous_frame(prev_radar_D: np.ndarray, T_curr_prev: np.ndarray) -> np.ndarray:
    """The ``previous-frame`` baseline: previous real radar points (k, 5) moved into the current frame.

    Positions are transformed by ``T_curr_prev`` (see :func:`ego_motion_transform`); Doppler and
    RSS are kept as measured. The caller restricts the result to the evaluated region like every
    other method's points.
    """
    prev = check_shape("prev_radar_D", np.asarray(prev_radar_D, dtype=np.float32), (None, 5))
    out = prev.copy()
    if len(prev):
        out[:, :3] = transform_points(T_curr_prev, prev[:, :3].astype(np.float64))
    return out
