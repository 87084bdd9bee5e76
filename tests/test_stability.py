"""Where methods fail: failing members flagged, measured growth and limits against linear theory."""
from __future__ import annotations

from pathlib import Path

import netCDF4
import numpy as np
import pytest

from ensemble import cli, fitting, records, runner, stability
from ensemble.engine import launch
from ensemble.methods import METHODS
from ensemble.scenes import chain, top
from ensemble.spec import load, members_table, parse

from .conftest import top_runfile
from .test_analysis import command

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def chain_scan():
    return runner.simulate(load(ROOT / "runs" / "stability_chain.toml"))


@pytest.fixture(scope="module")
def top_scan():
    return runner.simulate(load(ROOT / "runs" / "stability_top.toml"))


def limits(ds) -> dict[tuple[str, str], dict]:
    return {(row["method"], row["axis"]): row for row in stability.stability_limits(stability.stability_map(ds))}


# --- theory ------------------------------------------------------------------------------------------------

def test_theoretical_limits_are_the_known_ones():
    def chain_limit(method):
        return stability.theoretical_limit(lambda x: chain.axis_growth(METHODS[method], "h omega_max", x))

    def top_limit(method, axis):
        return stability.theoretical_limit(lambda x: top.axis_growth(METHODS[method], axis, x))

    assert chain_limit("verlet") == pytest.approx(2.0, rel=1e-9)
    assert chain_limit("symplectic_euler") == pytest.approx(2.0, rel=1e-9)
    assert chain_limit("rk4") == pytest.approx(2 * np.sqrt(2), rel=1e-9)
    assert chain_limit("yoshida4") == pytest.approx(1.573, abs=5e-4)
    assert chain_limit("euler") == 0.0 and top_limit("euler", "h Omega") == 0.0
    assert top_limit("rk4", "h Omega") == pytest.approx(2 * np.sqrt(2), rel=1e-9)
    assert top_limit("euler", "h c/lambda1") == pytest.approx(2.0, rel=1e-9)
    # rk4 on y' = -r y: R(-x) = 1 crosses where 1 - x/2 + x^2/6 - x^3/24 = 0
    cubic = np.roots([-1 / 24, 1 / 6, -1 / 2, 1])
    assert top_limit("rk4", "h c/lambda1") == pytest.approx(cubic[np.isreal(cubic)].real[0], rel=1e-9)
    assert top_limit("split2", "h Omega") == top_limit("split4", "h c/lambda1") == np.inf


def test_one_step_map_of_verlet_past_its_limit():
    z = np.array([2.01, 2.5, 3.0])
    trace = 2 - z**2  # of the map of x'' = -omega^2 x over a step, determinant 1
    larger = np.abs(trace - np.sqrt(trace**2 - 4)) / 2
    np.testing.assert_allclose(chain.axis_growth(METHODS["verlet"], "h omega_max", z), larger, rtol=1e-12)


def test_measured_growth_fits_the_later_samples_and_stops_at_failure():
    t = np.arange(40.0)
    growing = 3e-3 * 1.2**t + 5e-3 * 0.5**t  # a damped part that fades: the fit must not see it
    growing[30:] = np.nan  # failed at sample 30
    decaying = 0.9**t
    decaying[25:] = 0.0  # reached zero
    amplitudes = np.stack([growing, decaying])[:, None]  # (2 members, 1 motion, 40 samples)
    # the fade leaves 3e-6 of the amplitude at sample 15: the fitted factor is off by about 1e-7
    np.testing.assert_allclose(records.measured_growth(amplitudes, t, np.ones(2)), [1.2, 0.9], rtol=1e-6)
    # the fastest of two motions, and per step of 0.5 s
    two = np.stack([1.1 ** t, 1.3 ** t])[None]  # (1 member, 2 motions, 40 samples)
    assert records.measured_growth(two, t, np.array([0.5])) == pytest.approx(np.sqrt(1.3), rel=1e-12)


