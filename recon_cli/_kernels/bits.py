"""Bit-level numba intrinsics: the high half of a 64x64-bit product, leading zeros, and a
float64 from its bit pattern (each one machine instruction where the CPU has it)."""

from __future__ import annotations

from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, threading layer)


@intrinsic
def mulhi64(typingctx, a, b):
    """The high 64 bits of the 128-bit product of the uint64 ``a`` and ``b``."""
    if not (isinstance(a, types.Integer) and isinstance(b, types.Integer) and a.bitwidth == 64 and b.bitwidth == 64):
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
def f64_from_bits(typingctx, bits):
    """The float64 whose bit pattern is the 64-bit integer ``bits``."""
    if not (isinstance(bits, types.Integer) and bits.bitwidth == 64):
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return types.float64(bits), codegen

