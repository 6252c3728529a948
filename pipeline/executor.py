"""Run a frame stage's per-frame function over frames: a serial loop (the reference) or dask.

Workers need nothing but the cache URL, the data root and the configuration: everything a frame
needs is read inside ``process_frame`` from the cache (or, for calibrate, from the raw files).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import logging
import queue
import signal
import threading
import time
import traceback
import uuid
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator

import dask
import numpy as np
from threadpoolctl import threadpool_limits

from pipeline.cache import DONE, FAILED, FrameStore, frame_store, read_frame
from pipeline.cachefs import local_path
from pipeline.config import Config
from pipeline.dirstore import dir_store
from pipeline.errors import (CacheError, ClusterFailed, FrameError, PipelineError, cache_error, exception_line,
                             sigint_deferred)
from pipeline.progress import bar as progress_bar
from pipeline.stage import FrameStage

# glibc heap settings for local dask workers: arrays under 64 MiB come from a reused heap.
WORKER_MALLOC = {"MALLOC_MMAP_THRESHOLD_": 64 << 20, "MALLOC_TRIM_THRESHOLD_": 128 << 20}

# A run on a dask cluster that has had no worker this long stops (as long as check_cluster waits
# for the first one): dask itself would wait for a worker forever.
NO_WORKER_TIMEOUT_S = 60.0
# While no frame comes back, a run on a cluster asks the scheduler this often how many workers it
# has (one small request; never more often than a quarter of the no-worker timeout).
WORKER_CHECK_S = 5.0
# How long a server at the --scheduler address has to answer dask's handshake.
HANDSHAKE_TIMEOUT_S = 10.0


@functools.cache
def tune_heap() -> bool:
    """Apply WORKER_MALLOC to this process (serial runs) through glibc's mallopt; False elsewhere."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.mallopt(-3, WORKER_MALLOC["MALLOC_MMAP_THRESHOLD_"])  # M_MMAP_THRESHOLD
                    and libc.mallopt(-1, WORKER_MALLOC["MALLOC_TRIM_THRESHOLD_"]))  # M_TRIM_THRESHOLD
    except (OSError, AttributeError):
        return False


@dataclass(frozen=True)
class RunEnv:
    """Where a run reads and writes: picklable, shipped to every worker."""

    cfg: Config
    cache_root: str
    dataset: str
    data_root: str
    session: str = field(default_factory=lambda: uuid.uuid4().hex[:12], compare=False)
    """This environment's own token (one per command): what a process keeps of the raw dataset for
    its frames (the reader and its index, the split) is kept for one session, so that a cluster's
    workers, which outlive a run, read a dataset changed since (frames added) as it is now."""
    stage_run: str = field(default="", compare=False)
    """The token of one run of a frame stage's frames (set by the runner for that run, else empty):
    what the frames read of the finished upstream outputs, which the run holds against rewriting,
    is kept for it (:func:`run_memo`)."""

    def store(self, stage: str) -> FrameStore:
        return frame_store(self.cache_root, self.dataset, stage)

    def dir(self, stage: str):
        return dir_store(self.cache_root, self.dataset, stage)


_MEMO: dict[tuple, Any] = {}


def process_memo(key: tuple, build: Callable[[], Any]) -> Any:
    """A per-process cache for expensive objects shared by frames (loaded models, readers)."""
    if key not in _MEMO:
        if len(_MEMO) > 16:
            _MEMO.clear()
        _MEMO[key] = build()
    return _MEMO[key]


def run_memo(env: RunEnv, key: tuple, build: Callable[[], Any]) -> Any:
    """``build()`` once per process and run of a frame stage's frames (RunEnv.stage_run), for what
    its frames read of finished upstream outputs that do not change during the run (their records,
    their fingerprints: a request each on a remote cache); built each time outside such a run."""
    return process_memo((*key, env.stage_run), build) if env.stage_run else build()


