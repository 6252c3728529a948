"""Tiny deterministic stages for testing the cache, runner and executors (importable by workers)."""

from __future__ import annotations

import os

import numpy as np

from pipeline.stage import ArraySpec, DatasetStage, FrameStage

CALLS_FILE_ENV = "FAKE_STAGE_CALLS"


def _count_call(stage: str, frame_id: str) -> None:
    path = os.environ.get(CALLS_FILE_ENV)
    if path:
        with open(path, "a") as fh:
            fh.write(f"{stage} {frame_id}\n")
    stop_after = os.environ.get("FAKE_STAGE_STOP_AFTER")
    if stop_after and path:
        with open(path) as fh:
            if sum(1 for _ in fh) > int(stop_after):
                raise KeyboardInterrupt("simulated kill")


def first(inputs, cfg):
    _count_call("calibrate", inputs.frame_id)
    if inputs.frame_id.startswith("bad") and not os.environ.get("FAKE_STAGE_FIXED"):  # FIXED: the file was replaced
        raise ValueError(f"file {inputs.frame_id}.bin is truncated")
    rng = inputs.rng(1)
    n = int(rng.integers(0, 6))
    return {"points": rng.normal(size=(n, 3)).astype(np.float32), "value": np.float64(int(inputs.frame_id[-3:]))}


def second(inputs, cfg):
    _count_call("heatmaps", inputs.frame_id)
    pts = inputs.get("calibrate", "points")
    return {"total": np.float64(pts.sum() * cfg.heatmap.sigma_px[0] + inputs.get("calibrate", "value"))}


def summarise(inputs, cfg, out, fingerprint):
    total = sum(float(inputs.store("heatmaps").read("total", i)) for i in range(len(inputs.frame_ids)))
    out.write_text("total.txt", f"{total:.6f}")
    return {"message": f"total {total:.3f}"}


STAGES = [
    FrameStage("calibrate", (), ("split.seed",),
               lambda cfg: (ArraySpec("points", (8, 3), "float32", "m", fill=np.nan, ragged=True),
                            ArraySpec("value", (), "float64", "-")), first),
    FrameStage("heatmaps", ("calibrate",), ("heatmap.sigma_px",),
               lambda cfg: (ArraySpec("total", (), "float64", "-"),), second),
    DatasetStage("train", ("heatmaps",), ("train.epochs",), summarise),
]


def fake_cli(monkeypatch, ids):
    """The real CLI (its options and error handling) on these stages, with the frames ``ids()``
    lists (read at each run, so a test may change them): a function ``(tmp_path, *args)`` that
    invokes it on the cache ``tmp_path/cache`` and the data root ``tmp_path``."""
    from click.testing import CliRunner

    import pipeline.cli as cli
    from pipeline.executor import Executor
    from pipeline.runner import Pipeline

    def _pipeline(env, workers, scheduler, progress=None):
        return Pipeline(STAGES, env, Executor(workers, scheduler, progress), progress, frame_lister=lambda: list(ids()))

    monkeypatch.setattr(cli, "_pipeline", _pipeline)
    monkeypatch.setattr(cli, "_ensure_world", lambda env, progress: None)

    def invoke(tmp_path, *args: str):
        return CliRunner().invoke(cli.main, [*args, "--dataset", "synthetic", "--cache", str(tmp_path / "cache"),
                                             "--data-root", str(tmp_path)])
    return invoke
