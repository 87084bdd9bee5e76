"""Reading and validating run files (ensemble.members builds and checks each range's members table; one value's
checks and the draws are in ensemble.runfile).

A run file is TOML (see README.md). Every problem is a SpecError naming the
key, so the command line can print one line and exit with status 2.

Randomness: parameter `name` of member i takes values i*k .. i*k + k - 1 (k
values per member: 1, or one per mass or spring) of a PCG64 stream seeded by
(seed, crc32(name)), reached by jumping the stream ahead (PCG64.advance), so
any range of members is drawn in time proportional to its length. A value is
a pure function of (seed, parameter, member index): never of chunk size,
thread count, worker, or the order of keys in the file. Each value uses one
64-bit output: uniform as numpy's Generator.uniform, loguniform the C library's
exp of a uniform (ensemble.libm), normal the inverse normal CDF of a uniform on (0, 1).
(Observation noise is drawn where it is added, in the runner.)

Parsing imports no Numba: a run file is checked before any kernel is loaded.
"""
from __future__ import annotations

import hashlib
import io
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .events import parse as parse_events
from .inertia import SHAPES
from .members import (  # noqa: F401 (given_values, members_table, with_values: spec's API, built in members)
    check_before_start,
    given_values,
    members_table,
    with_values,
)
from .methods import METHODS
from .parameter import Mode, Parameter, ParameterError
from .results import DEFAULT_BLOWUP_FACTOR
from .runfile import (
    POLYGON,
    SETTINGS,
    Distribution,
    PerMember,
    SpecError,
    axis_values,
    expect,
    parameter_value,
    positive,
    shape_table,
    unknown,
    vertices_text,
)
from .scenes import SceneError, absolute, applies, methods_for, resolve
from .scenes.contract import RESERVED, SceneChanged, identity

TOP_LEVEL = {
    "scene": str, "method": str, "dt": float, "rtol": float, "atol": float, "t_end": float, "save_dt": float,
    "members": int, "seed": int, "save": list, "parameters": dict, "sweep": (dict, list), "observe": dict,
    "measure": dict, "blowup_factor": float, "device": str, "precision": str, "draws": str, "events": dict,
}
DRAWS = ("each member", "same at every point")  # whose stream a member's drawn parameters come from
DEVICES = ("cpu", "cuda")  # where the kernels run: this machine's cores, or an NVIDIA GPU (ensemble.engine.gpu)
PRECISIONS = ("float64", "float32")  # float32 on a GPU only
OBSERVE_KEYS = ("noise",)
MEASURE_KEYS = {"error": bool, "timing": bool, "repeats": int, "growth": bool}
REQUIRED = ("scene", "t_end", "save_dt", "members", "seed")
# How each member integrates; each may be a top-level value or a sweep axis.
_STEP_RTOL = 1e-9  # how close save_dt / dt and t_end / save_dt must be to whole numbers
# What a run file may ask for, refused before anything is allocated:
MAX_RUN_FILE_BYTES = 1_000_000  # a run file is a short text
MAX_NESTING = 32  # levels of arrays, inline tables and dotted keys: deeper, tomllib recurses past Python's limit
# or (dotted keys) takes time that grows with the square of the depth
MAX_STEPS = 10**12  # steps per member (t_end / dt), and saved samples per member (t_end / save_dt)
MAX_SEED = 2**63 - 1  # the seed is stored as a 64-bit integer
MAX_REPEATS = 100  # [measure] repeats: timed kernel calls per chunk
MAX_NOISE = 1e150  # observation noise's stddev: far below it a Gaussian draw (at most ~40 sd) stays finite


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
    noise: dict[str, float] = field(default_factory=dict)  # Gaussian observation noise: variable (a saved one, or
    # an event's times, <event>_time) -> stddev
    rtol: float | None = None  # top-level tolerances of adaptive methods
    atol: float | None = None
    measure: dict[str, object] = field(default_factory=dict)  # [measure]: error, timing, repeats, growth
    blowup_factor: float = DEFAULT_BLOWUP_FACTOR  # a member fails when its state outgrows its start this much
    device: str = "cpu"  # one of DEVICES
    precision: str = "float64"  # one of PRECISIONS
    draws: str = "each member"  # one of DRAWS: "same at every point" gives replica r the same draws at every point
    events: tuple = ()  # results.Event of the [events] tables (ensemble.events)
    # a user's scene: the identity of its sources when the run file was read (model refuses any other)
    sources: str | None = field(default=None, compare=False)
    # members per block of this process's CPU kernels for a run of few long members (runner.few_members_block
    # sets it where the kernels run); None: block_size's rule
    kernel_block: int | None = field(default=None, compare=False)

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


