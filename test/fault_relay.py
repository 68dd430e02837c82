"""Test-only fault injector: a node in its own process between the controller and the plant.

    python test/fault_relay.py SCHEDULE_JSON SEED   (ROS_DOMAIN_ID from the environment)

Subscribes ``drive_command_raw`` (the controller's ``drive_command`` remapped) and publishes
``drive_command`` to the plant, namespace /bike. SCHEDULE_JSON is a list of phases
``[[t_start_s, drop_probability, delay_s], ...]``, t_start_s in wall seconds from the first
DriveCommand with a current command (the loop braking; earlier ones are forwarded); each
message is dropped with the phase's probability (seeded) or forwarded after the phase's
delay, order kept. The phase in force and counts go to stdout, and the schedule's origin as
``relay t0 <time.monotonic()>`` (one clock for every process of the machine), so that the
test need not follow the controller's 1 kHz stream itself.

The relay waits on its input through bike_plant.loop.HotWait (one wait set, no executor per
message): on a 2-core machine every process of the test competes with the loop it observes."""
from __future__ import annotations

import collections
import json
import random
import sys
import time

import rclpy
from bike_msgs.msg import DriveCommand
from bike_plant.loop import LOOP_QOS, HotWait
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node


def main() -> int:
    schedule = sorted(json.loads(sys.argv[1]))
    rng = random.Random(int(sys.argv[2]))
    rclpy.init()
    node = Node("fault_relay", namespace="/bike")
    pub = node.create_publisher(DriveCommand, "drive_command", LOOP_QOS)
    queue: collections.deque = collections.deque()
    state = {"t0": None, "phase": -1, "in": 0, "dropped": 0, "out": 0}

    def phase_now(now: float):
        t = now - state["t0"]
        index = max(i for i, p in enumerate(schedule) if p[0] <= t) if t >= schedule[0][0] else 0
        if index != state["phase"]:
            state["phase"] = index
            print(f"relay phase {index} {schedule[index]} at {t:.3f}s", flush=True)
        return schedule[index]

    def on_drive(msg):
        now = time.monotonic()
        if state["t0"] is None:
            if msg.current_cmd_a <= 0.0:           # the session's Command not in force yet
                pub.publish(msg)
                return
            state["t0"] = now
            print(f"relay t0 {now:.6f}", flush=True)
        _, drop, delay = phase_now(now)
        state["in"] += 1
        if rng.random() < drop:
            state["dropped"] += 1
            return
        queue.append((now + delay, msg))

    sub = node.create_subscription(DriveCommand, "drive_command_raw", on_drive, LOOP_QOS)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    hot = HotWait(executor, [sub], node.context)
    try:
        while rclpy.ok():
            wait = 0.005 if not queue else max(0.0, min(0.005, queue[0][0] - time.monotonic()))
            hot.spin(wait)
            now = time.monotonic()
            while queue and queue[0][0] <= now:
                pub.publish(queue.popleft()[1])
                state["out"] += 1
    except KeyboardInterrupt:
        pass
    finally:
        print(f"relay in={state['in']} dropped={state['dropped']} out={state['out']}", flush=True)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
