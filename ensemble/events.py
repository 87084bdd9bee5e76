"""A run's events, from its run file to its result: the [events.<name>] tables checked (`parse`), and the result's
variables they add (`variables`, `records`). The kernels locate them (ensemble.engine.events).

    [events.tip]          # the event's name in the result
    of = "tilt"           # a saved variable of the scene, or one of its EVENTS (a vector takes `index = k`)
    value = 0.6           # the level it crosses (default 0)
    direction = "up"      # "up", "down" or "both" (the default)
    count = 1             # occurrences kept per member (default 1)
    stop = true           # the member stops at its first occurrence (default false)
    keep = ["omega"]      # variables of the scene kept at each kept occurrence (default none)

The result gains tip_time(member, tip) (s; NaN where fewer occurred), tip_count(member) (every occurrence, kept
or not), tip_<variable>(member, tip, ...) for each kept variable (as scipy's solve_ivp's y_events) and, where an
event stops its members, each saved variable's value at the stop, <variable>_at_stop.

A scene says what its events can watch in EVENT_VALUES: name -> ("state", first row) for a state variable (a
vector's components follow; the first row may be the name of a constant that gives it, as a chain's v), or
("function", name of a function in its physics, f(t, *state, *parameters) -> a value or a vector's values[, name
of its watch, watch(t, *state, *parameters, level) -> a value of the sign of f - level that costs less]). A field
of sites' events watch its state alone.
"""
from __future__ import annotations

import re

import numpy as np

from .results import Event
from .runfile import SpecError, expect, unknown

KEYS = {"of": str, "value": float, "direction": str, "count": int, "stop": bool, "index": int, "keep": list}
DIRECTIONS = ("up", "down", "both")
MAX_COUNT = 10_000  # occurrences kept per member: each is 8 bytes a member in the result
NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*\Z")


def parse(table: dict, scene, constants: dict, taken: set[str]) -> tuple[Event, ...]:
    """The run file's [events] table as Events, checked against the scene (its EVENT_VALUES, OBSERVABLES and
    sizes for `constants`); `taken`: the result's other names, which an event's variables must not clash with.
    SpecError names the first bad key."""
    events = []
    expect("events", table, dict)
    for name, entry in table.items():
        key = f"events.{name}"
        entry = expect(key, entry, dict)
        if not NAME.match(name):
            raise SpecError(key, "an event's name must be a letter then letters, digits or _ (it names the "
                                 "result's variables)")
        for inner in entry:
            if inner not in KEYS:
                raise unknown(f"{key}.{inner}", inner, KEYS)
        given = {inner: expect(f"{key}.{inner}", value, KEYS[inner]) for inner, value in entry.items()}
        if "of" not in given:
            raise SpecError(f"{key}.of", "is missing: the variable whose crossing is the event")
        keep = _kept(key, given.get("keep", []), scene)
        own = {f"{name}_time", f"{name}_count", name, *(f"{name}_{variable}" for variable in keep)}
        clash = own & taken
        if clash:
            raise SpecError(key, f"its variable {sorted(clash)[0]!r} would clash with the result's own; rename it")
        direction = given.get("direction", "both")
        if direction not in DIRECTIONS:
            raise SpecError(f"{key}.direction", f"must be one of {', '.join(map(repr, DIRECTIONS))}, got "
                                                f"{direction!r}")
        count = given.get("count", 1)
        if not 1 <= count <= MAX_COUNT:
            raise SpecError(f"{key}.count", f"must be in 1..{MAX_COUNT} (occurrences kept per member), got {count}")
        index, source = _source(key, given["of"], given.get("index"), scene, constants)
        events.append(Event(name, given["of"], index, source, float(given.get("value", 0.0)), direction, count,
                            given.get("stop", False), keep))
        taken = taken | own
    return tuple(events)


def _kept(key: str, keep: list, scene) -> tuple[str, ...]:
    """An event's `keep`: saved variables of the scene, each once."""
    for i, variable in enumerate(keep):
        if not isinstance(variable, str) or variable not in scene.OBSERVABLES:
            raise SpecError(f"{key}.keep[{i}]", f"unknown variable {variable!r}; {scene.NAME} saves: "
                                                f"{', '.join(scene.OBSERVABLES)}")
        if variable in keep[:i]:
            raise SpecError(f"{key}.keep[{i}]", f"names {variable!r} a second time")
    return tuple(keep)


