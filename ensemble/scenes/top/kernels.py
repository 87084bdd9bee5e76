"""The top's compiled kernels: its right-hand side, its exactly solved pieces, and one kernel per method.

Work rows (BLOCK members each): the rates w1, w2, w3, then the parameters p,
r1, r3 (see model.rates), then what the method needs. Generic helpers (rows
in and out, member checks, step control) are in ensemble.engine.blocks.
"""
from __future__ import annotations

import math
from functools import cache

import numpy as np
from numba import njit

from ...engine.blocks import (
    CONTROL_ROWS,
    FAST,
    HELPERS,
    STEP,
    H,
    Kernel,
    adaptive_constants,
    block_done,
    cache_line_array,
    check_members,
    control_step,
    counts_out,
    method_constants,
    rates_accept,
    rates_error,
    rates_load,
    rates_saved,
    rates_start,
    sin_cos,
    stack_array,
    trial_steps,
)
from ...methods import Method
from .model import PIECES

BLOCK = 128  # members per block
DRAG = PIECES.index("drag")


@njit(inline="always", fastmath=True, error_model="numpy")
def rhs(w1, w2, w3, p, r1, r3):
    """Time derivative of the body rates (rad s-2)."""
    return -p * w3 * w2 - r1 * w1, p * w3 * w1 - r1 * w2, -r3 * w3


@njit(inline="always", fastmath=True, error_model="numpy")
def rotate(w1, w2, w3, p, tau):
    """Free symmetric-top rotation for time tau (s): (w1, w2) turns about e3 by p w3 tau."""
    sin, cos = sin_cos(p * w3 * tau)
    return cos * w1 - sin * w2, sin * w1 + cos * w2, w3


@njit(inline="always", fastmath=True, error_model="numpy")
def drag_decay(r, tau):
    """Drag alone for time tau (s) scales a rate by exp(-r tau): r1 for w1, w2 and r3 for w3."""
    return math.exp(-r * tau)


def block_size(constants: dict, method: Method | None = None) -> int:
    """Members per kernel block: the same for every method and every top run."""
    return BLOCK


def kernel(method: Method, constants: dict):
    """Kernel(function, work rows) of a stepping method (compiled or cache-loaded); every top run shares it."""
    return _kernel(method)


@cache
def _kernel(method: Method):
    return _adaptive_kernel(method) if method.adaptive else _fixed_kernel(method)


def _fixed_kernel(method: Method):
    """Top kernel for an explicit Runge-Kutta tableau or a drag/rotation splitting.

    Work rows: w1, w2, w3, p, r1, r3, then (splitting) the drag factors of
    sequence entry e at rows 6 + 2 e, 7 + 2 e. A Runge-Kutta method's stage
    slopes are a member's own, within a step (stack_array). Stage and sequence
    loops have constant trip counts, so LLVM unrolls them, folds the method's
    coefficients and keeps the slopes in registers.
    """
    runge_kutta, S, a, b, E, pieces, fractions = method_constants(method)
    rows = 6 + (0 if runge_kutta else 2 * E)
    SLOPES = 3 * S

    helpers = HELPERS  # in the kernel's cache key (blocks.HELPERS)

    @njit(nogil=True, cache=True, **FAST)
    def kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress,
               works, start, first_block, end_block):
        """state0 (blocks, 3, BLOCK), rate (blocks, 3, BLOCK), limit (M,) -> samples (members, count, 3),
        status (M,), failure_time (M,) (s; set only where a member fails); M = blocks x BLOCK."""
        helpers  # a closure variable, so in the cache key
        work = cache_line_array(works.shape[1])
        for block in range(first_block, end_block):
            j0 = block * BLOCK
            work[:] = works[block]
            slopes = stack_array(SLOPES)  # stage s's k[c] at 3 s + c (Runge-Kutta)
            if start == 0:
                rates_load(work, state0, rate, block, samples, 3, BLOCK)
                check_members(work, 0, 3, BLOCK, j0, limit, status, failure_time, 0.0)  # a non-finite start
                if not runge_kutta:
                    for e in range(E):
                        if pieces[e] == DRAG:
                            for j in range(BLOCK):
                                work[(6 + 2 * e) * BLOCK + j] = drag_decay(work[4 * BLOCK + j], h * fractions[e])
                                work[(7 + 2 * e) * BLOCK + j] = drag_decay(work[5 * BLOCK + j], h * fractions[e])
            elif block_done(samples, status, progress, block, BLOCK):
                continue
            for i in range(max(start, 1), start + samples.shape[1]):
                for _ in range(steps_per_save):
                    for j in range(BLOCK):
                        y1 = work[j]
                        y2 = work[BLOCK + j]
                        y3 = work[2 * BLOCK + j]
                        p = work[3 * BLOCK + j]
                        r1 = work[4 * BLOCK + j]
                        r3 = work[5 * BLOCK + j]
                        if runge_kutta:
                            s1 = 0.0
                            s2 = 0.0
                            s3 = 0.0
                            for s in range(S):
                                z1 = y1
                                z2 = y2
                                z3 = y3
                                for r in range(s):  # a is zero from column s on
                                    ha = h * a[s * S + r]
                                    z1 += ha * slopes[3 * r]
                                    z2 += ha * slopes[3 * r + 1]
                                    z3 += ha * slopes[3 * r + 2]
                                d1, d2, d3 = rhs(z1, z2, z3, p, r1, r3)
                                slopes[3 * s], slopes[3 * s + 1], slopes[3 * s + 2] = d1, d2, d3
                                s1 += b[s] * d1
                                s2 += b[s] * d2
                                s3 += b[s] * d3
                            y1 += h * s1
                            y2 += h * s2
                            y3 += h * s3
                        else:
                            for e in range(E):
                                if pieces[e] == DRAG:
                                    decay = work[(6 + 2 * e) * BLOCK + j]
                                    y1 *= decay
                                    y2 *= decay
                                    y3 *= work[(7 + 2 * e) * BLOCK + j]
                                else:
                                    y1, y2, y3 = rotate(y1, y2, y3, p, h * fractions[e])
                        work[j] = y1
                        work[BLOCK + j] = y2
                        work[2 * BLOCK + j] = y3
                if rates_saved(work, samples, i - start, block, limit, status, failure_time, progress,
                               i * steps_per_save * h, -1, BLOCK):
                    break
            works[block] = work

    return Kernel(kernel, rows)


