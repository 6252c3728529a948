"""Aggregation of per-frame metrics and the evaluation report (report.json + report.md).

The JSON holds every number (NaN written as null); the Markdown holds one table of per-frame
metrics (mean and median over frames, model rows first), one table of distribution distances, one
of the model's count and metrics by ego speed, the physics checks and a paragraph, computed from
the numbers, naming the baselines the model does not beat on Chamfer, GOSPA and matched F1. Files
are written atomically (temporary file + rename).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from pipeline.baselines import REFERENCE_ROWS
from pipeline.egomotion import STOPPED_MPS
from pipeline.fileio import write_atomic
from pipeline.metrics import FRAME_METRICS, GOSPA_C_M, GOSPA_P, SPHERICAL_COLUMNS

TABLE_COLUMNS: tuple[tuple[str, str], ...] = (
    ("kl", "KL"), ("count_rel_err", "count rel. err"), ("count_sq_rel_err", "L_n"), ("rss_err", "L_a (RSS)"),
    ("chamfer_m", "Chamfer (m)"), ("gospa", "GOSPA (m)"), ("gospa_localisation", "GOSPA loc (m^2)"),
    ("gospa_missed", "GOSPA missed (m^2)"), ("gospa_false", "GOSPA false (m^2)"),
    ("precision", "precision"), ("recall", "recall"), ("f1", "F1"),
)
"""(metric key, Markdown header) of the main table, in order."""

COMPARED: tuple[tuple[str, bool], ...] = (("chamfer_m", False), ("gospa", False), ("f1", True))
"""Metrics of the "where the model does not beat every baseline" paragraph: (key, higher is better)."""

PAIRED_MODELS: tuple[str, ...] = ("model", "model-oracle-map")
"""The model rows compared with the baselines (the shortfall paragraph, the ceiling sentence)."""

SHORT_NAMES: dict[str, str] = {"chamfer_m": "Chamfer", "gospa": "GOSPA", "f1": "F1"}
"""Names of the COMPARED metrics in the report's sentences."""

SPEED_EDGES_MPS: tuple[float, ...] = (STOPPED_MPS, 5.0, 10.0)
"""Ego-speed bin edges (m/s) of the report's by-speed table; below the first edge the ego stands still."""

SPEED_COLUMNS: tuple[tuple[str, str], ...] = (
    ("count_rel_err", "count rel. err"), ("chamfer_m", "Chamfer (m)"), ("gospa", "GOSPA (m)"), ("f1", "F1"))
"""(metric key, header) of the model's means in the by-speed table."""


def metric_columns(frames: Sequence[Mapping[str, float]]) -> dict[str, np.ndarray]:
    """Per-frame metric dicts -> metric -> values (F,) float64, in frame order (NaN where a frame
    lacks the metric); keys in order of first appearance."""
    keys = list(dict.fromkeys(k for f in frames for k in f))
    return {key: np.array([float(f.get(key, math.nan)) for f in frames], dtype=np.float64) for key in keys}


def aggregate(per_frame: Mapping[str, Sequence[Mapping[str, float]]]) -> dict[str, dict[str, dict[str, float]]]:
    """Mean and median over frames of every metric of every method.

    ``per_frame``: method -> list of per-frame metric dicts. Returns method -> metric ->
    {mean, median, n (finite values used), n_nan (frames without a finite value: NaN or inf, or,
    from :func:`aggregate_columns` with aligned columns, a frame the method does not have)}; mean
    and median are NaN when no value is finite. Methods keep their input order.
    """
    return aggregate_columns({method: metric_columns(frames) for method, frames in per_frame.items()})


