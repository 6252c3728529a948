"""Dataset readers: one module per dataset, all returning pipeline.frame.FrameRecord.

``get_reader(cfg, data_root)`` picks the reader named by ``cfg.dataset.reader``:
vod, synthetic (VoD layout of the generated world), astyx, astyx_demo, msc, kitti.
Reader options (e.g. VoD ``radar_folder="radar_5frames"``, MSC ``pair_tolerance_s``) are passed
as keyword arguments.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from pipeline.config import Config
from pipeline.errors import ConfigError
from pipeline.readers.base import Reader

_READERS = {
    "vod": ("pipeline.readers.vod", "VodReader"),
    "synthetic": ("pipeline.readers.vod", "SyntheticReader"),
    "astyx": ("pipeline.readers.astyx", "AstyxReader"),
    "astyx_demo": ("pipeline.readers.astyx", "AstyxDemoReader"),
    "msc": ("pipeline.readers.msc", "MscReader"),
    "kitti": ("pipeline.readers.kitti", "KittiReader"),
}

__all__ = ["Reader", "get_reader", "reader_class", "reader_names"]


def reader_names() -> list[str]:
    """Names accepted by ``dataset.reader``."""
    return sorted(_READERS)


def reader_class(cfg: Config) -> type[Reader]:
    """The class of the reader named by ``cfg.dataset.reader``; ConfigError for an unknown name."""
    name = cfg.dataset.reader
    if name not in _READERS:
        raise ConfigError(f"unknown dataset.reader '{name}' (known: {', '.join(reader_names())})")
    module_name, class_name = _READERS[name]
    return getattr(importlib.import_module(module_name), class_name)


def get_reader(cfg: Config, data_root: str | Path, **options: object) -> Reader:
    """The reader of ``cfg.dataset.reader`` over ``data_root``; ConfigError for an unknown name."""
    name = cfg.dataset.reader
    cls = reader_class(cfg)
    if name == "msc":
        return cls.open(cfg, data_root, **options)
    return cls(cfg, data_root, **options)
