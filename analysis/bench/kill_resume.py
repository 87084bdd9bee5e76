"""Resume under SIGKILL at random moments: every resumed run ends with the bits of an uninterrupted one.

    python analysis/bench/kill_resume.py [--trials 10] [--members 120000] [--seed 1]

Runs the tops of a run file once uninterrupted, then per trial starts the
same run and SIGKILLs it after a random 0.6 to 2.2 s (during start-up, a
kernel, a write, a flush, the final rename), again and again with --resume
until a run finishes, and compares every variable with the uninterrupted
result. A kill after the result's rename but before the parts are deleted
leaves a complete result (a resume then refuses to replace it); that counts
as finished. Prints the kills and the trials that gave other bits (none
expected). tests/test_resume.py does the same at two fixed moments.
"""
from __future__ import annotations

import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import xarray as xr
from benchmark import TOPS
from hostinfo import host

from ensemble.arguments import OneLineParser, positive_int


def same_data(a: Path, b: Path) -> bool:
    """Every variable of two results bitwise equal."""
    with xr.open_dataset(a) as x, xr.open_dataset(b) as y:
        return set(x.variables) == set(y.variables) and all(
            np.asarray(x[n].values).tobytes() == np.asarray(y[n].values).tobytes() for n in x.variables)


def killed_until_done(command: list[str], rng: random.Random) -> int:
    """Run `command`, SIGKILLing it after rng's random delays and resuming, until a run ends; returns the kills."""
    kills, extra = 0, []
    while True:
        process = subprocess.Popen([*command, *extra], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        time.sleep(rng.uniform(0.6, 2.2))
        if process.poll() is None:
            process.send_signal(signal.SIGKILL)
            process.wait()
            kills, extra = kills + 1, ["--resume"]
            continue
        error = process.stderr.read()
        if process.returncode == 0 or "exists; use --force" in error:
            return kills
        raise SystemExit(f"kill_resume: a resumed run failed: {error.strip().splitlines()[-1:]}")


def main(argv=None) -> None:
    parser = OneLineParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=positive_int, default=10)
    parser.add_argument("--members", type=positive_int, default=120_000)
    parser.add_argument("--seed", type=int, default=1, help="seeds the kill times")
    args = parser.parse_args(argv)
    print(host(), flush=True)
    rng = random.Random(args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        runfile = folder / "tops.toml"
        runfile.write_text(TOPS.format(t_end=4.0, save_dt=0.1, members=args.members, save='["omega", "tilt"]'))
        command = [sys.executable, "-m", "ensemble", "run", str(runfile), "--quiet", "--chunk", "4096"]
        expected = folder / "expected.nc"
        subprocess.run([*command, "-o", str(expected)], check=True, stdout=subprocess.DEVNULL)
        kills, differ = 0, []
        for trial in range(args.trials):
            out = folder / f"trial{trial}.nc"
            kills += killed_until_done([*command, "-o", str(out)], rng)
            if not same_data(out, expected):
                differ.append(trial)
            out.unlink()
            print(f"trial {trial + 1}/{args.trials}: {kills} kills so far", flush=True)
    print(f"{args.trials} trials, {kills} SIGKILLs, {len(differ)} with other bits{': ' if differ else ''}"
          f"{', '.join(map(str, differ))}")
    if differ:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
