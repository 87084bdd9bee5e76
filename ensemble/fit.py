"""Fits over result datasets: tilt decay rates of tops, normal-mode frequencies of chains, the growth rates,
wobble frequencies and flip periods of free bodies.

Each fit takes a result Dataset (as `ensemble run` writes it) and returns a
Dataset over its members. Beside every estimate stand two predictions: the
physics (`*_theory`) and what the run's numerical method shows (`*_method`,
which equals the physics for `exact` and the top's split methods), so a
physics effect can be told from an integrator effect.

Error bars: with observation noise (the variable's `observation_noise_stddev`
attribute) they follow from that noise; without it, from the fit residuals.
A member whose fit is impossible (non-finite data, too few usable samples)
gets NaN and is counted in the result's `members_failed` attribute.
"""
from __future__ import annotations

import numpy as np
import xarray as xr
from scipy.interpolate import CubicSpline
from scipy.optimize import least_squares, linear_sum_assignment
from scipy.signal import find_peaks
from scipy.signal.windows import blackmanharris

from .errors import EnsembleError
from .methods import METHODS
from .scenes import body, chain, top

MIN_SAMPLES = 5  # usable samples a member needs for a fit
TILT_FLOOR = 1e-150  # rad: noise-free tilts below this are too close to underflow to use
NOISE_WINDOW = 5.0  # noisy tilts are used while the fitted tilt is this many stddevs from 0 and pi/2
PEAK_FALSE_ALARM = 30.0  # a spectral peak counts when its power exceeds this many times the noise's
PEAK_DYNAMIC_RANGE = 1e-7  # peaks weaker than this fraction of the strongest are rounding, not modes
MIN_PERIODS = 4  # periods a mode must complete in the record: slower ones sit in the drift's main lobe


class FitError(EnsembleError, ValueError):
    """A result that cannot be fitted: wrong scene, missing variables, too few samples."""


def _require(ds: xr.Dataset, scene: str, variables: tuple[str, ...], fit: str) -> None:
    found = ds.attrs.get("scene")
    if found != scene:
        what = "a " + repr(found) if found else "not from ensemble"
        raise FitError(f"{fit} needs a {scene} result; this one is {what}"
                       f" result")
    missing = [v for v in variables if v not in ds.variables]
    if missing:
        raise FitError(f"{fit}: the result lacks {', '.join(missing)} (save them in the run file)")
    if ds.sizes.get("t", 0) < MIN_SAMPLES:
        raise FitError(f"{fit}: the result has {ds.sizes.get('t', 0)} saved times; a fit needs at least {MIN_SAMPLES}")


def _noise(var: xr.DataArray) -> float:
    return float(var.attrs.get("observation_noise_stddev", 0.0))


def _members(ds: xr.Dataset) -> dict[str, xr.DataArray]:
    coords = {"member": ds["member"]}
    if "sweep_point" in ds:
        coords["sweep_point"] = ds["sweep_point"]
    return coords


# ---------------------------------------------------------------- tops


def member_settings(ds: xr.Dataset) -> tuple[np.ndarray, np.ndarray]:
    """Each member's method (names) and dt (s; NaN where none): per-member variables when swept, else attributes."""
    n = ds.sizes["member"]
    if "method" in ds.variables:
        names = np.array(ds["method"].attrs["flag_meanings"].split())
        methods = names[ds["method"].values.astype(int)]
    else:
        methods = np.full(n, ds.attrs["method"])
    dt = ds["dt"].values if "dt" in ds.variables else np.full(n, float(ds.attrs.get("dt", np.nan)))
    return methods, dt


def _method_prediction(ds: xr.Dataset, theory: np.ndarray, predict) -> np.ndarray:
    """What each member's method shows: predict(method (a Method), dt, member indices) per (method, dt) group.

    Adaptive methods keep their error to the tolerance: they show the physics.
    """
    methods, dt = member_settings(ds)
    out = np.array(theory, dtype=float, copy=True)
    for name, step in set(zip(methods, dt)):
        method = METHODS[name]
        if method.adaptive or not np.isfinite(step):
            continue
        chosen = np.flatnonzero((methods == name) & ((dt == step) | (np.isnan(dt) & np.isnan(step))))
        out[chosen] = predict(method, step, chosen)
    return out


