"""Parallel ensemble drivers: a scene's equations combined with a method.

Members run in blocks of BLOCK; prange goes over blocks and the innermost loop
over the members of a block, which LLVM vectorizes (see DESIGN.md). Kernels are
built once per (scene, method) by factories whose closures capture the
method's data as constants, and are cached on disk by Numba.
"""
from __future__ import annotations

from functools import cache

import numpy as np
from numba import njit, prange

from .methods import METHODS, Tableau
from .scenes import SCENES, top

BLOCK = 128  # members per block: a compile-time constant of every kernel
FAST = dict(fastmath=True, error_model="numpy", boundscheck=False)


def _top_rk_kernel(tableau: Tableau):
    """Explicit Runge-Kutta kernel for the top, generated from a Butcher tableau.

    The stage loops run over compile-time constants with the full (zero-padded)
    square of coefficients, so LLVM unrolls them and drops the zero terms: the
    result matches a hand-written stepper (measured in analysis/bench_top.py).
    """
    S = tableau.stages
    a = tuple(float(tableau.a[s][r]) if r < len(tableau.a[s]) else 0.0 for s in range(S) for r in range(S))
    b = tuple(float(x) for x in tableau.b)

    # One array per block holds everything the step touches, at constant offsets
    # (rows: w1, w2, w3, p, r1, r3, then k[s, c] at row 6 + 3 s + c). With a single
    # base pointer LLVM proves the rows disjoint and emits only the vector loop;
    # separate arrays need a runtime overlap check whose scalar fallback rounds
    # differently, which made results depend on heap addresses.
    @njit(parallel=True, cache=True, **FAST)
    def kernel(state0, rate, h, steps_per_save, samples):
        """state0 (3, M), rate (3, M) -> samples (n_save, 3, M); M a multiple of BLOCK."""
        n_save = samples.shape[0]
        for block in prange(state0.shape[1] // BLOCK):
            j0 = block * BLOCK
            j1 = j0 + BLOCK
            work = np.zeros((6 + 3 * S) * BLOCK)
            for c in range(3):
                work[c * BLOCK:(c + 1) * BLOCK] = state0[c, j0:j1]
                work[(3 + c) * BLOCK:(4 + c) * BLOCK] = rate[c, j0:j1]
                samples[0, c, j0:j1] = state0[c, j0:j1]
            for i in range(1, n_save):
                for _ in range(steps_per_save):
                    for j in range(BLOCK):
                        y1 = work[j]
                        y2 = work[BLOCK + j]
                        y3 = work[2 * BLOCK + j]
                        p = work[3 * BLOCK + j]
                        r1 = work[4 * BLOCK + j]
                        r3 = work[5 * BLOCK + j]
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
                        work[j] = y1 + h * s1
                        work[BLOCK + j] = y2 + h * s2
                        work[2 * BLOCK + j] = y3 + h * s3
                for c in range(3):
                    samples[i, c, j0:j1] = work[c * BLOCK:(c + 1) * BLOCK]

    return kernel


@cache
def kernel_for(scene: str, method: str):
    """The compiled (or cache-loaded) kernel of a stepping method on a scene."""
    m = METHODS[method]
    if scene == "top" and m.tableau is not None:
        return _top_rk_kernel(m.tableau)
    raise ValueError(f"no kernel for method {method!r} on scene {scene!r}")


def integrate(scene, method: str, state0: np.ndarray, rate: np.ndarray, dt: float,
              steps_per_save: int, n_save: int) -> np.ndarray:
    """Integrate members from state0 (state, M); returns samples (n_save, state, M).

    Member j's result depends only on its own state0[:, j] and rate[:, j]:
    never on M, the chunking or the thread count.
    """
    if METHODS[method].closed_form:
        t = np.arange(n_save) * (steps_per_save * dt)
        return scene.exact(state0, rate, t)
    n = state0.shape[1]
    padded = -(-n // BLOCK) * BLOCK
    if padded != n:  # pad with copies of the last member; trimmed below
        state0 = np.concatenate([state0, np.repeat(state0[:, -1:], padded - n, axis=1)], axis=1)
        rate = np.concatenate([rate, np.repeat(rate[:, -1:], padded - n, axis=1)], axis=1)
    samples = np.empty((n_save, state0.shape[0], padded))
    kernel_for(scene.NAME, method)(
        np.ascontiguousarray(state0), np.ascontiguousarray(rate), float(dt), int(steps_per_save), samples
    )
    return samples[:, :, :n]


def prepare(scene: str, method: str) -> None:
    """Compile (or load from Numba's cache) the kernel of a stepping method."""
    if not METHODS[method].closed_form:
        size = SCENES[scene].STATE_SIZE
        kernel_for(scene, method)(np.zeros((size, BLOCK)), np.zeros((size, BLOCK)), 1.0, 1,
                                  np.empty((1, size, BLOCK)))
