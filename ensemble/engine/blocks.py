"""Generic compiled helpers of the ensemble kernels: no scene lives here.

Members run in blocks of B; threads take groups of blocks (engine.launch.run_blocks)
and the innermost loop goes over the members of a block, which LLVM vectorizes. A kernel keeps everything
a step touches in one work array per block, row r of member j at r * B + j:
with a single base pointer LLVM proves the rows disjoint and emits only the
vector loop (separate arrays add a runtime overlap check whose scalar fallback
rounds differently, so results would depend on heap addresses).

Kernel inputs are laid out by block: state0 and rate (blocks, rows, B), so a
block reads contiguous memory (as (rows, members) arrays, each row of a block
was a separate cache line far from the next: loading and saving a block of
16-mass chains cost about as much as 200 of its steps, measured). Samples are
(members, count, state rows), member by member (sample_out), the saved
variables' layout. Per-member arrays (limit, status, failure_time, control,
counts) are (..., members).

The kernels are built from the engine's family code (ensemble.engine.frames and the families it calls, for a
member of D values; ensemble.engine.sites_kernels for a field of sites), and inline the helpers here. Numba keys
a cached kernel on its own file alone, so a generated kernel's file holds HELPERS, a hash of the helpers'
source.
How the runner calls a kernel is in `ensemble.engine.launch`.
"""
from __future__ import annotations

import hashlib
import math
import platform
from pathlib import Path
from typing import NamedTuple

import numpy as np
from llvmlite import ir as llvmlite_ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from ..methods import Method
from ..results import RHS_EVALS, UNDERFLOWED, Status
from .sources import ENGINE_SOURCES

#: A hash of sources.ENGINE_SOURCES (the helpers, the families' code, the status codes), held by every kernel's
#: file: Numba's disk cache keys a kernel on its own file, and would otherwise load a kernel compiled before a
#: helper changed.
HELPERS = hashlib.sha256(b"".join((Path(__file__).parent / name).read_bytes() for name in ENGINE_SOURCES)).hexdigest()

#: The kernels' compile flags. Of fast-math only contraction into fused multiply-adds, which every target with FMA
#: does alike: `nnan`/`ninf` let LLVM assume no value is NaN or inf (a right-hand side returning a constant NaN was
#: folded away, its member frozen with status ok), and `reassoc`, `arcp` and `afn` let it regroup arithmetic
#: differently in vector and scalar code, so the bits depended on the block, the vector width and the CPU.
FAST = dict(fastmath={"contract"}, error_model="numpy", boundscheck=False)
# Code that tests for NaN and infinity tests the exponent bits, and is compiled on its own (not inlined at Numba
# level): a kernel compiled by another version with full fast-math could fold a floating-point test away.
CAREFUL = dict(error_model="numpy", boundscheck=False)
_EXPONENT = 0x7FF0000000000000  # all ones in a float64's exponent: inf or NaN
_MAGNITUDE = 0x7FFFFFFFFFFFFFFF  # a float64's bits but its sign
_SMALLEST_NORMAL = 0x0010000000000000  # bits of 2.2250738585072014e-308: magnitudes below it are subnormal
_SIGN = -0x8000000000000000  # a float64's sign bit, as an int64
OK, BLEW_UP, UNDERFLOW = int(Status.OK), int(Status.BLEW_UP), int(Status.STEP_SIZE_UNDERFLOW)


class Kernel(NamedTuple):
    """A scene's compiled kernel for one method and the rows of its work array (rows x B floats per block)."""
    function: object
    rows: int


@intrinsic
def _int_bits(typingctx, x):
    """The bits of a float64 as an int64 (a register reinterpretation, which vectorizes)."""
    def codegen(context, builder, signature, arguments):
        return builder.bitcast(arguments[0], context.get_value_type(types.int64))
    return types.int64(types.float64), codegen


@intrinsic
def _float_bits(typingctx, bits):
    """The float64 whose bits are an int64."""
    def codegen(context, builder, signature, arguments):
        return builder.bitcast(arguments[0], context.get_value_type(types.float64))
    return types.float64(types.int64), codegen


