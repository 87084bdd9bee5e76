"""Where a whole run's seconds go: one `ensemble run` in this process, its steps timed as they happen.

    python analysis/bench/run_phases.py (RUNFILE | --workload tops|chains) [--members N] [--save-dt S] [--growth]

Runs RUNFILE, or one of the two whole-run workloads of benchmark.py --whole,
(into a temporary folder) with the run's own steps wrapped in
timers and prints each step's total seconds and calls, on whichever thread
it ran:

    kernel          the kernel calls (main thread; both cores when alone)
    finishing       a chunk finished on the finishing thread: what follows
      observing       the saved variables from the samples (tilt: compiled)
      amplitudes      what the growth fit reads (compiled; `[measure] growth` only)
      growth fit      growth_per_step (compiled; `[measure] growth` only)
      writing         saved variables into OUT.nc.tmp (HDF5, the system's copy)
    fsync           OUT.nc.tmp to the disk after each chunk (the parts' thread)

The run's seconds (loading its kernels from the cache included) and this
script's imports come first, then the stretches before the first kernel call
(loading the kernels, creating the file) and after the last one (the last
chunk's finishing, the records, closing the file), which nothing overlaps.
The C limit (limit.py) is measured just before and just after the run. The
steps overlap: finishing and fsync run while the next chunk's kernel does, on
the same two cores. --members and --save-dt replace the run file's values;
--growth adds `[measure] growth = true`.
"""
from __future__ import annotations

import collections
import dataclasses
import functools
import re
import tempfile
import threading
import time
from pathlib import Path

began = time.perf_counter()

from benchmark import WORKLOADS, c_limit, print_limit  # noqa: E402
from hostinfo import host  # noqa: E402

from ensemble import cli, parts, records, runner, store  # noqa: E402
from ensemble.arguments import OneLineParser, positive_int  # noqa: E402
from ensemble.engine import launch  # noqa: E402
from ensemble.spec import SpecError, load, parse  # noqa: E402

totals: dict[str, float] = collections.defaultdict(float)
calls: collections.Counter = collections.Counter()
moments: dict[str, float] = {}  # perf_counter() when the first kernel call began and the last one ended
_lock = threading.Lock()


def timed(owner, name: str, label: str) -> None:
    """Replace owner.name by a wrapper that adds its seconds to totals[label]."""
    function = getattr(owner, name)

    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            with _lock:
                totals[label] += time.perf_counter() - start
                calls[label] += 1

    setattr(owner, name, wrapper)


def time_kernel_calls() -> None:
    """Launch.segments yields after each kernel call: the time between yields is the kernel's."""
    segments = launch.Launch.segments

    def wrapper(self, *args, **kwargs):
        start = time.perf_counter()
        moments.setdefault("first kernel", start)
        for item in segments(self, *args, **kwargs):
            moments["last kernel"] = time.perf_counter()
            totals["kernel"] += moments["last kernel"] - start
            calls["kernel"] += 1
            yield item
            start = time.perf_counter()

    launch.Launch.segments = wrapper


def main(argv=None) -> None:
    imports = time.perf_counter() - began
    parser = OneLineParser(description=__doc__.split("\n")[0])
    parser.add_argument("runfile", type=Path, nargs="?")
    parser.add_argument("--workload", choices=WORKLOADS, help="a whole-run workload of benchmark.py instead")
    parser.add_argument("--members", type=positive_int, help="replace the run file's member count")
    parser.add_argument("--save-dt", type=float, help="replace the run file's save_dt (s): what saving costs, "
                                                     "against the same run saving less")
    parser.add_argument("--growth", action="store_true", help="measure growth_per_step ([measure] growth = true)")
    parser.add_argument("--no-limit", action="store_true", help="leave out the C limit before and after (its "
                                                                "timing takes most of this script's half minute)")
    args = parser.parse_args(argv)
    if (args.runfile is None) == (args.workload is None):
        parser.error("give a run file or --workload")
    try:
        spec = parse(WORKLOADS[args.workload], args.workload) if args.workload else load(args.runfile)
        for key, value in (("members", args.members), ("save_dt", args.save_dt)):
            if value is not None:
                spec = parse(re.sub(rf"(?m)^{key}\s*=.*$", f"{key} = {value!r}", spec.text))
        if args.growth:  # whatever the run file's [measure] table looks like (its text is not edited)
            spec = dataclasses.replace(spec, measure={**spec.measure, "growth": True})
    except SpecError as e:
        parser.error(f"{args.runfile or args.workload}: {e}")
    cli._skip_numba_blas_probe()  # as `ensemble run` does, so loading the kernels takes what it takes there
    timed(spec.model, "observe", "  observing")
    timed(spec.model, "amplitudes", "  amplitudes")
    time_kernel_calls()
    timed(runner, "_keep", "finishing")
    timed(records, "growth_per_step", "  growth fit")
    timed(store, "put_samples", "  writing")
    timed(parts, "fsync_path", "fsync")
    print(host(), flush=True)
    if not args.no_limit:
        print_limit("C limit, before", c_limit())
    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        summary = runner.run(spec, Path(folder) / "out.nc", progress=False)
        seconds = time.perf_counter() - start
    if not args.no_limit:
        print_limit("C limit, after", c_limit())
    print(f"{spec.n_members} members, {summary.member_steps:.3g} member-steps, {spec.n_save} samples: start-up "
          f"{imports:.2f} s (this script's imports), the run {seconds:.2f} s (of which {summary.preparing:.2f} s "
          "loading kernels)")
    print(f"  before the first kernel call {moments['first kernel'] - start:.3f} s, after the last "
          f"{start + seconds - moments['last kernel']:.3f} s (loading kernels included before; nothing else overlaps)")
    growth = ("  amplitudes", "  growth fit") if spec.measure["growth"] else ()
    for label in ("kernel", "finishing", "  observing", *growth, "  writing", "fsync"):
        print(f"  {label:14s} {totals[label]:7.3f} s in {calls[label]} calls")


if __name__ == "__main__":
    main()
