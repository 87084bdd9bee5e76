"""The chains' compiled kernels: forces from neighbours, ghost masses, kicks, drifts, tiles, and one kernel
per (method, n, ring).

Generic helpers (rows in and out, member checks, step control, the splitting
schedule) are in ensemble.engine.blocks.
"""
from __future__ import annotations

import math
from functools import cache
from pathlib import Path

import numpy as np
from numba import njit

from ...engine.blocks import (
    ATOL,
    CONTROL_ROWS,
    ERR,
    FAST,
    HELPERS,
    REJECTED_LAST,
    RTOL,
    STEP,
    H,
    Kernel,
    adaptive_constants,
    block_done,
    cache_line_array,
    check_members,
    control_step,
    counts_out,
    fill_failed,
    first_step,
    method_constants,
    rows_in,
    sample_out,
    select,
    splitting_schedule,
    start_control,
    trial_steps,
)
from ...methods import Method
from ...results import UNDERFLOWED
from .model import PIECES

TILE_ROWS, TILE_PIECES = 64, 32  # a long chain's splitting kernel: masses per tile, pieces per sweep
TILE_FROM_L1 = 1.5  # a splitting runs in tiles when a block's rows outgrow this many times the L1 data cache
KICK = PIECES.index("kick")


@njit(inline="always", fastmath=True, error_model="numpy")
def acceleration(x_left, x, x_right, c_left, c_right):
    """Acceleration (m/s^2) of a mass at x between neighbours x_left, x_right (m).

    c_left and c_right (1/s^2) are the springs' constants on each side over the mass.
    """
    return c_left * (x_left - x) + c_right * (x_right - x)


