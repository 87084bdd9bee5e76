"""The free rigid body with three different principal moments, under air drag -c omega.

Body frame, principal moments lambda1, lambda2, lambda3 (any order; recorded as given):

    lambda1 w1' = (lambda2 - lambda3) w2 w3 - c w1
    lambda2 w2' = (lambda3 - lambda1) w3 w1 - c w2
    lambda3 w3' = (lambda1 - lambda2) w1 w2 - c w3

The state is the three body rates (rad/s) and nothing more: with a drag torque
-c omega the dynamics need no orientation. With a_i = (lambda_j - lambda_k) /
lambda_i (i, j, k cyclic) and r_i = c / lambda_i the equations read
w_i' = a_i w_j w_k - r_i w_i. About the largest and the smallest moment the
rotation is stable and small tilts wobble; about the intermediate one they grow
(the tennis-racket effect). The right-hand side and pieces the kernels are built from are
in `physics.py` beside this file.
"""
from __future__ import annotations

import numpy as np

from ... import libm
from ...inertia import Body
from ...methods import AXIS_ROTATIONS, Method
from ...parameter import Parameter, ParameterError
from ..closed_form import times_by_members

NAME = "body"
PHYSICS = "ensemble.scenes.body.physics"  # rhs and pieces, from which ensemble.engine builds the kernels
SITES = False  # a member is D values, not a field of sites
PIECES = AXIS_ROTATIONS  # splitting methods: L turned about each body axis in turn, and drag, each exact
EVALUATING_PIECES = ()
AXES = (1, 2, 3)

PARAMETERS = {
    "lambda1": Parameter("kg m2", "principal moment of inertia about body axis e1"),
    "lambda2": Parameter("kg m2", "principal moment of inertia about body axis e2"),
    "lambda3": Parameter("kg m2", "principal moment of inertia about body axis e3"),
    "c": Parameter("kg m2 s-1", "air-drag torque coefficient (torque = -c omega)"),
    "spin0": Parameter("rad s-1", "magnitude of the angular velocity at t = 0"),
    "spin_axis": Parameter("1", "body axis (1, 2 or 3) the spin starts near", default=3.0),
    "tilt0": Parameter("rad", "angle between omega and the spin axis at t = 0"),
    "azimuth0": Parameter("rad", "azimuth of omega about the spin axis at t = 0, from the next axis (cyclic)",
                          default=0.0),
    "body": Parameter("", "the body as a uniform shape, instead of lambda1, lambda2 and lambda3",
                      derives=("lambda1", "lambda2", "lambda3")),
}

OBSERVABLES: dict[str, tuple[tuple[str, ...], str, str]] = {
    "omega": (("member", "t", "axis"), "rad s-1", "body-frame angular velocity"),
    "tilt": (("member", "t"), "rad", "angle between the angular velocity and the spin axis"),
    "energy": (("member", "t"), "J", "kinetic energy 1/2 sum lambda_i w_i^2"),
    "angular_momentum": (("member", "t"), "kg m2 s-1", "magnitude of the angular momentum |L|"),
}

# What events can watch (ensemble.events): omega's components are the kernel's state rows 0..2, the energy and |L|
# physics' value_ functions. (The tilt is measured from each member's spin axis, which the kernels do not hold.)
EVENT_VALUES = {"omega": ("state", 0), "energy": ("function", "value_energy"),
                "angular_momentum": ("function", "value_angular_momentum")}

_FLAT_BODY_RTOL = 1e-9  # a flat body sits exactly on the triangle inequality lambda3 = lambda1 + lambda2


def sizes(constants: dict) -> dict[str, int]:
    """Dimensions besides member and t: the three body axes."""
    return {"axis": 3}


def coordinates(constants: dict) -> dict[str, tuple[np.ndarray, str]]:
    return {"axis": (np.array(AXES, dtype=np.int32), "body-frame principal axis")}


def check_constants(constants: dict) -> None:
    """A body run has no run constants besides its shape."""


