"""A scene's kernel for a method: its family's template (ensemble.engine.templates) filled in with the scene's
physics, written as a Python file that Numba keys its disk cache on, then imported.

The file's name holds a hash of its text, and its text holds hashes of the scene's physics file and of the
engine's helpers (blocks.HELPERS): a change to any of them makes a new file, which compiles once, and a file is
never rewritten (Numba's cache index checks its source file's time stamp). The files live in kernel_folder().
"""
from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
import tempfile
from functools import cache
from pathlib import Path
from types import ModuleType

from numba import njit
from numba.core.registry import CPUDispatcher

from ..methods import Method
from ..scenes.contract import load, python_function
from ..tuning import applied, generated_block, kernel_folder
from . import sites, templates
from .blocks import FAST, HELPERS, Kernel

BLOCK = 128  # members per block of a scene whose kernel_rows are its whole state (rows of B floats each)


def physics_functions(where: str, names: tuple[str, ...]) -> tuple:
    """The compiled functions `names` of a scene's physics: its own @njit functions as they are, plain Python
    functions compiled to be inlined into the kernels (with the kernels' fast-math flags)."""
    module = load(where)
    found = [getattr(module, name) for name in names]
    return tuple(f if isinstance(f, CPUDispatcher) else _inlined(f) for f in found)


@cache
def _inlined(function):
    return njit(inline="always", **FAST)(function)


def physics_file(where: str) -> Path:
    """The file a scene's physics is read from."""
    return Path(where).resolve() if where.endswith(".py") else Path(load(where).__file__)


def physics_hash(where: str) -> str:
    """SHA-256 of a scene's physics file: generated kernel files hold it, so an edited scene compiles anew."""
    return hashlib.sha256(physics_file(where).read_bytes()).hexdigest()


def factor_counts(where: str, pieces: tuple[str, ...], parameters: int) -> dict[str, int]:
    """For each piece with a `<piece>_factors(tau, *p)` function, how many values it returns (called in Python)."""
    module = load(where)
    counts = {}
    for piece in pieces:
        factors = getattr(module, f"{piece}_factors", None)
        if factors is not None:
            counts[piece] = len(python_function(factors)(0.5, *([1.0] * parameters)))
    return counts


def block_size(scene, constants: dict, method: Method) -> int:
    """Members per kernel block: a field of sites' rule (ensemble.engine.sites.block_size), else the scene's BLOCK
    if it names one, else the run's or this machine's tuning (ensemble.tuning.generated_block), else BLOCK."""
    if getattr(scene, "SITES", False):
        return sites.block_size(constants, method)
    return getattr(scene, "BLOCK", None) or generated_block(BLOCK)


def kernel(scene, method: Method, constants: dict) -> Kernel:
    """Kernel(function, work rows) of a stepping method for a scene: compiled, or loaded from Numba's cache. A
    scene whose member is a field of sites (SITES) gets ensemble.engine.sites's templates, for its constants' n
    sites and boundary; every other scene the templates of ensemble.engine.templates."""
    if getattr(scene, "SITES", False):
        return _sites_generated(scene.NAME, scene.PHYSICS, method, constants["n"], constants["boundary"] == "periodic",
                                *sites.layout(constants, method))
    D, P = scene.kernel_rows(constants)
    return _generated(scene.NAME, scene.PHYSICS, tuple(scene.PIECES), method, D, P,
                      block_size(scene, constants, method), bool(applied().stages_outside))


@cache
def _sites_generated(name: str, where: str, method: Method, n: int, periodic: bool, B: int, tiled: bool) -> Kernel:
    body, rows = sites.source(name, where, physics_hash(where), method, n, periodic, B, tiled)
    return Kernel(load_source(body, f"{name}_{method.name}_{n}").kernel, rows)


@cache
def _generated(name: str, where: str, pieces: tuple[str, ...], method: Method, D: int, P: int, B: int,
               stages_outside: bool) -> Kernel:
    if method.adaptive:
        family, (body, rows), used = "adaptive", templates.adaptive(method, D, P), ("rhs",)
    elif method.tableau is not None:
        family, (body, rows), used = "runge_kutta", templates.runge_kutta(method, D, P, stages_outside), ("rhs",)
    else:
        module = load(where)
        factors = factor_counts(where, pieces, P)
        coordinates = hasattr(module, "to_pieces")
        family = "splitting"
        body, rows = templates.splitting(method, D, P, pieces, factors, coordinates)
        used = (*pieces, *(f"{p}_factors" for p in factors), *(("to_pieces", "from_pieces") if coordinates else ()))
    physics_import = (f"from ensemble.engine.kernels import physics_functions\n\n"
                      f"{', '.join(used)}, = physics_functions({where!r}, {used!r})")
    source = templates.header(family, name, method, physics_import,
                              physics_hash(where), HELPERS, D, P, B) + body
    return Kernel(load_source(source, f"{name}_{method.name}").kernel, rows)


def load_source(source: str, label: str) -> ModuleType:
    """Import generated `source` from its file in kernel_folder(), writing the file first if it is not there."""
    name = f"ensemble_kernel_{label}_{hashlib.sha256(source.encode()).hexdigest()[:16]}"
    if name in sys.modules:
        return sys.modules[name]
    folder = kernel_folder()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:  # a home folder that cannot be written (some cluster nodes): this machine's temporary folder
        folder = Path(tempfile.gettempdir()) / f"ensemble-kernels-{os.getuid()}"
        folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.py"
    if not path.exists():
        # Written under a temporary name and linked into place: never half a file, never a rewrite (other
        # processes may be writing the same file at once)
        handle, temporary = tempfile.mkstemp(dir=folder, suffix=".tmp")
        with os.fdopen(handle, "w") as out:
            out.write(source)
        try:
            os.link(temporary, path)
        except FileExistsError:
            pass
        finally:
            os.unlink(temporary)
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    sys.modules[name] = module
    return module
