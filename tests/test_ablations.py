"""`pipeline ablate`: the paper's Tables II and III trained on a tiny synthetic world, every variant
with its own settings, the report written, and a second run resuming instead of training again."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from pipeline.cli import main
from pipeline.checkpoint import read_meta
from pipeline.dirstore import RUN_TOKEN
from stages.ablations import TABLE2, TABLE3, _slug, markdown
from tests.test_pipeline_e2e import TINY


@pytest.fixture(scope="module")
def world(tiny_world, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("world") / "world"
    shutil.copytree(tiny_world, root)
    return root


def _ablate(world: Path, cache: Path, *extra: str):
    sets = [arg for key, value in TINY.items() for arg in ("--set", f"{key}={value}")]
    return CliRunner().invoke(main, ["ablate", "--dataset", "synthetic", "--data-root", str(world),
                                     "--cache", str(cache), "--workers", "1", *sets, *extra])


def test_ablate_trains_every_variant_with_its_settings_and_resumes(world, tmp_path):
    first = _ablate(world, tmp_path / "cache")
    assert first.exit_code == 0, first.output
    out = tmp_path / "cache" / "synthetic" / "ablations"
    assert f"ablations: {out / 'ablations.md'}" in first.output
    results = json.loads((out / "ablations.json").read_text())
    assert [r["variant"] for r in results["table2"]] == [name for name, _ in TABLE2]
    assert [r["variant"] for r in results["table3"]] == [name for name, _ in TABLE3]
    assert all(math.isfinite(r["L_KL"]) and math.isfinite(r["L_n"]) for r in results["table2"])
    assert all(math.isfinite(r["L_a"]) and r["L_a"] >= 0 for r in results["table3"])
    # each variant trained a net built with its own inputs (recorded in its checkpoint)
    for name, overrides in (*TABLE2, *TABLE3):
        arch = read_meta(out / _slug(name) / "best.safetensors")["arch"]
        for key, value in overrides.items():
            assert arch[key.split(".")[1]] == (value in ("true", "1")), (name, key, arch)
    assert len({r["L_a"] for r in results["table3"]}) > 1  # different inputs, different nets
    # a line as each variant is done (until 2026-12-07 a log showed none: the bars name no variant)
    base = results["baselines"]
    said = [line for line in first.output.splitlines() if line.startswith("ablate ")]
    assert said[0] == (f"ablate          baselines on the test split: mean training map L_KL {base['mean_map_kl']:.4f}, "
                       f"mean training count L_n {base['mean_count_L_n']:.4f}, "
                       f"median training RSS L_a {base['median_rss_L_a']:.3e}"), said[0]
    said = said[1:]
    n = len(TABLE2) + len(TABLE3)
    assert len(said) == n, first.output
    for k, (line, r) in enumerate(zip(said, results["table2"] + results["table3"]), 1):
        losses = (f"test L_KL {r['L_KL']:.4f}, L_n {r['L_n']:.4f}" if "L_KL" in r else f"test L_a {r['L_a']:.3e}")
        assert re.fullmatch(rf"ablate +{k}/{n} {re.escape(r['variant'])}: {losses} \(best epoch {r['best_epoch']}\), "
                            rf"trained epochs 1-{TINY['train.epochs']}, \d+ s", line), line
    report = (out / "ablations.md").read_text()
    assert "## Table II: Dis-Net" in report and "## Table III: RSS-Net" in report
    rows = [line for line in report.splitlines() if line.startswith("| ")]
    assert len(rows) == 1 + len(TABLE2) + 1 + 1 + len(TABLE3) + 1  # a header, the variants and a baseline, per table
    assert f"| baseline: mean training map and count | {base['mean_map_kl']:.4f} | {base['mean_count_L_n']:.4f} |" \
        in report and f"| baseline: median training RSS | {base['median_rss_L_a']:.3e} |" in report, report
    assert "nan" not in report  # the paper has no values for the synthetic world: left empty
    for table in report.split("## ")[1:]:  # every row as many cells as its header (Table II's had one too few)
        cells = [line.count("|") for line in table.splitlines() if line.startswith("|")]
        assert len(set(cells)) == 1, table
    astyx = markdown(results, "astyx")  # next to the paper's Astyx values
    assert "| image + speed |" in astyx and "| 0.2271 | 0.4499 |" in astyx and "| 1.45e-02 |" in astyx
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("*.safetensors")}
    again = _ablate(world, tmp_path / "cache", "--tables", "3")
    assert again.exit_code == 0, again.output
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*.safetensors")} == stamps  # resumed: nothing retrained
    rerun = json.loads((out / "ablations.json").read_text())
    said = [line for line in again.output.splitlines() if line.startswith("ablate ")][1:]
    assert len(said) == len(TABLE3) and all(f"already trained ({TINY['train.epochs']} epochs)" in s for s in said), said
    assert said[0].startswith("ablate          1/7 Cam: test L_a "), said
    assert rerun["table2"] == [] and [r["L_a"] for r in rerun["table3"]] == [r["L_a"] for r in results["table3"]]


@pytest.mark.parametrize("tables", ["4", "", "2,x"])
def test_ablate_refuses_unknown_tables_before_any_work(world, tmp_path, tables):
    out = _ablate(world, tmp_path / "cache", "--tables", tables)
    assert out.exit_code == 2 and "--tables" in out.output and "2 (Dis-Net), 3 (RSS-Net)" in out.output, out.output
    assert not (tmp_path / "cache").exists()


def test_ablate_on_a_remote_cache_trains_in_a_staging_folder_and_uploads(world, tmp_path):
    """On a remote (fsspec) cache ablate trains its variants in a local staging folder under
    run.staging_dir, uploads it and names the remote report (until 2026-12-06 it refused such a
    cache); run again on the same machine it resumes there instead of training again."""
    import uuid

    import fsspec

    url = f"memory://ablate-{uuid.uuid4().hex[:8]}"
    staging = tmp_path / "staging"
    first = _ablate(world, url, "--tables", "2", "--set", f"run.staging_dir={staging}")
    assert first.exit_code == 0, first.output
    assert f"ablations: {url}/synthetic/ablations/ablations.md" in first.output
    fs, root = fsspec.filesystem("memory"), url.removeprefix("memory://") + "/synthetic/ablations"
    results = json.loads(fs.cat_file(f"{root}/ablations.json"))
    assert [r["variant"] for r in results["table2"]] == [name for name, _ in TABLE2] and results["table3"] == []
    staged = next(staging.glob("ablations-*/staging"))
    for name, _ in TABLE2:
        assert fs.cat_file(f"{root}/{_slug(name)}/best.safetensors") == \
            (staged / _slug(name) / "best.safetensors").read_bytes()
    sets = [arg for key, value in {**TINY, "run.staging_dir": str(staging)}.items() for arg in ("--set", f"{key}={value}")]
    status = CliRunner().invoke(main, ["status", "--dataset", "synthetic", "--data-root", str(world), "--cache", url,
                                       *sets])
    assert f"report {url}/synthetic/ablations/ablations.md (table 2, 1 seed): all 2 runs trained" in status.output
    stamps = {p: p.stat().st_mtime_ns for p in staged.rglob("*.safetensors")}
    again = _ablate(world, url, "--tables", "2", "--set", f"run.staging_dir={staging}")
    assert again.exit_code == 0, again.output
    assert {p: p.stat().st_mtime_ns for p in staged.rglob("*.safetensors")} == stamps  # resumed: nothing retrained
    (staged / RUN_TOKEN).unlink()  # as an ablate before 2026-12-07 left its staging folder: kept too
    fs.rm(f"{root}/{RUN_TOKEN}")
    assert _ablate(world, url, "--tables", "2", "--set", f"run.staging_dir={staging}").exit_code == 0
    assert {p: p.stat().st_mtime_ns for p in staged.rglob("*.safetensors")} == stamps
    fs.rm(url.removeprefix("memory://"), recursive=True)


def test_ablate_cut_off_on_a_remote_cache_goes_on_on_another_machine(world, tmp_path, monkeypatch):
    """On a remote cache ablate's runs stayed in the staging folder of the machine that trained them
    until the whole ablate finished (until 2026-12-07): cut off, it began again on any other
    machine. Now each run's checkpoints are uploaded as it trains and once it is done, and an
    ablate on another machine downloads them and goes on: the finished run is not trained again."""
    import uuid

    import fsspec

    import stages.ablations as ablations

    url = f"memory://ablate-{uuid.uuid4().hex[:8]}"
    fs, root = fsspec.filesystem("memory"), url.removeprefix("memory://") + "/synthetic/ablations"
    train_and_test, calls = ablations._train_and_test, []

    def cut_off_at_the_second_run(*args, **kwargs):
        calls.append(args[4].name)
        if len(calls) == 2:
            raise KeyboardInterrupt  # Ctrl-C, or the machine gone, as the second run begins
        return train_and_test(*args, **kwargs)

    with monkeypatch.context() as patch:
        patch.setattr(ablations, "_train_and_test", cut_off_at_the_second_run)
        first = _ablate(world, url, "--tables", "2", "--set", f"run.staging_dir={tmp_path / 'machine-a'}")
    assert first.exit_code == 130 and calls == [_slug(name) for name, _ in TABLE2], first.output
    machine_a = next((tmp_path / "machine-a").glob("ablations-*/staging"))
    uploaded = sorted(f.removeprefix(f"/{root}/") for f in fs.find(root) if not f.endswith(RUN_TOKEN))
    assert uploaded == [f"image_only/{name}" for name in ("best.json", "best.safetensors", "last.json",
                                                            "last.safetensors")], uploaded
    for name in uploaded:
        assert fs.cat_file(f"{root}/{name}") == (machine_a / name).read_bytes(), name
    sets = [arg for key, value in {**TINY, "run.staging_dir": str(tmp_path / "machine-b")}.items()
            for arg in ("--set", f"{key}={value}")]
    status = CliRunner().invoke(main, ["status", "--dataset", "synthetic", "--data-root", str(world), "--cache", url,
                                       *sets])
    assert "ablations".ljust(16) + "unfinished, no report yet: 1 run(s) begun, 1 of them trained; " in status.output
    second = _ablate(world, url, "--tables", "2", "--set", f"run.staging_dir={tmp_path / 'machine-b'}")
    assert second.exit_code == 0, second.output
    said = [line for line in second.output.splitlines() if line.startswith("ablate ")]
    assert said[0] == f"ablate          resuming from 4 file(s) of {url}/synthetic/ablations", said
    assert "1/2 image only: " in said[2] and f"already trained ({TINY['train.epochs']} epochs), " in said[2], said
    assert "2/2 image + speed: " in said[3] and f"trained epochs 1-{TINY['train.epochs']}" in said[3], said
    machine_b = next((tmp_path / "machine-b").glob("ablations-*/staging"))
    assert (machine_b / "image_only" / "best.safetensors").read_bytes() == \
        (machine_a / "image_only" / "best.safetensors").read_bytes()
    assert json.loads(fs.cat_file(f"{root}/ablations.json"))["table2"][1]["variant"] == "image + speed"
    # status reads a staging folder only where the last ablate begun on the remote ran in it
    fs.rm(f"{root}/ablations.json")  # as if machine b had been cut off before the report

    def status_on(machine: str) -> str:
        sets = [arg for key, value in {**TINY, "run.staging_dir": str(tmp_path / machine)}.items()
                for arg in ("--set", f"{key}={value}")]
        out = CliRunner().invoke(main, ["status", "--dataset", "synthetic", "--data-root", str(world), "--cache",
                                        url, *sets])
        return next(line for line in out.output.splitlines() if line.startswith("ablations "))

    assert "2 run(s) begun, 2 of them trained" in status_on("machine-a")  # the remote's, not a's one run
    fs.pipe(f"{root}/{RUN_TOKEN}", (machine_a / RUN_TOKEN).read_bytes())  # as if a had begun the last ablate
    assert "1 run(s) begun, 1 of them trained" in status_on("machine-a")
    fs.rm(f"{root}/{RUN_TOKEN}")  # the remote's token gone, a's kept: ablate would go on from the remote
    assert "2 run(s) begun, 2 of them trained" in status_on("machine-a")
    fs.rm(url.removeprefix("memory://"), recursive=True)


def test_ablate_with_several_seeds_gives_each_run_and_their_mean(world, tmp_path):
    """--seeds N trains each variant with train.seed, train.seed + 1, ...: the first seed in the
    variant's own folder (a one-seed run's, which it resumes), the others beside it; the row holds
    the mean of the runs and the report their range. One run per variant did not rank Table II on
    Astyx (2026-12-07: a row's L_KL moved by up to 0.11 with the seed)."""
    cache = tmp_path / "cache"
    assert _ablate(world, cache, "--tables", "2").exit_code == 0
    out = cache / "synthetic" / "ablations"
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("*.safetensors")}
    again = _ablate(world, cache, "--tables", "2", "--seeds", "2", "--set", "train.seed=0")
    assert again.exit_code == 0, again.output
    said = [line for line in again.output.splitlines() if line.startswith("ablate ")][1:]
    assert [re.sub(r": .*", "", line.split(maxsplit=2)[2]) for line in said] == \
        ["image only, seed 0", "image only, seed 1", "image + speed, seed 0", "image + speed, seed 1"], said
    assert ["already trained" in line for line in said] == [True, False, True, False], said  # seed 0 resumed
    assert all(stamps[p] == p.stat().st_mtime_ns for p in stamps)
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == \
        ["image___speed", "image___speed-seed1", "image_only", "image_only-seed1"]
    results = json.loads((out / "ablations.json").read_text())
    assert results["meta"]["seeds"] == [0, 1]
    for row in results["table2"]:
        assert [r["seed"] for r in row["runs"]] == [0, 1]
        assert row["runs"][0]["L_KL"] != row["runs"][1]["L_KL"]  # another seed, another net
        for key in ("L_KL", "L_n"):
            assert row[key] == pytest.approx(np.mean([r[key] for r in row["runs"]]))
    report = (out / "ablations.md").read_text()
    assert "2 seeds (train.seed 0, 1): each loss is their mean" in report
    first = results["table2"][0]
    low, high = sorted(r["L_KL"] for r in first["runs"])
    assert f"| image only | {first['L_KL']:.4f} ({low:.4f} - {high:.4f}) |" in report, report
    # the baselines are the train stage's, on the same test split
    sets = [arg for key, value in TINY.items() for arg in ("--set", f"{key}={value}")]
    trained = CliRunner().invoke(main, ["run", "train", "--dataset", "synthetic", "--data-root", str(world),
                                        "--cache", str(cache), "--workers", "1", *sets])
    assert trained.exit_code == 0, trained.output
    stage = json.loads((cache / "synthetic" / "train" / "metrics.json").read_text())["baselines_test"]
    assert set(results["baselines"]) == set(stage) and len(stage) >= 5
    assert all(results["baselines"][k] == pytest.approx(stage[k], rel=1e-12) for k in stage), (results["baselines"], stage)


