"""Fit the tilt decay rate of every top in a result and test it against the course's law.

    python analysis/tilt_decay.py RESULT.nc [--check] [--against theory|method] [--sample 6]

Prints, per sweep point, the mean fitted rate +- its standard error, the
theory c (1/lambda1 - 1/lambda3), what the run's method shows, z, and pass or
fail. Writes the fits to RESULT_tilt_decay.nc and three charts,
RESULT_tilt_decay_{tilt,rates,z}.png. With --check the exit status is 1 when
a sweep point fails; bad input exits 2 with one line.
"""
from __future__ import annotations

import sys

import numpy as np

from ensemble import arguments, report
from ensemble.scenes.top import fits as top_fit


def label(sel, point, mode) -> str:
    return (report.point_label(sel) if point is not None else "") or "all members"


def draw(plt, ds, fits, rows, stem, sample):
    fig, ax = plt.subplots(figsize=(7, 4.5), layout="constrained")
    t = ds["t"].values
    for i, member in enumerate(np.unique(np.linspace(0, ds.sizes["member"] - 1, sample).astype(int))):
        color = f"C{i % 10}"
        ax.semilogy(t, np.tan(ds["tilt"].values[member]), ".", ms=2, color=color, alpha=0.5)
        line = np.exp(fits["log_tan_tilt0"].values[member] - fits["rate"].values[member] * t)
        rate = fits["rate"].values[member]
        ax.semilogy(t, line, "-", color=color, lw=1, label=f"member {member}: rate {rate:.4g} 1/s")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("tan(tilt)")
    ax.set_title("tilt of sample members (dots) and fitted lines")
    ax.legend(fontsize=7, loc="best")
    paths = [report.save(plt, fig, stem, "tilt")]

    theory = np.array([r.theory for r in rows])

    def draw_fits(ax):
        ax.errorbar(theory, [r.mean for r in rows], yerr=[r.error for r in rows], fmt="o", label="fitted mean +- error")
        ax.plot(theory, [r.method for r in rows], "x", label=f"what {ds.attrs['method']} shows")

    paths.append(report.save_against_theory(
        plt, stem, "rates", draw_fits, [min(theory.min(), 0), theory.max()], "theory c (1/lambda1 - 1/lambda3)",
        "theoretical rate (1/s)", "fitted rate (1/s)", "tilt decay rate per sweep point"))
    return paths


def main(argv=None) -> int:
    parser = report.parser(__doc__)
    parser.add_argument("--sample", type=arguments.positive_int, default=6, help="members drawn in the tilt chart")
    args = parser.parse_args(argv)
    return report.run_script(args, top_fit.tilt_decay, name="tilt_decay", value="rate", units="1/s",
                             title="tilt decay rates", label=label,
                             draw=lambda *a: draw(*a, sample=args.sample))


if __name__ == "__main__":
    sys.exit(main())
