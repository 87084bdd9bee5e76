"""Adaptive Dormand-Prince, [measure], sweeps over methods and steps, and the work-precision runs."""
import re
from pathlib import Path

import numpy as np
import pytest

from ensemble import fitting, records, runner
from ensemble.engine import launch
from ensemble.methods import DOPRI5, METHODS
from ensemble.records import measured_error
from ensemble.scenes import top
from ensemble.scenes.top import fits as top_fit
from ensemble.spec import SpecError, members_table, parse
from tests.conftest import top_runfile

RUNS = Path(__file__).resolve().parent.parent / "runs"
FAST_TOP = {"spin0": 200.0, "c": 1e-3, "tilt0": 0.3, "azimuth0": 0.5}  # precession ~ 0.8 x 200 cos 0.3 rad/s


def test_dopri5_tableau_has_order_5_and_an_order_4_embedded_pair():
    a = np.array(DOPRI5.square_a()).reshape(7, 7)
    c = np.array(DOPRI5.c)
    for weights, order in ((np.array(DOPRI5.b), 5), (np.array(DOPRI5.b) - np.array(DOPRI5.error), 4)):
        assert weights.sum() == pytest.approx(1.0, abs=1e-15)
        for k in range(1, order):  # the bushy-tree conditions b . c^k = 1 / (k + 1)
            assert weights @ c**k == pytest.approx(1 / (k + 1), abs=1e-14)
        assert weights @ a @ c == pytest.approx(1 / 6, abs=1e-14)
    assert sum(DOPRI5.error) == pytest.approx(0.0, abs=1e-16) and DOPRI5.fsal


def top_members(members=16, **parameters):
    return members_table(parse(top_runfile(members=members, t_end=2.0, save_dt=0.25,
                                           parameters={**FAST_TOP, **parameters})))


def error_against_exact(samples, values, t):
    return measured_error(samples, top.exact(values, {}, t))[0]


def test_dopri5_error_follows_rtol_over_six_decades():
    values = top_members()
    t = np.arange(9) * 0.25
    rtols = 10.0 ** -np.arange(4, 11)
    errors = []
    for rtol in rtols:
        samples, counts = launch.integrate(top, METHODS["dopri5"], values, {}, n_save=9, save_dt=0.25, rtol=rtol,
                                           atol=1e-14)[:2]
        errors.append(np.median(error_against_exact(samples, values, t)))
        evaluations = 1 + 6 * (counts[0] + counts[1])
        assert np.array_equal(counts[2], evaluations)  # FSAL: six new stages per trial step
    errors = np.array(errors)
    slope = np.polyfit(np.log(rtols), np.log(errors), 1)[0]
    assert slope == pytest.approx(1.0, abs=0.15)
    assert np.all((errors > rtols / 30) & (errors < rtols * 30))


def test_dopri5_beats_rk4_on_rhs_evaluations_at_1e_10():
    values = top_members(members=4)
    t = np.arange(9) * 0.25
    rk4 = None
    for steps_per_save in (1600, 3200, 6400, 12800, 25600):  # rk4: the first dt reaching 1e-10
        samples = launch.integrate(top, METHODS["rk4"], values, {}, n_save=9, save_dt=0.25,
                                   dt=0.25 / steps_per_save).samples
        if error_against_exact(samples, values, t).max() <= 1e-10:
            rk4 = 4 * steps_per_save * 8
            break
    dopri5 = None
    for rtol in 10.0 ** -np.arange(8, 14):
        samples, counts = launch.integrate(top, METHODS["dopri5"], values, {}, n_save=9, save_dt=0.25, rtol=rtol,
                                           atol=1e-14)[:2]
        if error_against_exact(samples, values, t).max() <= 1e-10:
            dopri5 = counts[2].max()
            break
    assert rk4 is not None and dopri5 is not None
    assert dopri5 < rk4 / 2, (dopri5, rk4)


