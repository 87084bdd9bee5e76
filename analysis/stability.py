"""Where each method fails: measured growth per step against linear theory, and energy drift.

    python analysis/stability.py RESULT.nc [--drift-step 0.5] [--check]

RESULT.nc comes from a stability scan such as runs/stability_chain.toml or
runs/stability_top.toml. Prints, per method and stability axis (h omega_max
for chains; h Omega and h c / lambda1 for tops), the theoretical limit beside
the measured one (where measured growth first exceeds 1 + 1e-3, interpolated
between the last stable and the first growing scan point) and counts the
failed members. Draws RESULT_stability_map.png (measured growth per step
against the dimensionless step, theory curves and limits) and
RESULT_stability_energy.png (relative energy error over the run of the member
of each method nearest to --drift-step on the oscillation axis). Writes the
map to RESULT_stability.nc. With --check the exit status is 1 when a measured
limit misses theory by more than 2%; bad input exits 2 with one line.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import xarray as xr

from ensemble import fit, report, stability
from ensemble.arguments import OneLineParser
from ensemble.errors import EXIT_BAD_INPUT, EXIT_CHECK_FAILED, EXIT_OK
from ensemble.methods import METHODS
from ensemble.results import Status
from ensemble.scenes import of_result

LIMIT_RTOL = 0.02  # --check: measured limits within this of theory


def limit_agrees(row: dict) -> bool:
    """Measured and theoretical limit agree: both none, both zero, or within LIMIT_RTOL. A limit with no theory on
    its axis alone (a body's splitting: the limit depends on the moments) is not judged; the map's per-member
    growth_theory covers it."""
    measured, theory = row["measured"], row["theory"]
    if np.isnan(theory):
        return True
    if np.isinf(theory) or theory == 0:
        return measured == theory
    return abs(measured / theory - 1) <= LIMIT_RTOL


def print_limits(rows: list[dict], points: xr.Dataset) -> None:
    print(f"{'method':<17} {'axis':<12} {'theory':>8} {'measured':>9} {'stable..growing':>16} {'miss':>7} "
          f"{'members':>7}  agree")
    for r in rows:
        bracket = f"{r['last_stable']:.3g}..{r['first_growing']:.3g}"
        miss = (f"{r['measured'] / r['theory'] - 1:+.1%}" if np.isfinite(r["theory"]) and r["theory"] > 0
                else "")
        print(f"{r['method']:<17} {r['axis']:<12} {r['theory']:>8.4g} {r['measured']:>9.4g} {bracket:>16} "
              f"{miss:>7} {r['members']:>7}  {'n/a' if np.isnan(r['theory']) else 'yes' if limit_agrees(r) else 'NO'}")
    print(f"limit: the smallest dimensionless step at which growth per step exceeds 1 (measured: 1 + "
          f"{stability.GROWTH_TOLERANCE:g}); inf: none, 0: grows at every step")
    for method in dict.fromkeys(points["method"].values):
        status = points["status"].values[points["method"].values == method]
        print(f"{method}: {np.sum(status == Status.BLEW_UP)} of {status.size} members blew up, "
              f"{np.sum(status == Status.STEP_SIZE_UNDERFLOW)} step size underflows")


def draw_map(plt, points: xr.Dataset, rows: list[dict], stem: Path) -> Path:
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
    return report.save(plt, fig, stem, "map")


FLOOR = 1e-17  # energy drifts below this are rounding, drawn at it
ENVELOPE_POINTS = 200  # the drift's oscillation is drawn as its upper envelope over this many windows


def _envelope(t: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Upper envelope: the largest value in each of ENVELOPE_POINTS windows, at the window's end time."""
    if values.size <= ENVELOPE_POINTS:
        return t, values
    edges = np.linspace(0, values.size, ENVELOPE_POINTS + 1).astype(int)
    return t[edges[1:] - 1], np.maximum.reduceat(values, edges[:-1])


def draw_energy(plt, ds: xr.Dataset, points: xr.Dataset, drift_step: float, stem: Path) -> Path | None:
    """The energy-drift chart; None (and one line saying why) when the result cannot give the drift."""
    try:
        drift = stability.energy_drift(ds)
    except fit.FitError as e:
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
    ax.set_title(f"energy drift, one member per method (upper envelope; < {FLOOR:g} drawn at {FLOOR:g})",
                 fontsize=9)
    ax.legend(fontsize=8)
    return report.save(plt, fig, stem, "energy")


def main(argv=None) -> int:
    parser = OneLineParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("result", type=Path, help="a result of a stability scan, e.g. runs/stability_chain.toml")
    parser.add_argument("--drift-step", type=float, default=0.5,
                        help="dimensionless step of the members in the energy-drift chart (default 0.5)")
    parser.add_argument("--check", action="store_true",
                        help=f"exit 1 when a measured limit misses theory by more than {LIMIT_RTOL:.0%}%")
    args = parser.parse_args(argv)
    loaded = report.load_result(args.result, stability.stability_map)
    if loaded is None:
        return EXIT_BAD_INPUT
    ds, points = loaded
    rows = stability.stability_limits(points)
    print(f"stability of {args.result} ({ds.attrs['scene']}, {ds.sizes['t'] - 1} saved intervals)")
    print_limits(rows, points)
    out, stem = report.outputs(args.result, "stability")
    try:
        points.to_netcdf(out)
        print(f"map: {out}")
        plt = report.pyplot()
        if plt is not None:
            charts = [draw_map(plt, points, rows, stem), draw_energy(plt, ds, points, args.drift_step, stem)]
            print("charts:", *[c for c in charts if c is not None])
    except OSError as e:
        report.cannot_write(out.parent, e)
    return EXIT_CHECK_FAILED if args.check and not all(limit_agrees(r) for r in rows) else EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
