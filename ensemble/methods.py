"""The integration methods: one place that says what each method is.

A method is data wherever it fits a standard form:
- explicit Runge-Kutta methods are Butcher tableaus;
- splitting methods are sequences of exactly solved pieces, each advanced by a
  fraction of the step; higher orders come from composing a symmetric
  splitting (Yoshida's triple jump).
The kernels in :mod:`ensemble.kernels` are generated from this data, so adding
such a method is one entry here.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Tableau:
    """Butcher tableau of an explicit Runge-Kutta method (a strictly lower triangular)."""

    a: tuple[tuple[float, ...], ...]
    b: tuple[float, ...]
    c: tuple[float, ...]

    @property
    def stages(self) -> int:
        return len(self.b)

    def stability(self, z):
        """Stability function R(z) = 1 + z b^T (I - z A)^-1 1: one step's factor on y' = lambda y, z = lambda h."""
        z = np.asarray(z, dtype=complex)
        s = self.stages
        a = np.array(self.square_a()).reshape(s, s)
        flat = z.reshape(-1)
        eye = np.eye(s)
        slopes = np.linalg.solve(eye[None] - flat[:, None, None] * a[None], np.ones((flat.size, s, 1)))
        return (1 + flat * (slopes[:, :, 0] @ np.array(self.b))).reshape(z.shape)

    def square_a(self) -> tuple[float, ...]:
        """a as a flat, zero-padded stages x stages tuple (row major)."""
        s = self.stages
        return tuple(float(row[r]) if r < len(row) else 0.0 for row in self.a for r in range(s))


@dataclass(frozen=True)
class Splitting:
    """One step as exactly solved pieces in turn: ((piece, fraction of the step), ...).

    Pieces are numbered; each scene says what its piece 0 and piece 1 are
    (chain: 0 kick, 1 drift; top: 0 drag, 1 free rotation).
    """

    sequence: tuple[tuple[int, float], ...]

    def composed(self, weights: tuple[float, ...]) -> Splitting:
        """This splitting applied with step fractions `weights` in turn; adjacent equal pieces merge."""
        merged: list[list] = []
        for w in weights:
            for piece, fraction in self.sequence:
                if merged and merged[-1][0] == piece:
                    merged[-1][1] += w * fraction
                else:
                    merged.append([piece, w * fraction])
        return Splitting(tuple((p, f) for p, f in merged))


_CBRT2 = 2.0 ** (1.0 / 3.0)
#: Yoshida's fourth-order triple jump: a symmetric second-order step composed with these fractions.
YOSHIDA4 = (1.0 / (2.0 - _CBRT2), -_CBRT2 / (2.0 - _CBRT2), 1.0 / (2.0 - _CBRT2))

EULER = Tableau(a=((0.0,),), b=(1.0,), c=(0.0,))
RK4 = Tableau(
    a=((0.0, 0.0, 0.0, 0.0), (0.5, 0.0, 0.0, 0.0), (0.0, 0.5, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0)),
    b=(1 / 6, 1 / 3, 1 / 3, 1 / 6),
    c=(0.0, 0.5, 0.5, 1.0),
)
KICK, DRIFT = 0, 1  # chain pieces
DRAG, ROTATE = 0, 1  # top pieces
VERLET = Splitting(((KICK, 0.5), (DRIFT, 1.0), (KICK, 0.5)))
STRANG_TOP = Splitting(((DRAG, 0.5), (ROTATE, 1.0), (DRAG, 0.5)))


@dataclass(frozen=True)
class Method:
    """An integration method, its order, and the scenes it applies to."""

    name: str
    order: int | None  # None: no truncation error (closed form)
    symplectic: bool
    scenes: tuple[str, ...]
    summary: str
    tableau: Tableau | None = None  # explicit Runge-Kutta methods
    splitting: Splitting | None = None  # splitting and composition methods
    closed_form: bool = False  # evaluates the scene's exact solution


METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method("euler", 1, False, ("top", "chain"), "explicit (forward) Euler", tableau=EULER),
        Method("symplectic_euler", 1, True, ("chain",), "kick, then drift (semi-implicit Euler)",
               splitting=Splitting(((KICK, 1.0), (DRIFT, 1.0)))),
        Method("verlet", 2, True, ("chain",), "velocity Verlet (leapfrog): half kick, drift, half kick",
               splitting=VERLET),
        Method("rk4", 4, False, ("top", "chain"), "classical fourth-order Runge-Kutta", tableau=RK4),
        Method("yoshida4", 4, True, ("chain",), "Yoshida's fourth-order composition of verlet",
               splitting=VERLET.composed(YOSHIDA4)),
        Method("split2", 2, False, ("top",), "Strang splitting: half drag decay, free rotation, half drag decay",
               splitting=STRANG_TOP),
        Method("split4", 4, False, ("top",), "Yoshida's fourth-order composition of split2",
               splitting=STRANG_TOP.composed(YOSHIDA4)),
        Method("exact", None, False, ("top", "chain"), "closed-form solution at the saved times (no stepping)",
               closed_form=True),
    )
}


def methods_for(scene: str) -> list[str]:
    """Names of the methods that apply to `scene`, in listing order."""
    return [name for name, m in METHODS.items() if scene in m.scenes]