def check(values: dict[str, np.ndarray]) -> None:
    """Physical constraints on per-member parameters; raises ParameterError for the first broken one."""
    unknown = ~np.isin(values["spin_axis"], AXES)
    if np.any(unknown):
        raise ParameterError("spin_axis", f"must be 1, 2 or 3, got {values['spin_axis'][np.argmax(unknown)]:g}")
    moments = [values[f"lambda{i}"] for i in AXES]
    for i, moment in zip(AXES, moments):
        if np.any(moment <= 0):
            raise ParameterError(f"lambda{i}", f"must be > 0 (got {moment.min():g})")
    if np.any(values["c"] < 0):
        raise ParameterError("c", f"must be >= 0 (got {values['c'].min():g})")
    if np.any(values["spin0"] <= 0):
        raise ParameterError("spin0", f"must be > 0: the tilt of a body at rest is undefined (got "
                                      f"{values['spin0'].min():g})")
    if np.any((values["tilt0"] < 0) | (values["tilt0"] > np.pi)):
        raise ParameterError("tilt0", "must lie in [0, pi]")
    for i in range(3):
        others = moments[(i + 1) % 3] + moments[(i + 2) % 3]
        broken = moments[i] > others * (1 + _FLAT_BODY_RTOL)
        if np.any(broken):
            m = int(np.argmax(broken))
            raise ParameterError(f"lambda{i + 1}", f"exceeds the sum of the other two moments (member {m}: "
                                                   f"{moments[0][m]:.6g}, {moments[1][m]:.6g}, {moments[2][m]:.6g} "
                                                   f"kg m2): no rigid body has that")


def check_exact(values: dict[str, np.ndarray]) -> None:
    """The closed form holds without drag only."""
    if np.any(values["c"] != 0):
        raise ParameterError("c", "the closed form (method 'exact', [measure] error) holds only for c = 0")


def derive(values: dict[str, np.ndarray], constants: dict) -> dict[str, np.ndarray]:
    return {}


def from_body(body: Body, source: str) -> dict[str, np.ndarray]:
    """lambda1 <= lambda2 <= lambda3 (kg m2, per member): a body's principal moments about its centre of mass."""
    moments = np.linalg.eigvalsh(body.inertia).reshape(-1, 3)
    return {f"lambda{i}": moments[:, i - 1] for i in AXES}


def _moments(values) -> np.ndarray:
    return np.stack([values[f"lambda{i}"] for i in AXES])


def spin_axes(spin_axis) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows (0-based) of the spin axis k and of the next two axes i, j in cyclic order, per member."""
    k = np.asarray(spin_axis).astype(int) - 1
    return k, (k + 1) % 3, (k + 2) % 3


def _pick(rows: np.ndarray, row: np.ndarray) -> np.ndarray:
    """rows (3, ..., members) at each member's row (members,)."""
    return np.take_along_axis(rows, np.broadcast_to(row, rows.shape[1:])[None], axis=0)[0]


def initial_state(values: dict[str, np.ndarray], constants: dict) -> np.ndarray:
    """Body rates at t = 0, shape (3, members), rad/s: spin0 cos tilt0 along the spin axis k, and spin0 sin
    tilt0 (cos azimuth0, sin azimuth0) along the next two axes in cyclic order."""
    spin, tilt, azimuth = values["spin0"], values["tilt0"], values["azimuth0"]
    k, i, j = spin_axes(values["spin_axis"])
    members = np.arange(spin.shape[0])
    state = np.empty((3, spin.shape[0]))
    state[i, members] = spin * libm.sin(tilt) * libm.cos(azimuth)
    state[j, members] = spin * libm.sin(tilt) * libm.sin(azimuth)
    state[k, members] = spin * libm.cos(tilt)
    return state


def rates(values: dict[str, np.ndarray]) -> np.ndarray:
    """Kernel parameters, shape (12, members): a1, a2, a3 (1), r1, r2, r3 (1/s), lambda1..3 and 1/lambda1..3
    (the splitting works in L = lambda w). No division in the hot loop."""
    lam = _moments(values)
    a = np.stack([(lam[(i + 1) % 3] - lam[(i + 2) % 3]) / lam[i] for i in range(3)])
    return np.concatenate((a, values["c"][None] / lam, lam, 1.0 / lam))


def inputs(values: dict[str, np.ndarray], constants: dict) -> tuple[np.ndarray, np.ndarray]:
    """Kernel state and parameters: body rates (3, members) and `rates` (12, members)."""
    return initial_state(values, constants), rates(values)


def kernel_rows(constants: dict) -> tuple[int, int]:
    return 3, 12