def test_dopri5_lands_on_the_save_grid_and_counts_its_steps():
    ds = runner.simulate(parse(top_runfile(method="dopri5", dt=None, rtol=1e-10, atol=1e-14, members=3,
                                           t_end=1.0, save_dt=0.1, parameters=FAST_TOP) + "[measure]\nerror = true\n"))
    assert ds.attrs["method"] == "dopri5" and ds.attrs["rtol"] == 1e-10
    assert np.all(ds.error_max < 1e-8)  # every saved time exactly on the grid, else the fast precession shows
    assert np.all(ds.steps_accepted > 10) and np.all(ds.rhs_evals == 1 + 6 * (ds.steps_accepted + ds.steps_rejected))


def test_tolerances_and_methods_sweep_in_grids_and_are_recorded():
    text = top_runfile(method=None, dt=None, members=2, t_end=0.5, save_dt=0.1, parameters=FAST_TOP).replace(
        "[parameters]", '[measure]\nerror = true\ntiming = true\nrepeats = 2\n[parameters]') + (
        '[[sweep]]\nmethod = ["rk4", "split4"]\ndt = [1e-3, 5e-4]\n'
        '[[sweep]]\nmethod = ["dopri5"]\nrtol = [1e-6, 1e-9]\natol = [1e-12]\n')
    spec = parse(text)
    assert spec.sweep_points == 6 and spec.n_members == 12
    ds = runner.simulate(spec)
    names = ds.method.attrs["flag_meanings"].split()
    assert names == ["rk4", "split4", "dopri5"]
    methods = np.array(names)[ds.method.values]
    assert list(methods) == ["rk4"] * 4 + ["split4"] * 4 + ["dopri5"] * 4
    np.testing.assert_array_equal(ds.dt.values[:8], [1e-3, 1e-3, 5e-4, 5e-4] * 2)
    assert np.all(np.isnan(ds.dt.values[8:])) and np.all(np.isnan(ds.rtol.values[:8]))
    np.testing.assert_array_equal(ds.rtol.values[8:], [1e-6, 1e-6, 1e-9, 1e-9])
    np.testing.assert_array_equal(ds.steps_accepted.values[:8], [500, 500, 1000, 1000] * 2)
    assert np.all(ds.seconds_per_step > 0) and np.all(np.isfinite(ds.error_max))
    # members of one kernel call share its timing
    assert ds.seconds_per_step.values[0] == ds.seconds_per_step.values[1]
    # fits know each member's method: rk4's prediction differs from split4's (which is the physics)
    rates = top_fit.tilt_decay(ds)
    assert np.all(rates.rate_method.values[4:] == rates.rate_theory.values[4:])


def _one_method(name: str, method: str) -> str:
    """A work-precision run file's text, untimed, with only the [[sweep]] tables of `method` (and only it)."""
    head, *tables = (RUNS / name).read_text().replace("timing = true", "timing = false").split("\n[[sweep]]")
    kept = [re.sub(r"method = \[.*\]", f'method = ["{method}"]', table) for table in tables
            if re.search(rf'method = \[[^]]*"{method}"', table)]
    return head + "".join("\n[[sweep]]" + table for table in kept)


WORK_PRECISION = [("work_precision_top.toml", method) for method in ("euler", "rk4", "split2", "split4", "dopri5")]
WORK_PRECISION += [("work_precision_chain.toml", method)
                   for method in ("euler", "symplectic_euler", "verlet", "yoshida4", "rk4", "dopri5")]


@pytest.mark.parametrize("name, method", WORK_PRECISION)
def test_work_precision_runs_show_each_fixed_step_methods_order(name, method):
    """Each method of a work-precision run file (one test each, so the kernels compile on every worker): at least
    2.7 decades of error, a fixed-step method's order within 0.15, and dopri5's tolerances spanning 8 decades."""
    ds = runner.simulate(parse(_one_method(name, method), name))
    table = fitting.work_precision(ds)
    assert set(table["method"].values) == {method}
    errors = table["error"].values
    assert errors.max() / errors.min() > 500  # at least 2.7 decades each
    if METHODS[method].adaptive:
        assert np.log10(errors.max() / errors.min()) >= 8
        return
    order, used = fitting.convergence_order(table, method)
    assert used >= 4 and order == pytest.approx(METHODS[method].order, abs=0.15), (method, order)


