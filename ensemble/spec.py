"""Reading and validating run files, and expanding them into a members table.

A run file is TOML (see README.md). Every problem is a SpecError naming the
key, so the command line can print one line and exit with status 2.

Randomness: parameter `name` of member i is the i-th draw of a stream seeded by
(seed, crc32(name)). Observation noise on variable `name` of member i comes
from a stream seeded by (seed, crc32("noise:" + name), i). Both depend only on
the seed, the variable and the member index, never on chunk size, thread
count, or the order of keys in the file.
"""
from __future__ import annotations

import difflib
import itertools
import math
import tomllib
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .methods import METHODS, methods_for
from .parameter import Mode, Parameter
from .scenes import SCENES


class SpecError(ValueError):
    """A problem in a run file, tied to the key where it is."""

    def __init__(self, key: str, problem: str):
        super().__init__(f"{key}: {problem}")
        self.key = key
        self.problem = problem


TOP_LEVEL = {
    "scene": str, "method": str, "dt": float, "t_end": float, "save_dt": float,
    "members": int, "seed": int, "save": list, "parameters": dict, "sweep": dict, "observe": dict,
}
OBSERVE_KEYS = ("noise",)
REQUIRED = ("scene", "method", "dt", "t_end", "save_dt", "members", "seed")
DISTRIBUTIONS = ("uniform", "normal", "loguniform")
_STEP_RTOL = 1e-9  # how close save_dt / dt and t_end / save_dt must be to whole numbers


@dataclass(frozen=True)
class Distribution:
    kind: str  # one of DISTRIBUTIONS
    args: tuple[float, float]

    def draw(self, rng: np.random.Generator, n: int) -> np.ndarray:
        lo, hi = self.args
        if self.kind == "uniform":
            return rng.uniform(lo, hi, n)
        if self.kind == "normal":
            return rng.normal(lo, hi, n)
        return np.exp(rng.uniform(math.log(lo), math.log(hi), n))


@dataclass(frozen=True)
class Spec:
    """A validated run file."""

    path: str
    text: str
    scene: str
    method: str
    dt: float
    t_end: float
    save_dt: float
    members: int  # replicas per sweep point
    seed: int
    save: tuple[str, ...]
    parameters: dict[str, float | list | Distribution | Mode] = field(repr=False)
    sweep: dict[str, tuple[float, ...]] = field(repr=False)
    constants: dict[str, int | str] = field(default_factory=dict)  # run constants, e.g. n, boundary
    noise: dict[str, float] = field(default_factory=dict)  # Gaussian observation noise: variable -> stddev
    table: dict[str, np.ndarray] | None = field(default=None, repr=False, compare=False)  # see members_table

    @property
    def steps_per_save(self) -> int:
        return round(self.save_dt / self.dt)

    @property
    def n_save(self) -> int:
        """Saved samples, including t = 0."""
        return round(self.t_end / self.save_dt) + 1

    @property
    def steps(self) -> int:
        return (self.n_save - 1) * self.steps_per_save

    @property
    def sweep_points(self) -> int:
        return math.prod(len(v) for v in self.sweep.values())

    @property
    def n_members(self) -> int:
        return self.sweep_points * self.members

    def times(self) -> np.ndarray:
        """Saved sample times (s)."""
        return np.arange(self.n_save) * (self.steps_per_save * self.dt)


def _type_name(kind) -> str:
    return {float: "a number", int: "an integer", str: "a string", list: "a list", dict: "a table"}[kind]


def _expect(key: str, value, kind):
    """Check the TOML type of a value; ints count as numbers, bools as nothing else."""
    ok = isinstance(value, kind) and not isinstance(value, bool)
    if kind is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not ok:
        raise SpecError(key, f"must be {_type_name(kind)}, got {type(value).__name__} {value!r}")
    return float(value) if kind is float else value


