"""The method families as CUDA kernels (numba-cuda): one GPU thread per member, its state in registers.

The same method data (ensemble.methods, through blocks.method_constants and adaptive_constants) and the same scene
physics as the CPU kernels (ensemble.engine.templates): the scene's functions are compiled as CUDA device
functions, and the stage loops, the splitting's sequence and the step control are written out for one member.
What differs from the CPU is where a member lives: a thread (cuda.grid) instead of a block lane, its state in
scalar variables, and the arrays in (rows, members) order so that neighbouring threads touch neighbouring memory.

A scene whose state is a field of sites (the chain: positions and velocities of n masses joined to their
neighbours) keeps it in one thread's local arrays, or, from SHARED_SITES sites on, spreads it over a block of
threads with the positions in shared memory (`SITES_*` templates, site_threads).

Without a GPU the kernels run under numba-cuda's simulator (NUMBA_ENABLE_CUDASIM=1), which the tests use.
"""
from __future__ import annotations

import hashlib
import math
import types
from functools import cache
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..errors import DeviceUnavailable
from ..methods import Method
from ..results import DEFAULT_BLOWUP_FACTOR, Outcome, Status
from .blocks import FIRST_LOG2_ERR_PREVIOUS, adaptive_constants, method_constants
from .inputs import adaptive_control, blowup_limits, fixed_counts
from .kernels import factor_counts, load_source, loaded, scene_identity

THREADS = 128  # threads per CUDA block
PRECISIONS = {"float64": np.float64, "float32": np.float32}
OK, BLEW_UP, UNDERFLOW = int(Status.OK), int(Status.BLEW_UP), int(Status.STEP_SIZE_UNDERFLOW)
#: A hash of this file and of blocks.py and results.py, which every CUDA kernel's file holds: numba-cuda's disk cache
#: (`cache=True`) keys a kernel on its own file, and would otherwise load one compiled before a device helper changed.
GPU_HELPERS = hashlib.sha256(b"".join((Path(__file__).parent / name).read_bytes()
                                      for name in ("gpu.py", "blocks.py", "../results.py"))).hexdigest()


def require_gpu() -> str:
    """The GPU's name, or DeviceUnavailable saying what is missing. The simulator counts as a GPU."""
    try:
        from numba import cuda
    except ImportError:  # pragma: no cover (numba-cuda is a test dependency)
        raise DeviceUnavailable("device cuda needs numba-cuda: pip install 'ensemble[cuda]'") from None
    if simulated():
        return "numba-cuda simulator"
    try:
        available = cuda.is_available()
    except Exception as error:  # noqa: BLE001 (the driver's own words)
        raise DeviceUnavailable(f"device cuda: no usable GPU ({str(error).splitlines()[0][:200]})") from None
    if not available:
        raise DeviceUnavailable("device cuda: no CUDA GPU or driver found on this machine "
                                "(numba.cuda.is_available() is False)")
    name = cuda.get_current_device().name
    return name.decode() if isinstance(name, bytes) else str(name)


def simulated() -> bool:
    from numba import config
    return bool(config.ENABLE_CUDASIM)


# ---------------------------------------------------------------- the scene's functions as device functions

def _sin_cos(x):
    return math.sin(x), math.cos(x)


# CPU helpers a scene's physics may call, and what a device function calls instead: blocks.sin_cos is written in
# LLVM intrinsics for the CPU's vector units; a GPU has its own sin and cos.
DEVICE_EQUIVALENTS = {"ensemble.engine.blocks.sin_cos": _sin_cos}


def device_function(function, done: dict | None = None):
    """`function` (plain Python or @njit) compiled as a CUDA device function, the compiled helpers it calls
    replaced by device functions too (DEVICE_EQUIVALENTS where the CPU's are written for vector units)."""
    from numba import cuda
    from numba.core.registry import CPUDispatcher

    done = {} if done is None else done
    python = function.py_func if isinstance(function, CPUDispatcher) else function
    if python in done:
        return done[python]
    names = dict(python.__globals__)
    for name in python.__code__.co_names:
        value = names.get(name)
        if isinstance(value, CPUDispatcher):
            key = f"{value.py_func.__module__}.{value.py_func.__name__}"
            equivalent = DEVICE_EQUIVALENTS.get(key)
            names[name] = device_function(equivalent or value, done)
    rebuilt = types.FunctionType(python.__code__, names, python.__name__, python.__defaults__, python.__closure__)
    done[python] = cuda.jit(device=True)(rebuilt)
    return done[python]


@cache
def device_functions(where: str, names: tuple[str, ...], expected: str) -> tuple:
    """A scene's functions `names` (its physics module `where`, whose sources must still be of identity
    `expected`: kernels.loaded) as device functions."""
    module = loaded(where, expected)
    done: dict = {}
    return tuple(device_function(getattr(module, name), done) for name in names)


# ---------------------------------------------------------------- templates

