"""The one way into the kernels: integrate(scene, method, values, constants, ...) -> Outcome.

The runner, `prepare`, the tests and every benchmark call this. A scene's kernels come from
ensemble.engine.kernels (its family's code bound to the scene's physics); they follow one of two call
conventions, over arrays laid out by block (see engine.blocks):

- fixed step: kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works, start,
  first_block, end_block);
- adaptive:   kernel(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, progress, works,
  start, first_block, end_block), control (3, members): first trial step (s; <= 0: estimate it), rtol, atol.

state0 and rate are (blocks, rows, B) (rows from the scene's kernel_rows),
limit (members,) the largest |state component| a member may reach, samples
(members, count, state rows), member by member (the saved variables' layout,
so nothing is transposed between the kernel and the file): samples start ..
start + count - 1 of the run, counts (3, members) as results.COUNTS, status
(members,), failure_time (members,; s), progress (blocks,; int64) the last of
`samples` each block has stored, and works (blocks, kernel.rows x B) each block's work array, zeroed
before the first call. A call with start = 0 starts the blocks from state0;
a later one continues from where `works` stands, so a run in several calls
(segments of its samples) gives the bits of one call. A call integrates blocks first_block
.. end_block - 1 on the calling thread without the GIL; `run_blocks` spreads a
launch's blocks over threads. Kernels are not compiled with parallel=True:
Numba's parallel lowering made compiling a kernel take twice as long
(analysis/bench/compile_time.py).
"""
from __future__ import annotations

import errno
import sys
import threading
from pathlib import Path

import numba
import numpy as np

from ..errors import EXIT_FAILED, EnsembleError
from ..methods import Method
from ..results import DEFAULT_BLOWUP_FACTOR, Outcome, Status
from ..scenes.contract import SceneError
from ..tuning import applied
from . import kernels
from .blocks import flush_subnormals, restore_float_mode
from .events import EVENT_STATE, event_spec, started
from .exact_events import ExactEvents
from .inputs import adaptive_control, blowup_limits, fixed_counts


def layout(scene, method: Method, constants: dict, block: int | None = None, events: tuple = ()) -> kernels.Layout:
    """The layout of a scene's CPU kernel for `method` (kernels.layout) with `events` (results.Event), computed
    without making the kernel; the closed form has no kernel: no rows (its block is the one a kernel would have:
    records times it so)."""
    if method.closed_form:
        return kernels.Layout(kernels.block_size(scene, constants, method, block, applied()), 0)
    return kernels.layout(scene, method, constants, block, events=tuple(event.source for event in events))


def integrate(scene, method: Method, values: dict[str, np.ndarray], constants: dict, *, n_save: int,
              save_dt: float, dt=None, rtol=None, atol=None,
              blowup_factor: float = DEFAULT_BLOWUP_FACTOR, watch=None, device: str = "cpu",
              precision: str = "float64", block: int | None = None, events: tuple = ()) -> Outcome:
    """Integrate the members described by `values` with `method`, saving n_save samples every save_dt (s).

    Fixed-step methods take the step dt (s, one value; save_dt a whole multiple
    of it). Adaptive methods take rtol and atol (per member or one value) and
    dt as the first trial step (NaN or None: estimated). The closed form is
    evaluated at the saved times. A member fails when its state is not finite
    or a component outgrows blowup_factor times its largest component at the
    start (checked at every saved sample), or when its adaptive step size
    underflows; it stops there and its later samples are NaN. A member's result
    depends only on its own values: never on how many members run with it,
    the chunking or the thread count. watch(fraction done) is called every WATCH_SECONDS while the kernel runs.
    `block`: members per kernel block for a run of few members (None: block_size's); the bits do not depend on it.
    `events` (results.Event): crossings located within each step (ensemble.engine.events), in the Outcome.
    """
    call = new_launch(scene, method, values, constants, n_save=n_save, save_dt=save_dt, dt=dt, rtol=rtol, atol=atol,
                      blowup_factor=blowup_factor, device=device, precision=precision, block=block, events=events)
    call.run(watch=watch)
    return call.outcome()


