"""The paper's ablations (Table II: Dis-Net with and without ego speed; Table III: RSS-Net input
combinations) over the train stage's data. Not a pipeline stage: `pipeline ablate` runs it after
calibrate, heatmaps and patches, training each variant into ``<cache>/<dataset>/ablations/<variant>``
(resumable like the train stage) and writing ``ablations.md`` / ``ablations.json`` beside them.
Models are selected on the val split; the table reports the test split.
"""

from __future__ import annotations

import json
import platform
import time
from collections import Counter
from posixpath import join
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from pipeline.config import Config
from pipeline.run_report import NAME_WIDTH
from stages.train import disnet_data, frame_table, held_out_baselines, rssnet_data, training_fingerprint, training_mean_map

if TYPE_CHECKING:  # pipeline.training imports torch, which a stage module does not import when loaded
    from pipeline.training import Publish

TABLE2 = (("image only", {"disnet.use_speed": "false"}), ("image + speed", {"disnet.use_speed": "true"}))
TABLE3 = tuple(
    (name, {"rssnet.use_camera": str(c), "rssnet.use_lidar": str(li), "rssnet.use_radar_point": str(rp)})
    for name, c, li, rp in (("Cam", 1, 0, 0), ("Li", 0, 1, 0), ("RP", 0, 0, 1), ("Cam+Li", 1, 1, 0),
                            ("Cam+RP", 1, 0, 1), ("Li+RP", 0, 1, 1), ("Cam+Li+RP (full)", 1, 1, 1)))
PAPER = {  # Song et al., Tables II and III
    "astyx": {"image only": (0.2359, 0.4745), "image + speed": (0.2271, 0.4499), "Cam+Li+RP (full)": 1.45e-2},
    "vod": {"image only": (0.1538, 0.0266), "image + speed": (0.1564, 0.0266), "Cam+Li+RP (full)": 3.95e-3},
    "msc": {"image only": (0.0539, 0.3561), "image + speed": (0.0524, 0.3545), "Cam+Li+RP (full)": 5.16e-8},
}


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name.lower()).strip("_")


def run_ablations(inputs, cfg: Config, out_root: Path, tables: tuple[str, ...] = ("2", "3"),
                  log: Callable[[str], None] = lambda line: None, seeds: int = 1,
                  publish: Publish | None = None) -> dict:
    """Train every variant of the requested tables ``seeds`` times (train.seed, train.seed + 1,
    ...); returns the results and writes the report. A variant's row holds the mean of its seeds'
    test losses and each seed's run (``runs``); ``baselines`` the train stage's held-out baselines
    (the mean training map and count, the median training RSS) on the same test split. The first seed trains into ``<variant>/``, the others
    into ``<variant>-seed<N>/``. ``log`` gets a line as each run is done (its test losses, where it
    resumed, its time): a run of several minutes a variant otherwise shows only the training's
    progress lines, which do not name the variant, and in a log file none at all for a variant
    shorter than run.progress_every_s. With ``publish`` (``out_root`` a local staging folder of a
    remote cache), each run's checkpoints are handed to it while it trains, as the train stage's
    are (run.checkpoint_upload_s), and once it is done: a run cut off resumes on any machine from
    the last upload, and a finished run is not trained again there."""
    table = frame_table(inputs)
    results: dict = {"table2": [], "table3": []}
    disnet = disnet_data(inputs, table)  # (data, split indices)
    idx = disnet[1]
    results["baselines"] = held_out_baselines(inputs, table, idx, cfg, training_mean_map(inputs, idx, cfg))
    log(f"{'ablate':<{NAME_WIDTH}} baselines on the test split: " + ", ".join(
        f"{label} {_fmt(loss, results['baselines'][key])}" for key, (label, loss) in BASELINES.items()
        if key in results["baselines"]))
    variants = [name for t, rows in (("2", TABLE2), ("3", TABLE3)) if t in tables for name, _ in rows]
    seed_list = [cfg.train.seed + k for k in range(seeds)]
    t_start = time.perf_counter()
    for number, rows in (("2", TABLE2), ("3", TABLE3)):
        if number not in tables:
            continue
        data = disnet if number == "2" else (rssnet_data(inputs, table, 0, 1), rssnet_data(inputs, table, 2, 2))
        for name, overrides in rows:
            runs = []
            for seed in seed_list:
                c = cfg.with_overrides({**overrides, "train.seed": str(seed)})
                run, trained = _train_and_test(number, inputs, c, data, out_root / run_folder(name, seed, seed_list),
                                               publish)
                runs.append(run)
                losses = ", ".join(f"{k} {_fmt(k, run[k])}" for k in LOSSES[number])
                log(f"{'ablate':<{NAME_WIDTH}} {variants.index(name) + 1}/{len(variants)} {name}"
                    f"{f', seed {seed}' if seeds > 1 else ''}: test {losses} (best epoch {run['best_epoch']}), "
                    f"{trained}, {run['seconds']:.0f} s")
            results[f"table{number}"].append(
                {"variant": name, **{k: float(np.mean([r[k] for r in runs])) for k in LOSSES[number]},
                 "best_epoch": runs[0]["best_epoch"], "seconds": sum(r["seconds"] for r in runs), "runs": runs})
    results["meta"] = {"dataset": inputs.env.dataset, "frames": {k: int(v) for k, v in zip(
        ("train", "val", "test"), [(table["ok"] & (table["split"] == p)).sum() for p in (0, 1, 2)])},
        "epochs": cfg.train.epochs, "patience": cfg.train.patience, "split_rule": cfg.split.rule,
        "hardware": _hardware(), "seeds": seed_list, "total_seconds": time.perf_counter() - t_start}
    out_root.mkdir(parents=True, exist_ok=True)
    (out_root / REPORT).write_text(json.dumps(results, indent=2, default=float))
    (out_root / MARKDOWN).write_text(markdown(results, cfg.profile))
    return results


