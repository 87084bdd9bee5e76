"""Spring chains: N masses joined by springs, between walls, free, or in a ring.

    m_i x_i'' = -k_{i-1} (x_i - x_{i-1}) - k_i (x_i - x_{i+1})

Boundaries: "fixed" (walls at both ends, N+1 springs), "free" (N-1 springs),
"periodic" (a ring of N springs). Spring s connects, in order:
fixed: the left wall and mass 1, mass s and s+1, ..., mass N and the right wall;
free: mass s and s+1; periodic: mass s and s+1, the last one mass N and mass 1.
Displacements x (m) are measured from equilibrium. The compiled acceleration of a mass,
from which ensemble.engine.sites builds the kernels, is in `physics.py` beside this file.
"""
from __future__ import annotations

import numpy as np

from ... import libm
from ...methods import KICK_DRIFT, Method
from ...parameter import Mode, Parameter, ParameterError
from ..closed_form import times_by_members

NAME = "chain"
PHYSICS = "ensemble.scenes.chain.physics"  # `acceleration` of a mass between its neighbours
SITES = True  # a member is a field of sites: the engine builds its kernels from ensemble.engine.sites
PIECES = KICK_DRIFT  # splitting methods: kick (v += tau a(x)) and drift (x += tau v)
EVALUATING_PIECES = ("kick",)  # a kick evaluates the forces
BOUNDARIES = ("fixed", "free", "periodic")

PARAMETERS = {
    "n": Parameter("1", "number of masses", integer=True),
    "boundary": Parameter("1", "boundary of the chain", default="fixed", choices=BOUNDARIES),
    "m": Parameter("kg", "mass", per="site"),
    "k": Parameter("N m-1", "spring constant", per="spring"),
    "x0": Parameter("m", "displacement at t = 0", default=0.0, per="site", mode=True),
    "v0": Parameter("m s-1", "velocity at t = 0", default=0.0, per="site", mode=True),
    "omega_max": Parameter("rad s-1", "highest normal frequency: each member's springs k are scaled by one factor "
                                      "to give it", optional=True),
}

OBSERVABLES: dict[str, tuple[tuple[str, ...], str, str]] = {
    "x": (("member", "t", "site"), "m", "displacement from equilibrium"),
    "v": (("member", "t", "site"), "m s-1", "velocity"),
    "energy": (("member", "t"), "J", "total energy 1/2 v.M.v + 1/2 x.K.x"),
}
EVENT_VALUES = {"x": ("state", 0), "v": ("state", "n")}  # ensemble.events: v's first row is the constant n


def spring_count(n: int, boundary: str) -> int:
    return {"fixed": n + 1, "free": n - 1, "periodic": n}[boundary]


def sizes(constants: dict) -> dict[str, int]:
    """Length of the per-site and per-spring parameters."""
    return {"site": constants["n"], "spring": spring_count(constants["n"], constants["boundary"])}


def coordinates(constants: dict) -> dict[str, tuple[np.ndarray, str]]:
    """Coordinate variables of the dimensions in `sizes`: values and long_name."""
    return {"site": (np.arange(1, constants["n"] + 1, dtype=np.int32), "mass number along the chain"),
            "spring": (np.arange(1, spring_count(constants["n"], constants["boundary"]) + 1, dtype=np.int32),
                       "spring number along the chain")}


def check_constants(constants: dict) -> None:
    """The run constants n and boundary; raises ParameterError."""
    if constants["n"] < 1:
        raise ParameterError("n", f"must be >= 1, got {constants['n']}")
    if constants["boundary"] == "free" and constants["n"] < 2:
        raise ParameterError("n", "a free chain needs at least 2 masses (it has n - 1 springs)")
    if constants["boundary"] == "periodic" and constants["n"] < 2:
        raise ParameterError("n", "a ring needs at least 2 masses (with one, its spring would join the mass to itself)")


def check(values: dict[str, np.ndarray]) -> None:
    """Physical constraints on per-member parameters; raises ParameterError for the first broken one."""
    for name in ("m", "k", "omega_max"):
        if name in values and values[name].size and np.any(values[name] <= 0):
            raise ParameterError(name, f"must be > 0 (got {values[name].min():g})")


