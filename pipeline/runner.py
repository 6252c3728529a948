"""Make-like orchestration: run a target stage and every upstream stage whose output is missing,
stale (fingerprint changed) or incomplete.

A stage's fingerprint hashes its name and version, the configuration keys it declares, the
fingerprints of its upstream stages and, for the first stage, the dataset listing. A stage whose
stored fingerprint differs is recomputed from scratch; one that matches only processes the frames
still pending. A stage rebuilt under an unchanged fingerprint (forced, or its output deleted)
marks the downstream outputs made from its old output stale.

Beside it: what a run reports (pipeline.run_report); the --frames option's parsing
(pipeline.frame_selection); the data root a cache was made from, and relocating it
(pipeline.dataroot, which also holds FIRST_STAGE); ``pipeline status`` and ``pipeline verify``,
which read a cache and change nothing (pipeline.inspection).
"""

from __future__ import annotations

import contextlib
import difflib
import errno
import hashlib
import json
import os
import sys
import time
import uuid
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import fsspec
import numpy as np

from pipeline.cache import DONE, EXCLUDED, FAILED, PENDING, done_digest
from pipeline.cachefs import is_local, join
from pipeline.config import jsonable
from pipeline.dataroot import FIRST_STAGE, absolute_root, made_from, other_root_message
from pipeline.dirstore import RUN_TOKEN, UNRECORDED
from pipeline.errors import (CacheError, ChunkError, ClusterFailed, ConfigError, FrameError, InterruptedKind,
                             MetadataError, PipelineError, StageInterrupted, cache_error, from_dask)
from pipeline.executor import Executor, FrameInputs, RunEnv
from pipeline.lock import held, reading, rewriting, stage_lock
from pipeline.run_report import NAME_WIDTH, StageReport
from pipeline.stage import DatasetStage, FrameStage, Stage
from pipeline.staleness import Staleness, explain, options_text, sets_to_restore

FAILURES_LOGGED = 20
"""Failed frames of a stage logged one by one in a run; the rest are counted (a failure common to
every frame of a large dataset would print one line per frame)."""


@dataclass
class DatasetInputs:
    """Read access to finished stage outputs, for dataset stages and frame selection."""

    env: RunEnv
    frame_ids: list[str]
    progress: bool = False
    publish: Callable[[list[Path]], bool] | None = None
    """Where a stage's output is staged locally for a remote cache: uploads the given files of the
    staging folder now, in one call (train's checkpoints of a finished epoch, so that a killed run
    resumes from them on any machine; a failed upload is logged, not raised, and returns False).
    None elsewhere."""

    @property
    def cfg(self):
        return self.env.cfg

    def store(self, stage: str):
        return self.env.store(stage)

    def dir(self, stage: str):
        return self.env.dir(stage)

    def frame(self, index: int) -> FrameInputs:
        """Per-frame accessor (same API as in frame stages)."""
        return FrameInputs(self.env, index, self.frame_ids[index])


def check_stage_name(name: str, names: list[str]) -> None:
    """ConfigError naming the known stages (and the nearest) when ``name`` is not one of ``names``."""
    if name not in names:
        near = difflib.get_close_matches(name, names, n=1)
        hint = f"; did you mean '{near[0]}'?" if near else ""
        raise ConfigError(f"unknown stage '{name}' (stages: {', '.join(names)}){hint}")


