"""Benchmark: what the client of a Dask run reads, writing NetCDF (the client writes) or Zarr (the workers do).

    python analysis/bench/client_bytes.py [--members 10000] [--workers 2] [--repeats 3]

Starts a Dask scheduler and N single-threaded workers as processes of their own (`dask scheduler`, `dask
worker`), then runs `ensemble run --scheduler` on a top sweep saving tilt and omega every 2 ms for 3 s (10^4
members: 480 MB of samples) into OUT.nc and into OUT.zarr, alternated. Of the `ensemble` process it reads
/proc/PID/io until it exits (rchar: bytes its read calls returned; a socket read through recv is not counted
there) and counts the bytes it received on its sockets (Tornado's IOStream.read_from_fd, patched in that process
alone). A LocalCluster is not used: the I/O of the worker processes it reaps is added to its own. Prints each
output's medians over the repeats and the Zarr/NetCDF ratios.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmark import TOPS
from hostinfo import host

COUNTED = """import atexit, os, sys
import tornado.iostream
received = [0]
read = tornado.iostream.IOStream.read_from_fd
def counted(self, buffer):
    got = read(self, buffer)
    received[0] += got or 0
    return got
tornado.iostream.IOStream.read_from_fd = counted
atexit.register(lambda: open(os.environ["RECEIVED_FILE"], "w").write(str(received[0])))
from ensemble.cli import entry
sys.argv[0] = "ensemble"
entry()
"""


def sweep(folder: Path, members: int) -> Path:
    """The run file of the measured sweep in `folder`: tops saving tilt and omega every 2 ms for 3 s."""
    runfile = folder / "sweep.toml"
    runfile.write_text(TOPS.format(t_end=3.0, save_dt=2e-3, members=members, save='["tilt", "omega"]'))
    return runfile


def io_of(pid: int) -> dict[str, int]:
    with open(f"/proc/{pid}/io") as file:
        return {key: int(value) for key, value in (line.split(": ") for line in file)}


def measured(runfile: Path, out: Path, scheduler: str, folder: Path) -> dict[str, float]:
    """rchar and wchar of the `ensemble run` process (its last reading before it exits), the bytes it received on
    its sockets, and its wall."""
    received = folder / "received"
    began = time.perf_counter()
    process = subprocess.Popen([sys.executable, "-c", COUNTED, "run", str(runfile), "-o", str(out), "--quiet",
                                "--force", "--scheduler", scheduler], stdout=subprocess.DEVNULL,
                               env={**os.environ, "RECEIVED_FILE": str(received)})
    last = {"rchar": 0, "wchar": 0}
    while process.poll() is None:
        try:
            last = io_of(process.pid)
        except OSError:  # it exited between poll and open
            break
        time.sleep(0.005)
    wall = time.perf_counter() - began
    if process.wait():
        raise SystemExit(f"ensemble run {out} failed")
    return {"rchar": last["rchar"], "wchar": last["wchar"], "received": int(received.read_text()), "wall": wall}


def cluster(folder: Path, workers: int) -> tuple[str, list[subprocess.Popen]]:
    """A scheduler and `workers` single-threaded workers, each a process of its own; (address, processes)."""
    file = folder / "scheduler.json"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    started = [subprocess.Popen(["dask", "scheduler", "--port", "0", "--dashboard-address", ":0",
                                 "--scheduler-file", str(file)], **quiet)]
    while not file.exists():
        time.sleep(0.1)
    threads = str(max(1, (os.cpu_count() or 1) // workers))
    started += [subprocess.Popen(["dask", "worker", "--scheduler-file", str(file), "--nthreads", "1",
                                  "--dashboard-address", ":0"], env={**os.environ, "NUMBA_NUM_THREADS": threads},
                                 **quiet) for _ in range(workers)]
    address = json.loads(file.read_text())["address"]
    from distributed import Client

    with Client(address) as client:
        client.wait_for_workers(workers)
    return address, started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--members", type=int, default=10000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(host())
    with tempfile.TemporaryDirectory() as name:
        folder = Path(name)
        runfile = sweep(folder, args.members)
        address, started = cluster(folder, args.workers)
        try:
            found = {"nc": [], "zarr": []}
            for _ in range(args.repeats):
                for kind in found:
                    found[kind].append(measured(runfile, folder / f"out.{kind}", address, folder))
        finally:
            for process in started[::-1]:
                process.terminate()
                process.wait()
        saved = sum(f.stat().st_size for f in (folder / "out.zarr").rglob("*") if f.is_file())
    print(f"{args.members} members, {args.workers} worker processes; the store holds {saved / 1e6:.0f} MB")
    medians = {kind: {key: statistics.median(r[key] for r in runs) for key in runs[0]} for kind, runs in found.items()}
    for kind, m in medians.items():
        walls = ", ".join(f"{r['wall']:.2f}" for r in found[kind])
        print(f"{kind:5s} client: received {m['received'] / 1e6:8.1f} MB on sockets, rchar {m['rchar'] / 1e6:7.1f} "
              f"MB, wchar {m['wchar'] / 1e6:7.1f} MB, wall {m['wall']:.2f} s (of {walls})")
    print(f"zarr/nc: received x{medians['zarr']['received'] / medians['nc']['received']:.3g}, "
          f"wall x{medians['zarr']['wall'] / medians['nc']['wall']:.3g}")


if __name__ == "__main__":
    main()
