"""What a kernel is given and what its step counts are, on either device (ensemble.engine.launch for the CPU,
ensemble.engine.gpu_launch for a GPU): each member's blow-up limit, an adaptive kernel's control, a fixed-step
run's counts."""
from __future__ import annotations

import math

import numpy as np

from ..methods import Method


def fixed_counts(method: Method, scene, ended: np.ndarray, dt: float, steps: int) -> np.ndarray:
    """Step counts (3, members) of a fixed-step run: every step up to t_end, or up to the time a member ended
    (failed, at a saved time; or stopped at an event, within a step; NaN: it ran to the end)."""
    taken = np.where(np.isnan(ended), steps, np.ceil(np.round(ended / dt, 9)))
    return np.stack([taken, np.zeros(taken.shape),
                     taken * method.evaluations_per_step(scene.EVALUATING_PIECES)]).astype(np.int64)


def adaptive_control(dt, rtol, atol, members: int) -> np.ndarray:
    """An adaptive kernel's per-member control (3, members): first trial step (s; 0: estimate it), rtol, atol, each
    one value or one per member (dt None or NaN: estimated)."""
    return np.stack([np.nan_to_num(np.broadcast_to(np.asarray(x, dtype=float), (members,)), nan=0.0)
                     for x in (np.nan if dt is None else dt, rtol, atol)])


def blowup_limits(state0: np.ndarray, blowup_factor: float) -> np.ndarray:
    """Each member's largest allowed |state component|: blowup_factor times its largest at the start."""
    if math.isinf(blowup_factor):  # only non-finite states fail (inf * 0 would be NaN)
        return np.full(state0.shape[1], np.inf)
    return np.ascontiguousarray(blowup_factor * np.abs(state0).max(axis=0))
