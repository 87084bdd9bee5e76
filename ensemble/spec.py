"""Reading and validating run files, and expanding them into a members table.

A run file is TOML (see README.md). Every problem is a SpecError naming the
key, so the command line can print one line and exit with status 2.

Randomness: parameter `name` of member i takes values i*k .. i*k + k - 1 (k
values per member: 1, or one per mass or spring) of a PCG64 stream seeded by
(seed, crc32(name)), reached by jumping the stream ahead (PCG64.advance), so
any range of members is drawn in time proportional to its length. A value is
a pure function of (seed, parameter, member index): never of chunk size,
thread count, worker, or the order of keys in the file. Each value uses one
64-bit output: uniform as numpy's Generator.uniform, loguniform its exp of a
uniform, normal the inverse normal CDF of a uniform on (0, 1).
(Observation noise is drawn where it is added, in the runner.)

Parsing imports no Numba: a run file is checked before any kernel is loaded.
"""
from __future__ import annotations

import difflib
import hashlib
import io
import itertools
import math
import re
import tomllib
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .errors import EnsembleError
from .inertia import SHAPES, polygon
from .methods import METHODS
from .parameter import Mode, Parameter, ParameterError
from .results import DEFAULT_BLOWUP_FACTOR
from .scenes import SceneError, absolute, applies, methods_for, resolve
from .scenes.contract import SceneChanged, identity


class SpecError(EnsembleError, ValueError):
    """A problem in a run file, tied to the key where it is."""

    def __init__(self, key: str, problem: str):
        super().__init__(f"{key}: {problem}")
        self.key = key
        self.problem = problem


TOP_LEVEL = {
    "scene": str, "method": str, "dt": float, "rtol": float, "atol": float, "t_end": float, "save_dt": float,
    "members": int, "seed": int, "save": list, "parameters": dict, "sweep": (dict, list), "observe": dict,
    "measure": dict, "blowup_factor": float, "device": str, "precision": str, "draws": str,
}
DRAWS = ("each member", "same at every point")  # whose stream a member's drawn parameters come from
DEVICES = ("cpu", "cuda")  # where the kernels run: this machine's cores, or an NVIDIA GPU (ensemble.engine.gpu)
PRECISIONS = ("float64", "float32")  # float32 on a GPU only
OBSERVE_KEYS = ("noise",)
MEASURE_KEYS = {"error": bool, "timing": bool, "repeats": int, "growth": bool}
REQUIRED = ("scene", "t_end", "save_dt", "members", "seed")
# How each member integrates; each may be a top-level value or a sweep axis.
SETTINGS = ("method", "dt", "rtol", "atol")
DEFAULT_TOLERANCES = {"rtol": 1e-6, "atol": 1e-9}  # for adaptive methods
DISTRIBUTIONS = ("uniform", "normal", "loguniform")
_STEP_RTOL = 1e-9  # how close save_dt / dt and t_end / save_dt must be to whole numbers
MAY_BE_INFINITE = ("blowup_factor",)  # inf: only a non-finite state fails a member
# What a run file may ask for, refused before anything is allocated:
MAX_RUN_FILE_BYTES = 1_000_000  # a run file is a short text
MAX_NESTING = 32  # levels of arrays, inline tables and dotted keys: deeper, tomllib recurses past Python's limit
# or (dotted keys) takes time that grows with the square of the depth
MAX_STEPS = 10**12  # steps per member (t_end / dt), and saved samples per member (t_end / save_dt)
MAX_SEED = 2**63 - 1  # the seed is stored as a 64-bit integer
MAX_TABLE_BYTES = 2**31  # every member's parameters, held in memory for the whole run
EIGENPROBLEM_ARRAYS = 3  # n x n arrays per member while mode starts are solved: stiffness, shapes, LAPACK's work
MAX_REPEATS = 100  # [measure] repeats: timed kernel calls per chunk
MAX_NOISE = 1e150  # observation noise's stddev: far below it a Gaussian draw (at most ~40 sd) stays finite
POLYGON = "polygon"  # a shape given by its mass and its vertices (a run constant), not by lengths


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
        return np.exp(np.random.Generator(bits).uniform(math.log(lo), math.log(hi), count))


