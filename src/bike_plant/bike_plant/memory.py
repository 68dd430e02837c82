"""Resident memory of a node process: what it is made of, and the library pages it can drop.

A loop node (plant, controller) imports numba, which maps LLVM (llvmlite's libllvmlite.so,
~180 MB on disk). Loading the node's cached kernels at start-up touches ~70 MB of it, and
those pages count in the process's RSS for as long as they stay mapped, although after the
warm-up nothing in the node runs LLVM again (the kernels are machine code of their own) and
the pages are clean copies of the file, shared with every other process that maps it.
:func:`release_clean_library_pages` unmaps them from this process (madvise MADV_DONTNEED):
the file's pages stay in the page cache (the next node's start-up finds them there), and
should LLVM run again in this process (a compile of a kernel the warm-up did not cover) it
faults them back in, at the cost of page faults, never of correctness.

Only a mapping that is read-only and holds no anonymous (copied-on-write) page is dropped:
the dynamic linker writes relocations into parts of a library (RELRO) and then makes them
read-only, and dropping those pages would bring back the unrelocated file contents (tried:
the process crashed at exit). Linux only; elsewhere nothing is released.

:func:`memory_mb` reads RSS, PSS (shared pages divided among the processes that map them) and
USS (this process's private pages) from /proc, for the benchmark.
"""
from __future__ import annotations

import ctypes
import re
import sys

MADV_DONTNEED = 4
# libraries used only to load the kernels (numba's code generator)
LOAD_TIME_LIBRARIES = ("libllvmlite.so",)

_HEADER = re.compile(r"^([0-9a-f]+)-([0-9a-f]+) (\S+) \S+ \S+ \S+\s*(.*)$")


def releasable_mappings(smaps_text: str, suffixes=LOAD_TIME_LIBRARIES,
                        resident_only: bool = True) -> list[tuple[int, int, int]]:
    """(start, end, rss_bytes) of each mapping in /proc/<pid>/smaps text that belongs to a library
    named by `suffixes`, is not writable and holds no anonymous or dirty page: the mappings
    whose resident pages are clean file pages, safe to drop and fault back. With
    ``resident_only=False`` also those with no page resident now (released before)."""
    out = []
    cur = None

    def close(m):
        if m is None or not m["path"].endswith(suffixes) or "w" in m["perms"] or (resident_only and m["rss"] == 0):
            return
        if m["anon"] != 0 or m["dirty"]:       # anon None: the record had no Anonymous line
            return
        out.append((m["start"], m["end"], m["rss"]))

    for line in smaps_text.splitlines():
        h = _HEADER.match(line)
        if h:
            close(cur)
            cur = {"start": int(h.group(1), 16), "end": int(h.group(2), 16), "perms": h.group(3),
                   "path": h.group(4).strip(), "rss": 0, "anon": None, "dirty": 0}
            continue
        if cur is None or ":" not in line:
            continue
        key, _, rest = line.partition(":")
        fields = rest.split()
        if not fields or not fields[0].isdigit():
            continue
        kib = int(fields[0]) * 1024
        if key == "Rss":
            cur["rss"] = kib
        elif key == "Anonymous":
            cur["anon"] = kib
        elif key in ("Private_Dirty", "Shared_Dirty"):
            cur["dirty"] += kib
    close(cur)
    return out


def _smaps_and_madvise():
    """(this process's /proc/self/smaps text, libc's madvise) on Linux; ("", None) where either
    is not available."""
    if not sys.platform.startswith("linux"):
        return "", None
    try:
        with open("/proc/self/smaps") as f:
            text = f.read()
        madvise = ctypes.CDLL(None, use_errno=True).madvise
    except (OSError, AttributeError):
        return "", None
    madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    madvise.restype = ctypes.c_int
    return text, madvise


def release_clean_library_pages(suffixes=LOAD_TIME_LIBRARIES) -> int:
    """Drop this process's clean, read-only pages of the libraries named by `suffixes` (see the
    module docstring). Returns the bytes that were resident in the mappings released (0 where
    /proc or madvise is not available)."""
    text, madvise = _smaps_and_madvise()
    if madvise is None:
        return 0
    released = 0
    for start, end, rss in releasable_mappings(text, suffixes):
        if madvise(start, end - start, MADV_DONTNEED) == 0:
            released += rss
    return released


class LoadTimePageReleaser:
    """``with LoadTimePageReleaser(): load the kernels``: drops the clean library pages of
    :func:`release_clean_library_pages` every ``period_s`` from a thread while the block runs,
    and once more at its end. Loading a node's cached kernels runs LLVM through ~65 MB of its
    library, and dropped only at the end those pages were all resident at once: the node's
    peak RSS (the 200 MB target of issue 6) was 175-183 MB on Python 3.11 and ~221 MB on 3.12,
    against ~110 MB once loaded. Dropped as it goes, LLVM faults back only the pages it is
    running (page-cache hits), and the peak falls by about the library's share.

    The mappings are chosen once, on entry (read-only, no anonymous page: see the module
    docstring); the thread then only calls madvise on them, never reading /proc again (a
    parse of /proc/self/smaps takes ~40 ms of the GIL, which slowed the load it ran beside)."""

    def __init__(self, period_s: float = 0.02, suffixes=LOAD_TIME_LIBRARIES):
        import threading

        self.period_s = period_s
        self.suffixes = suffixes
        self.ranges: list[tuple[int, int]] = []
        self.madvise = None
        self.passes = 0
        self._stop = threading.Event()
        self._thread = None

    def _release(self) -> None:
        for start, end in self.ranges:
            self.madvise(start, end - start, MADV_DONTNEED)

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self._release()
            self.passes += 1

    def __enter__(self) -> LoadTimePageReleaser:
        import threading

        try:
            import llvmlite.binding  # noqa: F401 - mapped now, so that its mappings are found
        except ImportError:
            pass
        text, self.madvise = _smaps_and_madvise()
        if self.madvise is not None:
            self.ranges = [(start, end) for start, end, _rss in releasable_mappings(text, self.suffixes,
                                                                                   resident_only=False)]
            self._release()
        if self.ranges:
            self._thread = threading.Thread(target=self._run, name="llvm-page-release", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self.ranges:
            self._release()


def memory_mb(pid: int | str = "self") -> dict:
    """{'rss', 'pss', 'uss'} of a process in MB from /proc/<pid>/smaps_rollup (uss: private
    clean + dirty pages); {} when the process is gone or /proc has no rollup."""
    vals = {}
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            for line in f:
                key, _, rest = line.partition(":")
                fields = rest.split()
                if fields and fields[0].isdigit():
                    vals[key] = int(fields[0]) / 1024.0
    except OSError:
        return {}
    if "Rss" not in vals:
        return {}
    return {"rss": vals["Rss"], "pss": vals.get("Pss", 0.0),
            "uss": vals.get("Private_Clean", 0.0) + vals.get("Private_Dirty", 0.0)}

