"""A field of sites (the chain: positions and velocities of n masses joined to their neighbours) as CUDA kernels:
one thread holds a short field in its local arrays; from SHARED_SITES sites on, a block of threads shares a field,
each thread owning a few sites, the positions in shared memory, the threads meeting at a barrier after each kick
and drift (each Runge-Kutta stage). The kernels' code is ensemble.engine.gpu_sites_kernels; a kernel's file is
ensemble.engine.gpu's header, the names that module's code reads bound to the chain's sizes, layout and method,
then that code, unchanged.
"""
from __future__ import annotations

from functools import cache

from ..methods import Method
from .blocks import adaptive_constants
from .gpu import GpuKernel, compiled
from .kernels import Layout

KERNELS_FILE = "gpu_sites_kernels.py"  # the kernels' code, which a kernel's file copies

BINDINGS = '''N, N2, PERIODIC = {N}, {N2}, {periodic}  # sites, positions with their ghosts, a ring
T, J = {T}, {J}  # threads per member, sites per thread
{method}
'''


def method_bindings(method: Method, J: int, events: bool = False) -> tuple[str, str]:
    """(family, the lines that bind the method's names in gpu_sites_kernels): its coefficients in REAL, and its
    stages (a splitting's pieces) written out as a chain of device functions; with `events`, a splitting's steps
    taken whole (each watched at its end: not merged with the next)."""
    if method.tableau is None:
        numbers, fractions = method.splitting.numbers, method.splitting.fractions
        return "splitting", (f"SEQUENCE, FRACTIONS = {numbers}, tuple(REAL(f) for f in {fractions})\n"
                             "PIECE_LOOP = device_unrolled(len(SEQUENCE))\n"
                             f"MERGED = {not events and len(numbers) > 1 and numbers[0] == numbers[-1]}")
    S = method.tableau.stages
    lines = [f"S, SJ = {S}, {S * J}  # stages, stage slopes per thread",
             f"A = tuple(REAL(a) for a in {method.tableau.square_a()})  # flat S x S",
             "STAGE_LOOP = device_unrolled(S)"]
    if not method.adaptive:
        weights = tuple(float(b) for b in method.tableau.b)
        return "runge_kutta", "\n".join([*lines, f"WEIGHTS = tuple(REAL(b) for b in {weights})"])
    _, _, e, *control = adaptive_constants(method)
    return "adaptive", "\n".join([*lines, f"ERROR = tuple(REAL(e) for e in {e})",
                                   f"CONTROLLER = {tuple(control)}  # alpha, beta, safety, min_factor, max_factor"])


WARP = 32  # threads that run in lockstep on an NVIDIA GPU
SHARED_SITES = 64  # fields of at least this many sites run as a block of threads each (docs/gpu.md: the layouts)
MOST_SITE_THREADS = 256  # threads per field of sites, at most
SHARED_BYTES = 48 * 1024  # the shared memory a block may hold without asking for more


def site_threads(n: int, method: Method, events: tuple = ()) -> int:
    """Threads per member for a field of n sites: 1 (the member in one thread's local arrays) for short fields,
    for fields whose positions outgrow SHARED_BYTES and where there are events (located on one thread), else a
    block of whole warps, up to MOST_SITE_THREADS, each thread owning a few sites with the positions in the
    block's shared memory."""
    if events:
        return 1
    shared = (n + 2) * 8 * (2 if method.tableau is not None else 1)  # x, and a Runge-Kutta stage's zx
    shared += 8 * MOST_SITE_THREADS if method.adaptive else 0  # where the threads add up the error norm
    if n < SHARED_SITES or shared > SHARED_BYTES:
        return 1
    return min(MOST_SITE_THREADS, WARP * -(-n // WARP))


def work_rows(method: Method, n: int, E: int = 0) -> int:
    """Rows of a field of n sites' works: its positions and velocities, and an adaptive member's first slopes, its
    controller's state and its counts, then its E events' values."""
    return (4 * n + 7 if method.adaptive else 2 * n) + E


EVENTS = '''from ensemble.engine.gpu_device import device_event_values
E, EVENT_ROWS = {E}, {rows}  # events, each one's row of the state (x; v)
VALUES = device_event_values({where!r}, {event_sources!r}, {sources!r})  # each one's value (engine.events)'''
NO_EVENTS = "E, EVENT_ROWS = 0, (0,)  # no events"
EVENT_FOOTER = ("\nremember, watch_fixed, watch_adaptive = kept, fixed_watch, adaptive_watch\n"
                "moved, family_step = {moved}, {step}")  # events.located's advance, and a fixed step's family step
EVENT_STEPS = {"splitting": dict(moved="fixed_moved", step="split_step"),
               "runge_kutta": dict(moved="fixed_moved", step="runge_kutta_step"),
               "adaptive": dict(moved="adaptive_moved", step=None)}


@cache
def sites_kernel(name: str, where: str, sources: str, pieces: tuple[str, ...], method: Method, n: int,
                 periodic: bool, precision: str, chosen: Layout) -> GpuKernel:
    """A scene's field-of-sites kernel for `method` over n sites (a ring if periodic) in `precision`, in the
    `chosen` layout's threads per member (site_threads): the GPU header, the bindings, gpu_sites_kernels's code,
    unchanged."""
    threads, events = chosen.threads, chosen.events
    J = -(-n // threads)
    family, bindings = method_bindings(method, J, bool(events))
    bindings = BINDINGS.format(N=n, N2=n + 2, periodic=periodic, T=threads, J=J, method=bindings)
    bindings += "\n" + (EVENTS.format(E=len(events), rows=tuple(source[1] for source in events), where=where,
                                      event_sources=events, sources=sources) if events else NO_EVENTS)
    footer = f"kernel = {family}_kernel" + (EVENT_FOOTER.format(**EVENT_STEPS[family]) if events else "")
    physics_import = f"acceleration, = device_functions({where!r}, ('acceleration',), {sources!r})"
    return GpuKernel(compiled(f"sites {family}", name, method, precision, physics_import, sources, 2 * n, 2 * n,
                              KERNELS_FILE, bindings, footer, threads, bool(events)), chosen)
