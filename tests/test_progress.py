"""Progress of long work where stderr is a log file (pipeline.progress): plain lines, at most one
every run.progress_every_s seconds; until 2026-12-07 a run whose stderr was not a terminal showed
no progress at all (a training of an hour wrote nothing to its log until it ended)."""

from __future__ import annotations

import io
import re

import pytest

from pipeline.config import load_config
from pipeline.errors import ConfigError
from pipeline.executor import Executor, RunEnv
from pipeline.progress import Heartbeat, bar
from pipeline.runner import Pipeline
from pipeline.training import epoch_line
from pipeline.world import generate
from stages import all_stages


class Clock:
    """time.monotonic for tqdm and Heartbeat, moved by hand."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.fixture
def clock(monkeypatch) -> Clock:
    import tqdm.std

    import pipeline.progress

    c = Clock()
    monkeypatch.setattr(tqdm.std, "time", c)  # tqdm's timer (tqdm.std imports time.time as time)
    monkeypatch.setattr(pipeline.progress.time, "monotonic", c)
    return c


def test_a_log_gets_a_line_per_interval_with_the_count_and_what_is_left(clock):
    log = io.StringIO()
    b = bar(total=100, desc="synthesize", unit="frame", every_s=60.0, stream=log)
    for _ in range(10):           # 10 frames in 50 s: within the first interval, nothing yet
        clock.now += 5.0
        b.update(1)
    assert log.getvalue() == ""
    clock.now += 15.0             # 65 s in: the first line
    b.update(1)
    for _ in range(40):           # 40 more frames over 40 s: no second line before 60 s have passed
        clock.now += 1.0
        b.update(1)
    clock.now += 30.0
    b.update(1)                   # 135 s in, 70 s after the first line: the second
    b.close()
    lines = log.getvalue().splitlines()
    assert len(lines) == 2 and "\r" not in log.getvalue()
    assert lines[0] == "synthesize: 11/100 (11%), 01:05 elapsed, about 08:45 left, 5.91s/frame"  # 65 s / 11
    assert lines[1].startswith("synthesize: 52/100 (52%), 02:15 elapsed")



def test_tqdm_s_monitor_never_redraws_a_log_s_bar_with_a_stale_count(clock):
    """tqdm's monitor thread redraws a bar whose miniters is above 1 once maxinterval has passed
    since its last line (tqdm 4.x, TMonitor.run: `miniters > 1 and now - last_print_t >=
    maxinterval` -> refresh); over an iterable the count shown is the one the loop last synced, at
    its last line. A training log (2026-12-08) got 'rssnet epoch 8/8: 73/252 (29%), 02:02 elapsed'
    and, a second later, '133/252 (53%), 02:03 elapsed'. A log's bar keeps miniters at 1: the
    monitor leaves it alone, and the loop writes at most a line an interval, with its count."""
    log = io.StringIO()
    b = bar(range(300), total=300, desc="rssnet epoch 8/8", unit="batch", every_s=60.0, stream=log)
    for i in b:
        clock.now += 1.0
        if b.miniters > 1 and clock.now - b.last_print_t >= b.maxinterval:  # the monitor's rule
            b.miniters = 1
            b.refresh(nolock=True)
    b.close()
    lines = log.getvalue().splitlines()
    counts = [int(re.match(r"rssnet epoch 8/8: (\d+)/300", line).group(1)) for line in lines]
    assert counts == [60, 120, 180, 240, 300], lines  # a line a minute, each with the count of its moment

def test_a_postfix_waits_for_the_interval_and_rides_on_the_next_line(clock):
    """Training sets the batch loss as a postfix every 10 batches; until 2026-12-07 that redrew the
    bar at once, so a log got three lines an epoch, each saying '0/21 (0%)' (tqdm's count is not
    synced before its first redraw), whatever run.progress_every_s said."""
    log = io.StringIO()
    b = bar(total=21, desc="disnet epoch 1/12", unit="batch", every_s=60.0, stream=log)
    for step in range(21):
        clock.now += 4.0
        if step % 10 == 0:
            b.set_postfix(loss="0.4123", refresh=False)
        b.update(1)
    b.close()
    assert log.getvalue() == "disnet epoch 1/12: 15/21 (71%), 01:00 elapsed, about 00:24 left, 4.00s/batch, loss=0.4123\n"


def test_the_mean_training_map_says_how_far_it_is(clock, capsys, monkeypatch):
    """The train stage reads every training heatmap for the mean map before any net trains (about 2
    minutes on 25,000 Astyx frames), silently until 2026-12-07."""
    import numpy as np

    import pipeline.net_baselines as B

    real = B.iter_batches

    def slow(arrays, order, batch_size):  # 30 s a batch on the fake clock
        for b in real(arrays, order, batch_size):
            clock.now += 30.0
            yield b

    monkeypatch.setattr(B, "iter_batches", slow)
    heatmaps = np.ones((40, 4, 6), np.float32)
    mean = B.mean_map_baseline(heatmaps, np.arange(40), batch=8, progress=True, every_s=60.0)
    np.testing.assert_allclose(mean.sum(), 1.0)
    lines = capsys.readouterr().err.splitlines()
    assert lines and lines[0].startswith("mean training map: 2/5 (40%), 01:00 elapsed"), lines
    assert B.mean_map_baseline(heatmaps, np.arange(40), batch=8) is not None and capsys.readouterr().err == ""


def test_short_work_and_switched_off_progress_write_nothing(clock):
    for every_s, enabled in ((60.0, True), (0.0, True), (1.0, False)):
        log = io.StringIO()
        for _ in bar(range(5), total=5, desc="x", enabled=enabled, every_s=every_s, stream=log):
            clock.now += 0.5 if every_s else 1000.0
        assert log.getvalue() == "", (every_s, enabled)


def test_a_terminal_gets_the_redrawn_bar(clock):
    term = Terminal()
    for _ in bar(range(3), total=3, desc="heatmaps", every_s=60.0, stream=term):
        clock.now += 1.0
    assert "\r" in term.getvalue() and "heatmaps" in term.getvalue()


def test_heartbeat_writes_at_most_once_an_interval_and_only_to_a_log(clock):
    log = io.StringIO()
    beat = Heartbeat(True, 60.0, log)
    clock.now += 59.0
    assert not beat.maybe("a")
    clock.now += 2.0
    assert beat.maybe("b")
    clock.now += 30.0
    assert not beat.maybe("c")
    clock.now += 31.0
    assert beat.maybe("d")
    assert log.getvalue() == "b\nd\n"
    clock.now += 1000.0
    assert not Heartbeat(True, 60.0, Terminal()).maybe("e") and not Heartbeat(False, 60.0, log).maybe("e")
    assert not Heartbeat(True, 0.0, log).maybe("e")


def test_epoch_line_names_the_losses_and_the_best_epoch():
    line = epoch_line("disnet", 3, 12, {"loss": 0.41234, "kl": 0.3}, {"loss": 0.39871, "kl": 0.25101}, "kl", 3, 52.4)
    assert line == "disnet epoch 3/12: train loss 0.4123, val loss 0.3987 kl 0.251 (best so far), 52 s"
    line = epoch_line("rssnet", 4, 12, {"loss": 0.02}, {"loss": 0.03}, "loss", 2, 7.0)
    assert line == "rssnet epoch 4/12: train loss 0.02, val loss 0.03 (best: epoch 2), 7 s"
    assert "no val split" in epoch_line("placenet", 1, 1, {"loss": 1.0}, None, "loss", 1, 1.0)


def test_the_interval_is_a_checked_setting():
    assert load_config("synthetic", {}, environ={}).run.progress_every_s == 60.0
    with pytest.raises(ConfigError, match="run.progress_every_s"):
        load_config("synthetic", {"run.progress_every_s": "-1"}, environ={})


def test_a_run_logged_to_a_file_shows_each_stage_and_epoch(tmp_path, capsys):
    """The whole path: a run whose stderr is not a terminal (pytest's capture, as a log file) writes
    progress lines of the frame stages and an epoch line per net, with the interval set short."""
    world = tmp_path / "world"
    generate(world, frames=4, seed=3, resolution_wh=(640, 384), sequence_len=4)
    tiny = {"train.epochs": "2", "placement.epochs": "1", "disnet.width": "8", "patches.points_per_frame": "16",
            "split.rule": "random", "train.threads": "1", "train.device": "cpu", "train.nets": "disnet"}
    for every_s, expect in (("0.000001", True), ("60", False)):
        cfg = load_config("synthetic", {**tiny, "run.progress_every_s": every_s}, environ={})
        cache = tmp_path / f"cache{every_s}"
        with Executor(1) as ex:  # progress left to the default: lines, as stderr is no terminal
            Pipeline(all_stages(), RunEnv(cfg, str(cache), "synthetic", str(world)), ex, log=lambda m: None).run("train")
        err = capsys.readouterr().err
        lines = err.splitlines()
        for stage in ("calibrate", "heatmaps", "patches"):
            assert any(re.match(rf"{stage}: \d/4 \(\d+%\)", line) for line in lines) == expect, (stage, err)
        assert any(re.match(r"disnet epoch 2/2: train loss [\d.e-]+, val loss", line) for line in lines) == expect, err
        if not expect:  # nothing at all from a run shorter than the interval (training's loss postfix included)
            assert not [line for line in lines if re.search(r": \d+/\d+ \(\d+%\)|epoch", line)], err
        assert "\r" not in err


def test_the_world_a_run_generates_follows_the_interval(tmp_path):
    """The synthetic world a run generates into its cache took its progress lines at the default
    minute whatever run.progress_every_s said (0, for none, included) until 2026-12-07."""
    from click.testing import CliRunner

    from pipeline.cli import main

    sets = ["--set", "dataset.world_frames=4", "--set", "dataset.world_sequence_len=4"]
    for every_s, expect in (("0.000001", True), ("0", False)):
        out = CliRunner().invoke(main, ["run", "calibrate", "--workers", "1", "--cache", str(tmp_path / every_s),
                                        *sets, "--set", f"run.progress_every_s={every_s}"])
        assert out.exit_code == 0, out.output
        assert bool(re.search(r"^generate-world: \d/4 \(\d+%\)", out.stderr, re.M)) == expect, out.stderr
