"""The Fast DDS 2.14 stale shared-memory port (bike_plant.shm_ports): a reader killed with
SIGKILL in a microsecond window of its listener leaves the writers on its old segment, and the
reader started next, which takes the same port, hears nothing (eProsima/Fast-DDS #5053; README,
reliability table). Checked here: the signature finder, the premise (a restarted reader takes
the killed one's ports), the failure on demand, and the guard experiment of the repro tool."""
from __future__ import annotations

import fcntl
import os
import pathlib
import subprocess
import sys
import time

import pytest
from node_harness import domain, printed, tool_module  # noqa: F401

from bike_plant import shm_ports

REPRO = pathlib.Path(__file__).resolve().parents[1] / "tools" / "shm_stale_port_repro.py"


def _maps(proc, pid, *ports, deleted=False):
    (proc / str(pid)).mkdir()
    tail = " (deleted)" if deleted else ""
    (proc / str(pid) / "maps").write_text("".join(
        f"7f00{i:08x}-7f01{i:08x} rw-s 00000000 00:1a 123 /dev/shm/fastrtps_port{p}{tail}\n"
        for i, p in enumerate(ports)) + "7f0200000000-7f0300000000 r-xp 00000000 00:1a 9 /usr/lib/libc.so.6\n")


def _locked_elsewhere(path) -> bool:
    """What Fast DDS's RobustExclusiveLock finds: flock on a new open file description."""
    fd = os.open(path, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)
    return False


def _release_held():
    """Let go of the locks shm_ports.hold_ports took in this (test) process."""
    for fd in shm_ports._held.values():
        os.close(fd)
    shm_ports._held.clear()


def test_writers_to_deleted_segments_are_named(tmp_path):
    """The controller's silent-writer warning names the processes that write to a deleted
    segment of its own ports (the failure itself)."""
    _maps(tmp_path, 4242, 7411, 7413, deleted=True)
    _maps(tmp_path, 4243, 7411)                  # the current segment: fine
    assert shm_ports.writers_to_deleted([7411, 7415], str(tmp_path)) == {7411: [4242]}
    assert shm_ports.writers_to_deleted([], str(tmp_path)) == {}


def test_the_stale_port_check_says_who_and_starts_over_once(tmp_path, monkeypatch):
    """What the controller, the plant and the session ask when nothing comes: the writers to a
    deleted segment of their ports, named, and a start over only while the process has not
    started over yet (it then holds its old ports)."""
    monkeypatch.setattr(shm_ports, "own_ports", lambda: [7411, 7413])
    _maps(tmp_path, 4242, 7411, deleted=True)
    _maps(tmp_path, 4243, 7413)
    why, start_over = shm_ports.stale_port_check(str(tmp_path))
    assert start_over and "pid(s) 4242 still write to a deleted segment of this node's shared-memory port 7411" in why
    assert "7413" not in why and "Fast-DDS #5053" in why
    monkeypatch.setitem(shm_ports._held, 7400, -1)          # started over once already
    assert shm_ports.stale_port_check(str(tmp_path))[1] is False
    monkeypatch.setattr(shm_ports, "own_ports", lambda: [7413])
    assert shm_ports.stale_port_check(str(tmp_path)) == ("", False)


def test_the_stale_port_watch_looks_every_period_from_its_start(monkeypatch):
    """The plant, session, recorder and (no writer matched) controller look for the signature
    once per period from their start, and start over only when stale_port_check says so."""
    looks = []
    answers = iter([("", False), ("pid(s) 4242 still write ...", True)])
    monkeypatch.setattr(shm_ports, "stale_port_check", lambda: looks.append(1) or next(answers))
    watch = shm_ports.StalePortWatch(3.0)
    assert watch.start_over(100.0) == "" and not looks          # the first call starts the clock
    assert watch.start_over(102.9) == "" and not looks
    assert watch.start_over(103.0) == "" and len(looks) == 1    # looked: nothing stale
    assert watch.start_over(105.0) == "" and len(looks) == 1
    assert watch.start_over(106.0) == "pid(s) 4242 still write ..." and len(looks) == 2
    assert watch.waited_s(106.0) == 6.0
    started = shm_ports.StalePortWatch(3.0, since=50.0)
    assert started.start_over(52.0) == "" and len(looks) == 2