def block_size(constants: dict, method: Method) -> int:
    """Members per kernel block for `method` on a chain of n masses: 64 below 16 masses, except for an adaptive
    pair whose 64 members' work rows (20n + 15 for dopri5, control rows included) would outgrow the host's L1
    data cache (l1_data_bytes): then two SIMD vectors of this host, but never fewer than 16. From 16 masses on,
    64 for fixed-step Runge-Kutta, and for splittings and adaptive pairs two SIMD vectors (vector_doubles: 8
    members with AVX2, 16 with AVX-512), or one where a block's work rows (4n + 2 for a splitting) would
    outgrow the L1 data cache, but never fewer than 8 for a pair.

    A splitting member's arithmetic does not depend on its block: results are the same bits on every host. An
    adaptive pair's takes the same steps in every block, but its values can differ in the last places between
    blocks, so between hosts whose L1 caches or vectors differ from 3 masses on (LLVM's fast-math code
    differs). Measured with
    `python analysis/bench/bench_chain.py --n 16 64 128 --repeats 5 --steps 1000 --block B` (2^20 masses):

    - verlet on an AVX-512 host (AMD EPYC Zen 5, 48 KiB L1d; 2026-11-25, commit 0d9a3d3), blocks of 8, 16 and
      32: n = 16 1.37e10, 1.57e10 and 1.17e10 mass-steps/s; n = 64 1.52e10, 1.59e10 and 1.11e10; n = 128
      1.56e10, 1.19e10 and 6.9e9 (the C of ../shared/limit 9e9 to 1.1e10 in the same rounds). At n = 2 (`--n 2`),
      blocks of 16, 32 and 64 gave 4.0e9, 9.9e9 and 1.09e10. Compiled for AVX2 on that host
      (NUMBA_CPU_NAME=znver3), blocks of 4, 8 and 16 gave 8.3e9, 1.50e10 and 1.52e10 at n = 16, and 1.15e10,
      1.66e10 and 1.21e10 at n = 128.
    - per member-step at n = 16 on an AVX2 host (AMD EPYC Zen 3; `analysis/bench/bench_dopri5.py`'s chains), blocks
      of 4, 8, 16 and 64: rk4 8.96e-8, 1.62e-7, 1.06e-7 and 6.86e-8 s; dopri5, in the same run as rk4 at 64,
      6.4, 2.3, 2.8 and 6.0 times rk4 (and 5.5 at 32). That was before a pair's accepted steps moved in selects.
    - dopri5 over rk4 on the AVX-512 host, after that: see analysis/bench/README.md (bench_dopri5.py --chain-block B).
      Below 16 masses there, dopri5 in blocks of 64 and 16 took 8.3e-9 and 1.05e-8 s per member-step at n = 3,
      1.02e-8 and 1.17e-8 at n = 4, 1.35e-8 and 1.30e-8 at n = 5, 2.3e-8 and 1.75e-8 at n = 6, and 6.6e-8 and
      2.4e-8 at n = 12; 64 members' rows fill 0.8, 1.0, 1.2, 1.4 and 2.7 times its 48 KiB L1 cache. Compiled
      for AVX2, blocks of 16 beat blocks of 8 from n = 6 to 12.

    A tableau's stage sums gain from longer rows; an adaptive block's members wait for the block's slowest, and
    its seven stages' rows outgrow the L1 cache in long blocks.
    """
    n = constants["n"]
    pair = 2 * vector_doubles()
    member_bytes = (_stage_rows(n, method.tableau.stages)[-1] + CONTROL_ROWS) * 8 if method.adaptive else 0
    if n < 16:
        return 64 if member_bytes * 64 <= l1_data_bytes() else max(pair, 16)
    if method.adaptive:
        return pair if member_bytes * pair <= l1_data_bytes() else max(pair // 2, 8)
    if method.tableau is not None:
        return 64
    return pair if (4 * n + 2) * pair * 8 <= l1_data_bytes() else pair // 2


@cache
def vector_doubles() -> int:
    """Doubles in one SIMD vector of this host's widest extension (LLVM's host features): 8 with AVX-512F,
    4 with AVX, else 2."""
    from llvmlite import binding

    features = binding.get_host_cpu_features()
    return 8 if features.get("avx512f") else 4 if features.get("avx") else 2


@cache
def l1_data_bytes(cpu: Path = Path("/sys/devices/system/cpu/cpu0/cache")) -> int:
    """Bytes of the first CPU's level 1 data cache (Linux sysfs: "48K"); 32 KiB where it cannot be read."""
    units = {"K": 1024, "M": 1024**2}
    for index in sorted(cpu.glob("index*")):
        try:
            level, kind, size = ((index / name).read_text().strip() for name in ("level", "type", "size"))
            if level == "1" and kind in ("Data", "Unified"):
                return int(size[:-1]) * units[size[-1]] if size[-1:] in units else int(size)
        except (OSError, ValueError):  # unreadable, or not in sysfs's form
            continue
    return 32 * 1024


def kernel(method: Method, constants: dict):
    """Kernel(function, work rows) of a stepping method (compiled or cache-loaded) for the run's n and boundary."""
    return _kernel(method, constants["n"], constants["boundary"] == "periodic")


@cache
def _kernel(method: Method, n: int, periodic: bool):
    return _adaptive_kernel(method, n, periodic) if method.adaptive else _fixed_kernel(method, n, periodic)


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
def _fill_halos(work, row, n, halo, B):
    """A tiled ring's rows from `row` on (one of X + 1, V, CL, CR) hold halo masses, its n masses, halo masses:
    the halos copy the masses at the ring's other end (mass n - halo + e before mass 1, mass e after mass n)."""
    for q in range(halo * B):
        work[row * B + q] = work[(row + n) * B + q]
        work[(row + halo + n) * B + q] = work[(row + halo) * B + q]


@njit(inline="always", **FAST)
def _refresh_halos(work, n, halo, B):
    """A tiled ring: its positions' and velocities' halos from its masses (nothing when halo is 0)."""
    m = n + 2 * halo
    if halo > 0:
        _fill_halos(work, 1, n, halo, B)
        _fill_halos(work, m + 2, n, halo, B)


@njit(inline="always", **FAST)
def _store_chain_sample(work, samples, save, block, n, halo, B):
    m = n + 2 * halo
    sample_out(work, 1 + halo, samples, save, block, 0, n, B)
    sample_out(work, m + 2 + halo, samples, save, block, n, n, B)


@njit(inline="always", **FAST)
def _load_chain_block(work, state0, rate, block, samples, n, halo, B, periodic):
    """Start a block's (zeroed) work array with its state and parameters; also its first sample. A tiled ring's
    rows hold n + 2 halo masses each, its own n between two halos (see _fixed_kernel)."""
    m = n + 2 * halo
    rows_in(work, 1 + halo, state0[block], 0, n, B)
    rows_in(work, m + 2 + halo, state0[block], n, n, B)
    rows_in(work, 2 * m + 2 + halo, rate[block], 0, n, B)
    rows_in(work, 3 * m + 2 + halo, rate[block], n, n, B)
    _store_chain_sample(work, samples, 0, block, n, halo, B)
    if halo > 0:
        _refresh_halos(work, n, halo, B)
        _fill_halos(work, 2 * m + 2, n, halo, B)
        _fill_halos(work, 3 * m + 2, n, halo, B)
    else:
        _set_ghosts(work, 0, n, B, periodic)


@njit(inline="always", **FAST)
def _fixed_start(work, works, state0, rate, block, samples, limit, status, failure_time, progress, start, n, halo,
                 B, periodic):
    """Copy a block's work array into the call's `work` (cache_line_array), and whether the block runs: a call
    at start 0 loads it from state0, a later one continues it unless every member has failed."""
    work[:] = works[block]
    if start == 0:
        _load_chain_block(work, state0, rate, block, samples, n, halo, B, periodic)
        m = n + 2 * halo
        check_members(work, 1, 2 * m + 1, B, block * B, limit, status, failure_time, 0.0)  # a non-finite start
        return True
    return not block_done(samples, status, progress, block, B)


@njit(inline="always", **FAST)
def _chain_saved(work, samples, save, block, limit, status, failure_time, progress, t, step_row, n, halo, B):
    """End of a save interval at time t (s): fail the members that blew up, store sample `save`; when no member
    of the block runs any more, fill its later samples with NaN and return True (the block is done). A tiled
    ring's halos are refreshed first, so the check sees its masses' values only."""
    _refresh_halos(work, n, halo, B)
    m = n + 2 * halo
    running = check_members(work, 1, 2 * m + 1, B, block * B, limit, status, failure_time, t, step_row)
    _store_chain_sample(work, samples, save, block, n, halo, B)
    if running == 0:
        fill_failed(samples, save + 1, block, B)
    progress[block] = samples.shape[1] - 1 if running == 0 else save
    return running == 0


@njit(inline="always", **FAST)
def _chain_acceleration(work, x, i, j, n, B):
    """Acceleration (m s-2) of mass i + 1 of member j, from the positions at row x (with ghosts)."""
    CL, CR = 2 * n + 2, 3 * n + 2
    return acceleration(work[(x + i) * B + j], work[(x + 1 + i) * B + j], work[(x + 2 + i) * B + j],
                              work[(CL + i) * B + j], work[(CR + i) * B + j])


@njit(inline="always", **FAST)
def _chain_slopes(work, zx, zv, kx, kv, n, B):
    """A stage's slopes: velocities from row zv into row kx, accelerations from row zx into row kv.

    One loop over the n x B values (mass i, member j at i B + j): a stage's rows kx, kv are known only at run
    time, and over a block's B members alone LLVM does not check them against the rows read, so it did not
    vectorize (a chain's dopri5 spent a third of its time here, scalar)."""
    for q in range(n * B):
        work[kx * B + q] = work[zv * B + q]
        work[kv * B + q] = _chain_acceleration(work, zx, 0, q, n, B)  # q = i B + j: mass i + 1, member j


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
    KV_s. rows = (X, V, ZX, ZV, KX, KV) as in _fixed_kernel; the step is h, or each member's own from row
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
def _kick(work, tau, lo, hi, n, B):
    """Kick masses lo + 1 .. hi: v += tau (s) times their acceleration."""
    w = work[lo * B:]  # rows from lo on, indexed from 0 (see _fixed_kernel)
    for q in range((hi - lo) * B):  # q = i B + j: mass lo + i + 1, member j
        w[(n + 2) * B + q] += tau * _chain_acceleration(w, 0, 0, q, n, B)


@njit(inline="always", **FAST)
def _drift(work, tau, lo, hi, n, B):
    """Drift masses lo + 1 .. hi: x += tau (s) times their velocity."""
    w = work[lo * B:]
    for q in range((hi - lo) * B):
        w[B + q] += tau * w[(n + 2) * B + q]


def tiles(n: int, B: int) -> bool:
    """Whether a splitting kernel runs a chain of n masses in blocks of B members in tiles (see _fixed_kernel):
    when a block's 4n + 2 rows outgrow TILE_FROM_L1 times the L1 data cache, and the chain is longer than two
    tiles (so a ring is longer than its halos). On the AVX-512 host (48 KiB L1d, blocks of 8) one piece at a
    time was faster at n = 200 and 256, tiles from n = 288 on: 1.70, 1.43 and 1.12 times the C verlet against
    1.22, 1.21 and 1.33 in tiles (analysis/bench/README.md)."""
    return n > 2 * TILE_ROWS and (4 * n + 2) * B * 8 > TILE_FROM_L1 * l1_data_bytes()


def ring_halo(method: Method) -> int:
    """Masses a long ring's rows hold beyond each end for a splitting `method`: the most kicks in one run of
    TILE_PIECES pieces (one mass each: how far a row end's wrong value travels before the halos are copied
    again)."""
    _, _, _, _, _, pieces, fractions = method_constants(method)
    kinds = splitting_schedule.py_func(pieces, fractions, 1.0, 2 * TILE_PIECES + 1, TILE_PIECES)[0]  # no compile
    return max(int(np.sum(kinds[c:c + TILE_PIECES] == KICK)) for c in range(0, len(kinds), TILE_PIECES))


def _stage_rows(n: int, stages: int) -> tuple[int, ...]:
    """The first rows of X, V, ZX, ZV, KX and KV in a Runge-Kutta kernel of `stages` stages (see _fixed_kernel; CL
    and CR lie between V and ZX), and the row after KV: where an adaptive kernel's control rows begin."""
    X, V = 0, n + 2
    ZX = V + 3 * n  # after V, CL and CR
    ZV = ZX + n + 2
    KX = ZV + n
    KV = KX + stages * n
    return X, V, ZX, ZV, KX, KV, KV + stages * n


def _fixed_kernel(method: Method, n: int, periodic: bool):
    """Chain kernel for n masses: a kick/drift splitting or an explicit Runge-Kutta tableau.

    Work rows (B = block_size({"n": n}, method) members each): X (n + 2: ghost, masses
    1..n, ghost), V (n), then CL and CR (n each: the springs' constants left
    and right of each mass over its mass, see model.inputs); in a tiled
    ring's rows, n + 2 halo masses stand where these have n (below).
    Runge-Kutta adds the stage state ZX (n + 2), ZV (n) and slopes KX, KV
    (stages x n each). Forces come from neighbours only: O(n) per step.

    A long chain's rows outgrow the L1 cache (tiles), so its splitting
    kernel runs TILE_PIECES pieces (kicks and drifts) at once over tiles of
    TILE_ROWS masses, each piece one mass behind the piece before it where
    kick and drift alternate (a wavefront): every mass still sees its
    neighbours as the one-piece-at-a-time order has them, so results are bit
    for bit the same. A ring's ends need each other's last piece, so a long
    ring's rows hold `halo` more masses on each side (ring_halo), copies of
    the masses at its other end made before each run of pieces: a wrong
    value at a row's end travels one mass a kick, so it never reaches the
    ring's own masses, which take the same bits as one piece at a time. A
    short ring copies its ghost masses after each drift. Kick and drift make
    one loop over their masses' values (mass i, member j at i B + j),
    indexed from 0 in a view of the work array: from a variable start,
    Numba's negative-index wraparound stays in the loop and LLVM does not
    vectorize it. As two loops (masses, then a block's B members, unrolled),
    LLVM on AVX-512 vectorized the loop over masses, with gathers: a tenth
    of the speed at n = 16 and 128.
    """
    B = block_size({"n": n}, method)
    runge_kutta, S, a, b, E, pieces, fractions = method_constants(method)
    tiled = not runge_kutta and tiles(n, B)
    halo = ring_halo(method) if tiled and periodic else 0
    m = n + 2 * halo  # masses in a row
    X, V, ZX, ZV, KX, KV, end = _stage_rows(m, S)
    rows = end if runge_kutta else ZX  # a splitting's rows end with CR
    stage_rows = (X, V, ZX, ZV, KX, KV)

    helpers = HELPERS  # in the kernel's cache key (blocks.HELPERS)

    @njit(nogil=True, cache=True, **FAST)
    def splitting_kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress,
                         works, start, first_block, end_block):
        """state0 (blocks, 2n, B), rate (blocks, 2n, B), limit (M,) -> samples (members, count, 2n),
        status (M,), failure_time (M,) (s; set only where a member fails); M = blocks x B."""
        helpers  # a closure variable, so in the cache key
        kinds, taus, lags = splitting_schedule(pieces, fractions, h, steps_per_save, TILE_PIECES)
        count = len(kinds)
        work = cache_line_array(works.shape[1])
        for block in range(first_block, end_block):
            running = _fixed_start(work, works, state0, rate, block, samples, limit, status, failure_time, progress,
                                   start, n, halo, B, periodic)
            if not running:
                continue
            for save in range(max(start, 1), start + samples.shape[1]):
                if tiled:
                    for c0 in range(0, count, TILE_PIECES):
                        c1 = min(c0 + TILE_PIECES, count)
                        _refresh_halos(work, n, halo, B)
                        for t0 in range(0, m + lags[c1 - 1], TILE_ROWS):
                            for p in range(c0, c1):
                                lo = max(t0 - lags[p], 0)
                                hi = min(t0 + TILE_ROWS - lags[p], m)
                                if kinds[p] == KICK:
                                    _kick(work, taus[p], lo, hi, m, B)
                                else:
                                    _drift(work, taus[p], lo, hi, m, B)
                else:
                    for p in range(count):
                        if kinds[p] == KICK:
                            _kick(work, taus[p], 0, n, n, B)
                        else:
                            _drift(work, taus[p], 0, n, n, B)
                            _set_ghosts(work, X, n, B, periodic)
                if _chain_saved(work, samples, save - start, block, limit, status, failure_time, progress,
                                save * steps_per_save * h, -1, n, halo, B):
                    break
            works[block] = work

    @njit(nogil=True, cache=True, **FAST)
    def runge_kutta_kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress,
                           works, start, first_block, end_block):
        """As splitting_kernel."""
        helpers  # a closure variable, so in the cache key
        work = cache_line_array(works.shape[1])
        for block in range(first_block, end_block):
            running = _fixed_start(work, works, state0, rate, block, samples, limit, status, failure_time, progress,
                                   start, n, 0, B, periodic)
            if not running:
                continue
            for save in range(max(start, 1), start + samples.shape[1]):
                for _ in range(steps_per_save):
                    for s in range(S):
                        _chain_stage(work, s, S, a, h, -1, stage_rows, n, B, periodic)
                    for i in range(n):
                        for j in range(B):
                            dx, dv = _stage_sums(work, b, S, KX, KV, i, j, n, B)
                            work[(X + 1 + i) * B + j] += h * dx
                            work[(V + i) * B + j] += h * dv
                if _chain_saved(work, samples, save - start, block, limit, status, failure_time, progress,
                                save * steps_per_save * h, -1, n, 0, B):
                    break
            works[block] = work

    return Kernel(runge_kutta_kernel if runge_kutta else splitting_kernel, rows)


