"""The method families as code (ensemble.engine.runge_kutta): one member's step, called directly."""
import numpy as np
import pytest
from numba import njit

from ensemble.engine import runge_kutta
from ensemble.engine.kernels import pair_of, tableau_of
from ensemble.engine.tuples import unrolled
from ensemble.methods import METHODS

OMEGA = 1.7  # rad/s


@njit
def oscillator(t, x, v, omega):
    """A harmonic oscillator: x'' = -omega^2 x."""
    return v, -omega * omega * x


@njit
def clock(t, y):
    """y' = t^3: a step's error shows whether its stages are taken at their nodes."""
    return (t * t * t,)


TABLEAUS = [name for name, method in METHODS.items() if method.tableau is not None]


@pytest.mark.parametrize("name", TABLEAUS)
def test_a_step_on_a_harmonic_oscillator_is_the_methods_stability_function(name):
    """On y' = A y a Runge-Kutta step is R(h A) y, R the method's stability function (methods.Tableau.stability,
    a linear solve of its own): computed through A's eigenvalues +-i omega, for three step sizes."""
    method = METHODS[name]
    stages, weights = tableau_of(method)
    A = np.array([[0.0, 1.0], [-OMEGA**2, 0.0]])
    values, vectors = np.linalg.eig(A)
    for h in (0.01, 0.1, 0.5):
        y = np.array([0.3, -0.8])
        expected = (vectors @ np.diag(method.tableau.stability(h * values)) @ np.linalg.solve(vectors, y)).real
        stepped = runge_kutta.step(oscillator, 0.25, h, (0.3, -0.8), (OMEGA,), stages, weights, unrolled(len(weights)))
        np.testing.assert_allclose(stepped, expected, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("name", TABLEAUS)
def test_a_steps_stages_are_taken_at_their_nodes(name):
    """y' = t^3 from t = 2: a method of order q >= 4 (rk4, dopri5) integrates it exactly, one of lower order errs
    by its quadrature's error, which a test of the weights alone (b) cannot show: the nodes c enter it."""
    method = METHODS[name]
    stages, weights = tableau_of(method)
    t, h = 2.0, 0.1
    (stepped,) = runge_kutta.step(clock, t, h, (1.0,), (), stages, weights, unrolled(len(weights)))
    exact = 1.0 + ((t + h) ** 4 - t**4) / 4
    quadrature = 1.0 + h * sum(b * (t + c * h) ** 3 for b, c in zip(method.tableau.b, method.tableau.c))
    assert stepped == pytest.approx(quadrature, rel=1e-15)
    if method.order >= 4:
        assert stepped == pytest.approx(exact, rel=1e-14)
    else:
        assert abs(stepped - exact) > 1e-6


@njit
def pushed(t, x, v):
    """Slopes as a scene may write them: an integer, and a float64 literal times a float32 value (a float64)."""
    return 1, 2.0 * v


@pytest.mark.parametrize("name", ["rk4", "dopri5"])
def test_a_scenes_slopes_take_the_states_type(name):
    """A float32 member stays float32 whatever types its scene's slopes come in (a stage's slopes are converted
    to the state's type), and an integer slope is a number: x' = 1, v' = 2 v from (0.5, 1) over h = 0.1 is
    (0.6, exp(0.2)) to the method's error."""
    stages, weights = tableau_of(METHODS[name])
    y = (np.float32(0.5), np.float32(1.0))
    x, v = runge_kutta.step(pushed, np.float32(0.0), np.float32(0.1), y, (), stages, weights, unrolled(len(weights)))
    assert np.float32(x) == x and np.float32(v) == v  # float32 values (Numba returns them as Python floats)
    assert x == pytest.approx(0.6, rel=1e-6) and v == pytest.approx(np.exp(0.2), rel=1e-5)  # rk4: (2h)^5 / 120


def test_dopri5s_trial_step_and_error_norm_are_scipys():
    """The adaptive pair's trial step (ensemble.engine.adaptive) against scipy's RK45, an implementation of its
    own of the same Dormand-Prince pair: the new state, its last slopes (FSAL), and the error norm with scipy's
    scale atol + rtol max(|y|, |y_new|)."""
    from scipy.integrate._ivp import rk

    from ensemble.engine import adaptive

    stages, error = pair_of(METHODS["dopri5"])
    y, t, h, rtol, atol = np.array([0.3, -0.8]), 0.25, 0.2, 1e-6, 1e-9
    k0 = np.array(oscillator.py_func(t, *y, OMEGA))
    K = np.empty((rk.RK45.n_stages + 1, 2))
    new, last = rk.rk_step(lambda t, y: np.array(oscillator.py_func(t, *y, OMEGA)), t, y, k0, h, rk.RK45.A,
                           rk.RK45.B, rk.RK45.C, K)
    slopes, stepped = adaptive.trial_step(oscillator, t, h, (0.3, -0.8), (OMEGA,), tuple(k0), stages,
                                          unrolled(len(error)))
    np.testing.assert_allclose(stepped, new, rtol=1e-15, atol=1e-16)
    np.testing.assert_allclose(slopes[-1], last, rtol=1e-15, atol=1e-16)
    scale = atol + np.maximum(np.abs(y), np.abs(new)) * rtol
    expected = np.linalg.norm(K.T @ rk.RK45.E * h / scale) / np.sqrt(2)
    norm = adaptive.error_norm(h, (0.3, -0.8), tuple(stepped), slopes, error, rtol, atol)
    assert norm == pytest.approx(expected, rel=1e-12) and norm > 1.0  # a step this long is rejected
