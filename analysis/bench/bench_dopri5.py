"""Benchmark: adaptive dopri5 against fixed-step rk4, per step and at equal accuracy.

    python analysis/bench/bench_dopri5.py [--repeats 3] [--chain-block B] [--chain-n 16 ...]

1. Kernel seconds per member-step of rk4 and dopri5, side by side in this
   process (medians of --repeats): 8192 aerobie tops (runs/aerobie.toml), and
   disordered chains of each --chain-n masses (default 16), 65,536 masses in
   all (--chain-block B: their dopri5 in blocks of B members instead of
   block_size's choice; a member takes the same steps in every block, its
   values agree to the last few bits).
2. The same for the tops in hand-written C (analysis/bench/c/top_dopri5.c, compiled
   here with gcc; skipped without it), alternated with ensemble's kernels:
   rk4 as ../shared/limit/ens.c writes it, and dopri5 with ensemble's step
   control written the same way: the ratio C can reach on this host, and how
   much of it is members waiting for the rest of their block at saved times.
3. Right-hand-side evaluations each needs for a largest error of 1e-10 over
   2 s on a top spinning at 200 rad/s: rk4 halves dt until it gets there,
   dopri5 lowers rtol by decades.
"""
from __future__ import annotations

import argparse
import ctypes
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
from hostinfo import force_chain_block, host, quiet_openmp

from ensemble.arguments import OneLineParser, positive_int
from ensemble.engine import launch
from ensemble.methods import METHODS
from ensemble.records import measured_error
from ensemble.scenes import chain, top
from ensemble.spec import members_table, parse

RUNS = Path(__file__).resolve().parents[2] / "runs"
C_SOURCE = Path(__file__).resolve().parent / "c" / "top_dopri5.c"
# -fallow-store-data-races: without it gcc makes each member's "new value or old" into a masked store (vmaskmovpd,
# slow on AMD Zen 3) where a blend and a whole store do.
C_FLAGS = ["-O3", "-march=native", "-ffast-math", "-fopenmp", "-fallow-store-data-races", "-fPIC"]
C_BLOCK = 128  # BS in top_dopri5.c
CHAIN = """scene = "chain"
method = "rk4"
dt = 1e-2
t_end = 10.0
save_dt = 1.0
members = {members}
seed = 1
[parameters]
n = {n}
boundary = "fixed"
m = {{ uniform = [0.5, 2.0] }}
k = 1.0
x0 = {{ uniform = [-0.1, 0.1] }}
"""


def per_step(scene, values, constants, dt, save_dt, n_save, repeats, others=None):
    """Median seconds per member-step of ensemble's rk4 (step dt) and dopri5 (rtol 1e-8) kernels, and of each
    run() in `others` (by name; it returns the member-steps it took), alternated in every repeat."""
    rk4, dopri5 = METHODS["rk4"], METHODS["dopri5"]
    for method in (rk4, dopri5):
        launch.prepare(scene, method, constants)
    fixed = launch.Launch(scene, rk4, values, constants, n_save=n_save, save_dt=save_dt, dt=dt)
    adaptive = launch.Launch(scene, dopri5, values, constants, n_save=n_save, save_dt=save_dt, rtol=1e-8, atol=1e-12)

    def steps_of(call):
        def run():
            call.run()
            counts = call.outcome().counts
            return counts[0].sum() + counts[1].sum()
        return run

    runs = {"rk4": steps_of(fixed), "dopri5": steps_of(adaptive), **(others or {})}
    seconds = {name: [] for name in runs}
    for _ in range(repeats):
        for name, run in runs.items():
            start = time.perf_counter()
            steps = run()
            seconds[name].append((time.perf_counter() - start) / steps)
    return {name: statistics.median(s) for name, s in seconds.items()}


def c_tops(values, n_save, save_dt, dt, folder):
    """run() functions (by name) of the hand-written C on the tops of `values` (members a multiple of C_BLOCK),
    for per_step: rk4 with step dt, dopri5 at rtol 1e-8; None without gcc."""
    if shutil.which("gcc") is None:
        return None
    quiet_openmp()
    objects, library = Path(folder) / "top_dopri5.o", Path(folder) / "top_dopri5.so"
    subprocess.run(["gcc", *C_FLAGS, "-c", str(C_SOURCE), "-o", str(objects)], check=True)
    # Linked without -ffast-math: with it gcc adds crtfastmath.o, which on loading sets the process's
    # flush-to-zero and denormals-are-zero modes, and ensemble's kernels in this process would run with them.
    subprocess.run(["gcc", "-shared", "-fopenmp", str(objects), "-o", str(library), "-lm"], check=True)
    c = ctypes.CDLL(str(library))
    double, long, pointer = ctypes.c_double, ctypes.c_long, ctypes.POINTER(ctypes.c_double)
    c.top_rk4.argtypes = [long, long, long, double, pointer, pointer]
    c.top_dopri5.argtypes = [long, long, double, double, double, double, *[double] * 5, pointer, pointer, pointer]
    state0, rate = (np.ascontiguousarray(x) for x in top.inputs(values, {}))
    members = state0.shape[1]
    assert members % C_BLOCK == 0, members
    control = METHODS["dopri5"].control
    steps_per_save = round(save_dt / dt)

    def rk4():
        w = state0.copy()
        c.top_rk4(members, n_save, steps_per_save, dt, _address(w), _address(rate))
        return members * (n_save - 1) * steps_per_save

    def dopri5():
        w, counts = state0.copy(), np.zeros((3, members))
        c.top_dopri5(members, n_save, save_dt, 1e-8, 1e-12, dt, control.alpha, control.beta, control.safety,
                     control.min_factor, control.max_factor, _address(w), _address(rate), _address(counts))
        dopri5.waited = 1.0 - counts[:2].sum() / counts[2].sum()  # share of the blocks' trial steps members waited
        return counts[:2].sum()

    return {"C rk4": rk4, "C dopri5": dopri5}


