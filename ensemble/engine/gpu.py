"""The method families as CUDA kernels (numba-cuda): one GPU thread per member, its state in registers.

A thread runs the CPU kernels' own code for its member: an explicit Runge-Kutta step (ensemble.engine.runge_kutta),
an adaptive pair's trial step and error norm (.adaptive) and its step control (.control), a splitting's sequence
of pieces (.splitting), compiled as CUDA device functions (`device_function`, with numba-cuda's equivalents of the
CPU intrinsics and the GPU's own sin, cos, log2 and exp2), as are the scene's functions. The kernels' frames (a
member's start, save intervals, failures) are templates here. What differs from the CPU is where a member
lives: a thread (cuda.grid) instead of a block lane, and the arrays in (rows, members) order so that neighbouring
threads touch neighbouring memory.

A scene whose state is a field of sites (the chain) has templates of its own (ensemble.engine.gpu_sites), built on
the pieces here; ensemble.engine.gpu_launch picks a scene's kernel and runs it.

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
from ..results import Status
from . import splitting
from .blocks import FIRST_LOG2_ERR_PREVIOUS, adaptive_constants, first_step
from .control import controlled
from .kernels import load_source, loaded, pair_of, tableau_of
from .sources import ENGINE_SOURCES

THREADS = 128  # threads per CUDA block
PRECISIONS = {"float64": np.float64, "float32": np.float32}
OK, BLEW_UP, UNDERFLOW = int(Status.OK), int(Status.BLEW_UP), int(Status.STEP_SIZE_UNDERFLOW)
#: A hash of this file, gpu_sites.py and the CPU kernels' code (sources.ENGINE_SOURCES), which every CUDA kernel's
#: file holds: numba-cuda's disk cache (`cache=True`) keys a kernel on its own file, and would otherwise load one
#: compiled before a device helper changed.
GPU_HELPERS = hashlib.sha256(b"".join((Path(__file__).parent / name).read_bytes()
                                      for name in ("gpu.py", "gpu_sites.py", *ENGINE_SOURCES))).hexdigest()


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


def _finite(x):
    return not (math.isnan(x) or math.isinf(x))


def _log2(x):
    return math.log2(x)


def _exp2(y):
    return 2.0 ** y


def _select(condition, if_true, if_false):
    return if_true if condition else if_false


# CPU helpers the engine's code or a scene's physics may call, and what a device function calls instead: they are
# written in bit operations and LLVM intrinsics for the CPU's vector units; a GPU has its own sin, cos, log2 and
# exp2, and its own test for a finite value.
DEVICE_EQUIVALENTS = {"ensemble.engine.blocks.sin_cos": _sin_cos, "ensemble.engine.blocks.finite": _finite,
                      "ensemble.engine.blocks.log2_positive": _log2, "ensemble.engine.blocks.exp2_of": _exp2}


def device_function(function, done: dict | None = None):
    """`function` (plain Python or @njit) compiled as a CUDA device function, the compiled helpers it calls
    replaced by device functions too (DEVICE_EQUIVALENTS where the CPU's are written for vector units), and the
    CPU intrinsics it calls by numba-cuda's (device_intrinsics)."""
    from numba import cuda
    from numba.core.registry import CPUDispatcher

    done = {} if done is None else done
    python = function.py_func if isinstance(function, CPUDispatcher) else function
    if python in done:
        return done[python]
    names = dict(python.__globals__)
    intrinsics = device_intrinsics()
    for name in python.__code__.co_names:
        value = names.get(name)
        if isinstance(value, CPUDispatcher):
            key = f"{value.py_func.__module__}.{value.py_func.__name__}"
            equivalent = DEVICE_EQUIVALENTS.get(key)
            names[name] = device_function(equivalent or value, done)
        elif any(value is cpu for cpu in intrinsics):
            names[name] = next(device for cpu, device in intrinsics.items() if value is cpu)
    rebuilt = types.FunctionType(python.__code__, names, python.__name__, python.__defaults__, python.__closure__)
    done[python] = cuda.jit(device=True)(rebuilt)
    return done[python]


@cache
def device_intrinsics() -> dict:
    """The CPU intrinsics the families call (ensemble.engine.tuples) and numba-cuda's equivalents: numba-cuda
    types calls in its own registry, where Numba's CPU intrinsics are unknown."""
    from numba import cuda
    from numba.cpython.unsafe.tuple import tuple_setitem

    from . import tuples
    from .blocks import select
    if simulated():  # the simulator runs device functions as Python
        return {tuple_setitem: lambda values, i, value: values[:i] + (value,) + values[i + 1:],
                tuples.repeated: lambda value, like: (value,) * len(like),
                tuples.added: lambda z, weight, slope: tuple(a + weight * b for a, b in zip(z, slope)),
                tuples.converted: lambda values, like: tuple(map(type(like[0]), values if isinstance(values, tuple)
                                                                 else (values,))),
                select: _select}
    from numba.cuda.cpython.unsafe.tuple import tuple_setitem as device_tuple_setitem
    from numba.cuda.extending import intrinsic
    return {tuple_setitem: device_tuple_setitem, tuples.repeated: intrinsic(tuples.repeated_typing),
            tuples.added: intrinsic(tuples.added_typing), tuples.converted: intrinsic(tuples.converted_typing),
            select: cuda.jit(device=True)(_select)}


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

from ensemble.engine import adaptive, runge_kutta
from ensemble.engine.gpu import (device_function, device_functions, device_helpers, device_splitting,
                                 device_unrolled)

controlled, first_step = device_helpers()

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

# Every adaptive kernel's step control, after a trial step's error norm `err`.
CONTROL_STEP = '''            accepted, underflowed, h_next, log2_previous, time = controlled(
                err, step, h, log2_previous, rejected_last, time, target, ALPHA, BETA, SAFETY, MIN_FACTOR, MAX_FACTOR)
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
        {k0}, = rhs(REAL(0.0), {y}, {p})
        h = REAL(control[0, m])
        if h <= 0.0:
            size = {size}
            slope = {slope}
            scale = atol + rtol * size
            h = REAL(first_step(size / scale, slope / scale, save_dt))
        time, log2_previous, rejected_last = REAL(0.0), {first_log2}, False
        accepted_count, rejected_count, evaluations = 0.0, 0.0, 1.0
''' + START_CHECKED + '''    for i in range(first, samples.shape[0]):
        target = (start + i) * save_dt
        while status[m] == {OK} and time < target:
            step = min(h, REAL(target - time))
{stages}
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


def _device_inlined(function):
    """A link of the engine's written-out loops (tuples.unrolled, the splitting's chains) as an inlined device
    function (plain Python under the simulator)."""
    from numba import cuda
    return function if simulated() else cuda.jit(device=True, inline="always")(function)


@cache
def device_unrolled(count: int):
    """tuples.unrolled(count) of device functions."""
    from .tuples import unrolled
    return unrolled(count, _device_inlined)


@cache
def device_splitting(where: str, pieces: tuple[str, ...], expected: str, sequence: tuple, precision: str) -> tuple:
    """(step, factors): a splitting's sequence_step and sequence_factors (ensemble.engine.splitting, the CPU
    kernels' own) of a scene's device functions, for a sequence of (piece number, fraction) entries, the fractions
    in `precision`."""
    module = loaded(where, expected)
    done: dict = {}
    named = [device_function(getattr(module, piece), done) for piece in pieces]
    factors = [device_function(getattr(module, f"{piece}_factors"), done) if hasattr(module, f"{piece}_factors")
               else None for piece in pieces]
    real = PRECISIONS[precision]
    return (splitting.sequence_step(tuple((named[n], real(f)) for n, f in sequence), _device_inlined),
            splitting.sequence_factors(tuple((factors[n], real(f)) for n, f in sequence), _device_inlined))


@cache
def device_helpers() -> tuple:
    """(controlled, first_step) as device functions (the generated kernels import them): the CPU kernels' own step
    control (control.controlled) and first trial step's guess (blocks.first_step), written once for both."""
    return device_function(controlled), device_function(first_step)


def _names(prefix: str, count: int) -> str:
    return ", ".join(f"{prefix}{c}" for c in range(count))


def indented(lines, indent: int) -> str:
    return "\n".join(" " * indent + line for line in lines) or " " * indent + "pass"


RUNGE_KUTTA = '''
rk_step = device_function(runge_kutta.step)  # a member's step, the CPU kernels' own
STAGES, WEIGHTS = (tuple(tuple(REAL(x) for x in row) for row in {stages!r}),
                   tuple(REAL(x) for x in {weights!r}))  # the tableau (kernels.tableau_of) in REAL
STAGE_LOOP = device_unrolled(len(WEIGHTS))
'''


def runge_kutta(method: Method, D: int, P: int) -> dict:
    """A member's step is ensemble.engine.runge_kutta.step, as on the CPU: the tableau in REAL, so that a float32
    kernel computes in float32."""
    t = "REAL(((start + i - 1) * steps_per_save + step) * h)"
    y, p = _names("y", D), _names("p", P)
    lines = [f"{y}, = rk_step(rhs, {t}, h, ({y},), ({p},), STAGES, WEIGHTS, STAGE_LOOP)"]
    stages, weights = tableau_of(method)
    return dict(step=indented(lines, 16), first_call="", enter="", leave="", used=("rhs",),
                head=RUNGE_KUTTA.format(stages=stages, weights=weights))


SPLITTING = '''
split_step, split_factors = device_splitting({where!r}, {pieces!r}, {physics_hash!r}, {sequence!r}, {precision!r})
'''


def splitting_fields(method: Method, D: int, P: int, where: str, pieces: tuple[str, ...], sources: str,
                     precision: str, coordinates: bool) -> dict:
    """A member's step is the CPU kernels' (ensemble.engine.splitting): its pieces' factors computed once a call,
    in registers."""
    y, p = _names("y", D), _names("p", P)
    sequence = tuple((number, float(f)) for number, f in method.splitting.sequence)
    return dict(step=indented([f"{y}, = split_step(h, ({y},), ({p},), factors)"], 16),
                first_call=indented([f"factors = split_factors(h, ({p},))"], 4),
                enter=indented([f"{y}, = to_pieces({y}, {p})"], 12) if coordinates else "",
                leave=indented([f"{y}, = from_pieces({y}, {p})"], 12) if coordinates else "",
                used=("to_pieces", "from_pieces") if coordinates else (),
                head=SPLITTING.format(where=where, pieces=pieces, physics_hash=sources, sequence=sequence,
                                      precision=precision))


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
        load_p=indented([f"p{c} = REAL(rate[{c}, m])" for c in range(P)], 4),
        load_start=indented([f"y{c} = REAL(state0[{c}, m])" for c in range(D)], 8),
        load_works=indented(load, 8), nan_y=" " * 12 + nan, nan_y_deep=" " * 16 + nan,
        store_sample0=indented([f"samples[0, {c}, m] = y{c}" for c in range(D)], 8),
        store_sample=indented([f"samples[i, {c}, m] = y{c}" for c in range(D)], 8),
        store_works=indented(store, 4), work_rows=len(rows))


ADAPTIVE_FAMILY = '''
trial_step = device_function(adaptive.trial_step)  # a member's trial step and error norm, the CPU kernels' own
error_norm = device_function(adaptive.error_norm)
STAGES, ERROR = (tuple(tuple(REAL(x) for x in row) for row in {stages!r}),
                 tuple(REAL(x) for x in {error!r}))  # the pair (kernels.pair_of) in REAL
STAGE_LOOP = device_unrolled(len(ERROR))
'''


def adaptive(method: Method, D: int, P: int) -> dict:
    """A member's trial step, its error norm and its step control are the CPU kernels' own (ensemble.engine.adaptive,
    .control)."""
    S, _, _, alpha, beta, safety, min_factor, max_factor = adaptive_constants(method)
    y, p, k0 = _names("y", D), _names("p", P), _names("k0_", D)
    stages, error = pair_of(method)
    lines = [f"slopes, new = trial_step(rhs, REAL(time), step, ({y},), ({p},), ({k0},), STAGES, STAGE_LOOP)",
             f"err = error_norm(step, ({y},), new, slopes, ERROR, rtol, atol)"]
    accept = [f"{y}, = new", f"{k0}, = slopes[S - 1]"]
    return dict(S=S, control=(alpha, beta, safety, min_factor, max_factor), k0=k0, p=p,
                size=f"max({', '.join(f'abs(y{c})' for c in range(D))}, ZERO)",
                slope=f"max({', '.join(f'abs(k0_{c})' for c in range(D))}, ZERO)",
                first_log2=f"REAL({FIRST_LOG2_ERR_PREVIOUS!r})", stages=indented(lines[:1], 12),
                error=indented(lines[1:], 12), accept=indented(accept, 16), used=("rhs",),
                head=ADAPTIVE_FAMILY.format(stages=stages, error=error))


class GpuKernel(NamedTuple):
    """A scene's CUDA kernel for one method, the rows of its works array (rows x members) and its threads per
    member (1: a thread per member, THREADS to a block; more: a block per member)."""
    function: object
    rows: int
    threads: int = 1


@cache
def member_kernel(name: str, where: str, sources: str, pieces: tuple[str, ...], method: Method, D: int, P: int,
                  precision: str) -> GpuKernel:
    common = _common(D, P, method.adaptive)
    if method.adaptive:
        family, fields, template = "adaptive", adaptive(method, D, P), ADAPTIVE
    elif method.tableau is not None:
        family, fields, template = "runge_kutta", runge_kutta(method, D, P), FIXED_STEP
    else:
        family, template = "splitting", FIXED_STEP
        coordinates = hasattr(loaded(where, sources), "to_pieces")
        fields = splitting_fields(method, D, P, where, pieces, sources, precision, coordinates)
    used, head = fields.pop("used"), fields.pop("head", "")
    physics_import = f"{', '.join(used)}, = device_functions({where!r}, {used!r}, {sources!r})" if used else ""
    return GpuKernel(compiled(family, name, method, precision, physics_import, sources, D, P,
                              head + template.format(**common, **fields, OK=OK, BLEW_UP=BLEW_UP,
                                                     UNDERFLOW=UNDERFLOW, member="cuda.grid(1)")),
                     common["work_rows"])


def compiled(family, name, method, precision, physics_import, physics, D, P, body, threads: int = 1):
    source = HEADER.format(family=family, scene=name, method=method.name, precision=precision,
                           physics_import=physics_import, physics_hash=physics, helpers=GPU_HELPERS, D=D, P=P,
                           tiny=float(np.finfo(precision).tiny)) + body
    layout = f"_{threads}threads" if threads > 1 else ""
    return load_source(source, f"cuda_{name}_{method.name}_{precision}{layout}").kernel
