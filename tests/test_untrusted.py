"""Untrusted files never run code: no unpickling or eval anywhere in the project source, checkpoints
are safetensors (a pickle disguised as a checkpoint is refused without being executed), configuration
is parsed with tomllib and --set values are data, index paths stay inside the data root.

Index entries that point outside the data root are rejected by the readers
(pipeline/readers/base.py ``inside_root``); tests/test_bad_input.py::test_index_entry_outside_dataset_root
covers it, and a direct check is below.
"""

from __future__ import annotations

import ast
import json
import pickle
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline import checkpoint as ckpt
from pipeline.config import load_config, parse_set_options
from pipeline.errors import CacheError, ConfigError, ReaderError

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("pipeline", "stages")

FORBIDDEN_CALLS = {
    "pickle.load": "unpickling runs code", "pickle.loads": "unpickling runs code",
    "pickle.Unpickler": "unpickling runs code", "_pickle.load": "unpickling runs code",
    "_pickle.loads": "unpickling runs code", "dill.load": "unpickling runs code",
    "dill.loads": "unpickling runs code", "cloudpickle.load": "unpickling runs code",
    "cloudpickle.loads": "unpickling runs code", "joblib.load": "unpickling runs code",
    "pandas.read_pickle": "unpickling runs code", "torch.save": "checkpoints must be safetensors",
    "marshal.load": "marshal runs code", "marshal.loads": "marshal runs code", "shelve.open": "shelve unpickles",
    "yaml.unsafe_load": "unsafe YAML", "yaml.full_load": "unsafe YAML", "yaml.load_all": "unsafe YAML",
    "eval": "eval of text", "exec": "exec of text", "builtins.eval": "eval of text",
    "builtins.exec": "exec of text", "__import__": "dynamic import by name",
}
FORBIDDEN_MODULES = {"marshal", "shelve", "dill", "cloudpickle"}


def _aliases(tree: ast.AST) -> dict[str, str]:
    """Local name -> dotted origin for every import in the module (any scope)."""
    out: dict[str, str] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                out[a.asname or a.name.split(".")[0]] = a.name if a.asname else a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.module:
            for a in node.names:
                out[a.asname or a.name] = f"{node.module}.{a.name}"
    return out


def _dotted(node: ast.AST, aliases: dict[str, str]) -> str | None:
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    head = aliases.get(node.id, node.id)
    return ".".join([head, *reversed(parts)])


def _keyword(call: ast.Call, name: str) -> ast.expr | None:
    return next((k.value for k in call.keywords if k.arg == name), None)


def _is_const(node: ast.expr | None, value: object) -> bool:
    return isinstance(node, ast.Constant) and node.value is value


def _yaml_loader_safe(call: ast.Call, aliases: dict[str, str]) -> bool:
    loader = _keyword(call, "Loader") or (call.args[1] if len(call.args) > 1 else None)
    name = _dotted(loader, aliases) if loader is not None else None
    return bool(name) and name.rsplit(".", 1)[-1] in ("SafeLoader", "CSafeLoader", "BaseLoader")


def scan_source(text: str, filename: str = "<source>") -> list[str]:
    """Problems found in one module: unsafe deserialisation and code evaluation (see module doc)."""
    tree = ast.parse(text, filename)
    aliases = _aliases(tree)
    problems = []
    for node in ast.walk(tree):
        where = f"{filename}:{getattr(node, 'lineno', '?')}"
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            mods = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            for m in mods:
                if m.split(".")[0] in FORBIDDEN_MODULES:
                    problems.append(f"{where}: imports {m}")
        if not isinstance(node, ast.Call):
            continue
        name = _dotted(node.func, aliases)
        if name is None:
            continue
        if name in FORBIDDEN_CALLS:
            problems.append(f"{where}: {name}() ({FORBIDDEN_CALLS[name]})")
        elif name == "torch.load" and not _is_const(_keyword(node, "weights_only"), True):
            problems.append(f"{where}: torch.load without weights_only=True")
        elif name in ("numpy.load", "numpy.lib.npyio.load"):
            flag = _keyword(node, "allow_pickle")
            if flag is not None and not _is_const(flag, False):
                problems.append(f"{where}: numpy.load with allow_pickle not False")
        elif name == "yaml.load" and not _yaml_loader_safe(node, aliases):
            problems.append(f"{where}: yaml.load without SafeLoader")
    return problems