@intrinsic
def select(typingctx, condition, if_true, if_false):
    """if_true if condition else if_false, as one LLVM select of two float64s. Python's conditional expression
    compiles to branches, which LLVM may turn into masked loads and stores (vmaskmovpd, slow on AMD Zen 3) when
    it vectorizes; a select becomes a blend, and the stores after it stay whole."""
    def codegen(context, builder, signature, arguments):
        return builder.select(*arguments)
    return types.float64(types.boolean, types.float64, types.float64), codegen


@intrinsic
def _fused_multiply_add(typingctx, a, b, c):
    """a b + c rounded once (LLVM's fma, a vector instruction on hosts with FMA)."""
    def codegen(context, builder, signature, arguments):
        double = context.get_value_type(types.float64)
        fma = cgutils.get_or_insert_function(builder.module, llvmlite_ir.FunctionType(double, [double] * 3),
                                             "llvm.fma.f64")
        return builder.call(fma, arguments)
    return types.float64(types.float64, types.float64, types.float64), codegen


_FLUSH_TO_ZERO = 0x8040  # x86's MXCSR bits FTZ (15) and DAZ (6): subnormal results and operands become zeros


def _mxcsr_intrinsic(name: str):
    """LLVM's llvm.x86.sse.<name> (stmxcsr or ldmxcsr) on an int32 on the stack."""
    def call(builder, slot):
        byte_pointer = llvmlite_ir.IntType(8).as_pointer()
        function = cgutils.get_or_insert_function(
            builder.module, llvmlite_ir.FunctionType(llvmlite_ir.VoidType(), [byte_pointer]), f"llvm.x86.sse.{name}")
        builder.call(function, [builder.bitcast(slot, byte_pointer)])
    return call


@intrinsic
def _swap_float_mode(typingctx, mode):
    """Set this thread's MXCSR (x86's floating-point control) to `mode`, an int32; returns what it was."""
    def codegen(context, builder, signature, arguments):
        slot = cgutils.alloca_once(builder, llvmlite_ir.IntType(32))
        _mxcsr_intrinsic("stmxcsr")(builder, slot)
        previous = builder.load(slot)
        builder.store(arguments[0], slot)
        _mxcsr_intrinsic("ldmxcsr")(builder, slot)
        return previous
    return types.int32(types.int32), codegen


@njit(nogil=True, cache=True)
def _read_float_mode():
    previous = _swap_float_mode(np.int32(0x1F80))  # x86's default: every exception masked, round to nearest
    _swap_float_mode(previous)
    return previous


@njit(nogil=True, cache=True)
def _set_float_mode(mode):
    return _swap_float_mode(np.int32(mode))


X86 = platform.machine().lower() in ("x86_64", "amd64", "i686", "x86")


def flush_subnormals() -> int | None:
    """Make this thread's arithmetic flush subnormals to zero (results and operands alike), and return the mode
    it had for restore_float_mode; None (nothing changed) off x86. The kernels' threads run so (launch.run_blocks):
    a value below 2.2e-308 that the kernels would carry as a subnormal costs each operation on it about a hundred
    cycles (a damped body decaying between its saves ran 5.5 times slower). Where no subnormal occurs, the bits
    are the same."""
    if not X86:
        return None
    previous = int(_read_float_mode())
    _set_float_mode(previous | _FLUSH_TO_ZERO)
    return previous


def restore_float_mode(previous: int | None) -> None:
    """Give this thread back the mode flush_subnormals found."""
    if previous is not None:
        _set_float_mode(previous)


CACHE_LINE = 64  # bytes