def run_folder(variant: str, seed: int, seeds: list[int]) -> str:
    """The folder, under the ablations folder, that the run of ``variant`` with ``seed`` (one of
    ``seeds``) trains into: the variant's own for the first seed, ``<variant>-seed<N>`` for the others."""
    return _slug(variant) if seed == seeds[0] else f"{_slug(variant)}-seed{seed}"


NETS = {"2": "disnet", "3": "rssnet"}
"""The net each table trains."""
REPORT, MARKDOWN = "ablations.json", "ablations.md"
"""The results of a finished `pipeline ablate` in the ablations folder, and its tables."""


def ablation_state(inputs, cfg: Config, folder) -> dict | None:
    """What the ablations folder ``folder`` (a DirStore) holds, for `pipeline status`: ``report``,
    the Markdown tables' path or URL (None without a report: ablate cut off); ``tables`` and
    ``seeds``; ``runs``, the runs the report covers (without one, those whose folders are there),
    and how many of them are ``trained`` with ``cfg`` and the data as they are now
    (stages.train.net_state), ``part-trained``, for other settings or data (``retrains``), ``not
    trained`` or with an ``unreadable`` checkpoint; ``error`` instead where the report cannot be
    read. None when the folder holds nothing. ``ablation_line`` says it in words."""
    from stages.train import checkpoint_meta, net_state

    try:
        present = {name.rstrip("/").rsplit("/", 1)[-1] for name in folder.fs.ls(folder.path, detail=False)}
    except (FileNotFoundError, NotADirectoryError):
        return None
    if not present:
        return None
    report = None
    if REPORT in present:
        try:
            report = json.loads(folder.fs.cat_file(folder.file(REPORT)))
        except (OSError, ValueError) as exc:
            return {"report": None, "error": f"an unreadable report {folder.file(REPORT)} ({exc})"}
    meta = (report or {}).get("meta", {})
    seeds = meta.get("seeds") or _seeds_in(present, cfg.train.seed)
    tables = [t for t in NETS if report is None or report.get(f"table{t}")]
    states: Counter = Counter()
    for number in tables:
        for name, overrides in TABLE2 if number == "2" else TABLE3:
            for seed in seeds:
                sub = run_folder(name, seed, seeds)
                if report is None and sub not in present:
                    continue
                try:
                    ck = checkpoint_meta(folder, f"{sub}/last.safetensors")
                except ValueError:
                    states["unreadable"] += 1
                    continue
                c = cfg.with_overrides({**overrides, "train.seed": str(seed)})
                states["not trained" if ck is None else net_state(inputs, c, NETS[number], ck)] += 1
    where = folder.file(MARKDOWN) if folder.is_local else join(folder.url, MARKDOWN)
    return {"report": where if report is not None else None, "tables": tables, "seeds": seeds,
            "runs": sum(states.values()), **{key: states[key] for key in RUN_STATES}}


