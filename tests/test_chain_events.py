"""Events on a field of sites (ensemble.engine.sites_kernels): a chain's crossings located on each member's own
step, against the two-mass chain's closed form: started from x = (a, 0) at rest, mass 1 moves as
x1 = a/2 (cos w1 t + cos w2 t), w1 = sqrt(k/m), w2 = sqrt(3 k/m), so it crosses 0 at (2j + 1) pi / (w1 + w2) and
(2j + 1) pi / (w2 - w1); mass 2's velocity is v2 = a/2 (w2 sin w2 t - w1 sin w1 t). Members that stop at an event,
runs in segments and resumed, a ring (its ends' ghosts), and the layout a run with events takes."""
import numpy as np
import pytest
from scipy.optimize import brentq

from ensemble.engine import kernels, launch
from ensemble.engine.sites import CHECK_STEPS
from ensemble.methods import METHODS
from ensemble.results import Event, Status
from ensemble.scenes import resolve

CHAIN = resolve("chain")
FIXED = {"n": 2, "boundary": "fixed"}
K = np.array([1.0, 1.5, 2.0, 0.7])  # N/m, per member
A = np.array([0.1, 0.05, 0.2, 0.1])  # m: mass 1's displacement at the start
T_END, SAVE_DT = 20.0, 0.1
# One kernel per method for every test here: the events' sources (x of mass 1, v of mass 2, rows 0 and 3 of the
# state) fix it; their levels, directions, counts and stops are the run's.
CROSS = Event("cross", "x", 0, ("state", 0), 0.0, "both", 20, keep=("x", "v"))
TURN = Event("turn", "v", 1, ("state", 3), 0.0, "down", 8)
SETTINGS = {"verlet": dict(dt=1e-2), "symplectic_euler": dict(dt=1e-3), "rk4": dict(dt=1e-2),
            "dopri5": dict(dt=np.nan, rtol=1e-9, atol=1e-12)}


def pluck(method: str, events=(CROSS, TURN), members=slice(None), save_dt=SAVE_DT, **settings):
    """The two-mass chains of K, A started from x = (A, 0) at rest, with `events`: the launch's Outcome."""
    M = len(K)
    values = {"m": np.ones((M, 2)), "k": np.repeat(K[:, None], 3, axis=1), "x0": np.stack((A, np.zeros(M)), 1),
              "v0": np.zeros((M, 2))}
    values = {name: value[members] for name, value in values.items()}
    return launch.integrate(CHAIN, METHODS[method], values, FIXED, n_save=round(T_END / save_dt) + 1,
                            save_dt=save_dt, events=events, **{**SETTINGS[method], **settings})


def motion(t):
    """x1, v1, x2, v2 and mass 2's acceleration a2 of each member at times t (..., members)."""
    w1, w2 = np.sqrt(K), np.sqrt(3 * K)
    c1, c2, s1, s2 = np.cos(w1 * t), np.cos(w2 * t), np.sin(w1 * t), np.sin(w2 * t)
    return (A / 2 * (c1 + c2), -A / 2 * (w1 * s1 + w2 * s2), A / 2 * (c1 - c2), A / 2 * (w2 * s2 - w1 * s1),
            A / 2 * (w2**2 * c2 - w1**2 * c1))


def roots(function, t_end: float, falling_only: bool = False) -> list[float]:
    """The roots of function(t) in (0, t_end), bracketed on a grid of 1e-3 s and found by brentq (only where it
    falls, if falling_only)."""
    t = np.arange(0.0, t_end, 1e-3)
    f = function(t)
    found = []
    for i in np.nonzero(np.sign(f[1:]) != np.sign(f[:-1]))[0]:
        if i > 0 and (not falling_only or f[i] > 0 > f[i + 1]):
            found.append(brentq(function, t[i], t[i + 1], xtol=1e-15, rtol=1e-15))
    return found


def own_errors(outcome) -> tuple[np.ndarray, np.ndarray]:
    """The method's largest error in x1 and in v2 over the saved samples, per member."""
    t = np.arange(outcome.samples.shape[0])[:, None] * SAVE_DT
    x1, _, _, v2, _ = motion(t)
    return (np.nanmax(np.abs(outcome.samples[:, 0] - x1), axis=0),
            np.nanmax(np.abs(outcome.samples[:, 3] - v2), axis=0))


