"""Executors: where work runs, on this machine's cores or on a Ray cluster.

A session is the unit of work (its stages depend on each other); sessions are independent, so both
executors map :func:`roomcap.pipeline.runner.process_session` over them. Within a session, a stage's
independent time chunks (``[triangulate.options] workers``, ``executor``:
:class:`roomcap.triangulate.chunks.StreamConfig`) run by :func:`chunk_runner`: in spawned processes or as Ray
tasks. Ray tasks ask for a GPU when onnxruntime on this machine offers CUDA and the keypoints stage is
part of the run. With Ray, a session triangulated in time chunks also sends its chunks to the cluster
as tasks of their own (:func:`ray_for_chunks`), so one long session spreads over the workers.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import signal
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import replace
from pathlib import Path
from typing import Any

from roomcap.core.errors import InputError
from roomcap.pipeline.config import PipelineConfig
from roomcap.pipeline.discover import SessionSource
from roomcap.pipeline.runner import SessionResult, check_session, output_root, process_session
from roomcap.triangulate.chunks import ChunkRunner, StreamConfig

log = logging.getLogger(__name__)
EXECUTORS = ("local", "ray")


def _threads_per_worker(workers: int) -> int:
    return max(1, (os.cpu_count() or 1) // max(1, workers))


def _ignore_sigint() -> None:
    """Worker processes leave Ctrl-C to the parent, which stops them (no traceback from each worker)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """Terminate a pool's processes at once. Stage outputs are written atomically, so a killed session
    resumes from its last finished stage."""
    procs = list(getattr(pool, "_processes", {}).values())  # no public API lists the workers
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        p.terminate()


def run_local(
    sources: list[SessionSource],
    out: Path | None,
    config: PipelineConfig,
    force: bool,
    workers: int,
    wait: bool = False,
) -> Iterator[SessionResult]:
    """Sessions in worker processes (in this process for one worker).

    A worker that dies (a native crash in a decoder, out of memory) breaks the pool; the sessions it took
    down are retried one at a time in a fresh process, so only the session that kills its worker again is
    reported failed and the others finish.
    """
    if workers <= 1 or len(sources) <= 1:
        for s in sources:
            yield process_session(s, out, config, force, wait=wait, chunks=chunk_runner)
        return
    threads = _threads_per_worker(workers)
    ctx = mp.get_context("spawn")  # not fork: onnxruntime and torch thread pools do not survive a fork
    broken: list[SessionSource] = []
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_ignore_sigint) as pool:
        futures = {
            pool.submit(process_session, s, out, config, force, threads, wait, chunk_runner): s
            for s in sources
        }
        try:
            for f in as_completed(futures):
                try:
                    yield f.result()
                except BrokenProcessPool:
                    broken.append(futures[f])
        except KeyboardInterrupt:  # Ctrl-C: stop the workers now; their finished stages are on disk
            _stop_workers(pool)
            raise
    for s in sorted(broken, key=sources.index):
        log.warning("session %s: its worker process died; retrying it alone", s.name)
        try:
            with ProcessPoolExecutor(max_workers=1, mp_context=ctx) as pool:
                yield pool.submit(
                    process_session, s, out, config, force, threads, wait, chunk_runner
                ).result()
        except BrokenProcessPool as e:
            yield SessionResult(
                s.name,
                str(output_root(s, out)),
                status="failed",
                failed_stage="worker",
                message=f"the worker process running this session died ({e or 'crashed'}): "
                "a native crash (decoder, model runtime) or out of memory. Run it alone with "
                "--workers 1 -v to see where; finished stages are kept.",
            )


def _cuda_available() -> bool:
    try:
        import onnxruntime as ort

        return "CUDAExecutionProvider" in ort.get_available_providers()
    except ImportError:
        return False


def ray_for_chunks(config: PipelineConfig) -> PipelineConfig:
    """``config`` with the triangulation's chunks on Ray where it is streamed and the user chose no
    executor: each session's chunks become Ray tasks nested in the session's task (which lends its CPU
    back while it waits for them). The parts and the stage's fingerprint are the same as with processes
    (``executor`` is a run-time setting)."""
    stream = config.triangulate.stream
    if not stream.streams or stream != StreamConfig(chunk_s=stream.chunk_s):  # whole, or the user's choice
        return config
    ray_stream = replace(stream, executor="ray")
    return config.replace(triangulate=replace(config.triangulate, stream=ray_stream))


def chunk_runner(stream: StreamConfig) -> ChunkRunner | None:
    """What runs a stage's independent chunks as ``stream`` says: None (in the stage's process, one
    worker), spawned processes, or Ray tasks (ray is imported now: a clear message where it is missing)."""
    if stream.executor == "ray":
        import_ray(*_CHUNKS_NEED_RAY)
        return chunks_on_ray
    return chunks_in_processes if stream.workers > 1 else None


_CHUNKS_NEED_RAY = (
    "executor = 'ray'",
    " (or set [triangulate.options] executor = 'processes' to use this machine's processes).",
)


def import_ray(needed_by: str, alternative: str = ""):
    """The ray module, or an InputError saying that ``needed_by`` needs it, how to install it, and the
    ``alternative``."""
    try:
        import ray
    except ImportError:
        raise InputError(f"{needed_by} needs ray: pip install 'roomcap[cluster]'{alternative}") from None
    return ray


