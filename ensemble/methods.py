"""The integration methods: one place that says what each method is.

A method is data wherever it fits a standard form:
- explicit Runge-Kutta methods are Butcher tableaus;
- splitting methods are sequences of exactly solved pieces, each advanced by a
  fraction of the step; higher orders come from composing a symmetric
  splitting (Yoshida's triple jump).
Nothing here names a scene. A splitting names the exactly solved pieces it is
made of (kick and drift, drag and rotation); a scene says which pieces it has
(its PIECES), and the methods that apply to it follow (`ensemble.scenes.methods_for`).
The scenes' kernels are generated from this data, so adding such a method is one
entry here.
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
    error: tuple[float, ...] | None = None  # b - b_hat of an embedded pair: h sum(error_s k_s) is the local error

    @property
    def fsal(self) -> bool:
        """First stage of the next step is the last of this one (the last row of a is b, at c = 1)."""
        return self.c[-1] == 1.0 and tuple(self.square_a()[-self.stages:]) == tuple(float(x) for x in self.b)

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

    `pieces` names the pieces (a scene with the same PIECES can take the
    method); the sequence numbers them by their place in `pieces`.
    """

    pieces: tuple[str, ...]
    sequence: tuple[tuple[int, float], ...]

    @property
    def numbers(self) -> tuple[int, ...]:
        """The sequence's piece numbers, in order."""
        return tuple(int(number) for number, _ in self.sequence)

    @property
    def fractions(self) -> tuple[float, ...]:
        """The sequence's fractions of the step, in order."""
        return tuple(float(fraction) for _, fraction in self.sequence)

    def evaluations(self, evaluating: tuple[str, ...]) -> int:
        """Right-hand-side evaluations per step: the pieces named in `evaluating` (a chain's kick evaluates the
        forces), less one where a step ends with the piece the next begins with (they merge)."""
        used = [p for p, _ in self.sequence if self.pieces[p] in evaluating]
        first, last = self.sequence[0][0], self.sequence[-1][0]
        return len(used) - (len(self.sequence) > 1 and first == last and self.pieces[first] in evaluating)

    def composed(self, weights: tuple[float, ...]) -> Splitting:
        """This splitting applied with step fractions `weights` in turn; adjacent equal pieces merge."""
        merged: list[list] = []
        for w in weights:
            for piece, fraction in self.sequence:
                if merged and merged[-1][0] == piece:
                    merged[-1][1] += w * fraction
                else:
                    merged.append([piece, w * fraction])
        return Splitting(self.pieces, tuple((p, f) for p, f in merged))


_CBRT2 = 2.0 ** (1.0 / 3.0)
#: Yoshida's fourth-order triple jump: a symmetric second-order step composed with these fractions.
YOSHIDA4 = (1.0 / (2.0 - _CBRT2), -_CBRT2 / (2.0 - _CBRT2), 1.0 / (2.0 - _CBRT2))