def new_launch(scene, method: Method, values: dict[str, np.ndarray], constants: dict, *, device: str = "cpu",
               **settings):
    """A launch of `values` on `device`: a Launch on this machine's cores, or for "cuda" an
    ensemble.engine.gpu_launch.GpuLaunch, which does the same on a GPU (in settings' `precision`, "float64" or
    "float32"). A closed form is evaluated with NumPy, on the CPU, whatever the device. `settings` are Launch's."""
    if device == "cuda" and not method.closed_form:
        from .gpu_launch import GpuLaunch

        settings.pop("block", None)  # a CPU kernel's layout
        return GpuLaunch(scene, method, values, constants, **settings)
    return Launch(scene, method, values, constants, **settings)


class Launch:
    """`integrate` in parts, on this machine's cores (new_launch chooses the device): the constructor lays out the
    inputs in the kernel's blocks; `segments` runs the kernel on them (anew each time), `segment` samples per
    kernel call, and yields each call's samples; `run` keeps them all; `outcome` returns what the last run did."""

    def __init__(self, scene, method: Method, values: dict[str, np.ndarray], constants: dict, *, n_save: int,
                 save_dt: float, dt=None, rtol=None, atol=None, blowup_factor: float = DEFAULT_BLOWUP_FACTOR,
                 segment: int | None = None, precision: str = "float64", block: int | None = None,
                 events: tuple = ()):
        self.scene, self.method, self.n_save, self.save_dt, self.dt = scene, method, n_save, save_dt, dt
        self.events = tuple(events)
        self.segment = max(1, min(segment or n_save, n_save))
        self.members = len(next(iter(values.values())))
        if method.closed_form:
            step = save_dt if dt is None or not np.isfinite(dt) else float(dt)
            spacing = round(save_dt / step) * step
            self.exact = lambda first, count: scene.exact(values, constants, np.arange(first, first + count) * spacing)
            self.watcher = ExactEvents(scene, values, constants, self.events, step, round(save_dt / step)) \
                if self.events else None
            return
        state0, rate = scene.inputs(values, constants)
        self.layout = layout(scene, method, constants, block, self.events)
        self.kernel = kernels.kernel(scene, method, constants, self.layout)
        block = self.layout.block
        limit = blowup_limits(state0, blowup_factor)
        if method.adaptive:
            control = adaptive_control(dt, rtol, atol, self.members)
            state0, rate, control, limit = _padded((state0, rate, control, limit[None]), block)
            self.control = control
        else:
            state0, rate, limit = _padded((state0, rate, limit[None]), block)
            self.steps_per_save = round(save_dt / dt)
        padded = state0.shape[1]
        blocks = padded // block
        self.state0, self.rate, self.limit = blocked(state0, block), blocked(rate, block), limit[0]
        self.state_rows = state0.shape[0]
        self.works = np.zeros((blocks, self.kernel.rows * block))
        self.status, self.failure_time = np.zeros(padded), np.empty(padded)
        self.progress = np.zeros(blocks, dtype=np.int64)
        self.counts = np.zeros((3, padded)) if method.adaptive else None  # fixed steps are counted afterwards
        if self.events:
            self.event_spec = event_spec(self.events)  # its arrays are made at each run's start (segments)

    def segments(self, threads: int | None = None, watch=None, resume: tuple[int, dict] | None = None):
        """Run the kernel (or evaluate the closed form) from the start, on `threads` threads (default
        thread_count()); yields (first, samples) per call, samples() returning samples first .. first + count - 1
        as (count, state rows, members): a view of the array the kernel wrote, member by member (a new one each
        call, so it may be read on another thread while the next call runs). watch(fraction of the run done), if
        given, is called from this thread while it waits. A run in segments gives the bits of one in a single
        call: each call continues from the work arrays the last one left. resume = (sample, state()) continues a
        run that had made samples 0 .. sample - 1 and then stopped, from what state() gave there."""
        first_sample = resume[0] if resume else 0
        if self.method.closed_form:
            yield from self._closed_form(first_sample, resume)
            return
        self.status[:] = 0.0
        self.failure_time[:] = np.nan
        self.works[:] = 0.0

        if self.method.adaptive:
            self.counts[:] = 0.0
            head = (self.state0, self.rate, self.control, float(self.save_dt), self.limit)
            tail = (self.counts, self.status, self.failure_time, self.progress, self.works)
        else:
            head = (self.state0, self.rate, float(self.dt), int(self.steps_per_save), self.limit)
            tail = (self.status, self.failure_time, self.progress, self.works)
        if self.events:
            self.__dict__.update(started(self.events, self.state_rows, self.status.size))
            tail += ((self.event_spec, *(getattr(self, name) for name in EVENT_STATE)),)
        for name, value in (resume[1] if resume else {}).items():
            getattr(self, name)[:] = value
        for first in range(first_sample, self.n_save, self.segment):
            samples = np.empty((self.members, min(self.segment, self.n_save - first), self.state_rows))
            self.progress[:] = 0
            done = None if watch is None else (
                lambda: watch(min(1.0, (first + self.progress.mean()) / max(self.n_save - 1, 1))))
            try:
                run_blocks(self.kernel.function, (*head, samples, *tail, first), self.state0.shape[0], threads, done)
            except Exception as error:  # noqa: BLE001 (only a scene's own code raises inside a kernel)
                stop = min(first + self.segment, self.n_save) - 1
                raise SceneRaised(f"{self.scene.PHYSICS}: raised {type(error).__name__}: {error}, between "
                                  f"t = {first * self.save_dt:g} and {stop * self.save_dt:g} s") from None
            yield first, lambda samples=samples: samples.transpose(1, 2, 0)

    def _closed_form(self, first_sample: int, resume: tuple[int, dict] | None):
        """segments of the closed form: its samples, and its events (ExactEvents) where the run has them."""
        if self.watcher is not None:
            self.watcher.reset()
            for name, value in (resume[1] if resume else {}).items():
                getattr(self.watcher, name)[:] = value
        for first in range(first_sample, self.n_save, self.segment):
            exact = self.exact(first, min(self.segment, self.n_save - first))
            if self.watcher is not None:
                self.watcher.watch(first, exact)
            yield first, lambda exact=exact: exact

    def state(self) -> dict[str, np.ndarray]:
        """Copies of what the kernel continues from (work arrays, status, failure times, adaptive counts), as the
        last segment that `segments` yielded left them: `segments(resume=(its first + count, state()))` continues
        from there, to the same bits. Empty for a closed form."""
        if self.method.closed_form:
            return self.watcher.state() if self.watcher is not None else {}
        names = ("works", "status", "failure_time") + (("counts",) if self.method.adaptive else ())
        names += EVENT_STATE if self.events else ()
        return {name: getattr(self, name).copy() for name in names}

    def takes(self, state: dict[str, np.ndarray]) -> bool:
        """Whether `state` (from state()) is of this launch's layout: the same arrays, shapes and types."""
        mine = self.state()
        return mine.keys() == state.keys() and all(
            mine[k].shape == state[k].shape and mine[k].dtype == state[k].dtype for k in mine)

    def run(self, threads: int | None = None, watch=None) -> None:
        """Run the whole record (as `segments`), keeping every sample for `outcome`."""
        parts = [samples() for _, samples in self.segments(threads, watch)]
        self.samples = parts[0] if len(parts) == 1 else np.concatenate(parts)

    def outcome(self) -> Outcome:
        """What the last `run` did, per member: samples (n_save, state rows, members), counts, status and failure
        time (with `segments`, counts, status and failure time only)."""
        samples = getattr(self, "samples", None)
        n = self.members
        if self.method.closed_form:
            if self.watcher is None:
                return Outcome(samples, np.zeros((3, n), np.int64), np.zeros(n, np.int8), np.full(n, np.nan))
            watched = self.watcher
            return Outcome(samples, np.zeros((3, n), np.int64), watched.status.astype(np.int8), np.full(n, np.nan),
                           watched.event_times.copy(), watched.event_counts.astype(np.int64), watched.stopped.copy(),
                           watched.event_states.copy())
        ended = self.failure_time[:n].copy()  # a failure's time, or a stop's (ensemble.engine.events)
        if self.method.adaptive:
            counts = self.counts[:, :n].astype(np.int64)
        else:
            counts = fixed_counts(self.method, self.scene, ended, self.dt, self.steps_per_save * (self.n_save - 1))
        failure_time = np.where(self.status[:n] == Status.STOPPED_BY_EVENT, np.nan, ended)
        if not self.events:
            return Outcome(samples, counts, self.status[:n].astype(np.int8), failure_time)
        return Outcome(samples, counts, self.status[:n].astype(np.int8), failure_time,
                       self.event_times[:, :, :n].copy(), self.event_counts[:, :n].astype(np.int64),
                       self.stopped[:, :n].copy(), self.event_states[..., :n].copy())


