"""Start-up: the whole `ensemble run` process on a tiny run file, beside Numba's own floor, warm cache.

    python analysis/bench/startup.py [--repeats 5]

Times (wall, medians of --repeats) four processes, each once per round:
a Python that loads one trivial cached @njit function (what any Numba program
pays before its first kernel runs), the same with Numba's BLAS probe skipped
as `ensemble run` skips it (ensemble.cli._skip_numba_blas_probe), `ensemble
run` on 10 tops (rk4, 1000 steps), and the same run file parsed only. Prints
the host first; run it twice on a fresh install (the first run compiles).
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from hostinfo import host

from ensemble.arguments import OneLineParser, positive_int

TEN_TOPS = """scene = "top"
method = "rk4"
dt = 1e-3
t_end = 1.0
save_dt = 0.1
members = 10
seed = 1
[parameters]
lambda1 = 1.0e-3
lambda3 = 2.0e-3
c = 1e-4
spin0 = 60.0
tilt0 = { uniform = [0.02, 0.2] }
"""
FLOOR = """from numba import njit
@njit(cache=True)
def f(x):
    return x + 1.0
f(1.0)
"""


def wall(command: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run(command, check=True, capture_output=True)
    return time.perf_counter() - start


def main() -> None:
    parser = OneLineParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=positive_int, default=5)
    args = parser.parse_args()
    print(host())
    if os.environ.get("PYTHONDONTWRITEBYTECODE"):
        print("PYTHONDONTWRITEBYTECODE is set: modules without a .pyc (an editable install's) are compiled from "
              "source in every process")
    with tempfile.TemporaryDirectory() as tmp:
        runfile, floor, skipped = Path(tmp) / "ten.toml", Path(tmp) / "floor.py", Path(tmp) / "skipped.py"
        runfile.write_text(TEN_TOPS)
        floor.write_text(FLOOR)
        skipped.write_text("from ensemble import cli\ncli._skip_numba_blas_probe()\n" + FLOOR)
        commands = {
            "numba floor (one cached @njit function)": [sys.executable, str(floor)],
            "the same, BLAS probe skipped": [sys.executable, str(skipped)],
            "ensemble run, 10 tops": [sys.executable, "-m", "ensemble", "run", str(runfile), "-o",
                                      f"{tmp}/ten.nc", "--force", "--quiet"],
            "parse the run file only": [sys.executable, "-c",
                                        f"from ensemble import spec; spec.load({str(runfile)!r})"],
        }
        for command in commands.values():  # warm the caches
            wall(command)
        times = {name: [] for name in commands}
        for _ in range(args.repeats):
            for name, command in commands.items():
                times[name].append(wall(command))
    for name, values in times.items():
        print(f"{name:<42} median {statistics.median(values):.2f} s  (range {min(values):.2f} .. {max(values):.2f})")


if __name__ == "__main__":
    main()
