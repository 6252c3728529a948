"""The `pipeline` command: one click group; shared options defined once; library errors become a
one-line message and exit code 2."""

from __future__ import annotations

import difflib
import functools
import json
import logging
import os
import re
import shlex
import sys
import textwrap
import warnings
from collections import Counter
from pathlib import Path

import click

from pipeline.cache import frame_store
from pipeline.cachefs import command_options, join
from pipeline.config import env_overrides, load_config, parse_set_options, profile_names
from pipeline.errors import ClusterFailed, ConfigError, MetadataError, PipelineError, StageInterrupted, from_dask
from pipeline.run_report import NAME_WIDTH, failed_frames_line
from pipeline.runner import check_stage_name
from pipeline.stage import FrameStage

DEFAULT_CACHE = "cache"


def _handle_errors(fn):
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except PipelineError as exc:
            click.echo(f"error: {exc}", err=True)
            sys.exit(2)
        except BrokenPipeError:  # stdout's reader is gone (`| head`): stop quietly, as Python's docs advise
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # the flush at exit fails no more
            sys.exit(1)
        except OSError as exc:  # e.g. a dataset folder or index that cannot be read
            click.echo(f"error: {exc}", err=True)
            sys.exit(2)
        except Exception as exc:
            if not from_dask(exc):
                raise
            # the cluster failed outside a stage's run (a stage's says ClusterFailed): while closing
            # it after the stages, which --force, if given, had rebuilt
            click.echo(f"error: {ClusterFailed.from_dask(exc, forced=bool(kwargs.get('force')))}", err=True)
            sys.exit(2)
        except StageInterrupted as exc:
            click.echo(exc.advice(), err=True)
            _quiet_cut_off_io()
            sys.exit(130)
        except KeyboardInterrupt:
            click.echo("interrupted", err=True)
            _quiet_cut_off_io()
            sys.exit(130)

    return wrapper


def _quiet_cut_off_io() -> None:
    """After a Ctrl-C: zarr's reads and writes that it cut off are tasks of zarr's event loop, which
    Python destroys at exit, each with asyncio's 'Task was destroyed but it is pending!', a
    'coroutine ... was never awaited' warning or an 'Exception ignored in: <coroutine ...>' traceback
    ('Event loop is closed'): up to about 190 lines after `interrupted` in a verify. What was
    written is settled by the cache's own rules (a frame's status last); they are noise."""
    logging.getLogger("asyncio").setLevel(logging.CRITICAL)
    warnings.filterwarnings("ignore", message="coroutine .* was never awaited", category=RuntimeWarning)
    sys.unraisablehook = lambda unraisable: None  # exceptions in those coroutines' finalisers


def dataset_options(fn):
    """--dataset, --data-root, --cache, --set: shared by every command that touches a dataset."""
    fn = click.option("--set", "sets", multiple=True, metavar="KEY=VALUE",
                      help="Override a configuration key, e.g. --set heatmap.sigma_px=50,50 (repeatable).")(fn)
    fn = click.option("--cache", "cache_root", default=lambda: os.environ.get("PIPELINE_CACHE", DEFAULT_CACHE),
                      show_default="cache (or $PIPELINE_CACHE)", metavar="PATH_OR_URL",
                      help="Cache root: a folder or any fsspec URL (s3://..., gcs://...).")(fn)
    fn = click.option("--data-root", default=lambda: os.environ.get("PIPELINE_DATA_ROOT", ""), metavar="PATH",
                      help="Root of the raw dataset (default: the one recorded in the cache, or the "
                           "built-in synthetic world).")(fn)
    fn = click.option("--dataset", default=lambda: os.environ.get("PIPELINE_DATASET", "synthetic"),
                      show_default="synthetic", metavar="NAME",
                      help=f"Dataset profile: one of {', '.join(profile_names())}.")(fn)
    return fn


def _absolute(path: str) -> str:
    """A local path made absolute (a relative one means another folder on a dask worker or in a
    later run from elsewhere); a file:// URL is its path (zarr's store for it creates no folders);
    other URLs and '' unchanged."""
    if path.startswith("file://"):
        path = path[len("file://"):] or "/"
    return path if not path or "://" in path else os.path.abspath(path)


def _check_url(option: str, url: str) -> None:
    """ConfigError when fsspec cannot open ``url`` at all: an unknown protocol, or one whose
    package is not installed (s3fs for s3://, gcsfs for gs://)."""
    if "://" not in url:
        return
    import fsspec
    from fsspec.registry import known_implementations

    try:
        fsspec.core.url_to_fs(url)
    except (ImportError, ValueError) as exc:
        known = url.split("://", 1)[0] in known_implementations  # its message names the package
        hint = ("install the package it names" if known else
                "use a protocol fsspec knows, with its package installed (e.g. s3:// with `pip install s3fs`)")
        raise ConfigError(f"{option} {url}: fsspec cannot open it ({str(exc).splitlines()[0]}); {hint}") from None


def _same_folder(a: str, b: str) -> bool:
    """True when local paths ``a`` and ``b`` name one existing folder (through a symbolic link, say)."""
    if "://" in a or "://" in b:
        return False
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _explicit_keys(sets: tuple[str, ...]) -> set[str]:
    """The configuration keys the user set: --set options and PIPELINE__ variables."""
    return set(parse_set_options(sets)) | set(env_overrides(dict(os.environ)))


def _check_not_empty(dataset: str, cache_root: str) -> None:
    """ConfigError for an empty --dataset or --cache: an unset shell variable in $PIPELINE_DATASET
    or $PIPELINE_CACHE ('' joined to the dataset is a folder at the root)."""
    if not dataset.strip():
        raise ConfigError(f"--dataset (or $PIPELINE_DATASET) is empty: give a dataset profile "
                          f"({', '.join(profile_names())})")
    if not cache_root.strip():
        raise ConfigError("--cache (or $PIPELINE_CACHE) is empty: give the cache folder or URL")