@njit(inline="always", **FAST)
def _chain_accept(work, X, V, ZX, ZV, KX, KV, C0, S, n, B):
    """After control_step: members whose step was accepted move to the stage state ZX, ZV (its last slopes are the
    next step's first); members whose step underflowed become NaN. In selects for blocks of 16 or more, in
    branches for fewer: each form is the faster at its block, as AVX-512 and as AVX2 code (analysis/bench/README.md,
    `python analysis/bench/bench_dopri5.py --chain-block B`)."""
    last = S - 1
    for i in range(n):
        for j in range(B):
            err = work[(C0 + ERR) * B + j]
            accepted = (work[(C0 + REJECTED_LAST) * B + j] == 0.0) & (err >= 0.0)
            underflowed = err == UNDERFLOWED
            if B >= 16:
                x, v = work[(X + 1 + i) * B + j], work[(V + i) * B + j]
                work[(X + 1 + i) * B + j] = select(accepted, work[(ZX + 1 + i) * B + j], select(underflowed, np.nan, x))
                work[(V + i) * B + j] = select(accepted, work[(ZV + i) * B + j], select(underflowed, np.nan, v))
                work[(KX + i) * B + j] = select(accepted, work[(KX + last * n + i) * B + j], work[(KX + i) * B + j])
                work[(KV + i) * B + j] = select(accepted, work[(KV + last * n + i) * B + j], work[(KV + i) * B + j])
            elif accepted:
                work[(X + 1 + i) * B + j] = work[(ZX + 1 + i) * B + j]
                work[(V + i) * B + j] = work[(ZV + i) * B + j]
                work[(KX + i) * B + j] = work[(KX + last * n + i) * B + j]
                work[(KV + i) * B + j] = work[(KV + last * n + i) * B + j]
            elif underflowed:
                work[(X + 1 + i) * B + j] = np.nan
                work[(V + i) * B + j] = np.nan


