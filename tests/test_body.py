"""The free rigid body: the elliptic closed form against DOP853, conservation, linear theory, the kernels'
orders, the symmetric body against the top, and bad input."""
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from scipy.integrate import solve_ivp

from ensemble import fitting, runner
from ensemble.engine import launch
from ensemble.methods import METHODS
from ensemble.scenes import body, top
from ensemble.scenes.body import fits as body_fit
from ensemble.spec import parse
from tests.conftest import refused

RUNS = Path(__file__).resolve().parent.parent / "runs"

RACKET = {"lambda1": 1.0, "lambda2": 2.0, "lambda3": 2.5}  # kg m2: three different moments, a valid body


def members(n=6, seed=1, **fixed):
    """n members with moments drawn inside the triangle inequality and random starts."""
    rng = np.random.default_rng(seed)
    lam = rng.uniform(1.0, 2.0, (3, n))  # any three values in [1, 2] obey lambda_i <= lambda_j + lambda_k
    values = {"lambda1": lam[0], "lambda2": lam[1], "lambda3": lam[2], "c": np.zeros(n),
              "spin0": rng.uniform(5, 20, n), "tilt0": rng.uniform(0, np.pi, n), "azimuth0": rng.uniform(0, 6.3, n),
              "spin_axis": np.full(n, 3.0)}
    values.update({k: np.broadcast_to(np.asarray(v, dtype=float), (n,)).copy() for k, v in fixed.items()})
    return values


def euler_rhs(lam, c=0.0):
    l1, l2, l3 = lam
    return lambda _, w: [((l2 - l3) * w[1] * w[2] - c * w[0]) / l1, ((l3 - l1) * w[2] * w[0] - c * w[1]) / l2,
                         ((l1 - l2) * w[0] * w[1] - c * w[2]) / l3]


@pytest.mark.parametrize("spin_axis", [1, 2, 3])
def test_closed_form_matches_dop853(spin_axis):
    """Random bodies and starts about each axis (both branches, L^2 above and below 2 E lambda_mid, and odd and
    even axis orders), each over 20 of its periods (20 flips, or 20 wobbles), to 1e-10 of the spin. The reference
    runs at scipy's tightest rtol, 2.5e-14: at rtol 1e-12 DOP853 itself drifts up to 1e-9 off over 20 periods
    (measured against rtol 1e-13 and 2.5e-14), while the closed form agrees with the tighter runs to 9e-12."""
    values, constants = members(8, seed=spin_axis, spin_axis=spin_axis), {}
    w0 = body.initial_state(values, constants)
    periods = body.flip_period(values, constants)
    for m in range(8):
        t = np.linspace(0.0, 20 * periods[m], 2001)
        exact = body.exact({name: v[m:m + 1] for name, v in values.items()}, constants, t)[:, :, 0]
        lam = [values[f"lambda{i}"][m] for i in (1, 2, 3)]
        ref = solve_ivp(euler_rhs(lam), (0, t[-1]), w0[:, m], method="DOP853", rtol=2.5e-14,
                        atol=2.5e-14 * values["spin0"][m], t_eval=t).y
        np.testing.assert_allclose(exact.T, ref, rtol=0, atol=1e-10 * values["spin0"][m])


def test_closed_form_keeps_energy_and_angular_momentum():
    values, constants = members(20, seed=4, spin_axis=2), {}
    w = body.exact(values, constants, np.linspace(0, 50, 101)).transpose(2, 0, 1)  # (members, t, 3)
    lam = np.stack([values[f"lambda{i}"] for i in (1, 2, 3)]).T[:, None, :]
    for conserved in (body.kinetic_energy(w, lam), body.angular_momentum(w, lam)):
        # measured: 1.7e-14 at worst over 50 s (ellipj is given u reduced modulo its period 4 K)
        np.testing.assert_allclose(conserved, np.broadcast_to(conserved[:, :1], conserved.shape), rtol=1e-13)