def _address(array):
    return array.ctypes.data_as(ctypes.POINTER(ctypes.c_double))


def evaluations_for(target: float):
    """rhs evaluations per member that rk4 and dopri5 need for a largest error <= target (fast top, 2 s)."""
    text = (RUNS / "aerobie.toml").read_text()
    spec = parse(text.replace("members = 200", "members = 4"))
    values = {name: v[:4] for name, v in members_table(spec).items()}
    values.update(spin0=np.full(4, 200.0), c=np.full(4, 1e-3))
    t = np.arange(9) * 0.25
    exact = top.exact(values, {}, t)
    rk4 = dopri5 = None
    for steps_per_save in 100 * 2 ** np.arange(10):
        samples = launch.integrate(top, METHODS["rk4"], values, {}, n_save=9, save_dt=0.25,
                                   dt=0.25 / steps_per_save).samples
        if measured_error(samples, exact)[0].max() <= target:
            rk4 = (4 * steps_per_save * 8, 0.25 / steps_per_save)
            break
    for rtol in 10.0 ** -np.arange(6, 15):
        samples, counts = launch.integrate(top, METHODS["dopri5"], values, {}, n_save=9, save_dt=0.25, rtol=rtol,
                                           atol=1e-14)[:2]
        if measured_error(samples, exact)[0].max() <= target:
            dopri5 = (int(counts[2].max()), rtol)
            break
    return rk4, dopri5


def main():
    parser = OneLineParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=positive_int, default=3)
    parser.add_argument("--chain-block", type=positive_int, help="members per block of the chains' dopri5 kernel "
                                                                 "(default: block_size's choice for this host)")
    parser.add_argument("--chain-n", type=positive_int, nargs="+", default=[16], help="masses per chain")
    args = parser.parse_args()
    if args.chain_block:
        force_chain_block(args.chain_block, adaptive_only=True)
    print(host())
    spec = parse((RUNS / "aerobie.toml").read_text().replace("members = 200", "members = 4096"))
    tops = {name: v[:8192] for name, v in members_table(spec).items()}
    with tempfile.TemporaryDirectory() as folder:
        c_runs = c_tops(tops, 31, 0.1, 1e-3, folder)
        seconds = per_step(top, tops, {}, 1e-3, 0.1, 31, args.repeats, c_runs)
    rk4, dopri5 = seconds["rk4"], seconds["dopri5"]
    print(f"top, 8192 members: rk4 {rk4:.3g} s, dopri5 {dopri5:.3g} s per member-step, ratio {dopri5 / rk4:.1f}")
    if "C rk4" in seconds:
        c_rk4 = seconds["C rk4"]
        c_dopri5 = seconds["C dopri5"]
        print(f"  hand-written C ({C_SOURCE.name}): rk4 {c_rk4:.3g} s, dopri5 {c_dopri5:.3g} s, ratio "
              f"{c_dopri5 / c_rk4:.1f}; ensemble's rk4 takes {rk4 / c_rk4:.2f} and its dopri5 {dopri5 / c_dopri5:.2f} "
              f"of the C's time; the C's members waited for their block in {c_runs['C dopri5'].waited:.1%} of its "
              "trial steps")
    else:
        print("  hand-written C: skipped (no gcc)")
    for n in args.chain_n:
        members = max(64, 2**16 // n)
        chain_spec = parse(CHAIN.format(members=members, n=n))
        seconds = per_step(chain, members_table(chain_spec), chain_spec.constants, 1e-2, 1.0, 11, args.repeats)
        rk4, dopri5 = seconds["rk4"], seconds["dopri5"]
        block = launch.layout(chain, METHODS["dopri5"], chain_spec.constants).block
        print(f"chain n = {n}, {members} members: rk4 {rk4:.3g} s, dopri5 {dopri5:.3g} s (blocks of {block}) per "
              f"member-step, ratio {dopri5 / rk4:.2f}")
    (rk4_evals, dt), (dopri5_evals, rtol) = evaluations_for(1e-10)
    print(f"top at 200 rad/s, error <= 1e-10 over 2 s: rk4 {rk4_evals} rhs evaluations (dt = {dt:.3g} s), "
          f"dopri5 {dopri5_evals} (rtol = {rtol:.0e}): {rk4_evals / dopri5_evals:.1f}x fewer")


if __name__ == "__main__":
    main()