def derive(values: dict[str, np.ndarray], constants: dict) -> dict[str, np.ndarray]:
    """Parameters computed from others: with omega_max, the springs k scaled to give that highest frequency.

    Raises ParameterError.

    Scaling every spring of a member by one factor keeps its mode shapes and
    multiplies every frequency by the factor's square root.
    """
    if "omega_max" not in values:
        return {}
    highest = normal_modes(values["m"], values["k"], constants["boundary"])[0][..., -1]
    if np.any(highest <= 0):
        raise ParameterError("omega_max", "needs a chain with a moving mode; this one has only zero modes")
    return {"k": values["k"] * ((values["omega_max"] / highest) ** 2)[:, None]}


def incidence(n: int, boundary: str) -> np.ndarray:
    """D (springs, n) with spring extensions D @ x."""
    d = np.zeros((spring_count(n, boundary), n))
    for s in range(d.shape[0]):
        if boundary == "fixed":
            if s < n:
                d[s, s] += 1.0
            if s > 0:
                d[s, s - 1] -= 1.0
        else:  # free: s and s + 1; periodic: s and (s + 1) mod n
            d[s, (s + 1) % n] += 1.0
            d[s, s] -= 1.0
    return d


def stiffness(k: np.ndarray, n: int, boundary: str) -> np.ndarray:
    """K = D^T diag(k) D, shape (..., n, n), N/m; k of shape (..., springs). Each spring touches one or two
    masses, so K is summed spring by spring in O(n) per member (tridiagonal, plus two corners for a ring)."""
    d = incidence(n, boundary)
    k = np.asarray(k, dtype=float)
    flat = k.reshape(-1, k.shape[-1])
    out = np.zeros((flat.shape[0], n, n))
    spring, column = np.nonzero(d)
    pairs = [(s, i, j) for s in range(d.shape[0]) for i in column[spring == s] for j in column[spring == s]]
    s, i, j = (np.array(x, dtype=int) for x in zip(*pairs))
    np.add.at(out, (slice(None), i, j), flat[:, s] * d[s, i] * d[s, j])
    return out.reshape(k.shape[:-1] + (n, n))


def extensions(x: np.ndarray, boundary: str) -> np.ndarray:
    """Spring extensions D @ x (m), (..., springs) from x (..., n), in O(n): each spring's right end minus its
    left end, a wall counting as 0 (see incidence)."""
    if boundary == "fixed":
        wall = np.zeros(x.shape[:-1] + (1,))
        return np.concatenate([x, wall], axis=-1) - np.concatenate([wall, x], axis=-1)
    if boundary == "free":
        return x[..., 1:] - x[..., :-1]
    return np.roll(x, -1, axis=-1) - x  # periodic


def energy(x, v, m, k, boundary: str) -> np.ndarray:
    """1/2 v.M.v + 1/2 x.K.x (J); x, v (..., n), m (..., n), k (..., springs) broadcast. O(n) per sample."""
    stretch = extensions(x, boundary)
    return 0.5 * np.sum(m * v * v, axis=-1) + 0.5 * np.sum(k * stretch * stretch, axis=-1)


def normal_modes(m, k, boundary: str = "fixed") -> tuple[np.ndarray, np.ndarray]:
    """Frequencies (rad/s, ascending) and mode shapes of K v = w^2 M v.

    m (..., n) kg, k (..., springs) N/m. Returns omega (..., n) and shapes
    (..., n, n) whose columns are M-orthonormal (shape^T M shape = I), each
    with its first clearly nonzero entry positive. Solved as the symmetric
    problem M^-1/2 K M^-1/2 u = w^2 u, which stays accurate for large mass
    ratios. Zero modes of free and periodic chains have omega = 0.
    """
    m = np.asarray(m, dtype=float)
    k = np.asarray(k, dtype=float)
    n = m.shape[-1]
    root = np.sqrt(m)
    scaled = stiffness(k, n, boundary) / (root[..., :, None] * root[..., None, :])
    eigenvalues, u = np.linalg.eigh(scaled)
    scale = np.abs(eigenvalues).max(axis=-1, keepdims=True)
    eigenvalues = np.where(eigenvalues < 1e-13 * scale, 0.0, eigenvalues)  # rounding around a zero mode
    shapes = u / root[..., :, None]
    big = np.abs(shapes) > 1e-8 * np.abs(shapes).max(axis=-2, keepdims=True)
    first = np.take_along_axis(shapes, np.argmax(big, axis=-2)[..., None, :], axis=-2)
    return np.sqrt(eigenvalues), shapes * np.sign(first)


