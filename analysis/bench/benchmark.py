"""The benchmark a user reads: ensemble against this machine's limit and the tools users would pick instead.

    python analysis/bench/benchmark.py [--full | --whole] [--out benchmark.nc] [--charts DIR] [--repeats 5]

Every figure is a rate of work: member-steps/s for tops, mass-steps/s for
chains, the median of --repeats timed calls on all threads. A peer that steps
differently (solve_ivp, diffrax) is timed doing the same job, the same members
over the same span to ensemble rk4's (or verlet's) accuracy there, and its rate
is that job's steps over its time. Cases and peers:

- top rk4, exact, split2, dopri5; chain verlet and yoshida4 at N = 2 and 16
  (--full: 128 and 1024 too), and verlet on rings of those lengths (ensemble
  and the C's fixed-chain verlet only);
- NumPy vectorized over members; a naive Numba version (one member per
  thread, prange, the right-hand side and the stepper passed as functions),
  timed on a share of the members (10^7 steps a call);
  scipy.integrate.solve_ivp per member, RK45 and DOP853, its rtol lowered by
  decades until its error is no larger; diffrax (jit of vmap, Tsit5 and
  Dopri8 with the same rule) when installed (pip install 'ensemble[bench]');
- the hand-written C of ../shared/limit/limit.py, when it sits beside the
  checkout, for the ratios the targets ask for: its top rk4 and its
  fixed-chain verlet of the same N are timed in a process of their own right
  after each of ensemble's timed calls of top rk4 and of every chain and ring
  case (hostinfo.CBeside), and each ratio is the median of the rounds'
  ratios, so a slow spell of the machine hits both sides. Its printed line
  (`C limit`) comes first, as limit.py runs it;
- the top's rk4 kernel alone on 1, 2, ... threads, in rounds;
- dopri5 against rk4 per member-step on 4096 16-mass chains (bench_dopri5.py's).

--full adds whole `ensemble run` processes: the two whole-run workloads of
issue 15, throughput and peak RSS against members (10^2 .. 10^6 tops),
NUMBA_NUM_THREADS 1 against 2 for a whole run (whose finishing thread uses a
second core even with one kernel thread), each in three rounds of all its
processes (medians; the thread gain the median of the rounds' ratios), and
the warm start-up of a 10-member run.
--whole runs the two workloads alone, --repeats times each (medians), between
two measurements of the C.
Quick took 53 s here and --full 120 s (2026-11-25, with the C in rounds and
the whole runs in three). The figures go to --out (NetCDF) and the charts
(rate against members, against N and against threads) to --charts; the last
lines print each target and whether it is met. The first line names the host.
"""
from __future__ import annotations

import argparse
import functools
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import bench_dopri5
import numpy as np
import xarray as xr
from bench_chain import numpy_verlet
from bench_top import numpy_rk
from hostinfo import LIMIT, CBeside, host

from ensemble import records, tuning
from ensemble.arguments import OneLineParser, positive_int
from ensemble.engine import launch
from ensemble.methods import METHODS
from ensemble.scenes import chain, top
from ensemble.scenes.top.physics import rhs as top_rhs
from ensemble.spec import members_table, parse

ROOT = Path(__file__).resolve().parents[2]
PEERS = ("ensemble", "C", "numpy", "numba_naive", "solve_ivp_RK45", "solve_ivp_DOP853", "diffrax_Tsit5",
         "diffrax_Dopri8")
_CUBE_ROOT_2 = 2.0 ** (1.0 / 3.0)
YOSHIDA4 = (1 / (2 - _CUBE_ROOT_2), -_CUBE_ROOT_2 / (2 - _CUBE_ROOT_2), 1 / (2 - _CUBE_ROOT_2))  # Yoshida's triple
IVP_MEMBERS = 4  # members solve_ivp and diffrax integrate one by one: their rate is per member anyway
NAIVE_WORK = 10**7  # steps (member- or mass-steps) of one timed call of the naive Numba peer: its members are
# independent, one per thread at a time, so a share of the case's members gives its rate (all of a 2**20-mass
# yoshida4 case took 46 s a call, most of the quick benchmark's time)