def _context(dataset: str, data_root: str, cache_root: str, sets: tuple[str, ...], need_root: bool = True):
    from pipeline.dataroot import default_data_root
    from pipeline.executor import RunEnv
    from pipeline.transfer import with_nets_from

    _check_not_empty(dataset, cache_root)
    overrides = parse_set_options(sets)
    cfg = load_config(dataset, overrides)
    cache_root, data_root = _absolute(cache_root), _absolute(data_root)  # workers and later runs elsewhere
    _check_url("--cache", cache_root)
    explicit = _explicit_keys(sets)
    cfg = with_nets_from(cfg, cache_root, explicit, require_trained=need_root)  # their radar's settings come too
    calib = frame_store(cache_root, dataset, "calibrate")
    try:
        recorded = calib.attrs().get("data_root", "") if calib.exists() else ""
    except MetadataError:  # nothing recorded to read: the default, or --data-root is needed
        recorded = ""
    if data_root and recorded and _same_folder(data_root, recorded):
        data_root = recorded  # a link or another spelling of the cache's own data root: its outputs stay current
    if not data_root:
        data_root = recorded
        if data_root and "://" not in data_root and not os.path.exists(data_root) and need_root:
            world = join(cache_root, dataset, "world")
            hint = f" (the synthetic world moved with the cache: --data-root {world})" if os.path.isdir(world) else ""
            raise ConfigError(f"dataset '{dataset}': the cache was made from the data at {data_root}, which is not "
                              f"there any more; if it moved, `pipeline relocate {command_options(dataset, cache_root)} "
                              f"--data-root NEW_PLACE`{hint}")
    if not data_root:
        data_root = default_data_root(cfg, cache_root, dataset)
    if not data_root and need_root and cfg.dataset.reader == "synthetic":  # a remote cache: no world in it
        ds = cfg.dataset
        raise ConfigError(f"dataset '{dataset}': the synthetic world is generated into the cache only when the "
                          f"cache is a local folder, not {cache_root}; generate it into a local one, `pipeline "
                          f"generate-world --out W --frames {ds.world_frames} --seed {ds.world_seed} --resolution "
                          f"{ds.world_resolution[0]}x{ds.world_resolution[1]} --sequence-len {ds.world_sequence_len}`, "
                          f"and give --data-root W")
    if not data_root and need_root:
        raise ConfigError(f"dataset '{dataset}' needs --data-root PATH (the folder holding the raw files)")
    return RunEnv(cfg=cfg, cache_root=cache_root, dataset=dataset, data_root=data_root)


def _ensure_world(env, progress: bool) -> None:
    """Generate the built-in synthetic world into the cache (when it is the data root) once, and
    again when the profile's world settings no longer match the one there."""
    if not _world_to_make(env):
        return
    if not _is_cache_world(env):  # never generate into (or over) a folder the user named
        raise ConfigError(f"--data-root {env.data_root}: no synthetic world there (no world.json). Omit "
                          f"--data-root to use the one generated in the cache, or make one with "
                          f"`pipeline generate-world --out {env.data_root}`")
    from pipeline.lock import stage_lock
    from pipeline.world import generate

    with stage_lock(join(env.cache_root, env.dataset, "locks", "world.lock"), "the synthetic world", wait_s=3600):
        if _world_matches(env):
            return
        ds = env.cfg.dataset
        click.echo(f"generating the synthetic world ({ds.world_frames} frames, seed {ds.world_seed}) "
                   f"into {env.data_root} ...", err=True)
        try:
            summary = generate(env.data_root, frames=ds.world_frames, seed=ds.world_seed,
                               resolution_wh=tuple(ds.world_resolution), sequence_len=ds.world_sequence_len,
                               progress=progress, every_s=env.cfg.run.progress_every_s)
        except KeyboardInterrupt:
            raise StageInterrupted("the synthetic world's generation", "frame", False) from None
        kept = summary.get("resumed_sequences", 0)
        resumed = f" ({kept} of {summary['sequences']} sequences kept from an interrupted run)" if kept else ""
        click.echo(f"  done in {summary.get('seconds', 0):.1f} s{resumed}", err=True)


def _world_to_make(env) -> bool:
    """True when a run would generate (or finish) the synthetic world first: none there yet, or, in
    the cache, one of other settings."""
    return env.cfg.dataset.reader == "synthetic" and not _world_matches(env)


def _world_matches(env) -> bool:
    """True when the data root holds a finished world. A world generated into the cache must also
    match the profile's settings; one the user pointed at with --data-root is taken as it is."""
    path = Path(env.data_root) / "world.json"
    if not path.exists():
        return False
    if not _is_cache_world(env):
        return True
    ds = env.cfg.dataset
    return not _world_differences(json.loads(path.read_text()), {
        "frames": ds.world_frames, "seed": ds.world_seed, "resolution_wh": list(ds.world_resolution),
        "sequence_len": ds.world_sequence_len})


def _world_differences(world: dict, wanted: dict) -> list[str]:
    """'seed 1 (asked: 5)' for each setting of ``wanted`` that the world's world.json ``world`` has otherwise."""
    return [f"{k} {world.get(k)} (asked: {v})" for k, v in wanted.items() if world.get(k) != v]


def _is_cache_world(env) -> bool:
    """True when the data root is the world folder inside the cache (where the CLI generates it)."""
    return Path(env.data_root).resolve() == Path(join(env.cache_root, env.dataset, "world")).resolve()


