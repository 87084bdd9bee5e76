"""Events (ensemble.events, ensemble.engine.events): each member's crossings located within its steps, against
closed forms: the pendulum's zero crossings (2 j + 1) K(m) / omega0 and the time its bob falls through a height
(an event function of the scene's own), a prolate top's tilt reaching a level; members that stop at an event;
runs that keep events alone; bad [events] tables refused in one line."""
import math
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import ensemble
from ensemble import cli, events
from ensemble.engine import launch
from ensemble.methods import METHODS
from ensemble.results import Event, Status
from ensemble.scenes import resolve
from ensemble.scenes.body.fits import body_rates
from ensemble.scenes.top.model import tilt_theory

from .conftest import refused, top_runfile

ROOT = Path(__file__).resolve().parents[1]
RUNS = ROOT / "runs"
PENDULUM = ROOT / "examples" / "pendulum.py"
OMEGA0 = 2.0
THETA0 = np.array([0.5, 1.5, 2.0, 2.8])  # the last two swing above the height of the axle
# One kernel per method for every pendulum test: the sources (a state component, the scene's event function)
# fix it; the levels, directions and counts are the run's.
EVENTS = (Event("zero", "theta", -1, ("state", 0), 0.0, "both", 6, keep=("theta", "theta_dot")),
          Event("low", "height", -1, ("function", "event_height", -1), 1.0, "down", 1))


def example(name: str):
    """The module of examples/<name>.py, for its closed forms."""
    import sys

    sys.path.insert(0, str(ROOT / "examples"))
    try:
        return __import__(name)
    finally:
        sys.path.pop(0)


def swing(method: str, dt: float, events=EVENTS, t_end: float = 10.0, save_dt: float = 0.1):
    """Four pendulums released at rest from THETA0, with `events`: the launch's Outcome."""
    values = {"omega0": np.full(4, OMEGA0), "theta0": THETA0, "theta_dot0": np.zeros(4)}
    return launch.integrate(resolve(str(PENDULUM)), METHODS[method], values, {}, n_save=round(t_end / save_dt) + 1,
                            save_dt=save_dt, dt=dt, rtol=1e-7, atol=1e-9, events=events)


def state_error(outcome, save_dt: float) -> np.ndarray:
    """The largest |theta - exact| of each member over the run, (members,)."""
    t = np.arange(outcome.samples.shape[0])[:, None] * save_dt
    exact, _ = example("pendulum").exact(t, THETA0[None], 0.0, OMEGA0)
    return np.max(np.abs(outcome.samples[:, 0, :] - exact), axis=0)


@pytest.mark.parametrize("method, dt", [("rk4", 0.02), ("yoshida4", 0.02), ("dopri5", np.nan)])
def test_pendulum_crossings_are_the_elliptic_times_to_the_methods_own_error(method, dt):
    outcome = swing(method, dt)
    module = example("pendulum")
    exact = module.crossing_times(THETA0, OMEGA0, 6)  # (members, 6), some after t = 10 s
    times = outcome.event_times[0].T
    assert np.all(outcome.event_counts[0] == np.sum(module.crossing_times(THETA0, OMEGA0, 20) < 10.0, axis=1))
    assert np.array_equal(np.isfinite(times), exact < 10.0)  # six kept at most, NaN where fewer occurred
    assert np.all(outcome.status == Status.OK) and np.all(np.isnan(outcome.stopped))
    speed = 2.0 * np.sin(THETA0 / 2.0) * OMEGA0  # |theta_dot| at the bottom
    own = state_error(outcome, 0.1)  # the method's error in theta, by its samples
    error = np.abs(np.where(exact < 10.0, times - exact, 0.0))
    assert np.all(error * speed[:, None] <= 2.0 * own[:, None] + 1e-13)
    assert np.max(error) > 0.0  # (not exact by accident)
    theta, theta_dot = outcome.event_states[0, :, 0].T, outcome.event_states[0, :, 1].T  # kept at each crossing
    assert np.array_equal(np.isfinite(theta_dot), exact < 10.0) and np.nanmax(np.abs(theta)) < 1e-12
    signs = np.where(np.arange(6) % 2 == 0, -1.0, 1.0)  # released at rest above 0: down through it first
    assert np.all(np.nan_to_num(np.abs(theta_dot - signs * speed[:, None])) <= 4.0 * OMEGA0 * own[:, None] + 1e-12)
    # the scene's event function: the bob falls through the axle's height once per swing (half a period) above it
    low = outcome.event_times[1, 0]
    first = module.height_times(THETA0[2:], OMEGA0, 1.0)
    half_period = 2.0 * (exact[2:, 1] - exact[2:, 0]) / 2.0
    falls = np.sum(first[:, None] + half_period[:, None] * np.arange(20) < 10.0, axis=1)
    assert np.all(outcome.event_counts[1] == [0, 0, *falls]) and np.all(np.isnan(low[:2]))
    falling = np.sin(math.pi / 2) * OMEGA0 * np.sqrt(2.0 * (np.cos(math.pi / 2) - np.cos(THETA0[2:])))  # |theta_dot|
    assert np.all(np.abs(low[2:] - first) * falling <= 2.0 * own[2:] + 1e-13)