EULER = Tableau(a=((0.0,),), b=(1.0,), c=(0.0,))
RK4 = Tableau(
    a=((0.0, 0.0, 0.0, 0.0), (0.5, 0.0, 0.0, 0.0), (0.0, 0.5, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0)),
    b=(1 / 6, 1 / 3, 1 / 3, 1 / 6),
    c=(0.0, 0.5, 0.5, 1.0),
)
#: Dormand and Prince (1980): fifth-order solution, fourth-order embedded estimate, first same as last.
DOPRI5 = Tableau(
    a=((),
       (1 / 5,),
       (3 / 40, 9 / 40),
       (44 / 45, -56 / 15, 32 / 9),
       (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
       (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
       (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84)),
    b=(35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0.0),
    c=(0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0),
    error=(71 / 57600, 0.0, -71 / 16695, 71 / 1920, -17253 / 339200, 22 / 525, -1 / 40),
)


@dataclass(frozen=True)
class StepControl:
    """The PI step-size controller of an adaptive method (Hairer, Norsett and Wanner, II.4).

    After a step with error norm err (1 = at tolerance), the next step is
    h * clip(safety * err^-alpha * err_previous^beta, min_factor, max_factor);
    after a rejection the factor is at most 1.
    """

    alpha: float
    beta: float
    safety: float = 0.9
    min_factor: float = 0.2
    max_factor: float = 10.0


#: A separable Hamiltonian's pieces: kick (v += tau a(x)) and drift (x += tau v).
KICK_DRIFT = ("kick", "drift")
#: A torque-free rotation and a linear drag, each solved exactly.
DRAG_ROTATION = ("drag", "rotate")
#: A free rigid body's kinetic energy as three pieces L_i^2 / (2 lambda_i), each a rotation of L about body axis
#: i, and a linear drag.
AXIS_ROTATIONS = ("rotate1", "rotate2", "rotate3", "drag")
SYMPLECTIC_EULER = Splitting(KICK_DRIFT, ((0, 1.0), (1, 1.0)))
VERLET = Splitting(KICK_DRIFT, ((0, 0.5), (1, 1.0), (0, 0.5)))
STRANG_DRAG_ROTATION = Splitting(DRAG_ROTATION, ((0, 0.5), (1, 1.0), (0, 0.5)))
#: Symmetric: half drag, half turns about axes 1 and 2, a whole turn about 3, then back.
SYMMETRIC_ROTATIONS = Splitting(AXIS_ROTATIONS, ((3, 0.5), (0, 0.5), (1, 0.5), (2, 1.0), (1, 0.5), (0, 0.5),
                                                 (3, 0.5)))


@dataclass(frozen=True)
class Method:
    """An integration method and its order; which scenes it applies to follows from its kind."""

    name: str
    order: int | None  # None: no truncation error (closed form)
    symplectic: bool
    summary: str
    tableau: Tableau | None = None  # explicit Runge-Kutta methods
    splitting: Splitting | None = None  # splitting and composition methods
    closed_form: bool = False  # evaluates the scene's exact solution
    control: StepControl | None = None  # adaptive methods: each member controls its own step

    @property
    def adaptive(self) -> bool:
        return self.control is not None

    def evaluations_per_step(self, evaluating: tuple[str, ...]) -> int:
        """Right-hand-side (force) evaluations of a fixed step: the stages, or the splitting pieces named in
        `evaluating` (a scene's EVALUATING_PIECES); 0 for the closed form."""
        if self.tableau is not None:
            return self.tableau.stages
        return self.splitting.evaluations(evaluating) if self.splitting is not None else 0


METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method("euler", 1, False, "explicit (forward) Euler", tableau=EULER),
        Method("symplectic_euler", 1, True, "kick, then drift (semi-implicit Euler)", splitting=SYMPLECTIC_EULER),
        Method("verlet", 2, True, "velocity Verlet (leapfrog): half kick, drift, half kick", splitting=VERLET),
        Method("rk4", 4, False, "classical fourth-order Runge-Kutta", tableau=RK4),
        Method("yoshida4", 4, True, "Yoshida's fourth-order composition of verlet",
               splitting=VERLET.composed(YOSHIDA4)),
        Method("split2", 2, False, "Strang splitting: half drag decay, free rotation, half drag decay",
               splitting=STRANG_DRAG_ROTATION),
        Method("split4", 4, False, "Yoshida's fourth-order composition of split2",
               splitting=STRANG_DRAG_ROTATION.composed(YOSHIDA4)),
        Method("rotations2", 2, False, "free-body rotations about each body axis in turn, symmetric, and drag "
               "(Poisson; keeps |L| when c = 0)", splitting=SYMMETRIC_ROTATIONS),
        Method("rotations4", 4, False, "Yoshida's fourth-order composition of rotations2",
               splitting=SYMMETRIC_ROTATIONS.composed(YOSHIDA4)),
        Method("dopri5", 5, False, "Dormand-Prince 5(4), adaptive: each member controls its step to rtol and atol",
               tableau=DOPRI5, control=StepControl(alpha=0.7 / 5 - 0.75 * 0.04, beta=0.04)),
        Method("exact", None, False, "closed-form solution at the saved times (no stepping)", closed_form=True),
    )
}
