"""The installed package's version, which results and worker checks record ("0+unknown" in a source tree that is
not installed)."""
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("ensemble")
except PackageNotFoundError:
    __version__ = "0+unknown"
