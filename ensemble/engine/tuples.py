"""One member's values as tuples: the arithmetic the method families (ensemble.engine.runge_kutta, .adaptive) do
on a member's state, written once for both devices.

A member's D state values and P parameters are tuples of floats (Numba's UniTuple), so that a scene's scalar
functions take them as `rhs(t, *y, *p)`. Loading, storing and adding tuples are intrinsics that write each value
out (a loop of tuple_setitem goes through memory until LLVM unrolls it, which it did not for a free body's 12
parameters: its kernel ran 17 times slower, scalar), and the families' loops over a method's stages are written
out by `unrolled`. ensemble.engine.gpu_device compiles these functions as CUDA device functions, with numba-cuda's
tuple_setitem and its own registration of the intrinsics here (gpu_device.device_intrinsics).
"""
from __future__ import annotations

from functools import cache

from numba import njit, types
from numba.extending import intrinsic

from .blocks import FAST


def repeated_typing(typingctx, value, like):
    """A tuple of len(like) copies of value (like: a tuple)."""
    tuple_type = types.UniTuple(value, like.count)

    def codegen(context, builder, signature, arguments):
        return context.make_tuple(builder, tuple_type, [arguments[0]] * like.count)
    return tuple_type(value, like), codegen


repeated = intrinsic(repeated_typing)


def _flat(values_type) -> list:
    """The value types of a tuple, a tuple of tuples flattened in order (a splitting's factors per sequence entry)."""
    return [v for inner in values_type for v in (_flat(inner) if isinstance(inner, types.BaseTuple) else [inner])]


def _row_pointer(context, builder, signature, arguments):
    """pointer(c): a pointer to member j's work row first + c (c an intp value; row r of member j at r B + j), of
    an intrinsic's arguments (work, first, B, j, values)."""
    work_type, first_type, B_type, j_type, _ = signature.args
    work, first, B, j, _ = arguments
    intp = types.intp
    first, B, j = (context.cast(builder, value, kind, intp) for value, kind in zip((first, B, j),
                                                                                     (first_type, B_type, j_type)))
    data = context.make_array(work_type)(context, builder, value=work).data
    return lambda c: builder.gep(data, [builder.add(builder.mul(builder.add(first, c), B), j)])


def _member_rows(context, builder, signature, arguments):
    """Pointers to member j's work rows first .. first + count - 1 (count: the values of the last argument, a tuple
    or a tuple of tuples)."""
    pointer = _row_pointer(context, builder, signature, arguments)
    return [pointer(context.get_constant(types.intp, c)) for c in range(len(_flat(signature.args[4])))]


def _values(builder, value, value_type) -> list:
    """The values of a tuple or a tuple of tuples, flattened in order."""
    if not isinstance(value_type, types.BaseTuple):
        return [value]
    return [v for c, inner in enumerate(value_type) for v in _values(builder, builder.extract_value(value, c), inner)]


def _nested(context, builder, like_type, dtype, values: list):
    """values (flat, consumed from the front) as a tuple shaped like like_type (a tuple or a tuple of tuples)."""
    if not isinstance(like_type, types.BaseTuple):
        return values.pop(0)
    inner = [_nested(context, builder, kind, dtype, values) for kind in like_type]
    return context.make_tuple(builder, _shaped(like_type, dtype), inner)


def _shaped(like_type, dtype):
    """The type of a tuple of dtype values shaped like like_type."""
    if not isinstance(like_type, types.BaseTuple):
        return dtype
    inner = [_shaped(kind, dtype) for kind in like_type]
    return types.BaseTuple.from_types(inner) if inner else types.Tuple(())


def _contiguous(typingctx, work):
    """Member rows are found by their flat index: the array must be C-contiguous (a work array, or a GPU's
    (rows, members) and (count, rows, members) arrays)."""
    from numba.core.errors import TypingError
    if not isinstance(work, types.Array) or work.layout != "C":
        raise TypingError(f"member rows of a {work}: a C-contiguous array is needed")


def loaded_typing(typingctx, work, first, B, j, like):
    """Member j's work rows first .. first + len(like) - 1 as a tuple (like: a tuple of that length, or a tuple of
    tuples, rows taken in order): straight loads (a loop through the work array, handed down in a tuple, kept
    Numba's reference counts in the members' loop, which then did not vectorize). Row r of member j is at flat
    index r B + j: in a GPU's (rows, members) array, B is its members (and in (count, rows, members), sample i's
    rows start at row i rows)."""
    _contiguous(typingctx, work)
    tuple_type = _shaped(like, work.dtype)

    def codegen(context, builder, signature, arguments):
        pointers = _member_rows(context, builder, signature, arguments)
        return _nested(context, builder, like, work.dtype, [builder.load(pointer) for pointer in pointers])
    return tuple_type(work, first, B, j, like), codegen


loaded = intrinsic(loaded_typing)


