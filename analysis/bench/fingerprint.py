"""Fingerprints of results: a SHA-256 of every data variable of every run file's result and of its fits.

    python analysis/bench/fingerprint.py [RUNFILE ...] [--chunk 256] [-o fingerprints.json]
    python analysis/bench/fingerprint.py [RUNFILE ...] --compare fingerprints.json

Runs each run file (default: every file in runs/) through `ensemble run` in a
subprocess, then fits the result as the analysis scripts do (tilt decay,
normal-mode frequencies, work against precision, stability map) and hashes
the bytes, dtype and shape of every variable. A change that must keep results
bit for bit (a refactoring, a new layout with the same arithmetic) records the
fingerprints before and compares after: --compare prints each difference and
exits 1 when there is one. Timings (seconds_per_step and what derives from
it) are left out: they differ on every run.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import xarray as xr

ROOT = Path(__file__).resolve().parents[2]
TIMINGS = {"seconds_per_step", "seconds"}


def digest(array: np.ndarray) -> str:
    array = np.ascontiguousarray(array)
    h = hashlib.sha256(f"{array.dtype.str}{array.shape}".encode())
    h.update(array.tobytes())
    return h.hexdigest()


def fingerprints(ds: xr.Dataset) -> dict[str, str]:
    return {name: digest(var.values) for name, var in sorted(ds.variables.items()) if name not in TIMINGS}


def fits_of(ds: xr.Dataset) -> dict[str, xr.Dataset]:
    """The fits the analysis scripts write for this result."""
    from ensemble import fitting, stability
    from ensemble.scenes.chain import fits as chain_fit
    from ensemble.scenes.top import fits as top_fit

    out = {}
    if ds.attrs.get("scene") == "top" and "tilt" in ds and ds.sizes["t"] >= fitting.MIN_SAMPLES:
        out["tilt_decay"] = top_fit.tilt_decay(ds)
    if ds.attrs.get("scene") == "chain" and "x" in ds and ds.sizes["t"] >= fitting.MIN_SAMPLES:
        out["normal_modes"] = chain_fit.mode_frequencies(ds)
    if "error_max" in ds:
        out["work_precision"] = fitting.work_precision(ds)
    if "growth_per_step" in ds and ds.attrs.get("members_per_sweep_point") == 1:
        out["stability"] = stability.stability_map(ds)
    return out


def record(runfile: Path, chunk: int, folder: Path) -> dict[str, str]:
    out = folder / f"{runfile.stem}.nc"
    done = subprocess.run([sys.executable, "-m", "ensemble", "run", str(runfile), "-o", str(out), "--force",
                           "--quiet", "--chunk", str(chunk)], capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"fingerprint: {runfile}: ensemble run failed: {done.stderr.strip()}")
    ds = xr.load_dataset(out)
    found = {f"{runfile.stem}:{name}": value for name, value in fingerprints(ds).items()}
    for fit_name, fits in fits_of(ds).items():
        found.update({f"{runfile.stem}/{fit_name}:{name}": value for name, value in fingerprints(fits).items()})
    return found


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runfiles", nargs="*", type=Path, help="run files (default: runs/*.toml)")
    parser.add_argument("--chunk", type=int, default=256, help="members per chunk (default 256)")
    parser.add_argument("-o", "--output", type=Path, help="write the fingerprints here (JSON)")
    parser.add_argument("--compare", type=Path, help="compare with fingerprints written before")
    args = parser.parse_args(argv)
    runfiles = args.runfiles or sorted((ROOT / "runs").glob("*.toml"))
    found = {}
    with tempfile.TemporaryDirectory() as tmp:
        for runfile in runfiles:
            found.update(record(runfile, args.chunk, Path(tmp)))
            print(f"{runfile.name}: done", file=sys.stderr)
    if args.output:
        args.output.write_text(json.dumps(found, indent=1, sort_keys=True) + "\n")
        print(f"{len(found)} fingerprints written to {args.output}")
    if not args.compare:
        return 0
    before = json.loads(args.compare.read_text())
    stems = {key.split(":")[0].split("/")[0] for key in found}
    before = {key: value for key, value in before.items() if key.split(":")[0].split("/")[0] in stems}
    differ = sorted(key for key in set(before) | set(found) if before.get(key) != found.get(key))
    for key in differ:
        print(f"differs: {key} ({'missing now' if key not in found else 'new' if key not in before else 'changed'})")
    print(f"{len(found) - len([k for k in differ if k in found])} of {len(found)} fingerprints equal; "
          f"{len(differ)} differ")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