def test_intermediate_axis_tilt_grows_at_sigma():
    """About the middle moment a small tilt grows as exp(sigma t), sigma = spin0 sqrt((lambda3 - lambda2)(lambda2
    - lambda1) / (lambda1 lambda3)): rk4 at h sigma = 4.5e-3 (its error ~ (h sigma)^4 / 120), fitted where the
    decaying part has died (sigma t > 9) and the tilt is still below 1e-4."""
    values = members(1, **RACKET, spin0=10.0, tilt0=1e-12, azimuth0=0.7, spin_axis=2)
    sigma = 10.0 * np.sqrt((2.5 - 2.0) * (2.0 - 1.0) / (1.0 * 2.5))
    assert body.growth_rate(values, {})[0] == pytest.approx(sigma, rel=1e-12)
    h, steps = 1e-3, 100
    samples = run("rk4", values, {}, h, steps, n_save=41)
    t = np.arange(41) * h * steps
    tilt = body.tilt(samples.transpose(1, 0, 2), 2)[:, 0]
    fitted = (sigma * t > 9) & (tilt < 1e-4)
    assert fitted.sum() >= 10
    slope = np.polyfit(t[fitted], np.log(tilt[fitted]), 1)[0]
    assert slope == pytest.approx(sigma, rel=1e-6)


@pytest.mark.parametrize("axis, i, j, k", [(1, 2.0, 2.5, 1.0), (3, 1.0, 2.0, 2.5)])
def test_stable_axes_wobble_at_omega_k(axis, i, j, k):
    """About the smallest and the largest moment the rates across the axis circle (on an ellipse) at Omega_k =
    w_k sqrt((lambda_i - lambda_k)(lambda_j - lambda_k) / (lambda_i lambda_j)): 10 turns in 10 periods, from
    the closed form at a tilt of 1e-4 (the wobble's own correction is of order tilt^2)."""
    values = members(1, **RACKET, spin0=10.0, tilt0=1e-4, azimuth0=0.7, spin_axis=axis)
    omega_k = 10.0 * np.cos(1e-4) * np.sqrt((i - k) * (j - k) / (i * j))  # the rate along the axis
    assert body.wobble_frequency(values, {})[0] == pytest.approx(omega_k, rel=1e-12)
    w = body.exact(values, {}, np.linspace(0, 20 * np.pi / omega_k, 4001))[:, :, 0]
    turns = np.unwrap(np.angle(w[:, axis % 3] + 1j * w[:, (axis + 1) % 3]))
    assert abs(turns[-1] - turns[0]) / (2 * np.pi) == pytest.approx(10.0, abs=1e-6)


def run(method, values, constants, dt, steps, n_save=2):
    return launch.integrate(body, METHODS[method], values, constants, n_save=n_save, save_dt=dt * steps,
                            dt=dt).samples


@pytest.mark.parametrize("method, dts", [("euler", (4e-4, 2e-4, 1e-4)), ("rk4", (1e-1, 5e-2, 2.5e-2)),
                                         ("rotations2", (1e-2, 5e-3, 2.5e-3)), ("rotations4", (1e-1, 5e-2, 2.5e-2))])
def test_convergence_order(method, dts):
    values, constants = members(4, seed=5, c=0.3, spin0=3.0, spin_axis=1), {}
    t_end = 1.0
    lam = [[values[f"lambda{i}"][m] for i in (1, 2, 3)] for m in range(4)]
    w0 = body.initial_state(values, constants)
    ref = np.stack([solve_ivp(euler_rhs(lam[m], 0.3), (0, t_end), w0[:, m], method="DOP853", rtol=1e-13,
                              atol=1e-14).y[:, -1] for m in range(4)], axis=1)
    errors = [np.abs(run(method, values, constants, dt, round(t_end / dt))[-1] - ref).max(axis=0) for dt in dts]
    slopes = np.diff(np.log(errors), axis=0) / np.diff(np.log(dts))[:, None]
    np.testing.assert_allclose(slopes, METHODS[method].order, atol=0.15)


