"""ensemble: Numba ensembles of classical-mechanics scenes (tops, spring chains, free rigid bodies, scenes of your
own), stored as NetCDF, and their fits against theory.

    import ensemble
    ds = ensemble.run("runs/aerobie.toml")   # an xarray.Dataset
    fits = ensemble.fit(ds)                  # fitted rates against c (1/lambda1 - 1/lambda3)
"""
import os as _os

# Intel's SVML (a Numba whose LLVM has it, with icc_rt installed) would vectorize the kernels' sin, exp, ... with
# functions of its own: other bits than the C library's on every other host. Read when Numba is imported.
_os.environ.setdefault("NUMBA_DISABLE_INTEL_SVML", "1")

from . import tuning as _tuning  # noqa: E402
from .version import __version__  # noqa: E402

_tuning.prepare()  # this machine's `ensemble tune` choices, before any Numba function of ours is made

from .errors import EnsembleError  # noqa: E402 (the root of every error ensemble raises)
from .parameter import Parameter, ParameterError  # noqa: E402 (what a scene file of your own imports)

__all__ = ["EnsembleError", "Parameter", "ParameterError", "__version__", "fit", "open", "run"]


def __getattr__(name: str):
    """ensemble.run, ensemble.open and ensemble.fit (ensemble.api), imported when first used: a command-line run
    does not load xarray before it needs it."""
    if name in ("run", "open", "fit"):
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'ensemble' has no attribute {name!r}")