@dataclass(frozen=True)
class Spec:
    """A validated run file."""

    path: str
    text: str
    scene: str
    method: str | None  # None when swept
    dt: float | None  # None when swept or not needed (adaptive and exact methods)
    t_end: float
    save_dt: float
    members: int  # replicas per sweep point
    seed: int
    save: tuple[str, ...]
    parameters: dict[str, float | list | Distribution | Mode] = field(repr=False)
    grids: tuple[dict[str, tuple], ...] = field(repr=False)  # sweep grids: axis -> values; the run is their union
    constants: dict[str, int | str] = field(default_factory=dict)  # run constants, e.g. n, boundary
    declared: dict[str, Parameter] = field(default_factory=dict, repr=False)  # every per-member parameter
    noise: dict[str, float] = field(default_factory=dict)  # Gaussian observation noise: variable -> stddev
    rtol: float | None = None  # top-level tolerances of adaptive methods
    atol: float | None = None
    measure: dict[str, object] = field(default_factory=dict)  # [measure]: error, timing, repeats, growth
    blowup_factor: float = DEFAULT_BLOWUP_FACTOR  # a member fails when its state outgrows its start this much
    device: str = "cpu"  # one of DEVICES
    precision: str = "float64"  # one of PRECISIONS
    draws: str = "each member"  # one of DRAWS: "same at every point" gives replica r the same draws at every point
    table: dict[str, np.ndarray] | None = field(default=None, repr=False, compare=False)  # see members_table
    # a user's scene: the identity of its sources when the run file was read (model refuses any other)
    sources: str | None = field(default=None, compare=False)

    @property
    def model(self):
        """The scene (ensemble.scenes.Scene) that `scene` names: for a user's scene, the sources the run file was
        read with (SceneError, one line, if it or a module of the user's it imports was edited since: a run never
        mixes two physics)."""
        scene = resolve(self.scene)
        module = getattr(scene, "module", None)
        if self.sources is not None and module is not None and identity(module) != self.sources:
            raise SceneChanged(f"{self.scene} (or a module of yours it imports) changed since the run began; a run "
                             f"takes one physics: run it again (--force to start over)")
        return scene

    @property
    def n_save(self) -> int:
        """Saved samples, including t = 0."""
        return round(self.t_end / self.save_dt) + 1

    @property
    def sweep(self) -> dict[str, tuple]:
        """Every sweep axis and the values it takes in any grid."""
        out: dict[str, tuple] = {}
        for grid in self.grids:
            for name, values in grid.items():
                out[name] = tuple(dict.fromkeys(out.get(name, ()) + values))
        return out

    @property
    def sweep_points(self) -> int:
        return sum(math.prod(len(v) for v in grid.values()) for grid in self.grids) or 1

    @property
    def n_members(self) -> int:
        return self.sweep_points * self.members

    @property
    def methods(self) -> tuple[str, ...]:
        """The methods the run uses, in order of first use (from the sweep grids: no members table needed)."""
        return tuple(dict.fromkeys(m for grid in self.grids or ({},) for m in grid.get("method", (self.method,))))

    def times(self, first: int = 0, stop: int | None = None) -> np.ndarray:
        """Saved sample times (s) of samples first .. stop - 1 (default: to the last): a run's whole record of
        times is never needed at once (a member may save 10^8 samples)."""
        return np.arange(first, self.n_save if stop is None else min(stop, self.n_save)) * self.save_dt


def _type_name(kind) -> str:
    if isinstance(kind, tuple):
        return " or ".join(map(_type_name, kind))
    return {float: "a number", int: "an integer", str: "a string", list: "a list", dict: "a table",
            bool: "true or false"}[kind]


def _expect(key: str, value, kind):
    """Check the TOML type of a value; ints count as numbers, bools as nothing else. Every number a run file gives
    passes here, so this is the one place that refuses NaN and infinity (TOML has both): a number must be finite
    unless its key is in MAY_BE_INFINITE."""
    ok = isinstance(value, kind) and (kind is bool or not isinstance(value, bool))
    if kind is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not ok:
        raise SpecError(key, f"must be {_type_name(kind)}, got {type(value).__name__} {value!r}")
    if kind is float and not math.isfinite(value) and not (math.isinf(value) and key in MAY_BE_INFINITE):
        raise SpecError(key, f"must be a finite number, got {value!r}")
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
    if not ratio <= MAX_STEPS:
        raise SpecError(key, f"{key} / {what} = {num!r} / {den!r} = {ratio:.3g}: more than the {MAX_STEPS:.0e} a run "
                             f"may ask for")
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
    if kind == "uniform" and not math.isfinite(hi - lo):
        raise SpecError(f"{key}.uniform", f"the range {lo!r} to {hi!r} is wider than a float64 can hold")
    if kind == "loguniform" and lo <= 0:
        raise SpecError(f"{key}.loguniform", f"bounds must be > 0, got {lo!r}")
    return Distribution(kind, (lo, hi))


def _parameter(key: str, value, parameter: Parameter):
    """A parameter's value in one of the forms its declaration accepts."""
    if isinstance(value, PerMember):
        if parameter.integer or parameter.choices or parameter.constant:
            raise SpecError(key, "is one value for the whole run, not one per member")
        return value
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
    if isinstance(value, dict) and "file" in value:
        raise SpecError(key, f"values from a file are {{ file = \"NAME.npy\" }} alone, got {value!r}")
    if isinstance(value, dict):
        return _distribution(key, value)
    if isinstance(value, list) and parameter.per:
        return [_expect(f"{key}[{i}]", x, float) for i, x in enumerate(value)]
    if isinstance(value, list):
        raise SpecError(key, "takes one value per member (a number or a distribution), got a list")
    return _expect(key, value, float)


