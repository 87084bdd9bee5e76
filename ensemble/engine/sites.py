"""Kernels over a field of sites: the method families' loops for a scene whose member is n sites on a line or a
ring, each accelerated by its two neighbours alone (the chain: masses joined by springs).

The scene's physics module gives one function, compiled with Numba:

    acceleration(x_left, x, x_right, c_left, c_right) -> acceleration of a site at x (m s-2)

where c_left and c_right are the site's couplings to its left and right neighbour (the scene's `rate` rows 0 .. n-1
and n .. 2n-1 of a member). The neighbour beyond an end is a ghost site at rest (a wall, through the wall's
coupling; a free end, through a coupling of 0) or, on a ring, a copy of the other end. The state is positions then
velocities (2n rows), and the splittings are KICK_DRIFT (kick: v += tau a(x); drift: x += tau v). The scene's
constants hold n and its boundary ("periodic" for a ring).

The families' kernels (explicit Runge-Kutta tableaus, kick/drift splittings, embedded adaptive pairs) are
ensemble.engine.sites_kernels's code, with events ensemble.engine.sites_events's too; `source` writes a kernel's
file: a header that binds the names that code reads to the scene's `acceleration`, the sizes, the rows, the
method's coefficients and the events, then the code, unchanged.
ensemble.engine.kernels imports it from a file that Numba keys its disk cache on. The helpers that do not call
`acceleration` are here, compiled once and inlined. This file also holds the layout's rules: members per block
(block_size) and when a long chain's splitting runs in tiles (tiles, ring_halo).

Work rows (B members each, row r of member j at r B + j): X (n + 2: ghost, sites 1..n, ghost), V (n), then CL and
CR (n each: the couplings); a tiled ring's rows hold its n sites between two halos (ring_halo; see
sites_kernels.splitting_kernel). Runge-Kutta adds the stage state ZX (n + 2), ZV (n) and slopes KX, KV (stages x n
each); an adaptive pair then its control rows (blocks.CONTROL_ROWS); a kernel with events then their rows
(event_rows). Forces come from neighbours only: O(n) per step.
"""
from __future__ import annotations

import hashlib
from functools import cache
from pathlib import Path

import numpy as np
from numba import njit

from ..methods import Method
from ..results import UNDERFLOWED
from ..tuning import Tuning
from .blocks import (
    CONTROL_ROWS,
    ERR,
    FAST,
    HELPERS,
    REJECTED_LAST,
    adaptive_constants,
    block_done,
    block_stopped,
    check_members,
    copy_into,
    rows_in,
    sample_out,
    select,
)
from .sources import copied_code

KERNELS_FILE = "sites_kernels.py"  # the kernels' code, which a kernel's file copies
EVENTS_FILE = "sites_events.py"  # the events' code, which a kernel's file with events copies after it
#: A hash of this file, the kernels' code and the engine's helpers: every sites kernel's file holds it (see
#: engine.kernels).
SITES_HELPERS = hashlib.sha256(b"".join((Path(__file__).parent / name).read_bytes() for name in
                                        ("sites.py", KERNELS_FILE, EVENTS_FILE)) + HELPERS.encode()).hexdigest()

TILE_ROWS, TILE_PIECES = 64, 32  # a long chain's splitting kernel: sites per tile, pieces per sweep
CHECK_STEPS = 32  # a fixed-step kernel with events: steps watched at once (sites_events), replayed to locate
TILE_FROM_L1 = 1.5  # a splitting runs in tiles when a block's rows outgrow this many times the L1 data cache
PIECES = ("kick", "drift")  # the splittings' pieces, in methods.KICK_DRIFT's order
KICK = PIECES.index("kick")


# ---------------------------------------------------------------- layout rules

