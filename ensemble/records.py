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
