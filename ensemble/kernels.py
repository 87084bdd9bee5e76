"""Parallel ensemble drivers: a scene's equations combined with a method.

Members run in blocks; prange goes over blocks and the innermost loop over the
members of a block, which LLVM vectorizes (see DESIGN.md). Each block keeps
everything a step touches in one work array at constant offsets: with a
single base pointer LLVM proves the rows disjoint and emits only the vector
loop (separate arrays add a runtime overlap check whose scalar fallback
rounds differently, so results would depend on heap addresses).

Kernel arrays are laid out by block: state0 and rate (blocks, rows, B) and
samples (n_save, blocks, rows, B), so a block reads and writes contiguous
memory (as (rows, members) arrays, each row of a block was a separate cache
line far from the next: loading and saving a block of 16-mass chains cost
about as much as 200 of its steps, measured). Per-member arrays (limit,
status, failure_time, control) are (..., members).

Kernels are generated per (scene, method, kernel key) by factories whose
closures capture the method's data as constants; Numba caches each on disk.
"""
from __future__ import annotations

import math
from functools import cache
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from .methods import DRAG, KICK, METHODS, Method
from .scenes import SCENES, chain, top

BLOCK = 128  # members per block of the top kernels
TILE_ROWS, TILE_PIECES = 64, 32  # a long chain's splitting kernel: masses per tile, pieces per sweep
FAST = dict(fastmath=True, error_model="numpy", boundscheck=False)
# Code that tests for NaN and infinity is compiled without fastmath, on its own (not inlined at Numba level),
# and tests the exponent bits: once LLVM inlines it into a fastmath kernel, it may assume that values made
# by fastmath arithmetic are never NaN and fold a floating-point test away (measured: a NaN chain state passed
# `not abs(x) <= limit`).
CAREFUL = dict(error_model="numpy", boundscheck=False)
_EXPONENT = 0x7FF0000000000000  # all ones in a float64's exponent: inf or NaN
_MAGNITUDE = 0x7FFFFFFFFFFFFFFF  # a float64's bits but its sign


@njit(inline="always", **CAREFUL)
def _finite(bits, i):
    """Whether the float64 whose int64 view is bits[i] is finite."""
    return (bits[i] & _EXPONENT) != _EXPONENT

OK, BLEW_UP, UNDERFLOW = 0, 1, 2  # a member's status
DEFAULT_BLOWUP_FACTOR = 1e6  # a member fails when its state outgrows its start by this factor


@njit(**CAREFUL)
def _check_members(work, first, count, B, j0, limit, status, failure_time, t, step_row=-1):
    """Fail, at time t (s), each running member of a block whose state rows [first, first + count) hold a value
    that is not finite or exceeds its limit: status BLEW_UP, state NaN, and (adaptive kernels) step 0 in row
    step_row, so it takes no more steps. Returns how many members still run."""
    bits = work.view(np.int64)
    limit_bits = limit.view(np.int64)
    running = 0
    for j in range(B):
        if status[j0 + j] != OK:
            continue
        largest = 0  # bits of the largest |value|: for floats >= 0 bits order as values do, inf and NaN on top
        for r in range(first, first + count):
            largest = max(largest, bits[r * B + j] & _MAGNITUDE)
        if largest < _EXPONENT and largest <= limit_bits[j0 + j]:
            running += 1
        else:
            status[j0 + j] = BLEW_UP
            failure_time[j0 + j] = t
            for r in range(first, first + count):
                work[r * B + j] = np.nan
            if step_row >= 0:
                work[step_row * B + j] = 0.0
    return running


@njit(inline="always", **FAST)
def _fill_failed(samples, first_save, block):
    """NaN for the samples from first_save on of a block whose members have all failed."""
    samples[first_save:, block] = np.nan


@njit(inline="always", **FAST)
def _rows_in(work, row, source, first, count, B):
    """Rows first .. first + count - 1 of a block's (rows, B) array into the work array from `row` on."""
    for i in range(count):
        for j in range(B):
            work[(row + i) * B + j] = source[first + i, j]


@njit(inline="always", **FAST)
def _rows_out(work, row, target, first, count, B):
    """Work rows row .. row + count - 1 into rows first .. first + count - 1 of a block's (rows, B) array."""
    for i in range(count):
        for j in range(B):
            target[first + i, j] = work[(row + i) * B + j]


@njit(inline="always", **FAST)
def _load_top_block(state0, rate, block, samples, rows):
    """A top block's work array (rows x BLOCK): rates w1, w2, w3, then p, r1, r3; also its first sample."""
    work = np.zeros(rows * BLOCK)
    _rows_in(work, 0, state0[block], 0, 3, BLOCK)
    _rows_in(work, 3, rate[block], 0, 3, BLOCK)
    _rows_out(work, 0, samples[0, block], 0, 3, BLOCK)
    return work


def _method_constants(method: Method):
    """A method's data as plain tuples for a kernel closure (unused parts get placeholders).

    Returns (runge_kutta, stages, a (stages x stages, flat), b, entries, pieces, fractions).
    """
    if method.tableau is not None:
        t = method.tableau
        return True, t.stages, t.square_a(), tuple(float(x) for x in t.b), 1, (0,), (0.0,)
    sequence = method.splitting.sequence
    return (False, 1, (0.0,), (0.0,), len(sequence),
            tuple(p for p, _ in sequence), tuple(float(f) for _, f in sequence))


