"""A field of sites (the chain: positions and velocities of n masses joined to their neighbours) as CUDA kernels:
one thread holds a short field in its local arrays; from SHARED_SITES sites on, a block of threads shares a field,
each thread owning a few sites, the positions in shared memory, the threads meeting at a barrier after each kick
and drift (each Runge-Kutta stage). Built on ensemble.engine.gpu's header, heads and step control.
"""
from __future__ import annotations

from functools import cache

from ..methods import Method
from .blocks import FIRST_LOG2_ERR_PREVIOUS, adaptive_constants
from .gpu import ADAPTIVE_HEAD, BLEW_UP, CONTROL_STEP, FIXED_HEAD, OK, UNDERFLOW, GpuKernel, compiled, indented

SITES_HEADER = '''
N, D = {N}, 2 * {N}  # sites, state values
PERIODIC = {periodic}
# A chain's T threads each own J sites: thread `lane` owns sites lane, lane + T, ... (T = 1: one thread holds the
# chain in its local arrays). Site q's position is x[q + 1]: x has a ghost site at rest at each end (0 and N + 1);
# the ends of a ring are each other's neighbours.
T, J = {T}, {J}


@cuda.jit(device=True)
def lane():
    return {lane}


@cuda.jit(device=True)
def neighbours(q):
    """Where in x site q's left and right neighbours are."""
    if PERIODIC:
        return N if q == 0 else q, 1 if q == N - 1 else q + 2
    return q, q + 2


@cuda.jit(device=True)
def failed(x, v, limit):
    """Whether any site of the chain is not finite or beyond `limit`; subnormals become zeros of their sign first,
    as the CPU's check_members makes them."""
    bad = 0
    for j in range(J):
        q = lane() + j * T
        if q < N:
            x[q + 1] = x[q + 1] if abs(x[q + 1]) >= TINY else x[q + 1] * ZERO
            v[j] = v[j] if abs(v[j]) >= TINY else v[j] * ZERO
            if not (abs(x[q + 1]) <= limit and abs(v[j]) <= limit) or math.isinf(x[q + 1]) or math.isinf(v[j]):
                bad = 1
    return {any_lane}


@cuda.jit(device=True)
def fail(x, v):
    for j in range(J):
        q = lane() + j * T
        if q < N:
            x[q + 1], v[j] = NAN, NAN


@cuda.jit(device=True)
def store(samples, i, m, x, v):
    for j in range(J):
        q = lane() + j * T
        if q < N:
            samples[i, q, m], samples[i, N + q, m] = x[q + 1], v[j]


@cuda.jit(device=True)
def over_lanes(value, scratch, largest):
    """The sum (largest: the largest) of every thread's `value` >= 0 over the chain's threads, in lane order, in
    each of them."""
    scratch[lane()] = value
    cuda.syncthreads()
    out = REAL(0.0)
    for t in range(T):
        out = max(out, scratch[t]) if largest else out + scratch[t]
    cuda.syncthreads()
    return out


@cuda.jit(device=True)
def kick(tau, x, v, cl, cr):
    for j in range(J):
        q = lane() + j * T
        if q < N:
            left, right = neighbours(q)
            v[j] += tau * acceleration(x[left], x[q + 1], x[right], cl[j], cr[j])
    {sync}


@cuda.jit(device=True)
def drift(tau, x, v, cl, cr):
    for j in range(J):
        q = lane() + j * T
        if q < N:
            x[q + 1] += tau * v[j]
    {sync}


'''

# A chain's start: its sites' springs and state, from state0 (first call) or works (later calls).
SITES_LOAD = '''    if lane() == 0:
        x[0], x[N + 1] = REAL(0.0), REAL(0.0)
    for j in range(J):
        q = lane() + j * T
        if q < N:
            cl[j], cr[j] = REAL(rate[q, m]), REAL(rate[N + q, m])
            if start == 0:
                x[q + 1], v[j] = REAL(state0[q, m]), REAL(state0[N + q, m])
            else:
                x[q + 1], v[j] = REAL(works[q, m]), REAL(works[N + q, m])
'''

# A field's start, checked as every saved sample is: a member that starts beyond its limit fails at t = 0.
SITES_START_CHECKED = '''        if failed(x, v, limit[m]):
            alive = False
            if lane() == 0:
                status[m], failure_time[m] = {BLEW_UP}, 0.0
            fail(x, v)
        store(samples, 0, m, x, v)
        first = 1
'''

