"""numba's cache=True keys a compiled function on its own source file; the kernels inline
code from other modules, so bike_plant.jit.invalidate_stale_numba_cache removes a module's
cache files when one of those is newer. It must look where numba really keeps them: beside
the source, or under NUMBA_CACHE_DIR when that is set (numba then uses it alone). Also the
jit module's JIT_COLD: a rare path stays a call under a forceinline caller."""
from __future__ import annotations

import os
import pathlib
import subprocess
import sys
import textwrap

from numba.core import config

from bike_plant.jit import invalidate_stale_numba_cache, numba_cache_dirs


def _make_module(tmp_path):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    kernel = pkg / "kernel.py"
    kernel.write_text("from numba import njit\n\n\n@njit(cache=True)\ndef f(x):\n    return x + 1\n")
    dep = pkg / "dep.py"
    dep.write_text("")
    return kernel, dep


def test_stale_cache_files_are_removed_beside_the_source_and_under_numba_cache_dir(tmp_path, monkeypatch):
    kernel, dep = _make_module(tmp_path)
    monkeypatch.setattr(config, "CACHE_DIR", str(tmp_path / "user_cache"))
    dirs = numba_cache_dirs(str(kernel))
    assert dirs[0] == kernel.parent / "__pycache__" and dirs[1].parent == tmp_path / "user_cache"
    files = []
    for d in dirs:
        d.mkdir(parents=True)
        for name in ("kernel.f-4.py311.nbi", "kernel.f-4.py311.1.nbc"):
            (d / name).write_bytes(b"x")
            files.append(d / name)
        (d / "other.g-1.py311.nbi").write_bytes(b"x")     # another module's: kept
    old = dep.stat().st_mtime - 100
    for f in files:
        os.utime(f, (old, old))
    assert invalidate_stale_numba_cache(str(kernel), [str(dep)]) == 4
    assert not any(f.exists() for f in files)
    assert all((d / "other.g-1.py311.nbi").exists() for d in dirs)
    # cache files newer than every dependency stay
    for f in files:
        f.write_bytes(b"x")
    assert invalidate_stale_numba_cache(str(kernel), [str(dep)]) == 0


def test_the_user_cache_dir_is_the_one_numba_writes(tmp_path):
    """numba_cache_dirs names the directory numba itself fills under NUMBA_CACHE_DIR (its own
    locator, run in a fresh interpreter with the variable set)."""
    kernel, _ = _make_module(tmp_path)
    user_cache = tmp_path / "user_cache"
    script = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(kernel.parent)!r})
        import kernel
        kernel.f(1)
        from bike_plant.jit import numba_cache_dirs
        print(numba_cache_dirs(kernel.__file__)[1])
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                         env=dict(os.environ, NUMBA_CACHE_DIR=str(user_cache)))
    assert out.returncode == 0, out.stderr
    where = out.stdout.strip().splitlines()[-1]
    written = list(user_cache.rglob("kernel.*.nb*"))
    assert written and {p.parent for p in written} == {pathlib.Path(where)}, (written, where)
    assert not list(kernel.parent.rglob("kernel.*.nb*"))      # nothing beside the source


def _called_from_loop(cold_opts, mark):
    """Compiles loop -> step (JIT_INLINE) -> rare (cold_opts, out_of_line() if mark), afresh;
    returns whether the loop's machine code still calls rare (it is out of line)."""
    import re

    import numpy as np
    from numba import njit

    from bike_plant.jit import JIT_HOT, JIT_INLINE, out_of_line

    @njit(**dict(cold_opts, cache=False))
    def rare(a):
        if mark:
            out_of_line()
        a[0] += 1.0
        return 0

    @njit(**dict(JIT_INLINE, cache=False))
    def step(a):
        if a[1] > 0.0:
            return rare(a)
        return 1

    @njit(**dict(JIT_HOT, cache=False))
    def loop(a, n):
        s = 0
        for _ in range(n):
            s += step(a)
        return s

    a = np.array([0.0, 1.0])
    assert loop(a, 3) == 0 and a[0] == 3.0
    name = rare.overloads[rare.signatures[0]].fndesc.mangled_name
    return re.search(r"call [^\n]*@" + re.escape(name) + r"\(", loop.inspect_llvm(loop.signatures[0])) is not None


def test_a_jit_cold_function_stays_out_of_line_under_a_forceinline_caller():
    """numba hands forceinline down to what a JIT_INLINE function calls, and LLVM inlines what
    it likes: the fused loop's rare paths (_overcurrent_trip, _segment_general, _hall_edges)
    were all inlined into it. JIT_COLD + out_of_line() keep such a function a call."""
    from bike_plant.jit import JIT_COLD, JIT_HOT
    assert _called_from_loop(JIT_COLD, True)
    assert not _called_from_loop(JIT_HOT, False)      # what the rare paths had: inlined
