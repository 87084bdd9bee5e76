"""What the runner records per member besides the saved variables: growth per step and measured error.

These run on the run path, so nothing here imports the analysis layer (fit, stability, scipy).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .methods import Method
from .results import Outcome

#: A decaying amplitude is used while above this fraction of its start (and above SUBNORMAL): in subnormal
#: numbers rounding stalls a decay (a last unit times 0.6 rounds back to itself).
DECAY_FLOOR = 1e-200
SUBNORMAL = 1e-290


def measured_growth(amplitudes: np.ndarray, t: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Amplitude growth factor per step of each member's fastest-growing motion; shape (members,).

    amplitudes (motions, samples, members) at times t (s); step (members,) s,
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
    growth = np.empty(a.shape[2])
    _fit_growth(a, np.ascontiguousarray(t, dtype=float), np.ascontiguousarray(np.broadcast_to(
        np.asarray(step, dtype=float), growth.shape)), growth)
    return growth


@njit(cache=True, nogil=True, error_model="numpy")
def _fit_growth(a, t, step, growth):
    """measured_growth into growth (members,). Sums run in sample order, as numpy's over that axis did (the same
    bits); the inner loops run over members, contiguous in `a`."""
    motions, samples, members = a.shape
    growth[:] = -np.inf
    count = np.empty(members, dtype=np.int64)  # samples before the first unusable one (not above the floor, NaN)
    first = np.empty(members, dtype=np.int64)  # the fit's window: samples first .. count - 1
    floor, t_mean, y_mean = np.empty(members), np.empty(members), np.empty(members)
    cross, square = np.empty(members), np.empty(members)
    logs = np.empty((samples, members))
    for m in range(motions):
        for j in range(members):
            floor[j] = max(DECAY_FLOOR * a[m, 0, j], SUBNORMAL)
            count[j] = 0
        for i in range(samples):
            for j in range(members):
                if count[j] == i and floor[j] < a[m, i, j] < np.inf:
                    count[j] = i + 1
        for j in range(members):
            first[j] = max(min(count[j] // 2, count[j] - 2), 0)
        t_mean[:], y_mean[:], cross[:], square[:] = 0.0, 0.0, 0.0, 0.0
        for i in range(samples):
            for j in range(members):
                if first[j] <= i < count[j]:
                    logs[i, j] = np.log(a[m, i, j])
                    t_mean[j] += t[i]
                    y_mean[j] += logs[i, j]
        for j in range(members):
            t_mean[j] /= count[j] - first[j]
            y_mean[j] /= count[j] - first[j]
        for i in range(samples):
            for j in range(members):
                if first[j] <= i < count[j]:
                    dt = t[i] - t_mean[j]
                    cross[j] += dt * (logs[i, j] - y_mean[j])
                    square[j] += dt * dt
        for j in range(members):
            if count[j] - first[j] >= 2:
                g = np.exp(cross[j] / square[j] * step[j])
                if g == g:
                    growth[j] = max(growth[j], g)
    for j in range(members):
        if not np.isfinite(growth[j]):
            growth[j] = np.nan


def growth_per_step(scene, method: Method, values: dict[str, np.ndarray], amplitudes: np.ndarray, outcome: Outcome,
                    t: np.ndarray, t_end: float) -> np.ndarray:
    """Each member's measured growth factor per step (see measured_growth) from the scene's amplitudes (motions,
    samples, members) at times t (s); per mean accepted step (time reached, t_end or its failure, over steps
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