@njit(inline="always")
def cache_line_array(size):
    """An uninitialized float64 array of `size` values that starts on a 64-byte cache line, so no SIMD vector of up
    to 64 bytes straddles two lines: a kernel call's work array, into which it copies its blocks one at a time
    (LLVM then knows it aliases nothing). Numba aligns new arrays to 32 bytes only, and the 64-byte vectors of
    AVX-512 crossed lines in some arrays and not in others: the same 1024-mass chain ran at 5.7e9, 7.5e9 or
    1.05e10 mass-steps/s from one set of arrays to the next."""
    doubles = CACHE_LINE // 8
    buffer = np.empty(size + doubles - 1)
    first = (-buffer.ctypes.data % CACHE_LINE) // 8
    return buffer[first:first + size]


@njit(inline="always", **FAST)
def copy_into(target, source):
    """target[r] = source[r] for every r of two 1-d arrays of one length: a block's work array in and out. Numba's
    slice assignment (`target[:] = source`) compiles the formatting of its shape-mismatch error into every process
    that compiles a kernel: about 3 s of a kernel's first compile."""
    for r in range(target.shape[0]):
        target[r] = source[r]


@njit(inline="always", **FAST)
def finite(x):
    """Whether the float64 x is finite, tested on its bits: fastmath assumes no float is NaN or inf, not an int."""
    return (_int_bits(x) & _EXPONENT) != _EXPONENT


@njit(**CAREFUL)
def check_members(work, first, count, B, j0, limit, status, failure_time, t, step_row=-1):
    """Fail, at time t (s), each running member of a block whose state rows [first, first + count) hold a value
    that is not finite or exceeds its limit: status BLEW_UP, state NaN, and (adaptive kernels) step 0 in row
    step_row, so it takes no more steps. Returns how many members still run.

    A subnormal state value (|x| < 2.2e-308) of a running member becomes a zero of its sign: a state decaying
    into subnormals would lose its digits (a damped top's tilt, read from its rates, jumped from 1e-18 to 0.6
    rad) and step 100 times slower. From a zero it steps on exactly (a top's transverse rates stay 0: tilt 0)."""
    bits = work.view(np.int64)
    limit_bits = limit.view(np.int64)
    running = 0
    for j in range(B):
        if status[j0 + j] != OK:
            continue
        largest = 0  # bits of the largest |value|: for floats >= 0 bits order as values do, inf and NaN on top
        for r in range(first, first + count):
            magnitude = bits[r * B + j] & _MAGNITUDE
            largest = max(largest, magnitude)
            if magnitude < _SMALLEST_NORMAL:
                bits[r * B + j] &= _SIGN
        if largest < _EXPONENT and largest <= limit_bits[j0 + j]:
            running += 1
        else:
            status[j0 + j] = BLEW_UP
            failure_time[j0 + j] = t
            for r in range(first, first + count):
                work[r * B + j] = np.nan
            if step_row >= 0:
                work[step_row * B + j] = 0.0
    return running


@njit(inline="always", **FAST)
def fill_failed(samples, first_save, block, B):
    """NaN for the samples from first_save on of a block whose members have all failed."""
    samples[block * B:(block + 1) * B, first_save:] = np.nan


@njit(inline="always", **FAST)
def block_done(samples, status, progress, block, B):
    """Whether every member of a block failed in an earlier call: then its samples of this call are NaN."""
    for j in range(B):
        if status[block * B + j] == OK:
            return False
    fill_failed(samples, 0, block, B)
    progress[block] = samples.shape[1] - 1
    return True


@njit(inline="always", **FAST)
def rows_in(work, row, source, first, count, B):
    """Rows first .. first + count - 1 of a block's (rows, B) array into the work array from `row` on."""
    for i in range(min(count, source.shape[0] - first)):  # bounds LLVM cannot unroll (see sample_out)
        for j in range(min(B, source.shape[1])):
            work[(row + i) * B + j] = source[first + i, j]


