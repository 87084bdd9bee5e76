"""Issue 41's whole runs against the kernel alone: does a whole `ensemble run` keep its kernel's speed?

    python analysis/bench/whole_vs_kernel.py [--repeats 2]

Two workloads that take the C of ../shared/limit about 10 s each: 262,144 tops (rk4, dt 1e-3 s, t_end 80 s,
omega and tilt every second) and 65,536 16-mass chains (verlet, dt 0.01 s, t_end 400 s, x every 20 s). Each
runs once untimed (compiling or loading its kernels), then --repeats times as a whole `ensemble run` process
(benchmark.whole_run); then the kernels alone are timed in a fresh process with this machine's tuning
(ensemble.tuner.measure_here: the top's rk4 at the engine's block, the chain's verlet at 16 masses). Prints
the host and limit.py's C before and after, each run's wall seconds and its own rate (its work over its own
seconds: start-up and loading left out), and both as shares of the kernel alone.
"""
from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmark import CHAINS, TOPS, c_limit, print_limit, whole_run
from hostinfo import host

from ensemble import tuning
from ensemble.arguments import OneLineParser, positive_int

WORKLOADS = {
    "262144 tops": (TOPS.format(t_end=80.0, save_dt=1.0, members=262144, save='["omega", "tilt"]'), "top rk4"),
    "65536 16-mass chains": (CHAINS.replace("t_end = 40.0", "t_end = 400.0").replace("save_dt = 2.0",
                                                                                   "save_dt = 20.0"),
                             "chain verlet N=16"),
}
KERNELS = """import json
from ensemble import tuner, tuning
from ensemble.engine.kernels import BLOCK
chosen = tuning.applied()
block = chosen.block or BLOCK
rates = tuner.measure_here(chosen.vector_bits, [block], chain=True)
print(json.dumps({"top rk4": rates[tuner.top_name(block)],
                  "chain verlet N=16": rates["chain verlet N=16"]}))"""


def main() -> None:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=positive_int, default=2)
    args = parser.parse_args()
    print(host())
    print(f"tuning: {tuning.describe()}")
    print_limit("C limit", c_limit())
    runs = {}
    with tempfile.TemporaryDirectory() as folder:
        for name, (text, _) in WORKLOADS.items():
            whole_run(text, Path(folder))  # untimed: compiles or loads the kernels
            runs[name] = [whole_run(text, Path(folder)) for _ in range(args.repeats)]
    done = subprocess.run([sys.executable, "-c", KERNELS], capture_output=True, text=True, check=True)
    alone = json.loads(done.stdout.strip().splitlines()[-1])
    for name, (_, kernel) in WORKLOADS.items():
        for wall, work, rate, _ in runs[name]:
            print(f"{name}: {wall:.2f} s wall, the run's own rate {rate:.3g} ({rate / alone[kernel]:.2f} of the "
                  f"kernel alone, {alone[kernel]:.3g}), by wall {work / wall:.3g} ({work / wall / alone[kernel]:.2f})")
    print_limit("C limit, again", c_limit())


if __name__ == "__main__":
    main()