def _nesting_problem(text: str) -> str | None:
    """Why the run file nests too deeply to be parsed (None if it does not), found before parsing: arrays and
    inline tables over MAX_NESTING deep, or a key of more than MAX_NESTING dotted parts. Strings and comments
    are left out of the count."""
    bare = re.sub(r'"""[\s\S]*?"""|\'\'\'[\s\S]*?\'\'\'|"(?:[^"\\\n]|\\.)*"|\'[^\'\n]*\'|#[^\n]*', '""', text)
    depth = deepest = 0
    for bracket in re.findall(r"[\[\]{}]", bare):
        depth += 1 if bracket in "[{" else -1
        deepest = max(deepest, depth)
    if deepest > MAX_NESTING + 1:  # a table header's brackets count once, an array of tables' twice
        return f"arrays and tables nest {deepest} deep; at most {MAX_NESTING}"
    for line in bare.splitlines():  # keys: before an =, or a table's header; not the values of a long array
        key = line.split("=", 1)[0] if "=" in line else line.strip().strip("[]")
        if key.count(".") >= MAX_NESTING and re.fullmatch(r'[\w.\-\s"]+', key):
            return f"a key of {key.count('.') + 1} dotted parts; at most {MAX_NESTING}"
    return None


def _top_level(text: str) -> dict:
    """The run file's top-level keys, each of its expected type."""
    problem = _nesting_problem(text)
    if problem:
        raise SpecError("TOML syntax", problem)
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
    for name in SETTINGS:
        if name in values.get("parameters", {}):
            raise SpecError(f"parameters.{name}", "is a run setting: give it at the top of the run file (or sweep "
                                                  "it under [sweep]), not under [parameters]")
    return values


def _grids(sweep) -> tuple[list[dict], list[str]]:
    """The sweep grids and where each is written: [sweep] is one grid, [[sweep]] tables a union of grids."""
    if isinstance(sweep, list):
        grids = [_expect(f"sweep[{g}]", grid, dict) for g, grid in enumerate(sweep)]
        return grids, [f"sweep[{g}]" for g in range(len(grids))]
    return ([sweep], ["sweep"]) if sweep else ([], [])


def parse(text: str, path: str = "<string>") -> Spec:
    """Validate run-file text; raises SpecError naming the first bad key."""
    values = _top_level(text)
    scene = absolute(values["scene"], Path(path).parent if path != "<string>" else Path.cwd())
    try:
        module = resolve(scene)
    except SceneError as error:
        raise SpecError("scene", str(error)) from None

    t_end = _positive("t_end", values["t_end"])
    save_dt = _positive("save_dt", values["save_dt"])
    grids, labels = _grids(values.get("sweep", {}))
    settings = {key: values[key] for key in SETTINGS if key in values}
    setting_axes = [_settings(settings, {k: v for k, v in grid.items() if k in SETTINGS}, label, module, save_dt)
                    for grid, label in zip(grids, labels)] or [_settings(settings, {}, "sweep", module, save_dt)]
    _whole_ratio("t_end", t_end, save_dt, "save_dt")
    if values["members"] < 1:
        raise SpecError("members", f"must be >= 1, got {values['members']}")
    _check_bounds(values["seed"], t_end, [axes.get("dt", (settings["dt"],) if "dt" in settings else ())
                                          for axes in setting_axes])

    save = _save(tuple(values.get("save", module.OBSERVABLES)), module)

    blowup_factor = values.get("blowup_factor", DEFAULT_BLOWUP_FACTOR)
    if not blowup_factor > 1:
        raise SpecError("blowup_factor", f"must be > 1 (a member fails when its state grows this many times its "
                                         f"size at the start), got {blowup_factor!r}")
    device, precision = _device(values.get("device", "cpu"), values.get("precision", "float64"))
    draws = _one_of("draws", values.get("draws", DRAWS[0]), DRAWS)
    noise = _noise(values.get("observe", {}), save, module)
    measure = _measure(values.get("measure", {}), module)

    parameters, grids, constants, declared = _parameters(
        _from_files(values.get("parameters", {}), Path(path).parent if path != "<string>" else Path.cwd()),
        [{k: v for k, v in grid.items() if k not in SETTINGS} for grid in grids], labels, module)
    for grid, axes in zip(grids, setting_axes):
        grid.update(axes)

    spec = Spec(path=str(path), text=text, scene=scene, method=settings.get("method"), dt=settings.get("dt"),
                t_end=t_end, save_dt=save_dt, members=values["members"], seed=values["seed"], save=save,
                parameters=parameters, grids=tuple(grids), constants=constants, noise=noise,
                declared=declared, rtol=settings.get("rtol"), atol=settings.get("atol"), measure=measure,
                blowup_factor=blowup_factor, device=device, precision=precision, draws=draws,
                sources=identity(module.module) if hasattr(module, "module") else None)
    sizes = module.sizes(constants)
    need = 8 * spec.n_members * (sum(sizes[p.per] if p.per else 1 for p in declared.values()) + len(SETTINGS) + 1)
    if need > MAX_TABLE_BYTES:
        raise SpecError("members", f"{spec.n_members} member(s) ({values['members']} per sweep point) need "
                                   f"{need / 1e9:.3g} GB of parameters in memory; at most "
                                   f"{MAX_TABLE_BYTES / 1e9:.3g} GB")
    # Drawing every member's values checks them; keep them, as mode starts may cost an eigensolve each.
    return replace(spec, table=_build_table(spec))