@njit(inline="always", **FAST)
def sample_out(work, row, samples, save, block, first, count, B):
    """Work rows row .. row + count - 1 into sample `save` of a kernel's member-major samples (members, count,
    state rows), as its state rows first .. first + count - 1, for the block's members that exist (a run's last
    block is padded). Each member's rows are contiguous: the samples need no transposing after the kernel.

    The loops' bounds depend on the samples' shape, which LLVM does not know: with constant bounds it unrolled
    a chain's copy (a 64-member block's 2n rows) into one block of thousands of loads and stores, whose
    instruction scheduling took most of the kernel's compile time (10 of 17 s at n = 16)."""
    j0 = block * B
    for j in range(min(B, samples.shape[0] - j0)):
        for i in range(min(count, samples.shape[2] - first)):
            samples[j0 + j, save, first + i] = work[(row + i) * B + j]


def adaptive_constants(method: Method):
    """An adaptive method's tableau and controller as plain constants for a kernel closure."""
    t, control = method.tableau, method.control
    assert t.fsal and t.error is not None, "adaptive kernels need an FSAL embedded pair"
    return (t.stages, t.square_a(), tuple(float(x) for x in t.error), control.alpha, control.beta, control.safety,
            control.min_factor, control.max_factor)


# Rows of an adaptive kernel's per-member control block (after the scene's rows); from COUNTED on, the member's
# counts so far in results.COUNTS order (accepted, rejected steps, right-hand-side evaluations).
H, TIME, STEP, ERR, LOG2_ERR_PREVIOUS, REJECTED_LAST, RTOL, ATOL, COUNTED = range(9)
CONTROL_ROWS = COUNTED + 3
FIRST_LOG2_ERR_PREVIOUS = math.log2(1e-4)  # the controller's memory before a member's first accepted step


_ROUNDER = 6755399441055744.0  # 1.5 * 2**52: adding it leaves an integer-valued float's value in the low bits
_LN2 = math.log(2.0)
_TWO_OVER_LN2 = 2.0 / math.log(2.0)


@njit(inline="always", **FAST)  # inlined into the step control: compiled with its flags
def log2_positive(x):
    """log2(x) (absolute error below 1e-10) of a finite x >= 2**-1022, in operations that vectorize: libm's log
    is a scalar call, which kept the step control's loop scalar."""
    bits = _int_bits(x)
    # The exponent as a float, made by writing it into the low bits of 2**52 (int64 to float64 has no AVX2
    # instruction).
    exponent = _float_bits(((bits >> 52) & 0x7FF) | 0x4330000000000000) - (4503599627370496.0 + 1023.0)
    mantissa = _float_bits((bits & 0x000FFFFFFFFFFFFF) | 0x3FF0000000000000)  # in [1, 2)
    high = mantissa > 1.4142135623730951
    mantissa = select(high, 0.5 * mantissa, mantissa)  # now in [sqrt(1/2), sqrt(2)]
    exponent = select(high, exponent + 1.0, exponent)
    t = (mantissa - 1.0) / (mantissa + 1.0)  # ln(mantissa) = 2 atanh(t), |t| <= 0.172
    t2 = t * t
    t4 = t2 * t2
    series = (1.0 + t2 * (1 / 3)) + t4 * ((1 / 5 + t2 * (1 / 7)) + t4 * (1 / 9 + t2 * (1 / 11)))  # see exp2_of
    return exponent + _TWO_OVER_LN2 * t * series


@njit(inline="always", **FAST)  # as log2_positive
def exp2_of(y):
    """2**y (relative error below 1e-13) for -1022 <= y <= 1023, and y clipped to that range beyond it, in
    operations that vectorize (see log2_positive)."""
    y = min(max(y, -1022.0), 1023.0)
    whole = np.floor(y + 0.5)  # a float: math.floor's int would be converted back, a scalar at a time
    f = (y - whole) * _LN2  # |f| <= ln(2) / 2
    f2 = f * f  # exp(f) to f**11 / 11!, by Estrin's scheme: four short chains instead of one long one
    f4 = f2 * f2
    power = (((1.0 + f) + f2 * (1 / 2 + f * (1 / 6)))
             + f4 * ((1 / 24 + f * (1 / 120)) + f2 * (1 / 720 + f * (1 / 5040)))
             + (f4 * f4) * ((1 / 40320 + f * (1 / 362880)) + f2 * (1 / 3628800 + f * (1 / 39916800))))
    return power * _float_bits((_int_bits(whole + _ROUNDER) - _int_bits(_ROUNDER) + 1023) << 52)