def _pipeline(env, workers: int, scheduler: str | None, progress: bool | None = None):
    from pipeline.executor import Executor
    from pipeline.runner import Pipeline
    from stages import all_stages

    return Pipeline(all_stages(), env, Executor(workers, scheduler, progress), progress)


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="radarsim-pipeline")
def main() -> None:
    """Simulate a commercial 4D automotive radar from camera + lidar (Song et al., IROS 2025).

    Stages: calibrate -> heatmaps, patches -> train -> synthesize -> export, evaluate. Outputs go to
    CACHE/DATASET/STAGE.zarr; every run resumes where the last one stopped.
    """


@main.command()
@click.argument("stage")
@dataset_options
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="dask worker processes (1 = serial, in-process). [default: run.workers = 2]")
@click.option("--scheduler", default=lambda: os.environ.get("DASK_SCHEDULER_ADDRESS", ""), metavar="ADDRESS",
              help="Run per-frame work on an existing dask.distributed cluster (tcp://HOST:PORT; "
                   "or $DASK_SCHEDULER_ADDRESS). Its workers need the package and access to the cache and data.")
@click.option("--frames", "frames_spec", default="", metavar="SPEC",
              help="Limit per-frame work to START:STOP[:STEP] frame indices or a comma list of frame ids "
                   "(train, export and evaluate use every finished frame of their inputs).")
@click.option("--strict", is_flag=True, help="Stop at the first failed frame with a non-zero exit code.")
@click.option("--force", is_flag=True, help="Recompute STAGE from scratch even if its output is current (train: "
              "its checkpoints are discarded and the nets trained again); with --frames, only those frames, in "
              "place (and the same frames of the stages after it).")
@click.option("--retry-failed", is_flag=True, help="Also re-run frames recorded as failed.")
@click.option("--wait", "wait_s", type=click.FloatRange(min=0.0), default=0.0, metavar="SECONDS",
              help="If another run holds a stage's lock, wait up to this long instead of stopping.")
@click.option("--dry-run", is_flag=True, help="Show per stage whether it is current and frames done / to do; compute nothing.")
@_handle_errors
def run(stage, dataset, data_root, cache_root, sets, workers, scheduler, frames_spec, strict, force,
        retry_failed, wait_s, dry_run):
    """Run STAGE and every upstream stage whose output is missing or stale (like make).

    STAGE is one of calibrate, heatmaps, patches, train, synthesize, export, evaluate.
    """
    from pipeline.frame_selection import parse_frames

    env = _context(dataset, data_root, cache_root, sets)
    workers = env.cfg.run.workers if workers is None else workers
    pipe = _pipeline(env, workers, scheduler or None)
    closure = pipe.upstream_closure(stage)
    pipe.check_config(stage)
    if dry_run:
        _dry_run(pipe, stage, closure, force, frames_spec, retry_failed)
        return
    pipe.executor.check_cluster(env.cache_root)  # before the world is generated or any output touched
    _ensure_world(env, pipe.progress)
    frames = parse_frames(frames_spec, pipe.frame_ids())
    whole = _whole_dataset_note(pipe, closure)
    if frames_spec and whole:
        click.echo(f"--frames {frames_spec}: limits the per-frame stages{whole}", err=True)
    try:
        reports = pipe.run(stage, frames=frames, strict=strict, force=force, retry_failed=retry_failed,
                           wait_s=wait_s)
    finally:
        pipe.executor.close()
    status_cmd = _note_failed(reports, dataset, cache_root)
    for r in reports:
        for key in ("report", "figures", "checkpoints", "output"):
            if key in r.summary:
                click.echo(f"{r.stage} {key}: {r.summary[key]}")
    _exit_if_nothing_done(reports, status_cmd)


def _note_failed(reports, dataset: str, cache_root: str) -> str:
    """'N frame(s) failed (first in ...); `pipeline status ...` lists why.' on stderr when frames of
    ``reports`` failed; returns that `pipeline status` command (for :func:`_exit_if_nothing_done`)."""
    status_cmd = f"pipeline status --dataset {shlex.quote(dataset)}"
    if cache_root != DEFAULT_CACHE:
        status_cmd += f" --cache {shlex.quote(cache_root)}"
    failed = failed_frames_line(reports)
    if failed:
        click.echo(f"{failed}; `{status_cmd}` lists why.", err=True)
    return status_cmd


def _dry_run(pipe, stage: str, closure: list[str], force: bool, frames_spec: str | None,
             retry_failed: bool) -> None:
    """--dry-run: each stage of ``closure`` current or not, frames done and to do, what --force and
    --frames would do, else what the run would compute (or that it has nothing to do); exit 2 when
    an output it would read is damaged (as the run would stop), and --frames refused as the run
    refuses it."""
    from pipeline.inspection import cache_status

    makes_world = _world_to_make(pipe.env) and _is_cache_world(pipe.env)
    unchecked = _check_frames(pipe, frames_spec, makes_world)
    if makes_world:
        ds = pipe.env.cfg.dataset
        click.echo(f"the synthetic world would be generated first ({ds.world_frames} frames, seed {ds.world_seed}) "
                   f"into {pipe.env.data_root}")
    if not makes_world:  # refused as the run refuses them: data at another place, --force --frames
        pipe.check_data_root((stage,), force)
        if force and frames_spec:
            pipe.check_forced_frames((stage,))
    rows = {r["stage"]: r for r in cache_status(pipe, reasons=0)}
    for name in closure:
        _print_status_row(rows[name])
    if force and frames_spec and isinstance(pipe.stages[stage], FrameStage):
        click.echo(f"--force --frames {frames_spec}: those frames of {stage} would be recomputed in place, "
                   f"the same frames of the frame stages after it marked to recompute, the dataset stages "
                   f"after it marked stale")
    elif force:
        click.echo(f"--force: {stage} would be recomputed from scratch, and what depends on it marked stale")
    if frames_spec:
        click.echo(f"--frames {frames_spec}: per-frame work would be limited to those frames{unchecked}"
                   f"{_whole_dataset_note(pipe, closure)}")
    if not (force or frames_spec):
        click.echo(_run_plan([rows[name] for name in closure], retry_failed, None if makes_world else _unlisted(pipe)))
    rebuilt = {stage} if force and not frames_spec else set()  # a forced rebuild replaces a damaged output
    _exit_if_damaged([rows[name] for name in closure if name not in rebuilt])


