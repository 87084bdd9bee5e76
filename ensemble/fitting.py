"""The fitting machinery the scenes' fits share (each scene's own fit is in ensemble/scenes/<scene>/fits.py, and a
scene's `fit(ds)` runs it): least squares with error bars, spectra, zero-crossing times, which prediction each
member's method makes, the fits' dataset layout; and the work-precision table of any result.

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

import sys

import numpy as np
import xarray as xr
from scipy.interpolate import CubicSpline
from scipy.optimize import least_squares
from scipy.signal import find_peaks
from scipy.signal.windows import blackmanharris

from . import libm
from .errors import EnsembleError
from .methods import METHODS
from .results import Status

Z_TOLERANCE = 5.0  # a noisy sweep point passes when its mean is within this many standard errors of theory...
RTOL = 1e-6  # ...or within this relative difference, a noise-free one (whose z has no meaning) only within it;
#              a fitted variable's own `check_rtol` attribute replaces it


MIN_SAMPLES = 5  # usable samples a member needs for a fit
PEAK_FALSE_ALARM = 30.0  # a spectral peak counts when its power exceeds this many times the noise's
PEAK_DYNAMIC_RANGE = 1e-7  # peaks weaker than this fraction of the strongest are rounding, not modes
MIN_PERIODS = 4  # periods a mode must complete in the record: slower ones sit in the drift's main lobe


class FitError(EnsembleError, ValueError):
    """A result that cannot be fitted: wrong scene, missing variables, too few samples."""


def progress(count: int, what: str):
    """range(count), with a progress bar on a terminal (or a notebook): a long fit shows how far it is."""
    from .bars import Bar

    return Bar(range(count), desc=what, unit="member", leave=False, disable=None, file=sys.stderr)


def require(ds: xr.Dataset, scene: str, variables: tuple[str, ...], fit: str, sampled: bool = True) -> None:
    """The result is the scene's and holds `variables`, and (sampled) enough saved times for a fit of them;
    FitError otherwise."""
    found = ds.attrs.get("scene")
    if found != scene:
        what = "a " + repr(found) if found else "not from ensemble"
        raise FitError(f"{fit} needs a {scene} result; this one is {what}"
                       f" result")
    missing = [v for v in variables if v not in ds.variables]
    if missing:
        raise FitError(f"{fit}: the result lacks {', '.join(missing)} (save them in the run file)")
    if sampled and ds.sizes.get("t", 0) < MIN_SAMPLES:
        raise FitError(f"{fit}: the result has {ds.sizes.get('t', 0)} saved times; a fit needs at least {MIN_SAMPLES}")


def noise_of(var: xr.DataArray) -> float:
    return float(var.attrs.get("observation_noise_stddev", 0.0))


def has_noise(ds: xr.Dataset) -> bool:
    """Whether a result carries observation noise on any variable (its z values then follow N(0, 1))."""
    return any(noise_of(ds[name]) > 0 for name in ds.data_vars)


def _members(ds: xr.Dataset) -> dict[str, xr.DataArray]:
    coords = {"member": ds["member"]}
    if "sweep_point" in ds:
        coords["sweep_point"] = ds["sweep_point"]
    return coords


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


def method_prediction(ds: xr.Dataset, theory: np.ndarray, predict) -> np.ndarray:
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


def masked_line(t, y, mask):
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


class _VariableProjection:
    """The model x(t) = a + b t + sum_k (c_k cos w_k t + s_k sin w_k t) per site, linear in all but the w_k.

    least_squares asks for the residual and then the Jacobian at the same w, so the last factorization is kept.
    """

    def __init__(self, t: np.ndarray, x: np.ndarray):
        self.tc, self.x = t - t.mean(), x
        self.last = {}

    def design(self, w):
        phase = np.outer(self.tc, w)
        return np.hstack((np.ones((self.tc.size, 1)), self.tc[:, None], libm.cos(phase), libm.sin(phase)))

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
        derivative = (-(tc[:, None] * libm.sin(phase))[:, None, :] * amplitudes[2:2 + k].T[None, :, :]
                      + (tc[:, None] * libm.cos(phase))[:, None, :] * amplitudes[2 + k:].T[None, :, :])
        flat = derivative.reshape(times, sites * k)
        projected = flat - q @ (q.T @ flat)
        return -projected.reshape(times * sites, k)


def member_frequencies(t: np.ndarray, x: np.ndarray, sigma: float, most: int):
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

MIN_FLIPS = 3  # crossings of tilt = pi/2 a record needs for a flip-period fit
PLATEAU = 0.9  # a crossing is fitted over the samples around it whose |w_k| stays below this share of its largest
HYSTERESIS = 5.0  # noisy spin-axis rates count as crossed once this many stddevs past zero


def integral(t, y):
    """The integral of y from t[0] to each t, of a cubic spline through the finite samples (NaN after them)."""
    finite = finite_end(y)
    out = np.full(t.size, np.nan)
    if finite >= 2:
        out[:finite] = CubicSpline(t[:finite], y[:finite]).antiderivative()(t[:finite])
    return out


def finite_end(y) -> int:
    """Samples before the first non-finite one (a failed member's record ends there)."""
    out = np.flatnonzero(~np.isfinite(y))
    return int(out[0]) if out.size else y.size


def crossing_period(t, spin, sigma):
    """(period (s), stderr, crossings) from the zero crossings of the spin-axis rate w_k: half a period apart.

    Each crossing time comes from a fit of the flip's own shape to the samples around it (_crossing); a line
    through the crossing times against their count gives the period, weighted by each time's variance. Without
    noise the variances are the crossing fits' residuals, and the line's scatter scales them when larger. NaNs
    with fewer than MIN_FLIPS crossings.
    """
    spin, t = spin[:finite_end(spin)], t[:finite_end(spin)]
    sign = np.where(spin > HYSTERESIS * sigma, 1.0, np.where(spin < -HYSTERESIS * sigma, -1.0, 0.0))
    known = np.flatnonzero(sign)
    changes = known[1:][np.diff(sign[known]) != 0]  # first sample on the new side of each crossing
    if changes.size < MIN_FLIPS:
        return np.nan, np.nan, changes.size
    times, variances = np.array([_crossing(t, spin, i, sigma) for i in changes]).T
    design = np.stack((np.ones(changes.size), np.arange(changes.size)), axis=1)
    weights = 1 / np.maximum(variances, np.finfo(float).tiny)
    normal = design.T @ (weights[:, None] * design)
    solution = np.linalg.solve(normal, design.T @ (weights * times))
    scatter = np.sum(weights * (times - design @ solution) ** 2) / max(changes.size - 2, 1)
    half_period_variance = np.linalg.inv(normal)[1, 1] * (1.0 if sigma > 0 else max(1.0, scatter))
    return 2 * solution[1], 2 * np.sqrt(half_period_variance), changes.size


def event_period(times: np.ndarray, per_period: int, sigma: float = 0.0) -> tuple[float, float, int]:
    """(period (s), stderr, occurrences) from a member's event times (NaN where fewer occurred), `per_period` of
    them a period apart (2 for a variable's crossings of zero both ways): a line through the times against their
    count. Its stderr: from `sigma`, the times' observation noise (s), where they have some; else from the scatter
    about the line (their rounding: 0 where the line is exact). NaNs with fewer than MIN_FLIPS."""
    times = times[np.isfinite(times)]
    if times.size < MIN_FLIPS:
        return np.nan, np.nan, times.size
    count = np.arange(times.size)
    slope, intercept = np.polyfit(count, times, 1)
    variance = sigma**2 if sigma > 0 else np.sum((times - intercept - slope * count) ** 2) / (times.size - 2)
    stderr = np.sqrt(variance / np.sum((count - count.mean()) ** 2))
    return per_period * slope, per_period * stderr, times.size


def _crossing(t, spin, after, sigma):
    """(time, variance) at which w_k crosses zero between samples after - 1 and after.

    Near a crossing a flipping body's w_k follows a tanh(b u + d u^3), u = t - t0: at the separatrix exactly
    a tanh, away from it an elliptic function the cubic term bends the tanh into. Fitted to the samples around
    the crossing whose |w_k| is below PLATEAU of its largest (at least three each side): a flip that takes
    few samples is still resolved, where a polynomial through them missed by many standard errors (issue 39).
    """
    amplitude = np.max(np.abs(spin))
    inside = np.abs(spin) < PLATEAU * amplitude
    first, last = after - 1, after
    while first > 0 and inside[first - 1]:
        first -= 1
    while last < t.size - 1 and inside[last + 1]:
        last += 1
    chosen = slice(max(min(first, after - 3), 0), min(max(last, after + 2), t.size - 1) + 1)
    step = t[1] - t[0]
    slope = (spin[after] - spin[after - 1]) / step
    if not slope * spin[after] > 0:  # noise left the sample before on the same side: start from `after` itself
        slope = np.copysign(amplitude / step, spin[after])
    origin = t[after] - spin[after] / slope  # linear interpolation
    u0 = t[chosen] - origin

    def residual(p):
        u = u0 - p[2]
        return p[0] * libm.tanh(p[1] * u + p[3] * u**3) - spin[chosen]

    def jacobian(p):
        u = u0 - p[2]
        shape = libm.tanh(p[1] * u + p[3] * u**3)
        bend = p[0] * (1 - shape**2)
        return np.stack((shape, bend * u, -bend * (p[1] + 3 * p[3] * u**2), bend * u**3), axis=1)

    height = np.copysign(amplitude, slope)
    fit = least_squares(residual, np.array([height, slope / height, 0.0, 0.0]), jac=jacobian, method="lm")
    covariance = np.linalg.pinv(fit.jac.T @ fit.jac)
    noise = sigma**2 if sigma > 0 else np.sum(fit.fun**2) / max(fit.fun.size - 4, 1)
    return origin + fit.x[2], noise * covariance[2, 2]


FIT_TITLES = {"tilt_decay": "tilt decay rate", "mode_frequencies": "normal-mode frequencies",
              "body_rates": "growth rate, wobble frequency and flip period"}  # what a physicist calls each fit


ENDED_WELL = (Status.OK, Status.STOPPED_BY_EVENT)  # a member's status that a fit may use


def dataset(ds: xr.Dataset, data: dict, dims, *, noise: float, fit: str,
             estimates: tuple[str, ...] = ("rate", "frequency")) -> xr.Dataset:
    """A fit's Dataset over members (and modes) from data: name -> (values, units, long_name). Members whose run
    did not end well (they blew up or their step underflowed; a stop at an event ends well) are left out: NaN in
    every float variable, counted in members_not_ok and, having no estimate, in members_failed."""
    out = xr.Dataset(coords=_members(ds))
    if "mode" in dims:
        out = out.assign_coords(mode=("mode", np.arange(1, ds.sizes["site"] + 1, dtype=np.int32)))
        out["mode"].attrs = {"units": "1", "long_name": "normal mode number, ascending in frequency"}
    not_ok = ~np.isin(ds["status"].values, ENDED_WELL) if "status" in ds else np.zeros(ds.sizes["member"], bool)
    for name, (values, units, long_name) in data.items():
        values = np.asarray(values)
        if values.dtype.kind == "f" and not_ok.any():
            values = np.where(not_ok.reshape(-1, *[1] * (values.ndim - 1)), np.nan, values)
        out[name] = (dims, values)
        out[name].attrs = {"units": units, "long_name": long_name}
    found = np.concatenate([out[name].values.reshape(out.sizes["member"], -1) for name in estimates if name in data],
                           axis=1)
    failed = int(np.all(~np.isfinite(found), axis=1).sum())  # members with no estimate at all
    out.attrs = {
        "Conventions": "CF-1.9",
        "title": f"{FIT_TITLES.get(fit, fit)} fits of {ds.attrs.get('title', 'an ensemble result')}",
        "fit": fit,
        "source": ds.attrs.get("source", ""),
        "method": ds.attrs.get("method", ""),
        "dt": ds.attrs.get("dt", np.nan),  # NaN when dt was swept
        "observation_noise_stddev": noise,
        "members_failed": failed,
        "members_not_ok": int(not_ok.sum()),
        "sweep_axes": ds.attrs.get("sweep_axes", ""),
    }
    return out


def work_precision(ds: xr.Dataset) -> xr.Dataset:
    """Per sweep point of a run with [measure] error (and timing): method, dt, rtol, median error and work.

    Returns over `point`: method (name), line (the chart's line: the method's
    name; see combined_work_precision), precision (the run's float type),
    dt (s; for adaptive methods the mean step t_end / steps), rtol, error
    (median over members of error_max), steps (median steps taken per
    member), rhs_evals (median) and seconds (median kernel seconds per member
    to t_end: seconds_per_step x steps; NaN without timing).
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
        accepted = np.median(ds["steps_accepted"].values[chosen])
        mean_step = float(ds.attrs["t_end"]) / accepted if accepted > 0 else np.nan  # the closed form takes none
        rows.append((methods[first], dt[first] if np.isfinite(dt[first]) else mean_step, rtol[first],
                     np.median(ds["error_max"].values[chosen]), taken, np.median(ds["rhs_evals"].values[chosen]),
                     np.median(timing[chosen] * steps[chosen])))
    columns = list(zip(*rows))
    out = xr.Dataset(coords={"point": np.arange(len(rows))})
    for name, values, units, long_name in (
            ("method", np.array(columns[0]), "", "integration method"),
            ("line", np.array(columns[0]), "", "the chart's line: the method, and where results differ their "
                                              "precision and device"),
            ("precision", np.full(len(rows), ds.attrs.get("precision", "float64")), "", "the kernels' float type"),
            ("dt", np.array(columns[1]), "s", "step (adaptive methods: mean step t_end / steps accepted)"),
            ("rtol", np.array(columns[2]), "1", "relative tolerance (adaptive methods)"),
            ("error", np.array(columns[3]), "1", "median over members of error_max"),
            ("steps", np.array(columns[4]), "1", "median steps per member, rejected ones included"),
            ("rhs_evals", np.array(columns[5]), "1", "median right-hand-side evaluations per member"),
            ("seconds", np.array(columns[6]), "s", "median kernel seconds per member to t_end")):
        out[name] = ("point", values, {"units": units, "long_name": long_name} if units else {"long_name": long_name})
    return out


ROUNDOFF = 1e3  # machine epsilons: errors below ROUNDOFF eps sqrt(steps) are round-off, not truncation
ASYMPTOTIC = 1e-2  # errors above this are not yet in the asymptotic regime


def combined_work_precision(tables: list[xr.Dataset], results: list[dict]) -> xr.Dataset:
    """Work-precision tables of several results (their attributes `results`) as one over `point`. Where the
    results differ in precision or device, each line is named by them too: `rk4 float32 cuda`."""
    differ = [key for key in ("precision", "device") if len({_kind(r, key) for r in results}) > 1]
    named = []
    for table, attrs in zip(tables, results):
        suffix = "".join(f" {_kind(attrs, key)}" for key in differ)
        lines = np.array([f"{method}{suffix}" for method in table["method"].values])
        named.append(table.assign(line=table["line"].copy(data=lines)))  # the callers' tables stay as they are
    combined = xr.concat(named, dim="point")
    return combined.assign_coords(point=np.arange(combined.sizes["point"]))


def _kind(attrs: dict, key: str) -> str:
    """A result's precision, or its device's kind (cpu or cuda, without the GPU's name)."""
    default = "float64" if key == "precision" else "cpu"
    return str(attrs.get(key, default)).split(":")[0]


def convergence_order(table: xr.Dataset, line: str) -> tuple[float, int]:
    """Measured order of a fixed-step method from a work_precision table: (slope of log error on log dt, points).
    `line`: the method's name, or the table's line of it (combined_work_precision).

    Uses the points in the asymptotic range: error below ASYMPTOTIC and above
    round-off (ROUNDOFF eps sqrt(steps), eps that of the run's precision). NaN
    with fewer than 3 such points.
    """
    chosen = table["line"].values == line
    error, dt, steps = (table[name].values[chosen] for name in ("error", "dt", "steps"))
    eps = np.finfo(str(table["precision"].values[chosen][0])).eps if chosen.any() else np.finfo(float).eps
    usable = np.isfinite(error) & (error < ASYMPTOTIC) & (error > ROUNDOFF * eps * np.sqrt(steps))
    if usable.sum() < 3:
        return np.nan, int(usable.sum())
    return float(np.polyfit(libm.log(dt[usable]), libm.log(error[usable]), 1)[0]), int(usable.sum())


def fitted_values(fits: xr.Dataset) -> list[str]:
    """The fitted quantities of a fit dataset: variables with a `<name>_theory` beside them."""
    return [name for name in fits.data_vars if f"{name}_theory" in fits]
