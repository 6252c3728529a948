"""Evaluation figures (matplotlib Agg canvas, imported inside the functions; pyplot is not used).

Every figure has a fixed size in inches and a fixed dpi (no tight bounding box), so the PNG size
is predictable: width = FIG_DPI * width_in pixels. Files are written atomically (temporary file +
rename). Real points are red, synthesized points blue.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from pipeline.fileio import atomic_path
from pipeline.frame import check_shape

FIG_DPI = 100
"""Dots per inch of every figure."""

FIG8_WIDTH_IN = 12.0
"""Width of the :func:`fig8` figure, inches (three panels per row)."""


def fig8_size_in(image_hw: tuple[int, int], n_rows: int) -> tuple[float, float]:
    """(width, height) in inches of :func:`fig8` for images of (H, W) pixels: each row is as tall
    as one panel's image at its aspect ratio plus room for the titles."""
    h, w = image_hw
    row_in = max(1.5, (FIG8_WIDTH_IN / 3.0 - 0.1) * h / w + 0.5)
    return FIG8_WIDTH_IN, round(row_in * n_rows, 2)


def _save(fig: Any, out_png: str | Path) -> Path:
    """Save ``fig`` to ``out_png`` atomically."""
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, dpi=FIG_DPI, format="png")
    return Path(out_png)


def _figure(width_in: float, height_in: float, nrows: int, ncols: int) -> tuple[Any, np.ndarray]:
    """A pyplot-free Figure (Agg canvas: no global state, safe in worker processes) and its axes."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=FIG_DPI)
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    return fig, axes


def fig8(out_png: str | Path, frames: Sequence[Mapping[str, Any]]) -> Path:
    """The paper's Fig. 8: one row per frame -- image, predicted map, real vs synthetic on the image.

    Each frame: ``image`` (H, W, 3) uint8 RGB, ``prob_map`` (h, w) (stretched over the image when
    its resolution differs), ``real_uv`` (N, 2) and ``syn_uv`` (M, 2) pixels of the image, ``title``.
    Figure size :func:`fig8_size_in` of the first frame's image at :data:`FIG_DPI`.
    """
    if not frames:
        raise ValueError("fig8: no frames to draw")
    first = check_shape("image", np.asarray(frames[0]["image"]), (None, None, 3))
    fig, axes = _figure(*fig8_size_in(first.shape[:2], len(frames)), len(frames), 3)
    for row, fr in zip(axes, frames):
        image = check_shape("image", np.asarray(fr["image"]), (None, None, 3))
        h, w = image.shape[:2]
        real_uv = check_shape("real_uv", np.asarray(fr["real_uv"], np.float64).reshape(-1, 2), (None, 2))
        syn_uv = check_shape("syn_uv", np.asarray(fr["syn_uv"], np.float64).reshape(-1, 2), (None, 2))
        extent = (-0.5, w - 0.5, h - 0.5, -0.5)
        row[0].imshow(image)
        title = fr.get("title", "")
        row[0].set_title(f"image ({title})" if title else "image", fontsize=8)
        row[1].imshow(np.asarray(fr["prob_map"], np.float64), cmap="magma", extent=extent, aspect="equal",
                      interpolation="nearest")
        row[1].set_title("predicted map", fontsize=8)
        row[2].imshow(image, extent=extent)
        row[2].scatter(real_uv[:, 0], real_uv[:, 1], s=3, c="red", label=f"real ({len(real_uv)})")
        row[2].scatter(syn_uv[:, 0], syn_uv[:, 1], s=3, c="blue", label=f"synthetic ({len(syn_uv)})")
        row[2].set_xlim(-0.5, w - 0.5)
        row[2].set_ylim(h - 0.5, -0.5)
        row[2].legend(fontsize=6, loc="upper right")
        row[2].set_title("real (red) vs synthetic (blue)", fontsize=8)
        for ax in row:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.subplots_adjust(left=0.01, right=0.99, top=0.97, bottom=0.01, wspace=0.03, hspace=0.25)
    return _save(fig, out_png)


BEV_AXES_HEIGHT_IN = 3.0
"""Height of each :func:`bev` panel's axes, inches (their width follows the panel's aspect)."""


def _bev_half_y(max_range_m: float, fov_az_deg: float | None) -> float:
    """Half the y span of a :func:`bev` panel, metres."""
    if fov_az_deg is None:
        return 0.8 * max_range_m
    half_az = np.deg2rad(min(float(fov_az_deg), 180.0)) / 2
    return 1.05 * max_range_m * max(np.sin(half_az), 0.2)


BEV_MARGINS_IN = (0.45, 0.15, 0.45, 0.55)
"""Room around each :func:`bev` panel's axes, inches: left (tick labels and "x (m, forward)"),
right, bottom (tick labels and "y (m, left)"), top (the title and the figure's legend)."""


def bev_size_in(n_panels: int, max_range_m: float = 50.0, fov_az_deg: float | None = None) -> tuple[float, float]:
    """(width, height) in inches of :func:`bev` with ``n_panels`` panels: each panel's axes are
    :data:`BEV_AXES_HEIGHT_IN` tall and as wide as the y span at equal axes, with
    :data:`BEV_MARGINS_IN` around them."""
    left, right, bottom, top = BEV_MARGINS_IN
    axes_w = BEV_AXES_HEIGHT_IN * 2 * _bev_half_y(max_range_m, fov_az_deg) / max_range_m
    return round(float(n_panels * (left + axes_w + right)), 2), round(bottom + BEV_AXES_HEIGHT_IN + top, 2)


def bev(out_png: str | Path, frames: Sequence[Mapping[str, Any]], max_range_m: float = 50.0,
        fov_az_deg: float | None = None) -> Path:
    """Bird's-eye view of real (red) and synthetic (blue) points, one panel per frame.

    Each frame: ``real_points_D`` (N, 3+) and ``syn_points_D`` (M, 3+) in {D} (only x, y used),
    ``title`` (the evaluate stage's names the frame and both point counts). Drawn with x (forward)
    up and y (left) to the left, equal axes, x in [0, max_range_m]. With the radar's total azimuth
    field of view ``fov_az_deg`` its edges are drawn (dashed) and y spans the field of view at
    ``max_range_m``, else +/- 0.8 max_range_m. One legend for the figure, above the panels.
    Figure size :func:`bev_size_in` at :data:`FIG_DPI`.
    """
    if not frames:
        raise ValueError("bev: no frames to draw")
    half_y = _bev_half_y(max_range_m, fov_az_deg)
    width_in, height_in = bev_size_in(len(frames), max_range_m, fov_az_deg)
    fig, axes = _figure(width_in, height_in, 1, len(frames))
    for ax, fr in zip(axes[0], frames):
        real = np.asarray(fr["real_points_D"], np.float64).reshape(-1, np.shape(fr["real_points_D"])[-1])
        syn = np.asarray(fr["syn_points_D"], np.float64).reshape(-1, np.shape(fr["syn_points_D"])[-1])
        ax.scatter(real[:, 1], real[:, 0], s=2, c="red", label="real")
        ax.scatter(syn[:, 1], syn[:, 0], s=2, c="blue", label="synthetic")
        if fov_az_deg is not None:  # the field of view's edges out to max_range_m
            half_az = np.deg2rad(min(float(fov_az_deg), 180.0)) / 2
            for side in (1.0, -1.0):
                ax.plot([0.0, side * max_range_m * np.sin(half_az)], [0.0, max_range_m * np.cos(half_az)],
                        ls="--", lw=0.6, c="0.6", zorder=0, label="field of view" if side > 0 else None)
        ax.set_xlim(half_y, -half_y)
        ax.set_ylim(0.0, max_range_m)
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel("y (m, left)", fontsize=7)
        ax.set_ylabel("x (m, forward)", fontsize=7)
        ax.set_title(str(fr.get("title", "")), fontsize=8)
        ax.tick_params(labelsize=6)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncols=len(labels), fontsize=7, frameon=False, markerscale=3,
               borderaxespad=0.1)
    left, right, bottom, top = BEV_MARGINS_IN
    axes_w = width_in / len(frames) - left - right
    fig.subplots_adjust(left=left / width_in, right=1 - right / width_in, bottom=bottom / height_in,
                        top=1 - top / height_in, wspace=(left + right) / axes_w)
    return _save(fig, out_png)


