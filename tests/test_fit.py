"""Fits of tilt decay rates and normal-mode frequencies against closed forms and method theory."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from ensemble import fitting, runner, spec
from ensemble.methods import METHODS
from ensemble.scenes import chain
from ensemble.scenes.chain import fits as chain_fit
from ensemble.scenes.top import fits as top_fit

from .conftest import top_runfile

RUNS = Path(__file__).resolve().parent.parent / "runs"


def simulate(text: str):
    return runner.simulate(spec.parse(text, "test.toml"))


def chain_runfile(method="exact", dt=0.05, t_end=100.0, save_dt=0.1, members=4, seed=5, n=2, m=1.0, k=1.0,
                  x0="{ uniform = [0.05, 0.1] }", noise=None) -> str:
    text = (f'scene = "chain"\nmethod = "{method}"\ndt = {dt}\nt_end = {t_end}\nsave_dt = {save_dt}\n'
            f'members = {members}\nseed = {seed}\n[parameters]\nn = {n}\nboundary = "fixed"\nm = {m}\nk = {k}\n'
            f'x0 = {x0}\n')
    if noise:
        text += f"[observe]\nnoise = {{ x = {noise} }}\n"
    return text


def small(path: Path, members: int) -> str:
    """A run file from runs/ with fewer members per sweep point."""
    return re.sub(r"^members = \d+", f"members = {members}", path.read_text(), flags=re.M)


# ---------------------------------------------------------------- method theory


def test_rk_stability_function_is_the_taylor_polynomial():
    z = np.array([-2.785, 0.3j, -0.5 + 1j, 2j * np.sqrt(2)])
    assert np.allclose(METHODS["rk4"].tableau.stability(z), 1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24, atol=1e-15)
    assert np.allclose(METHODS["euler"].tableau.stability(z), 1 + z, atol=1e-15)


def test_splitting_eigenvalues_give_the_verlet_frequency():
    omega, h = np.array([0.5, 1.0, 1.9]), 1.0
    for method in ("verlet", "symplectic_euler"):
        step = chain.step_eigenvalue(METHODS[method], omega, h)
        assert np.allclose(np.abs(step), 1.0, atol=1e-14)
        assert np.allclose(np.angle(step) / h, 2 / h * np.arcsin(omega * h / 2), rtol=1e-14)
    assert np.allclose(np.angle(chain.step_eigenvalue(METHODS["exact"], omega, h)), omega * h)


# ---------------------------------------------------------------- tops


def test_exact_tilt_decay_reproduces_the_course_rate():
    ds = simulate(top_runfile(method="exact", t_end=30.0, members=3, parameters={"c": None}, sweep={"c": [5e-5, 2e-4]}))
    fitted = top_fit.tilt_decay(ds)
    assert np.allclose(fitted.rate, fitted.rate_theory, rtol=1e-8)
    assert np.allclose(fitted.rate_theory.values, ds.c.values * (1 / 1e-3 - 1 / 2e-3))
    assert fitted.attrs["members_failed"] == 0


def test_prolate_tilt_grows_as_a_negative_rate():
    ds = simulate(small(RUNS / "prolate.toml", 3))
    fitted = top_fit.tilt_decay(ds)
    assert np.all(fitted.rate < 0)
    assert np.allclose(fitted.rate, -0.1, rtol=1e-8)


def test_euler_shows_its_own_tilt_rate_not_the_physics():
    # W h = 0.06 per step: euler multiplies the transverse rates by |1 + h (i W - r1)| > 1 each step.
    ds = simulate(top_runfile(method="euler", dt=1e-3, t_end=5.0, members=2))
    fitted = top_fit.tilt_decay(ds)
    assert np.all(fitted.rate_method < 0) and np.all(fitted.rate_theory > 0)
    assert np.allclose(fitted.rate, fitted.rate_method, rtol=2e-3)


def test_noisy_tilt_error_bars_are_calibrated():
    text = small(RUNS / "aerobie_noisy.toml", 150)
    fitted = top_fit.tilt_decay(simulate(text))
    z = fitted.z.values
    assert np.all(np.isfinite(z)) and z.size == 450
    assert stats.kstest(z, "norm").pvalue > 0.01
    for point, rate in enumerate([0.025, 0.05, 0.1]):
        chosen = fitted.rate.where(fitted.sweep_point == point, drop=True)
        assert abs(float(chosen.mean()) - rate) < 5 * float(chosen.std()) / np.sqrt(chosen.size)


def test_noisy_tilt_is_not_fitted_below_the_noise():
    ds = simulate(top_runfile(method="exact", t_end=200.0, save_dt=0.5, members=2, parameters={"c": 2e-4})
                  + '[observe]\nnoise = { tilt = 0.002 }\n')
    fitted = top_fit.tilt_decay(ds)
    model = np.arctan(np.tan(ds.tilt0.values[:, None]) * np.exp(-0.1 * ds.t.values[None, :]))
    assert np.all(fitted.samples_used.values <= (model > top_fit.NOISE_WINDOW * 0.002).sum(axis=1))
    assert np.all(fitted.samples_used.values < ds.sizes["t"] / 2)


# ---------------------------------------------------------------- chains


def test_course_two_mass_chain_frequency():
    """Started from random displacements, both modes ring at Verlet's (2/h) asin(w h / 2), w^2 = k/m and 3k/m."""
    fitted = chain_fit.mode_frequencies(simulate(small(RUNS / "two_mass.toml", 2)))
    verlet = 2 / 1e-3 * np.arcsin(np.array([1.0, np.sqrt(3.0)]) * 1e-3 / 2)
    assert np.allclose(fitted.frequency, verlet, rtol=1e-8)
    assert np.allclose(fitted.frequency_method, verlet, rtol=1e-14)
    assert np.allclose(fitted.frequency_theory.values, [1.0, np.sqrt(3.0)])
    assert np.all(fitted.excited == 1)