@dataclass
class FrameInputs:
    """What a per-frame function may read: its frame's upstream arrays, the raw reader, seeds."""

    env: RunEnv
    index: int
    frame_id: str
    _cache: dict = field(default_factory=dict)

    @property
    def cfg(self) -> Config:
        return self.env.cfg

    def get(self, stage: str, name: str) -> np.ndarray:
        """This frame's array ``name`` of ``stage`` (ragged arrays trimmed to their rows)."""
        key = (stage, name)
        if key not in self._cache:
            self._cache[key] = self.env.store(stage).read(name, self.index, self.env.stage_run)
        value = self._cache[key]
        if isinstance(value, Exception):  # its read in prefetch failed: raised where it is used
            raise value
        return value

    def prefetch(self, keys: list[tuple[str, str]]) -> None:
        """On a remote cache, read this frame's arrays ``keys`` ((stage, array name) pairs) at once,
        in two round trips to the store, one within a run of a stage's frames once the process has
        read their metadata (pipeline.cache.read_frame); :meth:`get` then returns them, or raises
        the error a read met. Each array was read in four round trips, one array after the other
        (until 2026-12-07). On a local cache nothing: :meth:`get` reads the chunk files."""
        wanted: dict[str, list[str]] = {}
        for stage, name in keys:
            if (stage, name) not in self._cache and local_path(self.env.store(stage).url) is None:
                wanted.setdefault(stage, []).append(name)
        if not wanted:
            return
        stages = list(wanted)
        got = read_frame([(self.env.store(stage), wanted[stage]) for stage in stages], self.index, self.env.stage_run)
        for stage, values in zip(stages, got):
            for name, value in values.items():
                self._cache[(stage, name)] = value

    def read_keys(self) -> list[tuple[str, str]]:
        """The (stage, array name) pairs this frame has read (or prefetched)."""
        return [key for key in self._cache if key[0] != "memo"]

    def memo(self, key: tuple, build: Callable[[], Any]) -> Any:
        """``build()`` once per key for this frame (work that several callers of one frame share,
        e.g. evaluate's baselines placing points on the same lidar candidates)."""
        key = ("memo", *key)
        if key not in self._cache:
            self._cache[key] = build()
        return self._cache[key]

    def clear_memo(self) -> None:
        """Forget what :meth:`memo` built (the arrays read stay cached); a benchmark that times the
        same frame again calls it so that each pass does the work."""
        self._cache = {k: v for k, v in self._cache.items() if k[0] != "memo"}

    @property
    def reader(self):
        """The dataset reader (built once per process and RunEnv.session)."""
        from pipeline.readers import get_reader

        key = ("reader", self.env.cfg.dataset, self.env.cfg.camera, self.env.cfg.radar, self.env.data_root,
               self.env.session)
        return process_memo(key, lambda: get_reader(self.env.cfg, self.env.data_root))

    def rng(self, seed: int, salt: int = 0) -> np.random.Generator:
        """A generator that depends only on (seed, salt, frame index): identical on any worker."""
        return np.random.default_rng([seed, salt, self.index])


_READ_SETS: dict[tuple[str, str], list[tuple[str, str]]] = {}  # (stage, run): the arrays a frame read


def process_frame(stage: FrameStage, env: RunEnv, index: int, frame_id: str) -> tuple[int, int, str]:
    """Compute and write one frame; returns (index, status code, reason).

    Frame problems (bad input, a PipelineError, ValueError) are recorded as FAILED with the reason;
    cache problems (disk full, read-only) abort the run.
    """
    store = env.store(stage.name)
    specs = stage.outputs(env.cfg)
    inputs = FrameInputs(env, index, frame_id)
    read_set = (stage.name, env.stage_run or env.session)
    try:
        inputs.prefetch(_READ_SETS.get(read_set, []))  # on a remote cache: what the frame before read
        out = stage.process(inputs, env.cfg)
        if local_path(store.url) is None:
            if len(_READ_SETS) > 64:
                _READ_SETS.clear()
            _READ_SETS[read_set] = inputs.read_keys()
        _check_outputs(stage, env.cfg, specs, out)
    except CacheError:
        raise
    except (PipelineError, ValueError, OSError, KeyError) as exc:
        reason = str(exc) if isinstance(exc, PipelineError) else f"{type(exc).__name__}: {exc}"
    except Exception as exc:  # a bug: record it with where it happened, keep the other frames going
        where = traceback.extract_tb(exc.__traceback__)[-1]
        reason = f"internal error {type(exc).__name__}: {exc} (at {where.filename}:{where.lineno})"
    else:
        store.write_frame(index, out, specs, env.stage_run)
        return index, DONE, ""
    if not reason.startswith(f"stage {stage.name}"):
        own = f"frame {frame_id}: "  # a ReaderError names its frame already
        reason = f"stage {stage.name}, frame {frame_id}: {reason[len(own):] if reason.startswith(own) else reason}"
    store.mark(index, FAILED, reason)
    return index, FAILED, reason


