"""Figures are real PNG files of the documented size with non-trivial content."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pipeline import figures as F


def _check_png(path, width_in, height_in, min_kb=5):
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None
    assert img.shape == (round(height_in * F.FIG_DPI), round(width_in * F.FIG_DPI), 3)
    assert path.stat().st_size > min_kb * 1024
    return img


def _has_color(img_bgr, bgr):
    """Some pixels close to a pure colour (red real points, blue synthetic points)."""
    return bool(np.any(np.all(np.abs(img_bgr.astype(int) - np.array(bgr)) < 40, axis=2)))


def test_fig8(tmp_path):
    rng = np.random.default_rng(0)
    frames = []
    for k in range(2):
        image = np.full((96, 320, 3), 128, np.uint8)  # grey: no red or blue of its own
        image[:, ::7] = 200
        prob = rng.uniform(0, 1, (24, 80))
        frames.append({"image": image, "prob_map": prob / prob.sum(),
                       "real_uv": rng.uniform([0, 0], [319, 95], (80, 2)),
                       "syn_uv": rng.uniform([0, 0], [319, 95], (60, 2)), "title": f"frame {k}"})
    path = F.fig8(tmp_path / "figs" / "fig8.png", frames)
    img = _check_png(path, *F.fig8_size_in((96, 320), 2))
    assert _has_color(img, (0, 0, 255)) and _has_color(img, (255, 0, 0))
    with pytest.raises(ValueError):
        F.fig8(tmp_path / "x.png", [])


def test_bev(tmp_path):
    rng = np.random.default_rng(1)
    real5 = np.column_stack([rng.uniform([0, -20, -1], [50, 20, 2], (200, 3)), rng.normal(0, 1, (200, 2))])
    frames = [{"real_points_D": real5,
               "syn_points_D": rng.uniform([0, -20, -1], [50, 20, 2], (150, 3)), "title": "bev"},
              {"real_points_D": np.zeros((0, 3)), "syn_points_D": np.zeros((0, 3)), "title": "empty"}]
    path = F.bev(tmp_path / "bev.png", frames)
    img = _check_png(path, *F.bev_size_in(2))
    assert _has_color(img, (0, 0, 255)) and _has_color(img, (255, 0, 0))


def _red_quadrants(path):
    """Red pixel counts in the lower-left, lower-right quadrants and the lower half (the legend,
    with its own red marker, sits above the panels)."""
    img = cv2.imread(str(path))
    red = np.all(np.abs(img.astype(int) - [0, 0, 255]) < 60, axis=2)
    h, w = red.shape
    return red[h // 2:, : w // 2].sum(), red[h // 2:, w // 2:].sum(), red[h // 2:].sum()


def _one_point_bev(tmp_path, name, xyz):
    frame = {"real_points_D": np.array([xyz], float), "syn_points_D": np.zeros((0, 3)), "title": ""}
    return _red_quadrants(F.bev(tmp_path / name, [frame]))


def test_bev_orientation(tmp_path):
    """y (left) is drawn to the left, x (forward) upwards."""
    ll, lr, _ = _one_point_bev(tmp_path, "left.png", (10.0, 30.0, 0.0))
    assert ll > 0 and lr == 0
    ll, lr, _ = _one_point_bev(tmp_path, "right.png", (10.0, -30.0, 0.0))
    assert ll == 0 and lr > 0
    assert _one_point_bev(tmp_path, "near.png", (5.0, 0.0, 0.0))[2] > 0
    assert _one_point_bev(tmp_path, "far.png", (45.0, 0.0, 0.0))[2] == 0


def test_bev_spans_the_field_of_view_when_given(tmp_path):
    """With the radar's azimuth field of view the panel's y span is the field of view at max range
    (a point 30 m to the side of a 64 deg radar is off the panel), and its edges are drawn."""
    def red_and_grey(name, xyz, fov):
        frame = {"real_points_D": np.array([xyz], float), "syn_points_D": np.zeros((0, 3)), "title": ""}
        img = cv2.imread(str(F.bev(tmp_path / name, [frame], 50.0, fov))).astype(int)
        red = np.all(np.abs(img - [0, 0, 255]) < 60, axis=2)
        grey = (np.ptp(img, axis=2) < 5) & (img[..., 0] > 120) & (img[..., 0] < 230)   # light neutral grey
        return red[img.shape[0] // 2:].sum(), grey.sum()
    red, grey_without = red_and_grey("wide.png", (10.0, 30.0, 0.0), None)
    assert red > 0
    assert red_and_grey("inside.png", (10.0, 25.0, 0.0), 64.0)[0] > 0
    red, grey = red_and_grey("outside.png", (10.0, 30.0, 0.0), 64.0)
    assert red == 0 and grey > grey_without + 250       # the two dashed edges


def test_bev_fits_its_panels_and_keeps_the_legend_off_the_points(tmp_path):
    """The figure is as wide as the panels at equal axes need (a wider field of view, a wider
    figure), with no wide blank margin or gap between panels, and its legend (the only red of a
    frame without points) lies above the panels' axes, not over the points."""
    assert F.bev_size_in(4, 50.0, 110.0)[0] > F.bev_size_in(4, 50.0, 64.0)[0]
    empty = {"real_points_D": np.zeros((0, 3)), "syn_points_D": np.zeros((0, 3)), "title": "frame 1: 0 real"}
    for fov in (64.0, 110.0, None):
        path = F.bev(tmp_path / f"bev{fov}.png", [empty] * 4, 50.0, fov)
        img = _check_png(path, *F.bev_size_in(4, 50.0, fov), min_kb=1).astype(int)
        ink = np.any(img < 250, axis=2)
        blank = np.concatenate([[0], (~ink.any(0)).astype(int), [0]])
        edges = np.flatnonzero(np.diff(blank))
        assert (edges[1::2] - edges[::2]).max() < 0.3 * F.FIG_DPI, fov   # no blank strip over 0.3 inch wide
        black = np.all(img < 60, axis=2)
        spine_rows = np.flatnonzero(black.sum(1) > img.shape[1] / 2)     # the axes' top and bottom edges
        red = np.all(np.abs(img - [0, 0, 255]) < 60, axis=2)
        assert red.any() and np.flatnonzero(red.any(1)).max() < spine_rows.min(), fov