@pytest.mark.parametrize("method", ["rk4", "verlet", "symplectic_euler", "dopri5"])  # merged half kicks, or not
def test_a_chains_crossings_are_the_closed_forms_to_the_methods_own_error(method):
    outcome = pluck(method)
    own_x, own_v = own_errors(outcome)
    w1, w2 = np.sqrt(K), np.sqrt(3 * K)
    assert np.all(outcome.status == Status.OK)
    for j in range(len(K)):
        odd = 2 * np.arange(40) + 1
        exact = np.sort(np.concatenate((odd * np.pi / (w1[j] + w2[j]), odd * np.pi / (w2[j] - w1[j]))))
        exact = exact[exact < T_END]
        assert outcome.event_counts[0, j] == len(exact)
        times = outcome.event_times[0, :, j]
        kept = min(len(exact), CROSS.count)
        assert np.all(np.isnan(times[kept:]))
        _, v1, _, _, _ = motion(exact[:kept, None])
        error = np.abs(times[:kept] - exact[:kept])
        assert np.all(error * np.abs(v1[:, j]) <= 2.0 * own_x[j] + 1e-13), (error, own_x[j])
        states = outcome.event_states[0, :kept, :, j]  # (x1, x2, v1, v2) kept at each crossing
        assert np.max(np.abs(states[:, 0])) < 1e-12
        assert np.all(np.abs(states[:, 2] - v1[:, j]) <= 4.0 * w2[j] * own_x[j] + 1e-12)
        # mass 2's velocity falling through 0: a crossing of the second event's own variable
        turns = roots(lambda t, j=j: motion(t[..., None] if np.ndim(t) else np.array([t]))[3][..., j],
                      T_END, falling_only=True)
        assert outcome.event_counts[1, j] == len(turns)
        kept = min(len(turns), TURN.count)
        _, _, _, _, a2 = motion(np.array(turns[:kept])[:, None])
        error = np.abs(outcome.event_times[1, :kept, j] - turns[:kept])
        assert np.all(error * np.abs(a2[:, j]) <= 2.0 * own_v[j] + 1e-13), (error, own_v[j])
    assert np.nanmax(np.abs(outcome.event_times[0].T[:, 0] - np.pi / (w1 + w2))) > 0.0  # (not exact by accident)
    if method == "verlet":  # watched between its merged half kicks: the samples of the kernel without events
        np.testing.assert_array_equal(outcome.samples, pluck(method, events=()).samples)


def test_chain_members_stop_at_an_event_the_others_run_on():
    """Mass 1 falling through -0.06 m stops its member: those of amplitude 0.1 and 0.2 m reach it, that of 0.05 m
    never does. A stopped member's state is the method's at the event, its later samples NaN."""
    level = -0.06
    stop = Event("cross", "x", 0, ("state", 0), level, "down", 1, True)
    outcome = pluck("rk4", (stop, TURN))
    own_x, _ = own_errors(outcome)
    reaches = A > -level
    assert np.array_equal(outcome.status == Status.STOPPED_BY_EVENT, reaches)
    assert np.all(outcome.status[~reaches] == Status.OK) and np.all(np.isnan(outcome.failure_time))
    first = np.array([roots(lambda t, j=j: motion(t[..., None] if np.ndim(t) else np.array([t]))[0][..., j] - level,
                            T_END)[0] for j in np.nonzero(reaches)[0]])
    when = outcome.event_times[0, 0, reaches]
    _, v1, _, _, _ = motion(first[:, None])
    assert np.all(np.abs(when - first) * np.abs(np.diag(v1[:, reaches])) <= 2.0 * own_x[reaches] + 1e-13)
    stopped = outcome.stopped[:, reaches]
    assert np.allclose(stopped[0], level, rtol=0, atol=1e-12) and np.all(np.isnan(outcome.stopped[:, ~reaches]))
    x1, v1, x2, v2, _ = (np.diag(value[:, reaches]) for value in motion(when[:, None]))
    assert np.allclose(stopped, np.stack((x1, x2, v1, v2)), rtol=0, atol=10 * np.max(own_x))
    assert np.array_equal(outcome.counts[0, reaches], np.ceil(when / SETTINGS["rk4"]["dt"]))  # to its stop's step
    t = np.arange(outcome.samples.shape[0]) * SAVE_DT
    for j, w in zip(np.nonzero(reaches)[0], when):
        assert np.all(np.isnan(outcome.samples[t > w, :, j])) and np.all(np.isfinite(outcome.samples[t < w, :, j]))
    assert np.all(np.isfinite(outcome.samples[:, :, ~reaches]))


