"""The free body's physics for the kernels: Euler's equations and the exactly solved pieces of its splittings.

The state is the body rates w1, w2, w3 (rad/s); the parameters are a1, a2, a3 (1), r1, r2, r3 (1/s), the moments
lambda1..3 (kg m2) and their inverses (see model.rates). The splittings work in L = lambda w within a save
interval (to_pieces and from_pieces): turning L about body axis i (the piece L_i^2 / (2 lambda_i)) keeps |L| to
rounding. The engine (ensemble.engine.kernels) builds every method's kernel from these functions.
"""
from __future__ import annotations

import math

from numba import njit

from ...engine.blocks import FAST, sin_cos


def rhs(t, w1, w2, w3, a1, a2, a3, r1, r2, r3, lambda1, lambda2, lambda3, inverse1, inverse2, inverse3):
    """Time derivative of the body rates (rad s-2): w_i' = a_i w_j w_k - r_i w_i."""
    return a1 * w2 * w3 - r1 * w1, a2 * w3 * w1 - r2 * w2, a3 * w1 * w2 - r3 * w3


def value_energy(t, w1, w2, w3, a1, a2, a3, r1, r2, r3, lambda1, lambda2, lambda3, inverse1, inverse2, inverse3):
    """One member's kinetic energy 1/2 sum lambda_i w_i^2 (J): what events watch with of = "energy"."""
    return 0.5 * (lambda1 * w1 * w1 + lambda2 * w2 * w2 + lambda3 * w3 * w3)


def value_angular_momentum(t, w1, w2, w3, a1, a2, a3, r1, r2, r3, lambda1, lambda2, lambda3, inverse1, inverse2,
                           inverse3):
    """One member's |L| (kg m2 s-1): what events watch with of = "angular_momentum"."""
    return math.sqrt((lambda1 * w1) ** 2 + (lambda2 * w2) ** 2 + (lambda3 * w3) ** 2)


@njit(inline="always", **FAST)  # a helper of the pieces: compiled, as what they call must be
def turn(x, y, angle):
    """(x, y) turned by -angle: the pair of L across a body axis under that axis' piece L_i^2 / (2 lambda_i)."""
    sin, cos = sin_cos(angle)
    return cos * x + sin * y, cos * y - sin * x


def to_pieces(w1, w2, w3, a1, a2, a3, r1, r2, r3, lambda1, lambda2, lambda3, inverse1, inverse2, inverse3):
    """The angular momentum L = lambda w (kg m2 s-1), in which the pieces are solved."""
    return w1 * lambda1, w2 * lambda2, w3 * lambda3


def from_pieces(L1, L2, L3, a1, a2, a3, r1, r2, r3, lambda1, lambda2, lambda3, inverse1, inverse2, inverse3):
    """The body rates w = L / lambda (rad/s)."""
    return L1 * inverse1, L2 * inverse2, L3 * inverse3


def rotate1(tau, L1, L2, L3, a1, a2, a3, r1, r2, r3, lambda1, lambda2, lambda3, inverse1, inverse2, inverse3):
    """The piece L1^2 / (2 lambda1) for time tau (s): (L2, L3) turns by L1 tau / lambda1."""
    L2, L3 = turn(L2, L3, L1 * inverse1 * tau)
    return L1, L2, L3


def rotate2(tau, L1, L2, L3, a1, a2, a3, r1, r2, r3, lambda1, lambda2, lambda3, inverse1, inverse2, inverse3):
    """The piece L2^2 / (2 lambda2) for time tau (s): (L3, L1) turns by L2 tau / lambda2."""
    L3, L1 = turn(L3, L1, L2 * inverse2 * tau)
    return L1, L2, L3


def rotate3(tau, L1, L2, L3, a1, a2, a3, r1, r2, r3, lambda1, lambda2, lambda3, inverse1, inverse2, inverse3):
    """The piece L3^2 / (2 lambda3) for time tau (s): (L1, L2) turns by L3 tau / lambda3."""
    L1, L2 = turn(L1, L2, L3 * inverse3 * tau)
    return L1, L2, L3


def drag_factors(tau, a1, a2, a3, r1, r2, r3, lambda1, lambda2, lambda3, inverse1, inverse2, inverse3):
    """Drag alone for time tau (s) scales L_i by exp(-r_i tau)."""
    return math.exp(-r1 * tau), math.exp(-r2 * tau), math.exp(-r3 * tau)


def drag(tau, L1, L2, L3, a1, a2, a3, r1, r2, r3, lambda1, lambda2, lambda3, inverse1, inverse2, inverse3,
         decay1, decay2, decay3):
    """Drag alone for time tau (s), its factors given by drag_factors."""
    return L1 * decay1, L2 * decay2, L3 * decay3
