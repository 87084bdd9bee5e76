"""The free body's charts of its fit (`ensemble fit`): tilts, growth rates and wobble frequencies, flip
periods."""
from __future__ import annotations

import numpy as np

from ... import plotting
from . import model as body


def draw(plt, ds, fits, rows, stem, members=None) -> list:
    """STEM_tilt.png (sample members); STEM_rates.png: growth rates and wobble frequencies against linear
    theory; where bodies flip, STEM_flips.png against the elliptic period and, for noisy records, STEM_flip_z.png."""
    paths = [_tilt_chart(plt, ds, fits, stem, members)]
    series = [(fits[f"{name}_theory"].values, fits[name].values, fits[f"{name}_stderr"].values,
               f"{name.replace('_', ' ')}, every member")
              for name in ("growth_rate", "wobble_frequency") if np.isfinite(fits[name].values).any()]
    if series:
        paths.append(plotting.against_theory(plt, stem, "rates", series, theory_label="linear theory",
                                           quantity="rate or frequency", units="1/s or rad/s",
                                           title="growth rates and wobble frequencies of small tilts"))
    period, theory = fits["flip_period"].values, fits["flip_period_theory"].values
    if (np.isfinite(period) & np.isfinite(theory)).any():
        paths.append(plotting.against_theory(
            plt, stem, "flips", [(theory, period, fits["flip_period_stderr"].values, "every member that flips")],
            theory_label="elliptic period 4 K(m) / Omega", quantity="flip period", units="s",
            title="flip period against theory"))
        if fits.attrs.get("observation_noise_stddev", 0.0) > 0:
            fig, ax = plt.subplots(figsize=(5.5, 4.5), layout="constrained")
            plotting.z_histogram(ax, fits["flip_z"].values, "flip periods")
            ax.set_title("flip periods: fitted against theory")
            paths.append(plotting.save(plt, fig, stem, "flip_z"))
    return paths


def _tilt_chart(plt, ds, fits, stem, members):
    """The tilt of sample members against time; where it grows, the fitted growing exponential through the
    last fitted sample (the fit's decaying part is not drawn, so early on the line runs below the dots)."""
    fig, ax = plt.subplots(figsize=(8, 4.5), layout="constrained")
    t = ds["t"].values
    tilts = body.tilt(ds["omega"].values.transpose(2, 1, 0), ds["spin_axis"].values).T  # (member, t)
    for i, member in enumerate(plotting.sample_members(ds, members)):
        color = f"C{i % 10}"
        tilt = tilts[member]
        used, rate = int(fits["samples_used"].values[member]), fits["growth_rate"].values[member]
        grows = np.isfinite(rate) and used >= 2
        ax.semilogy(t, tilt, ".", ms=3, color=color, zorder=3,
                    label=f"member {member}" + (f": growth rate {rate:.5g} 1/s" if grows else ""))
        if grows:
            ax.semilogy(t[:used], tilt[used - 1] * np.exp(rate * (t[:used] - t[used - 1])), "--", color="k", lw=0.6,
                        zorder=4)
    if np.isfinite(fits["growth_rate"].values).any():
        ax.plot([], [], "--", color="k", lw=0.6, label="fitted growing exponential\n(its decaying part not drawn)")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("tilt (rad)")
    ax.set_title("tilt of sample members (dots); dashed: the fitted growth where the tilt grows")
    ax.legend(**plotting.LEGEND_OUTSIDE)
    return plotting.save(plt, fig, stem, "tilt")
