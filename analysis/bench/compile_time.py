"""Compile time of kernels, and how soon Ctrl-C stops a run inside a kernel call.

    python analysis/bench/compile_time.py [--scene chain] [--n 4] [--methods rk4 verlet euler] [--repeats 3]
                                    [--interrupts 3] [--every]

Compile time: each method's kernel is prepared (`launch.prepare`) in a fresh
process with an empty NUMBA_CACHE_DIR, so it compiles; the script prints the
median wall time of --repeats. --every instead compiles every kernel of
every scene (each method that applies; chains with --n masses and fixed
ends) into one empty cache, in one process, and prints each and the total
(interpreter start included). Interrupts: `ensemble run` on one top whose
single save interval takes hours gets SIGINT one second after its output
`.part` appears (the kernel is running then); the script prints the median
time until the process exited and its exit statuses. Prints the host first:
compile time scales with the host's speed, which on a shared host varies
during a day.
"""
from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from hostinfo import host
from startup import TEN_TOPS

from ensemble.arguments import OneLineParser, positive_int

PREPARE = """import sys
from ensemble.engine import launch
from ensemble.methods import METHODS
from ensemble.scenes import SCENES
launch.prepare(SCENES[sys.argv[1]], METHODS[sys.argv[2]], {"n": int(sys.argv[3]), "boundary": "fixed"})
"""
EVERY = """import sys, time
start = time.perf_counter()
from ensemble.engine import launch
from ensemble.scenes import SCENES, methods_for
for name, scene in SCENES.items():
    for method in methods_for(scene):
        if method.closed_form:
            continue
        began = time.perf_counter()
        launch.prepare(scene, method, {"n": int(sys.argv[1]), "boundary": "fixed"})
        print(f"{name} {method.name}: {time.perf_counter() - began:.1f} s", flush=True)
print(f"every kernel: {time.perf_counter() - start:.1f} s since the interpreter started", flush=True)
"""
# One top whose single save interval is 5e9 steps (hours): the start-up benchmark's tops, changed.
LONG_TOP = TEN_TOPS.replace("dt = 1e-3\nt_end = 1.0\nsave_dt = 0.1\nmembers = 10",
                            "dt = 1e-7\nt_end = 1000.0\nsave_dt = 500.0\nmembers = 1")


def compile_seconds(scene: str, method: str, n: int) -> float:
    """Wall seconds of a process that prepares one kernel with an empty cache (interpreter start included)."""
    with tempfile.TemporaryDirectory() as cache:
        start = time.perf_counter()
        subprocess.run([sys.executable, "-c", PREPARE, scene, method, str(n)], check=True,
                       env={**os.environ, "NUMBA_CACHE_DIR": cache})
        return time.perf_counter() - start


def interrupt_seconds(folder: Path) -> tuple[float, int]:
    """Seconds from SIGINT to exit of a run inside a kernel call of hours, and its exit status."""
    runfile, out = folder / "long.toml", folder / "long.nc"
    runfile.write_text(LONG_TOP)
    for stale in folder.glob("long.nc*"):
        stale.unlink()
    run = subprocess.Popen([sys.executable, "-m", "ensemble", "run", str(runfile), "-o", str(out), "--quiet"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    while not (folder / "long.nc.part").exists() and run.poll() is None:
        time.sleep(0.05)
    time.sleep(1.0)
    sent = time.perf_counter()
    run.send_signal(signal.SIGINT)
    try:
        run.wait(timeout=120)
    finally:
        run.kill()
    return time.perf_counter() - sent, run.returncode


def main() -> None:
    parser = OneLineParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="chain")
    parser.add_argument("--n", type=positive_int, default=4, help="chain length (chain scene only)")
    parser.add_argument("--methods", nargs="+", default=["rk4", "verlet", "euler"])
    parser.add_argument("--repeats", type=positive_int, default=3)
    parser.add_argument("--interrupts", type=int, default=3, help="0: skip the Ctrl-C measurement")
    parser.add_argument("--every", action="store_true", help="compile every kernel of every scene, in one process")
    args = parser.parse_args()
    print(host(), flush=True)
    if args.every:
        with tempfile.TemporaryDirectory() as cache:
            start = time.perf_counter()
            subprocess.run([sys.executable, "-c", EVERY, str(args.n)], check=True,
                           env={**os.environ, "NUMBA_CACHE_DIR": cache})
        print(f"process wall time {time.perf_counter() - start:.1f} s")
        return
    for method in args.methods:
        seconds = [compile_seconds(args.scene, method, args.n) for _ in range(args.repeats)]
        print(f"{args.scene} {method} n={args.n}: compiled in {statistics.median(seconds):.1f} s "
              f"(median of {args.repeats}, range {min(seconds):.1f} .. {max(seconds):.1f})", flush=True)
    if args.interrupts > 0:
        with tempfile.TemporaryDirectory() as folder:
            results = [interrupt_seconds(Path(folder)) for _ in range(args.interrupts)]
        print(f"Ctrl-C inside a kernel call: exit after a median {statistics.median(s for s, _ in results):.2f} s "
              f"(range {min(s for s, _ in results):.2f} .. {max(s for s, _ in results):.2f}), exit statuses "
              f"{sorted({code for _, code in results})}")


if __name__ == "__main__":
    main()