def block_size(constants: dict, method: Method, tuning: Tuning) -> int:
    """Members per kernel block for `method` on a field of n sites: 64 below 16 sites, except for an adaptive
    pair whose 64 members' work rows (20n + 15 for dopri5, control rows included) would outgrow the host's L1
    data cache (l1_data_bytes): then two SIMD vectors of this host, but never fewer than 16. From 16 sites on,
    64 for fixed-step Runge-Kutta, and for splittings and adaptive pairs two SIMD vectors (vector_doubles: 8
    members with AVX2, 16 with AVX-512), or one where a block's work rows (4n + 2 for a splitting) would
    outgrow the L1 data cache, but never fewer than 8 for a pair. A member's arithmetic does not depend on its
    block: the bits are the same in every block, on every host. `ensemble tune` may replace a splitting's block
    from 16 sites on by a measured one (`tuning`'s sites_block). The measurements behind the rule:
    analysis/bench/README.md, "How the kernels are laid out"."""
    n = constants["n"]
    pair = 2 * vector_doubles()
    member_bytes = (stage_rows(n, method.tableau.stages)[-1] + CONTROL_ROWS) * 8 if method.adaptive else 0
    if n < 16:
        return 64 if member_bytes * 64 <= l1_data_bytes() else max(pair, 16)
    if method.adaptive:
        return pair if member_bytes * pair <= l1_data_bytes() else max(pair // 2, 8)
    if method.tableau is not None:
        return 64
    if (4 * n + 2) * pair * 8 <= l1_data_bytes():
        return tuning.sites_block or pair
    return pair // 2


@cache
def vector_doubles() -> int:
    """Doubles in one SIMD vector of this host's widest extension (LLVM's host features): 8 with AVX-512F,
    4 with AVX, else 2."""
    from llvmlite import binding

    features = binding.get_host_cpu_features()
    return 8 if features.get("avx512f") else 4 if features.get("avx") else 2


@cache
def l1_data_bytes(cpu: Path = Path("/sys/devices/system/cpu/cpu0/cache")) -> int:
    """Bytes of the first CPU's level 1 data cache (Linux sysfs: "48K"); 32 KiB where it cannot be read."""
    units = {"K": 1024, "M": 1024**2}
    for index in sorted(cpu.glob("index*")):
        try:
            level, kind, size = ((index / name).read_text().strip() for name in ("level", "type", "size"))
            if level == "1" and kind in ("Data", "Unified"):
                return int(size[:-1]) * units[size[-1]] if size[-1:] in units else int(size)
        except (OSError, ValueError):  # unreadable, or not in sysfs's form
            continue
    return 32 * 1024


def tiles(n: int, B: int, tuning: Tuning) -> bool:
    """Whether a splitting kernel runs a field of n sites in blocks of B members in tiles (see
    sites_kernels.splitting_kernel): when a block's 4n + 2 rows outgrow TILE_FROM_L1 times the L1 data cache, and
    the field is longer than two tiles (so a ring is longer than its halos), unless `ensemble tune` found one piece
    at a time faster here (`tuning`'s fused_sweeps). The measurements behind the rule are in
    analysis/bench/JOURNAL.md."""
    return (n > 2 * TILE_ROWS and (4 * n + 2) * B * 8 > TILE_FROM_L1 * l1_data_bytes()
            and tuning.fused_sweeps is not False)


def ring_halo(method: Method) -> int:
    """Sites a long ring's rows hold beyond each end for a splitting `method`: the most kicks in one run of
    TILE_PIECES pieces (one site each: how far a row end's wrong value travels before the halos are copied
    again)."""
    kinds = splitting_schedule.py_func(method.splitting.numbers, method.splitting.fractions, 1.0,
                                       2 * TILE_PIECES + 1, TILE_PIECES)[0]  # no compile
    return max(int(np.sum(kinds[c:c + TILE_PIECES] == KICK)) for c in range(0, len(kinds), TILE_PIECES))


def work_rows(method: Method, n: int, periodic: bool, tiled: bool, events: int = 0) -> int:
    """Rows of a kernel's work array (B floats each) for `method` over n sites (a ring if periodic), in tiles or
    not: a Runge-Kutta kernel's rows end with its stages' slopes, an adaptive one's with its control rows, a
    splitting's with the neighbours' rows CL and CR (its halos on a tiled ring); then those of its `events`
    (event_rows)."""
    halo = ring_halo(method) if tiled and periodic else 0
    rows = stage_rows(n + 2 * halo, method.tableau.stages if method.tableau is not None else 1)
    if method.tableau is None:
        return rows[2] + event_rows(method, n, events)
    return rows[-1] + (CONTROL_ROWS if method.adaptive else 0) + event_rows(method, n, events)


def event_rows(method: Method, n: int, events: int) -> int:
    """Work rows of a fixed-step kernel's events (sites_events's TRACE, CHECK): each event's values at the start
    of a group of CHECK_STEPS steps and after each step (CHECK_STEPS + 1 rows an event), and the state at the
    group's start (2n + 1 rows, a ghost among them). An adaptive kernel's events need none: its step's start and
    end are both in its rows."""
    if not events or method.adaptive:
        return 0
    return events * (CHECK_STEPS + 1) + 2 * n + 1


def event_work_row(source: tuple, n: int) -> int:
    """The work row of an event's value (results.Event.source, ("state", r): x of site r + 1, or v of site
    r - n + 1 from r = n), in an untiled kernel's rows (X + 1 + r; V + r - n)."""
    kind, r = source[:2]
    if kind != "state":
        raise ValueError(f"a field of sites' events watch its state, not {source!r}")
    return r + 1 if r < n else r + 2


def stage_rows(n: int, stages: int) -> tuple[int, ...]:
    """The first rows of X, V, ZX, ZV, KX and KV in a Runge-Kutta kernel of `stages` stages (CL and CR lie between
    V and ZX), and the row after KV: where an adaptive kernel's control rows begin."""
    X, V = 0, n + 2
    ZX = V + 3 * n  # after V, CL and CR
    ZV = ZX + n + 2
    KX = ZV + n
    KV = KX + stages * n
    return X, V, ZX, ZV, KX, KV, KV + stages * n


# ---------------------------------------------------------------- helpers that do not call the scene
# They take n, B and the rows as arguments: inlined into a kernel, these are its constants again.

@njit(**FAST)
def splitting_schedule(pieces, fractions, h, steps_per_save, chunk):
    """The pieces of one save interval of steps h (s): kinds (KICK or DRIFT), taus (s), and lags.

    pieces and fractions: a splitting's sequence (piece numbers, fractions
    of the step). Where a step ends with the piece the next begins with
    (verlet: a half kick), the two merge into one. lags[p] is how many sites piece p runs
    behind the first piece of its chunk (pieces in chunks of `chunk`): one
    more at each change between kick and drift.
    """
    E = len(pieces)
    merge = E > 1 and pieces[0] == pieces[E - 1]
    kinds = np.empty(E * steps_per_save, np.int64)
    taus = np.empty(E * steps_per_save)
    count = 0
    for step in range(steps_per_save):
        for e in range(E):
            if merge and e == 0 and step > 0:
                continue  # done by the previous step's last piece
            tau = h * fractions[e]
            if merge and e == E - 1 and step < steps_per_save - 1:
                tau += h * fractions[0]
            kinds[count] = pieces[e]
            taus[count] = tau
            count += 1
    lags = np.zeros(count, np.int64)
    for p in range(count):
        if p % chunk:
            lags[p] = lags[p - 1] + (kinds[p] != kinds[p - 1])
    return kinds[:count], taus[:count], lags


@njit(inline="always", **FAST)
def set_ghosts(work, x, n, B, periodic):
    """Ring: the ghost sites of the positions at row x copy sites n and 1; walls and free ends keep 0."""
    if periodic:
        for j in range(B):
            work[x * B + j] = work[(x + n) * B + j]
            work[(x + n + 1) * B + j] = work[(x + 1) * B + j]


@njit(inline="always", **FAST)
def _fill_halos(work, row, n, halo, B):
    """A tiled ring's rows from `row` on (one of X + 1, V, CL, CR) hold halo sites, its n sites, halo sites:
    the halos copy the sites at the ring's other end (site n - halo + e before site 1, site e after site n)."""
    for q in range(halo * B):
        work[row * B + q] = work[(row + n) * B + q]
        work[(row + halo + n) * B + q] = work[(row + halo) * B + q]


@njit(inline="always", **FAST)
def refresh_halos(work, n, halo, B):
    """A tiled ring: its positions' and velocities' halos from its sites (nothing when halo is 0)."""
    m = n + 2 * halo
    if halo > 0:
        _fill_halos(work, 1, n, halo, B)
        _fill_halos(work, m + 2, n, halo, B)


@njit(inline="always", **FAST)
def _store_sample(work, samples, save, block, n, halo, B):
    m = n + 2 * halo
    sample_out(work, 1 + halo, samples, save, block, 0, n, B)
    sample_out(work, m + 2 + halo, samples, save, block, n, n, B)


@njit(inline="always", **FAST)
def load_block(work, state0, rate, block, samples, n, halo, B, periodic):
    """Start a block's (zeroed) work array with its state and couplings; also its first sample. A tiled ring's
    rows hold n + 2 halo sites each, its own n between two halos."""
    m = n + 2 * halo
    rows_in(work, 1 + halo, state0[block], 0, n, B)
    rows_in(work, m + 2 + halo, state0[block], n, n, B)
    rows_in(work, 2 * m + 2 + halo, rate[block], 0, n, B)
    rows_in(work, 3 * m + 2 + halo, rate[block], n, n, B)
    _store_sample(work, samples, 0, block, n, halo, B)
    if halo > 0:
        refresh_halos(work, n, halo, B)
        _fill_halos(work, 2 * m + 2, n, halo, B)
        _fill_halos(work, 3 * m + 2, n, halo, B)
    else:
        set_ghosts(work, 0, n, B, periodic)


@njit(inline="always", **FAST)
def fixed_start(work, works, state0, rate, block, samples, limit, status, failure_time, progress, start, n, halo,
                B, periodic):
    """Copy a block's work array into the call's `work` (cache_line_array), and whether the block runs: a call
    at start 0 loads it from state0, a later one continues it unless every member has failed."""
    copy_into(work, works[block])
    if start == 0:
        load_block(work, state0, rate, block, samples, n, halo, B, periodic)
        m = n + 2 * halo
        check_members(work, 1, 2 * m + 1, B, block * B, limit, status, failure_time, 0.0)  # a non-finite start
        return True
    return not block_done(samples, status, progress, block, B)


@njit(inline="always", **FAST)
def saved(work, samples, save, block, limit, status, failure_time, progress, t, step_row, n, halo, B):
    """End of a save interval at time t (s): fail the members that blew up, store sample `save`; when no member
    of the block runs any more, fill its later samples with NaN and return True (the block is done). A tiled
    ring's halos are refreshed first, so the check sees its sites' values only."""
    refresh_halos(work, n, halo, B)
    m = n + 2 * halo
    running = check_members(work, 1, 2 * m + 1, B, block * B, limit, status, failure_time, t, step_row)
    _store_sample(work, samples, save, block, n, halo, B)
    return block_stopped(samples, progress, running, save, block, B)


@njit(inline="always", **FAST)
def stage_sums(work, weights, S, KX, KV, i, j, n, B):
    """sum_s weights[s] K_s for site i + 1 of member j: its x part and its v part."""
    dx = 0.0
    dv = 0.0
    for s in range(S):
        dx += weights[s] * work[(KX + s * n + i) * B + j]
        dv += weights[s] * work[(KV + s * n + i) * B + j]
    return dx, dv


@njit(inline="always", **FAST)
def drift(work, tau, lo, hi, n, B):
    """Drift sites lo + 1 .. hi: x += tau (s) times their velocity."""
    w = work[lo * B:]
    for q in range((hi - lo) * B):
        w[B + q] += tau * w[(n + 2) * B + q]


@njit(inline="always", **FAST)
def accept(work, X, V, ZX, ZV, KX, KV, C0, S, n, B):
    """After control_step: members whose step was accepted move to the stage state ZX, ZV (its last slopes are the
    next step's first); members whose step underflowed become NaN. In selects for blocks of 16 or more, in
    branches for fewer: each form is the faster at its block, as AVX-512 and as AVX2 code (analysis/bench/README.md,
    `python analysis/bench/bench_dopri5.py --chain-block B`)."""
    last = S - 1
    for i in range(n):
        for j in range(B):
            err = work[(C0 + ERR) * B + j]
            accepted = (work[(C0 + REJECTED_LAST) * B + j] == 0.0) & (err >= 0.0)
            underflowed = err == UNDERFLOWED
            if B >= 16:
                x, v = work[(X + 1 + i) * B + j], work[(V + i) * B + j]
                work[(X + 1 + i) * B + j] = select(accepted, work[(ZX + 1 + i) * B + j], select(underflowed, np.nan, x))
                work[(V + i) * B + j] = select(accepted, work[(ZV + i) * B + j], select(underflowed, np.nan, v))
                work[(KX + i) * B + j] = select(accepted, work[(KX + last * n + i) * B + j], work[(KX + i) * B + j])
                work[(KV + i) * B + j] = select(accepted, work[(KV + last * n + i) * B + j], work[(KV + i) * B + j])
            elif accepted:
                work[(X + 1 + i) * B + j] = work[(ZX + 1 + i) * B + j]
                work[(V + i) * B + j] = work[(ZV + i) * B + j]
                work[(KX + i) * B + j] = work[(KX + last * n + i) * B + j]
                work[(KV + i) * B + j] = work[(KV + last * n + i) * B + j]
            elif underflowed:
                work[(X + 1 + i) * B + j] = np.nan
                work[(V + i) * B + j] = np.nan


# ---------------------------------------------------------------- a kernel's file

HEADER = '''"""Generated by ensemble.engine.sites: the {family} kernel of {scene}, method {method}, {n} sites{ring}.

Do not edit: ensemble writes a new file whenever the engine's code or the scene's physics changes. Below the
bindings, the code of ensemble.engine.sites_kernels (then, with events, of ensemble.engine.sites_events),
unchanged.
"""
# physics: {physics_hash}
# helpers: {helpers_hash}
{imports}
from ensemble.engine.kernels import event_values, physics_functions

acceleration, = physics_functions({where!r}, ("acceleration",), {physics_hash!r})
VALUES = event_values({where!r}, {event_sources!r}, {physics_hash!r})  # each event's value on a member's (x; v)

N, HALO, B, PERIODIC = {n}, {halo}, {B}, {periodic}  # sites, halo sites beyond each end of a row, members, a ring
M = N + 2 * HALO  # sites in a row
S = {S}  # stages
X, V, ZX, ZV, KX, KV, C0 = {rows}  # first rows (see ensemble.engine.sites); C0: an adaptive pair's control
FAMILY = {family!r}
E, EVENT_ROWS, FIRST_EVENT = {E}, {event_rows}, {first_event}  # events: each one's work row, the events' first row
{bindings}
'''


def source(scene_name: str, where: str, physics_hash: str, method: Method, n: int, periodic: bool, B: int,
           tiled: bool, halo: int, events: tuple = ()) -> tuple[str, int]:
    """The kernel file's source for `method` over n sites (a ring if periodic) in blocks of B members, in tiles or
    not (`tiles`), a ring's rows holding `halo` sites beyond each end (`ring_halo`), with `events` (each one's
    results.Event.source; a kernel with events is never tiled), and its work rows; `where` names the scene's
    physics module (its `acceleration`), physics_hash the identity of its sources
    (ensemble.scenes.contract.identity)."""
    S = method.tableau.stages if method.tableau is not None else 1
    rows = stage_rows(n + 2 * halo, S)
    if method.adaptive:
        S, a, e, *control = adaptive_constants(method)
        family = "adaptive"
        bindings = (f"A = np.array({a})  # indexed by a loop variable: a constant array, not a tuple\n"
                    f"ERROR = {e}  # b - b_hat: h sum_s ERROR[s] k_s estimates the local error\n"
                    f"ALPHA, BETA, SAFETY, MIN_FACTOR, MAX_FACTOR = {tuple(control)}")
    elif method.tableau is not None:
        b = tuple(float(x) for x in method.tableau.b)
        family, bindings = "runge_kutta", f"A, WEIGHTS = {method.tableau.square_a()}, {b}  # the tableau: a (flat), b"
    else:
        family = "splitting"
        bindings = (f"SEQUENCE, FRACTIONS = {method.splitting.numbers}, {method.splitting.fractions}  # piece "
                    f"numbers (KICK or drift), fractions of the step\nTILED = {tiled}")
    imports, code = copied_code(KERNELS_FILE)
    if events:
        event_imports, event_code = copied_code(EVENTS_FILE)
        imports, code = f"{imports}\n{event_imports}", f"{code}\n\n{event_code}"
    first_event = work_rows(method, n, periodic, tiled)
    head = HEADER.format(family=family, scene=scene_name, method=method.name, n=n,
                         ring=" (a ring)" if periodic else "", physics_hash=physics_hash, helpers_hash=SITES_HELPERS,
                         imports=imports, where=where, event_sources=events, halo=halo, B=B, periodic=periodic, S=S,
                         rows=rows, E=len(events), event_rows=tuple(event_work_row(e, n) for e in events),
                         first_event=first_event, bindings=bindings)
    kernel = f"{family}_events_kernel" if events else f"{family}_kernel"
    return f"{head}\n\n{code}\n\nkernel = {kernel}\n", work_rows(method, n, periodic, tiled, len(events))
