"""ensemble: Numba ensembles of classical-mechanics scenes, stored as NetCDF."""
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("ensemble")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0+unknown"

from .errors import EnsembleError  # noqa: E402 (the root of every error ensemble raises)
from .parameter import Parameter, ParameterError  # noqa: E402 (what a scene file of your own imports)

__all__ = ["EnsembleError", "Parameter", "ParameterError", "__version__"]
