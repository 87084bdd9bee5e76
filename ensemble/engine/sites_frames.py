"""The field-of-sites families as code: the CPU kernels of a scene whose member is n sites, each accelerated by its
two neighbours (ensemble.engine.sites holds the layout's rules, the helpers that do not call the scene, and the
kernel file's header).

A kernel's file binds the scene's `acceleration`, the sizes and the rows and calls one frame here; Numba inlines
it, so that the sizes, the rows and the method's coefficients are constants of the loop nest LLVM compiles.
sizes: (N sites, HALO sites beyond each end of a tiled ring's rows, B members per block, PERIODIC, M = N + 2 HALO
sites in a row, S stages); rows: the first rows (X, V, ZX, ZV, KX, KV, C0) of sites.stage_rows, C0 an adaptive
pair's control block. Row r of member j is at r B + j.
"""
from __future__ import annotations

import math

from numba import njit

from .blocks import (
    ATOL,
    ERR,
    FAST,
    RTOL,
    STEP,
    H,
    block_done,
    cache_line_array,
    check_members,
    copy_into,
    counts_out,
    first_step,
    start_control,
    trial_steps,
)
from .control import control_step
from .sites import (
    KICK,
    TILE_PIECES,
    TILE_ROWS,
    accept,
    drift,
    fixed_start,
    load_block,
    refresh_halos,
    saved,
    set_ghosts,
    splitting_schedule,
    stage_sums,
)


@njit(inline="always", **FAST)
def site_acceleration(acceleration, work, x, i, j, n, B):
    """Acceleration (m s-2) of site i + 1 of member j, from the positions at row x (with ghosts)."""
    CL, CR = 2 * n + 2, 3 * n + 2
    return acceleration(work[(x + i) * B + j], work[(x + 1 + i) * B + j], work[(x + 2 + i) * B + j],
                        work[(CL + i) * B + j], work[(CR + i) * B + j])


@njit(inline="always", **FAST)
def slopes(acceleration, work, zx, zv, kx, kv, n, B):
    """A stage's slopes: velocities from row zv into row kx, accelerations from row zx into row kv.

    One loop over the n x B values (site i, member j at i B + j): a stage's rows kx, kv are known only at run
    time, and over a block's B members alone LLVM does not check them against the rows read, so it did not
    vectorize (a chain's dopri5 spent a third of its time here, scalar)."""
    for q in range(n * B):
        work[kx * B + q] = work[zv * B + q]
        work[kv * B + q] = site_acceleration(acceleration, work, zx, 0, q, n, B)  # q = i B + j: site i + 1, member j


@njit(inline="always", **FAST)
def stage(acceleration, sizes, rows, work, s, a, h, step_row):
    """Runge-Kutta stage s: its state Z = Y + sum_r h a[s, r] K_r into rows ZX, ZV, then its slopes into KX_s,
    KV_s. The step is h, or each member's own from row step_row when step_row >= 0 (adaptive kernels); a is the
    flat stages x stages tableau, zero from column s."""
    N, _, B, PERIODIC, _, S = sizes
    X, V, ZX, ZV, KX, KV, _ = rows
    for i in range(N):
        for j in range(B):
            hj = work[step_row * B + j] if step_row >= 0 else h
            zx = work[(X + 1 + i) * B + j]
            zv = work[(V + i) * B + j]
            for r in range(S):
                ha = hj * a[s * S + r]
                zx += ha * work[(KX + r * N + i) * B + j]
                zv += ha * work[(KV + r * N + i) * B + j]
            work[(ZX + 1 + i) * B + j] = zx
            work[(ZV + i) * B + j] = zv
    set_ghosts(work, ZX, N, B, PERIODIC)
    slopes(acceleration, work, ZX, ZV, KX + s * N, KV + s * N, N, B)


@njit(inline="always", **FAST)
def kick(acceleration, work, tau, lo, hi, n, B):
    """Kick sites lo + 1 .. hi: v += tau (s) times their acceleration. One loop over their values (site i, member
    j at i B + j), indexed from 0 in a view of the work array: from a variable start, Numba's negative-index
    wraparound stays in the loop and LLVM does not vectorize it."""
    w = work[lo * B:]  # rows from lo on, indexed from 0
    for q in range((hi - lo) * B):  # q = i B + j: site lo + i + 1, member j
        w[(n + 2) * B + q] += tau * site_acceleration(acceleration, w, 0, 0, q, n, B)


