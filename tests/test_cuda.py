"""Training and inference on a CUDA GPU (skipped without one; CI has none, so these run on a GPU
machine by hand: README, "On a GPU").

Each net learns there, its checkpoints (written from GPU tensors) load on a CPU-only machine with
the same weights, and killed runs resume. PlaceNet's resumed weights are the uninterrupted run's to
the bit. Dis-Net's cannot be: on the GPU two uninterrupted runs already differ, even with
cudnn.deterministic (measured 2026-12-04 on an H200), because the backward passes of adaptive
average pooling and bilinear upsampling add with atomics in no fixed order, and these tiny problems
amplify the difference. On the CPU every resume is exact (tests/test_training.py).
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np
import pytest
import torch

from pipeline import checkpoint as ckpt
from pipeline import inference as Inf
from pipeline import net_baselines as B
from pipeline import training as T
from tests.test_placement import make_place_data
from tests.test_placement import tiny_cfg as place_cfg
from tests.test_training import KilledAfter, _all_tensors, make_disnet_data, make_rss_data, tiny_cfg

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")

CUDA = {"train.device": "cuda"}


def _relative_l2(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> float:
    """|a - b| / |a| over all trained parameters (``model.`` tensors but the BN running statistics)."""
    keys = [k for k in a if k.startswith("model.") and a[k].is_floating_point() and "running_" not in k]
    diff = sum(float(((a[k].double() - b[k].double()) ** 2).sum()) for k in keys)
    return (diff / sum(float((a[k].double() ** 2).sum()) for k in keys)) ** 0.5


@contextmanager
def _full_float32():
    """Full float32 on the GPU (PyTorch's default convolutions there use TF32's 10-bit mantissa),
    so that GPU and CPU predictions can be compared closely."""
    saved = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


def _assert_loads_on_cpu_alike(load, cfg, path, predict) -> None:
    """The checkpoint loads on the CPU with the GPU model's exact weights, and predicts alike."""
    on_gpu, on_cpu = load(cfg, path, device="cuda"), load(cfg, path, device="cpu")
    assert next(on_gpu.parameters()).is_cuda and not next(on_cpu.parameters()).is_cuda
    gpu_state, cpu_state = on_gpu.state_dict(), on_cpu.state_dict()
    assert all(torch.equal(gpu_state[k].cpu(), cpu_state[k]) for k in cpu_state)
    with _full_float32():
        pairs = list(zip(predict(on_gpu), predict(on_cpu), strict=True))
    for got, want in pairs:
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5 * np.abs(want).max())


def test_disnet_learns_on_the_gpu_and_its_checkpoint_loads_on_the_cpu(tmp_path):
    data = make_disnet_data()
    cfg = tiny_cfg(**{"train.epochs": "8", **CUDA})
    res = T.train_disnet(cfg, data, tmp_path, progress=False)
    base = B.disnet_baseline(data.heatmaps, data.counts, data.train_idx, data.val_idx)
    assert res.curves[res.best_epoch - 1]["val_kl"] < 0.6 * base["kl"]
    assert res.curves[-1]["train_loss"] < 0.5 * res.curves[0]["train_loss"]
    assert "rng.cuda.0" in _all_tensors(res.last_path)
    _assert_loads_on_cpu_alike(Inf.load_disnet, cfg, res.best_path,
                               lambda m: Inf.disnet_predict(m, data.images, data.speeds))


def test_rssnet_and_placenet_learn_on_the_gpu_and_load_on_the_cpu(tmp_path):
    rss = make_rss_data(p=400, as_zarr=True)
    cfg = tiny_cfg(**{"train.epochs": "3", **CUDA})
    res = T.train_rssnet(cfg, rss, tmp_path / "rss", progress=False)
    base = B.rssnet_baseline(rss.rss, rss.train_idx, rss.val_idx, cfg.radar.rss_min, cfg.radar.rss_max)
    assert min(c["val_a"] for c in res.curves) < 0.5 * base["a"]
    _assert_loads_on_cpu_alike(Inf.load_rssnet, cfg, res.best_path,
                               lambda m: [Inf.rssnet_predict(m, rss.patches, rss.range_images, rss.point_vectors)])

    place = make_place_data()
    pcfg = place_cfg(**CUDA)
    res = T.train_placenet(pcfg, place, tmp_path / "place", progress=False)
    const = B.placenet_baseline(place.counts, place.train_idx, place.val_idx)
    assert T.placenet_metrics(Inf.load_placenet(pcfg, res.best_path), place, place.val_idx)["nll"] < const["nll"]
    _assert_loads_on_cpu_alike(Inf.load_placenet, pcfg, res.best_path,
                               lambda m: [Inf.placenet_predict(m, place.features)])


def test_placenet_killed_on_the_gpu_resumes_to_the_uninterrupted_weights(tmp_path):
    """PlaceNet (linear layers only) trains reproducibly on the GPU, so its resume is checked exactly."""
    data = make_place_data()
    cfg = place_cfg(**CUDA)
    ref = T.train_placenet(cfg, data, tmp_path / "a", progress=False)
    T.train_placenet(place_cfg(**{**CUDA, "placement.epochs": "2"}), data, tmp_path / "b", progress=False)
    res = T.train_placenet(cfg, data, tmp_path / "b", progress=False)
    assert res.resumed_from == 2 and res.epoch == 4
    a, b = _all_tensors(ref.last_path), _all_tensors(res.last_path)
    assert all(torch.equal(a[k], b[k]) for k in a if k.startswith(("model.", "optim.")))