SITES_FIXED = FIXED_HEAD + '''
    x = cuda.{x_memory}.array({N2}, REAL)  # sizes written as numbers: the arrays take constants only
    v = cuda.local.array({J}, REAL)
    cl = cuda.local.array({J}, REAL)
    cr = cuda.local.array({J}, REAL)
{arrays}
    alive = status[m] == {OK}
''' + SITES_LOAD + '''    {sync}
    first = 0
    if start == 0:
''' + SITES_START_CHECKED + '''    for i in range(first, samples.shape[0]):
        if alive:
            for step in range(steps_per_save):
{step}
            if failed(x, v, limit[m]):
                alive = False
                if lane() == 0:
                    status[m], failure_time[m] = {BLEW_UP}, (start + i) * steps_per_save * h
                fail(x, v)
        store(samples, i, m, x, v)
    for j in range(J):
        q = lane() + j * T
        if q < N:
            works[q, m], works[N + q, m] = x[q + 1], v[j]
'''


SITES_ADAPTIVE = ADAPTIVE_HEAD + '''    x = cuda.{x_memory}.array({N2}, REAL)
    v = cuda.local.array({J}, REAL)
    cl = cuda.local.array({J}, REAL)
    cr = cuda.local.array({J}, REAL)
    zx = cuda.{x_memory}.array({N2}, REAL)
    zv = cuda.local.array({J}, REAL)
    kx = cuda.local.array({SJ}, REAL)  # stage s's slopes at s J + j; stage 0's are the last step's last (FSAL)
    kv = cuda.local.array({SJ}, REAL)
    scratch = cuda.{x_memory}.array({T}, REAL)  # where the chain's threads add up the error norm
    rtol, atol = REAL(control[1, m]), REAL(control[2, m])
    alive = status[m] == {OK}
    if lane() == 0:
        zx[0], zx[N + 1] = REAL(0.0), REAL(0.0)
''' + SITES_LOAD + '''            if start != 0:
                kx[j], kv[j] = REAL(works[2 * N + q, m]), REAL(works[3 * N + q, m])
    {sync}
    first = 0
    if start == 0:
        size, slope = REAL(0.0), REAL(0.0)  # Hairer's guess of a first step, from |y| and |y'| in tolerances
        for j in range(J):
            q = lane() + j * T
            if q < N:
                left, right = neighbours(q)
                kx[j], kv[j] = v[j], acceleration(x[left], x[q + 1], x[right], cl[j], cr[j])
                size = max(size, abs(x[q + 1]) / (atol + rtol * abs(x[q + 1])), abs(v[j]) / (atol + rtol * abs(v[j])))
                slope = max(slope, abs(v[j]) / (atol + rtol * abs(x[q + 1])), abs(kv[j]) / (atol + rtol * abs(v[j])))
        size, slope = {max_size}, {max_slope}
        h = REAL(control[0, m])
        if h <= 0.0:
            h = REAL(first_step(size, slope, save_dt))
        time, log2_previous, rejected_last = REAL(0.0), {first_log2}, False
        accepted_count, rejected_count, evaluations = 0.0, 0.0, 1.0
''' + SITES_START_CHECKED + '''    else:
        time, h, log2_previous = REAL(works[4 * N, m]), REAL(works[4 * N + 1, m]), REAL(works[4 * N + 2, m])
        rejected_last = 0.0 != works[4 * N + 3, m]
        accepted_count, rejected_count, evaluations = works[4 * N + 4, m], works[4 * N + 5, m], works[4 * N + 6, m]
    for i in range(first, samples.shape[0]):
        target = (start + i) * save_dt
        while alive and time < target:
            step = min(h, REAL(target - time))
{stages}
            estimate = REAL(0.0)
            for j in range(J):
                q = lane() + j * T
                if q < N:
                    qx = step * ({error_x}) / (atol + rtol * max(abs(x[q + 1]), abs(zx[q + 1])))
                    qv = step * ({error_v}) / (atol + rtol * max(abs(v[j]), abs(zv[j])))
                    estimate += qx * qx + qv * qv
            err = math.sqrt({sum_estimate} / D)
''' + CONTROL_STEP + '''                for j in range(J):
                    q = lane() + j * T
                    if q < N:
                        x[q + 1], v[j] = zx[q + 1], zv[j]
                        kx[j], kv[j] = kx[(S - 1) * J + j], kv[(S - 1) * J + j]
            elif underflowed:
                alive = False
                if lane() == 0:
                    status[m], failure_time[m] = {UNDERFLOW}, time
                fail(x, v)
        if alive and failed(x, v, limit[m]):
            alive = False
            if lane() == 0:
                status[m], failure_time[m] = {BLEW_UP}, target
            fail(x, v)
        store(samples, i, m, x, v)
    for j in range(J):
        q = lane() + j * T
        if q < N:
            works[q, m], works[N + q, m], works[2 * N + q, m], works[3 * N + q, m] = x[q + 1], v[j], kx[j], kv[j]
    if lane() == 0:
        works[4 * N, m], works[4 * N + 1, m], works[4 * N + 2, m] = time, h, log2_previous
        works[4 * N + 3, m] = 1.0 if rejected_last else 0.0
        works[4 * N + 4, m], works[4 * N + 5, m], works[4 * N + 6, m] = accepted_count, rejected_count, evaluations
        counts[0, m], counts[1, m], counts[2, m] = accepted_count, rejected_count, evaluations
'''