def _top_kernel(method: Method):
    """Top kernel for an explicit Runge-Kutta tableau or a drag/rotation splitting.

    Work rows: w1, w2, w3, p, r1, r3, then either the stage slopes k[s, c] at
    row 6 + 3 s + c (Runge-Kutta) or the drag factors of sequence entry e at
    rows 6 + 2 e, 7 + 2 e (splitting). Stage and sequence loops have constant
    trip counts, so LLVM unrolls them, folds the method's coefficients and
    drops zero terms: a generated rk4 runs as fast as a hand-written one.
    """
    runge_kutta, S, a, b, E, pieces, fractions = _method_constants(method)
    rows = 6 + (3 * S if runge_kutta else 2 * E)

    @njit(parallel=True, cache=True, **FAST)
    def kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time):
        """state0 (blocks, 3, BLOCK), rate (blocks, 3, BLOCK), limit (M,) -> samples (n_save, blocks, 3, BLOCK),
        status (M,), failure_time (M,) (s; set only where a member fails); M = blocks x BLOCK."""
        n_save = samples.shape[0]
        for block in prange(state0.shape[0]):
            j0 = block * BLOCK
            work = _load_top_block(state0, rate, block, samples, rows)
            _check_members(work, 0, 3, BLOCK, j0, limit, status, failure_time, 0.0)  # a non-finite start
            if not runge_kutta:
                for e in range(E):
                    if pieces[e] == DRAG:
                        for j in range(BLOCK):
                            work[(6 + 2 * e) * BLOCK + j] = top.drag_decay(work[4 * BLOCK + j], h * fractions[e])
                            work[(7 + 2 * e) * BLOCK + j] = top.drag_decay(work[5 * BLOCK + j], h * fractions[e])
            for i in range(1, n_save):
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
                                for r in range(S):
                                    ha = h * a[s * S + r]
                                    z1 += ha * work[(6 + 3 * r) * BLOCK + j]
                                    z2 += ha * work[(7 + 3 * r) * BLOCK + j]
                                    z3 += ha * work[(8 + 3 * r) * BLOCK + j]
                                d1, d2, d3 = top.rhs(z1, z2, z3, p, r1, r3)
                                work[(6 + 3 * s) * BLOCK + j] = d1
                                work[(7 + 3 * s) * BLOCK + j] = d2
                                work[(8 + 3 * s) * BLOCK + j] = d3
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
                                    y1, y2, y3 = top.rotate(y1, y2, y3, p, h * fractions[e])
                        work[j] = y1
                        work[BLOCK + j] = y2
                        work[2 * BLOCK + j] = y3
                running = _check_members(work, 0, 3, BLOCK, j0, limit, status, failure_time, i * steps_per_save * h)
                _rows_out(work, 0, samples[i, block], 0, 3, BLOCK)
                if running == 0:
                    _fill_failed(samples, i + 1, block)
                    break

    return kernel


def _adaptive_constants(method: Method):
    """An adaptive method's tableau and controller as plain constants for a kernel closure."""
    t, control = method.tableau, method.control
    assert t.fsal and t.error is not None, "adaptive kernels need an FSAL embedded pair"
    return (t.stages, t.square_a(), tuple(float(x) for x in t.error), control.alpha, control.beta, control.safety,
            control.min_factor, control.max_factor)


# Rows of an adaptive kernel's per-member control block (after the scene's rows), and of `counts`.
H, TIME, STEP, ERR, ERR_PREVIOUS, REJECTED_LAST, RTOL, ATOL = range(8)
CONTROL_ROWS = 8
ACCEPTED, REJECTED, RHS_EVALS = range(3)


@njit(**CAREFUL)
def _control_step(work, c0, B, target, counts, j0, status, failure_time, new_stages, alpha, beta, safety,
                  min_factor, max_factor):
    """After a trial step of every member in a block: accept or reject each and choose its next step.

    A trial step costs `new_stages` right-hand-side evaluations (an FSAL pair reuses its last stage).
    A trial step whose error is not a number is rejected like one with a large error.

    Afterwards ERR is -1 for members that had no step to take, -2 for members
    whose step underflowed (they stop: H = 0, status UNDERFLOW at their
    time), and REJECTED_LAST is 0 for members whose step was accepted; the
    caller moves those to their new state.
    """
    bits = work.view(np.int64)
    for j in range(B):
        step = work[(c0 + STEP) * B + j]
        if step <= 0.0:
            work[(c0 + ERR) * B + j] = -1.0  # nothing to do: mark as not accepted
            continue
        finite = _finite(bits, (c0 + ERR) * B + j)
        err = work[(c0 + ERR) * B + j]
        counts[RHS_EVALS, j0 + j] += new_stages
        if finite and err <= 1.0:
            factor = safety * max(err, 1e-10) ** -alpha * work[(c0 + ERR_PREVIOUS) * B + j] ** beta
            if work[(c0 + REJECTED_LAST) * B + j] > 0.0:
                factor = min(factor, 1.0)
            factor = min(max_factor, max(min_factor, factor))
            remaining = target - work[(c0 + TIME) * B + j]
            work[(c0 + TIME) * B + j] = target if step >= remaining else work[(c0 + TIME) * B + j] + step
            # A step clipped to land on a saved time does not shrink the next one.
            work[(c0 + H) * B + j] = max(step * factor, work[(c0 + H) * B + j] if step >= remaining else 0.0)
            work[(c0 + ERR_PREVIOUS) * B + j] = max(err, 1e-4)
            work[(c0 + REJECTED_LAST) * B + j] = 0.0
            counts[ACCEPTED, j0 + j] += 1.0
        else:
            h = step * max(min_factor, safety * err ** -alpha) if finite else step * min_factor
            if h <= 1e-14 * target:  # the step underflowed: give up
                h = 0.0
                work[(c0 + ERR) * B + j] = -2.0
                status[j0 + j] = UNDERFLOW
                failure_time[j0 + j] = work[(c0 + TIME) * B + j]
            work[(c0 + H) * B + j] = h
            work[(c0 + REJECTED_LAST) * B + j] = 1.0
            counts[REJECTED, j0 + j] += 1.0


