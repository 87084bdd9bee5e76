"""Events on the closed form (method exact): each member's crossings of its events' levels, searched on a grid of
the run's step (its dt, or save_dt without one) and located on the closed form itself by the Illinois variant of
regula falsi (as ensemble.engine.events.root does on a method's step), to the last bits of the grid step's time.
The events' values are the kernels' own (kernels.event_values), evaluated by a compiled loop over members; the
closed form is the scene's `exact` at each member's own times. A crossing that comes and goes within one grid step
is missed, as it is by a stepping method of that step.

What a run keeps between its segments (`state`) is what the kernels keep: status (a stopped member's), event times,
counts and the stopped states; the grid's values at a segment's start are the closed form's there again.
"""
from __future__ import annotations

from functools import cache

import numpy as np
from numba import njit

from ..results import Status
from . import kernels
from .blocks import FAST
from .events import EVENT_STATE, ROOT_ITERATIONS, event_spec, started
from .tuples import loaded, stored

STOPPED = int(Status.STOPPED_BY_EVENT)
GRID_FLOATS = 1 << 22  # state values of a batch of grid times, all members (32 MiB)


@cache
def evaluator(values, D: int, P: int):
    """evaluate(t, y, p, out): every event's value (values(t, y, p) -> E floats) of n members, t (n,) s, y (D n,)
    and p (P n,) their state's and parameters' rows flattened, into out (E n,) likewise."""
    like_y, like_p = (0.0,) * D, (0.0,) * P

    @njit(**FAST)
    def evaluate(t, y, p, out):
        n = t.shape[0]
        for j in range(n):
            stored(out, 0, n, j, values(t[j], loaded(y, 0, n, j, like_y), loaded(p, 0, n, j, like_p)))
    return evaluate


def components(rows: tuple, D: int):
    """evaluate (as evaluator's) for events that are state components `rows` alone: picked with NumPy, nothing
    compiled (a field of sites' state is too long for a tuple)."""
    def evaluate(t, y, p, out):
        out.reshape(len(rows), -1)[:] = y.reshape(D, -1)[list(rows)]
    return evaluate