def test_dopri5_order_against_its_mean_step():
    """Over rtol 1e-6 .. 1e-10, the median error at t = 20 s against the closed form falls as the mean accepted
    step to the fifth power, within 0.15 (measured 4.92), as the fixed-step methods' orders are tested above."""
    values, constants = members(8, seed=5, spin0=3.0, spin_axis=1), {}
    exact = body.exact(values, constants, np.array([0.0, 20.0]))
    errors, steps = [], []
    for rtol in (1e-6, 1e-7, 1e-8, 1e-9, 1e-10):
        outcome = launch.integrate(body, METHODS["dopri5"], values, constants, n_save=2, save_dt=20.0, rtol=rtol,
                                   atol=1e-3 * rtol)
        errors.append(np.median(np.abs(outcome.samples[-1] - exact[-1]).max(axis=0) / np.abs(exact).max(axis=(0, 1))))
        steps.append(np.median(outcome.counts[0]))
    order = np.polyfit(np.log(20.0 / np.array(steps)), np.log(errors), 1)[0]
    assert order == pytest.approx(METHODS["dopri5"].order, abs=0.15)


def test_dopri5_meets_its_tolerance_against_the_closed_form():
    values, constants = members(16, seed=6, spin_axis=2), {}
    outcome = launch.integrate(body, METHODS["dopri5"], values, constants, n_save=9, save_dt=0.25, rtol=1e-9,
                               atol=1e-12)
    exact = body.exact(values, constants, np.arange(9) * 0.25)
    scale = np.abs(exact).max(axis=(0, 1))
    assert np.all(np.abs(outcome.samples - exact).max(axis=(0, 1)) / scale < 1e-7)
    assert np.all(outcome.counts[2] == 1 + 6 * (outcome.counts[0] + outcome.counts[1]))


def test_symmetric_body_is_the_top():
    """lambda1 = lambda2 and spin about axis 3: the top scene's equations, to rounding."""
    values = members(5, seed=7, c=2e-4, lambda2=None)
    values["lambda2"] = values["lambda1"]
    tops = {"lambda1": values["lambda1"], "lambda3": values["lambda3"], **{k: values[k] for k in
                                                                           ("c", "spin0", "tilt0", "azimuth0")}}
    for method in ("rk4", "dopri5"):
        kw = {"dt": 1e-3} if method == "rk4" else {"rtol": 1e-10, "atol": 1e-12}
        mine = launch.integrate(body, METHODS[method], values, {}, n_save=11, save_dt=0.1, **kw)
        theirs = launch.integrate(top, METHODS[method], tops, {}, n_save=11, save_dt=0.1, **kw)
        scale = np.abs(theirs.samples).max()
        np.testing.assert_allclose(mine.samples, theirs.samples, rtol=0, atol=1e-12 * scale)


BOX_RUN = """scene = "body"
method = "rk4"
dt = 1e-3
t_end = 1.0
save_dt = 0.1
members = 4
seed = 1
[parameters]
body = { shape = "box", mass = 0.2, width = 0.02, height = 0.08, depth = 0.16 }
c = 0.0
spin0 = 20.0
spin_axis = 2
tilt0 = 0.02
"""


def test_box_from_its_shape_runs_and_writes_its_moments(tmp_path):
    path = tmp_path / "box.nc"
    runner.run(parse(BOX_RUN), path, progress=False)
    ds = xr.load_dataset(path)
    lam = [float(ds[f"lambda{i}"][0]) for i in (1, 2, 3)]
    mass, sides = 0.2, np.array([0.02, 0.08, 0.16])
    expected = sorted(mass / 12 * np.array([sides[1] ** 2 + sides[2] ** 2, sides[0] ** 2 + sides[2] ** 2,
                                            sides[0] ** 2 + sides[1] ** 2]))
    np.testing.assert_allclose(lam, expected, rtol=1e-12)
    assert np.all(ds["spin_axis"] == 2) and set(ds.data_vars) >= {"omega", "tilt", "energy", "angular_momentum"}
    executable = shutil.which("compliance-checker", path=str(Path(sys.executable).parent)) or "compliance-checker"
    checker = subprocess.run([executable, "--test=cf:1.9", "-f", "json", "-o", "-", str(path)], capture_output=True,
                             text=True)
    assert json.loads(checker.stdout)["cf:1.9"]["high_count"] == 0