def aggregate_columns(columns: Mapping[str, Mapping[str, np.ndarray]]) -> dict[str, dict[str, dict[str, Any]]]:
    """:func:`aggregate` of method -> metric -> values (F,) over the method's frames (arrays, not a
    dict per frame: 12 methods' dicts took about 20 kB per evaluated frame), NaN where a method has
    no value for a frame (previous-frame on a sequence's first frame, Chamfer of an empty output).

    Where a baseline and a model row (:data:`PAIRED_MODELS`) do not have a COMPARED metric on the
    same frames, the baseline's entry gets ``paired``: model row -> {n, mean, median (the
    baseline's), model_mean, model_median} over the frames both have, which the comparisons use
    (a mean over other frames is no comparison: previous-frame lacks each test sequence's first frame);
    {n: 0} alone when they have no frame in common."""
    table: dict[str, dict[str, dict[str, Any]]] = {}
    for method, metrics in columns.items():
        row = {}
        for key, column in metrics.items():
            values = np.asarray(column, dtype=np.float64)
            ok = np.isfinite(values)
            row[key] = {
                "mean": float(values[ok].mean()) if ok.any() else math.nan,
                "median": float(np.median(values[ok])) if ok.any() else math.nan,
                "n": int(ok.sum()), "n_nan": int((~ok).sum()),
            }
        table[method] = row
    for model in (m for m in PAIRED_MODELS if m in columns):
        for method in (m for m in columns if not m.startswith("model")):
            for key, _ in COMPARED:
                if key not in columns[model] or key not in columns[method]:
                    continue
                mine, theirs = (np.asarray(columns[m][key], np.float64) for m in (model, method))
                if mine.shape != theirs.shape:
                    raise ValueError(f"aggregate_columns: {model} has {mine.shape[0]} frames of {key}, "
                                     f"{method} {theirs.shape[0]}: the columns must share the frames")
                a, b = np.isfinite(mine), np.isfinite(theirs)
                both = a & b
                if not b.any() or (np.array_equal(both, a) and np.array_equal(both, b)):
                    continue  # nothing to compare, or the same frames
                pair: dict[str, Any] = {"n": int(both.sum())}  # n = 0: no frame to compare them on
                if both.any():
                    pair.update(mean=float(theirs[both].mean()), median=float(np.median(theirs[both])),
                                model_mean=float(mine[both].mean()), model_median=float(np.median(mine[both])))
                table[method][key].setdefault("paired", {})[model] = pair
    return table


def order_methods(methods: Sequence[str]) -> list[str]:
    """Model rows first ('model', then other names starting with 'model'), then the rest in order."""
    first = [m for m in methods if m == "model"] + [m for m in methods if m.startswith("model") and m != "model"]
    return first + [m for m in methods if m not in first]


def _fmt(x: Any) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    x = float(x)
    return f"{x:.3g}" if abs(x) < 1e4 else f"{x:.3e}"


def _fmt_pair(a: float, b: float) -> str:
    """'a vs b' with 3 significant digits, or more (up to 6) where 3 would print unequal values alike."""
    for digits in range(3, 7):
        sa, sb = f"{a:.{digits}g}", f"{b:.{digits}g}"
        if sa != sb or a == b:
            break
    return f"{sa} vs {sb}"


def _jsonable(obj: Any) -> Any:
    """Plain JSON values: NaN/inf -> None, numpy scalars/arrays -> Python numbers/lists."""
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(float(obj)) else None
    return obj


def metrics_table_md(table: Mapping[str, Mapping[str, Mapping[str, float]]]) -> str:
    """Markdown table: one row per method (model first), the frames it has, 'mean / median' per
    metric column; then a line for each row averaged over fewer frames than the most any row has,
    and for each whose Chamfer covers fewer of its frames (undefined where either point set is empty)."""
    header = "| method | frames | " + " | ".join(h for _, h in TABLE_COLUMNS) + " |"
    lines = [header, "|" + "---|" * (len(TABLE_COLUMNS) + 2)]
    frames = {m: _frames_of(table[m]) for m in table}
    most = max(frames.values(), default=0)
    notes = []
    for method in order_methods(list(table)):
        cells = []
        for key, _ in TABLE_COLUMNS:
            s = table[method].get(key)
            cells.append("n/a" if s is None else f"{_fmt(s.get('mean'))} / {_fmt(s.get('median'))}")
        lines.append(f"| {method} | {frames[method]} | " + " | ".join(cells) + " |")
        if frames[method] < most:
            notes.append(f"`{method}` has {frames[method]} of the {most} frames (it has no value on the others); "
                         f"the model is compared with it on the frames it has (below).")
        chamfer = table[method].get("chamfer_m", {}).get("n", 0)
        if 0 < chamfer < frames[method]:
            notes.append(f"`{method}`: Chamfer over {chamfer} of its {frames[method]} frames (undefined where "
                         f"its output or the real radar has no point).")
    return "\n".join(lines) + ("\n\n" + "\n".join(f"- {n}" for n in notes) if notes else "")


def _frames_of(row: Mapping[str, Mapping[str, Any]]) -> int:
    """The frames a method has a value on: those of its GOSPA (defined for any two point sets)."""
    return int(row.get("gospa", {}).get("n", max((s.get("n", 0) for s in row.values()), default=0)))


