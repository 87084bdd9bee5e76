"""The torqued symmetric top (the flying ring): equations, exact solution, observables, theory.

Body frame, lambda1 = lambda2, air-drag torque -c omega:

    lambda1 w1' = (lambda1 - lambda3) w2 w3 - c w1
    lambda1 w2' = (lambda3 - lambda1) w3 w1 - c w2
    lambda3 w3' = -c w3

The state is the three body rates (rad/s) and nothing more. With
p = (lambda3 - lambda1)/lambda1, r1 = c/lambda1 and r3 = c/lambda3 the
equations read w1' = -p w3 w2 - r1 w1, w2' = p w3 w1 - r1 w2, w3' = -r3 w3.
The right-hand side and the exactly solved pieces the kernels are built from are in `physics.py` beside this file.
"""
from __future__ import annotations

import numpy as np

from ... import libm
from ...inertia import EQUAL_RTOL, Body
from ...methods import DRAG_ROTATION, Method
from ...parameter import Parameter, ParameterError
from ..closed_form import times_by_members

NAME = "top"
PHYSICS = "ensemble.scenes.top.physics"  # rhs and pieces, from which ensemble.engine builds the kernels
SITES = False  # a member is D values (the body rates), not a field of sites
PIECES = DRAG_ROTATION  # splitting methods: drag decay and free rotation, each solved exactly
EVALUATING_PIECES = ()  # neither piece evaluates the right-hand side

PARAMETERS = {
    "lambda1": Parameter("kg m2", "principal moment of inertia about the transverse axes e1, e2"),
    "lambda3": Parameter("kg m2", "principal moment of inertia about the symmetry axis e3"),
    "c": Parameter("kg m2 s-1", "air-drag torque coefficient (torque = -c omega)"),
    "spin0": Parameter("rad s-1", "magnitude of the angular velocity at t = 0"),
    "tilt0": Parameter("rad", "angle between omega and e3 at t = 0"),
    "azimuth0": Parameter("rad", "azimuth of omega about e3 at t = 0, from e1", default=0.0),
    "body": Parameter("", "the body as a uniform shape, instead of lambda1 and lambda3",
                      derives=("lambda1", "lambda3")),
}

# Saved variables: name -> (dims, units, long_name). Default: all of them.
OBSERVABLES: dict[str, tuple[tuple[str, ...], str, str]] = {
    "omega": (("member", "t", "axis"), "rad s-1", "body-frame angular velocity"),
    "tilt": (("member", "t"), "rad", "angle between the angular velocity and the symmetry axis e3"),
}

# What events can watch (ensemble.events): omega's components are the kernel's state rows 0..2; the tilt is
# physics.value_tilt, which the kernels watch through physics.watch_tilt (its sign against a level, cheaper).
EVENT_VALUES = {"omega": ("state", 0), "tilt": ("function", "value_tilt", "watch_tilt")}

# Relative slack for lambda3 <= 2 lambda1: a flat body sits exactly on the bound.
_FLAT_BODY_RTOL = 1e-9


def sizes(constants: dict) -> dict[str, int]:
    """Dimensions besides member and t: the three body axes."""
    return {"axis": 3}


def coordinates(constants: dict) -> dict[str, tuple[np.ndarray, str]]:
    """Coordinate variables of the dimensions in `sizes`: values and long_name."""
    return {"axis": (np.array([1, 2, 3], dtype=np.int32), "body-frame axis (3: symmetry axis)")}


def check_constants(constants: dict) -> None:
    """The top has no run constants."""