def _adaptive_kernel(method: Method, n: int, periodic: bool):
    """Chain kernel for an adaptive embedded pair; rows as in _fixed_kernel's Runge-Kutta kernel, then control rows.

    As for the top, every member of a block takes its own trial step at once,
    clipped to land on the next saved time.
    """
    B = block_size({"n": n}, method)
    S, a, e, alpha, beta, safety, min_factor, max_factor = adaptive_constants(method)
    a_array = np.array(a)  # indexed by a loop variable: a constant array, not a tuple
    X, V, ZX, ZV, KX, KV, C0 = _stage_rows(n, S)
    rows = C0 + CONTROL_ROWS
    stage_rows = (X, V, ZX, ZV, KX, KV)
    helpers = HELPERS  # in the kernel's cache key (blocks.HELPERS)

    @njit(nogil=True, cache=True, **FAST)
    def kernel(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, progress,
               works, start, first_block, end_block):
        """state0, rate (blocks, 2n, B); control (3, M): first step (s; <= 0: estimate it), rtol, atol;
        limit (M,) -> samples (members, count, 2n), counts (3, M): accepted, rejected, right-hand-side evaluations;
        status (M,) and failure_time (M,; s, set only where a member fails)."""
        helpers  # a closure variable, so in the cache key
        work = cache_line_array(works.shape[1])
        for block in range(first_block, end_block):
            j0 = block * B
            work[:] = works[block]
            if start == 0:
                _load_chain_block(work, state0, rate, block, samples, n, 0, B, periodic)
                _chain_slopes(work, X, V, KX, KV, n, B)
                for j in range(B):
                    rtol, atol = control[1, j0 + j], control[2, j0 + j]
                    h = control[0, j0 + j]
                    if h <= 0.0:
                        size = 0.0
                        slope = 0.0
                        for i in range(n):
                            x, v = work[(X + 1 + i) * B + j], work[(V + i) * B + j]
                            size = max(size, abs(x) / (atol + rtol * abs(x)), abs(v) / (atol + rtol * abs(v)))
                            slope = max(slope, abs(v) / (atol + rtol * abs(x)),
                                        abs(work[(KV + i) * B + j]) / (atol + rtol * abs(v)))
                        h = first_step(size, slope, save_dt)
                    start_control(work, C0, B, j, rtol, atol, h)
                # a non-finite start
                check_members(work, X + 1, 2 * n + 1, B, j0, limit, status, failure_time, 0.0, C0 + H)
            elif block_done(samples, status, progress, block, B):
                continue
            for save in range(max(start, 1), start + samples.shape[1]):
                target = save * save_dt
                while trial_steps(work, C0, B, target):
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
                    control_step(work, C0, B, target, j0, status, failure_time, S - 1, alpha, beta, safety,
                                  min_factor, max_factor)
                    _chain_accept(work, X, V, ZX, ZV, KX, KV, C0, S, n, B)
                    _set_ghosts(work, X, n, B, periodic)
                if _chain_saved(work, samples, save - start, block, limit, status, failure_time, progress,
                                target, C0 + H, n, 0, B):
                    break
            counts_out(work, C0, B, counts, j0)
            works[block] = work

    return Kernel(kernel, rows)