def test_a_chain_run_in_segments_resumed_or_alone_finds_the_bits_of_one_call():
    whole = pluck("rk4")
    M = len(K)
    values = {"m": np.ones((M, 2)), "k": np.repeat(K[:, None], 3, axis=1), "x0": np.stack((A, np.zeros(M)), 1),
              "v0": np.zeros((M, 2))}
    call = launch.new_launch(CHAIN, METHODS["rk4"], values, FIXED, n_save=201, save_dt=SAVE_DT, dt=1e-2,
                             events=(CROSS, TURN), segment=7)
    kept = next((first + 7, call.state()) for first, _ in call.segments() if first == 98)
    list(call.segments(resume=kept))
    np.testing.assert_array_equal(call.outcome().event_times, whole.event_times)
    np.testing.assert_array_equal(call.outcome().event_counts, whole.event_counts)
    # a step's start is replayed from the state kept every 32 steps: saving every 100 steps, the same bits
    sparse = pluck("rk4", save_dt=1.0)
    np.testing.assert_array_equal(sparse.event_times, whole.event_times)
    np.testing.assert_array_equal(sparse.event_states, whole.event_states)
    alone = pluck("rk4", members=slice(2, 3))  # in a block of its own
    np.testing.assert_array_equal(alone.event_times[..., 0], whole.event_times[..., 2])
    np.testing.assert_array_equal(alone.event_states[..., 0], whole.event_states[..., 2])


def test_a_rings_crossings_are_its_modal_solutions():
    """Three masses on a ring (its ends each other's neighbours, through the kernels' ghost sites), started at
    rest from x = (a, -a, 0) (the ring's centre of mass at rest): mass 3's crossings of 0 against the modal
    closed form (the scene's `exact`), root-found."""
    ring = {"n": 3, "boundary": "periodic"}
    values = {"m": np.array([[1.0, 2.0, 1.5]]), "k": np.array([[1.0, 0.5, 2.0]]), "x0": np.array([[0.1, -0.1, 0.0]]),
              "v0": np.zeros((1, 3))}
    event = Event("cross", "x", 2, ("state", 2), 0.0, "both", 40)
    outcome = launch.integrate(CHAIN, METHODS["verlet"], values, ring, n_save=201, save_dt=SAVE_DT, dt=1e-3,
                               events=(event,))
    def exact(t):
        x3 = CHAIN.exact(values, ring, np.atleast_1d(t))[:, 2, 0]
        return x3 if np.ndim(t) else float(x3[0])
    t = np.arange(201) * SAVE_DT
    own = np.max(np.abs(outcome.samples[:, 2, 0] - exact(t)))
    found = roots(exact, T_END)
    assert outcome.event_counts[0, 0] == len(found) > 5
    speed = np.abs(CHAIN.exact(values, ring, np.array(found))[:, 5, 0])
    assert np.all(np.abs(outcome.event_times[0, :len(found), 0] - found) * speed <= 2.0 * own + 1e-13)


def test_a_chain_with_events_steps_whole_and_untiled():
    """A long chain's splitting runs in tiles, across steps; with events it takes each step whole, untiled, so
    that each member's state at a step's end is there to watch."""
    long = {"n": 1029, "boundary": "fixed"}
    assert kernels.layout(CHAIN, METHODS["verlet"], long).tiled
    with_events = kernels.layout(CHAIN, METHODS["verlet"], long, events=(("state", 0),))
    assert not with_events.tiled
    plain = kernels.layout(CHAIN, METHODS["verlet"], long)
    # the event's values through a group of CHECK_STEPS steps, and the state at the group's start
    assert with_events.rows == plain.rows + (CHECK_STEPS + 1) + 2 * 1029 + 1


