"""numba options shared by the compiled kernels (bldc, spmsm and their controllers), and the
cache hygiene their modules need.

JIT: every kernel. FMA contraction and reciprocal multiplies (LLVM may fuse a * b + c into one
FMA, one rounding instead of two, and turn x / y into x * (1 / y)): round-off level, and the
same compiled code serves the plant and the controller's predictor, so batched == per-period
stays exact; NaN / Inf semantics stay IEEE (no 'fast' flag).
JIT_HOT: per-period kernels that allocate nothing: no reference counting of their array
arguments (numba's NRT would incref / decref each one with an atomic instruction per call).
JIT_INLINE: ... and inlined into the fused loops (numba passes each array as 7 scalars; the
per-period chain plant -> controller -> plant is otherwise call bound).
JIT_COLD: ... and never inlined (with out_of_line() in its body): the rare paths of those loops.
unlikely(cond): cond, marked rarely true for LLVM (branch weights only, no change of value).
rmul(x, y): x * y rounded on its own (LLVM fuses it into no add): numba's complex * float.
"""
from __future__ import annotations

from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

KERNEL_FASTMATH = {"contract", "arcp"}
JIT = dict(cache=True, error_model="numpy", fastmath=KERNEL_FASTMATH)
JIT_HOT = dict(JIT, _nrt=False)
JIT_INLINE = dict(JIT_HOT, forceinline=True)
# a rare path kept out of the hot loop: forceinline=False, set explicitly, as numba otherwise
# inherits forceinline from the caller (everything a JIT_INLINE kernel calls was inlined);
# the function's body also calls out_of_line(), so that LLVM does not inline it either
JIT_COLD = dict(JIT_HOT, forceinline=False)


@intrinsic
def unlikely(typingctx, cond):
    """cond (a bool) with llvm.expect(cond, false). A branch so marked stays a branch (LLVM
    does not fold a predictable branch into a select): a clamp that almost never applies
    then costs the value it guards no latency, where a select (min / max) adds its own."""
    if not isinstance(cond, types.Boolean):
        return None

    def codegen(context, builder, signature, args):
        i1 = ir.IntType(1)
        fn = builder.module.declare_intrinsic("llvm.expect", [i1], ir.FunctionType(i1, [i1, i1]))
        return builder.call(fn, [args[0], ir.Constant(i1, 0)])
    return types.boolean(cond), codegen


@intrinsic
def rmul(typingctx, x, y):
    """x * y of two float64, rounded before any add it feeds: the fmul carries only the arcp flag, so
    the fast-math pass (which flags only instructions without flags) leaves it without 'contract'
    and LLVM fuses it into no FMA. numba's complex * float multiplies by complex(y, 0): four
    products, two of them by zero, each part rounded as a product before the sum it enters;
    complex(rmul(z.real, y), rmul(z.imag, y)) gives the same bits (but for the sign of an exact
    zero) with two."""
    if not (x == types.float64 and y == types.float64):
        return None

    def codegen(context, builder, signature, args):
        return builder.fmul(args[0], args[1], flags=("arcp",))
    return types.float64(x, y), codegen


@intrinsic
def out_of_line(typingctx):
    """Marks the compiled function it is called in noinline for LLVM (no code emitted). numba
    links a callee's LLVM IR into its caller and LLVM inlines it at will: a rare path inlined
    into a hot loop adds its live values and code to the loop's register allocation."""
    def codegen(context, builder, signature, args):
        builder.function.attributes.add("noinline")
        return context.get_dummy_value()
    return types.none(), codegen


def numba_cache_dirs(module_file: str) -> list:
    """The directories where numba keeps the cache files of `module_file`'s functions: the
    __pycache__ beside it and, when NUMBA_CACHE_DIR is set (numba then writes there only),
    its sub-directory for the module's folder, found with numba's own locator."""
    import pathlib
    dirs = [pathlib.Path(module_file).resolve().parent / "__pycache__"]
    from numba.core import config
    if config.CACHE_DIR:
        from numba.core.caching import UserProvidedCacheLocator
        dirs.append(pathlib.Path(config.CACHE_DIR) / UserProvidedCacheLocator.get_suitable_cache_subpath(module_file))
    return dirs


def invalidate_stale_numba_cache(module_file: str, dependencies) -> int:
    """Delete this module's numba cache files if a module it calls into is newer.

    numba's cache=True keys a compiled function on its own source file only; functions
    here inline code and constants from other modules (params layout, plant kernels), so
    an edit there would otherwise leave a stale, silently wrong cache. Both places numba
    may keep them are checked (numba_cache_dirs: with NUMBA_CACHE_DIR set, the beside-the-
    source check alone missed them and a kernel ran on with the old inlined code). Returns
    the number of files removed."""
    import pathlib
    src = pathlib.Path(module_file).resolve()
    try:
        newest = max(pathlib.Path(d).resolve().stat().st_mtime for d in dependencies)
    except OSError:
        return 0
    removed = 0
    for cache_dir in numba_cache_dirs(module_file):
        if not cache_dir.is_dir():
            continue
        for f in list(cache_dir.glob(src.stem + ".*.nbi")) + list(cache_dir.glob(src.stem + ".*.nbc")):
            try:
                if f.stat().st_mtime < newest:
                    f.unlink()
                    removed += 1
            except OSError:
                pass
    return removed
