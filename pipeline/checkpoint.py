"""Training checkpoints without pickle: tensors in safetensors, everything else in JSON.

One checkpoint is ONE ``.safetensors`` file: model tensors (``model.<name>``), optimizer state
tensors (``optim.<param id>.<key>``) and RNG states (``rng.torch``, ``rng.cuda.<i>`` as uint8), with
the non-tensor state (epoch, fingerprint, curves, optimizer param groups, numpy bit-generator state)
as JSON in the file's metadata under ``"meta"``. The file is written to a temporary name and
renamed into place, so a kill at any instant leaves either the old or the new checkpoint, never a
mix; its data are flushed to the disk before the rename, so a power loss does too. A JSON sidecar (same stem, ``.json``) repeats the metadata for people and tools; loading
reads only the safetensors file.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file
from torch import Tensor, nn

from pipeline.errors import CacheError, cache_error, sigint_deferred
from pipeline.fileio import FILE_MODE, atomic_path, write_atomic

FORMAT = "pipeline-checkpoint/1"


def save_checkpoint(path: str | Path, tensors: dict[str, Tensor], meta: dict[str, Any]) -> None:
    """Atomically write ``tensors`` + ``meta`` (JSON-able) to ``path``, then the JSON sidecar."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"format": FORMAT, **meta}
    flat = {k: v.detach().to("cpu").contiguous().clone() for k, v in tensors.items()}
    with atomic_path(path, durable=True) as tmp:  # the resume point of hours of training: survives a power loss
        try:
            save_file(flat, str(tmp), metadata={"meta": json.dumps(meta)})
        except SafetensorError as exc:  # its I/O errors are not OSErrors: the errno is in the message
            code = re.search(r"\(os error (\d+)\)", str(exc))
            if code is None:
                raise CacheError(f"writing the checkpoint {path}: {exc}") from None
            raise cache_error(OSError(int(code[1]), os.strerror(int(code[1]))), f"writing the checkpoint {path}") from None
        os.chmod(tmp, FILE_MODE)  # safetensors creates its own file (0600): the mode open() would give
    write_json_atomic(path.with_suffix(".json"), meta)


def load_checkpoint(path: str | Path, prefix: str = "") -> tuple[dict[str, Tensor], dict[str, Any]]:
    """Read a checkpoint: (tensors whose key starts with ``prefix``, metadata dict). A Ctrl-C
    during the read stops it as KeyboardInterrupt once the read is done (:func:`sigint_deferred`),
    never as an unreadable checkpoint."""
    path = Path(path)
    try:
        with sigint_deferred(), safe_open(str(path), framework="pt", device="cpu") as f:
            meta = json.loads((f.metadata() or {}).get("meta", "{}"))
            tensors = {k: f.get_tensor(k) for k in f.keys() if k.startswith(prefix)}
    except FileNotFoundError:
        raise CacheError(f"{path}: checkpoint not found") from None
    except Exception as exc:  # safetensors raises its own error types for corrupt headers
        raise CacheError(f"{path}: unreadable checkpoint ({exc})") from None
    if meta.get("format") != FORMAT:
        raise CacheError(f"{path}: not a pipeline checkpoint (format {meta.get('format')!r})")
    check_finite_weights(path, tensors)
    return tensors, meta


WEIGHTS = (".weight", ".bias", ".running_mean", ".running_var")
"""Name endings of a net's weights and batch norm statistics: never NaN or inf in a checkpoint.
Other buffers may be (PlaceNet's and RSS-Net's training ranges hold NaN where not known)."""


def check_finite_weights(path: str | Path, tensors: dict[str, Tensor]) -> None:
    """CacheError naming the checkpoint ``path`` and the tensor when a weight (``model.*`` ending in
    WEIGHTS) holds a NaN or inf: the file is damaged, since training never saves one (it stops on
    a non-finite loss). Such an RSS-Net gave NaN RSS to every synthesized point without a word."""
    for name, t in tensors.items():
        if name.startswith("model.") and name.endswith(WEIGHTS) and t.is_floating_point():
            bad = int((~torch.isfinite(t)).sum())
            if bad:
                raise CacheError(f"{path}: {bad} of {t.numel()} values of {name[len('model.'):]} are not finite (NaN "
                                 f"or inf): the checkpoint is damaged; retrain it: `pipeline run train --force` (with "
                                 f"the same --dataset and --cache)")


