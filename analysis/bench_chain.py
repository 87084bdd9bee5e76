"""Benchmark: chain kernels against NumPy vectorized over members, at several chain lengths.

    python analysis/bench_chain.py [--masses 1048576] [--repeats 5] [--n 2 16 1024]

For each chain length n the ensemble holds about `masses` masses in all
(members = masses / n). The Numba verlet kernel and a NumPy velocity Verlet
(one force evaluation per step, as the kernel does) run side by side in this
process; the script prints median mass-steps per second and their ratio.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from ensemble import kernels
from ensemble.scenes import chain


def numpy_verlet(x, v, c_left, c_right, h, steps):
    """Velocity Verlet over members with NumPy: x, v and spring constants over mass c_left, c_right (n, M)."""
    x, v = x.copy(), v.copy()
    walls = np.zeros((x.shape[0] + 2, x.shape[1]))

    def acceleration():
        walls[1:-1] = x
        return c_left * (walls[:-2] - x) + c_right * (walls[2:] - x)

    a = acceleration()
    for _ in range(steps):
        v += 0.5 * h * a
        x += h * v
        a = acceleration()
        v += 0.5 * h * a
    return x, v


def median_seconds(fn, repeats):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--masses", type=int, default=2**20)
    parser.add_argument("--n", type=int, nargs="+", default=[2, 16, 1024])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    rng = np.random.default_rng(2026)
    h = 1e-2
    print(f"chain, fixed ends, velocity Verlet, about {args.masses} masses per ensemble, median of {args.repeats}")
    print(f"{'n':>5} {'members':>8} {'numba mass-steps/s':>19} {'numpy mass-steps/s':>19} {'ratio':>6}")
    rates = {}
    for n in args.n:
        members = max(args.masses // n, 1)
        values = {"m": rng.uniform(0.5, 2, (members, n)), "k": rng.uniform(0.5, 2, (members, n + 1)),
                  "x0": rng.normal(0, 0.1, (members, n)), "v0": np.zeros((members, n))}
        constants = {"n": n, "boundary": "fixed"}
        state, rate = chain.inputs(values, constants)
        key = chain.kernel_key(constants)
        kernel = kernels.kernel_for("chain", "verlet", key)
        block = kernels.block_size("chain", key)
        members -= members % block
        state, rate = state[:, :members], rate[:, :members]
        inputs = kernels.blocked(state, block), kernels.blocked(rate, block)
        samples = np.empty((2, members // block, 2 * n, block))
        failure = (np.full(members, np.inf), samples, np.zeros(members), np.full(members, np.nan))
        steps = 200
        kernel(*inputs, h, 1, *failure)  # compile or load; failure: limit, samples, status, time
        fast = members * n * steps / median_seconds(lambda: kernel(*inputs, h, steps, *failure), args.repeats)
        numpy_steps = 10
        slow = members * n * numpy_steps / median_seconds(
            lambda: numpy_verlet(state[:n], state[n:], rate[:n], rate[n:], h, numpy_steps), args.repeats)
        rates[n] = fast
        print(f"{n:>5} {members:>8} {fast:>19.3g} {slow:>19.3g} {fast / slow:>6.1f}")
    if len(rates) > 1:
        print(f"largest / smallest numba mass-steps/s across n: {max(rates.values()) / min(rates.values()):.2f}")


if __name__ == "__main__":
    main()
