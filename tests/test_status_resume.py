"""`pipeline status` of a train stage killed mid-run: what the next run goes on from."""

from __future__ import annotations

import shutil

import pytest

from pipeline.config import load_config
from pipeline.errors import StageInterrupted
from pipeline.executor import Executor, RunEnv
from pipeline.inspection import cache_status
from pipeline.runner import Pipeline
from stages import all_stages
from tests.test_pipeline_e2e import TINY
from tests.test_remote_cache import _killed_in_the_second_epoch


def _pipe(cache: str, world, staging, **overrides: str) -> Pipeline:
    cfg = load_config("synthetic", {**TINY, "train.nets": "disnet,placenet", "run.staging_dir": str(staging),
                                    **overrides}, environ={})
    return Pipeline(all_stages(), RunEnv(cfg, cache, "synthetic", str(world)), Executor(1), progress=False,
                    log=lambda m: None)


def _train_row(pipe: Pipeline) -> dict:
    return next(r for r in cache_status(pipe) if r["stage"] == "train")


@pytest.mark.parametrize("where", ["local", "remote"])
def test_status_says_which_epochs_an_unfinished_train_resumes_from(tiny_world, tmp_path, monkeypatch, where):
    """A train killed in Dis-Net's second epoch was shown as 'not run', as if hours of training were
    lost. Its status row names each net's last finished epoch, of the epochs now set (raising
    them resumes too), or that the checkpoint is for other settings, from which the net trains
    again; on a remote cache it reads the staging folder of this machine when that holds the last
    run's files."""
    import uuid

    import fsspec

    world = tmp_path / "world"
    shutil.copytree(tiny_world, world)
    cache = str(tmp_path / "cache") if where == "local" else f"memory://status-{uuid.uuid4().hex[:8]}"
    settings = {"train.epochs": "3", "run.checkpoint_upload_s": "3600"}  # remote: no upload before the kill
    pipe = _pipe(cache, world, tmp_path / "staging", **settings)
    pipe.run("patches")
    assert _train_row(pipe).get("resumes_from") is None
    with monkeypatch.context() as patch:
        _killed_in_the_second_epoch(patch)
        with pytest.raises(StageInterrupted):
            pipe.run("train")
    row = _train_row(pipe)
    assert not row["exists"] and row["resumes_from"] == "disnet epoch 1 of 3", row
    # the JSON sidecar of the next epoch's checkpoint, arrived before the checkpoint (one upload
    # sends both, an object store in any order): the run resumes from the checkpoint, epoch 1
    sidecar, = tmp_path.glob("**/disnet/last.json")
    sidecar.write_text(sidecar.read_text().replace('"epoch": 1,', '"epoch": 2,'))
    assert '"epoch": 2,' in sidecar.read_text()
    assert _train_row(pipe)["resumes_from"] == "disnet epoch 1 of 3"
    assert _train_row(_pipe(cache, world, tmp_path / "staging", **{**settings, "train.epochs": "5"}))[
        "resumes_from"] == "disnet epoch 1 of 5"
    assert _train_row(_pipe(cache, world, tmp_path / "staging", **{**settings, "train.epochs": "0"}))[
        "resumes_from"] == "disnet epoch 1, more than the 0 now asked (trains again)"  # a fresh run of 0
    assert _train_row(_pipe(cache, world, tmp_path / "staging", **{**settings, "train.lr": "0.01"}))[
        "resumes_from"] == "disnet epoch 1 for other settings or data (trains again)"
    if where == "remote":  # another machine's staging folder holds nothing: the remote has no checkpoint yet
        assert _train_row(_pipe(cache, world, tmp_path / "elsewhere", **settings)).get("resumes_from") is None
    pipe.run("train")
    assert _train_row(pipe)["exists"] and "resumes_from" not in _train_row(pipe)
    if where == "remote":
        fsspec.filesystem("memory").rm(cache.removeprefix("memory://"), recursive=True)


def test_status_line_of_an_unfinished_train(capsys):
    from pipeline.cli import _print_status_row

    _print_status_row({"stage": "train", "current": False, "exists": False, "resumes_from": "disnet epoch 1 of 3"})
    _print_status_row({"stage": "export", "current": False, "exists": False})
    _print_status_row({"stage": "evaluate", "current": False, "exists": False, "earlier_files": True})
    lines = capsys.readouterr().out.splitlines()
    assert lines == ["train           stale or missing    not finished; resumes from disnet epoch 1 of 3",
                     "export          stale or missing    not run",
                     "evaluate        stale or missing    files of an unfinished or stale run"]


