"""ensemble.libm: the C library's functions, value by value, whatever SIMD code NumPy would pick for this CPU."""
import math

import numpy as np
import pytest

from ensemble import libm

VALUES = np.random.default_rng(3).uniform(-20.0, 20.0, 20000)
OTHERS = np.random.default_rng(4).uniform(-20.0, 20.0, 20000)


@pytest.mark.parametrize("name, scalar", [("exp", math.exp), ("expm1", math.expm1), ("sin", math.sin),
                                          ("cos", math.cos), ("tan", math.tan), ("arctan", math.atan),
                                          ("tanh", math.tanh), ("log", lambda x: math.log(abs(x)))])
def test_each_function_is_the_c_librarys_bit_for_bit(name, scalar):
    """Python's math module calls the C library: an independent computation of the same values."""
    values = np.abs(VALUES) if name == "log" else VALUES
    np.testing.assert_array_equal(getattr(libm, name)(values), [scalar(v) for v in VALUES])


def test_arctan2_is_the_c_librarys_and_hypot_within_an_ulp_of_pythons():
    """atan2 as math's; hypot within one unit in the last place of math.hypot (CPython's own algorithm, not the
    C library's)."""
    np.testing.assert_array_equal(libm.arctan2(VALUES, OTHERS), [math.atan2(y, x) for y, x in zip(VALUES, OTHERS)])
    got = libm.hypot(VALUES, OTHERS)
    assert np.all(np.abs(got - [math.hypot(x, y) for x, y in zip(VALUES, OTHERS)]) <= np.spacing(got))


def test_shapes_broadcast_as_numpys():
    grid = libm.hypot(np.arange(3.0)[:, None], np.arange(4.0)[None, :])
    assert grid.shape == (3, 4) and grid[0, 3] == 3.0 and grid[2, 0] == 2.0
    assert libm.exp(0.0) == 1.0 and libm.exp(np.zeros((2, 0))).shape == (2, 0)