BOUNDARIES = ("fixed", "free", "periodic")  # sample_energy's boundary codes


@njit(cache=True, nogil=True, error_model="numpy")
def sample_energy(samples, m, k, boundary):
    """model.energy compiled, sums taken mass by mass and spring by spring: 1/2 v.M.v + 1/2 x.K.x (J), shape
    (members, t), from member-major samples (members, t, 2n) of (x; v), masses m (members, n) kg and springs k
    (members, springs) N/m; boundary its index in BOUNDARIES. A run saving or measuring the energy computes it
    here (numpy's temporaries cost as much as the kernel)."""
    members, count, rows = samples.shape
    n, springs = rows // 2, k.shape[1]
    out = np.empty((members, count))
    for a in range(members):
        for i in range(count):
            kinetic, potential = 0.0, 0.0
            for s in range(n):
                kinetic += m[a, s] * samples[a, i, n + s] * samples[a, i, n + s]
            for s in range(springs):
                if boundary == 0:  # spring s joins mass s - 1 (or the left wall) and mass s (or the right wall)
                    stretch = (samples[a, i, s] if s < n else 0.0) - (samples[a, i, s - 1] if s > 0 else 0.0)
                else:  # free ends: masses s and s + 1; a ring: s and (s + 1) mod n
                    stretch = samples[a, i, (s + 1) % n] - samples[a, i, s]
                potential += k[a, s] * stretch * stretch
            out[a, i] = 0.5 * kinetic + 0.5 * potential
    return out
