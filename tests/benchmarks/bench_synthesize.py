"""Synthesize speed at the synthetic profile's working resolution on 2 CPU threads, split into
network time (Dis-Net + RSS-Net + PlaceNet) and the rest (candidates and their features, sampling,
placement, Doppler, RSS-Net inputs).
Goal: at least 5 frames/s with the non-network part under 20%. Frames come from a small generated
world; weights are random (the network's speed does not depend on them). The rest does depend on
where the samples fall (samples without lidar support widen their window up to 4 times), so it is
measured on the random network's map, on the frame's real-radar heatmap, and, after `make demo`,
with the demo's trained networks (the stage's case); the last line is the last case with the
paper's camera-ray placement (synth.placement = ray), which needs no lidar candidates or PlaceNet.
Arguments KEY=VALUE override the synthetic profile's settings, e.g. placement.map_weight=1; the nets
run on synth.device (synth.device=cuda for a GPU)."""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from pipeline.config import load_config, parse_set_options  # noqa: E402
from pipeline.errors import CacheError, ConfigError  # noqa: E402
from pipeline.executor import Executor, FrameInputs, RunEnv, tune_heap  # noqa: E402
from pipeline.models.disnet import build_disnet  # noqa: E402
from pipeline.models.placenet import build_placenet  # noqa: E402
from pipeline.models.rssnet import build_rssnet  # noqa: E402
from pipeline.runner import Pipeline  # noqa: E402
from pipeline.inference import (disnet_predict, load_disnet, load_placenet, load_rssnet,  # noqa: E402
                                rssnet_predict, select_device)
from pipeline.world import generate as generate_world  # noqa: E402
from stages import all_stages  # noqa: E402
from stages.patches import point_inputs  # noqa: E402
from stages.synthesize import (Nets, frame_count, generate, lidar_candidates, lidar_tree,  # noqa: E402
                               uses_placenet_count)


TRAINED_CACHE = "cache"
"""The demo's cache: its trained networks, when present, are timed too."""


class Timed(torch.nn.Module):
    """A network whose forward calls add their wall time to ``seconds`` (PlaceNet runs inside
    ``generate``; its time is network time)."""

    def __init__(self, net: torch.nn.Module) -> None:
        super().__init__()
        self.net, self.seconds = net, 0.0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        t0 = time.perf_counter()
        out = self.net(x)
        if out.is_cuda:
            torch.cuda.synchronize()  # the GPU's work is network time, not the caller's
        self.seconds += time.perf_counter() - t0
        return out

    def __getattr__(self, name: str):
        """Everything else is the net's (e.g. PlaceNet's training-range check, counted as the rest,
        as synthesize does it outside the net)."""
        try:
            return super().__getattr__(name)
        except AttributeError:
            return getattr(super().__getattr__("net"), name)


