"""The top's fit: the tilt decay rate of each member, against the course's law and what its method shows."""
from __future__ import annotations

import numpy as np
import xarray as xr

from ... import fitting, libm
from ...fitting import MIN_SAMPLES
from . import model as top

TILT_FLOOR = 1e-150  # rad: noise-free tilts below this are too close to underflow to use


NOISE_WINDOW = 5.0  # noisy tilts are used while the fitted tilt is this many stddevs from 0 and pi/2


def tilt_decay(ds: xr.Dataset) -> xr.Dataset:
    """Fit tan(tilt) ~ exp(-rate t) per member of a top result: to its saved tilts, or where it saved none, to the
    times of its tilt events (`tilt_events`).

    Returns over member: rate (1/s; negative when the tilt grows, as for a
    prolate top), rate_stderr, rate_theory = c (1/lambda1 - 1/lambda3),
    rate_method (what the run's method shows, see top.tilt_rate_method),
    z = (rate - rate_theory) / rate_stderr, z_method likewise, and samples_used.
    """
    events = [name for name in ds.data_vars if ds[name].attrs.get("event_of") == "tilt"]
    sampled = "tilt" in ds or not events
    fitting.require(ds, "top", ("tilt",) * sampled + ("lambda1", "lambda3", "c", "tilt0", "spin0"), "tilt_decay",
                    sampled)
    t = ds["t"].values
    sigma = fitting.noise_of(ds["tilt"]) if sampled else 0.0
    values = {name: ds[name].values for name in top.PARAMETERS if name in ds}
    if not sampled:
        intercept, rate, stderr, used = _tilt_fit_events(ds, events)
    elif sigma > 0:
        intercept, rate, stderr, used = _tilt_fit_noisy(t, ds["tilt"].values, sigma)
    else:
        intercept, rate, stderr, used = _tilt_fit_clean(t, ds["tilt"].values)
    theory = values["c"] * (1 / values["lambda1"] - 1 / values["lambda3"])
    method = fitting.method_prediction(ds, theory, lambda m, dt, chosen: top.tilt_rate_method(
        m, {k: v[chosen] for k, v in values.items()}, dt, t))
    data = {
        "rate": (rate, "s-1", "fitted tilt decay rate: tan(tilt) ~ exp(-rate t)"),
        "rate_stderr": (stderr, "s-1", "standard error of rate"),
        "rate_theory": (theory, "s-1", "c (1/lambda1 - 1/lambda3)"),
        "rate_method": (method, "s-1", "rate shown by the member's method at its dt"),
        "z": ((rate - theory) / stderr, "1", "(rate - rate_theory) / rate_stderr"),
        "z_method": ((rate - method) / stderr, "1", "(rate - rate_method) / rate_stderr"),
        "log_tan_tilt0": (intercept, "1", "fitted line's log tan(tilt) at t = 0"),
        "samples_used": (used, "1", "saved times inside the fitted part of the record (from events: the start and "
                                    "the event times)"),
    }
    return fitting.dataset(ds, data, "member", noise=sigma, fit="tilt_decay")


def _tilt_fit_events(ds: xr.Dataset, events: list[str]):
    """From events alone: log tan(tilt) is log tan(tilt0) at t = 0 and log tan(level) at each time the tilt
    crossed a level (`events`: the result's tilt events' time variables); least squares over those points per
    member, its stderr from their residuals (0 with two points, whose line is exact: its error is the method's,
    which a check against theory judges)."""
    times = [np.zeros((ds.sizes["member"], 1))] + [ds[name].values for name in events]
    logs = [libm.log(libm.tan(ds["tilt0"].values))[:, None]] + [
        np.full(ds[name].shape, libm.log(libm.tan(ds[name].attrs["event_value"]))) for name in events]
    t, y = np.concatenate(times, axis=1), np.concatenate(logs, axis=1)
    a, rate, rss, count, sxx = fitting.masked_line(t, y, np.isfinite(t) & np.isfinite(y))
    with np.errstate(invalid="ignore", divide="ignore"):
        stderr = np.where(count > 2, np.sqrt(rss / (count - 2) / sxx), 0.0)
    bad = count < 2
    return (np.where(bad, np.nan, a), np.where(bad, np.nan, rate), np.where(bad, np.nan, stderr),
            count.astype(np.int32))


def _tilt_fit_clean(t, tilt):
    """Noise-free: ordinary least squares of log tan(tilt) on t; stderr from the residuals."""
    with np.errstate(invalid="ignore", divide="ignore"):
        y = libm.log(libm.tan(tilt))
    mask = np.isfinite(y) & (tilt > TILT_FLOOR) & (tilt < np.pi / 2)
    a, rate, rss, count, sxx = fitting.masked_line(t, y, mask)
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
        a, rate, _, _, _ = fitting.masked_line(t, libm.log(libm.tan(tilt)), start)
    for _ in range(iterations):
        model = libm.arctan(libm.exp(a[:, None] - rate[:, None] * t))
        mask = finite & (model > lo) & (model < hi)
        slope = np.where(mask, 0.5 * libm.sin(2 * model), 0.0)  # d model / d a
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
