"""The torqued top: exact solution, the tilt law, and the stepping methods against them."""
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from ensemble.engine import launch
from ensemble.methods import METHODS
from ensemble.scenes import applies, top
from ensemble.scenes.top.physics import rhs


def members(lambda1, lambda3, c, spin0, tilt0, azimuth0):
    """A members table from per-member lists."""
    names = ("lambda1", "lambda3", "c", "spin0", "tilt0", "azimuth0")
    return dict(zip(names, (np.atleast_1d(np.asarray(v, dtype=float)) for v in
                            (lambda1, lambda3, c, spin0, tilt0, azimuth0))))


# oblate (the aerobie), prolate, nearly spherical, no drag, strong drag
CASES = members(
    lambda1=[1e-3, 2e-3, 1e-3, 1e-3, 1e-3],
    lambda3=[2e-3, 1e-3, 1.1e-3, 1.5e-3, 1.8e-3],
    c=[1e-4, 1e-4, 5e-5, 0.0, 2e-3],
    spin0=[60.0, 40.0, 50.0, 30.0, 20.0],
    tilt0=[0.1, 0.3, 0.05, 0.4, 1.0],
    azimuth0=[0.0, 1.0, 2.0, 3.0, 4.0],
)


def relative_error(y, reference):
    """max |y - reference| / max |reference| per member; arrays (t, 3, members)."""
    return np.abs(y - reference).max(axis=(0, 1)) / np.abs(reference).max(axis=(0, 1))


def test_exact_matches_tight_reference_integration():
    state0, rate = top.initial_state(CASES), top.rates(CASES)
    t = np.linspace(0.0, 5.0, 51)
    exact = top.closed_form(state0, rate, t)
    for j in range(state0.shape[1]):
        def f(_, w, p=rate[:, j]):
            return rhs(0.0, *w, *p)
        ref = solve_ivp(f, (0, t[-1]), state0[:, j], method="DOP853", t_eval=t, rtol=1e-13, atol=1e-12)
        err = np.abs(ref.y.T - exact[:, :, j]).max() / np.abs(ref.y).max()
        assert err < 1e-10, (j, err)


def test_exact_at_zero_is_the_initial_state():
    state0, rate = top.initial_state(CASES), top.rates(CASES)
    np.testing.assert_array_equal(top.closed_form(state0, rate, [0.0])[0], state0)
    np.testing.assert_allclose(np.linalg.norm(state0, axis=0), CASES["spin0"], rtol=1e-15)
    np.testing.assert_allclose(top.tilt(state0, axis=0), CASES["tilt0"], rtol=1e-14)


def test_exact_tilt_follows_the_course_law():
    state0, rate = top.initial_state(CASES), top.rates(CASES)
    t = np.linspace(0.0, 30.0, 301)
    tilt = top.tilt(top.closed_form(state0, rate, t), axis=1).T
    law = top.tilt_theory(CASES, t)
    np.testing.assert_allclose(tilt, law, rtol=1e-12, atol=0)
    oblate, prolate = tilt[0], tilt[1]
    assert oblate[-1] < oblate[0] and prolate[-1] > prolate[0]


def run(method, table, dt, steps_per_save, n_save):
    return launch.integrate(top, METHODS[method], table, {}, n_save=n_save, save_dt=dt * steps_per_save, dt=dt).samples


def test_rk4_agrees_with_exact_to_1e_9_over_10_s():
    """Spin 50 rad/s; the body-frame precession rate p w3 is 5 rad/s (lambda3 = 1.1 lambda1)."""
    table = members(1e-3, 1.1e-3, 1e-4, 50.0, 0.2, 0.3)
    samples = run("rk4", table, 1e-3, 1000, 11)
    exact = top.exact(table, {}, np.arange(11) * 1.0)
    assert relative_error(samples, exact)[0] < 1e-9


def test_rk4_phase_error_matches_its_truncation_term():
    """Undamped aerobie: rk4's phase lags by (W h)^5 / 120 per step, W = p w3 (here 59.7 rad/s)."""
    table = members(1e-3, 2e-3, 0.0, 60.0, 0.1, 0.0)
    h, steps = 1e-3, 10_000
    samples = run("rk4", table, h, steps, 2)
    exact = top.exact(table, {}, [0.0, h * steps])
    transverse, precession = 60.0 * np.sin(0.1), 1.0 * 60.0 * np.cos(0.1)  # |w1 + i w2|, p w3
    predicted = transverse * steps * (precession * h) ** 5 / 120
    measured = np.linalg.norm(samples[1] - exact[1])
    assert measured == pytest.approx(predicted, rel=0.01)