class SceneRaised(EnsembleError):
    """A scene's own code raised an exception inside a kernel, during the run (exit status 3)."""

    exit_status = EXIT_FAILED


def thread_count() -> int:
    """Threads a launch runs on unless told otherwise: NUMBA_NUM_THREADS, by default the cores Numba sees."""
    return numba.config.NUMBA_NUM_THREADS


TASKS_PER_THREAD = 4  # a launch's blocks go to threads in this many groups per thread, so none waits long at the end
WATCH_SECONDS = 0.2  # how often the waiting thread calls `watch`


def run_blocks(kernel, arguments: tuple, blocks: int, threads: int | None = None, watch=None) -> None:
    """Call kernel(*arguments, first_block, end_block) over blocks 0 .. blocks - 1 in contiguous groups on
    `threads` threads (default thread_count()), calling watch() every WATCH_SECONDS while they run and once at
    the end. Each block's result depends on that block alone, so the grouping and the thread count leave every
    value unchanged.

    The threads are daemons and the calling thread only waits: Ctrl-C (KeyboardInterrupt) reaches the caller at
    once, and the process may exit while a kernel call is still running, without waiting for it.
    """
    threads = max(1, min(threads or thread_count(), blocks))
    bounds = np.linspace(0, blocks, min(blocks, TASKS_PER_THREAD * threads) + 1).round().astype(int)
    groups = iter(list(zip(bounds[:-1].tolist(), bounds[1:].tolist())))
    lock, failures = threading.Lock(), []

    def work():
        mode = flush_subnormals()
        try:
            while not failures:
                with lock:
                    group = next(groups, None)
                if group is None:
                    return
                try:
                    kernel(*arguments, *group)
                except BaseException as error:  # noqa: BLE001 (handed to the caller)
                    failures.append(error)
        finally:
            restore_float_mode(mode)

    workers = [threading.Thread(target=work, daemon=True, name="ensemble-kernel") for _ in range(threads)]
    for worker in workers:
        worker.start()
    for worker in workers:
        while worker.is_alive():
            worker.join(WATCH_SECONDS)
            if watch is not None:
                watch()
    if failures:
        raise failures[0]
    if watch is not None:
        watch()  # once more when every block is done


