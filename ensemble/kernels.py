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

    @njit(parallel=True, cache=True, **FAST)
    def kernel(state0, rate, h, steps_per_save, samples):
        """state0 (3, M), rate (3, M) -> samples (n_save, 3, M); M a multiple of BLOCK."""
        n_save = samples.shape[0]
        for block in prange(state0.shape[1] // BLOCK):
            j0 = block * BLOCK
            j1 = j0 + BLOCK
            w1 = state0[0, j0:j1].copy()
            w2 = state0[1, j0:j1].copy()
            w3 = state0[2, j0:j1].copy()
            p = rate[0, j0:j1].copy()
            r1 = rate[1, j0:j1].copy()
            r3 = rate[2, j0:j1].copy()
            k = np.zeros((S, 3, BLOCK))
            samples[0, 0, j0:j1] = w1
            samples[0, 1, j0:j1] = w2
            samples[0, 2, j0:j1] = w3
            for i in range(1, n_save):
                for _ in range(steps_per_save):
                    for j in range(BLOCK):
                        y1 = w1[j]
                        y2 = w2[j]
                        y3 = w3[j]
                        s1 = 0.0
                        s2 = 0.0
                        s3 = 0.0
                        for s in range(S):
                            z1 = y1
                            z2 = y2
                            z3 = y3
                            for r in range(S):
                                ha = h * a[s * S + r]
                                z1 += ha * k[r, 0, j]
                                z2 += ha * k[r, 1, j]
                                z3 += ha * k[r, 2, j]
                            d1, d2, d3 = top.rhs(z1, z2, z3, p[j], r1[j], r3[j])
                            k[s, 0, j] = d1
                            k[s, 1, j] = d2
                            k[s, 2, j] = d3
                            s1 += b[s] * d1
                            s2 += b[s] * d2
                            s3 += b[s] * d3
                        w1[j] = y1 + h * s1
                        w2[j] = y2 + h * s2
                        w3[j] = y3 + h * s3
                samples[i, 0, j0:j1] = w1
                samples[i, 1, j0:j1] = w2
                samples[i, 2, j0:j1] = w3

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