def exact(values: dict[str, np.ndarray], constants: dict, t: np.ndarray) -> np.ndarray:
    """Torque-free body rates at times t (s; (times,), or (times, members) for each member's own) in Jacobi
    elliptic functions; shape (times, 3, members).

    Members must have c = 0 (see check_exact). Per member the axes are put in
    the order (cn axis, intermediate axis, dn axis): the dn axis is the one
    the rate vector circles, the largest moment when L^2 >= 2 E lambda_mid,
    else the smallest. An odd reordering reverses the equations' sign, which
    negating the rates undoes. Then (Landau and Lifshitz, Mechanics, 37)
    w = (A1 cn u, A2 sn u, A3 dn u) with u = s Omega t + u0, where s carries
    the sense of the rotation and u0 = F(phi0 | m) the initial phase. Near the
    separatrix (a small tilt about the intermediate axis) m is within rounding
    of 1 and the solution holds only to about eps / (1 - m).
    """
    from scipy.special import ellipj, ellipk, ellipkinc  # here: scipy.special costs every run 0.2 s to import

    frame, parity, lam_f, w, to_dn, to_cn, rate, m = _elliptic(values, constants)
    with np.errstate(divide="ignore", invalid="ignore"):
        a1 = np.sqrt(to_dn / np.abs(lam_f[0] * (lam_f[2] - lam_f[0])))
        a2 = np.sqrt(to_dn / np.abs(lam_f[1] * (lam_f[2] - lam_f[1])))
        a3 = np.sqrt(to_cn / np.abs(lam_f[2] * (lam_f[2] - lam_f[0])))
        phi0 = libm.arctan2(np.where(a2 > 0, w[1] / a2, 0.0), np.where(a1 > 0, w[0] / a1, 0.0))
    sense = np.where(w[2] < 0, -1.0, 1.0) * np.sign(lam_f[2] - lam_f[1])
    moving = np.isfinite(rate) & (rate > 0) & np.isfinite(m)
    u0 = ellipkinc(phi0, np.where(moving, m, 0.0))
    u = np.where(moving, sense * rate, 0.0)[None, :] * times_by_members(t) + u0
    period = 4 * ellipk(np.where(moving, m, 0.0))  # sn, cn and dn repeat after 4 K: ellipj is most exact near 0
    sn, cn, dn, _ = ellipj(np.mod(u, period[None, :]), np.where(moving, m, 0.0)[None, :])
    spun = np.stack((a1 * cn, a2 * sn, np.where(w[2] < 0, -1.0, 1.0) * a3 * dn), axis=1)  # (t, 3, members)
    spun = np.where(moving[None, None, :], spun, w[None])  # a body spinning about a principal axis stays
    out = np.empty_like(spun)
    np.put_along_axis(out, np.broadcast_to(frame[None], spun.shape), parity * spun, axis=1)
    return out


def flip_period(values: dict[str, np.ndarray], constants: dict) -> np.ndarray:
    """Period (s) of the torque-free motion of the rates, 4 K(m) / Omega (see exact): started near the
    intermediate axis, the time in which the body flips over and back (its tilt from the spin axis goes to
    near pi and returns). c = 0 theory; inf for a body spinning exactly about a principal axis. K is evaluated
    from 1 - m, which near the separatrix is computed without cancellation."""
    from scipy.special import ellipkm1

    _, _, lam_f, w, _, _, rate, _ = _elliptic(values, constants)
    with np.errstate(divide="ignore", invalid="ignore"):
        complement = (lam_f[2] - lam_f[0]) * (lam_f[2] * (lam_f[2] - lam_f[1]) * w[2] ** 2
                                              - lam_f[0] * (lam_f[1] - lam_f[0]) * w[0] ** 2) / (
            (lam_f[2] - lam_f[1]) * _spread(_moments(values), initial_state(values, constants), lam_f[0]))
        return np.where(rate > 0, 4 * ellipkm1(np.clip(complement, 0.0, 1.0)) / rate, np.inf)


def _elliptic(values: dict[str, np.ndarray], constants: dict):
    """What the elliptic solution needs, per member (see exact): the axes in the formula's order (cn, sn, dn)
    `frame` (3, members), its `parity` (+-1), the moments `lam_f` and rates `w` (times parity) in that order,
    |2 E lam_f[2] - L^2| and |L^2 - 2 E lam_f[0]|, the rate Omega (1/s) and the parameter m."""
    lam = _moments(values)
    w0 = initial_state(values, constants)
    order = np.argsort(lam, axis=0, kind="stable")  # ascending moments, per member
    middle = np.take_along_axis(lam, order[1:2], axis=0)[0]
    frame = np.where(_spread(lam, w0, middle) >= 0, order, order[::-1])  # about the largest: L^2 >= 2 E lam_mid
    parity = np.where(np.linalg.det(np.eye(3)[frame.T]) > 0, 1.0, -1.0)
    lam_f = np.take_along_axis(lam, frame, axis=0)
    w = parity * np.take_along_axis(w0, frame, axis=0)
    to_dn = np.abs(_spread(lam, w0, lam_f[2]))
    to_cn = np.abs(_spread(lam, w0, lam_f[0]))
    with np.errstate(divide="ignore", invalid="ignore"):
        rate = np.sqrt(np.abs((lam_f[2] - lam_f[1]) / (lam_f[0] * lam_f[1] * lam_f[2])) * to_cn)
        m = np.clip(np.abs((lam_f[1] - lam_f[0]) / (lam_f[2] - lam_f[1])) * to_dn / to_cn, 0.0, 1.0)
    return frame, parity, lam_f, w, to_dn, to_cn, rate, m