HEADER = '''"""Generated by ensemble.engine.gpu: the {family} CUDA kernel of {scene}, method {method}, {precision}.

Do not edit: ensemble writes a new file whenever the template or the scene's physics changes.
"""
# physics: {physics_hash}
# helpers: {helpers}
import math

from numba import cuda, float32, float64, int8

from ensemble.engine.gpu import device_functions, device_helpers

next_step, = device_helpers()

{physics_import}

REAL = {precision}
D, P = {D}, {P}  # state rows, parameter rows
NAN = REAL(math.nan)
TINY, ZERO = REAL({tiny!r}), REAL(0.0)  # REAL's smallest normal value, and its zero: no literal widens REAL
'''

# Every fixed-step kernel's start: its member (a thread's; a block's, for a long field of sites). FIXED_STEP goes
# on with its start (or where the last call left it) and its save intervals.
FIXED_HEAD = '''
@cuda.jit(fastmath=False, cache=True)
def kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, works, start, members):
    m = {member}
    if m >= members:
        return
    h = REAL(h)
'''

# Every kernel's start, after a member's first state is loaded (first call) or its works reloaded (later calls):
# a start that is not finite fails the member at once.
START_CHECKED = '''        if {failed}:
            status[m], failure_time[m] = {BLEW_UP}, 0.0
{nan_y}
{store_sample0}
        first = 1
    else:
{load_works}
'''

FIXED_STEP = FIXED_HEAD + '''{load_p}
    first = 0
    if start == 0:
{load_start}
{flush}
''' + START_CHECKED + '''{first_call}
    for i in range(first, samples.shape[0]):
        if status[m] == {OK}:
{enter}
            for step in range(steps_per_save):
{step}
{leave}
{flush_deep}
            if {failed}:
                status[m], failure_time[m] = {BLEW_UP}, (start + i) * steps_per_save * h
{nan_y_deep}
{store_sample}
{store_works}
'''

# Every adaptive kernel's step control, after a trial step's error sum (`estimate`) over its D values.
CONTROL_STEP = '''            err = math.sqrt(estimate / D)
            accepted, h_next, log2_previous, underflowed, time = next_step(err, step, h, log2_previous,
                                                                           rejected_last, time, target, ALPHA, BETA,
                                                                           SAFETY, MIN_FACTOR, MAX_FACTOR)
            h = REAL(h_next)  # the step in REAL; the member's time, like the controller's state, in float64
            rejected_last = not accepted
            accepted_count += accepted
            rejected_count += not accepted
            evaluations += S - 1
            if accepted:
'''

# Every adaptive kernel's start: the pair's constants, its member (a thread's; a block's, for a long field of
# sites).
ADAPTIVE_HEAD = '''
S = {S}
ALPHA, BETA, SAFETY, MIN_FACTOR, MAX_FACTOR = {control}


@cuda.jit(fastmath=False, cache=True)
def kernel(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, works, start, members):
    m = {member}
    if m >= members:
        return
'''

ADAPTIVE = ADAPTIVE_HEAD + '''{load_p}
    rtol, atol = REAL(control[1, m]), REAL(control[2, m])
    first = 0
    if start == 0:
{load_start}
{flush}
        {k0} = rhs(REAL(0.0), {y}, {p})
        h = REAL(control[0, m])
        if h <= 0.0:
            size = {size}
            slope = {slope}
            scale = atol + rtol * size
            h = REAL(min(0.01 * (size / scale) / (slope / scale) if size / scale > 1e-5 and slope / scale > 1e-5
                         else 1e-6, save_dt))
        time, log2_previous, rejected_last = REAL(0.0), {first_log2}, False
        accepted_count, rejected_count, evaluations = 0.0, 0.0, 1.0
''' + START_CHECKED + '''    for i in range(first, samples.shape[0]):
        target = (start + i) * save_dt
        while status[m] == {OK} and time < target:
            step = min(h, REAL(target - time))
{stages}
            estimate = REAL(0.0)
{error}
''' + CONTROL_STEP + '''{accept}
            elif underflowed:
                status[m], failure_time[m] = {UNDERFLOW}, time
{nan_y_deep}
{flush}
        if status[m] == {OK} and ({failed}):
            status[m], failure_time[m] = {BLEW_UP}, target
{nan_y}
{store_sample}
{store_works}
    counts[0, m], counts[1, m], counts[2, m] = accepted_count, rejected_count, evaluations
'''


@cache
def device_helpers() -> tuple:
    """next_step as a device function (the generated kernels import it)."""
    from numba import cuda
    return (cuda.jit(device=True)(next_step),)