def test_the_report_says_how_models_were_selected():
    """Said 'models selected on val' also where the split had no val frame (the two View-of-Delft
    frames: 1 train, 1 test), where training picks its best epoch on the training loss."""
    results = {"table2": [], "table3": [], "meta": {"dataset": "vod", "frames": {"train": 1, "val": 0, "test": 1},
                                                    "split_rule": "block", "epochs": 2, "hardware": "CPU",
                                                    "total_seconds": 6.0}}
    assert "no val frames: models selected on their training loss" in markdown(results, "vod")
    results["meta"]["frames"]["val"] = 3
    assert "Test split; models selected on val." in markdown(results, "vod")


def test_the_report_says_how_many_runs_a_patience_stopped_early():
    """With train.patience the report's epochs are a most: it says how many runs stopped early
    (runs without the record, written before 2026-12-07, count as having run every epoch); without
    a patience it says the epochs alone."""
    run = {"seed": 0, "L_KL": 0.3, "L_n": 0.2, "best_epoch": 2, "seconds": 1.0}
    results = {"table2": [{"variant": "image", "L_KL": 0.3, "L_n": 0.2, "best_epoch": 2, "seconds": 2.0,
                           "runs": [{**run, "epochs": 5}, {**run, "epochs": 12}]}],
               "table3": [{"variant": "cam", "L_a": 0.02, "best_epoch": 3, "seconds": 1.0,
                           "runs": [{"seed": 0, "L_a": 0.02, "best_epoch": 3, "seconds": 1.0}]}],
               "meta": {"dataset": "astyx", "frames": {"train": 81, "val": 15, "test": 45}, "split_rule": "block",
                        "epochs": 12, "patience": 3, "hardware": "CPU", "total_seconds": 60.0}}
    assert "12 epochs (or fewer: train.patience 3 stopped 1 of 3 runs early), CPU" in markdown(results, "astyx")
    results["meta"]["patience"] = 0
    assert "12 epochs, CPU" in markdown(results, "astyx")


