"""generate(): write a whole synthetic world (all sequences) in the VoD layout.

Frames are numbered globally 00000.. in order; a sequence is ``sequence_len`` consecutive frames of
one scene (scene types cycle through ``scene_mix``). Sequences are independent and seeded by
(seed, sequence index), so they run in parallel (2 processes) and the same seed gives the same
bytes. ``world.json`` is written last (atomically): a folder without it is an incomplete world. A run
that stops (killed, a crash) leaves each finished sequence's entry under ``partial/``; the next
generate() with the same arguments keeps those sequences and makes only the others (the same bytes
as one uninterrupted run, since sequences are independent), other arguments start afresh.
"""

from __future__ import annotations

import json
import os
import shutil
import threading
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import ConfigError
from pipeline.progress import EVERY_S, bar as progress_bar
from pipeline.world.materials import MATERIALS
from pipeline.world.radar import RadarModel
from pipeline.world.rig import LIDAR_PATTERNS, make_rig
from pipeline.world.scene import LABELLED_CLASSES, SCENE_TYPES
from pipeline.world.sim import make_sequence
from pipeline.world.vod_writer import make_dirs, write_frame

GENERATOR_VERSION = "1"
WORLD_JSON = "world.json"
MAX_WORKERS = 2


def generate(out_dir: str | Path, frames: int, seed: int, resolution_wh: tuple[int, int] = (640, 384),
             scene_mix: tuple[str, ...] = ("residential", "urban", "highway"), lidar_lines: int = 64,
             sequence_len: int = 40, progress: bool = False, every_s: float = EVERY_S) -> dict:
    """Generate ``frames`` frames into ``out_dir``; returns a summary
    {frames, sequences, seconds, mean_radar_points, out_dir}. ``progress``: on stderr
    (pipeline.progress.bar; ``every_s``: seconds between its lines where stderr is no terminal).

    Raises ConfigError for invalid arguments. An existing world in ``out_dir`` is replaced.
    """
    _check_args(frames, resolution_wh, scene_mix, lidar_lines, sequence_len)
    start = time.perf_counter()
    root = Path(out_dir)
    args = {"version": GENERATOR_VERSION, "frames": int(frames), "seed": int(seed),
            "resolution_wh": [int(resolution_wh[0]), int(resolution_wh[1])], "scene_mix": list(scene_mix),
            "lidar_lines": int(lidar_lines), "sequence_len": int(sequence_len)}
    finished = _finished_sequences(root, args)
    if not finished:
        _clear(root)
        _write_json(root / PARTIAL / ARGS_JSON, args)
    make_dirs(root)
    jobs = [(str(root), i, first, min(sequence_len, frames - first), int(seed), scene_mix[i % len(scene_mix)],
             (int(resolution_wh[0]), int(resolution_wh[1])), int(lidar_lines))
            for i, first in enumerate(range(0, frames, sequence_len))]
    results = _run_jobs([j for j in jobs if j[1] not in finished], frames, progress,
                        sum(j[3] for j in jobs if j[1] in finished), every_s)
    results = sorted([*finished.values(), *results], key=lambda r: r["first_frame"])
    _write_index(root, results)
    counts = [c for r in results for c in r["radar_points"]]
    summary = {
        "frames": frames, "sequences": len(results), "mean_radar_points": float(np.mean(counts)),
    }
    world = {
        "generator": "pipeline.world", "version": GENERATOR_VERSION, "seed": int(seed), "frames": frames,
        "resolution_wh": [int(resolution_wh[0]), int(resolution_wh[1])], "lidar_lines": int(lidar_lines),
        "sequence_len": int(sequence_len), "scene_mix": list(scene_mix), "frame_rate_hz": 10.0,
        "materials": [{"id": i, "name": m.name, "rcs_dbsm": m.rcs_dbsm, "texture": m.texture}
                      for i, m in enumerate(MATERIALS)],
        "classes": list(LABELLED_CLASSES), "radar": _radar_description(RadarModel()),
        "mean_radar_points": summary["mean_radar_points"], "sequences": results,
    }
    _write_json(root / WORLD_JSON, world)
    shutil.rmtree(root / PARTIAL)
    summary["seconds"] = time.perf_counter() - start
    summary["resumed_sequences"] = len(finished)
    summary["out_dir"] = str(root)
    return summary


