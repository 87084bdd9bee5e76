"""Spring chains: their model (normal modes, modal solution, energy, theory) and, in `physics`, the compiled
acceleration their kernels are built from. The model's names are this package's, so
`ensemble.scenes.chain.normal_modes` works."""
from .model import *  # noqa: F403