def _source(key: str, of: str, index: int | None, scene, constants: dict) -> tuple[int, tuple]:
    """(index or -1, the kernels' value: ("state", row) or ("function", name, index or -1[, watch])) of `of`."""
    known = getattr(scene, "EVENT_VALUES", {})
    if of not in known:
        saved = [name for name in scene.OBSERVABLES if name not in known]
        why = f"; {', '.join(saved)} cannot be watched yet" if saved else ""
        raise SpecError(f"{key}.of", f"unknown variable {of!r}; {scene.NAME}'s events watch: "
                                     f"{', '.join(known) or 'nothing'}{why}")
    dims = scene.OBSERVABLES[of][0] if of in scene.OBSERVABLES else ("member", "t")
    vector = dims[2:]
    if vector:
        size = scene.sizes(constants)[vector[0]]
        if index is None:
            raise SpecError(f"{key}.index", f"{of!r} is a vector over {vector[0]}: say which value, index = 0.."
                                            f"{size - 1}")
        if not 0 <= index < size:
            raise SpecError(f"{key}.index", f"must be in 0..{size - 1} ({of!r} has {size} values), got {index}")
    elif index is not None:
        raise SpecError(f"{key}.index", f"{of!r} is a single value: leave index out")
    index = -1 if index is None else index
    kind, where, *watch = known[of]
    if kind == "state":
        first = constants[where] if isinstance(where, str) else where
        return index, ("state", first + max(index, 0))
    return index, ("function", where, index, *watch)


def variables(events: tuple[Event, ...], scene, save: tuple[str, ...], noise: dict[str, float]) -> dict[str, tuple]:
    """The result's variables of `events`: name -> (type, dims, units, long_name, comment, attributes). Per event
    <name>_time (member, <name>), which says what it watched (event_of, event_index: -1 for a single value,
    event_value, event_direction, event_stop: 0 or 1) and, where `noise` (spec.noise) gives its times some, its
    observation_noise_stddev; and <name>_count (member,); where an event stops members, each saved variable at
    the stop, <variable>_at_stop (its dims but t)."""
    out = {}
    for e in events:
        what = f"{e.of}[{e.index}]" if e.index >= 0 else e.of
        crossing = {"up": "rises to", "down": "falls to", "both": "crosses"}[e.direction]
        watched = {"event_of": e.of, "event_index": e.index, "event_value": e.level, "event_direction": e.direction,
                   "event_stop": int(e.stop)}
        sigma = noise.get(f"{e.name}_time")
        observed = "" if sigma is None else (", plus Gaussian observation noise of stddev observation_noise_stddev "
                                             "(s), drawn per member from the run's seed")
        out[f"{e.name}_time"] = ("f8", ("member", e.name), "s", f"time of {e.name}",
                                 f"the first {e.count} times at which {what} {crossing} {e.level:g}, located "
                                 f"within each step on the method's own path{observed}; NaN where fewer occurred",
                                 {**watched, **({} if sigma is None else {"observation_noise_stddev": sigma})})
        out[f"{e.name}_count"] = ("i8", ("member",), "1", f"occurrences of {e.name}", "every occurrence, kept in "
                                  f"{e.name}_time or not" + ("; at most 1: the member stops there" if e.stop else ""),
                                  {})
        for name in e.keep:
            dims, units, long_name = scene.OBSERVABLES[name]
            out[f"{e.name}_{name}"] = ("f8", ("member", e.name, *dims[2:]), units, f"{long_name} at {e.name}",
                                       f"at each time of {e.name}_time; NaN where fewer occurred", {})
    if any(e.stop for e in events):
        for name in save:
            dims, units, long_name = scene.OBSERVABLES[name]
            out[f"{name}_at_stop"] = ("f8", tuple(d for d in dims if d != "t"), units, f"{long_name} at stop",
                                      "at the event that stopped the member (status stopped_by_event); NaN for "
                                      "the others", {})
    return out


def dimensions(events: tuple[Event, ...]) -> dict[str, int]:
    """The result's dimensions of `events`: each one's kept occurrences."""
    return {e.name: e.count for e in events}


def records(events: tuple[Event, ...], outcome, scene, save: tuple[str, ...], values: dict,
            constants: dict) -> dict[str, np.ndarray]:
    """The per-member values of `variables` from a launch's Outcome (member first)."""
    out = {}
    for e, times, counts, states in zip(events, outcome.event_times, outcome.event_counts, outcome.event_states):
        out[f"{e.name}_time"] = np.ascontiguousarray(times[:e.count].T)
        out[f"{e.name}_count"] = counts
        if e.keep:
            kept = scene.observe(states[:e.count], e.keep, values, constants)  # (members, count, ...)
            out.update({f"{e.name}_{name}": np.ascontiguousarray(value) for name, value in kept.items()})
    if any(e.stop for e in events) and save:
        at_stop = scene.observe(outcome.stopped[None], save, values, constants)
        out.update({f"{name}_at_stop": np.ascontiguousarray(value[:, 0]) for name, value in at_stop.items()})
    return out
