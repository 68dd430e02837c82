"""`./bike fleet --graph K`: K namespaced bikes in one DDS graph, optionally spread over
network namespaces (one per "host"), and a fleet monitor that prints each bike's summary.

Each bike is the project's own launch description (config/launch/bike.launch.yaml: plant,
controller, session) in namespace /bike1 .. /bikeK, lockstep, started by its own
:class:`bike_session.launcher.Launcher` (a bike ends when its plant ends; one slow bike does
not cut the others short).

Clock: each lockstep plant is the clock source of its own bike and advances sim time at
its own pace, so K plants on one global ``/clock`` would interleave K unrelated time
lines (the session nodes would see time jump back and forth). Every node of bike k is
therefore started with the remap ``-r /clock:=clock``: the plant's publisher, the session
node's subscription and the ``use_sim_time`` time source of every node of the bike resolve
to ``/bikek/clock``. On a full ROS 2 install the same is a ``<set_remap from="/clock"
to="clock"/>`` in a ``<group>`` with ``<push-ros-namespace namespace="bikek"/>`` around an
``<include>`` of bike.launch.yaml. ``/diagnostics`` stays global (its entries carry the
node's namespace).

Placement: ``--netns bike2=hostb`` runs every node of bike 2 in network namespace
``hostb`` (``ip netns exec``); ``--netns bike1/controller=hostb`` only that node, so the
bike's lockstep loop itself crosses the link. The namespaces must exist (a lab would have
real hosts). DDS discovery must then reach beyond localhost:
ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET (Fast DDS, the rmw of the pip wheels, then uses its
default multicast discovery; with ROS_STATIC_PEERS for networks without multicast).
"""
from __future__ import annotations

import json
import math
import os
import pathlib
import shutil
import signal
import sys
import tempfile
import threading
import time
from dataclasses import dataclass

from . import launcher as L

CLOCK_REMAP = ["-r", "/clock:=clock"]
FLEET_NODES = ("plant", "controller", "session")


class FleetError(ValueError):
    """A bad fleet request (one clear message)."""


GATED_NODE = "controller"      # starts once the monitor is matched to the bike (the ride begins with it)
GATE_TIMEOUT_S = 120.0


@dataclass
class PlacedSpec:
    """A node of one bike: a fleet-unique name (bike1/plant), an optional network namespace,
    and an optional gate file: the process waits (``python -m bike_session.fleet_graph gate``)
    until the file exists, then execs the node."""
    inner: object
    name: str
    netns: str = ""
    shutdown_on_exit: bool = False
    gate: str = ""

    def command(self) -> list[str]:
        cmd = self.inner.command()
        if self.gate:
            cmd = [sys.executable, "-m", "bike_session.fleet_graph", "gate", self.gate, "--"] + cmd
        return ["ip", "netns", "exec", self.netns] + cmd if self.netns else cmd

    def popen_kwargs(self) -> dict:
        return self.inner.popen_kwargs()


def parse_placement(items) -> dict[str, str]:
    """['bike2=hostb', 'bike1/controller=hostb'] -> {'bike2': 'hostb', 'bike1/controller': 'hostb'}."""
    out = {}
    for item in items or []:
        key, sep, ns = str(item).partition("=")
        if not sep or not key or not ns or any(c in ns for c in "/ \t"):
            raise FleetError(f"--netns expects BIKE=NETNS or BIKE/NODE=NETNS (e.g. bike2=hostb), got {item!r}")
        out[key.strip("/")] = ns
    return out


def bike_specs(launch_file: str, config: str, duration_s: float, namespace: str,
               placement: dict[str, str], gate: str = "") -> list[PlacedSpec]:
    """The nodes of one fleet bike: bike.launch.yaml in `namespace`, /clock remapped into it;
    the controller waits for `gate` (a lockstep plant does not step before its controller is
    there, so nothing is missed by whoever opens the gate)."""
    specs = []
    for spec in L.parse_launch(launch_file, {"config": config, "duration": repr(float(duration_s)),
                                             "namespace": namespace}):
        if not isinstance(spec, L.NodeSpec):
            raise FleetError(f"fleet bikes are simulated: the launch file starts '{spec.name}' (an executable; "
                             "a CAN backend?)")
        spec.ros_args = list(spec.ros_args) + CLOCK_REMAP
        ns = placement.get(f"{namespace}/{spec.name}", placement.get(namespace, ""))
        specs.append(PlacedSpec(spec, f"{namespace}/{spec.name}", ns, spec.shutdown_on_exit,
                                gate if spec.name == GATED_NODE else ""))
    return specs


