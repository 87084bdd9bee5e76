"""The charts `ensemble fit`, `ensemble stability` and `ensemble work-precision` draw, as PNG files beside the
result; a scene's own charts are in its folder (ensemble/scenes/<scene>/plots.py).

They need matplotlib (the `plot` extra); ensemble.plotting.pyplot() says so in one line without it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import xarray as xr

from . import fitting, stability
from .fitting import RTOL, fitted_values
from .methods import METHODS
from .plotting import LEGEND_OUTSIDE, save, z_histogram
from .results import Status


def draw_misses(plt, fits: xr.Dataset, stem: Path, against: str, title: str, noisy: bool) -> Path:
    """How the fits miss their reference, STEM_z.png: z against N(0, 1) when the result has observation noise
    (`noisy`) and the fit gives z; without noise z has no distribution to follow (its error bar is the fit's own
    residual), so the relative miss (fitted / reference - 1) of each member is drawn at its member number, beside
    the bound --check holds a sweep point's mean to."""
    fig, ax = plt.subplots(figsize=(6.5, 4.5), layout="constrained")
    what = "theory" if against == "theory" else "what the method shows"
    if noisy and ("z" if against == "theory" else "z_method") in fits:
        z_histogram(ax, fits["z" if against == "theory" else "z_method"].values.ravel(), "fits", what)
        ax.set_title(f"{title}: fitted against {what}", fontsize=9)
        return save(plt, fig, stem, "z")
    for name, marker in zip(fitted_values(fits), "ox^"):
        reference = fits[f"{name}_method" if against == "method" and f"{name}_method" in fits else f"{name}_theory"]
        member = xr.broadcast(fits["member"], fits[name])[0].values.ravel()
        with np.errstate(divide="ignore", invalid="ignore"):
            miss = (fits[name].values / reference.values - 1).ravel()
        shown = np.isfinite(miss)
        if shown.any():
            ax.plot(member[shown], miss[shown], marker, ms=3, mfc="none", label=name.replace("_", " "))
    ax.axhline(0.0, color="k", lw=0.5)
    bound = max((float(fits[name].attrs.get("check_rtol", RTOL)) for name in fitted_values(fits)), default=RTOL)
    ax.axhspan(-bound, bound, color="g", alpha=0.15, label=f"+-{bound:g}: --check's bound on a sweep point's mean")
    ax.set_xlabel("member" + (" (every mode at its member)" if "mode" in fits.dims else ""))
    ax.set_ylabel(f"fitted / {what} - 1")
    why = "the fit gives no z" if noisy else "noise-free: no z"
    ax.set_title(f"{title}: relative miss of each member ({why})", fontsize=9)
    ax.legend(fontsize=8)
    return save(plt, fig, stem, "z")


def draw_stability_map(plt, points: xr.Dataset, rows: list[dict], stem: Path) -> Path:
    """Measured growth per step against the dimensionless step, per stability axis: markers (open: the member
    ran to the end; x: it failed), each method's theory (lines) and theoretical limit (dotted)."""
    from .scenes import of_result

    scene = of_result(points.attrs)
    axes_used = [a for a in scene.STABILITY_AXES if (points["axis"].values == a).any()]
    fig, panels = plt.subplots(1, len(axes_used), figsize=(6.5 * len(axes_used), 5), layout="constrained",
                               squeeze=False)
    for panel, axis in zip(panels[0], axes_used):
        on_axis = points["axis"].values == axis
        span = np.linspace(0, 1.05 * points["x"].values[on_axis].max(), 600)[1:]
        for i, method in enumerate(dict.fromkeys(points["method"].values[on_axis])):
            color, marker = f"C{i % 10}", "osD^v<>"[i % 7]  # methods with equal growth (verlet, symplectic euler)
            chosen = on_axis & (points["method"].values == method)  # must all show: markers and sizes differ
            x, growth, failed = (points[v].values[chosen] for v in ("x", "growth", "status"))
            panel.semilogy(span, scene.axis_growth(METHODS[method], axis, span), "-", color=color, lw=1, alpha=0.7)
            panel.semilogy(x[failed == Status.OK], growth[failed == Status.OK], marker, color=color, ms=7 - i,
                           mfc="none", label=method)
            panel.semilogy(x[failed != Status.OK], growth[failed != Status.OK], "x", color=color, ms=6)
            limit = next((r["theory"] for r in rows if r["method"] == method and r["axis"] == axis), np.nan)
            if np.isfinite(limit) and limit > 0:
                panel.axvline(limit, color=color, ls=":", lw=1)
        panel.axhline(1.0, color="k", lw=0.5)
        panel.set_xlabel(axis)
        panel.set_ylabel("growth factor per step")
        panel.set_title(f"{axis}: measured (open markers ok, x failed), theory (lines), limits (dotted)",
                        fontsize=9)
        panel.legend(fontsize=8)
    return save(plt, fig, stem, "map")


FLOOR = 1e-17  # energy drifts below this are rounding, drawn at it
ENVELOPE_POINTS = 200  # the drift's oscillation is drawn as its upper envelope over this many windows


