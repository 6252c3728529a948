"""Tests of the synthetic world (pipeline/world): file formats, physics of the hidden radar, lidar,
ray casting against a brute-force oracle, determinism."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from pipeline.errors import ConfigError
from pipeline.world import generate
from pipeline.world.materials import MATERIAL_ID, MATERIALS
from pipeline.world.radar import RadarModel, centres_world
from pipeline.world.raycast import cast_grid, first_hit_dense, spherical_windows
from pipeline.world.rig import lidar_directions, make_rig
from pipeline.world.scene import BOX, CYLINDER, PLANE, actor_states, ego_pose
from pipeline.world.sim import make_sequence

FRAMES, SEQ_LEN, SIZE = 12, 6, (320, 192)


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("world")
    summary = generate(root, frames=FRAMES, seed=5, resolution_wh=SIZE, scene_mix=("urban", "residential"),
                       lidar_lines=16, sequence_len=SEQ_LEN)
    assert summary["frames"] == FRAMES and summary["sequences"] == 2
    return root


def _radar(root: Path, fid: str) -> np.ndarray:
    return np.fromfile(root / "radar/training/velodyne" / f"{fid}.bin", np.float32).reshape(-1, 7)


def _calib(path: Path) -> dict[str, list[float]]:
    out = {}
    for line in path.read_text().splitlines():
        key, vals = line.split(":", 1)
        out[key] = [float(v) for v in vals.split()]
    return out


def test_layout_and_formats(world: Path) -> None:
    import cv2

    ids = (world / "ImageSets/full.txt").read_text().split()
    assert ids == [f"{i:05d}" for i in range(FRAMES)]
    seqs = [line.split() for line in (world / "ImageSets/sequences.txt").read_text().splitlines()]
    assert [(int(a), int(b)) for _, a, b in seqs] == [(0, 5), (6, 11)]
    meta = json.loads((world / "world.json").read_text())
    assert meta["frames"] == FRAMES and [s["name"] for s in meta["sequences"]] == [s[0] for s in seqs]
    assert [m["name"] for m in meta["materials"]] == [m.name for m in MATERIALS]
    for fid in ids:
        for sensor in ("lidar", "radar"):
            calib = _calib(world / sensor / "training/calib" / f"{fid}.txt")
            assert set(calib) == {"P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo"}
            assert len(calib["P2"]) == 12 and len(calib["Tr_velo_to_cam"]) == 12 and calib["Tr_imu_to_velo"] == []
            lines = (world / sensor / "training/pose" / f"{fid}.json").read_text().splitlines()
            keys = [next(iter(json.loads(line))) for line in lines]
            assert keys == ["odomToCamera", "mapToCamera", "UTMToCamera"]
            for line in lines:
                T = np.array(next(iter(json.loads(line).values()))).reshape(4, 4)
                assert np.allclose(T[3], [0, 0, 0, 1]) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3))
        radar = (world / "radar/training/velodyne" / f"{fid}.bin").stat().st_size
        assert radar % 28 == 0 and radar > 0
        assert (world / "radar/training/meta" / f"{fid}.bin").stat().st_size == radar // 28 * 8
        assert (world / "lidar/training/velodyne" / f"{fid}.bin").stat().st_size % 16 == 0
        img = cv2.imread(str(world / "lidar/training/image_2" / f"{fid}.png"))
        assert img.shape == (SIZE[1], SIZE[0], 3)
        assert (world / "radar/training/image_2" / f"{fid}.png").read_bytes() == \
            (world / "lidar/training/image_2" / f"{fid}.png").read_bytes()
        for line in (world / "lidar/training/label_2" / f"{fid}.txt").read_text().splitlines():
            f = line.split()
            assert len(f) == 16 and f[0] in ("Car", "Truck", "Pedestrian", "Cyclist")
            assert int(f[1]) >= 0 and 0 <= float(f[4]) <= float(f[6]) < SIZE[0]
    assert (np.abs(_radar(world, "00003")[:, 3]) <= 40).all()


def test_ego_velocity_recoverable_exactly(world: Path) -> None:
    """v_r - v_r_compensated = -(u . v_radar) per point, so a least-squares fit returns v_radar."""
    meta = json.loads((world / "world.json").read_text())
    for seq in meta["sequences"]:
        for k, v_true in enumerate(seq["radar_velocity_D"]):
            pts = _radar(world, f"{seq['first_frame'] + k:05d}").astype(np.float64)
            u = pts[:, :3] / np.linalg.norm(pts[:, :3], axis=1, keepdims=True)
            assert np.abs((pts[:, 4] - pts[:, 5]) + u @ np.array(v_true)).max() < 1e-4
            v_fit = np.linalg.lstsq(u, pts[:, 5] - pts[:, 4], rcond=None)[0]
            assert np.allclose(v_fit, v_true, atol=1e-3)


def test_labels_enclose_their_radar_points(world: Path) -> None:
    """Radar points whose meta object id equals a label's track id lie in that 3-D box (within noise),
    read entirely from the written files (labels, radar calibration, radar bins, meta)."""
    model = RadarModel()
    checked = 0
    for k in range(FRAMES):
        fid = f"{k:05d}"
        calib = _calib(world / "radar/training/calib" / f"{fid}.txt")
        T_cam_radar = np.vstack([np.array(calib["Tr_velo_to_cam"]).reshape(3, 4), [0, 0, 0, 1]])
        pts = _radar(world, fid).astype(np.float64)
        obj = np.fromfile(world / "radar/training/meta" / f"{fid}.bin", np.int32).reshape(-1, 2)[:, 0]
        r = np.linalg.norm(pts[:, :3], axis=1)
        ang = model.noise_clip * np.radians(model.az_sigma_deg + model.el_sigma_deg)
        bound = model.noise_clip * model.range_sigma_m + (r + 1) * ang + 1e-3
        cam = pts[:, :3] @ T_cam_radar[:3, :3].T + T_cam_radar[:3, 3]
        for line in (world / "lidar/training/label_2" / f"{fid}.txt").read_text().splitlines():
            f = line.split()
            sel = obj == int(f[1])
            if not sel.any():
                continue
            h, w, l, x, y, z, ry = map(float, f[8:15])
            d = cam[sel] - [x, y - h / 2, z]
            local = np.stack([d @ [np.cos(ry), 0, -np.sin(ry)], d @ [np.sin(ry), 0, np.cos(ry)], -d[:, 1]], 1)
            excess = np.abs(local) - [l / 2, w / 2, h / 2]
            assert (excess.max(axis=1) <= bound[sel]).all(), (fid, f[0], excess.max())
            checked += sel.sum()
    assert checked > 30


def _finite_difference_velocity(sim, t: float, h: float = 1e-4) -> np.ndarray:
    """Radar velocity over ground in {D} by central differences of the radar pose (independent path)."""
    T_plus = ego_pose(sim.scene, t + h)[0] @ sim.rig.T_vehicle_radar
    T_minus = ego_pose(sim.scene, t - h)[0] @ sim.rig.T_vehicle_radar
    v_W = (T_plus[:3, 3] - T_minus[:3, 3]) / (2 * h)
    return (ego_pose(sim.scene, t)[0] @ sim.rig.T_vehicle_radar)[:3, :3].T @ v_W


@pytest.mark.parametrize("scene_type", ["residential", "urban", "highway"])
def test_noise_free_doppler_is_range_rate(scene_type: str) -> None:
    """Noise-free Doppler equals (v_target - v_radar) . u, velocities by finite differences of poses."""
    sim = make_sequence(scene_type, 12, make_rig((160, 96), 16), seed=11, seq_index=2, noise=False)
    h = 1e-4
    n_static = n_moving = 0
    for k in (3, 9):
        data = sim.frame(k, ("radar",))
        scan, t = data.radar, data.t_s
        v_radar_D = _finite_difference_velocity(sim, t, h)
        pts_W = scan.points_D @ data.T_world_radar[:3, :3].T + data.T_world_radar[:3, 3]
        # match each point to its scattering centre and difference the centre's world position
        pos_t = centres_world(sim.scene, actor_states(sim.scene, t))[0]
        dist, idx = cKDTree(pos_t).query(pts_W)
        assert dist.max() < 1e-6
        v_W = (centres_world(sim.scene, actor_states(sim.scene, t + h))[0][idx]
               - centres_world(sim.scene, actor_states(sim.scene, t - h))[0][idx]) / (2 * h)
        v_target_D = v_W @ data.T_world_radar[:3, :3]
        u = scan.points_D / np.linalg.norm(scan.points_D, axis=1, keepdims=True)
        expected = np.sum((v_target_D - v_radar_D) * u, axis=1)
        assert np.abs(scan.doppler_mps - expected).max() < 1e-3
        static = scan.is_static
        assert np.abs(scan.doppler_mps[static] + u[static] @ v_radar_D).max() < 1e-3
        n_static += static.sum()
        n_moving += (~static).sum()
    assert n_static > 20
    if scene_type != "highway":  # highways may have no moving object in the field of view
        assert n_moving > 0


def _surface_distance(p_W: np.ndarray, prims, idx: np.ndarray) -> np.ndarray:
    """Distance (N,) from points to the nearest surface of primitives ``idx`` (oracle, per primitive)."""
    best = np.full(len(p_W), np.inf)
    for i in idx:
        rel = p_W - prims.centre[i]
        c, s = np.cos(prims.yaw[i]), np.sin(prims.yaw[i])
        local = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], 1)
        if prims.kind[i] == PLANE:
            d = np.abs(p_W[:, 2])
        else:
            if prims.kind[i] == BOX:
                q = np.abs(local) - prims.half[i]
            else:
                q = np.stack([np.hypot(local[:, 0], local[:, 1]) - prims.half[i, 0],
                              np.abs(local[:, 2]) - prims.half[i, 2]], 1)
            outside = np.linalg.norm(np.maximum(q, 0), axis=1)
            d = np.where(q.max(axis=1) > 0, outside, -q.max(axis=1))
        best = np.minimum(best, d)
    return best


def test_radar_points_lie_on_their_object_or_are_ghosts() -> None:
    model = RadarModel()
    sim = make_sequence("urban", 10, make_rig((160, 96), 16), seed=4, seq_index=1, radar_model=model)
    k_sigma = model.noise_clip
    n_on = n_off = 0
    for k in (0, 5, 9):
        data = sim.frame(k, ("radar",))
        scan = data.radar
        pts_W = scan.points_D @ data.T_world_radar[:3, :3].T + data.T_world_radar[:3, 3]
        r = np.linalg.norm(scan.points_D, axis=1)
        ang = k_sigma * np.radians(model.az_sigma_deg + model.el_sigma_deg)
        bound = k_sigma * model.range_sigma_m + (r + k_sigma * model.range_sigma_m) * ang + 1e-3
        for oid in np.unique(scan.object_id[scan.object_id >= 0]):
            sel = scan.object_id == oid
            actor = int(np.flatnonzero(sim.scene.object_id == oid)[0])
            prims = data.prims
            d = _surface_distance(pts_W[sel], prims, np.flatnonzero(prims.actor == actor))
            assert (d <= bound[sel]).all(), (oid, d.max())
            n_on += sel.sum()
        n_off += (scan.object_id < 0).sum()
        assert ((scan.object_id < 0) == (scan.material < 0)).all()
    assert n_on > 5 * n_off > 0


def test_point_count_rises_with_ego_speed() -> None:
    rig = make_rig((160, 96), 16)
    for scene_type in ("residential", "urban", "highway"):
        counts = []
        for speed in (1.5, 12.0):
            sim = make_sequence(scene_type, 8, rig, seed=21, seq_index=0, ego_speed_mps=speed)
            counts.append(np.mean([len(sim.frame(k, ("radar",)).radar.points_D) for k in range(0, 8, 2)]))
        assert counts[1] > 1.15 * counts[0], (scene_type, counts)


def test_lidar_sees_through_glass() -> None:
    rig = make_rig((160, 96), 16)
    sim = make_sequence("urban", 4, rig, seed=8, seq_index=3, noise=False)
    data = sim.frame(1, ("lidar",))
    prims = data.prims
    glass = prims.material == MATERIAL_ID["glass"]
    assert not glass[data.lidar.prim].any()
    # oracle: every lidar ray against every primitive, glass included
    dirs_L = lidar_directions(rig).reshape(-1, 3)
    T = data.T_world_lidar
    dirs_W = dirs_L @ T[:3, :3].T
    t, p = first_hit_dense(T[:3, 3], dirs_W, prims, np.arange(len(prims.kind)))
    through = np.flatnonzero((p >= 0) & (t < 100) & glass[np.maximum(p, 0)])
    assert len(through) > 20
    glass_hits_L = t[through, None] * dirs_L[through]
    dist, _ = cKDTree(data.lidar.points_L.astype(np.float64)).query(glass_hits_L)
    assert dist.min() > 1e-3
    assert (data.lidar.material != MATERIAL_ID["glass"]).all()


def test_windowed_casting_matches_dense_oracle() -> None:
    rig = make_rig((160, 96), 16, lidar_cols=300)
    sim = make_sequence("residential", 4, rig, seed=2, seq_index=0)
    data = sim.frame(2, ("radar",))
    prims = data.prims
    T = data.T_world_lidar
    dirs_W = (lidar_directions(rig).reshape(-1, 3) @ T[:3, :3].T).reshape(16, 300, 3)
    az, el = rig.lidar_az_rad, rig.lidar_el_rad
    az_step, el_step = az[0] - az[1], el[0] - el[1]
    win = spherical_windows(prims, T, az[0] + az_step / 2, az_step, 300, el[0] + el_step / 2, el_step, 16, 1e9)
    t_grid, p_grid = cast_grid(T[:3, 3], dirs_W, prims, win)
    t_dense, p_dense = first_hit_dense(T[:3, 3], dirs_W.reshape(-1, 3), prims, np.arange(len(prims.kind)))
    finite = np.isfinite(t_dense)
    assert (np.isfinite(t_grid.reshape(-1)) == finite).all()
    assert np.allclose(t_grid.reshape(-1)[finite], t_dense[finite], atol=1e-6)
    assert (prims.kind[np.unique(p_dense[finite])] != CYLINDER).any()


def _hash_tree(root: Path) -> str:
    h = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def test_same_seed_same_bytes(tmp_path: Path) -> None:
    kw = dict(frames=4, resolution_wh=(96, 64), lidar_lines=16, sequence_len=2, scene_mix=("highway", "urban"))
    generate(tmp_path / "a", seed=9, **kw)
    generate(tmp_path / "b", seed=9, **kw)
    assert _hash_tree(tmp_path / "a") == _hash_tree(tmp_path / "b")
    assert len(list((tmp_path / "a").rglob("*.bin"))) == 4 * 3


def test_failed_generation_leaves_no_world_json(tmp_path: Path, monkeypatch) -> None:
    import pipeline.world.generator as gen

    generate(tmp_path, frames=1, seed=0, resolution_wh=(64, 32), lidar_lines=16)
    assert (tmp_path / "world.json").exists()

    def boom(*args, **kwargs):
        raise RuntimeError("simulated crash")

    monkeypatch.setattr(gen, "run_sequence", boom)
    with pytest.raises(RuntimeError):
        generate(tmp_path, frames=1, seed=0, resolution_wh=(64, 32), lidar_lines=16)
    assert not (tmp_path / "world.json").exists()


def test_an_interrupted_generation_resumes_its_finished_sequences(tmp_path: Path, monkeypatch) -> None:
    """A run that stops keeps the sequences it finished; the next run with the same arguments makes
    only the others, and the world is byte for byte the uninterrupted one's. Other arguments start
    afresh. Until 2026-12-04 every run started from frame 0 (minutes lost on `make demo-large`)."""
    import pipeline.world.generator as gen

    kw = dict(frames=6, seed=4, resolution_wh=(64, 32), lidar_lines=16, sequence_len=2, scene_mix=("highway", "urban"))
    generate(tmp_path / "whole", **kw)
    real, calls = gen.run_sequence, []

    def stop_at_third(*job):
        calls.append(job[1])
        if job[1] == 2 and len(calls) == 3:
            raise KeyboardInterrupt("killed")
        return real(*job)

    monkeypatch.setattr(gen, "MAX_WORKERS", 1)  # in-process, so that the stop can be injected
    monkeypatch.setattr(gen, "run_sequence", stop_at_third)
    with pytest.raises(KeyboardInterrupt):
        generate(tmp_path / "w", **kw)
    assert not (tmp_path / "w" / "world.json").exists()
    summary = generate(tmp_path / "w", **kw)
    assert calls == [0, 1, 2, 2] and summary["resumed_sequences"] == 2
    assert not (tmp_path / "w" / "partial").exists()
    assert _hash_tree(tmp_path / "w") == _hash_tree(tmp_path / "whole")
    # stopped again, then asked for another seed: nothing of the first is kept
    calls.clear()
    monkeypatch.setattr(gen, "run_sequence", lambda *job: (calls.append(job[1]), real(*job))[1])
    (tmp_path / "w" / "world.json").unlink()
    (tmp_path / "w" / "partial").mkdir()
    (tmp_path / "w" / "partial" / "arguments.json").write_text("{}")
    assert generate(tmp_path / "w", **{**kw, "seed": 5})["resumed_sequences"] == 0 and calls == [0, 1, 2]


@pytest.mark.parametrize("change", [dict(lidar_lines=64), dict(sequence_len=1)])
def test_an_interrupted_generation_is_not_resumed_with_another_lidar_or_sequence_length(tmp_path: Path, monkeypatch,
                                                                                       change: dict) -> None:
    """A sequence finished with 16 lidar lines is not kept by a run asked for 64 (the world would
    mix two lidars), nor one finished with 2-frame sequences by a run asked for 1-frame ones
    (sequence k would name other frames)."""
    import pipeline.world.generator as gen

    kw = dict(frames=4, seed=4, resolution_wh=(64, 32), lidar_lines=16, sequence_len=2, scene_mix=("highway",))
    real, calls = gen.run_sequence, []

    def stop_at_second(*job):
        calls.append(job[1])
        if job[1] == 1 and len(calls) == 2:
            raise KeyboardInterrupt("killed")
        return real(*job)

    monkeypatch.setattr(gen, "MAX_WORKERS", 1)
    monkeypatch.setattr(gen, "run_sequence", stop_at_second)
    with pytest.raises(KeyboardInterrupt):
        generate(tmp_path, **kw)
    assert (tmp_path / "partial" / "seq00000.json").exists()
    summary = generate(tmp_path, **{**kw, **change})
    assert summary["resumed_sequences"] == 0
    world = json.loads((tmp_path / "world.json").read_text())
    assert {k: world[k] for k in change} == change


def test_each_lidar_pattern_spans_its_sensor_and_fits_the_profile_budget() -> None:
    """VLP-16: +-15 deg, HDL-64: +2 .. -24.8 deg, OS1-128: +-22.5 deg, one elevation per line; every
    scan has at most the synthetic profile's lidar.store_max_points rays (no reader truncates it)."""
    from pipeline.config import load_config

    budget = load_config("synthetic", environ={}).lidar.store_max_points
    for lines, (top, bottom) in {16: (15.0, -15.0), 64: (2.0, -24.8), 128: (22.5, -22.5)}.items():
        rig = make_rig((64, 32), lines)
        el = np.degrees(rig.lidar_el_rad)
        assert el.size == lines and el[0] == pytest.approx(top) and el[-1] == pytest.approx(bottom)
        assert lines * rig.lidar_az_rad.size <= budget, lines
    with pytest.raises(ValueError, match="lidar_lines"):
        make_rig((64, 32), 32)