# Cephes' sin and cos (sin.c): their minimax polynomials on [-pi/4, pi/4]; pi/2 as a sum of two doubles for the
# reduction
_PIO2 = (1.5707963267948966, 6.123233995736766e-17)
_SIN = (1.58962301576546568060e-10, -2.50507477628578072866e-8, 2.75573136213857245213e-6,
        -1.98412698295895385996e-4, 8.33333333332211858878e-3, -1.66666666666666307295e-1)
_COS = (-1.13585365213876817300e-11, 2.08757008419747316778e-9, -2.75573141792967388112e-7,
        2.48015872888517045348e-5, -1.38888888888730564116e-3, 4.16666666666665929218e-2)
SIN_COS_LIMIT = 2.0**46  # rad (7e13): the fused reduction keeps 2.2e-16 up to 1e14 (1e-14 at 1e15, nothing at 1e16)


@njit(inline="always", **FAST)
def sin_cos(x):
    """(sin x, cos x) of x (rad), each within 2.3e-16 of NumPy's (tests/test_top.py), in operations that vectorize:
    libm's sin and cos are scalar calls, which kept a top's splittings at a tenth of its rk4's speed. NaN for
    |x| > SIN_COS_LIMIT. The fused multiply-adds are single instructions on hosts with FMA3; elsewhere LLVM calls
    libm's fma, slower but as exact."""
    quadrants = np.floor(x * (2.0 / math.pi) + 0.5)  # the nearest multiple of pi/2, counted
    # Cody and Waite's reduction in fused operations: the first is exact, and LLVM does not reassociate them (as
    # fast-math lets it do with the differences of Cephes' three-part form, losing its digits)
    z = _fused_multiply_add(-quadrants, _PIO2[1], _fused_multiply_add(-quadrants, _PIO2[0], x))  # |z| <= pi/4
    zz = z * z
    sin = z + z * zz * (((((_SIN[0] * zz + _SIN[1]) * zz + _SIN[2]) * zz + _SIN[3]) * zz + _SIN[4]) * zz + _SIN[5])
    cos = (1.0 - 0.5 * zz) + zz * zz * (((((_COS[0] * zz + _COS[1]) * zz + _COS[2]) * zz + _COS[3]) * zz + _COS[4])
                                        * zz + _COS[5])
    q = _int_bits(quadrants + _ROUNDER) - _int_bits(_ROUNDER)  # the count as an integer (two's complement)
    swap = (q & 1) != 0
    sin_x = select(swap, cos, sin)
    cos_x = select(swap, sin, cos)
    sin_x = select((q & 2) != 0, -sin_x, sin_x)
    cos_x = select(((q + 1) & 2) != 0, -cos_x, cos_x)
    inside = abs(x) <= SIN_COS_LIMIT
    return select(inside, sin_x, np.nan), select(inside, cos_x, np.nan)


@njit(inline="always", **FAST)
def start_control(work, c0, B, j, rtol, atol, h):
    """A member's control rows at its start: tolerances, first trial step h (s), no error remembered, one
    right-hand-side evaluation counted (its first slopes)."""
    work[(c0 + RTOL) * B + j], work[(c0 + ATOL) * B + j] = rtol, atol
    work[(c0 + LOG2_ERR_PREVIOUS) * B + j] = FIRST_LOG2_ERR_PREVIOUS
    work[(c0 + H) * B + j] = h
    work[(c0 + COUNTED + RHS_EVALS) * B + j] = 1.0


@njit(inline="always", **FAST)
def counts_out(work, c0, B, counts, j0):
    """A block's counts so far (COUNTED rows) into counts (3, M), at the end of a kernel call."""
    for c in range(3):
        for j in range(B):
            counts[c, j0 + j] = work[(c0 + COUNTED + c) * B + j]