def next_step(err, step, h, log2_previous, rejected_last, time, target, alpha, beta, safety, min_factor,
              max_factor):
    """One member's step control after a trial step of size `step` from `time` towards the saved time `target`
    (blocks.control_step for one member, in branches where that one is in selects over a block): returns
    (accepted, next h, the error's log2 to remember, whether the step underflowed, the member's time after it)."""
    finite = not (math.isnan(err) or math.isinf(err))
    usable = err if finite else 1.0e300
    accepted = usable <= 1.0
    log2_err = math.log2(max(usable, 1e-10))
    factor = safety * 2.0 ** (-alpha * log2_err + (beta * log2_previous if accepted else 0.0))
    if accepted:
        factor = min(max_factor, max(min_factor, min(factor, 1.0) if rejected_last else factor))
        landed = step >= target - time  # a step clipped to land on the saved time does not shrink the next
        return (True, max(step * factor, h if landed else 0.0), max(log2_err, FIRST_LOG2_ERR_PREVIOUS), False,
                target if landed else time + step)
    rejected_h = step * (max(min_factor, factor) if finite else min_factor)
    underflowed = rejected_h <= 1e-14 * target
    return False, 0.0 if underflowed else rejected_h, log2_previous, underflowed, time


def _names(prefix: str, count: int) -> str:
    return ", ".join(f"{prefix}{c}" for c in range(count))


def _block(lines, indent: int) -> str:
    return "\n".join(" " * indent + line for line in lines) or " " * indent + "pass"


def _stage_lines(S: int, a: tuple, nodes: tuple, D: int, P: int, h: str, t: str, first: int):
    """Stages first .. S - 1 of one explicit Runge-Kutta step written out: stage s's slopes in k{s}_{c} (an FSAL
    pair starts at 1: stage 0's are the last step's last). Coefficients that are zero are left out."""
    p = _names("p", P)
    lines = []
    for s in range(first, S):
        for c in range(D):
            terms = "".join(f" + ({h} * REAL({a[s * S + r]!r})) * k{r}_{c}" for r in range(s) if a[s * S + r])
            lines.append(f"z{c} = y{c}{terms}")
        lines.append(f"{', '.join(f'k{s}_{c}' for c in range(D))}, = rhs(REAL({t} + REAL({nodes[s]!r}) * {h}), "
                     f"{_names('z', D)}, {p})")
    return lines


def runge_kutta(method: Method, D: int, P: int) -> dict:
    _, S, a, b, _, _, _ = method_constants(method)
    nodes = tuple(float(x) for x in method.tableau.c)
    lines = ["t = ((start + i - 1) * steps_per_save + step) * h"]
    lines += _stage_lines(S, a, nodes, D, P, "h", "t", 0)
    for c in range(D):
        sums = " + ".join(f"REAL({b[s]!r}) * k{s}_{c}" for s in range(S) if b[s])
        lines.append(f"y{c} = y{c} + h * ({sums})")
    return dict(step=_block(lines, 16), first_call="", enter="", leave="", used=("rhs",))


def splitting(method: Method, D: int, P: int, pieces: tuple[str, ...], factors: dict[str, int],
              coordinates: bool) -> dict:
    _, _, _, _, E, sequence, fractions = method_constants(method)
    y, p = _names("y", D), _names("p", P)
    first_call = []
    lines = []
    for e, number in enumerate(sequence):
        name = pieces[number]
        extra = ""
        if name in factors:
            f = ", ".join(f"f{e}_{c}" for c in range(factors[name]))
            first_call.append(f"{f}, = {name}_factors(h * REAL({fractions[e]!r}), {p})")
            extra = ", " + f
        lines.append(f"{y}, = {name}(h * REAL({fractions[e]!r}), {y}, {p}{extra})")
    used = (*pieces, *(f"{piece}_factors" for piece in factors),
            *(("to_pieces", "from_pieces") if coordinates else ()))
    return dict(step=_block(lines, 16), first_call=_block(first_call, 4),
                enter=_block([f"{y}, = to_pieces({y}, {p})"], 12) if coordinates else "",
                leave=_block([f"{y}, = from_pieces({y}, {p})"], 12) if coordinates else "",
                used=used)


ADAPTIVE_ROWS = ("time", "h", "log2_previous", "rejected_last", "accepted_count", "rejected_count", "evaluations")


def _failed(D: int, limit: str = "limit[m]") -> str:
    """The test that fails a member (the CPU's check_members): a state value not finite or beyond its limit."""
    within = " and ".join(f"abs(y{c}) <= {limit}" for c in range(D))
    infinite = " or ".join(f"math.isinf(y{c})" for c in range(D))
    return f"not ({within}) or {infinite}"


def _flush(D: int, indent: int) -> str:
    """Subnormal state values become zeros of their sign where the CPU's check_members makes them so (the start
    and each save), so that both give the same bits."""
    return "\n".join(" " * indent + f"y{c} = y{c} if abs(y{c}) >= TINY else y{c} * ZERO"
                     for c in range(D))


