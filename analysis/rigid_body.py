"""Fit how free bodies move about their spin axis and test it against theory.

    python analysis/rigid_body.py RESULT.nc [--check] [--against theory|method] [--sample 6]

Prints, per sweep point, the mean fitted growth rate of small tilts (spun
about the intermediate axis) or their wobble frequency (about a stable axis)
+- its standard error, the linear theory, what the run's method shows, z, and
pass or fail; then the flip period against the elliptic formula where the
records hold at least three flips. Writes the fits to RESULT_rigid_body.nc
and the charts RESULT_rigid_body_{tilt,rates,z}.png (and _flips, _flip_z when
bodies flip). With --check the exit status is 1 when a sweep point fails; bad
input exits 2 with one line.
"""
from __future__ import annotations

import sys

import numpy as np

from ensemble import arguments, report
from ensemble.scenes import body
from ensemble.scenes.body import fits as body_fit

QUANTITIES = (("growth_rate", "1/s", "growth rates of small tilts"),
              ("wobble_frequency", "rad/s", "wobble frequencies of small tilts"),
              ("flip_period", "s", "flip periods"))


def label(sel, point, mode) -> str:
    return (report.point_label(sel) if point is not None else "") or "all members"


def draw(plt, ds, fits, rows, stem, sample):
    present = [name for name in ("growth_rate", "wobble_frequency") if np.isfinite(fits[name].values).any()]
    paths = [_tilt_chart(plt, ds, fits, stem, sample)]

    def draw_fits(ax):
        for name, marker in zip(present, ".x"):
            ax.plot(fits[f"{name}_theory"].values, fits[name].values, marker, ms=4,
                    label=f"fitted {name.replace('_', ' ')}, every member")

    top = max([np.nanmax(fits[f"{name}_theory"].values) for name in present], default=1.0)
    paths.append(report.save_against_theory(
        plt, stem, "rates", draw_fits, [0, top], "linear theory", "theory (1/s or rad/s)", "fitted (1/s or rad/s)",
        "growth rates and wobble frequencies against theory"))
    period, period_theory = fits["flip_period"].values, fits["flip_period_theory"].values
    flipped = np.isfinite(period) & np.isfinite(period_theory)
    if flipped.any():
        paths.append(report.save_against_theory(
            plt, stem, "flips", lambda ax: ax.plot(period_theory[flipped], period[flipped], ".", ms=4,
                                                   label="fitted, every member that flips"),
            [np.min(period_theory[flipped]), np.max(period_theory[flipped])], "elliptic formula 4 K(m) / Omega",
            "theoretical flip period (s)", "fitted flip period (s)", "flip period against theory"))
        fig, ax = plt.subplots(figsize=(5.5, 4.5), layout="constrained")
        report.z_histogram(ax, fits["flip_z"].values, "flip periods")
        ax.set_title("flip periods: fitted against theory")
        paths.append(report.save(plt, fig, stem, "flip_z"))
    return paths


def _tilt_chart(plt, ds, fits, stem, sample):
    """The tilt of sample members against time; for growing tilts, the fitted exponential through the last
    fitted sample."""
    fig, ax = plt.subplots(figsize=(7, 4.5), layout="constrained")
    t = ds["t"].values
    tilts = body.tilt(ds["omega"].values.transpose(2, 1, 0), ds["spin_axis"].values).T  # (member, t)
    for i, member in enumerate(np.unique(np.linspace(0, ds.sizes["member"] - 1, sample).astype(int))):
        color = f"C{i % 10}"
        tilt = tilts[member]
        ax.semilogy(t, tilt, ".", ms=2, color=color, alpha=0.5)
        used, rate = int(fits["samples_used"].values[member]), fits["growth_rate"].values[member]
        if np.isfinite(rate) and used >= 2:
            ax.semilogy(t[:used], tilt[used - 1] * np.exp(rate * (t[:used] - t[used - 1])), "-", color=color, lw=1,
                        label=f"member {member}: growth rate {rate:.5g} 1/s")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("tilt (rad)")
    ax.set_title("tilt of sample members (dots), fitted exponentials where the tilt grows")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7, loc="best")
    return report.save(plt, fig, stem, "tilt")


def main(argv=None) -> int:
    parser = report.parser(__doc__)
    parser.add_argument("--sample", type=arguments.positive_int, default=6, help="members drawn in the tilt chart")
    args = parser.parse_args(argv)
    return report.run_script(args, body_fit.body_rates, name="rigid_body", value=QUANTITIES, units="",
                             title="free-body motions", label=label,
                             draw=lambda *a: draw(*a, sample=args.sample))


if __name__ == "__main__":
    sys.exit(main())