def test_a_run_in_segments_and_a_resumed_one_find_the_bits_of_one_call():
    whole = swing("rk4", 0.02)
    values = {"omega0": np.full(4, OMEGA0), "theta0": THETA0, "theta_dot0": np.zeros(4)}
    call = launch.new_launch(resolve(str(PENDULUM)), METHODS["rk4"], values, {}, n_save=101, save_dt=0.1, dt=0.02,
                             events=EVENTS, segment=7)
    kept = None
    for first, _ in call.segments():
        if first == 49:
            kept = (first + 7, call.state())  # what a segment log keeps
    call.run()
    for name in ("event_times", "event_counts", "samples"):
        np.testing.assert_array_equal(getattr(call.outcome(), name), getattr(whole, name))
    list(call.segments(resume=kept))  # a run resumed from the middle
    np.testing.assert_array_equal(call.outcome().event_times, whole.event_times)


def test_the_closed_forms_events_are_found_on_it_to_rounding():
    """Method exact: the crossings are root-found on the scene's closed form itself (a grid of dt brackets them),
    so they are the elliptic times to rounding; a run in segments, resumed from the middle, or of one member at a
    time gives the same bits."""
    module = example("pendulum")
    outcome = swing("exact", 0.05)
    exact = module.crossing_times(THETA0, OMEGA0, 6)
    times = outcome.event_times[0].T
    assert np.array_equal(np.isfinite(times), exact < 10.0)
    assert np.all(outcome.event_counts[0] == np.sum(module.crossing_times(THETA0, OMEGA0, 20) < 10.0, axis=1))
    assert np.nanmax(np.abs(times - exact)) < 1e-13
    signs = np.where(np.arange(6) % 2 == 0, -1.0, 1.0)
    speed = 2.0 * np.sin(THETA0 / 2.0) * OMEGA0
    assert np.nanmax(np.abs(outcome.event_states[0, :, 1].T - signs * speed[:, None])) < 1e-12
    assert np.allclose(outcome.event_times[1, 0, 2:], module.height_times(THETA0[2:], OMEGA0, 1.0), rtol=0,
                       atol=1e-13) and np.all(np.isnan(outcome.event_times[1, 0, :2]))
    values = {"omega0": np.full(4, OMEGA0), "theta0": THETA0, "theta_dot0": np.zeros(4)}
    call = launch.new_launch(resolve(str(PENDULUM)), METHODS["exact"], values, {}, n_save=101, save_dt=0.1, dt=0.05,
                             events=EVENTS, segment=7)
    kept = next((first + 7, call.state()) for first, _ in call.segments() if first == 49)
    list(call.segments(resume=kept))
    np.testing.assert_array_equal(call.outcome().event_times, outcome.event_times)
    for j in range(4):
        one = launch.integrate(resolve(str(PENDULUM)), METHODS["exact"], {k: v[j:j + 1] for k, v in values.items()},
                               {}, n_save=101, save_dt=0.1, dt=0.05, events=EVENTS)
        np.testing.assert_array_equal(one.event_times[..., 0], outcome.event_times[..., j])


def test_rk4s_crossing_times_converge_at_its_order():
    exact = example("pendulum").crossing_times(THETA0, OMEGA0, 6)
    errors = [np.nanmax(np.abs(swing("rk4", dt).event_times[0].T - exact)) for dt in (0.04, 0.02)]
    assert 2.0**4 / 1.5 < errors[0] / errors[1] < 2.0**4 * 1.5


