"""Bit-level numba intrinsics.

The high half of a 64x64-bit product, leading and trailing zeros, a float64 from its bit pattern,
and eight bytes of a uint8 array as one little-endian uint64 (each one machine instruction where the
CPU has it).
"""

from __future__ import annotations

import sys

from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)


@intrinsic
def mulhi64(typingctx, a, b):
    """The high 64 bits of the 128-bit product of the uint64 ``a`` and ``b``."""
    if not (
        isinstance(a, types.Integer)
        and isinstance(b, types.Integer)
        and a.bitwidth == 64
        and b.bitwidth == 64
    ):
        return None

    def codegen(context, builder, signature, args):
        wide = ir.IntType(128)
        p = builder.mul(builder.zext(args[0], wide), builder.zext(args[1], wide))
        return builder.trunc(builder.lshr(p, ir.Constant(wide, 64)), ir.IntType(64))

    return types.uint64(types.uint64, types.uint64), codegen


@intrinsic
def clz64(typingctx, a):
    """The number of leading zero bits of the uint64 ``a`` (64 for 0)."""
    if not (isinstance(a, types.Integer) and a.bitwidth == 64):
        return None

    def codegen(context, builder, signature, args):
        return builder.ctlz(args[0], ir.Constant(ir.IntType(1), 0))

    return types.uint64(types.uint64), codegen


@intrinsic
def ctz64(typingctx, a):
    """The number of trailing zero bits of the uint64 ``a`` (64 for 0)."""
    if not (isinstance(a, types.Integer) and a.bitwidth == 64):
        return None

    def codegen(context, builder, signature, args):
        return builder.cttz(args[0], ir.Constant(ir.IntType(1), 0))

    return types.uint64(types.uint64), codegen


@intrinsic
def load_u64le(typingctx, arr, i):
    """The bytes ``arr[i:i + 8]`` of a contiguous 1-d uint8 array as one little-endian uint64.

    An unaligned load: SWAR code reads eight characters at once. The caller guarantees ``0 <= i``
    and ``i + 8 <= len(arr)``: nothing is checked.
    """
    if not (
        isinstance(arr, types.Array)
        and arr.ndim == 1
        and arr.layout == "C"
        and arr.dtype == types.uint8
        and isinstance(i, types.Integer)
    ):
        return None

    def codegen(context, builder, signature, args):
        a = context.make_array(signature.args[0])(context, builder, args[0])
        idx = context.cast(builder, args[1], signature.args[1], types.intp)
        p = builder.bitcast(builder.gep(a.data, [idx]), ir.IntType(64).as_pointer())
        v = builder.load(p, align=1)
        if sys.byteorder == "big":
            v = builder.bswap(v)
        return v

    return types.uint64(arr, i), codegen


@intrinsic
def f64_from_bits(typingctx, bits):
    """The float64 whose bit pattern is the 64-bit integer ``bits``."""
    if not (isinstance(bits, types.Integer) and bits.bitwidth == 64):
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(bits), codegen