BAD = {
    "rtol <= 0": (dict(method="dopri5", rtol=0.0), "rtol", "> 0"),
    "atol < 0": (dict(method="dopri5", atol=-1e-9), "atol", "> 0"),
    "tolerance to a fixed-step method": (dict(method="rk4", rtol=1e-6), "rtol", "adaptive"),
    "fixed step without dt": (dict(method="rk4", dt=None), "dt", "missing"),
    "unknown method": (dict(method="dopri8"), "method", "unknown method"),
}


@pytest.mark.parametrize("case", BAD)
def test_bad_settings_name_their_key(case):
    top_level, key, words = BAD[case]
    with pytest.raises(SpecError) as error:
        parse(top_runfile(**top_level))
    assert error.value.key == key and words in str(error.value)


ADAPTIVE = top_runfile(method="dopri5", dt=None)
SWEPT_METHOD = top_runfile(method=None, dt=None)


@pytest.mark.parametrize("text, key, words", [
    (ADAPTIVE + '[sweep]\ndt = [1e-3, 1e-4]\n', "sweep.dt", "adaptive"),
    (ADAPTIVE + '[sweep]\nrtol = [1e-6, -1.0]\n', "sweep.rtol", "> 0"),
    (SWEPT_METHOD + '[[sweep]]\nmethod = ["rk4"]\ndt = [1e-3]\nrtol = [1e-6]\n', "sweep[0].rtol", "adaptive"),
    (SWEPT_METHOD + '[[sweep]]\nmethod = ["rk4"]\ndt = [1e-3]\nspin0 = [50.0]\n'
                    '[[sweep]]\nmethod = ["dopri5"]\nrtol = [1e-6]\n', "sweep[1]", "same parameters"),
    (top_runfile() + '[sweep]\ndt = [1e-3]\n', "sweep.dt", "top-level value and a sweep axis"),
], ids=["dt swept for dopri5", "bad rtol axis", "rtol for rk4", "grids sweep different parameters",
        "dt twice"])
def test_bad_sweeps_name_their_key(text, key, words):
    with pytest.raises(SpecError) as error:
        parse(text.replace("spin0 = 60.0\n", "") if "spin0 = [" in text else text)
    assert error.value.key == key and words in str(error.value)


def test_measuring_errors_needs_an_exact_solution(monkeypatch):
    monkeypatch.setattr(top, "exact", None)
    with pytest.raises(SpecError, match=r"measure.error: scene 'top' has no exact solution"):
        parse(top_runfile() + "[measure]\nerror = true\n")


