"""The torqued symmetric top: its model (equations, closed form, observables, theory) and, in `kernels`, its
compiled kernels. The model's names are this package's, so `ensemble.scenes.top.exact` is the closed form."""
from .model import *  # noqa: F403