def stored_typing(typingctx, work, first, B, j, values):
    """values (a tuple, or a tuple of tuples) into member j's work rows from first on, each converted to the
    array's type (a float32 GPU kernel's state into a float64 event array): straight stores, as `loaded`. values
    may also be a 1-d array (a field of sites' state: too many values for a tuple), stored by a loop."""
    _contiguous(typingctx, work)
    if isinstance(values, types.Array):
        return types.none(work, first, B, j, values), _stored_array

    def codegen(context, builder, signature, arguments):
        flat = _values(builder, arguments[4], values)
        for value, kind, pointer in zip(flat, _flat(values), _member_rows(context, builder, signature, arguments)):
            builder.store(context.cast(builder, value, kind, work.dtype), pointer)
        return context.get_dummy_value()
    return types.none(work, first, B, j, values), codegen


stored = intrinsic(stored_typing)


def _stored_array(context, builder, signature, arguments):
    """`stored` of a 1-d array's values, in a loop of pointers (a reshape of the work array calls a C helper of
    Numba's, which a GPU does not have)."""
    from numba.core import cgutils

    work_type, values_type = signature.args[0], signature.args[4]
    pointer = _row_pointer(context, builder, signature, arguments)
    source = context.make_array(values_type)(context, builder, value=arguments[4])
    shape, strides = cgutils.unpack_tuple(builder, source.shape), cgutils.unpack_tuple(builder, source.strides)
    with cgutils.for_range(builder, shape[0]) as loop:
        value = builder.load(cgutils.get_item_pointer2(context, builder, source.data, shape, strides,
                                                       values_type.layout, [loop.index]))
        builder.store(context.cast(builder, value, values_type.dtype, work_type.dtype), pointer(loop.index))
    return context.get_dummy_value()


def converted_typing(typingctx, values, like):
    """values (a tuple, as a scene's function returns it: its values may be of other types, say a float64 slope
    in a float32 kernel, or an integer) as a tuple of like's value type (like: a tuple of one type)."""
    if len(like) == 0:  # no values (a scene without parameters)
        return types.Tuple(())(values, like), lambda context, builder, signature, arguments: context.make_tuple(
            builder, types.Tuple(()), [])
    tuple_type = types.UniTuple(like.dtype, values.count if isinstance(values, types.BaseTuple) else 1)

    def codegen(context, builder, signature, arguments):
        value = arguments[0]
        if not isinstance(values, types.BaseTuple):
            return context.make_tuple(builder, tuple_type, [context.cast(builder, value, values, like.dtype)])
        return context.make_tuple(builder, tuple_type, [
            context.cast(builder, builder.extract_value(value, c), kind, like.dtype) for c, kind in enumerate(values)])
    return tuple_type(values, like), codegen


converted = intrinsic(converted_typing)


def added_typing(typingctx, z, weight, slope):
    """z + weight slope, value by value (tuples of one length), in z's precision, each value's multiply and add
    contracted as the kernels' own arithmetic is (blocks.FAST): one fused multiply-add."""
    def codegen(context, builder, signature, arguments):
        z_value, weight_value, slope_value = arguments
        weight_value = context.cast(builder, weight_value, signature.args[1], z.dtype)
        values = []
        for c in range(z.count):
            k = context.cast(builder, builder.extract_value(slope_value, c), slope[c], z.dtype)  # a scene's slope
            product = builder.fmul(weight_value, k, flags=("contract",))  # may be wider than a float32 state
            values.append(builder.fadd(builder.extract_value(z_value, c), product, flags=("contract",)))
        return context.make_tuple(builder, z, values)
    return z(z, weight, slope), codegen


added = intrinsic(added_typing)


@njit(inline="always", **FAST)
def combined(y, h, coefficients, slopes, first=0):
    """y + sum_r (h coefficients[first + r]) slopes[r], the nonzero coefficients in order. A zero coefficient's
    term is left out, not added as 0 k: without fast-math's licence to assume no NaN, LLVM must compute 0 k (which
    cost the free body's rk4 a tenth of its speed), and an infinite slope would give NaN."""
    for r in range(first, len(coefficients)):
        if coefficients[r] != 0.0:
            y = added(y, h * coefficients[r], slopes[r - first])
    return y


@cache
def unrolled(count: int, compiled=None):
    """run(body, carry, function, context): carry = body(i, carry, function, context) for i = 0 .. count - 1,
    returned; written out when Numba compiles it, i a constant in each copy of body (a loop over a method's
    stages, whose body calls the scene's `function`, is more than LLVM unrolls for a large state: a 40-value
    Lorenz-96's rk4 ran 3 times slower as a loop). compiled(python function) compiles each link, inlined (default:
    Numba's njit; ensemble.engine.gpu passes numba-cuda's device jit). A kernel's file makes it for its method's
    stage count and hands it down."""
    compiled = compiled or (lambda function: njit(inline="always", **FAST)(function))
    if count == 0:
        def run(body, carry, function, context):
            return carry
        return compiled(run)
    previous, last = unrolled(count - 1, compiled), count - 1

    def run(body, carry, function, context):
        return body(last, previous(body, carry, function, context), function, context)
    return compiled(run)
