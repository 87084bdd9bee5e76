"""ensemble: Numba ensembles of classical-mechanics scenes, stored as NetCDF."""
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("ensemble")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0+unknown"
