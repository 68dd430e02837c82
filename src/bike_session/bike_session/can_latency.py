"""DriveCommand -> CAN frame latency of the plant's ``backend: can`` (for ``./bike bench``).

:func:`can_latency` starts bike-drive-emulator and a real plant_node (backend can, realtime)
on a udp_multicast bus of their own, publishes DriveCommands from this process (rclpy, the
plant's DDS topic ``/bike/drive_command``) and times each until its Set_Input_Torque frame is
on the bus, as seen by a python-can listener in this process. Every command carries its own
torque value (a few mN m, harmless), so each frame is matched to the command that caused it.

What the figure includes: DDS delivery to the plant's subscription callback, the plant's
validation and encoding (CanBackend.submit), python-can's send, the UDP multicast loopback
and the listener's socket. The frame's timestamp is the receive time python-can records
(SO_TIMESTAMP where the kernel provides it), so the listener thread's own wake-up is left out.
The plant's in-process part alone (callback -> frame handed to the bus) is reported too
(``plant_submit_p50_us`` / ``plant_submit_max_us``, from its diagnostic).

    python -m bike_session.can_latency [--n 500] [--rate-hz 200] [--json FILE]

Imports rclpy: call it from tools (./bike bench), not from kernels.
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import random
import signal
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time

import yaml
from bike_plant.config import absolute_file_paths, dump_ros_params

GROUP = "239.74.163.2"
SET_INPUT_TORQUE = 0x0E


def _percentile(sorted_values: list[float], q: float) -> float:
    if not sorted_values:
        return float("nan")
    k = min(len(sorted_values) - 1, max(0, int(round(q * (len(sorted_values) - 1)))))
    return sorted_values[k]


def _config(base: pathlib.Path, out_dir: pathlib.Path, port: int) -> pathlib.Path:
    doc = yaml.safe_load(base.read_text())
    p = doc["/**"]["ros__parameters"]
    p["backend"] = "can"
    p["sync_mode"] = "realtime"
    can_section = p.setdefault("can", {})
    # no torque map: each command is found on the bus by its exact torque value
    can_section.update(interface="udp_multicast", channel=GROUP, port=port, emulator=False, log_file="",
                       torque_map_file="")
    absolute_file_paths(p, base.parent)
    path = out_dir / f"can_latency_{port}.yaml"
    path.write_text(dump_ros_params(doc, sort_keys=False))
    return path


def can_latency(n: int = 500, rate_hz: float = 200.0, config: str | os.PathLike | None = None,
                port: int | None = None, domain: int | None = None, timeout_s: float = 60.0) -> dict:
    """Publish ``n`` DriveCommands at ``rate_hz`` to a plant_node with backend can and time
    each until its Set_Input_Torque frame is on the bus. Returns a dict of milliseconds:
    p50_ms, p90_ms, p99_ms, max_ms, mean_ms, plus n, received, rate_hz, the plant's own share
    and a description. Raises RuntimeError if the plant never arms the emulated drive."""
    import can
    import rclpy
    from ament_index_python.packages import get_package_prefix
    from bike_msgs.msg import DriveCommand, PlantState
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from bike_plant import msgconv
    from bike_plant.config import default_config_path
    from bike_plant.loop import AUX_QOS, LOOP_QOS

    base = pathlib.Path(config) if config else default_config_path().with_name("bldc_can.yaml")
    port = port or random.SystemRandom().randint(41000, 48999)
    if domain is None:
        from bike_session import domains
        domain = domains.claim()
    procs: list[subprocess.Popen] = []
    tmp = tempfile.TemporaryDirectory(prefix="can_latency_")
    context = None
    bus = None
    executor = None
    logs: list = []
    threads: list[threading.Thread] = []
    stop = threading.Event()
    try:
        cfg_path = _config(base, pathlib.Path(tmp.name), port)
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                   PYTHONUNBUFFERED="1")
        logs += [open(pathlib.Path(tmp.name) / name, "w") for name in ("emulator.log", "plant.log")]
        procs.append(subprocess.Popen(
            [sys.executable, "-m", "bike_controller.drive_emulator", "--interface", "udp_multicast", "--channel", GROUP,
             "--port", str(port), "--config", str(cfg_path), "--quiet"],
            stdout=logs[0], stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env, start_new_session=True))
        plant = os.path.join(get_package_prefix("bike_plant"), "lib", "bike_plant", "plant_node")
        procs.append(subprocess.Popen(
            [plant, "--ros-args", "-r", "__ns:=/bike", "--params-file", str(cfg_path), "-p", f"config_path:={cfg_path}",
             "-p", "duration_s:=0.0", "-p", "command_timeout_s:=1.0"],
            stdout=logs[1], stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env, start_new_session=True))

        # the bus side: first arrival of each torque value
        bus = can.Bus(interface="udp_multicast", channel=GROUP, port=port)
        arrivals: dict[bytes, float] = {}
        lock = threading.Lock()

        def listen():
            while not stop.is_set():
                try:
                    msg = bus.recv(0.05)
                except Exception:  # noqa: BLE001
                    continue
                if msg is None or msg.arbitration_id != SET_INPUT_TORQUE or msg.is_remote_frame:
                    continue
                key = bytes(msg.data[:4])
                stamp = msg.timestamp or time.time()
                with lock:
                    arrivals.setdefault(key, stamp)

        threads.append(threading.Thread(target=listen, daemon=True))
        threads[-1].start()

        # the DDS side
        context = rclpy.Context()
        rclpy.init(context=context, domain_id=domain)
        node = Node("can_latency", namespace="/bike", context=context)
        pub = node.create_publisher(DriveCommand, "drive_command", LOOP_QOS)
        diag: dict = {}

        def on_diag(arr):
            for s in arr.status:
                if s.hardware_id == "bike_plant/can":
                    diag.update({kv.key: kv.value for kv in s.values})

        node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, AUX_QOS)
        node.create_subscription(PlantState, "plant_state", lambda m: None, LOOP_QOS)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        def spin():
            while not stop.is_set():
                try:
                    executor.spin_once(timeout_sec=0.05)
                except Exception:  # noqa: BLE001 -- context shut down under us
                    return

        threads.append(threading.Thread(target=spin, daemon=True))
        threads[-1].start()

        def command(seq: int, torque: float):
            return msgconv.drive_command_msg(seq, [], [], [], 0, torque_cmd_nm=torque)

        # warm-up: until the plant has armed the drive and forwards setpoints
        warm = struct.pack("<f", 0.0)
        end = time.monotonic() + timeout_s
        seq = 0
        while time.monotonic() < end:
            for p in procs:
                if p.poll() is not None:
                    raise RuntimeError(f"a process of the latency rig exited ({p.args[0]}, code {p.returncode})")
            pub.publish(command(seq, 0.0))
            seq += 1
            time.sleep(0.02)
            with lock:
                if warm in arrivals:
                    break
        else:
            raise RuntimeError(f"the plant did not arm the emulated drive within {timeout_s:g}s")
        time.sleep(0.5)

        sent: list[tuple[bytes, float]] = []
        period = 1.0 / rate_hz
        next_t = time.monotonic()
        for i in range(n):
            value = -1e-4 * (i + 1)                              # unique, float32-exact key below
            key = struct.pack("<f", value)
            now = time.monotonic()
            if now < next_t:
                time.sleep(next_t - now)
            next_t += period
            t_pub = time.time()
            pub.publish(command(seq, struct.unpack("<f", key)[0]))
            seq += 1
            sent.append((key, t_pub))
        time.sleep(0.5)
        with lock:
            lat = sorted(arrivals[key] - t for key, t in sent if key in arrivals)
        lat_ms = [x * 1e3 for x in lat]
        result = {
            "what": "DriveCommand published (rclpy) -> its Set_Input_Torque frame received on the CAN bus "
                    "(python-can udp_multicast), through plant_node backend can",
            "n": n, "received": len(lat_ms), "rate_hz": rate_hz,
            "p50_ms": _percentile(lat_ms, 0.5), "p90_ms": _percentile(lat_ms, 0.9),
            "p99_ms": _percentile(lat_ms, 0.99), "max_ms": lat_ms[-1] if lat_ms else float("nan"),
            "mean_ms": statistics.fmean(lat_ms) if lat_ms else float("nan"),
        }
        time.sleep(1.1)                                             # one more diagnostic
        for key in ("can_submit_latency_p50_us", "can_submit_latency_max_us"):
            if key in diag:
                result["plant_" + key[len("can_"):]] = float(diag[key])
        return result
    finally:
        stop.set()
        for thread in threads:
            thread.join(2.0)
        for p in procs:
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGINT)
                    p.wait(10)
                except (ProcessLookupError, subprocess.TimeoutExpired):
                    try:
                        os.killpg(p.pid, signal.SIGKILL)
                    except ProcessLookupError:
                        pass
                    p.wait()
        if executor is not None:
            executor.shutdown()
        if context is not None:
            rclpy.try_shutdown(context=context)
        if bus is not None:
            bus.shutdown()
        for f in logs:
            f.close()
        tmp.cleanup()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bike_session.can_latency", description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=500, help="DriveCommands to time (default 500)")
    ap.add_argument("--rate-hz", type=float, default=200.0, help="publishing rate (default 200)")
    ap.add_argument("--config", help="bike config (default config/bldc_can.yaml)")
    ap.add_argument("--json", help="also write the result to this file")
    args = ap.parse_args(argv)
    result = can_latency(args.n, args.rate_hz, args.config)
    text = json.dumps(result, indent=2)
    print(text)
    if args.json:
        pathlib.Path(args.json).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
