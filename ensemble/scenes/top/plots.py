"""The top's charts of its tilt-decay fit (`ensemble fit`): tilts with their fitted lines, and rates against
theory."""
from __future__ import annotations

import numpy as np

from ... import plotting


def draw(plt, ds, fits, rows, stem, members=None) -> list:
    """STEM_tilt.png: tan(tilt) of sample members (dots) and their fitted lines (dashed); STEM_rates.png: each
    sweep point's mean fitted rate against c (1/lambda1 - 1/lambda3), with residuals."""
    fig, ax = plt.subplots(figsize=(8, 4.5), layout="constrained")
    t = ds["t"].values
    for i, member in enumerate(plotting.sample_members(ds, members)):
        color = f"C{i % 10}"
        rate = fits["rate"].values[member]
        ax.semilogy(t, np.tan(ds["tilt"].values[member]), ".", ms=3, color=color, zorder=3,
                    label=f"member {member}: rate {rate:.4g} 1/s")
        line = np.exp(fits["log_tan_tilt0"].values[member] - rate * t)
        ax.semilogy(t, line, "--", color="k", lw=0.6, zorder=4)
    ax.plot([], [], "--", color="k", lw=0.6, label="fitted tan(tilt0) exp(-rate t)")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("tan(tilt)")
    ax.set_title("tilt of sample members (dots) and their fitted lines (dashed)")
    ax.legend(**plotting.LEGEND_OUTSIDE)
    paths = [plotting.save(plt, fig, stem, "tilt")]
    theory, mean, error = (np.array([getattr(r, name) for r in rows]) for name in ("theory", "mean", "error"))
    series = [(theory, mean, error, "fitted mean per sweep point")]
    if np.isfinite([r.method for r in rows]).any():
        series.append((theory, np.array([r.method for r in rows]), None, f"what {ds.attrs['method']} shows"))
    paths.append(plotting.against_theory(plt, stem, "rates", series, theory_label="c (1/lambda1 - 1/lambda3)",
                                       quantity="tilt decay rate", units="1/s",
                                       title="tilt decay rate per sweep point"))
    return paths
