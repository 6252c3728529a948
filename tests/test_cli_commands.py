"""The CLI's commands beside `run`: generate-world, check-physics and estimate-sigma, on a tiny
generated world (each was exercised only through the functions behind it)."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from pipeline.cli import main


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cli") / "world"
    out = CliRunner().invoke(main, ["generate-world", "--frames", "4", "--seed", "1", "--out", str(root)])
    assert out.exit_code == 0, out.output
    assert '"frames": 4' in out.output
    return root


def _digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_generate_world_is_the_same_bytes_for_the_same_seed(world, tmp_path):
    again = CliRunner().invoke(main, ["generate-world", "--frames", "4", "--seed", "1", "--out", str(tmp_path / "w")])
    assert again.exit_code == 0, again.output
    assert _digest(world) == _digest(tmp_path / "w") and len(_digest(world)) >= 4 * 3
    other = CliRunner().invoke(main, ["generate-world", "--frames", "4", "--seed", "2", "--out", str(tmp_path / "o")])
    assert other.exit_code == 0 and _digest(world) != _digest(tmp_path / "o")


def test_generate_world_refuses_to_replace_a_world_of_other_settings_unless_asked(world, tmp_path):
    """Until 2026-12-06 generating another seed over a world a cache was made from replaced it
    without a word, and the cache, run again, mixed the old world's finished frames with the new
    one's. The same settings again are no change; --replace replaces."""
    import shutil

    root = tmp_path / "w"
    shutil.copytree(world, root)
    args = ["generate-world", "--frames", "4", "--out", str(root)]
    out = CliRunner().invoke(main, [*args, "--seed", "5"])
    assert out.exit_code == 2 and "seed 1 (asked: 5)" in out.stderr and "--replace" in out.stderr
    assert _digest(root) == _digest(world)  # untouched
    assert CliRunner().invoke(main, [*args, "--seed", "1"]).exit_code == 0 and _digest(root) == _digest(world)
    out = CliRunner().invoke(main, [*args, "--seed", "5", "--replace"])
    assert out.exit_code == 0, out.output
    assert json.loads((root / "world.json").read_text())["seed"] == 5


def test_generate_world_defaults_to_the_demo_world_and_changes_only_the_lidar_with_its_lines(world, tmp_path):
    """The CLI's world has the synthetic profile's sequences (the world `make demo` generates;
    until 2026-12-06 its sequences were 40 frames, the profile's 20), and another lidar changes the
    lidar files alone: the same scenes, images, labels, poses and radar to the byte."""
    from pipeline.config import load_config

    meta = json.loads((world / "world.json").read_text())
    assert meta["sequence_len"] == load_config("synthetic", environ={}).dataset.world_sequence_len
    assert meta["lidar_lines"] == 64
    sparse = tmp_path / "w16"
    out = CliRunner().invoke(main, ["generate-world", "--frames", "4", "--seed", "1", "--out", str(sparse),
                                    "--lidar-lines", "16"])
    assert out.exit_code == 0, out.output
    assert json.loads((sparse / "world.json").read_text())["lidar_lines"] == 16
    dense, thin = _digest(world), _digest(sparse)
    assert dense.keys() == thin.keys()
    lidar = {k for k in dense if k.startswith("lidar/training/velodyne/")}
    assert len(lidar) == 4 and all(dense[k] != thin[k] for k in lidar)
    assert sum((world / k).stat().st_size for k in lidar) > 2 * sum((sparse / k).stat().st_size for k in lidar)
    same = [k for k in dense if k not in lidar and k != "world.json"]
    assert len(same) >= 4 * 5 and any(k.startswith("radar/") for k in same)
    assert all(dense[k] == thin[k] for k in same)
    bad = CliRunner().invoke(main, ["generate-world", "--frames", "2", "--out", str(tmp_path / "b"),
                                    "--lidar-lines", "32"])
    assert bad.exit_code == 2 and "'32' is not one of '16', '64', '128'" in bad.output