def _save(save: tuple, module) -> tuple[str, ...]:
    """The variables a run saves, checked: at least one, each the scene's, none twice."""
    for i, name in enumerate(save):
        if name not in module.OBSERVABLES:
            raise SpecError(f"save[{i}]", f"unknown variable {name!r}; {module.NAME} saves: "
                                          f"{', '.join(module.OBSERVABLES)}")
        if name in save[:i]:
            raise SpecError(f"save[{i}]", f"names {name!r} a second time")
    if not save:
        raise SpecError("save", "must name at least one variable")
    return save


def _one_of(key: str, value: str, allowed: tuple[str, ...]) -> str:
    if value not in allowed:
        raise SpecError(key, f"must be one of {', '.join(map(repr, allowed))}, got {value!r}")
    return value


def _from_files(given: dict, folder: Path) -> dict:
    """[parameters] with each `{ file = "NAME.npy" }` read (a path relative to the run file's folder): PerMember
    values, checked to be finite numbers."""
    out = dict(given)
    for name, value in given.items():
        if not (isinstance(value, dict) and set(value) == {"file"}):
            continue
        where = folder / _expect(f"parameters.{name}.file", value["file"], str)
        try:
            data = where.read_bytes()
            values = np.load(io.BytesIO(data), allow_pickle=False)
        except (OSError, ValueError, EOFError) as e:
            raise SpecError(f"parameters.{name}.file", f"{where}: cannot be read as a .npy array "
                                                       f"({getattr(e, 'strerror', None) or e})") from None
        if values.dtype.kind not in "iuf" or values.ndim not in (1, 2) or not np.all(np.isfinite(values)):
            raise SpecError(f"parameters.{name}.file", f"{where}: must hold finite numbers, one row a member, "
                                                       f"got {values.dtype} of shape {values.shape}")
        out[name] = PerMember(values.astype(float), f"{where} (sha256 {hashlib.sha256(data).hexdigest()[:16]})")
    return out


def _device(device: str, precision: str) -> tuple[str, str]:
    """The run file's device and precision, checked (not whether this machine has the device: see
    ensemble.engine.gpu.require_gpu)."""
    _one_of("device", device, DEVICES)
    _one_of("precision", precision, PRECISIONS)
    if precision == "float32" and device != "cuda":
        raise SpecError("precision", 'float32 runs on a GPU only (device = "cuda"); the CPU kernels are float64')
    return device, precision


def _check_bounds(seed: int, t_end: float, steps: list[tuple[float, ...]]) -> None:
    """The seed's range, and the steps per member of every grid's dt values."""
    if not 0 <= seed <= MAX_SEED:
        raise SpecError("seed", f"must be in 0 .. 2**63 - 1, got {seed}")
    for dt in (dt for grid in steps for dt in grid):
        if not t_end / dt <= MAX_STEPS:
            raise SpecError("dt", f"t_end / dt = {t_end / dt:.3g} steps per member: more than the {MAX_STEPS:.0e} "
                                  f"a run may ask for")


def _parameters(given: dict, grids: list[dict], labels: list[str], module):
    """[parameters] and the parameter axes of each sweep grid, checked against the scene's declarations.

    Returns per-member parameters (name -> value), each grid's axes (name ->
    values), run constants and the declarations of every per-member
    parameter the dataset records.
    """
    given, grids = dict(given), [dict(grid) for grid in grids]
    declared = dict(module.PARAMETERS)
    keys = {name: f"parameters.{name}" for name in declared}  # where each parameter's value is written
    constants = {}
    for name, parameter in module.PARAMETERS.items():
        if parameter.derives:
            _shape_parameter(name, given, grids, labels, declared, keys, constants)
    parameters = {}
    for name, value in given.items():
        if name not in declared:
            raise _unknown(f"parameters.{name}", name, module.PARAMETERS)
        parameters[name] = _parameter(keys[name], value, declared[name])
    axes = _parameter_axes(grids, labels, keys, declared, parameters, module)
    swept = set(axes[0]) if axes else set()
    for name, parameter in declared.items():
        if name not in parameters and name not in swept and not _derived(name, module, constants):
            if parameter.optional:
                continue
            if parameter.default is None:
                sources = [source for source, p in module.PARAMETERS.items() if name in p.derives]
                raise SpecError(keys[name], "missing (required" + "".join(
                    f"; or give parameters.{source} as a shape" for source in sources) + ")")
            parameters[name] = parameter.default
    constants.update({name: parameters.pop(name) for name, p in declared.items() if p.constant})
    try:
        module.check_constants(constants)
    except ParameterError as e:
        raise SpecError(f"parameters.{e.name}", e.problem) from None
    given = set(parameters) | swept
    return parameters, axes, constants, {name: p for name, p in declared.items()
                                         if not p.constant and (name in given or not p.optional)}