def test_a_mode_start_excites_that_mode_alone():
    """Started in mode 2, the start's amplitude in mode 1 is rounding (not excited) and mode 1 is not found."""
    text = small(RUNS / "two_mass.toml", 2).replace("x0 = { normal = [0.0, 0.1] }",
                                                    "x0 = { mode = 2, amplitude = 0.1 }")
    fitted = chain_fit.mode_frequencies(simulate(text))
    assert np.all(np.isnan(fitted.frequency.sel(mode=1))) and np.all(fitted.excited.sel(mode=1) == 0)
    assert np.all(fitted.excited.sel(mode=2) == 1)
    # mode 2's shape is (1, -1) / sqrt(2 m) (M-normalized), so amplitude 0.1 at each mass is 0.1 sqrt(2)
    np.testing.assert_allclose(fitted.mode_amplitude.sel(mode=2), 0.1 * np.sqrt(2.0), rtol=1e-12)


def test_uniform_32_chain_frequencies_from_data_alone():
    ds = simulate(small(RUNS / "uniform32.toml", 1).replace('method = "yoshida4"', 'method = "exact"'))
    fitted = chain_fit.mode_frequencies(ds)
    j = np.arange(1, 33)
    formula = 2 * np.sin(j * np.pi / 66)
    assert np.allclose(fitted.frequency.values, formula, rtol=1e-8)
    assert np.allclose(fitted.frequency_theory.values, formula, rtol=1e-12)


def test_disordered_verlet_chain_shows_the_verlet_frequencies():
    """At dt = 0.01 s (the run file takes 1e-3 s, where Verlet's shift is below the check's tolerance)."""
    text = small(RUNS / "disordered.toml", 2).replace("dt = 1e-3 ", "dt = 0.01 ")
    fitted = chain_fit.mode_frequencies(simulate(text))
    assert np.allclose(fitted.frequency, fitted.frequency_method, rtol=1e-8)
    assert not np.allclose(fitted.frequency, fitted.frequency_theory, rtol=1e-6)  # the integrator effect shows