def test_histograms(tmp_path):
    rng = np.random.default_rng(2)
    real = rng.normal(0, 1, (500, 5))
    syn = rng.normal(0.5, 1, (400, 5))
    path = F.histograms(tmp_path / "hist.png", real, syn)
    _check_png(path, 15.0, 3.0)
    path = F.histograms(tmp_path / "hist_empty.png", real, np.zeros((0, 5)))
    _check_png(path, 15.0, 3.0)
    with pytest.raises(ValueError):
        F.histograms(tmp_path / "bad.png", real, syn[:, :3])


def test_histograms_bin_a_column_of_other_units_apart(tmp_path, monkeypatch):
    """RSS in different units (dB(Mag) near 54, dBsm near -14): each set gets its own bins there,
    the other columns shared ones, and the panel's title says why."""
    from matplotlib.axes import Axes

    calls, titles, original, set_title = [], [], Axes.hist, Axes.set_title
    monkeypatch.setattr(Axes, "hist", lambda self, x, bins, **kw: calls.append((np.asarray(x), bins)) or
                        original(self, x, bins=bins, **kw))
    monkeypatch.setattr(Axes, "set_title", lambda self, t, **kw: titles.append(t) or set_title(self, t, **kw))
    rng = np.random.default_rng(2)
    real, syn = rng.normal(0, 1, (500, 5)), rng.normal(0.5, 1, (400, 5))
    real[:, 4] += 54.0
    syn[:, 4] -= 14.0
    F.histograms(tmp_path / "hist.png", real, syn, apart={"rss": "real dB (Mag), synthetic dBsm (not comparable)"})
    (real_rss, real_edges), (syn_rss, syn_edges) = calls[-2:]
    assert real_edges[0] == real_rss.min() and real_edges[-1] == real_rss.max()
    assert syn_edges[0] == syn_rss.min() and syn_edges[-1] == syn_rss.max()
    np.testing.assert_array_equal(calls[0][1], calls[1][1])     # range: shared edges
    assert calls[0][1][0] == min(real[:, 0].min(), syn[:, 0].min())
    assert titles[-1] == "rss: real dB (Mag), synthetic dBsm (not comparable)" and titles[0] == "range_m"


def test_histogram_axes_are_labelled_with_their_units(tmp_path, monkeypatch):
    """Until 2026-12-06 the histograms had titles only ('rss': no unit anywhere) and no axis labels."""
    from matplotlib.axes import Axes

    xlabels, ylabels, set_xlabel, set_ylabel = [], [], Axes.set_xlabel, Axes.set_ylabel
    monkeypatch.setattr(Axes, "set_xlabel", lambda self, t, **kw: xlabels.append(t) or set_xlabel(self, t, **kw))
    monkeypatch.setattr(Axes, "set_ylabel", lambda self, t, **kw: ylabels.append(t) or set_ylabel(self, t, **kw))
    rng = np.random.default_rng(2)
    F.histograms(tmp_path / "hist.png", rng.normal(0, 1, (50, 5)), rng.normal(0, 1, (40, 5)),
                 labels={"rss": "RSS (dB (Mag))"})
    assert xlabels == ["range (m)", "azimuth (rad)", "elevation (rad)", "Doppler (m/s)", "RSS (dB (Mag))"]
    assert len(ylabels) == 5 and all(y.startswith("density") for y in ylabels)


def test_the_evaluate_histograms_name_the_radars_rss_unit():
    """What the evaluate stage gives the histograms: the RSS unit of the dataset's radar, and with
    the nets of a radar of other RSS units both units, binned apart."""
    from pipeline.config import load_config
    from pipeline.transfer import settings
    from stages.evaluate import histogram_units

    assert histogram_units(load_config("astyx", environ={})) == ({}, {"rss": "RSS (dB (Mag))"})
    assert histogram_units(load_config("synthetic", environ={})) == ({}, {"rss": "RSS (dBsm)"})
    astyx_on_vod = load_config("vod", {"train.nets_from": "astyx"}, environ={}).with_overrides(
        settings(load_config("astyx", environ={})))
    apart, labels = histogram_units(astyx_on_vod)
    assert apart == {"rss": "real dBsm, synthetic dB (Mag) (not comparable)"}
    assert labels == {"rss": "RSS (real dBsm, synthetic dB (Mag))"}
