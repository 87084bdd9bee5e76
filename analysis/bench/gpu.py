"""The GPU's figures (issue 42, docs/gpu.md): the CUDA kernels' rates, the crossover with the CPU kernels, a whole
run against its kernel, and float32's error beside float64's. Every figure names the GPU and the host; rates are
medians of --repeats timed launches after a first (compiling) one, each launch's inputs already on the GPU and its
end state copied back (n_save = 2).

    python analysis/bench/gpu.py --json gpu.json            # on a machine with an NVIDIA GPU and numba-cuda
    python analysis/bench/gpu.py --quick                    # a smaller set (a few minutes of GPU time)

Top: the aerobie's tops (runs/aerobie.toml). Chain: disordered chains of N masses between walls. Lorenz: the GPU
papers' yardstick (runs/lorenz.toml, examples/lorenz.py), 2^23 systems of 1000 rk4 steps, on the GPU or, with
--device cpu, on this host's threads:

    python analysis/bench/gpu.py --only lorenz                          # the GPU's figures
    python analysis/bench/gpu.py --only lorenz --device cpu --lorenz-members 262144   # the CPU's, beside them
"""
from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from hostinfo import host  # noqa: E402

from ensemble.engine import (
    gpu_sites,  # noqa: E402
    launch,  # noqa: E402
)
from ensemble.engine.gpu import require_gpu  # noqa: E402
from ensemble.engine.gpu_device import simulated  # noqa: E402
from ensemble.methods import METHODS  # noqa: E402
from ensemble.runner import members_table  # noqa: E402
from ensemble.scenes import resolve  # noqa: E402
from ensemble.spec import load  # noqa: E402
from ensemble.spec import members_table as drawn  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
TOP_DT = 2.5e-4  # s, runs/aerobie.toml's
CHAIN_DT = 0.05  # s: h omega_max about 0.1 for the disordered chains below
TARGET_SECONDS = 0.4  # a timed launch's length, once calibrated
STEPS = (1e-2, 4e-3, 2e-3, 1e-3, 5e-4, 2.5e-4, 1e-4)  # s: float32's error against float64's, over 1 s
CROSSOVER = (10**2, 10**3, 10**4, 10**5, 10**6)
SIZES = {  # members per workload, each run where the GPU's memory allows (fits); --quick and --smoke (a check of
    # this script under the simulator) use fewer
    "full": dict(top=(10**4, 10**5, 10**6, 10**7, 10**8),
                 chain=((16, (10**4, 10**5, 10**6, 10**7)), (64, (10**4, 10**5)), (128, (10**4, 10**5, 10**6)),
                        (1024, (10**3, 10**4, 10**5))),
                 crossover=CROSSOVER, float32=10**4, dts=STEPS),
    "quick": dict(top=(10**4, 10**6, 10**8), chain=((16, (10**6,)), (32, (10**4, 10**5)), (64, (10**4, 10**5)),
                                                    (128, (10**4, 10**5)), (1024, (10**3, 10**4))),
                  crossover=CROSSOVER, float32=10**4, dts=STEPS),
    "smoke": dict(top=(2,), chain=((3, (2,)), (64, (2,))), crossover=(1,), float32=1, dts=(1e-2,)),
}
BOTH_LAYOUTS = 32  # masses from which chains are timed in both layouts
WHOLE_STEPS = 2_000_000  # steps per top in the whole run: about 70 s of integration for 10^7 tops on an H100


def fits(members: int, rows: int) -> bool:
    """Whether `members` with `rows` float64 values each (inputs, works, two segments of samples, and the host's
    copies) fit in the GPU's free memory, with a quarter to spare."""
    from numba import cuda

    if simulated():
        return True
    free, _ = cuda.current_context().get_memory_info()
    return members * rows * 8 <= 0.75 * free


def synchronize(device: str = "cuda"):
    if device == "cuda":
        from numba import cuda
        cuda.synchronize()