def test_gpu_random_state_round_trips_through_a_checkpoint():
    """The CUDA generator (dropout on the GPU) is saved and restored with the CPU one."""
    torch.manual_seed(0)
    saved = ckpt.rng_tensors()
    assert "rng.cuda.0" in saved
    want = torch.rand(5, device="cuda").cpu(), torch.rand(5)
    torch.rand(7, device="cuda"), torch.rand(3)
    ckpt.restore_rng(saved)
    got = torch.rand(5, device="cuda").cpu(), torch.rand(5)
    assert torch.equal(want[0], got[0]) and torch.equal(want[1], got[1])


@pytest.mark.parametrize("extra", [{}, {"train.flip": "true", "train.cutmix": "0.5", "train.ema_decay": "0.8",
                                         "train.jitter": "0.3", "train.map_dropout": "0.2",
                                         "train.lr_schedule": "cosine"}])
def test_disnet_killed_on_the_gpu_resumes_and_finishes(tmp_path, monkeypatch, capsys, extra):
    """Dis-Net on the GPU is not reproducible to the bit (see the module docstring), so a resumed run
    is checked for what it keeps (the finished epochs' records) and that it finishes; the weight
    differences are printed beside two uninterrupted runs' for the record."""
    monkeypatch.setattr(T, "WINDOW_BATCHES", 1)          # one read per batch: kill mid-epoch
    data = make_disnet_data(n=20)                        # 4 train batches + 2 val batches per epoch
    cfg = tiny_cfg(**{"train.batch_size": "4", **CUDA, **extra})
    ref = T.train_disnet(cfg, data, tmp_path / "a", progress=False, fingerprint="fp")
    again = T.train_disnet(cfg, data, tmp_path / "a2", progress=False, fingerprint="fp")
    killed = T.DisNetData(**{**data.__dict__, "images": KilledAfter(data.images, 2 * 6 + 2)})
    with pytest.raises(KeyboardInterrupt):               # dies after 2 optimizer steps of epoch 3
        T.train_disnet(cfg, killed, tmp_path / "b", progress=False, fingerprint="fp")
    kept = ckpt.read_meta(tmp_path / "b" / "last.safetensors")
    assert kept["epoch"] == 2
    res = T.train_disnet(cfg, data, tmp_path / "b", progress=False, fingerprint="fp")
    assert res.resumed_from == 2 and res.epoch == 3 and len(res.curves) == 3
    assert res.curves[:2] == kept["curves"]
    assert all(np.isfinite(v) for c in res.curves for v in c.values())
    a = _all_tensors(ref.last_path)
    with capsys.disabled():
        print(f"\n[Dis-Net on the GPU, {sorted(extra) or 'plain'}] relative L2 weight difference: two "
              f"uninterrupted runs {_relative_l2(a, _all_tensors(again.last_path)):.3g}, uninterrupted "
              f"against resumed {_relative_l2(a, _all_tensors(res.last_path)):.3g}")


def test_synthesize_runs_the_nets_on_the_gpu_and_agrees_with_the_cpu(tmp_path):
    """synth.device = cuda: the stage's nets are on the GPU, every frame is done, and the maps and
    counts agree with a CPU run of the same nets (TF32 convolutions round differently, so the
    sampled points may differ in detail); the same GPU run twice gives the same bytes."""
    from pipeline.cache import DONE
    from pipeline.config import load_config
    from pipeline.executor import Executor, FrameInputs, RunEnv
    from pipeline.runner import Pipeline
    from pipeline.world import generate
    from stages import all_stages
    from stages.synthesize import models
    from tests.test_pipeline_e2e import TINY, arrays

    generate(tmp_path / "world", frames=10, seed=5, resolution_wh=(640, 384), sequence_len=10)

    def synthesize(device: str) -> tuple[dict[str, np.ndarray], Pipeline]:
        cfg = load_config("synthetic", {**TINY, "synth.device": device}, environ={})
        env = RunEnv(cfg, str(tmp_path / "cache"), "synthetic", str(tmp_path / "world"))
        pipe = Pipeline(all_stages(), env, Executor(1, progress=False), progress=False, log=lambda m: None)
        pipe.run("synthesize", force=(tmp_path / "cache" / "synthetic" / "synthesize.zarr").exists())
        assert np.all(pipe.env.store("synthesize").status() == DONE)
        return arrays(tmp_path / "cache", "synthesize"), pipe

    on_cpu, _ = synthesize("cpu")
    on_gpu, pipe = synthesize("cuda")
    nets = models(FrameInputs(pipe.env, 0, pipe.frame_ids()[0]), pipe.env.cfg)
    assert all(next(net.parameters()).is_cuda for net in (nets.disnet, nets.rssnet, nets.placenet))
    np.testing.assert_allclose(on_gpu["n_hat"], on_cpu["n_hat"], rtol=1e-2)
    np.testing.assert_allclose(on_gpu["pred_map"], on_cpu["pred_map"], rtol=2e-2, atol=1e-3 * on_cpu["pred_map"].max())
    assert np.array_equal(on_gpu["candidates"], on_cpu["candidates"])
    n_cpu, n_gpu = int(on_cpu["points_count"].sum()), int(on_gpu["points_count"].sum())
    assert abs(n_gpu - n_cpu) <= 0.05 * n_cpu
    again, _ = synthesize("cuda")
    for name, values in on_gpu.items():
        np.testing.assert_array_equal(again[name], values, err_msg=name)