def _common(D: int, P: int, adaptive: bool) -> dict:
    """The template's fields every family shares: loading and storing a member, its samples and its works rows
    (where a kernel call leaves a member for the next: its state, and an adaptive member's slopes and control)."""
    y = _names("y", D)
    rows = [f"y{c}" for c in range(D)] + ([f"k0_{c}" for c in range(D)] + list(ADAPTIVE_ROWS) if adaptive else [])
    load = [f"{row} = REAL(works[{r}, m])" for r, row in enumerate(rows)]
    store = [f"works[{r}, m] = {row}" for r, row in enumerate(rows)]
    if adaptive:
        load = [line.replace("REAL(works[", "0.0 != (works[") if line.startswith("rejected_last") else
                line.replace("REAL(works[", "(works[") if line.startswith(("accepted_", "rejected_", "evaluations"))
                else line for line in load]
        store = [line.replace("= rejected_last", "= 1.0 if rejected_last else 0.0") for line in store]
    nan = f"{y}, = {', '.join(['NAN'] * D)},"
    return dict(
        y=y, failed=_failed(D), flush=_flush(D, 8), flush_deep=_flush(D, 12),
        load_p=_block([f"p{c} = REAL(rate[{c}, m])" for c in range(P)], 4),
        load_start=_block([f"y{c} = REAL(state0[{c}, m])" for c in range(D)], 8),
        load_works=_block(load, 8), nan_y=" " * 12 + nan, nan_y_deep=" " * 16 + nan,
        store_sample0=_block([f"samples[0, {c}, m] = y{c}" for c in range(D)], 8),
        store_sample=_block([f"samples[i, {c}, m] = y{c}" for c in range(D)], 8),
        store_works=_block(store, 4), work_rows=len(rows))


def adaptive(method: Method, D: int, P: int) -> dict:
    S, a, e, alpha, beta, safety, min_factor, max_factor = adaptive_constants(method)
    nodes = tuple(float(x) for x in method.tableau.c)
    stages = _stage_lines(S, a, nodes, D, P, "step", "time", 1)
    error = [f"q = step * ({' + '.join(f'REAL({e[s]!r}) * k{s}_{c}' for s in range(S) if e[s])}) / "
             f"(atol + rtol * max(abs(y{c}), abs(z{c})))\nestimate += q * q" for c in range(D)]
    accept = [f"y{c}, k0_{c} = z{c}, k{S - 1}_{c}" for c in range(D)]
    return dict(S=S, control=(alpha, beta, safety, min_factor, max_factor), k0=_names("k0_", D),
                p=_names("p", P), size=f"max({', '.join(f'abs(y{c})' for c in range(D))}, ZERO)",
                slope=f"max({', '.join(f'abs(k0_{c})' for c in range(D))}, ZERO)",
                first_log2=f"REAL({FIRST_LOG2_ERR_PREVIOUS!r})",
                stages=_block(stages, 12), error=_block("\n".join(error).splitlines(), 12),
                accept=_block(accept, 16), used=("rhs",))


class GpuKernel(NamedTuple):
    """A scene's CUDA kernel for one method, the rows of its works array (rows x members) and its threads per
    member (1: a thread per member, THREADS to a block; more: a block per member)."""
    function: object
    rows: int
    threads: int = 1


def kernel(scene, method: Method, constants: dict, precision: str = "float64") -> GpuKernel:
    """The CUDA kernel of a stepping method for a scene (compiled when first launched)."""
    D, P = scene.kernel_rows(constants)
    sources = scene_identity(scene)  # a cache key: an edited scene is another kernel
    if getattr(scene, "SITES", False):
        return _sites_kernel(scene.NAME, scene.PHYSICS, sources, tuple(scene.PIECES), method, constants["n"],
                             constants["boundary"] == "periodic", precision, site_threads(constants["n"], method))
    return _member_kernel(scene.NAME, scene.PHYSICS, sources, tuple(scene.PIECES), method, D, P, precision)


@cache
def _member_kernel(name: str, where: str, sources: str, pieces: tuple[str, ...], method: Method, D: int, P: int,
                   precision: str) -> GpuKernel:
    common = _common(D, P, method.adaptive)
    if method.adaptive:
        family, fields, template = "adaptive", adaptive(method, D, P), ADAPTIVE
    elif method.tableau is not None:
        family, fields, template = "runge_kutta", runge_kutta(method, D, P), FIXED_STEP
    else:
        family, template = "splitting", FIXED_STEP
        coordinates = hasattr(loaded(where, sources), "to_pieces")
        fields = splitting(method, D, P, pieces, factor_counts(where, pieces, P), coordinates)
    used = fields.pop("used")
    physics_import = f"{', '.join(used)}, = device_functions({where!r}, {used!r}, {sources!r})"
    return GpuKernel(_compiled(family, name, method, precision, physics_import, sources, D, P,
                               template.format(**common, **fields, OK=OK, BLEW_UP=BLEW_UP, UNDERFLOW=UNDERFLOW,
                                               member="cuda.grid(1)")),
                     common["work_rows"])


def _compiled(family, name, method, precision, physics_import, physics, D, P, body, threads: int = 1):
    source = HEADER.format(family=family, scene=name, method=method.name, precision=precision,
                           physics_import=physics_import, physics_hash=physics, helpers=GPU_HELPERS, D=D, P=P,
                           tiny=float(np.finfo(precision).tiny)) + body
    layout = f"_{threads}threads" if threads > 1 else ""
    return load_source(source, f"cuda_{name}_{method.name}_{precision}{layout}").kernel