def top_values(members: int) -> dict[str, np.ndarray]:
    """`members` aerobie tops: runs/aerobie.toml's first 10^4 draws, repeated."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "run.toml"
        path.write_text((ROOT / "runs" / "aerobie.toml").read_text().replace("members = 200", "members = 10000")
                        .replace("c = [5e-5, 1e-4, 2e-4]", "c = [1e-4]"))
        table = members_table(load(path), 0, 10_000)
    return {name: np.resize(np.asarray(v), (members,) + np.shape(v)[1:]) for name, v in table.items()}


def chain_values(n: int, members: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(7)
    base = {"m": rng.uniform(0.5, 2, (1000, n)), "k": rng.uniform(0.5, 2, (1000, n + 1)),
            "x0": rng.normal(0, 0.1, (1000, n)), "v0": np.zeros((1000, n))}
    return {name: np.resize(v, (members, v.shape[1])) for name, v in base.items()}


def timed(scene, method, values, constants, *, dt, t_end, device, repeats, **settings) -> tuple[float, object]:
    """(median seconds of a launch over t_end, its outcome); inputs are laid out once, outside the timing. A timed
    launch is the kernel and its two samples (start and end) copied to the host as the device hands them on: not
    converted to float64 (as Launch.run does for a float32 run's samples). settings: the launch's others
    (tolerances, precision, events)."""
    call = launch.new_launch(scene, method, values, constants, n_save=2, save_dt=t_end, dt=dt, device=device,
                             **settings)
    call.run()  # compiles
    seconds = []
    for _ in range(repeats):
        synchronize(device)
        start = time.perf_counter()
        for _ in call.segments():
            pass
        seconds.append(time.perf_counter() - start)
    call.run()
    return float(np.median(seconds)), call.outcome()


def calibrated(scene, method, values, constants, *, dt, probe_steps, device, repeats, **tolerances):
    """(member-steps/s of the kernel, steps, seconds of a launch): the launch's seconds less those of a launch of
    one step (its transfers: 10^8 tops copy 11 GB of samples), long enough to time (at least TARGET_SECONDS / 2
    of kernel): the steps double from probe_steps until it is, then grow to about TARGET_SECONDS."""
    overhead, _ = timed(scene, method, values, constants, dt=dt, t_end=dt, device=device, repeats=repeats,
                        **tolerances)
    steps = probe_steps
    while True:
        seconds, _ = timed(scene, method, values, constants, dt=dt, t_end=steps * dt, device=device, repeats=1,
                           **tolerances)
        work = max(seconds - overhead, 1e-6)
        if work >= TARGET_SECONDS / 2 or steps >= 10**7:
            break
        steps = int(steps * min(8.0, max(2.0, TARGET_SECONDS / work)))
    steps = int(min(10**7, max(probe_steps, steps * TARGET_SECONDS / work)))
    seconds, outcome = timed(scene, method, values, constants, dt=dt, t_end=steps * dt, device=device,
                             repeats=repeats, **tolerances)
    taken = float(outcome.counts[0].sum() + outcome.counts[1].sum())
    return taken / max(seconds - overhead, 1e-9), steps, seconds


def kernel_rates(sizes: dict, repeats: int) -> list[dict]:
    return chain_rates(sizes, repeats) + top_rates(sizes, repeats)


def top_rates(sizes: dict, repeats: int) -> list[dict]:
    rows, top = [], resolve("top")
    for members in sizes["top"]:
        if not fits(members, 3 * 8):  # state, rates, limits, works, two segments of samples: about 8 times D
            print(f"top members {members:,d}: not run, more than this GPU's free memory", flush=True)
            continue
        values = top_values(members)
        if members <= 10**7:  # on the host, whose NumPy temporaries for 10^8 tops would take 90 GB
            rows.append(closed_form_rate(top, values))
        for name, extra in (("rk4", {}), ("dopri5", {"rtol": 1e-8, "atol": 1e-10})):
            probe = 200 if name == "rk4" else 20
            rate, steps, seconds = calibrated(top, METHODS[name], values, {}, dt=TOP_DT, probe_steps=probe,
                                              device="cuda", repeats=repeats, **extra)
            rows.append(dict(scene="top", method=name, members=members, steps=steps, seconds=seconds,
                             rate=rate, unit="member-steps/s"))
            print(f"top {name:7s} members {members:>9,d}: {rate:.3g} member-steps/s ({steps} steps, {seconds:.3f} s)",
                  flush=True)
    return rows


def chain_layouts(n: int):
    """Each layout a chain of n masses is timed in, by name: from BOTH_LAYOUTS masses on, a block of threads per
    chain and one thread per chain, whatever gpu_sites.SHARED_SITES says, so that the two can be compared; below, the
    engine's one (""). While a name is yielded, gpu_sites.SHARED_SITES makes its layout the engine's; after, it is as it
    was."""
    shared_sites = gpu_sites.SHARED_SITES
    try:
        for layout in ("block", "thread") if n >= BOTH_LAYOUTS else ("",):
            gpu_sites.SHARED_SITES = {"thread": n + 1, "block": min(n, shared_sites)}.get(layout, shared_sites)
            yield layout
    finally:
        gpu_sites.SHARED_SITES = shared_sites


def chain_rates(sizes: dict, repeats: int) -> list[dict]:
    """Chains of N masses, in each of chain_layouts(N), so that the layouts' threshold is measured."""
    rows, chain = [], resolve("chain")
    for n, chains in sizes["chain"]:
        for members in chains:
            if not fits(members, 2 * n * 8):
                print(f"chain N={n} members {members:,d}: not run, more than this GPU's free memory", flush=True)
                continue
            values = chain_values(n, members)
            for name in ("verlet", "yoshida4", *(("dopri5",) if n in (16, 128) else ())):
                for layout in chain_layouts(n):
                    tolerances = {"rtol": 1e-8, "atol": 1e-10} if METHODS[name].adaptive else {}
                    rate, steps, seconds = calibrated(chain, METHODS[name], values, {"n": n, "boundary": "fixed"},
                                                      dt=CHAIN_DT, probe_steps=20, device="cuda", repeats=repeats,
                                                      **tolerances)
                    threads = gpu_sites.site_threads(n, METHODS[name])
                    rows.append(dict(scene=f"chain N={n}", method=name, members=members, steps=steps, layout=layout,
                                     seconds=seconds, rate=rate * n, unit="mass-steps/s", threads_per_chain=threads))
                    print(f"chain N={n:<5d} {name:8s} members {members:>9,d}, {threads:3d} threads per chain: "
                          f"{rate * n:.3g} mass-steps/s ({steps} steps, {seconds:.3f} s)", flush=True)
    return rows


def closed_form_rate(top, values: dict) -> dict:
    """The closed form (method exact), which runs on the host with NumPy on either device: member-samples/s of 11
    saved samples."""
    members = len(values["c"])
    start = time.perf_counter()
    launch.integrate(top, METHODS["exact"], values, {}, n_save=11, save_dt=0.1, device="cuda")
    seconds = time.perf_counter() - start
    print(f"top exact   members {members:>9,d}: {11 * members / seconds:.3g} member-samples/s (NumPy on the host, "
          f"{seconds:.3f} s)", flush=True)
    return dict(scene="top", method="exact", members=members, seconds=seconds, rate=11 * members / seconds,
                unit="member-samples/s (host)")


def crossover(sizes: dict, repeats: int) -> list[dict]:
    """Whole launches (inputs to the GPU and samples back included) of top rk4, 1000 steps saving 11 samples, on
    the CPU's threads and on the GPU, from 10^2 to 10^6 members."""
    rows, top = [], resolve("top")
    for members in sizes["crossover"]:
        values = top_values(members)
        seconds = {}
        for device in ("cpu", "cuda"):
            def once():
                launch.integrate(top, METHODS["rk4"], values, {}, n_save=11, save_dt=100 * TOP_DT, dt=TOP_DT,
                                 device=device)
            once()
            times = []
            for _ in range(repeats):
                start = time.perf_counter()
                once()
                times.append(time.perf_counter() - start)
            seconds[device] = float(np.median(times))
        rows.append(dict(members=members, cpu_seconds=seconds["cpu"], gpu_seconds=seconds["cuda"],
                         gpu_over_cpu_speed=seconds["cpu"] / seconds["cuda"]))
        print(f"crossover top rk4 members {members:>9,d}: cpu {seconds['cpu']:.4f} s, gpu {seconds['cuda']:.4f} s, "
              f"gpu {seconds['cpu'] / seconds['cuda']:.3g}x", flush=True)
    return rows


def float32_error(sizes: dict) -> list[dict]:
    """Top rk4's largest relative error against the closed form, float64 and float32, over 1 s at several dt."""
    rows, top = [], resolve("top")
    values = top_values(sizes["float32"])
    exact = top.exact(values, {}, np.array([0.0, 1.0]))[-1]
    for dt in sizes["dts"]:
        row = dict(dt=dt)
        for precision in ("float64", "float32"):
            start = time.perf_counter()
            outcome = launch.integrate(top, METHODS["rk4"], values, {}, n_save=2, save_dt=1.0, dt=dt, device="cuda",
                                       precision=precision)
            row[f"{precision}_seconds"] = time.perf_counter() - start
            row[precision] = float(np.max(np.abs(outcome.samples[-1] - exact) / np.abs(exact).max(axis=0)))
        rows.append(row)
        print(f"float32 vs float64, top rk4 over 1 s at dt {dt:g}: error {row['float64']:.2e} (float64), "
              f"{row['float32']:.2e} (float32)", flush=True)
    return rows


LORENZ = ROOT / "runs" / "lorenz.toml"
LORENZ_TOLERANCES = {"float64": 1e-8, "float32": 1e-5}  # dopri5's rtol = atol in each precision


def lorenz_values(members: int) -> tuple[object, dict[str, np.ndarray]]:
    """runs/lorenz.toml's scene and its first `members` members (rho drawn over [0, 21])."""
    spec = load(LORENZ)
    return spec.model, drawn(spec, 0, members)


def lorenz(members: int, device: str, repeats: int, t_end: float = 1.0) -> list[dict]:
    """The Lorenz yardstick timed as the papers time it: inputs already on the device, 1000 steps of 0.001 over
    t in [0, 1], the end state copied back; rk4 in float64 and float32 (the GPU's only), dopri5 at
    LORENZ_TOLERANCES. Each end state is compared with float64 rk4's, and the first 10^4 with the CPU's."""
    scene, values = lorenz_values(members)
    precisions = ("float64", "float32") if device == "cuda" else ("float64",)
    rows, reference = [], None
    for name in ("rk4", "dopri5"):
        for precision in precisions:
            extra = {"rtol": LORENZ_TOLERANCES[precision], "atol": LORENZ_TOLERANCES[precision]} \
                if METHODS[name].adaptive else {}
            seconds, outcome = timed(scene, METHODS[name], values, {}, dt=1e-3, t_end=t_end, device=device,
                                     repeats=repeats, precision=precision, **extra)
            steps = float(outcome.counts[0].sum() + outcome.counts[1].sum())
            end = np.asarray(outcome.samples[-1], dtype=np.float64)
            reference = end if reference is None and precision == "float64" else reference
            row = dict(scene="lorenz", method=name, precision=precision, device=device, members=members,
                       seconds=seconds, rate=steps / seconds, unit="member-steps/s", steps_per_member=steps / members,
                       **extra)
            if reference is not None:
                row["largest_difference_from_float64_rk4"] = float(np.nanmax(np.abs(end - reference)))
            if device == "cuda" and name == "rk4" and precision == "float64":
                row["largest_difference_from_cpu"] = cpu_difference(scene, values, end, t_end)
            rows.append(row)
            print(f"lorenz {name:6s} {precision} on {device}, {members:,d} members: {seconds * 1e3:.1f} ms for t in "
                  f"[0, {t_end:g}] ({steps / members:.0f} steps a member), {row['rate']:.3g} member-steps/s"
                  + "".join(f", {key} {row[key]:.2e}" for key in ("largest_difference_from_float64_rk4",
                                                                     "largest_difference_from_cpu") if key in row),
                  flush=True)
    return rows


def cpu_difference(scene, values: dict, end: np.ndarray, t_end: float, members: int = 10**4) -> float:
    """Largest difference between the GPU's float64 rk4 end states and the CPU kernel's, over the first members."""
    first = {name: v[:members] for name, v in values.items()}
    outcome = launch.integrate(scene, METHODS["rk4"], first, {}, n_save=2, save_dt=t_end, dt=1e-3, device="cpu")
    return float(np.max(np.abs(outcome.samples[-1] - end[:, :members])))  # (state, members)


def whole_lorenz(precision: str) -> dict:
    """`ensemble run runs/lorenz.toml --device cuda` in `precision`: the whole run's time, its own and in all."""
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "lorenz.nc"
        start = time.perf_counter()
        done = subprocess.run([sys.executable, "-m", "ensemble", "run", str(LORENZ), "-o", str(out), "--device",
                               "cuda", "--precision", precision, "--quiet"], capture_output=True, text=True)
        seconds = time.perf_counter() - start
        size = out.stat().st_size if done.returncode == 0 else 0
    said = re.search(r" in ([0-9.e+-]+) s:", done.stdout + done.stderr)
    row = dict(precision=precision, seconds=seconds, run_seconds=float(said.group(1)) if said else float("nan"),
               bytes=size, returncode=done.returncode, output=(done.stdout + done.stderr)[-600:])
    print(f"whole run of runs/lorenz.toml in {precision}: {seconds:.1f} s in all, {row['run_seconds']:.3f} s its "
          f"own, {size / 1e6:.0f} MB written, exit {done.returncode}\n{row['output'].strip()}", flush=True)
    return row


def whole_run(members: int, steps: int, kernel_rate: float | None, samples: int = 101) -> dict:
    """`ensemble run --device cuda` of `members` aerobie tops over 10 s in `steps` steps, saving `samples` samples
    of omega and tilt, against the kernel's rate."""
    dt = 10.0 / steps
    text = (ROOT / "runs" / "aerobie.toml").read_text().replace("members = 200", f"members = {members}")
    text = text.replace("dt = 2.5e-4", f"dt = {dt!r}").replace("save_dt = 0.1 ", f"save_dt = {10.0 / (samples - 1)!r} ")
    text = text.replace("c = [5e-5, 1e-4, 2e-4]", "c = [1e-4]").replace("t_end = 30.0", "t_end = 10.0")
    text = text.replace('seed = 2026', 'seed = 2026\nsave = ["omega", "tilt"]')
    with tempfile.TemporaryDirectory(dir=ROOT) as folder:
        path = Path(folder) / "run.toml"
        path.write_text(text)
        start = time.perf_counter()
        done = subprocess.run([sys.executable, "-m", "ensemble", "run", str(path), "-o", str(Path(folder) / "out.nc"),
                               "--device", "cuda", "--quiet"], capture_output=True, text=True)
        seconds = time.perf_counter() - start
        size = (Path(folder) / "out.nc").stat().st_size if done.returncode == 0 else 0
    said = re.search(r" in ([0-9.e+-]+) s:", done.stdout + done.stderr)  # the run's own time, start-up excluded
    run_seconds = float(said.group(1)) if said else float("nan")
    rate = members * steps / run_seconds
    row = dict(members=members, dt=dt, seconds=seconds, run_seconds=run_seconds, rate=rate, bytes=size,
               returncode=done.returncode, output=(done.stdout + done.stderr)[-600:], kernel_rate=kernel_rate,
               share_of_kernel=rate / kernel_rate if kernel_rate else None)
    print(f"whole run, {members:,d} tops, {steps} steps each, x {samples} samples of omega and tilt "
          f"({size / 1e9:.2f} GB): {seconds:.1f} s in all, {run_seconds:.2f} s its own, {rate:.3g} member-steps/s"
          + (f", {row['share_of_kernel']:.2f} of the kernel's {kernel_rate:.3g}" if kernel_rate else ""), flush=True)
    print(row["output"].strip(), flush=True)
    return row


def main() -> None:
    global TARGET_SECONDS
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="fewer sizes")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes: checks this script (simulator)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", type=Path, help="write the figures here")
    parser.add_argument("--only", choices=("kernels", "rates", "whole", "lorenz"),
                        help="only the kernels' figures (rates, crossover, float32), the rates alone, the whole run, "
                             "or the Lorenz yardstick")
    parser.add_argument("--device", choices=("cuda", "cpu"), default="cuda", help="where --only lorenz runs")
    parser.add_argument("--lorenz-members", type=int, default=2**23, help="Lorenz systems (default 8,388,608)")
    parser.add_argument("--no-whole-lorenz", action="store_true", help="time the Lorenz kernels alone")
    parser.add_argument("--tops", type=int, nargs="+", help="--only rates: tops of these sizes alone, no chains")
    parser.add_argument("--target", type=float, default=TARGET_SECONDS, help="a timed launch's length (s)")
    parser.add_argument("--whole-members", type=int, default=10**7, help="tops in the whole run (0: none)")
    parser.add_argument("--whole-steps", type=int, default=WHOLE_STEPS, help="steps per top in the whole run")
    parser.add_argument("--whole-samples", type=int, default=101, help="samples saved per top in the whole run")
    args = parser.parse_args()
    on_gpu = args.device == "cuda"
    figures = {"gpu": require_gpu() if on_gpu else None, "host": host(),
               "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    print(f"gpu: {figures['gpu']}\n{figures['host']}", flush=True)
    sizes = SIZES["smoke" if args.smoke else "quick" if args.quick else "full"]
    sizes = dict(sizes, top=tuple(args.tops), chain=()) if args.tops else sizes
    TARGET_SECONDS = 1e-3 if args.smoke else args.target
    if args.only == "lorenz":
        figures["lorenz"] = lorenz(args.lorenz_members, args.device, args.repeats, 0.01 if args.smoke else 1.0)
        if on_gpu and not args.no_whole_lorenz:
            figures["lorenz_whole"] = [whole_lorenz(precision) for precision in ("float32", "float64")]
    if args.only in (None, "kernels", "rates"):
        figures["kernels"] = kernel_rates(sizes, args.repeats)
    if args.only in (None, "kernels"):
        figures["crossover"] = crossover(sizes, args.repeats)
        figures["float32"] = float32_error(sizes)
    if args.whole_members and args.only in (None, "whole"):
        top = resolve("top")  # the kernel's rate at the whole run's size, for the share
        kernel_rate, _, _ = calibrated(top, METHODS["rk4"], top_values(args.whole_members), {}, dt=TOP_DT,
                                       probe_steps=200, device="cuda", repeats=args.repeats)
        figures["whole_run"] = whole_run(args.whole_members, args.whole_steps, kernel_rate, args.whole_samples)
    if args.json:
        args.json.write_text(json.dumps(figures, indent=1))


if __name__ == "__main__":
    main()