def check(values: dict[str, np.ndarray]) -> None:
    """Physical constraints on per-member parameters; raises ParameterError for the first broken one."""
    for name in ("lambda1", "lambda3"):
        if np.any(values[name] <= 0):
            raise ParameterError(name, f"must be > 0 (got {values[name].min():g})")
    if np.any(values["c"] < 0):
        raise ParameterError("c", f"must be >= 0 (got {values['c'].min():g})")
    if np.any(values["spin0"] <= 0):
        raise ParameterError("spin0", f"must be > 0: the tilt of a body at rest is undefined (got "
                                      f"{values['spin0'].min():g})")
    tilt0 = values["tilt0"]
    if np.any((tilt0 < 0) | (tilt0 > np.pi)):
        raise ParameterError("tilt0", "must lie in [0, pi]")
    ratio = values["lambda3"] / values["lambda1"]
    if np.any(ratio > 2 * (1 + _FLAT_BODY_RTOL)):
        raise ParameterError("lambda3", f"lambda3 > 2 lambda1 (ratio {ratio.max():.6g}): no rigid body has that")


def from_body(body: Body, source: str) -> dict[str, np.ndarray]:
    """lambda1 and lambda3 (kg m2, per member) of bodies that are symmetric tops about their centre of mass.

    Two of the three principal moments must be equal (to EQUAL_RTOL): they
    are lambda1, the third is lambda3. A ParameterError on `source` (the shape
    parameter) names the moments of the first body that has no such pair.
    """
    moments = np.linalg.eigvalsh(body.inertia).reshape(-1, 3)  # ascending, per member
    low, middle, high = moments.T
    low_pair = middle - low <= EQUAL_RTOL * high
    high_pair = high - middle <= EQUAL_RTOL * high
    if not np.all(low_pair | high_pair):
        i = int(np.argmin(low_pair | high_pair))
        which = f" (member {i})" if len(moments) > 1 else ""
        raise ParameterError(source, f"is not a symmetric top{which}: its principal moments about its centre of "
                                     f"mass are {low[i]:.6g}, {middle[i]:.6g}, {high[i]:.6g} kg m2, no two of them "
                                     f"equal; fly it as scene = \"body\"")
    lambda1 = np.where(low_pair, (low + middle) / 2, (middle + high) / 2)
    lambda3 = np.where(low_pair, np.where(high_pair, middle, high), low)
    return {"lambda1": lambda1, "lambda3": lambda3}


def initial_state(values: dict[str, np.ndarray]) -> np.ndarray:
    """Body rates at t = 0 from spin0, tilt0, azimuth0; shape (3, members), rad/s."""
    spin, tilt, azimuth = values["spin0"], values["tilt0"], values["azimuth0"]
    return np.stack(
        (spin * libm.sin(tilt) * libm.cos(azimuth), spin * libm.sin(tilt) * libm.sin(azimuth), spin * libm.cos(tilt))
    )


def rates(values: dict[str, np.ndarray]) -> np.ndarray:
    """Kernel parameters (p, r1, r3), shape (3, members): no division in the hot loop."""
    lambda1, lambda3, c = values["lambda1"], values["lambda3"], values["c"]
    return np.stack(((lambda3 - lambda1) / lambda1, c / lambda1, c / lambda3))


def inputs(values: dict[str, np.ndarray], constants: dict) -> tuple[np.ndarray, np.ndarray]:
    """Kernel state and parameters: body rates (3, members) and (p, r1, r3) (3, members)."""
    return initial_state(values), rates(values)


def kernel_rows(constants: dict) -> tuple[int, int]:
    """Rows of the kernel state and parameter arrays."""
    return 3, 3


def exact(values: dict[str, np.ndarray], constants: dict, t: np.ndarray) -> np.ndarray:
    """Closed-form body rates at times t (s): (times,), or (times, members) for each member's own; returns shape
    (times, 3, members)."""
    return closed_form(initial_state(values), rates(values), t)


