"""The integration methods: one place that says what each method is.

A method is data wherever it fits a standard form: explicit Runge-Kutta
methods are Butcher tableaus, and the kernels in :mod:`ensemble.kernels` are
generated from them. Adding an explicit Runge-Kutta method is one entry here.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Tableau:
    """Butcher tableau of an explicit Runge-Kutta method (a strictly lower triangular)."""

    a: tuple[tuple[float, ...], ...]
    b: tuple[float, ...]
    c: tuple[float, ...]

    @property
    def stages(self) -> int:
        return len(self.b)


@dataclass(frozen=True)
class Method:
    """An integration method, its order, and the scenes it applies to."""

    name: str
    order: int | None  # None: no truncation error (closed form)
    symplectic: bool
    scenes: tuple[str, ...]
    summary: str
    tableau: Tableau | None = None  # explicit Runge-Kutta methods
    closed_form: bool = False  # evaluates the scene's exact solution


METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method(
            "euler", 1, False, ("top",), "explicit (forward) Euler",
            Tableau(a=((0.0,),), b=(1.0,), c=(0.0,)),
        ),
        Method(
            "rk4", 4, False, ("top",), "classical fourth-order Runge-Kutta",
            Tableau(
                a=((0.0, 0.0, 0.0, 0.0), (0.5, 0.0, 0.0, 0.0), (0.0, 0.5, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0)),
                b=(1 / 6, 1 / 3, 1 / 3, 1 / 6),
                c=(0.0, 0.5, 0.5, 1.0),
            ),
        ),
        Method(
            "exact", None, False, ("top",), "closed-form solution at the saved times (no stepping)",
            closed_form=True,
        ),
    )
}


def methods_for(scene: str) -> list[str]:
    """Names of the methods that apply to `scene`, in listing order."""
    return [name for name, m in METHODS.items() if scene in m.scenes]