@pytest.mark.parametrize("kwargs", [dict(frames=0), dict(lidar_lines=32), dict(scene_mix=("moon",)),
                                    dict(sequence_len=0), dict(resolution_wh=(8, 8))])
def test_bad_arguments_raise_config_error(tmp_path: Path, kwargs: dict) -> None:
    args = dict(frames=2, seed=0, resolution_wh=(64, 32), lidar_lines=16)
    args.update(kwargs)
    with pytest.raises(ConfigError):
        generate(tmp_path, **args)


@pytest.mark.parametrize("frames, sequence_len", [(FRAMES, SEQ_LEN), (5, 2)])
def test_frame_ids_are_those_the_reader_lists(world, tmp_path, frames, sequence_len):
    """frame_ids (what --dry-run checks --frames against before the world is generated) gives the
    frames the reader lists from the generated files, a last sequence shorter than the others too."""
    from pipeline.config import load_config
    from pipeline.readers import get_reader
    from pipeline.world.generator import frame_ids

    root = world
    if frames != FRAMES:
        root = tmp_path / "world"
        generate(root, frames=frames, seed=1, resolution_wh=(64, 48), lidar_lines=16, sequence_len=sequence_len)
    assert get_reader(load_config("synthetic", environ={}), root).frame_ids() == frame_ids(frames)


