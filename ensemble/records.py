"""What the runner records per member besides the saved variables: growth per step and measured error.

These run on the run path, so nothing here imports the analysis layer (fit, stability, scipy).
"""
from __future__ import annotations

import numpy as np

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
    a motion's record; NaN where fewer than two samples remain.
    """
    a = np.asarray(amplitudes, dtype=float)
    floor = np.maximum(DECAY_FLOOR * a[:, :1], SUBNORMAL)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_a = np.where(a > floor, np.log(a), np.nan)
    count = np.cumprod(np.isfinite(log_a), axis=1).sum(axis=1, keepdims=True)  # samples before the first unusable
    start = np.maximum(np.minimum(count // 2, count - 2), 0)
    index = np.arange(a.shape[1])[None, :, None]
    window = (index >= start) & (index < count)
    weight = window.astype(float)
    total = weight.sum(axis=1)
    tt = np.broadcast_to(np.asarray(t, dtype=float)[None, :, None], a.shape)
    y = np.where(window, log_a, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_mean = (weight * tt).sum(axis=1) / total
        y_mean = y.sum(axis=1) / total
        dt = np.where(window, tt - t_mean[:, None], 0.0)
        slope = (dt * (y - y_mean[:, None])).sum(axis=1) / (dt * dt).sum(axis=1)
    slope = np.where(total >= 2, slope, np.nan)
    growth = np.exp(slope * np.asarray(step, dtype=float)[None, :])
    fastest = np.where(np.isnan(growth), -np.inf, growth).max(axis=0)
    return np.where(np.isfinite(fastest), fastest, np.nan)


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