def closed_form(state0: np.ndarray, rate: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Body rates at times t (s; (times,) or (times, members)) from rates at 0 (3, members) and (p, r1, r3); shape
    (times, 3, members).

    w3 = w30 exp(-r3 t). z = w1 + i w2 obeys z' = (i p w3 - r1) z, so
    z = z0 exp(-r1 t) exp(i theta), theta = p w30 (1 - exp(-r3 t)) / r3
    (p w30 t when r3 = 0).
    """
    p, r1, r3 = (x[None, :] for x in rate)
    t = times_by_members(t)
    w10, w20, w30 = (x[None, :] for x in state0)
    with np.errstate(divide="ignore", invalid="ignore"):
        spun_time = np.where(r3 > 0, -libm.expm1(-r3 * t) / r3, t)  # integral of exp(-r3 t)
    theta = p * w30 * spun_time
    decay = libm.exp(-r1 * t)
    cos, sin = libm.cos(theta), libm.sin(theta)
    w1 = decay * (w10 * cos - w20 * sin)
    w2 = decay * (w10 * sin + w20 * cos)
    w3 = w30 * libm.exp(-r3 * t)
    return np.stack((w1, w2, w3), axis=1)


def tilt(state: np.ndarray, axis: int) -> np.ndarray:
    """Angle (rad) between omega and e3; `axis` is the axis of `state` holding (w1, w2, w3)."""
    w1, w2, w3 = np.moveaxis(state, axis, 0)
    return libm.arctan2(libm.hypot(w1, w2), w3)


def tilt_theory(values: dict[str, np.ndarray], t: np.ndarray) -> np.ndarray:
    """The course's tilt law atan(tan(tilt0) exp(-c (1/lambda1 - 1/lambda3) t)), shape (members, len(t))."""
    rate = values["c"] * (1 / values["lambda1"] - 1 / values["lambda3"])
    return libm.arctan(libm.tan(values["tilt0"])[:, None] * libm.exp(-rate[:, None] * np.asarray(t)[None, :]))


def tilt_rate_method(method: Method, values: dict[str, np.ndarray], h: float, t: np.ndarray) -> np.ndarray:
    """The tilt decay rate (1/s) that `method` with step h (s) shows over times t (s); shape (members,).

    Per step, w1 + i w2 is multiplied by R(h (i W - r1)) with W = p w3 the
    body-frame precession rate, and w3 by R(-h r3); the log of their moduli's
    ratio over h is the instantaneous rate. W falls as w3 decays, so this
    returns the slope a straight-line fit of the predicted log tan(tilt) over
    t finds. Exact and split methods solve both pieces exactly (they
    commute), so they show the course's rate.
    """
    tableau = method.tableau
    p, r1, r3 = (x[:, None] for x in rates(values))
    if tableau is None:
        return (r1 - r3)[:, 0]
    t = np.asarray(t, dtype=float)
    w3 = initial_state(values)[2][:, None] * libm.exp(-r3 * t[None, :])
    transverse = np.abs(tableau.stability(h * (1j * p * w3 - r1)))
    axial = np.abs(tableau.stability(-h * r3))
    rate = -libm.log(transverse / axial) / h
    log_tan = -np.concatenate((np.zeros((rate.shape[0], 1)), np.cumsum(
        0.5 * (rate[:, 1:] + rate[:, :-1]) * np.diff(t), axis=1)), axis=1)
    return -np.polyfit(t, log_tan.T, 1)[0]


def derive(values: dict[str, np.ndarray], constants: dict) -> dict[str, np.ndarray]:
    """The top computes no parameters from others (its body shape is handled by the run file)."""
    return {}


#: The dimensionless steps a top's stability is read against: the transverse rates' rotation, h Omega with
#: Omega = (lambda3 - lambda1) w3 / lambda1 the body-frame precession rate, and their drag decay, h c / lambda1.
STABILITY_AXES = ("h Omega", "h c/lambda1")


def _amplification(method: Method, z: np.ndarray) -> np.ndarray:
    """|factor| per step on w' = (z / h) w: |R(z)| for a tableau; exact and split methods solve the rotation and
    the decay exactly (each split piece has total fraction 1), so exp(Re z)."""
    tableau = method.tableau
    return np.abs(tableau.stability(z)) if tableau is not None else libm.exp(np.real(z))


def axis_growth(method: Method, axis: str, x: np.ndarray) -> np.ndarray:
    """Growth factor per step of the fastest motion at x on a stability axis.

    h Omega: no drag; (w1, w2) turns (z = i x) while w3 stays (factor 1), so
    the fastest motion grows by max(|R(i x)|, 1). h c / lambda1: a top with
    lambda3 = lambda1 (Omega = 0) whose three rates all decay (z = -x).
    """
    x = np.asarray(x, dtype=float)
    if axis == STABILITY_AXES[0]:
        return np.maximum(_amplification(method, 1j * x), 1.0)
    return _amplification(method, -x + 0j)


def stability_axis(values: dict[str, np.ndarray], constants: dict, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each member's stability axis, the larger of h |Omega| and h c / lambda1, and its position on it; h (s)."""
    p, r1, _ = rates(values)
    omega = np.abs(p * initial_state(values)[2])
    rotating = omega >= r1
    return np.where(rotating, STABILITY_AXES[0], STABILITY_AXES[1]), h * np.where(rotating, omega, r1)


def step_growth(method: Method, values: dict[str, np.ndarray], constants: dict, h: np.ndarray) -> np.ndarray:
    """Theory: the growth factor per step of a member's fastest-growing motion at the start, of the transverse
    rates (w1 + i w2 times R(h (i Omega - r1))) and of w3 (R(-h r3)); motions at zero amplitude do not count."""
    p, r1, r3 = rates(values)
    w = initial_state(values)
    transverse = np.where(libm.hypot(w[0], w[1]) > 0, _amplification(method, h * (1j * p * w[2] - r1)), 0.0)
    axial = np.where(w[2] != 0, _amplification(method, -h * r3 + 0j), 0.0)
    return np.maximum(transverse, axial)


def amplitudes(samples: np.ndarray, values: dict[str, np.ndarray], constants: dict) -> np.ndarray:
    """Amplitudes of the top's two motions, |(w1, w2)| and |w3| (rad/s), shape (members, 2, samples), from
    samples (samples, 3, members)."""
    from .physics import observed_amplitudes  # compiled: the model alone does not import Numba

    return observed_amplitudes(np.ascontiguousarray(samples.transpose(2, 0, 1)))


def kinetic_energy(omega: np.ndarray, lambda1, lambda3) -> np.ndarray:
    """1/2 (lambda1 (w1^2 + w2^2) + lambda3 w3^2) (J) of body rates omega (..., 3) rad/s; conserved when c = 0."""
    return 0.5 * (lambda1 * (omega[..., 0] ** 2 + omega[..., 1] ** 2) + lambda3 * omega[..., 2] ** 2)


def conserved_energy(ds) -> np.ndarray:
    """The kinetic energy (J, (member, t)) of a result's members without drag (c = 0); NaN for the others.
    Raises KeyError naming the variable (omega) the result lacks."""
    if "omega" not in ds:
        raise KeyError("omega")
    energy = kinetic_energy(ds["omega"].values, ds["lambda1"].values[:, None], ds["lambda3"].values[:, None])
    energy[ds["c"].values != 0] = np.nan
    return energy


def observe(samples: np.ndarray, names, values: dict[str, np.ndarray], constants: dict) -> dict[str, np.ndarray]:
    """Saved variables, member-major, from kernel samples of shape (t, 3, members) (a run's are a view of a
    member-major array, which omega then is). The tilt is compiled (physics.observed_tilt): it is tilt() to a
    few units in the last place, at a tenth of libm's cost."""
    from .physics import observed_tilt  # compiled: the model alone does not import Numba

    omega = np.ascontiguousarray(samples.transpose(2, 0, 1))
    out = {}
    if "omega" in names:
        out["omega"] = omega
    if "tilt" in names:
        out["tilt"] = observed_tilt(omega)
    return out
