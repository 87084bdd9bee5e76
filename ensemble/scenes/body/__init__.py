"""The free rigid body with three different moments: its model (Euler's equations, the elliptic closed form,
observables, linear theory) and, in `physics`, the right-hand side and pieces its kernels are built from."""
from .model import *  # noqa: F403