@njit(inline="always", **FAST)
def _first_step(size, slope, save_dt):
    """Hairer's first guess from |y| and |y'| in units of the tolerance: 1% of their ratio, at most save_dt."""
    return min(0.01 * size / slope if size > 1e-5 and slope > 1e-5 else 1e-6, save_dt)


@njit(inline="always", **FAST)
def _trial_steps(work, c0, B, target):
    """Each member's next trial step (STEP), clipped to land on `target`; 0 for members there. Returns how many move."""
    left = 0
    for j in range(B):
        remaining = target - work[(c0 + TIME) * B + j]
        step = min(work[(c0 + H) * B + j], remaining) if remaining > 0.0 else 0.0
        work[(c0 + STEP) * B + j] = step
        work[(c0 + ERR) * B + j] = 0.0
        left += step > 0.0
    return left


def _top_adaptive_kernel(method: Method):
    """Top kernel for an adaptive embedded pair: every member controls its own step.

    Work rows: w1, w2, w3, p, r1, r3, stage slopes k[s, c] at 6 + 3 s + c, the
    new state (3 rows), then the control rows (H, TIME, ...). A trial step runs
    for all members of a block at once, each with its own step, clipped so it
    lands exactly on the next saved time; members already there take no step.
    """
    S, a, e, alpha, beta, safety, min_factor, max_factor = _adaptive_constants(method)
    a_array = np.array(a)  # indexed by a loop variable: a constant array, not a tuple
    K = 6
    NEW = K + 3 * S
    C0 = NEW + 3
    rows = C0 + CONTROL_ROWS

    @njit(parallel=True, cache=True, **FAST)
    def kernel(state0, rate, control, save_dt, limit, samples, counts, status, failure_time):
        """state0, rate (blocks, 3, BLOCK); control (3, M): first step (s; <= 0: estimate it), rtol, atol;
        limit (M,) -> samples (n_save, blocks, 3, BLOCK), counts (3, M): accepted, rejected, right-hand-side
        evaluations; status (M,) and failure_time (M,; s, set only where a member fails)."""
        n_save = samples.shape[0]
        B = BLOCK
        for block in prange(state0.shape[0]):
            j0 = block * B
            work = _load_top_block(state0, rate, block, samples, rows)
            for j in range(B):
                y1, y2, y3 = work[j], work[B + j], work[2 * B + j]
                d1, d2, d3 = top.rhs(y1, y2, y3, work[3 * B + j], work[4 * B + j], work[5 * B + j])
                work[K * B + j], work[(K + 1) * B + j], work[(K + 2) * B + j] = d1, d2, d3
                rtol, atol = control[1, j0 + j], control[2, j0 + j]
                work[(C0 + RTOL) * B + j], work[(C0 + ATOL) * B + j] = rtol, atol
                work[(C0 + ERR_PREVIOUS) * B + j] = 1e-4
                h = control[0, j0 + j]
                if h <= 0.0:
                    scale = atol + rtol * max(abs(y1), abs(y2), abs(y3))
                    h = _first_step(max(abs(y1), abs(y2), abs(y3)) / scale, max(abs(d1), abs(d2), abs(d3)) / scale,
                                    save_dt)
                work[(C0 + H) * B + j] = h
                counts[RHS_EVALS, j0 + j] = 1.0
            _check_members(work, 0, 3, B, j0, limit, status, failure_time, 0.0, C0 + H)  # a non-finite start
            for i in range(1, n_save):
                target = i * save_dt
                while _trial_steps(work, C0, B, target):
                    for s in range(1, S):  # stages outside, members inside, as in the chain kernels
                        for j in range(B):
                            h = work[(C0 + STEP) * B + j]
                            z1, z2, z3 = work[j], work[B + j], work[2 * B + j]
                            for r in range(S):  # a is zero from column s on
                                ha = h * a_array[s * S + r]
                                z1 += ha * work[(K + 3 * r) * B + j]
                                z2 += ha * work[(K + 3 * r + 1) * B + j]
                                z3 += ha * work[(K + 3 * r + 2) * B + j]
                            d1, d2, d3 = top.rhs(z1, z2, z3, work[3 * B + j], work[4 * B + j], work[5 * B + j])
                            work[(K + 3 * s) * B + j] = d1
                            work[(K + 3 * s + 1) * B + j] = d2
                            work[(K + 3 * s + 2) * B + j] = d3
                            work[NEW * B + j], work[(NEW + 1) * B + j], work[(NEW + 2) * B + j] = z1, z2, z3
                    for j in range(B):
                        # FSAL: the last stage was evaluated at the new state NEW
                        h = work[(C0 + STEP) * B + j]
                        y1, y2, y3 = work[j], work[B + j], work[2 * B + j]
                        z1, z2, z3 = work[NEW * B + j], work[(NEW + 1) * B + j], work[(NEW + 2) * B + j]
                        e1, e2, e3 = 0.0, 0.0, 0.0
                        for s in range(S):
                            e1 += e[s] * work[(K + 3 * s) * B + j]
                            e2 += e[s] * work[(K + 3 * s + 1) * B + j]
                            e3 += e[s] * work[(K + 3 * s + 2) * B + j]
                        rtol, atol = work[(C0 + RTOL) * B + j], work[(C0 + ATOL) * B + j]
                        q1 = h * e1 / (atol + rtol * max(abs(y1), abs(z1)))
                        q2 = h * e2 / (atol + rtol * max(abs(y2), abs(z2)))
                        q3 = h * e3 / (atol + rtol * max(abs(y3), abs(z3)))
                        work[(C0 + ERR) * B + j] = math.sqrt((q1 * q1 + q2 * q2 + q3 * q3) / 3.0)
                    _control_step(work, C0, B, target, counts, j0, status, failure_time, S - 1, alpha, beta, safety,
                                  min_factor, max_factor)
                    for j in range(B):
                        if work[(C0 + REJECTED_LAST) * B + j] == 0.0 and work[(C0 + ERR) * B + j] >= 0.0:
                            for c in range(3):
                                work[c * B + j] = work[(NEW + c) * B + j]
                                work[(K + c) * B + j] = work[(K + 3 * (S - 1) + c) * B + j]
                        elif work[(C0 + ERR) * B + j] == -2.0:
                            for c in range(3):
                                work[c * B + j] = np.nan
                running = _check_members(work, 0, 3, B, j0, limit, status, failure_time, target, C0 + H)
                _rows_out(work, 0, samples[i, block], 0, 3, B)
                if running == 0:
                    _fill_failed(samples, i + 1, block)
                    break

    return kernel