def test_status_of_a_report_made_stale_says_its_files_are_there(tiny_world, tmp_path):
    """A dataset stage marked stale (its upstream recomputed) keeps its files but not its record,
    and status called it 'not run' (until 2026-12-07) beside the report of its earlier run; a stage
    never run still is."""
    world = tmp_path / "world"
    shutil.copytree(tiny_world, world)
    pipe = _pipe(str(tmp_path / "cache"), world, tmp_path / "staging",
                 **{"train.epochs": "1", "train.nets": "disnet,rssnet,placenet"})
    pipe.run("evaluate")
    rows = {r["stage"]: r for r in cache_status(pipe)}
    assert rows["evaluate"]["exists"] and rows["evaluate"]["current"] and "earlier_files" not in rows["evaluate"]
    assert not rows["export"]["exists"] and rows["export"]["earlier_files"] is False
    pipe.run("synthesize", force=True)
    rows = {r["stage"]: r for r in cache_status(pipe)}
    assert (tmp_path / "cache" / "synthetic" / "evaluate" / "report.md").exists()
    assert not rows["evaluate"]["exists"] and rows["evaluate"]["earlier_files"] is True, rows["evaluate"]
    assert rows["export"]["earlier_files"] is False


def test_a_damaged_train_record_names_the_way_that_keeps_the_training(tiny_world, tmp_path):
    """A damaged train/_stage.json stops the run; its message names, beside --force (which trains
    again), deleting the file: the next run then resumes from the checkpoints, trains no epoch
    and gives the same nets."""
    import hashlib

    from pipeline.errors import MetadataError

    world = tmp_path / "world"
    shutil.copytree(tiny_world, world)
    pipe = _pipe(str(tmp_path / "cache"), world, tmp_path / "staging", **{"train.epochs": "2"})
    pipe.run("train")
    train = tmp_path / "cache" / "synthetic" / "train"
    best = {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in train.glob("*/best.safetensors")}
    record = train / "_stage.json"
    record.write_bytes(record.read_bytes()[:40])
    with pytest.raises(MetadataError, match=r"--force` \(or delete the file: the next run resumes from the checkpoints"):
        pipe.run("train")
    record.unlink()
    report = pipe.run("train")[-1]
    cfg = pipe.env.cfg
    assert report.summary["disnet"]["resumed_from"] == cfg.train.epochs == 2
    assert report.summary["placenet"]["resumed_from"] == cfg.placement.epochs > 0
    assert {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in best} == best


def test_status_of_a_train_whose_nets_have_a_patience_or_a_resume_point_inside_an_epoch(tmp_path, monkeypatch):
    """With train.patience, a net whose checkpoint already ended its run (best epoch that far back)
    is shown as done, and one trained past the epoch where the patience now set would have stopped
    it with another best epoch trains again (pipeline.continuation), with the reason; a checkpoint
    saved inside an epoch (train.checkpoint_every_s) says how far into it."""
    import torch

    from pipeline import checkpoint as ckpt
    from pipeline.dirstore import DirStore
    from stages import train as train_stage

    monkeypatch.setattr(train_stage, "training_fingerprint", lambda inputs, cfg, net: "fp")
    curves = [{"epoch": e, "val_loss": v, "train_loss": 1.0} for e, v in enumerate((3.0, 1.0, 2.0, 2.5, 0.5), 1)]
    for net, upto in (("disnet", 4), ("rssnet", 5)):
        ckpt.save_checkpoint(tmp_path / net / "last.safetensors", {"w": torch.zeros(1)},
                             {"net": net, "fingerprint": "fp", "epoch": upto, "selection": "val",
                              "best_epoch": 2 if upto == 4 else 5, "curves": curves[:upto]})

    def said(**settings: str) -> str | None:
        cfg = load_config("synthetic", {"train.nets": "disnet,rssnet", "train.epochs": "8", **settings}, environ={})
        return train_stage.resume_point(None, cfg, DirStore(str(tmp_path)))

    assert said() == "disnet epoch 4 of 8, rssnet epoch 5 of 8"
    assert said(**{"train.patience": "2"}) == (
        "disnet done, stopped early after epoch 4 of 8, rssnet epoch 5: its best epoch, 5, came after epoch 4, "
        "where a patience of 2 stops with epoch 2 best (trains again)")
    assert said(**{"train.patience": "3"}) == "disnet epoch 4 of 8, rssnet epoch 5 of 8"
    # a resume point inside an epoch (train.checkpoint_every_s): how far into it
    ckpt.save_checkpoint(tmp_path / "rssnet" / "last.safetensors", {"w": torch.zeros(1)},
                         {"net": "rssnet", "fingerprint": "fp", "epoch": 5, "selection": "val", "best_epoch": 5,
                          "curves": curves, "partial": {"epoch": 6, "windows": 3, "batches": 24, "of_batches": 40}})
    assert said() == "disnet epoch 4 of 8, rssnet epoch 5 of 8 and 24 of 40 batches of epoch 6"
