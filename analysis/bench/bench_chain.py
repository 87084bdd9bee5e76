"""Benchmark: chain kernels against NumPy vectorized over members, at several chain lengths.

    python analysis/bench/bench_chain.py [--masses 1048576] [--repeats 7] [--n 2 16 1024] [--steps 200]
                                   [--method verlet] [--boundary fixed] [--block B]

For each chain length n the ensemble holds about `masses` masses in all
(members = masses / n). The Numba kernel of --method and a NumPy velocity
Verlet with fixed ends (one force evaluation per step, as a verlet kernel
does) run side by side in this process, in rounds that time each contender
once; the script prints median mass-steps per second and the median of the
ratios taken within each round (this machine is shared: its speed drifts
between rounds, not within one). A kernel call runs --steps steps and saves
once: its fixed cost per call (blocking the inputs, allocating the samples)
weighs less the more steps a call makes. For a method other than verlet the
ratio compares unlike work (yoshida4 evaluates forces three times a step).

When ../shared/limit/limit.py sits beside the checkout, each round also times
its hand-written C verlet on fixed chains of the same n (at its best block
size), and the script prints the median of the ratios to the C taken within
each round: on these shared hosts the C's own rate wandered by 30% within
minutes, so a ratio to a C measured minutes apart says little.

--block B runs every kernel in blocks of B members instead of the block that
ensemble.engine.sites.block_size picks for this host: how its rule
was measured. A member's bits do not depend on its block.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from hostinfo import force_chain_block, host, limit_module

from ensemble.arguments import OneLineParser, positive_int
from ensemble.engine import launch
from ensemble.methods import METHODS
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


def seconds(fn):
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def contenders(n, masses, rng, h, steps, numpy_steps, method="verlet", boundary="fixed"):
    """For a chain of n masses: the members, and the Numba kernel and NumPy calls (each returns mass-steps)."""
    members = max(masses // n, 1)
    values = {"m": rng.uniform(0.5, 2, (members, n)),
              "k": rng.uniform(0.5, 2, (members, chain.spring_count(n, boundary))),
              "x0": rng.normal(0, 0.1, (members, n)), "v0": np.zeros((members, n))}
    constants = {"n": n, "boundary": boundary}
    block = launch.layout(chain, METHODS[method], constants).block
    members = max(members - members % block, block)
    values = {name: v[:members] for name, v in values.items()}
    state, rate = chain.inputs(values, constants)
    kernel = METHODS[method]
    launch.prepare(chain, kernel, constants)  # compile or load
    call = launch.Launch(chain, kernel, values, constants, n_save=2, save_dt=h * steps, dt=h, blowup_factor=np.inf)

    def fast():
        call.run()
        return members * n * steps

    def slow():
        numpy_verlet(state[:n], state[n:], rate[:n], rate[n:], h, numpy_steps)
        return members * n * numpy_steps

    return members, fast, slow


def main():
    parser = OneLineParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--masses", type=positive_int, default=2**20)
    parser.add_argument("--n", type=positive_int, nargs="+", default=[2, 16, 1024])
    parser.add_argument("--repeats", type=positive_int, default=7)
    parser.add_argument("--steps", type=positive_int, default=200,
                        help="Numba steps per kernel call (one saved sample)")
    parser.add_argument("--method", default="verlet", choices=["verlet", "yoshida4", "symplectic_euler"])
    parser.add_argument("--boundary", default="fixed", choices=["fixed", "free", "periodic"])
    parser.add_argument("--block", type=positive_int, help="members per kernel block (default: block_size's choice)")
    args = parser.parse_args()
    if args.block:
        force_chain_block(args.block)
    print(host() + (f", blocks of {args.block} members" if args.block else ""))
    rng = np.random.default_rng(2026)
    h = 1e-2
    runs = {n: contenders(n, args.masses, rng, h, args.steps, 10, args.method, args.boundary) for n in args.n}
    limit = limit_module()
    fast_rates = {n: [] for n in args.n}
    slow_rates = {n: [] for n in args.n}
    c_rates = {n: [] for n in args.n}
    for _ in range(args.repeats):  # rounds: every contender once, so slow spells of the machine hit them all
        for n, (_, fast, slow) in runs.items():
            fast_rates[n].append(fast() / seconds(fast))
            slow_rates[n].append(slow() / seconds(slow))
            if limit:
                c_rates[n].append(limit.chain_verlet_rate(N=n)[0])  # as limit.py: best block, medians of 5
    print(f"chain, {args.boundary} ends, {args.method}, about {args.masses} masses per ensemble, {args.steps} steps "
          f"per kernel call; medians of {args.repeats} rounds, ratios taken within each round")
    print(f"{'n':>5} {'members':>8} {'numba mass-steps/s':>19} {'numpy mass-steps/s':>19} {'ratio':>6} "
          f"{'ratio range':>12}" + (f" {'C verlet':>9} {'/ C':>5} {'range':>10}" if limit else ""))
    for n, (members, _, _) in runs.items():
        ratios = [f / s for f, s in zip(fast_rates[n], slow_rates[n])]
        line = (f"{n:>5} {members:>8} {statistics.median(fast_rates[n]):>19.3g} "
                f"{statistics.median(slow_rates[n]):>19.3g} {statistics.median(ratios):>6.1f} "
                f"{min(ratios):>5.1f}..{max(ratios):<5.1f}")
        if limit:
            to_c = [f / c for f, c in zip(fast_rates[n], c_rates[n])]
            line += (f" {statistics.median(c_rates[n]):>9.3g} {statistics.median(to_c):>5.2f} "
                     f"{min(to_c):>4.2f}..{max(to_c):<4.2f}")
        print(line)
    if len(args.n) > 1:
        spread = [max(r) / min(r) for r in zip(*fast_rates.values())]
        print(f"largest / smallest numba mass-steps/s across n, median over rounds: {statistics.median(spread):.2f}")


if __name__ == "__main__":
    main()