TOP_METHODS = [name for name, m in METHODS.items() if applies(m, top) and not (m.closed_form or m.adaptive)]


# strong drag (c / lambda ~ 1/s): the split methods' only error comes from drag and rotation not commuting
DRAGGED = members(
    lambda1=[1e-3, 1e-3, 2e-3], lambda3=[1.8e-3, 1.2e-3, 1e-3], c=[2e-3, 1e-3, 3e-3],
    spin0=[20.0, 40.0, 30.0], tilt0=[1.0, 0.3, 0.5], azimuth0=[4.0, 0.5, 2.0],
)


@pytest.mark.parametrize("method", TOP_METHODS)
def test_convergence_order(method):
    table = DRAGGED
    t_end = 1.0
    exact = top.exact(table, {}, [0.0, t_end])
    order = METHODS[method].order
    # asymptotic ranges: above rounding (split4 reaches 1e-13 near dt = 5e-3), below the nonlinear regime
    dts = {"euler": (2e-4, 1e-4, 5e-5), "rk4": (2e-2, 1e-2, 5e-3)}.get(method, (4e-2, 2e-2, 1e-2))
    errors = []
    for dt in dts:
        steps = round(t_end / dt)
        errors.append(relative_error(run(method, table, dt, steps, 2), exact))
    slopes = np.diff(np.log(np.array(errors)), axis=0) / np.diff(np.log(dts))[:, None]
    np.testing.assert_allclose(slopes, order, atol=0.15)


def test_member_result_does_not_depend_on_its_neighbours():
    """Padding, block position and chunking leave each member's bits unchanged."""
    rng = np.random.default_rng(3)
    n = 300
    table = members(np.full(n, 1e-3), rng.uniform(1e-3, 2e-3, n), rng.uniform(0, 2e-4, n),
                    rng.uniform(10, 60, n), rng.uniform(0, 1, n), rng.uniform(0, 6, n))
    whole = run("rk4", table, 1e-3, 50, 3)
    part = run("rk4", {k: v[7:139] for k, v in table.items()}, 1e-3, 50, 3)
    np.testing.assert_array_equal(whole[:, :, 7:139], part)


@pytest.mark.parametrize("method", ["rk4", "dopri5"])
def test_results_do_not_depend_on_the_threads(method):
    """Five blocks run on one thread, on two (in eight groups) and on five give the same bits, counts included."""
    rng = np.random.default_rng(4)
    n = 5 * 128 - 3
    table = members(np.full(n, 1e-3), rng.uniform(1e-3, 2e-3, n), rng.uniform(0, 2e-4, n),
                    rng.uniform(10, 60, n), rng.uniform(0, 1, n), rng.uniform(0, 6, n))
    call = launch.Launch(top, METHODS[method], table, {}, n_save=4, save_dt=0.05, dt=1e-3, rtol=1e-8, atol=1e-10)
    outcomes = []
    for threads in (1, 2, 5):
        call.run(threads=threads)
        outcomes.append(call.outcome())
    for other in outcomes[1:]:
        np.testing.assert_array_equal(other.samples, outcomes[0].samples)
        np.testing.assert_array_equal(other.counts, outcomes[0].counts)

def test_split_methods_are_exact_without_drag():
    """With c = 0 the drag piece is the identity and the rotation piece is the whole exact flow."""
    table = members([1e-3, 2e-3], [2e-3, 1e-3], [0.0, 0.0], [60.0, 40.0], [0.1, 0.3], [0.0, 1.0])
    exact = top.exact(table, {}, [0.0, 2.0])
    for method in ("split2", "split4"):
        assert relative_error(run(method, table, 1e-2, 200, 2), exact).max() < 1e-12


