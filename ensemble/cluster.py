"""Running a sweep's chunks on a dask.distributed cluster (the `dask` extra).

A task carries the run's spec and a member range: the worker builds those
members' parameters itself (spec.members_table draws and checks any range
directly), integrates them and returns their arrays, which the
client, the single writer of a NetCDF result, keeps as a part
(ensemble.parts). Into a Zarr store the worker writes them itself and returns
only a receipt (runner.zarr_task, ensemble.zarr_store); the workers must see
the store where the client does (check_sees). The client holds at most
IN_FLIGHT_PER_THREAD tasks per worker thread, so its memory stays flat however
long the sweep.

Threads: a task's kernel runs on NUMBA_NUM_THREADS (default: the worker's
cores) divided by the worker's Dask threads, at least one, so that the two
never oversubscribe the cores. `--workers N` starts N single-threaded worker
processes with NUMBA_NUM_THREADS = cores / N.
"""
from __future__ import annotations

import logging
import os
import secrets
import signal
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path

import numpy as np

from . import interrupts
from .errors import EnsembleError, Incomplete
from .spec import Spec, SpecError
from .version import __version__

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


def _reads(path, token: str) -> bool:
    """On a worker: whether the probe file at `path` (a Path or a URL's UPath) holds `token`."""
    try:
        return path.read_text() == token
    except OSError:
        return False


def check_sees(client, folder: Path, what: str) -> None:
    """Refuse (ClusterError) a cluster with a worker that does not see `folder` as this process does: each reads
    a probe file written there with a token of this call's."""
    token = secrets.token_hex(16)
    probe = folder.resolve() / f"probe-{token}"
    probe.write_text(token)
    try:
        blind = sorted(worker for worker, sees in client.run(_reads, probe, token).items() if not sees)
    finally:
        probe.unlink(missing_ok=True)
    if blind:
        raise ClusterError(f"{what}: worker {blind[0]} cannot read {folder.resolve()}; give an output on a path or "
                           f"URL every worker shares")


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


@dataclass
class _Job:
    """A member range the cluster computes: in one task, or (segmented) a task per segment, each continuing from
    what the last one carried back, while the client writes the range's part as the segments come."""
    start: int
    stop: int
    writer: object = None  # parts.PartWriter, from the first segment on
    log: object = None  # parts.SegmentLog of the range
    carried: dict | None = None  # what the next segment task continues from (parts.SegmentLog.kept)
    worker: str | None = None  # where the last segment ran: the next one goes there if it can


def compute_on(client, spec: Spec, todo: list[tuple[int, int]], parts, tally, bar, repeats: int, task,
               segment: int | None = None) -> None:
    """Compute the member ranges `todo` on the cluster and keep each as a part, in whatever order they finish;
    raises Incomplete naming the ranges whose tasks failed (after Dask's retries), once the rest are in.

    Whole records: task(spec, start, stop, repeats) -> (saved variables, records) (runner.chunk_task). Records
    run in segments of `segment` samples (each range one launch's: runner.one_launch_ranges): task(spec, start,
    stop, repeats, carried, segment) (runner.segment_task) computes one segment at a time, and each finished
    segment is saved as a segment file (parts.SegmentLog) before the next task continues from it: a run stopped
    inside a long member resumes from its last segment, here or on the cluster."""
    from distributed import as_completed

    jobs = _Jobs(client, spec, todo, parts, repeats, task, segment)
    limit = IN_FLIGHT_PER_THREAD * max(1, sum(client.nthreads().values()))
    running = as_completed([f for f in (jobs.next() for _ in range(limit)) if f is not None])
    failed, cause = [], ""
    try:
        for future in running:
            interrupts.check()  # a Ctrl-C that a library swallowed
            job = jobs.running.pop(future)
            try:
                result = future.result()
            except SpecError:  # a member of the range breaks the scene's constraints: the run stops here, once
                _settled(jobs.running)  # the tasks in flight are done (else they write into what the run deletes)
                raise
            except Exception as e:  # a worker that kept dying (KilledWorker), or the task raised
                failed.append((job.start, job.stop))
                cause = cause or f"{type(e).__name__}: {str(e).split('. ')[0]}".rstrip(": ")  # its first sentence
                if job.writer is not None:
                    job.writer.abandon()  # its segment files stay: --resume continues from them
                following = jobs.next()
            else:
                following = jobs.finished(job, result)
                if _receipt(result):  # a Zarr store's range, written by the worker
                    tally.merge(result["receipt"]["counts"])
                elif job.writer is not None and job.writer.done:
                    tally.add(job.writer.records)
                bar.n = parts.members_done()
                bar.refresh()
            future.release()
            if following is not None:
                running.add(following)
    except BaseException:
        jobs.abandon()
        raise
    if failed:
        raise Incomplete(sorted(failed), cause)