def test_status_says_what_the_ablations_folder_holds(world, tmp_path):
    """`pipeline status` did not mention ablate's folder (until 2026-12-07): a run of several minutes
    per variant, cut off or finished, left no trace in it. Now a line says whether a report is there
    and how many of its runs are trained with the command's settings and the data as they are, or
    that a cut-off ablate left runs to go on from."""
    cache = tmp_path / "cache"
    sets = [arg for key, value in TINY.items() for arg in ("--set", f"{key}={value}")]

    def status(*extra: str) -> str:
        out = CliRunner().invoke(main, ["status", "--dataset", "synthetic", "--data-root", str(world), "--cache",
                                        str(cache), *sets, *extra])
        assert out.exit_code == 0, out.output
        return "\n".join(line for line in out.output.splitlines() if line.startswith("ablations "))

    assert _ablate(world, cache, "--tables", "2").exit_code == 0
    assert status() == "ablations".ljust(16) + "report {} (table 2, 1 seed): all 2 runs trained with these settings " \
        "and data".format(cache / "synthetic" / "ablations" / "ablations.md")
    out = CliRunner().invoke(main, ["status", "--dataset", "synthetic", "--data-root", str(world), "--cache",
                                    str(cache), *sets, "--json"])
    assert out.exit_code == 0, out.output
    rows = json.loads(out.output)
    assert "ablations" not in [row["stage"] for row in rows[:-1]]  # the stages' rows, then the folder's
    assert rows[-1] == {"stage": "ablations", "folder": str(cache / "synthetic" / "ablations"),
                        "report": str(cache / "synthetic" / "ablations" / "ablations.md"), "tables": ["2"],
                        "seeds": [0], "runs": 2, "trained": 2, "part-trained": 0,
                        "retrains": 0, "not trained": 0, "unreadable": 0}
    more = int(TINY["train.epochs"]) + 1
    assert status("--set", f"train.epochs={more}").endswith(
        ": 0 of 2 runs trained with these settings and data; 2 part-trained (resume)")
    assert status("--set", "train.lr=0.5").endswith(
        ": 0 of 2 runs trained with these settings and data; 2 for other settings or data (train again)")
    report = cache / "synthetic" / "ablations" / "ablations.json"
    report.write_text('{"table2": [')  # cut short
    assert status().startswith("ablations".ljust(16) + f"an unreadable report {report} (")
    assert status().endswith("; `pipeline ablate` writes it again")
    out = CliRunner().invoke(main, ["status", "--dataset", "synthetic", "--data-root", str(world), "--cache",
                                    str(cache), *sets, "--json"])
    assert json.loads(out.output)[-1]["error"].startswith(f"an unreadable report {report} (")
    report.unlink()  # as if cut off before the report
    (cache / "synthetic" / "ablations" / "image_only" / "last.safetensors").unlink()
    assert status() == "ablations".ljust(16) + "unfinished, no report yet: 2 run(s) begun, 1 of them trained; " \
        "1 not trained; `pipeline ablate` with the same options goes on"
    shutil.rmtree(cache / "synthetic" / "ablations")
    assert status() == ""
