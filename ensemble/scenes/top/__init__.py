"""The torqued symmetric top: its model (equations, closed form, observables, theory) and, in `physics`, the
right-hand side and pieces its kernels are built from. The model's names are this package's, so
`ensemble.scenes.top.exact` is the closed form."""
from .model import *  # noqa: F403