def test_generate_world_passes_its_sequence_length_and_lidar_lines_on(tmp_path):
    """--sequence-len 1 (the least) and --lidar-lines 128 reach the world; --sequence-len 0 is
    refused before anything is written."""
    out = CliRunner().invoke(main, ["generate-world", "--frames", "2", "--seed", "1", "--out", str(tmp_path / "w"),
                                    "--resolution", "64x32", "--sequence-len", "1", "--lidar-lines", "128"])
    assert out.exit_code == 0, out.output
    meta = json.loads((tmp_path / "w" / "world.json").read_text())
    assert meta["sequence_len"] == 1 and len(meta["sequences"]) == 2 and meta["lidar_lines"] == 128
    bad = CliRunner().invoke(main, ["generate-world", "--frames", "2", "--out", str(tmp_path / "b"),
                                    "--sequence-len", "0"])
    assert bad.exit_code == 2 and not (tmp_path / "b").exists()


def test_generate_world_refuses_a_malformed_resolution_in_one_line(tmp_path):
    out = CliRunner().invoke(main, ["generate-world", "--frames", "2", "--out", str(tmp_path / "w"),
                                    "--resolution", "640by384"])
    assert out.exit_code == 2 and out.output.strip() == "error: --resolution: expected WxH, got '640by384'"


def test_check_physics_reports_every_range_rule_and_the_static_doppler(world, tmp_path):
    out = CliRunner().invoke(main, ["check-physics", "--dataset", "synthetic", "--data-root", str(world),
                                    "--cache", str(tmp_path / "cache"), "--workers", "1"])
    assert out.exit_code == 0, out.output
    assert "4 frame(s) of synthetic:" in out.output
    rows = dict(re.findall(r"^  (.+?): (.+)$", out.output, re.M))
    values = {name: dict(re.findall(r"(\w+) = ([^,]+)", line)) for name, line in rows.items()}
    rules = [name for name in values if name.startswith("range (")]
    assert len(rules) == 5 and "doppler (static points)" in values
    assert len({values[r]["points"] for r in rules}) == 1 and int(values[rules[0]]["points"]) > 100
    assert len({values[r]["no_support_share"] for r in rules}) == 1  # the same lidar window for every rule
    # the hidden radar's points lie on the surfaces the lidar sees, and its Doppler is the ego motion's
    oracle = values["range (best lidar point in the window, an oracle)"]
    assert float(oracle["median_abs_dr_m"]) < 0.3 and float(oracle["within_1m_share"]) > 0.7
    assert all(float(values[r]["median_abs_dr_m"]) >= float(oracle["median_abs_dr_m"]) for r in rules)
    assert float(values["doppler (static points)"]["median_abs_dv_mps"]) < 0.1


def test_check_physics_logs_its_progress(world, tmp_path):
    """check-physics read every calibrated frame without a word on stderr until 2026-12-07 (tens
    of thousands of frames: minutes of silence in a log)."""
    out = CliRunner().invoke(main, ["check-physics", "--dataset", "synthetic", "--data-root", str(world),
                                    "--cache", str(tmp_path / "cache"), "--workers", "1",
                                    "--set", "run.progress_every_s=0.000001"])
    assert out.exit_code == 0, out.output
    assert re.search(r"^check-physics: \d/4 \(\d+%\)", out.stderr, re.M), out.stderr


def test_estimate_sigma_uses_the_frames_asked_for(world, tmp_path):
    from pipeline.config import load_config
    from pipeline.heatmap import sigma_from_frames
    from pipeline.readers import get_reader

    args = ["estimate-sigma", "--dataset", "synthetic", "--data-root", str(world), "--cache", str(tmp_path / "c")]
    reader = get_reader(load_config("synthetic", environ={}), str(world))
    ids = reader.frame_ids()
    for spec, chosen in (("", ids), ("1:3", ids[1:3])):
        out = CliRunner().invoke(main, args + (["--frames", spec] if spec else []))
        assert out.exit_code == 0, out.output
        sx, sy = sigma_from_frames([reader.read(i) for i in chosen])
        assert f"estimated Sigma std: {sx:.1f} px (u), {sy:.1f} px (v)" in out.output
        assert f"--set heatmap.sigma_px={sx:.0f},{sy:.0f}" in out.output and sx > 0 and sy > 0
    bad = CliRunner().invoke(main, args + ["--frames", "99"])
    assert bad.exit_code == 2 and "'99' is no frame id here" in bad.output


