"""Benchmark: what events cost a kernel, never firing (at most 5% of its rate) and firing often.

    python analysis/bench/event_cost.py [--repeats 5] [--members 32768] [--methods rk4 split4 dopri5]
                                        [--device cuda --t-end 5]   (on a GPU: 10^6 members or more)
    python analysis/bench/event_cost.py --sites 16 [--methods verlet rk4 dopri5]   (chains of 16 masses)

Aerobie tops (spin 60 rad/s, tilts drawn in 0.02..0.2 rad) integrate 2 s (--t-end) with each method: without events,
with an event on a state component (omega[2] rising to 1e6 rad/s) and with one on an observable (the tilt rising to
1.5 rad: watched through the top's watch_tilt, as a run file's, and, "unwatched", through its value alone), none of
which occurs; and with one that fires often (omega[0] through 0, twice a precession period of 0.105 s: each member
every 52 steps or so, the first occurrence kept). With --sites n, chains of n unit masses between walls (unit
springs, x0 drawn in -0.1..0.1 m), without events and with one on mass 1's x rising to 1e6 m. Prints each kernel's
member-steps/s on all threads (median of the repeats, the kernels alternated) and the median and quartiles of the
repeats' ratios to the kernel without events. Two threads on two cores of a shared host spread these ratios by
several points; one thread on one core (NUMBA_NUM_THREADS=1 taskset -c 1 python ...) by about one.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from hostinfo import host

from ensemble.engine import launch
from ensemble.methods import METHODS
from ensemble.results import Event
from ensemble.scenes import resolve

WATCHED = {"none": (),
           "omega[2]": (Event("spin", "omega", 2, ("state", 2), 1e6, "up"),),
           "tilt": (Event("tip", "tilt", -1, ("function", "value_tilt", -1, "watch_tilt"), 1.5, "up"),),
           "tilt unwatched": (Event("tip", "tilt", -1, ("function", "value_tilt", -1), 1.5, "up"),),
           "omega[0] firing": (Event("turn", "omega", 0, ("state", 0), 0.0, "both"),)}


def tops(members: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    return {"lambda1": np.full(members, 1e-3), "lambda3": np.full(members, 2e-3), "c": np.full(members, 1e-4),
            "spin0": np.full(members, 60.0), "tilt0": rng.uniform(0.02, 0.2, members),
            "azimuth0": rng.uniform(0.0, 2 * np.pi, members)}


CHAIN_WATCHED = {"none": (), "x[0]": (Event("far", "x", 0, ("state", 0), 1e6, "up"),)}


def chains(members: int, n: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    return {"m": np.ones((members, n)), "k": np.ones((members, n + 1)), "x0": rng.uniform(-0.1, 0.1, (members, n)),
            "v0": np.zeros((members, n))}


def rate(method: str, values: dict, events: tuple, t_end: float = 0.5, device: str = "cpu", sites: int = 0) -> float:
    """Member-steps per second of one launch saving only the end (of tops, or of chains of `sites` masses); on a
    GPU, of a launch whose inputs are already there, timed as gpu.py times (the kernel, its end state back)."""
    scene, constants = (resolve("chain"), {"n": sites, "boundary": "fixed"}) if sites else (resolve("top"), {})
    if device == "cuda":
        from gpu import timed

        seconds, outcome = timed(scene, METHODS[method], values, constants, dt=1e-3, t_end=t_end, device=device,
                                 repeats=1, rtol=1e-8, atol=1e-10, events=events)
        return outcome.counts[0].sum() / seconds
    start = time.perf_counter()
    outcome = launch.integrate(scene, METHODS[method], values, constants, n_save=2, save_dt=t_end, dt=1e-3,
                               rtol=1e-8, atol=1e-10, events=events, device=device)
    return outcome.counts[0].sum() / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--members", type=int, default=1 << 15)
    parser.add_argument("--methods", nargs="+", default=["rk4", "split4", "dopri5"])
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    parser.add_argument("--sites", type=int, default=0, help="chains of this many masses instead of tops")
    parser.add_argument("--t-end", type=float, default=2.0, help="each launch's span (s; steps of 1e-3 s): on a "
                        "GPU, long enough that the kernel outlasts the transfers")
    args = parser.parse_args()
    print(host())
    if args.device == "cuda":
        from ensemble.engine.gpu import require_gpu

        print(f"device: {require_gpu()}")
    values = chains(args.members, args.sites) if args.sites else tops(args.members)
    watched = CHAIN_WATCHED if args.sites else WATCHED
    for method in args.methods:
        for events in watched.values():  # compiled (or loaded) before the clock
            rate(method, {name: v[:128] for name, v in values.items()}, events, 0.01, args.device, args.sites)
        rates = {label: [] for label in watched}
        for _ in range(args.repeats):
            for label, events in watched.items():
                rates[label].append(rate(method, values, events, args.t_end, args.device, args.sites))
        for label, measured in rates.items():
            ratios = [r / base for r, base in zip(measured, rates["none"])]
            low, _, high = statistics.quantiles(ratios, n=4) if len(ratios) > 1 else ratios * 3
            print(f"{method:7s} {label:15s} {statistics.median(measured):.3e} member-steps/s   "
                  f"x {statistics.median(ratios):.3f} (quartiles {low:.3f} {high:.3f})")


if __name__ == "__main__":
    main()
