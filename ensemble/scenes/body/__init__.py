"""The free rigid body with three different moments: its model (Euler's equations, the elliptic closed form,
observables, linear theory) and, in `kernels`, its compiled kernels."""
from .model import *  # noqa: F403