@pytest.mark.parametrize("change, key", [
    ({"lambda1": 1.0, "lambda2": 1.0, "lambda3": 2.5}, "parameters.lambda3"),  # 2.5 > 1 + 1: no such body
    ({"lambda1": 1.0, "lambda2": -2.0, "lambda3": 2.5}, "parameters.lambda2"),
    ({"lambda1": 1.0, "lambda2": 2.0, "lambda3": 2.5, "spin_axis": 4}, "parameters.spin_axis"),
])
def test_bad_body_input_is_one_line_and_exit_2(change, key, tmp_path, capsys):
    params = "\n".join(f"{k} = {v}" for k, v in change.items())
    text = BOX_RUN.replace('body = { shape = "box", mass = 0.2, width = 0.02, height = 0.08, depth = 0.16 }',
                           params)
    if "spin_axis" in change:
        text = text.replace("spin_axis = 2\n", "")
    refused(text, tmp_path, capsys, f"{key}:")


def test_exact_with_drag_is_refused(tmp_path, capsys):
    text = BOX_RUN.replace('method = "rk4"\ndt = 1e-3', 'method = "exact"').replace("c = 0.0", "c = 1e-4")
    refused(text, tmp_path, capsys, "parameters.c: the closed form")


def test_an_asymmetric_top_is_pointed_to_the_body_scene(tmp_path, capsys):
    text = BOX_RUN.replace('scene = "body"', 'scene = "top"').replace("spin_axis = 2\n", "")
    refused(text, tmp_path, capsys, 'scene = "body"')


def test_the_course_plate_from_its_vertices():
    """The 45-degree right triangle of mass M and legs a: about its centre of mass, moments (1/3, 1, 4/3) M a^2/12
    (the corner's (1, 3, 4) M a^2 / 12 less the parallel-axis shift), recorded with its vertices."""
    spec = parse(BOX_RUN.replace('body = { shape = "box", mass = 0.2, width = 0.02, height = 0.08, depth = 0.16 }',
                                 'body = { shape = "polygon", mass = 2.0, vertices = [[0, 0], [0.3, 0], [0, 0.3]] }'))
    ds = runner.simulate(spec)
    scale = 2.0 * 0.3**2 / 12
    np.testing.assert_allclose([float(ds[f"lambda{i}"][0]) / scale for i in (1, 2, 3)], [1 / 3, 1, 4 / 3],
                               rtol=1e-12)
    assert ds.attrs["body_shape"] == "polygon" and ds.attrs["body_vertices"] == "0.0,0.0 0.3,0.0 0.0,0.3"
    values = {name: ds[name].values for name in ("lambda1", "lambda2", "lambda3", "c", "spin0", "tilt0",
                                                 "spin_axis")}
    # sigma = w_2 sqrt((4/3 - 1)(1 - 1/3) / (1/3 4/3)) = w_2 / sqrt(2), with w_2 = spin0 cos(tilt0)
    np.testing.assert_allclose(body.growth_rate(values, {}), 20.0 * np.cos(0.02) / np.sqrt(2),
                               rtol=1e-12)


@pytest.mark.parametrize("vertices, key", [("[[0, 0], [1, 0], [2, 0]]", "parameters.body.vertices"),
                                           ("[[0, 0], [1]]", "parameters.body.vertices"),
                                           ("[[0, 0], [1, 0], [0, 1]], width = 0.1", "parameters.body.width")])
def test_bad_polygon_is_one_line_and_exit_2(vertices, key, tmp_path, capsys):
    text = BOX_RUN.replace('body = { shape = "box", mass = 0.2, width = 0.02, height = 0.08, depth = 0.16 }',
                           f'body = {{ shape = "polygon", mass = 1.0, vertices = {vertices} }}')
    refused(text, tmp_path, capsys, f"{key}:")


def test_rotations_keep_angular_momentum_and_bound_the_energy():
    """c = 0, 10^5 steps of rotations2 (h spin0 = 0.01) near the intermediate axis, flipping throughout: each
    piece turns L orthogonally, so |L| stays to rounding; the energy error stays bounded (no drift)."""
    values, constants = members(4, seed=8, **RACKET, spin0=10.0, tilt0=0.3, spin_axis=2), {}
    samples = launch.integrate(body, METHODS["rotations2"], values, constants, n_save=101, save_dt=1.0,
                               dt=1e-3).samples.transpose(2, 0, 1)
    lam = np.array([RACKET[f"lambda{i}"] for i in (1, 2, 3)])
    momentum, energy = body.angular_momentum(samples, lam), body.kinetic_energy(samples, lam)
    np.testing.assert_allclose(momentum, np.broadcast_to(momentum[:, :1], momentum.shape), rtol=1e-12)
    drift = np.abs(energy / energy[:, :1] - 1)
    assert drift.max() < 1e-4 and drift[:, 51:].max() < 2 * drift[:, 1:51].max()