def _check_outputs(stage: FrameStage, cfg: Config, specs, out: dict[str, np.ndarray]) -> None:
    for spec in specs:
        if spec.name not in out:
            raise FrameError(stage.name, "?", f"frame function returned no '{spec.name}'")
        value = np.asarray(out[spec.name])
        shape = spec.frame_shape(cfg)
        if spec.ragged:
            ok = value.ndim == len(shape) and value.shape[1:] == shape[1:]
            if ok and value.shape[0] > shape[0]:
                raise ValueError(f"{spec.name}: {value.shape[0]} rows exceed the capacity {shape[0]} "
                                 f"(raise the profile's store_max_points)")
        else:
            ok = value.shape == shape
        if not ok:
            raise ValueError(f"{spec.name}: expected per-frame shape {shape}, got {value.shape}")
        if spec.finite and value.dtype.kind in "fc":
            bad = ~np.isfinite(value)
            if bad.any():
                first = np.unravel_index(int(np.argmax(bad)), bad.shape)
                raise ValueError(f"{spec.name}: {int(bad.sum())} of {value.size} values are not finite (NaN or inf; "
                                 f"the first at index {tuple(int(i) for i in first)}): not written")


def _worker_probe(marker_url: str) -> bool:
    """Run on a cluster worker: True when the marker file the client wrote into the cache exists
    there (the package imported, or this function could not have been unpickled)."""
    import fsspec

    fs, path = fsspec.core.url_to_fs(marker_url)
    return bool(fs.exists(path))


def check_scheduler_answers(address: str, timeout_s: float | None = None) -> None:
    """PipelineError when a server listens at the tcp ``address`` but does not complete dask's
    handshake within ``timeout_s`` (e.g. the scheduler's dashboard, 8787 instead of 8786): dask's
    Client would wait for its answer forever. Nothing listening, another protocol or a malformed
    address are left to the Client, which reports them. ``timeout_s`` defaults to HANDSHAKE_TIMEOUT_S."""
    import asyncio
    import socket
    from concurrent.futures import ThreadPoolExecutor

    from distributed.comm import connect, parse_address, parse_host_port

    try:
        scheme, location = parse_address(address)
        host, port = parse_host_port(location)
    except ValueError:
        return
    if scheme != "tcp":
        return
    if not 0 < int(port or 0) < 65536:  # dask would try to connect to it for 30 s
        raise PipelineError(f"dask cluster at {address}: port {port} is not a TCP port (1-65535); give the "
                            f"scheduler's address, tcp://HOST:PORT (its port is 8786 by default)")
    timeout_s = HANDSHAKE_TIMEOUT_S if timeout_s is None else timeout_s
    try:
        socket.create_connection((host, port), timeout=timeout_s).close()
    except OSError:
        return

    async def handshake() -> None:
        comm = await asyncio.wait_for(connect(address, timeout=timeout_s), timeout_s)
        await comm.close()

    with ThreadPoolExecutor(1) as pool:  # a loop of its own: the caller may run one (a notebook)
        try:
            pool.submit(asyncio.run, handshake()).result()
        except Exception as exc:  # noqa: BLE001 - the timeout, or the other end closing or talking nonsense
            why = f"no answer within {timeout_s:g} s" if isinstance(exc, TimeoutError) else type(exc).__name__
            raise PipelineError(
                f"dask cluster at {address}: something listens there but does not answer as a dask scheduler "
                f"({why}); is it the scheduler's dashboard? Give the address the scheduler prints "
                f"('Scheduler at: tcp://HOST:PORT', port 8786 by default)") from None