def _check_netns(placement: dict[str, str], n_bikes: int) -> None:
    bikes = {f"bike{k}" for k in range(1, n_bikes + 1)}
    for key, ns in placement.items():
        bike, _, node = key.partition("/")
        if bike not in bikes:
            raise FleetError(f"--netns {key}={ns}: no such bike (bike1..bike{n_bikes})")
        if node and node not in FLEET_NODES:
            raise FleetError(f"--netns {key}={ns}: no such node (one of {', '.join(FLEET_NODES)})")
        if not os.path.exists(f"/run/netns/{ns}"):
            raise FleetError(f"--netns {key}={ns}: network namespace '{ns}' does not exist (ip netns add {ns})")
    if placement:
        rng = os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "")
        if rng.upper() not in ("SUBNET", "SYSTEM_DEFAULT"):
            raise FleetError("nodes in other network namespaces need DDS discovery beyond this host: "
                             f"ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET (now {rng or 'unset'})")


class FleetMonitor:
    """An rclpy node (in this process, the root network namespace) that listens to every
    bike's plant_state and keeps what the summary needs (energies are cumulative)."""

    def __init__(self, namespaces: list[str]):
        import rclpy
        from bike_msgs.msg import PlantState
        from rosgraph_msgs.msg import Clock
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

        self._rclpy = rclpy
        self.context = rclpy.context.Context()
        rclpy.init(context=self.context, args=["--ros-args", "--disable-rosout-logs"])
        self.node = rclpy.create_node("fleet_monitor", context=self.context)
        # reliable, keep-last: the end_of_run PlantState is not lost, and a slow monitor never
        # holds a plant back (a keep-last writer drops its oldest samples instead of blocking)
        qos = QoSProfile(depth=50, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
        self.data = {ns: {"messages": 0, "last": None, "speed_sum_rpm": 0.0, "faults": 0, "first_wall": None,
                          "last_wall": None, "clock_messages": 0} for ns in namespaces}
        self.subs = {}
        for ns in namespaces:
            self.subs[ns] = (
                self.node.create_subscription(PlantState, f"/{ns}/plant_state", self._make_cb(ns), qos),
                self.node.create_subscription(Clock, f"/{ns}/clock", self._make_clock_cb(ns), qos))
        # each bike keeps its sim time in its own namespace: nothing may arrive on the global /clock
        self.global_clock_messages = 0
        self.node.create_subscription(Clock, "/clock", self._on_global_clock, qos)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _make_cb(self, ns):
        def cb(msg):
            d = self.data[ns]
            now = time.monotonic()
            d["messages"] += 1
            d["speed_sum_rpm"] += msg.speed_rpm
            d["faults"] |= int(msg.faults)
            d["first_wall"] = d["first_wall"] or now
            d["last_wall"] = now
            if d["last"] is None or msg.seq >= d["last"]["seq"]:
                d["last"] = {"seq": int(msg.seq), "t_s": msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9,
                             "speed_rpm": msg.speed_rpm, "soc": msg.battery_soc, "end_of_run": bool(msg.end_of_run),
                             "mech_j": msg.energy_mech_in_j, "batt_j": msg.energy_battery_j,
                             "res_j": msg.energy_resistor_j, "loss_j": msg.energy_loss_j,
                             "stored_j": msg.energy_stored_j, "torque_nm": msg.torque_em_nm}
        return cb

    def matched(self, ns: str) -> bool:
        """Is the monitor matched to bike `ns`'s plant (plant_state and its clock)?"""
        return all(sub.get_publisher_count() >= 1 for sub in self.subs[ns])

    def _make_clock_cb(self, ns):
        def cb(_msg):
            self.data[ns]["clock_messages"] += 1
        return cb

    def _on_global_clock(self, _msg):
        self.global_clock_messages += 1

    def _spin(self):
        while not self._stop.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def close(self):
        self._stop.set()
        self.thread.join(timeout=2.0)
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.context)

    def summary(self, ns: str, gear_ratio: float) -> dict:
        d = self.data[ns]
        last = d["last"]
        out = {"bike": ns, "messages": d["messages"], "end_of_run_seen": bool(last and last["end_of_run"]),
               "faults": d["faults"], "clock_messages": d["clock_messages"]}
        if last is None or last["t_s"] <= 0:
            return out
        t = last["t_s"]
        out.update(sim_s=t, final_speed_rpm=last["speed_rpm"], final_cadence_rpm=last["speed_rpm"] / gear_ratio,
                   mean_speed_rpm=d["speed_sum_rpm"] / d["messages"],
                   mean_rider_power_w=last["mech_j"] / t, mean_battery_power_w=last["batt_j"] / t,
                   mean_resistor_power_w=last["res_j"] / t, final_soc=last["soc"],
                   ledger_residual_j=last["mech_j"] - last["batt_j"] - last["res_j"] - last["loss_j"]
                   - last["stored_j"])
        return out