def test_a_prolate_tops_tilt_reaches_its_level_at_the_closed_forms_time():
    """tan(tilt) = tan(tilt0) exp(c (1/lambda3 - 1/lambda1) t) for a prolate top (lambda3 < lambda1): the tilt
    reaches `level` at ln(tan(level) / tan(tilt0)) / (c (1/lambda3 - 1/lambda1))."""
    top = resolve("top")
    tilt0 = np.array([0.05, 0.1, 0.3])
    values = {"lambda1": np.full(3, 1e-3), "lambda3": np.full(3, 0.5e-3), "c": np.full(3, 1e-4),
              "spin0": np.full(3, 60.0), "tilt0": tilt0, "azimuth0": np.zeros(3)}
    level, rate = 0.6, 1e-4 * (1 / 0.5e-3 - 1 / 1e-3)
    tip = Event("tip", "tilt", -1, ("function", "value_tilt", -1, "watch_tilt"), level, "up", 1, True)
    assert events.parse({"tip": {"of": "tilt", "value": level, "direction": "up", "stop": True}}, top, {},
                        set()) == (tip,)  # a run file's tilt event is watched through watch_tilt
    outcomes = {}
    for method in ("rk4", "split4", "exact"):
        outcome = outcomes[method] = launch.integrate(top, METHODS[method], values, {}, n_save=301, save_dt=0.1,
                                                      dt=2e-3, events=(tip,))
        expected = np.log(math.tan(level) / np.tan(tilt0)) / rate
        t = np.arange(301) * 0.1
        own = np.nanmax(np.abs(top.tilt(outcome.samples, 1) - tilt_theory(values, t).T), axis=0)
        slope = rate * math.sin(level) * math.cos(level)  # d tilt / dt at the level
        assert np.all(outcome.status == Status.STOPPED_BY_EVENT)
        assert np.all(np.abs(outcome.event_times[0, 0] - expected) * slope <= 2.0 * own + 1e-12), method
        stopped = top.tilt(outcome.stopped, 0)  # the state kept at the event is on the level
        assert np.allclose(stopped, level, rtol=0, atol=1e-9)
        later = t[:, None] > expected[None, :] + 2e-3  # samples after the step it stopped in are NaN
        assert np.all(np.isnan(outcome.samples[:, 0, :][later])) and np.all(np.isfinite(outcome.samples[:, 0][~later]))
    unwatched = launch.integrate(top, METHODS["split4"], values, {}, n_save=301, save_dt=0.1, dt=2e-3,
                                 events=(tip._replace(source=tip.source[:3]),))  # the tilt's value alone
    for name in ("samples", "status", "event_times", "event_counts", "stopped"):  # the same bits
        assert np.array_equal(getattr(unwatched, name), getattr(outcomes["split4"], name), equal_nan=True), name


def test_the_tops_watch_has_the_sign_of_its_tilt_minus_the_level():
    """physics.watch_tilt, which the kernels evaluate instead of the tilt itself, has the sign of value_tilt -
    level (numpy's arctan2 of |(w1, w2)| and w3), on and off the spin axis, for levels in and beyond [0, pi], and
    for rates from 1e-150 to 1e150 rad/s (its squares neither overflow nor lose their bits there; its product
    with 1 / sin(level)^2 may overflow to inf, of the right sign, at a level of 1e-9 rad); a body at rest gives 0
    (a crossing to look at: the kernels then ask the tilt) for a level strictly between 0 and pi."""
    from ensemble.scenes.top.physics import watch_tilt

    rng = np.random.default_rng(5)
    rates = np.concatenate([rng.normal(size=(4000, 3)) * 10.0 ** rng.uniform(-3, 3, (4000, 1)),
                            rng.normal(size=(1000, 3)) * 10.0 ** rng.uniform(-150, 150, (1000, 1)),
                            [[0, 0, 5], [0, 0, -5], [0, 0, 0.0], [0, 0, -0.0], [1e-3, 0, -7], [0, -2, 0]]])
    levels = np.concatenate([[-0.5, 0.0, 1e-9, 0.6, math.pi / 2, math.pi - 1e-9, math.pi, 3.5],
                             rng.uniform(0, math.pi, 8)])
    for w1, w2, w3 in rates:
        tilt = np.arctan2(np.hypot(w1, w2), w3)
        for level in levels:
            with np.errstate(over="ignore"):  # rates of 1e150 rad/s over sin(1e-9 rad)^2: inf, of the right sign
                sign = watch_tilt(0.0, w1, w2, w3, 0.0, 0.0, 0.0, level)
            if w1 == w2 == w3 == 0.0 and 0.0 < level < math.pi:
                assert sign == 0.0, level
            elif abs(tilt - level) > 1e-12:
                assert np.sign(sign) == np.sign(tilt - level), (w1, w2, w3, level)
            elif tilt == level:
                assert sign == 0.0 or abs(sign) < 1e-12 * np.linalg.norm((w1, w2, w3)), (w1, w2, w3, level)
    assert math.isnan(watch_tilt(0.0, math.nan, 0.0, 1.0, 0.0, 0.0, 0.0, 0.5))
    assert math.isnan(watch_tilt(0.0, 0.0, 0.0, math.nan, 0.0, 0.0, 0.0, 0.5))