def test_the_splittings_sin_and_cos_match_numpy_to_an_ulp_of_one():
    from numba import njit

    from ensemble.engine.blocks import FAST, SIN_COS_LIMIT, sin_cos

    @njit(**FAST)  # as the kernels that inline it are compiled
    def both(x):
        sin, cos = np.empty_like(x), np.empty_like(x)
        for i in range(x.size):
            sin[i], cos[i] = sin_cos(x[i])
        return sin, cos

    rng = np.random.default_rng(7)
    x = np.concatenate([rng.uniform(-1, 1, 20_000) * 10.0 ** rng.integers(-9, 14, 20_000),
                        np.pi / 4 * np.arange(-40, 41), [0.0, -0.0, 1e-300, SIN_COS_LIMIT, -SIN_COS_LIMIT]])
    sin, cos = both(x)
    np.testing.assert_allclose(sin, np.sin(x), rtol=0, atol=2.3e-16)
    np.testing.assert_allclose(cos, np.cos(x), rtol=0, atol=2.3e-16)
    assert np.all(np.isnan(both(np.array([2 * SIN_COS_LIMIT, np.inf, np.nan]))))  # beyond the reduction: NaN


def test_observed_tilt_and_amplitudes_are_numpys_arctan2_and_hypot():
    """The run's compiled tilt and amplitudes (kernels.observed_tilt and observed_amplitudes: Cephes' atan in
    selects) against numpy's arctan2(hypot(w1, w2), w3) and hypot, over rates from 1e-13 to 1e13 rad/s of both
    signs: within 4 units in the last place; signed zeros and NaN as numpy gives them."""
    rng = np.random.default_rng(11)
    omega = rng.standard_normal((300, 50, 3)) * np.exp(rng.uniform(-30, 30, (300, 50, 3)))
    special = [[0, 0, 0.0], [0, 0, -0.0], [0, 0, 2], [0, 0, -2], [1, 0, 0], [0, -1, -0.0], [np.nan, 0, 1],
               [0, np.nan, 1], [1, 1, np.nan], [1e-320, 0, 1], [3, 4, -5], [1e300, 1e300, 1]]
    omega[0, :len(special)] = special
    samples = omega.transpose(1, 2, 0)  # (t, 3, members), as the runner hands them
    transverse = np.hypot(omega[..., 0], omega[..., 1])
    expected = np.arctan2(transverse, omega[..., 2])
    tilt = top.observe(samples, ("tilt",), {}, {})["tilt"]
    amplitudes = top.amplitudes(samples, {}, {})
    for got, want in ((tilt, expected), (amplitudes[:, 0], transverse), (amplitudes[:, 1], np.abs(omega[..., 2]))):
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
        finite = ~np.isnan(want)
        assert np.all(np.abs(got - want)[finite] <= 4 * np.spacing(np.abs(want[finite])))
    np.testing.assert_array_equal(np.signbit(tilt[0, :6]), np.signbit(expected[0, :6]))


def test_a_tilt_decaying_past_the_smallest_double_goes_to_zero_not_astray():
    """Issue 40, item 3: rk4 on a damped top whose rates decay into subnormal numbers kept them there (omega
    stuck at 3.7e-321) and its tilt jumped from 8.9e-19 to 0.6153 rad, status ok. Subnormal state values now
    become zeros where a member is checked (each saved sample): here tan(tilt) follows tan(tilt0) exp(-rate t)
    (rate = c (1/lambda1 - 1/lambda3) = 10/s) down to 1e-300 and is exactly 0 once the transverse rates
    (decaying at c / lambda1 = 20/s) pass the smallest double, and so are the rates at the end."""
    values = {"lambda1": np.full(4, 1e-3), "lambda3": np.full(4, 2e-3), "c": np.full(4, 0.02),
              "spin0": np.full(4, 60.0), "tilt0": np.linspace(0.05, 0.2, 4), "azimuth0": np.zeros(4)}
    outcome = launch.integrate(top, METHODS["rk4"], values, {}, n_save=21, save_dt=5.0, dt=1e-3)
    assert np.all(outcome.status == 0)
    t = np.arange(21) * 5.0
    tilt = top.observe(outcome.samples, ("tilt",), values, {})["tilt"]  # (members, t)
    law = np.log(np.tan(values["tilt0"]))[:, None] - 10.0 * t
    shown = tilt > 0
    assert np.all(np.diff(tilt, axis=1) <= 0) and not shown[:, -1].any()
    assert shown[:, :7].all()  # to t = 30 s: tan(tilt) about 1e-131
    np.testing.assert_allclose(np.log(np.tan(tilt[shown])), law[shown], rtol=1e-6)
    assert np.all(outcome.samples[-1] == 0.0)  # (t, rate, member): every rate flushed to zero by t = 100 s
