"""The chain's fit: each member's normal-mode frequencies from its x(t) alone, against det(K - w^2 M) = 0."""
from __future__ import annotations

import numpy as np
import xarray as xr
from scipy.optimize import linear_sum_assignment

from ... import fitting, libm
from . import model as chain


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
    fitting.require(ds, "chain", ("x", "m", "k"), "mode_frequencies")
    n, boundary = int(ds.attrs["n"]), str(ds.attrs["boundary"])
    t = ds["t"].values
    x = ds["x"].values
    sigma = fitting.noise_of(ds["x"])
    theory, shapes = chain.normal_modes(ds["m"].values, ds["k"].values, boundary)
    amplitude, excited = _mode_amplitudes(ds, theory, shapes)
    method = fitting.method_prediction(ds, theory, lambda m, dt, chosen: _angle(
        chain.step_eigenvalue(m, theory[chosen], dt)) / dt)
    frequency = np.full(theory.shape, np.nan)
    stderr = np.full(theory.shape, np.nan)
    for i in fitting.progress(x.shape[0], "fitting normal modes"):
        found, errors = fitting.member_frequencies(t, x[i], sigma, n)
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
    out = fitting.dataset(ds, data, ("member", "mode"), noise=sigma, fit="mode_frequencies")
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
        amplitude = np.where(omega > 0, libm.hypot(a, b / omega), np.nan)
    largest = np.nanmax(np.where(np.isfinite(amplitude), amplitude, 0.0), axis=1, keepdims=True)
    return amplitude, np.isfinite(amplitude) & (amplitude > EXCITED * largest)


def _angle(z: np.ndarray) -> np.ndarray:
    """np.angle(z) (rad), through the C library's atan2 (ensemble.libm)."""
    return libm.arctan2(z.imag, z.real)
