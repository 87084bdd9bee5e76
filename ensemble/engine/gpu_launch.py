"""A scene's CUDA kernel, chosen (`kernel`: one thread per member, or a field of sites' layout), and launched
(`GpuLaunch`: launch.Launch on a GPU, the arrays on the GPU, samples copied back on a stream of their own)."""
from __future__ import annotations

import numpy as np
from numba import cuda

from ..methods import Method
from ..results import DEFAULT_BLOWUP_FACTOR, Outcome, Status
from .events import EVENT_STATE, event_spec, start_values
from .gpu import THREADS, GpuKernel, member_kernel, require_gpu
from .gpu import work_rows as member_work_rows
from .gpu_device import PRECISIONS
from .gpu_sites import site_threads, sites_kernel
from .gpu_sites import work_rows as sites_work_rows
from .inputs import adaptive_control, blowup_limits, fixed_counts
from .kernels import Layout, scene_identity


@cuda.jit(cache=True)
def fill(flat, value):
    i = cuda.grid(1)
    if i < flat.size:
        flat[i] = value


def filled(array, value, stream) -> None:
    """Sets every element of a C-ordered device array to value, on the GPU."""
    if array.size:
        fill[-(-array.size // THREADS), THREADS, stream](array.reshape(array.size), value)


def layout(scene, method: Method, constants: dict, events: tuple = ()) -> Layout:
    """The Layout of a scene's CUDA kernel for `method`: a thread per member, THREADS members to a block of
    threads, or a field of sites' threads per member (gpu_sites.site_threads), then a member to a block. events:
    each one's results.Event.source (a field of sites with events takes one thread to a member)."""
    if scene.SITES:
        n = constants["n"]
        threads = site_threads(n, method, events)
        return Layout(1 if threads > 1 else THREADS, sites_work_rows(method, n, len(events)), threads=threads,
                      events=tuple(events))
    D = scene.kernel_rows(constants)[0]
    return Layout(THREADS, member_work_rows(method, D, len(events)), events=tuple(events))


def kernel(scene, method: Method, constants: dict, precision: str = "float64", chosen: Layout | None = None
           ) -> GpuKernel:
    """The CUDA kernel of a stepping method for a scene in the `chosen` layout (default: `layout`'s), compiled
    when first launched."""
    chosen = chosen or layout(scene, method, constants)
    D, P = scene.kernel_rows(constants)
    sources = scene_identity(scene)  # a cache key: an edited scene is another kernel
    if scene.SITES:
        return sites_kernel(scene.NAME, scene.PHYSICS, sources, tuple(scene.PIECES), method, constants["n"],
                            constants["boundary"] == "periodic", precision, chosen)
    return member_kernel(scene.NAME, scene.PHYSICS, sources, tuple(scene.PIECES), method, D, P, precision, chosen)


class GpuLaunch:
    """launch.Launch on a GPU: the same arguments, `segments`, `run` and `outcome`; the arrays live on the GPU, one
    thread per member. Each segment's samples are copied back on a stream of their own while the next segment
    integrates."""

    def __init__(self, scene, method: Method, values: dict[str, np.ndarray], constants: dict, *, n_save: int,
                 save_dt: float, dt=None, rtol=None, atol=None, blowup_factor: float = DEFAULT_BLOWUP_FACTOR,
                 segment: int | None = None, precision: str = "float64", events: tuple = ()):
        require_gpu()
        self.scene, self.method, self.n_save, self.save_dt, self.dt = scene, method, n_save, save_dt, dt
        self.events = tuple(events)
        self.segment = max(1, min(segment or n_save, n_save))
        self.members = len(next(iter(values.values())))
        self.real = PRECISIONS[precision]
        self.buffers = {}  # see _buffer
        state0, rate = scene.inputs(values, constants)
        self.state_rows = state0.shape[0]
        chosen = layout(scene, method, constants, tuple(e.source for e in self.events))
        self.kernel = kernel(scene, method, constants, precision, chosen)
        if self.events:
            self.event_spec = cuda.to_device(event_spec(self.events))
        self.no_events = () if self.events else tuple(cuda.to_device(np.zeros(shape)) for shape in (
            (0, 5), (0, 1, 1), (0, 1), (self.state_rows, 1), (0, 1, self.state_rows, 1)))  # a member kernel's
        # (or a field of sites') event arguments where it has none
        self.limit = cuda.to_device(blowup_limits(state0, blowup_factor).astype(self.real))
        self.state0 = cuda.to_device(np.ascontiguousarray(state0, dtype=self.real))
        self.rate = cuda.to_device(np.ascontiguousarray(rate, dtype=self.real))
        if method.adaptive:
            self.control = cuda.to_device(adaptive_control(dt, rtol, atol, self.members))
            self.head = (self.state0, self.rate, self.control, float(save_dt), self.limit)
        else:
            self.steps_per_save = round(save_dt / dt)
            self.head = (self.state0, self.rate, float(dt), int(self.steps_per_save), self.limit)

    def segments(self, threads: int | None = None, watch=None, resume: tuple[int, dict] | None = None):
        """As launch.Launch.segments (threads is ignored): yields (first, samples) per kernel call, samples()
        returning (count, state rows, members) float64 in host memory. Segment k + 1 integrates while the caller
        handles segment k, whose samples are overwritten by segment k + 2: the caller copies what it keeps."""
        n = self.members
        compute, copy = cuda.stream(), cuda.stream()
        if resume is None:
            start = self._started(compute)
        else:
            start = dict(resume[1])
            for name, value in start.items():
                setattr(self, name, cuda.to_device(value, stream=compute))
        tail = ((self.counts,) if self.method.adaptive else ()) + (self.status, self.failure_time, self.works)
        watched = (self.event_spec, *(getattr(self, name) for name in EVENT_STATE)) if self.events else self.no_events
        chosen = self.kernel.layout
        grid, block = max(1, -(-n // chosen.block)), chosen.block * chosen.threads  # blocks, threads per block
        copied, waiting = {}, None
        for k, first in enumerate(range(resume[0] if resume else 0, self.n_save, self.segment)):
            count = min(self.segment, self.n_save - first)
            shape = (count, self.state_rows, n)
            if k >= 2:
                copied[k - 2].wait(compute)  # its buffer is copied out before this segment overwrites it
            samples = self._buffer(("device", k % 2, shape), lambda: cuda.device_array(shape, dtype=self.real))
            self.kernel.function[grid, block, compute](*self.head, samples, *tail, first, n, *watched)
            snapshot = {name: getattr(self, name).copy_to_host(self._buffer(
                ("state", k % 2, name), lambda name=name: cuda.pinned_array(start[name].shape, start[name].dtype)),
                stream=compute) for name in start} if self.segment < self.n_save else {}  # state() of a
            # segment handed on; a record in one call is never continued, and needs no copy of its kernel state
            integrated = cuda.event()
            integrated.record(compute)
            integrated.wait(copy)
            host = self._buffer(("host", k % 2, shape), lambda: cuda.pinned_array(shape, dtype=self.real))
            samples.copy_to_host(host, stream=copy)
            copied[k] = cuda.event()
            copied[k].record(copy)
            if waiting is not None:
                yield self._handed(waiting, watch)
            waiting = (first, count, host, copied[k], snapshot)
        if waiting is not None:
            yield self._handed(waiting, watch)
        cuda.synchronize()

    def _start_values(self) -> dict[str, tuple[tuple[int, ...], type, float]]:
        """Each kernel-state array's (shape, dtype, value at a run's start): no status, no failure time (NaN), no
        steps counted, the events' start_values."""
        n = self.members
        return {"status": ((n,), np.int8, 0), "failure_time": ((n,), np.float64, np.nan),
                "works": ((self.kernel.rows, n), np.float64, 0.0),
                **({"counts": ((3, n), np.float64, 0.0)} if self.method.adaptive else {}),
                **({name: (shape, np.float64, value) for name, (shape, value)
                    in start_values(self.events, self.state_rows, n).items()} if self.events else {})}

    def _started(self, stream) -> dict[str, object]:
        """The kernel's state at a run's start (_start_values), made on the GPU in arrays kept for the launch's
        later runs: uploading 10^7 members' zeros would cost as much as integrating them."""
        start = {}
        for name, (shape, dtype, value) in self._start_values().items():
            start[name] = self._buffer(("start", name), lambda shape=shape, dtype=dtype: cuda.device_array(
                shape, dtype))
            filled(start[name], value, stream)
            setattr(self, name, start[name])
        return start

    def _buffer(self, key, make):
        """A buffer kept for later segments and runs of this launch: allocating pinned memory costs about as much
        as copying into it (0.3 s for 512 MB). Segments alternate between two: segment k's samples are handed on
        (the caller is done with them) before segment k + 2 is copied into the same buffer."""
        if key not in self.buffers:
            self.buffers[key] = make()
        return self.buffers[key]

    def _handed(self, waiting, watch):
        first, count, host, event, self._state = waiting
        event.synchronize()
        if watch is not None:
            watch(min(1.0, (first + count - 1) / max(self.n_save - 1, 1)))
        return first, lambda: host if host.dtype == np.float64 else host.astype(np.float64)

    def state(self) -> dict[str, np.ndarray]:
        """As launch.Launch.state: copies, in host memory, of what the last segment handed on left (empty for a
        record in one kernel call, which is never continued)."""
        return {name: value.copy() for name, value in self._state.items()}

    def takes(self, state: dict[str, np.ndarray]) -> bool:
        mine = self._start_values()
        return mine.keys() == state.keys() and all((v.shape, v.dtype) == mine[k][:2] for k, v in state.items())

    def run(self, threads: int | None = None, watch=None) -> None:
        keep = np.array if self.segment < self.n_save else np.asarray  # segments share two buffers: copies
        parts = [keep(samples()) for _, samples in self.segments(threads, watch)]
        self.samples = parts[0] if len(parts) == 1 else np.concatenate(parts)

    def outcome(self) -> Outcome:
        """As launch.Launch.outcome: a stopped member's failure time is its stop's until its steps are counted."""
        status, ended = self.status.copy_to_host(), self.failure_time.copy_to_host()
        if self.method.adaptive:
            counts = self.counts.copy_to_host().astype(np.int64)
        else:
            counts = fixed_counts(self.method, self.scene, ended, self.dt, self.steps_per_save * (self.n_save - 1))
        failure_time = np.where(status == Status.STOPPED_BY_EVENT, np.nan, ended)
        if not self.events:
            return Outcome(getattr(self, "samples", None), counts, status, failure_time)
        times, event_counts, stopped, states = (getattr(self, name).copy_to_host() for name in EVENT_STATE)
        return Outcome(getattr(self, "samples", None), counts, status, failure_time, times,
                       event_counts.astype(np.int64), stopped, states)