def _shape_parameter(name: str, given: dict, grids: list[dict], labels: list[str], declared: dict, keys: dict,
                     constants: dict) -> None:
    """A parameter that `derives` others (the top's `body`), given as a shape table, in place.

    Its shape becomes the constant `<name>_shape`, its mass and lengths become
    parameters `<name>_<dimension>` (swept as `<name>.<dimension>`), and the
    parameters it derives are computed from it when the members table is built.
    """
    parameter = declared.pop(name)
    if name not in given:
        for grid, label in zip(grids, labels):
            if name in grid:
                raise SpecError(f"{label}.{name}", f"needs parameters.{name} with its shape")
        return
    for other in parameter.derives:
        if other in given or any(other in grid for grid in grids):
            raise SpecError(f"parameters.{other}", f"is given by parameters.{name}; give "
                                                   f"{' and '.join(parameter.derives)}, or {name}, not both")
    shape, dimensions = _shape(f"parameters.{name}", given.pop(name))
    constants[f"{name}_shape"] = shape
    if shape == POLYGON:
        if "vertices" not in dimensions:
            raise SpecError(f"parameters.{name}.vertices", "missing (a polygon needs its vertices)")
        constants[f"{name}_vertices"] = _vertices(f"parameters.{name}.vertices", dimensions.pop("vertices"))
    lengths = ("mass", *(() if shape == POLYGON else SHAPES[shape].lengths))
    for dim in lengths:
        flat = f"{name}_{dim}"
        if flat in given or any(flat in grid for grid in grids):
            raise SpecError(f"{'parameters' if flat in given else 'sweep'}.{flat}",
                            f"give it as {dim} in parameters.{name} (or as {name}.{dim} under [sweep])")
        keys[flat] = f"parameters.{name}.{dim}"
        declared[flat] = Parameter("kg" if dim == "mass" else "m", f"{dim.replace('_', ' ')} of the {shape} body")
        if dim in dimensions:
            given[flat] = dimensions.pop(dim)
    for dim in dimensions:
        raise _unknown(f"parameters.{name}.{dim}", dim, ("shape", *lengths))
    for grid, label in zip(grids, labels):
        swept = _expect(f"{label}.{name}", grid.pop(name, {}), dict)
        for dim, axis in swept.items():
            if dim not in lengths:
                raise _unknown(f"{label}.{name}.{dim}", dim, lengths)
            grid[f"{name}_{dim}"] = axis


def _parameter_axes(grids: list[dict], labels: list[str], keys: dict, declared: dict, parameters: dict,
                    module) -> list[dict[str, tuple]]:
    """Each grid's parameter axes, checked: declared, not run constants, not also fixed, the same in every grid."""
    axes = []
    for grid, label in zip(grids, labels):
        checked = {}
        for name, axis in grid.items():
            key = f"{label}.{keys[name].removeprefix('parameters.')}" if name in keys else f"{label}.{name}"
            if name not in declared:
                raise _unknown(key, name, (*module.PARAMETERS, *SETTINGS))
            if declared[name].constant:
                raise SpecError(key, "is a run constant and cannot be swept; use one run file per value")
            if name in parameters:
                raise SpecError(key, "is both a parameter and a sweep axis; give it in one place only")
            checked[name] = _axis(key, axis, float)
        if axes and set(checked) != set(axes[0]):
            raise SpecError(label, f"sweeps parameters {sorted(checked)}, but {labels[0]} sweeps {sorted(axes[0])}: "
                                   f"every grid must sweep the same parameters (methods and steps may differ)")
        axes.append(checked)
    return axes


def _axis(key: str, axis, kind) -> tuple:
    if not isinstance(axis, list) or not axis:
        raise SpecError(key, f"a sweep axis must be a non-empty list, got {axis!r}")
    values = tuple(_expect(key, x, kind) for x in axis)
    repeated = [x for i, x in enumerate(values) if x in values[:i]]
    if repeated:
        raise SpecError(key, f"repeats the value {repeated[0]!r}: each sweep point once")
    return values