def _unknown(key: str, name: str, known) -> SpecError:
    close = difflib.get_close_matches(name, list(known), n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return SpecError(key, f"unknown key{hint}; known keys: {', '.join(sorted(known))}")


def _positive(key: str, value: float) -> float:
    if not value > 0 or not math.isfinite(value):
        raise SpecError(key, f"must be > 0 and finite, got {value!r}")
    return value


def _whole_ratio(key: str, num: float, den: float, what: str) -> None:
    ratio = num / den
    if round(ratio) < 1 or abs(ratio - round(ratio)) > _STEP_RTOL * ratio:
        raise SpecError(key, f"must be a whole multiple of {what} ({num!r} / {den!r} = {ratio:.12g})")


def _distribution(key: str, value: dict) -> Distribution:
    if len(value) != 1 or next(iter(value)) not in DISTRIBUTIONS:
        raise SpecError(key, f"a distribution is one of {{uniform=[lo,hi]}}, {{normal=[mu,sd]}}, "
                             f"{{loguniform=[lo,hi]}}; got {value!r}")
    kind, args = next(iter(value.items()))
    if not (isinstance(args, list) and len(args) == 2):
        raise SpecError(f"{key}.{kind}", f"must be a list of two numbers, got {args!r}")
    lo, hi = (_expect(f"{key}.{kind}", x, float) for x in args)
    if kind == "normal" and hi < 0:
        raise SpecError(f"{key}.normal", f"standard deviation must be >= 0, got {hi!r}")
    if kind != "normal" and lo > hi:
        raise SpecError(f"{key}.{kind}", f"lower bound {lo!r} is above upper bound {hi!r}")
    if kind == "loguniform" and lo <= 0:
        raise SpecError(f"{key}.loguniform", f"bounds must be > 0, got {lo!r}")
    return Distribution(kind, (lo, hi))


def _parameter(key: str, value, parameter: Parameter):
    """A parameter's value in one of the forms its declaration accepts."""
    if parameter.integer:
        return _expect(key, value, int)
    if parameter.choices:
        if value not in parameter.choices:
            raise SpecError(key, f"must be one of {', '.join(map(repr, parameter.choices))}, got {value!r}")
        return value
    if isinstance(value, dict) and parameter.mode and "mode" in value:
        if set(value) != {"mode", "amplitude"}:
            raise SpecError(key, f"a mode start is {{ mode = j, amplitude = A }}, got {value!r}")
        return Mode(_expect(f"{key}.mode", value["mode"], int), _expect(f"{key}.amplitude", value["amplitude"], float))
    if isinstance(value, dict):
        return _distribution(key, value)
    if isinstance(value, list) and parameter.per:
        return [_expect(f"{key}[{i}]", x, float) for i, x in enumerate(value)]
    if isinstance(value, list):
        raise SpecError(key, f"takes one value per member (a number or a distribution), got a list")
    return _expect(key, value, float)


def parse(text: str, path: str = "<string>") -> Spec:
    """Validate run-file text; raises SpecError naming the first bad key."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise SpecError("TOML syntax", str(e)) from None
    for key in raw:
        if key not in TOP_LEVEL:
            raise _unknown(key, key, TOP_LEVEL)
    for key in REQUIRED:
        if key not in raw:
            raise SpecError(key, "missing (required)")
    values = {key: _expect(key, raw[key], kind) for key, kind in TOP_LEVEL.items() if key in raw}

    scene = values["scene"]
    if scene not in SCENES:
        raise SpecError("scene", f"unknown scene {scene!r}; scenes: {', '.join(SCENES)}")
    module = SCENES[scene]
    method = values["method"]
    if method not in METHODS:
        raise SpecError("method", f"unknown method {method!r}; methods for {scene}: {', '.join(methods_for(scene))}")
    if scene not in METHODS[method].scenes:
        raise SpecError("method", f"{method!r} does not apply to scene {scene!r}; "
                                  f"use one of: {', '.join(methods_for(scene))}")

    dt = _positive("dt", values["dt"])
    t_end = _positive("t_end", values["t_end"])
    save_dt = _positive("save_dt", values["save_dt"])
    _whole_ratio("save_dt", save_dt, dt, "dt")
    _whole_ratio("t_end", t_end, save_dt, "save_dt")
    if values["members"] < 1:
        raise SpecError("members", f"must be >= 1, got {values['members']}")
    if values["seed"] < 0:
        raise SpecError("seed", f"must be >= 0, got {values['seed']}")

    save = tuple(values.get("save", module.OBSERVABLES))
    for i, name in enumerate(save):
        if name not in module.OBSERVABLES:
            raise SpecError(f"save[{i}]", f"unknown variable {name!r}; {scene} saves: {', '.join(module.OBSERVABLES)}")
    if not save:
        raise SpecError("save", "must name at least one variable")

    noise = _noise(values.get("observe", {}), save, module)

    declared = module.PARAMETERS
    parameters = {}
    for name, value in values.get("parameters", {}).items():
        if name not in declared:
            raise _unknown(f"parameters.{name}", name, declared)
        parameters[name] = _parameter(f"parameters.{name}", value, declared[name])
    sweep = {}
    for name, axis in values.get("sweep", {}).items():
        key = f"sweep.{name}"
        if name not in declared:
            raise _unknown(key, name, declared)
        if declared[name].constant:
            raise SpecError(key, "is a run constant and cannot be swept; use one run file per value")
        if name in parameters:
            raise SpecError(key, "is both a parameter and a sweep axis; give it in one place only")
        if not isinstance(axis, list) or not axis:
            raise SpecError(key, f"a sweep axis must be a non-empty list of numbers, got {axis!r}")
        sweep[name] = tuple(_expect(key, x, float) for x in axis)
    for name, parameter in declared.items():
        if name not in parameters and name not in sweep:
            if parameter.default is None:
                raise SpecError(f"parameters.{name}", "missing (required)")
            parameters[name] = parameter.default
    constants = {name: parameters.pop(name) for name, p in declared.items() if p.constant}
    for name, problem in module.check_constants(constants):
        raise SpecError(f"parameters.{name}", problem)

    spec = Spec(path=str(path), text=text, scene=scene, method=method, dt=dt, t_end=t_end,
                save_dt=save_dt, members=values["members"], seed=values["seed"], save=save,
                parameters=parameters, sweep=sweep, constants=constants, noise=noise)
    # Drawing every member's values checks them; keep them, as mode starts may cost an eigensolve each.
    return replace(spec, table=_build_table(spec))


def _noise(observe: dict, save: tuple[str, ...], module) -> dict[str, float]:
    """The [observe] table: noise = { variable = standard deviation (the variable's units) }."""
    for key in observe:
        if key not in OBSERVE_KEYS:
            raise _unknown(f"observe.{key}", key, OBSERVE_KEYS)
    noise = _expect("observe.noise", observe.get("noise", {}), dict)
    out = {}
    for name, sigma in noise.items():
        key = f"observe.noise.{name}"
        if name not in module.OBSERVABLES:
            raise _unknown(key, name, module.OBSERVABLES)
        if name not in save:
            raise SpecError(key, f"{name!r} is not saved; add it to save")
        sigma = _expect(key, sigma, float)
        if not sigma >= 0 or math.isinf(sigma):
            raise SpecError(key, f"must be a finite standard deviation >= 0, got {sigma}")
        out[name] = sigma
    return out


def load(path: str | Path) -> Spec:
    """Read and validate a run file."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise SpecError("run file", f"cannot read it: {e.strerror or e}") from None
    return parse(text, str(path))


def members_table(spec: Spec) -> dict[str, np.ndarray]:
    """Every member's parameter values, each an array over members (built once, by parse).

    Members are ordered sweep point major, replica minor; the table also holds
    `sweep_point`, the index of each member's point on the sweep grid.
    """
    return spec.table if spec.table is not None else _build_table(spec)


def _build_table(spec: Spec) -> dict[str, np.ndarray]:
    n = spec.n_members
    grid = list(itertools.product(*spec.sweep.values())) or [()]
    point = np.repeat(np.arange(len(grid)), spec.members)
    table = {"sweep_point": point}
    for i, name in enumerate(spec.sweep):
        table[name] = np.array([g[i] for g in grid], dtype=float)[point]
    scene = SCENES[spec.scene]
    sizes = scene.sizes(spec.constants)
    modes = {}
    for name, value in spec.parameters.items():
        per = scene.PARAMETERS[name].per
        shape = (n, sizes[per]) if per else (n,)
        if isinstance(value, Mode):
            modes[name] = value
        elif isinstance(value, Distribution):
            rng = np.random.default_rng([spec.seed, zlib.crc32(name.encode())])
            table[name] = value.draw(rng, math.prod(shape)).reshape(shape)
        elif isinstance(value, list):
            if len(value) != shape[1]:
                raise SpecError(f"parameters.{name}", f"has {len(value)} values; this chain has {shape[1]} "
                                                      f"{'masses' if per == 'site' else 'springs'}")
            table[name] = np.tile(np.array(value, dtype=float), (n, 1))
        else:
            table[name] = np.full(shape, value, dtype=float)
    for name in spec.sweep:
        per = scene.PARAMETERS[name].per
        if per:
            table[name] = np.repeat(table[name][:, None], sizes[per], axis=1)
    for name, problem in SCENES[spec.scene].check(table):
        where = "sweep" if name in spec.sweep else "parameters"
        raise SpecError(f"{where}.{name}", problem)
    for name, mode in modes.items():
        if not 1 <= mode.number <= sizes["site"]:
            raise SpecError(f"parameters.{name}.mode", f"must be in 1..{sizes['site']}, got {mode.number}")
        table[name] = scene.mode_start(mode, table["m"], table["k"], spec.constants["boundary"])
    return table


def observation_noise(spec: Spec, name: str, first: int, shape: tuple[int, ...]) -> np.ndarray:
    """Gaussian noise (stddev spec.noise[name]) for members first, first + 1, ...; shape (members, ...)."""
    stream = zlib.crc32(f"noise:{name}".encode())
    return spec.noise[name] * np.stack([
        np.random.default_rng([spec.seed, stream, first + i]).standard_normal(shape[1:]) for i in range(shape[0])
    ])
