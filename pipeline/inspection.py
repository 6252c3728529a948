"""Read-only inspection of a dataset's cache: ``pipeline status`` (cache_status: per stage, its
frame counts, whether it is current and why not, its failed frames' reasons) and ``pipeline
verify`` (verify_cache: every chunk of the frame stage outputs and every checkpoint and
recorded file of the dataset stage folders read, under a read lock). Both take the Pipeline,
whose fingerprints say what is current, and change no output.
"""

from __future__ import annotations

import os
import shlex
import tempfile
from pathlib import Path
from typing import Any, Callable

from pipeline.cache import DONE, STATUS_NAMES
from pipeline.cachefs import join
from pipeline.dataroot import FIRST_STAGE, made_from, other_root_message
from pipeline.errors import CacheError, ChunkError, MetadataError, PipelineError, cache_error
from pipeline.lock import reading
from pipeline.run_report import NAME_WIDTH
from pipeline.runner import DatasetInputs, Pipeline
from pipeline.staleness import options_text
from pipeline.stage import DatasetStage, FrameStage


def cache_status(pipe: Pipeline, reasons: int | None = None) -> list[dict[str, Any]]:
    """Per stage: done / failed / pending / excluded counts and whether it is current (which
    needs its upstream stages current too: a run would rebuild it after them; None: unknown),
    and the reasons of its first ``reasons`` failed frames (default all). A frame stage whose
    output cannot be read (damaged metadata or status chunk), or a dataset stage whose record
    (_stage.json) is damaged, gets ``damaged``, the error's message, and the other stages are
    still listed."""
    rows = []
    current_of: dict[str, bool | None] = {}
    own_stale: set[str] = set()  # outputs that are not current by themselves (not only their upstream)
    for name in pipe.order:
        stage = pipe.stages[name]
        row: dict[str, Any] = {"stage": name}
        try:
            current = pipe.is_current(name)
        except PipelineError as exc:
            current = None
            row["note"] = str(exc)
        if isinstance(stage, FrameStage):
            store = pipe.env.store(name)
            try:
                row["exists"] = store.exists()
                if row["exists"]:
                    store.check_metadata()
                    st = store.status()
                    row.update({STATUS_NAMES[c]: int((st == c).sum()) for c in STATUS_NAMES})
                    row["reasons"] = store.reasons(limit=reasons, status=st)
            except (CacheError, ChunkError) as exc:
                row.update(exists=True, damaged=str(exc))
                row.pop("note", None)  # the same error, from is_current
                current = None
        else:
            folder = pipe.env.dir(name)
            try:
                row["exists"] = folder.meta() is not None
            except MetadataError as exc:  # a damaged _stage.json
                row.update(exists=True, damaged=str(exc))
                row.pop("note", None)  # the same error, from is_current
                current = None
            else:
                row["summary"] = folder.summary()
                if not row["exists"] and stage.resume_point is not None:
                    row["resumes_from"] = _resume_point(pipe, stage, folder)
                if not row["exists"] and not row.get("resumes_from"):
                    row["earlier_files"] = folder.holds_files()  # else 'not run' while a stale report is there
        if current is False:
            own_stale.add(name)
        if name == FIRST_STAGE and row.get("exists") and (old := made_from(pipe)):
            row["note"] = other_root_message(pipe, old)
        elif current is False and row.get("exists"):
            try:
                why = pipe.why_stale(name, own_stale)
            except PipelineError:  # said by the row already
                why = None
            if why is not None:
                row["why"] = why.text
        row["current"] = _all_of([current, *(current_of.get(u) for u in stage.upstream)]) if row["exists"] else False
        current_of[name] = row["current"]
        rows.append(row)
    return rows


def _resume_point(pipe: Pipeline, stage: DatasetStage, out) -> str | None:
    """What a run of the unfinished dataset stage ``stage`` would go on from (stage.resume_point),
    in the folder it would resume: ``out``, or on a remote cache this machine's staging folder
    when it holds the last run's files (the same run token); None when nothing or unknown."""
    folder = out.work_folder(pipe.env.cfg.run.staging_dir) if stage.local_files else out
    if folder is not out and not folder.holds_run_of(out):
        folder = out
    try:
        return stage.resume_point(DatasetInputs(pipe.env, pipe.frame_ids()), pipe.env.cfg, folder)
    except (PipelineError, ChunkError):  # an unreadable upstream output: status says so on its own row
        return None


def _all_of(values: list[bool | None]) -> bool | None:
    """Three-valued AND: False if any is False, else None if any is unknown, else True."""
    return False if any(v is False for v in values) else None if any(v is None for v in values) else True


