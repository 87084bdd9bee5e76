"""Benchmark: how a Dask run into a Zarr store starts, and what its client holds, as the members grow.

    python analysis/bench/many_members.py [--members 100000 10000000 400000000] [--watch 15] [--workers 2]

Starts a Dask scheduler and N single-threaded workers as processes of their own (client_bytes.cluster), then,
for each member count, `ensemble run --scheduler` of tops (rk4, 100 steps, saving tilt at t = 0 and 0.1 s)
into OUT.zarr, as a process of its own. Of that client process it notes when the store's template is made and
when the first range's receipt arrives (the run is under way), its resident memory's peak (VmHWM) at that
moment and after `--watch` seconds of running, and how many members were in by then; then stops it with
SIGINT (a Ctrl-C: it keeps what it finished) and deletes the store. The default's largest count is the
largest whose result a disk of 73 GB free holds (a run refuses one that does not fit); `--no-space-check` lets
the client start a larger one anyway (it is stopped long before the disk fills).
"""
from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmark import TOPS
from client_bytes import cluster
from hostinfo import host


def peak_rss(pid: int) -> float:
    """The process's resident memory's peak so far (VmHWM), MB."""
    with open(f"/proc/{pid}/status") as file:
        return next(int(line.split()[1]) / 1e3 for line in file if line.startswith("VmHWM"))


UNCHECKED = ("import sys\nimport ensemble.preflight\nensemble.preflight.space_problem = lambda *a, **k: None\n"
             "from ensemble.cli import entry\nsys.argv[0] = 'ensemble'\nentry()\n")


def watched(runfile: Path, out: Path, scheduler: str, watch: float, space_check: bool) -> dict[str, float]:
    """Start `ensemble run` into `out`; the seconds until its template and its first receipt, its peak memory
    then and `watch` seconds later (or when it finished, if sooner), and the members in by then; stopped with
    SIGINT if still running."""
    parts = out.with_name(out.name + ".parts")
    began = time.perf_counter()
    command = ["-m", "ensemble"] if space_check else ["-c", UNCHECKED]
    process = subprocess.Popen([sys.executable, *command, "run", str(runfile), "-o", str(out), "--quiet",
                                "--scheduler", scheduler], stdout=subprocess.DEVNULL)
    found: dict[str, float] = {"members_in": 0}
    while process.poll() is None:
        now = time.perf_counter() - began
        try:
            found["peak_after"] = peak_rss(process.pid)
        except (OSError, StopIteration):  # it exited just now
            break
        if "template" not in found and (out.with_name(out.name + ".tmp") / "zarr.json").exists():
            found["template"] = now
        receipts = list(parts.glob("receipt-*.json"))
        if receipts and "first_receipt" not in found:
            found["first_receipt"], found["peak_at_first"] = now, found["peak_after"]
        found["members_in"] = max(found["members_in"], sum(int(p.stem.split("-")[2]) - int(p.stem.split("-")[1])
                                                           for p in receipts))
        if "first_receipt" in found and now > found["first_receipt"] + watch:
            process.send_signal(signal.SIGINT)
            break
        time.sleep(0.01)
    found["exit"], found["wall"] = process.wait(), time.perf_counter() - began
    for path in (out, out.with_name(out.name + ".tmp"), parts):
        shutil.rmtree(path, ignore_errors=True)
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--members", type=int, nargs="+", default=[10**5, 10**7, 4 * 10**8])
    parser.add_argument("--watch", type=float, default=15.0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--no-space-check", dest="space_check", action="store_false")
    args = parser.parse_args()
    print(host())
    with tempfile.TemporaryDirectory(dir=os.environ.get("BENCH_DIR")) as name:
        folder = Path(name)
        address, started = cluster(folder, args.workers)
        try:
            for members in args.members:
                runfile = folder / "many.toml"
                runfile.write_text(TOPS.format(t_end=0.1, save_dt=0.1, members=members, save='["tilt"]'))
                f = watched(runfile, folder / "many.zarr", address, args.watch, args.space_check)
                ended = "on SIGINT" if f["exit"] else f"done at {f['wall']:.1f} s"
                print(f"{members:.0e} members: template at {f['template']:.2f} s, first receipt at "
                      f"{f['first_receipt']:.2f} s; client peak RSS {f['peak_at_first']:.0f} MB then, "
                      f"{f['peak_after']:.0f} MB at the end ({f['members_in']:.3g} members in); exit {f['exit']} "
                      f"{ended}", flush=True)
        finally:
            for process in started[::-1]:
                process.terminate()
                process.wait()


if __name__ == "__main__":
    main()
