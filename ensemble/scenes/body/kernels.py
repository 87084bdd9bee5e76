"""The free body's compiled kernels: its right-hand side, its turns about the body axes, one kernel per method.

Work rows (BLOCK members each): the rates w1, w2, w3, then the parameters
a1, a2, a3, r1, r2, r3 (see model.rates), then what the method needs. The
layout and loops are the top's (ensemble/scenes/top/kernels.py) with six
parameter rows. Generic helpers are in ensemble.engine.blocks.
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


P = 12  # parameter rows: a1, a2, a3, r1, r2, r3, lambda1..3, 1/lambda1..3 (see model.rates)
LAMBDA, INVERSE = 9, 12  # work rows of lambda_1 and 1/lambda_1
DRAG = PIECES.index("drag")  # pieces 0, 1, 2 turn L about body axes 1, 2, 3


@njit(inline="always", fastmath=True, error_model="numpy")
def rhs(w1, w2, w3, a1, a2, a3, r1, r2, r3):
    """Time derivative of the body rates (rad s-2): w_i' = a_i w_j w_k - r_i w_i."""
    return a1 * w2 * w3 - r1 * w1, a2 * w3 * w1 - r2 * w2, a3 * w1 * w2 - r3 * w3


@njit(inline="always", fastmath=True, error_model="numpy")
def _rhs_of(w1, w2, w3, work, j, B):
    """rhs for member j of a block, its parameters at work rows 3 .. 8."""
    return rhs(w1, w2, w3, work[3 * B + j], work[4 * B + j], work[5 * B + j], work[6 * B + j], work[7 * B + j],
               work[8 * B + j])


def block_size(constants: dict, method: Method | None = None) -> int:
    """Members per kernel block: the same for every method and every body run."""
    return BLOCK


def kernel(method: Method, constants: dict):
    """Kernel(function, work rows) of a stepping method (compiled or cache-loaded); every body run shares it."""
    return _kernel(method)


@cache
def _kernel(method: Method):
    if method.adaptive:
        return _adaptive_kernel(method)
    return _fixed_kernel(method) if method.tableau is not None else _splitting_kernel(method)


@njit(inline="always", fastmath=True, error_model="numpy")
def turn(x, y, angle):
    """(x, y) turned by -angle: the pair of L across a body axis under that axis' piece L_i^2 / (2 lambda_i)."""
    sin, cos = sin_cos(angle)
    return cos * x + sin * y, cos * y - sin * x


@njit(inline="always", **FAST)
def _scale_rows(work, first, B):
    """Rows 0 .. 2 (w or L) times rows first .. first + 2 (lambda, to L; 1/lambda, back to w)."""
    for c in range(3):
        for j in range(B):
            work[c * B + j] *= work[(first + c) * B + j]


def _splitting_kernel(method: Method):
    """Kernel for a splitting into turns of L about each body axis and drag (method.splitting over PIECES).

    Work rows: w1, w2, w3 (L = lambda w within a save interval), the P
    parameters, then the drag factors exp(-r_c h f_e) of sequence entry e at
    rows K + 3 e + c. Piece i < 3 keeps L_i and turns (L_j, L_k) by (L_i /
    lambda_i) tau: |L| is kept to rounding.
    """
    _, _, _, _, E, pieces, fractions = method_constants(method)
    K = 3 + P
    rows = K + 3 * E

    helpers = HELPERS  # in the kernel's cache key (blocks.HELPERS)

    @njit(nogil=True, cache=True, **FAST)
    def kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress,
               works, start, first_block, end_block):
        """As _fixed_kernel's."""
        helpers  # a closure variable, so in the cache key
        work = cache_line_array(works.shape[1])
        for block in range(first_block, end_block):
            work[:] = works[block]
            if start == 0:
                rates_load(work, state0, rate, block, samples, P, BLOCK)
                check_members(work, 0, 3, BLOCK, block * BLOCK, limit, status, failure_time, 0.0)  # a non-finite start
                for e in range(E):
                    for c in range(3):
                        for j in range(BLOCK):
                            work[(K + 3 * e + c) * BLOCK + j] = math.exp(-work[(6 + c) * BLOCK + j] * h * fractions[e])
            elif block_done(samples, status, progress, block, BLOCK):
                continue
            for i in range(max(start, 1), start + samples.shape[1]):
                _scale_rows(work, LAMBDA, BLOCK)
                for _ in range(steps_per_save):
                    for j in range(BLOCK):
                        y1 = work[j]
                        y2 = work[BLOCK + j]
                        y3 = work[2 * BLOCK + j]
                        for e in range(E):
                            tau = h * fractions[e]
                            if pieces[e] == DRAG:
                                y1 *= work[(K + 3 * e) * BLOCK + j]
                                y2 *= work[(K + 3 * e + 1) * BLOCK + j]
                                y3 *= work[(K + 3 * e + 2) * BLOCK + j]
                            elif pieces[e] == 0:
                                y2, y3 = turn(y2, y3, y1 * work[INVERSE * BLOCK + j] * tau)
                            elif pieces[e] == 1:
                                y3, y1 = turn(y3, y1, y2 * work[(INVERSE + 1) * BLOCK + j] * tau)
                            else:
                                y1, y2 = turn(y1, y2, y3 * work[(INVERSE + 2) * BLOCK + j] * tau)
                        work[j] = y1
                        work[BLOCK + j] = y2
                        work[2 * BLOCK + j] = y3
                _scale_rows(work, INVERSE, BLOCK)
                if rates_saved(work, samples, i - start, block, limit, status, failure_time, progress,
                               i * steps_per_save * h, -1, BLOCK):
                    break
            works[block] = work

    return Kernel(kernel, rows)