def test_a_scenes_function_called_written_out_gives_what_its_star_call_gives():
    """events.written_out (the kernels' watch calls a scene's function with its arguments written out, so that
    Numba inlines it) passes the time, every state value, every parameter and the level in order, and picks a
    vector's value `index`: against the function called with *args."""
    from numba import njit

    from ensemble.engine.events import function_sign, function_value

    def watch(t, a, b, c, k, m, level):
        return (t + 2.0 * a - 3.0 * b + 5.0 * c) * k / m - level

    def vector(t, a, b, c, k, m):
        return (a * k, b * m, t + c)

    inlined = njit(inline="always")
    y, p = (0.25, -1.5, 3.0), (7.0, 0.5)
    signed = function_sign(inlined(watch), -1, counts=(3, 2))
    assert njit(lambda t, y, p, level: signed(t, y, p, level))(1.5, y, p, 0.75) == watch(1.5, *y, *p, 0.75)
    for index in range(3):
        picked = function_value(inlined(vector), index, counts=(3, 2))
        assert njit(lambda t, y, p: picked(t, y, p))(1.5, y, p) == vector(1.5, *y, *p)[index]


def test_a_crossing_that_only_the_watch_saw_is_put_at_the_nearer_end_of_its_step():
    """events.root: a step's values on either side of the level are bracketed (Illinois, to the last bits); values
    on one side (a watch's sign crossed, the value not) give the nearer end where it is on the level to rounding
    (WATCH_ROUNDING), and no crossing (NOT_CROSSED) where both are off it."""
    from numba import njit

    from ensemble.engine.events import NOT_CROSSED, WATCH_ROUNDING, root

    values = njit(lambda t, y, p: (y[0],))
    advance = njit(lambda t0, h, y0, p: (y0[0] + h * (1.0 + y0[0]),))  # y(s) = s from y0 = 0: a line
    find = njit(lambda level, y0, before, after: root(values, advance, 0, level, 0.0, 1.0, (y0,), (), before,
                                                      after))
    assert find(0.3, 0.0, 0.0, 1.0) == pytest.approx(0.3, abs=1e-15)
    assert find(0.3, 0.3, 0.3 - 1e-17, 1.3) == 0.0 and find(1.0, 0.0, 0.0, 1.0 - 1e-16) == 1.0
    assert find(0.3, 0.0, 0.3 * (1 + 1e-6), 1.0) == 0.0 and find(0.9, 0.0, 0.0, 0.9 * (1 - 1e-6)) == 1.0
    assert find(0.3, 0.0, 0.31, 1.0) == NOT_CROSSED and find(0.9, 0.0, 0.0, 0.89) == NOT_CROSSED
    assert find(0.3, 0.0, 0.3 * (1 + 2 * WATCH_ROUNDING), 1.0) == NOT_CROSSED


