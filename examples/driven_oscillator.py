"""A damped, driven oscillator, x'' + 2 gamma x' + omega0^2 x = F cos(Omega t): a scene of your own.

Run it with `scene = "examples/driven_oscillator.py"` in a run file (a path relative to the run file's folder,
as runs/driven_oscillator.toml does). This file is the whole scene: its state, its parameters and its
right-hand side (required), and its closed form and its steady-state theory with a fit (optional). See
docs/scenes.md for the contract.
"""
import math

import numpy as np

from ensemble import Parameter

NAME = "driven_oscillator"

STATE = {"x": ("m", "displacement"), "v": ("m s-1", "velocity")}

PARAMETERS = {  # x0 and v0 start the state; the others are the right-hand side's, in this order
    "gamma": Parameter("s-1", "damping rate"),
    "omega0": Parameter("rad s-1", "natural angular frequency"),
    "F": Parameter("m s-2", "driving force per unit mass"),
    "Omega": Parameter("rad s-1", "driving angular frequency"),
    "x0": Parameter("m", "displacement at t = 0"),
    "v0": Parameter("m s-1", "velocity at t = 0", default=0.0),
}


def rhs(t, x, v, gamma, omega0, F, Omega):
    """(x', v') of one member at time t (s)."""
    return v, F * math.cos(Omega * t) - 2.0 * gamma * v - omega0 * omega0 * x


def steady_state(gamma, omega0, F, Omega):
    """The driven response's cos and sin coefficients (m), x = A cos(Omega t) + B sin(Omega t)."""
    detuning, friction = omega0**2 - Omega**2, 2.0 * gamma * Omega
    squared = detuning**2 + friction**2
    return F * detuning / squared, F * friction / squared


def steady_amplitude(gamma, omega0, F, Omega):
    """The theory: F / sqrt((omega0^2 - Omega^2)^2 + (2 gamma Omega)^2) (m)."""
    return np.hypot(*steady_state(gamma, omega0, F, Omega))


def free_motion(t, gamma, omega0):
    """The damped free motion's two solutions (m per unit start), exp(-gamma t) cos(w t) and exp(-gamma t)
    sin(w t) / w with w = sqrt(omega0^2 - gamma^2): under-, critically or over-damped alike (w imaginary: cosh
    and sinh)."""
    damped = np.sqrt((omega0**2 - gamma**2) + 0j)
    c = np.cos(damped * t).real
    s = np.where(damped == 0, t, (np.sin(damped * t) / np.where(damped == 0, 1, damped)).real)  # sin(w t) / w
    decay = np.exp(-gamma * t)
    return decay * c, decay * s


def exact(t, x0, v0, gamma, omega0, F, Omega):
    """x(t) and v(t), numpy arrays broadcast over t (times, 1) and the members' values (1, members): the steady
    response plus the free motion that brings it to x0, v0."""
    A, B = steady_state(gamma, omega0, F, Omega)
    x_free, v_free = x0 - A, v0 - B * Omega  # the free motion's start
    k = v_free + gamma * x_free
    c, s = free_motion(t, gamma, omega0)
    x = A * np.cos(Omega * t) + B * np.sin(Omega * t) + x_free * c + k * s
    v = (-A * Omega * np.sin(Omega * t) + B * Omega * np.cos(Omega * t)
         + (k - gamma * x_free) * c - (gamma * k + (omega0**2 - gamma**2) * x_free) * s)
    return x, v


# For `ensemble stability` (optional, all four or none): the free oscillation's eigenvalues
# lambda = -gamma +- i sqrt(omega0^2 - gamma^2) decide how a method's step grows.
STABILITY_AXES = ("h omega0",)  # the dimensionless step of the free oscillation


def stability_axis(values, constants, h):
    """Each member's axis and its place on it, h omega0; h (s) and the values arrays over members."""
    x = h * np.broadcast_to(values["omega0"], np.shape(h))
    return np.full(x.shape, STABILITY_AXES[0]), x


def _factor(method, z):
    """|one step's factor| on y' = (z / h) y: a Runge-Kutta method's |R(z)|; the closed form's exp(Re z)."""
    return np.abs(method.tableau.stability(z)) if method.tableau is not None else np.exp(np.real(z))


def step_growth(method, values, constants, h):
    """Theory: the growth factor per step of a member's faster-growing free motion (h z at both eigenvalues)."""
    gamma, omega0 = (np.broadcast_to(values[name], np.shape(h)) for name in ("gamma", "omega0"))
    root = np.sqrt(omega0**2 - gamma**2 + 0j)
    return np.maximum(_factor(method, h * (-gamma + 1j * root)), _factor(method, h * (-gamma - 1j * root)))


def axis_growth(method, axis, x):
    """Growth factor per step of an undamped oscillation at x = h omega0 (z = i x)."""
    return _factor(method, 1j * np.asarray(x, dtype=float))


def fit(ds):
    """Each member's steady amplitude against the theory, an xarray Dataset over member: x fitted by least squares
    with A cos(Omega t) + B sin(Omega t) and the two free motions (so the transient does not bias A and B), the
    amplitude sqrt(A^2 + B^2). Without observation noise the fit is exact but for the method's error, so
    `ensemble fit --check` holds it to 1e-6 relative (check_rtol)."""
    import xarray as xr

    t = ds["t"].values
    members = ds.sizes["member"]
    values = {name: np.broadcast_to(ds[name].values, (members,)) for name in ("gamma", "omega0", "F", "Omega")}
    amplitude = np.empty(members)
    for j in range(members):
        gamma, omega0, Omega = values["gamma"][j], values["omega0"][j], values["Omega"][j]
        design = np.stack([np.cos(Omega * t), np.sin(Omega * t), *free_motion(t, gamma, omega0)], axis=1)
        (a, b, _, _), *_ = np.linalg.lstsq(design, ds["x"].values[j], rcond=None)
        amplitude[j] = math.hypot(a, b)
    theory = steady_amplitude(*(values[name] for name in ("gamma", "omega0", "F", "Omega")))
    return xr.Dataset({"amplitude": ("member", amplitude, {"units": "m", "long_name": "fitted steady amplitude",
                                                           "check_rtol": 1e-6}),
                       "amplitude_theory": ("member", theory, {"units": "m", "long_name": "steady amplitude, theory"})})
