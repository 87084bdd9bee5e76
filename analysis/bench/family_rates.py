"""Member-steps/s of the member families' CPU kernels (explicit Runge-Kutta, adaptive pairs, splittings) on the
top and the free body: a before-and-after check for a change to the engine's family code.

    python analysis/bench/family_rates.py [--repeats 7] [--members 32768] [--steps 400] [--lorenz96 40]
                                          [--cases top:split2 top:rk4]

Each rate is the median of --repeats kernel runs (launch.Launch.run, all threads), the cases run in turn so that a
slow spell of the machine hits them all. To compare two versions, run it with each on PYTHONPATH, in alternation,
beside `python ../shared/limit/limit.py`. The first line names the host. The adaptive pair runs at rtol = atol =
1e-9, its rate counted in its accepted steps. --lorenz96 N adds a user's scene of N state variables (Lorenz-96,
x_i' = (x_{i+1} - x_{i-2}) x_{i-1} - x_i + F, written out as one rhs of N + 2 arguments) with rk4 and dopri5.
"""
from __future__ import annotations

import argparse
import json
import runpy
import tempfile
from pathlib import Path

import numpy as np
from hostinfo import host

from ensemble.engine import launch
from ensemble.members import members_table
from ensemble.methods import METHODS
from ensemble.scenes import SCENES, resolve
from ensemble.spec import load
from ensemble.tuner import _seconds_in_turn

CASES = [("top", "rk4"), ("top", "dopri5"), ("top", "split2"), ("top", "split4"), ("body", "rk4"), ("body", "dopri5"),
         ("body", "rotations2"), ("body", "rotations4")]
RUNS = {"top": "runs/aerobie.toml", "body": "runs/tennis_racket.toml"}
ROOT = Path(__file__).resolve().parents[2]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--members", type=int, default=32768)
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--lorenz96", type=int, default=0, help="add Lorenz-96 over this many sites")
    parser.add_argument("--cases", nargs="+", metavar="SCENE:METHOD", choices=[f"{s}:{m}" for s, m in CASES],
                        help="only these cases (default: all)")
    args = parser.parse_args()
    print(host(), flush=True)
    calls, work = {}, {}
    if args.lorenz96:
        scene = lorenz96(args.lorenz96, Path(tempfile.mkdtemp()))
        rng = np.random.default_rng(0)
        values = {"F": np.full(args.members, 8.0), **{f"x{i}_0": rng.normal(0, 1, args.members)
                                                      for i in range(args.lorenz96)}}
        for name in ("rk4", "dopri5"):
            method = METHODS[name]
            calls[f"lorenz96 {name}"] = launch.Launch(
                scene, method, values, {}, n_save=2, save_dt=args.steps * 1e-3, dt=None if method.adaptive else 1e-3,
                rtol=1e-6, atol=1e-6)
            work[f"lorenz96 {name}"] = args.members * args.steps
    chosen = [tuple(case.split(":")) for case in args.cases] if args.cases else CASES
    for scene_name, method_name in chosen:
        table = members_table(load(RUNS[scene_name]))
        values = {name: np.resize(table[name], args.members) for name in SCENES[scene_name].PARAMETERS
                  if name in table}
        scene, method = SCENES[scene_name], METHODS[method_name]
        dt = 1e-3
        calls[f"{scene_name} {method_name}"] = launch.Launch(
            scene, method, values, {}, n_save=2, save_dt=args.steps * dt, dt=None if method.adaptive else dt,
            rtol=1e-9, atol=1e-9)
        work[f"{scene_name} {method_name}"] = args.members * args.steps
    seconds = _seconds_in_turn(list(calls.values()), args.repeats)
    rates = {name: work[name] / s for name, s in zip(calls, seconds)}
    for name, call in calls.items():
        if call.method.adaptive:  # its own steps: accepted ones per member
            rates[name] = float(call.outcome().counts[0].sum()) / seconds[list(calls).index(name)]
    print(json.dumps({name: float(f"{rate:.3g}") for name, rate in rates.items()}))


def lorenz96(n: int, folder: Path):
    """examples/lorenz96.py's scene of n sites, written into `folder`, resolved."""
    (folder / "lorenz96.py").write_text(runpy.run_path(str(ROOT / "examples" / "lorenz96.py"))["scene_text"](n))
    return resolve(str(folder / "lorenz96.py"))


if __name__ == "__main__":
    main()
