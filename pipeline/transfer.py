"""Nets trained on one dataset, used on another (``train.nets_from``): the method's purpose, a radar
learnt from one dataset's recordings synthesized for camera + lidar frames that have none.

What the nets carry from their dataset is the radar they learnt and the geometry of their inputs
(:data:`RADAR_SETTINGS`): its field of view and resolution, its count scale, its RSS range and
units, its Doppler convention, and the size of RSS-Net's image patches and local range images.
Those settings of the dataset that uses the nets must be the trained ones: :func:`with_nets_from`
puts them into its configuration (a value given explicitly that differs is an error), and the
train stage checks them (:func:`mismatches`) before it takes the checkpoints. Everything else
(camera, lidar, working resolution, splits) stays the dataset's own.

Dis-Net's map follows the image it is given, except its prior, the source's mean training map:
where the source radar's returns land in the source camera's image. On another camera (focal
length, crop, pitch) :func:`rebase_prior` moves that prior to the same directions from the radar
at the source radar's typical range (:func:`source_camera`, :func:`prior_in_target`).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.cache import frame_store
from pipeline.cachefs import command_options
from pipeline.config import Config, check_profile, load_config, own_radar
from pipeline.dirstore import DirStore, dir_store
from pipeline.errors import ConfigError, MetadataError, PipelineError

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


def nets_origin(cache_root: str, dataset: str) -> str:
    """The dataset whose train stage trained the nets that ``dataset``'s train stage holds: itself,
    or, where that one took another's (its summary's ``nets_from``), that one's origin, and so on
    (KITTI taking View-of-Delft's nets that are Astyx's: 'astyx'). Nets are taken from the origin,
    with its camera and settings, and retraining the origin makes every dataset down the chain
    stale. A dataset without a finished train stage is its own origin (the train stage then says
    it has not run). PipelineError on a loop."""
    chain = [dataset]
    while True:
        meta = source_train(cache_root, chain[-1]).meta() or {}
        taken_from = meta.get("summary", {}).get("nets_from")
        if not taken_from:
            return chain[-1]
        if taken_from in chain:
            raise PipelineError(f"train.nets_from: the datasets take their nets from each other in a loop "
                                f"({' -> '.join([*chain, taken_from])}); train one of them on its own radar")
        chain.append(taken_from)


def checked_origin(cfg: Config, cache_root: str) -> str:
    """The dataset that trained the nets ``cfg.train.nets_from`` leads to (:func:`nets_origin`);
    ConfigError when those are this dataset's own: taking them would first clear them as a stale
    train output."""
    origin = nets_origin(cache_root, cfg.train.nets_from)
    if origin == cfg.profile:
        raise ConfigError(f"train.nets_from = '{cfg.train.nets_from}': its nets are this dataset's own (taken from "
                          f"'{origin}'); leave train.nets_from empty to train here")
    return origin


def trained_settings(cache_root: str, dataset: str) -> dict[str, Any]:
    """The :data:`RADAR_SETTINGS` the finished train stage of ``dataset`` (a profile name) under
    ``cache_root`` trained with: its record (written since 2026-12-02), else the values its
    calibrate and patches outputs recorded, the rest from its profile. PipelineError when that
    train stage has not finished."""
    train = source_train(cache_root, dataset)
    meta = train.meta()
    if meta is None:
        raise PipelineError(f"train.nets_from = '{dataset}': no finished train stage at {train.url}; run "
                            f"`pipeline run train {command_options(dataset, cache_root)} --data-root ...` first")
    recorded = meta.get("summary", {}).get("settings")
    if recorded:
        return {key: recorded[key] for key in RADAR_SETTINGS if key in recorded}
    out = settings(load_config(dataset, environ={}))
    for stage in ("calibrate", "patches"):
        store = frame_store(cache_root, dataset, stage)
        if store.exists():
            out.update({k: v for k, v in store.attrs().get("config", {}).items() if k in out})
    return out


def _made_with_other_radar(cfg: Config, cache_root: str) -> bool:
    """Whether dataset ``cfg.profile``'s calibrate output under ``cache_root`` recorded radar
    settings other than ``cfg``'s (False without one, or where its metadata cannot be read: the run
    then stops on that)."""
    store = frame_store(cache_root, cfg.profile, "calibrate")
    try:
        recorded = store.attrs().get("config", {}) if store.exists() else {}
    except MetadataError:
        return False
    return any(key in recorded and recorded[key] != _json(cfg.get(key)) for key in RADAR_SETTINGS)


def other_nets_taken(cfg: Config, cache_root: str) -> str:
    """The dataset whose nets this dataset's finished train stage took, where that is not the one
    ``cfg.train.nets_from`` names; '' otherwise (or where the record cannot be read)."""
    try:
        meta = dir_store(cache_root, cfg.profile, "train").meta()
    except MetadataError:  # the run stops on it, naming the file
        return ""
    taken = ((meta or {}).get("summary") or {}).get("nets_from") or ""
    return taken if taken != cfg.train.nets_from else ""


def _refuse_other_nets_by_default(cfg: Config, cache_root: str) -> None:
    """ConfigError where this dataset's finished train stage took the nets of another dataset than
    ``cfg.train.nets_from`` names (the profile's value: the user did not set it)."""
    taken = other_nets_taken(cfg, cache_root)
    if not taken:
        return
    now = (f"take those of '{cfg.train.nets_from}' (the profile's train.nets_from)" if cfg.train.nets_from
           else "train its own nets (the profile's train.nets_from is empty)")
    raise ConfigError(f"dataset '{cfg.profile}': its outputs in this cache were made with the nets of '{taken}' "
                      f"(train.nets_from = {taken}); without train.nets_from this run would {now} and make those "
                      f"outputs again, from the first stage whose settings differ. Add `--set train.nets_from={taken}` "
                      f"to go on with them, or set train.nets_from to change them (`--set train.nets_from=` trains "
                      f"here); nothing was run")


def mismatches(cfg: Config, trained: dict[str, Any]) -> list[str]:
    """'key=trained value (here: value)' for each of ``trained`` that ``cfg`` does not have."""
    return [f"{key}={_text(value)} (here: {_text(_json(cfg.get(key)))})" for key, value in trained.items()
            if _json(cfg.get(key)) != value]


def with_nets_from(cfg: Config, cache_root: str, explicit: Iterable[str] = (), require_trained: bool = False) -> Config:
    """``cfg`` with the trained :data:`RADAR_SETTINGS` of dataset ``cfg.train.nets_from`` (``cfg``
    itself when it names none, or its train stage has not finished: the train stage then stops
    with a message). ``explicit``: the keys the user set (--set, PIPELINE__ variables); one of them
    set to another value than the nets were trained with is a ConfigError. ``require_trained`` (a
    run): no finished train stage there is a ConfigError too where this dataset's calibrate output
    was made with other radar settings (the nets', before): the profile's would replace it; so is
    a train.nets_from left to the profile (not in ``explicit``) that differs from the one this
    dataset's finished train stage took its nets with: the run would make its outputs again with
    other nets (a --set train.nets_from=astyx forgotten on a later command)."""
    source = cfg.train.nets_from
    if require_trained and "train.nets_from" not in set(explicit):
        _refuse_other_nets_by_default(cfg, cache_root)
    if not source:
        return cfg
    if source == cfg.profile:
        raise ConfigError(f"train.nets_from = '{source}' names this dataset itself; leave it empty to train here")
    check_profile(source, "train.nets_from")
    source = checked_origin(cfg, cache_root)
    if source_train(cache_root, source).meta() is None:
        if require_trained and _made_with_other_radar(cfg, cache_root):
            raise ConfigError(f"train.nets_from = '{cfg.train.nets_from}': no finished train stage at "
                              f"{source_train(cache_root, source).url}, and this dataset's outputs were made with "
                              f"its radar settings, which the profile's would replace: run `pipeline run train "
                              f"{command_options(source, cache_root)} --data-root ...` first (nothing was run)")
        return cfg  # nothing trained there yet: the train stage says so when it runs
    trained = trained_settings(cache_root, source)
    clash = [m for m in mismatches(cfg, trained) if m.split("=", 1)[0] in set(explicit)]
    if clash:
        raise ConfigError(f"train.nets_from = '{source}': the nets were trained with other settings than given: "
                          f"{'; '.join(clash)}; the simulated radar is the trained one: drop those --set options")
    return cfg.with_overrides(trained)


@dataclass(frozen=True)
class Comparison:
    """How the evaluate stage compares a dataset's real radar with the synthesized one: ``rss``,
    whether RSS values are compared (the same units); ``doppler_span_mps``, the span modulo which
    Doppler is compared (0: none); ``notes``, what the report says about it (empty when nothing is
    left out); ``real_doppler_span_mps``, the real radar's own span (its physics check)."""

    rss: bool
    doppler_span_mps: float
    real_doppler_span_mps: float
    notes: tuple[str, ...] = ()


def comparison(cfg: Config) -> Comparison:
    """What of the dataset's real radar (its profile's: RSS unit, Doppler span) the synthesized
    radar of ``cfg`` (another dataset's when train.nets_from names one) can be compared with.

    Different RSS units: RSS is not compared (an RSS gate between dB(Mag) and dBsm matches nothing).
    Doppler: modulo the simulated radar's span when it aliases, else modulo the real radar's, so
    that a radar that wraps is compared with one that does not as the wrapping one measures.
    """
    r = cfg.radar
    if not cfg.train.nets_from:
        return Comparison(True, r.doppler_span_mps, r.doppler_span_mps)
    own = own_radar(cfg)
    notes = []
    rss = own.rss_unit == r.rss_unit
    if not rss:
        notes.append(f"RSS not compared: the real radar ({own.name}) measures {own.rss_unit}, the synthesized one "
                     f"({r.name}, nets of '{cfg.train.nets_from}') {r.rss_unit}; matched F1 gates position and "
                     f"Doppler only, and the RSS columns are empty")
    span = r.doppler_span_mps or own.doppler_span_mps
    if r.doppler_span_mps and own.doppler_span_mps and r.doppler_span_mps != own.doppler_span_mps:
        notes.append(f"Doppler compared modulo the synthesized radar's span {r.doppler_span_mps:g} m/s; the real "
                     f"radar's is {own.doppler_span_mps:g} m/s, so some of its wrapped values compare wrongly")
    elif span != r.doppler_span_mps:
        notes.append(f"Doppler compared modulo the real radar's span {span:g} m/s (the synthesized radar does not wrap)")
    elif span != own.doppler_span_mps:
        notes.append(f"Doppler compared modulo the synthesized radar's span {span:g} m/s (the real radar does not wrap)")
    overlap = (f" (with eval.split = {cfg.eval.split}, the evaluated frames among them)"
               if cfg.eval.split in ("all", "train") else "")
    notes.append(f"the baselines' counts and maps come from this dataset's own radar on its train split{overlap}, "
                 f"which the nets of '{cfg.train.nets_from}' never saw: they know this radar's count and layout")
    return Comparison(rss, float(span), float(own.doppler_span_mps), tuple(notes))


def _json(value: Any) -> Any:
    return json.loads(json.dumps(list(value) if isinstance(value, tuple) else value))


def _text(value: Any) -> str:
    return ",".join(str(v) for v in value) if isinstance(value, list) else str(value)


@dataclass(frozen=True)
class SourceCamera:
    """The camera the nets' dataset was calibrated with: ``K_working`` (3, 3) intrinsics of its
    working image (``working_wh`` pixels), ``T_radar_cam`` (4, 4) camera -> radar {D} (m), and
    ``range_m``, the median range of its radar's points (where the prior's directions are taken)."""

    K_working: np.ndarray
    T_radar_cam: np.ndarray
    working_wh: tuple[int, int]
    range_m: float


DEFAULT_RANGE_M = 20.0
"""range_m of a source without radar points in its calibrate output."""
SOURCE_CAMERA_FRAMES = 200
"""source_camera reads the radar points of at most this many frames (evenly spaced) for range_m."""


def source_camera(cache_root: str, dataset: str) -> SourceCamera:
    """The typical camera of ``dataset``'s calibrate output under ``cache_root``: the element-wise
    median intrinsics and camera position and the chordal mean rotation over its finished frames (a
    dataset with two calibration sets, like Astyx's, gets one between them), and its radar points'
    median range. PipelineError when that output has no finished frame."""
    from pipeline.cache import DONE

    store = frame_store(cache_root, dataset, "calibrate")
    done = np.flatnonzero(store.status() == DONE) if store.exists() else np.zeros(0, int)
    if not len(done):
        raise PipelineError(f"train.nets_from = '{dataset}': its calibrate output at {store.url} has no finished "
                            f"frame, and Dis-Net's prior needs that dataset's camera; run `pipeline run calibrate "
                            f"--dataset {dataset} --data-root ...` with this cache")
    K = np.median(np.asarray(store.array("K").oindex[done], np.float64), axis=0)
    T = np.asarray(store.array("T_radar_cam").oindex[done], np.float64)
    u, _, vt = np.linalg.svd(T[:, :3, :3].mean(0))
    if np.linalg.det(u @ vt) < 0:
        raise PipelineError(f"{store.url}: the camera rotations of dataset '{dataset}' do not average to a rotation")
    some = done[np.unique(np.linspace(0, len(done) - 1, min(len(done), SOURCE_CAMERA_FRAMES)).astype(int))]
    ranges = np.concatenate([np.linalg.norm(store.read("radar", int(i))[:, :3], axis=1) for i in some])
    T_typical = np.eye(4)
    T_typical[:3, :3], T_typical[:3, 3] = u @ vt, np.median(T[:, :3, 3], axis=0)
    w, h = (int(v) for v in store.attrs().get("config", {}).get("camera.working_size", (0, 0)))
    if w < 1 or h < 1:
        raise PipelineError(f"{store.url}: records no camera.working_size; run `pipeline run calibrate --force "
                            f"--dataset {dataset} ...` with this cache")
    return SourceCamera(K, T_typical, (w, h), float(np.median(ranges)) if len(ranges) else DEFAULT_RANGE_M)


def camera_record(camera: SourceCamera) -> dict[str, Any]:
    """``camera`` as JSON values (the train stage keeps it beside the nets it copies)."""
    return {"K_working": camera.K_working.tolist(), "T_radar_cam": camera.T_radar_cam.tolist(),
            "working_wh": list(camera.working_wh), "range_m": camera.range_m}


def camera_from_record(record: dict[str, Any]) -> SourceCamera:
    """Inverse of :func:`camera_record`."""
    return SourceCamera(np.asarray(record["K_working"], np.float64), np.asarray(record["T_radar_cam"], np.float64),
                        tuple(int(v) for v in record["working_wh"]), float(record["range_m"]))


def prior_in_target(prior_hw: np.ndarray, source: SourceCamera, K_working: np.ndarray, T_radar_cam: np.ndarray,
                    working_wh: tuple[int, int]) -> np.ndarray:
    """Dis-Net's prior (h, w) probability map over the source camera's working image, moved to the
    same places around the radar in a target camera (intrinsics ``K_working`` of its working image
    of ``working_wh`` pixels, ``T_radar_cam`` (4, 4) camera -> {D}), on an (h, w) grid over that
    image: float64 (h, w) summing to 1.

    Each target cell looks along its ray to the point at the source's radar range (``range_m``
    from the radar: the cameras' offsets from the radar matter at radar ranges), and takes the
    source's probability where the source camera sees that point (bilinear), times the cells of
    the source grid one target cell covers there. Beyond the source image's edges the prior is
    taken as at its nearest edge (the radar's field of view is wider than its camera's, and its
    pattern does not stop at that camera's edge); behind the source camera it is the prior's
    smallest."""
    import cv2

    prior = np.asarray(prior_hw, np.float64)
    h, w = prior.shape
    A_s = _grid_from_pixels((w, h), source.working_wh) @ np.asarray(source.K_working, np.float64)
    A_t = _grid_from_pixels((w, h), working_wh) @ np.asarray(K_working, np.float64)
    jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.stack([jj, ii, np.ones((h, w))], -1) @ np.linalg.inv(A_t).T @ np.asarray(T_radar_cam)[:3, :3].T
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)                               # unit, in {D}
    origin = np.asarray(T_radar_cam, np.float64)[:3, 3]                               # the camera in {D}
    along = rays @ origin
    reach = np.sqrt(np.maximum(along ** 2 - origin @ origin + source.range_m ** 2, 0.0)) - along
    points_D = origin + reach[..., None] * rays                                        # range_m from the radar
    T_cam_D = np.linalg.inv(np.asarray(source.T_radar_cam, np.float64))
    in_source = points_D @ T_cam_D[:3, :3].T + T_cam_D[:3, 3]
    ahead = in_source[..., 2] > 1e-3
    at = (in_source / np.where(ahead, in_source[..., 2], 1.0)[..., None]) @ A_s.T      # source grid cells
    sampled = cv2.remap(prior.astype(np.float32), at[..., 0].astype(np.float32), at[..., 1].astype(np.float32),
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    (dx_di, dx_dj), (dy_di, dy_dj) = np.gradient(at[..., 0]), np.gradient(at[..., 1])
    cells = np.abs(dx_dj * dy_di - dx_di * dy_dj)                                      # source cells per target cell
    out = np.where(ahead, sampled * cells, prior.min())
    return out / out.sum()


def _grid_from_pixels(grid_wh: tuple[int, int], working_wh: tuple[int, int]) -> np.ndarray:
    """(3, 3): working-image pixel coordinates -> coordinates on a (h, w) grid laid over the image
    (cell centres at ((j + 0.5) W / w - 0.5, (i + 0.5) H / h - 0.5), as a resize puts them)."""
    (w, h), (W, H) = grid_wh, (int(working_wh[0]), int(working_wh[1]))
    return np.array([[w / W, 0.0, 0.5 * w / W - 0.5], [0.0, h / H, 0.5 * h / H - 0.5], [0.0, 0.0, 1.0]])


def rebase_mixed_prior(prob_map_hw: np.ndarray, prior_source_hw: np.ndarray, prior_target_hw: np.ndarray,
                       w: float) -> np.ndarray:
    """:func:`rebase_prior` of a map that mixes a share ``w`` of its source prior into the network's
    own, (1 - w) map + w source (disnet.prior_mix): the network's part rebased, mixed with the
    target prior at the same share, so that the share chosen on val is kept; float32 summing to 1."""
    if w <= 0:
        return rebase_prior(prob_map_hw, prior_source_hw, prior_target_hw)
    source = np.asarray(prior_source_hw, np.float64) / np.sum(prior_source_hw)
    target = np.asarray(prior_target_hw, np.float64) / np.sum(prior_target_hw)
    own = np.clip(np.asarray(prob_map_hw, np.float64) - w * source, 0.0, None)  # (1 - w) times the network's map
    if w >= 1 or not own.sum() > 0:
        return target.astype(np.float32)
    out = (1 - w) * rebase_prior(own, source, target).astype(np.float64) + w * target
    return (out / out.sum()).astype(np.float32)


def rebase_prior(prob_map_hw: np.ndarray, prior_source_hw: np.ndarray, prior_target_hw: np.ndarray) -> np.ndarray:
    """Dis-Net's map (h, w) made with its source prior (its log added to the logits), as it would
    be with ``prior_target_hw`` instead: proportional to map * target / source; float32 summing to 1."""
    out = np.asarray(prob_map_hw, np.float64) * np.asarray(prior_target_hw, np.float64) / \
        np.asarray(prior_source_hw, np.float64)
    return (out / out.sum()).astype(np.float32)
