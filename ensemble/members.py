"""The members table: each member's parameter values, drawn from the run's seed and its index alone (ensemble.spec's
docstring says how), or given member by member. `spec` is an ensemble.spec.Spec throughout (this module is below
it: spec checks its members here).

No process holds every member's values: a range's are built where it is integrated, in time and memory
proportional to its length, and checked there (members_table). Reading a run file checks the members
before_start() names, so that a bad sweep value or distribution is refused before anything runs."""
from __future__ import annotations

import hashlib
import itertools
import math
from dataclasses import replace

import numpy as np

from .inertia import SHAPES, polygon
from .methods import METHODS
from .parameter import Mode, ParameterError
from .runfile import DEFAULT_TOLERANCES, POLYGON, SETTINGS, Distribution, PerMember, SpecError, parameter_value
from .scenes import SceneError

CHECKED_BEFORE_START = 2**16  # members a run file's reading checks (all of a smaller run): about 10 ms
SAMPLED_POINTS = 1024  # sweep points whose first members are checked then, at most (spread over the grid)
MAX_EIGENPROBLEM_BYTES = 2**31  # a range's mode starts, solved at once
EIGENPROBLEM_ARRAYS = 3  # n x n arrays per member while mode starts are solved: stiffness, shapes, LAPACK's work


def with_values(spec, values: dict):
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
        parameters[name] = parameter_value(f"values.{name}", PerMember(array, "ensemble.run(values=...)"), known)
        declared[name] = known
    spec = replace(spec, parameters=parameters, declared=declared)
    check_before_start(spec)
    return spec


def given_values(spec) -> str:
    """Where the parameters given member by member came from ("" if none): "name: source; ..."."""
    return "; ".join(f"{name}: {value.source}" for name, value in spec.parameters.items()
                     if isinstance(value, PerMember))


def members_table(spec, start: int = 0, stop: int | None = None) -> dict[str, np.ndarray]:
    """The parameter values of members start .. stop - 1 (default: every member), each an array over those
    members, built in time proportional to the range's length and checked (SpecError naming the range when a
    member breaks the scene's constraints: one the checks before the start did not reach).

    Members are ordered sweep point major, replica minor; the table also holds
    `sweep_point`, the index of each member's point on the sweep grids, and how
    each member integrates: `method` (names), `dt`, `rtol`, `atol` (NaN where
    the method takes none).
    """
    stop = spec.n_members if stop is None else stop
    try:
        return build_table(spec, start, stop)
    except SpecError as e:
        raise SpecError(e.key, f"{e.problem} (among members {start} to {stop - 1}, met as they were integrated: "
                               f"the members checked before the start passed)") from None


def before_start(spec) -> list[tuple[int, int]]:
    """The member ranges a run file's reading checks: every member of a run of at most CHECKED_BEFORE_START, else
    the first members of each sweep point (of SAMPLED_POINTS points spread over the grid, the last included),
    CHECKED_BEFORE_START in all, at least one each."""
    n, per_point = spec.n_members, spec.members
    if n <= CHECKED_BEFORE_START:
        return [(0, n)]
    points = spec.sweep_points
    sampled = sorted({*range(0, points, -(-points // SAMPLED_POINTS)), points - 1})
    each = max(1, min(per_point, CHECKED_BEFORE_START // len(sampled)))
    return [(p * per_point, p * per_point + each) for p in sampled]


def check_before_start(spec) -> None:
    """Build and check the members of before_start(spec) (SpecError for the first bad one); keep none."""
    points = grid_points(spec)
    for start, stop in before_start(spec):
        build_table(spec, start, stop, points)


def members_sha256(spec) -> str:
    """The SHA-256 of the values given member by member and of the members checked before the start: what, with
    the run file's text and the versions, makes every member's values (ensemble.parts.fingerprint)."""
    digest = hashlib.sha256()
    for name, value in sorted(spec.parameters.items()):
        if isinstance(value, PerMember):
            given = np.ascontiguousarray(value.values, dtype=float)
            digest.update(f"{name} given {given.shape}".encode() + given.tobytes())
    points = grid_points(spec)
    for start, stop in before_start(spec):
        table = build_table(spec, start, stop, points)
        for name in sorted(table):
            values = np.ascontiguousarray(table[name])
            digest.update(f"{name} {start} {values.dtype.str} {values.shape}".encode() + values.tobytes())
    return digest.hexdigest()


def grid_points(spec) -> list[dict]:
    """Every sweep point's values (axis: value), in member order ([{}] for a run without a sweep)."""
    return [dict(zip(grid, combination)) for grid in spec.grids
            for combination in itertools.product(*grid.values())] or [{}]


def point_settings(spec, points: list[dict]) -> list[dict]:
    """How the members of each of `points` integrate: method, dt, rtol and atol (None where the method takes
    none; an adaptive method's default tolerances where the run gives none)."""
    top_level = {"method": spec.method, "dt": spec.dt, "rtol": spec.rtol, "atol": spec.atol}
    settings = [{key: p.get(key, top_level[key]) for key in SETTINGS} for p in points]
    for s in settings:
        if METHODS[s["method"]].adaptive:
            s.update({key: value for key, value in DEFAULT_TOLERANCES.items() if s[key] is None})
    return settings


def build_table(spec, start: int, stop: int, points: list[dict] | None = None) -> dict[str, np.ndarray]:
    """members_table's, unchecked by range; `points`: grid_points(spec), when the caller has them."""
    n = stop - start
    points = grid_points(spec) if points is None else points
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
        if need > MAX_EIGENPROBLEM_BYTES:
            raise SpecError(f"parameters.{name}", f"a mode start solves each member's {sizes['site']} x "
                                                  f"{sizes['site']} eigenproblem at once: {n} member(s) need "
                                                  f"{need / 1e9:.3g} GB; at most {MAX_EIGENPROBLEM_BYTES / 1e9:.3g} GB")
        table[name] = scene.mode_start(mode, table["m"], table["k"], spec.constants["boundary"])
    return table


def _member_settings(spec, points: list[dict], point: np.ndarray) -> dict[str, np.ndarray]:
    """Each member's method, dt, rtol and atol (NaN where its method takes none), from its sweep point."""
    settings = point_settings(spec, points)
    out = {"method": np.array([s["method"] for s in settings])[point]}
    for key in ("dt", "rtol", "atol"):
        out[key] = np.array([np.nan if s[key] is None else s[key] for s in settings], dtype=float)[point]
    return out


def _values(spec, name: str, value, start: int, n: int, sizes: dict[str, int]) -> np.ndarray:
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


def _from_shape(spec, source: str, table: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
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
