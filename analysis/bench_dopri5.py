"""Benchmark: adaptive dopri5 against fixed-step rk4, per step and at equal accuracy.

    python analysis/bench_dopri5.py [--repeats 3]

1. Kernel seconds per member-step of rk4 and dopri5, side by side in this
   process (medians of --repeats): 8192 aerobie tops (runs/aerobie.toml), and
   4096 disordered 16-mass chains.
2. Right-hand-side evaluations each needs for a largest error of 1e-10 over
   2 s on a top spinning at 200 rad/s: rk4 halves dt until it gets there,
   dopri5 lowers rtol by decades.
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
from hostinfo import host

from ensemble.arguments import OneLineParser, positive_int
from ensemble.engine import launch
from ensemble.methods import METHODS
from ensemble.records import measured_error
from ensemble.scenes import chain, top
from ensemble.spec import members_table, parse

RUNS = Path(__file__).resolve().parent.parent / "runs"
CHAIN = """scene = "chain"
method = "rk4"
dt = 1e-2
t_end = 10.0
save_dt = 1.0
members = 4096
seed = 1
[parameters]
n = 16
boundary = "fixed"
m = { uniform = [0.5, 2.0] }
k = 1.0
x0 = { uniform = [-0.1, 0.1] }
"""


def per_step(scene, values, constants, dt, save_dt, n_save, repeats):
    """Median kernel seconds per member-step of rk4 (step dt) and dopri5 (rtol 1e-8)."""
    rk4, dopri5 = METHODS["rk4"], METHODS["dopri5"]
    for method in (rk4, dopri5):
        launch.prepare(scene, method, constants)
    fixed = launch.Launch(scene, rk4, values, constants, n_save=n_save, save_dt=save_dt, dt=dt)
    adaptive = launch.Launch(scene, dopri5, values, constants, n_save=n_save, save_dt=save_dt, rtol=1e-8, atol=1e-12)
    rk4, dopri5 = [], []
    for _ in range(repeats):
        for call, seconds in ((fixed, rk4), (adaptive, dopri5)):
            start = time.perf_counter()
            call.run()
            elapsed = time.perf_counter() - start
            counts = call.outcome().counts
            seconds.append(elapsed / (counts[0].sum() + counts[1].sum()))
    return statistics.median(rk4), statistics.median(dopri5)


def evaluations_for(target: float):
    """rhs evaluations per member that rk4 and dopri5 need for a largest error <= target (fast top, 2 s)."""
    text = (RUNS / "aerobie.toml").read_text()
    spec = parse(text.replace("members = 200", "members = 4"))
    values = {name: v[:4] for name, v in members_table(spec).items()}
    values.update(spin0=np.full(4, 200.0), c=np.full(4, 1e-3))
    t = np.arange(9) * 0.25
    exact = top.exact(values, {}, t)
    rk4 = dopri5 = None
    for steps_per_save in 100 * 2 ** np.arange(10):
        samples = launch.integrate(top, METHODS["rk4"], values, {}, n_save=9, save_dt=0.25,
                                   dt=0.25 / steps_per_save).samples
        if measured_error(samples, exact)[0].max() <= target:
            rk4 = (4 * steps_per_save * 8, 0.25 / steps_per_save)
            break
    for rtol in 10.0 ** -np.arange(6, 15):
        samples, counts = launch.integrate(top, METHODS["dopri5"], values, {}, n_save=9, save_dt=0.25, rtol=rtol,
                                           atol=1e-14)[:2]
        if measured_error(samples, exact)[0].max() <= target:
            dopri5 = (int(counts[2].max()), rtol)
            break
    return rk4, dopri5


def main():
    parser = OneLineParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=positive_int, default=3)
    args = parser.parse_args()
    print(host())
    spec = parse((RUNS / "aerobie.toml").read_text().replace("members = 200", "members = 4096"))
    tops = {name: v[:8192] for name, v in members_table(spec).items()}
    rk4, dopri5 = per_step(top, tops, {}, 1e-3, 0.1, 31, args.repeats)
    print(f"top, 8192 members: rk4 {rk4:.3g} s, dopri5 {dopri5:.3g} s per member-step, ratio {dopri5 / rk4:.1f}")
    chain_spec = parse(CHAIN)
    rk4, dopri5 = per_step(chain, members_table(chain_spec), chain_spec.constants, 1e-2, 1.0, 11, args.repeats)
    print(f"chain n = 16, 4096 members: rk4 {rk4:.3g} s, dopri5 {dopri5:.3g} s per member-step, "
          f"ratio {dopri5 / rk4:.1f}")
    (rk4_evals, dt), (dopri5_evals, rtol) = evaluations_for(1e-10)
    print(f"top at 200 rad/s, error <= 1e-10 over 2 s: rk4 {rk4_evals} rhs evaluations (dt = {dt:.3g} s), "
          f"dopri5 {dopri5_evals} (rtol = {rtol:.0e}): {rk4_evals / dopri5_evals:.1f}x fewer")


if __name__ == "__main__":
    main()