@pytest.mark.parametrize("method", ["rk4", "verlet"])
def test_several_crossings_in_one_watched_group_each_located_and_none_after_a_stop(method):
    """Stiff springs: mass 1 crosses 0 every 13 steps or sooner, several times in a group of CHECK_STEPS steps
    that a kernel watches at once, until mass 2 falling through -0.06 m stops its member mid-group (those of
    amplitude 0.1 and 0.2 m; that of 0.05 m never). Each crossing is the closed form's to the method's own
    error, none is counted after the stop, and saving every 8 steps (groups of 8) gives the same crossings."""
    k, a, dt, t_end = np.array([300.0, 330.0, 360.0, 400.0]), np.array([0.1, 0.05, 0.2, 0.1]), 1e-2, 2.0
    w1, w2 = np.sqrt(k), np.sqrt(3 * k)  # rad/s: mass 1 at a/2 (cos w1 t + cos w2 t), mass 2 at a/2 (cos w1 t - ..)
    assert np.all(2 * np.pi / (w1 + w2) < 14 * dt)
    values = {"m": np.ones((4, 2)), "k": np.repeat(k[:, None], 3, axis=1), "x0": np.stack((a, np.zeros(4)), 1),
              "v0": np.zeros((4, 2))}
    events = (Event("cross", "x", 0, ("state", 0), 0.0, "both", 400),
              Event("low", "x", 1, ("state", 1), -0.06, "down", 1, True))

    def run(save_steps):
        return launch.integrate(CHAIN, METHODS[method], values, FIXED, n_save=round(t_end / (save_steps * dt)) + 1,
                                save_dt=save_steps * dt, dt=dt, events=events)

    outcome = run(20)
    every_step = launch.integrate(CHAIN, METHODS[method], values, FIXED, n_save=round(t_end / dt) + 1, save_dt=dt,
                                  dt=dt).samples[:, 0]  # mass 1's x after every step, without events
    t = np.arange(len(every_step))[:, None] * dt
    own = np.max(np.abs(every_step - a / 2 * (np.cos(w1 * t) + np.cos(w2 * t))), axis=0)  # m: the method's error
    for j in range(4):
        def x2(t, j=j):
            return a[j] / 2 * (np.cos(w1[j] * t) - np.cos(w2[j] * t)) + 0.06
        stopped = roots(x2, t_end, falling_only=True)[:1]
        assert (outcome.status[j] == Status.STOPPED_BY_EVENT) == bool(stopped) == (a[j] > 0.06)
        odd = 2 * np.arange(200) + 1
        exact = np.sort(np.concatenate((odd * np.pi / (w1[j] + w2[j]), odd * np.pi / (w2[j] - w1[j]))))
        exact = exact[exact < min(stopped + [t_end])]
        assert outcome.event_counts[0, j] == len(exact)
        if not stopped:
            assert np.bincount((exact / dt).astype(int) // CHECK_STEPS).max() >= 2  # several in one group
        times = outcome.event_times[0, :len(exact), j]
        speed = np.abs(a[j] / 2 * (w1[j] * np.sin(w1[j] * exact) + w2[j] * np.sin(w2[j] * exact)))
        assert np.all(np.abs(times - exact) * speed <= 2.0 * own[j] + 1e-13)
        assert np.all(np.isnan(outcome.event_times[0, len(exact):, j]))
        if stopped:  # mass 1 would cross again in the stop's own group
            assert abs(outcome.event_times[1, 0, j] - stopped[0]) < 1e-3
            after = np.min(odd * np.pi / (w1[j] + w2[j]), where=odd * np.pi / (w1[j] + w2[j]) > stopped[0],
                           initial=np.inf)
            assert int(after / dt) // CHECK_STEPS == int(stopped[0] / dt) // CHECK_STEPS
    dense = run(8)
    np.testing.assert_array_equal(dense.event_counts, outcome.event_counts)
    if method == "rk4":
        np.testing.assert_array_equal(dense.event_times, outcome.event_times)
    else:  # verlet's merged half kicks are split at every saved time: the same steps to rounding
        np.testing.assert_allclose(dense.event_times, outcome.event_times, rtol=0, atol=1e-13)