class GpuLaunch:
    """launch.Launch on a GPU: the same arguments, `segments`, `run` and `outcome`; the arrays live on the GPU, one
    thread per member. Each segment's samples are copied back on a stream of their own while the next segment
    integrates."""

    def __init__(self, scene, method: Method, values: dict[str, np.ndarray], constants: dict, *, n_save: int,
                 save_dt: float, dt=None, rtol=None, atol=None, blowup_factor: float = DEFAULT_BLOWUP_FACTOR,
                 segment: int | None = None, precision: str = "float64"):
        from numba import cuda

        require_gpu()
        self.scene, self.method, self.n_save, self.save_dt, self.dt = scene, method, n_save, save_dt, dt
        self.segment = max(1, min(segment or n_save, n_save))
        self.members = len(next(iter(values.values())))
        self.real = PRECISIONS[precision]
        self.buffers = {}  # see _buffer
        state0, rate = scene.inputs(values, constants)
        self.state_rows = state0.shape[0]
        self.kernel = kernel(scene, method, constants, precision)
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
        from numba import cuda

        n = self.members
        compute, copy = cuda.stream(), cuda.stream()
        start = {"status": np.zeros(n, np.int8), "failure_time": np.full(n, np.nan),
                 "works": np.zeros((self.kernel.rows, n)), **({"counts": np.zeros((3, n))} if self.method.adaptive
                                                                else {}), **(resume[1] if resume else {})}
        for name, value in start.items():
            setattr(self, name, cuda.to_device(value))
        tail = ((self.counts,) if self.method.adaptive else ()) + (self.status, self.failure_time, self.works)
        per_block = THREADS if self.kernel.threads == 1 else 1  # members per block of threads
        grid, block = max(1, -(-n // per_block)), THREADS if per_block > 1 else self.kernel.threads
        copied, waiting = {}, None
        for k, first in enumerate(range(resume[0] if resume else 0, self.n_save, self.segment)):
            count = min(self.segment, self.n_save - first)
            shape = (count, self.state_rows, n)
            if k >= 2:
                copied[k - 2].wait(compute)  # its buffer is copied out before this segment overwrites it
            samples = self._buffer(("device", k % 2, shape), lambda: cuda.device_array(shape, dtype=self.real))
            self.kernel.function[grid, block, compute](*self.head, samples, *tail, first, n)
            snapshot = {name: getattr(self, name).copy_to_host(
                self._buffer(("state", k % 2, name), lambda name=name: cuda.pinned_array_like(start[name])),
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
        n, rows = self.members, self.kernel.rows
        mine = {"status": ((n,), np.int8), "failure_time": ((n,), np.float64), "works": ((rows, n), np.float64),
                **({"counts": ((3, n), np.float64)} if self.method.adaptive else {})}
        return mine.keys() == state.keys() and all((v.shape, v.dtype) == mine[k] for k, v in state.items())

    def run(self, threads: int | None = None, watch=None) -> None:
        keep = np.array if self.segment < self.n_save else np.asarray  # segments share two buffers: copies
        parts = [keep(samples()) for _, samples in self.segments(threads, watch)]
        self.samples = parts[0] if len(parts) == 1 else np.concatenate(parts)

    def outcome(self) -> Outcome:
        status, failure_time = self.status.copy_to_host(), self.failure_time.copy_to_host()
        if self.method.adaptive:
            counts = self.counts.copy_to_host().astype(np.int64)
        else:
            counts = fixed_counts(self.method, self.scene, failure_time, self.dt,
                                   self.steps_per_save * (self.n_save - 1))
        return Outcome(getattr(self, "samples", None), counts, status, failure_time)


# ---------------------------------------------------------------- fields of sites: the chain

SITES_HEADER = '''
N, D = {N}, 2 * {N}  # sites, state values
PERIODIC = {periodic}
# A chain's T threads each own J sites: thread `lane` owns sites lane, lane + T, ... (T = 1: one thread holds the
# chain in its local arrays). Site q's position is x[q + 1]: x has a ghost site at rest at each end (0 and N + 1);
# the ends of a ring are each other's neighbours.
T, J = {T}, {J}


@cuda.jit(device=True)
def lane():
    return {lane}


@cuda.jit(device=True)
def neighbours(q):
    """Where in x site q's left and right neighbours are."""
    if PERIODIC:
        return N if q == 0 else q, 1 if q == N - 1 else q + 2
    return q, q + 2


@cuda.jit(device=True)
def failed(x, v, limit):
    """Whether any site of the chain is not finite or beyond `limit`; subnormals become zeros of their sign first,
    as the CPU's check_members makes them."""
    bad = 0
    for j in range(J):
        q = lane() + j * T
        if q < N:
            x[q + 1] = x[q + 1] if abs(x[q + 1]) >= TINY else x[q + 1] * ZERO
            v[j] = v[j] if abs(v[j]) >= TINY else v[j] * ZERO
            if not (abs(x[q + 1]) <= limit and abs(v[j]) <= limit) or math.isinf(x[q + 1]) or math.isinf(v[j]):
                bad = 1
    return {any_lane}


@cuda.jit(device=True)
def fail(x, v):
    for j in range(J):
        q = lane() + j * T
        if q < N:
            x[q + 1], v[j] = NAN, NAN


@cuda.jit(device=True)
def store(samples, i, m, x, v):
    for j in range(J):
        q = lane() + j * T
        if q < N:
            samples[i, q, m], samples[i, N + q, m] = x[q + 1], v[j]


@cuda.jit(device=True)
def over_lanes(value, scratch, largest):
    """The sum (largest: the largest) of every thread's `value` >= 0 over the chain's threads, in lane order, in
    each of them."""
    scratch[lane()] = value
    cuda.syncthreads()
    out = REAL(0.0)
    for t in range(T):
        out = max(out, scratch[t]) if largest else out + scratch[t]
    cuda.syncthreads()
    return out


@cuda.jit(device=True)
def kick(tau, x, v, cl, cr):
    for j in range(J):
        q = lane() + j * T
        if q < N:
            left, right = neighbours(q)
            v[j] += tau * acceleration(x[left], x[q + 1], x[right], cl[j], cr[j])
    {sync}


@cuda.jit(device=True)
def drift(tau, x, v, cl, cr):
    for j in range(J):
        q = lane() + j * T
        if q < N:
            x[q + 1] += tau * v[j]
    {sync}


'''

# A chain's start: its sites' springs and state, from state0 (first call) or works (later calls).
SITES_LOAD = '''    if lane() == 0:
        x[0], x[N + 1] = REAL(0.0), REAL(0.0)
    for j in range(J):
        q = lane() + j * T
        if q < N:
            cl[j], cr[j] = REAL(rate[q, m]), REAL(rate[N + q, m])
            if start == 0:
                x[q + 1], v[j] = REAL(state0[q, m]), REAL(state0[N + q, m])
            else:
                x[q + 1], v[j] = REAL(works[q, m]), REAL(works[N + q, m])
'''

SITES_FIXED = FIXED_HEAD + '''
    x = cuda.{x_memory}.array({N2}, REAL)  # sizes written as numbers: the arrays take constants only
    v = cuda.local.array({J}, REAL)
    cl = cuda.local.array({J}, REAL)
    cr = cuda.local.array({J}, REAL)
{arrays}
    alive = status[m] == {OK}
''' + SITES_LOAD + '''    {sync}
    first = 0
    if start == 0:
        if failed(x, v, limit[m]):
            alive = False
            if lane() == 0:
                status[m], failure_time[m] = {BLEW_UP}, 0.0
            fail(x, v)
        store(samples, 0, m, x, v)
        first = 1
    for i in range(first, samples.shape[0]):
        if alive:
            for step in range(steps_per_save):
{step}
            if failed(x, v, limit[m]):
                alive = False
                if lane() == 0:
                    status[m], failure_time[m] = {BLEW_UP}, (start + i) * steps_per_save * h
                fail(x, v)
        store(samples, i, m, x, v)
    for j in range(J):
        q = lane() + j * T
        if q < N:
            works[q, m], works[N + q, m] = x[q + 1], v[j]
'''


SITES_ADAPTIVE = ADAPTIVE_HEAD + '''    x = cuda.{x_memory}.array({N2}, REAL)
    v = cuda.local.array({J}, REAL)
    cl = cuda.local.array({J}, REAL)
    cr = cuda.local.array({J}, REAL)
    zx = cuda.{x_memory}.array({N2}, REAL)
    zv = cuda.local.array({J}, REAL)
    kx = cuda.local.array({SJ}, REAL)  # stage s's slopes at s J + j; stage 0's are the last step's last (FSAL)
    kv = cuda.local.array({SJ}, REAL)
    scratch = cuda.{x_memory}.array({T}, REAL)  # where the chain's threads add up the error norm
    rtol, atol = REAL(control[1, m]), REAL(control[2, m])
    alive = status[m] == {OK}
    if lane() == 0:
        zx[0], zx[N + 1] = REAL(0.0), REAL(0.0)
''' + SITES_LOAD + '''            if start != 0:
                kx[j], kv[j] = REAL(works[2 * N + q, m]), REAL(works[3 * N + q, m])
    {sync}
    first = 0
    if start == 0:
        size, slope = REAL(0.0), REAL(0.0)  # Hairer's guess of a first step, from |y| and |y'| in tolerances
        for j in range(J):
            q = lane() + j * T
            if q < N:
                left, right = neighbours(q)
                kx[j], kv[j] = v[j], acceleration(x[left], x[q + 1], x[right], cl[j], cr[j])
                size = max(size, abs(x[q + 1]) / (atol + rtol * abs(x[q + 1])), abs(v[j]) / (atol + rtol * abs(v[j])))
                slope = max(slope, abs(v[j]) / (atol + rtol * abs(x[q + 1])), abs(kv[j]) / (atol + rtol * abs(v[j])))
        size, slope = {max_size}, {max_slope}
        h = REAL(control[0, m])
        if h <= 0.0:
            h = REAL(min(0.01 * size / slope if size > 1e-5 and slope > 1e-5 else 1e-6, save_dt))
        time, log2_previous, rejected_last = REAL(0.0), {first_log2}, False
        accepted_count, rejected_count, evaluations = 0.0, 0.0, 1.0
        if failed(x, v, limit[m]):
            alive = False
            if lane() == 0:
                status[m], failure_time[m] = {BLEW_UP}, 0.0
            fail(x, v)
        store(samples, 0, m, x, v)
        first = 1
    else:
        time, h, log2_previous = REAL(works[4 * N, m]), REAL(works[4 * N + 1, m]), REAL(works[4 * N + 2, m])
        rejected_last = 0.0 != works[4 * N + 3, m]
        accepted_count, rejected_count, evaluations = works[4 * N + 4, m], works[4 * N + 5, m], works[4 * N + 6, m]
    for i in range(first, samples.shape[0]):
        target = (start + i) * save_dt
        while alive and time < target:
            step = min(h, REAL(target - time))
{stages}
            estimate = REAL(0.0)
            for j in range(J):
                q = lane() + j * T
                if q < N:
                    qx = step * ({error_x}) / (atol + rtol * max(abs(x[q + 1]), abs(zx[q + 1])))
                    qv = step * ({error_v}) / (atol + rtol * max(abs(v[j]), abs(zv[j])))
                    estimate += qx * qx + qv * qv
            estimate = {sum_estimate}
''' + CONTROL_STEP + '''                for j in range(J):
                    q = lane() + j * T
                    if q < N:
                        x[q + 1], v[j] = zx[q + 1], zv[j]
                        kx[j], kv[j] = kx[(S - 1) * J + j], kv[(S - 1) * J + j]
            elif underflowed:
                alive = False
                if lane() == 0:
                    status[m], failure_time[m] = {UNDERFLOW}, time
                fail(x, v)
        if alive and failed(x, v, limit[m]):
            alive = False
            if lane() == 0:
                status[m], failure_time[m] = {BLEW_UP}, target
            fail(x, v)
        store(samples, i, m, x, v)
    for j in range(J):
        q = lane() + j * T
        if q < N:
            works[q, m], works[N + q, m], works[2 * N + q, m], works[3 * N + q, m] = x[q + 1], v[j], kx[j], kv[j]
    if lane() == 0:
        works[4 * N, m], works[4 * N + 1, m], works[4 * N + 2, m] = time, h, log2_previous
        works[4 * N + 3, m] = 1.0 if rejected_last else 0.0
        works[4 * N + 4, m], works[4 * N + 5, m], works[4 * N + 6, m] = accepted_count, rejected_count, evaluations
        counts[0, m], counts[1, m], counts[2, m] = accepted_count, rejected_count, evaluations
'''


def _sites_loop(lines: list[str]) -> list[str]:
    """`lines` for each site j of this thread's (site q), in a loop over them."""
    return ["for j in range(J):", "    q = lane() + j * T", "    if q < N:", *("        " + line for line in lines)]


def _sites_stages(S: int, a: tuple, h: str, first: int, sync: str) -> list[str]:
    """Runge-Kutta stages first .. S - 1 over a field of sites: stage s's state into zx, zv, its slopes into kx,
    kv at s J + j (site q = lane + j T). Coefficients that are zero are left out."""
    lines = []
    for s in range(first, S):
        terms_x = "".join(f" + ({h} * REAL({a[s * S + r]!r})) * kx[{r} * J + j]" for r in range(s) if a[s * S + r])
        lines += _sites_loop([f"zx[q + 1] = x[q + 1]{terms_x}", f"zv[j] = v[j]{terms_x.replace('kx[', 'kv[')}"])
        lines += [sync, *_sites_loop(["left, right = neighbours(q)", f"kx[{s} * J + j] = zv[j]",
                                      f"kv[{s} * J + j] = acceleration(zx[left], zx[q + 1], zx[right], cl[j], cr[j])"]),
                  sync]  # every site's slopes read its neighbours' zx before the next stage writes it
    return lines


def sites_adaptive(method: Method, layout: dict) -> dict:
    """An embedded pair over a field of sites: as the member template's, the error norm and the first step's
    guess taken over the chain's threads (all of them then choose the same step)."""
    S, a, e, alpha, beta, safety, min_factor, max_factor = adaptive_constants(method)
    error_x = " + ".join(f"REAL({e[s]!r}) * kx[{s} * J + j]" for s in range(S) if e[s])
    shared = layout["T"] > 1
    return dict(S=S, SJ=S * layout["J"], control=(alpha, beta, safety, min_factor, max_factor),
                sum_estimate="over_lanes(estimate, scratch, False)" if shared else "estimate",
                max_size="over_lanes(size, scratch, True)" if shared else "size",
                max_slope="over_lanes(slope, scratch, True)" if shared else "slope",
                first_log2=f"REAL({FIRST_LOG2_ERR_PREVIOUS!r})",
                stages=_block(_sites_stages(S, a, "step", 1, layout["sync"]), 12), error_x=error_x,
                error_v=error_x.replace("kx[", "kv["))


def sites_splitting(method: Method, pieces: tuple[str, ...]) -> dict:
    """A kick/drift splitting's step over a field of sites. As on the CPU (blocks.splitting_schedule), a step that
    ends with the piece the next begins with (verlet's half kicks) merges the two."""
    _, _, _, _, E, sequence, fractions = method_constants(method)
    merge = E > 1 and sequence[0] == sequence[-1]
    lines = []
    for e, number in enumerate(sequence):
        call = f"{pieces[number]}(h * REAL({fractions[e]!r}){{extra}}, x, v, cl, cr)"
        if merge and e == 0:
            lines += ["if step == 0:", "    " + call.format(extra="")]
        elif merge and e == E - 1:
            lines.append(call.format(extra=f" + (h * REAL({fractions[0]!r}) if step < steps_per_save - 1 else "
                                           "REAL(0.0))"))
        else:
            lines.append(call.format(extra=""))
    return dict(arrays="", step=_block(lines, 16))


def sites_runge_kutta(method: Method, n: int, layout: dict) -> dict:
    """An explicit Runge-Kutta step over a field of sites: the stage state zx (shared by the chain's threads) and
    zv, and the stage slopes kx, kv (S J each) of this thread's sites."""
    _, S, a, b, _, _, _ = method_constants(method)
    lines = _sites_stages(S, a, "h", 0, layout["sync"])  # the chain's forces do not depend on time: no stage times
    sums_x = " + ".join(f"REAL({b[s]!r}) * kx[{s} * J + j]" for s in range(S) if b[s])
    lines += _sites_loop([f"x[q + 1] += h * ({sums_x})", f"v[j] += h * ({sums_x.replace('kx[', 'kv[')})"])
    J = layout["J"]
    arrays = [f"zx = cuda.{layout['x_memory']}.array({n + 2}, REAL)", f"zv = cuda.local.array({J}, REAL)",
              f"kx = cuda.local.array({S * J}, REAL)", f"kv = cuda.local.array({S * J}, REAL)",
              "if lane() == 0:", "    zx[0], zx[N + 1] = REAL(0.0), REAL(0.0)"]
    return dict(arrays=_block(arrays, 4), step=_block(lines, 16))


WARP = 32  # threads that run in lockstep on an NVIDIA GPU
SHARED_SITES = 64  # fields of at least this many sites run as a block of threads each (docs/gpu.md: the layouts)
MOST_SITE_THREADS = 256  # threads per field of sites, at most
SHARED_BYTES = 48 * 1024  # the shared memory a block may hold without asking for more


def site_threads(n: int, method: Method) -> int:
    """Threads per member for a field of n sites: 1 (the member in one thread's local arrays) for short fields
    and for fields whose positions outgrow SHARED_BYTES, else a block of whole warps, up to
    MOST_SITE_THREADS, each thread owning a few sites with the positions in the block's shared memory."""
    shared = (n + 2) * 8 * (2 if method.tableau is not None else 1)  # x, and a Runge-Kutta stage's zx
    shared += 8 * MOST_SITE_THREADS if method.adaptive else 0  # where the threads add up the error norm
    if n < SHARED_SITES or shared > SHARED_BYTES:
        return 1
    return min(MOST_SITE_THREADS, WARP * -(-n // WARP))


def sites_layout(n: int, threads: int) -> dict:
    """The template fields that place a field of n sites: in one thread (threads = 1) or a block of threads."""
    shared = threads > 1
    return dict(T=threads, J=-(-n // threads), lane="cuda.threadIdx.x" if shared else "0",
                member="cuda.blockIdx.x" if shared else "cuda.grid(1)", x_memory="shared" if shared else "local",
                sync="cuda.syncthreads()" if shared else "pass",
                any_lane="cuda.syncthreads_or(bad)" if shared else "bad")


@cache
def _sites_kernel(name: str, where: str, sources: str, pieces: tuple[str, ...], method: Method, n: int,
                  periodic: bool, precision: str, threads: int) -> GpuKernel:
    layout = sites_layout(n, threads)
    if method.adaptive:
        family, template, fields, rows = "adaptive", SITES_ADAPTIVE, sites_adaptive(method, layout), 4 * n + 7
    elif method.tableau is not None:
        family, template, fields, rows = "runge_kutta", SITES_FIXED, sites_runge_kutta(method, n, layout), 2 * n
    else:
        family, template, fields, rows = "splitting", SITES_FIXED, sites_splitting(method, pieces), 2 * n
    numbers = dict(N=n, N2=n + 2, periodic=periodic, OK=OK, BLEW_UP=BLEW_UP, UNDERFLOW=UNDERFLOW,
                   **layout)
    body = SITES_HEADER.format(**numbers) + template.format(**numbers, **fields)
    physics_import = f"acceleration, = device_functions({where!r}, ('acceleration',), {sources!r})"
    return GpuKernel(_compiled(f"sites {family}", name, method, precision, physics_import, sources,
                               2 * n, 2 * n, body, threads), rows, threads)