def project_files() -> list[Path]:
    return sorted(p for d in SCANNED for p in (ROOT / d).rglob("*.py"))


def test_project_source_has_no_unsafe_deserialisation_or_eval():
    files = project_files()
    assert len(files) > 20  # the scan really sees the project
    problems = [p for f in files for p in scan_source(f.read_text(), str(f.relative_to(ROOT)))]
    assert problems == []


@pytest.mark.parametrize("source", [
    "import pickle\npickle.load(open('x', 'rb'))",
    "import pickle as pk\npk.loads(b'')",
    "from pickle import loads\nloads(b'')",
    "import torch\ntorch.load('w.pt')",
    "import torch\ntorch.load('w.pt', weights_only=False)",
    "from torch import load\nload('w.pt', map_location='cpu')",
    "import numpy as np\nnp.load('a.npy', allow_pickle=True)",
    "import numpy\nnumpy.load('a.npy', allow_pickle=flag)",
    "eval('1 + 1')",
    "exec(code)",
    "import yaml\nyaml.load(text)",
    "import yaml\nyaml.load(text, Loader=yaml.Loader)",
    "import yaml\nyaml.unsafe_load(text)",
    "import marshal",
    "import shelve\nshelve.open('db')",
    "import torch\ntorch.save(model.state_dict(), 'w.pt')",
])
def test_scanner_flags_unsafe_code(source):
    assert scan_source(source), source


@pytest.mark.parametrize("source", [
    "import torch\ntorch.load('w.pt', weights_only=True)",
    "import numpy as np\nnp.load('a.npy')\nnp.load('b.npy', allow_pickle=False)",
    "import yaml\nyaml.safe_load(text)\nyaml.load(text, Loader=yaml.SafeLoader)",
    "import ast\nast.literal_eval('[1, 2]')",
    "import tomllib\ntomllib.loads('a = 1')",
    "model.eval()",  # nn.Module.eval is a method, not the builtin
    "import json\njson.loads('{}')",
])
def test_scanner_accepts_safe_code(source):
    assert scan_source(source) == []


# ------------------------------------------------------------------------------- checkpoints


def test_checkpoint_file_is_plain_safetensors(tmp_path):
    """A saved checkpoint is a safetensors file: 8-byte header length, JSON header, raw tensor
    bytes; no pickle or zip (torch.save) container anywhere."""
    path = tmp_path / "net_last.safetensors"
    tensors = {"model.w": torch.arange(6, dtype=torch.float32).reshape(2, 3), "rng.torch": torch.get_rng_state()}
    ckpt.save_checkpoint(path, tensors, {"epoch": 3})
    raw = path.read_bytes()
    (n,) = struct.unpack("<Q", raw[:8])
    header = json.loads(raw[8:8 + n])
    assert set(header) == {"__metadata__", "model.w", "rng.torch"}
    assert header["model.w"]["dtype"] == "F32" and header["model.w"]["shape"] == [2, 3]
    assert not raw.startswith(b"PK") and b"\x80\x04" not in raw[:8 + n]
    loaded, meta = ckpt.load_checkpoint(path)
    assert torch.equal(loaded["model.w"], tensors["model.w"]) and meta["epoch"] == 3
    assert json.loads(path.with_suffix(".json").read_text())["epoch"] == 3


