"""Benchmark: what events that never fire cost a kernel (issue: at most 5% of its rate).

    python analysis/bench/event_cost.py [--repeats 5] [--members 32768] [--methods rk4 split4 dopri5]
                                        [--device cuda]   (on a GPU: give it 10^6 members or more)

Aerobie tops (spin 60 rad/s, tilts drawn in 0.02..0.2 rad) integrate 0.5 s with each method: without events,
with an event on a state component (omega[2] rising to 1e6 rad/s) and with one on an observable (the tilt
rising to 1.5 rad), none of which occurs. Prints each kernel's member-steps/s on all threads (median of the
repeats, the three kernels alternated) and the median of the repeats' ratios to the kernel without events.
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
           "tilt": (Event("tip", "tilt", -1, ("function", "value_tilt", -1), 1.5, "up"),)}


def tops(members: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    return {"lambda1": np.full(members, 1e-3), "lambda3": np.full(members, 2e-3), "c": np.full(members, 1e-4),
            "spin0": np.full(members, 60.0), "tilt0": rng.uniform(0.02, 0.2, members),
            "azimuth0": rng.uniform(0.0, 2 * np.pi, members)}


def rate(method: str, values: dict, events: tuple, t_end: float = 0.5, device: str = "cpu") -> float:
    """Member-steps per second of one launch saving only the end."""
    start = time.perf_counter()
    outcome = launch.integrate(resolve("top"), METHODS[method], values, {}, n_save=2, save_dt=t_end, dt=1e-3,
                               rtol=1e-8, atol=1e-10, events=events, device=device)
    return outcome.counts[0].sum() / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--members", type=int, default=1 << 15)
    parser.add_argument("--methods", nargs="+", default=["rk4", "split4", "dopri5"])
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    args = parser.parse_args()
    print(host())
    if args.device == "cuda":
        from ensemble.engine.gpu import require_gpu

        print(f"device: {require_gpu()}")
    values = tops(args.members)
    for method in args.methods:
        for events in WATCHED.values():  # compiled (or loaded) before the clock
            rate(method, {name: v[:128] for name, v in values.items()}, events, 0.01, args.device)
        rates = {label: [] for label in WATCHED}
        for _ in range(args.repeats):
            for label, events in WATCHED.items():
                rates[label].append(rate(method, values, events, device=args.device))
        for label, measured in rates.items():
            ratio = statistics.median(r / base for r, base in zip(measured, rates["none"]))
            print(f"{method:7s} {label:9s} {statistics.median(measured):.3e} member-steps/s   x {ratio:.3f}")


if __name__ == "__main__":
    main()
