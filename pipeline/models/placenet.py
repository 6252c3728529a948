"""PlaceNet: the intensity of real radar returns at a lidar point (pipeline.placement).

Input: the candidate's features (pipeline.placement.FEATURES), standardised with the training
set's mean and standard deviation (buffers, saved with the weights). The training features'
pipeline.input_range.RANGE_PERCENTILES are saved too (``feature_low``, ``feature_high``): :meth:`PlaceNet.outside_range`
says which inputs of another dataset (train.nets_from) the net never saw the like of. An MLP of ``depth`` hidden
layers of ``width`` units (ReLU) outputs log lambda: lambda is the expected number of real radar
points whose nearest candidate this lidar point is, trained with the Poisson negative
log-likelihood (pipeline.models.losses.poisson_loss).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from pipeline.input_range import outside, training_range
from pipeline.placement import FEATURES



class PlaceNet(nn.Module):
    OPTIONAL_BUFFERS = ("feature_low", "feature_high")
    """Absent from checkpoints written before 2026-12-04: loaded as unbounded (no range check)."""

    def __init__(self, n_features: int = len(FEATURES), width: int = 64, depth: int = 2) -> None:
        super().__init__()
        if n_features < 1 or width < 1 or depth < 1:
            raise ValueError(f"PlaceNet: n_features, width and depth must be >= 1, got {n_features}, {width}, {depth}")
        self.n_features = n_features
        self.register_buffer("feature_mean", torch.zeros(n_features))
        self.register_buffer("feature_std", torch.ones(n_features))
        self.register_buffer("feature_low", torch.full((n_features,), -torch.inf, dtype=torch.float64))
        self.register_buffer("feature_high", torch.full((n_features,), torch.inf, dtype=torch.float64))
        layers: list[nn.Module] = []
        for k in range(depth):
            layers += [nn.Linear(n_features if k == 0 else width, width), nn.ReLU()]
        self.mlp = nn.Sequential(*layers, nn.Linear(width, 1))
        self.count_scale: float | None = None
        """s: s times the intensity summed over a frame's candidates estimates its real radar
        points (pipeline.training.placenet_count_scale); saved in the checkpoint's metadata since
        2026-12-05, None before."""

    def set_standardisation(self, features: np.ndarray) -> None:
        """Mean and standard deviation of training features (N, n_features), a constant column
        std 1, and their training range (pipeline.input_range.training_range)."""
        x = np.asarray(features, np.float64).reshape(-1, self.n_features)
        if len(x) == 0:
            raise ValueError("PlaceNet.set_standardisation: no training features")
        std = x.std(axis=0)
        self.feature_mean.copy_(torch.as_tensor(x.mean(axis=0)))
        self.feature_std.copy_(torch.as_tensor(np.where(std > 1e-6, std, 1.0)))
        low, high = training_range(x)
        self.feature_low.copy_(torch.as_tensor(low))
        self.feature_high.copy_(torch.as_tensor(high))

    def has_training_range(self) -> bool:
        """Whether the net was saved with its training range (not before 2026-12-04)."""
        return bool(torch.isfinite(self.feature_low).all())

    def outside_range(self, features: np.ndarray) -> np.ndarray:
        """Bool (C, n_features): which of the features (C, n_features) lie outside the training
        range (never for a net saved without it)."""
        return outside(np.asarray(features, np.float64).reshape(-1, self.n_features), self.feature_low.cpu().numpy(),
                       self.feature_high.cpu().numpy())

    def forward(self, features: Tensor) -> Tensor:
        """features (B, n_features) -> log intensity (B,)."""
        if features.dim() != 2 or features.shape[1] != self.n_features:
            raise ValueError(f"PlaceNet: expected features (B, {self.n_features}), got {tuple(features.shape)}")
        x = (features.to(self.feature_mean.dtype) - self.feature_mean) / self.feature_std
        return self.mlp(x).squeeze(1)


def placenet_kwargs(cfg) -> dict:
    """Constructor arguments of PlaceNet from a Config (placement.width, placement.depth)."""
    return {"n_features": len(FEATURES), "width": cfg.placement.width, "depth": cfg.placement.depth}


def build_placenet(cfg) -> PlaceNet:
    """PlaceNet from a Config."""
    return PlaceNet(**placenet_kwargs(cfg))