class _Payload:
    """Unpickling this creates the file named in ``marker`` (a stand-in for arbitrary code)."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (Path(self.marker),))


@pytest.mark.parametrize("as_torch_zip", [False, True])
def test_pickle_disguised_as_checkpoint_is_refused_without_running(tmp_path, as_torch_zip):
    marker = tmp_path / "PWNED"
    path = tmp_path / "disnet_last.safetensors"
    if as_torch_zip:
        torch.save({"model.w": _Payload(str(marker))}, path)
    else:
        path.write_bytes(pickle.dumps(_Payload(str(marker))))
    for load in (ckpt.load_checkpoint, ckpt.read_meta):
        with pytest.raises(CacheError, match="unreadable checkpoint"):
            load(path)
    assert not marker.exists()


def test_train_stage_outputs_are_safetensors_only():
    """The train stage writes checkpoints, and inference reads them, through pipeline.checkpoint
    (safetensors) only."""
    training, inference = ((ROOT / "pipeline" / name).read_text() for name in ("training.py", "inference.py"))
    assert "save_checkpoint" in training and "load_checkpoint" in inference
    for text in (training, inference):
        assert "torch.save" not in text and "torch.load" not in text
        assert scan_source(text) == []


# ---------------------------------------------------------------------- configuration, paths


def test_configuration_is_toml_data_never_code(tmp_path):
    config_src = (ROOT / "pipeline" / "config.py").read_text()
    calls = {_dotted(n.func, _aliases(ast.parse(config_src))) for n in ast.walk(ast.parse(config_src))
             if isinstance(n, ast.Call)}
    assert {"tomllib.loads", "tomllib.load"} & calls
    marker = tmp_path / "PWNED"
    payload = f"__import__('pathlib').Path({str(marker)!r}).touch()"
    with pytest.raises(ConfigError):
        load_config("synthetic", parse_set_options([f"train.epochs={payload}"]), environ={})
    cfg = load_config("synthetic", parse_set_options([f"train.nets={payload}"]), environ={})
    assert cfg.train.nets == payload  # kept as text
    with pytest.raises(ConfigError):
        load_config("synthetic", {}, environ={"PIPELINE__TRAIN__LR": payload})
    assert not marker.exists()


@pytest.mark.parametrize("shared", [False, True], ids=["alone", "resolved-folders-shared"])
def test_index_paths_cannot_leave_the_data_root(tmp_path, shared):
    """Also with the resolved folders kept across calls (an index's entries): a file that is a
    link, or a folder that became one, is still followed."""
    from pipeline.readers.base import inside_root

    resolved = {} if shared else None

    def check(relative):
        return inside_root(root, relative, "000001", root / "index.json", resolved)

    root = tmp_path / "data"
    (root / "radar").mkdir(parents=True)
    (tmp_path / "secret.txt").write_text("x")
    assert check("radar/000001.txt") == root / "radar" / "000001.txt"
    for bad in ("../secret.txt", "radar/../../secret.txt", "radar/../..", str(tmp_path / "secret.txt")):
        with pytest.raises(ReaderError, match="outside the dataset root"):
            check(bad)
    (root / "link").symlink_to(tmp_path)
    for bad in ("link/secret.txt", "link/missing.txt"):  # a missing file: its folder still decides
        with pytest.raises(ReaderError, match="outside the dataset root"):
            check(bad)
    assert check("radar/missing.txt") == root / "radar" / "missing.txt"  # a partial download's index
    (root / "radar" / "out.txt").symlink_to(tmp_path / "secret.txt")  # in a folder resolved before
    for bad in ("radar/out.txt", "missing/../radar/out.txt", "radar/missing/../out.txt"):
        with pytest.raises(ReaderError, match="outside the dataset root"):
            check(bad)
    (root / "radar" / "loop.txt").symlink_to(root / "radar" / "loop.txt")   # a file linked to itself
    with pytest.raises(ReaderError, match="cannot be resolved"):
        check("radar/loop.txt")


def test_npy_written_by_stages_loads_without_pickle(tmp_path):
    """Arrays the stages save with numpy are plain (np.load's default allow_pickle=False works)."""
    path = tmp_path / "mean_heatmap.npy"
    np.save(path, np.ones((2, 3), np.float32), allow_pickle=False)
    assert np.load(path).shape == (2, 3)
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError):
        np.load(tmp_path / "obj.npy")