def read_meta(path: str | Path) -> dict[str, Any]:
    """Metadata of a checkpoint without reading its tensors (a Ctrl-C as for :func:`load_checkpoint`)."""
    path = Path(path)
    try:
        with sigint_deferred(), safe_open(str(path), framework="pt", device="cpu") as f:
            return json.loads((f.metadata() or {}).get("meta", "{}"))
    except Exception as exc:
        raise CacheError(f"{path}: unreadable checkpoint ({exc})") from None


def write_json_atomic(path: str | Path, obj: Any) -> None:
    """Write JSON to a temporary file and rename it into place."""
    write_atomic(path, json.dumps(obj, indent=1))


def model_tensors(model: nn.Module) -> dict[str, Tensor]:
    """``model.state_dict()`` under the ``model.`` prefix."""
    return {f"model.{k}": v for k, v in model.state_dict().items()}


def strip_prefix(tensors: dict[str, Tensor], prefix: str) -> dict[str, Tensor]:
    """Keys starting with ``prefix``, with the prefix removed."""
    return {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}


def flatten_optimizer(optimizer: torch.optim.Optimizer) -> tuple[dict[str, Tensor], dict[str, Any]]:
    """Optimizer state dict -> (tensors ``optim.<pid>.<key>``, JSON part: param groups + scalars)."""
    sd = optimizer.state_dict()
    tensors: dict[str, Tensor] = {}
    scalars: dict[str, dict[str, Any]] = {}
    for pid, state in sd["state"].items():
        for key, value in state.items():
            if isinstance(value, Tensor):
                tensors[f"optim.{pid}.{key}"] = value
            else:
                scalars.setdefault(str(pid), {})[key] = value
    groups = [{k: (list(v) if isinstance(v, tuple) else v) for k, v in g.items()} for g in sd["param_groups"]]
    return tensors, {"param_groups": groups, "scalars": scalars}


def unflatten_optimizer(tensors: dict[str, Tensor], json_part: dict[str, Any]) -> dict[str, Any]:
    """Inverse of :func:`flatten_optimizer`: an ``optimizer.load_state_dict`` argument."""
    state: dict[int, dict[str, Any]] = {}
    for key, value in strip_prefix(tensors, "optim.").items():
        pid, name = key.split(".", 1)
        state.setdefault(int(pid), {})[name] = value
    for pid, values in json_part["scalars"].items():
        state.setdefault(int(pid), {}).update(values)
    groups = [{k: (tuple(v) if isinstance(v, list) and k != "params" else v) for k, v in g.items()}
              for g in json_part["param_groups"]]
    return {"state": state, "param_groups": groups}


def rng_tensors() -> dict[str, Tensor]:
    """torch CPU (and CUDA, when present) generator states as uint8 tensors."""
    out = {"rng.torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        for i, s in enumerate(torch.cuda.get_rng_state_all()):
            out[f"rng.cuda.{i}"] = s
    return out


def restore_rng(tensors: dict[str, Tensor]) -> None:
    """Set the torch generators from :func:`rng_tensors` output (CUDA states only where present)."""
    torch.set_rng_state(tensors["rng.torch"])
    cuda = [tensors[k] for k in sorted(k for k in tensors if k.startswith("rng.cuda."))]
    if cuda and torch.cuda.is_available() and len(cuda) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(cuda)


def numpy_rng_state(rng: np.random.Generator) -> dict[str, Any]:
    """JSON-able state of a numpy Generator (Python ints keep 128-bit values exactly)."""
    return rng.bit_generator.state


def numpy_rng_from_state(state: dict[str, Any]) -> np.random.Generator:
    """A numpy Generator in the saved state."""
    bit_gen = getattr(np.random, state["bit_generator"])()
    bit_gen.state = state
    return np.random.Generator(bit_gen)