def _settings(top: dict, axes: dict, label: str, module, save_dt: float) -> dict[str, tuple]:
    """Check how one grid's members integrate: its method, dt, rtol and atol axes against the top-level values.

    Returns the grid's setting axes (the swept ones).
    """
    out = {}
    for key, axis in axes.items():
        if key in top:
            raise SpecError(f"{label}.{key}", "is both a top-level value and a sweep axis; give it in one place only")
        out[key] = _axis(f"{label}.{key}", axis, str if key == "method" else float)
    where = {key: f"{label}.{key}" if key in out else key for key in SETTINGS}
    if "method" not in top and "method" not in out:
        raise SpecError("method", "missing (required)")
    tolerances = [key for key in ("rtol", "atol") if key in top or key in out]
    for key in tolerances:
        for value in out.get(key, (top.get(key),)):
            if not value > 0 or not math.isfinite(value):
                raise SpecError(where[key], f"must be > 0 and finite, got {value!r}")
    for value in out.get("dt", (top["dt"],) if "dt" in top else ()):
        _positive(where["dt"], value)
    for method in out.get("method", (top.get("method"),)):
        _check_method(method, module, where, tolerances, "dt" in out, "dt" in top or "dt" in out)
        if not METHODS[method].adaptive and ("dt" in top or "dt" in out):
            for value in out.get("dt", (top.get("dt"),)):
                _whole_ratio("save_dt", save_dt, value, "dt")
    return out


def _check_method(method: str, module, where: dict[str, str], tolerances: list[str], dt_swept: bool,
                  dt_given: bool) -> None:
    """One method of a grid: known, applicable to the scene, and given the settings its kind takes."""
    names = ", ".join(m.name for m in methods_for(module))
    if method not in METHODS:
        raise SpecError(where["method"], f"unknown method {method!r}; methods for {module.NAME}: {names}")
    m = METHODS[method]
    if not applies(m, module):
        raise SpecError(where["method"], f"{method!r} does not apply to scene {module.NAME!r}; use one of: {names}")
    if m.adaptive:
        if dt_swept:
            raise SpecError(where["dt"], f"is swept, but {method!r} is adaptive: dt is only its first trial step; "
                                         f"sweep rtol instead")
        return
    if tolerances:
        adaptive = ", ".join(m.name for m in methods_for(module) if m.adaptive)
        raise SpecError(where[tolerances[0]], f"tolerances apply only to adaptive methods ({adaptive}); {method!r} "
                                              f"takes a fixed step dt")
    if not dt_given and not m.closed_form:
        raise SpecError("dt", f"missing (required by the fixed-step method {method!r})")


def _measure(measure: dict, module) -> dict[str, object]:
    """The [measure] table: error = true, timing = true, repeats = N (best of N timed kernel calls), growth =
    true (growth_per_step, for stability studies)."""
    out = {"error": False, "timing": False, "repeats": 3, "growth": False}
    for key, value in measure.items():
        if key not in MEASURE_KEYS:
            raise _unknown(f"measure.{key}", key, MEASURE_KEYS)
        out[key] = _expect(f"measure.{key}", value, MEASURE_KEYS[key])
    if not 1 <= out["repeats"] <= MAX_REPEATS:
        raise SpecError("measure.repeats", f"must be in 1..{MAX_REPEATS} (timed kernel calls per chunk), got "
                                           f"{out['repeats']}")
    if out["error"] and getattr(module, "exact", None) is None:
        raise SpecError("measure.error", f"scene {module.NAME!r} has no exact solution to measure errors against")
    return out


def _derived(name: str, module, constants: dict) -> bool:
    """`name` is computed from a shape parameter that the run file gives."""
    return any(name in p.derives and f"{source}_shape" in constants for source, p in module.PARAMETERS.items())


def _shape(key: str, value) -> tuple[str, dict]:
    """A shape table { shape = "...", mass = ..., <lengths> = ... }: the shape and the rest."""
    if not isinstance(value, dict) or "shape" not in value:
        raise SpecError(key, f'must be a shape table such as {{ shape = "annulus", mass = 0.1, r_inner = 0.1, '
                             f'r_outer = 0.13 }}, got {value!r}')
    value = dict(value)
    shape = value.pop("shape")
    if not isinstance(shape, str) or (shape not in SHAPES and shape != POLYGON):
        raise SpecError(f"{key}.shape", f"unknown shape {shape!r}; shapes: {', '.join(SHAPES)}, {POLYGON}")
    return shape, value


