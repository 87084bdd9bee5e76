"""A scene from a user's own file or module, written to the short contract, and the checks that tell its author
what is wrong in one line.

A scene file (see docs/scenes.md and examples/driven_oscillator.py) needs:

- STATE: name -> (units, long_name) of each state variable, in order;
- PARAMETERS: name -> ensemble.Parameter; `<state>0` gives a state variable's value at t = 0, every other
  parameter is passed to the right-hand side, in this order;
- rhs(t, *state, *parameters): the time derivative of one member's state, a tuple of len(STATE) numbers.

Optional:

- NAME (default: the file's stem);
- PIECES, and for each piece `<piece>(tau, *state, *parameters)`: its exact flow for time tau, for splitting
  methods (methods.KICK_DRIFT, say); EVALUATING_PIECES: those that evaluate the forces;
- exact(t, *state0, *parameters): the closed form with numpy broadcasting (t is a column (times, 1), every
  other argument a row (1, members); for events, t is (times, members), each member's own times), a tuple of
  len(STATE) arrays; it gives the `exact` method and [measure] error;
- EVENTS, and for each name `event_<name>(t, *state, *parameters)`: a value whose crossings a run file's
  [events] can watch (`of = "<name>"`) where no state variable says it;
- check(values): raise ensemble.ParameterError(name, problem) for a value no member can have;
- fit(ds): the scene's fit of a result, an xarray.Dataset (its theory against what was measured);
- charts(plt, ds, fits, rows, stem, members): the scene's own charts of that fit for `ensemble fit --charts`,
  a list of the PNG files written (STEM_<name>.png).

Its functions are compiled with Numba (nopython mode), so they use math and numpy, and any helper they call
is itself decorated with numba.njit.
"""
from __future__ import annotations

import ast
import hashlib
import importlib
import importlib.util
import inspect
import json
import re
import sys
import sysconfig
from pathlib import Path
from types import ModuleType

import numpy as np

from ..errors import EXIT_FAILED, EnsembleError
from ..parameter import Parameter
from . import chain
from .closed_form import times_by_members

#: Names a result already uses: a scene's state and parameters must not take them.
RESERVED = ("t", "member", "method", "dt", "rtol", "atol", "steps_accepted", "steps_rejected", "rhs_evals",
            "error_max", "error_final", "seconds_per_step", "status", "failure_time", "growth_per_step", "sweep_point",
            "run", "run_index", "member_in_run", "sweep_point_in_run", "run_path")  # the last: ensemble.open's


class SceneError(EnsembleError, ValueError):
    """A scene that does not keep the contract; the message is one line that says what is wrong and where."""


class SceneChanged(SceneError):
    """A user's scene edited while its run was under way: the run stops, its finished chunks kept (exit 3)."""

    exit_status = EXIT_FAILED


def module_from_file(path: Path) -> ModuleType:
    """Import a Python file under a module name made from its resolved path, again whenever its text or that of a
    module of the user's it imports (`sources`) has changed since: an edited scene is never run with its old
    physics."""
    path = Path(path).resolve()
    name = f"ensemble_scene_{path.stem}_{hashlib.sha256(str(path).encode()).hexdigest()[:12]}"
    current = sys.modules.get(name)
    if current is not None and not stale(current):
        return current
    if current is not None:
        _reload_users_modules(current)
    text = path.read_bytes()  # read once: the module runs the very text its hash is taken of
    module = importlib.util.module_from_spec(importlib.util.spec_from_file_location(name, path))
    sys.modules[name] = module
    try:
        exec(compile(text, str(path), "exec"), module.__dict__)
    except BaseException:
        del sys.modules[name]
        raise
    module.__ensemble_sources__ = {str(path): hashlib.sha256(text).hexdigest(), **_users_modules(module)}
    return module