def _check_args(frames: int, resolution_wh: tuple[int, int], scene_mix: tuple[str, ...], lidar_lines: int,
                sequence_len: int) -> None:
    if int(frames) < 1:
        raise ConfigError(f"world frames must be >= 1, got {frames}")
    if int(sequence_len) < 1:
        raise ConfigError(f"world sequence_len must be >= 1, got {sequence_len}")
    if len(resolution_wh) != 2 or min(resolution_wh) < 16:
        raise ConfigError(f"world resolution must be (W, H) with both >= 16, got {resolution_wh}")
    if not scene_mix or any(s not in SCENE_TYPES for s in scene_mix):
        raise ConfigError(f"scene_mix {scene_mix!r}: each entry must be one of {SCENE_TYPES}")
    if lidar_lines not in LIDAR_PATTERNS:
        raise ConfigError(f"lidar_lines must be one of {sorted(LIDAR_PATTERNS)}, got {lidar_lines}")


PARTIAL = "partial"
"""Folder of an unfinished world: its arguments and each finished sequence's entry."""
ARGS_JSON = "arguments.json"


def _write_json(path: Path, value: Any) -> None:
    """Write ``value`` as JSON atomically (a temporary file renamed)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(value, indent=1))
    os.replace(tmp, path)


def _finished_sequences(root: Path, args: dict) -> dict[int, dict]:
    """{sequence index: world.json entry} of the sequences an unfinished run with the same
    ``args`` completed in ``root`` (empty: none, a finished world, or other arguments)."""
    if (root / WORLD_JSON).exists():
        return {}
    try:
        if json.loads((root / PARTIAL / ARGS_JSON).read_text()) != args:
            return {}
        entries = [json.loads(p.read_text()) for p in sorted((root / PARTIAL).glob("seq*.json"))]
    except (OSError, ValueError):  # nothing to resume, or a file cut short: start afresh
        return {}
    return {int(e["index"]): e["entry"] for e in entries}


def _clear(root: Path) -> None:
    """Remove a previous world's marker first, then its folders (only the ones this module writes)."""
    marker = root / WORLD_JSON
    if marker.exists():
        marker.unlink()
    for sub in (PARTIAL, "lidar", "radar", "ImageSets"):
        if (root / sub).exists():
            shutil.rmtree(root / sub)


PARENT_POLL_S = 0.5
"""How often a generating worker checks that the process that started it is still there."""


def _watch_parent(parent_pid: int) -> None:
    """Pool initializer: the worker exits once the process that started it is gone (killed with
    SIGKILL or SIGTERM), instead of generating on as an orphan that holds the run's output open."""
    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_POLL_S)
        os._exit(1)

    threading.Thread(target=watch, name="watch-parent", daemon=True).start()


def _run_jobs(jobs: list[tuple], frames: int, progress: bool, done_frames: int = 0,
              every_s: float = EVERY_S) -> list[dict]:
    """Run the sequence jobs (in 2 processes when there are several); results in sequence order.
    Each finished sequence's entry is recorded under ``partial/`` as it comes in (what a later run
    resumes from); ``done_frames`` of the ``frames`` were made by an earlier run."""
    bar = progress_bar(total=frames, initial=done_frames, unit="frame", enabled=progress, desc="generate-world",
                       every_s=every_s)
    workers = min(MAX_WORKERS, len(jobs), os.cpu_count() or 1)
    results = []

    def finished(job: tuple, res: dict) -> None:
        _write_json(Path(job[0]) / PARTIAL / f"seq{job[1]:05d}.json", {"index": job[1], "entry": res})
        results.append(res)
        bar.update(res["last_frame"] - res["first_frame"] + 1)

    if workers <= 1:
        for job in jobs:
            finished(job, run_sequence(*job))
    else:
        import multiprocessing

        # spawn, not fork: forking a process that already runs threads (torch, dask, BLAS) can
        # deadlock the child on a lock some thread held at the fork
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_watch_parent,
                                 initargs=(os.getpid(),)) as pool:
            futures = {pool.submit(_run_job, job): job for job in jobs}
            for future in as_completed(futures):  # recorded in the order they finish: none waits on another
                finished(futures[future], future.result())
    bar.close()
    return sorted(results, key=lambda r: r["first_frame"])


