"""The free body's fit: the growth rate or wobble frequency of small tilts about the spin axis, and the flip
period, against the linear theory, the elliptic period and what the member's method shows."""
from __future__ import annotations

import numpy as np
import xarray as xr

from ... import fitting, libm
from ...fitting import MIN_SAMPLES
from . import model as body

BODY_MAX_TILT = 0.1  # rad: the linear regime, where small tilts move at the linear theory's rates


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
    (the tilt crosses pi/2), at least MIN_FLIPS of them: the run's events on
    that rate where it has them, else its samples (`_flip_periods`).

    Theory: the linear exponents at the start (body.transverse_exponents) and
    the elliptic flip period (c = 0 only, NaN otherwise). With drag the fit
    holds to first order in c. *_method: what the member's method shows
    (body.step_exponents). z and z_method compare whichever of growth rate and
    wobble frequency applies. Returns a Dataset over member.
    """
    fitting.require(ds, "body", ("omega", "lambda1", "lambda2", "lambda3", "c", "spin0", "tilt0"), "body_rates")
    t = ds["t"].values
    omega = ds["omega"].values  # (member, t, axis)
    sigma = fitting.noise_of(ds["omega"])
    constants = {}
    values = {name: ds[name].values for name in body.PARAMETERS if name in ds}
    values.setdefault("azimuth0", np.zeros(omega.shape[0]))
    values.setdefault("spin_axis", np.full(omega.shape[0], float(ds.attrs.get("spin_axis", 3))))  # older results
    k, i, j = body.spin_axes(values["spin_axis"])
    lam = np.stack([values[f"lambda{a}"] for a in body.AXES])
    damping = values["c"] * (1 / lam[i, np.arange(k.size)] + 1 / lam[j, np.arange(k.size)]) / 2
    growing = np.abs(body.transverse_exponents(values, constants)[0].imag) == 0  # a saddle: real exponents

    spin0 = values["spin0"] * libm.cos(values["tilt0"])
    fitted = np.array([_small_tilt_fit(t, omega[m], k[m], spin0[m], damping[m], growing[m], sigma, max_tilt)
                       for m in range(omega.shape[0])]).reshape(-1, 3).T
    estimate, stderr, used = fitted
    theory = _shown(body.transverse_exponents(values, constants)[0], growing)
    method = fitting.method_prediction(ds, theory, lambda m, dt, chosen: _shown(body.step_exponents(
        m, {name: v[chosen] for name, v in values.items()}, constants, dt)[0], growing[chosen]))
    flips = _flip_periods(ds, t, omega, k, sigma)
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
    return fitting.dataset(ds, data, "member", noise=sigma, fit="body_rates",
                    estimates=("growth_rate", "wobble_frequency", "flip_period"))


def _flip_periods(ds: xr.Dataset, t, omega, k, sigma) -> np.ndarray:
    """(flip period, stderr, crossings) per member, (3, members): from the run's events on the member's spin-axis
    rate crossing zero (located within the steps: fitting.event_period) where it has one, else from its samples
    (fitting.crossing_period). An event-based stderr comes from the event times' own observation noise where the
    run gives them some ([observe] noise = { flip_time = ... }); without it, from their scatter about their
    line, which holds their rounding, not the method's own error in the period: flip_z is then no z."""
    events = {int(ds[name].attrs["event_index"]): name for name in ds.data_vars
              if ds[name].attrs.get("event_of") == "omega" and ds[name].attrs.get("event_value") == 0.0}
    out = []
    for m in fitting.progress(omega.shape[0], "fitting flip periods"):
        name = events.get(int(k[m]))
        if name is None:
            out.append(fitting.crossing_period(t, omega[m, :, k[m]], sigma))
        else:
            both = ds[name].attrs["event_direction"] == "both"
            out.append(fitting.event_period(ds[name].values[m], 2 if both else 1, fitting.noise_of(ds[name])))
    return np.array(out).reshape(-1, 3).T


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
    clock = fitting.integral(t, spin) / spin0
    end = _linear_end(libm.arctan2(libm.hypot(across[:, 0], across[:, 1]), spin), max_tilt)
    for _ in range(3 if sigma > 0 else 1):
        if end < MIN_SAMPLES:
            return np.nan, np.nan, end
        motion = _SmallTilt(t[:end], clock[:end], across[:end], damping, growing)
        estimate, stderr = motion.fit(sigma)
        if sigma == 0:
            break
        model = motion.basis(motion.p, t, clock) @ motion.amplitudes(motion.p)
        end, before = _linear_end(libm.arctan2(libm.hypot(model[:, 0], model[:, 1]), np.abs(spin)), max_tilt), end
        if end == before:
            break
    return estimate, stderr, end


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
        decay = libm.exp(-self.damping * t)
        if self.growing:
            return decay[:, None] * np.stack((libm.exp(p * clock), libm.exp(-p * clock)), axis=1)
        return decay[:, None] * np.stack((libm.cos(p * clock), libm.sin(p * clock)), axis=1)

    def basis_derivative(self, p):
        t, clock = self.t, self.clock
        decay = libm.exp(-self.damping * t) * clock
        if self.growing:
            return decay[:, None] * np.stack((libm.exp(p * clock), -libm.exp(-p * clock)), axis=1)
        return decay[:, None] * np.stack((-libm.sin(p * clock), libm.cos(p * clock)), axis=1)

    def amplitudes(self, p):
        return np.linalg.lstsq(self.basis(p, self.t, self.clock), self.across, rcond=None)[0]

    def _start(self):
        """p from the data alone: the slope of log |rates| over the second half (saddle) or of their unwrapped
        angle, each rate scaled by its rms so the wobble's ellipse is a circle (wobble)."""
        half = self.t.size // 2
        if self.growing:
            with np.errstate(divide="ignore"):
                size = libm.log(libm.hypot(self.across[half:, 0], self.across[half:, 1]))
            slope = np.polyfit(self.clock[half:], size, 1)[0] if half >= 2 and np.all(np.isfinite(size)) else np.nan
            return slope + self.damping if np.isfinite(slope) and slope + self.damping > 0 else 1.0 / self.t[-1]
        scaled = self.across * libm.exp(self.damping * self.t)[:, None]
        scaled = scaled / np.sqrt(np.mean(scaled**2, axis=0))
        angle = np.unwrap(libm.arctan2(scaled[:, 1], scaled[:, 0]))
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
