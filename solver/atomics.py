"""Atomic operations on the elements of int64 arrays, for compiled code that two threads
run at once (``solver.ik.shared``): numba offers no atomics of its own on the CPU, and a
plain load in a loop may be hoisted out of it. Each compiles to one LLVM atomic
instruction; ``cpu_pause`` is the x86 spin-wait hint."""

from __future__ import annotations

import platform
from typing import Any

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

X86 = platform.machine().lower() in ("x86_64", "amd64", "i386", "i686")


def _element(context: Any, builder: Any, array_type: Any, array: Any, index: Any) -> Any:
    ary = context.make_array(array_type)(context, builder, array)
    return cgutils.get_item_pointer(context, builder, array_type, ary, [index],
                                    wraparound=False)


def _atomic_load(typingctx: Any, array: Any, index: Any) -> Any:
    """array[index], read with acquire ordering."""
    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        return builder.load_atomic(_element(context, builder, sig.args[0], *args),
                                   "acquire", 8)
    return types.int64(array, index), codegen


def _atomic_store(typingctx: Any, array: Any, index: Any, value: Any) -> Any:
    """array[index] = value, with release ordering: writes before it are seen first."""
    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        ptr = _element(context, builder, sig.args[0], args[0], args[1])
        builder.store_atomic(args[2], ptr, "release", 8)
        return context.get_dummy_value()
    return types.void(array, index, value), codegen


def _atomic_cas(typingctx: Any, array: Any, index: Any, expected: Any, new: Any) -> Any:
    """array[index] = new if it holds expected; True if it did."""
    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        ptr = _element(context, builder, sig.args[0], args[0], args[1])
        pair = builder.cmpxchg(ptr, args[2], args[3], "seq_cst", "seq_cst")
        return builder.extract_value(pair, 1)
    return types.boolean(array, index, expected, new), codegen


def _cpu_pause(typingctx: Any) -> Any:
    """The spin-wait hint (x86 ``pause``): a spinning thread yields the core's pipeline.
    Nothing elsewhere (LLVM has no such intrinsic on other machines)."""
    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        if not X86:
            return context.get_dummy_value()
        fn = cgutils.get_or_insert_function(builder.module,
                                            ir.FunctionType(ir.VoidType(), []),
                                            "llvm.x86.sse2.pause")
        builder.call(fn, [])
        return context.get_dummy_value()
    return types.void(), codegen


# typed Any for mypy: an intrinsic's call signature is not its typing function's
atomic_load: Any = intrinsic(_atomic_load)
atomic_store: Any = intrinsic(_atomic_store)
atomic_cas: Any = intrinsic(_atomic_cas)
cpu_pause: Any = intrinsic(_cpu_pause)
