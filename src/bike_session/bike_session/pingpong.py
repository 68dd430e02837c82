"""DDS ping-pong between two rclpy processes with the loop's own message sizes.

The limit of the lockstep node graph is one PlantState -> DriveCommand round trip per
batch, so the benchmark compares the graph with this bare round trip of the same
message types and array sizes (batch_periods N).

    python -m bike_session.pingpong echo --n 20      # the echo side (a separate process)
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


def measure(n: int, round_trips: int = 2000, warmup: int = 100) -> dict:
    """Round trips per second and latency percentiles against an echo process."""
    import rclpy
    from bike_msgs.msg import DriveCommand, PlantState

    proc = subprocess.Popen([sys.executable, "-m", "bike_session.pingpong", "echo", "--n", str(n)],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node("pingpong_measure", context=context)
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
        latencies.sort()
        total = sum(latencies)
        return {"round_trips_per_s": len(latencies) / total,
                "p50_us": latencies[len(latencies) // 2] * 1e6,
                "p99_us": latencies[int(len(latencies) * 0.99)] * 1e6}
    finally:
        rclpy.try_shutdown(context=context)
        try:
            os.killpg(proc.pid, 2)
            proc.wait(5)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            proc.kill()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("role", choices=["echo", "measure"])
    parser.add_argument("--n", type=int, default=20)
    opts = parser.parse_args(argv)
    if opts.role == "echo":
        return echo(opts.n)
    print(measure(opts.n))
    return 0


if __name__ == "__main__":
    sys.exit(main())
