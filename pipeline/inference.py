"""The trained nets at work: loading a checkpoint into its net (as the configuration or the
checkpoint says), the device, the nets' inputs from array rows, and batched prediction (Dis-Net's
map and count, RSS-Net's RSS, PlaceNet's intensity); what a checkpoint's metadata adds (PlaceNet's
count scale, RSS-Net's residual quantiles and the draws from them)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from pipeline import checkpoint as ckpt
from pipeline.errors import ConfigError
from pipeline.models.disnet import DisNet, disnet_kwargs
from pipeline.models.placenet import PlaceNet, placenet_kwargs
from pipeline.models.resnet import resnet18_backbone
from pipeline.models.rssnet import RSSNet, rssnet_kwargs
from pipeline.rows import Batch, iter_batches, n_rows


def select_device(name: str, key: str = "train.device") -> torch.device:
    """'auto' -> cuda when available else cpu; 'cpu' / 'cuda' as given (ConfigError naming the
    setting ``key`` if unusable)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"{key} = '{name}' but CUDA is not available (use 'auto' or 'cpu')")
    if not (name == "cpu" or name.startswith("cuda")):
        raise ConfigError(f"{key} must be 'auto', 'cpu' or 'cuda', got '{name}'")
    return torch.device(name)


def disnet_inputs(batch: Batch, device: torch.device) -> tuple[Tensor, Tensor]:
    """uint8 (B, H, W, 3) -> float (B, 3, H, W) in [0, 1] on device; speeds (B,) float32."""
    img = torch.from_numpy(np.ascontiguousarray(batch["images"])).to(device)
    img = img.permute(0, 3, 1, 2).float() / 255.0
    speed = torch.from_numpy(np.asarray(batch["speeds"], np.float32)).to(device)
    return img, speed


def rssnet_inputs(model: RSSNet, batch: Batch, device: torch.device) -> tuple[Tensor | None, ...]:
    """The enabled branches' inputs of one batch on ``device``, None for a dropped branch: patches
    uint8 (B, ps, ps, 3) -> float (B, 3, ps, ps) in [0, 1]; range images and point vectors float32."""
    patch = range_image = point = None
    if model.use_camera:
        patch = torch.from_numpy(np.ascontiguousarray(batch["patches"])).to(device)
        patch = patch.permute(0, 3, 1, 2).float() / 255.0                 # (B, 3, ps, ps)
    if model.use_lidar:
        range_image = torch.from_numpy(np.asarray(batch["range_images"], np.float32)).to(device)
    if model.use_radar_point:
        point = torch.from_numpy(np.asarray(batch["point_vectors"], np.float32)).to(device)
    return patch, range_image, point


def rss_arrays(model: RSSNet, patches: Any, range_images: Any, point_vectors: Any) -> dict[str, Any]:
    """The arrays the enabled branches read (dropped branches read nothing)."""
    named = {"patches": (model.use_camera, patches), "range_images": (model.use_lidar, range_images),
             "point_vectors": (model.use_radar_point, point_vectors)}
    out = {}
    for name, (used, array) in named.items():
        if used:
            if array is None:
                raise ValueError(f"RSS-Net uses '{name}' (see rssnet.*) but no array was given")
            out[name] = array
    return out


def jsonable_arch(kwargs: dict[str, Any]) -> dict[str, Any]:
    """A net's constructor arguments as its checkpoint records them (tuples as lists)."""
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in kwargs.items()}


def saved_count_scale(meta: dict) -> float | None:
    """PlaceNet's count scale from its checkpoint's metadata; None where it holds none (saved
    before 2026-12-05) or not a finite number."""
    scale = meta.get("count_scale")
    return float(scale) if isinstance(scale, (int, float)) and math.isfinite(scale) else None


RESIDUAL_KEY = "rss_residual_quantiles"
"""RSS-Net checkpoint metadata: the quantiles of its validation residuals (synth.rss_sampling)."""


RESIDUAL_LEVELS = np.linspace(0.0, 1.0, 101)
"""Levels of the residual quantiles a checkpoint keeps (0 and 1: the smallest and largest)."""


def saved_residual_quantiles(meta: dict) -> np.ndarray | None:
    """RSS-Net's residual quantiles (len(RESIDUAL_LEVELS),) from its checkpoint's metadata; None
    where it holds none (saved before 2026-12-06, or trained without validation points) or not
    finite, non-decreasing numbers."""
    q = meta.get(RESIDUAL_KEY)
    try:
        q = np.asarray(q, np.float64)
    except (TypeError, ValueError):
        return None
    ok = q.shape == RESIDUAL_LEVELS.shape and np.all(np.isfinite(q)) and np.all(np.diff(q) >= 0)
    return q if ok else None


def draw_residuals(quantiles: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n,) residuals drawn from the distribution whose quantiles at RESIDUAL_LEVELS are
    ``quantiles`` (inverse transform, linear between the levels)."""
    return np.interp(rng.random(n), RESIDUAL_LEVELS, np.asarray(quantiles, np.float64))


def model_state(model: nn.Module, tensors: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The ``model.`` tensors of a checkpoint as ``model``'s state dict; buffers that later versions
    added (``OPTIONAL_BUFFERS``, absent from older checkpoints) keep the model's defaults."""
    state = ckpt.strip_prefix(tensors, "model.")
    for name in getattr(model, "OPTIONAL_BUFFERS", ()):
        state.setdefault(name, model.state_dict()[name])
    return state