def test_the_stale_peer_watch_starts_over_at_two_looks_in_a_row_once_and_stops_looking(monkeypatch):
    """Running nodes (session, controller): a stale writer seen once is a watchdog still to
    re-open the port; seen at two looks in a row it is named and the node starts over, once.
    Clean looks end the watch after ``looks``; a look that found one keeps it going."""
    stale, clean = ("pid(s) 4242 still write ...", True), ("", False)
    answers = iter([stale, clean, stale, stale])
    monkeypatch.setattr(shm_ports, "stale_port_check", lambda: next(answers))
    watch = shm_ports.StalePeerWatch(looks=3, period_s=3.0, since=0.0)
    assert watch.look(2.0) == "" and watch.done == 0                  # not due
    assert watch.look(3.0) == "" and watch.in_a_row == 1               # once: not yet
    assert watch.look(6.0) == "" and watch.in_a_row == 0               # healed by its watchdog
    assert watch.look(9.0) == "" and watch.done == 3                   # its looks are over, but ...
    assert not watch.finished                                          # ... the last one found one
    assert watch.look(12.0) == "pid(s) 4242 still write ..., 3s after it was first seen"
    assert watch.finished and watch.look(15.0) == ""                   # said once
    clean = iter([("", False)] * 3)
    monkeypatch.setattr(shm_ports, "stale_port_check", lambda: next(clean))
    quiet = shm_ports.StalePeerWatch(looks=2, period_s=3.0, since=0.0)
    assert quiet.look(3.0) == quiet.look(6.0) == "" and quiet.finished
    assert quiet.look(9.0) == "" and quiet.done == 2                   # no look after its last