def prepare(scene, method: Method, constants: dict, device: str = "cpu", precision: str = "float64",
            values: dict | None = None, block: int | None = None, events: tuple = ()) -> None:
    """Compile (or load from Numba's disk cache) the kernel of a stepping method, on one empty block of `block`
    members (None: block_size's; on a GPU, on the first member of `values`, saving only its start). A scene whose
    functions Numba cannot compile raises SceneError, one line saying why."""
    if method.closed_form:
        return
    try:
        if device == "cuda":
            new_launch(scene, method, values, constants, n_save=1, save_dt=1.0, dt=values["dt"] if method.adaptive
                       else 1.0, rtol=values["rtol"], atol=values["atol"], device=device, precision=precision,
                       events=events).run()
            return
        _call_fresh(scene, method, constants, block, events)
    except Exception as error:  # Numba's errors (numba-cuda has classes of its own)
        if not type(error).__module__.startswith("numba"):
            raise
        cause = _numba_cause(str(error))
        raise SceneError(f"{scene.PHYSICS}: the {method.name} kernel does not compile: {cause}") from None


def _numba_cause(message: str) -> str:
    """The informative line of a Numba error message (its first lines name the compiler pass that failed)."""
    skip = ("Failed in", "During:", "File ", "<source", "^", "No implementation of function", "There are")
    lines = [line.strip() for line in message.splitlines()]
    useful = [line for line in lines if line and not line.startswith(skip)]
    return (useful[0] if useful else lines[0])[:300]


