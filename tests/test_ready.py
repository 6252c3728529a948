"""A frame stage's ``ready`` hook runs before its output is recreated: a forced run whose inputs
cannot serve it (synthesize with an unreadable checkpoint) stops with its output and the outputs
after it untouched, instead of wiping them first."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import pytest

from pipeline.cache import DONE
from pipeline.dirstore import dir_store
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
        save_checkpoint(tmp_path / "cache" / "synthetic" / "train" / net / "best.safetensors", weights,
                        {"epoch": 1, "count_scale": 1.2})
    inputs = SimpleNamespace(dir=lambda name: train)
    ready(inputs, cfg)  # a NaN buffer is no weight
    weights["model.fc.weight"][0] = float("inf")
    save_checkpoint(tmp_path / "cache" / "synthetic" / "train" / "rssnet" / "best.safetensors", weights, {"epoch": 1})
    with pytest.raises(PipelineError) as exc:
        ready(inputs, cfg)
    assert "rssnet/best.safetensors: 1 of 8 values of fc.weight are not finite" in str(exc.value)
    assert str(exc.value).count("`pipeline run train --force`") == 1


def test_synthesize_needs_placenets_count_scale_only_for_the_blended_count(tmp_path):
    """A PlaceNet checkpoint saved without its count scale (before 2026-12-05) is refused, naming
    the retraining and synth.count=disnet, where synth.count = predicted blends PlaceNet's count in;
    Dis-Net's count alone and the ray placement need none."""
    import numpy as np
    import torch

    from pipeline.checkpoint import save_checkpoint
    from stages.synthesize import frame_count, uses_placenet_count

    train = dir_store(str(tmp_path / "cache"), "synthetic", "train")
    weights = {"model.fc.weight": torch.zeros(8)}
    for net, meta in (("disnet", {}), ("rssnet", {}), ("placenet", {"count_scale": float("nan")})):
        save_checkpoint(tmp_path / "cache" / "synthetic" / "train" / net / "best.safetensors", weights, meta)
    inputs = SimpleNamespace(dir=lambda name: train)
    cfg = load_config("synthetic", {}, environ={})
    refused = (r"placenet/best.safetensors: PlaceNet's checkpoint holds no count scale.*"
               r"`pipeline run train --force`.*synth.count=disnet")
    with pytest.raises(PipelineError, match=refused):
        ready(inputs, cfg)  # before the output is recreated
    with pytest.raises(PipelineError, match=refused):
        check_checkpoints(train, cfg)  # select, which reads the headers only
    for overrides in ({"synth.count": "disnet"}, {"synth.count": "oracle"}, {"synth.placement": "ray"},
                      {"train.nets_from": "astyx"},  # another dataset's PlaceNet counts another lidar's points
                      {"train.nets_from": "vod"}):
        ready(inputs, load_config("synthetic", overrides, environ={}))
        assert not uses_placenet_count(load_config("synthetic", overrides, environ={}))
    assert uses_placenet_count(cfg)
    # the blend: the geometric mean of Dis-Net's count and the scaled summed intensity
    n, n_placenet = frame_count(50.0, np.array([10.0, 20.0, 2.0]), 2.5)
    assert n_placenet == 80.0 and n == pytest.approx(np.sqrt(50.0 * 80.0))
    assert frame_count(50.0, np.zeros(0), 2.5) == (0.0, 0.0)  # no candidate: nothing can be placed
    assert frame_count(0.25, np.array([1.0, 3.0]), 4.0) == (2.0, 16.0)  # a count under 1 is not raised to 1
    assert frame_count(-3.0, np.array([1.0]), 4.0) == (0.0, 4.0)  # a negative count is none