@njit(inline="always", **FAST)
def _pieces(acceleration, sizes, rows, work, kinds, taus, lags, tiled):
    """One save interval's pieces (splitting_schedule's kinds, taus and lags) over a block: in tiles of TILE_ROWS
    sites, TILE_PIECES pieces at a time, each piece lagging the one before where kick and drift alternate (a
    wavefront: every site sees its neighbours as one piece at a time has them, so the bits are the same; a tiled
    ring's halos are refreshed before each run of pieces), or one piece at a time over the whole field."""
    N, HALO, B, PERIODIC, M, _ = sizes
    count = len(kinds)
    if tiled:
        for c0 in range(0, count, TILE_PIECES):
            c1 = min(c0 + TILE_PIECES, count)
            refresh_halos(work, N, HALO, B)
            for t0 in range(0, M + lags[c1 - 1], TILE_ROWS):
                for p in range(c0, c1):
                    lo = max(t0 - lags[p], 0)
                    hi = min(t0 + TILE_ROWS - lags[p], M)
                    if kinds[p] == KICK:
                        kick(acceleration, work, taus[p], lo, hi, M, B)
                    else:
                        drift(work, taus[p], lo, hi, M, B)
    else:
        for p in range(count):
            if kinds[p] == KICK:
                kick(acceleration, work, taus[p], 0, N, N, B)
            else:
                drift(work, taus[p], 0, N, N, B)
                set_ghosts(work, rows[0], N, B, PERIODIC)


@njit(inline="always", **FAST)
def splitting(acceleration, sizes, rows, sequence, fractions, tiled, state0, rate, h, steps_per_save, limit,
              samples, status, failure_time, progress, works, start, first_block, end_block):
    """A kick/drift splitting's kernel: sequence and fractions its piece numbers (KICK or drift) and fractions of
    the step; tiled: whether its pieces run in tiles (sites.tiles). Arguments after `tiled` as the kernel's."""
    N, HALO, B, PERIODIC, _, _ = sizes
    kinds, taus, lags = splitting_schedule(sequence, fractions, h, steps_per_save, TILE_PIECES)
    work = cache_line_array(works.shape[1])
    for block in range(first_block, end_block):
        if not fixed_start(work, works, state0, rate, block, samples, limit, status, failure_time, progress, start,
                           N, HALO, B, PERIODIC):
            continue
        for save in range(max(start, 1), start + samples.shape[1]):
            _pieces(acceleration, sizes, rows, work, kinds, taus, lags, tiled)
            if saved(work, samples, save - start, block, limit, status, failure_time, progress,
                     save * steps_per_save * h, -1, N, HALO, B):
                break
        copy_into(works[block], work)


@njit(inline="always", **FAST)
def runge_kutta(acceleration, sizes, rows, a, weights, state0, rate, h, steps_per_save, limit, samples, status,
                failure_time, progress, works, start, first_block, end_block):
    """An explicit Runge-Kutta method's kernel: a its tableau (S x S, flat), weights its b."""
    N, _, B, PERIODIC, _, S = sizes
    X, V, _, _, KX, KV, _ = rows
    work = cache_line_array(works.shape[1])
    for block in range(first_block, end_block):
        if not fixed_start(work, works, state0, rate, block, samples, limit, status, failure_time, progress, start,
                           N, 0, B, PERIODIC):
            continue
        for save in range(max(start, 1), start + samples.shape[1]):
            for _ in range(steps_per_save):
                for s in range(S):
                    stage(acceleration, sizes, rows, work, s, a, h, -1)
                for i in range(N):
                    for j in range(B):
                        dx, dv = stage_sums(work, weights, S, KX, KV, i, j, N, B)
                        work[(X + 1 + i) * B + j] += h * dx
                        work[(V + i) * B + j] += h * dv
            if saved(work, samples, save - start, block, limit, status, failure_time, progress,
                     save * steps_per_save * h, -1, N, 0, B):
                break
        copy_into(works[block], work)