def _whole_ratio(key: str, num: float, den: float, what: str) -> None:
    ratio = num / den
    if not ratio <= MAX_STEPS:
        raise SpecError(key, f"{key} / {what} = {num!r} / {den!r} = {ratio:.3g}: more than the {MAX_STEPS:.0e} a run "
                             f"may ask for")
    if round(ratio) < 1 or abs(ratio - round(ratio)) > _STEP_RTOL * ratio:
        raise SpecError(key, f"must be a whole multiple of {what} ({num!r} / {den!r} = {ratio:.12g})")


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
            raise unknown(key, key, TOP_LEVEL)
    for key in REQUIRED:
        if key not in raw:
            raise SpecError(key, "missing (required)")
    values = {key: expect(key, raw[key], kind) for key, kind in TOP_LEVEL.items() if key in raw}
    for name in SETTINGS:
        if name in values.get("parameters", {}):
            raise SpecError(f"parameters.{name}", "is a run setting: give it at the top of the run file (or sweep "
                                                  "it under [sweep]), not under [parameters]")
    return values


def _grids(sweep) -> tuple[list[dict], list[str]]:
    """The sweep grids and where each is written: [sweep] is one grid, [[sweep]] tables a union of grids."""
    if isinstance(sweep, list):
        grids = [expect(f"sweep[{g}]", grid, dict) for g, grid in enumerate(sweep)]
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

    t_end = positive("t_end", values["t_end"])
    save_dt = positive("save_dt", values["save_dt"])
    grids, labels = _grids(values.get("sweep", {}))
    settings = {key: values[key] for key in SETTINGS if key in values}
    setting_axes = [_settings(settings, {k: v for k, v in grid.items() if k in SETTINGS}, label, module, save_dt)
                    for grid, label in zip(grids, labels)] or [_settings(settings, {}, "sweep", module, save_dt)]
    _whole_ratio("t_end", t_end, save_dt, "save_dt")
    if values["members"] < 1:
        raise SpecError("members", f"must be >= 1, got {values['members']}")
    _check_bounds(values["seed"], t_end, [axes.get("dt", (settings["dt"],) if "dt" in settings else ())
                                          for axes in setting_axes])

    save = _save(tuple(values.get("save", module.OBSERVABLES)), module, bool(values.get("events")))

    blowup_factor = values.get("blowup_factor", DEFAULT_BLOWUP_FACTOR)
    if not blowup_factor > 1:
        raise SpecError("blowup_factor", f"must be > 1 (a member fails when its state grows this many times its "
                                         f"size at the start), got {blowup_factor!r}")
    device, precision = _device(values.get("device", "cpu"), values.get("precision", "float64"))
    draws = _one_of("draws", values.get("draws", DRAWS[0]), DRAWS)
    measure = _measure(values.get("measure", {}), module)

    parameters, grids, constants, declared = _parameters(
        _from_files(values.get("parameters", {}), Path(path).parent if path != "<string>" else Path.cwd()),
        [{k: v for k, v in grid.items() if k not in SETTINGS} for grid in grids], labels, module)
    for grid, axes in zip(grids, setting_axes):
        grid.update(axes)
    events = _events(values.get("events", {}), module, constants, declared)
    noise = _noise(values.get("observe", {}), save, module, events)

    spec = Spec(path=str(path), text=text, scene=scene, method=settings.get("method"), dt=settings.get("dt"),
                t_end=t_end, save_dt=save_dt, members=values["members"], seed=values["seed"], save=save,
                parameters=parameters, grids=tuple(grids), constants=constants, noise=noise,
                declared=declared, rtol=settings.get("rtol"), atol=settings.get("atol"), measure=measure,
                blowup_factor=blowup_factor, device=device, precision=precision, draws=draws, events=events,
                sources=identity(module.module) if hasattr(module, "module") else None)
    check_before_start(spec)
    return spec


def _save(save: tuple, module, events: bool) -> tuple[str, ...]:
    """The variables a run saves, checked: each the scene's, none twice, at least one unless the run has
    events (which it then keeps alone)."""
    for i, name in enumerate(save):
        if name not in module.OBSERVABLES:
            raise SpecError(f"save[{i}]", f"unknown variable {name!r}; {module.NAME} saves: "
                                          f"{', '.join(module.OBSERVABLES)}")
        if name in save[:i]:
            raise SpecError(f"save[{i}]", f"names {name!r} a second time")
    if not save and not events:
        raise SpecError("save", "must name at least one variable (or the run must have [events])")
    return save