class Executor:
    """Maps ``process_frame`` over frames, serially or on a dask.distributed cluster.

    ``workers`` == 1 and no ``scheduler``: in-process serial loop. Otherwise a LocalCluster of
    ``workers`` processes (started on first use, reused for every stage of the run) or the
    existing cluster at ``scheduler``. A cluster that has had no worker for
    ``no_worker_timeout_s`` while frames are left stops the run with a PipelineError (the frames
    finished so far are kept).
    """

    def __init__(self, workers: int = 2, scheduler: str | None = None, progress: bool | None = None,
                 no_worker_timeout_s: float = NO_WORKER_TIMEOUT_S) -> None:
        self.workers = max(1, int(workers))
        self.scheduler = scheduler
        self.progress = True if progress is None else progress  # a bar on a terminal, else lines (pipeline.progress)
        self.no_worker_timeout_s = float(no_worker_timeout_s)
        self._client = None
        self._cluster = None

    @property
    def distributed(self) -> bool:
        return bool(self.scheduler) or self.workers > 1

    def client(self):
        if self._client is None:
            from distributed import Client, LocalCluster

            if self.scheduler:
                check_scheduler_answers(self.scheduler)
                # a lost scheduler is reported in one line (cli); the client's own traceback would bury it
                logging.getLogger("distributed.client").setLevel(logging.CRITICAL)
                self._client = Client(self.scheduler)
            else:
                # dask's workers trim the heap after every 64 KiB freed, which also pins glibc's mmap
                # threshold at 128 KiB: every image-sized array is then a fresh mmap and page-faults
                # in (measured on Astyx calibrate: 3.9 M faults and 1.3x on 2 workers; with these
                # settings 0.1 M faults and 1.8x).
                try:
                    with dask.config.set({f"distributed.nanny.pre-spawn-environ.{k}": v
                                          for k, v in WORKER_MALLOC.items()}), _workers_without_sigint():
                        self._cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                                     dashboard_address=":0", silence_logs=logging.CRITICAL)
                except Exception as exc:  # e.g. 'Nanny failed to start.': dask's own traceback runs to 118 lines
                    raise PipelineError(f"the local dask cluster of {self.workers} workers could not start "
                                        f"({_cause_line(exc)}); --workers 1 runs the stages in this process, "
                                        f"without a cluster") from None
                self._client = Client(self._cluster)
        return self._client

    def check_cluster(self, cache_root: str, timeout_s: float = 60.0) -> None:
        """With an existing cluster (``scheduler``): connect now, before any output is touched, and
        run one probe task that imports the package and looks for a marker file written into the
        cache (created here if it is not there yet: a first run), then look for it on every worker
        connected (workers joining later are not probed). PipelineError naming the problem: no
        connection (a malformed or wrong address), no worker, the package missing on the workers,
        the cache elsewhere on their machines (naming the workers that miss it)."""
        if not self.scheduler:
            return
        import uuid

        import fsspec

        # an empty folder is no object on an object store: a file the worker must see
        fs, path = fsspec.core.url_to_fs(cache_root)
        marker = f"{path.rstrip('/')}/.cluster-probe-{uuid.uuid4().hex}"
        try:
            if "://" not in cache_root or cache_root.startswith("file://"):  # an object store needs no folders
                fs.makedirs(path, exist_ok=True)
            fs.pipe_file(marker, b"")
        except OSError as exc:
            raise cache_error(exc, f"writing a probe file into the cache {cache_root}") from None
        try:
            try:
                client = self.client()
            except PipelineError:
                raise
            except Exception as exc:  # a malformed address, a refused connection
                raise PipelineError(f"dask cluster at {self.scheduler}: cannot connect ({exception_line(exc)}); "
                                    f"give the scheduler's address, tcp://HOST:PORT") from None
            try:
                client.wait_for_workers(1, timeout=timeout_s)
                url = fs.unstrip_protocol(marker)
                found = client.submit(_worker_probe, url, pure=False).result(timeout=timeout_s)
                # the task ran on one worker; every worker connected now must see the cache too
                blind = sorted(w for w, seen in client.run(_worker_probe, url).items() if not seen)
            except Exception as exc:  # timeouts, a worker that cannot unpickle the task
                raise PipelineError(f"dask cluster at {self.scheduler}: no worker ran a probe task within "
                                    f"{timeout_s:.0f} s ({exception_line(exc)}); its workers need this package "
                                    f"installed and the cache at the same path") from None
        finally:
            try:
                fs.rm_file(marker)
            except Exception:  # noqa: BLE001 - a marker left behind must not hide the probe's own error
                pass
        if not found or blind:
            which = f" ({', '.join(blind)})" if blind else ""
            raise PipelineError(f"dask cluster at {self.scheduler}: a worker{which} does not see the cache "
                                f"{cache_root}; its workers need the cache at the same path (a shared filesystem or "
                                f"an fsspec URL)")

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
        if self._cluster is not None:
            self._cluster.close()
        self._client = self._cluster = None

    def __enter__(self) -> "Executor":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def map(self, stage: FrameStage, env: RunEnv, todo: list[tuple[int, str]],
            strict: bool = False) -> Iterator[tuple[int, int, str]]:
        """Yield (index, status, reason) as frames finish; with ``strict`` stop at the first failure."""
        bar = progress_bar(total=len(todo), desc=stage.name, unit="frame", enabled=self.progress,
                           every_s=env.cfg.run.progress_every_s)
        try:
            for result in self._results(stage, env, todo, strict):
                bar.update(1)
                yield result
        finally:
            bar.close()

    def _results(self, stage, env, todo, strict):
        if not todo:
            return
        if not self.distributed:
            tune_heap()
            with one_blas_thread():  # entered once: it costs ~0.5 ms, a small frame ~20 ms
                for index, frame_id in todo:
                    result = process_frame(stage, env, index, frame_id)
                    yield result
                    if strict and result[1] == FAILED:
                        return
            return
        client = self.client()
        # keys unique to this call: a key submitted again (another run from this process, another
        # client with the same id()) would be joined to the old task and get its result
        token = uuid.uuid4().hex[:12]
        futures = [client.submit(process_frames, stage, env, batch, strict, pure=False,
                                 key=f"{stage.name}-{batch[0][0]}-{token}")
                   for batch in _batches(todo, self._slots(client))]
        finished: queue.SimpleQueue = queue.SimpleQueue()
        for fut in futures:  # in the order they finish, like as_completed, but with a wake-up
            fut.add_done_callback(finished.put)
        try:
            for _ in futures:
                fut = self._next_finished(client, finished)
                for result in fut.result():
                    yield result
                    if strict and result[1] == FAILED:
                        return
        finally:
            client.cancel([f for f in futures if not f.done()])

    def _next_finished(self, client, finished: queue.SimpleQueue):
        """The next future to finish. While none does, ask the scheduler every few seconds whether
        it still has a worker: PipelineError once it has had none for ``no_worker_timeout_s``
        (dask would keep the tasks waiting for one forever)."""
        wake = max(0.1, min(WORKER_CHECK_S, self.no_worker_timeout_s / 4))
        none_since = None
        while True:
            try:
                return finished.get(timeout=wake)
            except queue.Empty:
                pass
            if self._worker_count(client) > 0:
                none_since = None
            elif none_since is None:
                none_since = time.monotonic()
            elif time.monotonic() - none_since >= self.no_worker_timeout_s:
                where = self.scheduler or f"{self._cluster.scheduler_address} (the local cluster)"
                raise ClusterFailed(f"dask cluster at {where} has had no worker for {self.no_worker_timeout_s:g} s",
                                    after=" (once the cluster has workers)")

    @staticmethod
    def _worker_count(client) -> int:
        """Workers the scheduler knows now (one request that lists at most one of them)."""
        info = client.scheduler_info(n_workers=1)
        return int(info.get("n_workers", len(info.get("workers", {}))))

    def _slots(self, client) -> int:
        """Worker threads of the cluster (the local cluster's size without asking it)."""
        if self._cluster is not None:
            return self.workers
        return max(1, sum(w.get("nthreads", 1) for w in client.scheduler_info().get("workers", {}).values()))