def test_flip_period_is_the_elliptic_formula():
    """Started 0.1 rad from the intermediate axis, the tilt crosses pi/2 upward once per period 4 K(m) / Omega:
    dopri5 at rtol 1e-12, crossings interpolated between samples 1e-4 s apart (cubic through four samples)."""
    values, constants = members(1, **RACKET, spin0=10.0, tilt0=0.1, azimuth0=0.3, spin_axis=2), {}
    period = body.flip_period(values, constants)[0]
    save_dt = 1e-4
    n_save = int(3.2 * period / save_dt)
    samples = launch.integrate(body, METHODS["dopri5"], values, constants, n_save=n_save, save_dt=save_dt,
                               rtol=1e-12, atol=1e-12).samples
    tilt = body.tilt(samples.transpose(1, 0, 2), 2)[:, 0] - np.pi / 2
    t = np.arange(n_save) * save_dt
    ups = np.flatnonzero((tilt[:-1] < 0) & (tilt[1:] >= 0))
    crossings = []
    for i in ups[(ups >= 1) & (ups < n_save - 2)]:
        fit = np.polynomial.Polynomial.fit(t[i - 1:i + 3], tilt[i - 1:i + 3], 3)
        roots = [r.real for r in fit.roots() if abs(r.imag) < 1e-12 and t[i] <= r.real <= t[i + 1]]
        crossings.append(roots[0])
    assert len(crossings) >= 3
    np.testing.assert_allclose(np.diff(crossings), period, rtol=1e-6)


# ---------------------------------------------------------------- fits: body_rates and `ensemble fit`

FIT_RUN = """
scene = "body"
method = "{method}"
dt = {dt}
t_end = {t_end}
save_dt = {save_dt}
members = {members}
seed = 7
[parameters]
lambda1 = 1.0
lambda2 = 2.0
lambda3 = 2.5
c = {c}
spin0 = 3.0
spin_axis = {axis}
tilt0 = {tilt0}
azimuth0 = {{ uniform = [0.0, 6.283185307179586] }}
{observe}
"""


def fitted(tmp_path, method="rk4", dt=1e-3, t_end=12.0, members=6, c=0.0, axis=2,
           tilt0="{ loguniform = [1e-8, 1e-7] }", observe="", save_dt=0.005, **kw):
    path = tmp_path / f"fit_{method}_{axis}_{members}.nc"
    text = FIT_RUN.format(method=method, dt=dt, t_end=t_end, members=members, c=c, axis=axis, tilt0=tilt0,
                          observe=observe, save_dt=save_dt)
    runner.run(parse(text, "fit.toml"), path, progress=False)
    return body_fit.body_rates(xr.load_dataset(path), **kw)


@pytest.mark.parametrize("axis, name", [(1, "wobble_frequency"), (2, "growth_rate"), (3, "wobble_frequency")])
def test_noise_free_rates_are_the_linear_theory(tmp_path, axis, name):
    """rk4 at h mu = 3e-3: the method's own shift (1e-12) is far below the 1e-6 asked of the fit."""
    fits = fitted(tmp_path, axis=axis, max_tilt=1e-3)
    other = "wobble_frequency" if name == "growth_rate" else "growth_rate"
    assert np.isnan(fits[other]).all() and fits["samples_used"].min() >= 100
    np.testing.assert_allclose(fits[name], fits[f"{name}_theory"], rtol=1e-6)
    theory = body.growth_rate if name == "growth_rate" else body.wobble_frequency
    values = {k: np.full(1, v) for k, v in (*RACKET.items(), ("c", 0.0), ("spin0", 3.0), ("tilt0", 0.0),
                                            ("spin_axis", axis))}
    np.testing.assert_allclose(fits[f"{name}_theory"], theory(values, {})[0], rtol=1e-7)


