"""A scene's kernel for a method, written as a Python file that Numba keys its disk cache on, then imported: for an
member family (an explicit Runge-Kutta method, an adaptive pair, a splitting), a short file that binds the
scene's functions, the sizes and the method's coefficients to the family's code (ensemble.engine.frames,
.runge_kutta, .adaptive, .splitting); for a field of sites, ensemble.engine.sites_kernels's code after bindings of
its own (ensemble.engine.sites.source).

A kernel's identity is everything that decides its arithmetic. The file's name holds a hash of its text, and its
text holds the method's coefficients and the layout, the identity of the scene's sources (its file and the user's
modules it imports: ensemble.scenes.contract.identity), a hash of the engine's code (blocks.HELPERS) and the
compile target (LLVM's CPU name and features, Numba's version, the fast-math flags): a change
to any of them makes a new file, which compiles once. A file is imported only when its text matches its name (else
it is written again, with one line said), and never rewritten otherwise (Numba's cache index checks its source
file's time stamp). The files live in tuning.private_kernel_folder().
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
from typing import NamedTuple

from numba import njit
from numba.core.registry import CPUDispatcher

from .. import inlining
from ..methods import Method
from ..scenes.contract import SceneError, identity, load, python_function
from ..tuning import KernelFolderError, Tuning, applied, private_kernel_folder
from . import sites
from .blocks import CONTROL_ROWS, FAST, HELPERS, Kernel, adaptive_constants

BLOCK = 128  # members per block of a scene whose kernel_rows are its whole state (rows of B floats each)


def physics_functions(where: str, names: tuple[str, ...], expected: str) -> tuple:
    """The compiled functions `names` of a scene's physics for the field-of-sites kernels
    (ensemble.engine.sites_kernels), which call them by name: its own @njit functions as they are, plain Python
    functions compiled to be inlined
    (with the kernels' fast-math flags). SceneError when the scene's sources are no longer those of identity
    `expected`, which the kernel's file was generated for."""
    module = loaded(where, expected)
    found = [getattr(module, name) for name in names]
    return tuple(f if isinstance(f, CPUDispatcher) else njit(inline="always", **FAST)(f) for f in found)


def loaded(where: str, expected: str) -> ModuleType:
    """A scene's module, which must be the sources of identity `expected` (SceneError if it changed meanwhile)."""
    module = load(where)
    if identity(module) != expected:
        raise SceneError(f"{where} (or a module of yours it imports) changed while its kernels were being made; "
                         f"run again")
    return module


def scene_identity(scene) -> str:
    """The identity of the sources a scene runs: a user's scene's as they were when its run was read (a kernel
    made later refuses sources edited since, in one line: a run never mixes two physics), a built-in scene's
    physics module's."""
    module = getattr(scene, "module", None)
    return identity(module if module is not None else load(scene.PHYSICS))


@cache
def compile_target() -> str:
    """What Numba compiles the CPU kernels for and with: LLVM's CPU name and features (NUMBA_CPU_NAME and
    NUMBA_CPU_FEATURES, or the tuning's, or the host's), Numba's version, the fast-math flags, and whether Intel's
    SVML vectorizes math functions (off unless Numba was imported before ensemble with it on, or
    NUMBA_DISABLE_INTEL_SVML=0 asks for it: its bits are not the C library's)."""
    from llvmlite import binding
    from numba import __version__ as numba_version
    from numba.core import config

    name = config.CPU_NAME or binding.get_host_cpu_name()
    features = config.CPU_FEATURES if config.CPU_FEATURES is not None else binding.get_host_cpu_features().flatten()
    return (f"cpu {name}; features {features}; numba {numba_version}; fastmath {sorted(FAST['fastmath'])}; "
            f"svml {'on' if config.USING_SVML else 'off'}")


def factor_counts(where: str, pieces: tuple[str, ...], parameters: int) -> dict[str, int]:
    """For each piece with a `<piece>_factors(tau, *p)` function, how many values it returns (called in Python)."""
    module = load(where)
    counts = {}
    for piece in pieces:
        factors = getattr(module, f"{piece}_factors", None)
        if factors is not None:
            counts[piece] = len(python_function(factors)(0.5, *([1.0] * parameters)))
    return counts


def block_size(scene, constants: dict, method: Method, block: int | None, tuning: Tuning) -> int:
    """Members per kernel block: a field of sites' rule (ensemble.engine.sites.block_size), else `block` (a run of
    few members: runner.few_members_block), else the tuning's, else BLOCK."""
    if scene.SITES:
        return sites.block_size(constants, method, tuning)
    return block or tuning.block or BLOCK


class Layout(NamedTuple):
    """Where a kernel keeps its members: computed once (`layout`; on a GPU, gpu_launch.layout) from the scene, the
    method, a run's constants, the device and this machine's tuning, and handed to the kernel's maker and its
    launch."""
    block: int  # members per block: a block's work array is rows x block floats, row r of member j at r block + j
    # (a GPU's works are rows x members; a block of threads holds `block` members)
    rows: int  # work rows: a member's state, parameters, and what its method keeps between calls
    tiled: bool = False  # a field of sites' splitting sweeps its sites in tiles (sites.tiles)
    halo: int = 0  # sites a long ring's rows hold beyond each end (sites.ring_halo)
    threads: int = 1  # threads per member (a GPU's field of sites: gpu_sites.site_threads)
    events: tuple = ()  # each event's value (results.Event.source): rows of its own (ensemble.engine.events)


def layout(scene, method: Method, constants: dict, block: int | None = None, tuning: Tuning | None = None,
           events: tuple = ()) -> Layout:
    """The Layout of a scene's CPU kernel for `method`, computed without making the kernel. block: members per
    block for a run of few members (runner.few_members_block); None for block_size's rule. tuning: this
    process's (ensemble.tuning.applied) unless given. The rows: a field of sites' (sites.work_rows), or a member's
    state and parameters, then an adaptive pair's slopes, trial state and control block, or a splitting's factors
    (the `<piece>_factors` called in Python), then its events' (events: each one's results.Event.source)."""
    tuning = tuning or applied()
    B = block_size(scene, constants, method, block, tuning)
    if scene.SITES:
        n, periodic = constants["n"], constants["boundary"] == "periodic"
        tiled = method.splitting is not None and not events and sites.tiles(n, B, tuning)
        return Layout(B, sites.work_rows(method, n, periodic, tiled, len(events)), tiled,
                      sites.ring_halo(method) if tiled and periodic else 0, events=tuple(events))
    D, P = scene.kernel_rows(constants)
    rows = _member_rows(scene.PHYSICS, tuple(scene.PIECES), method, D, P)
    return Layout(B, rows + event_rows(D, len(events), method.adaptive), events=tuple(events))


def kernel(scene, method: Method, constants: dict, chosen: Layout | None = None) -> Kernel:
    """Kernel(function, work rows) of a stepping method for a scene in `chosen` layout (default: `layout`'s):
    compiled, or loaded from Numba's cache. A scene whose member is a field of sites (SITES) gets
    ensemble.engine.sites_kernels's, for its constants' n sites and boundary; every other scene its family's
    code."""
    chosen = chosen or layout(scene, method, constants)
    sources = scene_identity(scene)  # a cache key: an edited scene is another kernel
    if scene.SITES:
        return _sites_generated(scene.NAME, scene.PHYSICS, sources, method, constants["n"],
                                constants["boundary"] == "periodic", chosen)
    D, P = scene.kernel_rows(constants)
    return _generated(scene.NAME, scene.PHYSICS, sources, tuple(scene.PIECES), method, D, P, chosen.block,
                      chosen.events)


@cache
def _sites_generated(name: str, where: str, sources: str, method: Method, n: int, periodic: bool,
                     chosen: Layout) -> Kernel:
    body, rows = sites.source(name, where, sources, method, n, periodic, chosen.block, chosen.tiled, chosen.halo,
                              chosen.events)
    label = f"{name}_{method.name}_{n}" + ("_events" if chosen.events else "")
    return Kernel(load_source(body, label).kernel, rows)


def _member_rows(where: str, pieces: tuple[str, ...], method: Method, D: int, P: int) -> int:
    if method.tableau is None:
        return D + P + sum(map(len, _like_factors(where, pieces, method, P)))
    if method.adaptive:
        return D + P + D * method.tableau.stages + D + CONTROL_ROWS
    return D + P


def _like_factors(where: str, pieces: tuple[str, ...], method: Method, P: int) -> tuple:
    """A splitting's factors per sequence entry, as tuples of as many zeros."""
    factors = factor_counts(where, pieces, P)
    return tuple((0.0,) * factors.get(pieces[number], 0) for number in method.splitting.numbers)


@cache
def _generated(name: str, where: str, sources: str, pieces: tuple[str, ...], method: Method, D: int, P: int,
               B: int, events: tuple = ()) -> Kernel:
    """A member family's kernel (ensemble.engine.runge_kutta, .adaptive, .splitting) of a scene; with events
    (each one's results.Event.source), their rows after the family's and a kernel that takes their arrays."""
    rows = _member_rows(where, pieces, method, D, P)
    fields = dict(scene=name, method=method.name, physics_hash=sources, helpers_hash=HELPERS, where=where, D=D, P=P,
                  B=B, event_sources=events, first_event_row=rows, E=len(events))
    if method.tableau is None:
        sequence = tuple(zip(method.splitting.numbers, method.splitting.fractions))
        source = (HEADER + SPLITTING + (SPLITTING_EVENTS if events else NO_EVENTS)).format(
            family="splitting", **fields, pieces=pieces, sequence=sequence,
            like_factors=_like_factors(where, pieces, method, P))
        source += FIXED_STEP_EVENTS if events else FIXED_STEP
    elif not method.adaptive:
        source = (HEADER + RUNGE_KUTTA + (RUNGE_KUTTA_EVENTS if events else NO_EVENTS)).format(
            family="runge_kutta", **fields, tableau=tableau_of(method), S=method.tableau.stages)
        source += FIXED_STEP_EVENTS if events else FIXED_STEP
    else:
        source = (HEADER + ADAPTIVE + (ADAPTIVE_EVENTS if events else NO_ADAPTIVE_EVENTS)).format(
            family="adaptive", **fields, tableau=pair_of(method), S=method.tableau.stages,
            controller=adaptive_constants(method)[3:])
        source += ADAPTIVE_KERNEL_EVENTS if events else ADAPTIVE_KERNEL
    label = f"{name}_{method.name}" + ("_events" if events else "")
    return Kernel(load_source(source, label).kernel, rows + event_rows(D, len(events), method.adaptive))


def event_rows(D: int, E: int, adaptive: bool) -> int:
    """Work rows of a member kernel's E events: adaptive, their signs at a step's start; fixed steps, their
    signs at the last step's end, which members crossed, and the state at a step's start
    (ensemble.engine.events.fixed_watcher)."""
    return (E if adaptive else E + 1 + D) if E else 0


def event_values(where: str, sources: tuple, expected: str):
    """values(t, y, p) -> each event's value (ensemble.engine.events.values_of), from each event's source
    (results.Event.source), the scene's functions from its physics module `where` (of identity `expected`)."""
    from . import events

    module = loaded(where, expected)
    return events.values_of(sources, lambda name: _called(getattr(module, name)))


def event_signs(where: str, sources: tuple, expected: str, D: int, P: int):
    """signs(t, y, p, levels) -> each event's sign against its level (ensemble.engine.events.signs_of): the
    scene's watch where a function source names one, else the value's difference from the level; the scene's
    functions inlined into the kernel's watch (`_called`), with a state of D values and P parameters."""
    from . import events

    module = loaded(where, expected)
    return events.signs_of(sources, lambda name: _called(getattr(module, name), "always"), counts=(D, P))


HEADER = '''"""Generated by ensemble.engine.kernels: the {family} kernel of {scene}, method {method}.

Do not edit: ensemble writes a new file whenever the scene's physics or the engine's code changes.
"""
# physics: {physics_hash}
# helpers: {helpers_hash}
from numba import njit

from ensemble.engine import events, runge_kutta, splitting
from ensemble.engine.blocks import FAST
from ensemble.engine.adaptive import advance_of as adaptive_advance
from ensemble.engine.frames import adaptive, fixed_step
from ensemble.engine.kernels import called_functions, event_signs, event_values, splitting_functions
from ensemble.engine.tuples import unrolled

LIKE_Y, LIKE_P = (0.0,) * {D}, (0.0,) * {P}  # a member's state and parameters: their lengths matter
B = {B}  # members per block
'''
NO_EVENTS = '''BEGIN, REMEMBER, STEPS = events.NO_BEGIN, events.NO_REMEMBER, events.NO_STEPS
'''
NO_ADAPTIVE_EVENTS = '''BEGIN, LEVELS, WATCH = events.NO_BEGIN, events.NO_LEVELS, events.NO_ADAPTIVE_WATCH
'''
EVENT_VALUES = '''VALUES = event_values({where!r}, {event_sources!r}, {physics_hash!r})  # each event's value
SIGNS = event_signs({where!r}, {event_sources!r}, {physics_hash!r}, {D}, {P})  # each event's sign against its level
'''
FIXED_STEP = '''

@njit(nogil=True, cache=True, **FAST)
def kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works, start,
           first_block, end_block):
    fixed_step(INTERVAL, LIKE_Y, LIKE_P, B, state0, rate, h, steps_per_save, limit, samples, status, failure_time,
               progress, works, start, first_block, end_block, BEGIN, REMEMBER, STEPS, ())
'''
FIXED_STEP_EVENTS = '''

@njit(nogil=True, cache=True, **FAST)
def kernel(state0, rate, h, steps_per_save, limit, samples, status, failure_time, progress, works, event_arrays,
           start, first_block, end_block):
    fixed_step(INTERVAL, LIKE_Y, LIKE_P, B, state0, rate, h, steps_per_save, limit, samples, status, failure_time,
               progress, works, start, first_block, end_block, BEGIN, REMEMBER, STEPS, event_arrays)
'''
RUNGE_KUTTA = '''rhs, = called_functions({where!r}, ("rhs",), {physics_hash!r})
TABLEAU = {tableau!r}  # the stages' Butcher rows (c_s, a_s0, .., a_s,S-1), and b
INTERVAL = runge_kutta.members_interval(rhs, TABLEAU, unrolled({S}))  # the stages written out
'''
RUNGE_KUTTA_EVENTS = EVENT_VALUES + '''ADVANCE = runge_kutta.advance_of(rhs, TABLEAU, unrolled({S}))
BEGIN, REMEMBER, STEPS = events.fixed_watcher(VALUES, SIGNS, ADVANCE, None, {first_event_row}, {E})
'''
SPLITTING = '''PIECES, FACTORS, TO_PIECES, FROM_PIECES = splitting_functions({where!r}, {pieces!r}, {physics_hash!r})
SEQUENCE = {sequence!r}  # the method's entries: piece number, fraction of the step
LIKE_FACTORS = {like_factors!r}  # each entry's factors (their count matters)
INTERVAL = splitting.interval_of(PIECES, FACTORS, TO_PIECES, FROM_PIECES, SEQUENCE, LIKE_FACTORS)
'''
SPLITTING_EVENTS = EVENT_VALUES + '''ADVANCE = splitting.advance_of(PIECES, FACTORS, TO_PIECES, FROM_PIECES, SEQUENCE)
BEGIN, REMEMBER, STEPS = events.fixed_watcher(VALUES, SIGNS, ADVANCE, FROM_PIECES, {first_event_row}, {E})
'''
ADAPTIVE = '''rhs, = called_functions({where!r}, ("rhs",), {physics_hash!r})
TABLEAU = {tableau!r}  # the stages' Butcher rows (c_s, a_s0, .., a_s,S-1), and b - b_hat
STAGE_LOOP = unrolled({S})  # the stages written out
CONTROLLER = {controller!r}  # alpha, beta, safety, min_factor, max_factor
'''
ADAPTIVE_EVENTS = EVENT_VALUES + '''ADVANCE = adaptive_advance(rhs, TABLEAU, STAGE_LOOP)
BEGIN, LEVELS, WATCH = events.adaptive_watcher(VALUES, SIGNS, ADVANCE, {first_event_row}, {E})
'''
ADAPTIVE_KERNEL = '''

@njit(nogil=True, cache=True, **FAST)
def kernel(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, progress, works, start,
           first_block, end_block):
    adaptive(rhs, TABLEAU, STAGE_LOOP, CONTROLLER, LIKE_Y, LIKE_P, B, state0, rate, control, save_dt, limit,
             samples, counts, status, failure_time, progress, works, start, first_block, end_block, BEGIN, LEVELS,
             WATCH, ())
'''
ADAPTIVE_KERNEL_EVENTS = '''

@njit(nogil=True, cache=True, **FAST)
def kernel(state0, rate, control, save_dt, limit, samples, counts, status, failure_time, progress, works,
           event_arrays, start, first_block, end_block):
    adaptive(rhs, TABLEAU, STAGE_LOOP, CONTROLLER, LIKE_Y, LIKE_P, B, state0, rate, control, save_dt, limit,
             samples, counts, status, failure_time, progress, works, start, first_block, end_block, BEGIN, LEVELS,
             WATCH, event_arrays)
'''


def tableau_of(method: Method) -> tuple:
    """An explicit Runge-Kutta method's tableau as ensemble.engine.runge_kutta takes it: its stages' Butcher rows
    (c_s, a_s0, .., a_s,S-1) and its weights b, floats."""
    tableau = method.tableau
    S, a, c = tableau.stages, tableau.square_a(), tableau.c
    return (tuple((float(c[s]), *a[s * S:(s + 1) * S]) for s in range(S)), tuple(float(x) for x in tableau.b))


def pair_of(method: Method) -> tuple:
    """An embedded pair as ensemble.engine.adaptive takes it: its stages' Butcher rows and its error weights."""
    return tableau_of(method)[0], tuple(float(x) for x in method.tableau.error)


@cache
def called_functions(where: str, names: tuple[str, ...], expected: str) -> tuple:
    """physics_functions for the families written as code, which call a scene's functions with a member's tuples
    (`rhs(t, *y, *p)`): compiled as functions of their own, which LLVM inlines, since Numba inlines no call with
    *args."""
    module = loaded(where, expected)
    return tuple(_called(getattr(module, name)) for name in names)


def splitting_functions(where: str, pieces: tuple[str, ...], expected: str) -> tuple:
    """A scene's functions for a splitting (ensemble.engine.splitting), as called_functions compiles them: its
    pieces, in the splitting's numbering; each piece's `<piece>_factors` or None; to_pieces and from_pieces, or
    None."""
    module = loaded(where, expected)
    named = lambda name: _called(getattr(module, name)) if hasattr(module, name) else None  # noqa: E731
    return (tuple(named(piece) for piece in pieces), tuple(named(f"{piece}_factors") for piece in pieces),
            named("to_pieces"), named("from_pieces"))


@cache
def _called(function, inline: str = "never"):
    """A scene's function compiled with its own @njit options (or FAST, a plain function's) and Numba's `inline`:
    "never" for a call with *args, which LLVM inlines; "always" for the kernels' watch, which calls it with its
    arguments written out (events.written_out) and Numba inlines. Once per function and setting (an edited
    scene's module has new functions)."""
    if not isinstance(function, CPUDispatcher):
        return njit(inline=inline, **FAST)(function)
    if function.targetoptions.get("inline", "never") == inline:
        return function
    return njit(**{**function.targetoptions, "inline": inline})(function.py_func)


def load_source(source: str, label: str) -> ModuleType:
    """Import generated `source`, headed by the compile target, from its file in the kernel folder: written first
    if it is not there, written again (one line said) if its text is not `source`. Numba's inliner is edited
    first (ensemble.inlining: up to a third off the kernel's compile, the same code)."""
    inlining.apply()
    source = f"# compiled for: {compile_target()}\n{source}"
    name = f"ensemble_kernel_{label}_{hashlib.sha256(source.encode()).hexdigest()[:16]}"
    if name in sys.modules:
        return sys.modules[name]
    path = private_kernel_folder() / f"{name}.py"
    try:
        found = path.read_text()
    except (OSError, UnicodeDecodeError):
        found = None
    if found is not None and found != source:
        print(f"ensemble: {path} did not match its name (edited or damaged); writing it again", file=sys.stderr)
    if found != source:
        try:
            _write(path, source, replace=found is not None)
        except OSError as e:  # a full disk, a folder made read-only
            raise KernelFolderError(f"{path.parent}: cannot write a kernel file there ({e.strerror or e}); free "
                                    f"space, or set ENSEMBLE_KERNEL_DIR to another folder") from None
    module = importlib.util.module_from_spec(importlib.util.spec_from_file_location(name, path))
    exec(compile(source, str(path), "exec"), module.__dict__)  # the text checked, not the file read again
    sys.modules[name] = module
    return module


def _write(path: Path, text: str, replace: bool) -> None:
    """Write a kernel file under a temporary name and move it into place: never half a file. A new file is linked
    (another process may be writing the same one at once); a damaged one is replaced."""
    handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(handle, "w") as out:
        out.write(text)
    try:
        if replace:
            os.replace(temporary, path)
        else:
            os.link(temporary, path)
    except FileExistsError:
        pass
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)