def test_the_repro_tools_guard_holds_only_zombie_ports_a_live_process_maps(tmp_path):
    tool = tool_module("shm_stale_port_repro")
    shm, proc = tmp_path / "shm", tmp_path / "proc"
    shm.mkdir()
    proc.mkdir()
    for port in (7411, 7413, 7415):
        (shm / f"fastrtps_port{port}").write_bytes(b"\0" * 64)
        (shm / f"fastrtps_port{port}_el").write_bytes(b"")
    _maps(proc, 4242, 7411)                       # a live writer still maps 7411
    holder = subprocess.Popen([sys.executable, "-c",     # 7415's owner is alive and holds its lock
                               "import fcntl, os, sys, time; fd = os.open(sys.argv[1], os.O_RDONLY); "
                               "fcntl.flock(fd, fcntl.LOCK_EX); print('locked', flush=True); time.sleep(60)",
                               str(shm / "fastrtps_port7415_el")], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        assert tool.hold_stale_ports(str(shm), str(proc)) == [7411]
        assert _locked_elsewhere(shm / "fastrtps_port7411_el")       # a participant moves on
        assert not _locked_elsewhere(shm / "fastrtps_port7413_el")   # nobody maps it: let go
    finally:
        _release_held()
        holder.kill()
        holder.wait()


@pytest.mark.faults
def test_a_reader_restarted_after_kill_9_takes_the_killed_ones_ports(domain, monkeypatch):
    """The premise, real DDS: a reader started after one killed with SIGKILL listens on exactly
    the killed one's shared-memory ports (Fast DDS gives a participant the lowest port whose
    lock nobody holds), and own_ports() sees them. (The repro tool's writer and readers.)"""
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    tool = tool_module("shm_stale_port_repro")
    nodes = [tool._Proc("writer")]
    try:
        first = tool._Proc("reader")
        nodes.append(first)
        assert first.heard(20.0), first.out[-20:]
        ports1 = shm_ports.own_ports(first.p.pid)
        assert ports1, "the reader listens on shared-memory ports (rmw_fastrtps, LOCALHOST)"
        first.stop()                                      # SIGKILL
        time.sleep(0.5)
        second = tool._Proc("reader")
        nodes.append(second)
        assert second.heard(20.0), second.out[-20:]
        assert shm_ports.own_ports(second.p.pid) == ports1
    finally:
        for n in nodes:
            n.stop()


@pytest.mark.faults
def test_the_stale_port_failure_on_demand(domain):
    """tools/shm_stale_port_repro.py kills a reader in the microseconds its listener is in use
    but neither waiting nor processing (which the full suite hit about once in 10 runs): the
    reader started after it hears nothing while the writer maps a deleted segment. This is
    Fast DDS 2.14's failure, not ours; if an update fixes it, this test fails and says so."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    # exit 2: the window was not caught (a loaded host); exit 0: about 1 kill in 10 in the
    # window still leaves the writer on the live segment. Either way the premise did not
    # happen: up to 3 attempts (a fixed Fast DDS would hear in every one). A reader that is not
    # deaf hears the writer ~1-2 s after its start (its imports; participants announce every
    # 0.5 s, config/fastdds.xml): 5 s to hear it, the writer's map of a deleted segment beside
    for _attempt in range(3):
        run = subprocess.run([sys.executable, str(REPRO), "--wait-s", "5"], env=env, capture_output=True,
                             text=True, timeout=240)
        if run.returncode == 1:
            break
    assert run.returncode == 1, run.stdout + run.stderr[-2000:]
    assert "second reader on ports" in run.stdout and "DEAF for 5 s" in run.stdout, run.stdout
    assert "writer maps deleted port segments ['" in run.stdout, run.stdout


def test_hold_ports_keeps_a_participant_off_them(tmp_path):
    """bike_plant.loop.start_over_on_fresh_ports holds its old ports' locks: Fast DDS's flock on them
    fails (so no later participant inherits the stale port), own_ports() leaves them out, and
    a lock file the old participant removed at its clean exit is made again."""
    (tmp_path / "fastrtps_port7411_el").write_bytes(b"")
    try:
        assert shm_ports.hold_ports([7411, 7413], str(tmp_path)) == [7411, 7413]
        assert _locked_elsewhere(tmp_path / "fastrtps_port7411_el")
        assert _locked_elsewhere(tmp_path / "fastrtps_port7413_el")
        assert shm_ports.held_ports() == [7411, 7413]
        assert not set(shm_ports.own_ports()) & {7411, 7413}
    finally:
        _release_held()


def test_a_ctrl_c_while_a_node_starts_over_is_not_lost(domain, tmp_path):
    """run_loop_node with real rclpy nodes: a Ctrl-C that lands while the new node is made
    (bike_plant.loop.start_over_on_fresh_ports) goes to the old node's handler; the new node stops at
    once instead of running on."""
    script = tmp_path / "node.py"
    script.write_text(
        "import os, signal, sys, time\n"
        "from rclpy.executors import SingleThreadedExecutor\n"
        "from rclpy.node import Node\n"
        "from bike_plant import node as bn\n"
        "made = []\n"
        "class Fake(Node):\n"
        "    def __init__(self, **kwargs):\n"
        "        super().__init__('fake', **kwargs)\n"
        "        self.executor_ = SingleThreadedExecutor(context=self.context)\n"
        "        self.executor_.add_node(self)\n"
        "        self.stop_requested = False\n"
        "        made.append(self)\n"
        "        if len(made) == 2:\n"
        "            os.kill(os.getpid(), signal.SIGINT)   # while the new node is made\n"
        "    def run(self):\n"
        "        if len(made) == 1:\n"
        "            self.fresh_ports_wanted = True\n"
        "            return 0\n"
        "        t0 = time.monotonic()\n"
        "        while not self.stop_requested and time.monotonic() - t0 < 5.0:\n"
        "            time.sleep(0.01)\n"
        "        print('stopped' if self.stop_requested else 'ran on', flush=True)\n"
        "        return 3\n"
        "sys.exit(bn.run_loop_node(Fake, 'fake'))\n")
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    out = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 3 and printed(out.stdout) == ["stopped"], (out.returncode, out.stdout, out.stderr[-2000:])


def test_a_lockstep_plant_that_finds_a_stale_port_before_its_first_state_starts_over(ros_domain):
    """A lockstep plant looks for a stale shared-memory port (Fast DDS's, see above) while it
    still waits for the controller's and the recorder's match, before it has published a
    state. Its diagnostic there read the last state's snapshot, which did not exist yet:
    AttributeError, plant exit 1, in the middle of a kill -9 test on a loaded host (CI,
    2026-12-07). Now it says so and asks for fresh ports as after its first state. (The stale
    port is stood in for: the real one takes a kill in a microsecond window, see
    test_nodes_realtime.)"""
    import rclpy
    from rclpy.context import Context

    from bike_plant.node import PlantNode

    class StalePort:                  # what StalePortWatch finds on a stale port, at once
        def start_over(self):
            return "pid(s) 4242 still write to a deleted segment of this node's shared-memory port 7003"

        def waited_s(self):
            return 7.0

    ctx = Context()
    rclpy.init(context=ctx, domain_id=ros_domain)
    try:
        plant = PlantNode(context=ctx)
        plant.deaf_watch = StalePort()
        assert plant._check_deaf_start() is True
        assert plant.fresh_ports_wanted and plant.stop_requested
        assert "pid(s) 4242 still write to a deleted segment" in plant.wait_reason
        plant.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
