"""The data a cache was made from, and moving it.

The first stage's output records the data root it was made from (in the fingerprints, as
absolute_root gives it). A run naming another data root stops (made_from, other_root_message),
unless the data moved: the other place lists the same frames under the same settings
(moved_from), and relocate_cache, after computing some frames there and finding them as
cached, gives every output the fingerprint it has at the new place. default_data_root: the
data root when a command gives none.

The functions take the Pipeline, whose fingerprints say what is current; pipeline.runner
imports this module, so here the Pipeline is named for type checking only.
"""

from __future__ import annotations

import contextlib
import os
import shlex
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.cache import DONE
from pipeline.cachefs import command_options
from pipeline.errors import MetadataError, PipelineError
from pipeline.executor import FrameInputs
from pipeline.lock import rewriting, stage_lock
from pipeline.stage import FrameStage
from pipeline.staleness import Staleness, options_text, sets_to_restore

if TYPE_CHECKING:
    from pipeline.runner import Pipeline

FIRST_STAGE = "calibrate"
"""The stage that reads the dataset: its fingerprint holds the data root and the frames, and its
output records the data root (made_from)."""


def made_from(pipe: Pipeline) -> str | None:
    """The data root the first stage's output was made from, when this run's is another (which
    would make every stage recompute); else None, also when there is no output or it records none."""
    store = pipe.env.store(FIRST_STAGE)
    try:
        if not store.exists():
            return None
    except MetadataError:  # nothing recorded to compare: the run stops on it, or rebuilds it when forced
        return None
    old = store.attrs().get("data_root") or ""
    return old if old and absolute_root(old) != absolute_root(pipe.env.data_root) else None


def moved_from(pipe: Pipeline) -> str | None:
    """:func:`made_from`, when nothing else keeps that output from being current (the same
    frames, the same settings): the data moved, or this run names other data at another place
    that lists the same frames. Else None."""
    old = made_from(pipe)
    if old is None:
        return None
    return old if pipe.env.store(FIRST_STAGE).fingerprint() == pipe.at(old).fingerprint(FIRST_STAGE) else None


def other_root_message(pipe: Pipeline, old: str) -> str:
    """Why a run at this data root, not the cache's ``old`` one (:func:`made_from`), stops, and the ways on."""
    new, dataset = absolute_root(pipe.env.data_root), pipe.env.dataset
    where = command_options(dataset, pipe.env.cache_root)
    start = f"dataset '{dataset}': its cache was made from the data at {old}; the data root {new} "
    force = f"`pipeline run {FIRST_STAGE} {where} --force --data-root {shlex.quote(new)}` recomputes everything from it"
    if moved_from(pipe) == old:
        return (f"{start}lists the same frames, and would make every stage recompute, training included. The "
                f"same data moved: `pipeline relocate {where} --data-root {shlex.quote(new)}` checks some of its "
                f"frames and keeps every output. Other data: {force} (or use another --cache)")
    return (f"{start}{_frames_here(pipe, old)}. Running on it would recompute every stage, training included, "
            f"and replace what the cache holds. To do so: {force}; to keep this cache, use another --cache for "
            f"the new data; to run on the cache's own data, omit --data-root")


def _frames_here(pipe: Pipeline, old: str, shown: int = 3) -> str:
    """How the frames at this data root compare with the cache's: 'lists 1 frame(s), 1 of them
    among the cache's 2 (not listed here: 01047)', or that they are the same but the first
    stage's settings or code differ."""
    try:
        cached = pipe.env.store(FIRST_STAGE).frame_ids()
    except MetadataError:
        cached = None
    here = pipe.frame_ids()
    if cached is None:
        return f"lists {len(here)} frame(s)"
    if cached == here:
        return (f"lists the same {len(here)} frame(s), but {FIRST_STAGE}'s settings or code differ from those "
                f"of the cache's output, so `pipeline relocate` cannot keep it{_first_stage_difference(pipe, old)}")
    listed = set(here)
    absent = [f for f in cached if f not in listed]
    more = f" and {len(absent) - shown} more" if len(absent) > shown else ""
    lacking = f" (not listed here: {', '.join(absent[:shown])}{more})" if absent else ""
    return f"lists {len(here)} frame(s), {len(cached) - len(absent)} of them among the cache's {len(cached)}{lacking}"


def _first_stage_difference(pipe: Pipeline, old: str) -> str:
    """': made with split.seed=0 (this command: 7), and `--set split.seed=0` gives this command the
    cache's settings' where the first stage's output was made with other settings at its own data
    root ``old`` (:func:`made_from`); '' where that is not what differs, or it cannot be told."""
    try:
        why = pipe.at(old).why_stale(FIRST_STAGE)
    except PipelineError:  # a damaged record: the run that reads it says so
        return ""
    if why is None or not why.reasons:
        return ""
    sets, _ = sets_to_restore([why])
    return f": {why.text}" + (f", and `{options_text(sets)}` gives this command the cache's settings" if sets else "")