def sources(module: ModuleType) -> dict[str, str]:
    """SHA-256 of each file whose code a scene's module runs, by path: its own, and every module of the user's
    (outside the standard library, site-packages and ensemble) it imports, directly or through another, as they
    were when it was imported."""
    found = getattr(module, "__ensemble_sources__", None)
    if found is None:  # a module by dotted name: as it is on the disk now (a built-in scene's never changes)
        found = {module.__file__: _file_hash(module.__file__), **_users_modules(module)}
        module.__ensemble_sources__ = found
    return found


def identity(module: ModuleType) -> str:
    """One SHA-256 of the sources a scene's module runs: what its kernels are keyed on."""
    return hashlib.sha256(json.dumps(sources(module), sort_keys=True).encode()).hexdigest()


def stale(module: ModuleType) -> bool:
    """Whether a file a scene's module runs has changed (or gone) since it was imported."""
    return any(_file_hash(path) != digest for path, digest in sources(module).items())


def _file_hash(path: str) -> str | None:
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return None


_NOT_USERS = tuple({sysconfig.get_path(key) for key in ("stdlib", "platstdlib", "purelib", "platlib")}
                   | {str(Path(__file__).resolve().parents[1])})  # ...and ensemble's own package


def _users_modules(module: ModuleType, seen: dict[str, str] | None = None) -> dict[str, str]:
    """{path: SHA-256} of the user's modules that `module` imports or refers to (a module, or a function or class
    of one, in its namespace), and of theirs in turn."""
    seen = {} if seen is None else seen
    for value in [*_imported(module), *vars(module).values()]:
        owner = getattr(python_function(value), "__module__", None)
        used = value if isinstance(value, ModuleType) else sys.modules.get(owner if isinstance(owner, str) else "")
        path = getattr(used, "__file__", None)
        if used is None or used is module or not path or not path.endswith(".py"):
            continue
        path = str(Path(path).resolve())
        if path in seen or path.startswith(_NOT_USERS):
            continue
        seen[path] = _file_hash(path)
        _users_modules(used, seen)
    return seen


def _imported(module: ModuleType) -> list[ModuleType]:
    """The modules that `module`'s text imports (`import a.b`, `from a import b`: a constant imported so leaves no
    trace in its namespace), as they are imported now."""
    try:
        tree = ast.parse(Path(module.__file__).read_bytes())
    except (OSError, SyntaxError, ValueError, TypeError):
        return []
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            try:
                base = importlib.util.resolve_name("." * node.level + (node.module or ""), module.__package__)
            except (ImportError, ValueError):
                continue
            names += [base, *(f"{base}.{alias.name}" for alias in node.names)]
    return [sys.modules[name] for name in dict.fromkeys(names) if name in sys.modules]


def _reload_users_modules(module: ModuleType) -> None:
    """Import again the user's modules a scene's module uses whose files changed, the most deeply used first."""
    by_file = {str(Path(m.__file__).resolve()): m for m in list(sys.modules.values())
               if isinstance(getattr(m, "__file__", None), str)}
    own = next(iter(sources(module)))
    for path, digest in reversed(list(sources(module).items())):
        if path != own and path in by_file and _file_hash(path) != digest:
            importlib.reload(by_file[path])


def load(where: str) -> ModuleType:
    """A scene's module: a file by path (ending in .py) or a module by dotted name, imported again when a file it
    runs has changed; SceneError when it does not import."""
    try:
        if where.endswith(".py"):
            if not Path(where).is_file():
                raise SceneError(f"{where}: no such file")
            return module_from_file(Path(where))
        module = importlib.import_module(where)
        if stale(module):
            _reload_users_modules(module)
            module = importlib.reload(module)
            del module.__ensemble_sources__
        return module
    except SceneError:
        raise
    except SystemExit as error:  # sys.exit or argparse at import: not ensemble's own exit
        raise SceneError(f"{where} does not import: it called sys.exit({error.code!r}) (a scene file must not "
                         f"run a program when imported)") from None
    except Exception as error:  # noqa: BLE001 (any error in the user's file is reported in one line)
        line = _line_of(error, where)
        raise SceneError(f"{where} does not import{line}: {type(error).__name__}: {error}") from None