def test_estimate_sigma_skips_and_names_unreadable_frames(world, tmp_path):
    """Until 2026-12-05 the first unreadable frame stopped it (and it held every frame read in memory)."""
    import shutil

    from pipeline.config import load_config
    from pipeline.heatmap import sigma_from_frames
    from pipeline.readers import get_reader

    copy = tmp_path / "world"
    shutil.copytree(world, copy)
    reader = get_reader(load_config("synthetic", environ={}), str(copy))
    ids = reader.frame_ids()
    images = sorted(copy.glob("*/training/image_2/*.png"))  # the world's two layouts: each has the images
    bad = ids[1]
    for image in images:
        if image.stem == bad:
            image.write_bytes(b"not a png")
    args = ["estimate-sigma", "--dataset", "synthetic", "--data-root", str(copy), "--cache", str(tmp_path / "c")]
    out = CliRunner().invoke(main, args)
    assert out.exit_code == 0, out.output
    assert re.search(rf"^1 unreadable frame\(s\) skipped: {bad}: .*{bad}", out.stderr, re.M), out.stderr
    sx, sy = sigma_from_frames([reader.read(i) for i in ids if i != bad])
    assert (sx, sy) != sigma_from_frames([reader.read(i) for i in ids[2:]])  # frame 0 was used
    assert f"estimated Sigma std: {sx:.1f} px (u), {sy:.1f} px (v) at full resolution from {len(ids) - 1} frame(s)" \
        in out.stdout
    for image in images:
        image.write_bytes(b"")
    out = CliRunner().invoke(main, args)
    assert out.exit_code == 2 and "Traceback" not in out.output
    assert out.stderr.startswith("error: dataset synthetic: cannot estimate Sigma from the 0 readable frame(s) (")
    assert f"; {len(ids)} unreadable frame(s) skipped: " in out.stderr and "and 1 more" in out.stderr


def test_a_number_that_is_no_id_is_refused_where_ids_are_numbers():
    """'60' on Astyx (ids '000060') was taken as index 60, another frame, and --force recomputed it."""
    from pipeline.errors import ConfigError
    from pipeline.frame_selection import parse_frames

    ids = [f"{i:06d}" for i in range(0, 400, 4)]  # Astyx-like: numbered, not every number
    assert parse_frames("000060,000064", ids) == [15, 16] and parse_frames("60:62", ids) == [60, 61]
    with pytest.raises(ConfigError, match="'60' is no frame id here .*'60:61'"):
        parse_frames("60", ids)
    assert parse_frames("1,a", ["a", "b"]) == [1, 0]  # ids that are no numbers: a number is an index


@pytest.mark.parametrize("setting, words", [("split.rule=sequnce", "'split.rule' must be one of sequence"),
                                            ("synth.count=orcale", "'synth.count' must be one of predicted, disnet, oracle")])
def test_a_misspelt_choice_is_refused_before_any_output_is_touched(world, tmp_path, setting, words):
    """A typo in split.rule failed every calibrate frame, discarding a finished output; one in
    synth.count recomputed synthesize with the predicted count."""
    args = ["--dataset", "synthetic", "--data-root", str(world), "--cache", str(tmp_path / "c"), "--workers", "1"]
    assert CliRunner().invoke(main, ["run", "calibrate", *args]).exit_code == 0
    stamp = (tmp_path / "c" / "synthetic" / "calibrate.zarr" / "zarr.json").stat().st_mtime_ns
    out = CliRunner().invoke(main, ["run", "synthesize", *args, "--set", setting])
    assert out.exit_code == 2 and words in out.output, out.output
    assert (tmp_path / "c" / "synthetic" / "calibrate.zarr" / "zarr.json").stat().st_mtime_ns == stamp
    assert not (tmp_path / "c" / "synthetic" / "heatmaps.zarr").exists()


