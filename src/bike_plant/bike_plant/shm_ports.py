"""Which Fast DDS shared-memory ports a process listens on, and who still writes to a deleted one.

Why: the ROS 2 Jazzy wheels run Fast DDS 2.14, and under ``ROS_AUTOMATIC_DISCOVERY_RANGE=
LOCALHOST`` (our default, tools/env.sh) rmw_fastrtps always adds its shared-memory transport
(FASTDDS_BUILTIN_TRANSPORTS and XML transport settings are overridden there). A participant
takes the lowest port N whose listener lock, an flock on ``/dev/shm/fastrtps_port<N>_el``,
nobody holds. The port of a process killed with SIGKILL is such a "zombie": the next
participant deletes its segment and creates a new one under the same name. A live process
that had sent to the killed one keeps its handle on the old, now deleted, segment and goes on
writing into it; it re-opens the port only when its watchdog finds the dead listener stuck,
which it never does if the kill landed while the listener was in use but neither waiting nor
processing, a window of microseconds (Fast DDS SharedMemGlobal.hpp: ``Port::is_zombie``,
``open_port_internal``, the port watchdog; eProsima/Fast-DDS #5053, fix proposed in PRs
#4728 / #4737, not in 2.14). The new node is then matched and receives nothing from that
process, for good. tools/shm_stale_port_repro.py makes it happen on demand.

:func:`writers_to_deleted` finds that signature (a live process mapping a deleted segment of
one of this node's ports), so a node fed nothing can say why (:func:`stale_port_check`); the
node then starts over on fresh ports (bike_plant.loop.start_over_on_fresh_ports: controller, plant,
session, recorder) and :func:`hold_ports` keeps its old ones.
Reading other processes' ``/proc/<pid>/maps`` needs the same user (or root); a process we
cannot read is skipped.
"""
from __future__ import annotations

import fcntl
import os
import re
import time

PROC_DIR = "/proc"
SHM_DIR = "/dev/shm"
DEAF_CHECK_S = 3.0      # a node that has heard nothing looks for the signature this often [wall s]
_LOCK_RE = re.compile(r"fastrtps_port(\d+)_el")
_MAP_RE = re.compile(rb"/fastrtps_port(\d+)( \(deleted\))?$", re.M)
_held: dict = {}        # port -> fd of a lock this process keeps (bike_plant.loop.start_over_on_fresh_ports)


def own_ports(pid: int | None = None, proc_dir: str = PROC_DIR) -> list:
    """The Fast DDS shared-memory ports a process (default: this one) listens on: the port
    locks its participants hold (for this process, not those hold_ports keeps)."""
    fd_dir = os.path.join(proc_dir, "self" if pid is None else str(pid), "fd")
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
    return sorted(ports - set(_held)) if pid is None else sorted(ports)


def _port_mappings(proc_dir: str):
    """(pid, {port: deleted?}) for every other live process that maps Fast DDS port segments."""
    me = os.getpid()
    try:
        pids = [int(p) for p in os.listdir(proc_dir) if p.isdigit()]
    except OSError:
        return
    for pid in pids:
        if pid == me:
            continue
        try:
            with open(os.path.join(proc_dir, str(pid), "maps"), "rb") as f:
                text = f.read()
        except OSError:
            continue                     # gone, or not ours to read
        ports = {}
        for port, deleted in _MAP_RE.findall(text):
            ports[int(port)] = ports.get(int(port), False) or bool(deleted)
        if ports:
            yield pid, ports


def mapped_ports(proc_dir: str = PROC_DIR) -> dict:
    """{port: [pid, ...]}: the Fast DDS port segments other live processes map (send to)."""
    found: dict = {}
    for pid, ports in _port_mappings(proc_dir):
        for port in ports:
            found.setdefault(port, []).append(pid)
    return found


def writers_to_deleted(ports, proc_dir: str = PROC_DIR) -> dict:
    """{port: [pid, ...]}: live processes that map a deleted segment of one of ``ports``, i.e.
    send to this node over a segment it no longer reads (the module docstring)."""
    want = set(ports)
    found: dict = {}
    if not want:
        return found
    for pid, mapped in _port_mappings(proc_dir):
        for port, deleted in mapped.items():
            if deleted and port in want:
                found.setdefault(port, []).append(pid)
    return found