def _envelope(t: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Upper envelope: the largest value in each of ENVELOPE_POINTS windows, at the window's end time."""
    if values.size <= ENVELOPE_POINTS:
        return t, values
    edges = np.linspace(0, values.size, ENVELOPE_POINTS + 1).astype(int)
    return t[edges[1:] - 1], np.maximum.reduceat(values, edges[:-1])


def draw_energy_drift(plt, ds: xr.Dataset, points: xr.Dataset, drift_step: float, stem: Path) -> Path | None:
    """The relative energy error over the run of the member of each method nearest to `drift_step` on the
    oscillation axis; None (and one line saying why) when the result cannot give the drift."""
    from .scenes import of_result

    try:
        drift = stability.energy_drift(ds)
    except fitting.FitError as e:
        print(f"no energy chart: {e}")
        return None
    oscillation = of_result(points.attrs).STABILITY_AXES[0]  # the energy is conserved without drag
    fig, ax = plt.subplots(figsize=(7, 4.5), layout="constrained")
    drawn = False
    for i, method in enumerate(dict.fromkeys(points["method"].values)):
        chosen = np.flatnonzero((points["method"].values == method) & (points["axis"].values == oscillation))
        members = [m for m in points["member"].values[chosen] if np.isfinite(drift.sel(member=m).values[1:]).any()]
        if not members:
            continue
        x = points["x"].sel(member=members).values
        member = members[int(np.argmin(np.abs(x - drift_step)))]
        values = drift.sel(member=member).values[1:]
        t, envelope = _envelope(ds["t"].values[1:], np.maximum(values, FLOOR))
        ax.semilogy(t, envelope, "-", color=f"C{i % 10}", lw=1,
                    label=f"{method} at {oscillation} = {float(points['x'].sel(member=member)):.3g}"
                          f"{' (symplectic)' if METHODS[method].symplectic else ''}")
        drawn = True
    if not drawn:
        plt.close(fig)
        return None
    ax.set_xlabel("t (s)")
    ax.set_ylabel("|E / E(0) - 1|")
    ax.set_title(f"energy drift, one member per method\n(upper envelope; < {FLOOR:g} drawn at {FLOOR:g})",
                 fontsize=9)
    ax.legend(**LEGEND_OUTSIDE)
    return save(plt, fig, stem, "energy")


def draw_work_precision(plt, table: xr.Dataset, stem: Path, title: str) -> Path:
    """Error against kernel seconds per member (this machine), against right-hand-side evaluations per member
    (any machine) and against the step with reference slopes dt^order, one line per method (and per precision or
    device where the table combines results: a method's colour, a result's line style)."""
    fig, (cost, evaluations, steps) = plt.subplots(1, 3, figsize=(17, 5), layout="constrained")
    unevaluated = []
    methods = list(dict.fromkeys(table["method"].values))
    suffixes = list(dict.fromkeys(line[len(method):] for line, method in zip(table["line"].values,
                                                                               table["method"].values)))
    for line in dict.fromkeys(table["line"].values):
        chosen = table["line"].values == line
        method = str(table["method"].values[chosen][0])
        style = dict(color=f"C{methods.index(method) % 10}", label=line,
                     linestyle=("-", "--", "-.", ":")[suffixes.index(line[len(method):]) % 4], marker="o")
        error, dt, seconds, rhs = (table[name].values[chosen] for name in ("error", "dt", "seconds", "rhs_evals"))
        order = np.argsort(dt)
        steps.loglog(dt[order], error[order], **style)
        if np.any(rhs > 0):
            evaluations.loglog(rhs[order], error[order], **style)
        else:
            unevaluated.append(line)
        if np.isfinite(seconds).any():
            cost.loglog(seconds[order], error[order], **style)
        nominal = METHODS[method].order
        usable = np.isfinite(error) & (error < fitting.ASYMPTOTIC) & (error > 0)
        if usable.any() and nominal and suffixes.index(line[len(method):]) == 0:  # reference slope dt^order
            anchor = np.flatnonzero(usable)[np.argmax(dt[usable])]  # through the most accurate asymptotic point
            span = np.array([dt[usable].min(), dt[usable].max()])
            steps.loglog(span, error[anchor] * (span / dt[anchor]) ** nominal, ":", color=style["color"],
                         label=f"dt^{nominal}")
    cost.set_xlabel("kernel seconds per member to t_end")
    cost.set_title("work against precision: this machine's kernel time")
    evaluations.set_xlabel("right-hand-side (force) evaluations per member to t_end")
    evaluations.set_title("work against precision: evaluations (any machine)"
                          + (f"\nnot drawn, no rhs evaluations (exact pieces): {', '.join(unevaluated)}"
                             if unevaluated else ""), fontsize=10)
    steps.set_xlabel("dt (s); adaptive methods: mean step")
    steps.set_title("error against step, with reference slopes")
    for ax in (cost, evaluations, steps):
        ax.set_ylabel("relative error (median of error_max)")
        ax.grid(True, which="major", alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    fig.suptitle(title)
    return save(plt, fig, stem)