def step_eigenvalue(method: Method, omega, h: float) -> np.ndarray:
    """What one step of `method` does to a normal mode of frequency omega (rad/s): a complex factor.

    Its angle over h is the frequency the method shows, its modulus the
    amplitude growth per step (1 for a stable symplectic step). Runge-Kutta:
    R(i omega h); splittings: the eigenvalue of the one-step map of
    x'' = -omega^2 x with positive angle, or past the stability limit, where
    both are real, the larger one; exact: exp(i omega h).
    """
    omega = np.asarray(omega, dtype=float)
    if method.closed_form:
        return np.exp(1j * omega * h)
    if method.tableau is not None:
        return method.tableau.stability(1j * omega * h)
    step = np.broadcast_to(np.eye(2), omega.shape + (2, 2)).copy()
    for piece, fraction in method.splitting.sequence:
        tau = fraction * h
        one = np.broadcast_to(np.eye(2), omega.shape + (2, 2)).copy()
        if method.splitting.pieces[piece] == "drift":
            one[..., 0, 1] = tau  # x += tau v
        else:
            one[..., 1, 0] = -omega**2 * tau  # v += tau a
        step = one @ step
    eigenvalues = np.linalg.eigvals(step)
    first, second = eigenvalues[..., 0], eigenvalues[..., 1]
    # past the limit both are real: the one that grows
    pick_first = (first.imag > second.imag) | ((first.imag == second.imag) & (np.abs(first) >= np.abs(second)))
    return np.where(pick_first, first, second)


#: The dimensionless steps a chain's stability is read against.
STABILITY_AXES = ("h omega_max",)


def axis_growth(method: Method, axis: str, x: np.ndarray) -> np.ndarray:
    """Growth factor per step of a normal mode at x = h omega on STABILITY_AXES[0]."""
    return np.abs(step_eigenvalue(method, x, 1.0))


