"""Work against precision: what each digit of accuracy costs, per method, from a run with [measure].

    python analysis/work_precision.py RESULT.nc

RESULT.nc comes from a run with `[measure] error = true` (and `timing = true`
for the cost axis), such as runs/work_precision_top.toml. Prints a table per
method: its points (dt or rtol, median error, steps, rhs evaluations, kernel
seconds per member) and its measured convergence order beside the nominal
one. Draws RESULT_work_precision.png: error against kernel seconds per member
to t_end (seconds_per_step x steps: the work of a whole run), one line per
method, error against right-hand-side evaluations per member (the same on
any machine), and error against dt with reference slopes dt^order. Bad input exits
2 with one line.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import xarray as xr

from ensemble import fit, report
from ensemble.arguments import OneLineParser
from ensemble.errors import EXIT_BAD_INPUT
from ensemble.methods import METHODS


def print_table(table: xr.Dataset) -> None:
    for method in dict.fromkeys(table["method"].values):
        m = METHODS[method]
        chosen = table["method"].values == method
        order, used = fit.convergence_order(table, method)
        against = "mean step" if m.adaptive else "dt"
        print(f"{method}: nominal order {m.order}, measured {order:.3f} "
              f"(slope of log error on log {against} over {used} points in the asymptotic range)")
        print(f"  {'dt (s)':>10} {'rtol':>9} {'error':>10} {'steps':>10} {'rhs evals':>10} {'s/member':>10}")
        for i in np.flatnonzero(chosen):
            row = {name: table[name].values[i] for name in ("dt", "rtol", "error", "steps", "rhs_evals", "seconds")}
            print(f"  {row['dt']:>10.3g} {row['rtol']:>9.2g} {row['error']:>10.3g} {row['steps']:>10.0f} "
                  f"{row['rhs_evals']:>10.0f} {row['seconds']:>10.3g}")


def draw(plt, table: xr.Dataset, stem: Path, title: str) -> Path:
    fig, (cost, evaluations, steps) = plt.subplots(1, 3, figsize=(17, 5), layout="constrained")
    for method in dict.fromkeys(table["method"].values):
        chosen = table["method"].values == method
        error, dt, seconds, rhs = (table[name].values[chosen] for name in ("error", "dt", "seconds", "rhs_evals"))
        order = np.argsort(dt)
        line, = steps.loglog(dt[order], error[order], "o-", label=method)
        evaluations.loglog(rhs[order], error[order], "o-", color=line.get_color(), label=method)
        if np.isfinite(seconds).any():
            cost.loglog(seconds[order], error[order], "o-", color=line.get_color(), label=method)
        nominal = METHODS[method].order
        usable = np.isfinite(error) & (error < fit.ASYMPTOTIC) & (error > 0)
        if usable.any():  # reference slope dt^order through the method's most accurate asymptotic point
            anchor = np.flatnonzero(usable)[np.argmax(dt[usable])]
            span = np.array([dt[usable].min(), dt[usable].max()])
            steps.loglog(span, error[anchor] * (span / dt[anchor]) ** nominal, ":", color=line.get_color(),
                         label=f"dt^{nominal}")
    cost.set_xlabel("kernel seconds per member to t_end (seconds_per_step x steps)")
    cost.set_ylabel("relative error (median of error_max)")
    cost.set_title("work against precision: this machine's kernel time")
    evaluations.set_xlabel("right-hand-side (force) evaluations per member to t_end")
    evaluations.set_ylabel("relative error (median of error_max)")
    evaluations.set_title("work against precision: evaluations (any machine)")
    steps.set_xlabel("dt (s); adaptive methods: mean step")
    steps.set_ylabel("relative error (median of error_max)")
    steps.set_title("error against step, with reference slopes")
    for ax in (cost, evaluations, steps):
        ax.grid(True, which="major", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    return report.save(plt, fig, stem)


def main(argv=None) -> int:
    parser = OneLineParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("result", type=Path, help="a result of a run with [measure] error = true")
    args = parser.parse_args(argv)
    loaded = report.load_result(args.result, fit.work_precision)
    if loaded is None:
        return EXIT_BAD_INPUT
    ds, table = loaded
    print(f"work against precision in {args.result} ({ds.attrs['scene']}, t_end = {ds.attrs['t_end']} s)")
    print_table(table)
    if "seconds_per_step" not in ds:
        print("no timing in this result ([measure] timing = true): the cost panel is empty")
    out, stem = report.outputs(args.result, "work_precision")
    try:
        table.to_netcdf(out)
        print(f"table: {out}")
        plt = report.pyplot()
        if plt is not None:
            print("chart:", draw(plt, table, stem, f"{ds.attrs['scene']}: {ds.attrs.get('title', '')}"))
    except OSError as e:
        report.cannot_write(out.parent, e)
    return 0


if __name__ == "__main__":
    sys.exit(main())