def test_the_compiled_growth_fit_equals_a_numpy_polyfit_member_by_member():
    """records.measured_growth (compiled) against np.polyfit over each motion's window: the second half of the
    samples before the first one that is not above DECAY_FLOOR times the start (failed, NaN, infinite, zero)."""
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 4.0, 41)
    a = np.exp(np.cumsum(rng.normal(0.0, 0.3, (2, 41, 60)), axis=1))
    a[0, 30:, :10] = np.nan
    a[1, 17:, 10:20] = np.inf
    a[0, 9:, 20:30] = 1e-210 * a[0, 0, 20:30]
    a[1, :, 30:35] = 0.0
    a[:, 1:, 35:40] = np.nan  # one sample: no fit
    step = rng.uniform(0.01, 0.1, 60)
    expected = np.full(60, np.nan)
    for j in range(60):
        for m in range(2):
            usable = (a[m, :, j] > max(records.DECAY_FLOOR * a[m, 0, j], records.SUBNORMAL)) & (a[m, :, j] < np.inf)
            count = int(np.argmin(usable)) if not usable.all() else len(t)
            start = max(min(count // 2, count - 2), 0)
            if count - start >= 2:
                slope = np.polyfit(t[start:count], np.log(a[m, start:count, j]), 1)[0]
                expected[j] = np.fmax(expected[j], np.exp(slope * step[j]))
    np.testing.assert_allclose(records.measured_growth(a.transpose(2, 0, 1), t, step), expected, rtol=1e-10)
    assert np.isnan(expected[35:40]).all() and np.isfinite(expected[:35]).all()


# --- measured limits -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("method", ["symplectic_euler", "verlet", "rk4", "yoshida4"])
def test_measured_chain_limits_are_within_2_percent_of_theory(chain_scan, method):
    row = limits(chain_scan)[(method, "h omega_max")]
    assert row["measured"] == pytest.approx(row["theory"], rel=0.02)
    assert row["last_stable"] < row["theory"] < row["first_growing"]


@pytest.mark.parametrize("axis", ["h Omega", "h c/lambda1"])
def test_measured_top_rk4_limits_are_within_2_percent_of_theory(top_scan, axis):
    row = limits(top_scan)[("rk4", axis)]
    expected = 2 * np.sqrt(2) if axis == "h Omega" else 2.785
    assert row["measured"] == pytest.approx(expected, rel=0.02)


def test_euler_grows_on_every_undamped_oscillation(chain_scan, top_scan):
    for ds, axis in ((chain_scan, "h omega_max"), (top_scan, "h Omega")):
        points = stability.stability_map(ds)
        chosen = (points["method"].values == "euler") & (points["axis"].values == axis)
        x, growth = points["x"].values[chosen], points["growth"].values[chosen]
        assert chosen.sum() >= 7 and x.min() <= 0.05
        np.testing.assert_allclose(growth, np.sqrt(1 + x**2), rtol=1e-5)  # |1 + i x| per step
        assert np.all(growth > 1) and limits(ds)[("euler", axis)]["measured"] == 0.0


def test_methods_that_never_fail_on_the_top(top_scan):
    for method in ("split2", "split4"):
        for axis in top.STABILITY_AXES:
            assert limits(top_scan)[(method, axis)]["measured"] == np.inf
    points = stability.stability_map(top_scan)
    dopri5 = points["method"].values == "dopri5"
    assert np.all(points["status"].values[dopri5] == 0)  # its step control keeps it stable


def test_measured_growth_agrees_with_theory_across_the_scans(chain_scan, top_scan):
    for ds in (chain_scan, top_scan):
        points = stability.stability_map(ds)
        fixed = ~np.isin(points["method"].values, ["dopri5"]) & np.isfinite(points["growth"].values)
        np.testing.assert_allclose(points["growth"].values[fixed], points["growth_theory"].values[fixed], rtol=1e-3)


def test_energy_drift_over_the_long_run(chain_scan):
    drift = stability.energy_drift(chain_scan)
    points = stability.stability_map(chain_scan)

    def member(method, x):
        return int(points["member"].values[(points["method"].values == method) & np.isclose(points["x"].values, x)][0])

    for method in ("verlet", "symplectic_euler", "yoshida4"):  # bounded: the second half no worse than the first
        d = drift.sel(member=member(method, 0.5)).values
        assert np.all(np.isfinite(d)) and d[1500:].max() < 1.01 * d[1:1500].max() < 0.5
    rk4 = chain_scan["energy"].sel(member=member("rk4", 0.5)).values
    steps = np.arange(rk4.size)
    # rk4 loses energy slowly, by |R(0.5 i)|^2 per step
    np.testing.assert_allclose(rk4 / rk4[0], np.abs(chain.step_eigenvalue(METHODS["rk4"], 0.5, 1.0)) ** (2 * steps),
                               rtol=1e-6)
    assert 0.2 < rk4[-1] / rk4[0] < 0.9
    euler = drift.sel(member=member("euler", 0.05)).values
    assert np.all(np.diff(euler[1:]) > 0) and euler[-1] > 100


# --- failing members ---------------------------------------------------------------------------------------

def verlet_chain_text(omega_max: list[float], members: int, **extra) -> str:
    head = "\n".join(f"{k} = {v}" for k, v in extra.items())
    return f"""
scene = "chain"
method = "verlet"
dt = 1.0
t_end = 400.0
save_dt = 4.0
members = {members}
seed = 3
{head}
[measure]
growth = true
[parameters]
n = 4
m = {{ uniform = [0.5, 2.0] }}
k = {{ uniform = [0.5, 2.0] }}
x0 = {{ mode = 4, amplitude = 0.01 }}
[sweep]
omega_max = {omega_max}
"""


def test_ten_percent_past_the_limit_are_flagged_and_the_rest_unaffected(tmp_path, capsys):
    scan = [0.1 * i for i in range(1, 19)] + [2.05, 2.5]  # 2 of 20 points past verlet's limit h omega = 2
    path = tmp_path / "scan.toml"
    path.write_text(verlet_chain_text(scan, 5))
    out = tmp_path / "scan.nc"
    assert cli.main(["run", str(path), "-o", str(out)]) == 0
    assert "10 of 100 members failed (10 blew up, 0 step size underflow)" in capsys.readouterr().out
    with netCDF4.Dataset(out) as nc:
        assert np.isnan(nc["energy"].getncattr("_FillValue")) and np.isnan(nc["failure_time"].getncattr("_FillValue"))
        assert list(nc["status"].flag_values) == [0, 1, 2, 3]
    ds = runner.simulate(load(path))
    past = ds["omega_max"].values > 2
    assert past.sum() == 10
    np.testing.assert_array_equal(ds["status"].values, np.where(past, 1, 0))
    assert np.all(np.isnan(ds["failure_time"].values[~past]))
    for i in np.flatnonzero(past):  # NaN from the failure on, finite before, fewer steps counted
        failed = ds["t"].values >= ds["failure_time"].values[i]
        assert np.all(np.isnan(ds["x"].values[i, failed])) and np.all(np.isfinite(ds["x"].values[i, ~failed]))
        assert ds["steps_accepted"].values[i] == ds["failure_time"].values[i]  # dt = 1 s
    # the members that did not fail are bit for bit those of a run without the failing ones
    path.write_text(verlet_chain_text(scan[:-2], 5))
    alone = runner.simulate(load(path))
    np.testing.assert_array_equal(ds["x"].values[~past], alone["x"].values)
    np.testing.assert_array_equal(ds["growth_per_step"].values[~past], alone["growth_per_step"].values)
    assert "second half of its samples" in ds["growth_per_step"].attrs["comment"]


def test_growth_is_measured_only_when_the_run_file_asks_and_the_map_says_how(tmp_path):
    """Without `[measure] growth = true` a run neither fits nor stores growth_per_step, and stability_map says in
    one line what to add; every other variable is bit for bit the same."""
    path = tmp_path / "scan.toml"
    path.write_text(verlet_chain_text([0.5, 2.5], 2))
    asked = runner.simulate(load(path))
    path.write_text(verlet_chain_text([0.5, 2.5], 2).replace("[measure]\ngrowth = true\n", ""))
    plain = runner.simulate(load(path))
    assert "growth_per_step" in asked and "growth_per_step" not in plain
    assert set(asked.data_vars) - set(plain.data_vars) == {"growth_per_step"}
    for name in plain.data_vars:
        np.testing.assert_array_equal(plain[name].values, asked[name].values)
    with pytest.raises(fitting.FitError, match=r"add `\[measure\] growth = true` to its run file"):
        stability.stability_map(plain)


def test_growth_of_a_chain_started_in_its_highest_mode_matches_theory_within_1_percent(tmp_path):
    for method, scan in (("verlet", [2.05, 2.3, 3.0]), ("euler", [0.3, 1.0]), ("rk4", [2.9, 3.2]),
                         ("yoshida4", [1.6, 2.0])):
        path = tmp_path / f"{method}.toml"
        path.write_text(verlet_chain_text(scan, 2).replace('"verlet"', f'"{method}"')
                        .replace("save_dt = 4.0", "save_dt = 1.0").replace("t_end = 400.0", "t_end = 200.0"))
        ds = runner.simulate(load(path))
        h = np.ones(ds.sizes["member"])
        values = {name: ds[name].values for name in ("m", "k")}
        expected = chain.step_growth(METHODS[method], values, {"boundary": "fixed"}, h)
        highest = chain.axis_growth(METHODS[method], "h omega_max", ds["omega_max"].values)
        np.testing.assert_allclose(expected, highest, rtol=1e-12)  # past the limit the highest mode grows fastest
        np.testing.assert_allclose(ds["growth_per_step"].values, expected, rtol=0.01)


def test_a_non_finite_start_fails_at_once_and_spares_its_block():
    values = {"m": np.ones((3, 4)), "k": np.ones((3, 5)), "x0": np.full((3, 4), 0.01), "v0": np.zeros((3, 4))}
    values["x0"][1, 2] = np.nan
    out = launch.integrate(chain, METHODS["verlet"], values, {"n": 4, "boundary": "fixed"}, n_save=4, save_dt=0.5,
                           dt=0.1)
    np.testing.assert_array_equal(out.status, [0, 1, 0])
    assert out.failure_time[1] == 0.0 and out.counts[0, 1] == 0 and np.all(np.isnan(out.samples[1:, :, 1]))
    np.testing.assert_array_equal(out.samples[:, :, 0], out.samples[:, :, 2])
    assert np.all(np.isfinite(out.samples[:, :, [0, 2]]))


def test_a_step_size_underflow_is_status_2():
    # no step can meet rtol = atol = 1e-300: the step shrinks until it underflows
    ds = runner.simulate(parse(top_runfile(method="dopri5", dt=None, atol=1e-300, members=2,
                                           sweep={"rtol": [1e-300, 1e-6]})))
    impossible = ds["rtol"].values == 1e-300
    np.testing.assert_array_equal(ds["status"].values, np.where(impossible, 2, 0))
    assert np.all(ds["failure_time"].values[impossible] == 0.0)  # no step was ever accepted
    assert np.all(np.isnan(ds["omega"].values[impossible][:, 1:]))
    assert np.all(np.isfinite(ds["omega"].values[~impossible]))


# --- run files and the chart -------------------------------------------------------------------------------

def test_omega_max_scales_the_springs(tmp_path):
    ds = runner.simulate(parse(verlet_chain_text([0.5, 1.7], 3)))
    omega, shapes = chain.normal_modes(ds["m"].values, ds["k"].values)
    np.testing.assert_allclose(omega[:, -1], ds["omega_max"].values, rtol=1e-12)
    unscaled = parse(verlet_chain_text([0.5, 1.7], 6).replace("omega_max = [0.5, 1.7]", ""))
    assert "omega_max" not in runner.simulate(unscaled)  # optional: absent unless given
    # the same draws, scaled: the mode shapes stay
    np.testing.assert_allclose(shapes, chain.normal_modes(ds["m"].values, members_table(unscaled)["k"])[1], atol=1e-12)


@pytest.mark.parametrize("text, key", [
    (verlet_chain_text([0.5, -1.0], 1), "sweep.omega_max"),
    (verlet_chain_text([0.5], 1).replace("n = 4", 'n = 1\nboundary = "periodic"')
     .replace("x0 = { mode = 4, amplitude = 0.01 }", "x0 = 0.01"), "parameters.n"),  # a ring of one mass
    (verlet_chain_text([0.5], 1, blowup_factor=1.0), "blowup_factor"),
    (verlet_chain_text([0.5], 1, blowup_factor='"big"'), "blowup_factor"),
])
def test_bad_stability_input_is_one_line_naming_the_key(tmp_path, capsys, text, key):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    assert cli.main(["run", str(path), "-o", str(tmp_path / "bad.nc")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{key}:" in err[0]
    assert not list(tmp_path.glob("bad.nc*"))


def test_stability_command_prints_limits_and_draws(tmp_path, chain_scan):
    result = tmp_path / "stability_chain.nc"
    chain_scan.to_netcdf(result)
    done = command("stability", result, "--check", "--charts", tmp_path)
    assert done.returncode == 0, done.stderr
    assert [line.split()[0] for line in done.stdout.splitlines() if line.endswith("yes")] == [
        "euler", "symplectic_euler", "verlet", "rk4", "yoshida4"]
    for chart in ("map", "energy"):
        assert (tmp_path / f"stability_chain_stability_{chart}.png").stat().st_size > 10_000
    missing = command("stability", tmp_path / "none.nc")
    assert missing.returncode == 2 and len(missing.stderr.strip().splitlines()) == 1