def tilt_decay(ds: xr.Dataset) -> xr.Dataset:
    """Fit tan(tilt) ~ exp(-rate t) per member of a top result.

    Returns over member: rate (1/s; negative when the tilt grows, as for a
    prolate top), rate_stderr, rate_theory = c (1/lambda1 - 1/lambda3),
    rate_method (what the run's method shows, see top.tilt_rate_method),
    z = (rate - rate_theory) / rate_stderr, z_method likewise, and samples_used.
    """
    _require(ds, "top", ("tilt", "lambda1", "lambda3", "c", "tilt0", "spin0"), "tilt_decay")
    t = ds["t"].values
    tilt = ds["tilt"].values
    sigma = _noise(ds["tilt"])
    values = {name: ds[name].values for name in top.PARAMETERS if name in ds}
    intercept, rate, stderr, used = _tilt_fit_noisy(t, tilt, sigma) if sigma > 0 else _tilt_fit_clean(t, tilt)
    theory = values["c"] * (1 / values["lambda1"] - 1 / values["lambda3"])
    method = _method_prediction(ds, theory, lambda m, dt, chosen: top.tilt_rate_method(
        m, {k: v[chosen] for k, v in values.items()}, dt, t))
    data = {
        "rate": (rate, "s-1", "fitted tilt decay rate: tan(tilt) ~ exp(-rate t)"),
        "rate_stderr": (stderr, "s-1", "standard error of rate"),
        "rate_theory": (theory, "s-1", "c (1/lambda1 - 1/lambda3)"),
        "rate_method": (method, "s-1", "rate shown by the member's method at its dt"),
        "z": ((rate - theory) / stderr, "1", "(rate - rate_theory) / rate_stderr"),
        "z_method": ((rate - method) / stderr, "1", "(rate - rate_method) / rate_stderr"),
        "log_tan_tilt0": (intercept, "1", "fitted line's log tan(tilt) at t = 0"),
        "samples_used": (used, "1", "saved times inside the fitted part of the record"),
    }
    return _dataset(ds, data, "member", noise=sigma, fit="tilt_decay")


def _masked_line(t, y, mask):
    """Least-squares line y = a - rate t over mask, per row.

    Returns a, rate, the residual sum of squares, the count of masked-in
    samples and their sum of squared deviations of t (all per row).
    """
    w = mask.astype(float)
    y = np.where(mask, y, 0.0)
    count = w.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        t_mean = (w * t).sum(axis=1) / count
        y_mean = (w * y).sum(axis=1) / count
        dt = np.where(mask, t - t_mean[:, None], 0.0)
        sxx = (dt * dt).sum(axis=1)
        slope = (dt * (y - y_mean[:, None])).sum(axis=1) / sxx
        a = y_mean - slope * t_mean
        rss = (w * (y - a[:, None] - slope[:, None] * t) ** 2).sum(axis=1)
    return a, -slope, rss, count, sxx


def _tilt_fit_clean(t, tilt):
    """Noise-free: ordinary least squares of log tan(tilt) on t; stderr from the residuals."""
    with np.errstate(invalid="ignore", divide="ignore"):
        y = np.log(np.tan(tilt))
    mask = np.isfinite(y) & (tilt > TILT_FLOOR) & (tilt < np.pi / 2)
    a, rate, rss, count, sxx = _masked_line(t, y, mask)
    with np.errstate(invalid="ignore", divide="ignore"):
        stderr = np.sqrt(rss / (count - 2) / sxx)
    bad = count < MIN_SAMPLES
    return (np.where(bad, np.nan, a), np.where(bad, np.nan, rate), np.where(bad, np.nan, stderr),
            count.astype(np.int32))


def _tilt_fit_noisy(t, tilt, sigma, iterations=12):
    """Gaussian noise of stddev sigma on the tilt: least squares of tilt = atan(exp(a - rate t)).

    This is the line log tan(tilt) = a - rate t, fitted where the noise is
    Gaussian (on the tilt itself); the fitted part of the record is where the
    model tilt lies NOISE_WINDOW sigma inside (0, pi/2), chosen from the model
    and not from the noisy data, so the choice does not bias the fit.
    """
    finite = np.isfinite(tilt)
    lo, hi = NOISE_WINDOW * sigma, np.pi / 2 - NOISE_WINDOW * sigma
    with np.errstate(invalid="ignore", divide="ignore"):
        start = finite & (tilt > 2 * lo) & (tilt < np.pi / 2 - 2 * lo)
        a, rate, _, _, _ = _masked_line(t, np.log(np.tan(tilt)), start)
    for _ in range(iterations):
        model = np.arctan(np.exp(a[:, None] - rate[:, None] * t))
        mask = finite & (model > lo) & (model < hi)
        slope = np.where(mask, 0.5 * np.sin(2 * model), 0.0)  # d model / d a
        res = np.where(mask, tilt - model, 0.0)
        ja, jr = slope, -t * slope  # d model / d (a, rate)
        saa, sar, srr = (ja * ja).sum(1), (ja * jr).sum(1), (jr * jr).sum(1)
        ga, gr = (ja * res).sum(1), (jr * res).sum(1)
        with np.errstate(invalid="ignore", divide="ignore"):
            det = saa * srr - sar * sar
            a = a + (srr * ga - sar * gr) / det
            rate = rate + (saa * gr - sar * ga) / det
    count = mask.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        stderr = sigma * np.sqrt(saa / det)
    bad = (count < MIN_SAMPLES) | ~np.isfinite(rate)
    return (np.where(bad, np.nan, a), np.where(bad, np.nan, rate), np.where(bad, np.nan, stderr),
            count.astype(np.int32))