def check_graph_args(n_bikes: int, duration_s: float, timeout_s: float | None = None,
                     placement: dict[str, str] | None = None) -> dict[str, str]:
    """FleetError naming a bad --graph / --seconds / --timeout / --netns before anything starts
    (./bike fleet checks them before it picks the fleet's domain); the placement as a dict."""
    if isinstance(n_bikes, bool) or not isinstance(n_bikes, int) or not 1 <= n_bikes <= 64:
        raise FleetError(f"--graph expects 1..64 bikes, got {n_bikes!r}")
    if not (isinstance(duration_s, (int, float)) and math.isfinite(duration_s) and duration_s > 0):
        raise FleetError(f"--seconds must be a finite number > 0, got {duration_s!r}")   # inf was "must be > 0"
    from bike_plant.config import MAX_SIM_TIME_S
    if duration_s > MAX_SIM_TIME_S:
        # each bike's session refused it once the fleet had started ("fleet graph: FAILED")
        raise FleetError(f"--seconds must be at most {MAX_SIM_TIME_S:g} (the ROS clock's int64 nanoseconds), "
                         f"got {duration_s!r}")
    if timeout_s is not None and not (isinstance(timeout_s, (int, float)) and math.isfinite(timeout_s)
                                      and timeout_s > 0):
        # a timeout <= 0 stopped every bike at once: "FAILED" with no word of the timeout
        raise FleetError(f"--timeout must be a finite number > 0, got {timeout_s!r}")
    placement = dict(placement or {})
    _check_netns(placement, n_bikes)
    return placement


def run_graph(n_bikes: int, config: str, duration_s: float, placement: dict[str, str] | None = None,
              launch_file: str | None = None, timeout_s: float | None = None, out=sys.stdout,
              quiet_nodes: bool = False) -> dict:
    """Start K bikes, wait for every bike to end (or the timeout), return the summaries.
    Keys: bikes (list of per-bike summaries), exit_codes {bike/node: code}, wall_s, ok."""
    from bike_plant.config import load_config

    placement = check_graph_args(n_bikes, duration_s, timeout_s, placement)
    cfg = load_config(config)
    if str(cfg.get("backend", "sim")) != "sim":
        raise FleetError("fleet bikes are simulated: use a config with backend: sim")
    if str(cfg.get("sync_mode", "lockstep")) != "lockstep":
        raise FleetError("the fleet graph runs lockstep (each bike its own sim clock): the config has "
                         f"sync_mode {cfg.get('sync_mode')!r}")
    gear = float((cfg.get("load") or {}).get("gear_ratio", 35.0))
    if launch_file is None:
        from .cli import default_launch_file
        launch_file = str(default_launch_file())
    namespaces = [f"bike{k}" for k in range(1, n_bikes + 1)]
    gate_dir = tempfile.mkdtemp(prefix="bike_fleet_")
    gates = {ns: os.path.join(gate_dir, f"{ns}.go") for ns in namespaces}
    bikes = {ns: bike_specs(launch_file, str(config), duration_s, ns, placement, gates[ns]) for ns in namespaces}
    sink = open(os.devnull, "w") if quiet_nodes else out
    launchers = {ns: L.Launcher(specs, stdout=sink) for ns, specs in bikes.items()}
    monitor = FleetMonitor(namespaces)
    stop_all = threading.Event()

    def request_stop(*_args):
        stop_all.set()
        for la in launchers.values():
            la.request_stop()

    previous = {}
    if threading.current_thread() is threading.main_thread():
        previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    codes: dict[str, int] = {}
    t0 = time.monotonic()
    matched_after: dict[str, float] = {}
    try:
        for la in launchers.values():
            la.start()
        results = {}

        def wait(ns, la):
            results[ns] = la.wait(timeout_s)

        threads = [threading.Thread(target=wait, args=(ns, la), daemon=True) for ns, la in launchers.items()]
        for th in threads:
            th.start()
        # each bike rides (its controller starts) once the monitor is matched to its plant:
        # a short run is otherwise over before discovery across the link has finished
        closed = set(namespaces)
        while closed and any(th.is_alive() for th in threads):
            for ns in list(closed):
                if monitor.matched(ns):
                    pathlib.Path(gates[ns]).touch()
                    closed.discard(ns)
                    matched_after[ns] = time.monotonic() - t0
            time.sleep(0.02)
        for th in threads:
            while th.is_alive():
                th.join(0.2)
        for ns, res in results.items():
            for name, code in res.items():
                codes[f"{name}"] = code
    finally:
        for la in launchers.values():
            if any(p.poll() is None for p in la.procs.values()):
                la.shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        time.sleep(0.2)
        monitor.close()
        shutil.rmtree(gate_dir, ignore_errors=True)
        if quiet_nodes:
            sink.close()
    wall = time.monotonic() - t0
    summaries = [monitor.summary(ns, gear) for ns in namespaces]
    for s in summaries:
        s["placement"] = {spec.name.split("/")[1]: (spec.netns or "root") for spec in bikes[s["bike"]]}
        s["monitor_matched_after_s"] = matched_after.get(s["bike"])
    bad = {name: code for name, code in codes.items() if code not in (0, -signal.SIGINT, 130)}
    ok = (not bad and not stop_all.is_set() and all(s["end_of_run_seen"] for s in summaries)
          and monitor.global_clock_messages == 0)
    return {"bikes": summaries, "exit_codes": codes, "failed_nodes": bad, "wall_s": wall, "ok": ok,
            "duration_s": float(duration_s), "global_clock_messages": monitor.global_clock_messages}


