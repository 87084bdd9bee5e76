"""A run file's values, one at a time: the error that names where a problem is (SpecError), the checks of a value's
type, finiteness and sign, distributions and their seeded draws, values given member by member, shape tables and
sweep axes. ensemble.spec reads whole run files with these; ensemble.members builds the members table."""
from __future__ import annotations

import difflib
import math
import zlib
from dataclasses import dataclass

import numpy as np

from .errors import EnsembleError
from .inertia import SHAPES
from .parameter import Mode, Parameter

DISTRIBUTIONS = ("uniform", "normal", "loguniform")
MAY_BE_INFINITE = ("blowup_factor",)  # inf: only a non-finite state fails a member
POLYGON = "polygon"  # a shape given by its mass and its vertices (a run constant), not by lengths
SETTINGS = ("method", "dt", "rtol", "atol")
DEFAULT_TOLERANCES = {"rtol": 1e-6, "atol": 1e-9}  # for adaptive methods


class SpecError(EnsembleError, ValueError):
    """A problem in a run file, tied to the key where it is."""

    def __init__(self, key: str, problem: str):
        super().__init__(f"{key}: {problem}")
        self.key = key
        self.problem = problem

    def __reduce__(self):  # as a Dask worker sends it back: rebuilt from both its arguments
        return SpecError, (self.key, self.problem)


@dataclass(frozen=True, eq=False)
class PerMember:
    """A parameter's values given member by member (a run file's `{ file = "x0.npy" }`, or ensemble.run's
    `values=`): (values, ...) over the run's members, or over the replicas of a sweep point (each point then
    takes the same), with one value, or one per site or spring, each."""
    values: np.ndarray
    source: str  # where they came from: the file and its SHA-256, or "ensemble.run(values=...)"

    def take(self, start: int, n: int, shape: tuple[int, ...], members: int, n_members: int) -> np.ndarray:
        """Members start .. start + n - 1's values, of shape `shape` (n, ...)."""
        index = np.arange(start, start + n)
        if len(self.values) != n_members:
            index = index % members
        return np.asarray(self.values[index], dtype=float).reshape(shape)


@dataclass(frozen=True)
class Distribution:
    kind: str  # one of DISTRIBUTIONS
    args: tuple[float, float]

    def draw(self, seed: int, name: str, start: int, count: int) -> np.ndarray:
        """Values start .. start + count - 1 of parameter `name`'s stream (see the module's docstring)."""
        bits = np.random.PCG64([seed, zlib.crc32(name.encode())])
        bits.advance(start)
        lo, hi = self.args
        if self.kind == "uniform":
            return np.random.Generator(bits).uniform(lo, hi, count)
        if self.kind == "normal":
            from scipy.special import ndtri

            return lo + hi * ndtri(((bits.random_raw(count) >> 12) + 0.5) * 2.0**-52)  # 52 bits, never 0 or 1
        from . import libm  # imports Numba: a run file is checked without it

        return libm.exp(np.random.Generator(bits).uniform(math.log(lo), math.log(hi), count))


def type_name(kind) -> str:
    if isinstance(kind, tuple):
        return " or ".join(map(type_name, kind))
    return {float: "a number", int: "an integer", str: "a string", list: "a list", dict: "a table",
            bool: "true or false"}[kind]


def expect(key: str, value, kind):
    """Check the TOML type of a value; ints count as numbers, bools as nothing else. Every number a run file gives
    passes here, so this is the one place that refuses NaN and infinity (TOML has both): a number must be finite
    unless its key is in MAY_BE_INFINITE."""
    ok = isinstance(value, kind) and (kind is bool or not isinstance(value, bool))
    if kind is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not ok:
        raise SpecError(key, f"must be {type_name(kind)}, got {type(value).__name__} {value!r}")
    if kind is float and not math.isfinite(value) and not (math.isinf(value) and key in MAY_BE_INFINITE):
        raise SpecError(key, f"must be a finite number, got {value!r}")
    return float(value) if kind is float else value