def test_noisy_chain_error_bars_are_calibrated():
    text = chain_runfile(members=200, x0="{ uniform = [-0.1, 0.1] }", noise=0.01)
    fitted = chain_fit.mode_frequencies(simulate(text))
    for mode in (1, 2):
        z = fitted.z.sel(mode=mode).values
        z = z[np.isfinite(z)]
        assert z.size > 150
        assert stats.kstest(z, "norm").pvalue > 0.01


# ---------------------------------------------------------------- bad input


def test_wrong_scene_missing_variables_and_short_records_are_errors():
    top_ds = simulate(top_runfile(members=1, t_end=1.0))
    with pytest.raises(fitting.FitError, match="needs a chain result"):
        chain_fit.mode_frequencies(top_ds)
    with pytest.raises(fitting.FitError, match="lacks tilt"):
        top_fit.tilt_decay(top_ds.drop_vars("tilt"))
    with pytest.raises(fitting.FitError, match="at least 5"):
        top_fit.tilt_decay(top_ds.isel(t=slice(0, 3)))


def test_members_that_cannot_be_fitted_are_counted_not_averaged():
    ds = simulate(chain_runfile(members=3))
    ds["x"][1, 10] = np.nan
    fitted = chain_fit.mode_frequencies(ds)
    assert np.all(np.isnan(fitted.frequency[1])) and np.all(np.isfinite(fitted.frequency[[0, 2]]))
    assert fitted.attrs["members_failed"] == 1
    top_ds = simulate(top_runfile(members=2, t_end=1.0))
    top_ds["tilt"][0] = np.nan
    fitted = top_fit.tilt_decay(top_ds)
    assert np.isnan(fitted.rate[0]) and np.isfinite(fitted.rate[1]) and fitted.attrs["members_failed"] == 1


# ---------------------------------------------------------------- observation noise


def test_noise_is_seeded_per_member_and_recorded(tmp_path):
    text = chain_runfile(members=5, t_end=2.0, noise=0.01)
    parsed = spec.parse(text, "noise.toml")
    whole, chunked = tmp_path / "whole.nc", tmp_path / "chunked.nc"
    runner.run(parsed, whole, progress=False)
    runner.run(parsed, chunked, chunk=2, progress=False)
    import xarray as xr

    a, b = xr.load_dataset(whole), xr.load_dataset(chunked)
    assert np.array_equal(a.x.values, b.x.values)
    assert a.x.attrs["observation_noise_stddev"] == 0.01
    clean = simulate(chain_runfile(members=5, t_end=2.0))
    residual = (a.x - clean.x).values
    assert 0.008 < residual.std() < 0.012 and abs(residual.mean()) < 0.003
    assert np.array_equal(clean.v.values, a.v.values)  # only x is noisy


@pytest.mark.parametrize("observe, problem", [
    ("noise = { x = -0.1 }", "observe.noise.x: must be a standard deviation in 0..1e+150"),
    ("noise = { x = 1e308 }", "observe.noise.x: must be a standard deviation in 0..1e+150 (a larger one turns"),
    ("noise = { y = 0.1 }", "observe.noise.y: unknown key"),
    ("noise = { x = 0.1 }\nnoisy = 1", "observe.noisy: unknown key"),
])
def test_bad_noise_is_refused(observe, problem):
    with pytest.raises(spec.SpecError, match=re.escape(problem)):
        spec.parse(chain_runfile() + f"[observe]\n{observe}\n", "bad.toml")


def test_noise_on_an_unsaved_variable_is_refused():
    text = chain_runfile().replace('seed = 5\n', 'seed = 5\nsave = ["v"]\n') + "[observe]\nnoise = { x = 0.1 }\n"
    with pytest.raises(spec.SpecError, match="observe.noise.x: 'x' is not saved"):
        spec.parse(text, "bad.toml")
