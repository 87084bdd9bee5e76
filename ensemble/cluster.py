"""Running a sweep's chunks on a dask.distributed cluster (the `dask` extra).

A task carries the run's spec, without its members table, and a member range:
the worker builds those members' parameters itself (spec.members_table draws
any range directly), integrates them and returns their arrays. Workers never
write files: the client is the single writer. It keeps each finished chunk
as a part (ensemble.parts) and holds at most IN_FLIGHT_PER_THREAD tasks per
worker thread, so its memory stays flat however long the sweep.

Threads: a task's kernel runs on NUMBA_NUM_THREADS (default: the worker's
cores) divided by the worker's Dask threads, at least one, so that the two
never oversubscribe the cores. `--workers N` starts N single-threaded worker
processes with NUMBA_NUM_THREADS = cores / N.
"""
from __future__ import annotations

import logging
import os
import signal
from importlib.metadata import version

import numpy as np

from . import __version__, interrupts
from .errors import EnsembleError, Incomplete
from .spec import Spec

IN_FLIGHT_PER_THREAD = 2  # tasks submitted per worker thread at a time: one running, one queued
CONNECT_SECONDS = 10


class ClusterError(EnsembleError):
    """The cluster cannot be used: one line for the user (exit status 2)."""


def versions() -> dict[str, str]:
    """The versions a chunk's bits depend on, as this process has them."""
    return {"ensemble": __version__, "numba": version("numba"), "numpy": np.__version__}


def connect(scheduler: str | None = None, workers: int | None = None):
    """A dask.distributed Client of the cluster at `scheduler` (tcp://HOST:PORT), or of a LocalCluster of
    `workers` processes started here; refuses workers whose versions differ from this process's."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ClusterError("--scheduler and --workers need dask.distributed; install it with "
                           "pip install 'ensemble[dask]'") from None
    if scheduler:
        try:
            client = Client(scheduler, timeout=f"{CONNECT_SECONDS}s")
        except (OSError, TimeoutError, ValueError) as e:
            raise ClusterError(f"--scheduler {scheduler}: cannot connect ({str(e).splitlines()[0]})") from None
    else:
        cores = os.cpu_count() or 1
        # Worker processes started while SIGINT is ignored keep ignoring it (Python leaves an inherited SIG_IGN
        # alone): Ctrl-C reaches this process alone, which stops them, instead of a traceback from each worker.
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                                   env={"NUMBA_NUM_THREADS": str(max(1, cores // workers))},
                                   silence_logs=logging.CRITICAL)  # failures reach the user as one line of ours
        finally:
            signal.signal(signal.SIGINT, previous)
        client = Client(cluster)
    try:
        _check_versions(client, scheduler or f"--workers {workers}")
    except BaseException:
        close(client)
        raise
    return client


def close(client) -> None:
    """Close the client, and the LocalCluster it started if any."""
    cluster = client.cluster
    client.close()
    if cluster is not None:
        cluster.close()


def _check_versions(client, where: str) -> None:
    ours = versions()
    found = client.run(versions)
    if not found:
        raise ClusterError(f"{where}: the cluster has no workers")
    for worker, theirs in found.items():
        if theirs != ours:
            differ = ", ".join(f"{k} {theirs.get(k)} (here {v})" for k, v in ours.items() if theirs.get(k) != v)
            raise ClusterError(f"{where}: worker {worker} has {differ}; install the same versions on every worker")


class Collected:
    """A chunk's saved variables in memory: the sink compute_chunk streams its samples to on a worker."""

    def __init__(self, spec: Spec, start: int, stop: int):
        scene = spec.model
        sizes = {"member": stop - start, "t": spec.n_save, **scene.sizes(spec.constants)}
        self.start = start
        self.samples = {name: np.full([sizes[d] for d in scene.OBSERVABLES[name][0]], np.nan) for name in spec.save}

    def write_samples(self, start: int, first: int, data: dict[str, np.ndarray]) -> None:
        from .store import put_samples

        put_samples(self.samples, start - self.start, first, data)


def compute_on(client, spec: Spec, todo: list[tuple[int, int]], parts, tally, bar, repeats: int, task) -> None:
    """Compute the member ranges `todo` on the cluster with task(spec, start, stop, repeats) -> (saved variables,
    records) (runner.chunk_task) and keep each as a part, in whatever order they finish; raises Incomplete naming
    the ranges whose tasks failed (after Dask's retries), once the rest are in."""
    from dataclasses import replace

    from distributed import as_completed

    light = replace(spec, table=None)  # a few kB: each worker draws its own members (not scattered: a worker
    # that dies would take scattered data with it)
    limit = IN_FLIGHT_PER_THREAD * max(1, sum(client.nthreads().values()))
    pending = iter(todo)
    ranges = {}

    def submit():
        for start, stop in pending:
            future = client.submit(task, light, start, stop, repeats, pure=False)
            ranges[future] = (start, stop)
            return future
        return None

    running = as_completed([f for f in (submit() for _ in range(limit)) if f is not None])
    failed, cause = [], ""
    for future in running:
        interrupts.check()  # a Ctrl-C that a library swallowed
        start, stop = ranges.pop(future)
        try:
            samples, records = future.result()
        except Exception as e:  # a worker that kept dying (KilledWorker), or the task raised
            failed.append((start, stop))
            cause = cause or f"{type(e).__name__}: {str(e).split('. ')[0]}".rstrip(": ")  # its first sentence
        else:
            writer = parts.begin(start, stop)
            try:
                writer.write_samples(start, 0, samples)
                writer.write(start, records)
            except BaseException:
                writer.abandon()
                raise
            writer.finish()
            tally.add(records)
            bar.n = parts.members_done()
            bar.refresh()
        future.release()
        following = submit()
        if following is not None:
            running.add(following)
    if failed:
        raise Incomplete(sorted(failed), cause)
