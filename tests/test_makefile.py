"""The Makefile's command lines (`make -n`, with PIPELINE=pipeline so that nothing is installed or
run) and clean-cache's refusals (run for real, in a temporary folder)."""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="no make")


def _make(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    base = {k: v for k, v in os.environ.items()
            if k not in ("DATASET", "DATA_ROOT", "CACHE", "WORKERS", "ARGS") and not k.startswith("PIPELINE_")}
    return subprocess.run(["make", "--no-print-directory", "-C", str(ROOT), *args], capture_output=True, text=True,
                          env={**base, **(env or {})}, timeout=60)


def _pipeline_argv(*args: str, env: dict[str, str] | None = None) -> list[str]:
    """The pipeline command line `make -n ARGS` would run, split as the shell splits it."""
    out = _make("-n", "PIPELINE=pipeline", *args, env=env)
    assert out.returncode == 0, out.stderr
    lines = [line for line in out.stdout.splitlines() if line.startswith("pipeline ")]
    assert len(lines) == 1, out.stdout
    return shlex.split(lines[0])


def _option(argv: list[str], name: str) -> str:
    return argv[argv.index(name) + 1]


def test_folders_with_spaces_stay_one_argument():
    """Until 2026-12-06 `make heatmaps DATA_ROOT='/data/my data'` ran `--data-root /data/my data`:
    click's 'Got unexpected extra argument (data)'; the same for CACHE."""
    argv = _pipeline_argv("heatmaps", "DATASET=vod", "DATA_ROOT=/data/my data", "CACHE=/tmp/my cache",
                          "ARGS=--frames 0:2 --set train.epochs=2")
    assert argv[:3] == ["pipeline", "run", "heatmaps"]
    assert _option(argv, "--data-root") == "/data/my data" and _option(argv, "--cache") == "/tmp/my cache"
    assert _option(argv, "--dataset") == "vod" and _option(argv, "--frames") == "0:2"  # ARGS: several options
    argv = _pipeline_argv("status", "CACHE=/tmp/my cache", "DATA_ROOT=/data/it's here")
    assert _option(argv, "--cache") == "/tmp/my cache" and _option(argv, "--data-root") == "/data/it's here"


def test_pipeline_variables_give_dataset_and_cache():
    """`PIPELINE_DATASET=vod make status` ran status of the synthetic dataset in ./cache: the
    Makefile always passed --dataset synthetic --cache cache, so the variables the README says give
    those options were ignored. DATASET and CACHE still win."""
    env = {"PIPELINE_DATASET": "vod", "PIPELINE_CACHE": "/big/cache"}
    for target in ("status", "heatmaps"):
        argv = _pipeline_argv(target, env=env)
        assert _option(argv, "--dataset") == "vod" and _option(argv, "--cache") == "/big/cache"
    argv = _pipeline_argv("status", "DATASET=astyx", "CACHE=c2", env=env)
    assert _option(argv, "--dataset") == "astyx" and _option(argv, "--cache") == "c2"
    argv = _pipeline_argv("status")
    assert _option(argv, "--dataset") == "synthetic" and _option(argv, "--cache") == "cache"


@pytest.mark.parametrize("variables", [["DATASET="], ["DATASET=a/.."], ["DATASET=.."], ["DATASET= "]])
def test_clean_cache_refuses_what_would_delete_more_than_one_dataset(tmp_path, variables):
    """`make clean-cache DATASET=` ran `rm -rf cache/`: every dataset's cache (`CACHE= DATASET=`: `rm -rf /`)."""
    for name in ("astyx", "vod"):
        (tmp_path / "cache" / name).mkdir(parents=True)
    out = _make("clean-cache", f"CACHE={tmp_path / 'cache'}", *variables)
    assert out.returncode != 0 and "nothing deleted" in out.stderr, out.stderr
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == ["astyx", "vod"]
    out = _make("clean-cache", "CACHE=", "DATASET=h45d-no-such-dataset")
    assert out.returncode != 0 and "CACHE is empty" in out.stderr
    out = _make("clean-cache", f"CACHE={tmp_path / 'cache'}", "DATASET=vod")
    assert out.returncode == 0, out.stderr
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == ["astyx"]


def test_make_help_lists_every_target_the_readme_names():
    """`make help` was 'No rule to make target' though the targets carried `##` descriptions."""
    import re

    out = _make("help")
    assert out.returncode == 0, out.stderr
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    table = readme.split("## Make targets", 1)[1].split("\n## ", 1)[0]
    named = set(re.findall(r"`make ([a-z-]+)`", table)) - {"calibrate", "heatmaps", "evaluate"}
    assert named >= {"help", "setup", "demo", "status", "clean-cache"}
    listed = set(re.findall(r"^  make (\S+)", out.stdout, re.M))
    assert named <= listed, named - listed
    assert "calibrate heatmaps patches train synthesize export evaluate" in out.stdout


def test_workers_is_passed_only_when_given():
    """Until 2026-12-06 make always passed --workers 2, which overrode `ARGS="--set run.workers=1"`
    and PIPELINE__RUN__WORKERS: run.workers is the default, WORKERS=N still sets it."""
    for target in ("heatmaps", "demo"):
        out = _make("-n", "PIPELINE=pipeline", target, "ARGS=--set run.workers=1")
        assert out.returncode == 0, out.stderr
        runs = [shlex.split(line) for line in out.stdout.splitlines() if line.startswith("pipeline ")]
        assert runs and all("--workers" not in argv and "run.workers=1" in argv for argv in runs), out.stdout
    assert _option(_pipeline_argv("heatmaps", "WORKERS=3"), "--workers") == "3"