def distances_table_md(distances: Mapping[str, Mapping[str, float]]) -> str:
    """Markdown table of 1-D Wasserstein distances (synthetic vs real), one row per method."""
    lines = ["| method | " + " | ".join(SPHERICAL_COLUMNS) + " |", "|" + "---|" * (len(SPHERICAL_COLUMNS) + 1)]
    for method in order_methods(list(distances)):
        lines.append(f"| {method} | " + " | ".join(_fmt(distances[method].get(c)) for c in SPHERICAL_COLUMNS) + " |")
    return "\n".join(lines)


def physics_md(physics: Mapping[str, Any]) -> str:
    """Bullet list of physics-check numbers (nested dicts flattened as 'check.key')."""
    lines = []
    for name, value in physics.items():
        if isinstance(value, Mapping):
            items = ", ".join(f"{k} = {_fmt(v)}" for k, v in value.items() if not isinstance(v, (np.ndarray, list)))
            lines.append(f"- {name}: {items}")
        else:
            lines.append(f"- {name}: {_fmt(value)}")
    return "\n".join(lines) if lines else "- (none)"


def _beats(value: float, other: float, higher_is_better: bool) -> bool:
    """``value`` strictly better than ``other`` (a tie does not beat)."""
    return value > other if higher_is_better else value < other


def model_shortfalls(table: Mapping[str, Mapping[str, Mapping[str, float]]], model: str = "model",
                     stat: str = "mean") -> dict[str, list[dict[str, Any]]]:
    """Per compared metric, the non-model methods at least as good as ``model`` on ``stat``.

    A method counts when its value is finite and not worse than the model's (ties count: the
    model does not *beat* it), both over the frames both have (``paired`` entries of
    :func:`aggregate_columns`; one with no frame in common is left out). Methods whose name starts
    with 'model' are variants, not baselines.
    Returns metric -> list of {method, value, model_value, frames (of the pair, or None: all the
    model's)}; metric -> [] when the model wins, and the metric is left out when the model has no
    finite value for it.
    """
    out: dict[str, list[dict[str, Any]]] = {}
    if model not in table:
        return out
    for key, higher in COMPARED:
        mv = table[model].get(key, {}).get(stat, math.nan)
        if not math.isfinite(mv):
            continue
        out[key] = []
        for method, row in table.items():
            if method.startswith("model") or method in REFERENCE_ROWS:
                continue
            pair = row.get(key, {}).get("paired", {}).get(model)
            if pair is not None and pair["n"] == 0:
                continue  # no frame in common: no comparison
            bv, mine = (pair[stat], pair[f"model_{stat}"]) if pair else (row.get(key, {}).get(stat, math.nan), mv)
            if math.isfinite(bv) and not _beats(mine, bv, higher):
                out[key].append({"method": method, "value": bv, "model_value": mine,
                                 "frames": pair["n"] if pair else None})
    return out


def shortfall_paragraph(table: Mapping[str, Mapping[str, Mapping[str, float]]]) -> str:
    """The "where the model does not beat every baseline" text, from the means and medians."""
    if "model" not in table:
        return "No `model` row: nothing to compare."
    names = {"chamfer_m": "Chamfer distance", "gospa": "GOSPA", "f1": "matched F1"}
    sentences, oracle = [], False
    for stat in ("mean", "median"):
        for key, losers in model_shortfalls(table, stat=stat).items():
            oracle |= any("oracle" in d["method"] for d in losers)
            if losers:
                who = ", ".join(f"`{d['method']}` ({_fmt(d['value'])}" + (
                    f" on the {d['frames']} frames it has, the model {_fmt(d['model_value'])} on them)"
                    if d["frames"] is not None else ")") for d in losers)
                sentences.append(f"{names[key]} ({stat}): the model ({_fmt(table['model'][key][stat])}) "
                                 f"does not beat {who}.")
    if not sentences:
        return ("The model beats every baseline on Chamfer distance, GOSPA and matched F1 (mean and median)."
                + _gospa_scale_sentence(table))
    note = " Oracle-count rows are given the true count, an advantage the model does not have." if oracle else ""
    return (" ".join(sentences) + note + _placement_sentence(table) + _ceiling_sentence(table)
            + _gospa_scale_sentence(table))


