"""Shared test helpers: isolated DDS domains and real node processes; the SPMSM paper-bench config."""
from __future__ import annotations

import faulthandler
import os
import pathlib
import random
import signal
import subprocess
import sys
import time

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
DEFAULT_CONFIG = ROOT / "config" / "bldc_default.yaml"
LAUNCH_FILE = ROOT / "config" / "launch" / "bike.launch.yaml"
SPMSM_CONFIG = ROOT / "config" / "spmsm_default.yaml"

# `bike run` options of the long graph rides whose subject is a session feature (shifting, the
# spin-down, the heart-rate ERG, replay, ...), not the batch exchange: 5 ms batches, not 1 ms.
# A lockstep graph is bound by its DDS round trip per batch, so a ride runs about 3x faster (the
# shifting ride: 34 s -> 11 s). The batched loop is exact for any N (test_batched_loop); the
# default N is ridden by the demo graph, the lockstep, fault and launcher tests.
FAST_BATCHES = ("--set", "batch_periods=100")


def spmsm_paper_config() -> dict:
    """spmsm_default.yaml as the paper's test bench (paper 001, section 6), not the bike: the
    printed Rs = 6.84 ohm (the default config reads it as 0.684 ohm, see its comment; the
    cases that need that set it explicitly), dynamometer load, shaft at rest."""
    from bike_plant.config import load_config
    c = load_config(SPMSM_CONFIG)
    assert c["spmsm"]["rs_ohm"] == 0.684
    c["spmsm"]["rs_ohm"] = 6.84
    c["load"]["kind"] = "dynamometer"
    c["mechanics"]["speed0_rpm"] = 0.0
    return c


# A test stuck inside C code that holds the GIL (rclpy's publish blocked in Fast DDS: seen in
# CI, a writer mutex held by a thread spinning on a half-made shared-memory segment) never lets
# pytest-timeout's handler run, and the run would sit until CI's own limit. faulthandler's
# timer runs in a C thread without the GIL: past HANG_S it prints every thread's Python stack
# and ends the run (exit 1). pytest-timeout (300 s, pytest.ini) still handles ordinary hangs.
# The stacks go to the runner's own stderr, not to the test's captured one (lost at the exit).
HANG_S = float(os.environ.get("BIKE_TEST_HANG_S", "600"))
_hang_fd = [2]


@pytest.fixture(autouse=True)
def _hang_watchdog():
    faulthandler.dump_traceback_later(HANG_S, exit=True, file=_hang_fd[0])
    yield
    faulthandler.cancel_dump_traceback_later()


def _runner_stderr_fd(config) -> int:
    """A copy of the stderr the runner had before pytest captured it (fd 2 if not captured)."""
    capman = config.pluginmanager.getplugin("capturemanager")
    err = getattr(getattr(capman, "_global_capturing", None), "err", None)
    return os.dup(getattr(err, "targetfd_save", 2))


