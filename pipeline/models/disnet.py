"""Dis-Net (paper Fig. 4): image (+ ego speed) -> radar point distribution over pixels and count.

- Backbone: ResNet-18 trunk (``pipeline.models.resnet``) -> F (B, 8w, H/32, W/32), w = width.
- Distribution branch: four stride-2 transpose convolutions 8w -> 4w -> 2w -> w -> 1 (BN + ReLU
  after all but the last), bilinear resize to exactly ``out_hw``, log-softmax over all pixels:
  a proper log-probability map (the paper's "sigmoid" is not a distribution).
- Number branch: adaptive average pool to a fixed 5 x 18 grid, 1x1 conv 8w -> 1 (90 values, the
  authors' FC input size, so any image size works; the same function as their conv-then-pool),
  FC 90 -> 12 + ReLU; speed |v_D| / 10 m/s -> FC 1 -> 12 + ReLU (dropped when ``use_speed`` is
  False); concat -> FC -> + count prior logit -> sigmoid * max_points. The count prior (an
  extension of the paper, see ``set_count_prior``) is a piecewise-linear function of the ego speed
  held in buffers (COUNT_PRIOR_KNOTS knots, saved in checkpoints); all zeros (logit 0) unless a
  speed table is set (a single prior count goes to the head's bias instead).
  ``count_grad_scale`` (a training setting, not saved with the architecture) scales the gradient
  the number branch sends back into the backbone. ``map_dropout`` (also a training setting)
  zeroes whole channels of the features the distribution branch decodes with that probability
  in training mode (spatial dropout, Tompson et al. 2015); the number branch is not affected.
- ``speed_map`` (an extension of the paper): the features the distribution branch decodes are
  modulated by the ego speed, F * (1 + gamma(s)) + beta(s) per channel (FiLM, Perez et al. 2018),
  gamma and beta from an MLP 1 -> 32 -> 2 * 8w whose last layer starts at zero (so training starts
  from the speed-free network).
- ``skips`` (an extension of the paper): after each of the first three transpose convolutions
  (1/16, 1/8, 1/4 of the input) a 1x1 convolution of the backbone's feature map of the same size
  (layer3, layer2, layer1) is added (FPN-style lateral connections; zero-initialised, so training
  starts from the paper's decoder). The map then sees local appearance, not only the 1/32 grid.

The input image is RGB float in [0, 1]; ImageNet mean/std normalisation happens inside.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pipeline.models.resnet import ResNet18Backbone, resnet18_backbone

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
COUNT_GRID = (5, 18)
"""Fixed grid the number branch pools the 1-channel feature map to (5 * 18 = 90 values)."""
SPEED_SCALE_MPS = 10.0
"""The ego speed enters the network divided by this, m/s."""
COUNT_PRIOR_KNOTS = 8
"""Knots of the count prior's piecewise-linear function of the ego speed."""