def _gospa_scale_sentence(table: Mapping[str, Mapping[str, Mapping[str, float]]], empty: str = "no-points") -> str:
    """How the rows' mean GOSPA compares with emitting nothing (the ``empty`` row), and why it can win."""
    base = table.get(empty, {}).get("gospa", {}).get("mean", math.nan)
    if not math.isfinite(base):
        return ""
    rows = [m for m in order_methods(list(table)) if m != empty
            and math.isfinite(table[m].get("gospa", {}).get("mean", math.nan))]
    worse = [m for m in rows if table[m]["gospa"]["mean"] >= base]
    unmatched = GOSPA_C_M ** GOSPA_P / 2.0
    where = (f"{len(worse)} of the {len(rows)} other rows score no better ({', '.join(f'`{m}`' for m in worse)})"
             if worse else "every other row scores better")
    return (f" For scale, `{empty}` (an empty output) has a mean GOSPA of {_fmt(base)} m, and {where}: "
            f"every point left unassigned, synthetic or real, costs c^p/2 = {_fmt(unmatched)} m^2 "
            f"(c = {_fmt(GOSPA_C_M)} m), so a synthetic point lowers GOSPA only where it lands within c of a "
            "real point that would otherwise be missed, and while most points miss, fewer points score "
            "better. Read GOSPA next to the counts and F1.")


def _ceiling_sentence(table: Mapping[str, Mapping[str, Mapping[str, float]]], ceiling: str = "model-oracle-map") -> str:
    """Which baselines even a perfect Dis-Net (the ``ceiling`` row) does not beat, on the means."""
    if ceiling not in table:
        return ""
    parts = [f"{SHORT_NAMES[key]} (" + ", ".join(f"`{d['method']}`" for d in losers) + ")"
             for key, losers in model_shortfalls(table, model=ceiling).items() if losers]
    if not parts:
        return (f" `{ceiling}` (the frame's real heatmap and count) beats every baseline on the means: "
                "a better Dis-Net can close these gaps.")
    return (f" Even `{ceiling}` (the frame's real heatmap and count, i.e. a perfect Dis-Net) does not beat, "
            f"on the means: {'; '.join(parts)}. Those gaps are out of reach of any map the method can learn.")


def speed_breakdown(speed_mps: np.ndarray, real_count: np.ndarray, model_count: np.ndarray,
                    model_metrics: Mapping[str, np.ndarray],
                    edges_mps: Sequence[float] = SPEED_EDGES_MPS) -> list[dict[str, Any]]:
    """The model's count and metrics per ego-speed bin (a stopped ego is where a radar loses its
    static world to the zero-Doppler filter, and where a count learnt mostly in motion can fail).

    ``speed_mps`` (F,) ego speed |v| per frame, ``real_count`` (F,) real points, ``model_count``
    (F,) the model's count, ``model_metrics`` metric -> the model's values (F,) (:func:`metric_columns`),
    all in one frame order. Returns one dict per non-empty bin: label, lo_mps, hi_mps (inf for the last), frames,
    real_count and model_count (means), and the mean of every SPEED_COLUMNS metric (finite values);
    frames without a finite speed form a last bin labelled 'unknown' (lo_mps and hi_mps NaN).
    """
    speed = np.asarray(speed_mps, np.float64)
    real, pred = np.asarray(real_count, np.float64), np.asarray(model_count, np.float64)
    columns = {key: np.asarray(model_metrics.get(key, np.full(len(speed), math.nan)), np.float64)
               for key, _ in SPEED_COLUMNS}
    if not all(speed.shape == real.shape == pred.shape == c.shape for c in columns.values()):
        raise ValueError(f"speed_breakdown: {speed.shape}, {real.shape}, {pred.shape} and "
                         f"{[c.shape for c in columns.values()]} frames differ")
    bounds = [0.0, *edges_mps, math.inf]
    bins = [(_speed_label(lo, hi), lo, hi, np.flatnonzero((speed >= lo) & (speed < hi)))
            for lo, hi in zip(bounds[:-1], bounds[1:])]
    bins.append(("unknown", math.nan, math.nan, np.flatnonzero(~np.isfinite(speed))))
    rows = []
    for label, lo, hi, idx in bins:
        if idx.size == 0:
            continue
        row = {"label": label, "lo_mps": lo, "hi_mps": hi, "frames": int(idx.size),
               "real_count": float(real[idx].mean()), "model_count": float(pred[idx].mean())}
        for key, _ in SPEED_COLUMNS:
            v = columns[key][idx]
            row[key] = float(v[np.isfinite(v)].mean()) if np.isfinite(v).any() else math.nan
        rows.append(row)
    return rows