def _sites_loop(lines: list[str]) -> list[str]:
    """`lines` for each site j of this thread's (site q), in a loop over them."""
    return ["for j in range(J):", "    q = lane() + j * T", "    if q < N:", *("        " + line for line in lines)]


def _sites_stages(S: int, a: tuple, h: str, first: int, sync: str) -> list[str]:
    """Runge-Kutta stages first .. S - 1 over a field of sites: stage s's state into zx, zv, its slopes into kx,
    kv at s J + j (site q = lane + j T). Coefficients that are zero are left out."""
    lines = []
    for s in range(first, S):
        terms_x = "".join(f" + ({h} * REAL({a[s * S + r]!r})) * kx[{r} * J + j]" for r in range(s) if a[s * S + r])
        lines += _sites_loop([f"zx[q + 1] = x[q + 1]{terms_x}", f"zv[j] = v[j]{terms_x.replace('kx[', 'kv[')}"])
        lines += [sync, *_sites_loop(["left, right = neighbours(q)", f"kx[{s} * J + j] = zv[j]",
                                      f"kv[{s} * J + j] = acceleration(zx[left], zx[q + 1], zx[right], cl[j], cr[j])"]),
                  sync]  # every site's slopes read its neighbours' zx before the next stage writes it
    return lines


def sites_adaptive(method: Method, layout: dict) -> dict:
    """An embedded pair over a field of sites: as the member template's, the error norm and the first step's
    guess taken over the chain's threads (all of them then choose the same step)."""
    S, a, e, alpha, beta, safety, min_factor, max_factor = adaptive_constants(method)
    error_x = " + ".join(f"REAL({e[s]!r}) * kx[{s} * J + j]" for s in range(S) if e[s])
    shared = layout["T"] > 1
    return dict(S=S, SJ=S * layout["J"], control=(alpha, beta, safety, min_factor, max_factor),
                sum_estimate="over_lanes(estimate, scratch, False)" if shared else "estimate",
                max_size="over_lanes(size, scratch, True)" if shared else "size",
                max_slope="over_lanes(slope, scratch, True)" if shared else "slope",
                first_log2=f"REAL({FIRST_LOG2_ERR_PREVIOUS!r})",
                stages=indented(_sites_stages(S, a, "step", 1, layout["sync"]), 12), error_x=error_x,
                error_v=error_x.replace("kx[", "kv["))


def sites_splitting(method: Method, pieces: tuple[str, ...]) -> dict:
    """A kick/drift splitting's step over a field of sites. As on the CPU (blocks.splitting_schedule), a step that
    ends with the piece the next begins with (verlet's half kicks) merges the two."""
    sequence, fractions = method.splitting.numbers, method.splitting.fractions
    E = len(sequence)
    merge = E > 1 and sequence[0] == sequence[-1]
    lines = []
    for e, number in enumerate(sequence):
        call = f"{pieces[number]}(h * REAL({fractions[e]!r}){{extra}}, x, v, cl, cr)"
        if merge and e == 0:
            lines += ["if step == 0:", "    " + call.format(extra="")]
        elif merge and e == E - 1:
            lines.append(call.format(extra=f" + (h * REAL({fractions[0]!r}) if step < steps_per_save - 1 else "
                                           "REAL(0.0))"))
        else:
            lines.append(call.format(extra=""))
    return dict(arrays="", step=indented(lines, 16))