def _line_of(error: BaseException, where: str) -> str:
    if isinstance(error, SyntaxError) and error.lineno:
        return f" (line {error.lineno})"
    frames = [f for f in inspect.getinnerframes(error.__traceback__) if f.filename.endswith(Path(where).name)]
    return f" (line {frames[-1].lineno})" if frames else ""


def python_function(f):
    """The Python function behind a scene's function, compiled (@njit) or not, to call it without compiling."""
    return getattr(f, "py_func", f)


def _parameters_of(function) -> list[str]:
    return list(inspect.signature(python_function(function)).parameters)


class UserScene:
    """A scene written to the short contract, with everything else the engine and the store ask of a scene."""

    STABILITY_AXES: tuple[str, ...] = ()

    def __init__(self, module: ModuleType, where: str):
        self.module, self.PHYSICS, self.SITES = module, where, False
        self.NAME = scene_name(module, where)
        for required in ("STATE", "PARAMETERS", "rhs"):
            if not hasattr(module, required):
                raise SceneError(f"{where} has no {required} ({_REQUIRED[required]})")
        self.STATE = dict(module.STATE)
        self.PARAMETERS = dict(module.PARAMETERS)
        self.PIECES = tuple(getattr(module, "PIECES", ()))
        self.EVALUATING_PIECES = tuple(getattr(module, "EVALUATING_PIECES", ()))
        self.starts = [f"{name}0" for name in self.STATE]
        self.rates = [name for name in self.PARAMETERS if name not in self.starts]
        self.OBSERVABLES = {name: (("member", "t"), units, long_name)
                            for name, (units, long_name) in self.STATE.items()}
        self.EVENTS = tuple(getattr(module, "EVENTS", ()))
        self.EVENT_VALUES = {name: ("state", k) for k, name in enumerate(self.STATE)}  # ensemble.events
        self.EVENT_VALUES.update({name: ("function", f"event_{name}") for name in self.EVENTS
                                  if isinstance(name, str)})
        if hasattr(module, "exact"):
            self.exact = self._exact
        if hasattr(module, "fit"):
            self.fit = module.fit
        if hasattr(module, "charts"):
            self.charts = module.charts
        if all(hasattr(module, name) for name in STABILITY):  # `ensemble stability` reads a result against them
            self.STABILITY_AXES = tuple(module.STABILITY_AXES)
            self.stability_axis, self.step_growth, self.axis_growth = (
                module.stability_axis, module.step_growth, module.axis_growth)
        _check(self)

    def sizes(self, constants: dict) -> dict[str, int]:
        return {}

    def coordinates(self, constants: dict) -> dict:
        return {}

    def check_constants(self, constants: dict) -> None:
        pass

    def check(self, values: dict[str, np.ndarray]) -> None:
        if not hasattr(self.module, "check"):
            return
        try:
            self.module.check(values)
        except EnsembleError:
            raise
        except Exception as e:  # noqa: BLE001 (the user's code: one line that says whose it is)
            raise SceneError(f"{self.PHYSICS}: check(values) raised {type(e).__name__}: {e} (a value no member "
                             f"can have raises ensemble.ParameterError(name, problem))") from None

    def derive(self, values: dict, constants: dict) -> dict:
        return {}

    def kernel_rows(self, constants: dict) -> tuple[int, int]:
        return len(self.STATE), len(self.rates)

    def inputs(self, values: dict[str, np.ndarray], constants: dict) -> tuple[np.ndarray, np.ndarray]:
        """The state at t = 0 (len(STATE), members) and the rhs's parameters (len(rates), members)."""
        members = len(next(iter(values.values())))
        state0 = np.stack([np.broadcast_to(np.asarray(values[name], dtype=float), (members,)) for name in self.starts])
        rates = [np.broadcast_to(np.asarray(values[name], dtype=float), (members,)) for name in self.rates]
        return state0, np.stack(rates) if rates else np.zeros((0, members))

    def _exact(self, values: dict[str, np.ndarray], constants: dict, t: np.ndarray) -> np.ndarray:
        """The module's closed form at times t (s; (times,), or (times, members) for each member's own): (times,
        len(STATE), members)."""
        state0, rates = self.inputs(values, constants)
        t = times_by_members(t)
        columns = self.module.exact(t, *(row[None, :] for row in state0), *(row[None, :] for row in rates))
        return np.stack([np.broadcast_to(c, (t.shape[0], state0.shape[1])) for c in columns], axis=1)

    def observe(self, samples: np.ndarray, names, values: dict, constants: dict) -> dict[str, np.ndarray]:
        """Each saved state variable, (members, t), from samples (t, state, members)."""
        return {name: np.ascontiguousarray(samples[:, c, :].T) for c, name in enumerate(self.STATE) if name in names}

    def amplitudes(self, samples: np.ndarray, values: dict, constants: dict) -> np.ndarray:
        """The state's Euclidean norm, (members, 1, t): the motion whose growth [measure] growth fits (a single
        variable of an oscillation passes through zero every half period, the norm does not)."""
        return np.sqrt(np.sum(samples.transpose(2, 1, 0) ** 2, axis=1, keepdims=True))

    def conserved_energy(self, ds) -> np.ndarray:
        """No conserved energy is declared: NaN (member, t)."""
        return np.full((ds.sizes["member"], ds.sizes["t"]), np.nan)