def _unlisted(pipe) -> str | None:
    """Why the dataset's frames cannot be listed (the run stops there: e.g. a data root one folder
    above the dataset's), or None."""
    try:
        pipe.frame_ids()
    except PipelineError as exc:
        return str(exc).splitlines()[0]
    return None


def _run_plan(rows: list[dict], retry_failed: bool, unlisted: str | None = None) -> str:
    """--dry-run's last line, from the stages' status rows (pipeline.inspection.cache_status): the
    stages a run would compute, a frame stage that is current with the number of its frames to do
    (pending, and failed with --retry-failed), or that it has nothing to do; that it would stop
    where the dataset's frames cannot be listed (``unlisted``: why)."""
    if unlisted:
        return f"a run would stop before computing anything: {unlisted}"
    todo, failed = [], []
    for row in rows:
        if row.get("damaged"):
            continue  # the dry run exits naming it
        if row.get("current") is None:
            todo.append(f"{row['stage']} (whether it is current is unknown)")
        elif not row["current"]:
            todo.append(row["stage"])
        elif "done" in row:
            n = row["pending"] + row["failed"] * retry_failed
            if row["failed"] and not retry_failed:
                failed.append(f"{row['stage']} {row['failed']:,}")
            if n:
                todo.append(f"{row['stage']} ({n:,} frame(s))")
    if todo:
        return f"a run would compute: {', '.join(todo)}"
    left = f"; failed frames stay failed ({', '.join(failed)}; --retry-failed runs them again)" if failed else ""
    return f"nothing to do: every stage is current and finished{left}"


def _check_frames(pipe, frames_spec: str | None, makes_world: bool) -> str:
    """--dry-run's check of --frames against the dataset's frames: the ConfigError the run would
    stop with (exit 2), or, when the frames cannot be listed (no data there), ' (not checked:
    ...)' for the --frames line; '' when checked. The frames of a synthetic world the run would
    generate into the cache first (``makes_world``: none there yet, or one of other settings) are
    those its settings give, without generating it."""
    from pipeline.frame_selection import parse_frames
    from pipeline.world.generator import frame_ids

    if not frames_spec:
        return ""
    if makes_world:
        ids = frame_ids(pipe.env.cfg.dataset.world_frames)
    else:
        try:
            ids = pipe.frame_ids()
        except PipelineError as exc:
            return f" (not checked against the dataset's frames: {str(exc).splitlines()[0]})"
    parse_frames(frames_spec, ids)
    return ""


def _exit_if_nothing_done(reports, status_cmd: str) -> None:
    """Exit 1 when a frame stage with failed frames has none done: it made nothing (the stages that
    need it were not run), which is no success for a script (some failed frames beside
    done ones are: see --strict)."""
    nothing = _made_nothing(reports)
    if not nothing:
        return
    r = nothing[0]
    if r.failures:
        first = (r.failures[0][1] or "no reason recorded").splitlines()[0]
        why = f"all {r.processed} frame(s) it tried in this run failed, e.g. {first}"
    else:
        why = f"its {r.failed} failed frame(s) failed in an earlier run (`{status_cmd}` lists why; " \
              f"--retry-failed tries them again)"
    click.echo(f"error: stage {r.stage} has no frame done: {why}", err=True)
    sys.exit(1)


def _made_nothing(reports) -> list:
    """The reports of frame stages with failed frames and none done."""
    return [r for r in reports if r.action != "dataset" and r.done == 0 and r.failed]


def _whole_dataset_note(pipe, names: list[str]) -> str:
    """'; train, export use every ...' for the stages of ``names`` that --frames does not limit."""
    whole = [n for n in names if not isinstance(pipe.stages[n], FrameStage)]
    if not whole:
        return ""
    verb = "uses" if len(whole) == 1 else "use"
    return (f"; {', '.join(whole)} {verb} every finished frame of {'its' if len(whole) == 1 else 'their'} inputs, "
            f"not only those (they run again when more frames finish)")


def _print_status_row(row: dict, notes: dict[str, int] | None = None) -> None:
    """One stage's status line and its note. ``notes``: how many rows still to be printed hold each
    note; a note is printed once, with that number when it is more than one."""
    current = {True: "current", False: "stale or missing", None: "unknown"}[row.get("current")]
    if row.get("current") and row.get("pending"):  # the settings match, frames are left: not finished
        current = "current, unfinished"
    if "done" in row:
        click.echo(f"{row['stage']:<{NAME_WIDTH}} {current:<19} done {row['done']:>6}  failed {row['failed']:>5}  "
                   f"pending {row['pending']:>6}  excluded {row['excluded']:>5}")
    elif row.get("damaged"):
        click.echo(f"{row['stage']:<{NAME_WIDTH}} {current:<19} damaged: {row['damaged']}")
    else:
        state = "finished" if row.get("exists") else \
            f"not finished; resumes from {row['resumes_from']}" if row.get("resumes_from") else \
            "files of an unfinished or stale run" if row.get("earlier_files") else "not run"
        click.echo(f"{row['stage']:<{NAME_WIDTH}} {current:<19} {state}")
    if row.get("why"):
        click.echo(f"{'':<{NAME_WIDTH}} not current: {row['why']}")
    note = row.get("note")
    if note and (notes is None or notes.get(note)):
        more = notes.pop(note) if notes is not None else 1
        click.echo(f"{'':<{NAME_WIDTH}} note: {note}{f' (so for {more} stages)' if more > 1 else ''}")