def format_graph(result: dict) -> str:
    lines = [f"fleet graph: {len(result['bikes'])} bikes, {result['duration_s']:g} s simulated each, "
             f"{result['wall_s']:.1f} s wall (start-up included)"]
    lines.append(f"{'bike':<8}{'placement (node@netns)':<44}{'msgs':>6}{'sim s':>7}{'rider W':>9}{'battery W':>10}"
                 f"{'cadence':>9}{'SOC':>8}{'faults':>7}  end")
    for s in result["bikes"]:
        hosts = set(s["placement"].values())
        place = f"all@{hosts.pop()}" if len(hosts) == 1 else ",".join(f"{n}@{h}" for n, h in s["placement"].items())
        if "sim_s" in s:
            lines.append(f"{s['bike']:<8}{place:<44}{s['messages']:>6}{s['sim_s']:>7.2f}{s['mean_rider_power_w']:>9.1f}"
                         f"{s['mean_battery_power_w']:>10.1f}{s['final_cadence_rpm']:>9.1f}{s['final_soc']:>8.4f}"
                         f"{s['faults']:>7}  {'yes' if s['end_of_run_seen'] else 'NO'}")
        else:
            lines.append(f"{s['bike']:<8}{place:<44}{s['messages']:>6}  (no PlantState received)")
    lines.append(f"messages on the global /clock: {result['global_clock_messages']} (each bike's sim time is on "
                 "/bikeK/clock)")
    for name, code in result["failed_nodes"].items():
        lines.append(f"node {name} exited with code {code}")
    lines.append("fleet graph: OK" if result["ok"] else "fleet graph: FAILED")
    return "\n".join(lines)


def _gate(argv: list[str]) -> int:
    """`python -m bike_session.fleet_graph gate FILE -- CMD...`: wait for FILE, then exec CMD
    (same process, so the launcher's signals reach the node)."""
    if len(argv) < 3 or argv[1] != "--":
        print("usage: python -m bike_session.fleet_graph gate FILE -- CMD...", file=sys.stderr)
        return 2
    path, cmd = argv[0], argv[2:]
    deadline = time.monotonic() + GATE_TIMEOUT_S
    while not os.path.exists(path):
        if time.monotonic() > deadline:
            print(f"fleet gate: {path} not opened within {GATE_TIMEOUT_S:g} s; starting anyway", file=sys.stderr)
            break
        time.sleep(0.02)
    os.execv(cmd[0], cmd)
    return 1                                   # not reached


if __name__ == "__main__":
    if sys.argv[1:2] == ["gate"]:
        try:
            sys.exit(_gate(sys.argv[2:]))
        except KeyboardInterrupt:
            sys.exit(130)
    print("usage: python -m bike_session.fleet_graph gate FILE -- CMD... (used by ./bike fleet --graph)",
          file=sys.stderr)
    sys.exit(2)