def test_a_top_come_to_rest_crosses_no_level():
    """A heavily damped oblate top (c = 0.1 kg m2/s: its rates fall 50 to 100 times e a second) whose tilt only
    falls, at 50/s (tan(tilt) = tan(tilt0) exp(-50 t)): its rates' squares fall below the smallest double (flushed
    to 0 in the kernels) within 7.2 s, where the tilt's watch rises from below 0 to 0. The tilt itself is far below
    any level there, so no rise through 0.3 rad is counted, and the fall through 0.04 rad is counted once, at its
    closed form's time (a second was counted at rest before events.root asked the value, and is where an
    occurrence past `count`, counted without being located, is counted without asking it)."""
    top = resolve("top")
    tilt0 = np.array([0.05, 0.1, 0.2])
    values = {"lambda1": np.full(3, 1e-3), "lambda3": np.full(3, 2e-3), "c": np.full(3, 0.1),
              "spin0": np.full(3, 60.0), "tilt0": tilt0, "azimuth0": np.zeros(3)}
    watched = ("function", "value_tilt", -1, "watch_tilt")
    rise, fall = Event("rise", "tilt", -1, watched, 0.3, "up", 1), Event("fall", "tilt", -1, watched, 0.04, "both", 1)
    for method in ("rk4", "split4"):
        outcome = launch.integrate(top, METHODS[method], values, {}, n_save=10, save_dt=1.0, dt=2e-3,
                                   events=(rise, fall))
        assert np.all(np.abs(outcome.samples[-1]) ** 2 < np.finfo(float).tiny), method  # every square underflows
        assert np.all(outcome.event_counts == [[0], [1]]) and np.all(np.isnan(outcome.event_times[0])), method
        expected = np.log(np.tan(tilt0) / math.tan(0.04)) / 50.0
        assert np.allclose(outcome.event_times[1, 0], expected, rtol=0, atol=1e-6), method


def test_a_tops_fit_finds_its_tilt_decay_rate_from_event_times_alone(tmp_path):
    """An oblate top's tilt falls through 0.05 rad at ln(tan(tilt0) / tan(0.05)) / (c (1/lambda1 - 1/lambda3)):
    `ensemble fit` of a run that saves nothing but that event finds the decay rate from it and tilt0."""
    text = top_runfile(dt=2.5e-4, t_end=30.0, save_dt=30.0, save=[], members=6,
                       parameters={"tilt0": {"uniform": [0.051, 0.09]}, "c": None}, sweep={"c": [2.5e-5, 1e-4]})
    path = tmp_path / "tops.toml"
    path.write_text(text + '[events.low]\nof = "tilt"\nvalue = 0.05\ndirection = "down"\nstop = true\n')
    assert cli.main(["run", str(path), "-o", str(tmp_path / "tops.nc"), "--quiet"]) == 0
    assert cli.main(["fit", str(tmp_path / "tops.nc"), "--check"]) == 0
    with xr.open_dataset(tmp_path / "tops.nc") as ds, xr.open_dataset(tmp_path / "tops_tilt_decay.nc") as fits:
        theory = ds["c"].values * (1 / 1e-3 - 1 / 2e-3)
        crossed = np.log(np.tan(ds["tilt0"].values) / np.tan(0.05)) / theory < 30.0
        assert np.array_equal(np.isfinite(fits["rate"].values), crossed) and 0 < crossed.sum() < 12
        assert np.allclose(fits["rate"].values[crossed], theory[crossed], rtol=1e-8, atol=0)
        assert np.all(ds["status"].values == np.where(crossed, Status.STOPPED_BY_EVENT, Status.OK))


def test_a_boxs_flip_period_from_its_flip_events_is_the_elliptic_period(tmp_path):
    """Boxes spun near their intermediate axis flip over and back: the spin-axis rate crosses zero twice a period.
    With those crossings as events (free of the observation noise on the samples), the body's fit finds the
    period 4 K(m) / Omega to the method's error, and the same period as its fit of the noisy samples within
    their error bars."""
    text = (RUNS / "tennis_racket_noisy.toml").read_text().replace("members = 200", "members = 4").replace(
        "[parameters]", '[events.flip]\nof = "omega"\nindex = 1\ncount = 64\n[parameters]')
    path = tmp_path / "racket.toml"
    path.write_text(text)
    assert cli.main(["run", str(path), "-o", str(tmp_path / "racket.nc"), "--quiet"]) == 0
    with xr.open_dataset(tmp_path / "racket.nc") as ds:
        fits = ensemble.fit(ds)
        sampled = body_rates(ds.drop_vars("flip_time"))  # the same fit of the noisy samples alone
    period, theory = fits["flip_period"].values, fits["flip_period_theory"].values
    assert np.all(np.isfinite(period)) and np.all(fits["flips"].values >= 3)
    assert np.allclose(period, theory, rtol=1e-9, atol=0)
    assert np.max(np.abs(period - theory) / theory) < 1e-3 * np.median(sampled["flip_period_stderr"] / theory)
    assert np.all(np.abs(sampled["flip_period"] - period) < 5 * sampled["flip_period_stderr"])