class _Jobs:
    """The member ranges a run computes on the cluster: submitted as tasks, a few at a time (next), and kept as
    their results come (finished)."""

    def __init__(self, client, spec: Spec, todo: list[tuple[int, int]], parts, repeats: int, task,
                 segment: int | None):
        self.client, self.parts, self.repeats, self.task, self.segment = client, parts, repeats, task, segment
        self.spec = spec  # a few kB: each worker draws its own members (not scattered: a worker that dies would
        # take scattered data with it)
        self.pending, self.running = iter(todo), {}

    def submit(self, job: _Job):
        where = {"workers": [job.worker], "allow_other_workers": True} if job.worker else {}
        more = [job.carried, self.segment] if self.segment is not None else []
        future = self.client.submit(self.task, self.spec, job.start, job.stop, self.repeats, *more, pure=False,
                                    **where)
        self.running[future] = job
        return future

    def next(self):
        """The next range's first task (None when every range has been submitted)."""
        for start, stop in self.pending:
            job = _Job(start, stop)
            if self.segment is not None:
                job.writer = self.parts.begin(start, stop)
                job.log = job.writer.log(start, stop)
                job.carried = job.log.kept()
            return self.submit(job)
        return None

    def finished(self, job: _Job, result):
        """Keep what a task returned; the task to run next (the range's next segment, or the next range's)."""
        if _receipt(result):  # the worker wrote the range into a Zarr store (runner.zarr_task)
            self.parts.keep(result["receipt"])
            return self.next()
        if self.segment is not None and "records" not in result:
            _keep_segment(job, result)
            return self.submit(job)
        _keep(job, result if self.segment is not None else {"samples": result[0], "records": result[1]},
              self.parts)
        return self.next()

    def abandon(self) -> None:
        for job in self.running.values():
            if job.writer is not None:
                job.writer.abandon()


def _settled(running: dict) -> None:
    """Wait for the tasks in flight to end, whatever they return: a task running on a worker writes its range into
    the store (or its segment files), which a stopped run deletes."""
    from distributed import wait

    wait(list(running))


def _receipt(result) -> bool:
    """Whether a task returned a receipt (runner.zarr_task) rather than its members' arrays."""
    return isinstance(result, dict) and "receipt" in result


def _keep_segment(job: _Job, found: dict) -> None:
    """Write a segment a task returned (runner.segment_task) and save it, then carry it to the next task."""
    if found["restarted"]:  # the worker could not continue the kept segments (another kernel layout)
        job.log.restart()
        job.carried = None
    first, samples, record = found["first"], found["samples"], found["record"]
    job.writer.write_samples(job.start, first, samples)
    job.log.save(first, samples, found["state"], record)
    before = job.carried or {"amplitudes": [], "errors": []}
    job.carried = {"sample": first + len(next(iter(samples.values()))[0]), "state": found["state"],
                   "noise": record["noise"],
                   **{name: before[name] + ([record[name]] if name in record else []) for name in ("amplitudes",
                                                                                                   "errors")}}
    job.worker = found["worker"]


def _keep(job: _Job, found: dict, parts) -> None:
    """Write a range's records (and its samples, when they come whole) and make it a part."""
    writer = job.writer or parts.begin(job.start, job.stop)
    job.writer = writer
    try:
        if "samples" in found:
            writer.write_samples(job.start, 0, found["samples"])
        writer.write(job.start, found["records"])
    except BaseException:
        writer.abandon()
        job.writer = None
        raise
    writer.finish()