def sites_runge_kutta(method: Method, n: int, layout: dict) -> dict:
    """An explicit Runge-Kutta step over a field of sites: the stage state zx (shared by the chain's threads) and
    zv, and the stage slopes kx, kv (S J each) of this thread's sites."""
    S, a, b = method.tableau.stages, method.tableau.square_a(), tuple(float(x) for x in method.tableau.b)
    lines = _sites_stages(S, a, "h", 0, layout["sync"])  # the chain's forces do not depend on time: no stage times
    sums_x = " + ".join(f"REAL({b[s]!r}) * kx[{s} * J + j]" for s in range(S) if b[s])
    lines += _sites_loop([f"x[q + 1] += h * ({sums_x})", f"v[j] += h * ({sums_x.replace('kx[', 'kv[')})"])
    J = layout["J"]
    arrays = [f"zx = cuda.{layout['x_memory']}.array({n + 2}, REAL)", f"zv = cuda.local.array({J}, REAL)",
              f"kx = cuda.local.array({S * J}, REAL)", f"kv = cuda.local.array({S * J}, REAL)",
              "if lane() == 0:", "    zx[0], zx[N + 1] = REAL(0.0), REAL(0.0)"]
    return dict(arrays=indented(arrays, 4), step=indented(lines, 16))


WARP = 32  # threads that run in lockstep on an NVIDIA GPU
SHARED_SITES = 64  # fields of at least this many sites run as a block of threads each (docs/gpu.md: the layouts)
MOST_SITE_THREADS = 256  # threads per field of sites, at most
SHARED_BYTES = 48 * 1024  # the shared memory a block may hold without asking for more


def site_threads(n: int, method: Method) -> int:
    """Threads per member for a field of n sites: 1 (the member in one thread's local arrays) for short fields
    and for fields whose positions outgrow SHARED_BYTES, else a block of whole warps, up to
    MOST_SITE_THREADS, each thread owning a few sites with the positions in the block's shared memory."""
    shared = (n + 2) * 8 * (2 if method.tableau is not None else 1)  # x, and a Runge-Kutta stage's zx
    shared += 8 * MOST_SITE_THREADS if method.adaptive else 0  # where the threads add up the error norm
    if n < SHARED_SITES or shared > SHARED_BYTES:
        return 1
    return min(MOST_SITE_THREADS, WARP * -(-n // WARP))


def sites_layout(n: int, threads: int) -> dict:
    """The template fields that place a field of n sites: in one thread (threads = 1) or a block of threads."""
    shared = threads > 1
    return dict(T=threads, J=-(-n // threads), lane="cuda.threadIdx.x" if shared else "0",
                member="cuda.blockIdx.x" if shared else "cuda.grid(1)", x_memory="shared" if shared else "local",
                sync="cuda.syncthreads()" if shared else "pass",
                any_lane="cuda.syncthreads_or(bad)" if shared else "bad")


@cache
def sites_kernel(name: str, where: str, sources: str, pieces: tuple[str, ...], method: Method, n: int,
                 periodic: bool, precision: str, threads: int) -> GpuKernel:
    layout = sites_layout(n, threads)
    if method.adaptive:
        family, template, fields, rows = "adaptive", SITES_ADAPTIVE, sites_adaptive(method, layout), 4 * n + 7
    elif method.tableau is not None:
        family, template, fields, rows = "runge_kutta", SITES_FIXED, sites_runge_kutta(method, n, layout), 2 * n
    else:
        family, template, fields, rows = "splitting", SITES_FIXED, sites_splitting(method, pieces), 2 * n
    numbers = dict(N=n, N2=n + 2, periodic=periodic, OK=OK, BLEW_UP=BLEW_UP, UNDERFLOW=UNDERFLOW,
                   **layout)
    body = SITES_HEADER.format(**numbers) + template.format(**numbers, **fields)
    physics_import = f"acceleration, = device_functions({where!r}, ('acceleration',), {sources!r})"
    return GpuKernel(compiled(f"sites {family}", name, method, precision, physics_import, sources,
                              2 * n, 2 * n, body, threads), rows, threads)