def relocate_cache(pipe: Pipeline, check_frames: int = 3, wait_s: float = 0.0) -> dict[str, Any]:
    """Make the outputs made from the data at its old place (:func:`moved_from`) current for this
    data root: first ``check_frames`` finished frames of the first stage, spread over the
    dataset, are computed from it and must equal the cached ones (PipelineError naming the frame
    and array otherwise); then every output current for the old place gets the fingerprint it
    has here, the first stage last, so that a relocation stopped half-way can be run again."""
    old = moved_from(pipe)
    if old is None and (made := made_from(pipe)) is not None:
        raise PipelineError(f"dataset '{pipe.env.dataset}': cannot relocate the cache, made from the data at "
                            f"{made}, to {absolute_root(pipe.env.data_root)}: it {_frames_here(pipe, made)}; "
                            f"nothing was changed")
    if old is None:
        raise PipelineError(f"dataset '{pipe.env.dataset}': nothing to relocate (no output made from data at "
                            f"another place with the same frames; `pipeline status` shows what is current)")
    checked = _same_data(pipe, check_frames)
    before = pipe.at(old)
    _refuse_leaving_behind(pipe, before, old)
    moved = []
    with contextlib.ExitStack() as locks:
        for name in pipe.order:
            what = f"stage '{name}' of dataset '{pipe.env.dataset}'"
            locks.enter_context(stage_lock(pipe.lock_url(name), what, wait_s))
            locks.enter_context(rewriting(pipe.lock_url(name), what, wait_s))
        for name in [*pipe.order[1:][::-1], FIRST_STAGE]:
            out = pipe.env.store(name) if isinstance(pipe.stages[name], FrameStage) else pipe.env.dir(name)
            if out.fingerprint() == before.fingerprint(name):
                out.set_fingerprint(pipe.fingerprint(name), data_root=pipe.env.data_root)
                moved.append(name)
    return {"from": old, "to": absolute_root(pipe.env.data_root), "checked_frames": checked, "stages": moved[::-1]}


def _refuse_leaving_behind(pipe: Pipeline, before: Pipeline, old: str) -> None:
    """PipelineError, before anything is changed, where outputs were made with other settings than
    this command's (``before``: this command at the ``old`` data root): relocating now would keep
    only the others, and leave those as made from ``old``, which no later relocate finds (its first
    stage is moved), so that the next run would recompute them, training included (until
    2026-12-07). Outputs that are stale for other reasons (marked stale, made from another output)
    are left, as before."""
    made_with_other: dict[str, Staleness] = {}
    for name in pipe.order[1:]:
        try:
            why = before.why_stale(name)
        except PipelineError:  # a damaged record: the run that reads it says so
            continue
        if why is not None and why.sets:
            made_with_other[name] = why
    if not made_with_other:
        return
    sets, _ = sets_to_restore(list(made_with_other.values()))
    raise PipelineError(f"dataset '{pipe.env.dataset}': the outputs of {', '.join(made_with_other)} were made with other settings "
                        f"than this command's, so relocating with them would leave those outputs as made from "
                        f"{old}, to be recomputed by the next run: run relocate with the options they were made "
                        f"with, `{options_text(sets)}`; nothing was changed")


def _same_data(pipe: Pipeline, n: int) -> list[str]:
    """The ids of up to ``n`` finished frames of the first stage (spread over the dataset) that
    the data here gives exactly as cached; PipelineError naming the frame and array otherwise."""
    from pipeline.executor import one_blas_thread

    stage, store, ids = pipe.stages[FIRST_STAGE], pipe.env.store(FIRST_STAGE), pipe.frame_ids()
    done = np.flatnonzero(store.status() == DONE)
    picks = done[np.unique(np.linspace(0, len(done) - 1, min(n, len(done))).round().astype(int))] if len(done) else []
    for i in picks:
        with one_blas_thread():  # as the executor computed them
            out = stage.process(FrameInputs(pipe.env, int(i), ids[i]), pipe.env.cfg)
        for spec in stage.outputs(pipe.env.cfg):
            cached = store.read(spec.name, int(i))
            new = np.asarray(out[spec.name]).astype(cached.dtype, copy=False)
            same = new.shape == cached.shape and (np.array_equal(new, cached, equal_nan=True)
                                                  if cached.dtype.kind in "fc" else np.array_equal(new, cached))
            if not same:
                raise PipelineError(f"dataset '{pipe.env.dataset}': the data at {absolute_root(pipe.env.data_root)} "
                                    f"is not the data the cache was made from: frame {ids[i]} gives another "
                                    f"'{spec.name}' than cached; nothing was changed")
    return [ids[int(i)] for i in picks]


def absolute_root(data_root: str) -> str:
    """A data root as fingerprints hold it: local paths absolute, URLs as they are."""
    return data_root if "://" in data_root else os.path.abspath(data_root)


def default_data_root(cfg, cache_root: str, dataset: str) -> str:
    """Data root when none is given: the profile's, or (synthetic world) a folder in the cache; ''
    for the synthetic world of a remote (fsspec URL) cache, since the readers read local files."""
    if cfg.dataset.data_root:
        return cfg.dataset.data_root
    if cfg.dataset.reader == "synthetic" and "://" not in cache_root:
        return str(Path(cache_root) / dataset / "world")
    return ""