_BLAS_THREADS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def chunks_in_processes(fn: Callable[..., Any], jobs: dict[int, tuple], workers: int) -> Iterator:
    """``fn(*jobs[i])`` in ``workers`` spawned processes; yields (i, result) as each finishes.

    Each process gets its share of the cores' BLAS threads (read when numpy loads, so set in the
    environment the processes are spawned with): with the default of one per core, 2 processes on 2 cores
    ran at 1.16x one process, with one each at 1.93x (bench_triangulate_workers.py)."""
    ctx = mp.get_context("spawn")
    share = str(max(1, (os.cpu_count() or 1) // max(1, min(workers, len(jobs)))))
    saved = {v: os.environ.get(v) for v in _BLAS_THREADS}
    with ProcessPoolExecutor(min(workers, len(jobs)), mp_context=ctx) as pool:
        try:  # the processes start at the submits (spawn: on demand), with this environment
            os.environ.update({v: share for v in _BLAS_THREADS if saved[v] is None})
            futures = {pool.submit(fn, *args): i for i, args in jobs.items()}
        finally:
            for v, old in saved.items():
                if old is None:
                    os.environ.pop(v, None)
        try:
            for f in as_completed(futures):
                yield futures[f], f.result()
        except BaseException:  # killed, or the caller stopped: the queued chunks are not started
            pool.shutdown(wait=True, cancel_futures=True)
            raise


def chunks_on_ray(fn: Callable[..., Any], jobs: dict[int, tuple], workers: int) -> Iterator:
    """``fn(*jobs[i])`` as Ray tasks of one CPU each; yields (i, result) as each finishes.

    In a running Ray (a cluster, or inside a session's task of ``reprocess --executor ray``) the tasks
    go to its free CPUs; a task blocked in ``ray.wait`` lends its CPU back, so nesting does not deadlock.
    Where no Ray runs in this process, a local one of ``workers`` CPUs is started and stopped after."""
    ray = import_ray(*_CHUNKS_NEED_RAY)
    started_here = not ray.is_initialized()
    if started_here:
        # a new local instance of our own ("local"), never someone else's running cluster
        ray.init(address="local", num_cpus=workers, include_dashboard=False, log_to_driver=False)
    pending: dict = {}
    try:
        task = ray.remote(num_cpus=1)(fn)
        pending = {task.remote(*args): i for i, args in jobs.items()}
        while pending:
            (ref,), _ = ray.wait(list(pending), num_returns=1)
            i = pending.pop(ref)
            try:
                result = ray.get(ref)
            except ray.exceptions.RayTaskError as e:  # the worker's own error (a bad file), not Ray's wrapper
                if isinstance(e.cause, Exception):
                    raise e.cause from None
                raise
            yield i, result
    finally:
        for ref in pending:  # killed, failed or stopped: the chunks not yet written are not run
            ray.cancel(ref)
        if started_here:
            ray.shutdown()


def run_ray(
    sources: list[SessionSource],
    out: Path | None,
    config: PipelineConfig,
    force: bool,
    workers: int,
    address: str | None,
    wait: bool = False,
) -> Iterator[SessionResult]:
    ray = import_ray("the Ray executor")
    config = ray_for_chunks(config)
    started_here = not ray.is_initialized()
    if started_here:
        # no --address: a new local instance of our own ("local"), never someone else's running cluster
        kw = {"address": address} if address else {"address": "local", "num_cpus": workers}
        ray.init(include_dashboard=False, log_to_driver=False, **kw)
    try:
        gpus = 1 if ("keypoints" in config.stages and _cuda_available()) else 0
        threads = _threads_per_worker(workers)
        task = ray.remote(num_cpus=1, num_gpus=gpus)(process_session)
        pending = [task.remote(s, out, config, force, threads, wait, chunk_runner) for s in sources]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])
    finally:
        if started_here:
            ray.shutdown()


def run_sessions(
    sources: list[SessionSource],
    out: Path | None,
    config: PipelineConfig,
    *,
    force: bool = False,
    executor: str = "local",
    workers: int | None = None,
    address: str | None = None,
    on_result: Callable[[SessionResult], None] | None = None,
    wait: bool = False,
) -> list[SessionResult]:
    """Process all sessions; results in the order of ``sources``. A session another run is processing
    (its lock, ``pipeline.lock``) is answered ``locked``, or with ``wait`` processed once that run ends."""
    if executor not in EXECUTORS:
        raise ValueError(f"unknown executor '{executor}'; valid: {list(EXECUTORS)}")
    # default: half the cores, two threads each; the 2D models already use 2 threads well, and on 2 cores one
    # session at a time is faster than two (bench/bench_pipeline_throughput.py: 3.7 vs 3.35 sessions/min)
    workers = workers or max(1, (os.cpu_count() or 1) // 2)
    by_name: dict[str, SessionResult] = {}
    todo = []
    for s in sources:  # sessions already up to date are answered here, without starting workers
        r = None if force else check_session(s, out, config)
        if r is None:
            todo.append(s)
            continue
        by_name[r.name] = r
        if on_result:
            on_result(r)
    if not todo:
        return [by_name[s.name] for s in sources]
    it = (
        run_local(todo, out, config, force, workers, wait)
        if executor == "local"
        else run_ray(todo, out, config, force, workers, address, wait)
    )
    for r in it:
        by_name[r.name] = r
        if on_result:
            on_result(r)
    return [by_name[s.name] for s in sources]
