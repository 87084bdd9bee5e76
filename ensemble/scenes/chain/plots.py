"""The chain's charts of its normal-mode fit (`ensemble fit`): a member's spectrum, and frequencies against
theory."""
from __future__ import annotations

import numpy as np
from scipy.signal.windows import blackmanharris

from ... import plotting


def draw(plt, ds, fits, rows, stem, members=None) -> list:
    """STEM_spectrum.png: the power spectrum of the first member asked for (default 0) with the eigenfrequencies
    and the fitted ones; STEM_frequencies.png: every fitted frequency against its eigenfrequency, with
    residuals."""
    member = members[0] if members else 0
    t = ds["t"].values
    x = ds["x"].values[member]
    pad = 8 * t.size
    omega = 2 * np.pi * np.fft.rfftfreq(pad, t[1] - t[0])
    window = blackmanharris(t.size)[:, None]  # the fit's (ensemble.fitting.member_frequencies)
    power = np.sum(np.abs(np.fft.rfft((x - x.mean(axis=0)) * window, pad, axis=0)) ** 2, axis=1)
    fig, ax = plt.subplots(figsize=(8, 4.5), layout="constrained")
    ax.semilogy(omega, power / power.max(), lw=1,
                label=f"member {member}, summed over sites (Blackman-Harris window, as the fit's peak search)")
    theory = fits["frequency_theory"].values[member]
    for j, w in enumerate(theory):
        ax.axvline(w, color="k", ls="--", lw=0.7, label="theory (eigenfrequencies)" if j == 0 else None)
    found = fits["frequency"].values[member]
    ax.plot(found[np.isfinite(found)], np.full(np.isfinite(found).sum(), 2.0), "rv", label="fitted")
    ax.set_xlim(0, 1.15 * max(theory.max(), 1e-12))
    ax.set_ylim(1e-12, 5)
    ax.set_xlabel("angular frequency (rad/s)")
    ax.set_ylabel("power (relative to the largest)")
    ax.set_title("spectrum of x(t)")
    ax.legend(**plotting.LEGEND_OUTSIDE)
    paths = [plotting.save(plt, fig, stem, "spectrum")]
    theory = fits["frequency_theory"].values.ravel()
    series = [(theory, fits["frequency"].values.ravel(), fits["frequency_stderr"].values.ravel(),
               "fitted, every member and mode")]
    if "frequency_method" in fits and np.isfinite(fits["frequency_method"].values).any():
        series.append((theory, fits["frequency_method"].values.ravel(), None, f"what {ds.attrs['method']} shows"))
    paths.append(plotting.against_theory(plt, stem, "frequencies", series, theory_label="eigenfrequency",
                                       quantity="frequency", units="rad/s",
                                       title="fitted frequencies against theory"))
    return paths