def chain_block(n: int) -> int:
    """Members per block for a chain of n masses.

    From 16 masses on, a block is 8 members: each row is one 64-byte line (one
    AVX-512 vector), so a row update is a single vector operation. Shorter
    chains ran 2x slower in 8-member blocks than in 64-member ones (measured
    side by side; our guess is too little independent work per step).
    """
    return 64 if n < 16 else 8


# Chain work arrays (B members a row) start with the rows X (n + 2: ghost, masses 1..n, ghost), V (n),
# CL and CR (n each). The helpers below take n, B and the rows as arguments instead of closing over them:
# a kernel closure that holds other compiled functions pickles differently in every process, so Numba's
# disk cache never matches it. Inlined into a kernel, the arguments are the kernel's constants again.

@njit(inline="always", **FAST)
def _set_ghosts(work, x, n, B, periodic):
    """Ring: the ghost sites of the positions at row x copy masses n and 1; walls and free ends keep 0."""
    if periodic:
        for j in range(B):
            work[x * B + j] = work[(x + n) * B + j]
            work[(x + n + 1) * B + j] = work[(x + 1) * B + j]


@njit(inline="always", **FAST)
def _store_chain_sample(work, samples, save, block, n, B):
    _rows_out(work, 1, samples[save, block], 0, n, B)
    _rows_out(work, n + 2, samples[save, block], n, n, B)


@njit(inline="always", **FAST)
def _load_chain_block(state0, rate, block, samples, n, B, rows, periodic):
    """A block's work array (rows x B) with its state and parameters (CL and CR follow each other); also its
    first sample."""
    work = np.zeros(rows * B)
    _rows_in(work, 1, state0[block], 0, n, B)
    _rows_in(work, n + 2, state0[block], n, n, B)
    _rows_in(work, 2 * n + 2, rate[block], 0, 2 * n, B)
    _store_chain_sample(work, samples, 0, block, n, B)
    _set_ghosts(work, 0, n, B, periodic)
    return work


@njit(inline="always", **FAST)
def _chain_saved(work, samples, save, block, limit, status, failure_time, t, step_row, n, B):
    """End of a save interval at time t (s): fail the members that blew up, store sample `save`; when no member
    of the block runs any more, fill its later samples with NaN and return True (the block is done)."""
    running = _check_members(work, 1, 2 * n + 1, B, block * B, limit, status, failure_time, t, step_row)
    _store_chain_sample(work, samples, save, block, n, B)
    if running == 0:
        _fill_failed(samples, save + 1, block)
    return running == 0