def test_flip_times_observed_with_noise_give_calibrated_flip_periods(tmp_path):
    """Issue 52, item 4: flip events are located on the steps, free of the samples' noise, so their periods'
    error bars held the times' rounding and flip_z had sd 56 on the noisy racket. Flip times observed with
    timing noise ([observe] noise = { flip_time = 10 us }) are the located times plus that noise (member i's from
    the stream of (seed, "noise:flip_time", i)), and each period's error bar comes from it: over the noisy racket's
    three spins, flip_z has sd within 0.8 to 1.2 and passes a KS test against N(0, 1)."""
    import zlib

    from scipy.stats import kstest

    text = (RUNS / "tennis_racket_noisy.toml").read_text().replace("members = 200", "members = 100").replace(
        "[parameters]", '[events.flip]\nof = "omega"\nindex = 1\ncount = 64\n[parameters]')
    (tmp_path / "plain.toml").write_text(text)
    (tmp_path / "timed.toml").write_text(text.replace("noise = { omega = 0.005 }",
                                                      "noise = { omega = 0.005, flip_time = 1e-5 }"))
    for name in ("plain", "timed"):
        assert cli.main(["run", str(tmp_path / f"{name}.toml"), "-o", str(tmp_path / f"{name}.nc"), "--quiet"]) == 0
    with xr.open_dataset(tmp_path / "plain.nc") as plain, xr.open_dataset(tmp_path / "timed.nc") as timed:
        assert timed["flip_time"].attrs["observation_noise_stddev"] == 1e-5
        np.testing.assert_array_equal(timed["omega"].values, plain["omega"].values)
        stream = zlib.crc32(b"noise:flip_time")
        draws = np.stack([np.random.default_rng([2028, stream, i]).standard_normal(64) for i in range(300)])
        np.testing.assert_allclose(timed["flip_time"].values, plain["flip_time"].values + 1e-5 * draws,
                                   rtol=0, atol=1e-14)
        fits = ensemble.fit(timed)
    z = fits["flip_z"].values[fits["flips"].values >= 3]  # a member of fewer crossings has no period
    assert z.size > 250 and 0.8 < np.std(z) < 1.2 and kstest(z, "norm").pvalue > 1e-3, (z.size, np.std(z))


def test_a_heavy_tops_nutation_period_from_its_turning_points_is_the_elliptic_one(tmp_path):
    """runs/heavy_top.toml: tops released at a tilt of 0.5 rad with their spin alone nutate between that tilt
    (a root of the cubic f(u), u = cos(tilt)) and a lower one; their turning points (the scene's event function
    u' = 0) are half a period apart, the period 4 K(m) / sqrt(beta (u3 - u1)), and near the fast top's
    2 pi lambda1 / (lambda3 w3); the precession angle kept at them (keep) advances at the mean rate that a
    quadrature over a nutation period gives, near the fast top's M g R / (lambda3 w3)."""
    out = tmp_path / "heavy.nc"
    assert cli.main(["run", str(RUNS / "heavy_top.toml"), "-o", str(out), "--quiet"]) == 0
    assert cli.main(["fit", str(out), "--check"]) == 0
    heavy_top = example("heavy_top")
    with xr.open_dataset(out) as ds, xr.open_dataset(tmp_path / "heavy_fit.nc") as fits:
        spin = ds["w30"].values
        start = [np.broadcast_to(ds[f"{name}0"].values, spin.shape) for name in heavy_top.STATE]
        moments = [np.broadcast_to(ds[name].values, spin.shape) for name in ("lambda1", "lambda3", "MgR")]
        u1, u2, u3 = heavy_top.nutation_roots(*start, *moments)
        assert np.allclose(u2, math.cos(0.5), rtol=0, atol=1e-12) and np.all((u1 < u2) & (u3 > 1))
        theory = fits["nutation_period_theory"].values
        assert np.allclose(fits["nutation_period"].values, theory, rtol=1e-9, atol=0)
        ratio = theory / (2 * np.pi * 1e-3 / (5e-4 * spin))  # to the fast top's period, spins in rising order
        assert np.all(np.diff(ratio) < 0) and np.all(ratio > 1) and ratio[-1] < 1.01
        assert np.all(ds["turn_count"].values == np.floor(2.0 / (theory / 2)))  # a turning point every half period
        precession = fits["precession_rate_theory"].values  # phi kept at each turning point: its mean rate
        assert np.allclose(fits["precession_rate"].values, precession, rtol=1e-9, atol=0)
        fast = precession / (0.05 / (5e-4 * spin))  # to the fast top's M g R / (lambda3 w3)
        assert np.all(np.diff(fast) < 0) and np.all(fast > 1) and fast[-1] < 1.01