# ---------------------------------------------------------------- chains


def mode_frequencies(ds: xr.Dataset) -> xr.Dataset:
    """Estimate each chain member's normal-mode frequencies from its saved x(t) alone.

    Peaks of the windowed spectrum (summed over sites) give starting
    frequencies; a least-squares fit of a sum of sinusoids (plus a constant
    and a drift, per site) refines them far below the FFT bin 2 pi / T. The
    residual is searched again until no significant peak is left. Only then
    are the estimates matched to the theoretical frequencies (nearest, one to
    one). Returns over (member, mode): frequency (rad/s; NaN for modes not
    found, and for zero modes, which do not oscillate), frequency_stderr,
    frequency_theory (eigenfrequencies of K v = w^2 M v), frequency_method
    (what the run's method shows, see chain.step_eigenvalue), z, z_method,
    mode_amplitude (m, the start's amplitude in each mode) and excited (1
    where the start put energy in the mode, 0 where it did not: a chain
    started in one mode rings in no other; zero modes do not oscillate).
    """
    _require(ds, "chain", ("x", "m", "k"), "mode_frequencies")
    n, boundary = int(ds.attrs["n"]), str(ds.attrs["boundary"])
    t = ds["t"].values
    x = ds["x"].values
    sigma = _noise(ds["x"])
    theory, shapes = chain.normal_modes(ds["m"].values, ds["k"].values, boundary)
    amplitude, excited = _mode_amplitudes(ds, theory, shapes)
    method = _method_prediction(ds, theory, lambda m, dt, chosen: np.angle(
        chain.step_eigenvalue(m, theory[chosen], dt)) / dt)
    frequency = np.full(theory.shape, np.nan)
    stderr = np.full(theory.shape, np.nan)
    for i in range(x.shape[0]):
        found, errors = _member_frequencies(t, x[i], sigma, n)
        oscillating = np.flatnonzero(theory[i] > 0)
        if found.size == 0 or oscillating.size == 0:
            continue
        cost = np.abs(found[:, None] - method[i, oscillating][None, :])
        rows, cols = linear_sum_assignment(cost)
        frequency[i, oscillating[cols]] = found[rows]
        stderr[i, oscillating[cols]] = errors[rows]
    with np.errstate(invalid="ignore", divide="ignore"):
        z = (frequency - theory) / stderr
        z_method = (frequency - method) / stderr
    data = {
        "frequency": (frequency, "rad s-1", "fitted normal-mode angular frequency"),
        "frequency_stderr": (stderr, "rad s-1", "standard error of frequency"),
        "frequency_theory": (theory, "rad s-1", "eigenfrequency of K v = w^2 M v"),
        "frequency_method": (method, "rad s-1", "frequency shown by the member's method at its dt"),
        "z": (z, "1", "(frequency - frequency_theory) / frequency_stderr"),
        "z_method": (z_method, "1", "(frequency - frequency_method) / frequency_stderr"),
        "mode_amplitude": (amplitude, "m", "amplitude of the start in the mode"),
    }
    out = _dataset(ds, data, ("member", "mode"), noise=sigma, fit="mode_frequencies")
    out["excited"] = (("member", "mode"), excited.astype(np.int8),
                      {"long_name": "whether the start put energy in the mode",
                       "flag_values": np.array([0, 1], np.int8), "flag_meanings": "not_excited excited"})
    return out


EXCITED = 1e-9  # a mode holding less than this fraction of a member's largest mode amplitude was not excited


def _mode_amplitudes(ds: xr.Dataset, omega: np.ndarray, shapes: np.ndarray):
    """Each member's start in its modes: amplitude sqrt(a^2 + (b / w)^2) (m) with a, b the M-projections of x0
    and v0 on the mode, and whether it exceeds EXCITED of the member's largest. Zero modes: NaN, not excited."""
    mass = ds["m"].values
    x0 = ds["x"].values[:, 0, :]
    v0 = ds["v0"].values if "v0" in ds else np.zeros_like(x0)
    a = np.einsum("mij,mi->mj", shapes, mass * x0)
    b = np.einsum("mij,mi->mj", shapes, mass * v0)
    with np.errstate(divide="ignore", invalid="ignore"):
        amplitude = np.where(omega > 0, np.hypot(a, b / omega), np.nan)
    largest = np.nanmax(np.where(np.isfinite(amplitude), amplitude, 0.0), axis=1, keepdims=True)
    return amplitude, np.isfinite(amplitude) & (amplitude > EXCITED * largest)


