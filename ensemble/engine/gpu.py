"""The method families as CUDA kernels (numba-cuda): one GPU thread per member, its state in registers.

The same method data (ensemble.methods, through blocks.method_constants and adaptive_constants) and the same scene
physics as the CPU kernels (ensemble.engine.templates): the scene's functions are compiled as CUDA device
functions, and the stage loops, the splitting's sequence and the step control are written out for one member.
What differs from the CPU is where a member lives: a thread (cuda.grid) instead of a block lane, its state in
scalar variables, and the arrays in (rows, members) order so that neighbouring threads touch neighbouring memory.

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
from .blocks import FIRST_LOG2_ERR_PREVIOUS, adaptive_constants, first_step, method_constants
from .kernels import factor_counts, load_source, loaded

THREADS = 128  # threads per CUDA block
PRECISIONS = {"float64": np.float64, "float32": np.float32}
OK, BLEW_UP, UNDERFLOW = int(Status.OK), int(Status.BLEW_UP), int(Status.STEP_SIZE_UNDERFLOW)
#: A hash of this file, gpu_sites.py, blocks.py and results.py, which every CUDA kernel's file holds: numba-cuda's
#: disk cache (`cache=True`) keys a kernel on its own file, and would otherwise load one compiled before a device
#: helper changed.
GPU_HELPERS = hashlib.sha256(b"".join((Path(__file__).parent / name).read_bytes()
                                      for name in ("gpu.py", "gpu_sites.py", "blocks.py", "../results.py"))).hexdigest()


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

next_step, first_step = device_helpers()

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
            h = REAL(first_step(size / scale, slope / scale, save_dt))
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
    """(next_step, first_step) as device functions (the generated kernels import them): first_step is the CPU
    kernels' own (blocks.first_step), so the first trial step's guess is written once for both devices."""
    from numba import cuda
    return cuda.jit(device=True)(next_step), cuda.jit(device=True)(first_step.py_func)


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


def indented(lines, indent: int) -> str:
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
    return dict(step=indented(lines, 16), first_call="", enter="", leave="", used=("rhs",))


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
    return dict(step=indented(lines, 16), first_call=indented(first_call, 4),
                enter=indented([f"{y}, = to_pieces({y}, {p})"], 12) if coordinates else "",
                leave=indented([f"{y}, = from_pieces({y}, {p})"], 12) if coordinates else "",
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
        load_p=indented([f"p{c} = REAL(rate[{c}, m])" for c in range(P)], 4),
        load_start=indented([f"y{c} = REAL(state0[{c}, m])" for c in range(D)], 8),
        load_works=indented(load, 8), nan_y=" " * 12 + nan, nan_y_deep=" " * 16 + nan,
        store_sample0=indented([f"samples[0, {c}, m] = y{c}" for c in range(D)], 8),
        store_sample=indented([f"samples[i, {c}, m] = y{c}" for c in range(D)], 8),
        store_works=indented(store, 4), work_rows=len(rows))


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
                stages=indented(stages, 12), error=indented("\n".join(error).splitlines(), 12),
                accept=indented(accept, 16), used=("rhs",))


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
        fields = splitting(method, D, P, pieces, factor_counts(where, pieces, P), coordinates)
    used = fields.pop("used")
    physics_import = f"{', '.join(used)}, = device_functions({where!r}, {used!r}, {sources!r})"
    return GpuKernel(compiled(family, name, method, precision, physics_import, sources, D, P,
                              template.format(**common, **fields, OK=OK, BLEW_UP=BLEW_UP, UNDERFLOW=UNDERFLOW,
                                              member="cuda.grid(1)")),
                     common["work_rows"])


def compiled(family, name, method, precision, physics_import, physics, D, P, body, threads: int = 1):
    source = HEADER.format(family=family, scene=name, method=method.name, precision=precision,
                           physics_import=physics_import, physics_hash=physics, helpers=GPU_HELPERS, D=D, P=P,
                           tiny=float(np.finfo(precision).tiny)) + body
    layout = f"_{threads}threads" if threads > 1 else ""
    return load_source(source, f"cuda_{name}_{method.name}_{precision}{layout}").kernel
