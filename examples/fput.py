"""A Fermi-Pasta-Ulam-Tsingou alpha chain: masses joined by springs whose force grows with the stretch d as
k (d + ALPHA d^2), between walls, free or in a ring. The chain's parameters (n, boundary, m, k, x0, v0: see
`ensemble.scenes.chain`) and one function: the acceleration of a mass between its neighbours.

    ensemble run runs/fput.toml
"""
from numba import njit

NAME = "fput"
SITES = True  # a member is a field of n sites, each moved by its two neighbours
ALPHA = 0.25  # 1/m: the springs' quadratic stiffening


@njit(inline="always")
def acceleration(x_left, x, x_right, c_left, c_right):
    """Acceleration (m s-2) of a mass at x (m) between neighbours at x_left and x_right; c_left and c_right
    (s-2) are the springs' k on each side over the mass."""
    right, left = x_right - x, x - x_left
    return c_right * (right + ALPHA * right * right) - c_left * (left + ALPHA * left * left)
