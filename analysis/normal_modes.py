"""Fit the normal-mode frequencies of every chain in a result and test them against theory.

    python analysis/normal_modes.py RESULT.nc [--check] [--against theory|method] [--member 0]

Prints, per sweep point and mode, the mean fitted frequency +- its standard
error, the eigenfrequency of K v = w^2 M v, what the run's method shows
(velocity Verlet: (2/h) asin(w h / 2)), z, and pass or fail; modes that never
ring are listed as none fitted. Writes the fits to RESULT_normal_modes.nc and
three charts, RESULT_normal_modes_{spectrum,frequencies,z}.png. With --check
the exit status is 1 when a fitted mode fails; bad input exits 2 with one line.
"""
from __future__ import annotations

import sys

import numpy as np

from ensemble import report
from ensemble.scenes.chain import fits as chain_fit


def label(sel, point, mode) -> str:
    where = report.point_label(sel) if point is not None else ""
    return f"{where}, mode {mode}" if where else f"mode {mode}"


def draw(plt, ds, fits, rows, stem, member):
    t = ds["t"].values
    x = ds["x"].values[member]
    pad = 8 * t.size
    omega = 2 * np.pi * np.fft.rfftfreq(pad, t[1] - t[0])
    power = np.sum(np.abs(np.fft.rfft((x - x.mean(axis=0)) * np.hanning(t.size)[:, None], pad, axis=0)) ** 2, axis=1)
    fig, ax = plt.subplots(figsize=(7, 4.5), layout="constrained")
    ax.semilogy(omega, power / power.max(), lw=1, label=f"member {member}, summed over sites (Hann window)")
    theory = fits["frequency_theory"].values[member]
    for j, w in enumerate(theory):
        ax.axvline(w, color="k", ls="--", lw=0.7, label="theory (eigenfrequencies)" if j == 0 else None)
    found = fits["frequency"].values[member]
    ax.plot(found[np.isfinite(found)], np.ones(np.isfinite(found).sum()), "rv", label="fitted")
    ax.set_xlim(0, 1.15 * max(theory.max(), 1e-12))
    ax.set_ylim(1e-12, 3)
    ax.set_xlabel("angular frequency (rad/s)")
    ax.set_ylabel("power (relative to the largest)")
    ax.set_title("spectrum of x(t)")
    ax.legend(loc="lower left", fontsize=8)
    paths = [report.save(plt, fig, stem, "spectrum")]

    th, fr = fits["frequency_theory"].values.ravel(), fits["frequency"].values.ravel()
    ok = np.isfinite(fr)
    paths.append(report.save_against_theory(
        plt, stem, "frequencies", lambda ax: ax.plot(th[ok], fr[ok], ".", ms=4, label="fitted, every member and mode"),
        [0, th.max()], "theory", "eigenfrequency (rad/s)", "fitted frequency (rad/s)",
        "fitted frequencies against theory"))
    return paths


def main(argv=None) -> int:
    parser = report.parser(__doc__)
    parser.add_argument("--member", type=int, default=0, help="member whose spectrum is drawn")
    args = parser.parse_args(argv)

    def validate(ds):
        if not 0 <= args.member < ds.sizes["member"]:
            raise ValueError(f"--member {args.member} is not in 0..{ds.sizes['member'] - 1}")

    return report.run_script(args, chain_fit.mode_frequencies, name="normal_modes", value="frequency", units="rad/s",
                             title="normal-mode frequencies", label=label, validate=validate,
                             draw=lambda *a: draw(*a, member=args.member))


if __name__ == "__main__":
    sys.exit(main())
