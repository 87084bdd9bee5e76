"""Spring chains: their model (forces, normal modes, modal solution, energy, theory) and, in `kernels`, their
compiled kernels. The model's names are this package's, so `ensemble.scenes.chain.normal_modes` works."""
from .model import *  # noqa: F403