def stale_port_check(proc_dir: str = PROC_DIR) -> tuple:
    """For a node fed nothing (the controller, plant, session and recorder ask): (why,
    start_over). ``why`` names each live process that writes to a deleted segment of this
    process's ports ("" if none); ``start_over`` is True when there is one and this process has
    not started over yet (it holds no old ports): then a new participant on fresh ports heals it
    (bike_plant.loop.start_over_on_fresh_ports)."""
    stale = writers_to_deleted(own_ports(), proc_dir)
    why = "; ".join(f"pid(s) {', '.join(map(str, pids))} still write to a deleted segment of this node's "
                    f"shared-memory port {port}" for port, pids in sorted(stale.items()))
    if why:
        why += " (Fast DDS stale port after a kill -9, eProsima/Fast-DDS #5053)"
    return why, bool(stale) and not _held


class StalePortWatch:
    """The look of a node that has heard nothing yet (plant, session, recorder, a controller
    with no writer matched): :func:`stale_port_check` every ``period_s`` from ``since`` (wall
    time; default: the first call). The writers' discovery data goes into the stale segment
    too, so no matched writer is waited for."""

    def __init__(self, period_s: float = DEAF_CHECK_S, since: float | None = None):
        self.period_s = period_s
        self.since = since
        self.next_at = None if since is None else since + period_s

    def start_over(self, now: float | None = None) -> str:
        """The writers to a deleted segment of this node's ports, named (stale_port_check's
        ``why``), when the node should start over on fresh ports now; "" otherwise."""
        return self.look(now) or ""

    def look(self, now: float | None = None) -> str | None:
        """None when the next look is not due yet; else :meth:`start_over`'s answer ("" when
        this look found nothing to start over for)."""
        now = time.monotonic() if now is None else now
        if self.since is None:
            self.since, self.next_at = now, now + self.period_s
        if now < self.next_at:
            return None
        self.next_at = now + self.period_s
        why, fresh = stale_port_check()
        return why if fresh else ""

    def waited_s(self, now: float | None = None) -> float:
        """Wall seconds since ``since`` (after the first :meth:`start_over`)."""
        return (time.monotonic() if now is None else now) - self.since


STALE_PEER_LOOKS = 5    # a running node looks this many times for a peer that cannot reach it (StalePeerWatch)


class StalePeerWatch:
    """The look of a node that already hears some of its peers (session, recorder, controller)
    for one that still cannot reach it: a live process that writes to a deleted segment of this
    node's ports at two looks in a row (``period_s`` apart). After a kill -9 the killed node's
    peers keep such a handle until their port watchdog re-opens the port, 0.5-3 s after the
    restarted node took it (6 of 8 restarts measured), or for good when the kill landed in the
    listener's window; one watchdog may heal while another does not (a restarted session that
    followed /clock but whose status never reached a reader, CI 2026-12-07). Such a handle is
    one taken before this node started (nobody deletes the segment of a port whose lock a live
    node holds), so it looks ``looks`` times from ``since`` (start-up) and then stops, unless
    the last look found one: then it goes on until the second in a row."""

    def __init__(self, looks: int = STALE_PEER_LOOKS, period_s: float = DEAF_CHECK_S, since: float | None = None):
        self.watch = StalePortWatch(period_s, since)
        self.looks = looks
        self.done = 0            # looks taken
        self.in_a_row = 0        # ... of which the last ones in a row found a stale writer
        self.fired = False

    @property
    def finished(self) -> bool:
        """Nothing more to look for: it fired, or its looks are over and the last was clean."""
        return self.fired or (self.done >= self.looks and self.in_a_row == 0)

    def look(self, now: float | None = None) -> str:
        """The writers named and since when (stale_port_check's ``why``) when the node should
        start over on fresh ports now (once); "" otherwise (not due, clean, or finished)."""
        if self.finished:
            return ""
        why = self.watch.look(now)
        if why is None:
            return ""
        self.done += 1
        self.in_a_row = self.in_a_row + 1 if why else 0
        if self.in_a_row < 2:
            return ""
        self.fired = True
        return f"{why}, {(self.in_a_row - 1) * self.watch.period_s:g}s after it was first seen"


def hold_ports(ports, shm_dir: str = SHM_DIR) -> list:
    """Take and keep, for the life of the process, the listener locks of ``ports`` (this
    process's old ports, after its participant left them), so that no participant started
    later takes them: a live writer may still hold a stale handle on that port number. Fast
    DDS's own flock on a new file description then fails and it moves on. Returns the ports
    held (a lock another process took meanwhile is skipped)."""
    for port in ports:
        if port in _held:
            continue
        try:
            fd = os.open(os.path.join(shm_dir, f"fastrtps_port{port}_el"), os.O_RDONLY | os.O_CREAT, 0o666)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        _held[port] = fd
    return sorted(p for p in ports if p in _held)


def held_ports() -> list:
    return sorted(_held)