def test_work_precision_command_prints_orders_and_draws(tmp_path):
    import subprocess
    import sys

    out = tmp_path / "wp.nc"
    text = (RUNS / "work_precision_top.toml").read_text().replace("timing = true", "timing = true\nrepeats = 1")
    runner.run(parse(text, "wp.toml"), out, progress=False)
    done = subprocess.run([sys.executable, "-m", "ensemble", "work-precision", str(out), "--charts", str(tmp_path)],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert re.search(r"^rk4: nominal order 4, measured 3\.9\d|^rk4: nominal order 4, measured 4\.0\d", done.stdout,
                     flags=re.M), done.stdout
    assert (tmp_path / "wp_work_precision.png").stat().st_size > 20_000
    bad = subprocess.run([sys.executable, "-m", "ensemble", "work-precision", str(tmp_path / "x.nc")],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1


def test_adaptive_run_launches_once_per_chunk_and_setting(monkeypatch):
    """dopri5 without dt (NaN per member) used to start a launch per member: NaN != NaN split every range."""
    calls = []
    segments = launch.Launch.segments

    def counted(self, *args, **kwargs):
        calls.append(1)
        return segments(self, *args, **kwargs)

    monkeypatch.setattr(launch.Launch, "segments", counted)
    spec = parse(top_runfile(method="dopri5", dt=None, members=150, t_end=0.2, parameters={"c": None},
                             sweep={"c": [1e-4, 2e-4]}))
    ds = runner.simulate(spec, chunk=128)
    chunks, settings = -(-300 // 128), 1
    assert 0 < len(calls) <= chunks * settings and ds.sizes["member"] == 300


def test_a_run_calls_the_kernel_once_per_chunk_and_setting(monkeypatch):
    """Adaptive members without dt (NaN) share one launch: a run's kernel launches number at most its chunks
    times its distinct settings (NaN != NaN once made every member a launch of its own, 1000x slower)."""
    launches = []
    real = launch.Launch.__init__

    def counted(self, *args, **kwargs):
        launches.append(1)
        real(self, *args, **kwargs)

    monkeypatch.setattr(launch.Launch, "__init__", counted)
    spec = parse(top_runfile(method="dopri5", dt=None, members=1024, t_end=0.2))
    runner.simulate(spec, chunk=256)
    assert len(launches) == 4  # 1024 members / 256 per chunk, one setting
    swept = parse(top_runfile(method=None, members=100, t_end=0.2, sweep={"method": ["rk4", "dopri5"]}))
    launches.clear()
    runner.simulate(swept, chunk=128)
    assert len(launches) <= 2 * 2, len(launches)  # 200 members in 2 chunks, 2 settings


# --- the step controller -----------------------------------------------------------------------------------

def test_the_controllers_log2_and_exp2_match_numpy():
    from numba import njit

    from ensemble.engine.blocks import FAST, exp2_of, log2_positive

    @njit(**FAST)  # as the kernels that inline them are compiled
    def both(x, y):
        return [log2_positive(v) for v in x], [exp2_of(v) for v in y]

    rng = np.random.default_rng(5)
    x = np.concatenate([10.0 ** rng.uniform(-307, 308, 20_000), [2.0**-1022, 1.0, np.sqrt(2.0), 2.0, 1e300]])
    y = np.concatenate([rng.uniform(-1000, 1000, 20_000), [-1022.0, -0.5, 0.0, 0.5, 1023.0]])
    logs, powers = (np.array(v) for v in both(x, y))
    np.testing.assert_allclose(logs, np.log2(x), rtol=0, atol=1e-10)
    np.testing.assert_allclose(powers, np.exp2(y), rtol=1e-13)
    np.testing.assert_array_equal(both(x[:2], np.array([-5000.0, 5000.0]))[1], [2.0**-1022, 2.0**1023])  # clipped


def reference_control(step, err, h, time, log2_previous, rejected_last, target, control):
    """The controller of methods.StepControl for one member, in plain Python with math.pow: (time, h, err
    previous, rejected last, err row, counts (accepted, rejected, evaluations), underflowed)."""
    alpha, beta, safety, min_factor, max_factor = control
    if step <= 0.0:
        return time, h, log2_previous, rejected_last, -1.0, (0, 0, 0), False
    previous = 2.0**log2_previous
    if np.isfinite(err) and err <= 1.0:
        factor = safety * max(err, 1e-10) ** -alpha * previous**beta
        factor = min(factor, 1.0) if rejected_last > 0.0 else factor
        factor = min(max_factor, max(min_factor, factor))
        landed = step >= target - time
        return (target if landed else time + step, max(step * factor, h if landed else 0.0),
                np.log2(max(err, 1e-4)), 0.0, err, (1, 0, 6), False)
    new_h = step * (max(min_factor, safety * err**-alpha) if np.isfinite(err) else min_factor)
    if new_h <= 1e-14 * target:
        return time, 0.0, log2_previous, 1.0, -2.0, (0, 1, 6), True
    return time, new_h, log2_previous, 1.0, err, (0, 1, 6), False


def test_control_step_chooses_the_steps_of_its_formula_for_every_kind_of_member():
    from numba import njit

    from ensemble.engine import blocks
    from ensemble.engine.control import control_step

    B, rows = 64, blocks.CONTROL_ROWS
    method = METHODS["dopri5"].control
    control = alpha, beta, safety, min_factor, max_factor = (method.alpha, method.beta, method.safety,
                                                               method.min_factor, method.max_factor)

    @njit(**blocks.FAST)  # as the kernels that inline it are compiled
    def step_all(work, target, counts, status, failure_time):
        control_step(work, 0, B, target, 0, status, failure_time, 6.0, alpha, beta, safety, min_factor,
                     max_factor)
        blocks.counts_out(work, 0, B, counts, 0)

    rng = np.random.default_rng(11)
    target = 1.0
    for trial in range(20):
        step = np.where(rng.random(B) < 0.2, 0.0, 10.0 ** rng.uniform(-17, -1, B))
        err = 10.0 ** rng.uniform(-12, 3, B)
        err[rng.random(B) < 0.1] = np.nan
        err[rng.random(B) < 0.05] = np.inf
        err[rng.random(B) < 0.05] = 0.0
        h = 10.0 ** rng.uniform(-4, -1, B)
        time = np.where(rng.random(B) < 0.3, target - step * rng.uniform(0.5, 1.0, B), rng.uniform(0, 0.9, B))
        log2_previous = np.log2(10.0 ** rng.uniform(-4, 0, B))
        rejected_last = (rng.random(B) < 0.3).astype(float)
        work = np.zeros(rows * B)
        for row, values in ((blocks.STEP, step), (blocks.ERR, err), (blocks.H, h), (blocks.TIME, time),
                            (blocks.LOG2_ERR_PREVIOUS, log2_previous), (blocks.REJECTED_LAST, rejected_last)):
            work[row * B:(row + 1) * B] = values
        counts, status, failure_time = np.zeros((3, B)), np.zeros(B), np.full(B, np.nan)
        step_all(work, target, counts, status, failure_time)
        rows_of = work.reshape(rows, B)
        for j in range(B):
            want = reference_control(step[j], err[j], h[j], time[j], log2_previous[j], rejected_last[j], target,
                                     control)
            got = (rows_of[blocks.TIME, j], rows_of[blocks.H, j], rows_of[blocks.LOG2_ERR_PREVIOUS, j],
                   rows_of[blocks.REJECTED_LAST, j], rows_of[blocks.ERR, j])
            np.testing.assert_allclose(got, want[:5], rtol=1e-9, atol=0, equal_nan=True,
                                       err_msg=f"trial {trial}, member {j}")
            np.testing.assert_array_equal(counts[:, j], want[5])
            assert (status[j] == 2) == want[6] and (failure_time[j] == time[j]) == want[6]


def test_timed_cost_grows_in_proportion_to_the_steps_whatever_the_members(monkeypatch):
    """[measure] timing times every point in one configuration (TIMED_KERNEL_BLOCKS blocks, calls of at least
    TIMED_SECONDS), so that seconds_per_step x steps grows 100x for 100x the steps (issue 50: it grew 150x to
    190x on a 3-mass chain with 2 members, the timed member count changing with the steps). Checked against a
    clock on which a call costs 1 ms, a member 2 us, each member's first 200 steps 5 ns more each, and a
    member-step 3 ns times (1 + 1 / blocks in the call). Real kernel costs are measured by the benchmarks."""
    from types import SimpleNamespace

    clock = [0.0]
    real_run = launch.Launch.run
    spec = parse(top_runfile(members=2))
    block = launch.layout(spec.model, METHODS["rk4"], spec.constants).block

    def costed(self, *args, **kwargs):
        real_run(self, *args, **kwargs)
        steps = self.outcome().counts[0] + self.outcome().counts[1]  # per member
        clock[0] += 1e-3 + 2e-6 * self.members + 5e-9 * float(np.minimum(steps, 200).sum()) + 3e-9 * float(
            steps.sum()) * (1 + 1 / -(-self.members // block))

    monkeypatch.setattr(launch.Launch, "run", costed)
    monkeypatch.setattr(records, "time", SimpleNamespace(perf_counter=lambda: clock[0]))
    step = 3e-9 * (1 + 1 / records.TIMED_KERNEL_BLOCKS)
    cost = {}
    for t_end, members in ((0.08, 2), (8.0, 2), (0.08, 3000)):
        spec = parse(top_runfile(t_end=t_end, save_dt=t_end / 4, members=members))
        outcome, seconds = runner.integrate(spec, METHODS["rk4"], members_table(spec), repeats=2)
        assert outcome.counts[0][0] == round(t_end / 1e-3)
        assert seconds == pytest.approx(step, rel=0.2), (t_end, members)  # calls long enough for the fixed costs
        cost[t_end, members] = seconds * outcome.counts[0][0]
    assert cost[8.0, 2] / cost[0.08, 2] == pytest.approx(100, rel=0.02)
    assert cost[0.08, 3000] == pytest.approx(cost[0.08, 2], rel=0.02)
