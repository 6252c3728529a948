"""A frame stage's ``ready`` hook runs before its output is recreated: a forced run whose inputs
cannot serve it (synthesize with an unreadable checkpoint) stops with its output and the outputs
after it untouched, instead of wiping them first."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import pytest

from pipeline.cache import DONE, dir_store
from pipeline.config import load_config
from pipeline.errors import PipelineError
from pipeline.executor import Executor, RunEnv
from pipeline.runner import Pipeline
from stages.synthesize import check_checkpoints, ready
from tests import fake_stages
from tests.test_damaged_cache import IDS


def test_a_forced_stage_that_is_not_ready_keeps_its_output(tmp_path):
    ready = {"ok": True}

    def check_ready(inputs, cfg):
        if not ready["ok"]:
            raise PipelineError("heatmaps: its inputs cannot serve it")

    stages = [s if s.name != "heatmaps" else replace(s, ready=check_ready) for s in fake_stages.STAGES]
    env = RunEnv(cfg=load_config("synthetic", {}, environ={}), cache_root=str(tmp_path / "cache"), dataset="fake",
                 data_root=str(tmp_path))
    pipe = Pipeline(stages, env, Executor(1), progress=False, log=lambda m: None, frame_lister=lambda: list(IDS))
    pipe.run("train")
    before = [float(env.store("heatmaps").read("total", i)) for i in range(len(IDS))]
    ready["ok"] = False
    for frames in (None, [2]):  # the whole output recreated, or frames recomputed in place
        with pytest.raises(PipelineError, match="cannot serve it"):
            pipe.run("heatmaps", frames=frames, force=True)
        assert (env.store("heatmaps").status() == DONE).all()
        assert [float(env.store("heatmaps").read("total", i)) for i in range(len(IDS))] == before
        assert pipe.is_current("train")  # downstream not marked stale
    ready["ok"] = True
    assert pipe.run("heatmaps", force=True)[-1].processed == len(IDS)


@pytest.mark.parametrize("content", [b"", b"garbage that is no safetensors header", None])
def test_synthesize_names_an_unreadable_checkpoint_and_how_to_retrain(tmp_path, content):
    cfg = load_config("synthetic", {}, environ={})
    train = dir_store(str(tmp_path / "cache"), "synthetic", "train")
    for net in ("disnet", "rssnet", "placenet"):
        (tmp_path / "cache" / "synthetic" / "train" / net).mkdir(parents=True)
        if content is not None:
            (tmp_path / "cache" / "synthetic" / "train" / net / "best.safetensors").write_bytes(content)
    with pytest.raises(PipelineError) as exc:
        check_checkpoints(train, cfg)
    if content is None:
        assert "no disnet, rssnet, placenet checkpoint" in str(exc.value)
    else:
        assert "disnet/best.safetensors: unreadable checkpoint" in str(exc.value)
        assert "`pipeline run train --force`" in str(exc.value)


def test_synthesize_checks_the_weights_before_its_output_is_recreated(tmp_path):
    """synthesize's ready hook (run as above) reads the weights, not only the header: a
    checkpoint with an inf weight stops a forced run before the finished frames are wiped (a frame's
    model load found it only after)."""
    import torch

    from pipeline.checkpoint import save_checkpoint

    cfg = load_config("synthetic", {}, environ={})
    train = dir_store(str(tmp_path / "cache"), "synthetic", "train")
    weights = {"model.fc.weight": torch.zeros(8), "model.feature_low": torch.full((2,), float("nan"))}
    for net in ("disnet", "rssnet", "placenet"):
        save_checkpoint(tmp_path / "cache" / "synthetic" / "train" / net / "best.safetensors", weights, {"epoch": 1})
    inputs = SimpleNamespace(dir=lambda name: train)
    ready(inputs, cfg)  # a NaN buffer is no weight
    weights["model.fc.weight"][0] = float("inf")
    save_checkpoint(tmp_path / "cache" / "synthetic" / "train" / "rssnet" / "best.safetensors", weights, {"epoch": 1})
    with pytest.raises(PipelineError) as exc:
        ready(inputs, cfg)
    assert "rssnet/best.safetensors: 1 of 8 values of fc.weight are not finite" in str(exc.value)
    assert str(exc.value).count("`pipeline run train --force`") == 1