def _events(table: dict, module, constants: dict, declared: dict) -> tuple:
    """The [events] tables (ensemble.events.parse)."""
    if not table:
        return ()
    taken = set(RESERVED) | set(declared) | set(module.OBSERVABLES) | set(module.sizes(constants))
    return parse_events(table, module, constants, taken)


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
        where = folder / expect(f"parameters.{name}.file", value["file"], str)
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
            raise unknown(f"parameters.{name}", name, module.PARAMETERS)
        parameters[name] = parameter_value(keys[name], value, declared[name])
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
    shape, dimensions = shape_table(f"parameters.{name}", given.pop(name))
    constants[f"{name}_shape"] = shape
    if shape == POLYGON:
        if "vertices" not in dimensions:
            raise SpecError(f"parameters.{name}.vertices", "missing (a polygon needs its vertices)")
        constants[f"{name}_vertices"] = vertices_text(f"parameters.{name}.vertices", dimensions.pop("vertices"))
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
        raise unknown(f"parameters.{name}.{dim}", dim, ("shape", *lengths))
    for grid, label in zip(grids, labels):
        swept = expect(f"{label}.{name}", grid.pop(name, {}), dict)
        for dim, axis in swept.items():
            if dim not in lengths:
                raise unknown(f"{label}.{name}.{dim}", dim, lengths)
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
                raise unknown(key, name, (*module.PARAMETERS, *SETTINGS))
            if declared[name].constant:
                raise SpecError(key, "is a run constant and cannot be swept; use one run file per value")
            if name in parameters:
                raise SpecError(key, "is both a parameter and a sweep axis; give it in one place only")
            checked[name] = axis_values(key, axis, float)
        if axes and set(checked) != set(axes[0]):
            raise SpecError(label, f"sweeps parameters {sorted(checked)}, but {labels[0]} sweeps {sorted(axes[0])}: "
                                   f"every grid must sweep the same parameters (methods and steps may differ)")
        axes.append(checked)
    return axes


def _settings(top: dict, axes: dict, label: str, module, save_dt: float) -> dict[str, tuple]:
    """Check how one grid's members integrate: its method, dt, rtol and atol axes against the top-level values.

    Returns the grid's setting axes (the swept ones).
    """
    out = {}
    for key, axis in axes.items():
        if key in top:
            raise SpecError(f"{label}.{key}", "is both a top-level value and a sweep axis; give it in one place only")
        out[key] = axis_values(f"{label}.{key}", axis, str if key == "method" else float)
    where = {key: f"{label}.{key}" if key in out else key for key in SETTINGS}
    if "method" not in top and "method" not in out:
        raise SpecError("method", "missing (required)")
    tolerances = [key for key in ("rtol", "atol") if key in top or key in out]
    for key in tolerances:
        for value in out.get(key, (top.get(key),)):
            if not value > 0 or not math.isfinite(value):
                raise SpecError(where[key], f"must be > 0 and finite, got {value!r}")
    for value in out.get("dt", (top["dt"],) if "dt" in top else ()):
        positive(where["dt"], value)
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
            raise unknown(f"measure.{key}", key, MEASURE_KEYS)
        out[key] = expect(f"measure.{key}", value, MEASURE_KEYS[key])
    if not 1 <= out["repeats"] <= MAX_REPEATS:
        raise SpecError("measure.repeats", f"must be in 1..{MAX_REPEATS} (timed kernel calls per chunk), got "
                                           f"{out['repeats']}")
    if out["error"] and getattr(module, "exact", None) is None:
        raise SpecError("measure.error", f"scene {module.NAME!r} has no exact solution to measure errors against")
    return out


def _derived(name: str, module, constants: dict) -> bool:
    """`name` is computed from a shape parameter that the run file gives."""
    return any(name in p.derives and f"{source}_shape" in constants for source, p in module.PARAMETERS.items())


def _noise(observe: dict, save: tuple[str, ...], module, events: tuple) -> dict[str, float]:
    """The [observe] table: noise = { variable = standard deviation (the variable's units) }, a variable being a
    saved one or an event's times (<event>_time, s)."""
    for key in observe:
        if key not in OBSERVE_KEYS:
            raise unknown(f"observe.{key}", key, OBSERVE_KEYS)
    noise = expect("observe.noise", observe.get("noise", {}), dict)
    times = [f"{e.name}_time" for e in events]
    out = {}
    for name, sigma in noise.items():
        key = f"observe.noise.{name}"
        if name not in (*module.OBSERVABLES, *times):
            raise unknown(key, name, (*module.OBSERVABLES, *times))
        if name in times:
            out[name] = _stddev(key, sigma)
            continue
        if name not in save:
            raise SpecError(key, f"{name!r} is not saved; add it to save")
        out[name] = _stddev(key, sigma)
    return out


def _stddev(key: str, sigma) -> float:
    sigma = expect(key, sigma, float)
    if not 0 <= sigma <= MAX_NOISE:
        raise SpecError(key, f"must be a standard deviation in 0..{MAX_NOISE:g} (a larger one turns values into "
                             f"inf), got {sigma}")
    return sigma


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