def _fixed_kernel(method: Method):
    """Kernel for an explicit Runge-Kutta tableau. Work rows: w1, w2, w3, the P parameters. The stage slopes are a
    member's own, within a step (stack_array). Stage loops have constant trip counts, so LLVM unrolls them, folds
    the tableau's coefficients and keeps the slopes in registers."""
    _, S, a, b, _, _, _ = method_constants(method)
    rows = 3 + P
    SLOPES = 3 * S

    helpers = HELPERS  # in the kernel's cache key (blocks.HELPERS)

    @njit(nogil=True, cache=True, **FAST)
    def kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress,
               works, start, first_block, end_block):
        """state0 (blocks, 3, BLOCK), rate (blocks, P, BLOCK), limit (M,) -> samples (members, count, 3),
        status (M,), failure_time (M,) (s; set only where a member fails); M = blocks x BLOCK."""
        helpers  # a closure variable, so in the cache key
        work = cache_line_array(works.shape[1])
        for block in range(first_block, end_block):
            work[:] = works[block]
            slopes = stack_array(SLOPES)  # stage s's k[c] at 3 s + c
            if start == 0:
                rates_load(work, state0, rate, block, samples, P, BLOCK)
                check_members(work, 0, 3, BLOCK, block * BLOCK, limit, status, failure_time, 0.0)  # a non-finite start
            elif block_done(samples, status, progress, block, BLOCK):
                continue
            for i in range(max(start, 1), start + samples.shape[1]):
                for _ in range(steps_per_save):
                    for j in range(BLOCK):
                        y1 = work[j]
                        y2 = work[BLOCK + j]
                        y3 = work[2 * BLOCK + j]
                        a1, a2, a3 = work[3 * BLOCK + j], work[4 * BLOCK + j], work[5 * BLOCK + j]
                        r1, r2, r3 = work[6 * BLOCK + j], work[7 * BLOCK + j], work[8 * BLOCK + j]
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
                            d1, d2, d3 = rhs(z1, z2, z3, a1, a2, a3, r1, r2, r3)
                            slopes[3 * s], slopes[3 * s + 1], slopes[3 * s + 2] = d1, d2, d3
                            s1 += b[s] * d1
                            s2 += b[s] * d2
                            s3 += b[s] * d3
                        work[j] = y1 + h * s1
                        work[BLOCK + j] = y2 + h * s2
                        work[2 * BLOCK + j] = y3 + h * s3
                if rates_saved(work, samples, i - start, block, limit, status, failure_time, progress,
                               i * steps_per_save * h, -1, BLOCK):
                    break
            works[block] = work

    return Kernel(kernel, rows)


def _adaptive_kernel(method: Method):
    """Kernel for an adaptive embedded pair: every member controls its own step.

    Work rows: w1, w2, w3, the P parameters, stage slopes k[s, c] at K + 3 s + c, the
    new state (3 rows), then the control rows (H, TIME, ...). A trial step runs
    for all members of a block at once, each with its own step, clipped so it
    lands exactly on the next saved time; members already there take no step.
    """
    S, a, e, alpha, beta, safety, min_factor, max_factor = adaptive_constants(method)
    a_array = np.array(a)  # indexed by a loop variable: a constant array, not a tuple
    K = 3 + P
    NEW = K + 3 * S
    C0 = NEW + 3
    rows = C0 + CONTROL_ROWS

    helpers = HELPERS  # in the kernel's cache key (blocks.HELPERS)

    @njit(nogil=True, cache=True, **FAST)
    def kernel(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, progress,
               works, start, first_block, end_block):
        """state0 (blocks, 3, BLOCK), rate (blocks, P, BLOCK); control (3, M): first step (s; <= 0: estimate
        it), rtol, atol;
        limit (M,) -> samples (members, count, 3), counts (3, M): accepted, rejected, right-hand-side
        evaluations; status (M,) and failure_time (M,; s, set only where a member fails)."""
        helpers  # a closure variable, so in the cache key
        B = BLOCK
        work = cache_line_array(works.shape[1])
        for block in range(first_block, end_block):
            j0 = block * B
            work[:] = works[block]
            if start == 0:
                rates_load(work, state0, rate, block, samples, P, BLOCK)
                for j in range(B):
                    d1, d2, d3 = _rhs_of(work[j], work[B + j], work[2 * B + j], work, j, B)
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
                            d1, d2, d3 = _rhs_of(z1, z2, z3, work, j, B)
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
