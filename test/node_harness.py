"""Helpers for the tests that start real node processes (test_nodes_*.py).

Each test gets its own ROS_DOMAIN_ID (locked by bike_session.domains) and discovery limited to localhost;
nodes run as separate OS processes (the installed console scripts), the test talks to
them through its own rclpy context on the same domain.
"""
from __future__ import annotations

import os
import pathlib
import re
import signal
import subprocess
import tempfile
import threading
import time

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config" / "bldc_default.yaml"
# wait_for: after a watched process exits, how long its last messages may take to be read here
EXIT_GRACE_S = 2.0


def log_file(prefix: str):
    """An open log file for a node process's output, named after the node, in the directory
    conftest sets for this pytest run (BIKE_TEST_LOG_DIR, under pytest's basetemp: pytest keeps
    the last three runs' and deletes older ones). Logs of failed tests stay readable, and the
    host's /tmp no longer fills with them (~600 files after a few suite runs)."""
    return tempfile.NamedTemporaryFile("w+", prefix=f"{prefix}-", suffix=".log", delete=False,
                                       dir=os.environ.get("BIKE_TEST_LOG_DIR") or None)

rclpy = pytest.importorskip("rclpy")
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile  # noqa: E402


def executable(pkg: str, exe: str) -> str:
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix

    try:
        path = os.path.join(get_package_prefix(pkg), "lib", pkg, exe)
    except PackageNotFoundError:
        pytest.skip(f"package {pkg} not built / sourced (source tools/env.sh)")
    if not os.access(path, os.X_OK):
        pytest.skip(f"{path} not installed (colcon build)")
    return path


class NodeProcess:
    """One node as an OS process (own process group), output captured to a file."""

    # a node started through bike_plant.entry prints every thread's stack on SIGUSR1
    dumps_stacks = True

    def __init__(self, pkg: str, exe: str, domain: int, params: dict | None = None, ns: str = "/bike",
                 remaps: dict | None = None, config: pathlib.Path | None = None):
        args = [executable(pkg, exe), "--ros-args", "-r", f"__ns:={ns}"]
        for old, new in (remaps or {}).items():
            args += ["-r", f"{old}:={new}"]
        args += ["--params-file", str(config or CONFIG)]
        if config is not None:
            args += ["-p", f"config_path:={config}"]      # the defaults of the parameters it does not set
        for key, value in (params or {}).items():
            args += ["-p", f"{key}:={value}"]
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                   BIKE_ROOT=str(ROOT), PYTHONUNBUFFERED="1")
        self.log = log_file(exe)
        self.name = exe
        self.proc = subprocess.Popen(args, stdout=self.log, stderr=subprocess.STDOUT, env=env, cwd=str(ROOT),
                                     start_new_session=True)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def output(self) -> str:
        self.log.flush()
        return pathlib.Path(self.log.name).read_text(errors="replace")

    def wait(self, timeout: float) -> int | None:
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def signal(self, sig: int) -> None:
        if self.alive():
            os.killpg(self.proc.pid, sig)

    def stacks(self) -> str:
        """Every thread's Python stack as the node prints it now (SIGUSR1, bike_plant.entry);
        '' when it has exited or prints none. For a failure message: where a quiet node is."""
        if not (self.dumps_stacks and self.alive()):
            return ""
        before = len(self.output())
        os.kill(self.proc.pid, signal.SIGUSR1)
        time.sleep(0.5)
        return self.output()[before:]

    def stop(self, timeout: float = 5.0) -> int | None:
        """SIGINT, then SIGKILL if it does not end within ``timeout``; returns the exit code."""
        if self.alive():
            self.signal(signal.SIGINT)
            if self.wait(timeout) is None:
                self.signal(signal.SIGKILL)
                self.wait(5.0)
                return None
        return self.proc.returncode


def stop_all(procs, timeout: float = 5.0) -> list[int | None]:
    """NodeProcess.stop for several nodes at once: SIGINT to every one first, then each is
    waited for up to ``timeout`` from that signal (SIGKILL after it), so that their shutdowns
    (~0.4 s each, seconds on a loaded host) overlap instead of adding up. Returns each one's
    exit code as stop() does (None: it had to be killed)."""
    procs = list(procs)
    for p in procs:
        p.signal(signal.SIGINT)
    end = time.monotonic() + timeout
    codes = []
    for p in procs:
        if p.wait(max(0.0, end - time.monotonic())) is None:
            p.signal(signal.SIGKILL)
            p.wait(5.0)
            codes.append(None)
        else:
            codes.append(p.proc.returncode)
    return codes


def _writers_to_deleted_ports_of(pid: int) -> dict:
    """{port: [pid, ...]} of live processes, this test's included, that map a deleted segment
    of one of ``pid``'s shared-memory ports ({} when it has none or is gone)."""
    from bike_plant import shm_ports
    try:
        ports = shm_ports.own_ports(pid)
        found = shm_ports.writers_to_deleted(ports)
        with open(f"/proc/{os.getpid()}/maps", "rb") as f:
            mine = f.read()
    except OSError:
        return {}
    for port in ports:
        if f"/fastrtps_port{port} (deleted)".encode() in mine:
            found.setdefault(port, []).append(os.getpid())
    return found


