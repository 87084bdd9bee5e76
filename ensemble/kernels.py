"""Parallel ensemble drivers: a scene's equations combined with a method.

Members run in blocks; prange goes over blocks and the innermost loop over the
members of a block, which LLVM vectorizes (see DESIGN.md). Each block keeps
everything a step touches in one work array at constant offsets: with a
single base pointer LLVM proves the rows disjoint and emits only the vector
loop (separate arrays add a runtime overlap check whose scalar fallback
rounds differently, so results would depend on heap addresses).

Kernels are generated per (scene, method, kernel key) by factories whose
closures capture the method's data as constants; Numba caches each on disk.
"""
from __future__ import annotations

from functools import cache

import numpy as np
from numba import njit, prange

from .methods import DRAG, KICK, METHODS, Method
from .scenes import SCENES, chain, top

BLOCK = 128  # members per block of the top kernels
FAST = dict(fastmath=True, error_model="numpy", boundscheck=False)


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
    def kernel(state0, rate, h, steps_per_save, samples):
        """state0 (3, M), rate (3, M) -> samples (n_save, 3, M); M a multiple of BLOCK."""
        n_save = samples.shape[0]
        for block in prange(state0.shape[1] // BLOCK):
            j0 = block * BLOCK
            j1 = j0 + BLOCK
            work = np.zeros(rows * BLOCK)
            for c in range(3):
                work[c * BLOCK:(c + 1) * BLOCK] = state0[c, j0:j1]
                work[(3 + c) * BLOCK:(4 + c) * BLOCK] = rate[c, j0:j1]
                samples[0, c, j0:j1] = state0[c, j0:j1]
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
                for c in range(3):
                    samples[i, c, j0:j1] = work[c * BLOCK:(c + 1) * BLOCK]

    return kernel


def chain_block(n: int) -> int:
    """Members per block for a chain of n masses.

    From 16 masses on, a block is 8 members: each row is one 64-byte line (one
    AVX-512 vector), so a row update is a single vector operation. Shorter
    chains ran 2x slower in 8-member blocks than in 64-member ones (measured
    side by side; our guess is too little independent work per step).
    """
    return 64 if n < 16 else 8


def _chain_kernel(method: Method, n: int, periodic: bool):
    """Chain kernel for n masses: a kick/drift splitting or an explicit Runge-Kutta tableau.

    Work rows (B = chain_block(n) members each): X (n + 2: ghost, masses
    1..n, ghost), V (n), then CL and CR (n each: the springs' constants left
    and right of each mass over its mass, see chain.inputs); Runge-Kutta adds
    the stage state ZX (n + 2), ZV (n) and slopes KX, KV (stages x n each).
    Forces come from neighbours only: O(n) per step.
    """
    B = chain_block(n)
    X, V = 0, n + 2
    CL = V + n
    CR = CL + n
    runge_kutta, S, a, b, E, pieces, fractions = _method_constants(method)
    # A splitting that starts and ends with the same piece (verlet: kick) merges
    # the end of one step with the start of the next inside a save interval.
    merge = E > 1 and pieces[0] == pieces[E - 1]
    ZX = CR + n
    ZV = ZX + n + 2
    KX = ZV + n
    KV = KX + S * n
    rows = KV + S * n if runge_kutta else CR + n

    @njit(inline="always", **FAST)
    def set_ghosts(work, x):
        """Ring: ghost sites copy masses n and 1; walls and free ends keep ghosts at 0."""
        if periodic:
            for j in range(B):
                work[x * B + j] = work[(x + n) * B + j]
                work[(x + n + 1) * B + j] = work[(x + 1) * B + j]

    @njit(inline="always", **FAST)
    def load_block(state0, rate, j0, samples):
        """A block's work array with its state and parameters; also its first sample."""
        work = np.zeros(rows * B)
        for i in range(n):
            work[(X + 1 + i) * B:(X + 2 + i) * B] = state0[i, j0:j0 + B]
            work[(V + i) * B:(V + 1 + i) * B] = state0[n + i, j0:j0 + B]
            work[(CL + i) * B:(CL + 1 + i) * B] = rate[i, j0:j0 + B]
            work[(CR + i) * B:(CR + 1 + i) * B] = rate[n + i, j0:j0 + B]
            samples[0, i, j0:j0 + B] = state0[i, j0:j0 + B]
            samples[0, n + i, j0:j0 + B] = state0[n + i, j0:j0 + B]
        set_ghosts(work, X)
        return work

    @njit(inline="always", **FAST)
    def store_sample(work, samples, save, j0):
        for i in range(n):
            samples[save, i, j0:j0 + B] = work[(X + 1 + i) * B:(X + 2 + i) * B]
            samples[save, n + i, j0:j0 + B] = work[(V + i) * B:(V + 1 + i) * B]

    @njit(parallel=True, cache=True, **FAST)
    def splitting_kernel(state0, rate, h, steps_per_save, samples):
        """state0 (2n, M), rate (2n, M) -> samples (n_save, 2n, M); M a multiple of B."""
        for block in prange(state0.shape[1] // B):
            j0 = block * B
            work = load_block(state0, rate, j0, samples)
            for save in range(1, samples.shape[0]):
                for step in range(steps_per_save):
                    for e in range(E):
                        tau = h * fractions[e]
                        if merge and e == 0 and step > 0:
                            continue  # done by the previous step's last piece
                        if merge and e == E - 1 and step < steps_per_save - 1:
                            tau += h * fractions[0]
                        if pieces[e] == KICK:
                            for i in range(n):
                                for j in range(B):
                                    work[(V + i) * B + j] += tau * chain.acceleration(
                                        work[(X + i) * B + j], work[(X + 1 + i) * B + j],
                                        work[(X + 2 + i) * B + j], work[(CL + i) * B + j],
                                        work[(CR + i) * B + j])
                        else:
                            for i in range(n):
                                for j in range(B):
                                    work[(X + 1 + i) * B + j] += tau * work[(V + i) * B + j]
                            set_ghosts(work, X)
                store_sample(work, samples, save, j0)

    @njit(parallel=True, cache=True, **FAST)
    def runge_kutta_kernel(state0, rate, h, steps_per_save, samples):
        """state0 (2n, M), rate (2n, M) -> samples (n_save, 2n, M); M a multiple of B."""
        for block in prange(state0.shape[1] // B):
            j0 = block * B
            work = load_block(state0, rate, j0, samples)
            for save in range(1, samples.shape[0]):
                for _ in range(steps_per_save):
                    for s in range(S):
                        for i in range(n):
                            for j in range(B):
                                zx = work[(X + 1 + i) * B + j]
                                zv = work[(V + i) * B + j]
                                for r in range(S):
                                    ha = h * a[s * S + r]
                                    zx += ha * work[(KX + r * n + i) * B + j]
                                    zv += ha * work[(KV + r * n + i) * B + j]
                                work[(ZX + 1 + i) * B + j] = zx
                                work[(ZV + i) * B + j] = zv
                        set_ghosts(work, ZX)
                        for i in range(n):
                            for j in range(B):
                                work[(KX + s * n + i) * B + j] = work[(ZV + i) * B + j]
                                work[(KV + s * n + i) * B + j] = chain.acceleration(
                                    work[(ZX + i) * B + j], work[(ZX + 1 + i) * B + j],
                                    work[(ZX + 2 + i) * B + j], work[(CL + i) * B + j],
                                    work[(CR + i) * B + j])
                    for i in range(n):
                        for j in range(B):
                            dx = 0.0
                            dv = 0.0
                            for s in range(S):
                                dx += b[s] * work[(KX + s * n + i) * B + j]
                                dv += b[s] * work[(KV + s * n + i) * B + j]
                            work[(X + 1 + i) * B + j] += h * dx
                            work[(V + i) * B + j] += h * dv
                store_sample(work, samples, save, j0)

    return runge_kutta_kernel if runge_kutta else splitting_kernel


@cache
def kernel_for(scene: str, method: str, key: tuple = ()):
    """The compiled (or cache-loaded) kernel of a stepping method; `key` from the scene's kernel_key."""
    m = METHODS[method]
    if scene == "top":
        return _top_kernel(m)
    return _chain_kernel(m, *key)


def block_size(scene: str, key: tuple) -> int:
    return BLOCK if scene == "top" else chain_block(key[0])


def integrate(scene, method: str, values: dict[str, np.ndarray], constants: dict, dt: float,
              steps_per_save: int, n_save: int) -> np.ndarray:
    """Integrate the members described by `values`; returns samples (n_save, state, members).

    A member's result depends only on its own values: never on how many
    members run with it, the chunking or the thread count.
    """
    t = np.arange(n_save) * (steps_per_save * dt)
    if METHODS[method].closed_form:
        return scene.exact(values, constants, t)
    state0, rate = scene.inputs(values, constants)
    key = scene.kernel_key(constants)
    block = block_size(scene.NAME, key)
    n = state0.shape[1]
    padded = -(-n // block) * block
    if padded != n:  # pad with copies of the last member; trimmed below
        state0 = np.concatenate([state0, np.repeat(state0[:, -1:], padded - n, axis=1)], axis=1)
        rate = np.concatenate([rate, np.repeat(rate[:, -1:], padded - n, axis=1)], axis=1)
    samples = np.empty((n_save, state0.shape[0], padded))
    kernel_for(scene.NAME, method, key)(
        np.ascontiguousarray(state0), np.ascontiguousarray(rate), float(dt), int(steps_per_save), samples
    )
    return samples[:, :, :n]


def prepare(scene: str, method: str, constants: dict) -> None:
    """Compile (or load from Numba's cache) the kernel of a stepping method."""
    if METHODS[method].closed_form:
        return
    module = SCENES[scene]
    key = module.kernel_key(constants)
    state_rows, rate_rows = module.kernel_rows(constants)
    block = block_size(scene, key)
    kernel_for(scene, method, key)(np.zeros((state_rows, block)), np.zeros((rate_rows, block)), 1.0, 1,
                                   np.empty((1, state_rows, block)))