RUN_STATES = {"trained": "trained", "part-trained": "part-trained (resume)",
              "retrains": "for other settings or data (train again)", "not trained": "not trained",
              "unreadable": "with an unreadable checkpoint"}
"""The states ablation_state counts the runs in, and how ablation_line says each."""


def ablation_line(state: dict) -> str:
    """`pipeline status`'s line on the ablations folder, from ``ablation_state``."""
    if "error" in state:
        return f"{state['error']}; `pipeline ablate` writes it again"
    runs, tables, seeds = state["runs"], state["tables"], state["seeds"]
    said = ", ".join(f"{state[key]} {text}" for key, text in RUN_STATES.items() if key != "trained" and state[key])
    if state["report"] is None:
        return (f"unfinished, no report yet: {runs} run(s) begun, {state['trained']} of them trained"
                + (f"; {said}" if said else "") + "; `pipeline ablate` with the same options goes on")
    head = (f"report {state['report']} ({'tables 2 and 3' if len(tables) == 2 else f'table {tables[0]}' if tables else 'no table'}, "
            f"{len(seeds)} seed{'s' if len(seeds) > 1 else ''}): ")
    if state["trained"] == runs:
        return head + f"all {runs} runs trained with these settings and data"
    return head + f"{state['trained']} of {runs} runs trained with these settings and data; {said}"


def _seeds_in(names: set[str], first: int) -> list[int]:
    """The seeds whose runs the folder names ``names`` hold: ``first`` (the variants' own folders)
    and each N of a ``<variant>-seed<N>``."""
    more = {int(tail) for head, sep, tail in (n.rpartition("-seed") for n in names) if sep and tail.isdigit()}
    return [first, *sorted(more - {first})]


LOSSES = {"2": ("L_KL", "L_n"), "3": ("L_a",)}
"""The test losses each table reports."""
BASELINES = {"mean_map_kl": ("mean training map L_KL", "L_KL"), "mean_count_L_n": ("mean training count L_n", "L_n"),
             "median_rss_L_a": ("median training RSS L_a", "L_a")}
"""The held-out baselines (stages.train.held_out_baselines) each table shows below its variants:
how they are named, and which loss each is."""


def _train_and_test(number: str, inputs, cfg: Config, data, folder: Path,
                    publish: Publish | None = None) -> tuple[dict, str]:
    """Train table ``number``'s net with ``cfg`` into ``folder`` (resuming what is there), hand its
    checkpoints to ``publish`` (see run_ablations) and test its best epoch: (the run's record: seed,
    test losses, best epoch, seconds; what was trained). ``data``: Dis-Net's (data, split
    indices), or RSS-Net's (train + val, test) samples."""
    from pipeline.inference import load_disnet, load_rssnet
    from pipeline.training import disnet_metrics, publish_checkpoints, rssnet_metrics, train_disnet, train_rssnet

    t0 = time.perf_counter()
    train = train_disnet if number == "2" else train_rssnet
    res = train(cfg, data[0], folder, progress=inputs.progress, publish=publish,
                fingerprint=training_fingerprint(inputs, cfg, NETS[number]))
    if publish is not None and res.epoch > res.resumed_from:  # its last epochs, not yet uploaded
        publish_checkpoints(publish, res.best_path, res.last_path)
    if number == "2":
        frames, idx = data
        m = disnet_metrics(load_disnet(cfg, res.best_path, device="cpu"), frames, idx["test"], cfg.train.alpha)
        losses = {"L_KL": m["kl"], "L_n": m["n"]}
    else:
        test = data[1]
        losses = {"L_a": rssnet_metrics(load_rssnet(cfg, res.best_path, device="cpu"), test, test.train_idx)["a"]}
    trained = (f"trained epochs {res.resumed_from + 1}-{res.epoch}" if res.epoch > res.resumed_from
               else f"already trained ({res.epoch} epochs)")
    if res.stopped_early:
        trained += f" (stopped early: train.patience {cfg.train.patience})"
    return {"seed": cfg.train.seed, **losses, "best_epoch": res.best_epoch, "epochs": res.epoch,
            "seconds": time.perf_counter() - t0}, trained