@main.command()
@dataset_options
@click.option("--reasons", type=click.IntRange(min=0), default=5, show_default=True, help="Failure reasons shown per stage.")
@click.option("--json", "as_json", is_flag=True, help="Print machine-readable JSON.")
@_handle_errors
def status(dataset, data_root, cache_root, sets, reasons, as_json):
    """Per stage: frames done / failed / pending / excluded, and whether its fingerprint is current
    ('current, unfinished': current with frames pending, as after an interrupted run). Exit code 2
    when a stage's output is damaged (every stage is still listed)."""
    from pipeline.inspection import cache_status

    env = _context(dataset, data_root, cache_root, sets, need_root=False)
    missing = not _cache_exists(env)
    pipe = _pipeline(env, 1, None, progress=False)
    rows = cache_status(pipe, reasons=None if as_json else reasons)
    ablations = None if missing else _ablations(pipe)
    if as_json:
        click.echo(json.dumps(rows + ([{"stage": "ablations", **ablations}] if ablations else []), indent=2, default=str))
    else:
        click.echo(f"dataset {dataset}  cache {join(cache_root, dataset)}  data {env.data_root or '(none)'}")
        if missing:
            click.echo("(no cache of this dataset there: nothing has run with this --cache and --dataset)")
        from pipeline.transfer import other_nets_taken

        taken = "" if "train.nets_from" in _explicit_keys(sets) else other_nets_taken(env.cfg, env.cache_root)
        if taken:
            click.echo(f"(made with the nets of '{taken}', which this command leaves out: the stages below are as a "
                       f"run without them would find them; add --set train.nets_from={taken})")
        notes = Counter(row["note"] for row in rows if row.get("note"))
        for row in rows:
            _print_status_row(row, notes)
            for i, why in list(row.get("reasons", {}).items())[:reasons]:  # 'stage S, frame ID: ...' names it
                click.echo(f"{'':<{NAME_WIDTH}} {why if why.startswith('stage ') else f'frame {i}: {why}'}")
        if ablations:
            from stages.ablations import ablation_line

            click.echo(f"{'ablations':<{NAME_WIDTH}} {ablation_line(ablations)}")
    _exit_if_damaged(rows)


def _ablations(pipe) -> dict | None:
    """What the ablations folder holds (stages.ablations.ablation_state), for `pipeline status`,
    with ``folder``, where it holds anything: on a remote cache this machine's staging folder while
    the remote has no report and the last ablate begun there ran here (the staging folder may hold
    epochs not yet uploaded), else the remote. None where the upstream outputs cannot be read
    (their rows say so)."""
    from pipeline.runner import DatasetInputs
    from stages.ablations import REPORT, ablation_state

    folder = pipe.env.dir("ablations")
    work = folder.work_folder(pipe.env.cfg.run.staging_dir)
    if work is not folder and not folder.fs.exists(folder.file(REPORT)) and (
            work.holds_files() and work.holds_run_of(folder) or work.holds_untokened_run_of(folder)):
        folder = work  # what ablate would go on from (below)
    try:
        state = ablation_state(DatasetInputs(pipe.env, pipe.frame_ids()), pipe.env.cfg, folder)
    except PipelineError:  # ChunkError among them
        return None
    return None if state is None else {"folder": folder.path if folder.is_local else folder.url, **state}


def _cache_exists(env) -> bool:
    """Whether the cache holds a folder for ``env``'s dataset."""
    import fsspec

    fs, path = fsspec.core.url_to_fs(join(env.cache_root, env.dataset))
    return fs.exists(path)


def _exit_if_damaged(rows: list[dict]) -> None:
    """After the rows are printed: the first damaged stage output as the error line, exit code 2."""
    damaged = [row["damaged"] for row in rows if row.get("damaged")]
    if damaged:
        more = f" (and {len(damaged) - 1} more damaged stage output(s) above)" if len(damaged) > 1 else ""
        click.echo(f"error: {damaged[0]}{more}", err=True)
        sys.exit(2)


@main.command()
@_handle_errors
def datasets():
    """List the dataset profiles shipped with the package."""
    rows = []
    for name in profile_names():
        cfg = load_config(name, environ={})
        width, height = cfg.camera.working_size
        rows.append((name, cfg.radar.name, f"working {width}x{height}", cfg.dataset.description))
    name_w, radar_w, size_w = (max(len(row[i]) for row in rows) for i in range(3))
    for name, radar, size, description in rows:
        click.echo(f"{name:<{name_w}}  {radar:<{radar_w}}  {size:<{size_w}}  {description}")


@main.command("config")
@dataset_options
@click.argument("keys", nargs=-1, metavar="[KEY]...")
@click.option("--full", is_flag=True, help="Each key's whole description, not its first sentence.")
@_handle_errors
def config(dataset, data_root, cache_root, sets, keys, full):
    """Print the configuration a run with these options would use: each KEY (a section such as
    `disnet`, or a key such as `placement.map_weight`; all without KEY), its value in --set's
    syntax, where the value comes from, and what it does."""
    from pipeline.config import all_keys, key_docs, profile_values

    env = _context(dataset, data_root, cache_root, sets, need_root=False)
    chosen = _chosen_keys(keys, all_keys())
    overrides = {k.lower() for k in parse_set_options(sets)}
    from_env = {k.lower() for k in env_overrides(dict(os.environ))}
    profile, base = profile_values(dataset), load_config(dataset, parse_set_options(sets))
    docs = key_docs()
    for key in chosen:
        value = env.cfg.get(key)
        if value != base.get(key):  # train.nets_from: the radar settings of the dataset that trained the nets
            origin = f"the nets of {env.cfg.train.nets_from}"
        elif key.lower() in overrides:
            origin = "--set"
        elif key.lower() in from_env:
            origin = "environment"
        else:
            origin = f"profile {dataset}" if key in profile else "default"
        click.echo(f"{key} = {_as_set_value(value)}  ({origin})")
        doc = docs.get(key, "")
        text = " ".join(doc.split()) if full else _first_sentence(doc)
        if text:
            click.echo(textwrap.fill(text, width=100, initial_indent="    ", subsequent_indent="    "))