@njit(inline="always", **FAST)
def _chain_acceleration(work, x, i, j, n, B):
    """Acceleration (m s-2) of mass i + 1 of member j, from the positions at row x (with ghosts)."""
    CL, CR = 2 * n + 2, 3 * n + 2
    return chain.acceleration(work[(x + i) * B + j], work[(x + 1 + i) * B + j], work[(x + 2 + i) * B + j],
                              work[(CL + i) * B + j], work[(CR + i) * B + j])


@njit(inline="always", **FAST)
def _chain_slopes(work, zx, zv, kx, kv, n, B):
    """A stage's slopes: velocities from row zv into row kx, accelerations from row zx into row kv."""
    for i in range(n):
        for j in range(B):
            work[(kx + i) * B + j] = work[(zv + i) * B + j]
            work[(kv + i) * B + j] = _chain_acceleration(work, zx, i, j, n, B)


@njit(inline="always", **FAST)
def _stage_sums(work, weights, S, KX, KV, i, j, n, B):
    """sum_s weights[s] K_s for mass i + 1 of member j: its x part and its v part."""
    dx = 0.0
    dv = 0.0
    for s in range(S):
        dx += weights[s] * work[(KX + s * n + i) * B + j]
        dv += weights[s] * work[(KV + s * n + i) * B + j]
    return dx, dv


@njit(inline="always", **FAST)
def _chain_stage(work, s, S, a, h, step_row, rows, n, B, periodic):
    """Runge-Kutta stage s: its state Z = Y + sum_r h a[s, r] K_r into rows ZX, ZV, then its slopes into KX_s,
    KV_s. rows = (X, V, ZX, ZV, KX, KV) as in _chain_kernel; the step is h, or each member's own from row
    step_row when step_row >= 0 (adaptive kernels); a is the flat stages x stages tableau, zero from column s.
    """
    X, V, ZX, ZV, KX, KV = rows
    for i in range(n):
        for j in range(B):
            hj = work[step_row * B + j] if step_row >= 0 else h
            zx = work[(X + 1 + i) * B + j]
            zv = work[(V + i) * B + j]
            for r in range(S):
                ha = hj * a[s * S + r]
                zx += ha * work[(KX + r * n + i) * B + j]
                zv += ha * work[(KV + r * n + i) * B + j]
            work[(ZX + 1 + i) * B + j] = zx
            work[(ZV + i) * B + j] = zv
    _set_ghosts(work, ZX, n, B, periodic)
    _chain_slopes(work, ZX, ZV, KX + s * n, KV + s * n, n, B)


@njit(inline="always", **FAST)
def _kick(work, tau, lo, hi, n, B, T):
    """Kick masses lo + 1 .. hi (0 <= hi - lo <= T): v += tau (s) times their acceleration."""
    w = work[lo * B:]  # rows from lo on, indexed from a loop of constant trip count T (see _chain_kernel)
    for i in range(T):
        if i >= hi - lo:
            break
        for j in range(B):
            w[(n + 2 + i) * B + j] += tau * _chain_acceleration(w, 0, i, j, n, B)


@njit(inline="always", **FAST)
def _drift(work, tau, lo, hi, n, B, T):
    """Drift masses lo + 1 .. hi (0 <= hi - lo <= T): x += tau (s) times their velocity."""
    w = work[lo * B:]
    for i in range(T):
        if i >= hi - lo:
            break
        for j in range(B):
            w[(1 + i) * B + j] += tau * w[(n + 2 + i) * B + j]


@njit(**FAST)
def _splitting_schedule(pieces, fractions, h, steps_per_save, chunk):
    """The pieces of one save interval of steps h (s): kinds (KICK or DRIFT), taus (s), and lags.

    Where a step ends with the piece the next begins with (verlet: a half
    kick), the two merge into one. lags[p] is how many masses piece p runs
    behind the first piece of its chunk (pieces in chunks of `chunk`): one
    more at each change between kick and drift.
    """
    E = len(pieces)
    merge = E > 1 and pieces[0] == pieces[E - 1]
    kinds = np.empty(E * steps_per_save, np.int64)
    taus = np.empty(E * steps_per_save)
    count = 0
    for step in range(steps_per_save):
        for e in range(E):
            if merge and e == 0 and step > 0:
                continue  # done by the previous step's last piece
            tau = h * fractions[e]
            if merge and e == E - 1 and step < steps_per_save - 1:
                tau += h * fractions[0]
            kinds[count] = pieces[e]
            taus[count] = tau
            count += 1
    lags = np.zeros(count, np.int64)
    for p in range(count):
        if p % chunk:
            lags[p] = lags[p - 1] + (kinds[p] != kinds[p - 1])
    return kinds[:count], taus[:count], lags