def _adaptive_kernel(method: Method):
    """Top kernel for an adaptive embedded pair: every member controls its own step.

    Work rows: w1, w2, w3, p, r1, r3, stage slopes k[s, c] at 6 + 3 s + c, the
    new state (3 rows), then the control rows (H, TIME, ...). A trial step runs
    for all members of a block at once, each with its own step, clipped so it
    lands exactly on the next saved time; members already there take no step.
    """
    S, a, e, alpha, beta, safety, min_factor, max_factor = adaptive_constants(method)
    a_array = np.array(a)  # indexed by a loop variable: a constant array, not a tuple
    K = 6
    NEW = K + 3 * S
    C0 = NEW + 3
    rows = C0 + CONTROL_ROWS

    helpers = HELPERS  # in the kernel's cache key (blocks.HELPERS)

    @njit(nogil=True, cache=True, **FAST)
    def kernel(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, progress,
               works, start, first_block, end_block):
        """state0, rate (blocks, 3, BLOCK); control (3, M): first step (s; <= 0: estimate it), rtol, atol;
        limit (M,) -> samples (members, count, 3), counts (3, M): accepted, rejected, right-hand-side
        evaluations; status (M,) and failure_time (M,; s, set only where a member fails)."""
        helpers  # a closure variable, so in the cache key
        B = BLOCK
        work = cache_line_array(works.shape[1])
        for block in range(first_block, end_block):
            j0 = block * B
            work[:] = works[block]
            if start == 0:
                rates_load(work, state0, rate, block, samples, 3, BLOCK)
                for j in range(B):
                    d1, d2, d3 = rhs(work[j], work[B + j], work[2 * B + j], work[3 * B + j], work[4 * B + j],
                                     work[5 * B + j])
                    rates_start(work, control, K, C0, B, j, j0, d1, d2, d3, save_dt)
                check_members(work, 0, 3, B, j0, limit, status, failure_time, 0.0, C0 + H)  # a non-finite start
            elif block_done(samples, status, progress, block, BLOCK):
                continue
            for i in range(max(start, 1), start + samples.shape[1]):
                target = i * save_dt
                while trial_steps(work, C0, B, target):
                    for s in range(1, S):  # stages outside, members inside, as in the chain kernels
                        for j in range(B):
                            h = work[(C0 + STEP) * B + j]
                            z1, z2, z3 = work[j], work[B + j], work[2 * B + j]
                            for r in range(s):  # a is zero from column s on
                                ha = h * a_array[s * S + r]
                                z1 += ha * work[(K + 3 * r) * B + j]
                                z2 += ha * work[(K + 3 * r + 1) * B + j]
                                z3 += ha * work[(K + 3 * r + 2) * B + j]
                            d1, d2, d3 = rhs(z1, z2, z3, work[3 * B + j], work[4 * B + j], work[5 * B + j])
                            work[(K + 3 * s) * B + j] = d1
                            work[(K + 3 * s + 1) * B + j] = d2
                            work[(K + 3 * s + 2) * B + j] = d3
                            work[NEW * B + j], work[(NEW + 1) * B + j], work[(NEW + 2) * B + j] = z1, z2, z3
                    rates_error(work, K, NEW, C0, S, e, B)
                    control_step(work, C0, B, target, j0, status, failure_time, S - 1, alpha, beta, safety,
                                  min_factor, max_factor)
                    rates_accept(work, K, NEW, C0, S, B)
                if rates_saved(work, samples, i - start, block, limit, status, failure_time, progress,
                               target, C0 + H, BLOCK):
                    break
            counts_out(work, C0, B, counts, j0)
            works[block] = work

    return Kernel(kernel, rows)