class Collector:
    """The test's own node: records what the bike publishes, publishes what the test needs."""

    def __init__(self, domain: int, topics: dict, ns: str = "/bike"):
        from bike_plant.loop import AUX_QOS, LOOP_QOS

        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = Node("test_collector", namespace=ns, context=self.context)
        self.data: dict[str, list] = {}
        self.stamps: dict[str, list] = {}
        self.subs = {}
        self.callbacks: dict[str, object] = {}
        for topic, msg_type in topics.items():
            self.data[topic] = []
            self.stamps[topic] = []
            qos = AUX_QOS if topic in ("/diagnostics", "battery", "session_status") else LOOP_QOS
            # the test is not in the loop (no flow control): a deep reader queue so that a
            # busy test process never loses a message the plant sent
            qos = QoSProfile(history=qos.history, depth=10000, reliability=qos.reliability, durability=qos.durability)
            if topic == "session_status":
                # the session keeps its last 100 statuses (transient local): a reader matched
                # seconds late (seen: after a plant restart) still gets the run's first ones
                qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
            self.subs[topic] = self.node.create_subscription(msg_type, topic, self._cb(topic), qos)
        self.loop_qos = LOOP_QOS
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        # every subscription taken straight from one wait set, as the loop nodes take theirs:
        # the executor's ~150 us of Python per message left this reader at ~50 states/s of a
        # realtime plant's 1000 beside two CPU hogs (seconds behind; three tests failed on it)
        from bike_plant.loop import HotWait
        self.hot = HotWait(self.executor, list(self.subs.values()), self.context)
        self._stop = False
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _cb(self, topic):
        def callback(msg):
            self.data[topic].append(msg)
            self.stamps[topic].append(time.monotonic())
            hook = self.callbacks.get(topic)
            if hook is not None:
                hook(msg)
        return callback

    def _spin(self):
        while not self._stop and self.context.ok():
            try:
                self.hot.spin(0.05)
            except (Exception, KeyboardInterrupt):  # context shut down under us (HotWait: as a Ctrl-C)
                break

    def reads_from(self, topic: str, node_name: str) -> bool:
        """This reader of ``topic`` has matched the writer of node ``node_name`` (and every
        writer the graph lists: the graph can list one before DDS matched it). On a starved
        machine discovery takes seconds, and a volatile writer's samples sent before the match
        never arrive."""
        infos = self.node.get_publishers_info_by_topic(self.node.resolve_topic_name(topic))
        return (any(i.node_name == node_name for i in infos)
                and self.subs[topic].get_publisher_count() >= len(infos))

    def publisher(self, msg_type, topic):
        return self.node.create_publisher(msg_type, topic, self.loop_qos)

    def wait_for(self, predicate, timeout: float, what: str = "condition", procs=()) -> None:
        end = time.monotonic() + timeout
        exited = None
        while time.monotonic() < end:
            if predicate():
                return
            if exited is None:
                exited = next((p for p in procs if not p.alive()), None)
                if exited is not None:
                    # its last messages (an end_of_run) can still be on their way to this process,
                    # which a loaded host delays (seen: a plant's normal exit, its end_of_run not yet read)
                    end = min(end, time.monotonic() + EXIT_GRACE_S)
            time.sleep(0.01)
        if exited is not None:
            raise AssertionError(f"{exited.name} exited ({exited.proc.returncode}) while waiting for {what}:\n"
                                 f"{exited.output()}")
        logs = []
        for p in procs:
            logs.append(f"--- {p.name}:\n{p.output()[-3000:]}")
            stale = _writers_to_deleted_ports_of(p.pid)
            if stale:
                logs.append(f"--- {p.name}: live processes still write to deleted segments of its shared-memory "
                            f"ports (Fast DDS stale port, bike_plant.shm_ports; this test is pid {os.getpid()}): "
                            f"{stale}")
            stacks = p.stacks()
            if stacks:
                logs.append(f"--- {p.name}, its threads at the timeout:\n{stacks[-6000:]}")
        logs = "\n".join(logs)
        raise AssertionError(f"timeout ({timeout}s) waiting for {what}\n{logs}")

    def close(self):
        self._stop = True
        self.thread.join(2.0)
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture
def domain():
    """A DDS domain locked against other runs on this host (bike_session.domains)."""
    from bike_session import domains
    d = domains.claim()
    yield d
    domains.release(d)


def tool_module(name: str):
    """tools/<name>.py as a module (the tools are scripts, not a package)."""
    import importlib.util
    spec = importlib.util.spec_from_file_location(name, ROOT / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_FAST_DDS_LOG = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d+ \[\w+ (Error|Warning|Info)\] ")
_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def printed(stdout: str) -> list[str]:
    """The lines a process with DDS participants printed itself: its stdout without Fast
    DDS's own log lines, which Fast DDS 2.14 writes to stdout, e.g. "[RTPS_TRANSPORT_SHM Error]
    Failed init_port fastrtps_port<N>: open_and_lock_file failed" when a participant tried a
    shared-memory port whose lock another process on this host holds (a node that started over
    on fresh ports keeps its old ones, bike_plant.shm_ports.hold_ports; or a participant that
    took the port first). That depends on what else runs on the host: under load, with other
    tests' nodes, it came before a test script's own line."""
    return [line for line in stdout.splitlines() if not _FAST_DDS_LOG.match(_ANSI.sub("", line))]


def stamp_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def publish_wall_times(states, received) -> list[float]:
    """Wall time (time.monotonic()) at which the plant published each state: its sim stamp plus
    the smallest (receipt - stamp) over this and every later state. Late receipt (a test
    process that lags and then gets a burst) only adds to that difference; a realtime plant
    that resynchronises after an overrun adds to it for good, hence the minimum over the
    states that follow, not over all."""
    import numpy as np
    offsets = np.array([r - stamp_ns(m.header.stamp) * 1e-9 for m, r in zip(states, received)])
    suffix_min = np.minimum.accumulate(offsets[::-1])[::-1]
    return [stamp_ns(m.header.stamp) * 1e-9 + float(o) for m, o in zip(states, suffix_min)]