class ExactEvents:
    """A closed-form run's events (results.Event), its members described by `values`, on a grid of `step` (s),
    `steps` of it between saved samples. `watch` goes through each segment of samples in turn."""

    def __init__(self, scene, values: dict, constants: dict, events: tuple, step: float, steps: int):
        self.scene, self.values, self.constants, self.step, self.steps = scene, values, constants, step, steps
        self.rate = np.ascontiguousarray(scene.inputs(values, constants)[1])
        D, P = scene.kernel_rows(constants)
        sources = tuple(e.source for e in events)
        if all(source[0] == "state" for source in sources):
            self.evaluate = components(tuple(source[1] for source in sources), D)
        else:
            self.evaluate = evaluator(kernels.event_values(scene.PHYSICS, sources, kernels.scene_identity(scene)), D, P)
        self.D = D
        self.events = events
        spec = event_spec(events)
        self.levels, self.signs, self.stops, self.kept, self.keeps = spec[:, 0], spec[:, 1], spec[:, 2] > 0, \
            spec[:, 3].astype(np.int64), spec[:, 4] > 0
        self.reset()

    def reset(self) -> None:
        """Back to the run's start."""
        self.status = np.zeros(self.rate.shape[1])
        self.__dict__.update(started(self.events, self.D, self.rate.shape[1]))

    def state(self) -> dict[str, np.ndarray]:
        """Copies of what a later segment continues from (as launch.Launch.state)."""
        return {name: getattr(self, name).copy() for name in ("status", *EVENT_STATE)}

    def watch(self, first: int, samples: np.ndarray) -> None:
        """Every crossing in the grid steps that end at samples first .. first + len(samples) - 1, recorded; the
        samples (count, D, members) of a member stopped at or before them set to NaN."""
        members = self.rate.shape[1]
        start, end = max(first - 1, 0) * self.steps, (first + len(samples) - 1) * self.steps
        batch = max(1, min(256, GRID_FLOATS // max(self.D * members, 1)))
        stop_grid = np.full(members, np.inf)  # a member stopped here: its samples from this grid point are NaN
        for a in range(start, end, batch):
            grid = np.arange(a, min(a + batch, end) + 1)
            self._crossings(grid, self._grid_values(grid * self.step), stop_grid)
        sample_grid = (first + np.arange(len(samples))) * self.steps
        gone = (self.status == STOPPED)[None, :] & (sample_grid[:, None] >= stop_grid[None, :])
        gone |= (self.status == STOPPED)[None, :] & ~np.isfinite(stop_grid)[None, :]  # stopped in an earlier segment
        samples[np.broadcast_to(gone[:, None, :], samples.shape)] = np.nan

    def _grid_values(self, times: np.ndarray) -> np.ndarray:
        """Every event's value of every member at `times` (s): (times, E, members)."""
        states = self.scene.exact(self.values, self.constants, times)  # (T, D, M)
        T, D, M = states.shape
        out = np.empty((len(self.levels), T * M))
        self.evaluate(np.repeat(times, M), np.ascontiguousarray(states.transpose(1, 0, 2)).reshape(-1),
                      np.ascontiguousarray(np.tile(self.rate, T)).reshape(-1), out.reshape(-1))
        return out.reshape(-1, T, M).transpose(1, 0, 2)

    def _at(self, t: np.ndarray, members: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(events' values (E, n), states (D, n)) of `members` (n indices) at their own times t (n,), s."""
        chosen = {name: value[members] for name, value in self.values.items()}
        states = np.ascontiguousarray(self.scene.exact(chosen, self.constants, t[None, :])[0])
        out = np.empty((len(self.levels), t.size))
        self.evaluate(t, states.reshape(-1), np.ascontiguousarray(self.rate[:, members]).reshape(-1),
                      out.reshape(-1))
        return out, states

    def _crossings(self, grid: np.ndarray, values: np.ndarray, stop_grid: np.ndarray) -> None:
        """Record the crossings between neighbouring grid points (values: (len(grid), E, members)) of the members
        still going, in each member's order; those after a member's first stopping one are not."""
        before, after = values[:-1], values[1:]
        level, sign = self.levels[None, :, None], self.signs[None, :, None]
        up, down = (before < level) & (after >= level), (before > level) & (after <= level)  # as events.crossed
        hit = ((up & (sign >= 0.0)) | (down & (sign <= 0.0))) & (self.status != STOPPED)[None, None, :]
        k, e, j = np.nonzero(hit)
        if not k.size:
            return
        t0 = grid[k] * self.step
        s = self._roots(t0, e, j, before[k, e, j], after[k, e, j])
        order = np.lexsort((e, s, k, j))  # each member's crossings in time, then by event
        k, e, j, s, t0 = k[order], e[order], j[order], s[order], t0[order]
        stopping = self.stops[e]
        first_stop = np.full(self.status.size, k.size)
        np.minimum.at(first_stop, j[stopping], np.nonzero(stopping)[0])  # each member's first stopping crossing
        first_stop[first_stop == k.size] = -1
        stop = first_stop[j]
        kept = (stop < 0) | (k < k[stop]) | ((k == k[stop]) & (s <= s[stop]))
        self._record(e[kept], j[kept], t0[kept] + s[kept] * self.step)
        stopped = np.nonzero(first_stop >= 0)[0]
        if stopped.size:
            at = first_stop[stopped]
            when = t0[at] + s[at] * self.step
            self.stopped[:, stopped] = self._at(when, stopped)[1]
            self.status[stopped] = STOPPED
            stop_grid[stopped] = grid[k[at]] + 1

    def _record(self, e: np.ndarray, j: np.ndarray, t: np.ndarray) -> None:
        """Occurrences of events e by members j at times t (s), in each member's order: the first `count` of
        each event kept, every one counted."""
        order = np.lexsort((np.arange(e.size), j, e))  # stable: by event, member, then time
        e, j, t = e[order], j[order], t[order]
        new_group = np.r_[True, (e[1:] != e[:-1]) | (j[1:] != j[:-1])]
        group_start = np.maximum.accumulate(np.where(new_group, np.arange(e.size), 0))
        rank = self.event_counts[e, j].astype(np.int64) + np.arange(e.size) - group_start
        kept = rank < self.kept[e]
        self.event_times[e[kept], rank[kept], j[kept]] = t[kept]
        keeps = kept & self.keeps[e]
        if keeps.any():
            self.event_states[e[keeps], rank[keeps], :, j[keeps]] = self._at(t[keeps], j[keeps])[1].T
        np.add.at(self.event_counts, (e, j), 1.0)

    def _roots(self, t0, e, j, before, after) -> np.ndarray:
        """The fraction s of the grid step from t0 (s) at which each crossing's event e of member j reaches its
        level (before, after: its values at the step's ends): Illinois, as ensemble.engine.events.root."""
        level = self.levels[e]
        a, b, ga, gb = np.zeros(e.size), np.ones(e.size), before - level, after - level
        side, result, going = np.zeros(e.size), np.ones(e.size), gb != 0.0
        for _ in range(ROOT_ITERATIONS):
            if not going.any():
                break
            s = np.where(going, (a * gb - b * ga) / np.where(going, gb - ga, 1.0), 0.5)
            s = np.where((a < s) & (s < b), s, 0.5 * (a + b))
            neighbours = going & ~((a < s) & (s < b))
            result[neighbours], going = b[neighbours], going & ~neighbours
            live = np.nonzero(going)[0]
            g = np.zeros(e.size)
            g[live] = self._at(t0[live] + s[live] * self.step, j[live])[0][e[live], np.arange(live.size)] - level[live]
            root = going & (g == 0.0)
            result[root], going = s[root], going & ~root
            upper = going & ((g > 0.0) == (gb > 0.0))
            lower = going & ~upper
            ga = np.where(upper & (side == 1), 0.5 * ga, ga)
            gb = np.where(lower & (side == -1), 0.5 * gb, gb)
            b, gb = np.where(upper, s, b), np.where(upper, g, gb)
            a, ga = np.where(lower, s, a), np.where(lower, g, ga)
            side = np.where(upper, 1.0, np.where(lower, -1.0, side))
            close = going & (b - a <= 1e-15)
            result[close], going = b[close], going & ~close
        return np.where(going, b, result)