def _chosen_keys(queries: tuple[str, ...], keys: list[str]) -> list[str]:
    """The keys each query names (a key, or every key of a section); ConfigError with the nearest
    key for a query that names none."""
    chosen = []
    for query in queries or ("",):
        q = query.strip().rstrip(".")
        found = [k for k in keys if not q or k == q or k.startswith(q + ".")]
        if not found:
            near = difflib.get_close_matches(q, keys + sorted({k.split(".")[0] for k in keys}), n=1, cutoff=0.5)
            raise ConfigError(f"no configuration key or section '{query}'" + (f"; did you mean '{near[0]}'?" if near else ""))
        chosen += [k for k in found if k not in chosen]
    return chosen


def _as_set_value(value) -> str:
    """A value as --set takes it: tuples comma-separated, booleans true/false, '' for an empty string."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple):
        return ",".join(_as_set_value(v) for v in value)
    return str(value) if value != "" else "''"  # a float's str is the shortest text that reads back the same


def _first_sentence(doc: str) -> str:
    """The first sentence of a key's description (up to a full stop before a capital letter, or
    the end), on one line."""
    text = " ".join(doc.split())
    end = re.search(r"\.\s(?=[A-Z])", text)
    return text if end is None else text[:end.start() + 1]


@main.command("generate-world")
@click.option("--frames", type=int, default=240, show_default=True, help="Number of frames.")
@click.option("--seed", type=int, default=0, show_default=True, help="Generator seed (same seed, same bytes).")
@click.option("--out", required=True, type=click.Path(file_okay=False), help="Output folder (View-of-Delft layout).")
@click.option("--scene-mix", default="residential,urban,highway", show_default=True, help="Comma list of scene types.")
@click.option("--resolution", default="640x384", show_default=True, help="Image size WxH.")
@click.option("--sequence-len", type=click.IntRange(min=1),
              default=lambda: load_config("synthetic", environ={}).dataset.world_sequence_len,
              show_default="the synthetic profile's dataset.world_sequence_len",
              help="Frames per sequence (each sequence is another scene).")
@click.option("--lidar-lines", type=click.Choice(["16", "64", "128"]), default="64", show_default=True,
              help="The lidar's lines (VLP-16, HDL-64 or OS1-128 pattern). The same seed gives the same "
                   "scenes, images and radar with any of them.")
@click.option("--replace", is_flag=True, help="Replace a world of other settings in --out (caches made from it "
                                               "must then be recomputed: pipeline run calibrate --force).")
@_handle_errors
def generate_world(frames, seed, out, scene_mix, resolution, sequence_len, lidar_lines, replace):
    """Generate the built-in synthetic world (camera, lidar and a hidden radar model).

    With the defaults it is the world `make demo` generates into its cache."""
    from pipeline.world import generate

    try:
        w, h = (int(v) for v in resolution.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--resolution: expected WxH, got '{resolution}'") from None
    mix = tuple(s.strip() for s in scene_mix.split(",") if s.strip())
    wanted = {"seed": seed, "frames": frames, "resolution_wh": [w, h], "scene_mix": list(mix),
              "lidar_lines": int(lidar_lines), "sequence_len": sequence_len}
    if not replace:
        _refuse_another_world(Path(out), wanted)
    summary = generate(out, frames=frames, seed=seed, resolution_wh=(w, h), scene_mix=mix,
                       lidar_lines=int(lidar_lines), sequence_len=sequence_len, progress=True)
    click.echo(json.dumps(summary, indent=2, default=str))


def _refuse_another_world(out: Path, wanted: dict) -> None:
    """ConfigError when ``out`` holds a finished world whose settings differ from ``wanted``: a
    cache made from it, run again, would mix its frames with the new world's (its finished frames
    are kept, the others read from the new files) without a word."""
    try:
        world = json.loads((out / "world.json").read_text())
    except (OSError, ValueError):
        return  # no finished world there (or not one of ours): nothing a cache was made from
    differ = _world_differences(world, wanted)
    if differ:
        raise ConfigError(f"--out {out} holds a synthetic world of other settings: {'; '.join(differ)}. Caches made "
                          f"from it would mix its frames with the new one's: write to another --out, or pass "
                          f"--replace (and recompute those caches: pipeline run calibrate --force)")


@main.command("estimate-sigma")
@dataset_options
@click.option("--frames", "frames_spec", default="", metavar="SPEC", help="Frames to use (default: all).")
@_handle_errors
def estimate_sigma(dataset, data_root, cache_root, sets, frames_spec):
    """Estimate the heatmap Sigma (full-resolution pixels) from radar points on annotated objects."""
    from pipeline.frame_selection import parse_frames
    from pipeline.heatmap import sigma_from_frames
    from pipeline.progress import bar
    from pipeline.readers import get_reader

    env = _context(dataset, data_root, cache_root, sets)
    _ensure_world(env, True)  # as run, ablate and check-physics do (else: 0 frames)
    reader = get_reader(env.cfg, env.data_root)
    ids = reader.frame_ids()
    if not ids:  # said as `run` says it, not as "0 readable frame(s): give more frames"
        raise reader.no_frames_error(env.data_root)
    chosen = parse_frames(frames_spec, ids) or range(len(ids))
    skipped: list[tuple[str, str]] = []

    def readable():  # one frame in memory at a time; an unreadable one is skipped and named, as `run` does
        for i in bar(chosen, total=len(chosen), desc="estimate-sigma", unit="frame",
                     every_s=env.cfg.run.progress_every_s):
            try:
                frame = reader.read(ids[i])
            except (PipelineError, ValueError, OSError, KeyError) as exc:
                skipped.append((ids[i], str(exc).splitlines()[0] if str(exc) else type(exc).__name__))
                continue
            if not frame.has_radar:  # e.g. KITTI: no frame of it can give Sigma, however many
                raise ConfigError(f"dataset {dataset} has no radar (frame {ids[i]}): Sigma is estimated from "
                                  f"radar points; estimate it on the dataset whose radar is simulated "
                                  f"(train.nets_from), which trains the nets")
            yield frame

    try:
        sx, sy = sigma_from_frames(readable())
    except ValueError as exc:  # no object with enough radar points in the frames read
        raise PipelineError(f"dataset {dataset}: cannot estimate Sigma from the {len(chosen) - len(skipped)} "
                            f"readable frame(s) ({exc})" + (f"; {_skipped_text(skipped)}" if skipped else "")
                            + "; it needs frames with labelled objects that hold radar points: give more "
                              "frames (--frames, or all by leaving it out)") from None
    if skipped:
        click.echo(_skipped_text(skipped), err=True)
    click.echo(f"estimated Sigma std: {sx:.1f} px (u), {sy:.1f} px (v) at full resolution from "
               f"{len(chosen) - len(skipped)} frame(s) (profile uses {env.cfg.heatmap.sigma_px}); set it with "
               f"--set heatmap.sigma_px={sx:.0f},{sy:.0f}")


def _skipped_text(skipped: list[tuple[str, str]], shown: int = 3) -> str:
    """'2 unreadable frame(s) skipped: 000012: why; 000013: why' (the first ``shown``)."""
    more = f"; and {len(skipped) - shown} more" if len(skipped) > shown else ""
    return f"{len(skipped)} unreadable frame(s) skipped: " + "; ".join(f"{i}: {why}" for i, why in skipped[:shown]) + more


@main.command()
@dataset_options
@click.option("--tables", default="2,3", show_default=True, help="Which of the paper's tables: 2 (Dis-Net), 3 (RSS-Net).")
@click.option("--seeds", type=click.IntRange(min=1), default=1, show_default=True,
              help="Train each variant this many times (train.seed, train.seed + 1, ...); the tables give "
                   "the mean and the range: on small datasets one run does not rank the rows.")
@click.option("--workers", type=click.IntRange(min=1), default=None, help="dask workers for the preprocessing stages.")
@_handle_errors
def ablate(dataset, data_root, cache_root, sets, tables, seeds, workers):
    """Train the paper's ablation variants (Tables II and III) and write a table next to the paper's.

    The tables, with the train stage's baselines, and each variant's checkpoints go to
    CACHE/DATASET/ablations/; a rerun resumes what was trained (on a remote cache, on any machine:
    each run's checkpoints are uploaded as it trains)."""
    from pipeline.runner import DatasetInputs, StagedUploads, go_on_staged, new_run_token
    from stages.ablations import run_ablations

    chosen = tuple(dict.fromkeys(t.strip() for t in tables.split(",") if t.strip()))
    if not chosen or not set(chosen) <= {"2", "3"}:
        raise click.BadParameter(f"'{tables}': give 2 (Dis-Net), 3 (RSS-Net) or 2,3", param_hint="--tables")
    env = _context(dataset, data_root, cache_root, sets)
    pipe = _pipeline(env, env.cfg.run.workers if workers is None else workers, None)
    _ensure_world(env, pipe.progress)
    try:  # one run, which reports each stage once (calibrate, which both need, too)
        reports = pipe.run(("heatmaps", "patches"))
    finally:
        pipe.executor.close()
    _exit_if_nothing_done(reports, _note_failed(reports, dataset, cache_root))  # as `run` says it
    folder = env.dir("ablations")  # on a remote cache: trained in a local staging folder, uploaded as it goes
    work = folder.work_folder(env.cfg.run.staging_dir)
    uploads = None
    if work is not folder:  # go on from this machine's staging folder, or from what the last run uploaded
        # a staging folder an ablate before 2026-12-07 left has no token (the remote none either): kept
        if work.holds_untokened_run_of(folder) or not go_on_staged(folder, work, "ablate", pipe.log):
            new_run_token(folder, work)
        uploads = StagedUploads(folder, work, "ablate", pipe.log)
    try:
        run_ablations(DatasetInputs(env, pipe.frame_ids(), pipe.progress), env.cfg, Path(work.path), chosen,
                      log=pipe.log, seeds=seeds, publish=uploads.publish if uploads else None)
    except StageInterrupted:
        raise
    except KeyboardInterrupt:  # each variant resumes from its last finished epoch
        raise StageInterrupted("ablate", "resumes", False) from None
    if uploads is not None:
        folder.upload(work, uploads.left())
    click.echo((Path(work.path) / "ablations.md").read_text())
    click.echo(f"ablations: {folder.file('ablations.md') if work is folder else join(folder.url, 'ablations.md')}")


@main.command("check-physics")
@dataset_options
@click.option("--workers", type=click.IntRange(min=1), default=None, help="dask workers for calibrate.")
@_handle_errors
def check_physics(dataset, data_root, cache_root, sets, workers):
    """Physics checks on real frames, no learning: lidar range vs measured radar range per range
    estimator (median / 90th percentile |dr|, share without lidar support) and the Doppler of static
    points vs the ego velocity (median |dv|). Runs calibrate first."""
    import numpy as np

    from pipeline.cache import DONE
    from pipeline.runner import DatasetInputs
    from stages.evaluate import physics_checks

    env = _context(dataset, data_root, cache_root, sets)
    pipe = _pipeline(env, env.cfg.run.workers if workers is None else workers, None)
    _ensure_world(env, pipe.progress)
    try:
        reports = pipe.run("calibrate")
    finally:
        pipe.executor.close()
    status_cmd = _note_failed(reports, dataset, cache_root)  # the checks leave those frames out
    _exit_if_nothing_done(reports, status_cmd)
    frames = np.flatnonzero(env.store("calibrate").status() == DONE)
    result = physics_checks(DatasetInputs(env, pipe.frame_ids(), pipe.progress), env.cfg, frames)
    click.echo(f"{len(frames)} frame(s) of {dataset}:")
    for name, values in result.items():
        click.echo(f"  {name}: " + ", ".join(f"{k} = {v:.3g}" if isinstance(v, float) else f"{k} = {v}"
                                            for k, v in values.items()))


@main.command()
@dataset_options
@click.option("--check-frames", type=click.IntRange(min=1), default=3, show_default=True,
              help="Frames recomputed from the new place and compared with the cache first.")
@click.option("--wait", "wait_s", type=click.FloatRange(min=0), default=0.0, metavar="SECONDS",
              help="If a run holds a stage's lock, wait up to this long instead of stopping.")
@_handle_errors
def relocate(dataset, data_root, cache_root, sets, check_frames, wait_s):
    """Point the cache at the new place of its data (--data-root), keeping every output.

    Some frames are computed from the new place first and must equal the cached ones; then the
    outputs made from the old place become current for the new one (nothing is recomputed).
    """
    if not data_root:
        raise ConfigError("relocate needs --data-root PATH: the new place of the dataset's raw files")
    from pipeline.dataroot import relocate_cache

    env = _context(dataset, data_root, cache_root, sets)
    result = relocate_cache(_pipeline(env, 1, None, progress=False), check_frames, wait_s)
    click.echo(f"relocated dataset {dataset} from {result['from']} to {result['to']}: frames "
               f"{', '.join(result['checked_frames'])} identical; {len(result['stages'])} output(s) kept "
               f"({', '.join(result['stages'])})")


@main.command()
@dataset_options
@click.option("--stage", "stages", multiple=True, metavar="STAGE",
              help="Verify only this stage's output (repeatable; default: every output there is).")
@click.option("--wait", "wait_s", type=click.FloatRange(min=0), default=0.0, show_default=True,
              help="Seconds to wait for a run rewriting an output.")
@_handle_errors
def verify(dataset, data_root, cache_root, sets, stages, wait_s):
    """Read every chunk of the finished frames of each stage output, every checkpoint, and every
    file a dataset stage recorded when it finished (size and SHA-256): the damaged frames and
    files, by stage, with the command that recomputes them (e.g. after copying a cache). Exit code
    2 when anything is damaged."""
    from pipeline.inspection import verify_cache, verify_lines
    from pipeline.progress import bar

    env = _context(dataset, data_root, cache_root, sets, need_root=False)
    if not _cache_exists(env):  # a mistyped path: not 'nothing damaged', nor lock folders made there
        raise PipelineError(f"no cache of dataset {dataset} at {join(env.cache_root, dataset)}: nothing to verify "
                            f"(another --cache or --dataset?)")
    pipe = _pipeline(env, 1, None, progress=False)
    unknown = [s for s in stages if s not in pipe.stages]
    if unknown:
        raise ConfigError(f"--stage {unknown[0]}: no such stage (one of {', '.join(pipe.order)})")
    bars: dict = {}

    def progress(stage: str, n: int, total: int) -> None:
        if stage not in bars:  # the stages are read one after the other: the last one's bar is done
            for done in bars.values():  # (left open, each next bar was drawn below it, with escape codes)
                done.close()
            bars[stage] = bar(total=total, desc=f"verify {stage}", unit="chunk", every_s=env.cfg.run.progress_every_s)
        bars[stage].update(n)

    try:
        rows = verify_cache(pipe, list(stages) or None, progress, wait_s)
    finally:  # also on Ctrl-C or an error: the message then starts on a line of its own
        for stage_bar in bars.values():
            stage_bar.close()
    click.echo(f"dataset {dataset}  cache {join(cache_root, dataset)}")
    rerun = command_options(dataset, env.cache_root) + \
        "".join(f" --set {shlex.quote(s)}" for s in sets)  # the repair runs with this command's settings
    lines, bad = verify_lines(pipe, rows, rerun)
    for line in lines:
        click.echo(line)
    if not rows:
        click.echo("no stage output to verify")
    if bad:
        click.echo(f"error: {bad} stage output(s) damaged (above)", err=True)
        sys.exit(2)


@main.command()
@click.argument("stage")
@dataset_options
@_handle_errors
def unlock(stage, dataset, data_root, cache_root, sets):
    """Remove the lock of STAGE (or 'world', the synthetic world's generation) left by a run that
    died on another machine."""
    from pipeline.config import check_profile
    from pipeline.lock import remove_lock
    from stages import all_stages

    check_stage_name(stage, [s.name for s in all_stages()] + ["world"])  # world: the synthetic world's generation
    _check_not_empty(dataset, cache_root)
    check_profile(dataset)  # an unknown dataset is refused, not 'no lock at cache/astx/locks/...'
    _check_url("--cache", cache_root)
    url = join(cache_root, dataset, "locks", f"{stage}.lock")
    click.echo(f"removed {url}" if remove_lock(url) else f"no lock at {url}")


if __name__ == "__main__":  # pragma: no cover
    main()