def verify_cache(pipe: Pipeline, names: list[str] | None = None,
                 progress: Callable[[str, int, int], None] | None = None, wait_s: float = 0.0) -> list[dict[str, Any]]:
    """Read every chunk of the frame stage outputs (and every checkpoint and recorded file of
    the dataset stage folders: DirStore.check_files) of ``names`` (default: every stage with an
    output), holding them against rewriting meanwhile. Per stage: ``frames`` (frame ids by
    index), ``checked`` (done frames read), ``damaged`` ({frame index: message}), ``findings``
    (the same without the command that recomputes each frame: :func:`verify_lines` names one for
    all), ``frame_ids_damaged``, ``problem`` (the output cannot be read at all, or a dataset
    stage's file is damaged), ``checkpoints`` (read), ``files`` (checked; None: none recorded).
    ``progress(stage, n, total)``."""
    rows = []
    for name in names or pipe.order:
        stage, row = pipe.stages[name], {"stage": name}
        with reading([pipe.lock_url(name)], f"verify of stage '{name}'", wait_s):
            if isinstance(stage, FrameStage):
                store = pipe.env.store(name)
                try:
                    if not store.exists():
                        continue
                    ids = store.frame_ids()
                    status, errors = store.verify(progress and (lambda n, total, _name=name: progress(_name, n, total)))
                except (CacheError, ChunkError) as exc:  # metadata: nothing of it can be read
                    rows.append({**row, "problem": str(exc)})
                    continue
                row.update(checked=int((status == DONE).sum()), damaged={i: str(e) for i, e in errors.items()},
                           findings={i: getattr(e, "finding", str(e)) for i, e in errors.items()},
                           frame_ids_damaged=[ids[i] for i in errors])
            else:
                folder = pipe.env.dir(name)
                try:
                    if folder.meta() is None:
                        continue
                except MetadataError as exc:  # its record is damaged: made again as a whole
                    rows.append({**row, "problem": str(exc), "checkpoints": 0})
                    continue
                row["checkpoints"], problems = _checkpoints_read(folder)
                row["files"], damaged = folder.check_files(progress and (lambda n, total, _name=name: progress(_name, n, total)))
                problems += damaged[:5] + [f"... and {len(damaged) - 5} more file(s)"] * (len(damaged) > 5)
                if problems:
                    row["problem"] = "; ".join(problems)
        rows.append(row)
    return rows


def verify_lines(pipe: Pipeline, rows: list[dict[str, Any]], rerun: str) -> tuple[list[str], int]:
    """The lines `pipeline verify` prints for :func:`verify_cache`'s ``rows`` (a line per stage,
    the damaged frames or files, the command that recomputes them), and how many stage outputs are
    damaged. ``rerun``: the options the repair command takes (--dataset, --cache and the verify
    command's own --set options, with which the repair runs)."""
    lines, bad, pad = [], 0, " " * NAME_WIDTH
    for row in rows:
        name = row["stage"]
        if "problem" in row:
            bad += 1
            lines.append(f"{name:<{NAME_WIDTH}} cannot be read: {row['problem']}")
            if "checkpoints" in row:  # a dataset stage: its output is made again as a whole
                lines.append(f"{pad} make it again: pipeline run {name} {rerun} --force")
                lines += _not_current(pipe, name)
        elif "checkpoints" in row:
            read = [f"{row['files']} file(s) intact"] * (row["files"] is not None) + \
                [f"{row['checkpoints']} checkpoint(s) read"] * bool(row["checkpoints"])
            lines.append(f"{name:<{NAME_WIDTH}} " + ("; ".join(read) or "finished (its files are not checked: it "
                                                                      "finished before files were recorded)"))
        elif row["damaged"]:
            bad += 1
            ids = row["frame_ids_damaged"]
            lines.append(f"{name:<{NAME_WIDTH}} {row['checked']} finished frame(s) read: {len(ids)} damaged")
            lines += [f"{pad} {message}" for message in list(row["findings"].values())[:5]]
            if len(ids) > 5:
                lines.append(f"{pad} ... and {len(ids) - 5} more")
            lines.append(f"{pad} recompute them: pipeline run {name} {rerun} --force --frames "
                         f"{shlex.quote(','.join(ids))}")
            lines += _not_current(pipe, name)
        else:
            lines.append(f"{name:<{NAME_WIDTH}} {row['checked']} finished frame(s) read: every chunk intact")
    return lines, bad


def _not_current(pipe: Pipeline, name: str) -> list[str]:
    """The line saying that the repair command would not find stage ``name`` current (made with
    other settings, e.g. a --set left out such as train.nets_from): the run would make it, and the
    stages before it that are stale too, anew; none where it is current."""
    try:
        stale = [n for n in pipe.upstream_closure(name) if not pipe.is_current(n)]
    except Exception:  # noqa: BLE001 - only words: the data may not be here (a copied cache)
        return []
    if not stale:
        return []
    before = [n for n in stale if n != name]
    redo = f"recomputes {before[0]} and every stage after it" if before else f"makes {name} anew"
    sets, settings_only = pipe.forgotten_sets(stale)
    options = options_text(sets)
    give = f"add `{options}` to both" if settings_only else \
        "give verify and the run the --set options the cache was made with" + \
        (f" (those recorded: `{options}`)" if sets else "")
    return [f"{'':<{NAME_WIDTH}} (not current with this command's settings, with which that run {redo}: {give})"]


def _checkpoints_read(folder) -> tuple[int, list[str]]:
    """(checkpoints read, the problem of each that cannot be) under a dataset stage's folder; on a
    remote cache each is downloaded (one at a time, into a temporary folder) and read, and its
    problem names its remote URL."""
    from pipeline.checkpoint import load_checkpoint

    def problem(path: Path, shown: str) -> str | None:
        try:
            load_checkpoint(path)
        except CacheError as exc:
            return str(exc).replace(str(path), shown)
        return None

    if folder.is_local:
        paths = sorted(Path(folder.path).rglob("*.safetensors"))
        return len(paths), [p for p in (problem(path, str(path)) for path in paths) if p]
    try:
        names = sorted(f for f in folder.fs.find(folder.path) if f.endswith(".safetensors"))
    except OSError as exc:
        return 0, [str(cache_error(exc, f"listing {folder.url}"))]
    problems = []
    with tempfile.TemporaryDirectory(prefix="verify-") as tmp:
        local = Path(tmp) / "checkpoint.safetensors"
        for name in names:
            shown = join(folder.url, os.path.relpath(name, folder.path))
            try:
                folder.fs.get(name, str(local))
            except OSError as exc:
                problems.append(str(cache_error(exc, f"downloading {shown}")))
                continue
            problems.append(problem(local, shown))
    return len(names), [p for p in problems if p]