class UserSitesScene:
    """A user's field of sites: a file or module that sets SITES = True and gives one compiled-to-be function,
    acceleration(x_left, x, x_right, c_left, c_right) (m s-2) of a site at x between its neighbours, c_left and
    c_right its couplings to each (a spring's k over the site's m, 1/s^2): the built-in chain's masses, springs,
    boundaries, parameters, starts and saved x and v, with the user's forces (a Fermi-Pasta-Ulam chain's
    nonlinear springs, say). Every sites family runs it (ensemble.engine.sites_kernels, gpu_sites_kernels). The
    chain's harmonic energy, closed form, stability theory and mode fits hold for its linear springs alone, and
    are left out."""

    SITES = True
    STABILITY_AXES: tuple[str, ...] = ()
    PIECES, EVALUATING_PIECES = chain.PIECES, chain.EVALUATING_PIECES
    PARAMETERS = chain.PARAMETERS
    OBSERVABLES = {name: about for name, about in chain.OBSERVABLES.items() if name != "energy"}
    EVENT_VALUES = chain.EVENT_VALUES  # its sites' x and v (ensemble.engine.sites_events)

    def __init__(self, module: ModuleType, where: str):
        self.module, self.PHYSICS = module, where
        self.NAME = scene_name(module, where)
        if not hasattr(module, "acceleration"):
            raise SceneError(f"{where} sets SITES = True but has no acceleration(x_left, x, x_right, c_left, "
                             f"c_right), the acceleration of a site between its neighbours")
        _signature(where, module.acceleration, "acceleration", list(SITE_ARGUMENTS))
        _compiled_helpers(where, module, "acceleration")
        if len(_returns(where, module.acceleration, "acceleration", [0.1, 0.2, 0.4, 1.0, 1.0])) != 1:
            raise SceneError(f"{where}: acceleration must return one number, the site's acceleration")
        for name in ("sizes", "coordinates", "check_constants", "check", "derive", "inputs", "kernel_rows",
                     "observe", "amplitudes", "mode_start"):  # mode_start: a start in a normal mode of the linear chain
            setattr(self, name, getattr(chain, name))

    conserved_energy = UserScene.conserved_energy  # none declared: NaN


SITE_ARGUMENTS = ("x_left", "x", "x_right", "c_left", "c_right")

#: What a scene declares for `ensemble stability` (all or none): the names of its dimensionless steps, each
#: member's axis and place on it, the growth per step linear theory predicts for a member, and along an axis.
STABILITY = ("STABILITY_AXES", "stability_axis", "step_growth", "axis_growth")

_REQUIRED = {"STATE": "name -> (units, long_name) of each state variable",
             "PARAMETERS": "name -> ensemble.Parameter, with <state>0 for each state variable's start",
             "rhs": "its right-hand side, rhs(t, *state, *parameters)"}