def _chain_kernel(method: Method, n: int, periodic: bool):
    """Chain kernel for n masses: a kick/drift splitting or an explicit Runge-Kutta tableau.

    Work rows (B = chain_block(n) members each): X (n + 2: ghost, masses
    1..n, ghost), V (n), then CL and CR (n each: the springs' constants left
    and right of each mass over its mass, see chain.inputs); Runge-Kutta adds
    the stage state ZX (n + 2), ZV (n) and slopes KX, KV (stages x n each).
    Forces come from neighbours only: O(n) per step.

    A long chain's rows outgrow the L1 cache, so its splitting kernel runs
    TILE_PIECES pieces (kicks and drifts) at once over tiles of TILE_ROWS
    masses, each piece one mass behind the piece before it where kick and
    drift alternate (a wavefront): every mass still sees its neighbours as
    the one-piece-at-a-time order has them, so results are bit for bit the
    same. A ring's ghost masses need every piece to finish first, so rings
    run one piece at a time. Kick and drift index rows from a loop of
    constant trip count: with a variable start, Numba's negative-index
    wraparound stays in the loop and LLVM does not vectorize it.
    """
    B = chain_block(n)
    X, V = 0, n + 2
    CL = V + n
    CR = CL + n
    runge_kutta, S, a, b, E, pieces, fractions = _method_constants(method)
    tiled = not periodic and n > 2 * TILE_ROWS
    ZX = CR + n
    ZV = ZX + n + 2
    KX = ZV + n
    KV = KX + S * n
    rows = KV + S * n if runge_kutta else CR + n
    stage_rows = (X, V, ZX, ZV, KX, KV)

    @njit(parallel=True, cache=True, **FAST)
    def splitting_kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time):
        """state0 (blocks, 2n, B), rate (blocks, 2n, B), limit (M,) -> samples (n_save, blocks, 2n, B),
        status (M,), failure_time (M,) (s; set only where a member fails); M = blocks x B."""
        kinds, taus, lags = _splitting_schedule(pieces, fractions, h, steps_per_save, TILE_PIECES)
        count = len(kinds)
        for block in prange(state0.shape[0]):
            j0 = block * B
            work = _load_chain_block(state0, rate, block, samples, n, B, rows, periodic)
            _check_members(work, X + 1, 2 * n + 1, B, j0, limit, status, failure_time, 0.0)  # a non-finite start
            for save in range(1, samples.shape[0]):
                if tiled:
                    for c0 in range(0, count, TILE_PIECES):
                        c1 = min(c0 + TILE_PIECES, count)
                        for t0 in range(0, n + lags[c1 - 1], TILE_ROWS):
                            for p in range(c0, c1):
                                lo = max(t0 - lags[p], 0)
                                hi = min(t0 + TILE_ROWS - lags[p], n)
                                if kinds[p] == KICK:
                                    _kick(work, taus[p], lo, hi, n, B, TILE_ROWS)
                                else:
                                    _drift(work, taus[p], lo, hi, n, B, TILE_ROWS)
                else:
                    for p in range(count):
                        if kinds[p] == KICK:
                            _kick(work, taus[p], 0, n, n, B, n)
                        else:
                            _drift(work, taus[p], 0, n, n, B, n)
                            _set_ghosts(work, X, n, B, periodic)
                if _chain_saved(work, samples, save, block, limit, status, failure_time, save * steps_per_save * h, -1,
                                n, B):
                    break

    @njit(parallel=True, cache=True, **FAST)
    def runge_kutta_kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time):
        """As splitting_kernel."""
        for block in prange(state0.shape[0]):
            j0 = block * B
            work = _load_chain_block(state0, rate, block, samples, n, B, rows, periodic)
            _check_members(work, X + 1, 2 * n + 1, B, j0, limit, status, failure_time, 0.0)  # a non-finite start
            for save in range(1, samples.shape[0]):
                for _ in range(steps_per_save):
                    for s in range(S):
                        _chain_stage(work, s, S, a, h, -1, stage_rows, n, B, periodic)
                    for i in range(n):
                        for j in range(B):
                            dx, dv = _stage_sums(work, b, S, KX, KV, i, j, n, B)
                            work[(X + 1 + i) * B + j] += h * dx
                            work[(V + i) * B + j] += h * dv
                if _chain_saved(work, samples, save, block, limit, status, failure_time, save * steps_per_save * h, -1,
                                n, B):
                    break

    return runge_kutta_kernel if runge_kutta else splitting_kernel