def _spread(lam: np.ndarray, w: np.ndarray, moment: np.ndarray) -> np.ndarray:
    """L^2 - 2 E moment = sum_i lambda_i (lambda_i - moment) w_i^2, summed without the cancellation of the
    difference (a start near a principal axis has both terms nearly equal)."""
    return np.sum(lam * (lam - moment) * w**2, axis=0)


def tilt(w: np.ndarray, spin_axis) -> np.ndarray:
    """Angle (rad) between omega and the spin axis: w (3, ..., members) rad/s; spin_axis 1, 2 or 3, one or per
    member."""
    k, i, j = spin_axes(spin_axis)
    return libm.arctan2(libm.hypot(_pick(w, i), _pick(w, j)), _pick(w, k))


def kinetic_energy(omega: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """1/2 sum lambda_i w_i^2 (J); omega (..., 3) rad/s, lam (..., 3) kg m2."""
    return 0.5 * np.sum(lam * omega**2, axis=-1)


def angular_momentum(omega: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """|L| = |(lambda_i w_i)| (kg m2 s-1); omega (..., 3), lam (..., 3)."""
    return np.sqrt(np.sum((lam * omega) ** 2, axis=-1))


def observe(samples: np.ndarray, names, values: dict[str, np.ndarray], constants: dict) -> dict[str, np.ndarray]:
    """Saved variables from kernel samples of shape (t, 3, members), member-major."""
    omega = np.ascontiguousarray(samples.transpose(2, 0, 1))  # (members, t, 3)
    lam = _moments(values).T[:, None, :]
    out = {}
    if "omega" in names:
        out["omega"] = omega
    if "tilt" in names:
        out["tilt"] = np.ascontiguousarray(tilt(samples.transpose(1, 0, 2), values["spin_axis"]).T)
    if "energy" in names:
        out["energy"] = kinetic_energy(omega, lam)
    if "angular_momentum" in names:
        out["angular_momentum"] = angular_momentum(omega, lam)
    return out


def conserved_energy(ds) -> np.ndarray:
    """The kinetic energy (J, (member, t)) of members without drag; NaN for the others."""
    if "energy" not in ds:
        raise KeyError("energy")
    energy = ds["energy"].values.copy()
    energy[ds["c"].values != 0] = np.nan
    return energy


# ---------------------------------------------------------------- linear theory about the spin axis

def transverse_exponents(values: dict[str, np.ndarray], constants: dict) -> np.ndarray:
    """Exponents mu (1/s, complex, shape (2, members)) of small tilts about the spin axis k at the start:
    d(w_i, w_j)/dt = [[-r_i, a_i w_k], [a_j w_k, -r_j]] (w_i, w_j), so mu = -(r_i + r_j)/2 +- sqrt(((r_i -
    r_j)/2)^2 + a_i a_j w_k^2), with w_k = spin0 cos tilt0 (rad/s). Without drag:
    +-i Omega_k about a stable axis, Omega_k = spin0 sqrt((lambda_i - lambda_k)(lambda_j - lambda_k) / (lambda_i
    lambda_j)); +-sigma about the intermediate one."""
    _, i, j = spin_axes(values["spin_axis"])
    a, r = np.split(rates(values)[:6], 2)
    a_i, a_j, r_i, r_j = _pick(a, i), _pick(a, j), _pick(r, i), _pick(r, j)
    wk = values["spin0"] * libm.cos(values["tilt0"])
    root = np.sqrt((((r_i - r_j) / 2) ** 2 + a_i * a_j * wk**2).astype(complex))
    return np.stack((-(r_i + r_j) / 2 + root, -(r_i + r_j) / 2 - root))


def step_exponents(method: Method, values: dict[str, np.ndarray], constants: dict, h: np.ndarray) -> np.ndarray:
    """What a fixed-step method of step h (s) shows of the exponents mu (see transverse_exponents): log(R(h mu)) / h
    for a Runge-Kutta method; for a splitting, log of the eigenvalues of its one-step map on small tilts, over h.
    Complex, shape (2, members), 1/s; the imaginary part is the wobble frequency the method shows."""
    if method.splitting is None:
        with np.errstate(divide="ignore", invalid="ignore"):
            factor = method.tableau.stability(h * transverse_exponents(values, constants))
            return np.log(factor.astype(complex)) / h
    step = _linear_split_step(method, values, constants, h)
    trace, det = step[0, 0] + step[1, 1], step[0, 0] * step[1, 1] - step[0, 1] * step[1, 0]
    root = np.sqrt((trace**2 / 4 - det).astype(complex))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.log(np.stack((trace / 2 + root, trace / 2 - root))) / h


def _linear_split_step(method: Method, values, constants, h) -> np.ndarray:
    """A splitting's one-step map (2, 2, members) on L across the spin axis k, (L_i, L_j) with i, j = k + 1, k + 2
    (cyclic), linearized about the spin L_k = lambda_k w_k. The turn about axis k turns (L_i, L_j) by -L_k tau /
    lambda_k; the turn about axis i, by the small angle L_i tau / lambda_i, moves L_j by +L_k L_i tau / lambda_i,
    the turn about j moves L_i by -L_k L_j tau / lambda_j (as L' = L x omega); drag scales each L_a by exp(-c tau /
    lambda_a)."""
    k, i, j = spin_axes(values["spin_axis"])
    lam = _moments(values)
    spin_l = _pick(lam, k) * values["spin0"] * libm.cos(values["tilt0"])
    n = spin_l.shape[0]
    zero, one = np.zeros(n), np.ones(n)
    step = np.broadcast_to(np.eye(2)[:, :, None], (2, 2, n)).copy()
    for piece, fraction in method.splitting.sequence:
        tau = h * fraction
        name = method.splitting.pieces[piece]
        if name == "drag":
            decay = libm.exp(-values["c"] * tau / lam)
            piece_map = np.array([[_pick(decay, i), zero], [zero, _pick(decay, j)]])
            spin_l = spin_l * _pick(decay, k)
        else:
            axis = int(name[-1]) - 1
            angle = spin_l * tau / lam[axis]
            turn = np.array([[libm.cos(angle), libm.sin(angle)], [-libm.sin(angle), libm.cos(angle)]])
            piece_map = np.where(axis == k, turn, np.where(axis == i, np.array([[one, zero], [angle, one]]),
                                                           np.array([[one, -angle], [zero, one]])))
        step = np.einsum("abm,bcm->acm", piece_map, step)
    return step


def wobble_frequency(values: dict[str, np.ndarray], constants: dict) -> np.ndarray:
    """Omega_k (rad/s) of small tilts about a stable spin axis (NaN about the intermediate one), c = 0 theory."""
    mu = transverse_exponents({**values, "c": np.zeros_like(values["c"])}, constants)[0]
    return np.where(np.abs(mu.imag) > np.abs(mu.real), np.abs(mu.imag), np.nan)


def growth_rate(values: dict[str, np.ndarray], constants: dict) -> np.ndarray:
    """sigma (1/s) at which small tilts about the spin axis grow: the largest real exponent (with drag)."""
    return transverse_exponents(values, constants).real.max(axis=0)


STABILITY_AXES = ("h Omega",)


def axis_growth(method: Method, axis: str, x: np.ndarray) -> np.ndarray:
    """Growth per step of a small wobble at x = h Omega (no drag): max(|R(i x)|, 1). NaN for a splitting, whose
    one-step map depends on the moments and not on h Omega alone (see step_exponents)."""
    x = np.asarray(x, dtype=float)
    if method.tableau is None:
        return np.full(x.shape, np.nan)
    return np.maximum(np.abs(method.tableau.stability(1j * x)), 1.0)


def stability_axis(values: dict[str, np.ndarray], constants: dict, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each member's position h |mu| on the wobble axis (h in s)."""
    mu = transverse_exponents(values, constants)[0]
    return np.full(mu.shape, STABILITY_AXES[0]), h * np.abs(mu)


def step_growth(method: Method, values: dict[str, np.ndarray], constants: dict, h: np.ndarray) -> np.ndarray:
    """Theory: per-step factor of the fastest small tilt, the largest |exp(h mu)| the method shows."""
    return np.max(np.abs(np.exp(h * step_exponents(method, values, constants, h))), axis=0)


def amplitudes(samples: np.ndarray, values: dict[str, np.ndarray], constants: dict) -> np.ndarray:
    """The tilt's two motions: |rates across the spin axis| and |rate along it| (rad/s), (members, 2, samples)."""
    w = samples.transpose(1, 0, 2)
    k, i, j = spin_axes(values["spin_axis"])
    return np.stack((libm.hypot(_pick(w, i), _pick(w, j)), np.abs(_pick(w, k)))).transpose(2, 0, 1)