@pytest.mark.parametrize("method, dt", [("rk4", 0.25), ("rotations2", 0.05), ("rotations4", 0.1)])
def test_fits_show_each_methods_own_rate(tmp_path, method, dt):
    """At steps where the method's wobble frequency or growth rate misses the physics by 1e-4 to 1e-2, the fits
    equal what body.step_exponents predicts (stability function, or the splitting's linearized one-step map)."""
    for axis, name in ((3, "wobble_frequency"), (2, "growth_rate")):
        fits = fitted(tmp_path, method, dt, t_end=50 * dt if axis == 2 else 40.0, axis=axis, max_tilt=1e-3,
                      save_dt=dt)
        shown, theory = fits[f"{name}_method"].values, fits[f"{name}_theory"].values
        assert np.all(np.abs(shown / theory - 1) > 1e-5)
        np.testing.assert_allclose(fits[name], shown, rtol=1e-6 * np.abs(shown / theory - 1).min() / 1e-5)


def test_splitting_one_step_map_on_small_tilts_is_the_kernels():
    """The linearized map step_exponents uses is what the rotations kernels do to a 1e-9 rad tilt, with drag."""
    from ensemble.scenes.body import model
    for axis in (1, 2, 3):
        values, constants = members(3, seed=axis, c=0.05, tilt0=1e-9, spin_axis=axis), {}
        for method in ("rotations2", "rotations4"):
            samples = launch.integrate(body, METHODS[method], values, constants, n_save=2, dt=0.2, save_dt=0.2).samples
            lam = np.stack([values[f"lambda{a}"] for a in (1, 2, 3)])
            across = [(axis) % 3, (axis + 1) % 3]
            start, end = samples[0][across] * lam[across], samples[1][across] * lam[across]
            step = model._linear_split_step(METHODS[method], values, constants, 0.2)
            np.testing.assert_allclose(np.einsum("abm,bm->am", step, start), end, rtol=1e-7, atol=1e-22)


def test_flip_period_fit_is_the_elliptic_formula(tmp_path):
    fits = fitted(tmp_path, "rk4", 1e-3, t_end=30.0, tilt0="{ uniform = [0.01, 0.1] }")
    assert fits["flips"].min() >= 3
    np.testing.assert_allclose(fits["flip_period"], fits["flip_period_theory"], rtol=1e-6)


def test_noisy_z_values_follow_the_standard_normal(tmp_path):
    """300 members per axis with 0.003 rad/s of noise on omega: z of the growth rate, the wobble frequency and
    the flip period pass a KS test against N(0, 1)."""
    from scipy.stats import kstest
    noise = '[observe]\nnoise = { omega = 0.003 }'
    for axis, columns in ((2, ("z", "flip_z")), (3, ("z",))):
        fits = fitted(tmp_path, "rk4", 0.01, t_end=30.0, members=300, axis=axis, tilt0="{ uniform = [0.003, 0.01] }",
                      observe=noise, save_dt=0.01)
        for column in columns:
            z = fits[column].values[np.isfinite(fits[column].values)]
            assert z.size >= 250 and kstest(z, "norm").pvalue > 1e-3, (axis, column, z.mean(), z.std())


def test_flip_z_follows_the_standard_normal_at_every_spin_of_the_noisy_racket(tmp_path):
    """Issue 39: runs/tennis_racket_noisy.toml as shipped (200 boxes at each spin, 10 to 40 rad/s, noise 0.005
    rad/s). At 40 rad/s a flip's crossing of w_k = 0 takes about three saved samples; a polynomial through ten
    samples around it missed by up to 29 standard errors (sd of z 6.6, KS p 1e-22). Each spin's flip z now
    passes a KS test against N(0, 1)."""
    from scipy.stats import kstest
    path = tmp_path / "noisy.nc"
    runner.run(parse((RUNS / "tennis_racket_noisy.toml").read_text(), "noisy.toml"), path, progress=False)
    ds = xr.load_dataset(path)
    fits = body_fit.body_rates(ds)
    for spin in (10.0, 20.0, 40.0):
        z = fits["flip_z"].values[ds["spin0"].values == spin]
        z = z[np.isfinite(z)]
        assert z.size >= 190 and kstest(z, "norm").pvalue > 0.01, (spin, z.std())


