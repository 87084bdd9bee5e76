"""This machine's kernel layout, chosen by measurement (`ensemble tune`) and kept in a small file.

LLVM picks a vector width for each CPU model: on recent Intel server cores it prefers 256-bit vectors even where
512-bit ones are there, and the hand-written C of ../shared/limit, compiled with gcc, uses 512. On an Intel Xeon
(Emerald Rapids) the top's rk4 kernel ran at 0.64 of that C with 256-bit vectors and at 1.02 with 512
(docs/speed.md). No rule fits every CPU, so `ensemble tune` times the candidates here: the vector width LLVM
prefers (a process-wide setting of Numba's code generator), the members per block and the loop order of the
kernels the engine generates from its templates, and a field of sites' splitting layout (its blocks, and its kicks
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
import math
import os
import platform
import tempfile
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

from .errors import EnsembleError

FORMAT = 1
HINT = "ensemble: this machine's kernels are untuned; `ensemble tune` (once, about a minute) may make runs faster"


@dataclass(frozen=True)
class Tuning:
    """The choices: vector_bits (512 or 256: the width LLVM is told to prefer; None: its own choice for this CPU)
    and block (members per block of the kernels generated from the engine's templates; None: the engine's);
    stages_outside (True: their explicit Runge-Kutta kernels sweep a block's members once per stage, slopes in work
    rows, instead of taking each member's whole step at once with its slopes in registers; None: the latter).
    For a field of sites' splittings from 16 sites on (ensemble.engine.sites): sites_block, members per block
    where a block's rows fit the L1 data cache (None: the rule's two SIMD vectors; where they outgrow it the rule's
    one vector stays), and fused_sweeps (False: long fields sweep one kick or drift at a time where the rule would
    run TILE_PIECES of them fused in tiles; None: the rule). features: Numba's CPU features string that gives
    vector_bits here (kept in the file; a file whose string is not this machine's own is ignored: another
    string compiles other arithmetic, a garbled one aborts LLVM)."""
    vector_bits: int | None = None
    block: int | None = None
    stages_outside: bool | None = None
    sites_block: int | None = None
    fused_sweeps: bool | None = None
    features: str | None = field(default=None, compare=False)

    def summary(self) -> str:
        """The choices in words."""
        sites = self.sites_block or "the engine's rule"
        sweeps = "swept one piece at a time" if self.fused_sweeps is False else "in tiles"
        order = "stages outside members" if self.stages_outside else "members' steps whole"
        return (f"vectors {width_name(self.vector_bits)}, generated kernels' blocks "
                f"{self.block or 'the engine default'}, Runge-Kutta {order}, fields of sites' splitting blocks "
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
    """SHA-256 of the engine's kernel sources: its templates (for members of D values and for fields of sites)
    and its helpers."""
    root = Path(__file__).parent
    digest = hashlib.sha256()
    for path in (root / "engine" / "templates.py", root / "engine" / "sites.py", root / "engine" / "blocks.py"):
        digest.update(path.read_bytes())
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
                        stages_outside=choices.get("stages_outside"), sites_block=choices.get("sites_block"),
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
            and (tuning.fused_sweeps is None or tuning.fused_sweeps is False)
            and (tuning.stages_outside is None or tuning.stages_outside is True))


BLOCKS = (32, 64, 128, 256)  # the block sizes a generated kernel may be tuned to
TIMED_BLOCKS = (64, 128, 256)  # those `ensemble tune` times (32 was the slowest on the Intel Xeon: docs/speed.md)
SITES_BLOCKS = (2, 4, 8, 16, 32, 64)  # the blocks a fields of sites' splitting may be tuned to
_applied: Tuning | None = None
_few_members: int | None = None  # members_block's


def applied() -> Tuning:
    """The tuning this process runs with (apply's), or the engine's rules."""
    return _applied or Tuning()


def generated_block(default: int) -> int:
    """Members per block of a kernel generated from the engine's templates: members_block's while a run of few
    members is under way, else the tuning's, else `default`."""
    return _few_members or applied().block or default


@contextmanager
def members_block(block: int | None):
    """While in the block, generated kernels run `block` members per block (None: as before): a run of fewer
    members than a block sets it (runner.few_members_block)."""
    global _few_members
    previous, _few_members = _few_members, block
    try:
        yield
    finally:
        _few_members = previous


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

CANDIDATE_MARGIN = 1.05  # a candidate replaces the default only when this much faster: blocks within 5% are noise here
ROUNDS = 2  # each candidate's process runs this many times, the candidates in turn


def tune(say=print) -> tuple[Tuning, dict]:
    """Time the candidates on this machine and return (the winning Tuning, the rates measured). Each vector width
    runs in a process of its own (it is fixed once Numba has compiled), ROUNDS times in turn; the top's rk4
    kernel at the engine's block and the chain's verlet at 16 masses vote with the geometric mean of their rates.
    Then, under the winning width, all in one process, ROUNDS times: the blocks and the loop order of the
    generated kernels (the top's rk4, top_layouts), and a field of sites' splitting layouts (the chain's verlet
    at 16 and 1024 masses: blocks of one, two or four SIMD vectors, fused sweeps in tiles or one piece at a time;
    sites_layouts). A candidate replaces the default only when CANDIDATE_MARGIN faster."""
    widths = [512, 256] if "avx512f" in host_key()["vectors"].split(",") else [None]
    from .engine.kernels import BLOCK

    _compiled([(bits, [(BLOCK, False)], True, []) for bits in widths])
    rounds = [{bits: _measured(bits, [(BLOCK, False)]) for bits in widths} for _ in range(ROUNDS)]
    rates = {bits: {case: sum(r[bits][case] for r in rounds) / ROUNDS for case in rounds[0][bits]} for bits in widths}
    for bits in widths:
        say(f"  vectors {width_name(bits):>14}: " + ", ".join(f"{k} {v:.3g}" for k, v in rates[bits].items()))
    spread = max(_spread([r[bits] for r in rounds]) for bits in widths)
    score = {bits: math.prod(rates[bits].values()) ** (1 / len(rates[bits])) for bits in widths}
    # LLVM's own choice is one of the two widths: a width is kept only when clearly faster than the other
    bits = _pick({None: min(score.values()), **score}, None, spread)
    tops, layouts = top_layouts(BLOCK), sites_layouts()
    _compiled([(bits, tops[1:], False, layouts[1:2]), (bits, [], False, layouts[2:])])  # tops[0] is compiled
    timed = [_measured(bits, tops, chain=False, layouts=layouts) for _ in range(ROUNDS)]
    mean = {name: sum(t[name] for t in timed) / ROUNDS for name in timed[0]}
    spread = max(spread, _spread(timed))
    say("  generated kernels under the chosen vectors: " + ", ".join(f"{top_name(*top)} {mean[top_name(*top)]:.3g}"
                                                                     for top in tops))
    say("  fields of sites under the chosen vectors: " + ", ".join(f"{layout_name(*lay)} {mean[layout_name(*lay)]:.3g}"
                                                                    for lay in layouts))
    say(f"  spread of one case's rate between rounds: up to {spread:.3f}x; a candidate replaces the engine's rule "
        f"only when faster than it by more (and by {CANDIDATE_MARGIN}x at least)")
    blocks = {b: mean[top_name(b, False)] for b, outside in tops if not outside}
    block = _pick(blocks, BLOCK, spread)
    outside = _pick({outside: mean[top_name(BLOCK, outside)] for b, outside in tops if b == BLOCK}, False, spread)
    short = _pick({b: mean[layout_name(n, b, fused)] for n, b, fused in layouts if n == 16}, layouts[0][1], spread)
    fused = _pick({fused: mean[layout_name(n, b, fused)] for n, b, fused in layouts if n > 16}, True, spread)
    measured = {"vectors": {width_name(b): rates[b] for b in widths}, "layouts": mean, "spread": spread,
                "units": "member-steps/s (top), mass-steps/s (chain)"}
    return Tuning(vector_bits=bits, block=None if block == BLOCK else block, stages_outside=outside or None,
                  sites_block=None if short == layouts[0][1] else short,
                  fused_sweeps=None if fused else False), measured


def _pick(rates: dict, default, spread: float = 1.0):
    """The fastest candidate of `rates`, where any but `default` must be faster by CANDIDATE_MARGIN and by more
    than `spread` (how far one case's rate moved between rounds) to win."""
    margin = max(CANDIDATE_MARGIN, spread)
    return max(rates, key=lambda c: rates[c] / (1.0 if c == default else margin))


def _spread(rounds: list[dict]) -> float:
    """The largest ratio between two rounds' rates of one case (rounds: case -> rate, one dict a round)."""
    return max(max(r[case] for r in rounds) / min(r[case] for r in rounds) for case in rounds[0])


def top_layouts(block: int) -> list[tuple[int, bool]]:
    """The generated kernels' layouts `ensemble tune` times on the top's rk4, (members per block, stages outside):
    the engine's block first, then the other TIMED_BLOCKS, then the engine's block with the stages outside."""
    return [(block, False), *((b, False) for b in TIMED_BLOCKS if b != block), (block, True)]


def top_name(block: int, outside: bool) -> str:
    return f"top rk4, block {block}" + (", stages outside" if outside else "")


def sites_layouts() -> list[tuple[int, int, bool]]:
    """The fields of sites' layouts `ensemble tune` times, (sites, members per block, fused sweeps): at 16 sites,
    whose blocks' rows fit the L1 cache, blocks of two SIMD vectors (the rule's) and four; at 1024, whose rows
    outgrow it, blocks of one vector fused in tiles (the rule's) and swept one piece at a time. The rule's first
    in each."""
    from .engine.sites import vector_doubles

    vector = vector_doubles()
    return [(16, 2 * vector, True), (16, 4 * vector, True), (1024, vector, True), (1024, vector, False)]


def layout_name(n: int, block: int, fused: bool) -> str:
    return f"chain verlet N={n}, block {block}" + ("" if fused else ", one piece at a time")


def width_name(bits: int | None) -> str:
    return "LLVM's choice" if bits is None else f"{bits}-bit"


def _measured(bits: int | None, tops: list, chain: bool = True, layouts: list = ()) -> dict[str, float]:
    """measure_here's rates, from a process of its own."""
    return _in_processes([(bits, tops, chain, list(layouts), False)])[0]


def _compiled(asks: list[tuple]) -> None:
    """Compile (into Numba's cache) the kernels of each of `asks`, (bits, tops, chain, layouts) as _measured
    takes them, in processes that run at once: the timed processes then load them. Compiling is most of
    `ensemble tune`'s minute, and it needs no quiet machine."""
    _in_processes([(*ask, True) for ask in asks])


def _in_processes(asks: list[tuple]) -> list[dict]:
    """measure_here's answer to each of `asks` (its arguments), each from a process of its own, started at once."""
    import subprocess
    import sys

    started = [(ask[0], subprocess.Popen([sys.executable, "-c", "from ensemble.tuning import _serve; "
                                          f"_serve({json.dumps(ask)!r})"],
                                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
               for ask in asks]
    answers = []
    for bits, process in started:
        out, err = process.communicate()
        if process.returncode != 0:
            raise RuntimeError(f"timing the {width_name(bits)} vectors failed: "
                               f"{(err.strip().splitlines() or ['?'])[-1]}")
        answers.append(json.loads(out.strip().splitlines()[-1]))
    return answers


def _serve(asked: str) -> None:
    print(json.dumps(measure_here(*json.loads(asked))))


def measure_here(bits: int | None, tops: list, chain: bool = True, layouts: list = (),
                 compile_only: bool = False) -> dict[str, float]:
    """In a process that has compiled nothing yet, with LLVM preferring `bits`-bit vectors: the top's rk4 kernel
    in each of `tops`, (block, stages outside), in member-steps/s; the chain's verlet at 16 masses in the engine's
    layout (with chain) and in each of `layouts`, (n, block, fused), in mass-steps/s. Each the median of 5 calls,
    the kernels called in turn. compile_only: call each once (compiling it or loading it from the cache), and
    measure nothing."""
    import numpy as np

    set_features(vector_features(bits))
    from .engine import launch
    from .methods import METHODS
    from .scenes import SCENES

    members, steps = 32768, 1000
    rng = np.random.default_rng(0)
    top = {"lambda1": np.full(members, 1e-3), "lambda3": np.full(members, 2e-3), "c": np.full(members, 1e-4),
           "spin0": np.full(members, 60.0), "tilt0": rng.uniform(0.02, 0.2, members),
           "azimuth0": rng.uniform(0.0, 6.28, members)}
    calls = {}  # name: (launch, steps it makes)
    for block, outside in tops:
        apply(Tuning(block=block, stages_outside=outside or None))
        calls[top_name(block, outside)] = (launch.Launch(SCENES["top"], METHODS["rk4"], top, {}, n_save=2,
                                                          save_dt=steps * 1e-3, dt=1e-3), members * steps)
    chains = [(16, None, None), (2, None, None)] if chain else []  # a short chain too: its rate falls otherwise
    for n, block, fused in chains + [tuple(layout) for layout in layouts]:
        # sites_block sets the block where rows fit the L1 cache; at 1024 sites the rule gives the layout's own
        apply(Tuning(sites_block=block, fused_sweeps=None if fused is not False else False))
        count = 65536 // n  # chains
        masses = {"m": np.ones((count, n)), "k": np.ones((count, n + 1)), "x0": rng.normal(0, 0.1, (count, n)),
                  "v0": np.zeros((count, n))}
        name = f"chain verlet N={n}" if block is None else layout_name(n, block, fused)
        calls[name] = (launch.Launch(SCENES["chain"], METHODS["verlet"], masses, {"n": n, "boundary": "fixed"},
                                     n_save=2, save_dt=steps * 0.01, dt=0.01), n * count * steps)
    apply(None)
    if compile_only:
        for call, _ in calls.values():
            call.run()
        return {}
    seconds = _seconds_in_turn([call for call, _ in calls.values()])
    return {name: work / s for (name, (_, work)), s in zip(calls.items(), seconds)}


def _seconds_in_turn(calls: list, repeats: int = 5) -> list[float]:
    """Median seconds of each launch's run, the launches called in turn `repeats` times (after one call each that
    compiles or loads its kernel), so that a slow spell of the machine hits them all."""
    import statistics
    import time

    for call in calls:
        call.run()
    seconds = [[] for _ in calls]
    for _ in range(repeats):
        for call, timed in zip(calls, seconds):
            start = time.perf_counter()
            call.run()
            timed.append(time.perf_counter() - start)
    return [statistics.median(timed) for timed in seconds]


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