def measure(frames, cfg, disnet, rssnet, placenet, source: str) -> tuple[float, float, int, int]:
    """(network s, rest s, frames, points) over 2 timed passes after a warm-up pass. ``source``:
    'network' samples the random network's own map (n = 300), 'radar' the frame's real-radar
    heatmap with the real count: the distribution a trained Dis-Net approximates, so samples fall
    where the lidar has support as they do in use; 'trained network' the map and count of the
    demo's trained Dis-Net, as the stage does (blended with PlaceNet's count where the stage blends
    it: stages.synthesize.uses_placenet_count)."""
    t_net = t_rest = 0.0
    n_frames = n_points = 0
    placenet = Timed(placenet)
    nets = Nets(disnet, rssnet, placenet)
    for rep in range(3):
        for f in frames:
            image, ego = f.get("calibrate", "image"), f.get("calibrate", "ego_velocity")
            t0 = time.perf_counter()
            maps, n_hat = disnet_predict(disnet, image[None], np.array([np.linalg.norm(ego)], np.float32))
            t1 = time.perf_counter()
            if source == "network":
                prob, n = maps[0], 300  # random weights would give an arbitrary n_hat
            elif source == "trained network":
                prob, n = maps[0], float(n_hat[0])
            else:
                prob, n = f.get("heatmaps", "heatmap"), float(f.get("heatmaps", "count"))
            placenet.seconds = 0.0
            f.clear_memo()  # each pass computes the candidates and PlaceNet's intensities again
            if source == "trained network" and uses_placenet_count(cfg) and placenet.count_scale is not None:
                n = frame_count(n, lidar_candidates(f, cfg, placenet)[2], placenet.count_scale)[0]  # as the stage
            out = generate(f, cfg, prob, n, nets, f.rng(rep, 1), rss=False)
            pts = out["points"][:, :3].astype(np.float64)
            patches, ranges = point_inputs(image, f.get("calibrate", "K"), f.get("calibrate", "T_radar_cam"),
                                           f.get("calibrate", "lidar"), pts, cfg, lidar_tree(f, cfg))  # as generate
            t2 = time.perf_counter()
            rssnet_predict(rssnet, patches, ranges, out["points"][:, [0, 1, 2, 8]])
            t3 = time.perf_counter()
            if rep:  # the first pass warms up
                t_net += (t1 - t0) + (t3 - t2) + placenet.seconds
                t_rest += t2 - t1 - placenet.seconds
                n_frames += 1
                n_points += len(pts)
    return t_net, t_rest, n_frames, n_points


def main() -> None:
    torch.set_num_threads(2)
    tune_heap()  # the heap settings the stage runs with (serial executor and dask workers)
    try:
        overrides = parse_set_options(sys.argv[1:])
        cfg = load_config("synthetic", overrides, environ={})
        device = str(select_device(cfg.synth.device, "synth.device"))
    except ConfigError as exc:
        sys.exit(f"bench_synthesize.py: {exc}")
    with tempfile.TemporaryDirectory() as tmp:
        generate_world(f"{tmp}/world", frames=8, seed=3, resolution_wh=tuple(cfg.dataset.world_resolution))
        env = RunEnv(cfg, f"{tmp}/cache", "synthetic", f"{tmp}/world")
        pipe = Pipeline(all_stages(), env, Executor(1, progress=False), progress=False, log=lambda m: None)
        pipe.run("heatmaps")
        random = tuple(net.eval().to(device) for net in (build_disnet(cfg, load_backbone=False), build_rssnet(cfg),
                                                         build_placenet(cfg)))
        frames = [FrameInputs(env, i, f) for i, f in enumerate(pipe.frame_ids())]
        runs = [("network", *random), ("radar", *random)]
        trained = Path(TRAINED_CACHE) / "synthetic" / "train"
        try:  # after `make demo`: the real case
            runs.append(("trained network", *(load(cfg, str(trained / name / "best.safetensors"), device=device)
                                              for name, load in (("disnet", load_disnet), ("rssnet", load_rssnet),
                                                                 ("placenet", load_placenet)))))
        except (CacheError, ConfigError) as exc:
            print(f"(no usable trained models under {trained}: run `make demo` to also time the trained "
                  f"networks; {str(exc).splitlines()[0]})")
        ray = load_config("synthetic", {**overrides, "synth.placement": "ray"}, environ={})
        size = f"{cfg.camera.working_size[0]}x{cfg.camera.working_size[1]}"
        for (source, disnet, rssnet, placenet), c in [(run, cfg) for run in runs] + [(runs[-1], ray)]:
            t_net, t_rest, n_frames, n_points = measure(frames, c, disnet, rssnet, placenet, source)
            total = t_net + t_rest
            print(f"synthesize {size}, {c.synth.placement} placement, samples from the {source} map, "
                  f"{n_points / n_frames:.0f} points/frame, nets on {device}, 2 threads: {n_frames / total:.1f} "
                  f"frames/s (network {1e3 * t_net / n_frames:.1f} ms, rest {1e3 * t_rest / n_frames:.1f} ms per "
                  f"frame), non-network share {t_rest / total:.2f} (goal < 0.20)")


if __name__ == "__main__":
    main()