def _chain_adaptive_kernel(method: Method, n: int, periodic: bool):
    """Chain kernel for an adaptive embedded pair; rows as in _chain_kernel's Runge-Kutta kernel, then control rows.

    As for the top, every member of a block takes its own trial step at once,
    clipped to land on the next saved time.
    """
    B = chain_block(n)
    X, V = 0, n + 2
    CL = V + n
    CR = CL + n
    ZX = CR + n
    ZV = ZX + n + 2
    S, a, e, alpha, beta, safety, min_factor, max_factor = _adaptive_constants(method)
    a_array = np.array(a)  # indexed by a loop variable: a constant array, not a tuple
    KX = ZV + n
    KV = KX + S * n
    C0 = KV + S * n
    rows = C0 + CONTROL_ROWS
    stage_rows = (X, V, ZX, ZV, KX, KV)
    @njit(parallel=True, cache=True, **FAST)
    def kernel(state0, rate, control, save_dt, limit, samples, counts, status, failure_time):
        """state0, rate (blocks, 2n, B); control (3, M): first step (s; <= 0: estimate it), rtol, atol;
        limit (M,) -> samples (n_save, blocks, 2n, B), counts (3, M): accepted, rejected, right-hand-side evaluations;
        status (M,) and failure_time (M,; s, set only where a member fails)."""
        for block in prange(state0.shape[0]):
            j0 = block * B
            work = _load_chain_block(state0, rate, block, samples, n, B, rows, periodic)
            _chain_slopes(work, X, V, KX, KV, n, B)
            for j in range(B):
                rtol, atol = control[1, j0 + j], control[2, j0 + j]
                work[(C0 + RTOL) * B + j], work[(C0 + ATOL) * B + j] = rtol, atol
                work[(C0 + ERR_PREVIOUS) * B + j] = 1e-4
                counts[RHS_EVALS, j0 + j] = 1.0
                h = control[0, j0 + j]
                if h <= 0.0:
                    size = 0.0
                    slope = 0.0
                    for i in range(n):
                        x, v = work[(X + 1 + i) * B + j], work[(V + i) * B + j]
                        size = max(size, abs(x) / (atol + rtol * abs(x)), abs(v) / (atol + rtol * abs(v)))
                        slope = max(slope, abs(v) / (atol + rtol * abs(x)),
                                    abs(work[(KV + i) * B + j]) / (atol + rtol * abs(v)))
                    h = _first_step(size, slope, save_dt)
                work[(C0 + H) * B + j] = h
            # a non-finite start
            _check_members(work, X + 1, 2 * n + 1, B, j0, limit, status, failure_time, 0.0, C0 + H)
            for save in range(1, samples.shape[0]):
                target = save * save_dt
                while _trial_steps(work, C0, B, target):
                    for s in range(1, S):  # FSAL: stage 0 is the last step's final stage
                        _chain_stage(work, s, S, a_array, 0.0, C0 + STEP, stage_rows, n, B, periodic)
                    # FSAL: the last stage state ZX, ZV is the new state; estimate its error
                    for i in range(n):
                        for j in range(B):
                            ex, ev = _stage_sums(work, e, S, KX, KV, i, j, n, B)
                            h = work[(C0 + STEP) * B + j]
                            rtol, atol = work[(C0 + RTOL) * B + j], work[(C0 + ATOL) * B + j]
                            qx = h * ex / (atol + rtol * max(abs(work[(X + 1 + i) * B + j]),
                                                             abs(work[(ZX + 1 + i) * B + j])))
                            qv = h * ev / (atol + rtol * max(abs(work[(V + i) * B + j]), abs(work[(ZV + i) * B + j])))
                            work[(C0 + ERR) * B + j] += qx * qx + qv * qv
                    for j in range(B):
                        work[(C0 + ERR) * B + j] = math.sqrt(work[(C0 + ERR) * B + j] / (2 * n))
                    _control_step(work, C0, B, target, counts, j0, status, failure_time, S - 1, alpha, beta, safety,
                                  min_factor, max_factor)
                    for i in range(n):
                        for j in range(B):
                            if work[(C0 + REJECTED_LAST) * B + j] == 0.0 and work[(C0 + ERR) * B + j] >= 0.0:
                                work[(X + 1 + i) * B + j] = work[(ZX + 1 + i) * B + j]
                                work[(V + i) * B + j] = work[(ZV + i) * B + j]
                                work[(KX + i) * B + j] = work[(KX + (S - 1) * n + i) * B + j]
                                work[(KV + i) * B + j] = work[(KV + (S - 1) * n + i) * B + j]
                            elif work[(C0 + ERR) * B + j] == -2.0:
                                work[(X + 1 + i) * B + j] = np.nan
                                work[(V + i) * B + j] = np.nan
                    _set_ghosts(work, X, n, B, periodic)
                if _chain_saved(work, samples, save, block, limit, status, failure_time, target, C0 + H, n, B):
                    break

    return kernel


@cache
def kernel_for(scene: str, method: str, key: tuple = ()):
    """The compiled (or cache-loaded) kernel of a stepping method; `key` from the scene's kernel_key."""
    m = METHODS[method]
    if scene == "top":
        return _top_adaptive_kernel(m) if m.adaptive else _top_kernel(m)
    return _chain_adaptive_kernel(m, *key) if m.adaptive else _chain_kernel(m, *key)


def block_size(scene: str, key: tuple) -> int:
    return BLOCK if scene == "top" else chain_block(key[0])


class Outcome(NamedTuple):
    """What a kernel call did, per member (the last axis)."""

    samples: np.ndarray  # (n_save, state, members); NaN from the first saved time at which a member had failed
    counts: np.ndarray  # (3, members) int64: steps accepted, steps rejected, right-hand-side evaluations
    status: np.ndarray  # (members,) int8: OK, BLEW_UP or UNDERFLOW
    failure_time: np.ndarray  # (members,) s: saved time at which a failure was seen (step time for UNDERFLOW); NaN if OK


def _limits(state0: np.ndarray, blowup_factor: float) -> np.ndarray:
    """Each member's largest allowed |state component|: blowup_factor times its largest at the start."""
    if math.isinf(blowup_factor):  # only non-finite states fail (inf * 0 would be NaN)
        return np.full(state0.shape[1], np.inf)
    return np.ascontiguousarray(blowup_factor * np.abs(state0).max(axis=0))


