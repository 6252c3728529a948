"""Training losses with the paper's printing errors corrected (see METHOD.md). All return one value
per frame / per point so that metrics can be averaged per frame, not per batch."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.nn import functional as F


def kl_loss(log_pred: Tensor, target: Tensor) -> Tensor:
    """L_KL per frame: sum_x P(x) log(P(x) / P_hat(x)) (eq. 8 corrected) = KL(target || prediction).

    log_pred (B, H, W): log-probabilities (log-softmax output); target (B, H, W): probabilities
    summing to 1 per frame. Pixels with P = 0 contribute 0 (0 log 0 = 0). Returns (B,) >= 0.
    """
    if log_pred.shape != target.shape or log_pred.dim() < 2:
        raise ValueError(f"kl_loss: log_pred {tuple(log_pred.shape)} and target {tuple(target.shape)} "
                         "must have the same shape (B, H, W)")
    target = target.to(log_pred.dtype)
    per_pixel = torch.special.xlogy(target, target) - target * log_pred
    return per_pixel.flatten(1).sum(dim=1)


def count_loss(n_hat: Tensor, n: Tensor) -> Tensor:
    """L_n per frame: ((n_hat - n) / n)^2 (eq. 9 corrected). n_hat, n (B,); n must be > 0."""
    if n_hat.shape != n.shape:
        raise ValueError(f"count_loss: n_hat {tuple(n_hat.shape)} and n {tuple(n.shape)} differ in shape")
    n = n.to(n_hat.dtype)
    if bool((n <= 0).any()):
        raise ValueError("count_loss: true counts must be > 0 (frames without radar points have no target)")
    return ((n_hat - n) / n) ** 2


def rss_loss(a_hat_norm: Tensor, a_norm: Tensor) -> Tensor:
    """L_a per point: (a_hat_norm - a_norm)^2 with a_norm = (a - a_min) / (a_max - a_min) (eq. 22). (B,)."""
    if a_hat_norm.shape != a_norm.shape:
        raise ValueError(f"rss_loss: shapes {tuple(a_hat_norm.shape)} and {tuple(a_norm.shape)} differ")
    return (a_hat_norm - a_norm.to(a_hat_norm.dtype)) ** 2


def poisson_loss(log_rate: Tensor, count: Tensor) -> Tensor:
    """Poisson negative log-likelihood per point without the constant log(count!):
    exp(log_rate) - count * log_rate. log_rate, count (B,); counts >= 0. (B,)."""
    if log_rate.shape != count.shape:
        raise ValueError(f"poisson_loss: shapes {tuple(log_rate.shape)} and {tuple(count.shape)} differ")
    return F.poisson_nll_loss(log_rate, count.to(log_rate.dtype), log_input=True, full=False, reduction="none")
