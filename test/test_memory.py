"""bike_plant.memory: which library pages a node may drop after its kernels are loaded, and that
dropping them leaves a process whose kernels (and a later compile) still run and which exits
cleanly; a real node's RSS with them dropped."""
from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from bike_plant.memory import LOAD_TIME_LIBRARIES, memory_mb, releasable_mappings

LIB = "/venv/lib/python3.11/site-packages/llvmlite/binding/libllvmlite.so"


def _mapping(start: int, perms: str, path: str, rss_kb: int, anon_kb: int = 0, dirty_kb: int = 0,
             with_anon_line: bool = True) -> str:
    lines = [f"{start:012x}-{start + 0x10000:012x} {perms} 00000000 08:01 1234                       {path}",
             "Size:                 64 kB",
             f"Rss:            {rss_kb:8d} kB",
             "Pss:                  10 kB",
             "Shared_Clean:         10 kB",
             f"Shared_Dirty:   {0:8d} kB",
             "Private_Clean:         0 kB",
             f"Private_Dirty:  {dirty_kb:8d} kB",
             "Referenced:           10 kB"]
    if with_anon_line:
        lines.append(f"Anonymous:      {anon_kb:8d} kB")
    lines += ["Swap:                  0 kB", "VmFlags: rd ex mr mw me"]
    return "\n".join(lines)


def test_only_clean_read_only_pages_of_the_named_library_are_released():
    smaps = "\n".join([
        _mapping(0x7f0000000000, "r--p", LIB, 40),                      # ELF header, rodata: clean
        _mapping(0x7f0000010000, "r-xp", LIB, 60),                      # text: clean
        _mapping(0x7f0000020000, "r--p", LIB, 16, anon_kb=16, dirty_kb=16),   # RELRO: relocated, then read-only
        _mapping(0x7f0000030000, "rw-p", LIB, 8),                       # data: writable
        _mapping(0x7f0000040000, "r-xp", LIB, 0),                       # nothing resident
        _mapping(0x7f0000050000, "r-xp", "/usr/lib/libc.so.6", 50),    # another library
        _mapping(0x7f0000060000, "r-xp", LIB, 30, with_anon_line=False),    # truncated record: unknown
        _mapping(0x7f0000070000, "rw-p", "", 100),                      # anonymous memory
    ])
    got = releasable_mappings(smaps)
    assert got == [(0x7f0000000000, 0x7f0000010000, 40 * 1024), (0x7f0000010000, 0x7f0000020000, 60 * 1024)]
    assert releasable_mappings(smaps, ("libc.so.6",)) == [(0x7f0000050000, 0x7f0000060000, 50 * 1024)]
    assert releasable_mappings("") == []
    assert LOAD_TIME_LIBRARIES == ("libllvmlite.so",)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_process_that_dropped_llvm_runs_its_kernels_compiles_again_and_exits_cleanly():
    # in a child: the RELRO case above, had it been released, crashed the process at exit
    script = textwrap.dedent("""
        import numpy as np
        from bike_plant import bldc as K
        from bike_plant.config import load_config, default_config_path
        from bike_plant.params import plant_params_from_config, pack_params
        from bike_plant.memory import release_clean_library_pages, memory_mb

        def rss_file_mb():
            for line in open("/proc/self/status"):
                if line.startswith("RssFile:"):
                    return int(line.split()[1]) / 1024

        cfg = load_config(default_config_path())
        p = pack_params(plant_params_from_config(cfg))

        def run():
            state = K.new_state(p, 3000.0, 0.7)
            n = 400
            ga = np.full(n, 0b100001, np.uint8)
            gb = np.zeros(n, np.uint8)
            sp = np.full(n, 0.5)
            samples = np.zeros((n, 3))
            ec = np.zeros(2 * n + 8, np.uint64)
            es = np.zeros(2 * n + 8, np.uint8)
            K.step_batch(state, p, ga, gb, sp, ec, es, samples, np.zeros(3))
            return samples.copy(), state.copy()

        a, sa = run()
        before = rss_file_mb()
        released = release_clean_library_pages() / 2**20
        after = rss_file_mb()
        b, sb = run()
        assert np.array_equal(a, b) and np.array_equal(sa, sb)
        import numba

        @numba.njit
        def fresh(x):          # a compile after the release: LLVM's pages come back as needed
            return x * 2.0 + 1.0
        assert fresh(3.0) == 7.0
        print(f"released {released:.1f} rssfile {before:.1f} -> {after:.1f}")
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout + out.stderr
    words = out.stdout.split()
    released, before, after = float(words[1]), float(words[3]), float(words[5])
    assert released > 10.0, out.stdout
    assert before - after > 10.0, out.stdout


def test_mappings_released_before_are_still_found_for_the_load_time_releaser():
    smaps = "\n".join([_mapping(0x7f0000000000, "r-xp", LIB, 0),
                       _mapping(0x7f0000010000, "r--p", LIB, 0, anon_kb=16, dirty_kb=16)])
    assert releasable_mappings(smaps) == []
    assert releasable_mappings(smaps, resident_only=False) == [(0x7f0000000000, 0x7f0000010000, 0)]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_kernels_loaded_under_the_load_time_releaser_peak_lower_and_run_the_same():
    """The plant node's kernels loaded (the backend made and warmed up, as the node does) with
    LLVM's library pages dropped as they load: the process's peak RSS (VmHWM) is lower than
    with the pages dropped only at the end (175-183 MB against ~125 MB here on Python 3.11),
    and the kernels compute the same. Each case in its own child (a peak is per process)."""
    script = textwrap.dedent("""
        import sys
        import numpy as np
        from bike_plant.config import load_config, default_config_path
        from bike_plant.memory import LoadTimePageReleaser, release_clean_library_pages
        from bike_plant.node import make_backend

        def hwm_mb():
            for line in open("/proc/self/status"):
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024

        cfg = load_config(default_config_path())

        def load():
            backend = make_backend("sim", cfg, 1)
            backend.warm_up(20)
            return backend

        if sys.argv[1] == "releaser":
            with LoadTimePageReleaser(0.01) as releaser:
                backend = load()
            assert releaser.ranges and releaser.passes > 0
        else:
            backend = load()
            release_clean_library_pages()
        backend.safe_batch(200)
        snap = backend.snapshot()
        print(hwm_mb(), sum(abs(v) for v in snap.values() if isinstance(v, float) and np.isfinite(v)))
    """)
    peaks, results = {}, {}
    for case in ("end", "releaser"):
        out = subprocess.run([sys.executable, "-c", script, case], capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, out.stdout + out.stderr
        peaks[case], results[case] = (float(w) for w in out.stdout.split()[-2:])
    assert results["releaser"] == results["end"]
    assert peaks["releaser"] < peaks["end"] - 15.0, peaks


def test_memory_mb_reads_this_process():
    m = memory_mb()
    assert m["rss"] > 10.0 and 0.0 < m["uss"] <= m["pss"] + 1e-6 <= m["rss"] + 1e-6
    assert memory_mb(2 ** 22 + 12345) == {}