def scene_name(module: ModuleType, where: str) -> str:
    """A user's scene's NAME (default: its file's or module's name), which names files: SceneError otherwise."""
    name = getattr(module, "NAME", Path(where).stem if where.endswith(".py") else where.rsplit(".", 1)[-1])
    if not (isinstance(name, str) and re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_.-]*", name)):
        raise SceneError(f"{where}: NAME must be letters, digits, _, . and - (it names files), not {name!r}")
    return name


def _check_names(scene: UserScene) -> None:
    """The scene's name, its state variables' and its parameters': names of files and of variables in results."""
    where = scene.PHYSICS
    if not scene.STATE:
        raise SceneError(f"{where}: STATE is empty")
    for name in (*scene.STATE, *scene.PARAMETERS):
        if not (isinstance(name, str) and name.isidentifier() and name.isascii()):
            raise SceneError(f"{where}: {name!r} is not a name for a state variable or a parameter (letters, digits "
                             f"and _, not starting with a digit)")
        if name in RESERVED:
            raise SceneError(f"{where}: {name!r} is a name every result already uses ({', '.join(RESERVED)})")
    for name, value in scene.PARAMETERS.items():
        if not isinstance(value, Parameter):
            raise SceneError(f"{where}: PARAMETERS[{name!r}] is not an ensemble.Parameter")


def _compiled_helpers(where: str, module: ModuleType, name: str) -> None:
    """The functions of the scene's file that `name` calls (and that those call) are compiled with numba.njit: a
    plain Python function inside a kernel fails to compile with a NameError that names no cause."""
    seen, todo = set(), [getattr(module, name)]
    while todo:
        function = todo.pop()
        code = getattr(function, "py_func", function).__code__
        for called in code.co_names:
            helper = module.__dict__.get(called)
            if called in seen or helper is None:
                continue
            seen.add(called)
            if inspect.isfunction(helper):
                raise SceneError(f"{where}: {name} calls {called}, a plain Python function: decorate it with "
                                 f"@numba.njit (the kernels are compiled, and call only compiled functions)")
            if hasattr(helper, "py_func"):
                todo.append(helper)


def _check(scene: UserScene) -> None:
    """The contract's rules, each failure one line naming the scene's file and what is wrong."""
    where, module = scene.PHYSICS, scene.module
    _check_names(scene)
    missing = [name for name in scene.starts if name not in scene.PARAMETERS]
    if missing:
        raise SceneError(f"{where}: PARAMETERS has no {missing[0]!r} (the value of {missing[0][:-1]!r} at t = 0)")
    clash = [name for name in scene.STATE if name in scene.PARAMETERS]
    if clash:
        raise SceneError(f"{where}: {clash[0]!r} is both a state variable and a parameter")
    arguments = ["t", *scene.STATE, *scene.rates]
    _signature(where, module.rhs, "rhs", arguments)
    _compiled_helpers(where, module, "rhs")
    _returns(where, module.rhs, "rhs", [0.0] + [1.0] * (len(arguments) - 1), len(scene.STATE))
    for piece in scene.PIECES:
        if not hasattr(module, piece):
            raise SceneError(f"{where}: PIECES names {piece!r}, but the file has no function {piece}")
        factors = []
        if hasattr(module, f"{piece}_factors"):
            function, name = getattr(module, f"{piece}_factors"), f"{piece}_factors"
            _signature(where, function, name, ["tau", *scene.rates])
            factors = [f"f{i}" for i in range(len(_returns(where, function, name, [0.5] + [1.0] * len(scene.rates))))]
        _signature(where, getattr(module, piece), piece, ["tau", *scene.STATE, *scene.rates, *factors])
        _compiled_helpers(where, module, piece)
        _returns(where, getattr(module, piece), piece, [0.5] + [1.0] * (len(arguments) - 1 + len(factors)),
                 len(scene.STATE))
    _check_events(scene, arguments)
    if hasattr(module, "exact"):
        _signature(where, module.exact, "exact", ["t", *scene.starts, *scene.rates])
        _exact_returns(where, module.exact, len(scene.STATE), len(scene.starts) + len(scene.rates))
    declared = [name for name in STABILITY if hasattr(module, name)]
    if declared and len(declared) < len(STABILITY):
        missing = [name for name in STABILITY if name not in declared]
        raise SceneError(f"{where}: it declares {', '.join(declared)} for stability maps, but not "
                         f"{', '.join(missing)}")