def test_crossing_fit_recovers_the_period_from_the_closed_forms_samples():
    """The flip-period fit on the closed form's own samples (no integrator): the racket's boxes at 40 rad/s with
    tilts of 1e-4 to 1e-2 rad, saved every 0.01 s (a crossing spans about three samples), give the elliptic
    period to 1e-7, and its stated error is the fit's (tiny, from the fits' residuals)."""
    from ensemble.spec import load, members_table
    spec = load(RUNS / "tennis_racket.toml")
    values = {name: column[100:110] for name, column in members_table(spec).items()}  # spin0 = 40 rad/s
    assert np.all(values["spin0"] == 40.0)
    t = np.arange(601) * 0.01
    samples = body.exact(values, spec.constants, t)  # (t, axis, member)
    theory = body.flip_period(values, spec.constants)
    for member in range(10):
        period, stderr, flips = fitting.crossing_period(t, samples[:, 1, member], 0.0)
        assert flips >= 6 and abs(period / theory[member] - 1) < 1e-7 and stderr < 1e-6 * period


def test_body_rates_refuses_a_top_result(tmp_path):
    path = tmp_path / "top.nc"
    text = BOX_RUN.replace('scene = "body"', 'scene = "top"')
    text = text.replace('body = { shape = "box", mass = 0.2, width = 0.02, height = 0.08, depth = 0.16 }',
                        "lambda1 = 1.0\nlambda3 = 2.0").replace("spin_axis = 2\n", "")
    runner.run(parse(text, "top.toml"), path, progress=False)
    with pytest.raises(fitting.FitError, match="body_rates needs a body result; this one is a 'top' result"):
        body_fit.body_rates(xr.load_dataset(path))


def test_fit_checks_the_course_plate(tmp_path):
    result = tmp_path / "plate.nc"
    text = (Path(__file__).parent.parent / "runs" / "triangle_plate.toml").read_text().replace("members = 100",
                                                                                           "members = 8")
    runner.run(parse(text, "triangle_plate.toml"), result, progress=False)
    done = subprocess.run([sys.executable, "-m", "ensemble", "fit", str(result), "--check", "--charts", str(tmp_path)],
                          capture_output=True, text=True, cwd=Path(__file__).parent.parent)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.startswith("fitted growth rate of small tilts about the spin axis [growth_rate]")
    assert "FAIL" not in done.stdout
    rows = re.findall(r"^spin_axis = (\d) .* pass$", done.stdout, flags=re.M)
    assert rows == ["2", "1", "3", "2"]  # growth rate, wobble frequency about 1 and 3, flip period: one sweep
    for chart in ("tilt", "rates", "z"):
        assert (tmp_path / f"plate_body_rates_{chart}.png").stat().st_size > 10_000


def test_growth_on_small_tilts_about_a_stable_axis_is_the_methods_one_step_map(tmp_path):
    """About the largest axis of (1, 2, 2.5) kg m2, rk4 grows past h Omega = 2 sqrt(2), and rotations2, though
    it keeps |L|, turns the stable axis unstable past h Omega = 0.93 (its linearized one-step map, step_exponents).
    A 1e-150 rad tilt over 200 steps stays linear, so each member's measured growth per step equals the
    prediction (stability_map's growth_theory)."""
    from ensemble import stability
    run = '''scene = "body"
dt = 1.0
t_end = 200.0
save_dt = 1.0
members = 1
seed = 1
save = ["omega"]
[measure]
growth = true
[parameters]
lambda1 = 1.0
lambda2 = 2.0
lambda3 = 2.5
c = 0.0
tilt0 = 1e-150
spin_axis = 3
[[sweep]]
method = ["rk4"]
spin0 = [2.0, 4.7, 5.0]
[[sweep]]
method = ["rotations2"]
spin0 = [1.0, 1.55, 1.6, 1.8]
'''
    path = tmp_path / "scan.nc"
    runner.run(parse(run, "scan.toml"), path, progress=False)
    points = stability.stability_map(xr.load_dataset(path))
    measured, theory = points["growth"].values, points["growth_theory"].values
    grows = theory > 1.01
    assert list(grows) == [False, True, True, False, True, True, True]
    np.testing.assert_allclose(measured[grows], theory[grows], rtol=2e-4)
    # the others neither grow nor (the rate along the axis holding) decay: measured 1 within the scan's tolerance
    np.testing.assert_allclose(measured[~grows], 1.0, atol=stability.GROWTH_TOLERANCE)
