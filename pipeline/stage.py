"""Declarations of pipeline stages: what a stage reads, writes and which configuration it uses.

A stage is data (in the spirit of rechunker / pangeo-forge recipes): the executor creates the
declared output arrays before any compute, then calls the stage's pure per-frame function and
writes the result into the frame's own chunks. Stage modules in ``stages/`` build these objects;
this library never imports ``stages``.

Two kinds:
- ``FrameStage``: maps a pure function over frames; outputs are zarr arrays with one chunk per
  frame under ``<cache>/<dataset>/<stage>.zarr``. A dataset stage's per-frame work can be one too
  (``part_of``), so that it is resumable and runs on the executor.
- ``DatasetStage``: one function over the whole dataset (training, evaluation); writes files into
  ``<cache>/<dataset>/<stage>/``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

if TYPE_CHECKING:
    from pipeline.config import Config


@dataclass(frozen=True)
class ArraySpec:
    """One per-frame output array.

    ``shape`` is the per-frame shape (the frame axis is prepended), either a tuple or a function of
    the configuration. ``ragged``: the first per-frame axis is a capacity; the frame function
    returns fewer rows, the executor pads with ``fill`` and writes ``<name>_count`` (int32).
    ``finite``: every value the frame function returns must be finite; a NaN or inf fails the frame
    (naming the array and the first bad value's index) instead of reaching the stages after it and the export
    (a damaged checkpoint's NaN weight gave NaN RSS without a word).
    """

    name: str
    shape: tuple[int, ...] | Callable[["Config"], tuple[int, ...]]
    dtype: str
    units: str
    fill: Any = 0
    ragged: bool = False
    finite: bool = False

    def frame_shape(self, cfg: "Config") -> tuple[int, ...]:
        """Per-frame shape under ``cfg``."""
        return tuple(self.shape(cfg) if callable(self.shape) else self.shape)


@dataclass(frozen=True)
class FrameStage:
    """A stage that maps ``process(inputs, cfg) -> {array name: per-frame array}`` over frames.

    ``select(cfg, dataset_inputs) -> bool mask (F,)`` limits the frames the stage works on (for
    example one split); unselected frames are reported as excluded.
    ``check(cfg)``: ConfigError for settings the stage cannot run with; the runner calls it for
    every stage of a run before any output is touched.
    ``part_of``: the dataset stage whose per-frame part this is (evaluate's per-frame metrics,
    which the report then reads): ``--force`` on that stage recomputes this one too.
    ``summarise(store, cfg) -> lines``: what a run that processed frames prints under the stage's
    line (e.g. points the stage dropped over all its finished frames); none when it returns none.
    ``ready(dataset_inputs, cfg)``: PipelineError when its upstream outputs cannot serve it (e.g.
    a checkpoint unreadable); called, with the upstream stages up to date, before its own output
    is recreated or any frame of it recomputed.
    """

    name: str
    upstream: tuple[str, ...]
    config_keys: tuple[str, ...]
    outputs: Callable[["Config"], tuple[ArraySpec, ...]]
    process: Callable[..., dict[str, np.ndarray]]
    version: int = 1
    select: Callable[..., np.ndarray] | None = None
    doc: str = ""
    check: Callable[["Config"], None] | None = None
    part_of: str = ""
    summarise: Callable[..., list[str]] | None = None
    ready: Callable[..., None] | None = None


@dataclass(frozen=True)
class DatasetStage:
    """A stage run once over the whole dataset: ``run(inputs, cfg, out) -> summary dict``;
    ``check`` as for FrameStage. ``extra_fingerprint(cfg, env)``: what else the output depends on
    (e.g. another dataset's train stage, for train.nets_from), a string in its fingerprint ('' adds
    nothing). ``local_files``: see the field."""

    name: str
    upstream: tuple[str, ...]
    config_keys: tuple[str, ...]
    run: Callable[..., dict[str, Any]]
    version: int = 1
    doc: str = ""
    extra_fingerprint: Callable[["Config", Any], str] | None = field(default=None)
    check: Callable[["Config"], None] | None = None
    local_files: bool = False
    """Writes its output folder with local file APIs (checkpoints, reports): on a remote (fsspec)
    cache it writes into a local staging folder (run.staging_dir) that is uploaded when it finishes."""
    resumes: bool = False
    """Goes on from what an interrupted run of it saved in its folder (train's per-epoch
    checkpoints). Otherwise the folder is emptied before the stage runs, so that its files all come
    from one run, whatever an earlier run left when it failed or was killed."""
    resume_point: Callable[[Any, "Config", Any], str | None] | None = None
    """For a stage that ``resumes``: ``(inputs, cfg, folder) -> words`` saying what an unfinished
    run left in ``folder`` that the next run goes on from (None: nothing), for `pipeline status`."""


Stage = FrameStage | DatasetStage