def _speed_label(lo: float, hi: float) -> str:
    if lo == 0:
        return f"< {_fmt(hi)} m/s"
    return f">= {_fmt(lo)} m/s" if math.isinf(hi) else f"{_fmt(lo)}-{_fmt(hi)} m/s"


def speed_table_md(rows: Sequence[Mapping[str, Any]]) -> str:
    """Markdown table of :func:`speed_breakdown` rows."""
    lines = ["| ego speed | frames | real count | model count | " + " | ".join(h for _, h in SPEED_COLUMNS) + " |",
             "|" + "---|" * (4 + len(SPEED_COLUMNS))]
    for r in rows:
        lines.append(f"| {r['label']} | {r['frames']} | {_fmt(r['real_count'])} | {_fmt(r['model_count'])} | "
                     + " | ".join(_fmt(r[k]) for k, _ in SPEED_COLUMNS) + " |")
    return "\n".join(lines)


def _placement_sentence(table: Mapping[str, Mapping[str, Mapping[str, float]]],
                        model: str = "model-oracle-count", baseline: str = "mean-map-oracle-count") -> str:
    """Like for like, both given the true count: does the model's map place points better than the
    mean map (the comparison the oracle-count rows exist for)?"""
    if model not in table or baseline not in table:
        return ""
    won, lost = [], []
    for key, higher in COMPARED:
        mv, bv = (table[m].get(key, {}).get("mean", math.nan) for m in (model, baseline))
        if math.isfinite(mv) and math.isfinite(bv):
            (won if _beats(mv, bv, higher) else lost).append(f"{SHORT_NAMES[key]} {_fmt_pair(mv, bv)}")
    if not won and not lost:
        return ""
    text = f" Given the true count, like for like, `{model}` against `{baseline}` (means):"
    if won:
        text += f" better on {', '.join(won)}"
    if lost:
        text += ("; " if won else " ") + f"not better on {', '.join(lost)}"
    return text + "."


def write_report(out_dir: str | Path, dataset: str, split: str,
                 table: Mapping[str, Mapping[str, Mapping[str, float]]],
                 distances: Mapping[str, Mapping[str, float]], physics: Mapping[str, Any],
                 meta: Mapping[str, Any], by_speed: Sequence[Mapping[str, Any]] = ()) -> tuple[Path, Path]:
    """Write ``report.json`` and ``report.md`` into ``out_dir``; returns their paths.

    ``table`` from :func:`aggregate`; ``distances`` method -> {range_m, azimuth_rad, ...}
    (:func:`pipeline.metrics.distribution_distances`); ``physics`` check name -> dict of numbers
    (arrays such as per-point residuals are kept in the JSON only); ``meta`` free-form run facts
    (frames, config fingerprint, counts of skipped frames...); ``by_speed`` rows of
    :func:`speed_breakdown` (the section is left out when empty).
    """
    out = Path(out_dir)
    shortfalls = {stat: model_shortfalls(table, stat=stat) for stat in ("mean", "median")}
    doc = {"dataset": dataset, "split": split, "metrics": table, "metric_keys": list(FRAME_METRICS),
           "distribution_distances": distances, "physics_checks": physics,
           "model_does_not_beat": shortfalls, "by_ego_speed": list(by_speed), "meta": meta}
    json_path, md_path = out / "report.json", out / "report.md"
    write_atomic(json_path, json.dumps(_jsonable(doc), indent=2, allow_nan=False) + "\n")
    meta_lines = "\n".join(f"- {k}: {v}" for k, v in meta.items())
    md = (
        f"# Fidelity report: {dataset} ({split})\n\n{meta_lines}\n\n"
        "## Per-frame metrics (mean / median over frames)\n\n"
        "Lower is better except precision, recall and F1. L_n is the mean of the squared relative "
        "count error; GOSPA parts are squared-metre contributions summing to GOSPA^2.\n\n"
        f"{metrics_table_md(table)}\n\n"
        "## Distribution distances (1-D Wasserstein; each method against the real points of the frames it has)\n\n"
        f"{distances_table_md(distances)}\n\n"
        + (f"## The model by ego speed (means over frames)\n\n{speed_table_md(by_speed)}\n\n" if by_speed else "")
        + f"## Physics checks (real frames)\n\n{physics_md(physics)}\n\n"
        + f"## Where the model does not beat every baseline\n\n{shortfall_paragraph(table)}\n"
    )
    write_atomic(md_path, md)
    return json_path, md_path