def _vertices(key: str, value) -> str:
    """A polygon's vertices [[x1, y1], [x2, y2], ...] (m), as the text "x1,y1 x2,y2 ..." the dataset records."""
    if not isinstance(value, list) or not all(isinstance(v, list) and len(v) == 2 for v in value):
        raise SpecError(key, f"must be a list of [x, y] pairs in m, such as [[0, 0], [0.3, 0], [0, 0.3]], "
                             f"got {value!r}")
    pairs = [[_expect(key, x, float) for x in v] for v in value]
    return " ".join(f"{x!r},{y!r}" for x, y in pairs)


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
        if not 0 <= sigma <= MAX_NOISE:
            raise SpecError(key, f"must be a standard deviation in 0..{MAX_NOISE:g} (a larger one turns values into "
                                 f"inf), got {sigma}")
        out[name] = sigma
    return out


def load(path: str | Path) -> Spec:
    """Read and validate a run file."""
    path = Path(path)
    try:
        with open(path, "rb") as file:
            raw = file.read(MAX_RUN_FILE_BYTES + 1)
    except OSError as e:
        raise SpecError("run file", f"cannot read it: {e.strerror or e}") from None
    if len(raw) > MAX_RUN_FILE_BYTES:
        raise SpecError("run file", f"is larger than {MAX_RUN_FILE_BYTES / 1e6:g} MB; a run file is a short TOML text")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise SpecError("run file", f"is not UTF-8 text (byte {e.start})") from None
    return parse(text, str(path))


def with_values(spec: Spec, values: dict) -> Spec:
    """`spec` with parameters given member by member (name: an array over the run's members, or over a sweep
    point's, each member a number or a row of one per site or spring), in place of what the run file says."""
    parameters, declared = dict(spec.parameters), dict(spec.declared)
    for name, given in values.items():
        known = spec.model.PARAMETERS.get(name)
        if known is None or name in spec.sweep or known.constant:
            raise SpecError(f"values.{name}", f"is not a per-member parameter of the {spec.model.NAME} scene that "
                                              f"this run does not sweep")
        try:
            array = np.array(given, dtype=float)
        except (TypeError, ValueError):
            raise SpecError(f"values.{name}", f"must be an array of numbers, got {type(given).__name__}") from None
        if array.ndim not in (1, 2) or not np.all(np.isfinite(array)):
            raise SpecError(f"values.{name}", f"must be finite numbers, one row a member, got shape {array.shape}")
        parameters[name] = _parameter(f"values.{name}", PerMember(array, "ensemble.run(values=...)"), known)
        declared[name] = known
    spec = replace(spec, parameters=parameters, declared=declared)
    return replace(spec, table=_build_table(spec))


def given_values(spec: Spec) -> str:
    """Where the parameters given member by member came from ("" if none): "name: source; ..."."""
    return "; ".join(f"{name}: {value.source}" for name, value in spec.parameters.items()
                     if isinstance(value, PerMember))


def members_table(spec: Spec, start: int = 0, stop: int | None = None) -> dict[str, np.ndarray]:
    """The parameter values of members start .. stop - 1 (default: every member), each an array over those
    members: a slice of the table parse built, or (a spec sent without it, as to a Dask worker) built for
    that range alone, in time proportional to its length.

    Members are ordered sweep point major, replica minor; the table also holds
    `sweep_point`, the index of each member's point on the sweep grids, and how
    each member integrates: `method` (names), `dt`, `rtol`, `atol` (NaN where
    the method takes none).
    """
    stop = spec.n_members if stop is None else stop
    if spec.table is None:
        return _build_table(spec, start, stop)
    if (start, stop) == (0, spec.n_members):
        return spec.table
    return {name: values[start:stop] for name, values in spec.table.items()}


def _build_table(spec: Spec, start: int = 0, stop: int | None = None) -> dict[str, np.ndarray]:
    stop = spec.n_members if stop is None else stop
    n = stop - start
    points = [dict(zip(grid, combination)) for grid in spec.grids
              for combination in itertools.product(*grid.values())] or [{}]
    point = np.arange(start, stop) // spec.members
    table = {"sweep_point": point}
    for name in spec.sweep:
        if name not in SETTINGS:
            table[name] = np.array([p[name] for p in points], dtype=float)[point]
    table.update(_member_settings(spec, points, point))
    scene = spec.model
    sizes = scene.sizes(spec.constants)
    modes = {name: value for name, value in spec.parameters.items() if isinstance(value, Mode)}
    for name, value in spec.parameters.items():
        if name not in modes:
            table[name] = _values(spec, name, value, start, n, sizes)
    for name in spec.sweep:
        per = spec.declared[name].per if name in spec.declared else None
        if per:
            table[name] = np.repeat(table[name][:, None], sizes[per], axis=1)
    for source, parameter in scene.PARAMETERS.items():
        if f"{source}_shape" in spec.constants:
            table.update(_from_shape(spec, source, table))
    closed_form = spec.measure["error"] or any(METHODS[m].closed_form for m in set(table["method"]))
    try:
        scene.check(table)
        table.update(scene.derive(table, spec.constants))
        if closed_form and hasattr(scene, "check_exact"):
            scene.check_exact(table)
    except ParameterError as e:
        raise SpecError(f"{'sweep' if e.name in spec.sweep else 'parameters'}.{e.name}", e.problem) from None
    except SceneError as e:  # the scene's check raised something else than a ParameterError
        raise SpecError("scene", str(e)) from None
    for name, mode in modes.items():
        if not 1 <= mode.number <= sizes["site"]:
            raise SpecError(f"parameters.{name}.mode", f"must be in 1..{sizes['site']}, got {mode.number}")
        need = EIGENPROBLEM_ARRAYS * 8 * sizes["site"] ** 2 * n
        if need > MAX_TABLE_BYTES:
            raise SpecError(f"parameters.{name}", f"a mode start solves each member's {sizes['site']} x "
                                                  f"{sizes['site']} eigenproblem at once: {n} member(s) need "
                                                  f"{need / 1e9:.3g} GB; at most {MAX_TABLE_BYTES / 1e9:.3g} GB")
        table[name] = scene.mode_start(mode, table["m"], table["k"], spec.constants["boundary"])
    return table