def test_a_sleeping_top_stays_up_above_the_spin_threshold_and_falls_below_it(tmp_path):
    """runs/sleeping_top.toml: tops at a tilt of 0.05 rad, spun across (lambda3 w3)^2 = 4 lambda1 M g R, each
    stopped at its first turning point: the tilt kept there is the cubic's arccos(u1), large below the threshold
    and near the start above it."""
    out = tmp_path / "sleeping.nc"
    assert cli.main(["run", str(RUNS / "sleeping_top.toml"), "-o", str(out), "--quiet"]) == 0
    assert cli.main(["fit", str(out), "--check"]) == 0
    with xr.open_dataset(out) as ds, xr.open_dataset(tmp_path / "sleeping_fit.nc") as fits:
        threshold = 2 * math.sqrt(1e-3 * 0.05) / 5e-4  # rad/s
        below = ds["w30"].values < threshold
        assert below.any() and (~below).any() and np.all(ds["status"].values == Status.STOPPED_BY_EVENT)
        tilt = fits["max_tilt"].values
        assert np.allclose(tilt, fits["max_tilt_theory"].values, rtol=1e-9, atol=0)
        assert np.all(tilt[below] > 0.9) and np.all(tilt[~below] < 0.11)


def pendulum_runfile(extra: str = "", save: str | None = None) -> str:
    return (f'scene = "{PENDULUM}"\nmethod = "rk4"\ndt = 0.02\nt_end = 10.0\nsave_dt = 0.1\nmembers = 4\n'
            f'seed = 3\n' + (f"save = {save}\n" if save is not None else "") +
            '[parameters]\nomega0 = 2.0\ntheta0 = { uniform = [0.3, 3.0] }\n'
            '[events.bottom]\nof = "theta"\ndirection = "up"\nstop = true\n'
            '[events.axle]\nof = "height"\nvalue = 1.0\ndirection = "down"\ncount = 2\n' + extra)


def test_a_run_file_stops_members_at_an_event_and_keeps_their_state_there(tmp_path, capsys):
    path = tmp_path / "run.toml"
    path.write_text(pendulum_runfile())
    assert cli.main(["run", str(path), "-o", str(tmp_path / "a.nc"), "--quiet"]) == 0
    assert "; 4 stopped at events" in capsys.readouterr().out
    with xr.open_dataset(tmp_path / "a.nc") as ds:
        theta0 = ds["theta0"].values
        first_up = example("pendulum").crossing_times(theta0, OMEGA0, 2)[:, 1]  # down through 0 first, then up
        assert np.all(ds["status"].values == Status.STOPPED_BY_EVENT)
        assert np.all(np.isnan(ds["failure_time"].values))  # stopped, not failed
        assert np.allclose(ds["bottom_time"].values[:, 0], first_up, rtol=0, atol=1e-6)
        assert np.all(ds["bottom_count"].values == 1)
        assert np.array_equal(ds["steps_accepted"].values, np.ceil(first_up / 0.02))  # to the step it stopped in
        assert np.allclose(ds["theta_at_stop"].values, 0.0, atol=1e-9)
        assert np.allclose(ds["theta_dot_at_stop"].values, 2 * np.sin(theta0 / 2) * OMEGA0, rtol=1e-6)
        t = ds["t"].values[None, :]
        theta = ds["theta"].values
        assert np.all(np.isnan(theta[t > first_up[:, None] + 0.1]))
        assert np.all(np.isfinite(theta[t < first_up[:, None]]))
        above = theta0 > math.pi / 2  # those fall through the axle's height from either side before the stop
        assert np.all(ds["axle_count"].values == 2 * above) and ds.sizes["axle"] == 2
        assert np.array_equal(np.isfinite(ds["axle_time"].values), np.repeat(above[:, None], 2, axis=1))
        first_fall = example("pendulum").height_times(theta0[above], OMEGA0, 1.0)
        assert np.allclose(ds["axle_time"].values[above, 0], first_fall, rtol=0, atol=1e-6)
        assert ds["status"].attrs["flag_meanings"].split()[3] == "stopped_by_event"
        whole = ds.load()
    # events alone (save = []), and one member per chunk: the same bits
    path.write_text(pendulum_runfile(save="[]"))
    assert cli.main(["run", str(path), "-o", str(tmp_path / "b.nc"), "--quiet", "--chunk", "1"]) == 0
    with xr.open_dataset(tmp_path / "b.nc") as alone:
        assert "theta" not in alone and "theta_at_stop" not in alone
        for name in ("bottom_time", "bottom_count", "axle_time", "axle_count", "status"):
            np.testing.assert_array_equal(alone[name].values, whole[name].values)


