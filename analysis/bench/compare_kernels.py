"""The kernels of two revisions of ensemble, alternated in the same minutes: a change's effect on each kernel.

    python analysis/bench/compare_kernels.py OLD [NEW] [--repeats 5] [--members 16384] [--steps 10000] [--only top]

Checks out OLD and NEW (default: the working tree) as compare_revisions.py does, each with a Numba cache of its
own, and times every method's kernel on tops and free bodies (launch.integrate, the kernel alone after one
untimed call that compiles it) in one process per revision and round, the revisions alternated (--only: the
kernels whose name, "top rk4" say, contains the text). Prints each kernel's member-steps per second, median of
the rounds, the rounds' spread, and new / old, between two runs of the C limit (limit.py).
"""
from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmark import c_limit, print_limit
from compare_revisions import checked_out
from hostinfo import host

from ensemble.arguments import OneLineParser, positive_int

TIMER = """
import json, sys, time
import numpy as np
from ensemble.engine import launch
from ensemble.methods import METHODS
from ensemble.scenes import SCENES, methods_for
members, steps = {members}, {steps}
rng = np.random.default_rng(1)
values = {{
    "top": {{"lambda1": np.full(members, 1e-3), "lambda3": rng.uniform(1.2e-3, 1.9e-3, members),
            "c": np.full(members, 1e-4), "spin0": rng.uniform(20, 80, members),
            "tilt0": rng.uniform(0.05, 0.3, members), "azimuth0": np.zeros(members)}},
    "body": {{"lambda1": np.full(members, 1.0), "lambda2": np.full(members, 2.0), "lambda3": np.full(members, 2.5),
             "c": np.full(members, 0.01), "spin0": np.full(members, 10.0), "tilt0": rng.uniform(0.05, 0.3, members),
             "azimuth0": np.zeros(members), "spin_axis": np.full(members, 3.0)}},
}}
rates = {{}}
for name, table in values.items():
    scene = SCENES[name]
    for method in methods_for(scene):
        if method.closed_form or {only!r} not in f"{{name}} {{method.name}}":
            continue
        settings = dict(rtol=1e-8, atol=1e-10) if method.adaptive else dict(dt=1e-3)
        def call():
            return launch.integrate(scene, method, table, {{}}, n_save=2, save_dt=steps * 1e-3, **settings)
        call()
        start = time.perf_counter()
        outcome = call()
        seconds = time.perf_counter() - start
        rates[f"{{name}} {{method.name}}"] = float(outcome.counts[0].sum()) / seconds
print(json.dumps(rates))
"""


def main(argv=None) -> None:
    parser = OneLineParser(description=__doc__.split("\n")[0])
    parser.add_argument("old", help="a git revision")
    parser.add_argument("new", nargs="?", help="a git revision (default: the working tree)")
    parser.add_argument("--repeats", type=positive_int, default=5)
    parser.add_argument("--members", type=positive_int, default=16384)
    parser.add_argument("--steps", type=positive_int, default=10000, help="steps per member per call")
    parser.add_argument("--only", default="", help="time only the kernels whose name contains this")
    args = parser.parse_args(argv)
    print(host(), flush=True)
    code = TIMER.format(members=args.members, steps=args.steps, only=args.only)
    with tempfile.TemporaryDirectory() as tmp, checked_out(parser, args.old, args.new, Path(tmp)) as trees:
        rounds = {name: [] for name in trees}
        print_limit("C limit, before", c_limit())
        for _ in range(args.repeats):
            for name, (tree, env) in trees.items():
                done = subprocess.run([sys.executable, "-c", code], env=env, cwd=tmp, capture_output=True, text=True)
                if done.returncode:
                    raise SystemExit(f"compare_kernels: {name}: {done.stderr.strip().splitlines()[-1]}")
                rounds[name].append(json.loads(done.stdout))
        print_limit("C limit, after", c_limit())
    (old_name, old), (new_name, new) = rounds.items()
    print(f"{'kernel':<18} {old_name:>14} {new_name:>14}  new / old   (member-steps/s, medians of {args.repeats}; "
          f"each revision's slowest and fastest round)")
    for kernel in old[0]:
        a, b = (statistics.median(r[kernel] for r in runs) for runs in (old, new))
        spread = "  ".join(f"{min(r[kernel] for r in runs):.3g} to {max(r[kernel] for r in runs):.3g}"
                           for runs in (old, new))
        print(f"{kernel:<18} {a:>14.3g} {b:>14.3g}  {b / a:.3f}   {spread}")


if __name__ == "__main__":
    main()
