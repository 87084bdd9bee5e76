"""A spring chain's compiled physics: the acceleration of a mass between its neighbours, from which
ensemble.engine.sites builds the chain's kernels, and the energy of saved samples."""
from __future__ import annotations

import numpy as np
from numba import njit

from ...engine.blocks import FAST


@njit(inline="always", **FAST)
def acceleration(x_left, x, x_right, c_left, c_right):
    """Acceleration (m/s^2) of a mass at x between neighbours x_left, x_right (m).

    c_left and c_right (1/s^2) are the springs' constants on each side over the mass.
    """
    return c_left * (x_left - x) + c_right * (x_right - x)


@njit(cache=True, nogil=True, error_model="numpy")
def sample_energy(samples, m, k, boundary):
    """model.energy compiled, sums taken mass by mass and spring by spring: 1/2 v.M.v + 1/2 x.K.x (J), shape
    (members, t), from member-major samples (members, t, 2n) of (x; v), masses m (members, n) kg and springs k
    (members, springs) N/m; boundary its index in model.BOUNDARIES. A run saving or measuring the energy computes it
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
