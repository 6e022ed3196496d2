"""Hand-built calls the compiled block pass needs that Numba has no word for
(LLVM intrinsics): FFTW's new-array execute functions called through their
addresses, and sequentially consistent atomic operations on int64 arrays
(the batch counter and the gate of :mod:`afmdrift.registration._passes`).

The FFTW addresses are run-time values (arguments), so the kernels calling
them stay cacheable.
"""

from __future__ import annotations

from typing import Any

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from afmdrift.registration._jit import jit

__all__ = ["atomic_load", "atomic_store", "fetch_add", "fftw_execute", "publish"]


def _fftw_execute_typing(typingctx, fn, plan, src, dst):  # type: ignore[no-untyped-def]
    """Call the C function at address ``fn`` with the pointers ``(plan, src,
    dst)`` (all integers): one of FFTW's new-array execute functions. The
    address is a run-time value, so functions calling this stay cacheable."""
    if not all(isinstance(t, types.Integer) for t in (fn, plan, src, dst)):
        return None
    sig = types.void(fn, plan, src, dst)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        ptr = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.VoidType(), [ptr, ptr, ptr])
        target = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(target, [builder.inttoptr(a, ptr) for a in args[1:]])
        return context.get_dummy_value()

    return sig, codegen


fftw_execute: Any = intrinsic(_fftw_execute_typing)


def _is_int64_slot(counter: Any, index: Any) -> bool:
    """Whether ``(counter, index)`` types an element of an int64 array."""
    return (
        isinstance(counter, types.Array)
        and counter.dtype == types.int64
        and isinstance(index, types.Integer)
    )


def _slot_pointer(context: Any, builder: Any, signature: Any, args: Any) -> Any:
    """LLVM pointer to ``counter[index]`` (the intrinsics' first two arguments)."""
    aryty = signature.args[0]
    ary = context.make_array(aryty)(context, builder, args[0])
    return cgutils.get_item_pointer(context, builder, aryty, ary, [args[1]])  # type: ignore[no-untyped-call]


def _fetch_add_typing(typingctx, counter, index):  # type: ignore[no-untyped-def]
    """Atomically add 1 to ``counter[index]`` (int64 array); returns the old
    value."""
    if not _is_int64_slot(counter, index):
        return None

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        one = context.get_constant(types.int64, 1)
        return builder.atomic_rmw(
            "add", _slot_pointer(context, builder, signature, args), one, "seq_cst"
        )

    return types.int64(counter, index), codegen


fetch_add: Any = intrinsic(_fetch_add_typing)


def _atomic_load_typing(typingctx, counter, index):  # type: ignore[no-untyped-def]
    """``counter[index]`` of an int64 array, read atomically (every read is
    a new load: a loop waiting on it sees another thread's store)."""
    if not _is_int64_slot(counter, index):
        return None

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        return builder.load_atomic(_slot_pointer(context, builder, signature, args), "seq_cst", 8)

    return types.int64(counter, index), codegen


atomic_load: Any = intrinsic(_atomic_load_typing)


def _atomic_store_typing(typingctx, counter, index, value):  # type: ignore[no-untyped-def]
    """``counter[index] = value`` on an int64 array, atomically and after
    every earlier write of this thread (sequentially consistent): a thread
    that reads the new value with :func:`atomic_load` also sees those."""
    if not (_is_int64_slot(counter, index) and isinstance(value, types.Integer)):
        return None

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        val = context.cast(builder, args[2], signature.args[2], types.int64)
        builder.store_atomic(val, _slot_pointer(context, builder, signature, args), "seq_cst", 8)
        return context.get_dummy_value()

    return types.void(counter, index, value), codegen


atomic_store: Any = intrinsic(_atomic_store_typing)


@jit
def publish(flags, index, value):  # type: ignore[no-untyped-def]
    """``flags[index] = value`` (int64 array) as :func:`atomic_store`: for
    the calling thread to open a pass's gate or end its batches once all it
    wrote before is visible to the workers."""
    atomic_store(flags, index, value)
