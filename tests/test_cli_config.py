"""`pipeline config`: every key with the value a run would use, where it comes from and what it does."""

from __future__ import annotations

import re

import pytest

from click.testing import CliRunner

from pipeline.cli import main
from pipeline.config import all_keys, key_docs, load_config

LINE = re.compile(r"^(\w+\.\w+) = (.*)  \((.+)\)$")


def _lines(output: str) -> dict[str, tuple[str, str]]:
    return {m[1]: (m[2], m[3]) for m in map(LINE.match, output.splitlines()) if m}


def test_every_key_is_listed_with_a_value_that_set_reads_back(tmp_path):
    """Without KEY every key is listed once, with a description, and its printed value is --set's
    syntax for the same value (floats and tuples included)."""
    out = CliRunner().invoke(main, ["config", "--dataset", "astyx", "--cache", str(tmp_path / "cache")])
    assert out.exit_code == 0, out.output
    listed = _lines(out.output)
    assert list(listed) == all_keys()
    assert set(key_docs()) == set(all_keys()) and all(key_docs().values())
    cfg = load_config("astyx", environ={})
    for key, (text, _) in listed.items():
        again = load_config("astyx", {key: "" if text == "''" else text}, environ={})
        assert again.get(key) == cfg.get(key), (key, text)


def test_origins_and_sections(tmp_path):
    """A key is said to come from --set, the environment, the profile or the default, in that order
    of precedence; a section name lists its keys; the first sentence of each description follows."""
    args = ["config", "--dataset", "astyx", "--cache", str(tmp_path / "cache"), "--set", "disnet.prior_mix=val",
            "disnet", "train.epochs", "train.seed", "radar.doppler_span_mps"]
    out = CliRunner().invoke(main, args, env={"PIPELINE__TRAIN__SEED": "7", "PIPELINE__DISNET__PRIOR_MIX": "off"})
    assert out.exit_code == 0, out.output
    listed = _lines(out.output)
    assert [k for k in listed if k.startswith("disnet.")] == [k for k in all_keys() if k.startswith("disnet.")]
    assert listed["disnet.prior_mix"] == ("val", "--set")      # --set wins over the environment
    assert listed["train.seed"] == ("7", "environment")
    assert listed["train.epochs"] == ("12", "profile astyx")
    assert listed["radar.doppler_span_mps"] == ("10.3936", "profile astyx")
    assert listed["disnet.use_speed"] == ("true", "default")
    assert "    Epochs per net." in out.output.splitlines()
    short = [line for line in out.output.splitlines() if line.startswith("    With ``prior``: 'val' mixes")]
    assert short and "convex" not in out.output  # the first sentence only, without --full
    full = CliRunner().invoke(main, [*args[:5], "--full", "disnet.prior_mix"])
    assert full.exit_code == 0 and "L_KL is convex" in full.output


def test_an_unknown_key_names_the_nearest(tmp_path):
    out = CliRunner().invoke(main, ["config", "--cache", str(tmp_path / "cache"), "placement.map_wieght"])
    assert out.exit_code == 2
    assert "no configuration key or section 'placement.map_wieght'; did you mean 'placement.map_weight'?" in out.output


def test_set_keys_are_matched_ignoring_case_as_the_environment_variables_are(tmp_path):
    """--set TRAIN.EPOCHS=2 was 'unknown configuration key' with no suggestion, while
    PIPELINE__TRAIN__EPOCHS (any case) sets train.epochs."""
    from pipeline.config import parse_set_options

    args = ["config", "--cache", str(tmp_path / "cache"), "train.epochs", "dataset.radar_mount_T_radar_lidar"]
    eye = "1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1"
    out = CliRunner().invoke(main, [*args, "--set", "TRAIN.EPOCHS=2", "--set", f"Dataset.Radar_Mount_t_radar_lidar={eye}"])
    assert out.exit_code == 0, out.output
    lines = _lines(out.output)
    assert lines["train.epochs"] == ("2", "--set") and lines["dataset.radar_mount_T_radar_lidar"][1] == "--set"
    assert parse_set_options(["TRAIN.EPOCHS=2"]) == {"train.epochs": "2"}  # the key as the configuration spells it
    assert load_config("synthetic", parse_set_options(["Train.Epochs=3"]), environ={}).train.epochs == 3
    bad = CliRunner().invoke(main, [*args, "--set", "TRAIN.EPOCS=2"])
    assert bad.exit_code == 2 and "unknown configuration key 'TRAIN.EPOCS'; did you mean 'train.epochs'?" in bad.output


