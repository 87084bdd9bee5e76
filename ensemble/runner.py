"""Running a validated spec: members in chunks through the launch into NetCDF.

Nothing here imports the analysis layer (fit, stability, report): a run starts fast.
"""
from __future__ import annotations

import math
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np

from . import interrupts, tuning
from .bars import BAR, Bar
from .engine import launch
from .errors import EnsembleError
from .interrupts import HeldInterrupts, LateInterrupt
from .members import grid_points, point_settings
from .methods import METHODS, Method
from .parts import Parts
from .places import place
from .records import Record, kernel_seconds_per_step, measured_growth
from .results import Outcome, Status
from .spec import Spec, SpecError, members_table
from .store import Writer, member_variables
from .summary import ANNOUNCE_AFTER, Summary, Tally
from .zarr_store import Receipts, ZarrWriter, exists, is_zarr, task_members, zarr_problem

CHUNK_BYTES = 32 * 2**20  # saved data held in memory per chunk
CHUNK_MEMBER_STEPS = 2e9  # work per chunk: about two seconds at this project's kernel speeds
PIPELINE_CHUNKS = 4  # a run of fewer chunks is cut into this many, each at least an eighth of a chunk's bytes
# On a GPU a chunk is larger: it needs 10^5 to 10^6 members at once to fill the card (one thread each), and runs
# about a hundred times the work in the same seconds.
GPU_CHUNK_BYTES, GPU_CHUNK_MEMBER_STEPS = 2**30, 2e11


def chunk_budget(spec: Spec) -> tuple[int, float]:
    """(bytes of saved data, member-steps of work) per chunk on the run's device."""
    return (GPU_CHUNK_BYTES, GPU_CHUNK_MEMBER_STEPS) if spec.device == "cuda" else (CHUNK_BYTES, CHUNK_MEMBER_STEPS)


def _record_bytes(spec: Spec) -> tuple[int, int]:
    """Bytes one member needs per saved sample while its chunk runs (kernel samples and saved variables), and once
    (its kernel work array, the largest of the run's methods)."""
    scene = spec.model
    sizes = scene.sizes(spec.constants)
    state_rows, _ = scene.kernel_rows(spec.constants)
    saved = sum(math.prod(sizes[d] for d in scene.OBSERVABLES[v][0][2:]) for v in spec.save)
    work = max((launch.layout(scene, METHODS[name], spec.constants).rows for name in spec.methods), default=0)
    return 8 * (state_rows + saved), 8 * work


def run_block(spec: Spec) -> int:
    """Members per kernel block for the run's chunks: the largest block of its methods' kernels, in the run's
    few-members block where it has one (blocks are powers of 2, so a chunk of whole blocks of it is whole blocks
    of every method's)."""
    scene = spec.model
    return max(launch.layout(scene, METHODS[name], spec.constants, spec.kernel_block).block for name in spec.methods)


