#!/usr/bin/env python3
"""Reproduce, on demand, the Fast DDS 2.14 stale shared-memory port that made a node restarted
after kill -9 deaf (bike_plant.shm_ports), and try a guard against it.

Three plain rclpy processes on this host (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, where the
Jazzy rmw_fastrtps always uses shared memory): a writer (10 samples every 1 ms) stays up; a
best-effort reader is killed with SIGKILL at the one moment that matters; a second reader is
started 1.5 s later (with --guard: after taking the locks of the killed reader's ports, see
hold_stale_ports) and must hear the writer.

The moment: each port segment (/dev/shm/fastrtps_port<N>) ends with a status byte per listener
(1024 of 20 bytes before the domain name: bit 0 in use, bit 1 waiting, bit 2 processing;
Fast DDS SharedMemGlobal.hpp, PortNode / ListenerStatus). A listener killed while in use but
neither waiting nor processing (between popping a buffer and starting on it, a window of
microseconds) is never found stuck by the writer's port watchdog, so the writer keeps its handle
on that segment; the new reader takes the same port number (the lowest whose lock nobody holds),
deletes the segment and makes a new one, and the writer's samples go into the deleted one. The
probe polls the reader's status byte, stops the reader (SIGSTOP) when it reads "in use" alone,
and kills it if the byte still says so once it is stopped; the byte is frozen from then on.

    source tools/env.sh && python tools/shm_stale_port_repro.py            # deaf: exit 1
    source tools/env.sh && python tools/shm_stale_port_repro.py --guard    # hears: exit 0

The guard is an experiment, not in the nodes. It kept a restarted node off the stale port in
every run, but in the first fresh-clone CI run with it every node holding such locks, a test
process hung for good: writers kept re-creating the dead port's segment (nobody took it over
until the dead participant's lease ran out), a writer killed during one of those re-creations
left a segment with an uninitialised header, and the next process to open it spun in boost's
managed_open_or_create_impl while holding its DataWriter's mutex (and, inside rclpy's
publish, the GIL). A rare deaf node is better than a hung one. The nodes heal it another way:
a node (controller, plant, session, recorder) that finds itself on a stale port before it has
heard anything starts over with a new participant while the old one still holds its ports,
and the old one then leaves cleanly (bike_plant.loop.start_over_on_fresh_ports; test_nodes_realtime.py
forces it on each real node with this tool's functions). About 1 kill in 10 in the window
still leaves the writer on the live segment (exit 0): run it again.

Exit status: 0 the restarted reader heard the writer, 1 it did not within --wait-s, 2 the window
was not caught or the segment layout is not the one above (another Fast DDS version).
"""
from __future__ import annotations

import argparse
import mmap
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time

from bike_plant import shm_ports

STATUS_STRIDE_B = 20       # sizeof(ListenerStatus) in Fast DDS 2.14
MAX_LISTENERS = 1024
IN_USE, WAITING, PROCESSING = 1, 2, 4


def hold_stale_ports(shm_dir: str = shm_ports.SHM_DIR, proc_dir: str = shm_ports.PROC_DIR) -> list:
    """Take and keep the lock of each port that another live process maps and whose lock file
    nobody holds (a killed process's port), so this process's participant finds it locked and
    takes a fresh port. Returns those ports."""
    mapped = shm_ports.mapped_ports(proc_dir)
    locks = (re.fullmatch(r"fastrtps_port(\d+)_el", name) for name in os.listdir(shm_dir))
    ports = [int(m.group(1)) for m in locks if m and int(m.group(1)) in mapped]
    return shm_ports.hold_ports(ports, shm_dir)        # a lock a live listener holds is skipped