def _load_into(model: nn.Module, arch: dict[str, Any], path: str | Path, device: torch.device) -> nn.Module:
    tensors, meta = ckpt.load_checkpoint(path, prefix="model.")
    if meta.get("arch") != arch:
        diff = {k: (meta.get("arch", {}).get(k), v) for k, v in arch.items()
                if meta.get("arch", {}).get(k) != v}
        raise ConfigError(f"{path}: checkpoint architecture differs from the configuration "
                          f"(saved, configured): {diff}")
    try:
        model.load_state_dict(model_state(model, tensors), strict=True)
    except RuntimeError as exc:  # e.g. a checkpoint of an older version of the network
        raise ConfigError(f"{path}: the checkpoint does not fit this version's network (written by an "
                          f"older version? run the train stage again): {exc}") from exc
    return model.to(device).eval()


def _arch(cfg, kwargs, path: str | Path, saved: bool) -> dict[str, Any]:
    """A net's constructor arguments: ``kwargs(cfg)``, or with ``saved`` those its checkpoint
    ``path`` was written with (nets trained on another dataset, train.nets_from)."""
    if not saved:
        return jsonable_arch(kwargs(cfg))
    arch = ckpt.read_meta(path).get("arch")
    if not isinstance(arch, dict):
        raise ConfigError(f"{path}: the checkpoint records no architecture (written by an older version?)")
    return arch


def load_disnet(cfg, path: str | Path, device: str | None = None, saved_arch: bool = False) -> DisNet:
    """Dis-Net from a checkpoint (best or last), eval mode, on cfg.train.device (or ``device``);
    ``saved_arch``: built as the checkpoint says, not as ``cfg`` (its map then has the size it was
    trained at, the working size of its dataset)."""
    arch = _arch(cfg, disnet_kwargs, path, saved_arch)
    model = DisNet(backbone=resnet18_backbone(None, width=arch["width"]), **arch)
    return _load_into(model, arch, path, select_device(device or cfg.train.device))


def load_rssnet(cfg, path: str | Path, device: str | None = None, saved_arch: bool = False) -> RSSNet:
    """RSS-Net from a checkpoint (best or last), eval mode, on cfg.train.device (or ``device``);
    ``saved_arch`` as for :func:`load_disnet`."""
    arch = _arch(cfg, rssnet_kwargs, path, saved_arch)
    model = _load_into(RSSNet(**arch), arch, path, select_device(device or cfg.train.device))
    model.residual_quantiles = saved_residual_quantiles(ckpt.read_meta(path))
    return model


def load_placenet(cfg, path: str | Path, device: str | None = None, saved_arch: bool = False) -> PlaceNet:
    """PlaceNet from a checkpoint (best or last), eval mode, on cfg.train.device (or ``device``);
    ``saved_arch`` as for :func:`load_disnet`."""
    arch = _arch(cfg, placenet_kwargs, path, saved_arch)
    model = _load_into(PlaceNet(**arch), arch, path, select_device(device or cfg.train.device))
    model.count_scale = saved_count_scale(ckpt.read_meta(path))
    return model


def device_of(model: nn.Module) -> torch.device:
    """The device of a net's parameters."""
    return next(model.parameters()).device


@torch.no_grad()
def disnet_predict(model: DisNet, images: Any, speeds: Any, batch: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """images (B, H, W, 3) uint8 RGB, speeds (B,) m/s -> (prob_map (B, h, w) float32 summing to 1
    per frame at the model's out_hw, n_hat (B,) float32 expected point count)."""
    model.eval()
    device = device_of(model)
    n = n_rows(images)
    maps = np.empty((n, *model.out_hw), np.float32)
    counts = np.empty(n, np.float32)
    arrays = {"images": images, "speeds": np.asarray(speeds, np.float32).reshape(-1)}
    for s, b in zip(range(0, n, batch), iter_batches(arrays, np.arange(n), batch)):
        log_map, n_hat = model(*disnet_inputs(b, device))
        maps[s:s + len(n_hat)] = log_map.exp().cpu().numpy()
        counts[s:s + len(n_hat)] = n_hat.cpu().numpy()
    return maps, counts


@torch.no_grad()
def rssnet_predict(model: RSSNet, patches: Any, range_images: Any, point_vectors: Any,
                   batch: int = 256) -> np.ndarray:
    """RSS (N,) float32 in dataset units for N points; inputs of dropped branches may be None."""
    model.eval()
    device = device_of(model)
    arrays = rss_arrays(model, patches, range_images, point_vectors)
    n = n_rows(next(iter(arrays.values())))
    out = np.empty(n, np.float32)
    for s, b in zip(range(0, n, batch), iter_batches(arrays, np.arange(n), batch)):
        a_hat = model(*rssnet_inputs(model, b, device))
        out[s:s + len(a_hat)] = model.to_rss(a_hat).cpu().numpy()
    return out


@torch.no_grad()
def placenet_predict(model: PlaceNet, features: np.ndarray, batch: int = 65536) -> np.ndarray:
    """Intensity lambda (C,) float64 >= 0 of candidates with features (C, n_features)."""
    model.eval()
    x = np.asarray(features, np.float32)
    out = np.empty(len(x), np.float64)
    for s in range(0, len(x), batch):
        out[s:s + batch] = model(torch.from_numpy(x[s:s + batch]).to(device_of(model))).exp().double().cpu().numpy()
    return out