@njit(inline="always", **FAST)
def _adaptive_start(acceleration, sizes, rows, work, control, save_dt, j0):
    """A block's first slopes, and each member's first trial step (control[0], or Hairer's guess where it is not
    positive) and tolerances into its control rows."""
    N, _, B, _, _, _ = sizes
    X, V, _, _, KX, KV, C0 = rows
    slopes(acceleration, work, X, V, KX, KV, N, B)
    for j in range(B):
        rtol, atol = control[1, j0 + j], control[2, j0 + j]
        h = control[0, j0 + j]
        if h <= 0.0:
            size = 0.0
            slope = 0.0
            for i in range(N):
                x, v = work[(X + 1 + i) * B + j], work[(V + i) * B + j]
                size = max(size, abs(x) / (atol + rtol * abs(x)), abs(v) / (atol + rtol * abs(v)))
                slope = max(slope, abs(v) / (atol + rtol * abs(x)),
                            abs(work[(KV + i) * B + j]) / (atol + rtol * abs(v)))
            h = first_step(size, slope, save_dt)
        start_control(work, C0, B, j, rtol, atol, h)


@njit(inline="always", **FAST)
def _error_norms(sizes, rows, work, error):
    """Each member's error norm of its trial step into its control row ERR: the RMS over positions and velocities
    of h sum_s error[s] k_s over atol + rtol max(|y|, |new|) (FSAL: the last stage state ZX, ZV is the new state)."""
    N, _, B, _, _, S = sizes
    X, V, ZX, ZV, KX, KV, C0 = rows
    for i in range(N):
        for j in range(B):
            ex, ev = stage_sums(work, error, S, KX, KV, i, j, N, B)
            h = work[(C0 + STEP) * B + j]
            rtol, atol = work[(C0 + RTOL) * B + j], work[(C0 + ATOL) * B + j]
            x, z = work[(X + 1 + i) * B + j], work[(ZX + 1 + i) * B + j]
            qx = h * ex / (atol + rtol * max(abs(x), abs(z)))
            v, z = work[(V + i) * B + j], work[(ZV + i) * B + j]
            qv = h * ev / (atol + rtol * max(abs(v), abs(z)))
            work[(C0 + ERR) * B + j] += qx * qx + qv * qv
    for j in range(B):
        work[(C0 + ERR) * B + j] = math.sqrt(work[(C0 + ERR) * B + j] / (2 * N))


@njit(inline="always", **FAST)
def adaptive(acceleration, sizes, rows, a, error, controller, state0, rate, control, save_dt, limit, samples, counts,
             status, failure_time, progress, works, start, first_block, end_block):
    """An embedded pair's kernel: every member of a block takes its own trial step at once, clipped to land on
    the next saved time. a: the tableau (S x S, flat, an array: indexed by a loop variable); error: b - b_hat;
    controller: alpha, beta, safety, min_factor, max_factor (control.control_step)."""
    N, _, B, PERIODIC, _, S = sizes
    X, V, ZX, ZV, KX, KV, C0 = rows
    alpha, beta, safety, min_factor, max_factor = controller
    work = cache_line_array(works.shape[1])
    for block in range(first_block, end_block):
        j0 = block * B
        copy_into(work, works[block])
        if start == 0:
            load_block(work, state0, rate, block, samples, N, 0, B, PERIODIC)
            _adaptive_start(acceleration, sizes, rows, work, control, save_dt, j0)
            # a non-finite start
            check_members(work, X + 1, 2 * N + 1, B, j0, limit, status, failure_time, 0.0, C0 + H)
        elif block_done(samples, status, progress, block, B):
            continue
        for save in range(max(start, 1), start + samples.shape[1]):
            target = save * save_dt
            while trial_steps(work, C0, B, target):
                for s in range(1, S):  # FSAL: stage 0 is the last step's final stage
                    stage(acceleration, sizes, rows, work, s, a, 0.0, C0 + STEP)
                _error_norms(sizes, rows, work, error)
                control_step(work, C0, B, target, j0, status, failure_time, S - 1, alpha, beta, safety, min_factor,
                             max_factor)
                accept(work, X, V, ZX, ZV, KX, KV, C0, S, N, B)
                set_ghosts(work, X, N, B, PERIODIC)
            if saved(work, samples, save - start, block, limit, status, failure_time, progress, target, C0 + H, N, 0,
                     B):
                break
        counts_out(work, C0, B, counts, j0)
        copy_into(works[block], work)