def test_world_in_the_cache_follows_the_profile(tmp_path: Path) -> None:
    """The world generated into the cache is made once, and again when its profile settings
    change; a world the user points at with --data-root is never regenerated."""
    from pipeline.cli import _ensure_world
    from pipeline.config import load_config
    from pipeline.executor import RunEnv

    def env(frames: int, root: Path | None = None) -> RunEnv:
        cfg = load_config("synthetic", {"dataset.world_frames": str(frames), "dataset.world_resolution": "64,48",
                                        "dataset.world_sequence_len": "2"}, environ={})
        cache = tmp_path / "cache"
        return RunEnv(cfg, str(cache), "synthetic", str(root or cache / "synthetic" / "world"))

    first = env(3)
    _ensure_world(first, progress=False)
    world_json = Path(first.data_root) / "world.json"
    made = world_json.stat().st_mtime_ns
    _ensure_world(first, progress=False)
    assert world_json.stat().st_mtime_ns == made  # same settings: kept
    _ensure_world(env(4), progress=False)
    world = json.loads(world_json.read_text())
    assert world["frames"] == 4 and world["sequence_len"] == 2  # changed settings: regenerated
    own = tmp_path / "own"
    generate(own, frames=2, seed=5, resolution_wh=(64, 48))
    _ensure_world(env(4, own), progress=False)
    assert json.loads((own / "world.json").read_text())["frames"] == 2  # the user's world is left alone


