#!/usr/bin/env python3
"""Does a node restarted after kill -9 hear every writer that survived it?

Plain rclpy, no bike code: PEERS long-lived writer processes (a 100 Hz and a 1 kHz rate, half
of them also reading the victim's own topic, as the session and plant read the controller's)
stay up while a victim process subscribing to all of them is started, killed with SIGKILL at a
random moment after it heard them all, and started again, RESTARTS times. A restart that has
not heard a peer within --wait-s counts as deaf; the probe then waits up to --give-up-s to
tell late from never. Exit status 0 when no restart was deaf, 1 otherwise.

Why: a realtime controller restarted after kill -9 beside a running plant once answered
nothing for 30 s (CI; again 2026-12-04 in one of seven full local runs, where its log showed
that no PlantState ever reached it; README, reliability table). This asks the middleware the
same question without the bike's nodes, on the machine and the RMW at hand. (The cause, found
later: a kill landing in a microsecond window of the reader's shared-memory listener leaves the
writers on a stale port; random kills rarely hit it, so this probe did not.
tools/shm_stale_port_repro.py hits it on purpose.)

    source tools/env.sh && python tools/dds_restart_probe.py --restarts 100
    ... --best-effort --payload-bytes 600 --rates-hz 1000    # closer to the realtime controller

(--best-effort: the restarted reader is best effort, as a realtime controller's PlantState
reader is; --payload-bytes: the peers send Strings of that size, a PlantState at N = 20 being
~600 B; --rates-hz: the peers' rates.)

Run it beside CPU hogs to load it like the recovery test was loaded. The victim's output is
read by a thread: select() on a buffered pipe misses lines already in the reader's buffer
(an earlier version of this probe counted such lines as deaf restarts).
"""
from __future__ import annotations

import argparse
import os
import queue
import random
import signal
import subprocess
import sys
import threading
import time


def peer_main(topic: str, rate_hz: float, reads_victim: bool, payload_bytes: int = 0) -> None:
    """A surviving writer: publishes `topic` at rate_hz until SIGINT / SIGTERM (payload_bytes >
    0: a std_msgs/String of that many bytes instead of a Float64)."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Float64, String
    rclpy.init()
    node = rclpy.create_node("probe_peer_" + topic)
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    payload = "x" * payload_bytes
    pub = node.create_publisher(String if payload else Float64, topic, qos)
    if reads_victim:
        node.create_subscription(Float64, "probe_victim", lambda _m: None, qos)
    count = [0]

    def tick():
        count[0] += 1
        pub.publish(String(data=payload) if payload else Float64(data=float(count[0])))
        if count[0] == 1:
            print("publishing", flush=True)      # the driver starts the first victim on this
    node.create_timer(1.0 / rate_hz, tick)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):   # rclpy's own SIGINT / SIGTERM handling
        pass
    except RuntimeError:
        # the same shutdown, landed between two waits: rclpy then fails to build the next wait
        # set on the invalid context (RCLError, a RuntimeError) instead of raising the above
        if rclpy.ok():
            raise


def victim_main(topics: list, best_effort: bool = False, big: bool = False) -> None:
    """The restarted node: prints 'heard TOPIC' once per topic, answers each message of the
    first topic on probe_victim (a writer of its own, read by some peers). best_effort: its
    readers are best effort (the writers stay reliable), as a realtime controller's
    PlantState reader is (bike_plant.loop.REALTIME_QOS). big: the peers send Strings
    (--payload-bytes)."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Float64, String
    rclpy.init()
    node = rclpy.create_node("probe_victim")
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(Float64, "probe_victim", qos)
    if best_effort:
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    heard = set()

    def on(topic):
        def cb(msg):
            if topic not in heard:
                heard.add(topic)
                print(f"heard {topic}", flush=True)
            if topic == topics[0]:
                pub.publish(Float64(data=0.0))
        return cb
    for t in topics:
        node.create_subscription(String if big else Float64, t, on(t), qos)
    rclpy.spin(node)


def transports_in_effect(env) -> str:
    """What Fast DDS sends over. Under ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST the Jazzy
    rmw_fastrtps installs its own shared-memory + UDPv4 transports, so FASTDDS_BUILTIN_TRANSPORTS
    (and an XML profile's transports) have no effect there; only other ranges honour them."""
    if env.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "") == "LOCALHOST":
        return "SHM + UDPv4 (rmw_fastrtps for LOCALHOST)"
    return env.get("FASTDDS_BUILTIN_TRANSPORTS", "DEFAULT (SHM + UDPv4)")


def _lines(proc) -> "queue.Queue":
    q: queue.Queue = queue.Queue()

    def pump():
        for line in proc.stdout:
            q.put(line.strip())
        q.put(None)
    threading.Thread(target=pump, daemon=True).start()
    return q