def stability_axis(values: dict[str, np.ndarray], constants: dict, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each member's stability axis and position on it: h omega_max, h (s) per member."""
    highest = normal_modes(values["m"], values["k"], constants["boundary"])[0][..., -1]
    return np.full(highest.shape, STABILITY_AXES[0]), h * highest


def step_growth(method: Method, values: dict[str, np.ndarray], constants: dict, h: np.ndarray) -> np.ndarray:
    """Theory: the growth factor per step of a member's fastest-growing normal mode; h (s) per member.

    A mode missing from the start still grows (or decays) from rounding, so
    after long enough it dominates the energy, whatever the start.
    """
    omega = normal_modes(values["m"], values["k"], constants["boundary"])[0]
    return axis_growth(method, STABILITY_AXES[0], np.asarray(h)[:, None] * omega).max(axis=-1)


def amplitudes(samples: np.ndarray, values: dict[str, np.ndarray], constants: dict) -> np.ndarray:
    """sqrt(energy) (sqrt(J)) of each member at each sample, shape (members, 1, samples): the chain's one motion
    whose growth is measured (its fastest-growing mode soon dominates the energy)."""
    e = observe(samples, ("energy",), values, constants)["energy"]  # (members, samples)
    return np.sqrt(e)[:, None, :]


def mode_start(mode: Mode, m, k, boundary: str) -> np.ndarray:
    """Displacements (or velocities) along normal mode `mode.number`, largest entry `mode.amplitude`."""
    _, shapes = normal_modes(m, k, boundary)
    shape = shapes[..., :, mode.number - 1]
    return mode.amplitude * shape / np.abs(shape).max(axis=-1, keepdims=True)


def kernel_springs(k: np.ndarray, n: int, boundary: str) -> np.ndarray:
    """Spring constants in the kernels' layout, shape (n + 2, members).

    The kernels number masses 1..n with ghost sites 0 and n+1 (at rest for
    walls and free ends; copies of masses n and 1 in a ring); row r holds the
    spring between sites r - 1 and r, and row 0 is unused.
    """
    members = k.shape[0]
    rows = np.zeros((n + 2, members))
    if boundary == "fixed":
        rows[1:] = k.T
    elif boundary == "free":
        rows[2:n + 1] = k.T
    else:
        rows[2:n + 1] = k[:, :n - 1].T
        rows[1] = rows[n + 1] = k[:, n - 1]
    return rows


def inputs(values: dict[str, np.ndarray], constants: dict) -> tuple[np.ndarray, np.ndarray]:
    """Kernel state (x; v) and parameters (k_left / m; k_right / m), each shape (2n, members)."""
    n, boundary = constants["n"], constants["boundary"]
    state = np.concatenate((values["x0"].T, values["v0"].T))
    springs = kernel_springs(values["k"], n, boundary)
    minv = 1.0 / values["m"].T
    return state, np.concatenate((springs[1:n + 1] * minv, springs[2:] * minv))


def kernel_rows(constants: dict) -> tuple[int, int]:
    """Rows of the kernel state (x; v) and parameter (k_left / m; k_right / m) arrays."""
    return 2 * constants["n"], 2 * constants["n"]


def exact(values: dict[str, np.ndarray], constants: dict, t: np.ndarray) -> np.ndarray:
    """Modal superposition at times t (s; (times,), or (times, members) for each member's own); samples (times,
    2n, members) as (x; v).

    q_j(t) = q_j(0) cos(w_j t) + q_j'(0) sin(w_j t) / w_j, with q = shape^T M x;
    a zero mode drifts: q(t) = q(0) + q'(0) t.
    """
    boundary = constants["boundary"]
    t = times_by_members(t).T[:, :, None]  # (M or 1, T, 1)
    m = values["m"]
    omega, shapes = normal_modes(m, values["k"], boundary)  # (M, n), (M, n, n)
    q0 = np.einsum("mij,mi->mj", shapes, m * values["x0"])
    p0 = np.einsum("mij,mi->mj", shapes, m * values["v0"])
    wt = omega[:, None, :] * t  # (M, T, n)
    moving = omega[:, None, :] > 0
    safe = np.where(moving, omega[:, None, :], 1.0)
    q = q0[:, None] * libm.cos(wt) + p0[:, None] * np.where(moving, libm.sin(wt) / safe, t)
    qdot = -q0[:, None] * omega[:, None, :] * libm.sin(wt) + p0[:, None] * libm.cos(wt)
    x = np.einsum("mij,mtj->tim", shapes, q)
    v = np.einsum("mij,mtj->tim", shapes, qdot)
    return np.concatenate((x, v), axis=1)


def observe(samples: np.ndarray, names, values: dict[str, np.ndarray], constants: dict) -> dict[str, np.ndarray]:
    """Saved variables from samples (t, 2n, members), member-major."""
    n = constants["n"]
    x = samples[:, :n].transpose(2, 0, 1)
    v = samples[:, n:].transpose(2, 0, 1)
    out = {}
    if "x" in names:
        out["x"] = np.ascontiguousarray(x)
    if "v" in names:
        out["v"] = np.ascontiguousarray(v)
    if "energy" in names:
        from .physics import sample_energy  # compiled: the model alone does not import Numba

        out["energy"] = sample_energy(np.ascontiguousarray(samples.transpose(2, 0, 1)),
                                      np.ascontiguousarray(values["m"], dtype=float),
                                      np.ascontiguousarray(values["k"], dtype=float),
                                      BOUNDARIES.index(constants["boundary"]))
    return out


def conserved_energy(ds) -> np.ndarray:
    """The saved energy (J, (member, t)): every chain conserves it. Raises KeyError naming it when not saved."""
    if "energy" not in ds:
        raise KeyError("energy")
    return ds["energy"].values