class _VariableProjection:
    """The model x(t) = a + b t + sum_k (c_k cos w_k t + s_k sin w_k t) per site, linear in all but the w_k.

    least_squares asks for the residual and then the Jacobian at the same w, so the last factorization is kept.
    """

    def __init__(self, t: np.ndarray, x: np.ndarray):
        self.tc, self.x = t - t.mean(), x
        self.last = {}

    def design(self, w):
        phase = np.outer(self.tc, w)
        return np.hstack((np.ones((self.tc.size, 1)), self.tc[:, None], np.cos(phase), np.sin(phase)))

    def solve(self, w):
        """Least-squares amplitudes for frequencies w: orthonormal basis Q, amplitudes, residual."""
        if self.last.get("w") is None or not np.array_equal(self.last["w"], w):
            q, r = np.linalg.qr(self.design(w))
            projected = q.T @ self.x
            self.last.update(w=w.copy(), solved=(q, np.linalg.solve(r, projected), self.x - q @ projected))
        return self.last["solved"]

    def residual(self, w):
        return self.solve(w)[2].ravel()

    def jacobian(self, w):
        """Kaufman's variable-projection Jacobian: -(I - Q Q^T) (d design / d w_k) amplitudes, all k at once."""
        q, amplitudes, _ = self.solve(w)
        tc, (times, sites), k = self.tc, self.x.shape, w.size
        phase = np.outer(tc, w)  # (times, k)
        # d design / d w_k times the amplitudes: (times, sites, k)
        derivative = (-(tc[:, None] * np.sin(phase))[:, None, :] * amplitudes[2:2 + k].T[None, :, :]
                      + (tc[:, None] * np.cos(phase))[:, None, :] * amplitudes[2 + k:].T[None, :, :])
        flat = derivative.reshape(times, sites * k)
        projected = flat - q @ (q.T @ flat)
        return -projected.reshape(times * sites, k)


def _member_frequencies(t: np.ndarray, x: np.ndarray, sigma: float, most: int):
    """Frequencies (rad/s, ascending) and their standard errors in x (times, sites)."""
    if not np.all(np.isfinite(x)):
        return np.empty(0), np.empty(0)
    times, sites = x.shape
    window = blackmanharris(times)
    pad = 4 * 2 ** int(np.ceil(np.log2(times)))
    grid = 2 * np.pi * np.fft.rfftfreq(pad, t[1] - t[0])
    lobe = 4 * pad // times  # the window's main-lobe half width, in padded bins
    noise_power = sigma**2 * np.sum(window**2) * sites
    model = _VariableProjection(t, x)
    solve = model.solve

    scale = np.sqrt(np.mean(x**2))
    slowest = 2 * np.pi * MIN_PERIODS / (t[-1] - t[0])
    found = np.empty(0)
    strongest = None
    left = solve(found)[2]
    fit = None
    while found.size < most:
        power = np.sum(np.abs(np.fft.rfft(left * window[:, None], pad, axis=0)) ** 2, axis=1)
        power[grid < slowest] = 0.0
        strongest = strongest or power.max()
        floor = max(PEAK_DYNAMIC_RANGE * strongest, PEAK_FALSE_ALARM * noise_power)
        peaks, _ = find_peaks(power, height=floor, distance=lobe)
        new = [grid[p] for p in peaks if np.all(np.abs(grid[p] - found) > grid[1] * lobe / 4)]
        if not new or power.max() == 0.0:
            break
        new = sorted(new, key=lambda w: -power[np.searchsorted(grid, w)])[: most - found.size]
        fit = least_squares(model.residual, np.concatenate((found, new)), jac=model.jacobian, method="lm",
                            xtol=1e-15, ftol=1e-15, gtol=1e-15)
        found = fit.x
        left = solve(found)[2]
        if sigma == 0 and np.sqrt(np.mean(left**2)) < 1e-11 * scale:
            break
    if fit is None:
        return np.empty(0), np.empty(0)
    # A fit can pull a component to zero or past the Nyquist frequency when the record
    # is too short to separate two modes; such components are not estimates of a mode.
    keep = (found > slowest) & (found < grid[-1])
    found, jacobian = found[keep], fit.jac[:, keep]
    dof = times * sites - found.size - sites * (2 + 2 * found.size)
    variance = sigma**2 if sigma > 0 else np.sum(left**2) / max(dof, 1)
    try:
        errors = np.sqrt(np.diag(np.linalg.inv(jacobian.T @ jacobian)) * variance)
    except np.linalg.LinAlgError:
        errors = np.full(found.size, np.nan)
    order = np.argsort(found)
    return found[order], errors[order]


# ---------------------------------------------------------------- free bodies

