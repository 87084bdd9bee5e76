"""What a launch's samples become (Record: the saved variables with their observation noise, handed on as they
come) and what the runner records per member besides them: growth per step, measured error, the kernel's timing.

These run on the run path, so nothing here imports the analysis layer (fit, stability, scipy).
"""
from __future__ import annotations

import math
import time
import zlib

import numpy as np
from numba import njit

from .engine import launch
from .events import records as event_records
from .methods import Method
from .results import COUNTS, Outcome
from .spec import Spec

#: A decaying amplitude is used while above this fraction of its start (and above SUBNORMAL): in subnormal
#: numbers rounding stalls a decay (a last unit times 0.6 rounds back to itself).
DECAY_FLOOR = 1e-200
SUBNORMAL = 1e-290


def measured_growth(amplitudes: np.ndarray, t: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Amplitude growth factor per step of each member's fastest-growing motion; shape (members,).

    amplitudes (members, motions, samples) at times t (s); step (members,) s,
    the step each member took (an adaptive method's mean accepted step). Per
    motion, the slope of log amplitude against time is fitted by least
    squares over the second half of the samples taken before the member
    failed (the first ones mix in the motions a step damps), so a transient
    or the last values alone do not decide it. Motions that start at zero
    amplitude are skipped, and samples below DECAY_FLOOR times the start end
    a motion's record; NaN where fewer than two samples remain. Compiled: a
    run fits every member's record, and in numpy this cost as much as the
    kernel (it releases the GIL, so it overlaps the next chunk's kernel).
    """
    a = np.ascontiguousarray(amplitudes, dtype=float)
    growth = np.empty(a.shape[0])
    _fit_growth(a, np.ascontiguousarray(t, dtype=float), np.ascontiguousarray(np.broadcast_to(
        np.asarray(step, dtype=float), growth.shape)), growth)
    return growth


@njit(cache=True, nogil=True, error_model="numpy")
def _fit_growth(a, t, step, growth):
    """measured_growth into growth (members,), a member at a time (its samples are contiguous in `a`). Sums run
    in sample order, as numpy's over that axis did (the same bits)."""
    members, motions, samples = a.shape
    logs = np.empty(samples)
    for j in range(members):
        fastest = -np.inf
        for m in range(motions):
            floor = max(DECAY_FLOOR * a[j, m, 0], SUBNORMAL)
            count = 0  # samples before the first unusable one (not above the floor, NaN)
            while count < samples and floor < a[j, m, count] < np.inf:
                count += 1
            first = max(min(count // 2, count - 2), 0)  # the fit's window: samples first .. count - 1
            if count - first < 2:
                continue
            t_mean, y_mean = 0.0, 0.0
            for i in range(first, count):
                logs[i] = np.log(a[j, m, i])
                t_mean += t[i]
                y_mean += logs[i]
            t_mean /= count - first
            y_mean /= count - first
            cross, square = 0.0, 0.0
            for i in range(first, count):
                dt = t[i] - t_mean
                cross += dt * (logs[i] - y_mean)
                square += dt * dt
            g = np.exp(cross / square * step[j])
            if g == g:
                fastest = max(fastest, g)
        growth[j] = fastest if np.isfinite(fastest) else np.nan


def growth_per_step(scene, method: Method, values: dict[str, np.ndarray], amplitudes: np.ndarray, outcome: Outcome,
                    t: np.ndarray, t_end: float) -> np.ndarray:
    """Each member's measured growth factor per step (see measured_growth) from the scene's amplitudes (members,
    motions, samples) at times t (s); per mean accepted step (time reached, t_end or its failure, over steps
    accepted) for adaptive methods."""
    step = values["dt"]
    if method.adaptive:
        reached = np.where(np.isnan(outcome.failure_time), t_end, outcome.failure_time)
        with np.errstate(invalid="ignore", divide="ignore"):
            step = reached / outcome.counts[0]
    return measured_growth(amplitudes, t, step)


def relative_error(samples: np.ndarray, exact: np.ndarray) -> np.ndarray:
    """max |y - y_exact| / max |y_exact| over the state, per sample and member: (samples, members) from
    samples and exact (samples, state, members). A member with non-finite values has an infinite error."""
    with np.errstate(invalid="ignore", divide="ignore"):
        relative = np.abs(samples - exact).max(axis=1) / np.abs(exact).max(axis=1)
    relative[~np.isfinite(relative) & np.isfinite(exact).all(axis=1)] = np.inf
    return relative


def error_records(relative: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """error_max and error_final per member from a whole record's relative_error: the largest after the start,
    and the last."""
    return relative[1:].max(axis=0) if len(relative) > 1 else relative[0], relative[-1]


def measured_error(samples: np.ndarray, exact: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per member: max over saved samples, and at the last one, of max |y - y_exact| / max |y_exact| over the state.

    samples and exact: (n_save, state, members). A member with non-finite values has an infinite error.
    """
    return error_records(relative_error(samples, exact))


TIMED_KERNEL_BLOCKS = 16  # blocks in a timed call, whatever the point's members: one block costs more per step
TIMED_STEPS_PER_MEMBER = 1000  # steps each member takes at least in a timed call
TIMED_SECONDS = 0.05  # a timed call lasts at least this long (as timeit's autorange does): the timer, the call's
#                       own cost and each member's first steps stay small against it


def kernel_seconds_per_step(scene, method: Method, values: dict[str, np.ndarray], constants: dict, outcome: Outcome,
                            repeats: int, settings: dict) -> float:
    """The kernel's seconds per member-step on one thread: the best of `repeats` calls over their member-steps.

    Every point is timed in one configuration, so that its cost grows in proportion to its steps: the point's
    members repeated (in order) to TIMED_KERNEL_BLOCKS whole blocks, from their start over as many steps as
    make a call last at least TIMED_SECONDS (at least TIMED_STEPS_PER_MEMBER each; `settings` are the run's,
    `outcome` what it did). It times stepping alone: no layout, no output, on one thread whatever the point's
    member count. A run on T threads costs about 1/T of it per member-step."""
    taken = int(outcome.counts[0].sum() + outcome.counts[1].sum())
    if taken == 0:
        return np.nan
    members = len(outcome.status)
    block = launch.layout(scene, method, constants, settings.get("block")).block
    chosen = np.resize(np.arange(members), TIMED_KERNEL_BLOCKS * block)
    subset = {name: np.asarray(v)[chosen] for name, v in values.items()}
    settings = {**settings, "rtol": subset["rtol"], "atol": subset["atol"]}
    if method.adaptive:
        settings["dt"] = subset["dt"]
    run_span = settings["save_dt"]  # s: the run's, from its start to t_end

    def launch_for(steps: int) -> launch.Launch:
        """A launch in which each member takes about `steps` steps."""
        span = steps * settings["dt"] if not method.adaptive else run_span * steps * members / taken
        return launch.new_launch(scene, method, subset, constants, **{**settings, "save_dt": span})

    def best(call: launch.Launch, calls: int) -> float:
        """The best time of `calls` runs of `call` (inf for none)."""
        seconds = np.inf
        for _ in range(calls):
            start = time.perf_counter()
            call.run(threads=1)  # one thread: how many blocks a point has cannot leave threads idle
            seconds = min(seconds, time.perf_counter() - start)
        return seconds

    steps = TIMED_STEPS_PER_MEMBER
    call = launch_for(steps)
    seconds = best(call, 1)
    while seconds < TIMED_SECONDS:
        steps = math.ceil(steps * min(10.0, 1.2 * TIMED_SECONDS / max(seconds, 1e-9)))
        call = launch_for(steps)
        seconds = best(call, 1)
    seconds = min(seconds, best(call, repeats - 1))
    counts = call.outcome().counts
    return seconds / float(counts[0].sum() + counts[1].sum())


def noise_streams(spec: Spec, name: str, first: int, members: int) -> list[np.random.Generator]:
    """The observation noise streams of variable `name` for members first .. first + members - 1: member i's is
    seeded by (seed, crc32("noise:" + name), i). Drawn in time order, a segment at a time."""
    stream = zlib.crc32(f"noise:{name}".encode())
    return [np.random.default_rng([spec.seed, stream, first + i]) for i in range(members)]


class Record:
    """What a launch's samples become: saved variables (with observation noise) handed to write_samples(first
    sample, variables) as they come, and the amplitudes and errors that [measure] asks for, kept for the
    per-member records."""

    def __init__(self, spec: Spec, method: Method, values: dict[str, np.ndarray], first: int, members: int,
                 write_samples):
        self.spec, self.method, self.values, self.write_samples = spec, method, values, write_samples
        self.scene, self.first = spec.model, first
        self.noise = {name: noise_streams(spec, name, first, members) for name in spec.noise if name in spec.save}
        self.amplitudes, self.errors = [], []

    def add(self, start: int, samples: np.ndarray) -> dict[str, np.ndarray]:
        """Samples start, start + 1, ... (count, state rows, members) of the launch; returns the saved variables
        written for them (name: (members, count, ...))."""
        spec, scene = self.spec, self.scene
        data = scene.observe(samples, spec.save, self.values, spec.constants)
        for name, streams in self.noise.items():
            data[name] = data[name] + spec.noise[name] * np.stack([g.standard_normal(data[name].shape[1:])
                                                                   for g in streams])
        self.write_samples(start, data)
        if spec.measure["growth"] and not self.method.closed_form:
            self.amplitudes.append(scene.amplitudes(samples, self.values, spec.constants))
        if spec.measure["error"]:
            exact = scene.exact(self.values, spec.constants, spec.times(start, start + len(samples)))
            self.errors.append(relative_error(samples, exact))
        return data

    def state(self) -> dict:
        """What the record continues from after the last `add`: its noise streams' states ("noise") and that
        add's pieces of the amplitudes and errors (arrays)."""
        state = {"noise": {name: [g.bit_generator.state for g in streams] for name, streams in self.noise.items()}}
        for name in ("amplitudes", "errors"):
            if getattr(self, name):
                state[name] = getattr(self, name)[-1]
        return state

    def restore(self, noise: dict, amplitudes: list[np.ndarray], errors: list[np.ndarray]) -> None:
        """Continue from the pieces that `state` gave, add by add, and the noise states of the last."""
        for name, states in noise.items():
            for generator, state in zip(self.noise[name], states):
                generator.bit_generator.state = state
        self.amplitudes, self.errors = list(amplitudes), list(errors)

    def records(self, outcome: Outcome, seconds_per_step=None) -> dict[str, np.ndarray]:
        """The per-member records (member, ...) once every sample is added; seconds_per_step() times the kernel when
        the run measures timing."""
        spec, method, members = self.spec, self.method, len(outcome.status)
        records = dict(zip(COUNTS, outcome.counts), status=outcome.status, failure_time=outcome.failure_time)
        if spec.measure["growth"]:
            records["growth_per_step"] = (np.full(members, np.nan) if method.closed_form else growth_per_step(
                self.scene, method, self.values, _joined(self.amplitudes, axis=2), outcome, spec.times(), spec.t_end))
        if spec.measure["error"]:
            records["error_max"], records["error_final"] = error_records(_joined(self.errors, axis=0))
        if spec.measure["timing"]:
            records["seconds_per_step"] = np.full(members, np.nan if method.closed_form else seconds_per_step())
        if spec.events:
            records.update(event_records(spec.events, outcome, self.scene, spec.save, self.values, spec.constants))
            for name in spec.noise.keys() - set(spec.save):  # event times observed with noise
                draws = [g.standard_normal(records[name].shape[1:]) for g in noise_streams(spec, name, self.first,
                                                                                          members)]
                records[name] = records[name] + spec.noise[name] * np.stack(draws)
        return records


def _joined(pieces: list[np.ndarray], axis: int) -> np.ndarray:
    """np.concatenate of pieces along axis, without copying a single piece. A chunk's kernel call makes one,
    and copying its amplitudes into new memory took up to 5 ms a chunk in a 262,144-top run."""
    return pieces[0] if len(pieces) == 1 else np.concatenate(pieces, axis=axis)
