"""The C library's elementary functions as NumPy ufuncs, for what the host computes into a result: draws, scenes'
inputs, closed forms, fits.

NumPy's own exp, log, tan, arctan, ... run SIMD code chosen for the CPU at hand: on a host with AVX-512 they round
about one value in twenty otherwise than on one without (loguniform draws, a top's closed form, log tan tilt).
These call the C library's function value by value, as the compiled kernels do, so a result's bits are the same
on every x86-64 host with FMA. Shapes broadcast as NumPy's; real (float64) values only. Each is compiled (or
loaded from Numba's cache) at its first use: importing this module imports no Numba, so a run file is read
without it.
"""
from __future__ import annotations

import math


def _exp(x):
    return math.exp(x)


def _expm1(x):
    return math.expm1(x)


def _log(x):
    return math.log(x)


def _sin(x):
    return math.sin(x)


def _cos(x):
    return math.cos(x)


def _tan(x):
    return math.tan(x)


def _arctan(x):
    return math.atan(x)


def _tanh(x):
    return math.tanh(x)


def _arctan2(y, x):
    return math.atan2(y, x)


def _hypot(x, y):
    return math.hypot(x, y)


ONE, TWO = ["float64(float64)"], ["float64(float64, float64)"]
SCALARS = {"exp": (_exp, ONE), "expm1": (_expm1, ONE), "log": (_log, ONE), "sin": (_sin, ONE), "cos": (_cos, ONE),
           "tan": (_tan, ONE), "arctan": (_arctan, ONE), "tanh": (_tanh, ONE), "arctan2": (_arctan2, TWO),
           "hypot": (_hypot, TWO)}


def __getattr__(name: str):
    """libm.exp and the others: the C library's function of SCALARS as a ufunc, made at its first use."""
    if name not in SCALARS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from numba import vectorize

    function, signatures = SCALARS[name]
    made = globals()[name] = vectorize(signatures, cache=True)(function)
    return made