@njit(inline="always", **FAST)
def first_step(size, slope, save_dt):
    """Hairer's first guess from |y| and |y'| in units of the tolerance: 1% of their ratio, at most save_dt."""
    return min(0.01 * size / slope if size > 1e-5 and slope > 1e-5 else 1e-6, save_dt)


@njit(inline="always", **FAST)
def trial_steps(work, c0, B, target):
    """Each member's next trial step (STEP), clipped to land on `target`; 0 for members there. Returns how many move."""
    left = 0
    for j in range(B):
        remaining = target - work[(c0 + TIME) * B + j]
        step = select(remaining > 0.0, min(work[(c0 + H) * B + j], remaining), 0.0)
        work[(c0 + STEP) * B + j] = step
        work[(c0 + ERR) * B + j] = 0.0
        left += step > 0.0
    return left


# A member's state: D rows from row 0, then its P parameter rows (ensemble.engine.frames);
# adaptive kernels keep stage slopes at rows K + D s + c and the trial step's new state at rows NEW + c.

@njit(inline="always", **FAST)
def state_load(work, state0, rate, block, samples, D, P, B):
    """Start a block's (zeroed) work array: D state rows, then P parameter rows; also its first sample."""
    rows_in(work, 0, state0[block], 0, D, B)
    rows_in(work, D, rate[block], 0, P, B)
    sample_out(work, 0, samples, 0, block, 0, D, B)


@njit(inline="always", **FAST)
def block_stopped(samples, progress, running, save, block, B):
    """After a block stored sample `save` with `running` members still running: whether none runs any more, its
    later samples then filled with NaN. progress[block] becomes the last sample the block has stored."""
    if running == 0:
        fill_failed(samples, save + 1, block, B)
    progress[block] = samples.shape[1] - 1 if running == 0 else save
    return running == 0


@njit(inline="always", **FAST)
def state_saved(work, samples, save, block, limit, status, failure_time, progress, t, step_row, D, B):
    """End of a save interval at time t (s): fail the members that blew up, store sample `save`; when no member
    of the block runs any more, fill its later samples with NaN and return True (the block is done). progress[block]
    becomes the last sample the block has stored."""
    running = check_members(work, 0, D, B, block * B, limit, status, failure_time, t, step_row)
    sample_out(work, 0, samples, save, block, 0, D, B)
    return block_stopped(samples, progress, running, save, block, B)


@njit(inline="always", **FAST)
def state_start(work, control, K, C0, B, j, j0, D, save_dt):
    """Start member j of a block of an adaptive kernel, its first slopes already in rows K .. K + D - 1: its
    tolerances and first trial step from `control` (Hairer's guess where none is given), one rhs evaluation
    counted."""
    rtol, atol = control[1, j0 + j], control[2, j0 + j]
    h = control[0, j0 + j]
    if h <= 0.0:
        size = abs(work[j])
        slope = abs(work[K * B + j])
        for c in range(1, D):
            size = max(size, abs(work[c * B + j]))
            slope = max(slope, abs(work[(K + c) * B + j]))
        scale = atol + rtol * size
        h = first_step(size / scale, slope / scale, save_dt)
    start_control(work, C0, B, j, rtol, atol, h)


@njit(inline="always", **FAST)
def state_accept(work, K, NEW, C0, S, D, B):
    """After control_step: members whose step was accepted move to the new state (its last stage is the next
    step's first); members whose step underflowed become NaN."""
    for j in range(B):  # selects, not branches: see control_step
        err = work[(C0 + ERR) * B + j]
        accepted = (work[(C0 + REJECTED_LAST) * B + j] == 0.0) & (err >= 0.0)
        underflowed = err == UNDERFLOWED
        for c in range(D):
            state, new = work[c * B + j], work[(NEW + c) * B + j]
            slope, last = work[(K + c) * B + j], work[(K + D * (S - 1) + c) * B + j]
            work[c * B + j] = select(accepted, new, select(underflowed, np.nan, state))
            work[(K + c) * B + j] = select(accepted, last, slope)