class DisNet(nn.Module):
    """Distribution + count network.

    ``forward(image (B, 3, H, W) float [0, 1], speed_mps (B,))`` returns
    ``(log_map (B, out_h, out_w), n_hat (B,))``: ``log_map.exp()`` sums to 1 per frame and
    ``n_hat`` lies in (0, max_points).
    """

    OPTIONAL_BUFFERS = ("prior_mix",)
    """Buffers absent from checkpoints written before 2026-12-06 (those load with no mixture)."""

    def __init__(self, width: int = 64, use_speed: bool = True, max_points: int = 1000,
                 out_hw: tuple[int, int] = (160, 320), backbone: ResNet18Backbone | None = None,
                 use_prior: bool = False, speed_map: bool = False, skips: bool = False) -> None:
        super().__init__()
        if max_points < 1:
            raise ValueError(f"max_points must be >= 1, got {max_points}")
        self.use_speed = use_speed
        self.max_points = int(max_points)
        self.out_hw = (int(out_hw[0]), int(out_hw[1]))
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.backbone = backbone if backbone is not None else ResNet18Backbone(width)
        c = self.backbone.out_channels
        self.decoder = nn.Sequential(
            _up(c, c // 2), _up(c // 2, c // 4), _up(c // 4, c // 8),
            nn.ConvTranspose2d(c // 8, 1, 4, stride=2, padding=1))
        self.laterals = None
        if skips:  # layer3, layer2, layer1 -> the outputs of the first three decoder stages
            self.laterals = nn.ModuleList(nn.Conv2d(c // k, c // k, 1) for k in (2, 4, 8))
            for conv in self.laterals:
                nn.init.zeros_(conv.weight)
                nn.init.zeros_(conv.bias)
        self.use_prior = use_prior
        # log of the mean training map, added to the decoder's logits (set_prior); saved in checkpoints
        self.register_buffer("prior_logits", torch.zeros(self.out_hw))
        # the share w of the prior mixed into the output map, (1 - w) map + w prior (set after
        # training on the val split: disnet.prior_mix); 0 while training
        self.register_buffer("prior_mix", torch.zeros(()))
        if use_prior:  # start exactly at the prior: the decoder learns the per-frame residual
            nn.init.zeros_(self.decoder[-1].weight)
            nn.init.zeros_(self.decoder[-1].bias)
        self.speed_film = None
        if speed_map:
            self.speed_film = nn.Sequential(nn.Linear(1, 32), nn.ReLU(inplace=True), nn.Linear(32, 2 * c))
            nn.init.zeros_(self.speed_film[-1].weight)
            nn.init.zeros_(self.speed_film[-1].bias)
        self.count_conv = nn.Conv2d(c, 1, 1)
        self.count_fc = nn.Linear(COUNT_GRID[0] * COUNT_GRID[1], 12)
        self.speed_fc = nn.Linear(1, 12) if use_speed else None
        self.count_head = nn.Linear(24 if use_speed else 12, 1)
        # count prior: logit(count / max_points) at increasing ego speeds (set_count_prior)
        self.register_buffer("count_prior_speed_mps", torch.arange(COUNT_PRIOR_KNOTS, dtype=torch.float32))
        self.register_buffer("count_prior_logit", torch.zeros(COUNT_PRIOR_KNOTS))
        self.count_grad_scale = 1.0
        self.map_dropout = 0.0

    def forward(self, image: Tensor, speed_mps: Tensor | None = None) -> tuple[Tensor, Tensor]:
        b = image.shape[0]
        pyramid = self.backbone.pyramid(self._normalise(image))
        feat = pyramid[-1]                                              # (B, C, H/32, W/32)
        map_feat = feat
        if self.speed_film is not None:
            gamma, beta = self.speed_film(_speed_input(speed_mps, b, feat.dtype, "speed_map")).chunk(2, dim=1)
            map_feat = feat * (1 + gamma[:, :, None, None]) + beta[:, :, None, None]
        if self.training and self.map_dropout > 0:                      # whole channels, rescaled
            map_feat = F.dropout2d(map_feat, self.map_dropout)
        logits = self._decode(map_feat, pyramid)                        # (B, 1, H/2, W/2)
        logits = F.interpolate(logits, size=self.out_hw, mode="bilinear", align_corners=False)
        logits = logits + self.prior_logits                             # (B, 1, H, W)
        log_map = F.log_softmax(logits.reshape(b, -1), dim=1).reshape(b, *self.out_hw)
        if self.use_prior and bool(self.prior_mix > 0):
            log_map = mix_with_prior(log_map, self.prior_logits, self.prior_mix)
        count_feat = _scale_grad(feat, self.count_grad_scale)           # same values, scaled gradient
        return log_map, self.count_from_grid(F.adaptive_avg_pool2d(count_feat, COUNT_GRID), speed_mps)

    def count_from_grid(self, grid_feat: Tensor, speed_mps: Tensor | None = None) -> Tensor:
        """The number branch after pooling: backbone features pooled to COUNT_GRID (B, C, 5, 18)
        (+ speed (B,) m/s) -> n_hat (B,). Pooling first is exact: the 1x1 convolution is affine
        per cell and the adaptive average pool averages cells."""
        b = grid_feat.shape[0]
        grid = self.count_conv(grid_feat)                               # (B, 1, 5, 18)
        code = F.relu(self.count_fc(grid.reshape(b, -1)))               # (B, 12)
        if self.speed_fc is not None:
            s = _speed_input(speed_mps, b, code.dtype, "use_speed")
            code = torch.cat([code, F.relu(self.speed_fc(s))], dim=1)   # (B, 24)
        logit = self.count_head(code).squeeze(1) + self._count_prior_logit(speed_mps, b)
        return torch.sigmoid(logit) * self.max_points                  # (B,)

    def _count_prior_logit(self, speed_mps: Tensor | None, b: int) -> Tensor:
        """The count prior's logit (B,) at the ego speeds (B,) m/s: linear between knots, flat beyond
        the first and last (np.interp's rule). Without ``use_speed`` the prior is constant (its
        first knot), so a speed-blind network never sees the speed."""
        x, y = self.count_prior_speed_mps, self.count_prior_logit
        if not self.use_speed:
            return y[0].expand(b)
        s = _speed_input(speed_mps, b, x.dtype, "use_speed").reshape(b) * SPEED_SCALE_MPS
        hi = torch.searchsorted(x, s.contiguous()).clamp(1, x.numel() - 1)
        x0, x1, y0, y1 = x[hi - 1], x[hi], y[hi - 1], y[hi]
        t = ((s - x0) / (x1 - x0)).clamp(0.0, 1.0)
        return y0 + t * (y1 - y0)

    @torch.no_grad()
    def count_grid_features(self, image: Tensor) -> Tensor:
        """What the number branch reads of ``image`` (B, 3, H, W) float [0, 1]: the backbone's
        1/32 features pooled to COUNT_GRID, (B, C, 5, 18)."""
        return F.adaptive_avg_pool2d(self.backbone(self._normalise(image)), COUNT_GRID)

    def _normalise(self, image: Tensor) -> Tensor:
        """RGB in [0, 1] -> ImageNet-normalised backbone input."""
        return (image - self.mean) / self.std

    def count_parameters(self) -> list[nn.Parameter]:
        """The number branch's own parameters (not the shared backbone's)."""
        modules = [self.count_conv, self.count_fc, self.count_head, self.speed_fc]
        return [p for m in modules if m is not None for p in m.parameters()]

    def _decode(self, feat: Tensor, pyramid: list[Tensor]) -> Tensor:
        """Decoder logits (B, 1, H/2, W/2) from the 1/32 features, plus the lateral skips if any."""
        if self.laterals is None:
            return self.decoder(feat)
        x = feat
        for up, lateral, skip in zip(self.decoder[:3], self.laterals, pyramid[2::-1]):
            x = up(x)
            if x.shape[-2:] != skip.shape[-2:]:  # odd sizes: the backbone rounded up on the way down
                x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = x + lateral(skip)
        return self.decoder[3](x)

    @torch.no_grad()
    def set_count_prior(self, counts: float | np.ndarray, speeds_mps: np.ndarray | None = None) -> None:
        """Start the number branch at a prior count and learn the per-frame deviation from it.

        ``counts``: one count (e.g. the training mean), the prior at every speed: zero head
        weights, head bias logit(count / max_points). Or counts (K,) at strictly increasing
        ``speeds_mps`` (K,), 2 <= K <= COUNT_PRIOR_KNOTS (see
        ``pipeline.net_baselines.speed_count_prior``): zero head weights and bias, the prior's logits in
        the buffers, linear in the logit between the knots. A network built without ``use_speed``
        takes one count only.
        """
        y = np.atleast_1d(np.asarray(counts, np.float64))
        x = np.arange(y.size, dtype=np.float64) if speeds_mps is None else np.asarray(speeds_mps, np.float64)
        if not (1 <= y.size <= COUNT_PRIOR_KNOTS and x.shape == y.shape and np.all(np.isfinite(x))
                and np.all(np.isfinite(y)) and np.all(np.diff(x) > 0)):
            raise ValueError(f"count prior: need 1 to {COUNT_PRIOR_KNOTS} finite counts at strictly "
                             f"increasing speeds, got counts {y.tolist()} at {x.tolist()}")
        if not self.use_speed and y.size > 1:
            raise ValueError("count prior: a network without use_speed takes one count, not a speed table")
        q = np.clip(y / self.max_points, 1e-4, 1 - 1e-4)
        logit = np.log(q / (1 - q))
        nn.init.zeros_(self.count_head.weight)
        if y.size == 1:  # in the head's bias: the same arithmetic as before the speed prior existed
            self.count_head.bias.fill_(float(logit[0]))
            self.count_prior_speed_mps.copy_(torch.arange(COUNT_PRIOR_KNOTS, dtype=torch.float32))
            self.count_prior_logit.zero_()
            return
        pad = COUNT_PRIOR_KNOTS - y.size  # repeat the last value beyond the last knot: flat there too
        self.count_prior_speed_mps.copy_(torch.from_numpy(np.concatenate([x, x[-1] + 1.0 + np.arange(pad)])).float())
        self.count_prior_logit.copy_(torch.from_numpy(np.concatenate([logit, np.full(pad, logit[-1])])).float())
        nn.init.zeros_(self.count_head.bias)

    @torch.no_grad()
    def set_prior_mix(self, w: float) -> None:
        """Mix the share ``w`` in [0, 1] of the prior into the output map (no effect without
        use_prior)."""
        if not 0.0 <= float(w) <= 1.0:
            raise ValueError(f"prior mix: w must lie in [0, 1], got {w}")
        self.prior_mix.fill_(float(w))

    @torch.no_grad()
    def set_prior(self, prob_map: np.ndarray, floor: float = 1e-6) -> None:
        """Use log(prob_map) (H, W), e.g. the mean training heatmap, as the map's prior logits."""
        p = np.asarray(prob_map, dtype=np.float64)
        if p.shape != self.out_hw:
            raise ValueError(f"prior map: expected shape {self.out_hw}, got {p.shape}")
        p = p / p.sum()
        self.prior_logits.copy_(torch.from_numpy(np.log((1 - floor) * p + floor / p.size)).float())


def mix_with_prior(log_map: Tensor, prior_logits: Tensor, w: Tensor | float) -> Tensor:
    """log((1 - w) exp(log_map) + w prior) (B, H, W): the maps (log-probabilities) mixed with the
    prior (H, W) logits' distribution, share w in [0, 1]."""
    w = torch.as_tensor(w, dtype=log_map.dtype, device=log_map.device)
    log_prior = F.log_softmax(prior_logits.reshape(-1).to(log_map.dtype), dim=0).reshape(prior_logits.shape)
    return torch.logaddexp(log_map + torch.log1p(-w), log_prior + torch.log(w))


def _speed_input(speed_mps: Tensor | None, b: int, dtype: torch.dtype, switch: str) -> Tensor:
    """(B, 1) network input from the ego speed (B,) m/s; ValueError naming ``switch`` when absent."""
    if speed_mps is None:
        raise ValueError(f"DisNet was built with {switch}=True: forward needs speed_mps (B,)")
    return speed_mps.reshape(b, 1).to(dtype) / SPEED_SCALE_MPS


def _scale_grad(x: Tensor, scale: float) -> Tensor:
    """``x`` in the forward pass; the gradient flowing back through it is multiplied by ``scale``."""
    return x if scale == 1.0 else x * scale + x.detach() * (1.0 - scale)


def _up(in_ch: int, out_ch: int) -> nn.Sequential:
    """Transpose conv doubling H and W exactly, then BN + ReLU."""
    return nn.Sequential(nn.ConvTranspose2d(in_ch, out_ch, 4, stride=2, padding=1, bias=False),
                         nn.BatchNorm2d(out_ch), nn.ReLU(inplace=True))


def disnet_kwargs(cfg) -> dict:
    """Constructor arguments of DisNet from a Config (disnet.*, radar.max_points, camera.working_size)."""
    w, h = cfg.camera.working_size
    return {"width": cfg.disnet.width, "use_speed": cfg.disnet.use_speed,
            "max_points": cfg.radar.max_points, "out_hw": (h, w), "use_prior": cfg.disnet.prior,
            "speed_map": cfg.disnet.speed_map, "skips": cfg.disnet.skips}


def build_disnet(cfg, load_backbone: bool = True) -> DisNet:
    """DisNet from a Config; loads cfg.disnet.backbone_weights (torchvision ResNet-18) when set."""
    kw = disnet_kwargs(cfg)
    weights = cfg.disnet.backbone_weights if load_backbone else ""
    backbone = resnet18_backbone(weights or None, width=kw["width"])
    return DisNet(backbone=backbone, **kw)