def pytest_configure(config):
    """A runner started as a background job of a script (`make test &` in a non-interactive
    shell, some CI agents) inherits SIGINT ignored, and every process the tests start would
    too: the Ctrl-C tests and the nodes' stop on SIGINT would fail on the environment, not on
    the code. Give SIGINT its default meaning (a caught signal is reset to the default in a
    child at exec; an ignored one stays ignored)."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    _hang_fd[0] = _runner_stderr_fd(config)


@pytest.fixture(scope="session", autouse=True)
def node_log_dir(tmp_path_factory):
    """Node processes started by the tests log here (node_harness.log_file), not loose in /tmp."""
    path = tmp_path_factory.mktemp("node-logs")
    os.environ["BIKE_TEST_LOG_DIR"] = str(path)
    yield path
    os.environ.pop("BIKE_TEST_LOG_DIR", None)


@pytest.fixture
def ros_domain(monkeypatch):
    """A DDS domain of its own for this test (locked against other runs on this host, see
    bike_session.domains), discovery limited to this host."""
    from bike_session import domains
    domain = domains.claim()
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    yield domain
    domains.release(domain)


def bike_command(*args: str, timeout: float = 240, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run `python -m bike_session.cli ARGS` (what ./bike does inside the environment).

    On timeout the CLI gets SIGINT (its launcher then stops every node it started, which
    run in their own sessions and would outlive a SIGKILL of the CLI), and the test fails
    with what the run printed so far."""
    proc = subprocess.Popen([sys.executable, "-m", "bike_session.cli", *args], cwd=ROOT,
                            env=env or os.environ.copy(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
        raise AssertionError(f"`bike {' '.join(args)}` did not finish within {timeout} s\n"
                             f"--- stdout (tail):\n{out[-6000:]}\n--- stderr (tail):\n{err[-3000:]}") from None
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


_FRONT_DOOR_USED: set[str] = set()      # the test functions whose first ./bike_cli call started ./bike


@pytest.fixture
def bike_cli(request):
    """`./bike ARGS` of an input the CLI refuses before it starts anything (a node, a connection, a
    measurement): a CompletedProcess. The first call of each test function (of its first parameter
    set that runs) starts ./bike itself, in a subprocess; the others call bike_session.cli.main, the
    code ./bike runs, in this process, their output captured at the file descriptors (capfd), its
    return or SystemExit taken as the exit status: a ./bike start is 0.6-1.5 s on a loaded 2-core
    host. In this process a refusal that came too late fails the test: the launcher, the domain claim
    and rclpy.init raise."""
    from bike_session import cli, domains, launcher

    def started(*_args, **_kwargs):
        raise AssertionError("the refused input got as far as starting a run")

    def run(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
        domain = str(random.randint(101, 200))
        if request.node.originalname not in _FRONT_DOOR_USED:
            _FRONT_DOOR_USED.add(request.node.originalname)
            return subprocess.run([str(ROOT / "bike"), *args], capture_output=True, text=True, timeout=timeout,
                                  env=dict(os.environ, ROS_DOMAIN_ID=domain))
        import rclpy
        capfd = request.getfixturevalue("capfd")
        with pytest.MonkeyPatch.context() as patched:
            patched.setenv("ROS_DOMAIN_ID", domain)
            for module, name in ((launcher, "run"), (domains, "ensure_private_domain"), (rclpy, "init")):
                patched.setattr(module, name, started)
            capfd.readouterr()
            try:
                code = cli.main(list(args))
            except SystemExit as exc:       # argparse's usage errors (as python does at its exit)
                code = exc.code
                if code is not None and not isinstance(code, int):
                    print(code, file=sys.stderr)
                    code = 1
            out = capfd.readouterr()
        return subprocess.CompletedProcess(["cli.main (in this process)", *args], code or 0, out.out, out.err)
    return run


class NodeProcess:
    """One node executable in its own process group, output captured to a file."""

    def __init__(self, pkg: str, exe: str, args: list[str], log_dir: pathlib.Path):
        from bike_session.launcher import executable_path

        self.log_path = log_dir / f"{exe}.log"
        self._log = open(self.log_path, "w")
        self.proc = subprocess.Popen([executable_path(pkg, exe), *args], stdout=self._log, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, start_new_session=True)
        self._interrupted = False

    @property
    def pid(self) -> int:
        return self.proc.pid

    def output(self) -> str:
        self._log.flush()
        return self.log_path.read_text()

    def kill9(self) -> None:
        os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait()

    def interrupt(self) -> None:
        """SIGINT, once (stop() then only waits): several nodes stopping at once overlap."""
        if self.proc.poll() is None and not self._interrupted:
            self._interrupted = True
            os.killpg(self.proc.pid, signal.SIGINT)

    def stop(self, timeout: float = 10.0) -> int:
        if self.proc.poll() is None:
            self.interrupt()
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self._log.close()
        return self.proc.returncode

    def wait(self, timeout: float) -> int:
        return self.proc.wait(timeout)


def mean_erg_power_w(states, config: pathlib.Path | str = ROOT / "config" / "bldc_default.yaml") -> float:
    """Mean of the power ERG holds, the rider's (braking -T_em w + the bike's friction of
    ``config``, bike_controller.modes.erg_power_w), over PlantStates (messages, or the arrays
    of bags.plant_state_array)."""
    import numpy as np

    from bike_controller.modes import erg_power_w, friction_figures
    from bike_plant.config import load_config
    friction = friction_figures(load_config(config))
    if isinstance(states, (list, tuple)):
        tem = np.array([m.torque_em_nm for m in states])
        w = np.array([m.speed_rad_s for m in states])
    else:
        tem, w = states["torque_em_nm"], states["speed_rad_s"]
    return float(np.mean(erg_power_w(tem, w, friction)))


def ros_parameters_of(ros_args: list[str], names) -> dict:
    """The values a real rclpy node started with ``ros_args`` (``--ros-args ...``) gets for the
    parameters ``names`` (rcl's own parsing of params files and -p overrides; arrays as lists)."""
    import rclpy
    from rclpy.node import Node

    context = rclpy.Context()
    rclpy.init(args=ros_args, context=context)
    try:
        node = Node("parameters_of", context=context, automatically_declare_parameters_from_overrides=True)
        got = {name: node.get_parameter(name).value for name in names}
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
    return {name: list(value) if not isinstance(value, (str, bytes)) and hasattr(value, "__len__") else value
            for name, value in got.items()}


def wait_for(predicate, timeout_s: float, interval_s: float = 0.05) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(interval_s)
    return predicate()


def _ip(*args: str, netns: str | None = None) -> None:
    cmd = (["ip", "netns", "exec", netns, "ip"] if netns else ["ip"]) + list(args)
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        pytest.fail(f"`{' '.join(cmd)}` failed ({res.returncode}): {res.stderr.strip()} -- this test needs "
                    "root and network namespaces (ip netns + veth); it must not be skipped", pytrace=False)


@pytest.fixture
def host_b():
    """Network namespace 'host B' joined to this one ('host A') by a veth pair, 10.x.y.1 <-> 10.x.y.2
    (test_fleet_graph's bikes, test_ftms's two mDNS responders)."""
    tag = f"{os.getpid() % 100000}{random.randint(0, 99):02d}"
    ns, dev_a, dev_b = f"flb{tag}", f"fla{tag}", f"flc{tag}"
    subnet = f"10.{random.randint(100, 250)}.{random.randint(0, 250)}"
    created = []
    try:
        _ip("netns", "add", ns)
        created.append("ns")
        _ip("link", "add", dev_a, "type", "veth", "peer", "name", dev_b)
        created.append("veth")
        _ip("link", "set", dev_b, "netns", ns)
        _ip("addr", "add", f"{subnet}.1/24", "dev", dev_a)
        _ip("link", "set", dev_a, "up")
        _ip("addr", "add", f"{subnet}.2/24", "dev", dev_b, netns=ns)
        _ip("link", "set", dev_b, "up", netns=ns)
        _ip("link", "set", "lo", "up", netns=ns)
        yield {"netns": ns, "dev_a": dev_a, "addr_a": f"{subnet}.1", "addr_b": f"{subnet}.2"}
    finally:
        if "veth" in created:
            subprocess.run(["ip", "link", "del", dev_a], capture_output=True)
        if "ns" in created:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
    assert not os.path.exists(f"/run/netns/{ns}"), "the test's network namespace was not removed"