def _cause_line(exc: BaseException) -> str:
    """'RuntimeError: Nanny failed to start.; caused by FileNotFoundError: ...': the first line of
    ``exc`` and of the exception at the end of its chain of causes, where that is another."""
    def line(e: BaseException) -> str:
        text = str(e).strip()
        return f"{type(e).__name__}: {text.splitlines()[0]}" if text else type(e).__name__

    root, seen = exc, {id(exc)}
    while (root.__cause__ or root.__context__) is not None and id(root.__cause__ or root.__context__) not in seen:
        root = root.__cause__ or root.__context__
        seen.add(id(root))
    return line(exc) if root is exc or line(root) == line(exc) else f"{line(exc)}; caused by {line(root)}"


@contextlib.contextmanager
def _workers_without_sigint() -> Iterator[None]:
    """Start the local cluster's worker processes with SIGINT blocked, and keep a SIGINT that
    reaches this process meanwhile for the moment the cluster is up.

    Ctrl-C in a terminal reaches the whole process group, and each worker printed its
    KeyboardInterrupt traceback before the run's one 'interrupted' line. The run itself stops them
    when it stops. SIGINT is blocked in this thread while the cluster starts: the threads started
    here (dask's event loop, which spawns the workers) and the workers, whose own threads all come
    from their blocked main thread, inherit the block across fork and exec, so none ever takes a
    SIGINT. This process meanwhile records a SIGINT (another of its threads takes it, or it waits
    until the block is lifted) and raises it once the guard is left. Before, SIGINT was ignored
    (SIG_IGN, which workers inherit too) for the 1-2 s of the start, and a Ctrl-C then was lost:
    the run went on to its end with exit code 0.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    from multiprocessing import resource_tracker

    # started now, in this thread: started by the first worker's spawn, it would lift the block in dask's
    # event loop thread when done (it blocks SIGINT itself while it spawns, then unblocks it)
    resource_tracker.ensure_running()
    with sigint_deferred():  # records a SIGINT, raised to the run's own handler (KeyboardInterrupt) at the end
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            yield
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # one still pending reaches the recorder now


def process_frames(stage: FrameStage, env: RunEnv, batch: list[tuple[int, str]],
                   strict: bool = False) -> list[tuple[int, int, str]]:
    """``process_frame`` over a batch of frames (one dask task); with ``strict`` stop at a failure.

    A batch whose task was cancelled (the run stopped: --strict, Ctrl-C, the client gone) stops
    before its next frame: dask cannot stop a running task, it only drops its result.

    An error that stops the run (a CacheError: the cache not writable, a damaged metadata file)
    reaches the client without the exceptions it was raised from: dask pickles those too, and one
    that cannot be unpickled (zarr's GroupNotFoundError, many of botocore's) turned the error into
    a bare Exception that the CLI showed as a traceback."""
    results = []
    fatal = None
    with one_blas_thread():
        for index, frame_id in batch:
            if _task_cancelled():
                break
            try:
                results.append(process_frame(stage, env, index, frame_id))
            except PipelineError as exc:
                fatal = exc
                break
            if strict and results[-1][1] == FAILED:
                break
    if fatal is not None:
        fatal.__cause__ = fatal.__context__ = None
        raise fatal.with_traceback(None)
    return results


def _task_cancelled() -> bool:
    """True in a dask task that its worker has been told to forget (its client cancelled it or
    went away); False outside a dask worker."""
    try:
        from distributed import get_worker

        worker = get_worker()
        ts = worker.state.tasks.get(worker.get_current_task())
    except Exception:  # not in a dask task (or a distributed without these): never cancelled
        return False
    return ts is not None and ts.state == "cancelled"


def one_blas_thread() -> threadpool_limits:
    """Per-frame work runs on one BLAS thread in every process, serial or dask: a multi-threaded
    GEMM may sum in another order (seen with OpenBLAS on AMD EPYC: heatmaps differed in the last
    bit between a serial run and dask workers), and --workers N means N cores anyway."""
    return threadpool_limits(limits=1, user_api="blas")


MAX_BATCH = 24
"""Frames of one dask task at most. A reader that follows objects across frames (Astyx, VoD) reads
the neighbours of a batch's first and last frame again on the worker that did not read them: on the
141 Astyx frames in ../shared/data (2026-12-06) calibrate + heatmaps + patches on 2 workers ran at
17.9-18.2 frames/s with batches of up to 8, 20.3-20.8 with 24 (the serial run 12.1-13.2)."""


def _batches(todo: list[tuple[int, str]], slots: int, per_slot: int = 2,
             max_batch: int = MAX_BATCH) -> list[list[tuple[int, str]]]:
    """Consecutive batches of frames that shrink towards the end of the run (guided scheduling):
    each holds the frames left divided by ``slots * per_slot`` (rounded up), at most
    ``max_batch``.

    One dask task per frame costs a few milliseconds of scheduling in the client process, which
    shares the machine with the workers; short per-frame work (heatmaps: ~5 ms) then scales badly.
    Batches of equal size left one worker idle at the end of a stage while the other finished a
    whole batch (8 Astyx frames of calibrate, 0.4 s); the last batches now hold one frame each.
    Dask starts the tasks in the order they were submitted, up to the workers' concurrency (seen
    in its task stream on Astyx), so the large batches go first. Each frame still writes its own
    status, so resuming after a kill is unchanged.
    """
    batches, start, parts = [], 0, max(1, slots * per_slot)
    while start < len(todo):
        size = min(max_batch, -(-(len(todo) - start) // parts))
        batches.append(todo[start:start + size])
        start += size
    return batches
