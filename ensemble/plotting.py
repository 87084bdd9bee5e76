"""The pieces every chart is drawn with (the package's charts in ensemble.charts, a scene's in its plots.py):
pyplot without a display, saving a chart as PNG, fitted values against their theory, z histograms, the members
a per-member chart draws."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import xarray as xr

LEGEND_OUTSIDE = {"loc": "upper left", "bbox_to_anchor": (1.02, 1.0), "fontsize": 7, "borderaxespad": 0.0}


def pyplot():
    """matplotlib.pyplot, drawing to files; None, after one line on stderr, without the `plot` extra (the tables
    and --check need no matplotlib)."""
    try:
        import matplotlib
    except ImportError:
        print('no charts: they need matplotlib (pip install "ensemble[plot]"); the table above stands',
              file=sys.stderr)
        return None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(plt, fig, stem: Path, chart: str = "") -> Path:
    """Write a chart as STEM_CHART.png (STEM.png without a chart name) and close it."""
    path = stem.with_name(f"{stem.name}_{chart}.png" if chart else f"{stem.name}.png")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def against_theory(plt, stem: Path, chart: str, series: list[tuple], *, theory_label: str, quantity: str,
                   units: str, title: str) -> Path:
    """Fitted values against theory (top, with the line fitted = theory) and their residuals fitted - theory
    with error bars (bottom: a miss too small to see against the values shows there).

    series: (theory, fitted, stderr or None, label) per set of points, arrays of one shape.
    """
    fig, (values, residuals) = plt.subplots(2, 1, figsize=(6, 6), sharex=True, height_ratios=(3, 2),
                                            layout="constrained")
    low, high = np.inf, -np.inf
    for i, (theory, fitted, stderr, label) in enumerate(series):
        ok = np.isfinite(theory) & np.isfinite(fitted)
        if not ok.any():
            continue
        values.plot(theory[ok], fitted[ok], "o.^sx"[i % 5], ms=4, mfc="none", color=f"C{i}", label=label)
        residuals.errorbar(theory[ok], (fitted - theory)[ok], yerr=None if stderr is None else stderr[ok],
                           fmt="o.^sx"[i % 5], ms=4, mfc="none", color=f"C{i}", elinewidth=0.8)
        low, high = min(low, theory[ok].min()), max(high, theory[ok].max())
    if np.isfinite(low):
        pad = 0.05 * (high - low) or 0.05 * max(abs(low), 1e-300)
        span = [low - pad, high + pad]
        values.plot(span, span, "k--", lw=1, label=theory_label)
    residuals.axhline(0.0, color="k", lw=0.8)
    for ax in (values, residuals):
        ax.ticklabel_format(useOffset=False)  # an offset label makes a 1e-13 difference look like a gap
    values.set(ylabel=f"fitted {quantity} ({units})", title=title)
    residuals.set(xlabel=f"theory: {theory_label} ({units})", ylabel=f"fitted - theory ({units})")
    residuals.set_title("residuals, +- standard error", fontsize=8)
    values.legend(fontsize=8)
    return save(plt, fig, stem, chart)


Z_SPAN = 50.0  # z histograms show |z| up to this; larger values are counted at the edge, and the legend says so


def z_histogram(ax, z: np.ndarray, label: str, reference: str = "theory") -> None:
    """Histogram of z values as a density, with the N(0, 1) density over it."""
    z = z[np.isfinite(z)]
    span = min(max(4.0, float(np.nanmax(np.abs(z))) if z.size else 4.0), Z_SPAN)
    outside = int(np.sum(np.abs(z) > span))
    clipped = f", {outside} beyond +-{span:g} drawn at the edges" if outside else ""
    ax.hist(np.clip(z, -span, span), bins=40, range=(-span, span), density=True, alpha=0.6,
            label=f"{label} ({z.size}{clipped})")
    grid = np.linspace(-span, span, 400)
    ax.plot(grid, np.exp(-grid**2 / 2) / np.sqrt(2 * np.pi), "k-", label="N(0, 1)")
    ax.set_xlabel(f"z = (fitted - {reference}) / standard error")
    ax.set_ylabel("density")
    ax.legend(fontsize=8)


def sample_members(ds: xr.Dataset, members: list[int] | None, count: int = 6) -> list[int]:
    """The members a per-member chart draws: those asked for, else `count` spread evenly over the result."""
    if members:
        return list(members)
    return [int(m) for m in np.unique(np.linspace(0, ds.sizes["member"] - 1, count).astype(int))]