def _is_spawned_worker(pid: int) -> bool:
    """Whether process ``pid`` is a multiprocessing 'spawn' worker (not its resource tracker)."""
    try:
        return b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False


def _children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` (from /proc)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
def test_generating_workers_exit_when_the_run_is_killed(tmp_path: Path) -> None:
    """Until 2026-12-04 a run killed while generating the world left its two worker processes
    generating on as orphans, holding the run's output open (a wrapper reading it hung)."""
    import signal
    import subprocess
    import sys
    import time

    code = (f"from pipeline.world import generate; generate({str(tmp_path / 'w')!r}, frames=400, seed=0, "
            f"resolution_wh=(64, 32), sequence_len=20, progress=False)")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not [c for c in _children(proc.pid) if _is_spawned_worker(c)]:
            time.sleep(0.2)
        workers = [c for c in _children(proc.pid) if _is_spawned_worker(c)]
        assert workers, "no generating worker started"
        time.sleep(1.0)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and any(Path(f"/proc/{w}").exists() for w in workers):
            time.sleep(0.2)
        alive = [w for w in workers if Path(f"/proc/{w}").exists()
                 and Path(f"/proc/{w}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"]
        for w in alive:
            os.kill(w, signal.SIGKILL)
        assert not alive, f"workers {alive} outlived the killed run"
    finally:
        if proc.poll() is None:
            proc.kill()


@pytest.mark.skipif(not Path("/proc/self/stat").exists() or (os.cpu_count() or 1) < 2,
                    reason="reads /proc; generates in two processes only with two cores")
def test_a_killed_two_process_generation_resumes_to_the_same_bytes(tmp_path: Path) -> None:
    """The resume of the two-process path (the one `make demo` takes): a run SIGKILLed once its
    first sequence is recorded keeps what it finished, and the next run makes only the rest, to the
    bytes of an uninterrupted run."""
    import signal
    import subprocess
    import sys
    import time

    kw = dict(frames=40, seed=3, resolution_wh=(64, 32), lidar_lines=16, sequence_len=2,
              scene_mix=("highway", "urban"))
    code = f"from pipeline.world import generate; generate({str(tmp_path / 'w')!r}, **{kw!r})"
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    partial, workers = tmp_path / "w" / "partial", []
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and proc.poll() is None and not list(partial.glob("seq*.json")):
            workers = [c for c in _children(proc.pid) if _is_spawned_worker(c)] or workers
            time.sleep(0.01)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert len(workers) == 2, "the run did not generate in two processes"
    deadline = time.monotonic() + 10          # the workers notice within PARENT_POLL_S
    while time.monotonic() < deadline and any(Path(f"/proc/{w}").exists() for w in workers):
        time.sleep(0.1)
    assert not (tmp_path / "w" / "world.json").exists(), "the run finished before it was killed"
    summary = generate(tmp_path / "w", **kw)
    assert 1 <= summary["resumed_sequences"] < 20
    generate(tmp_path / "whole", **kw)
    assert _hash_tree(tmp_path / "w") == _hash_tree(tmp_path / "whole")