def test_an_empty_cache_option_is_refused_not_a_folder_at_the_root(world, monkeypatch):
    monkeypatch.setenv("PIPELINE_CACHE", "")
    for args in (["--cache", ""], []):
        out = CliRunner().invoke(main, ["run", "calibrate", "--dataset", "synthetic", "--data-root", str(world), *args])
        assert out.exit_code == 2 and "--cache (or $PIPELINE_CACHE) is empty" in out.output, out.output
    assert not Path("/synthetic").exists()


def test_an_empty_dataset_option_is_refused_naming_the_variable(tmp_path, monkeypatch):
    """`PIPELINE_DATASET= pipeline status` (an unset shell variable) said "unknown dataset profile ''",
    not where the empty name came from; unlock looked for a lock at CACHE//locks, and unlock of an
    unknown or empty dataset (or with an empty --cache) said 'no lock at ...' with exit code 0."""
    monkeypatch.setenv("PIPELINE_DATASET", "")
    cache = ["--cache", str(tmp_path / "c")]
    for command in (["status"], ["config"], ["run", "calibrate", "--dry-run"], ["unlock", "train"]):
        out = CliRunner().invoke(main, [*command, *cache])
        assert out.exit_code == 2 and out.stderr.startswith("error: --dataset (or $PIPELINE_DATASET) is empty: give "
                                                             "a dataset profile (astyx, "), (command, out.output)
    monkeypatch.delenv("PIPELINE_DATASET")
    out = CliRunner().invoke(main, ["unlock", "train", "--dataset", "astx", *cache])
    assert out.exit_code == 2 and "unknown dataset profile 'astx'" in out.stderr and "did you mean 'astyx'" in out.stderr
    out = CliRunner().invoke(main, ["unlock", "train", "--cache", ""])
    assert out.exit_code == 2 and "--cache (or $PIPELINE_CACHE) is empty" in out.stderr
    out = CliRunner().invoke(main, ["unlock", "train", *cache])
    assert out.exit_code == 0 and out.output.startswith("no lock at ")


def test_verify_and_status_say_when_there_is_no_cache(tmp_path):
    """A mistyped --cache: verify said 'no stage output to verify' with exit code 0 (and made lock
    folders there); status listed every stage as not run."""
    where = tmp_path / "typo"
    out = CliRunner().invoke(main, ["verify", "--dataset", "astyx", "--cache", str(where)])
    assert out.exit_code == 2 and f"no cache of dataset astyx at {where / 'astyx'}" in out.output, out.output
    assert not where.exists()
    out = CliRunner().invoke(main, ["status", "--dataset", "astyx", "--cache", str(where)])
    assert out.exit_code == 0 and "(no cache of this dataset there" in out.output


def test_a_file_url_cache_is_its_folder(world, tmp_path):
    out = CliRunner().invoke(main, ["run", "heatmaps", "--dataset", "synthetic", "--data-root", str(world),
                                    "--cache", f"file://{tmp_path / 'c'}", "--workers", "1"])
    assert out.exit_code == 0, out.output
    assert (tmp_path / "c" / "synthetic" / "heatmaps.zarr" / "zarr.json").is_file()


def test_ctrl_c_while_the_world_is_generated_says_its_sequences_are_kept(tmp_path, monkeypatch):
    """The run generates the built-in world first; Ctrl-C there keeps its finished sequences."""
    import pipeline.world

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline.world, "generate", interrupted)
    out = CliRunner().invoke(main, ["run", "calibrate", "--cache", str(tmp_path / "cache")])
    assert out.exit_code == 130
    assert out.output.strip().splitlines()[-1] == (
        "interrupted in the synthetic world's generation: its finished frames are kept; "
        "run the same command again to resume")


