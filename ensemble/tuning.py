"""This machine's kernel layout, chosen by measurement (`ensemble tune`) and kept in a small file.

LLVM picks a vector width for each CPU model: on recent Intel server cores it prefers 256-bit vectors even where
512-bit ones are there, and the hand-written C of ../shared/limit, compiled with gcc, uses 512. On an Intel Xeon
(Emerald Rapids) the top's rk4 kernel ran at 0.64 of that C with 256-bit vectors and at 1.02 with 512
(docs/speed.md). No rule fits every CPU, so `ensemble tune` times the candidates here: the vector width LLVM
prefers (a process-wide setting of Numba's code generator), the members per block of the
kernels of a member of D values, and a field of sites' splitting layout (its blocks, and its kicks
and drifts fused in tiles or swept one at a time). The winners go to tuning_path(), keyed by the CPU model, its
vector extensions, Numba's version and a hash of the engine's kernel sources; a file of another machine or
engine is ignored with one line. Importing ensemble applies a valid file (`prepare`), before any Numba function
of ours exists; a run without one uses the engine's rules and says once that `ensemble tune` may make runs
faster. Nothing tunes on its own.

No choice changes a member's arithmetic: a block holds members side by side, each computed alone, the vector
width only changes how many lanes an instruction holds (with fast-math's contraction alone, LLVM may not regroup
arithmetic per width), tiles keep each site's order of pieces, and the Runge-Kutta kernels' two loop orders take
the same operations in the same order (tests/test_tuning.py and tests/test_targets.py check them).
"""
from __future__ import annotations

import hashlib
import json
import os
import platform
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

from .engine.sources import ENGINE_SOURCES
from .errors import EnsembleError

FORMAT = 1
HINT = "ensemble: this machine's kernels are untuned; `ensemble tune` (once, about a minute) may make runs faster"


@dataclass(frozen=True)
class Tuning:
    """The choices: vector_bits (512 or 256: the width LLVM is told to prefer; None: its own choice for this CPU)
    and block (members per block of the kernels of a member of D values; None: the engine's).
    For a field of sites' splittings from 16 sites on (ensemble.engine.sites): sites_block, members per block
    where a block's rows fit the L1 data cache (None: the rule's two SIMD vectors; where they outgrow it the rule's
    one vector stays), and fused_sweeps (False: long fields sweep one kick or drift at a time where the rule would
    run TILE_PIECES of them fused in tiles; None: the rule). features: Numba's CPU features string that gives
    vector_bits here (kept in the file; a file whose string is not this machine's own is ignored: another
    string compiles other arithmetic, a garbled one aborts LLVM)."""
    vector_bits: int | None = None
    block: int | None = None
    sites_block: int | None = None
    fused_sweeps: bool | None = None
    features: str | None = field(default=None, compare=False)

    def summary(self) -> str:
        """The choices in words."""
        sites = self.sites_block or "the engine's rule"
        sweeps = "swept one piece at a time" if self.fused_sweeps is False else "in tiles"
        return (f"vectors {width_name(self.vector_bits)}, generated kernels' blocks "
                f"{self.block or 'the engine default'}, fields of sites' splitting blocks "
                f"{sites}, long fields {sweeps}")


def kernel_folder() -> Path:
    """Where this machine's generated kernel files (ensemble.engine.kernels) and its tuning go: ENSEMBLE_KERNEL_DIR,
    else NUMBA_CACHE_DIR/ensemble-kernels, else the user's cache folder (XDG_CACHE_HOME or
    ~/.cache)/ensemble/kernels."""
    if os.environ.get("ENSEMBLE_KERNEL_DIR"):
        return Path(os.environ["ENSEMBLE_KERNEL_DIR"])
    if os.environ.get("NUMBA_CACHE_DIR"):
        return Path(os.environ["NUMBA_CACHE_DIR"]) / "ensemble-kernels"
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "ensemble" / "kernels"


class KernelFolderError(EnsembleError):
    """The kernel folder is not this user's own: code in it could run as ours (exit status 2)."""