def _member_settings(spec: Spec, points: list[dict], point: np.ndarray) -> dict[str, np.ndarray]:
    """Each member's method, dt, rtol and atol (NaN where its method takes none), from its sweep point."""
    top_level = {"method": spec.method, "dt": spec.dt, "rtol": spec.rtol, "atol": spec.atol}
    settings = [{key: p.get(key, top_level[key]) for key in SETTINGS} for p in points]
    for s in settings:
        if METHODS[s["method"]].adaptive:
            s.update({key: value for key, value in DEFAULT_TOLERANCES.items() if s[key] is None})
    out = {"method": np.array([s["method"] for s in settings])[point]}
    for key in ("dt", "rtol", "atol"):
        out[key] = np.array([np.nan if s[key] is None else s[key] for s in settings], dtype=float)[point]
    return out


def _values(spec: Spec, name: str, value, start: int, n: int, sizes: dict[str, int]) -> np.ndarray:
    """Parameter `name` of members start .. start + n - 1: (n,), or (n, sites or springs) for a per-site one."""
    per = spec.declared[name].per
    shape = (n, sizes[per]) if per else (n,)
    if isinstance(value, PerMember):
        given = value.values.shape
        if given[0] not in (spec.n_members, spec.members) or given[1:] != shape[1:]:
            each = f"{shape[1]} values (one per {per})" if per else "one value"
            point = f", or of the {spec.members} of a sweep point" if spec.members != spec.n_members else ""
            raise SpecError(f"parameters.{name}", f"{value.source}: has shape {given}; it takes {each} for each of "
                                                  f"the run's {spec.n_members} members{point}")
        return value.take(start, n, shape, spec.members, spec.n_members)
    if isinstance(value, Distribution):
        per_member = math.prod(shape[1:])
        if spec.draws == "each member":
            return value.draw(spec.seed, name, start * per_member, n * per_member).reshape(shape)
        out = np.empty((n, per_member))  # member j draws what replica j % members draws at the first point
        done = 0
        while done < n:
            replica = (start + done) % spec.members
            run = min(n - done, spec.members - replica)
            out[done:done + run] = value.draw(spec.seed, name, replica * per_member, run * per_member).reshape(
                run, per_member)
            done += run
        return out.reshape(shape)
    if isinstance(value, list):
        if len(value) != shape[1]:
            raise SpecError(f"parameters.{name}", f"has {len(value)} values; one per {per} takes {shape[1]}")
        return np.tile(np.array(value, dtype=float), (n, 1))
    return np.full(shape, value, dtype=float)


def _from_shape(spec: Spec, source: str, table: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The parameters that shape parameter `source` derives, for every member."""
    name = spec.constants[f"{source}_shape"]
    try:
        with np.errstate(over="ignore", invalid="ignore"):  # moments past a float64 are refused below
            if name == POLYGON:
                vertices = [[float(x) for x in pair.split(",")]
                            for pair in spec.constants[f"{source}_vertices"].split()]
                body = polygon(table[f"{source}_mass"], vertices)
            else:
                shape = SHAPES[name]
                body = shape.build(**{dim: table[f"{source}_{dim}"] for dim in ("mass", *shape.lengths)})
    except ParameterError as e:
        where = "sweep" if f"{source}_{e.name}" in spec.sweep else "parameters"
        raise SpecError(f"{where}.{source}.{e.name}", e.problem) from None
    if not np.all(np.isfinite(body.inertia)):
        raise SpecError(f"parameters.{source}", "its moments of inertia (mass times length squared) are beyond a "
                                                "float64's range (1.8e308 kg m2)")
    try:
        return spec.model.from_body(body, source)
    except ParameterError as e:
        raise SpecError(f"parameters.{e.name}", e.problem) from None
