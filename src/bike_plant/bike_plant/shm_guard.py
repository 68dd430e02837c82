"""Keep a (re)started node off the shared-memory ports of killed nodes that live processes still use.

Why: the ROS 2 Jazzy wheels run Fast DDS 2.14, and under ``ROS_AUTOMATIC_DISCOVERY_RANGE=
LOCALHOST`` (our default, tools/env.sh) rmw_fastrtps always adds its shared-memory transport
(FASTDDS_BUILTIN_TRANSPORTS and XML transport settings are overridden there). A participant
takes the lowest port N whose listener lock, an flock on ``/dev/shm/fastrtps_port<N>_el``,
nobody holds. The port of a process killed with SIGKILL is such a "zombie": the new
participant deletes its segment and creates a new one under the same name. A live process
that had sent to the killed one keeps its handle on the old, now deleted, segment and goes on
writing into it; it re-opens the port only when its watchdog finds the dead listener stuck,
which it never does if the kill landed between two of the listener's steps (Fast DDS
SharedMemGlobal.hpp: ``Port::is_zombie``, ``open_port_internal``, the port watchdog;
eProsima/Fast-DDS #5053, #5469, fix proposed in PRs #4728 / #4737, not in 2.14). The new node
is then matched and receives nothing from that process, for good: a realtime controller
restarted after kill -9 beside a running plant got no PlantState for 30 s (about 1 full test
run in 10), and a restarted recorder lost a stretch of states until the plant's watchdog
re-opened the port.

What: before the node creates its participant, :func:`hold_stale_ports` takes the lock of
every zombie port that another live process still maps and holds it for the node's life, so
Fast DDS's own lock attempt fails ("already locked") and it moves on to a fresh port; the
writers then open that port by its new name. A zombie that no live process maps is released
at once (taking it over is harmless). Reading other processes' ``/proc/<pid>/maps`` needs the
same user (or root); a process we cannot read counts as not mapping anything.
"""
from __future__ import annotations

import fcntl
import os
import re

SHM_DIR = "/dev/shm"
PROC_DIR = "/proc"
_LOCK_RE = re.compile(r"fastrtps_port(\d+)_el")
_MAP_RE = re.compile(rb"/fastrtps_port(\d+)(?:\s|$)")

_held: list = []        # lock fds held for the life of the process (closing one releases it)
_held_ports: set = set()


def _zombie_locks(shm_dir: str) -> dict:
    """{port: fd} for each port lock file nobody holds (we now hold it)."""
    try:
        names = os.listdir(shm_dir)
    except OSError:
        return {}
    locks = {}
    for name in names:
        m = _LOCK_RE.fullmatch(name)
        if m is None:
            continue
        try:
            fd = os.open(os.path.join(shm_dir, name), os.O_RDONLY)
        except OSError:
            continue                     # removed meanwhile: its owner closed cleanly
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)                 # a live listener holds it: Fast DDS skips it anyway
            continue
        locks[int(m.group(1))] = fd
    return locks


def ports_mapped_by_others(proc_dir: str = PROC_DIR, self_pid: int | None = None) -> dict:
    """{port: [pid, ...]} of the Fast DDS port segments other live processes have mapped."""
    me = os.getpid() if self_pid is None else self_pid
    mapped: dict = {}
    try:
        pids = [int(p) for p in os.listdir(proc_dir) if p.isdigit()]
    except OSError:
        return mapped
    for pid in pids:
        if pid == me:
            continue
        try:
            with open(os.path.join(proc_dir, str(pid), "maps"), "rb") as f:
                text = f.read()
        except OSError:
            continue                     # gone, or not ours to read
        if b"fastrtps_port" not in text:
            continue
        for port in {int(m) for m in _MAP_RE.findall(text)}:
            mapped.setdefault(port, []).append(pid)
    return mapped


def hold_stale_ports(shm_dir: str = SHM_DIR, proc_dir: str = PROC_DIR) -> list:
    """Take and keep the lock of each zombie Fast DDS port that another live process maps (the
    module docstring says why). Returns those ports, sorted; [] on a clean host. Call it
    before the process creates its first participant."""
    locks = _zombie_locks(shm_dir)
    if not locks:
        return []
    mapped = ports_mapped_by_others(proc_dir)
    kept = []
    for port, fd in locks.items():
        if port in mapped:
            _held.append(fd)
            _held_ports.add(port)
            kept.append(port)
        else:
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)
    return sorted(kept)


def own_ports(proc_dir: str = PROC_DIR) -> list:
    """The Fast DDS shared-memory ports this process listens on (the port locks its
    participants hold; not those the guard holds to keep it off)."""
    fd_dir = os.path.join(proc_dir, "self", "fd")
    ports = set()
    try:
        fds = os.listdir(fd_dir)
    except OSError:
        return []
    for fd in fds:
        try:
            m = _LOCK_RE.search(os.readlink(os.path.join(fd_dir, fd)))
        except OSError:
            continue
        if m is not None:
            ports.add(int(m.group(1)))
    return sorted(ports - _held_ports)


def writers_to_deleted(ports, proc_dir: str = PROC_DIR) -> dict:
    """{port: [pid, ...]}: live processes that map a deleted segment of one of ``ports``, i.e.
    send to this node over a segment it no longer reads (the failure the guard prevents)."""
    want = set(ports)
    found: dict = {}
    if not want:
        return found
    try:
        pids = [p for p in os.listdir(proc_dir) if p.isdigit()]
    except OSError:
        return found
    for pid in pids:
        try:
            with open(os.path.join(proc_dir, pid, "maps"), "rb") as f:
                text = f.read()
        except OSError:
            continue
        for m in re.finditer(rb"/fastrtps_port(\d+) \(deleted\)", text):
            port = int(m.group(1))
            if port in want and int(pid) not in found.get(port, []):
                found.setdefault(port, []).append(int(pid))
    return found


def release_all() -> None:
    """Let go of every held lock (tests; a node holds them until it exits)."""
    _held_ports.clear()
    while _held:
        fd = _held.pop()
        try:
            fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)
