"""One long member, interrupted midway, resumes from its last finished segment (issue 40, item 8).

    python analysis/bench/long_member.py [--t-end 40000] [--at 0.5] [--signal INT|KILL]

Runs one top (rk4, dt = 1e-4 s, tilt saved every 0.01 s, t_end seconds) once
uninterrupted, then again, sending the signal at the fraction --at of the
uninterrupted run's time, and finishes it with --resume. Prints the host, the
three wall times, the interrupted run's last line, the resume's first, and
whether the resumed result has the uninterrupted bits. Before segments were
kept, the resume started from sample 0 and took the whole run's time again.
"""
from __future__ import annotations

import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from hostinfo import host
from kill_resume import same_data

from ensemble.arguments import OneLineParser, positive_float

RUN_FILE = """scene = "top"
method = "rk4"
dt = 1e-4
t_end = {t_end}
save_dt = 0.01
members = 1
seed = 1
[parameters]
lambda1 = 1.0e-3
lambda3 = 2.0e-3
c = 1e-5
spin0 = 60.0
tilt0 = 0.1
azimuth0 = 0.0
"""


def timed(command: list[str], stop_after: float | None = None, sign=signal.SIGINT) -> tuple[float, str]:
    """(wall seconds, stderr) of `command`, sent `sign` after stop_after seconds if given."""
    start = time.perf_counter()
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    if stop_after is not None:
        time.sleep(stop_after)
        process.send_signal(sign)
    _, err = process.communicate()
    return time.perf_counter() - start, err


def main(argv=None) -> None:
    parser = OneLineParser(description=__doc__.split("\n")[0])
    parser.add_argument("--t-end", type=positive_float, default=40000.0, help="seconds of the member's motion")
    parser.add_argument("--at", type=positive_float, default=0.5, help="when to interrupt, a fraction of the run")
    parser.add_argument("--signal", choices=["INT", "KILL"], default="INT")
    args = parser.parse_args(argv)
    print(host())
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        runfile = folder / "long.toml"
        runfile.write_text(RUN_FILE.format(t_end=args.t_end))
        base = [sys.executable, "-m", "ensemble", "run", str(runfile)]
        whole, _ = timed([*base, "-o", str(folder / "whole.nc"), "--quiet"])
        out = folder / "long.nc"
        stopped, said = timed([*base, "-o", str(out)], whole * args.at, getattr(signal, f"SIG{args.signal}"))
        resumed, began = timed([*base, "-o", str(out), "--resume"])
        print(f"uninterrupted: {whole:.1f} s; interrupted at {whole * args.at:.1f} s (SIG{args.signal}), after "
              f"{stopped:.1f} s; resumed in {resumed:.1f} s")
        print(f"it said: {said.strip().splitlines()[-1] if said.strip() else '(nothing)'}")
        print(f"the resume said: {began.strip().splitlines()[0]}")
        print(f"the resumed result has the uninterrupted bits: {same_data(out, folder / 'whole.nc')}")


if __name__ == "__main__":
    main()