def segment_samples(spec: Spec) -> int:
    """Saved samples per kernel call: every one, unless one kernel block's share of them would outgrow
    CHUNK_BYTES, or its work CHUNK_MEMBER_STEPS (on a GPU, chunk_budget's); then the record runs in segments of
    this many samples (each call continues the last), and an interrupted run continues from the last segment that
    finished (ensemble.parts.SegmentLog)."""
    per_sample, _ = _record_bytes(spec)
    block = run_block(spec)
    memory, work = chunk_budget(spec)
    steps = steps_per_member(spec)
    by_work = spec.n_save * work / (block * steps) if steps else spec.n_save
    return int(max(1, min(spec.n_save, memory // (per_sample * block), by_work)))


def member_bytes(spec: Spec) -> int:
    """Memory (bytes) one member takes while its chunk runs: a segment of its record, its kernel work array, and
    (`[measure] growth`) the two amplitudes per saved sample that growth_per_step is fitted to (a whole
    record's)."""
    per_sample, once = _record_bytes(spec)
    return per_sample * segment_samples(spec) + once + (16 * spec.n_save if spec.measure["growth"] else 0)


def smallest_chunk(spec: Spec) -> int:
    """Members in the smallest chunk a run can hold: one kernel block (or every member, if fewer)."""
    return min(run_block(spec), spec.n_members)


def steps_per_member(spec: Spec) -> float:
    """The most steps a member of the run takes with a fixed step, t_end / dt (adaptive members: t_end over
    their first trial step, a guess, at least one; 0 when every member is in closed form). From the sweep grids,
    as the members table's dt is: segment_samples asks for it per chunk, and no process holds the whole table
    (building it costs time in proportion to the run)."""
    steps = [dt for grid in spec.grids or ({},) for dt in grid.get("dt", (spec.dt,))
             if dt is not None and math.isfinite(dt) and dt > 0]
    return max(1.0, spec.t_end / min(steps)) if steps else 0.0


def default_chunk(spec: Spec) -> int:
    """Members per chunk: a multiple of the kernel block that keeps a chunk within CHUNK_BYTES of memory
    (member_bytes) and CHUNK_MEMBER_STEPS of work (so chunks end, and finished members reach the file, every few
    seconds); on a GPU within GPU_CHUNK_BYTES and GPU_CHUNK_MEMBER_STEPS. A run that would make fewer than
    PIPELINE_CHUNKS chunks makes that many, if each still holds
    an eighth of CHUNK_BYTES: a chunk is observed and written while the next one's kernel runs, and the last one's
    finishing waits for nothing else, so it should be short. Whole `ensemble run` processes of 10^4 tops
    (analysis/bench/README.md) took 0.81 of their time in four chunks instead of two; 10^3 ran fastest in one."""
    block = run_block(spec)
    chunk_bytes, chunk_steps = chunk_budget(spec)
    chunk = chunk_bytes // member_bytes(spec) // block * block
    steps = steps_per_member(spec)
    if steps > 0:
        chunk = min(chunk, int(chunk_steps // steps) // block * block)
    chunk = min(max(chunk, block), spec.n_members)  # at least one kernel block
    pieces = min(PIPELINE_CHUNKS, spec.n_members * member_bytes(spec) // (chunk_bytes // 8))
    if pieces > 1 and spec.n_members < pieces * chunk:
        share = -(-spec.n_members // pieces)
        chunk = min(chunk, max(block, -(-share // block) * block))
    return chunk


def _same_settings(table: dict[str, np.ndarray], j0: int, j1: int):
    """Ranges [k0, k1) within [j0, j1) of consecutive members that one launch can run (same method and dt; a dt
    of NaN, as adaptive and closed-form members have without one, equals NaN here)."""
    if j1 <= j0:
        return
    method, dt = np.asarray(table["method"][j0:j1]), np.asarray(table["dt"][j0:j1], dtype=float)
    same = (method[1:] == method[:-1]) & ((dt[1:] == dt[:-1]) | (np.isnan(dt[1:]) & np.isnan(dt[:-1])))
    edges = [j0, *(j0 + 1 + np.flatnonzero(~same)).tolist(), j1]
    yield from zip(edges[:-1], edges[1:])


def _settings(spec: Spec, method: Method, values: dict[str, np.ndarray]) -> dict:
    """A launch's settings for members that share one method and dt."""
    dt = values["dt"] if method.adaptive else float(values["dt"][0])
    return dict(n_save=spec.n_save, save_dt=spec.save_dt, dt=dt, rtol=values["rtol"], atol=values["atol"],
                blowup_factor=spec.blowup_factor, device=spec.device, precision=spec.precision,
                block=spec.kernel_block, events=spec.events)


def integrate(spec: Spec, method: Method, values: dict[str, np.ndarray], repeats: int = 0,
              watch=None) -> tuple[Outcome, float]:
    """Integrate members that share one method and dt; returns what the launch did and, when `repeats` > 0, the
    kernel's seconds per member-step (see kernel_seconds_per_step; NaN otherwise). watch as launch.integrate's."""
    scene = spec.model
    settings = _settings(spec, method, values)
    outcome = launch.integrate(scene, method, values, spec.constants, **settings, watch=watch)
    if repeats < 1 or method.closed_form:
        return outcome, np.nan
    stepping = {**settings, "n_save": 2, "save_dt": spec.t_end}  # the same steps, saving only the end
    return outcome, kernel_seconds_per_step(scene, method, values, spec.constants, outcome, repeats, stepping)


def integrate_members(spec: Spec, method: Method, values: dict[str, np.ndarray], first: int, write_samples,
                      repeats: int = 0, watch=None, threads: int | None = None, log=None, segment: int | None = None):
    """Integrate members first, first + 1, ... (one method and dt); returns finish(), which hands their saved
    variables to write_samples(first sample, variables) and returns the per-member records (member,).

    A record in one kernel call (segment_samples) is observed and written in finish(), so that finish can run on
    another thread while the next kernel runs; a record in segments is, segment by segment, as it comes (its
    kernel's buffer is reused), and each finished segment is saved to `log` (a parts.SegmentLog), from whose
    last segment the members continue. watch as launch.integrate's."""
    scene = spec.model
    settings = _settings(spec, method, values)
    segment = segment or segment_samples(spec)
    call = launch.new_launch(scene, method, values, spec.constants, **settings, segment=segment)
    record = Record(spec, method, values, first, call.members, write_samples)
    whole = []
    resume = log and log.resumed(call, record)
    for start, samples in call.segments(threads, watch=watch, resume=resume):
        if call.segment == call.n_save:
            whole.append((start, samples))
        else:
            data = record.add(start, samples())
            if log is not None:
                log.save(start, data, call.state(), record.state())
    outcome = call.outcome()
    stepping = {**settings, "n_save": 2, "save_dt": spec.t_end}  # the same steps, saving only the end

    def finish() -> dict[str, np.ndarray]:
        for start, samples in whole:
            record.add(start, samples())
        return record.records(outcome, lambda: kernel_seconds_per_step(scene, method, values, spec.constants,
                                                                       outcome, repeats, stepping))

    return finish


def integrate_chunk(spec: Spec, start: int, stop: int, sink, repeats: int = 0, watch=None,
                    threads: int | None = None, segment: int | None = None):
    """Integrate members start .. stop - 1 on `threads` threads (default launch.thread_count()); returns finish(),
    which hands their saved variables to sink.write_samples(first member, first sample, variables) (see
    integrate_members) and returns their records and member variables (member, ...: store.member_variables).
    watch(fraction) as launch.integrate's, over the whole range; `segment`: samples per kernel call (default
    segment_samples(spec))."""
    table = members_table(spec, start, stop)
    finishes = []
    for k0, k1 in _same_settings(table, 0, stop - start):
        values = {name: v[k0:k1] for name, v in table.items()}
        fraction = (lambda f, k0=k0, k1=k1: watch((k0 + f * (k1 - k0)) / (stop - start))) if watch else None
        finishes.append(integrate_members(
            spec, METHODS[str(values["method"][0])], values, start + k0,
            lambda first, samples, k0=k0: sink.write_samples(start + k0, first, samples),
            repeats, watch=fraction, threads=threads,
            log=sink.log(start + k0, start + k1) if hasattr(sink, "log") else None, segment=segment))

    def finish() -> dict[str, np.ndarray]:
        records = [f() for f in finishes]
        return {**{name: np.concatenate([r[name] for r in records]) for name in records[0]},
                **member_variables(spec, table, start)}

    return finish


def compute_chunk(spec: Spec, start: int, stop: int, sink, repeats: int = 0, watch=None,
                  threads: int | None = None, segment: int | None = None) -> dict[str, np.ndarray]:
    """integrate_chunk, finished at once: returns the records and member variables (member, ...)."""
    return integrate_chunk(spec, start, stop, sink, repeats, watch, threads, segment)()


class _SegmentDone(Exception):
    """A segment task's segment is finished (raised through integrate_members by CarriedLog.save)."""


class CarriedLog:
    """On a Dask worker, the segment log of one member range (as parts.SegmentLog locally), carried by the tasks
    themselves: the range continues from `carried` (what parts.SegmentLog.kept gives, None: from the start), and
    the integration stops once its next segment is finished, so that the client saves that segment before the
    next task continues it."""

    def __init__(self, carried: dict | None):
        self.carried, self.finished, self.restarted = carried, None, False

    def resumed(self, call, record) -> tuple[int, dict] | None:
        if self.carried is None:
            return None
        if not call.takes(self.carried["state"]):  # a worker of another kernel layout: from the start
            self.restarted = True
            return None
        record.restore(self.carried["noise"], self.carried["amplitudes"], self.carried["errors"])
        return self.carried["sample"], self.carried["state"]

    def save(self, first: int, data: dict[str, np.ndarray], state: dict[str, np.ndarray], record: dict) -> None:
        self.finished = {"first": first, "samples": data, "state": state, "record": record,
                         "restarted": self.restarted}
        raise _SegmentDone


def segment_task(spec: Spec, start: int, stop: int, repeats: int, carried: dict | None, segment: int) -> dict:
    """On a Dask worker: the next segment (of `segment` samples, as the client cut them) of members start ..
    stop - 1 (one launch's settings), continuing from `carried` (None: the first). Returns that segment ("first",
    "samples": saved variables (members, samples, ...), "state", "record", "restarted": it started again from
    sample 0) or, once every segment is done, the members' records and member variables ("records")."""
    from distributed import get_worker

    threads = max(1, launch.thread_count() // get_worker().state.nthreads)
    values = members_table(spec, start, stop)
    log = CarriedLog(carried)
    try:
        spec = replace(spec, kernel_block=few_members_block(spec))  # as a local run would
        finish = integrate_members(spec, METHODS[str(values["method"][0])], values, start, lambda *_: None,
                                   repeats, threads=threads, log=log, segment=segment)
        records = finish()
    except _SegmentDone:
        return {**log.finished, "worker": get_worker().address}
    return {"records": {**records, **member_variables(spec, values, start)}, "worker": get_worker().address}


def one_launch_ranges(spec: Spec, todo: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """The member ranges `todo` cut where the launch's settings change (each a range segment_task takes), from
    the sweep points' settings (no members table is built)."""
    settings = point_settings(spec, grid_points(spec))
    launch_of = [(s["method"], np.nan if s["dt"] is None else s["dt"]) for s in settings]
    out = []
    for start, stop in todo:
        points = np.arange(start // spec.members, (stop - 1) // spec.members + 1)
        table = {"method": np.array([launch_of[p][0] for p in points]),
                 "dt": np.array([launch_of[p][1] for p in points], dtype=float)}
        edges = [max(start, int(points[k0]) * spec.members) for k0, _ in _same_settings(table, 0, len(points))]
        out += list(zip(edges, [*edges[1:], stop]))
    return out


def run(spec: Spec, out: str | Path, *, chunk: int | None = None, progress: bool = True, force: bool = False,
        resume: bool = False, command: str | None = None, client=None, task=None) -> Summary:
    """Integrate every member of `spec` and write the dataset to `out` (NetCDF, or a Zarr store for a name ending
    in .zarr: ensemble.zarr_store); an existing `out` only with
    force. Finished chunks are kept as parts (ensemble.parts) until the result is complete: with `resume`, a run
    stopped midway computes only what its parts lack (raises parts.PartsError if they are another run's).
    `client` (a dask.distributed Client) computes the chunks on its cluster with `task` (default chunk_task, or
    segment_task for records run in segments: cluster.compute_on); chunks that keep failing there raise
    Incomplete after the rest are done. `command` is recorded in the
    file's history (default: `ensemble run <run file>`). A run of few, long members here runs them in a smaller
    block (few_members_block; on a cluster the workers choose it)."""
    spec = replace(spec, kernel_block=None if client else few_members_block(spec))
    return _run(spec, place(out), chunk, progress, force, resume, command, client, task)


def few_members_block(spec: Spec) -> int | None:
    """Members per block for a run of fewer members than its kernels' block, when the block's idle lanes would
    cost more than CHUNK_MEMBER_STEPS (a few seconds; below that a kernel compiled anew for the smaller block
    costs more): the smallest power of 2 that holds the members, at least FEW_MEMBERS_BLOCK. None otherwise, on a
    GPU, and for fields of sites (the chain), whose blocks follow their own rule (ensemble.engine.sites). A block
    computes all its lanes however few are members, and a member's arithmetic does not depend on its block: the
    bits are the same."""
    scene = spec.model
    if spec.device != "cpu" or scene.SITES:
        return None
    block = run_block(replace(spec, kernel_block=None))
    if spec.n_members >= block or steps_per_member(spec) * block < CHUNK_MEMBER_STEPS:
        return None
    return min(block, max(FEW_MEMBERS_BLOCK, 1 << (spec.n_members - 1).bit_length()))


FEW_MEMBERS_BLOCK = 8  # the smallest block: one AVX-512 vector of doubles, two of AVX2


def _run(spec: Spec, out: Path, chunk: int | None, progress: bool, force: bool, resume: bool,
         command: str | None, client, task) -> Summary:
    tuning.prepare()
    folder = _folder_kind(out)
    if resume and folder.left_complete(out, spec):
        folder.discard(out)
        return Summary(0, 0, 0.0, resumed=spec.n_members, complete_already=True)
    if exists(out) and not force:
        raise FileExistsError(f"{out}: exists; pass force=True to replace it")
    if force and not resume:
        folder.discard(out)
    parts = folder(out, spec, resume=resume) if folder is Parts else folder(out, spec, resume=resume, client=client)
    if resume and progress:
        dropped = f"; dropped {', '.join(parts.dropped)}" if parts.dropped else ""
        going = "".join(f"; members {j0} to {j1 - 1} continue from sample {k} of {spec.n_save}"
                        for j0, j1, k in parts.continuing())
        print(f"resuming: {parts.members_done()} of {spec.n_members} members in {len(parts.parts)} part(s) kept"
              f"{going}{dropped}", file=sys.stderr, flush=True)
    held = HeldInterrupts()
    try:
        n = spec.n_members
        chunk = chunk or (dask_chunk(spec, sum(client.nthreads().values())) if client else default_chunk(spec))
        if is_zarr(out):  # a task's range is whole chunks (or a shard): those of the store a resume continues
            chunk = task_members(parts.store, spec) if parts.parts or parts.continuing() else chunk
            task = task or (partial(zarr_task, store=parts.store.resolve(), folder=parts.segments.resolve(),
                                    segment=segment_samples(spec)) if client else None)
        todo = [(j, min(j + chunk, stop)) for start, stop in parts.missing() for j in range(start, stop, chunk)]
        preparing = 0.0 if client or not todo else prepare_kernels(spec, announce=progress)
        _say_tuning(progress)
        repeats = spec.measure["repeats"] if spec.measure["timing"] else 0
        tally = Tally()
        began = time.perf_counter()
        with _writer(out, spec, command, parts, chunk) as result:
            parts.result = result
            with Bar(total=n, initial=parts.members_done(), unit="member", file=sys.stderr, disable=not progress,
                      leave=False, bar_format=BAR) as bar:
                if todo and steps_per_member(spec):
                    bar.set_postfix_str(f"about {n * steps_per_member(spec):.2g} member-steps in all", refresh=False)
                if client is None:
                    _compute_here(spec, todo, parts, tally, bar, repeats)
                else:
                    _compute_on_cluster(client, spec, todo, parts, tally, bar, repeats, task)
            parts.settle()  # every part sealed before the result is complete
            interrupts.check()
            held.start()  # a Ctrl-C from here waits until the result is whole and the parts are gone
            ended = parts.assemble()
    except BaseException as error:
        held.stop()
        with HeldInterrupts():  # a second Ctrl-C must not cut the cleanup short
            kept = parts.close()
            if isinstance(error, SpecError) or not (kept or folder.segments_left(out)):
                folder.discard(out)  # nothing finished, or a member the run file makes bad: no resume can use it
        raise
    folder.discard(out)
    summary = _summary(spec, tally, ended, time.perf_counter() - began, preparing)
    if held.stop():
        raise LateInterrupt(summary)
    return summary


def _folder_kind(out: Path):
    """Where a run keeps what it finished: parts (ensemble.parts) beside NetCDF, receipts beside a Zarr store."""
    if not is_zarr(out):
        return Parts
    problem = zarr_problem()
    if problem:
        raise EnsembleError(f"{out}: {problem}")
    return Receipts


def _writer(out: Path, spec: Spec, command: str | None, parts, chunk: int):
    """The result being written: NetCDF (store.Writer) or a Zarr store (zarr_store.ZarrWriter)."""
    if is_zarr(out):
        return ZarrWriter(out, spec, command, (chunk, segment_samples(spec)),
                          reopen=bool(parts.parts or parts.continuing()))
    return Writer(out, spec, command, reopen=bool(parts.parts or parts.segments))


def zarr_task(spec: Spec, start: int, stop: int, repeats: int = 0, *, store: Path, folder: Path,
              segment: int) -> dict:
    """On a Dask worker: members start .. stop - 1 of `spec` integrated and written into the Zarr store at
    `store` (their chunks, no one else's), `segment` samples at a time (the store's chunks: as the client cut
    them), a record in segments continuing from its last segment kept in `folder` (zarr_store.segments_folder);
    returns their receipt alone (zarr_store.Region.receipt)."""
    from distributed import get_worker

    from .zarr_store import Region

    threads = max(1, launch.thread_count() // get_worker().state.nthreads)
    region = Region(store, spec, start, stop, folder)
    spec = replace(spec, kernel_block=few_members_block(spec))  # as a local run would
    region.write(start, compute_chunk(spec, start, stop, region, repeats, threads=threads, segment=segment))
    return {"receipt": region.receipt()}


def _say_tuning(progress: bool) -> None:
    """What there is to say of this machine's tuning (ensemble.tuning), once the kernels compile: bad input found
    while compiling says its one line alone."""
    said = tuning.pending_line()
    if said and progress:
        print(said, file=sys.stderr, flush=True)


def _compute_on_cluster(client, spec: Spec, todo: list[tuple[int, int]], parts: Parts, tally: Tally, bar: Bar,
                        repeats: int, task) -> None:
    """cluster.compute_on: whole chunks a task each, or, for records run in segments, a segment a task (each
    finished segment a unit that resumes). Into a Zarr store a task writes its whole range, segment by segment
    (the receipt of a range is its unit)."""
    from .cluster import compute_on

    segment = segment_samples(spec)
    if segment < spec.n_save and not isinstance(parts, Receipts):
        compute_on(client, spec, one_launch_ranges(spec, todo), parts, tally, bar, repeats, task or segment_task,
                   segment=segment)
    else:
        compute_on(client, spec, todo, parts, tally, bar, repeats, task or chunk_task)


def _summary(spec: Spec, tally: Tally, ended: np.ndarray, seconds: float, preparing: float) -> Summary:
    """`ended`: how many members ended in each Status (Parts.assemble)."""
    return Summary(tally.members, tally.member_steps, seconds,
                   tally.step_counts.pop() if len(tally.step_counts) == 1 else None,
                   blew_up=int(ended[Status.BLEW_UP]), underflowed=int(ended[Status.STEP_SIZE_UNDERFLOW]),
                   stopped=int(ended[Status.STOPPED_BY_EVENT]),
                   closed_form=all(METHODS[name].closed_form for name in spec.methods), preparing=preparing,
                   resumed=spec.n_members - tally.members)


def chunk_task(spec: Spec, start: int, stop: int, repeats: int = 0):
    """On a Dask worker: members start .. stop - 1 of `spec`, as (saved variables, records), arrays over members."""
    from distributed import get_worker

    from .cluster import Collected

    threads = max(1, launch.thread_count() // get_worker().state.nthreads)
    sink = Collected(spec, start, stop)
    spec = replace(spec, kernel_block=few_members_block(spec))  # as a local run would
    records = compute_chunk(spec, start, stop, sink, repeats, threads=threads)
    return sink.samples, records


def _compute_here(spec: Spec, todo: list[tuple[int, int]], parts: Parts, tally: Tally, bar: Bar,
                  repeats: int) -> None:
    """Compute the member ranges `todo` in this process, in order, each into a new part. While a chunk's kernel
    runs, the chunk before it is observed, written and sealed on a thread of its own, unless its record comes in
    segments (written as they come) or the run times its kernels (which must run alone)."""
    overlap = segment_samples(spec) == spec.n_save and not spec.measure["timing"]
    finishing = ThreadPoolExecutor(1, thread_name_prefix="ensemble-finish") if overlap else None
    pending = None
    try:
        for start, stop in todo:
            interrupts.check()  # a Ctrl-C that a library swallowed
            writer = parts.begin(start, stop)
            try:
                finish = integrate_chunk(spec, start, stop, writer, repeats, watch=_advance(bar, stop - start))
            except BaseException:
                writer.abandon()
                raise
            if pending is not None:
                tally.add(pending.result())  # one chunk waits to be finished at a time: memory stays bounded
            if finishing is None:
                tally.add(_keep(finish, writer))
            else:
                pending = finishing.submit(_keep, finish, writer)
        if pending is not None:
            tally.add(pending.result())
    finally:
        if finishing is not None:
            finishing.shutdown()  # waits for the chunk being written: HDF5 must not be used by two threads at once


def _keep(finish, writer) -> dict[str, np.ndarray]:
    """Finish an integrated chunk into its part `writer` (see integrate_chunk); returns its records."""
    try:
        records = finish()
        writer.write(writer.start, records)
    except BaseException:
        writer.abandon()
        raise
    writer.finish()
    return records


TASKS_PER_WORKER_THREAD = 4  # a cluster run is cut into at least this many tasks per worker thread


def dask_chunk(spec: Spec, threads: int) -> int:
    """Members per task on a cluster with `threads` worker threads in all: default_chunk, but small enough that
    every thread gets TASKS_PER_WORKER_THREAD tasks; a task returns its members' whole record at once, so a
    record run in segments (segment_samples) gets the smallest chunk."""
    if segment_samples(spec) < spec.n_save:
        return smallest_chunk(spec)
    block = run_block(spec)
    share = -(-spec.n_members // (TASKS_PER_WORKER_THREAD * threads))
    return max(smallest_chunk(spec), min(default_chunk(spec), -(-share // block) * block))


def _advance(bar: Bar, members: int):
    """A launch's watch: moves `bar` from where it stands to that plus `members` times the fraction done."""
    start = bar.n

    def watch(fraction: float) -> None:
        bar.n = start + fraction * members
        bar.refresh()

    return watch


def prepare_kernels(spec: Spec, announce: bool = True) -> float:
    """Compile (or load from Numba's disk cache) the run's kernels, observables and (`[measure] growth`) growth
    fit; returns the seconds it took.

    Loading from the cache takes well under a second. When it takes longer
    (compiling, once per machine) and `announce`, one line on stderr says so
    while it happens, and another how long it took.
    """
    scene = spec.model
    names = "/".join(spec.methods)
    said = threading.Event()

    def say():
        said.set()
        print(f"compiling the {names} kernels for {spec.model.NAME} (once per machine; later runs load them) ...",
              file=sys.stderr, flush=True)

    timer = threading.Timer(ANNOUNCE_AFTER, say)
    if announce:
        timer.start()
    start = time.perf_counter()

    def compile_all():
        for name in spec.methods:
            launch.prepare(scene, METHODS[name], spec.constants, device=spec.device, precision=spec.precision,
                           values=members_table(spec, 0, 1), block=spec.kernel_block, events=spec.events)
        one = np.zeros((1, 1, scene.kernel_rows(spec.constants)[0])).transpose(1, 2, 0)  # as a kernel's samples
        scene.observe(one, tuple(scene.OBSERVABLES), members_table(spec, 0, 1), spec.constants)  # what observing
        if spec.measure["growth"]:  # and the growth fit compile, too
            measured_growth(scene.amplitudes(one, members_table(spec, 0, 1), spec.constants), np.zeros(1),
                            np.ones(1))

    try:
        interrupts.on_a_thread(compile_all)
    finally:
        timer.cancel()
    seconds = time.perf_counter() - start
    if said.is_set():
        print(f"compiled in {seconds:.1f} s", file=sys.stderr, flush=True)
    return seconds


def simulate(spec: Spec, *, chunk: int | None = None):
    """Run `spec` and return its dataset in memory (xarray), through the same file path as `run`."""
    import xarray as xr

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "result.nc"
        run(spec, path, chunk=chunk, progress=False)
        return xr.load_dataset(path)