def node_main(role: str, guard: bool) -> None:
    """writer: Float64 in bursts of 10 every 1 ms, reliable. reader: best effort; prints
    'heard' once."""
    if guard:
        print("guard: kept off ports", hold_stale_ports(), flush=True)
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Float64
    rclpy.init()
    node = rclpy.create_node("shm_repro_" + role)
    if role == "writer":
        pub = node.create_publisher(Float64, "shm_repro", QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        msg = Float64(data=1.0)

        def burst():                    # 10 kHz of samples: more windows to catch per second
            for _ in range(10):
                pub.publish(msg)
        node.create_timer(0.001, burst)
    else:
        def on_msg(_msg, seen=[]):
            if not seen:
                seen.append(True)
                print("heard", flush=True)
        node.create_subscription(Float64, "shm_repro", on_msg,
                                 QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass


class _Proc:
    def __init__(self, role: str, guard: bool = False):
        args = [sys.executable, os.path.abspath(__file__), "--role", role] + (["--guard"] if guard else [])
        self.p = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: queue.Queue = queue.Queue()
        self.out: list = []
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self):
        for line in self.p.stdout:
            self.out.append(line.rstrip())
            self.lines.put(line.strip())

    def heard(self, wait_s: float) -> bool:
        until = time.monotonic() + wait_s
        while time.monotonic() < until:
            try:
                if self.lines.get(timeout=max(0.0, until - time.monotonic())) == "heard":
                    return True
            except queue.Empty:
                break
        return False

    def stop(self):
        if self.p.poll() is None:
            self.p.kill()
        self.p.wait(10)


def _stopped(pid: int) -> bool:
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[1].split()[0] == "T"


def find_listener(port: int, sample_s: float = 0.3):
    """(mmap, offset of the status byte) of the one active listener of the port: the entry that
    is in use and was seen both waiting and processing; None if there is no such entry."""
    with open(os.path.join(shm_ports.SHM_DIR, f"fastrtps_port{port}"), "rb") as f:
        m = mmap.mmap(f.fileno(), 0, prot=mmap.PROT_READ)       # the map keeps its own fd
    end = m[:].rfind(b"fastrtps\0")
    base = end - MAX_LISTENERS * STATUS_STRIDE_B
    if end < 0 or base < 0:
        return None
    seen: dict = {}
    until = time.monotonic() + sample_s
    while time.monotonic() < until:
        for k in range(8):                          # the first few entries (a fresh port uses entry 0)
            seen.setdefault(k, set()).add(m[base + k * STATUS_STRIDE_B])
    for k, values in seen.items():
        if all(v & IN_USE for v in values) and any(v & WAITING for v in values) and any(v & PROCESSING for v in values):
            return m, base + k * STATUS_STRIDE_B
    return None


def find_data_listener(ports, give_up_s: float = 30.0):
    """find_listener on the domain's data port (the highest of a participant's ports: the other,
    7001 here, carries no user data, so a kill in its window leaves the data flowing), sampled
    again until give_up_s: on a loaded host one 0.3 s sample can miss the listener's waiting or
    processing state. (port, (mmap, offset)), or None."""
    if not ports:
        return None
    port = max(ports)
    until = time.monotonic() + give_up_s
    while True:
        found = find_listener(port)
        if found or time.monotonic() >= until:
            return (port, found) if found else None


def kill_in_window(pid: int, m, off: int, give_up_s: float) -> int | None:
    """SIGKILL the process while its listener is in use and neither waiting nor processing;
    returns the number of stops it took, None if not caught within give_up_s."""
    stops = 0
    until = time.monotonic() + give_up_s
    while time.monotonic() < until:
        if m[off] != IN_USE:
            continue
        stops += 1
        os.kill(pid, signal.SIGSTOP)
        while not _stopped(pid):
            pass
        if m[off] == IN_USE:
            os.kill(pid, signal.SIGKILL)
            return stops
        os.kill(pid, signal.SIGCONT)
    return None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--guard", action="store_true",
                    help="the second reader first holds the locks of stale ports (an experiment: see the docstring)")
    ap.add_argument("--wait-s", type=float, default=10.0, help="the second reader must hear the writer within this")
    ap.add_argument("--give-up-s", type=float, default=60.0, help="give up catching the window after this")
    ap.add_argument("--role", choices=["driver", "writer", "reader"], default="driver", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.role != "driver":
        node_main(args.role, args.guard)
        return 0
    procs = [_Proc("writer")]
    try:
        time.sleep(1.0)
        first = _Proc("reader")
        procs.append(first)
        if not first.heard(20.0):
            print("shm stale port repro: the first reader never heard the writer", first.out[-10:], flush=True)
            return 2
        ports = sorted(set(shm_ports.own_ports(first.p.pid)) - set(shm_ports.own_ports(procs[0].p.pid)))
        hit = find_data_listener(ports)
        if hit is None:
            print(f"shm stale port repro: no active listener found in data port {max(ports, default=None)} of "
                  f"{ports} (another segment layout?)", flush=True)
            return 2
        data_port, found = hit
        t_hunt = time.monotonic()
        stops = kill_in_window(first.p.pid, *found, args.give_up_s)
        if stops is None:
            print(f"shm stale port repro: window not caught in {args.give_up_s:g} s", flush=True)
            return 2
        first.p.wait(10)
        frozen = found[0][found[1]]
        time.sleep(1.5)
        second = _Proc("reader", guard=args.guard)
        procs.append(second)
        heard = second.heard(args.wait_s)
        deleted = [str(port) for port, pids in sorted(shm_ports.writers_to_deleted(ports).items())
                   if procs[0].p.pid in pids]
        print(f"shm stale port repro: first reader killed in the window after {stops} stop(s), "
              f"{time.monotonic() - t_hunt:.1f} s (status byte "
              f"{frozen:#04x}, data port {data_port} of {ports}); second reader{' (guarded)' if args.guard else ''} on ports "
              f"{shm_ports.own_ports(second.p.pid)} {'heard the writer' if heard else f'DEAF for {args.wait_s:g} s'}; "
              f"writer maps deleted port segments {deleted or 'none'}", flush=True)
        guard_lines = [line for line in second.out if line.startswith("guard:")]
        if guard_lines:
            print(guard_lines[0], flush=True)
        return 0 if heard else 1
    finally:
        for p in reversed(procs):
            p.stop()


if __name__ == "__main__":
    sys.exit(main())