BODY_MAX_TILT = 0.1  # rad: the linear regime, where small tilts move at the linear theory's rates
MIN_FLIPS = 3  # crossings of tilt = pi/2 a record needs for a flip-period fit
CROSSING_SAMPLES = 10  # samples of the spin-axis rate fitted by a polynomial around each crossing
CROSSING_DEGREE = 5
HYSTERESIS = 5.0  # noisy spin-axis rates count as crossed once this many stddevs past zero


def body_rates(ds: xr.Dataset, max_tilt: float = BODY_MAX_TILT) -> xr.Dataset:
    """Fit, per member of a body result, the small tilt's motion about the spin axis and the flip period.

    The linear part of the record is its start, up to the first sample whose
    tilt reaches max_tilt (rad). There the two rates across the spin axis k
    (axes i, j) are fitted by the linear motion: e^(-d t) (P e^(s u) + Q
    e^(-s u)) about the intermediate axis, giving growth_rate = s - d (1/s), or
    e^(-d t) (A cos W u + B sin W u) about a stable axis, giving
    wobble_frequency = W (rad/s); d = c (1/lambda_i + 1/lambda_j) / 2. The
    clock u (s) = integral of w_k dt / w_k(0) is read from the recorded spin:
    given w_k(t), the rates across obey linear equations exactly, so without
    drag the fit holds at any tilt, not only to first order in it. The flip
    period (s) comes from the times at which the spin-axis rate crosses zero
    (the tilt crosses pi/2), in records with at least MIN_FLIPS of them.

    Theory: the linear exponents at the start (body.transverse_exponents) and
    the elliptic flip period (c = 0 only, NaN otherwise). With drag the fit
    holds to first order in c. *_method: what the member's method shows
    (body.step_exponents). z and z_method compare whichever of growth rate and
    wobble frequency applies. Returns a Dataset over member.
    """
    _require(ds, "body", ("omega", "lambda1", "lambda2", "lambda3", "c", "spin0", "tilt0"), "body_rates")
    t = ds["t"].values
    omega = ds["omega"].values  # (member, t, axis)
    sigma = _noise(ds["omega"])
    constants = {}
    values = {name: ds[name].values for name in body.PARAMETERS if name in ds}
    values.setdefault("azimuth0", np.zeros(omega.shape[0]))
    values.setdefault("spin_axis", np.full(omega.shape[0], float(ds.attrs.get("spin_axis", 3))))  # older results
    k, i, j = body.spin_axes(values["spin_axis"])
    lam = np.stack([values[f"lambda{a}"] for a in body.AXES])
    damping = values["c"] * (1 / lam[i, np.arange(k.size)] + 1 / lam[j, np.arange(k.size)]) / 2
    growing = np.abs(body.transverse_exponents(values, constants)[0].imag) == 0  # a saddle: real exponents

    spin0 = values["spin0"] * np.cos(values["tilt0"])
    fitted = np.array([_small_tilt_fit(t, omega[m], k[m], spin0[m], damping[m], growing[m], sigma, max_tilt)
                       for m in range(omega.shape[0])]).reshape(-1, 3).T
    estimate, stderr, used = fitted
    theory = _shown(body.transverse_exponents(values, constants)[0], growing)
    method = _method_prediction(ds, theory, lambda m, dt, chosen: _shown(body.step_exponents(
        m, {name: v[chosen] for name, v in values.items()}, constants, dt)[0], growing[chosen]))
    flips = np.array([_flip_period(t, omega[m, :, k[m]], sigma) for m in range(omega.shape[0])]).reshape(-1, 3).T
    period_theory = np.where(growing & (values["c"] == 0), body.flip_period(values, constants), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        z, z_method, flip_z = (estimate - theory) / stderr, (estimate - method) / stderr, \
            (flips[0] - period_theory) / flips[1]
    data = _split_by_axis(growing, estimate, stderr, theory, method)
    data.update({
        "z": (z, "1", "(estimate - theory) / stderr, of growth_rate or wobble_frequency"),
        "z_method": (z_method, "1", "(estimate - method) / stderr, of growth_rate or wobble_frequency"),
        "samples_used": (used, "1", "saved times in the fitted linear part of the record"),
        "flip_period": (flips[0], "s", "fitted period of flipping over and back"),
        "flip_period_stderr": (flips[1], "s", "standard error of flip_period"),
        "flip_period_theory": (period_theory, "s", "elliptic period 4 K(m) / Omega of the torque-free motion"),
        "flip_z": (flip_z, "1", "(flip_period - flip_period_theory) / flip_period_stderr"),
        "flips": (flips[2], "1", "recorded crossings of tilt = pi/2"),
    })
    return _dataset(ds, data, "member", noise=sigma, fit="body_rates",
                    estimates=("growth_rate", "wobble_frequency", "flip_period"))


def _split_by_axis(growing, estimate, stderr, theory, method) -> dict:
    """The fitted exponent as growth_rate (members spun about the intermediate axis) and wobble_frequency (the
    others), each with its stderr, theory and method prediction; NaN where it does not apply."""
    data = {}
    for name, chosen, units, what in (("growth_rate", growing, "s-1", "growth rate of small tilts"),
                                      ("wobble_frequency", ~growing, "rad s-1", "wobble frequency of small tilts")):
        data.update({
            name: (np.where(chosen, estimate, np.nan), units, f"fitted {what} about the spin axis"),
            f"{name}_stderr": (np.where(chosen, stderr, np.nan), units, f"standard error of {name}"),
            f"{name}_theory": (np.where(chosen, theory, np.nan), units, f"linear theory's {what}"),
            f"{name}_method": (np.where(chosen, method, np.nan), units, f"{what} shown by the member's method"),
        })
    return data


def _shown(exponent: np.ndarray, growing: np.ndarray) -> np.ndarray:
    """The growth rate (real part) of a saddle's exponent, the wobble frequency (|imaginary part|) of the others."""
    return np.where(growing, exponent.real, np.abs(exponent.imag))


def _small_tilt_fit(t, omega, k, spin0, damping, growing, sigma, max_tilt):
    """(estimate, stderr, samples used) of one member; NaNs when it cannot be fitted.

    omega: (t, 3); spin0: w_k at t = 0 (rad/s). With noise the fitted part
    ends where the fitted model's tilt (not the noisy data's) reaches
    max_tilt, so the choice does not bias the fit.
    """
    across, spin = omega[:, [(k + 1) % 3, (k + 2) % 3]], omega[:, k]
    clock = _integral(t, spin) / spin0
    end = _linear_end(np.arctan2(np.hypot(across[:, 0], across[:, 1]), spin), max_tilt)
    for _ in range(3 if sigma > 0 else 1):
        if end < MIN_SAMPLES:
            return np.nan, np.nan, end
        motion = _SmallTilt(t[:end], clock[:end], across[:end], damping, growing)
        estimate, stderr = motion.fit(sigma)
        if sigma == 0:
            break
        model = motion.basis(motion.p, t, clock) @ motion.amplitudes(motion.p)
        end, before = _linear_end(np.arctan2(np.hypot(model[:, 0], model[:, 1]), np.abs(spin)), max_tilt), end
        if end == before:
            break
    return estimate, stderr, end


def _integral(t, y):
    """The integral of y from t[0] to each t, of a cubic spline through the finite samples (NaN after them)."""
    finite = _finite_end(y)
    out = np.full(t.size, np.nan)
    if finite >= 2:
        out[:finite] = CubicSpline(t[:finite], y[:finite]).antiderivative()(t[:finite])
    return out


def _finite_end(y) -> int:
    """Samples before the first non-finite one (a failed member's record ends there)."""
    return _linear_end(np.where(np.isfinite(y), 0.0, np.inf), 1.0)


def _linear_end(tilt, max_tilt) -> int:
    """Samples before the first whose tilt reaches max_tilt or is not finite."""
    out = np.flatnonzero(~(tilt < max_tilt))
    return int(out[0]) if out.size else tilt.size


class _SmallTilt:
    """The two rates across the spin axis, (times, 2), as basis(p) @ amplitudes: linear in all but the exponent p
    (s of a saddle, W of a wobble), which Gauss-Newton on the projected residual finds. t: times (s); clock: the
    spin's clock u (s) at those times."""

    def __init__(self, t, clock, across, damping, growing):
        self.t, self.clock, self.across, self.damping, self.growing = t, clock, across, damping, growing
        self.p = self._start()

    def basis(self, p, t, clock):
        decay = np.exp(-self.damping * t)
        if self.growing:
            return decay[:, None] * np.stack((np.exp(p * clock), np.exp(-p * clock)), axis=1)
        return decay[:, None] * np.stack((np.cos(p * clock), np.sin(p * clock)), axis=1)

    def basis_derivative(self, p):
        t, clock = self.t, self.clock
        decay = np.exp(-self.damping * t) * clock
        if self.growing:
            return decay[:, None] * np.stack((np.exp(p * clock), -np.exp(-p * clock)), axis=1)
        return decay[:, None] * np.stack((-np.sin(p * clock), np.cos(p * clock)), axis=1)

    def amplitudes(self, p):
        return np.linalg.lstsq(self.basis(p, self.t, self.clock), self.across, rcond=None)[0]

    def _start(self):
        """p from the data alone: the slope of log |rates| over the second half (saddle) or of their unwrapped
        angle, each rate scaled by its rms so the wobble's ellipse is a circle (wobble)."""
        half = self.t.size // 2
        if self.growing:
            with np.errstate(divide="ignore"):
                size = np.log(np.hypot(self.across[half:, 0], self.across[half:, 1]))
            slope = np.polyfit(self.clock[half:], size, 1)[0] if half >= 2 and np.all(np.isfinite(size)) else np.nan
            return slope + self.damping if np.isfinite(slope) and slope + self.damping > 0 else 1.0 / self.t[-1]
        scaled = self.across * np.exp(self.damping * self.t)[:, None]
        scaled = scaled / np.sqrt(np.mean(scaled**2, axis=0))
        angle = np.unwrap(np.arctan2(scaled[:, 1], scaled[:, 0]))
        return abs(np.polyfit(self.clock, angle, 1)[0])

    def _projected_jacobian(self, p):
        """d residual / d p after the amplitudes are solved for (Kaufman), and the residual; both (times * 2,)."""
        basis = self.basis(p, self.t, self.clock)
        q, r = np.linalg.qr(basis)
        amplitudes = np.linalg.solve(r, q.T @ self.across)
        derivative = self.basis_derivative(p) @ amplitudes
        jacobian = -(derivative - q @ (q.T @ derivative))
        return jacobian.ravel(), (self.across - basis @ amplitudes).ravel()

    def fit(self, sigma, iterations=50):
        """(p's estimate of growth rate or wobble frequency, its standard error)."""
        p = self.p
        jacobian, residual = self._projected_jacobian(p)
        for _ in range(iterations):
            step = -(jacobian @ residual) / (jacobian @ jacobian)
            if not np.isfinite(step):
                return np.nan, np.nan
            trial = p + step
            at_trial = self._projected_jacobian(trial)
            while _squares(at_trial[1]) > _squares(residual) and abs(trial - p) > 1e-15 * p:
                trial = p + (trial - p) / 2
                at_trial = self._projected_jacobian(trial)
            p, (jacobian, residual) = trial, at_trial  # the accepted point's evaluation serves the next step
            if abs(step) <= 1e-11 * abs(p):
                break
        self.p = p
        dof = residual.size - 5
        variance = sigma**2 if sigma > 0 else np.sum(residual**2) / max(dof, 1)
        estimate = p - self.damping if self.growing else p
        return estimate, np.sqrt(variance / (jacobian @ jacobian))


def _squares(residual):
    return residual @ residual


def _flip_period(t, spin, sigma):
    """(period (s), stderr, crossings) from the zero crossings of the spin-axis rate w_k: half a period apart.

    Each crossing time is the root of a polynomial fitted to the samples around
    it; a line through the crossing times against their count gives the
    period. NaNs with fewer than MIN_FLIPS crossings.
    """
    spin, t = spin[:_finite_end(spin)], t[:_finite_end(spin)]
    sign = np.where(spin > HYSTERESIS * sigma, 1.0, np.where(spin < -HYSTERESIS * sigma, -1.0, 0.0))
    known = np.flatnonzero(sign)
    changes = known[1:][np.diff(sign[known]) != 0]  # first sample on the new side of each crossing
    if changes.size < MIN_FLIPS:
        return np.nan, np.nan, changes.size
    times, variances = np.array([_crossing(t, spin, i, sigma) for i in changes]).T
    count = np.arange(changes.size)
    design = np.stack((np.ones(changes.size), count), axis=1)
    weights = 1 / variances if sigma > 0 else np.ones(changes.size)
    normal = design.T @ (weights[:, None] * design)
    solution = np.linalg.solve(normal, design.T @ (weights * times))
    residual = times - design @ solution
    variance = 1.0 if sigma > 0 else np.sum(residual**2) / max(changes.size - 2, 1)
    half_period_variance = np.linalg.inv(normal)[1, 1] * variance
    return 2 * solution[1], 2 * np.sqrt(half_period_variance), changes.size


def _crossing(t, spin, after, sigma):
    """(time, variance) at which a polynomial fitted to the samples around index `after` crosses zero."""
    first = int(np.clip(after - CROSSING_SAMPLES // 2, 0, t.size - CROSSING_SAMPLES))
    chosen = slice(first, first + CROSSING_SAMPLES)
    origin, scale = t[after], t[1] - t[0]
    x = (t[chosen] - origin) / scale
    design = np.vander(x, CROSSING_DEGREE + 1)
    coefficients = np.linalg.lstsq(design, spin[chosen], rcond=None)[0]
    derivative = np.polyder(coefficients)
    root = -spin[after] / (spin[after] - spin[after - 1])  # linear interpolation, in steps from `after`
    for _ in range(20):
        root = root - np.polyval(coefficients, root) / np.polyval(derivative, root)
    row = np.vander([root], CROSSING_DEGREE + 1)[0]
    value_variance = sigma**2 * row @ np.linalg.inv(design.T @ design) @ row
    return origin + root * scale, value_variance * (scale / np.polyval(derivative, root)) ** 2


def _dataset(ds: xr.Dataset, data: dict, dims, *, noise: float, fit: str,
             estimates: tuple[str, ...] = ("rate", "frequency")) -> xr.Dataset:
    out = xr.Dataset(coords=_members(ds))
    if "mode" in dims:
        out = out.assign_coords(mode=("mode", np.arange(1, ds.sizes["site"] + 1, dtype=np.int32)))
        out["mode"].attrs = {"units": "1", "long_name": "normal mode number, ascending in frequency"}
    for name, (values, units, long_name) in data.items():
        out[name] = (dims, values)
        out[name].attrs = {"units": units, "long_name": long_name}
    found = np.concatenate([out[name].values.reshape(out.sizes["member"], -1) for name in estimates if name in data],
                           axis=1)
    failed = int(np.all(~np.isfinite(found), axis=1).sum())  # members with no estimate at all
    out.attrs = {
        "Conventions": "CF-1.9",
        "title": f"{fit} fits of {ds.attrs.get('title', 'an ensemble result')}",
        "source": ds.attrs.get("source", ""),
        "method": ds.attrs.get("method", ""),
        "dt": ds.attrs.get("dt", np.nan),  # NaN when dt was swept
        "observation_noise_stddev": noise,
        "members_failed": failed,
        "sweep_axes": ds.attrs.get("sweep_axes", ""),
    }
    return out


def work_precision(ds: xr.Dataset) -> xr.Dataset:
    """Per sweep point of a run with [measure] error (and timing): method, dt, rtol, median error and work.

    Returns over `point`: method (name), dt (s; for adaptive methods the mean
    step t_end / steps), rtol, error (median over members of error_max),
    steps (median steps taken per member), rhs_evals (median) and seconds
    (median kernel seconds per member to t_end: seconds_per_step x steps;
    NaN without timing).
    """
    if "error_max" not in ds:
        raise FitError("work_precision needs a result of a run with [measure] error = true (no error_max in it)")
    methods, dt = member_settings(ds)
    points = ds["sweep_point"].values
    steps = ds["steps_accepted"].values + ds["steps_rejected"].values
    rtol = ds["rtol"].values if "rtol" in ds else np.full(points.size, float(ds.attrs.get("rtol", np.nan)))
    timing = ds["seconds_per_step"].values if "seconds_per_step" in ds else np.full(points.size, np.nan)
    rows = []
    for point in np.unique(points):
        chosen = points == point
        first = np.flatnonzero(chosen)[0]
        taken = np.median(steps[chosen])
        mean_step = float(ds.attrs["t_end"]) / np.median(ds["steps_accepted"].values[chosen])
        rows.append((methods[first], dt[first] if np.isfinite(dt[first]) else mean_step, rtol[first],
                     np.median(ds["error_max"].values[chosen]), taken, np.median(ds["rhs_evals"].values[chosen]),
                     np.median(timing[chosen] * steps[chosen])))
    columns = list(zip(*rows))
    out = xr.Dataset(coords={"point": np.arange(len(rows))})
    for name, values, units, long_name in (
            ("method", np.array(columns[0]), "", "integration method"),
            ("dt", np.array(columns[1]), "s", "step (adaptive methods: mean step t_end / steps accepted)"),
            ("rtol", np.array(columns[2]), "1", "relative tolerance (adaptive methods)"),
            ("error", np.array(columns[3]), "1", "median over members of error_max"),
            ("steps", np.array(columns[4]), "1", "median steps per member, rejected ones included"),
            ("rhs_evals", np.array(columns[5]), "1", "median right-hand-side evaluations per member"),
            ("seconds", np.array(columns[6]), "s", "median kernel seconds per member to t_end")):
        out[name] = ("point", values, {"units": units, "long_name": long_name} if units else {"long_name": long_name})
    return out


ROUNDOFF = 1e3 * np.finfo(float).eps  # errors below ROUNDOFF sqrt(steps) are round-off, not truncation
ASYMPTOTIC = 1e-2  # errors above this are not yet in the asymptotic regime


def convergence_order(table: xr.Dataset, method: str) -> tuple[float, int]:
    """Measured order of a fixed-step method from a work_precision table: (slope of log error on log dt, points).

    Uses the points in the asymptotic range: error below ASYMPTOTIC and above
    round-off (ROUNDOFF sqrt(steps)). NaN with fewer than 3 such points.
    """
    chosen = table["method"].values == method
    error, dt, steps = (table[name].values[chosen] for name in ("error", "dt", "steps"))
    usable = np.isfinite(error) & (error < ASYMPTOTIC) & (error > ROUNDOFF * np.sqrt(steps))
    if usable.sum() < 3:
        return np.nan, int(usable.sum())
    return float(np.polyfit(np.log(dt[usable]), np.log(error[usable]), 1)[0]), int(usable.sum())
