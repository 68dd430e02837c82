"""DDS ping-pong between two rclpy processes with the loop's own message sizes.

The limit of the lockstep node graph is one PlantState -> DriveCommand round trip per
batch, so the benchmark compares the graph with this bare round trip of the same
message types and array sizes (batch_periods N).

    python -m bike_session.pingpong echo --n 20      # the echo side (a separate process)

``tuned=True`` (echo role ``echo-tuned``): the same exchange over the graph's own transport
pieces, as a floor for comparison: serialized bytes (``raw=True``), the loop nodes' wait set
(bike_plant.loop.HotWait) and their lockstep busy wait on both ends. The echo answers each
ping with the same pre-serialized pong; replies are counted (reliable, in order).
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time

QOS_DEPTH = 10


def _make_messages(n: int):
    from bike_msgs.msg import DriveCommand, PlantState

    ping = PlantState()
    ping.batch_periods = n
    ping.current_samples_a = [0.0] * (3 * n)
    ping.hall_edge_counts = [0] * 2
    ping.hall_edge_states = [0] * 2
    pong = DriveCommand()
    pong.gates_a = bytes(n)
    pong.gates_b = bytes(n)
    pong.split = [0.5] * n
    return ping, pong


def echo(n: int) -> int:
    """Answer every PlantState on 'ping' with a DriveCommand on 'pong' carrying its seq."""
    import rclpy
    from bike_msgs.msg import DriveCommand, PlantState

    rclpy.init()
    node = rclpy.create_node("pingpong_echo")
    _, pong = _make_messages(n)
    pub = node.create_publisher(DriveCommand, "pong", QOS_DEPTH)

    def on_ping(msg):
        pong.seq = msg.seq
        pub.publish(pong)

    node.create_subscription(PlantState, "ping", on_ping, QOS_DEPTH)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        rclpy.try_shutdown()
    return 0


def echo_tuned(n: int) -> int:
    """The echo of a tuned ping-pong (see the module docstring)."""
    import rclpy
    from bike_msgs.msg import DriveCommand, PlantState
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.serialization import serialize_message

    from bike_plant.loop import LOCKSTEP_BUSY_WAIT_S, LOOP_QOS, HotWait

    rclpy.init()
    node = rclpy.create_node("pingpong_echo")
    _, pong = _make_messages(n)
    raw_pong = serialize_message(pong)
    pub = node.create_publisher(DriveCommand, "pong", LOOP_QOS)
    sub = node.create_subscription(PlantState, "ping", lambda _raw: pub.publish(raw_pong), LOOP_QOS, raw=True)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    hot = HotWait(executor, [sub], node.context)
    try:
        while True:
            hot.spin(0.1, LOCKSTEP_BUSY_WAIT_S)
    except KeyboardInterrupt:
        pass
    finally:
        executor.shutdown()                     # see bike_plant.node.run_loop_node
        rclpy.try_shutdown()
    return 0


def _measure_tuned(node, context, n: int, round_trips: int, warmup: int) -> list[float]:
    from bike_msgs.msg import DriveCommand, PlantState
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.serialization import serialize_message

    from bike_plant.loop import LOCKSTEP_BUSY_WAIT_S, LOOP_QOS, HotWait

    ping, _ = _make_messages(n)
    raw_ping = serialize_message(ping)
    pub = node.create_publisher(PlantState, "ping", LOOP_QOS)
    got = [0]
    sub = node.create_subscription(DriveCommand, "pong", lambda _raw: got.__setitem__(0, got[0] + 1), LOOP_QOS,
                                   raw=True)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    hot = HotWait(executor, [sub], context)
    try:
        deadline = time.monotonic() + 30
        while (pub.get_subscription_count() == 0 or node.count_publishers("pong") == 0) and time.monotonic() < deadline:
            hot.spin(0.05)
        latencies = []
        for i in range(warmup + round_trips):
            want = got[0] + 1
            start = time.perf_counter()
            pub.publish(raw_ping)
            while got[0] < want:
                hot.spin(1.0, LOCKSTEP_BUSY_WAIT_S)
                if time.perf_counter() - start > 5.0:
                    raise RuntimeError("ping-pong echo stopped answering")
            if i >= warmup:
                latencies.append(time.perf_counter() - start)
    finally:
        executor.remove_node(node)
        executor.shutdown()
    return latencies


def _summary(latencies: list[float]) -> dict:
    latencies = sorted(latencies)
    return {"round_trips_per_s": len(latencies) / sum(latencies),
            "p50_us": latencies[len(latencies) // 2] * 1e6,
            "p99_us": latencies[int(len(latencies) * 0.99)] * 1e6}


def measure(n: int, round_trips: int = 2000, warmup: int = 100, tuned: bool = False) -> dict:
    """Round trips per second and latency percentiles against an echo process."""
    import rclpy
    from bike_msgs.msg import DriveCommand, PlantState

    role = "echo-tuned" if tuned else "echo"
    proc = subprocess.Popen([sys.executable, "-m", "bike_session.pingpong", role, "--n", str(n)],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node("pingpong_measure", context=context)
        if tuned:
            return _summary(_measure_tuned(node, context, n, round_trips, warmup))
        executor = rclpy.executors.SingleThreadedExecutor(context=context)
        executor.add_node(node)
        ping, _ = _make_messages(n)
        pub = node.create_publisher(PlantState, "ping", QOS_DEPTH)
        got = threading.Event()
        last = {"seq": -1}

        def on_pong(msg):
            last["seq"] = msg.seq
            got.set()

        node.create_subscription(DriveCommand, "pong", on_pong, QOS_DEPTH)
        deadline = time.monotonic() + 30
        while (pub.get_subscription_count() == 0 or node.count_publishers("pong") == 0) and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        latencies = []
        for seq in range(warmup + round_trips):
            ping.seq = seq
            start = time.perf_counter()
            pub.publish(ping)
            while last["seq"] != seq:
                executor.spin_once(timeout_sec=1.0)
                if time.perf_counter() - start > 5.0:
                    raise RuntimeError("ping-pong echo stopped answering")
            if seq >= warmup:
                latencies.append(time.perf_counter() - start)
        return _summary(latencies)
    finally:
        rclpy.try_shutdown(context=context)
        try:
            os.killpg(proc.pid, 2)
            proc.wait(5)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            proc.kill()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("role", choices=["echo", "echo-tuned", "measure", "measure-tuned"])
    parser.add_argument("--n", type=int, default=20)
    opts = parser.parse_args(argv)
    if opts.role == "echo":
        return echo(opts.n)
    if opts.role == "echo-tuned":
        return echo_tuned(opts.n)
    print(measure(opts.n, tuned=opts.role == "measure-tuned"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