def integrate(scene, method: str, values: dict[str, np.ndarray], constants: dict, dt: float,
              steps_per_save: int, n_save: int, blowup_factor: float = DEFAULT_BLOWUP_FACTOR) -> Outcome:
    """Integrate the members described by `values` with a fixed step dt (s), saving every steps_per_save steps.

    A member fails when its state is not finite or a component outgrows
    blowup_factor times its largest component at the start (checked at
    every saved sample); it stops there and its later samples are NaN.
    A member's result depends only on its own values: never on how many
    members run with it, the chunking or the thread count.
    """
    m = METHODS[method]
    t = np.arange(n_save) * (steps_per_save * dt)
    if m.closed_form:
        samples = scene.exact(values, constants, t)
        n = samples.shape[2]
        return Outcome(samples, np.zeros((3, n), dtype=np.int64), np.zeros(n, dtype=np.int8), np.full(n, np.nan))
    state0, rate = scene.inputs(values, constants)
    key = scene.kernel_key(constants)
    n = state0.shape[1]
    limit = _limits(state0, blowup_factor)
    block = block_size(scene.NAME, key)
    state0, rate, limit = _padded((state0, rate, limit[None]), block)
    samples = np.empty((n_save, state0.shape[1] // block, state0.shape[0], block))
    status = np.zeros(state0.shape[1])
    failure_time = np.full(state0.shape[1], np.nan)
    kernel_for(scene.NAME, method, key)(blocked(state0, block), blocked(rate, block), float(dt), int(steps_per_save),
                                        limit[0], samples, status, failure_time)
    failure_time = failure_time[:n]
    steps = np.where(np.isnan(failure_time), steps_per_save * (n_save - 1), np.rint(failure_time / dt))
    counts = np.stack([steps, np.zeros(n), steps * m.evaluations_per_step(scene.NAME)]).astype(np.int64)
    return Outcome(unblocked(samples)[:, :, :n], counts, status[:n].astype(np.int8), failure_time)


def integrate_adaptive(scene, method: str, values: dict[str, np.ndarray], constants: dict, first_step: np.ndarray,
                       rtol: np.ndarray, atol: np.ndarray, save_dt: float, n_save: int,
                       blowup_factor: float = DEFAULT_BLOWUP_FACTOR) -> Outcome:
    """Integrate with an adaptive method, each member to its own rtol and atol (arrays over members).

    first_step (s, per member; NaN or <= 0: estimated) is only the first
    trial step. Samples fall exactly at the saved times. A member fails as
    in `integrate`, or with status UNDERFLOW when its step size underflows.
    """
    state0, rate = scene.inputs(values, constants)
    key = scene.kernel_key(constants)
    n = state0.shape[1]
    control = np.stack([np.nan_to_num(np.broadcast_to(x, (n,)).astype(float), nan=0.0)
                        for x in (first_step, rtol, atol)])
    limit = _limits(state0, blowup_factor)
    block = block_size(scene.NAME, key)
    state0, rate, control, limit = _padded((state0, rate, control, limit[None]), block)
    samples = np.empty((n_save, state0.shape[1] // block, state0.shape[0], block))
    counts = np.zeros((3, state0.shape[1]))
    status = np.zeros(state0.shape[1])
    failure_time = np.full(state0.shape[1], np.nan)
    kernel_for(scene.NAME, method, key)(blocked(state0, block), blocked(rate, block), control, float(save_dt), limit[0],
                                        samples, counts, status, failure_time)
    return Outcome(unblocked(samples)[:, :, :n], counts[:, :n].astype(np.int64), status[:n].astype(np.int8), failure_time[:n])


def _padded(arrays, block: int) -> tuple[np.ndarray, ...]:
    """(rows, members) arrays padded to a whole number of blocks with copies of the last member."""
    n = arrays[0].shape[1]
    extra = -(-n // block) * block - n
    return tuple(np.ascontiguousarray(np.concatenate([x, np.repeat(x[:, -1:], extra, axis=1)], axis=1) if extra else x)
                 for x in arrays)


def blocked(x: np.ndarray, block: int) -> np.ndarray:
    """A (rows, members) array, members a multiple of block, in a kernel's layout (members / block, rows, block)."""
    rows, members = x.shape
    return np.ascontiguousarray(x.reshape(rows, members // block, block).transpose(1, 0, 2))


def unblocked(samples: np.ndarray) -> np.ndarray:
    """A kernel's samples (n_save, blocks, rows, block) as (n_save, rows, members)."""
    n_save, blocks, rows, block = samples.shape
    return samples.transpose(0, 2, 1, 3).reshape(n_save, rows, blocks * block)


def prepare(scene: str, method: str, constants: dict) -> None:
    """Compile (or load from Numba's cache) the kernel of a stepping method."""
    if METHODS[method].closed_form:
        return
    module = SCENES[scene]
    key = module.kernel_key(constants)
    state_rows, rate_rows = module.kernel_rows(constants)
    block = block_size(scene, key)
    state0, rate = np.zeros((1, state_rows, block)), np.zeros((1, rate_rows, block))
    samples = np.empty((1, 1, state_rows, block))
    limit, status, failure_time = np.ones(block), np.zeros(block), np.zeros(block)
    if METHODS[method].adaptive:
        kernel_for(scene, method, key)(state0, rate, np.ones((3, block)), 1.0, limit, samples, np.zeros((3, block)),
                                       status, failure_time)
    else:
        kernel_for(scene, method, key)(state0, rate, 1.0, 1, limit, samples, status, failure_time)