def _call_fresh(scene, method: Method, constants: dict, block: int | None = None, events: tuple = ()) -> None:
    """_call_once; where Numba's disk cache of the kernel cannot be loaded (a truncated or damaged file), its
    cache files are deleted, with one line said, and the kernel compiled again; where it cannot be written (a
    full disk, a folder that cannot be written), one line says so and the kernel compiled here is used."""
    try:
        _call_once(scene, method, constants, block, events)
    except Exception as error:  # noqa: BLE001 (unpickling and LLVM's parser raise many kinds)
        made = kernels.kernel(scene, method, constants, layout(scene, method, constants, block, events)).function
        files = cache_files(made)
        cannot_write = isinstance(error, OSError) and error.errno in CANNOT_WRITE
        if not files and not cannot_write:  # nothing was cached: the kernel does not compile
            raise
        for file in files:
            file.unlink(missing_ok=True)
        if cannot_write:
            print(f"ensemble: cannot write Numba's cache of the {method.name} kernel in {cache_folder(made)} "
                  f"({error.strerror}); every run compiles it again until it can", file=sys.stderr, flush=True)
        else:
            print(f"ensemble: Numba's cache of the {method.name} kernel in {files[0].parent} could not be loaded "
                  f"({type(error).__name__}); compiling it again", file=sys.stderr, flush=True)
        _call_once(scene, method, constants, block, events)


CANNOT_WRITE = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM}  # a cache that cannot be saved


def cache_folder(dispatcher) -> Path | None:
    """Where Numba keeps the disk cache of a compiled function (None if it has none)."""
    files = getattr(getattr(dispatcher, "_cache", None), "_cache_file", None)  # numba.core.caching's
    return Path(files._cache_path) if hasattr(files, "_index_name") else None


def cache_files(dispatcher) -> list[Path]:
    """The files of Numba's disk cache of a compiled function (its index and its data)."""
    folder = cache_folder(dispatcher)
    if folder is None:
        return []
    stem = dispatcher._cache._cache_file._index_name.removesuffix(".nbi")
    return sorted([*folder.glob(f"{stem}.nbi"), *folder.glob(f"{stem}.*.nbc")])


def _call_once(scene, method: Method, constants: dict, block: int | None = None, events: tuple = ()) -> None:
    state_rows, rate_rows = scene.kernel_rows(constants)
    chosen = layout(scene, method, constants, block, events)
    kernel, block = kernels.kernel(scene, method, constants, chosen), chosen.block
    works = np.zeros((1, kernel.rows * block))
    state0, rate = np.zeros((1, state_rows, block)), np.zeros((1, rate_rows, block))
    samples = np.empty((block, 1, state_rows))
    limit, status, failure_time, progress = np.ones(block), np.zeros(block), np.zeros(block), np.zeros(1, np.int64)
    E = len(events)
    watched = ((np.zeros((E, 5)), np.zeros((E, 1, block)), np.zeros((E, block)), np.zeros((state_rows, block)),
                np.zeros((E, 1, state_rows, 1))),) if events else ()
    if method.adaptive:
        kernel.function(state0, rate, np.ones((3, block)), 1.0, limit, samples, np.zeros((3, block)), status,
                        failure_time, progress, works, *watched, 0, 0, 1)
    else:
        kernel.function(state0, rate, 1.0, 1, limit, samples, status, failure_time, progress, works, *watched, 0, 0,
                        1)


def _padded(arrays, block: int) -> tuple[np.ndarray, ...]:
    """(rows, members) arrays padded to a whole number of blocks with copies of the last member."""
    n = arrays[0].shape[1]
    extra = -(-n // block) * block - n
    return tuple(np.ascontiguousarray(np.concatenate([x, np.repeat(x[:, -1:], extra, axis=1)], axis=1) if extra else x)
                 for x in arrays)


def blocked(x: np.ndarray, block: int) -> np.ndarray:
    """A (rows, members) array, members a multiple of block, in a kernel's layout (members / block, rows, block)."""
    rows, members = x.shape
    return np.ascontiguousarray(x.reshape(rows, members // block, block).transpose(1, 0, 2))