def _edges(values: np.ndarray, bins: int) -> np.ndarray:
    """``bins`` + 1 equal bin edges over the range of ``values`` (a unit wide when they are equal)."""
    lo, hi = float(values.min()), float(values.max())
    return np.linspace(lo, hi if hi > lo else lo + 1.0, bins + 1)


AXIS_LABELS = {"range_m": "range (m)", "azimuth_rad": "azimuth (rad)", "elevation_rad": "elevation (rad)",
               "doppler_mps": "Doppler (m/s)", "rss": "RSS"}
"""x-axis label of each :func:`histograms` column by default (RSS: its unit is the radar's,
given by the caller)."""


def histograms(out_png: str | Path, real: np.ndarray, syn: np.ndarray,
               names: Sequence[str] = ("range_m", "azimuth_rad", "elevation_rad", "doppler_mps", "rss"),
               bins: int = 50, apart: Mapping[str, str] | None = None,
               labels: Mapping[str, str] | None = None) -> Path:
    """Histograms (densities) of each column of real (N, C) vs synthetic (M, C) points, C = len(names).

    Typically spherical arrays [range_m, azimuth_rad, elevation_rad, doppler_mps, rss]
    (pipeline.metrics.to_spherical). Shared bin edges per column over finite values of both sets,
    except the columns in ``apart`` (name -> a title saying why, e.g. RSS in different units):
    each set over its own range. Each panel's x axis is labelled ``labels[name]``, else
    :data:`AXIS_LABELS`' (else the name), its y axis "density (1/unit of x)".
    Figure size (3 * C) x 3 inches at :data:`FIG_DPI`.
    """
    apart = dict(apart or {})
    labels = {**AXIS_LABELS, **(labels or {})}
    real = check_shape("real", np.asarray(real, np.float64), (None, len(names)))
    syn = check_shape("syn", np.asarray(syn, np.float64), (None, len(names)))
    fig, axes = _figure(3.0 * len(names), 3.0, 1, len(names))
    for k, (ax, name) in enumerate(zip(axes[0], names)):
        r, s = real[:, k][np.isfinite(real[:, k])], syn[:, k][np.isfinite(syn[:, k])]
        both = np.concatenate([r, s])
        if both.size:
            for values, colour, label in ((r, "red", "real"), (s, "blue", "synthetic")):
                if values.size:
                    ax.hist(values, bins=_edges(values if name in apart else both, bins), density=True, color=colour,
                            alpha=0.5, label=f"{label} ({values.size})")
            ax.legend(fontsize=6)
        ax.set_title(f"{name}: {apart[name]}" if name in apart else name, fontsize=8 if name not in apart else 6)
        ax.set_xlabel(labels.get(name, name), fontsize=7)
        ax.set_ylabel("density (1/unit of x)", fontsize=6)
        ax.tick_params(labelsize=6)
    fig.subplots_adjust(left=0.05, right=0.98, top=0.88, bottom=0.17, wspace=0.35)
    return _save(fig, out_png)