# ---------------------------------------------------------------- observing: tilt and amplitudes from samples

_ATAN_P = (-8.750608600031904122785e-1, -1.615753718733365076637e1, -7.500855792314704667340e1,
           -1.228866684490136173410e2, -6.485021904942025371773e1)  # Cephes' atan: x + x^3 P(x^2) / Q(x^2)
_ATAN_Q = (2.485846490142306297962e1, 1.650270098316988542046e2, 4.328810604912902668951e2,
           4.853903996359136964868e2, 1.945506571482613964425e2)
_PI_LOW, _PI_2_LOW = 1.2246467991473532e-16, 6.123233995736766e-17  # pi - float(pi), pi/2 - float(pi/2)
OBSERVING = dict(error_model="numpy", fastmath={"contract"})  # no fastmath: NaN samples (failed members) stay NaN


@njit(inline="always", **OBSERVING)
def _atan_nonnegative(x):
    """atan(x) for x >= 0 or NaN, Cephes' rational form with its range reduction, in selects: libm's atan2 is a
    scalar call (about 30 ns; this vectorizes)."""
    big, middle = x > 2.414213562373095, x > 0.66  # tan(3 pi / 8)
    z = -1.0 / x if big else ((x - 1.0) / (x + 1.0) if middle else x)
    base = math.pi / 2 if big else (math.pi / 4 if middle else 0.0)
    low = _PI_2_LOW if big else (0.5 * _PI_2_LOW if middle else 0.0)
    z2 = z * z
    p = (((_ATAN_P[0] * z2 + _ATAN_P[1]) * z2 + _ATAN_P[2]) * z2 + _ATAN_P[3]) * z2 + _ATAN_P[4]
    q = ((((z2 + _ATAN_Q[0]) * z2 + _ATAN_Q[1]) * z2 + _ATAN_Q[2]) * z2 + _ATAN_Q[3]) * z2 + _ATAN_Q[4]
    return base + ((z * (z2 * p / q) + z) + low)


@njit(inline="always", **OBSERVING)
def _tilt_and_transverse(w1, w2, w3):
    """(atan2(|(w1, w2)|, w3) (rad), |(w1, w2)| (rad/s)): numpy's arctan2 and hypot to a few units in the last
    place (tested), NaN if any rate is."""
    w1, w2 = abs(w1), abs(w2)
    high, low = (w1, w2) if w1 > w2 else (w2, w1)  # a NaN lands in low, or makes high > 0 false
    ratio = low / high
    transverse = high * math.sqrt(1.0 + ratio * ratio) if high > 0.0 else w1 + w2
    r = _atan_nonnegative(transverse / abs(w3))
    angle = (math.pi - r) + _PI_LOW if w3 < 0.0 else r
    on_axis = math.pi if math.copysign(1.0, w3) < 0.0 else 0.0  # atan2(0, +-0)
    return (on_axis if transverse == 0.0 and w3 == 0.0 else angle), transverse


@njit(cache=True, nogil=True, **OBSERVING)
def observed_tilt(omega):
    """Tilt (rad), (members, t), of member-major rates omega (members, t, 3) rad/s (see model.tilt)."""
    members, count, _ = omega.shape
    tilt, row = np.empty((members, count)), np.empty((3, count))
    for a in range(members):
        for i in range(count):  # a member's rates in rows of their own: the loop below then vectorizes
            row[0, i], row[1, i], row[2, i] = omega[a, i, 0], omega[a, i, 1], omega[a, i, 2]
        for i in range(count):
            tilt[a, i] = _tilt_and_transverse(row[0, i], row[1, i], row[2, i])[0]
    return tilt


@njit(cache=True, nogil=True, **OBSERVING)
def observed_amplitudes(omega):
    """|(w1, w2)| and |w3| (rad/s), (members, 2, t), of member-major rates omega (members, t, 3) (see
    model.amplitudes)."""
    members, count, _ = omega.shape
    out, row = np.empty((members, 2, count)), np.empty((3, count))
    for a in range(members):
        for i in range(count):
            row[0, i], row[1, i], row[2, i] = omega[a, i, 0], omega[a, i, 1], omega[a, i, 2]
        for i in range(count):
            out[a, 0, i] = _tilt_and_transverse(row[0, i], row[1, i], row[2, i])[1]
            out[a, 1, i] = abs(row[2, i])
    return out
