"""ResNet-18 feature extractor (conv1 ... layer4, no classifier) with torchvision's parameter names.

The module tree mirrors ``torchvision.models.resnet18`` exactly (``conv1``, ``bn1``, ``layer1.0.conv1``,
``layer2.0.downsample.0`` ...), so a torchvision ResNet-18 state dict loads into it; its ``fc.*``
entries are ignored. ``width`` scales every channel count (64 = the standard network, whose
feature map has 512 channels); only width 64 is compatible with torchvision weights.

Weights are loaded by the builder :func:`resnet18_backbone`, never by the constructor.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import torch
from torch import Tensor, nn

from pipeline.errors import ConfigError, first_sentence, sigint_deferred


class BasicBlock(nn.Module):
    """Two 3x3 convolutions with a residual connection (torchvision's BasicBlock)."""

    def __init__(self, in_ch: int, out_ch: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_ch, out_ch, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(out_ch)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(out_ch, out_ch, 3, stride=1, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(out_ch)
        self.downsample: nn.Module | None = None
        if stride != 1 or in_ch != out_ch:
            self.downsample = nn.Sequential(
                nn.Conv2d(in_ch, out_ch, 1, stride=stride, bias=False), nn.BatchNorm2d(out_ch))

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class ResNet18Backbone(nn.Module):
    """ResNet-18 trunk: image (B, 3, H, W) -> feature map (B, 8*width, ceil(H/32), ceil(W/32)).

    The input is expected already normalised (ImageNet mean/std); the caller does it.
    """

    def __init__(self, width: int = 64) -> None:
        super().__init__()
        if width < 1:
            raise ValueError(f"ResNet-18 width must be >= 1, got {width}")
        self.width = width
        self.out_channels = 8 * width
        self.conv1 = nn.Conv2d(3, width, 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        self.layer1 = _stage(width, width, stride=1)
        self.layer2 = _stage(width, 2 * width, stride=2)
        self.layer3 = _stage(2 * width, 4 * width, stride=2)
        self.layer4 = _stage(4 * width, 8 * width, stride=2)
        _init_like_torchvision(self)

    def forward(self, x: Tensor) -> Tensor:
        return self.pyramid(x)[-1]

    def pyramid(self, x: Tensor) -> list[Tensor]:
        """Outputs of layer1 ... layer4: (B, w, H/4, W/4), (B, 2w, H/8, W/8), (B, 4w, H/16, W/16),
        (B, 8w, H/32, W/32) (sizes rounded up)."""
        c1 = self.layer1(self.maxpool(self.relu(self.bn1(self.conv1(x)))))
        c2 = self.layer2(c1)
        c3 = self.layer3(c2)
        return [c1, c2, c3, self.layer4(c3)]

    def load_torchvision_state_dict(self, state: dict[str, Tensor], source: str = "state dict") -> None:
        """Load a torchvision ResNet-18 state dict; ``fc.*`` is dropped, every other key must match."""
        trunk = {k: v for k, v in state.items() if not k.startswith("fc.")}
        own = self.state_dict()
        missing = sorted(set(own) - set(trunk))
        unexpected = sorted(set(trunk) - set(own))
        if missing or unexpected:
            raise ConfigError(f"{source}: not a ResNet-18 state dict of width {self.width} "
                              f"(missing {missing[:5]}, unexpected {unexpected[:5]})")
        bad = [k for k, v in trunk.items() if tuple(v.shape) != tuple(own[k].shape)]
        if bad:
            raise ConfigError(f"{source}: shape mismatch for {bad[:5]} (model width {self.width}; "
                              "torchvision weights need disnet.width = 64)")
        self.load_state_dict(trunk, strict=True)


def _stage(in_ch: int, out_ch: int, stride: int) -> nn.Sequential:
    return nn.Sequential(BasicBlock(in_ch, out_ch, stride), BasicBlock(out_ch, out_ch, 1))


def _init_like_torchvision(model: nn.Module) -> None:
    for m in model.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)


WEIGHTS_FORMATS = ".safetensors (safetensors) or .pth / .pt (torch.save of a state dict)"
"""The weights files :func:`load_state_dict_file` reads, as its messages name them."""

_TORCH_LEGACY_MAGIC = (0x1950A86A20F9469CFC6C).to_bytes(10, "little")
"""The magic number that opens a torch.save file of the format before torch 1.6 (pickled)."""


def load_state_dict_file(path: str | Path) -> dict[str, Tensor]:
    """Read a state dict from ``.safetensors`` (safetensors) or ``.pth``/``.pt`` (torch.load with
    ``weights_only=True``, which refuses arbitrary pickled objects).

    ConfigError naming the file for a missing file, another format, a file that cannot be read as
    its suffix says (damaged, truncated, or of another format) and one holding more than tensors.
    A Ctrl-C during the read stops it as KeyboardInterrupt once the read is done (:func:`sigint_deferred`).
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: weights file not found")
    suffix = path.suffix.lower()
    if suffix == ".safetensors":
        from safetensors import SafetensorError
        from safetensors.torch import load_file
        try:
            with sigint_deferred():  # torch turns a KeyboardInterrupt while it makes the tensors into ValueError
                return load_file(str(path))
        except (SafetensorError, OSError) as exc:
            raise _unreadable(path, "a safetensors file", first_sentence(exc)) from None
    if suffix in (".pth", ".pt"):
        return _load_torch_state_dict(path)
    raise ConfigError(f"{path}: unsupported weights format '{suffix}' (use .safetensors, .pth or .pt)")


def _load_torch_state_dict(path: Path) -> dict[str, Tensor]:
    """A ``.pth``/``.pt`` file's state dict (:func:`load_state_dict_file`)."""
    try:
        with sigint_deferred():
            state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        if not _is_torch_save_file(path):  # text or other bytes: torch's advice (weights_only=False) is wrong
            raise _unreadable(path, "a torch.save file", _unpickler_reason(exc)) from None
        raise ConfigError(f"{path}: refused to load (not a plain tensor state dict: {_unpickler_reason(exc)}); "
                          "save the model's state_dict() instead, or convert it to .safetensors") from None
    except Exception as exc:  # noqa: BLE001 - a damaged file fails anywhere in torch's reader (zip, unpickler)
        raise _unreadable(path, "a torch.save file", first_sentence(exc)) from None
    if not isinstance(state, dict):
        raise ConfigError(f"{path}: expected a state dict, found {type(state).__name__}")
    return state


def _is_torch_save_file(path: Path) -> bool:
    """Whether ``path`` is in one of torch.save's formats: a zip archive (torch >= 1.6) or a pickle
    opened by torch's magic number (``_use_new_zipfile_serialization=False``)."""
    import zipfile
    if zipfile.is_zipfile(path):
        return True
    with open(path, "rb") as f:
        return _TORCH_LEGACY_MAGIC in f.read(32)


def _unpickler_reason(exc: BaseException) -> str:
    """The reason in torch's weights-only refusal (e.g. 'Unsupported global: GLOBAL m.X'), without
    its advice to load the file unsafely."""
    text = str(exc)
    _, found, after = text.partition("WeightsUnpickler error:")
    lines = [line.strip() for line in (after if found else text).splitlines() if line.strip()]
    return lines[0].split(" was not an allowed global")[0] if lines else type(exc).__name__


def _unreadable(path: Path, what: str, detail: str) -> ConfigError:
    """The one-line error for a weights file that cannot be read as ``what`` (``detail``: the reader's
    own reason)."""
    return ConfigError(f"{path}: cannot be read as {what} ({detail}): the file is damaged (truncated or "
                       f"overwritten) or not a weights file; weights files are {WEIGHTS_FORMATS}: "
                       "save or download it again")


def resnet18_backbone(weights_path: str | Path | None = None, width: int = 64) -> ResNet18Backbone:
    """Build a ResNet-18 trunk; load a local torchvision-format state dict when a path is given."""
    model = ResNet18Backbone(width)
    if weights_path:
        model.load_torchvision_state_dict(load_state_dict_file(weights_path), source=str(weights_path))
    return model
