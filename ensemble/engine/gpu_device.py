"""The engine's CPU code as CUDA device functions (numba-cuda), for the kernels of ensemble.engine.gpu and
.gpu_sites: a function the CPU kernels compile (a family's step, the step control, a scene's physics) compiled
again for the GPU (`device_function`), the CPU's intrinsics and vectorizable helpers replaced by the GPU's own,
and the engine's written-out loops (tuples.unrolled, the splittings' chains) made of device functions. Under
numba-cuda's simulator (NUMBA_ENABLE_CUDASIM=1) they stay Python.
"""
from __future__ import annotations

import math
import types
from functools import cache

import numpy as np

from . import splitting
from .blocks import first_step
from .control import counted
from .kernels import loaded

PRECISIONS = {"float64": np.float64, "float32": np.float32}


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
                tuples.loaded: _simulated_loaded, tuples.stored: _simulated_stored,
                tuples.repeated: lambda value, like: (value,) * len(like),
                tuples.added: lambda z, weight, slope: tuple(a + weight * b for a, b in zip(z, slope)),
                tuples.converted: lambda values, like: tuple(map(type(like[0]), values if isinstance(values, tuple)
                                                                 else (values,))) if like else (),
                select: _select}
    from numba.cuda.cpython.unsafe.tuple import tuple_setitem as device_tuple_setitem
    from numba.cuda.extending import intrinsic
    return {tuple_setitem: device_tuple_setitem, tuples.repeated: intrinsic(tuples.repeated_typing),
            tuples.loaded: intrinsic(tuples.loaded_typing), tuples.stored: intrinsic(tuples.stored_typing),
            tuples.added: intrinsic(tuples.added_typing), tuples.converted: intrinsic(tuples.converted_typing),
            select: cuda.jit(device=True)(_select)}


def _simulated_loaded(array, first, B, j, like):
    """tuples.loaded in Python: the values at flat indices (first + c) B + j of a C-contiguous array."""
    return tuple(np.asarray(array).reshape(-1)[first * B + j::B][:len(like)])


def _simulated_stored(array, first, B, j, values):
    np.asarray(array).reshape(-1)[first * B + j:(first + len(values)) * B:B] = values


def device_tuples() -> tuple:
    """(loaded, stored, converted, repeated, tuple_setitem): the engine's tuple intrinsics (ensemble.engine.tuples)
    for code the GPU compiles (Python under the simulator)."""
    from numba.cpython.unsafe.tuple import tuple_setitem

    from . import tuples
    found = device_intrinsics()
    return tuple(found[cpu] for cpu in (tuples.loaded, tuples.stored, tuples.converted, tuples.repeated,
                                        tuple_setitem))


@cache
def device_functions(where: str, names: tuple[str, ...], expected: str) -> tuple:
    """A scene's functions `names` (its physics module `where`, whose sources must still be of identity
    `expected`: kernels.loaded) as device functions."""
    module = loaded(where, expected)
    done: dict = {}
    return tuple(device_function(getattr(module, name), done) for name in names)


@cache
def device_event_values(where: str, sources: tuple, expected: str):
    """values(t, y, p) -> each event's value (ensemble.engine.events.values_of, kernels.event_values) of device
    functions: a state component, or a scene's function (its physics module `where`, of identity `expected`)."""
    from . import events

    module, done = loaded(where, expected), {}
    return events.values_of(sources, lambda name: device_function(getattr(module, name), done), device_inlined)


@cache
def device_event_signs(where: str, sources: tuple, expected: str):
    """signs(t, y, p, levels) -> each event's sign against its level (ensemble.engine.events.signs_of,
    kernels.event_signs) of device functions: a scene's watch where a function source names one, else the value's
    difference from the level."""
    from . import events

    module, done = loaded(where, expected), {}
    return events.signs_of(sources, lambda name: device_function(getattr(module, name), done), device_inlined)


@cache
def device_events() -> tuple:
    """(crossed, located): ensemble.engine.events's, as device functions (the event kernels import them)."""
    from . import events
    return device_function(events.crossed), device_function(events.located)


def device_inlined(function):
    """A link of the engine's written-out loops (tuples.unrolled, the splitting's chains) as an inlined device
    function (plain Python under the simulator)."""
    from numba import cuda
    return function if simulated() else cuda.jit(device=True, inline="always")(function)


@cache
def device_unrolled(count: int):
    """tuples.unrolled(count) of device functions."""
    from .tuples import unrolled
    return unrolled(count, device_inlined)


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
    return (splitting.sequence_step(tuple((named[n], real(f)) for n, f in sequence), device_inlined),
            splitting.sequence_factors(tuple((factors[n], real(f)) for n, f in sequence), device_inlined))


@cache
def device_helpers() -> tuple:
    """(counted, first_step) as device functions (the generated kernels import them): the CPU kernels' own step
    control (control.controlled, through control.counted) and first trial step's guess (blocks.first_step),
    written once for both."""
    return device_function(counted), device_function(first_step)
