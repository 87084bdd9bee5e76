"""The top's physics for the kernels: its right-hand side, its exactly solved pieces, and its compiled observables.

The state is the body rates w1, w2, w3 (rad/s) and the parameters are p, r1, r3 (see model.rates). The engine
(ensemble.engine.kernels) builds every method's kernel from these functions, compiled and inlined.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ...engine.blocks import sin_cos


def rhs(t, w1, w2, w3, p, r1, r3):
    """Time derivative of the body rates (rad s-2)."""
    return -p * w3 * w2 - r1 * w1, p * w3 * w1 - r1 * w2, -r3 * w3


def drag_factors(tau, p, r1, r3):
    """Drag alone for time tau (s) scales w1 and w2 by exp(-r1 tau) and w3 by exp(-r3 tau)."""
    return math.exp(-r1 * tau), math.exp(-r3 * tau)


def drag(tau, w1, w2, w3, p, r1, r3, decay1, decay3):
    """Drag alone for time tau (s), its factors given by drag_factors."""
    return w1 * decay1, w2 * decay1, w3 * decay3


def rotate(tau, w1, w2, w3, p, r1, r3):
    """Free symmetric-top rotation for time tau (s): (w1, w2) turns about e3 by p w3 tau."""
    sin, cos = sin_cos(p * w3 * tau)
    return cos * w1 - sin * w2, sin * w1 + cos * w2, w3


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


def value_tilt(t, w1, w2, w3, p, r1, r3):
    """One member's tilt (rad), the value a run file's events watch with of = "tilt" (ensemble.events)."""
    return _tilt_and_transverse(w1, w2, w3)[0]


def watch_tilt(t, w1, w2, w3, p, r1, r3, level):
    """Of the sign of value_tilt - level (rad) at a fraction of its cost, for the kernels' watch of a tilt event
    (ensemble.engine.events). For 0 < level < pi, |w| sin(tilt - level) = a - b, a = |(w1, w2)| cos(level) and
    b = w3 sin(level), has that sign (on the spin axis too), and so has (a|a| - b|b|) / sin(level)^2 (x|x| rises
    with x), which needs no square root; 0 for a body at rest and where the squares underflow (a crossing to
    look at, which the tilt itself then denies: ensemble.engine.events.root). Other levels (the axis's own, 0
    and pi, and those the tilt never reaches) take the tilt itself. NaN where a rate is; +-inf, of the right
    sign, where rates beyond 1e145 rad/s meet a level within 1e-9 rad of the axis."""
    if not 0.0 < level < math.pi:  # the same for every member: a branch the kernel's loop predicts
        return _tilt_and_transverse(w1, w2, w3)[0] - level
    c, s = math.cos(level), math.sin(level)
    return (w1 * w1 + w2 * w2) * (c * abs(c) / (s * s)) - w3 * abs(w3)


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