def private_kernel_folder() -> Path:
    """kernel_folder(), made if missing, readable and writable by this user alone (0700): its files are imported
    as code. Where the default one cannot be made (a home folder that cannot be written, on some cluster nodes),
    this user's folder in the machine's temporary folder; ENSEMBLE_KERNEL_DIR is used as given or not at all.
    KernelFolderError, in one line, for a folder another user owns or one that cannot be made or kept private."""
    folder = kernel_folder()
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as e:
        if os.environ.get("ENSEMBLE_KERNEL_DIR"):
            raise KernelFolderError(f"{folder}: cannot make the kernel folder ({e.strerror or e}); set "
                                    f"ENSEMBLE_KERNEL_DIR to a folder you can write") from None
        folder = Path(tempfile.gettempdir()) / f"ensemble-kernels-{os.getuid()}"
        try:
            folder.mkdir(mode=0o700, exist_ok=True)
        except OSError as e:
            raise KernelFolderError(f"{folder}: cannot make the kernel folder ({e.strerror or e}); set "
                                    f"ENSEMBLE_KERNEL_DIR to a folder of your own") from None
    found = os.stat(folder)
    if found.st_uid != os.getuid():
        raise KernelFolderError(f"{folder}: the kernel folder belongs to another user (uid {found.st_uid}) and its "
                                f"files would run as your code; set ENSEMBLE_KERNEL_DIR to a folder of your own")
    if found.st_mode & 0o077:
        try:
            os.chmod(folder, 0o700)  # one of ours made by an older version, or by a umask that lets others in
        except OSError as e:
            raise KernelFolderError(f"{folder}: cannot make the kernel folder private ({e.strerror or e}); set "
                                    f"ENSEMBLE_KERNEL_DIR to a folder of your own") from None
    return folder


def tuning_path() -> Path:
    """ENSEMBLE_TUNING_FILE, else tuning.json beside the generated kernels (kernel_folder)."""
    if os.environ.get("ENSEMBLE_TUNING_FILE"):
        return Path(os.environ["ENSEMBLE_TUNING_FILE"])
    return kernel_folder() / "tuning.json"


def host_key() -> dict[str, str]:
    """What a tuning holds for: the CPU model and its vector extensions, Numba's version, and the engine's kernel
    sources (a new engine may want other choices)."""
    from importlib.metadata import version

    model, flags = cpu()
    vectors = ",".join(sorted(f for f in flags if f.startswith(("avx", "fma", "sse4"))))
    return {"cpu": model, "vectors": vectors, "numba": version("numba"), "engine": engine_hash()}


def cpu() -> tuple[str, set[str]]:
    """This machine's CPU model and its feature flags (from /proc/cpuinfo; elsewhere what platform says)."""
    model, flags = None, set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and model is None:
                model = line.split(":", 1)[1].strip()
            elif line.startswith("flags") and not flags:
                flags = set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return model or platform.processor() or "unknown CPU", flags  # platform.processor() runs `uname -p`


def engine_hash() -> str:
    """SHA-256 of the engine's kernel sources: its family code, its helpers and the sites' kernels."""
    root = Path(__file__).parent / "engine"
    digest = hashlib.sha256()
    for name in ("sites.py", "sites_kernels.py", *ENGINE_SOURCES):
        digest.update((root / name).read_bytes())
    return digest.hexdigest()


def load(path: Path | None = None) -> tuple[Tuning | None, str | None]:
    """(the tuning of this machine from `path` (default tuning_path()), None) or (None, one line saying why there
    is none: untuned, or a file that is unreadable or another machine's)."""
    path = path or tuning_path()
    if not path.exists():
        return None, HINT
    try:
        found = json.loads(path.read_text())
        choices = found["choices"]
        tuning = Tuning(vector_bits=choices.get("vector_bits"), block=choices.get("block"),
                        sites_block=choices.get("sites_block"),
                        fused_sweeps=choices.get("fused_sweeps"), features=choices.get("features"))
        if not _known(tuning):
            raise ValueError("unknown choices")
        if tuning.features is not None and tuning.features != vector_features(tuning.vector_bits):
            raise ValueError("its CPU features are not this machine's")  # they would compile other arithmetic
    except (OSError, ValueError, KeyError, TypeError, AttributeError, RecursionError) as e:
        return None, f"ensemble: ignoring {path}: it cannot be read ({e}); `ensemble tune` writes a new one"
    if found.get("format") != FORMAT or found.get("host") != host_key():
        return None, (f"ensemble: ignoring {path}: it was tuned on another machine, Numba or engine; "
                      f"`ensemble tune` tunes this one")
    return tuning, None


def _known(tuning: Tuning) -> bool:
    """Whether a tuning read from a file holds only choices this version makes."""
    def block_in(value, allowed) -> bool:
        return type(value) is int and value in allowed

    return (tuning.vector_bits in (None, 256, 512) and (tuning.block is None or block_in(tuning.block, BLOCKS))
            and (tuning.sites_block is None or block_in(tuning.sites_block, SITES_BLOCKS))
            and (tuning.fused_sweeps is None or tuning.fused_sweeps is False))