def test_start_stop_written_as_frame_ids_is_refused_where_the_ids_are_not_the_indices():
    """'--frames 000100:000110' on Astyx (141 frames, ids 000000-000545 with gaps) selected the
    frames at indices 100-109 (ids 000370-000374 and 000420-000424), and --force recomputed them without a word."""
    from pipeline.errors import ConfigError
    from pipeline.frame_selection import parse_frames

    ids = [f"{i:06d}" for i in [*range(0, 11), *range(60, 80), *range(300, 315)]]
    with pytest.raises(ConfigError, match=r"'000060' is written as a frame id \(there is no index 60\): the "
                                          r"frames with ids from 000060 up to 000070 \(not included\) are `--frames 11:21`"):
        parse_frames("000060:000070", ids)
    with pytest.raises(ConfigError, match="'000005' .* are `--frames 3:`"):
        parse_frames("000005:", [f"{i:06d}" for i in [1, 2, 3, 5, 8]])
    with pytest.raises(ConfigError, match="no frame here has one of the ids from 000100 up to 000200"):
        parse_frames("000100:000200", ids)
    # where the ids name the frames the indices do, START:STOP stands (the synthetic world's ids)
    assert parse_frames("000000:000005", ids) == [0, 1, 2, 3, 4] and parse_frames("5:7", ids) == [5, 6]
    assert parse_frames("00005:00007", [f"{i:05d}" for i in range(20)]) == [5, 6]


def test_estimate_sigma_generates_the_synthetic_world_into_the_cache_first(tmp_path, monkeypatch):
    """Until 2026-12-06 estimate-sigma read the cache's world without generating it, as `run`,
    ablate and check-physics do: on a fresh cache it said 'cannot estimate Sigma from the 0
    readable frame(s) ... give more frames' (with --frames: 'selects no frame (this dataset has 0')."""
    cache = tmp_path / "c"
    sets = ["--set", "dataset.world_frames=4", "--set", "dataset.world_sequence_len=4"]
    out = CliRunner().invoke(main, ["estimate-sigma", "--cache", str(cache), *sets])
    assert out.exit_code == 0, out.output
    assert (cache / "synthetic" / "world" / "world.json").exists()
    assert "estimated Sigma std:" in out.stdout and "from 4 frame(s)" in out.stdout


def test_estimate_sigma_says_no_frames_found_and_no_radar(tmp_path):
    """A data root without frames was 'cannot estimate Sigma from the 0 readable frame(s) ... give
    more frames', and KITTI (no radar: no frame of it can give Sigma) the same after reading every
    frame. Now the first as `run` says it, the second at the first frame read."""
    from tests.test_readers_kitti import _make

    (tmp_path / "empty").mkdir()
    out = CliRunner().invoke(main, ["estimate-sigma", "--dataset", "kitti", "--data-root", str(tmp_path / "empty"),
                                    "--cache", str(tmp_path / "c")])
    assert out.exit_code == 2 and "Traceback" not in out.output
    assert out.stderr.startswith(f"error: dataset at {tmp_path / 'empty'}: no frames found (a frame needs "), out.stderr
    _make(tmp_path / "kitti")
    out = CliRunner().invoke(main, ["estimate-sigma", "--dataset", "kitti", "--data-root", str(tmp_path / "kitti"),
                                    "--cache", str(tmp_path / "c"), "--set", "camera.full_size=64,48",
                                    "--set", "camera.crop_rows=0,48"])
    assert out.exit_code == 2 and "Traceback" not in out.output
    assert out.stderr.startswith("error: dataset kitti has no radar (frame 000007)"), out.stderr


def test_verify_logs_each_stage_without_escape_codes(world, tmp_path):
    """verify's bars were left open until every stage was read, so on a log each later one was drawn
    below the first and closed with cursor-up escape codes (lines of '\\x1b[A' in the file; found
    2026-12-07): each stage's bar is now closed when the next stage's reading begins."""
    cache = ["--dataset", "synthetic", "--data-root", str(world), "--cache", str(tmp_path / "cache")]
    assert CliRunner().invoke(main, ["run", "heatmaps", *cache, "--workers", "1"]).exit_code == 0
    out = CliRunner().invoke(main, ["verify", *cache, "--set", "run.progress_every_s=0.000001"])
    assert out.exit_code == 0, out.output
    assert "\x1b" not in out.stderr and "\r" not in out.stderr, repr(out.stderr)
    assert re.search(r"^verify calibrate: \d+/\d+ \(\d+%\)", out.stderr, re.M), out.stderr
    assert re.search(r"^verify heatmaps: \d+/\d+ \(\d+%\)", out.stderr, re.M), out.stderr