def _wait_heard(q, heard: set, want: set, until_s: float) -> None:
    while heard < want and time.monotonic() < until_s:
        try:
            line = q.get(timeout=max(0.0, until_s - time.monotonic()))
        except queue.Empty:
            return
        if line is None:                  # the victim died
            return
        if line.startswith("heard "):
            heard.add(line.split(None, 1)[1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--restarts", type=int, default=50)
    ap.add_argument("--peers", type=int, default=4)
    ap.add_argument("--wait-s", type=float, default=7.0, help="a restart must hear every peer within this")
    ap.add_argument("--give-up-s", type=float, default=40.0, help="then wait this long to tell late from never")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--silent-topic", action="store_true",
                    help="the victim also subscribes to a topic nobody writes (checks that the probe sees deafness)")
    ap.add_argument("--best-effort", action="store_true",
                    help="the victim reads best effort (the writers stay reliable), as a realtime controller does")
    ap.add_argument("--payload-bytes", type=int, default=0,
                    help="the peers send std_msgs/String messages of this size (a PlantState at N = 20: ~600 B)")
    ap.add_argument("--rates-hz", default="100,1000", help="the peers' rates, alternating (default 100,1000)")
    ap.add_argument("--role", choices=["driver", "peer", "victim"], default="driver", help=argparse.SUPPRESS)
    ap.add_argument("role_args", nargs="*", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.role == "peer":
        peer_main(args.role_args[0], float(args.role_args[1]), args.role_args[2] == "1", args.payload_bytes)
        return 0
    if args.role == "victim":
        victim_main(args.role_args, args.best_effort, args.payload_bytes > 0)
        return 0
    if args.restarts < 1 or args.peers < 1 or args.wait_s <= 0 or args.give_up_s < args.wait_s:
        ap.error("need --restarts >= 1, --peers >= 1, 0 < --wait-s <= --give-up-s")
    try:
        rates = [float(x) for x in args.rates_hz.split(",")]
    except ValueError:
        rates = []
    if not rates or not all(0.0 < r <= 20000.0 for r in rates) or args.payload_bytes < 0:
        ap.error("need --rates-hz of numbers in (0, 20000], --payload-bytes >= 0")

    rng = random.Random(args.seed)
    me = os.path.abspath(__file__)
    peers = {f"probe_w{i}": (rates[i % len(rates)], i % 4 < 2) for i in range(args.peers)}
    topics = list(peers) + (["probe_nobody"] if args.silent_topic else [])
    size = ["--payload-bytes", str(args.payload_bytes)]
    procs = [subprocess.Popen([sys.executable, me, "--role", "peer", *size, t, str(rate), "1" if reads else "0"],
                              stdout=subprocess.PIPE, text=True)
             for t, (rate, reads) in peers.items()]
    victim_flags = (["--best-effort"] if args.best_effort else []) + size
    deaf = late = 0
    try:
        # every peer publishing before the first victim starts (a fixed 2 s wait before: most of
        # it idle once the peers were up, ~0.5 s on an idle host); the victim still has --wait-s
        # to hear each of them, as after every restart
        started = time.monotonic()
        for q in [_lines(p) for p in procs]:
            try:
                q.get(timeout=max(0.0, started + args.wait_s - time.monotonic()))
            except queue.Empty:          # a peer that never publishes: its topic counts as deaf below
                pass
        for i in range(args.restarts):
            victim = subprocess.Popen([sys.executable, me, "--role", "victim", *victim_flags, *topics],
                                      stdout=subprocess.PIPE, text=True)
            t0 = time.monotonic()
            q, heard = _lines(victim), set()
            _wait_heard(q, heard, set(topics), t0 + args.wait_s)
            if heard < set(topics):
                missing = sorted(set(topics) - heard)
                _wait_heard(q, heard, set(topics), t0 + args.give_up_s)
                never = sorted(set(topics) - heard)
                deaf += 1
                late += not never
                print(f"restart {i}: not heard within {args.wait_s:g} s: {missing}; "
                      f"never within {args.give_up_s:g} s: {never or 'none'}", flush=True)
            time.sleep(rng.uniform(0.05, 1.0))     # kill at a random moment of its steady state
            victim.kill()
            victim.wait()
            time.sleep(rng.uniform(0.0, 0.5))
    finally:
        for p in procs:
            p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
    print(f"dds restart probe: {deaf} of {args.restarts} restarts deaf to a surviving writer "
          f"({late} only late), {args.peers} peers at {args.rates_hz} Hz"
          f"{f', {args.payload_bytes} B messages' if args.payload_bytes else ''}"
          f"{', best-effort reader' if args.best_effort else ''}, "
          f"RMW {os.environ.get('RMW_IMPLEMENTATION', 'default')}, transports {transports_in_effect(os.environ)}",
          flush=True)
    return 1 if deaf else 0


if __name__ == "__main__":
    sys.exit(main())