def _check_events(scene: UserScene, arguments: list[str]) -> None:
    """EVENTS: names, each with its event_<name>(t, *state, *parameters) returning one number."""
    where, module = scene.PHYSICS, scene.module
    for name in scene.EVENTS:
        if not (isinstance(name, str) and name.isidentifier() and name.isascii()):
            raise SceneError(f"{where}: EVENTS holds {name!r}, not a name (letters, digits and _)")
        if name in scene.STATE:
            raise SceneError(f"{where}: EVENTS names {name!r}, a state variable, which events watch already")
        function = getattr(module, f"event_{name}", None)
        if function is None:
            raise SceneError(f"{where}: EVENTS names {name!r}, but the file has no function event_{name}")
        _signature(where, function, f"event_{name}", arguments)
        _compiled_helpers(where, module, f"event_{name}")
        value = _returns(where, function, f"event_{name}", [0.0] + [1.0] * (len(arguments) - 1))
        if len(value) != 1:
            raise SceneError(f"{where}: event_{name} must return one number, got {len(value)}")


def _exact_returns(where: str, exact, size: int, arguments: int) -> None:
    """exact must return `size` arrays that broadcast to (times, members): tried on 2 times and 3 members."""
    t, row = np.array([[0.0], [0.5]]), np.ones((1, 3))
    try:
        with np.errstate(all="ignore"):
            columns = exact(t, *([row] * arguments))
    except Exception as error:  # noqa: BLE001 (reported in one line)
        raise SceneError(f"{where}: exact(t, ...) on 2 times and 3 members raised {type(error).__name__}: "
                         f"{error}") from None
    count = len(columns) if isinstance(columns, (tuple, list)) else "not a tuple"
    if count != size:
        raise SceneError(f"{where}: exact must return a tuple of {size} arrays (one per state variable), got "
                         f"{count}")
    for c, column in enumerate(columns):
        try:
            np.broadcast_to(np.asarray(column, dtype=float), (2, 3))
        except (ValueError, TypeError):
            raise SceneError(f"{where}: exact's value {c} does not broadcast to (times, members) = (2, 3) for t "
                             f"of shape (2, 1) and parameters of shape (1, 3)") from None


def _signature(where: str, function, name: str, arguments: list[str]) -> None:
    if not callable(function):
        raise SceneError(f"{where}: {name} is not a function")
    found = _parameters_of(function)
    if len(found) != len(arguments):
        raise SceneError(f"{where}: {name} takes {len(found)} argument(s), ({', '.join(found)}); ensemble calls it "
                         f"as {name}({', '.join(arguments)})")


def _returns(where: str, function, name: str, arguments: list[float], size: int | None = None) -> tuple:
    """Call `function` in Python on sample values: it must return `size` numbers (any number if None)."""
    try:
        with np.errstate(all="ignore"):
            result = python_function(function)(*arguments)
    except Exception as error:  # noqa: BLE001 (reported in one line)
        raise SceneError(f"{where}: {name}({', '.join(map(str, arguments))}) raised {type(error).__name__}: "
                         f"{error}") from None
    values = result if isinstance(result, (tuple, list)) else (result,)
    numbers = all(isinstance(v, (int, float, np.floating, np.integer)) for v in values)
    if size is not None and (len(values) != size or not numbers):
        raise SceneError(f"{where}: {name} must return a tuple of {size} numbers (one per state variable), got "
                         f"{result!r}")
    if not numbers:
        raise SceneError(f"{where}: {name} must return a tuple of numbers, got {result!r}")
    return tuple(values)