def test_synthesize_draws_the_blended_count_and_records_its_parts(monkeypatch):
    """A frame's points are drawn to the geometric mean of Dis-Net's count and PlaceNet's (the
    count scale times the intensity summed over the frame's candidates); n_hat is that mean and
    n_parts holds Dis-Net's count and PlaceNet's, in that order. Dis-Net's count alone, the ray
    placement and another dataset's nets draw Dis-Net's count, PlaceNet's recorded as -1 (not
    computed: the report leaves it out); the oracle draws the real count, n_hat Dis-Net's."""
    import numpy as np

    import pipeline.inference
    import stages.synthesize as S

    w, h = load_config("synthetic", {}, environ={}).camera.working_size
    placenet = SimpleNamespace(count_scale=2.0)
    nets = S.Nets(disnet=SimpleNamespace(use_prior=False), rssnet=None, placenet=placenet)
    # candidates whose coordinates and outside-range counts sum to other than their intensities (8)
    candidates = (np.full((3, 3), 7.0), np.zeros((3, 2)), np.array([1.0, 2.0, 5.0]), np.array([9, 9], np.int32))
    frame = {("calibrate", "ego_velocity"): np.array([3.0, 4.0, 0.0]),
             ("calibrate", "image"): np.zeros((h, w, 3), np.uint8), ("heatmaps", "count"): np.int32(11)}
    inputs = SimpleNamespace(get=lambda stage, name: frame[(stage, name)],
                             rng=lambda seed, salt: np.random.default_rng([seed, salt]))
    drawn = []

    def generate(inputs, cfg, prob_map, n, nets, rng):
        drawn.append(n)
        return {"points": np.zeros((0, 9), np.float32), "counts": np.zeros(5, np.int32), "candidates": np.int32(3),
                "outside_training": np.zeros(2, np.int32), "rss_points": np.int32(0), "rss_outside": np.int32(0)}

    def disnet_predict(net, images, speeds):
        assert speeds.tolist() == [5.0]
        return np.full((1, h, w), 1.0 / (h * w), np.float32), np.array([4.0], np.float32)

    monkeypatch.setattr(S, "models", lambda inputs, cfg: nets)
    monkeypatch.setattr(S, "lidar_candidates", lambda inputs, cfg, net: candidates if net is placenet else None)
    monkeypatch.setattr(S, "generate", generate)
    monkeypatch.setattr(pipeline.inference, "disnet_predict", disnet_predict)

    def run(**overrides: str) -> tuple[float, float, list[float]]:
        drawn.clear()
        out = S.process(inputs, load_config("synthetic", overrides, environ={}))
        assert len(drawn) == 1
        return drawn[0], float(out["n_hat"]), out["n_parts"].tolist()

    assert run() == (8.0, 8.0, [4.0, 16.0])  # PlaceNet's 2 * (1 + 2 + 5) = 16, sqrt(4 * 16) = 8
    for overrides in ({"synth.count": "disnet"}, {"synth.placement": "ray"}, {"train.nets_from": "astyx"}):
        assert run(**overrides) == (4.0, 4.0, [4.0, -1.0]), overrides
    assert run(**{"synth.count": "oracle"}) == (11.0, 4.0, [4.0, -1.0])



def test_residual_rss_sampling_needs_rssnets_residual_quantiles(tmp_path):
    """synth.rss_sampling = residual refuses an RSS-Net checkpoint without its residual quantiles
    (saved before 2026-12-06, or trained without validation points), naming the retraining and
    synth.rss_sampling=mean; the default (RSS-Net's prediction) needs none; a misspelt value is
    refused before anything runs."""
    import numpy as np
    import torch

    from pipeline.checkpoint import save_checkpoint
    from pipeline.errors import ConfigError
    from pipeline.inference import RESIDUAL_KEY, RESIDUAL_LEVELS
    from stages.synthesize import check_generation

    train = dir_store(str(tmp_path / "cache"), "synthetic", "train")
    weights = {"model.fc.weight": torch.zeros(8)}
    for net, meta in (("disnet", {}), ("rssnet", {}), ("placenet", {"count_scale": 1.0})):
        save_checkpoint(tmp_path / "cache" / "synthetic" / "train" / net / "best.safetensors", weights, meta)
    inputs = SimpleNamespace(dir=lambda name: train)
    residual = load_config("synthetic", {"synth.rss_sampling": "residual"}, environ={})
    refused = (r"rssnet/best.safetensors: RSS-Net's checkpoint holds no residual quantiles.*"
               r"`pipeline run train --force`.*synth.rss_sampling=mean")
    with pytest.raises(PipelineError, match=refused):
        ready(inputs, residual)
    with pytest.raises(PipelineError, match=refused):
        check_checkpoints(train, residual)
    ready(inputs, load_config("synthetic", {}, environ={}))  # the default: RSS-Net's prediction
    save_checkpoint(tmp_path / "cache" / "synthetic" / "train" / "rssnet" / "best.safetensors", weights,
                    {RESIDUAL_KEY: np.linspace(-5, 5, len(RESIDUAL_LEVELS)).tolist()})
    ready(inputs, residual)
    with pytest.raises(ConfigError, match="'synth.rss_sampling' must be one of mean, residual"):
        check_generation(load_config("synthetic", {"synth.rss_sampling": "residuals"}, environ={}))
