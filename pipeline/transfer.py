"""Nets trained on one dataset, used on another (``train.nets_from``): the method's purpose, a radar
learnt from one dataset's recordings synthesized for camera + lidar frames that have none.

What the nets carry from their dataset is the radar they learnt and the geometry of their inputs
(:data:`RADAR_SETTINGS`): its field of view and resolution, its count scale, its RSS range and
units, its Doppler convention, and the size of RSS-Net's image patches and local range images.
Those settings of the dataset that uses the nets must be the trained ones: :func:`with_nets_from`
puts them into its configuration (a value given explicitly that differs is an error), and the
train stage checks them (:func:`mismatches`) before it takes the checkpoints. Everything else
(camera, lidar, working resolution, splits) stays the dataset's own.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from typing import Any

from pipeline.cache import DirStore, dir_store, frame_store
from pipeline.config import Config, load_config
from pipeline.errors import ConfigError, PipelineError

RADAR_SETTINGS = ("radar.name", "radar.az_res_deg", "radar.el_res_deg", "radar.fov_az_deg", "radar.fov_el_deg",
                  "radar.max_range_m", "radar.max_points", "radar.rss_min", "radar.rss_max", "radar.rss_unit",
                  "radar.doppler_sign", "radar.doppler_span_mps",
                  "patches.r_c_px", "patches.r_l_m", "patches.range_image_size", "patches.patch_size_px")
"""The settings that trained nets carry to another dataset (module docstring)."""


def settings(cfg: Config) -> dict[str, Any]:
    """The :data:`RADAR_SETTINGS` of ``cfg``, as JSON values (what the train stage records)."""
    return {key: _json(cfg.get(key)) for key in RADAR_SETTINGS}


def source_train(cache_root: str, dataset: str) -> DirStore:
    """The train stage output of ``dataset`` under ``cache_root`` (whose nets another dataset uses)."""
    return dir_store(cache_root, dataset, "train")


def trained_settings(cache_root: str, dataset: str) -> dict[str, Any]:
    """The :data:`RADAR_SETTINGS` the finished train stage of ``dataset`` (a profile name) under
    ``cache_root`` trained with: its record (written since 2026-12-02), else the values its
    calibrate and patches outputs recorded, the rest from its profile. PipelineError when that
    train stage has not finished."""
    train = source_train(cache_root, dataset)
    meta = train.meta()
    if meta is None:
        raise PipelineError(f"train.nets_from = '{dataset}': no finished train stage at {train.url}; run "
                            f"`pipeline run train --dataset {dataset} --data-root ...` with this cache first")
    recorded = meta.get("summary", {}).get("settings")
    if recorded:
        return {key: recorded[key] for key in RADAR_SETTINGS if key in recorded}
    out = settings(load_config(dataset, environ={}))
    for stage in ("calibrate", "patches"):
        store = frame_store(cache_root, dataset, stage)
        if store.exists():
            out.update({k: v for k, v in store.attrs().get("config", {}).items() if k in out})
    return out


def mismatches(cfg: Config, trained: dict[str, Any]) -> list[str]:
    """'key=trained value (here: value)' for each of ``trained`` that ``cfg`` does not have."""
    return [f"{key}={_text(value)} (here: {_text(_json(cfg.get(key)))})" for key, value in trained.items()
            if _json(cfg.get(key)) != value]


def with_nets_from(cfg: Config, cache_root: str, explicit: Iterable[str] = ()) -> Config:
    """``cfg`` with the trained :data:`RADAR_SETTINGS` of dataset ``cfg.train.nets_from`` (``cfg``
    itself when it names none, or its train stage has not finished: the train stage then stops
    with a message). ``explicit``: the keys the user set (--set, PIPELINE__ variables); one of them
    set to another value than the nets were trained with is a ConfigError."""
    source = cfg.train.nets_from
    if not source:
        return cfg
    if source == cfg.profile:
        raise ConfigError(f"train.nets_from = '{source}' names this dataset itself; leave it empty to train here")
    if source_train(cache_root, source).meta() is None:
        return cfg  # nothing trained there yet: the train stage says so when it runs
    trained = trained_settings(cache_root, source)
    clash = [m for m in mismatches(cfg, trained) if m.split("=", 1)[0] in set(explicit)]
    if clash:
        raise ConfigError(f"train.nets_from = '{source}': the nets were trained with other settings than given: "
                          f"{'; '.join(clash)}; the simulated radar is the trained one: drop those --set options")
    return cfg.with_overrides(trained)


def _json(value: Any) -> Any:
    return json.loads(json.dumps(list(value) if isinstance(value, tuple) else value))


def _text(value: Any) -> str:
    return ",".join(str(v) for v in value) if isinstance(value, list) else str(value)