def unknown(key: str, name: str, known) -> SpecError:
    close = difflib.get_close_matches(name, list(known), n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return SpecError(key, f"unknown key{hint}; known keys: {', '.join(sorted(known))}")


def positive(key: str, value: float) -> float:
    if not value > 0 or not math.isfinite(value):
        raise SpecError(key, f"must be > 0 and finite, got {value!r}")
    return value


def distribution(key: str, value: dict) -> Distribution:
    if len(value) != 1 or next(iter(value)) not in DISTRIBUTIONS:
        raise SpecError(key, f"a distribution is one of {{uniform=[lo,hi]}}, {{normal=[mu,sd]}}, "
                             f"{{loguniform=[lo,hi]}}; got {value!r}")
    kind, args = next(iter(value.items()))
    if not (isinstance(args, list) and len(args) == 2):
        raise SpecError(f"{key}.{kind}", f"must be a list of two numbers, got {args!r}")
    lo, hi = (expect(f"{key}.{kind}", x, float) for x in args)
    if kind == "normal" and hi < 0:
        raise SpecError(f"{key}.normal", f"standard deviation must be >= 0, got {hi!r}")
    if kind != "normal" and lo > hi:
        raise SpecError(f"{key}.{kind}", f"lower bound {lo!r} is above upper bound {hi!r}")
    if kind == "uniform" and not math.isfinite(hi - lo):
        raise SpecError(f"{key}.uniform", f"the range {lo!r} to {hi!r} is wider than a float64 can hold")
    if kind == "loguniform" and lo <= 0:
        raise SpecError(f"{key}.loguniform", f"bounds must be > 0, got {lo!r}")
    return Distribution(kind, (lo, hi))


def parameter_value(key: str, value, parameter: Parameter):
    """A parameter's value in one of the forms its declaration accepts."""
    if isinstance(value, PerMember):
        if parameter.integer or parameter.choices or parameter.constant:
            raise SpecError(key, "is one value for the whole run, not one per member")
        return value
    if parameter.integer:
        return expect(key, value, int)
    if parameter.choices:
        if value not in parameter.choices:
            raise SpecError(key, f"must be one of {', '.join(map(repr, parameter.choices))}, got {value!r}")
        return value
    if isinstance(value, dict) and parameter.mode and "mode" in value:
        if set(value) != {"mode", "amplitude"}:
            raise SpecError(key, f"a mode start is {{ mode = j, amplitude = A }}, got {value!r}")
        return Mode(expect(f"{key}.mode", value["mode"], int), expect(f"{key}.amplitude", value["amplitude"], float))
    if isinstance(value, dict) and "file" in value:
        raise SpecError(key, f"values from a file are {{ file = \"NAME.npy\" }} alone, got {value!r}")
    if isinstance(value, dict):
        return distribution(key, value)
    if isinstance(value, list) and parameter.per:
        return [expect(f"{key}[{i}]", x, float) for i, x in enumerate(value)]
    if isinstance(value, list):
        raise SpecError(key, "takes one value per member (a number or a distribution), got a list")
    return expect(key, value, float)


def axis_values(key: str, axis, kind) -> tuple:
    if not isinstance(axis, list) or not axis:
        raise SpecError(key, f"a sweep axis must be a non-empty list, got {axis!r}")
    values = tuple(expect(key, x, kind) for x in axis)
    repeated = [x for i, x in enumerate(values) if x in values[:i]]
    if repeated:
        raise SpecError(key, f"repeats the value {repeated[0]!r}: each sweep point once")
    return values


def shape_table(key: str, value) -> tuple[str, dict]:
    """A shape table { shape = "...", mass = ..., <lengths> = ... }: the shape and the rest."""
    if not isinstance(value, dict) or "shape" not in value:
        raise SpecError(key, f'must be a shape table such as {{ shape = "annulus", mass = 0.1, r_inner = 0.1, '
                             f'r_outer = 0.13 }}, got {value!r}')
    value = dict(value)
    shape = value.pop("shape")
    if not isinstance(shape, str) or (shape not in SHAPES and shape != POLYGON):
        raise SpecError(f"{key}.shape", f"unknown shape {shape!r}; shapes: {', '.join(SHAPES)}, {POLYGON}")
    return shape, value


def vertices_text(key: str, value) -> str:
    """A polygon's vertices [[x1, y1], [x2, y2], ...] (m), as the text "x1,y1 x2,y2 ..." the dataset records."""
    if not isinstance(value, list) or not all(isinstance(v, list) and len(v) == 2 for v in value):
        raise SpecError(key, f"must be a list of [x, y] pairs in m, such as [[0, 0], [0.3, 0], [0, 0.3]], "
                             f"got {value!r}")
    pairs = [[expect(key, x, float) for x in v] for v in value]
    return " ".join(f"{x!r},{y!r}" for x, y in pairs)