class Pipeline:
    """Stages of one dataset under one cache root, and how to bring them up to date."""

    def __init__(self, stages: list[Stage], env: RunEnv, executor: Executor | None = None,
                 progress: bool | None = None, log: Callable[[str], None] | None = None,
                 frame_lister: Callable[[], list[str]] | None = None) -> None:
        self.stages = {s.name: s for s in stages}
        self.order = [s.name for s in stages]
        self.env = env
        self.executor = executor or Executor(1)
        self.progress = True if progress is None else progress  # a bar on a terminal, else lines (pipeline.progress)
        self.log = log or (lambda msg: print(msg, file=sys.stderr))
        self._fp: dict[str, str] = {}
        self._done: dict[str, str] = {}
        """Done-frames digest of the frame stages this run brought up to date (saves re-reading
        their status for the dataset stages after them)."""
        self._frame_ids: list[str] | None = None
        self._frame_lister = frame_lister

    # ---- planning -------------------------------------------------------------------------

    def upstream_closure(self, target: str) -> list[str]:
        """``target`` and everything it depends on, in execution order."""
        check_stage_name(target, self.order)
        need: set[str] = set()
        stack = [target]
        while stack:
            name = stack.pop()
            if name not in need:
                need.add(name)
                stack.extend(self.stages[name].upstream)
        return [n for n in self.order if n in need]

    def frame_ids(self) -> list[str]:
        """The dataset's frames, as the reader lists them."""
        if self._frame_ids is None:
            reader = None
            if self._frame_lister is not None:
                ids = self._frame_lister()
            else:
                from pipeline.readers import get_reader

                root = self.env.data_root
                if not root:
                    raise PipelineError(f"dataset '{self.env.dataset}': no data root given (--data-root)")
                if "://" not in root and not os.path.isdir(root):
                    raise PipelineError(f"dataset '{self.env.dataset}': the data root {absolute_root(root)} is not "
                                        f"a folder")
                reader = get_reader(self.env.cfg, root)
                ids = reader.frame_ids()
                skipped = {k: v for k, v in reader.report().items() if v}
                if skipped:  # e.g. index entries without files: in no stage's status, so said here
                    self.log(f"{'reader':<{NAME_WIDTH}} " + ", ".join(f"{k.replace('_', ' ')}: {v}" for k, v in skipped.items())
                             + reader.skipped_text())
            if len(set(ids)) != len(ids):
                raise PipelineError(f"dataset at {self.env.data_root}: the reader listed duplicate frame ids")
            if not ids:
                if reader is not None:
                    raise reader.no_frames_error(self.env.data_root)
                raise PipelineError(f"dataset at {self.env.data_root}: no frames found")
            self._frame_ids = list(ids)
        return self._frame_ids

    def fingerprint(self, name: str) -> str:
        """Current fingerprint of stage ``name`` (recursive over upstream stages)."""
        if name not in self._fp:
            stage = self.stages[name]
            parts: dict[str, Any] = {
                "stage": name, "version": stage.version,
                "config": self.env.cfg.fingerprint(stage.config_keys),
                "upstream": [self.fingerprint(u) for u in stage.upstream],
            }
            if name == FIRST_STAGE:
                parts["data_root"] = absolute_root(self.env.data_root)
                parts["frames"] = self._frames_digest()
                from pipeline.readers import reader_class

                version = reader_class(self.env.cfg).version
                if version != 1:  # absent at 1: outputs made before readers had versions stay current
                    parts["reader_version"] = version
            extra = stage.extra_fingerprint(self.env.cfg, self.env) if isinstance(stage, DatasetStage) and \
                stage.extra_fingerprint else ""
            if extra:  # absent when empty: outputs made before a stage had one stay current
                parts["extra"] = extra
            text = json.dumps(parts, sort_keys=True)
            self._fp[name] = hashlib.sha256(text.encode()).hexdigest()[:16]
        return self._fp[name]

    def _frames_digest(self) -> str:
        """SHA-256 of the dataset's frame ids (the first stage's fingerprint holds it)."""
        return hashlib.sha256("\n".join(self.frame_ids()).encode()).hexdigest()

    def record(self, name: str) -> dict[str, Any]:
        """What stage ``name``'s output is made with under this command, recorded with the output
        (frame stages in its attributes, dataset stages in _stage.json) for :meth:`why_stale`: its
        configuration values, code version and upstream outputs' fingerprints; the first stage's
        data root and frames; a dataset stage's other inputs (``extra``, e.g. the nets it takes)."""
        stage, cfg = self.stages[name], self.env.cfg
        rec: dict[str, Any] = {"version": stage.version,
                               "config": {k: jsonable(cfg.get(k)) for k in stage.config_keys},
                               "upstream": {u: self.fingerprint(u) for u in stage.upstream}}
        if name == FIRST_STAGE:
            rec.update(data_root=self.env.data_root, frames_digest=self._frames_digest())
        if isinstance(stage, DatasetStage) and stage.extra_fingerprint:
            rec["extra"] = stage.extra_fingerprint(cfg, self.env)
        return rec

    def why_stale(self, name: str, stale: set[str] | None = None) -> Staleness | None:
        """Why the output of stage ``name`` is not current under this command (its own record
        against :meth:`record`; a stage whose upstream only is not current is current here);
        None where it is, or there is no output. MetadataError where its record is damaged.
        ``stale``: the stages whose own output is not current, when the caller knows them."""
        stage = self.stages[name]
        if isinstance(stage, FrameStage):
            store = self.env.store(name)
            if not store.exists():
                return None
            recorded = store.attrs()
        else:
            recorded = self.env.dir(name).meta()
            if recorded is None:
                return None
        if recorded.get("fingerprint") == self.fingerprint(name):
            if isinstance(stage, DatasetStage) and "frames" in recorded and recorded["frames"] != self.frames_read(name):
                return Staleness(("its per-frame inputs finished other frames since it ran",))
            return None
        closure = [u for u in self.upstream_closure(name) if u != name]
        stale_up = {u for u in closure if u in stale} if stale is not None else \
            {u for u in closure if not self.is_current(u)}
        return explain(recorded, self.record(name), self.env.cfg.dataset.reader, stale_up)

    def forgotten_sets(self, names: list[str]) -> tuple[list[str], bool]:
        """The ``--set`` options ('key=value') that would give this command the settings the
        outputs of ``names`` that are not current were made with, and whether, as far as they
        record, those options are all that differs (:func:`pipeline.staleness.sets_to_restore`)."""
        whys = []
        for name in names:
            try:
                why = self.why_stale(name)
            except PipelineError:
                return [], False
            if why is not None:
                whys.append(why)
        return sets_to_restore(whys)

    def frames_read(self, name: str) -> dict[str, str]:
        """Which frames the per-frame upstream stages of stage ``name`` have done (stage -> digest)."""
        return {u: self._done.get(u) or self.env.store(u).done_digest() for u in self.stages[name].upstream
                if isinstance(self.stages[u], FrameStage)}

    def is_current(self, name: str) -> bool:
        """A per-frame stage: its fingerprint matches. A dataset stage also needs its per-frame
        inputs to hold the frames it read (a frame retried, or finished by a later run, makes it
        stale). Outputs written before dataset stages recorded their frames pass on the fingerprint."""
        stage = self.stages[name]
        if isinstance(stage, FrameStage):
            return self.env.store(name).fingerprint() == self.fingerprint(name)
        meta = self.env.dir(name).meta() or {}
        if meta.get("fingerprint") != self.fingerprint(name):
            return False
        return "frames" not in meta or meta["frames"] == self.frames_read(name)

    # ---- running --------------------------------------------------------------------------

    def run(self, target: str | tuple[str, ...], frames: list[int] | None = None, strict: bool = False,
            force: bool = False, retry_failed: bool = False, wait_s: float = 0.0) -> list[StageReport]:
        """Bring ``target`` (a stage, or a tuple of stages) and its upstream stages up to date, each
        stage once; returns one report per stage run. A frame stage with failed frames and none done
        stops the stages that need it (they get no report), not the others.

        ``frames``: restrict per-frame work to these frame indices. ``force``: recompute ``target``
        even if current; with ``frames``, a current frame stage recomputes only those frames (and
        the same frames of the frame stages after it, the dataset stages after it marked stale).
        With ``strict`` the first failed frame raises FrameError.
        """
        targets = (target,) if isinstance(target, str) else tuple(target)
        reports = []
        self._done.clear()
        for name in targets:
            self.check_config(name)
        self.check_data_root(targets, force)
        if force and frames is not None:
            self.check_forced_frames(targets)
        needed = {name for t in targets for name in self.upstream_closure(t)}
        closure = [name for name in self.order if name in needed]
        skipped: set[str] = set()  # stages needing a frame stage that has no frame done
        for name in closure:
            if name in skipped:
                continue
            stage = self.stages[name]
            what = f"stage '{name}' of dataset '{self.env.dataset}'"
            t0 = time.perf_counter()
            forced = force and (name in targets or getattr(stage, "part_of", "") in targets)
            # up to date with nothing to run: found under a shared lock, which runs started together can
            # all hold; otherwise the exclusive one, which a run writing the output holds
            report = None if forced else self._report_if_nothing_to_do(stage, what, retry_failed)
            if report is None:
                report = self._bring_up_to_date(stage, what, forced, frames, strict, retry_failed, wait_s)
            report.seconds = time.perf_counter() - t0
            reports.append(report)
            self.log(report.line())
            for note in report.notes:
                self.log(f"{'':<{NAME_WIDTH}} {note}")
            if strict and report.failed:
                raise self._strict_error(name, report)
            if isinstance(stage, FrameStage) and report.done == 0 and report.failed:
                # every frame failed: the stages that need it would fail or refuse for want of input; the
                # others (another target's, e.g. patches beside heatmaps) still run
                after = [n for n in closure if n != name and name in self.upstream_closure(n) and n not in skipped]
                if after:
                    skipped.update(after)
                    self.log(f"{'':<{NAME_WIDTH}} no frame of {name} is done: the stages that need it were not run "
                             f"({', '.join(after)})")
        return reports

    def check_forced_frames(self, targets: tuple[str, ...]) -> None:
        """ConfigError where ``--force --frames`` would not recompute just those frames: a frame
        stage the run needs holds finished frames but is not current (made with other settings,
        code or inputs than this run's, or marked stale), so the run would make it anew, keeping
        only those frames. The usual cause is a repair command (verify's, a damaged chunk's) run
        without the --set options the cache was made with."""
        needed = {name for t in targets for name in self.upstream_closure(t)}
        for name in (n for n in self.order if n in needed and isinstance(self.stages[n], FrameStage)):
            store = self.env.store(name)
            try:
                if not store.exists() or self.is_current(name):
                    continue
                done = int((store.status() == DONE).sum())
            except PipelineError:  # damaged, or no frames to list: the run stops on it (a forced rebuild replaces it)
                continue
            if done:
                why = self.why_stale(name)
                sets, settings_only = self.forgotten_sets([n for n in self.order if n in needed])
                options = options_text(sets)
                give = (f"Add `{options}` (the settings the cache was made with)" if settings_only else
                        "Give the run the --set options the cache was made with" +
                        (f" (those recorded: `{options}`)" if sets else ""))
                raise ConfigError(
                    f"--force --frames: {name} holds {done} finished frame(s) made with other settings, code or "
                    f"inputs than this run's ({why.text if why else '`pipeline status` shows it not current'}), so "
                    f"the run would not recompute just those frames but make {name} anew with only them. {give}, "
                    f"or leave out --frames to recompute it whole; nothing was run")

    def at(self, data_root: str) -> "Pipeline":
        """This pipeline reading its frames (as listed here) at ``data_root``."""
        return Pipeline(list(self.stages.values()), replace(self.env, data_root=data_root), self.executor,
                        progress=False, log=self.log, frame_lister=self.frame_ids)

    def _strict_error(self, name: str, report: StageReport) -> FrameError:
        """The error --strict stops with: the first frame that failed in this run (or, when every
        failure is from an earlier run, the first one recorded), named by its id."""
        if report.failures:
            index, reason = report.failures[0]
        else:
            index, reason = next(iter(self.env.store(name).reasons(limit=1).items()))
        frame = self.frame_ids()[index]
        prefix = f"stage {name}, frame {frame}: "
        problem = reason[len(prefix):] if reason.startswith(prefix) else reason
        return FrameError(name, frame, f"{problem} (--strict: stopped; {report.failed} frame(s) of the stage failed)")

    def lock_url(self, name: str) -> str:
        return join(self.env.cache_root, self.env.dataset, "locks", f"{name}.lock")

    def check_data_root(self, targets: tuple[str, ...], force: bool) -> None:
        """PipelineError where the cache was made from data at another place than this data root
        (every output would be recomputed) and the run does not force the first stage."""
        old = made_from(self)
        if old and not (force and FIRST_STAGE in targets):  # every output would be recomputed: only when asked
            raise PipelineError(other_root_message(self, old))

    def check_config(self, target: str) -> None:
        """ConfigError for settings a stage of ``target``'s run cannot work with, before any output
        is touched (each stage's ``check``)."""
        closure = self.upstream_closure(target)
        for name in closure:
            check = self.stages[name].check
            if check is not None:
                check(self.env.cfg)

    def downstream(self, name: str) -> list[str]:
        """Stages that depend on ``name``, directly or not, in execution order."""
        out: set[str] = set()
        for other in self.order:
            if name in self.stages[other].upstream or out & set(self.stages[other].upstream):
                out.add(other)
        return [n for n in self.order if n in out]

    def invalidate_downstream(self, name: str) -> None:
        """As ``name`` starts to be rebuilt (forced, or its output was missing, e.g. deleted by hand,
        or stale), before any of it is written: its fingerprint may equal the one its downstream
        outputs were made from, yet its outputs will be new (training is not bit-reproducible across
        thread counts): mark every downstream output stale so that the next run recomputes it, also
        where this one is killed while rebuilding."""
        for other in self.downstream(name):
            stage = self.stages[other]
            store = self.env.store(other) if isinstance(stage, FrameStage) else self.env.dir(other)
            try:
                recorded = store.fingerprint()
            except MetadataError:  # cannot pass as current: a run of it stops and says why
                continue
            if recorded == self.fingerprint(other):  # would pass as current; others are stale already
                store.invalidate()
                self.log(f"{other:<{NAME_WIDTH}} marked stale (upstream {name} is being recomputed)")

    def redo_frames(self, name: str, frames: list[int]) -> None:
        """Mark ``frames`` of frame stage ``name`` pending, to be recomputed in place (``--force
        --frames``), and the same frames of every frame stage after it, which were made from them
        (their excluded frames stay excluded); the dataset stages after it are marked stale. The
        stages after it go first, so that a run killed half-way leaves them to be recomputed."""
        for other in [*self.downstream(name), name]:
            if isinstance(self.stages[other], DatasetStage):
                folder = self.env.dir(other)
                if folder.fingerprint() == self.fingerprint(other):
                    folder.invalidate()
                    self.log(f"{other:<{NAME_WIDTH}} marked stale (frames of upstream {name} are recomputed)")
                continue
            store = self.env.store(other)
            if not store.exists():
                continue
            try:
                status, snapshot = store.status_and_snapshot()
                redo = [i for i in frames if 0 <= i < len(status) and status[i] in (DONE, FAILED)]
            except ChunkError:  # a damaged status chunk: marking the frames rewrites it
                status = snapshot = None
                redo = [i for i in frames if 0 <= i < len(self.frame_ids())]
            for i in redo:
                store.mark(i, PENDING)
            if redo and other == name and status is not None:  # its status in one object again (the run holds its lock)
                marked = np.zeros(len(status), bool)
                marked[redo] = True
                status[marked] = PENDING
                store.save_status_snapshot(status, after=snapshot, changed=marked)
            if redo and other != name:
                self.log(f"{other:<{NAME_WIDTH}} {len(redo)} frame(s) to recompute (upstream {name} recomputes them)")

    def _report_if_nothing_to_do(self, stage: Stage, what: str, retry_failed: bool) -> StageReport | None:
        """The report of stage ``stage`` when it is up to date with nothing left to run (no pending
        frame, none to retry), found under a shared lock on it and its inputs (one that another run
        checking them may also hold) rather than its exclusive one; None when there is work, or
        anything is in the way (another run writing it, damage, a remote cache, whose locks are
        files only): run() then takes the exclusive lock, whose path reports it."""
        url = self.lock_url(stage.name)
        if not is_local(fsspec.core.url_to_fs(url)[0]) or held(url):
            return None
        try:
            with reading([url, *(self.lock_url(u) for u in stage.upstream)], what):
                if not self.is_current(stage.name):
                    return None
                if isinstance(stage, DatasetStage):
                    summary = self.env.dir(stage.name).summary()
                    report = StageReport(stage.name, "dataset", summary={**summary, "message": "up to date"})
                else:
                    store = self.env.store(stage.name)
                    store.check_metadata()
                    status = store.status()
                    if (status == PENDING).any() or (retry_failed and (status == FAILED).any()) or \
                            self._blocked_frames_ready(stage, status).any():
                        return None
                    report = StageReport(stage.name, "resumed").set_counts(status)
        except (PipelineError, OSError):
            return None
        if held(url):  # a run that started writing it (appending frames) while this one read it
            return None
        if isinstance(stage, FrameStage):
            self._done[stage.name] = done_digest(status)
        return report

    def _blocked_frames_ready(self, stage: FrameStage, status: np.ndarray,
                              up_statuses: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """(F,) bool: the frames that failed only because an upstream frame had failed, and whose
        upstream frames are now all done (they were never tried: the next run tries them).
        ``up_statuses``: the per-frame upstream stages' status, when the caller has read them."""
        ready = np.zeros(len(status), bool)
        if not (status == FAILED).any():
            return ready
        if up_statuses is None:
            up_statuses = {up: self.env.store(up).status() for up in stage.upstream
                           if isinstance(self.stages[up], FrameStage)}
        upstream_done = np.ones(len(status), bool)
        for up_status in up_statuses.values():
            upstream_done &= up_status == DONE
        candidates = np.flatnonzero((status == FAILED) & upstream_done)  # the reasons of these only: a read each
        for i, reason in self.env.store(stage.name).reasons(candidates, status=status).items():
            ready[i] = reason.startswith("upstream stage ")
        return ready

    def _ensure_created(self, stage: FrameStage, force: bool) -> bool:
        store = self.env.store(stage.name)
        fp = self.fingerprint(stage.name)
        if not force and store.fingerprint() == fp:
            return False
        cfg = self.env.cfg
        specs = stage.outputs(cfg)
        attrs = {"stage": stage.name, "dataset": self.env.dataset, "profile": cfg.profile,
                 "data_root": self.env.data_root, **self.record(stage.name), "doc": stage.doc}
        store.create(fp, self.frame_ids(), specs, {s.name: s.frame_shape(cfg) for s in specs}, attrs)
        return True

    def _frames_to_do(self, stage: FrameStage, store, status: np.ndarray, frames: list[int] | None,
                      retry_failed: bool, marked: np.ndarray) -> np.ndarray:
        """Mask (F,) of the frames of ``stage`` to compute now: pending ones (and failed ones with
        ``retry_failed``; else those blocked by an upstream that is done now), limited to ``frames``.
        Marks in ``store`` the frames an upstream failure or exclusion blocks, and the pending frames
        the stage's configuration does not select (excluded), with the reason; and in ``marked``
        (F,), a copy of ``status``, the codes it wrote."""
        ids = self.frame_ids()
        todo_mask = status == PENDING
        if retry_failed:
            todo_mask |= status == FAILED
        up_statuses = {up: self.env.store(up).status() for up in stage.upstream
                       if isinstance(self.stages[up], FrameStage)}
        if not retry_failed:  # e.g. after `run calibrate --retry-failed`
            todo_mask |= self._blocked_frames_ready(stage, status, up_statuses)
        if frames is not None:
            sel = np.zeros(len(ids), bool)
            sel[[i for i in frames if 0 <= i < len(ids)]] = True
            todo_mask &= sel
        # Frames whose upstream failed or was excluded cannot be computed: record why.
        for up, up_status in up_statuses.items():
            for code, word in ((FAILED, "failed"), (EXCLUDED, "was excluded")):
                blocked = todo_mask & (up_status == code)
                store.mark_many(np.flatnonzero(blocked), code, f"upstream stage {up} {word} for this frame")
                marked[blocked] = code
                todo_mask &= ~blocked
            todo_mask &= up_status == DONE
        if stage.select is not None and (todo_mask.any() or (status == PENDING).any()):
            chosen = np.asarray(stage.select(DatasetInputs(self.env, ids), self.env.cfg), bool)
            # every pending frame the configuration leaves out, whatever --frames asked for, so
            # that the pending count is what is left to do
            left_out = (todo_mask | (status == PENDING)) & ~chosen
            store.mark_many(np.flatnonzero(left_out), EXCLUDED, "not selected by this stage's configuration")
            marked[left_out] = EXCLUDED
            todo_mask &= chosen
        return todo_mask

    def _run_frames(self, stage: FrameStage, frames: list[int] | None, strict: bool, force: bool,
                    retry_failed: bool) -> StageReport:
        created = self._ensure_created(stage, force)
        store = self.env.store(stage.name)
        if not created:  # resumed: an array whose metadata is damaged stops the run before any frame
            store.check_metadata()
        ids = self.frame_ids()
        status, snapshot = store.status_and_snapshot()
        written = status.copy()  # the status as this run writes it
        report = StageReport(stage.name, "recomputed" if created else "resumed")
        todo_mask = self._frames_to_do(stage, store, status, frames, retry_failed, written)
        todo = [(int(i), ids[int(i)]) for i in np.flatnonzero(todo_mask)]
        env = replace(self.env, stage_run=uuid.uuid4().hex[:12])  # this run's: executor.run_memo
        for index, code, reason in self.executor.map(stage, env, todo, strict):
            report.processed += 1
            written[index] = code
            if code == FAILED:
                report.failures.append((index, reason))
                if len(report.failures) <= FAILURES_LOGGED:
                    self.log(f"  failed: {reason}")
                if strict:
                    break
        if len(report.failures) > FAILURES_LOGGED:
            self.log(f"  ... and {len(report.failures) - FAILURES_LOGGED} more failed frame(s) of {stage.name} in this "
                     f"run: `pipeline status --reasons N` lists their reasons")
        if report.processed:  # the run's frames reach the disk before it reports them done
            store.flush()
        # A remote output's status in one object, for the next readers of every frame's (their own
        # reads of the one-chunk-per-frame array took a request per frame). A frame that a run
        # stopped by --strict was still computing may finish after it: the snapshot then has it as
        # it was (pending or failed: computed again), never done where it is not. One that holds it
        # already was written after the last write of a status chunk: kept, with the column
        # snapshots read under it; else the new one succeeds the one this run read its status from
        # (pipeline.snapshots: the columns read under that one are brought up to date from the frames
        # whose code changed here, which are all it wrote: a frame it computes was pending or
        # failed, and one that fails again has no array written).
        store.save_status_snapshot(written, keep_unchanged=True, after=snapshot, changed=written != status)
        self._done[stage.name] = done_digest(written)  # what frames_read would read again
        report.set_counts(written)
        if stage.summarise is not None and report.processed:
            try:
                report.notes = list(stage.summarise(store, self.env.cfg))
            except (ChunkError, CacheError) as exc:  # a damaged chunk fails its frame's readers, not this run
                report.notes = [f"summary unavailable: {exc}"]
        return report

    def _bring_up_to_date(self, stage: Stage, what: str, forced: bool, frames: list[int] | None, strict: bool,
                          retry_failed: bool, wait_s: float) -> StageReport:
        """Run ``stage`` (or the frames of it that are left) under its locks; ``forced``: --force
        applies to it. The arguments otherwise as for :meth:`run`. Ctrl-C raises StageInterrupted, a
        failed dask cluster ClusterFailed (each saying whether to drop --force on the rerun)."""
        begun = False  # a forced recomputation has begun: a repeated --force would start it again
        try:
            with stage_lock(self.lock_url(stage.name), what, wait_s), \
                    reading([self.lock_url(u) for u in stage.upstream], what, wait_s):
                try:
                    current = self.is_current(stage.name)
                except MetadataError:  # damaged output metadata: only a forced rebuild replaces it
                    if not forced or frames is not None:
                        raise
                    current = False
                redo = forced and frames is not None and isinstance(stage, FrameStage) and current
                rebuild = (forced and not redo) or not current
                if (rebuild or redo) and getattr(stage, "ready", None) is not None:
                    stage.ready(DatasetInputs(self.env, self.frame_ids()), self.env.cfg)  # before any loss
                with rewriting(self.lock_url(stage.name), what, wait_s) if rebuild or redo else contextlib.nullcontext():
                    begun = forced
                    if redo:
                        self.redo_frames(stage.name, frames)
                    elif rebuild:
                        # new outputs under a fingerprint that downstream outputs may already carry:
                        # marked stale first, so that a run killed while rebuilding leaves them stale
                        self.invalidate_downstream(stage.name)
                    if isinstance(stage, FrameStage):
                        return self._run_frames(stage, frames, strict, rebuild and forced, retry_failed)
                    return self._run_dataset(stage, forced, rebuild)
        except KeyboardInterrupt:
            raise StageInterrupted(stage.name, _interrupted_kind(stage), begun) from None
        except ClusterFailed as exc:
            raise exc.in_stage(stage.name, _interrupted_kind(stage), begun) from None
        except Exception as exc:
            if not from_dask(exc):
                raise
            raise ClusterFailed.from_dask(exc, stage=stage.name, kind=_interrupted_kind(stage), forced=begun) from exc

    def _run_dataset(self, stage: DatasetStage, force: bool, rebuild: bool) -> StageReport:
        """Run a dataset stage when ``rebuild`` (forced or not current, as run() found), else report it current."""
        out = self.env.dir(stage.name)
        fp = self.fingerprint(stage.name)
        report = StageReport(stage.name, "dataset")
        if not rebuild:
            report.summary = {**out.summary(), "message": "up to date"}
            return report
        frames, record = self.frames_read(stage.name), self.record(stage.name)
        if not force and out.fingerprint() == fp:
            self.log(f"{stage.name:<{NAME_WIDTH}} recomputing: its per-frame inputs finished other frames since it ran")
        # a stage writing with local file APIs on a remote cache writes into a local staging folder,
        # uploaded when it finishes (its checkpoints resume from there on this machine)
        work = out.work_folder(self.env.cfg.run.staging_dir) if stage.local_files else out
        staged = work is not out
        self._prepare_output(stage, out, work, force)
        uploads = StagedUploads(out, work, stage.name, self.log) if staged else None
        try:
            summary = stage.run(DatasetInputs(self.env, self.frame_ids(), self.progress,
                                              uploads.publish if uploads else None), self.env.cfg, work, fingerprint=fp)
        except OSError as exc:
            if not _writing_into(exc, work.path):
                raise  # a read error, or one naming other files only (e.g. a dataset file it read)
            raise cache_error(exc, f"{stage.name}: writing into {work.path}") from None
        sizes = work.sizes()
        work.write_manifest(sizes)  # uploaded with the files it records
        if uploads is not None:
            files = uploads.left()
            told = [f for f in files if f.name not in UNRECORDED]  # what it sends, the bookkeeping files aside
            sent = f" (the other {len(sizes) - len(told)} as it ran)" if len(told) < len(sizes) else ""
            self.log(f"{stage.name:<{NAME_WIDTH}} uploading {len(told)} file(s), "
                     f"{sum(f.stat().st_size for f in told) / 1e6:.1f} MB, to {out.url}{sent}")
            out.upload(work, files)
            summary = _moved_paths(summary, work.path, out.url)
            if not stage.resumes:  # nothing to resume from: the local copy of an export is not kept
                work.clear()
        out.finish(fp, summary, frames, record)
        report.summary = summary
        return report

    def _prepare_output(self, stage: DatasetStage, out, work, force: bool) -> None:
        """Make the folder ``work`` the stage writes into ready: ``out`` itself, or its local staging
        folder on a remote cache. From scratch (forced, or a stage that does not resume) both are
        emptied; else as :func:`go_on_staged` leaves them. Then ``out`` loses its completion mark
        and a staged run that does not go on in the last run's staging folder writes a new token
        into both (:func:`new_run_token`)."""
        staged = work is not out
        if force or not stage.resumes:
            out.clear()  # from scratch: nothing of an earlier run is reused or left (forced: train's checkpoints too)
            if staged:
                work.clear()
            same_run = False
        else:
            same_run = go_on_staged(out, work, stage.name, self.log)
        out.ensure()
        out.invalidate()
        if staged and not same_run:
            new_run_token(out, work)


def go_on_staged(out, work, name: str, log: Callable[[str], None]) -> bool:
    """Ready the folder ``work`` that a resumable output ``out`` (a DirStore) is written into, ``out``
    itself or its local staging folder on a remote cache, for a run that goes on from what is there;
    whether ``work`` is a staging folder holding the last run begun in ``out`` (its RUN_TOKEN). A
    staging folder that does not (begun elsewhere, run elsewhere since, or cut off while
    downloading) is replaced by what ``out`` holds, said in ``log`` under ``name``; else a killed
    run's half-written files go (and a killed upload's, on a remote folder)."""
    staged = work is not out
    same_run = staged and work.holds_run_of(out)
    if staged and not same_run:
        out.remove_temporaries()  # a killed upload's (DirStore.upload on a filesystem that writes in place)
        work.clear()
        taken = out.download(work)
        if taken:
            log(f"{name:<{NAME_WIDTH}} resuming from {taken} file(s) of {out.url}")
        return False
    left = [os.path.relpath(path, work.path) for path in work.remove_temporaries()]
    if staged:
        left += [os.path.relpath(path, out.path) for path in out.remove_temporaries()]
    if left:
        files = f"file{'s' * (len(left) > 1)}"
        log(f"{name:<{NAME_WIDTH}} removed {len(left)} temporary {files} a killed run left: "
            f"{', '.join(left[:3])}{' ...' * (len(left) > 3)}")
    return same_run


def new_run_token(out, work) -> None:
    """A new RUN_TOKEN in the remote folder ``out`` and its staging folder ``work``: the run about to
    begin in ``work`` is the last begun in ``out``. Written where the run does not go on in the last
    run's staging folder only (one that does keeps theirs: a kill between the two writes would
    otherwise leave them different and the next run downloading the last upload instead of going on
    from the newer staging folder). Creates both folders where they are not there."""
    out.ensure()
    work.ensure()
    token = uuid.uuid4().hex
    for folder in (out, work):
        folder.write_text(RUN_TOKEN, token)


@dataclass
class StagedUploads:
    """Uploads of a local staging folder ``work`` into the remote output ``out`` (DirStores) that a
    stage (or ablate), named ``name`` in ``log``, writes: the files it hands over while it runs
    (:meth:`publish`: train's checkpoints of a finished epoch), and when it is done the files not
    uploaded as they now are (:meth:`left`; every file was uploaded again until 2026-12-07)."""

    out: Any
    work: Any
    name: str
    log: Callable[[str], None]
    sent: dict[str, tuple[int, int, int]] = field(default_factory=dict)
    """Each file uploaded, by path, with its inode, size and modification time then."""

    def publish(self, paths: list[Path]) -> bool:
        """Upload ``paths`` of the staging folder now, in one call (DatasetInputs.publish); whether
        it did. A failure is said in the log: the run goes on, and its upload at the end sends
        them (or fails)."""
        root = Path(self.work.path)
        paths = [Path(p) if Path(p).is_absolute() else root / p for p in paths]  # as DirStore.upload takes them
        seen = {str(path): _file_state(path) for path in paths}  # before: a file written again meanwhile goes again
        try:
            self.out.upload(self.work, paths)
        except CacheError as exc:
            self.log(f"{self.name:<{NAME_WIDTH}} {exc}; going on (a kill now resumes from the last upload, or from "
                     f"{self.work.path} on this machine)")
            return False
        self.sent.update(seen)
        return True

    def left(self) -> list[Path]:
        """The files of the staging folder but ``_stage.json`` that :meth:`publish` did not upload
        as they now are: what the upload at the end sends."""
        root = Path(self.work.path)
        return [path for path in sorted(root.rglob("*")) if path.is_file() and path.name != "_stage.json"
                and self.sent.get(str(path)) != _file_state(path)]


def _file_state(path: Path) -> tuple[int, int, int]:
    """(inode, size, modification time in ns) of ``path``: a file written again (checkpoints are
    written to a temporary name and renamed) differs in one of them."""
    st = os.stat(path)
    return st.st_ino, st.st_size, st.st_mtime_ns


WRITE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS)
"""Errors only a write raises: one without a file name, from a dataset stage, is its output's
(a write(2) that fails names no file)."""


def _moved_paths(summary: dict[str, Any], old: str, new: str) -> dict[str, Any]:
    """``summary`` with the folder ``old`` (a staging folder) written as ``new`` (the remote folder
    it was uploaded to) in its string values."""
    old = old.rstrip("/")
    return {k: v.replace(old, new.rstrip("/")) if isinstance(v, str) else v for k, v in summary.items()}


def _writing_into(exc: OSError, folder: str) -> bool:
    """Whether ``exc`` came from writing into ``folder``: it names a file there, or names none and
    only a write raises it (WRITE_ERRNOS)."""
    named = [os.path.abspath(os.fspath(f)) for f in (exc.filename, exc.filename2) if f is not None]
    if not named:
        return exc.errno in WRITE_ERRNOS
    folder = os.path.abspath(folder)
    return any(os.path.commonpath([f, folder]) == folder for f in named)


def _interrupted_kind(stage: Stage) -> InterruptedKind:
    """What an interrupted run of ``stage`` leaves to go on from (:class:`StageInterrupted`)."""
    if isinstance(stage, FrameStage):
        return "frame"
    return "resumes" if stage.resumes else "dataset"