def naive_members(members: int, n: int, steps: int) -> int:
    """How many of a case's members the naive Numba peer integrates: NAIVE_WORK steps, at least 256 members
    (1024-mass chains: 4 MB of state, beyond the L2 cache like the whole case's)."""
    return min(members, max(256, NAIVE_WORK // (n * steps)))


def median_seconds(fn, repeats: int) -> float:
    return statistics.median(timed_rounds(fn, repeats)[0])


def timed_rounds(fn, repeats: int, c=None) -> tuple[list[float], list[float]]:
    """Seconds of `repeats` calls of fn() and, given c(), the C's rate measured right after each call."""
    seconds, c_rates = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        seconds.append(time.perf_counter() - start)
        if c is not None:
            c_rates.append(c())
    return seconds, c_rates


def ensemble_rates(work: float, seconds: list[float], c_rates: list[float]) -> dict[str, float]:
    """ensemble's rate, `work` steps over the median of `seconds`, and with C rates taken in the same rounds,
    their median ("C") and the median of the rounds' ratios ("to_C")."""
    rates = {"ensemble": work / statistics.median(seconds)}
    if c_rates:
        rates["C"] = statistics.median(c_rates)
        rates["to_C"] = statistics.median(work / s / c for s, c in zip(seconds, c_rates))
    return rates


# --- the scenes' workloads -------------------------------------------------------------------------------------

def top_values(members: int) -> dict[str, np.ndarray]:
    """Aerobie tops (runs/aerobie.toml's draws), `members` of them."""
    text = (ROOT / "runs" / "aerobie.toml").read_text().replace("members = 200", f"members = {members}")
    table = members_table(parse(text.replace("c = [5e-5, 1e-4, 2e-4]", "c = [1e-4]")))
    return {name: np.asarray(v) for name, v in table.items()}


def chain_values(n: int, members: int, rng, springs: int | None = None) -> dict[str, np.ndarray]:
    """Disordered chains of n masses: n + 1 springs (fixed ends) unless told `springs`."""
    return {"m": rng.uniform(0.5, 2, (members, n)), "k": rng.uniform(0.5, 2, (members, springs or n + 1)),
            "x0": rng.normal(0, 0.1, (members, n)), "v0": np.zeros((members, n))}


def relative_error(y: np.ndarray, exact: np.ndarray) -> float:
    """The largest over members of the runner's relative error; y, exact (state, members)."""
    return float(records.relative_error(y[None], exact[None]).max())


# --- the naive Numba peer: one member per thread, scene and stepper as functions ---------------------------------

def naive_numba():
    """(integrate, top_f, chain_f, rk4_step, verlet_step, yoshida_step): integrate(f, step, state, rate, h,
    steps, symplectic) advances every member (state (members, rows), rate (members, parameters)) with prange
    over members, calling the stepper and the right-hand side it is given (first-class functions: no inlining
    across them, no cache)."""
    from numba import njit, prange

    @njit
    def top_f(y, p, out):  # p = (p, r1, r3), as the top's physics.rhs
        out[0] = -p[0] * y[2] * y[1] - p[1] * y[0]
        out[1] = p[0] * y[2] * y[0] - p[1] * y[1]
        out[2] = -p[2] * y[2]

    @njit
    def chain_f(x, p, out):  # fixed ends; p = (k_left / m, k_right / m) per mass, 2n values
        n = x.shape[0]
        for i in range(n):
            left = x[i - 1] if i > 0 else 0.0
            right = x[i + 1] if i < n - 1 else 0.0
            out[i] = p[i] * (left - x[i]) + p[n + i] * (right - x[i])

    @njit
    def rk4_step(f, y, p, h, k):
        rows = y.shape[0]
        f(y, p, k[0])
        for s in range(1, 4):
            c = 0.5 * h if s < 3 else h
            for r in range(rows):
                k[4, r] = y[r] + c * k[s - 1, r]
            f(k[4], p, k[s])
        for r in range(rows):
            y[r] += h / 6 * (k[0, r] + 2 * k[1, r] + 2 * k[2, r] + k[3, r])

    @njit
    def verlet_step(f, y, p, h, k):  # y = (x, v); k[0] holds the acceleration at x
        n = y.shape[0] // 2
        x, v = y[:n], y[n:]
        for i in range(n):
            v[i] += 0.5 * h * k[0, i]
            x[i] += h * v[i]
        f(x, p, k[0])
        for i in range(n):
            v[i] += 0.5 * h * k[0, i]

    w1, w0 = YOSHIDA4[0], YOSHIDA4[1]

    @njit
    def yoshida_step(f, y, p, h, k):
        verlet_step(f, y, p, w1 * h, k)
        verlet_step(f, y, p, w0 * h, k)
        verlet_step(f, y, p, w1 * h, k)

    @njit(parallel=True)
    def integrate(f, step, state, rate, h, steps, symplectic):
        for j in prange(state.shape[0]):
            y = state[j].copy()
            k = np.zeros((5, y.shape[0]))
            if symplectic:
                f(y[:y.shape[0] // 2], rate[j], k[0])
            for _ in range(steps):
                step(f, y, rate[j], h, k)
            state[j] = y

    return integrate, top_f, chain_f, rk4_step, verlet_step, yoshida_step


# --- peers that step their own way: matched to ensemble's error ------------------------------------------------

def matched_ivp(solve, error_of, target: float, tolerances=10.0 ** -np.arange(3, 14)):
    """The first tolerance whose solve() reaches error_of(result) <= target: (seconds, tolerance, error), the
    seconds a median of three; NaNs when none does."""
    for rtol in tolerances:
        if error_of(solve(rtol)) <= target:
            return median_seconds(lambda rtol=rtol: solve(rtol), 3), rtol, error_of(solve(rtol))
    return np.nan, np.nan, np.nan


def solve_ivp_seconds(method: str, f, y0: np.ndarray, t_end: float, exact: np.ndarray, target: float):
    """scipy's solve_ivp on each of the members y0 (state, members) in turn, to error <= target at t_end."""
    from scipy.integrate import solve_ivp

    def solve(rtol):
        return np.stack([solve_ivp(f(j), (0.0, t_end), y0[:, j], method=method, rtol=rtol, atol=rtol * 1e-3).y[:, -1]
                         for j in range(y0.shape[1])], axis=1)

    return matched_ivp(solve, lambda y: relative_error(y, exact), target)


def diffrax_seconds(solver: str, vector_field, y0: np.ndarray, args: np.ndarray, t_end: float, exact: np.ndarray,
                    target: float):
    """diffrax (jit of vmap over members) to error <= target at t_end; NaNs when diffrax is not installed."""
    try:
        import diffrax
        import jax
        import jax.numpy as jnp
    except ImportError:
        return np.nan, np.nan, np.nan
    jax.config.update("jax_enable_x64", True)

    def one(y, a, rtol):
        solution = diffrax.diffeqsolve(diffrax.ODETerm(vector_field), getattr(diffrax, solver)(), 0.0, t_end,
                                       None, y, args=a, stepsize_controller=diffrax.PIDController(
                                           rtol=rtol, atol=rtol * 1e-3), max_steps=10**7)
        return solution.ys[-1]

    # the tolerance is an argument, not a constant: one compile serves every tolerance matched_ivp tries (it
    # compiles at the first, untimed, call)
    compiled = jax.jit(jax.vmap(one, in_axes=(0, 0, None)))

    def solve(rtol):
        return np.asarray(compiled(jnp.asarray(y0.T), jnp.asarray(args), rtol).block_until_ready()).T

    return matched_ivp(solve, lambda y: relative_error(y, exact), target)


# --- the cases -------------------------------------------------------------------------------------------------

def top_case(method: str, members: int, steps: int, repeats: int, peers: bool, naive, timed: int | None = None,
             c=None) -> dict[str, float]:
    """Rates (member-steps/s) of the top with `method` over `steps` steps of 1e-4 s, and its peers'; ensemble's
    from `timed` calls (default `repeats`), each followed by c() (the C's rate) when given (ensemble_rates)."""
    h, values, constants = 1e-4, top_values(members), {}
    launch.prepare(top, METHODS[method], constants)
    adaptive = METHODS[method].adaptive
    settings = dict(rtol=1e-8, atol=1e-12) if adaptive else dict(dt=h)
    call = launch.Launch(top, METHODS[method], values, constants, n_save=2, save_dt=h * steps,
                         blowup_factor=np.inf, **settings)
    seconds, c_rates = timed_rounds(call.run, timed or repeats, c)
    taken = call.outcome().counts[:2].sum() if adaptive else members * steps
    rates = ensemble_rates(taken, seconds, c_rates)
    if not peers:
        return rates
    state, rate = top.inputs(values, constants)
    exact = top.exact(values, constants, np.array([h * steps]))[-1]
    target = max(relative_error(call.outcome().samples[-1][:, :IVP_MEMBERS], exact[:, :IVP_MEMBERS]), 1e-13)
    few = min(members, 256)
    rates["numpy"] = few * steps / median_seconds(
        lambda: numpy_rk(METHODS["rk4"].tableau, state[:, :few].copy(), rate[:, :few], h, steps), 1)
    integrate, top_f, _, rk4_step, _, _ = naive
    share = naive_members(members, 1, steps)
    rows, params = np.ascontiguousarray(state.T[:share]), np.ascontiguousarray(rate.T[:share])
    integrate(top_f, rk4_step, rows[:8].copy(), params[:8], h, 1, False)  # compile
    rates["numba_naive"] = share * steps / median_seconds(lambda: integrate(top_f, rk4_step, rows.copy(), params, h,
                                                                            steps, False), repeats)
    y0, ex = state[:, :IVP_MEMBERS], exact[:, :IVP_MEMBERS]
    for name in ("RK45", "DOP853"):
        seconds, _, _ = solve_ivp_seconds(name, lambda j: lambda t, y: np.array(top_rhs(
            t, y[0], y[1], y[2], rate[0, j], rate[1, j], rate[2, j])), y0, h * steps, ex, target)
        rates[f"solve_ivp_{name}"] = IVP_MEMBERS * steps / seconds

    def field(t, y, a):
        return _stack(-a[0] * y[2] * y[1] - a[1] * y[0], a[0] * y[2] * y[0] - a[1] * y[1], -a[2] * y[2])

    for name in ("Tsit5", "Dopri8"):
        seconds, _, _ = diffrax_seconds(name, field, y0, rate[:, :IVP_MEMBERS].T, h * steps, ex, target)
        rates[f"diffrax_{name}"] = IVP_MEMBERS * steps / seconds
    return rates


def kernel_threads(members: int, steps: int, repeats: int) -> tuple[list[int], np.ndarray]:
    """The top's rk4 kernel alone on 1 .. launch.thread_count() threads: median member-steps/s of `repeats` rounds,
    each timing every thread count once (this shared machine's speed drifts between minutes)."""
    h, values = 1e-4, top_values(members)
    launch.prepare(top, METHODS["rk4"], {})
    call = launch.Launch(top, METHODS["rk4"], values, {}, n_save=2, save_dt=h * steps, dt=h, blowup_factor=np.inf)
    threads = list(range(1, launch.thread_count() + 1))
    seconds = {t: [] for t in threads}
    for _ in range(repeats):
        for t in threads:
            start = time.perf_counter()
            call.run(threads=t)
            seconds[t].append(time.perf_counter() - start)
    return threads, np.array([members * steps / statistics.median(seconds[t]) for t in threads])


def _stack(*rows):
    import jax.numpy as jnp

    return jnp.stack(rows)


def chain_case(method: str, n: int, masses: int, steps: int, repeats: int, peers: bool, naive,
               timed: int | None = None, boundary: str = "fixed", c=None) -> dict[str, float]:
    """Rates (mass-steps/s) of chains of n masses with `method`, h = 0.01, and (fixed ends) its peers' (verlet's
    job); ensemble's from `timed` calls (default `repeats`), each followed by c() when given (as top_case's)."""
    h, constants, rng = 0.01, {"n": n, "boundary": boundary}, np.random.default_rng(1)
    block = launch.layout(chain, METHODS[method], constants).block
    members = max(masses // n // block, 1) * block
    values = chain_values(n, members, rng, chain.spring_count(n, boundary))
    launch.prepare(chain, METHODS[method], constants)
    call = launch.Launch(chain, METHODS[method], values, constants, n_save=2, save_dt=h * steps, dt=h,
                         blowup_factor=np.inf)
    rates = ensemble_rates(members * n * steps, *timed_rounds(call.run, timed or repeats, c))
    if not peers or boundary != "fixed":
        return rates
    state, rate = chain.inputs(values, constants)
    few_values = {name: v[:IVP_MEMBERS] for name, v in values.items()}  # the exact solution of all would take
    exact = chain.exact(few_values, constants, np.array([h * steps]))[-1]  # n^2 floats a member
    target = max(relative_error(call.outcome().samples[-1][:, :IVP_MEMBERS], exact), 1e-13)
    few = min(members, max(1, 2**16 // n))
    substeps = (1.0,) if method == "verlet" else YOSHIDA4  # verlet steps of h times these make one step

    def numpy_steps():
        x, v = state[:n, :few], state[n:, :few]
        for _ in range(steps if len(substeps) > 1 else 1):
            for w in substeps:
                x, v = numpy_verlet(x, v, rate[:n, :few], rate[n:, :few], w * h, 1 if len(substeps) > 1 else steps)

    rates["numpy"] = few * n * steps / median_seconds(numpy_steps, 1)
    integrate, _, chain_f, _, verlet_step, yoshida_step = naive
    step = verlet_step if method == "verlet" else yoshida_step
    share = naive_members(members, n, steps)
    rows, params = np.ascontiguousarray(state.T[:share]), np.ascontiguousarray(rate.T[:share])
    integrate(chain_f, step, rows[:2].copy(), params[:2], h, 1, True)  # compile
    rates["numba_naive"] = share * n * steps / median_seconds(
        lambda: integrate(chain_f, step, rows.copy(), params, h, steps, True), repeats)
    y0, ex = state[:, :IVP_MEMBERS], exact

    def f(j):
        c_left, c_right = rate[:n, j], rate[n:, j]

        def derivative(t, y):
            x = np.concatenate(([0.0], y[:n], [0.0]))
            return np.concatenate((y[n:], c_left * (x[:-2] - x[1:-1]) + c_right * (x[2:] - x[1:-1])))
        return derivative

    for name in ("RK45", "DOP853"):
        seconds, _, _ = solve_ivp_seconds(name, f, y0, h * steps, ex, target)
        rates[f"solve_ivp_{name}"] = IVP_MEMBERS * n * steps / seconds

    def field(t, y, a):
        import jax.numpy as jnp

        x = jnp.concatenate((jnp.zeros(1), y[:n], jnp.zeros(1)))
        return jnp.concatenate((y[n:], a[:n] * (x[:-2] - x[1:-1]) + a[n:] * (x[2:] - x[1:-1])))

    for name in ("Tsit5", "Dopri8"):
        seconds, _, _ = diffrax_seconds(name, field, y0, rate[:, :IVP_MEMBERS].T, h * steps, ex, target)
        rates[f"diffrax_{name}"] = IVP_MEMBERS * n * steps / seconds
    return rates


def c_limit() -> dict[str, float]:
    """The C kernels' rates from limit.py beside the checkout ({} when it is not there)."""
    if not LIMIT.exists():
        return {}
    out = subprocess.run([sys.executable, str(LIMIT)], capture_output=True, text=True, check=True).stdout
    rates = {}
    for line in out.splitlines():
        if match := re.match(r"(top rk4|chain verlet N=(\d+))\s+([0-9.e+]+)", line):
            rates["top rk4" if match[2] is None else f"chain verlet N={match[2]}"] = float(match[3])
        elif match := re.match(r"peak FMA\s+([0-9.e+]+)", line):
            rates["peak flop/s"] = float(match[1])
    return rates


#: Flops a step of a case makes, as ../shared/limit/ens.c counts them (a fused multiply-add is 2): a top rk4
#: member-step 68, a verlet mass-step 10 (a chain's and a ring's); yoshida4 makes three verlet force sweeps a step.
FLOPS_PER_STEP = {"top rk4": 68, "verlet": 10, "yoshida4": 30}


def peak_share(name: str, rate: float, limit: dict[str, float]) -> str:
    """' , P% of peak' for a case whose flops per step are counted (FLOPS_PER_STEP), with limit.py's peak."""
    flops = FLOPS_PER_STEP.get(name) or next((f for k, f in FLOPS_PER_STEP.items() if f" {k} " in f" {name} "), None)
    peak = limit.get("peak flop/s")
    return f", {rate * flops / peak:.0%} of peak" if flops and peak else ""


# --- whole runs (--full) ---------------------------------------------------------------------------------------

TOPS = """scene = "top"
method = "rk4"
dt = 1e-3
t_end = {t_end}
save_dt = {save_dt}
members = {members}
seed = 1
save = {save}
[parameters]
lambda1 = 1.0e-3
lambda3 = 2.0e-3
c = 1e-4
spin0 = 60.0
tilt0 = {{ uniform = [0.02, 0.2] }}
azimuth0 = {{ uniform = [0.0, 6.283185307179586] }}
"""
CHAINS = """scene = "chain"
method = "verlet"
dt = 0.01
t_end = 40.0
save_dt = 2.0
members = 65536
seed = 1
save = ["x"]
[parameters]
n = 16
boundary = "fixed"
m = { uniform = [0.5, 2.0] }
k = 1.0
x0 = { uniform = [-0.1, 0.1] }
"""

#: The two whole-run workloads of issue 15 as run files, by name (run_phases.py and compare_revisions.py).
WORKLOADS = {"tops": TOPS.format(t_end=8.0, save_dt=0.1, members=262144, save='["omega", "tilt"]'), "chains": CHAINS}


PEAK = ("import atexit, runpy, sys\n"
        "def peak():\n"
        "    for line in open('/proc/self/status'):\n"
        "        if line.startswith('VmHWM'):\n"
        "            print('peak', line.split()[1], file=sys.stderr)\n"
        "atexit.register(peak)\n"
        "sys.argv = ['ensemble', *sys.argv[1:]]\n"
        "runpy.run_module('ensemble', run_name='__main__')\n")  # the peak of this process alone: a fork's
# high-water mark (ru_maxrss) includes the memory of the process it was forked from


def whole_run(text: str, folder: Path, threads: int | None = None, env: dict[str, str] | None = None
              ) -> tuple[float, float, float, float]:
    """`ensemble run` of a run file's text in a process of its own (its environment updated with `env`): (wall
    seconds, member-steps (mass-steps for chains) in the run, the rate the run reports (its work over its own
    seconds: start-up and loading the kernels excluded), peak RSS in MB)."""
    path, out = folder / "run.toml", folder / "run.nc"
    path.write_text(text)
    out.unlink(missing_ok=True)
    env = {**os.environ, **(env or {}), **({"NUMBA_NUM_THREADS": str(threads)} if threads else {})}
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", PEAK, "run", str(path), "-o", str(out), "--quiet"],
                          capture_output=True, text=True, env=env)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"benchmark: ensemble run failed: {done.stderr.strip().splitlines()[-1:]}")
    spec = parse(text)
    work = spec.n_members * round(spec.t_end / float(members_table(spec)["dt"][0])) * spec.constants.get("n", 1)
    seconds = float(re.search(r" in ([0-9.e+-]+) s: ", done.stdout)[1])
    peak = float(re.search(r"^peak (\d+)", done.stderr, re.M)[1]) / 1024
    out.unlink(missing_ok=True)
    return wall, work, work / seconds, peak


def warm_start(folder: Path) -> float:
    """Median wall seconds of a warm-cache 10-member run (three runs after one that fills the cache)."""
    text = TOPS.format(t_end=1.0, save_dt=0.1, members=10, save='["omega", "tilt"]')
    whole_run(text, folder)
    return statistics.median(whole_run(text, folder)[0] for _ in range(3))


# --- report ----------------------------------------------------------------------------------------------------

def main() -> None:
    parser = OneLineParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--full", action="store_true", help="every chain length, whole runs and scaling")
    parser.add_argument("--repeats", type=positive_int, default=5)
    parser.add_argument("--out", type=Path, default=Path("benchmark.nc"), help="figures (NetCDF)")
    parser.add_argument("--charts", type=Path, default=Path("benchmark_charts"), help="folder for the PNG charts")
    parser.add_argument("--no-peers", action="store_true", help="ensemble and C only (fast)")
    parser.add_argument("--whole", action="store_true", help="only the two whole-run workloads, --repeats times "
                                                            "each, beside the C measured just before them")
    args = parser.parse_args()
    print(host(), flush=True)
    print(f"tuning: {tuning.describe()}", flush=True)
    if args.whole:
        return whole_only(args.repeats)
    peers, naive = not args.no_peers, naive_numba()
    lengths = (2, 16, 128, 1024) if args.full else (2, 16)
    limit = c_limit()
    print_limit("C limit", limit)
    runs = {f"top {m}": lambda peers, timed=None, c=None, m=m: top_case(m, 65536, 1000, args.repeats, peers, naive,
                                                                       timed, c)
            for m in ("rk4", "exact", "split2", "dopri5")}
    runs.update({f"chain {m} N={n}": lambda peers, timed=None, c=None, m=m, n=n: chain_case(
        m, n, 2**20, 1000, args.repeats, peers, naive, timed, c=c) for m in ("verlet", "yoshida4") for n in lengths})
    runs.update({f"ring verlet N={n}": lambda peers, timed=None, c=None, n=n: chain_case(
        "verlet", n, 2**20, 1000, args.repeats, False, naive, timed, "periodic", c) for n in lengths})
    with_peers = [name for name in runs if peers and (name == "top rk4" or name.startswith("chain"))]  # on tops,
    # the peers do rk4's job
    # ensemble's kernels first, before any peer has loaded its libraries (JAX starts threads of its own) into this
    # process, each timed call followed by its C kernel's (c_kernel_beside); a case with peers then calls its
    # kernel once more, for the error the peers must match
    beside = CBeside()
    try:
        cases = {name: case(False, c=functools.partial(beside.rate, c_kernel_beside(name))
                            if beside.available and c_kernel_beside(name) else None)
                 for name, case in runs.items()}
    finally:
        beside.close()
    threads, by_threads = kernel_threads(65536, 1000, args.repeats)
    chain_spec = parse(bench_dopri5.CHAIN.format(members=4096, n=16))
    per_step = bench_dopri5.per_step(chain, members_table(chain_spec), chain_spec.constants, 1e-2, 1.0, 11,
                                     args.repeats)
    chain_adaptive = per_step["dopri5"] / per_step["rk4"]
    print(f"chain dopri5 per member-step (4096 16-mass chains): {chain_adaptive:.2f}x rk4", flush=True)
    for name, case in runs.items():
        if name in with_peers:
            cases[name] = {**case(True, timed=1), **cases[name]}  # ensemble's (and the C's) from the rounds
        print(name, _row(cases[name]) + peak_share(name, cases[name]["ensemble"], limit), flush=True)
    print("top rk4 kernel on", ", ".join(f"{t} thread(s) {r:.3g}" for t, r in zip(threads, by_threads)), flush=True)
    names = list(cases)
    rates = np.array([[cases[c].get(p, np.nan) for p in PEERS] for c in names])
    ds = xr.Dataset({"rate": (("case", "implementation"), rates, {
        "long_name": "work rate", "units": "steps/s",
        "comment": "member-steps/s for tops, mass-steps/s for chains; a peer stepping its own way is credited with "
                   "the ensemble job's steps (same members, span and accuracy) over its time"})},
        coords={"case": names, "implementation": list(PEERS)}, attrs={"host": host(), "full": int(args.full)})
    ds["kernel_thread_rate"] = ("kernel_threads", by_threads, {
        "units": "member-steps/s", "long_name": "top rk4 kernel alone (65,536 members, 1000 steps)"})
    ds["ratio_to_c"] = ("case", [cases[c].get("to_C", np.nan) for c in names], {
        "units": "1", "long_name": "ensemble over the C kernel it stands beside",
        "comment": "the median over rounds of each round's ratio: a C call (limit.py's kernels) right after each "
                   "of ensemble's timed calls; chains and rings beside the C's fixed-chain verlet of their N"})
    ds = ds.assign_coords(kernel_threads=threads)
    ds["chain_dopri5_cost"] = ((), chain_adaptive, {"units": "1", "long_name": "chain dopri5 over rk4 seconds per "
                                                    "member-step (4096 16-mass chains)"})
    targets = []
    if len(threads) > 1:
        gain = by_threads[1] / by_threads[0]
        targets.append(("kernel alone, 1 -> 2 threads >= 1.8x", f"{gain:.2f}x", gain >= 1.8))
    if "top rk4" in cases and "top dopri5" in cases:
        ratio = cases["top rk4"]["ensemble"] / cases["top dopri5"]["ensemble"]
        targets.append(("dopri5 per member-step on tops <= 3x rk4", f"{ratio:.1f}x", ratio <= 3))
    targets.append(("dopri5 per member-step on 16-mass chains <= 2.5x rk4", f"{chain_adaptive:.2f}x",
                    chain_adaptive <= 2.5))
    for name in names:
        if name.startswith(("chain", "ring")) and "to_C" in cases[name]:
            share = cases[name]["to_C"]
            sweeps = len(YOSHIDA4) if "yoshida4" in name else 1  # force sweeps a step; C verlet makes one
            per_sweep = f" ({share * sweeps:.2f} per force sweep)" if sweeps > 1 else ""
            targets.append((f"{name} >= 0.9 of C verlet's mass-steps/s", f"{share:.2f}{per_sweep}", share >= 0.9))
    if args.full:
        ds = ds.merge(full_runs(limit, targets))
    args.out.unlink(missing_ok=True)
    ds.to_netcdf(args.out)
    charts(ds, args.charts)
    print(f"figures in {args.out}, charts in {args.charts}/")
    for what, value, met in targets:
        print(f"{'met    ' if met else 'NOT met'}  {what}: {value}")


def whole_only(repeats: int) -> None:
    """--whole: the two workloads, then the C again, and the targets."""
    targets = []
    limit = c_limit()
    print_limit("C limit", limit)
    with tempfile.TemporaryDirectory() as tmp:
        rates = workloads(limit, targets, Path(tmp), repeats)
    after = c_limit()
    print_limit("C limit, after", after)
    for name, rate in rates.items():
        if name in after:
            print(f"whole run beside {name}: {rate / after[name]:.2f} of the C after", flush=True)
    for what, value, met in targets:
        print(f"{'met    ' if met else 'NOT met'}  {what}: {value}")


def _row(rates: dict[str, float]) -> str:
    to_c = f"  (ensemble / C {rates['to_C']:.2f}, median over rounds)" if "to_C" in rates else ""
    return "  ".join(f"{p} {rates[p]:.3g}" for p in PEERS if p in rates and np.isfinite(rates[p])) + to_c


def c_kernel_beside(case: str) -> str | None:
    """The C kernel (limit.py's name) a case is measured beside: top rk4 beside the C's, a chain or ring of N
    masses (any method) beside the C's fixed-chain verlet of N masses; None for the rest."""
    if case == "top rk4":
        return "top rk4"
    if case.startswith(("chain", "ring")):
        return f"chain verlet N={case.split('N=')[1]}"
    return None


def workloads(limit: dict[str, float], targets: list, folder: Path, repeats: int) -> dict[str, float]:
    """The two whole-run workloads of issue 15 against the C limit: median wall seconds of `repeats` warm runs each;
    returns their rates by the name of the C kernel they stand beside."""
    rates = {}
    for name, text, kernel in (("262144 tops", WORKLOADS["tops"], "top rk4"),
                               ("65536 16-mass chains", WORKLOADS["chains"], "chain verlet N=16")):
        whole_run(text, folder)  # untimed: after an install or an edit, the first run compiles its kernels
        walls, works = zip(*(whole_run(text, folder)[:2] for _ in range(repeats)))
        wall, work, c = statistics.median(walls), works[0], limit.get(kernel)
        share = work / wall / c if c else np.nan
        print(f"whole run, {name}: {wall:.2f} s (median of {repeats}: {', '.join(f'{w:.2f}' for w in walls)}), "
              f"{work / wall:.3g} steps/s, {share:.2f} of C", flush=True)
        targets.append((f"whole run of {name} >= 0.9 of C", f"{share:.2f}", share >= 0.9))
        rates[kernel] = work / wall
    return rates


def print_limit(label: str, limit: dict[str, float]) -> None:
    print(f"{label}:", ", ".join(f"{k} {v:.3g}" for k, v in limit.items()) or "limit.py not found", flush=True)


WHOLE_ROUNDS = 3  # --full's whole runs: rounds of every process of a comparison, medians over them


def full_runs(limit: dict[str, float], targets: list) -> xr.Dataset:
    """Whole `ensemble run` processes: the two workloads against C (measured again just before them), members,
    threads, RSS and the start-up; each comparison in WHOLE_ROUNDS rounds of all its processes, medians."""
    limit = c_limit() or limit
    print_limit("C limit, again", limit)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        workloads(limit, targets, folder, repeats=WHOLE_ROUNDS)
        members = [10**k for k in range(2, 7)]
        runs = np.array([[whole_run(TOPS.format(t_end=2.0, save_dt=0.02, members=m, save='["tilt"]'), folder)
                          for m in members] for _ in range(WHOLE_ROUNDS)])  # (round, members, wall/work/rate/RSS)
        wall, work, rate, _ = np.median(runs, axis=0).T
        rss = runs[:, :, 3].max(axis=0)  # the largest of the rounds' peaks
        for k, m in enumerate(members):
            print(f"{m:>8} tops (101 samples): {rate[k]:.3g} member-steps/s in the run ({work[k] / wall[k]:.3g} "
                  f"with start-up), peak RSS {rss[k]:.0f} MB; medians (RSS: the largest) of {WHOLE_ROUNDS} rounds",
                  flush=True)
        spread = rate[2:].min() / rate[2:].max()
        targets.append(("throughput (the run's own) from 10^4 members within 20% of the best", f"{spread:.2f}",
                        spread >= 0.8))
        targets.append(("10^6 tops with 100 samples under 600 MB", f"{rss[-1]:.0f} MB", rss[-1] < 600))
        threads = [1, 2]
        text = TOPS.format(t_end=8.0, save_dt=0.1, members=65536, save='["omega", "tilt"]')
        by_round = np.array([[whole_run(text, folder, t)[2] for t in threads] for _ in range(WHOLE_ROUNDS)])
        by_threads = np.median(by_round, axis=0)
        gain = float(np.median(by_round[:, 1] / by_round[:, 0]))
        print(f"threads 1 -> 2 (65536 tops, the run's own rate): {by_threads[0]:.3g} -> {by_threads[1]:.3g} "
              f"member-steps/s, {gain:.2f}x (median of the rounds' ratios: "
              f"{', '.join(f'{g:.2f}' for g in by_round[:, 1] / by_round[:, 0])})", flush=True)
        targets.append(("whole run, 1 -> 2 threads >= 1.8x", f"{gain:.2f}x", gain >= 1.8))
        start = warm_start(folder)
        print(f"warm 10-member run: {start:.2f} s", flush=True)
        targets.append(("warm 10-member run <= 0.7 s", f"{start:.2f} s", start <= 0.7))
    return xr.Dataset({"run_rate": ("members", rate, {"units": "member-steps/s", "long_name": "whole-run rate"}),
                       "peak_rss": ("members", rss, {"units": "MB", "long_name": "peak resident memory"}),
                       "thread_rate": ("threads", by_threads, {"units": "member-steps/s"}),
                       "warm_start": ((), start, {"units": "s", "long_name": "warm 10-member run, whole process"})},
                      coords={"members": members, "threads": threads})


def charts(ds: xr.Dataset, folder: Path) -> None:
    """PNG charts: chain rate against N, the kernel's rate against threads (with --full the whole run's too),
    and (with --full) the whole run's against members."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("no charts: pip install 'ensemble[plot]'")
        return
    folder.mkdir(parents=True, exist_ok=True)
    for method in ("verlet", "yoshida4"):
        names = [c for c in ds.case.values if str(c).startswith(f"chain {method}")]
        if not names:
            continue
        n = [int(str(c).split("N=")[1]) for c in names]
        fig, ax = plt.subplots()
        for peer in ds.implementation.values:
            y = ds.rate.sel(case=names, implementation=peer).values
            if np.isfinite(y).any():
                ax.loglog(n, y, "o-", label=str(peer))
        ax.set(xlabel="masses N", ylabel="mass-steps/s", title=f"chain {method}, {ds.host}"[:90])
        ax.legend(fontsize=7)
        fig.savefig(folder / f"chain_{method}_against_n.png", dpi=120)
        plt.close(fig)
    if "run_rate" in ds:
        fig, ax = plt.subplots()
        ax.plot(ds.members, ds.run_rate, "o-")
        ax.set(xscale="log", xlabel="members", ylabel="member-steps/s", title=f"whole run, tops rk4, {ds.host}"[:90],
               ylim=(0, None))
        fig.savefig(folder / "run_rate_against_members.png", dpi=120)
        plt.close(fig)
    fig, ax = plt.subplots()
    ax.plot(ds.kernel_threads, ds.kernel_thread_rate, "o-", label="kernel alone")
    if "thread_rate" in ds:
        ax.plot(ds.threads, ds.thread_rate, "s-", label="whole run (its own rate)")
    ax.set(xlabel="threads (NUMBA_NUM_THREADS)", ylabel="member-steps/s", title=f"tops rk4, {ds.host}"[:90],
           xticks=ds.kernel_threads.values, ylim=(0, None))
    ax.legend(fontsize=7)
    fig.savefig(folder / "rate_against_threads.png", dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
