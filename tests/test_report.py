"""Aggregation and report files."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from pipeline import report as R
from pipeline.metrics import SPHERICAL_COLUMNS


def _frames(rng, n, chamfer, gospa, f1):
    out = []
    for _ in range(n):
        out.append({"kl": float(rng.uniform(0, 1)), "count_rel_err": 0.1, "count_sq_rel_err": 0.01,
                    "rss_err": math.nan, "chamfer_m": chamfer, "gospa": gospa, "gospa_localisation": 1.0,
                    "gospa_missed": 2.0, "gospa_false": 3.0, "precision": f1, "recall": f1, "f1": f1})
    return out


def test_aggregate_mean_median_and_nans():
    t = R.aggregate({"m": [{"a": 1.0, "b": math.nan}, {"a": 2.0, "b": 4.0}, {"a": 6.0}]})
    assert t["m"]["a"] == {"mean": 3.0, "median": 2.0, "n": 3, "n_nan": 0}
    assert t["m"]["b"]["mean"] == 4.0 and t["m"]["b"]["n"] == 1 and t["m"]["b"]["n_nan"] == 2
    empty = R.aggregate({"m": [{"a": math.nan}]})
    assert math.isnan(empty["m"]["a"]["mean"]) and empty["m"]["a"]["n_nan"] == 1


def test_order_methods():
    assert R.order_methods(["uniform", "model-oracle-count", "mean-map", "model"]) == [
        "model", "model-oracle-count", "uniform", "mean-map"]


def test_shortfalls():
    rng = np.random.default_rng(0)
    table = R.aggregate({
        "uniform": _frames(rng, 3, chamfer=5.0, gospa=20.0, f1=0.1),
        "model": _frames(rng, 3, chamfer=2.0, gospa=10.0, f1=0.3),
        "lidar-subsample": _frames(rng, 3, chamfer=1.5, gospa=12.0, f1=0.3),
        "model-oracle-count": _frames(rng, 3, chamfer=0.1, gospa=1.0, f1=0.9),
    })
    s = R.model_shortfalls(table)
    assert [d["method"] for d in s["chamfer_m"]] == ["lidar-subsample"]
    assert s["gospa"] == []
    assert [d["method"] for d in s["f1"]] == ["lidar-subsample"]  # a tie is not a win
    text = R.shortfall_paragraph(table)
    assert "lidar-subsample" in text and "uniform" not in text and "GOSPA" not in text
    assert "model-oracle-map" not in text  # no ceiling row, no ceiling sentence
    winner = R.aggregate({"model": _frames(rng, 2, 1.0, 1.0, 0.9), "uniform": _frames(rng, 2, 5.0, 5.0, 0.1)})
    assert "beats every baseline" in R.shortfall_paragraph(winner)


def test_ceiling_sentence_names_the_baselines_a_perfect_map_does_not_beat():
    rng = np.random.default_rng(2)
    rows = {"model": _frames(rng, 3, chamfer=2.0, gospa=19.0, f1=0.14),
            "model-oracle-map": _frames(rng, 3, chamfer=1.8, gospa=18.5, f1=0.16),
            "lidar-subsample": _frames(rng, 3, chamfer=2.1, gospa=19.5, f1=0.15),
            "previous-frame": _frames(rng, 3, chamfer=1.1, gospa=14.0, f1=0.48)}
    text = R.shortfall_paragraph(R.aggregate(rows))
    ceiling = text[text.index("Even `model-oracle-map`"):]
    assert "Chamfer (`previous-frame`)" in ceiling and "F1 (`previous-frame`)" in ceiling
    assert "lidar-subsample" not in ceiling
    del rows["previous-frame"]
    text = R.shortfall_paragraph(R.aggregate(rows))
    assert "a better Dis-Net can close these gaps" in text and "lidar-subsample" in text


def test_no_points_row_is_a_yardstick_not_a_baseline():
    rng = np.random.default_rng(3)
    rows = {"model": _frames(rng, 3, chamfer=2.0, gospa=20.0, f1=0.14),
            "uniform": _frames(rng, 3, chamfer=2.4, gospa=19.5, f1=0.10),
            "lidar-subsample": _frames(rng, 3, chamfer=2.1, gospa=21.0, f1=0.13),
            "no-points": _frames(rng, 3, chamfer=math.nan, gospa=17.0, f1=math.nan)}
    table = R.aggregate(rows)
    assert [d["method"] for d in R.model_shortfalls(table)["gospa"]] == ["uniform"]  # not no-points
    text = R.shortfall_paragraph(table)
    scale = text[text.index("For scale"):]
    assert "mean GOSPA of 17 m" in scale and "3 of the 3 other rows score no better" in scale
    assert "c^p/2 = 2 m^2" in scale
    rows["no-points"] = _frames(rng, 3, chamfer=math.nan, gospa=20.5, f1=math.nan)
    scale = R.shortfall_paragraph(R.aggregate(rows))
    assert "1 of the 3 other rows score no better (`lidar-subsample`)" in scale
    del rows["no-points"]
    assert "For scale" not in R.shortfall_paragraph(R.aggregate(rows))


def test_write_report_files(tmp_path):
    rng = np.random.default_rng(1)
    per_frame = {"uniform": _frames(rng, 4, 5.0, 20.0, 0.1), "model": _frames(rng, 4, 2.0, 10.0, 0.3),
                 "mean-map": _frames(rng, 4, 3.0, 9.0, 0.2)}
    table = R.aggregate(per_frame)
    distances = {m: {c: float(i) for i, c in enumerate(SPHERICAL_COLUMNS)} for m in per_frame}
    distances["model"]["rss"] = math.nan
    physics = {"range": {"median_abs_dr": 3.8, "p90_abs_dr": 20.0, "no_support_share": 0.046,
                         "abs_dr": np.arange(3.0)},
               "doppler": {"median_abs_dv": 0.1, "n_static": 10}}
    out = tmp_path / "eval" / "vod"
    jp, mp = R.write_report(out, "vod", "test", table, distances, physics, {"frames": 4, "fingerprint": "abc"})
    assert jp.exists() and mp.exists()
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary files left
    doc = json.loads(jp.read_text())  # strict JSON: NaN became null
    assert doc["dataset"] == "vod" and doc["split"] == "test"
    assert doc["metrics"]["model"]["chamfer_m"]["mean"] == 2.0
    assert doc["metrics"]["model"]["rss_err"]["mean"] is None
    assert doc["distribution_distances"]["model"]["rss"] is None
    assert doc["physics_checks"]["range"]["abs_dr"] == [0.0, 1.0, 2.0]
    assert [d["method"] for d in doc["model_does_not_beat"]["mean"]["gospa"]] == ["mean-map"]
    md = mp.read_text()
    rows = [line for line in md.splitlines() if line.startswith("| ") and not line.startswith("| method")]
    metric_rows = rows[:3]
    assert [r.split("|")[1].strip() for r in metric_rows] == ["model", "uniform", "mean-map"]
    header = next(line for line in md.splitlines() if line.startswith("| method | frames | KL"))
    assert len(header.split("|")) - 2 == 2 + len(R.TABLE_COLUMNS)
    assert metric_rows[0].startswith("| model | 4 | ") and "2 / 2" in metric_rows[0]  # frames; chamfer mean / median
    assert "median_abs_dr = 3.8" in md and "mean-map" in md.split("does not beat every baseline")[-1]
    assert "by ego speed" not in md  # no rows: no section
    by_speed = R.speed_breakdown(np.array([0.0, 1.0, 6.0, 11.0]), np.full(4, 10), np.full(4, 12),
                                R.metric_columns(per_frame["model"]))
    R.write_report(out, "vod", "test", table, distances, physics, {}, by_speed)
    md = mp.read_text()
    assert md.index("## Distribution distances") < md.index("## The model by ego speed") < md.index("## Physics")
    assert "| < 0.5 m/s | 1 | 10 | 12 |" in md
    assert json.loads(jp.read_text())["by_ego_speed"][0]["model_count"] == 12
    # rewriting replaces the files atomically
    R.write_report(out, "vod", "test", table, distances, {}, {})
    assert json.loads(jp.read_text())["physics_checks"] == {}


def test_speed_breakdown_bins_frames_by_ego_speed():
    speeds = np.array([0.0, 0.2, 3.0, 7.0, 12.0, 30.0])
    real = np.array([50, 60, 150, 200, 160, 140])
    pred = np.array([100, 110, 150, 190, 170, 150])
    frames = [{"count_rel_err": abs(p - r) / r, "chamfer_m": c, "gospa": 20.0, "f1": f}
              for p, r, c, f in zip(pred, real, [3.0, 1.0, 2.0, 2.0, 2.0, math.nan], [0.1, 0.1, 0.2, 0.3, 0.2, 0.4])]
    rows = R.speed_breakdown(speeds, real, pred, R.metric_columns(frames))
    assert [r["label"] for r in rows] == ["< 0.5 m/s", "0.5-5 m/s", "5-10 m/s", ">= 10 m/s"]
    assert [r["frames"] for r in rows] == [2, 1, 1, 2]
    stopped = rows[0]
    assert stopped["real_count"] == 55 and stopped["model_count"] == 105 and stopped["chamfer_m"] == 2.0
    assert math.isclose(stopped["count_rel_err"], (1.0 + 50 / 60) / 2)
    assert rows[-1]["chamfer_m"] == 2.0 and math.isclose(rows[-1]["f1"], 0.3)  # NaN ignored
    two = R.speed_breakdown(speeds[:2], real[:2], pred[:2], R.metric_columns(frames[:2]))
    assert two[0]["frames"] == 2  # empty bins left out
    unknown = R.speed_breakdown(np.r_[np.nan, speeds[1:]], real, pred, R.metric_columns(frames))
    assert unknown[-1]["label"] == "unknown" and unknown[-1]["frames"] == 1 and unknown[-1]["real_count"] == 50
    assert sum(r["frames"] for r in unknown) == 6
    md = R.speed_table_md(rows)
    assert "| < 0.5 m/s | 2 | 55 | 105 |" in md and md.count("\n") == 5
    try:
        R.speed_breakdown(speeds, real, pred, R.metric_columns(frames[:3]))
    except ValueError as exc:
        assert "differ" in str(exc)
    else:
        raise AssertionError("mismatched lengths must raise")


def test_placement_sentence_compares_the_oracle_count_rows_like_for_like():
    rng = np.random.default_rng(4)
    rows = {"model": _frames(rng, 3, chamfer=2.0, gospa=20.4, f1=0.18),
            "model-oracle-count": _frames(rng, 3, chamfer=1.9, gospa=19.8, f1=0.17),
            "mean-map-oracle-count": _frames(rng, 3, chamfer=2.1, gospa=20.2, f1=0.12)}
    text = R.shortfall_paragraph(R.aggregate(rows))
    assert "does not beat `mean-map-oracle-count` (20.2)" in text
    like = text[text.index("Given the true count, like for like"):]
    assert "better on Chamfer 1.9 vs 2.1, GOSPA 19.8 vs 20.2, F1 0.17 vs 0.12." in like
    rows["model-oracle-count"] = _frames(rng, 3, chamfer=2.2, gospa=19.8, f1=0.17)
    like = R.shortfall_paragraph(R.aggregate(rows))
    assert "better on GOSPA 19.8 vs 20.2, F1 0.17 vs 0.12; not better on Chamfer 2.2 vs 2.1." in like
    rows["model-oracle-count"] = _frames(rng, 3, chamfer=2.2, gospa=20.19, f1=0.17)
    assert "GOSPA 20.19 vs 20.2" in R.shortfall_paragraph(R.aggregate(rows))  # more digits where 3 tie
    del rows["mean-map-oracle-count"]
    assert "like for like" not in R.shortfall_paragraph(R.aggregate(rows))


def test_physics_summary_rows_and_share_within_tolerance():
    from stages.evaluate import RANGE_CHECK_TOLERANCE_M, _physics_summary

    abs_dr = np.full((4, 5), np.nan)  # columns: mean, nearest, median, min rules, best (oracle)
    abs_dr[:, 1] = [0.5, 2.0, np.nan, 1.0]
    abs_dr[:, 4] = [0.1, 0.2, np.nan, 3.0]
    out = _physics_summary(abs_dr, np.array([0.1, 0.3]))
    key = f"within_{RANGE_CHECK_TOLERANCE_M:g}m_share"
    near = out["range (nearest rule)"]
    assert near[key] == pytest.approx(2 / 3)  # 0.5 and 1.0 of the three supported values
    assert near["no_support_share"] == pytest.approx(0.25) and near["points"] == 4
    assert near["median_abs_dr_m"] == pytest.approx(1.0)
    best = out["range (best lidar point in the window, an oracle)"]
    assert best[key] == pytest.approx(2 / 3) and best["median_abs_dr_m"] == pytest.approx(0.2)
    assert out["doppler (static points)"]["median_abs_dv_mps"] == pytest.approx(0.2)
    empty = _physics_summary(np.full((2, 5), np.nan), np.zeros(0))
    assert np.isnan(empty["range (mean rule)"][key]) and empty["range (mean rule)"]["no_support_share"] == 1.0
    assert np.isnan(empty["doppler (static points)"]["median_abs_dv_mps"])


def test_a_baseline_with_fewer_frames_is_compared_on_the_frames_it_has():
    """Until 2026-12-05 previous-frame (no value on a sequence's first frame: 76 of the demo's 80)
    was compared by its mean over its frames against the model's over all of them, and the table
    did not say over how many frames each row was averaged (a helper's audit)."""
    nan = math.nan
    model = {"chamfer_m": np.array([1.0, 1.0, 1.0, 9.0]), "gospa": np.array([10.0, 10.0, 10.0, 30.0]),
             "f1": np.array([0.5, 0.5, 0.5, 0.0])}
    # previous-frame lacks frame 3, on which the model happens to be bad: over all frames the
    # model (mean Chamfer 3.0) looks worse than previous-frame (2.0), on the same frames it is better
    previous = {"chamfer_m": np.array([2.0, 2.0, 2.0, nan]), "gospa": np.array([12.0, 12.0, 12.0, nan]),
                "f1": np.array([0.4, 0.4, 0.4, nan])}
    empty = {"chamfer_m": np.array([nan, 0.5, 0.5, 0.5]), "gospa": np.array([11.0, 5.0, 5.0, 5.0]),
             "f1": np.array([0.0, 0.9, 0.9, 0.9])}  # no points on frame 0: Chamfer undefined there
    table = R.aggregate_columns({"model": model, "previous-frame": previous, "lidar-subsample": empty})
    assert table["previous-frame"]["chamfer_m"]["n"] == 3 and table["previous-frame"]["chamfer_m"]["mean"] == 2.0
    assert table["previous-frame"]["chamfer_m"]["paired"]["model"] == {
        "n": 3, "mean": 2.0, "median": 2.0, "model_mean": 1.0, "model_median": 1.0}
    assert "paired" not in table["lidar-subsample"]["gospa"]  # the same frames: nothing to pair
    # no frame in common: no comparison (it was by the means over different frames)
    apart = R.aggregate_columns({"model": {"chamfer_m": np.array([5.0, 5.0, nan, nan])},
                                 "previous-frame": {"chamfer_m": np.array([nan, nan, 1.0, 1.0])}})
    assert apart["previous-frame"]["chamfer_m"]["paired"]["model"] == {"n": 0}
    assert R.model_shortfalls(apart) == {"chamfer_m": []}
    shortfalls = R.model_shortfalls(table)
    assert [d["method"] for d in shortfalls["chamfer_m"]] == ["lidar-subsample"]
    assert shortfalls["chamfer_m"][0] == {"method": "lidar-subsample", "value": 0.5, "model_value": 11 / 3, "frames": 3}
    assert all(d["method"] != "previous-frame" for losers in shortfalls.values() for d in losers)
    text = R.shortfall_paragraph(table)
    assert ("Chamfer distance (mean): the model (3) does not beat `lidar-subsample` (0.5 on the 3 frames it has, "
            "the model 3.67 on them).") in text
    md = R.metrics_table_md(table)
    assert "| previous-frame | 3 | " in md and "| model | 4 | " in md
    assert "- `previous-frame` has 3 of the 4 frames (it has no value on the others)" in md
    assert "- `lidar-subsample`: Chamfer over 3 of its 4 frames (undefined where its output or the real radar" in md
    with pytest.raises(ValueError, match="the columns must share the frames"):
        R.aggregate_columns({"model": model, "previous-frame": {k: v[:3] for k, v in previous.items()}})


def test_table_cells_are_mean_then_median_and_the_median_shortfalls_use_medians(tmp_path):
    """The table's header says 'mean / median'; report.json's model_does_not_beat.median and the
    paragraph's '(median)' sentences compare medians (hand-computed: the model's Chamfer [1, 1, 10]
    has mean 4 and median 1; the baseline's [2, 2, 2] both 2)."""
    rows = {"model": [{"chamfer_m": c, "gospa": 10.0, "f1": 0.5} for c in (1.0, 1.0, 10.0)],
            "uniform": [{"chamfer_m": 2.0, "gospa": 20.0, "f1": 0.1} for _ in range(3)]}
    table = R.aggregate(rows)
    md = R.metrics_table_md(table)
    model_row = next(line for line in md.splitlines() if line.startswith("| model |"))
    chamfer_cell = model_row.split("|")[3 + [k for k, _ in R.TABLE_COLUMNS].index("chamfer_m")].strip()
    assert chamfer_cell == "4 / 1"
    jp, mp = R.write_report(tmp_path, "vod", "test", table, {}, {}, {})
    beaten = json.loads(jp.read_text())["model_does_not_beat"]
    assert [d["method"] for d in beaten["mean"]["chamfer_m"]] == ["uniform"]
    assert beaten["median"]["chamfer_m"] == []
    # a median shortfall names the model's median, not its mean
    rows["model"] = [{"chamfer_m": c, "gospa": 10.0, "f1": 0.5} for c in (1.0, 5.0, 5.0)]
    rows["uniform"] = [{"chamfer_m": 4.0, "gospa": 20.0, "f1": 0.1} for _ in range(3)]
    text = R.shortfall_paragraph(R.aggregate(rows))
    assert "Chamfer distance (median): the model (5) does not beat `uniform` (4)." in text
    assert "Chamfer distance (mean)" not in text   # mean 3.67 beats 4


def test_the_ceiling_row_is_paired_with_a_baseline_on_its_own_frames():
    """model-oracle-map is compared with previous-frame over the frames both have, with its own
    values there (not the model's): ceiling [3, 3, 3, 0] vs previous-frame [2, 2, 2, -] is 3 vs 2,
    so the ceiling does not beat it, while the model [1, 1, 1, 9] does (1 vs 2)."""
    nan = math.nan
    table = R.aggregate_columns({"model": {"chamfer_m": np.array([1.0, 1.0, 1.0, 9.0])},
                                 "model-oracle-map": {"chamfer_m": np.array([3.0, 3.0, 3.0, 0.0])},
                                 "previous-frame": {"chamfer_m": np.array([2.0, 2.0, 2.0, nan])}})
    assert R.model_shortfalls(table)["chamfer_m"] == []
    assert R.model_shortfalls(table, model="model-oracle-map")["chamfer_m"] == [
        {"method": "previous-frame", "value": 2.0, "model_value": 3.0, "frames": 3}]


def test_speed_bins_hold_their_lower_edge_and_a_gospa_tie_scores_no_better():
    """'< 0.5 m/s' leaves out 0.5 m/s itself, which opens the next bin; a row whose mean GOSPA equals
    the empty output's scores no better than it."""
    edges = R.SPEED_EDGES_MPS
    speeds = np.array(edges, np.float64)            # each exactly on an edge
    ones = np.ones(len(speeds))
    rows = R.speed_breakdown(speeds, ones, ones, {})
    assert [(r["lo_mps"], r["frames"]) for r in rows] == [(e, 1) for e in edges]
    assert all(r["label"] != f"< {edges[0]:g} m/s" for r in rows)
    rng = np.random.default_rng(5)
    table = R.aggregate({"model": _frames(rng, 2, chamfer=2.0, gospa=17.0, f1=0.1),
                         "uniform": _frames(rng, 2, chamfer=3.0, gospa=16.0, f1=0.1),
                         "no-points": _frames(rng, 2, chamfer=math.nan, gospa=17.0, f1=math.nan)})
    assert "1 of the 2 other rows score no better (`model`)" in R.shortfall_paragraph(table)