def _fmt(key: str, value: float) -> str:
    return f"{value:.3e}" if key == "L_a" else f"{value:.4f}"


def _hardware() -> str:
    import torch

    dev = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "CPU"
    return f"{dev}, {platform.processor() or platform.machine()}, torch {torch.__version__}, {torch.get_num_threads()} threads"


def markdown(results: dict, profile: str) -> str:
    """Tables II and III next to the paper's values for the profile's dataset, the held-out
    baselines below the variants; with several seeds each loss is their mean with the lowest and
    highest run in brackets."""
    paper = PAPER.get(profile, {})
    meta = results["meta"]
    base = results.get("baselines", {})
    seeds = meta.get("seeds", [0])
    several = len(seeds) > 1
    runs = [r for t in ("table2", "table3") for row in results.get(t, []) for r in row.get("runs", [])]
    early = sum(r.get("epochs", meta["epochs"]) < meta["epochs"] for r in runs)
    stopping = (f" (or fewer: train.patience {meta['patience']} stopped {early} of {len(runs)} runs early)"
                if meta.get("patience") else "")
    lines = [f"# Ablations: {meta['dataset']}", "",
             f"Frames train/val/test: {meta['frames']['train']}/{meta['frames']['val']}/{meta['frames']['test']} "
             f"(split rule '{meta['split_rule']}'), {meta['epochs']} epochs{stopping}, {meta['hardware']}, "
             f"total {meta['total_seconds'] / 60:.1f} min. Test split; "
             + ("models selected on val." if meta["frames"]["val"] else "no val frames: models selected on their "
                "training loss (pipeline.training).")
             + (f" {len(seeds)} seeds (train.seed {', '.join(map(str, seeds))}): each loss is their mean, "
                f"(lowest - highest) beside it; train time: this run's, the seeds together." if several else ""), ""]

    def cell(r: dict, key: str) -> str:
        if not several:
            return _fmt(key, r[key])
        values = [run[key] for run in r["runs"]]
        return f"{_fmt(key, r[key])} ({_fmt(key, min(values))} - {_fmt(key, max(values))})"

    if results["table2"]:
        lines += ["## Table II: Dis-Net", "", "| input | L_KL | L_n | paper L_KL | paper L_n | train time |",
                  "|---|---|---|---|---|---|"]
        for r in results["table2"]:
            p = paper.get(r["variant"])
            ref = "| | |" if p is None else f"| {p[0]:.4f} | {p[1]:.4f} |"
            lines.append(f"| {r['variant']} | {cell(r, 'L_KL')} | {cell(r, 'L_n')} {ref} {r['seconds']:.0f} s |")
        if "mean_map_kl" in base:
            lines.append(f"| baseline: mean training map and count | {_fmt('L_KL', base['mean_map_kl'])} | "
                         f"{_fmt('L_n', base['mean_count_L_n'])} | | | |")
        lines.append("")
    if results["table3"]:
        lines += ["## Table III: RSS-Net", "", "| inputs | L_a | paper L_a | train time |", "|---|---|---|---|"]
        for r in results["table3"]:
            p = paper.get(r["variant"])
            lines.append(f"| {r['variant']} | {cell(r, 'L_a')} | {'' if p is None else f'{p:.2e}'} | {r['seconds']:.0f} s |")
        if "median_rss_L_a" in base:
            lines.append(f"| baseline: median training RSS | {_fmt('L_a', base['median_rss_L_a'])} | | |")
        lines.append("")
    return "\n".join(lines)