def bad_pendulum(extra: str) -> str:
    return (f'scene = "{PENDULUM}"\nmethod = "rk4"\ndt = 0.02\nt_end = 1.0\nsave_dt = 0.5\nmembers = 1\nseed = 3\n'
            '[parameters]\nomega0 = 2.0\ntheta0 = 1.0\n' + extra)


@pytest.mark.parametrize("table, expected", [
    ('[events.e]\nof = "phi"\n', "events.e.of: unknown variable 'phi'"),
    ('[events.e]\nof = "theta"\ncount = 0\n', "events.e.count: must be in 1..10000"),
    ('[events.e]\nof = "theta"\ncount = 1000000000\n', "events.e.count: must be in 1..10000"),
    ('[events.e]\nof = "theta"\ndirection = "sideways"\n', "events.e.direction: must be one of"),
    ('[events.e]\nof = "theta"\nindex = 1\n', "events.e.index: 'theta' is a single value"),
    ('[events.theta_dot]\nof = "theta"\n', "events.theta_dot: its variable 'theta_dot' would clash"),
    ('[events.omega0]\nof = "theta"\n', "would clash"),
    ('[events.e]\nvalue = 1.0\n', "events.e.of: is missing"),
    ('[events.e]\nof = "theta"\nlevel = 1.0\n', "events.e.level: unknown key"),
    ('[events.e]\nof = "theta"\nkeep = ["theta", "psi"]\n', "events.e.keep[1]: unknown variable 'psi'"),
    ('[events.e]\nof = "theta"\nkeep = ["theta", "theta"]\n', "events.e.keep[1]: names 'theta' a second time"),
    ('[events.e]\nof = "theta"\nkeep = "theta"\n', "events.e.keep: must be"),
    ('[events.e]\nof = "theta"\nkeep = ["theta"]\n[events.e_theta]\nof = "theta"\n', "would clash"),
    ('[events.e]\nof = "theta"\n[observe]\nnoise = { f_time = 0.1 }\n',
     "observe.noise.f_time: unknown key (did you mean 'e_time'?)"),
    ('[events.e]\nof = "theta"\n[observe]\nnoise = { e_time = -0.1 }\n', "observe.noise.e_time: must be a standard"),
])
def test_a_bad_events_table_is_one_line_and_nothing_written(tmp_path, capsys, table, expected):
    refused(bad_pendulum(table), tmp_path, capsys, expected)


def test_a_vector_without_index_and_an_event_function_of_the_wrong_signature_are_refused(tmp_path, capsys):
    refused(top_runfile() + '[events.e]\nof = "omega"\n', tmp_path, capsys, "events.e.index: 'omega' is a vector")
    refused(top_runfile() + '[events.e]\nof = "omega"\nindex = 3\n', tmp_path, capsys, "must be in 0..2")
    scene = tmp_path / "scene.py"
    scene.write_text(PENDULUM.read_text().replace("def event_height(t, theta, theta_dot, omega0):",
                                                  "def event_height(t, theta):"))
    line = refused(bad_pendulum('[events.e]\nof = "height"\n').replace(str(PENDULUM), str(scene)), tmp_path, capsys,
                   "event_height takes 2 argument(s)")
    assert "scene.py" in line
    from .test_chain import chain_runfile

    refused(chain_runfile() + '[events.e]\nof = "x"\n', tmp_path, capsys, "events.e.index: 'x' is a vector over site")
    refused(chain_runfile() + '[events.e]\nof = "energy"\n', tmp_path, capsys,
            "events.e.of: unknown variable 'energy'; chain's events watch: x, v; energy cannot be watched yet")