def _run_job(job: tuple) -> dict:
    return run_sequence(*job)


def run_sequence(root: str, seq_index: int, first_frame: int, n_frames: int, seed: int, scene_type: str,
                 resolution_wh: tuple[int, int], lidar_lines: int) -> dict:
    """Simulate and write one sequence; returns its entry for world.json."""
    import cv2

    cv2.setNumThreads(1)
    rig = make_rig(resolution_wh, lidar_lines)
    sim = make_sequence(scene_type, n_frames, rig, seed, seq_index)
    rng = np.random.default_rng([seed, seq_index, 99])
    T_map_world = _planar_transform(rng.uniform(-2000, 2000, 2), rng.uniform(-np.pi, np.pi))
    T_utm_map = _planar_transform(np.array([594000.0, 5762000.0]), np.radians(1.4))
    speeds, counts, v_radar = [], [], []
    for k in range(n_frames):
        data = sim.frame(k)
        write_frame(Path(root), frame_id(first_frame + k), data, rig, T_map_world, T_utm_map)
        speeds.append(round(data.ego_speed_mps, 4))
        counts.append(int(len(data.radar.points_D)))
        v_radar.append([round(float(v), 6) for v in data.v_radar_D])
    return {"name": f"seq{seq_index:03d}_{scene_type}", "scene": scene_type, "first_frame": first_frame,
            "last_frame": first_frame + n_frames - 1, "curvature_1pm": float(sim.scene.layout.kappa_1pm),
            "ego_speed_mps": speeds, "mean_ego_speed_mps": round(float(np.mean(speeds)), 4),
            "radar_velocity_D": v_radar, "radar_points": counts}


def _planar_transform(xy: np.ndarray, yaw: float) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    T[:2, 3] = xy
    return T


def frame_id(number: int) -> str:
    """The id of the world's frame ``number`` (counted from 0): the stem of its files."""
    return f"{number:05d}"


def frame_ids(frames: int) -> list[str]:
    """The frame ids of a world of ``frames`` frames, as its reader lists them: every frame is
    written whole, numbered 0 to frames - 1 whatever the other settings (the dry run checks
    --frames against them before the world is generated)."""
    return [frame_id(i) for i in range(frames)]


def _write_index(root: Path, results: list[dict]) -> None:
    """ImageSets/full.txt (frame ids) and ImageSets/sequences.txt (name first last, inclusive)."""
    ids = [frame_id(f) for r in results for f in range(r["first_frame"], r["last_frame"] + 1)]
    (root / "ImageSets" / "full.txt").write_text("".join(i + "\n" for i in ids))
    (root / "ImageSets" / "sequences.txt").write_text(
        "".join(f"{r['name']} {frame_id(r['first_frame'])} {frame_id(r['last_frame'])}\n" for r in results))


def _radar_description(model: RadarModel) -> dict:
    """The radar's public characteristics (what a radar data sheet would say)."""
    return {"fov_az_deg": model.fov_az_deg, "fov_el_deg": model.fov_el_deg, "max_range_m": model.max_range_m,
            "az_res_deg": 1.5, "el_res_deg": 1.5, "doppler_convention": "range rate, negative approaching",
            "rss_unit": "dB (with range fall-off)", "rss_range_db": [model.rss_min_db, model.rss_max_db]}
