"""Benchmark: the top's Numba kernels against NumPy vectorized over members.

    python analysis/bench/bench_top.py [--members 65536] [--steps 1000] [--repeats 7]

Both run in this process, side by side; the script prints medians and their
ratio (these machines are shared: quote ratios, not single times). Then the
free body's rk4 kernel (three moments, six parameters a member) against the
top's, in rounds that time each once, with the median of the ratios taken
within a round; with ../shared/limit/limit.py beside the checkout, each round
also times its hand-written C top rk4 on as many members and steps. It also
times a small run file through the command line
three times, so the later runs show the warm-cache start-up cost.
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from hostinfo import host, limit_module

from ensemble.arguments import OneLineParser, positive_int
from ensemble.engine import launch
from ensemble.engine.kernels import BLOCK
from ensemble.methods import METHODS
from ensemble.scenes import body, top
from ensemble.scenes.top.physics import rhs

ROOT = Path(__file__).resolve().parents[2]


def numpy_rk(tableau, state, rate, h, steps):
    """Explicit Runge-Kutta over members with NumPy, from the same tableau and right-hand side."""
    def f(y):
        return np.stack(rhs(0.0, y[0], y[1], y[2], rate[0], rate[1], rate[2]))
    for _ in range(steps):
        k = []
        for s in range(tableau.stages):
            y = state.copy()
            for r, a in enumerate(tableau.a[s][:s]):
                if a:
                    y += h * a * k[r]
            k.append(f(y))
        state = state + h * sum(b * ks for b, ks in zip(tableau.b, k))
    return state


def median_rate(fn, members, steps, repeats):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return members * steps / statistics.median(times)


def body_against_top(table, h, args):
    """rk4 on free bodies (lambda2 between lambda1 and lambda3) against rk4 on the same tops, in rounds."""
    n = len(table["c"])
    rk4 = METHODS["rk4"]
    bodies = {**table, "lambda2": 0.5 * (table["lambda1"] + table["lambda3"])}
    calls = {}
    for scene, values, constants in ((top, table, {}), (body, {**bodies, "spin_axis": np.full(n, 3.0)}, {})):
        launch.prepare(scene, rk4, constants)
        calls[scene.NAME] = launch.Launch(scene, rk4, values, constants, n_save=2, save_dt=h * args.steps, dt=h,
                                          blowup_factor=np.inf).run
    limit = limit_module()
    rates = {name: [] for name in (*calls, "C")}
    for _ in range(args.repeats):
        for name, call in calls.items():
            rates[name].append(median_rate(call, n, args.steps, 1))
        if limit:
            rates["C"].append(limit.top_rk4_rate(M=n, steps=args.steps, h=h, repeats=1))  # times its kernel alone
    for name, against in (("body", "top"), ("top", "C")):
        if not rates[against]:
            continue
        ratios = [b / t for b, t in zip(rates[name], rates[against])]
        print(f"rk4, {name} {statistics.median(rates[name]):.3g} against {against} "
              f"{statistics.median(rates[against]):.3g} member-steps/s: ratio {statistics.median(ratios):.2f} "
              f"(range {min(ratios):.2f}..{max(ratios):.2f}, within rounds)")


def main():
    parser = OneLineParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--members", type=positive_int, default=65536)
    parser.add_argument("--steps", type=positive_int, default=1000)
    parser.add_argument("--numpy-steps", type=positive_int, default=20)
    parser.add_argument("--repeats", type=positive_int, default=7)
    args = parser.parse_args()
    print(host())

    rng = np.random.default_rng(2026)
    n = max(args.members // BLOCK, 1) * BLOCK  # whole kernel blocks
    table = {"lambda1": np.full(n, 1e-3), "lambda3": rng.uniform(1.2e-3, 2e-3, n), "c": rng.uniform(0, 2e-4, n),
             "spin0": rng.uniform(30, 60, n), "tilt0": rng.uniform(0.02, 0.2, n), "azimuth0": rng.uniform(0, 6, n)}
    state, rate = top.initial_state(table), top.rates(table)
    h = 1e-3
    print(f"top, {n} members, Numba {args.steps} steps, NumPy {args.numpy_steps} steps, "
          f"median of {args.repeats}")
    print(f"{'method':<8} {'numba member-steps/s':>21} {'numpy member-steps/s':>21} {'ratio':>7}")
    for name in ("euler", "rk4"):
        method = METHODS[name]
        launch.prepare(top, method, {})  # compile or load
        call = launch.Launch(top, method, table, {}, n_save=2, save_dt=h * args.steps, dt=h, blowup_factor=np.inf)
        fast = median_rate(call.run, n, args.steps, args.repeats)
        slow = median_rate(lambda: numpy_rk(method.tableau, state, rate, h, args.numpy_steps),
                           n, args.numpy_steps, args.repeats)
        print(f"{name:<8} {fast:>21.3g} {slow:>21.3g} {fast / slow:>7.1f}")
    body_against_top(table, h, args)

    with tempfile.TemporaryDirectory() as tmp:
        walls = []
        for _ in range(3):
            start = time.perf_counter()
            subprocess.run([sys.executable, "-m", "ensemble", "run", str(ROOT / "runs" / "aerobie.toml"),
                            "-o", f"{tmp}/a.nc", "--force", "--quiet"], check=True, capture_output=True)
            walls.append(time.perf_counter() - start)
    print("ensemble run runs/aerobie.toml, whole process wall time (s): "
          + ", ".join(f"{w:.2f}" for w in walls) + " (first may compile; later ones load the cache)")


if __name__ == "__main__":
    main()