def test_a_value_the_nets_of_another_dataset_bring_is_named_so(tmp_path, monkeypatch):
    """With train.nets_from the nets' radar settings replace the profile's (pipeline.transfer):
    those keys are said to come from that dataset's nets."""
    from dataclasses import replace

    import pipeline.transfer

    def with_nets_from(cfg, *args, **kwargs):
        return replace(cfg, radar=replace(cfg.radar, name="Their radar"), train=replace(cfg.train, nets_from="vod"))

    monkeypatch.setattr(pipeline.transfer, "with_nets_from", with_nets_from)
    out = CliRunner().invoke(main, ["config", "--dataset", "kitti", "--cache", str(tmp_path / "cache"), "radar.name",
                                    "radar.fov_az_deg"])
    assert out.exit_code == 0, out.output
    listed = _lines(out.output)
    assert listed["radar.name"] == ("Their radar", "the nets of vod")
    assert listed["radar.fov_az_deg"][1] in ("profile kitti", "default")


def test_every_text_choice_is_held_where_it_is_set_with_the_nearest_named():
    """Every key of CHOICES refuses other values when the configuration is built (profile,
    environment, --set), naming the key, its values and the nearest; every default and profile
    value is one of them; the modules that act on a key take the same values."""
    from pipeline.config import CHOICES, SECTIONS, profile_names
    from pipeline.errors import ConfigError
    from pipeline.export import IMAGE_FORMATS

    for key, values in CHOICES.items():
        section, name = key.split(".")
        assert getattr(SECTIONS[section](), name) in values, key
        for profile in profile_names():
            assert load_config(profile, environ={}).get(key) in values, (profile, key)
        for value in values:
            assert load_config("synthetic", {key: value}, environ={}).get(key) == value
        near = values[0][:-1] + "x" if len(values[0]) > 3 else values[0] + "x"
        with pytest.raises(ConfigError) as err:
            load_config("synthetic", {key: near}, environ={})
        assert str(err.value).startswith(f"'{key}' must be one of {', '.join(values)}, got '{near}'"), str(err.value)
        assert str(err.value).endswith(f"; did you mean '{values[0]}'?"), str(err.value)
    assert tuple(IMAGE_FORMATS) == CHOICES["export.image_format"]


def test_a_misspelt_choice_is_refused_by_a_command_whose_stages_do_not_use_it(tmp_path):
    """Until 2026-12-07 a text choice was checked by the stage that used it: `run calibrate --set
    synth.placement=lidr` ran calibrate and `status` answered, leaving the typo unnoticed, and a
    variable in the environment likewise."""
    cache = str(tmp_path / "cache")
    for args, env in ((["run", "calibrate", "--data-root", str(tmp_path / "none"), "--set", "synth.placement=lidr"], {}),
                      (["status", "--set", "synth.placement=lidr"], {}),
                      (["status"], {"PIPELINE__SYNTH__PLACEMENT": "lidr"})):
        out = CliRunner().invoke(main, [*args, "--dataset", "synthetic", "--cache", cache], env=env)
        assert out.exit_code == 2, out.output
        assert "must be one of lidar, ray, got 'lidr'; did you mean 'lidar'?" in out.output, out.output
        assert ("PIPELINE__SYNTH__PLACEMENT" in out.output) == bool(env), out.output
    assert not (tmp_path / "cache").exists()
