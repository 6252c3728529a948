"""Networks and losses: shapes, switches, torchvision key compatibility, losses against numpy."""

from __future__ import annotations

import itertools
import os

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from pipeline.config import load_config
from pipeline.errors import ConfigError
from pipeline.models.disnet import DisNet, build_disnet
from pipeline.models.losses import count_loss, kl_loss, rss_loss
from pipeline.models.resnet import ResNet18Backbone, load_state_dict_file, resnet18_backbone
from pipeline.models.rssnet import RSSNet, normalise_range_image
from pipeline.rangeimage import EMPTY

torch.set_num_threads(1)


def torchvision_resnet18_keys() -> list[str]:
    """The state-dict keys of torchvision.models.resnet18(), written out from its architecture:
    stem conv1/bn1, four layers of two BasicBlocks (conv1, bn1, conv2, bn2; the first block of
    layers 2-4 has downsample.0 conv + downsample.1 BN), classifier fc."""
    def bn(prefix: str) -> list[str]:
        return [f"{prefix}.{k}" for k in ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")]

    keys = ["conv1.weight", *bn("bn1")]
    for layer, block in itertools.product(range(1, 5), range(2)):
        p = f"layer{layer}.{block}"
        keys += [f"{p}.conv1.weight", *bn(f"{p}.bn1"), f"{p}.conv2.weight", *bn(f"{p}.bn2")]
        if layer > 1 and block == 0:
            keys += [f"{p}.downsample.0.weight", *bn(f"{p}.downsample.1")]
    return keys + ["fc.weight", "fc.bias"]


def test_resnet_state_dict_has_torchvision_keys_and_shapes():
    keys = torchvision_resnet18_keys()
    assert len(keys) == 122
    sd = ResNet18Backbone(64).state_dict()
    assert set(sd) == set(keys) - {"fc.weight", "fc.bias"}
    assert sd["conv1.weight"].shape == (64, 3, 7, 7)
    assert sd["layer2.0.downsample.0.weight"].shape == (128, 64, 1, 1)
    assert sd["layer4.1.conv2.weight"].shape == (512, 512, 3, 3)
    assert sd["layer3.0.bn1.running_var"].shape == (256,)


@pytest.mark.parametrize("suffix", [".safetensors", ".pth"])
def test_resnet_weights_round_trip_with_fc(tmp_path, suffix):
    torch.manual_seed(1)
    state = {k: v.clone() for k, v in ResNet18Backbone(64).state_dict().items()}
    state = {k: (torch.randn_like(v) if v.is_floating_point() else v + 7) for k, v in state.items()}
    state["fc.weight"], state["fc.bias"] = torch.randn(1000, 512), torch.randn(1000)
    path = tmp_path / f"resnet18{suffix}"
    save_file(state, str(path)) if suffix == ".safetensors" else torch.save(state, path)
    loaded = resnet18_backbone(path).state_dict()
    assert set(loaded) == set(state) - {"fc.weight", "fc.bias"}
    assert all(torch.equal(loaded[k], state[k]) for k in loaded)


class _NotATensor:
    """An arbitrary pickled object: torch.load(weights_only=True) must refuse it."""


def test_resnet_weights_errors(tmp_path):
    good = ResNet18Backbone(8).state_dict()
    bad = dict(good)
    del bad["layer1.0.conv1.weight"]
    save_file(bad, str(tmp_path / "missing.safetensors"))
    with pytest.raises(ConfigError, match="missing"):
        resnet18_backbone(tmp_path / "missing.safetensors", width=8)
    save_file(good, str(tmp_path / "narrow.safetensors"))
    with pytest.raises(ConfigError, match="shape mismatch"):
        resnet18_backbone(tmp_path / "narrow.safetensors", width=16)
    (tmp_path / "w.bin").write_bytes(b"x")
    with pytest.raises(ConfigError, match="unsupported"):
        load_state_dict_file(tmp_path / "w.bin")
    with pytest.raises(ConfigError, match="not found"):
        load_state_dict_file(tmp_path / "absent.pth")
    torch.save({"conv1.weight": torch.zeros(1), "obj": _NotATensor()}, tmp_path / "evil.pth")
    with pytest.raises(ConfigError, match="refused"):
        load_state_dict_file(tmp_path / "evil.pth")


def test_resnet_weights_damaged_files_are_one_line_errors_naming_the_file(tmp_path):
    """A damaged weights file (overwritten, truncated, text under a weights name) is a ConfigError
    naming the file, saying it is damaged and which formats are read; before, safetensors' own
    error and torch's zip error came as tracebacks, and a text .pth got torch's advice to load it
    with weights_only=False."""
    good = tmp_path / "good.pth"
    torch.save(ResNet18Backbone(8).state_dict(), good)
    (tmp_path / "garbage.safetensors").write_text("garbage\n")
    save_file(ResNet18Backbone(8).state_dict(), str(tmp_path / "cut.safetensors"))
    cut = (tmp_path / "cut.safetensors").read_bytes()
    (tmp_path / "cut.safetensors").write_bytes(cut[: len(cut) // 2])
    (tmp_path / "head.pth").write_bytes(good.read_bytes()[:600])
    (tmp_path / "text.pth").write_text("garbage\n")
    (tmp_path / "empty.pt").write_bytes(b"")
    for name in ("garbage.safetensors", "cut.safetensors", "head.pth", "text.pth", "empty.pt"):
        with pytest.raises(ConfigError) as info:
            load_state_dict_file(tmp_path / name)
        text = str(info.value)
        assert text.startswith(f"{tmp_path / name}: cannot be read as"), text
        assert "damaged" in text and ".safetensors" in text and ".pth" in text, text
        assert "\n" not in text and "weights_only" not in text, text
    torch.save({"conv1.weight": torch.zeros(1), "obj": _NotATensor()}, tmp_path / "evil.pth")
    with pytest.raises(ConfigError, match="refused") as info:
        load_state_dict_file(tmp_path / "evil.pth")
    assert "_NotATensor" in str(info.value) and "weights_only" not in str(info.value)
    assert "\n" not in str(info.value)


def test_resnet_feature_map_stride_32():
    out = ResNet18Backbone(8)(torch.rand(2, 3, 64, 96))
    assert out.shape == (2, 64, 2, 3)


@pytest.mark.parametrize("in_hw,out_hw", [((32, 64), (32, 64)), ((40, 72), (37, 70))])
def test_disnet_shapes_and_distribution(in_hw, out_hw):
    torch.manual_seed(0)
    model = DisNet(width=8, use_speed=True, max_points=50, out_hw=out_hw).eval()
    log_map, n_hat = model(torch.rand(3, 3, *in_hw), torch.tensor([0.0, 5.0, 20.0]))
    assert log_map.shape == (3, *out_hw) and n_hat.shape == (3,)
    assert torch.allclose(log_map.exp().sum(dim=(1, 2)), torch.ones(3), atol=1e-5)
    assert bool(((n_hat > 0) & (n_hat < 50)).all())


def test_disnet_speed_switch():
    torch.manual_seed(0)
    img = torch.rand(2, 3, 32, 64)
    with_speed = DisNet(width=8, use_speed=True, out_hw=(32, 64)).eval()
    with pytest.raises(ValueError, match="speed"):
        with_speed(img, None)
    torch.nn.init.normal_(with_speed.speed_fc.weight)
    _, n1 = with_speed(img, torch.tensor([0.0, 0.0]))
    _, n2 = with_speed(img, torch.tensor([30.0, 30.0]))
    assert not torch.equal(n1, n2)
    no_speed = DisNet(width=8, use_speed=False, out_hw=(32, 64)).eval()
    assert no_speed.speed_fc is None and no_speed.count_head.in_features == 12
    assert torch.equal(no_speed(img, torch.tensor([0.0, 1.0]))[1], no_speed(img, None)[1])


def test_disnet_speed_map_modulates_the_map_only():
    """disnet.speed_map: starts as the speed-free network, then the speed moves the map, not the count."""
    torch.manual_seed(0)
    img = torch.rand(2, 3, 32, 64)
    plain = DisNet(width=8, use_speed=True, out_hw=(32, 64)).eval()
    film = DisNet(width=8, use_speed=True, out_hw=(32, 64), speed_map=True).eval()
    missing, unexpected = film.load_state_dict(plain.state_dict(), strict=False)
    assert not unexpected and missing and all(k.startswith("speed_film.") for k in missing)
    stopped, moving = torch.tensor([0.0, 0.0]), torch.tensor([12.0, 12.0])
    for a, b in zip(film(img, moving), plain(img, moving)):  # zero-initialised last layer: identity
        assert torch.equal(a, b)
    torch.nn.init.normal_(film.speed_film[-1].weight, std=0.5)
    (map_0, n_0), (map_12, n_12) = film(img, stopped), film(img, moving)
    assert not torch.allclose(map_0, map_12)
    # the number branch reads the unmodulated features
    assert torch.equal(n_0, plain(img, stopped)[1]) and torch.equal(n_12, plain(img, moving)[1])
    blind = DisNet(width=8, use_speed=False, out_hw=(32, 64), speed_map=True).eval()
    with pytest.raises(ValueError, match="speed_map"):
        blind(img, None)


@pytest.mark.parametrize("in_hw", [(32, 64), (40, 72)])
def test_disnet_skips_start_as_the_paper_decoder_then_see_local_features(in_hw):
    """disnet.skips: zero-initialised laterals give the paper's decoder (at sizes divisible by 32;
    otherwise the decoder's stages are resized to the backbone's); a non-zero lateral changes the
    map, which stays a distribution of the right size."""
    torch.manual_seed(0)
    img = torch.rand(1, 3, *in_hw)
    plain = DisNet(width=8, out_hw=in_hw).eval()
    skip = DisNet(width=8, out_hw=in_hw, skips=True).eval()
    missing, unexpected = skip.load_state_dict(plain.state_dict(), strict=False)
    assert not unexpected and missing and all(k.startswith("laterals.") for k in missing)
    assert [tuple(c.weight.shape[:2]) for c in skip.laterals] == [(32, 32), (16, 16), (8, 8)]
    speed = torch.tensor([5.0])
    if in_hw[0] % 32 == 0 and in_hw[1] % 32 == 0:
        for a, b in zip(skip(img, speed), plain(img, speed)):
            assert torch.equal(a, b)
    # only the finest lateral (layer1, 1/4 resolution) is switched on
    torch.nn.init.normal_(skip.laterals[2].weight, std=1.0)
    log_map, _ = skip(img, speed)
    assert log_map.shape == (1, *in_hw) and not torch.allclose(log_map, plain(img, speed)[0])
    assert torch.allclose(log_map.exp().sum(), torch.tensor(1.0), atol=1e-5)


def _count_grads(model: DisNet, img: torch.Tensor, speed: torch.Tensor) -> tuple[torch.Tensor, dict]:
    model.zero_grad()
    log_map, n_hat = model(img, speed)
    count_loss(n_hat, torch.tensor([40.0, 7.0])).sum().backward()
    return n_hat.detach(), {k: p.grad.clone() for k, p in model.named_parameters() if p.grad is not None}


@pytest.mark.parametrize("scale", [0.0, 0.25])
def test_disnet_count_grad_scale_scales_only_the_backbone_gradient(scale):
    torch.manual_seed(0)
    model = DisNet(width=8, use_speed=True, max_points=50, out_hw=(32, 64)).train()
    img, speed = torch.rand(2, 3, 32, 64), torch.tensor([3.0, 12.0])
    torch.manual_seed(1)
    n_full, full = _count_grads(model, img, speed)
    model.count_grad_scale = scale
    torch.manual_seed(1)
    n_scaled, scaled = _count_grads(model, img, speed)
    assert torch.equal(n_full, n_scaled)  # forward values unchanged
    backbone = [k for k in full if k.startswith("backbone.")]
    head = [k for k in full if k.startswith(("count_", "speed_fc"))]
    assert backbone and head
    for k in head:  # the number branch itself still learns from L_n at full strength
        torch.testing.assert_close(scaled[k], full[k])
    for k in backbone:
        if scale == 0.0:
            assert k not in scaled or not scaled[k].any()
        else:
            torch.testing.assert_close(scaled[k], full[k] * scale, rtol=1e-4, atol=1e-8)


@pytest.mark.parametrize("use_speed", [True, False])
def test_disnet_number_branch_from_pooled_features(use_speed):
    """count_from_grid(count_grid_features(x)) is forward's n_hat; pooling before the 1x1
    convolution equals the authors' convolution before pooling (12 x 20 cells onto 5 x 18)."""
    torch.manual_seed(0)
    model = DisNet(width=8, use_speed=use_speed, max_points=50, out_hw=(48, 80)).eval()
    torch.nn.init.normal_(model.count_head.weight)
    img, speed = torch.rand(2, 3, 384, 640), torch.tensor([3.0, 12.0])
    _, n_hat = model(img, speed)
    grid = model.count_grid_features(img)
    assert grid.shape == (2, 64, 5, 18)
    torch.testing.assert_close(model.count_from_grid(grid, speed), n_hat)
    feat = model.backbone((img - model.mean) / model.std)
    assert feat.shape[-2:] == (12, 20)
    conv_first = torch.nn.functional.adaptive_avg_pool2d(model.count_conv(feat), (5, 18))
    torch.testing.assert_close(model.count_conv(grid), conv_first, rtol=1e-5, atol=1e-6)
    names = {n for n, p in model.named_parameters() if any(p is q for q in model.count_parameters())}
    assert names == {n for n, _ in model.named_parameters() if n.startswith(("count_", "speed_fc"))}
    assert len(names) == (8 if use_speed else 6)


def test_disnet_map_dropout_acts_on_the_map_in_training_only():
    torch.manual_seed(0)
    model = DisNet(width=8, use_speed=True, max_points=50, out_hw=(32, 64))
    torch.nn.init.normal_(model.decoder[-1].weight)
    img, speed = torch.rand(2, 3, 32, 64), torch.tensor([3.0, 12.0])
    model.eval()
    ref_map, ref_n = model(img, speed)
    model.map_dropout = 0.5
    eval_map, eval_n = model(img, speed)
    assert torch.equal(eval_map, ref_map) and torch.equal(eval_n, ref_n)
    model.train()
    model.map_dropout = 0.0
    torch.manual_seed(1)
    plain_map, plain_n = model(img, speed)
    model.map_dropout = 0.5
    torch.manual_seed(1)
    drop_map, drop_n = model(img, speed)
    assert torch.equal(drop_n, plain_n) and not torch.allclose(drop_map, plain_map)


def test_build_disnet_loads_backbone_weights(tmp_path):
    torch.manual_seed(3)
    state = ResNet18Backbone(64).state_dict()
    save_file(state, str(tmp_path / "r18.safetensors"))
    cfg = load_config("synthetic", {"disnet.width": "64", "disnet.backbone_weights": str(tmp_path / "r18.safetensors")})
    torch.manual_seed(4)
    model = build_disnet(cfg)
    got = model.backbone.state_dict()
    assert all(torch.equal(got[k], state[k]) for k in state)
    assert model.out_hw == (cfg.camera.working_size[1], cfg.camera.working_size[0])


SWITCHES = [c for c in itertools.product([True, False], repeat=3) if any(c)]


@pytest.mark.parametrize("cam,li,rp", SWITCHES)
def test_rssnet_switches(cam, li, rp):
    torch.manual_seed(0)
    model = RSSNet(cam, li, rp, patch_size=16, range_image_size=(128, 32), rss_min=-30, rss_max=40).eval()
    b = 5
    patch = torch.rand(b, 3, 16, 16) if cam else None
    rimg = torch.full((b, 32, 128), EMPTY) if li else None
    point = torch.randn(b, 4) * 10 if rp else None
    out = model(patch, rimg, point)
    assert out.shape == (b,) and bool(torch.isfinite(out).all())
    assert (model.patch_branch is not None) == cam and (model.range_branch is not None) == li
    assert (model.point_fc is not None) == rp
    assert model.head[0].in_features == 128 * (int(cam or li) + int(rp))
    if cam:
        with pytest.raises(ValueError, match="patch"):
            model(None, rimg, point)
        with pytest.raises(ValueError, match="expected shape"):
            model(torch.rand(b, 3, 8, 8), rimg, point)


def test_rssnet_needs_an_input_and_range():
    with pytest.raises(ValueError, match="at least one"):
        RSSNet(False, False, False, rss_min=0, rss_max=1)
    with pytest.raises(ValueError, match="rss_max"):
        RSSNet(rss_min=1, rss_max=1)


def test_rssnet_units_round_trip():
    model = RSSNet(rss_min=-74.0, rss_max=39.8)
    rss = torch.tensor([-74.0, 0.0, 39.8, 12.5])
    assert torch.allclose(model.normalise_rss(rss), (rss + 74.0) / 113.8)
    assert torch.allclose(model.to_rss(model.normalise_rss(rss)), rss, atol=1e-5)


def test_range_image_normalisation():
    raw = torch.tensor([[[0.0, 255.0, 127.5, EMPTY, float("nan"), 300.0]]])
    out = normalise_range_image(raw)
    assert out.shape == (1, 2, 1, 6)
    assert torch.allclose(out[0, 0, 0], torch.tensor([-1.0, 1.0, 0.0, 0.0, 0.0, 0.0]))
    assert torch.equal(out[0, 1, 0], torch.tensor([1.0, 1.0, 1.0, 0.0, 0.0, 0.0]))


def _random_maps(rng, b=4, h=6, w=7, zero_share=0.3):
    p = rng.random((b, h, w)) * (rng.random((b, h, w)) > zero_share)
    p /= p.sum(axis=(1, 2), keepdims=True)
    q = rng.random((b, h, w)) + 1e-3
    q /= q.sum(axis=(1, 2), keepdims=True)
    return p, q


@pytest.mark.parametrize("seed", range(5))
def test_kl_loss_against_numpy(seed):
    rng = np.random.default_rng(seed)
    p, q = _random_maps(rng)
    log_q = torch.tensor(np.log(q), requires_grad=True)
    got = kl_loss(log_q, torch.tensor(p))
    mask = p > 0
    want = np.array([np.sum(p[i][mask[i]] * np.log(p[i][mask[i]] / q[i][mask[i]])) for i in range(len(p))])
    assert got.shape == (len(p),)
    np.testing.assert_allclose(got.detach().numpy(), want, rtol=1e-10)
    assert bool((got >= 0).all())
    got.sum().backward()
    assert bool(torch.isfinite(log_q.grad).all())


def test_kl_loss_zero_for_identical_maps_and_shape_error():
    rng = np.random.default_rng(0)
    p, _ = _random_maps(rng)
    p_t = torch.tensor(p, dtype=torch.float32)
    log_p = torch.log_softmax(torch.log(p_t.clamp_min(1e-30)).flatten(1), 1).view_as(p_t)
    assert torch.allclose(kl_loss(log_p, p_t), torch.zeros(len(p)), atol=1e-5)
    with pytest.raises(ValueError):
        kl_loss(log_p, p_t[:, :3])


def test_count_and_rss_losses_against_numpy():
    n_hat = np.array([10.0, 250.5, 3.0])
    n = np.array([12.0, 200.0, 3.0])
    got = count_loss(torch.tensor(n_hat), torch.tensor(n)).numpy()
    np.testing.assert_allclose(got, [(-2 / 12) ** 2, (50.5 / 200) ** 2, 0.0])
    with pytest.raises(ValueError, match="> 0"):
        count_loss(torch.tensor([1.0]), torch.tensor([0.0]))
    a_hat, a = np.array([0.1, 0.5, 1.2]), np.array([0.3, 0.5, 1.0])
    np.testing.assert_allclose(rss_loss(torch.tensor(a_hat), torch.tensor(a)).numpy(), (a_hat - a) ** 2)
    with pytest.raises(ValueError):
        rss_loss(torch.zeros(3), torch.zeros(2))


def test_disnet_priors_start_at_the_baselines():
    """With use_prior, an untrained Dis-Net predicts exactly the prior map and the prior count."""
    import numpy as np

    from pipeline.models.disnet import DisNet

    torch.manual_seed(0)
    model = DisNet(width=8, use_speed=True, max_points=500, out_hw=(32, 64), use_prior=True).eval()
    prior = np.random.default_rng(0).random((32, 64)) + 0.01
    prior /= prior.sum()
    model.set_prior(prior)
    model.set_count_prior(123.0)
    log_map, n_hat = model(torch.rand(2, 3, 32, 64), torch.tensor([0.0, 9.0]))
    np.testing.assert_allclose(log_map.exp().detach().numpy(), np.broadcast_to(prior, (2, 32, 64)), rtol=1e-4)
    np.testing.assert_allclose(n_hat.detach().numpy(), [123.0, 123.0], rtol=1e-5)
    with pytest.raises(ValueError, match="expected shape"):
        model.set_prior(np.ones((3, 3)))


def test_speed_count_prior_is_linear_in_the_logit_between_knots_and_flat_beyond():
    """A count prior at ego speeds: an untrained number branch (zero head) predicts it exactly at
    the knots, the logit's linear interpolation between them, the end values beyond; a speed-blind
    network takes one count only; bad tables are refused. The prior is saved with the weights."""
    import numpy as np

    from pipeline.models.disnet import DisNet

    torch.manual_seed(0)
    model = DisNet(width=8, use_speed=True, max_points=500, out_hw=(32, 64), use_prior=True).eval()
    model.set_count_prior(np.array([50.0, 150.0, 100.0]), np.array([0.0, 5.0, 10.0]))
    speeds = torch.tensor([0.0, 5.0, 10.0, 2.5, 20.0, 7.0])
    grid = torch.randn(speeds.numel(), 64, 5, 18)  # the features do not matter with a zero head
    n_hat = model.count_from_grid(grid, speeds).detach().numpy()
    logit = lambda n: np.log(n / 500 / (1 - n / 500))  # noqa: E731
    mid = lambda a, b, t: 500 / (1 + np.exp(-((1 - t) * logit(a) + t * logit(b))))  # noqa: E731
    np.testing.assert_allclose(n_hat, [50, 150, 100, mid(50, 150, 0.5), 100, mid(150, 100, 0.4)], rtol=1e-4)
    _, from_forward = model(torch.rand(2, 3, 32, 64), torch.tensor([0.0, 20.0]))
    np.testing.assert_allclose(from_forward.detach().numpy(), [50, 100], rtol=1e-4)

    copy = DisNet(width=8, use_speed=True, max_points=500, out_hw=(32, 64), use_prior=True).eval()
    copy.load_state_dict(model.state_dict())
    np.testing.assert_allclose(copy.count_from_grid(grid, speeds).detach().numpy(), n_hat, rtol=1e-6)

    blind = DisNet(width=8, use_speed=False, max_points=500, out_hw=(32, 64), use_prior=True).eval()
    blind.set_count_prior(80.0)
    np.testing.assert_allclose(blind.count_from_grid(grid[:2]).detach().numpy(), [80, 80], rtol=1e-4)
    # one count sits in the head's bias (the arithmetic of the plain mean prior), not in the table
    model.set_count_prior(80.0)
    assert model.count_head.bias.item() == pytest.approx(logit(80.0)) and not model.count_prior_logit.any()
    np.testing.assert_allclose(model.count_from_grid(grid, speeds).detach().numpy(), np.full(6, 80.0), rtol=1e-4)
    with pytest.raises(ValueError, match="one count"):
        blind.set_count_prior(np.array([50.0, 60.0]), np.array([0.0, 1.0]))
    for counts, knots in (([50.0, 60.0], [1.0, 1.0]), ([50.0, np.nan], [0.0, 1.0]), ([1.0] * 9, list(range(9)))):
        with pytest.raises(ValueError, match="strictly increasing"):
            model.set_count_prior(np.array(counts), np.array(knots))


def test_importing_the_package_keeps_onednn_off_its_avx512_kernels():
    """pipeline/__init__ caps oneDNN at AVX2 (its AVX-512 1x1-convolution weight gradient segfaults
    on some AMD EPYC machines), even when torch was imported first; a user's setting wins."""
    import subprocess
    import sys

    code = ("import torch\nimport pipeline\ntorch.set_num_threads(2)\n"  # one thread takes torch's own kernels
            "x = torch.rand(2, 16, 20, 20, requires_grad=True)\ntorch.nn.Conv2d(16, 32, 1)(x).sum().backward()\n")
    env = {k: v for k, v in os.environ.items() if k not in ("ONEDNN_MAX_CPU_ISA", "OMP_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", code], env={**env, "ONEDNN_VERBOSE": "1"},
                         capture_output=True, text=True, check=True)
    out = out.stdout + out.stderr
    assert "onednn_verbose" in out and "avx512" not in out
    assert subprocess.run([sys.executable, "-c", "import os, pipeline; print(os.environ['ONEDNN_MAX_CPU_ISA'])"],
                          env={**env, "ONEDNN_MAX_CPU_ISA": "ALL"}, capture_output=True, text=True,
                          check=True).stdout.strip() == "ALL"


def _bn_eval(bn: torch.nn.BatchNorm2d, x: torch.Tensor) -> torch.Tensor:
    return torch.nn.functional.batch_norm(x, bn.running_mean, bn.running_var, bn.weight, bn.bias, False, 0.0, bn.eps)


def _reference_block(block, x: torch.Tensor, stride: int) -> torch.Tensor:
    """torchvision's BasicBlock written out (eval mode): relu(bn2(conv2(relu(bn1(conv1(x))))) + shortcut),
    shortcut = bn(1x1 conv, stride) of x where the shape changes, else x."""
    F_ = torch.nn.functional
    out = F_.relu(_bn_eval(block.bn1, F_.conv2d(x, block.conv1.weight, stride=stride, padding=1)))
    out = _bn_eval(block.bn2, F_.conv2d(out, block.conv2.weight, padding=1))
    if block.downsample is None:
        shortcut = x
    else:
        shortcut = _bn_eval(block.downsample[1], F_.conv2d(x, block.downsample[0].weight, stride=stride))
    return F_.relu(out + shortcut)


def test_resnet_forward_is_torchvisions_resnet18_written_out():
    """pyramid() against ResNet-18 computed with functional ops from the same weights: stem conv 7x7
    stride 2 + BN + ReLU + max-pool 3x3 stride 2, then layer1..4 of two BasicBlocks (first block of
    layers 2-4 with stride 2), ReLU after the residual sum."""
    F_ = torch.nn.functional
    torch.manual_seed(0)
    net = ResNet18Backbone(8).eval()
    for m in net.modules():  # non-trivial BN statistics and affine parameters: every BN matters
        if isinstance(m, torch.nn.BatchNorm2d):
            with torch.no_grad():
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.5, 0.5)
    x = torch.randn(2, 3, 64, 96)
    y = F_.max_pool2d(F_.relu(_bn_eval(net.bn1, F_.conv2d(x, net.conv1.weight, stride=2, padding=3))), 3, 2, 1)
    want = []
    for layer, stride in ((net.layer1, 1), (net.layer2, 2), (net.layer3, 2), (net.layer4, 2)):
        y = _reference_block(layer[1], _reference_block(layer[0], y, stride), 1)
        want.append(y)
    with torch.no_grad():
        got = net.pyramid(x)
    assert len(got) == 4
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w, rtol=1e-4, atol=1e-5)


def test_resnet_initialisation_is_torchvisions():
    """Convolutions: Kaiming normal, fan_out mode, ReLU gain (std sqrt(2 / (out_channels k^2)));
    BN weight 1, bias 0."""
    torch.manual_seed(0)
    net = ResNet18Backbone(64)
    for name in ("conv1", "layer1.0.conv1", "layer4.1.conv2", "layer2.0.downsample.0"):
        w = net.get_submodule(name).weight.detach()
        fan_out = w.shape[0] * w.shape[2] * w.shape[3]
        assert float(w.std()) == pytest.approx(np.sqrt(2.0 / fan_out), rel=0.05), name
        assert abs(float(w.mean())) < 0.1 * np.sqrt(2.0 / fan_out), name
    bn = net.get_submodule("layer3.1.bn2")
    assert torch.equal(bn.weight, torch.ones_like(bn.weight)) and not bn.bias.any()


def test_networks_normalise_rgb_with_imagenet_statistics():
    """Dis-Net's image and RSS-Net's patch reach their first convolution ImageNet-normalised: the
    ImageNet mean colour as 0, one standard deviation above it as 1."""
    from pipeline.models.disnet import IMAGENET_MEAN, IMAGENET_STD

    mean, std = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    disnet = DisNet(width=8, out_hw=(32, 64)).eval()
    rssnet = RSSNet(True, False, False, patch_size=16, rss_min=0.0, rss_max=1.0).eval()
    seen: dict[str, list[torch.Tensor]] = {"disnet": [], "rssnet": []}
    disnet.backbone.conv1.register_forward_pre_hook(lambda m, args: seen["disnet"].append(args[0]))
    rssnet.patch_branch[0].register_forward_pre_hook(lambda m, args: seen["rssnet"].append(args[0]))
    with torch.no_grad():
        for k in (0.0, 1.0):
            disnet((mean + k * std).expand(1, 3, 32, 64), torch.tensor([5.0]))
            rssnet((mean + k * std).expand(1, 3, 16, 16), None, None)
    for net, (zero, one) in seen.items():
        torch.testing.assert_close(zero, torch.zeros_like(zero), atol=1e-6, rtol=0, msg=net)
        torch.testing.assert_close(one, torch.ones_like(one), atol=1e-5, rtol=0, msg=net)


def test_rssnet_point_vector_scaling():
    """[x, y, z] enter divided by 50 m, the Doppler by 10 m/s."""
    from pipeline.models.rssnet import normalise_point

    got = normalise_point(torch.tensor([[50.0, -25.0, 5.0, -10.0], [0.0, 10.0, -50.0, 2.5]]))
    torch.testing.assert_close(got, torch.tensor([[1.0, -0.5, 0.1, -1.0], [0.0, 0.2, -1.0, 0.25]]))


def test_disnet_speed_map_is_film_of_the_decoded_features():
    """disnet.speed_map: the decoder reads F * (1 + gamma(s)) + beta(s) per channel, s = speed / 10 m/s."""
    torch.manual_seed(0)
    film = DisNet(width=8, use_speed=True, out_hw=(32, 64), speed_map=True).eval()
    torch.nn.init.normal_(film.speed_film[-1].weight, std=0.5)
    torch.nn.init.normal_(film.speed_film[-1].bias, std=0.5)
    seen = []
    film.decoder.register_forward_pre_hook(lambda m, args: seen.append(args[0]))
    img, speed = torch.rand(2, 3, 32, 64), torch.tensor([3.0, 14.0])
    with torch.no_grad():
        film(img, speed)
        feat = film.backbone((img - film.mean) / film.std)
        gamma, beta = film.speed_film(speed[:, None] / 10.0).chunk(2, dim=1)
    assert gamma.abs().max() > 0.1 and beta.abs().max() > 0.1
    torch.testing.assert_close(seen[0], feat * (1 + gamma[:, :, None, None]) + beta[:, :, None, None])


def test_count_prior_follows_np_interp_of_the_logit_also_outside_the_knots():
    """A full table of COUNT_PRIOR_KNOTS knots (no padding): the prior is np.interp of the logit,
    flat below the first knot (slow frames are common: a knot sits at its bin's mean speed) and
    beyond the last."""
    from pipeline.models.disnet import COUNT_PRIOR_KNOTS

    torch.manual_seed(0)
    model = DisNet(width=8, use_speed=True, max_points=500, out_hw=(32, 64)).eval()
    knots = np.array([2.0, 4.0, 5.0, 7.0, 8.0, 10.0, 13.0, 20.0])
    counts = np.array([60.0, 120.0, 90.0, 200.0, 150.0, 100.0, 80.0, 300.0])
    assert knots.size == COUNT_PRIOR_KNOTS
    model.set_count_prior(counts, knots)
    speeds = np.array([0.0, 1.0, 2.0, 3.0, 4.5, 9.0, 16.0, 20.0, 25.0, 40.0])
    grid = torch.randn(speeds.size, 64, 5, 18)  # a zero head: the features do not matter
    got = model.count_from_grid(grid, torch.tensor(speeds, dtype=torch.float32)).detach().numpy()
    q = counts / 500
    want = 500 / (1 + np.exp(-np.interp(speeds, knots, np.log(q / (1 - q)))))
    np.testing.assert_allclose(got, want, rtol=1e-4)


def test_disnet_prior_mix_mixes_the_map_with_its_prior_only():
    """set_prior_mix(w): the map becomes (1 - w) map + w prior for w in [0, 1], both ends
    included (w = 1: the prior alone), the count untouched; a network without use_prior ignores
    the share (its prior logits are no prior); shares outside [0, 1] are refused."""
    torch.manual_seed(0)
    img, speed = torch.rand(2, 3, 32, 64), torch.tensor([0.0, 9.0])
    model = DisNet(width=8, use_speed=True, max_points=500, out_hw=(32, 64), use_prior=True).eval()
    prior = np.random.default_rng(0).random((32, 64)) + 0.01
    model.set_prior(prior / prior.sum())
    torch.nn.init.normal_(model.decoder[-1].weight, std=10.0)  # a map other than the prior
    with torch.no_grad():
        plain, n_plain = model(img, speed)
    p = torch.softmax(model.prior_logits.reshape(-1).double(), 0).reshape(32, 64)
    assert (plain.exp().double() - p).abs().sum() > 0.1
    for w in (0.0, 0.3, 1.0):
        model.set_prior_mix(w)
        with torch.no_grad():
            log_map, n_hat = model(img, speed)
        assert torch.allclose(log_map.exp().double(), (1 - w) * plain.exp().double() + w * p, atol=1e-7)
        assert torch.equal(n_hat, n_plain)
    for bad in (-0.1, 1.01):
        with pytest.raises(ValueError, match="prior mix"):
            model.set_prior_mix(bad)
    blind = DisNet(width=8, use_speed=True, out_hw=(32, 64)).eval()
    with torch.no_grad():
        before = blind(img, speed)[0]
        blind.set_prior_mix(0.5)
        assert torch.equal(blind(img, speed)[0], before)
