"""Why an output is not current: the record every output keeps of what it was made with, compared
with the command's (pipeline.staleness, Pipeline.why_stale / forgotten_sets), as status, the
--force --frames refusal and verify say it."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

import tests.fake_stages as fake_stages
from pipeline.config import load_config
from pipeline.errors import ConfigError
from pipeline.executor import Executor, RunEnv
from pipeline.inspection import cache_status
from pipeline.runner import Pipeline
from pipeline.staleness import explain, set_text

IDS = [f"{i:03d}" for i in range(6)]


def make_pipeline(tmp_path: Path, **overrides) -> Pipeline:
    cfg = load_config("synthetic", overrides, environ={})
    env = RunEnv(cfg=cfg, cache_root=str(tmp_path / "cache"), dataset="fake", data_root=str(tmp_path))
    return Pipeline(fake_stages.STAGES, env, Executor(1), progress=False, log=lambda m: None,
                    frame_lister=lambda: list(IDS))


def record(config=None, upstream=None, version=1, **more):
    return {"version": version, "config": config or {}, "upstream": upstream or {}, **more}


# ---- explain, on records ------------------------------------------------------------------------

def test_a_setting_of_another_value_is_named_with_the_set_option_that_gives_it_back():
    old = {"fingerprint": "a", **record({"synth.count": "disnet", "heatmap.sigma_px": [30.0, 30.0], "synth.seed": 3})}
    now = record({"synth.count": "predicted", "heatmap.sigma_px": (50.0, 50.0), "synth.seed": 3})
    why = explain(old, now, "synthetic")
    assert why.text == ("made with synth.count=disnet (this command: predicted), "
                        "heatmap.sigma_px=30.0,30.0 (this command: 50.0,50.0)")
    assert why.sets == ("synth.count=disnet", "heatmap.sigma_px=30.0,30.0") and why.settings_only


def test_set_text_reads_back_as_the_value():
    cfg = load_config("synthetic", {"heatmap.sigma_px": set_text([12.5, 7.0]), "synth.rss_sampling": set_text("mean"),
                                    "disnet.speed_count_prior": set_text(True), "synth.seed": set_text(4)}, environ={})
    assert cfg.heatmap.sigma_px == (12.5, 7.0) and cfg.synth.rss_sampling == "mean"
    assert cfg.disnet.speed_count_prior is True and cfg.synth.seed == 4


def test_keys_the_record_lacks_or_another_reader_uses_are_not_differences():
    """A key added to the stage since (absent from the record) is not compared, except one of
    ADDED_KEYS, which outputs of before were made at its old value; a key only another reader uses
    is in no fingerprint here."""
    old = {"fingerprint": "a", **record({"synth.seed": 3})}
    now = record({"synth.seed": 3, "synth.sampling": "iid", "synth.rss_sampling": "residual",
                  "dataset.world_frames": 99})
    why = explain(old, now, "astyx")
    assert why.sets == ("synth.rss_sampling=mean",)
    assert explain({"fingerprint": "a", **record({"dataset.world_frames": 10})}, record({"dataset.world_frames": 99}),
                   "synthetic").sets == ("dataset.world_frames=10",)


def test_what_no_setting_brings_back_is_said_and_leaves_settings_only_false():
    old = {"fingerprint": "a", **record({"synth.seed": 3}, version=2)}
    why = explain(old, record({"synth.seed": 4}, version=3), "synthetic")
    assert "made by another version of the stage's code (2, now 3)" in why.reasons
    assert why.sets == ("synth.seed=3",) and not why.settings_only
    data = explain({"fingerprint": "a", **record(data_root="/old", frames_digest="x")},
                   record(data_root="/new", frames_digest="y"), "synthetic")
    assert data.reasons == ("made from the data at /old", "made from another list of frames than the data root gives now")
    assert explain({"fingerprint": "stale"}, record(), "synthetic").text.startswith("marked stale")
    unknown = explain({"fingerprint": "a"}, record(), "synthetic")  # a record from before records
    assert "not recorded" in unknown.text and not unknown.settings_only


def test_upstream_outputs_are_named_as_stale_or_recomputed_since():
    old = {"fingerprint": "a", **record(upstream={"heatmaps": "h1", "train": "t1"})}
    now = record(upstream={"heatmaps": "h2", "train": "t2"})
    why = explain(old, now, "synthetic", stale_upstream={"heatmaps"})
    assert why.reasons == ("made from another output of heatmaps", "made from an earlier output of train, recomputed since")
    assert not why.settings_only
    assert explain(old, now, "synthetic", stale_upstream={"heatmaps", "train"}).settings_only


def test_the_nets_a_train_output_took_are_named():
    ours = record(extra="")
    theirs = {"fingerprint": "a", **record(extra="astyx:f00:17.0")}
    why = explain(theirs, ours, "vod")
    assert why.sets == ("train.nets_from=astyx",) and why.settings_only
    assert "made with the nets of 'astyx'" in why.text
    again = explain(theirs, record(extra="astyx:f01:18.0"), "vod")
    assert again.text == "the nets of 'astyx' were trained again since it was made" and not again.settings_only
    own = explain({"fingerprint": "a", **ours}, record(extra="astyx>msc:f:1"), "vod")
    assert own.text == "made with its own nets (this command: train.nets_from=astyx)" and not own.settings_only


# ---- the pipeline ------------------------------------------------------------------------------

def test_outputs_record_what_they_were_made_with(tmp_path):
    pipe = make_pipeline(tmp_path)
    pipe.run("train")
    attrs = pipe.env.store("heatmaps").attrs()
    assert attrs["version"] == 1 and attrs["config"] == {"heatmap.sigma_px": [30.0, 30.0]}
    assert attrs["upstream"] == {"calibrate": pipe.fingerprint("calibrate")}
    assert pipe.env.store("calibrate").attrs()["frames_digest"] == pipe._frames_digest()
    meta = json.loads((tmp_path / "cache" / "fake" / "train" / "_stage.json").read_text())
    assert meta["config"] == {"train.epochs": pipe.env.cfg.train.epochs}
    assert meta["upstream"] == {"heatmaps": pipe.fingerprint("heatmaps")} and meta["version"] == 1
    assert all(pipe.why_stale(n) is None for n in pipe.order)


def test_why_stale_names_the_setting_and_forgotten_sets_gives_it_back(tmp_path):
    make_pipeline(tmp_path, **{"heatmap.sigma_px": "50,50", "train.epochs": "3"}).run("train")
    pipe = make_pipeline(tmp_path)
    assert pipe.why_stale("calibrate") is None
    assert pipe.why_stale("heatmaps").text == "made with heatmap.sigma_px=50.0,50.0 (this command: 30.0,30.0)"
    assert pipe.why_stale("train").reasons == (
        f"made with train.epochs=3 (this command: {pipe.env.cfg.train.epochs})", "made from another output of heatmaps")
    sets, settings_only = pipe.forgotten_sets(pipe.order)
    assert sets == ["heatmap.sigma_px=50.0,50.0", "train.epochs=3"] and settings_only
    overrides = dict(s.split("=", 1) for s in sets)
    assert all(make_pipeline(tmp_path, **overrides).is_current(n) for n in pipe.order)


def test_the_force_frames_refusal_names_the_options_to_add(tmp_path):
    make_pipeline(tmp_path, **{"heatmap.sigma_px": "50,50"}).run("train")
    with pytest.raises(ConfigError) as err:
        make_pipeline(tmp_path).run("train", frames=[1], force=True)
    assert "(made with heatmap.sigma_px=50.0,50.0 (this command: 30.0,30.0))" in str(err.value)
    assert "Add `--set heatmap.sigma_px=50.0,50.0` (the settings the cache was made with)" in str(err.value)
    # pasted with them, it recomputes that frame in place
    reports = {r.stage: r for r in make_pipeline(tmp_path, **{"heatmap.sigma_px": "50.0,50.0"})
               .run("heatmaps", frames=[1], force=True)}
    assert reports["heatmaps"].processed == 1 and reports["heatmaps"].done == len(IDS)


def test_status_and_verify_say_why_and_what_to_add(tmp_path, monkeypatch):
    cli = fake_stages.fake_cli(monkeypatch, lambda: IDS)
    assert cli(tmp_path, "run", "train", "--workers", "1", "--set", "heatmap.sigma_px=50,50").exit_code == 0
    status = cli(tmp_path, "status")
    assert status.exit_code == 0
    assert re.search(r"heatmaps +stale or missing .*\n +not current: made with heatmap\.sigma_px=50\.0,50\.0 "
                     r"\(this command: 30\.0,30\.0\)\n", status.stdout), status.stdout
    assert re.search(r"train +stale or missing +finished\n +not current: made from another output of heatmaps\n",
                     status.stdout), status.stdout
    assert "calibrate       current" in status.stdout and status.stdout.count("not current:") == 2
    # a damaged chunk: verify's repair command, and what to add to it
    chunk = next((tmp_path / "cache" / "synthetic" / "heatmaps.zarr" / "total" / "c").iterdir())
    chunk.write_bytes(b"garbage")
    verify = cli(tmp_path, "verify")
    assert "add `--set heatmap.sigma_px=50.0,50.0` to both" in verify.stdout, verify.stdout


def test_a_dataset_stage_whose_inputs_finished_more_frames_says_so(tmp_path):
    make_pipeline(tmp_path).run("train", frames=[0, 1, 2])
    pipe = make_pipeline(tmp_path)
    assert pipe.why_stale("train") is None
    pipe.run("heatmaps")
    pipe = make_pipeline(tmp_path)
    assert pipe.why_stale("train").text == "its per-frame inputs finished other frames since it ran"
    assert {r["stage"]: r for r in cache_status(pipe)}["train"]["why"] == pipe.why_stale("train").text


def test_forgotten_sets_leave_out_the_radar_settings_that_come_with_other_nets(tmp_path, monkeypatch):
    """A transferred cache (train.nets_from=astyx) read without the option: calibrate's radar
    settings differ too, but they follow from the nets; the option alone is what to add."""
    from pipeline.staleness import Staleness

    whys = {"calibrate": Staleness(("a",), ("radar.fov_az_deg=110.0", "split.seed=3"), True),
            "train": Staleness(("b",), ("train.nets_from=astyx",), True)}
    pipe = make_pipeline(tmp_path)
    monkeypatch.setattr(pipe, "why_stale", lambda name: whys.get(name))
    assert pipe.forgotten_sets(pipe.order) == (["split.seed=3", "train.nets_from=astyx"], True)
    del whys["train"]
    assert pipe.forgotten_sets(pipe.order) == (["radar.fov_az_deg=110.0", "split.seed=3"], True)
    whys["heatmaps"] = Staleness(("c",))  # something no option brings back
    assert pipe.forgotten_sets(pipe.order) == (["radar.fov_az_deg=110.0", "split.seed=3"], False)