BLOCKS = (32, 64, 128, 256)  # the block sizes a generated kernel may be tuned to
TIMED_BLOCKS = (64, 128, 256)  # those `ensemble tune` times (32 was the slowest on the Intel Xeon: docs/speed.md)
SITES_BLOCKS = (2, 4, 8, 16, 32, 64)  # the blocks a fields of sites' splitting may be tuned to
_applied: Tuning | None = None


def applied() -> Tuning:
    """The tuning this process runs with (apply's), or the engine's rules."""
    return _applied or Tuning()


def apply(tuning: Tuning | None) -> str | None:
    """Run this process's kernels with `tuning` (None: the engine's rules). The vector width takes effect only
    before Numba's code generator starts (its first compile or cache load), and not where NUMBA_CPU_FEATURES or
    NUMBA_CPU_NAME is set; returns one line when it had started already with another width, else None."""
    global _applied
    _applied = tuning
    if tuning is None or tuning.vector_bits is None:
        return None
    if "NUMBA_CPU_FEATURES" in os.environ or "NUMBA_CPU_NAME" in os.environ:  # the user's own choice stands
        _applied = Tuning(block=tuning.block)
        return None
    if not set_features(tuning.features or vector_features(tuning.vector_bits)):
        _applied = Tuning(block=tuning.block)
        return (f"ensemble: the tuned {tuning.vector_bits}-bit vectors need a fresh process (Numba code was "
                f"compiled before ensemble was imported); this run uses the width LLVM prefers")
    return None


def vector_features(bits: int | None) -> str | None:
    """Numba's CPU features string for this host with LLVM told to prefer `bits`-bit vectors (None: as is)."""
    if bits is None:
        return None
    from llvmlite import binding

    return binding.get_host_cpu_features().flatten() + (",-prefer-256-bit" if bits == 512 else ",+prefer-256-bit")


def set_features(features: str | None) -> bool:
    """Set Numba's CPU features for this process's code generator; False if it had started with others. Before
    Numba is imported, through NUMBA_CPU_FEATURES (importing Numba here would slow down every `ensemble` command
    by a quarter of a second; processes started from this one inherit it)."""
    import sys

    if "numba" not in sys.modules:
        if features is None:
            os.environ.pop("NUMBA_CPU_FEATURES", None)
        else:
            os.environ["NUMBA_CPU_FEATURES"] = features
        return True
    from numba.core import config, registry

    if "_toplevel_target_context" in registry.cpu_target.__dict__:
        return config.CPU_FEATURES == features
    config.CPU_FEATURES = features
    return True


def save(tuning: Tuning, measured: dict, path: Path | None = None) -> Path:
    """Write the tuning file (atomically): the choices, what they hold for, and the rates they were chosen by."""
    path = path or tuning_path()
    if path.parent == kernel_folder():
        private_kernel_folder()
    path.parent.mkdir(parents=True, exist_ok=True)
    choices = {**asdict(tuning), "features": tuning.features or vector_features(tuning.vector_bits)}
    text = json.dumps({"format": FORMAT, "host": host_key(), "choices": choices, "measured": measured}, indent=1)
    handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(handle, "w") as out:
        out.write(text)
    os.replace(temporary, path)
    return path


# ---------------------------------------------------------------- measuring (`ensemble tune`)

def width_name(bits: int | None) -> str:
    return "LLVM's choice" if bits is None else f"{bits}-bit"


_prepared = False
_pending: str | None = None


def prepare() -> None:
    """Load this machine's tuning file and apply it, once per process, before anything is compiled: importing
    ensemble calls it (ensemble/__init__.py), ahead of every Numba function of ours. What to say about it waits
    for pending_line."""
    global _prepared, _pending
    if _prepared:
        return
    _prepared = True
    tuning, line = load()
    _pending = apply(tuning) or line


def pending_line() -> str | None:
    """The one line prepare has to say (untuned, a file ignored, a width that came too late), once per process."""
    global _pending
    line, _pending = _pending, None
    return line


def describe() -> str:
    """What this process runs with, in words (benchmarks print it beside the host)."""
    if _applied is None or _applied == Tuning():
        return "untuned (the engine's rules and LLVM's vector width)"
    return f"{applied().summary()} (from {tuning_path()})"
