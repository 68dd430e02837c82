"""Session node + recorder node as real OS processes over DDS, driven by a test clock/plant.

The test process plays the plant: it publishes /clock and PlantState (plus one message on
every other bike topic), the session node answers with its Command timeline and the
recorder writes the MCAP bag. Then the bag must hold every topic, decode with an EMPTY
typestore (rosbags) and with mcap_ros2, carry sim-time log times, and the Command
timeline must match the profile.
"""
from __future__ import annotations

import contextlib

import json
import os
import pathlib
import signal
import subprocess
import time

import pytest

from conftest import wait_for

ROOT = pathlib.Path(__file__).resolve().parents[1]
LIB = ROOT / "install" / "bike_session" / "lib" / "bike_session"
NS = "/bike"
PERIOD = 0.1
DURATION = 1.0
STEP_NS = 10_000_000        # test plant: one PlantState per 10 ms of sim time
PROFILE = """name: unit_profile
segments:
  - {kind: ramp, duration_s: 0.5, start: 0.0, end: 1.0, label: up}
  - {kind: step, duration_s: 0.3, command: 0.5, mode: motoring, label: push}
  - {kind: step, duration_s: 0.5, command: 0.25, label: tail}
"""
CONFIG = """/**:
  ros__parameters:
    use_sim_time: true
    plant_seed: 42
    duration_s: 1.0
    session:
      profile: unit_profile.yaml
      period_s: 0.1
"""


class Proc:
    def __init__(self, exe: str, args: list[str], log_dir: pathlib.Path):
        self.log_path = log_dir / f"{exe}.log"
        self.err_path = log_dir / f"{exe}.err"
        self._out = open(self.log_path, "w")
        self._err = open(self.err_path, "w")
        self.proc = subprocess.Popen([str(LIB / exe), "--ros-args", "-r", f"__ns:={NS}", *args],
                                     stdout=self._out, stderr=self._err, stdin=subprocess.DEVNULL,
                                     start_new_session=True, env=os.environ.copy())

    def out(self) -> str:
        self._out.flush()
        return self.log_path.read_text()

    def err(self) -> str:
        self._err.flush()
        return self.err_path.read_text()

    def signal(self, sig=signal.SIGINT) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, sig)

    def wait(self, timeout: float) -> int:
        try:
            return self.proc.wait(timeout)
        finally:
            self._out.flush()
            self._err.flush()

    def kill(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        self._out.close()
        self._err.close()


@pytest.fixture
def procs():
    started: list[Proc] = []
    yield started
    for p in started:
        p.kill()


def _expected_commands():
    """(stamp_ns, command, mode) the session must publish for PROFILE / PERIOD / DURATION."""
    from bike_session.profiles import parse_profile_text

    prof = parse_profile_text(PROFILE)
    out = []
    # the clock reaches DURATION: tau_j <= DURATION + PERIOD (12 values) plus the final 0
    for j in range(13):
        tau_ns = j * 100_000_000
        cmd, mode, _, _ = prof.command_at(tau_ns * 1e-9)
        if tau_ns >= 1_000_000_000:
            cmd = 0.0
        out.append((tau_ns, cmd, mode))
    return out


def _qos(depth=100, latched=False):
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def _stamp(msg, t_ns):
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
    return msg


def test_session_and_recorder_processes(tmp_path, ros_domain, procs):
    import rclpy
    from bike_msgs.msg import Command, ControllerStatus, DriveCommand, PlantState, SessionStatus
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.context import Context
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import BatteryState
    from std_msgs.msg import String

    (tmp_path / "unit_profile.yaml").write_text(PROFILE)
    config = tmp_path / "bike.yaml"
    config.write_text(CONFIG)
    record_dir = tmp_path / "runs"

    recorder = Proc("recorder_node", ["--params-file", str(config), "-p", f"record_dir:={record_dir}",
                                      "-p", "bag_name:=bag"], tmp_path)
    procs.append(recorder)
    session = Proc("session_node", ["--params-file", str(config), "-p", f"config_path:={config}"], tmp_path)
    procs.append(session)

    ctx = Context()
    rclpy.init(context=ctx, domain_id=ros_domain)
    node = rclpy.create_node("test_plant", namespace=NS, context=ctx)
    from rclpy.executors import SingleThreadedExecutor

    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        got_cmd, got_status, got_info = [], [], []
        node.create_subscription(Command, "command", got_cmd.append, _qos(latched=True))
        node.create_subscription(SessionStatus, "session_status", got_status.append, _qos(latched=True))
        node.create_subscription(String, "session_info", got_info.append, _qos(1, latched=True))
        pub_clock = node.create_publisher(Clock, "/clock", _qos())
        pub_ps = node.create_publisher(PlantState, "plant_state", _qos())
        others = {
            "drive_command": node.create_publisher(DriveCommand, "drive_command", _qos()),
            "controller_status": node.create_publisher(ControllerStatus, "controller_status", _qos()),
            "battery": node.create_publisher(BatteryState, "battery", _qos()),
            "/diagnostics": node.create_publisher(DiagnosticArray, "/diagnostics", _qos()),
        }

        def spin(seconds):
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                executor.spin_once(timeout_sec=0.01)

        # discovery: both nodes see our clock, the recorder sees every topic we publish
        def ready():
            spin(0.05)
            return (pub_clock.get_subscription_count() >= 2 and pub_ps.get_subscription_count() >= 1
                    and all(p.get_subscription_count() >= 1 for p in others.values())
                    and node.count_subscribers(f"{NS}/command") >= 2 and node.count_publishers(f"{NS}/command") >= 1
                    and len(got_info) == 1)
        assert wait_for(ready, 15.0), (recorder.err()[-2000:], session.err()[-2000:])
        # (the recorder prints its bag once its constructor returns, which can be just after
        # discovery saw the subscriptions it made: ci16 read nothing yet)
        assert wait_for(lambda: recorder.out().startswith(f"bag: {record_dir / 'bag'}"), 10.0), \
            (recorder.out()[-500:], recorder.err()[-2000:])
        # one /clock reader each, their own, although the config says use_sim_time: true (rclpy's
        # time source would add a second one to each, and the plant delivers every /clock to it)
        spin(0.5)
        assert pub_clock.get_subscription_count() == 2
        # what the session's own writers offer, for the bag's offered_qos_profiles below
        live_durability = {t: {i.qos_profile.durability for i in node.get_publishers_info_by_topic(f"{NS}/{t}")}
                           for t in ("command", "session_status", "session_info")}

        for name, pub in others.items():
            msg = pub.msg_type()
            _stamp(msg, 5_000_000)
            pub.publish(msg)
        steps = int(DURATION * 1e9) // STEP_NS
        for k in range(steps + 1):
            t_ns = k * STEP_NS
            c = Clock()
            c.clock.sec, c.clock.nanosec = divmod(t_ns, 1_000_000_000)
            pub_clock.publish(c)
            ps = _stamp(PlantState(), t_ns)
            ps.seq = k
            ps.machine, ps.backend = "bldc", "test"
            ps.end_of_run = k == steps
            pub_ps.publish(ps)
            spin(0.003)

        assert session.wait(10.0) == 0, session.err()[-2000:]
        spin(0.3)
        recorder.signal(signal.SIGINT)
        assert recorder.wait(10.0) == 0, recorder.err()[-2000:]
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)

    # ---- what the session published (as received live)
    expected = _expected_commands()
    live = [(m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec, m.command, m.mode) for m in got_cmd]
    assert [t for t, _, _ in live] == [t for t, _, _ in expected]
    assert [(c, m) for _, c, m in live] == [(pytest.approx(c, abs=1e-12), m) for _, c, m in expected]
    assert got_status[-1].state == SessionStatus.STATE_DONE
    assert got_status[-1].profile_name == "unit_profile"
    assert [s.state for s in got_status if s.state == SessionStatus.STATE_RUNNING]
    info = json.loads(got_info[0].data)
    assert info["profile_text"] == PROFILE and info["config_text"] == CONFIG
    assert info["seeds"] == {"plant_seed": 42} and info["software_version"] and info["start_wall_time"]

    # ---- the bag, read with an EMPTY typestore (definitions embedded)
    bag = record_dir / "bag"
    assert (bag / "metadata.yaml").is_file()
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    assert "bike_msgs/msg/PlantState" not in get_typestore(Stores.EMPTY).types
    by_topic: dict[str, list] = {}
    with AnyReader([bag]) as reader:
        for conn, t_ns, raw in reader.messages():
            by_topic.setdefault(conn.topic, []).append((t_ns, reader.deserialize(raw, conn.msgtype)))
    all_topics = {"/clock", "/diagnostics", *(f"{NS}/{t}" for t in (
        "command", "plant_state", "drive_command", "controller_status", "session_status", "session_info", "battery"))}
    assert set(by_topic) == all_topics, {t: len(v) for t, v in by_topic.items()}
    assert len(by_topic["/clock"]) == steps + 1
    assert len(by_topic[f"{NS}/plant_state"]) == steps + 1
    # log time = sim time
    for t_ns, m in by_topic["/clock"]:
        assert t_ns == m.clock.sec * 1_000_000_000 + m.clock.nanosec
    for topic in ("plant_state", "command", "session_status", "battery", "drive_command", "controller_status"):
        for t_ns, m in by_topic[f"{NS}/{topic}"]:
            assert t_ns == m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
    assert by_topic[f"{NS}/session_info"][0][0] <= int(DURATION * 1e9)
    assert by_topic[f"{NS}/plant_state"][-1][1].end_of_run
    recorded = sorted((t, m.command, m.mode) for t, m in by_topic[f"{NS}/command"])
    assert recorded == [(t, pytest.approx(c, abs=1e-12), m) for t, c, m in expected]

    # ---- offered QoS as rosbag2 records it: the publishers' own. `ros2 bag play` offers it again
    # (rosbag2_storage qos.cpp): a transient_local topic recorded volatile (as /command and
    # /session_status were) replays without the history a late subscriber gets live
    import yaml
    from rclpy.qos import DurabilityPolicy

    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    offered = {t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"]
               for t in meta["topics_with_message_count"]}
    for topic, live in live_durability.items():
        assert live == {DurabilityPolicy.TRANSIENT_LOCAL}, (topic, live)
        assert [q["durability"] for q in offered[f"{NS}/{topic}"]] == ["transient_local"], topic
    assert [q["durability"] for q in offered[f"{NS}/plant_state"]] == ["volatile"]     # the test's writer

    # ---- and with an independent decoder (mcap_ros2)
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    mcap_file = next(bag.glob("*.mcap"))
    seen = {}
    with open(mcap_file, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
            if channel.topic == f"{NS}/command":    # the data file's channel says the same
                assert "durability: transient_local" in channel.metadata["offered_qos_profiles"]
            if channel.topic == f"{NS}/plant_state":
                assert message.log_time == decoded.header.stamp.sec * 1_000_000_000 + decoded.header.stamp.nanosec
                assert schema.name == "bike_msgs/msg/PlantState" and schema.encoding == "ros2msg"
    assert seen == {t: len(v) for t, v in by_topic.items()}


def test_session_bad_profile_exits_2(tmp_path, ros_domain, procs):
    (tmp_path / "bad.yaml").write_text("segments:\n  - {kind: step, duration_s: 1, command: 3}\n")
    session = Proc("session_node", ["-p", "session.profile:=bad.yaml", "-p", f"config_path:={tmp_path / 'x.yaml'}"],
                   tmp_path)
    procs.append(session)
    assert session.wait(15.0) == 2
    err = session.err()
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert f"{tmp_path / 'bad.yaml'}: segments[0].command" in err and "[0, 1]" in err


def test_recorder_sqlite3_stops_after_silence(tmp_path, ros_domain, procs):
    rec = Proc("recorder_node", ["-p", f"record_dir:={tmp_path}", "-p", "bag_name:=quiet", "-p", "storage:=sqlite3"],
               tmp_path)
    procs.append(rec)
    assert wait_for(lambda: rec.out().startswith("bag: "), 15.0), rec.err()
    time.sleep(0.5)
    start = time.monotonic()
    rec.signal(signal.SIGTERM)
    assert rec.wait(10.0) == 0, rec.err()
    assert time.monotonic() - start < 6.0
    from bike_session.bags import open_bag

    with open_bag(tmp_path / "quiet") as bag:
        assert len(bag.topics) == 10 and sum(bag.message_counts().values()) == 0   # with drive_truth
    assert list((tmp_path / "quiet").glob("*.db3"))
    # the same bag name again: refused with one line, exit 2
    again = Proc("recorder_node", ["-p", f"record_dir:={tmp_path}", "-p", "bag_name:=quiet"], tmp_path)
    procs.append(again)
    assert again.wait(15.0) == 2
    assert "already exists" in again.err() and "Traceback" not in again.err()


@contextlib.contextmanager
def _publisher_node(name: str, domain: int):
    """A node of the test process (its own context) standing in for one of the graph's publishers."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node(name, namespace=NS, context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        yield node, executor
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def test_recorder_adapts_to_volatile_command_publisher(tmp_path, ros_domain, procs):
    """A replayer-like volatile Command publisher is still recorded (QoS downgrade)."""
    from bike_msgs.msg import Command, PlantState

    rec = Proc("recorder_node", ["-p", f"record_dir:={tmp_path}", "-p", "bag_name:=vol"], tmp_path)
    procs.append(rec)
    with _publisher_node("replayer", ros_domain) as (node, executor):
        pub = node.create_publisher(Command, "command", _qos())          # volatile
        pub_ps = node.create_publisher(PlantState, "plant_state", _qos())
        assert wait_for(lambda: pub.get_subscription_count() >= 1 and pub_ps.get_subscription_count() >= 1, 15.0), \
            rec.err()[-2000:]
        for j in range(3):
            pub.publish(_stamp(Command(command=0.1 * j), j * 100_000_000))
        pub_ps.publish(PlantState(end_of_run=True))
        executor.spin_once(timeout_sec=0.3)
        rec.signal(signal.SIGINT)
        assert rec.wait(10.0) == 0, rec.err()[-2000:]
    from bike_session.bags import read_topic

    assert [round(m.command, 6) for m in read_topic(tmp_path / "vol", "command")] == [0.0, 0.1, 0.2]
    assert "volatile publisher appeared" in rec.err()


def test_recorder_writes_a_republished_plant_state_once(tmp_path, ros_domain, procs):
    """The lockstep plant re-publishes an unanswered PlantState and /clock (republish_s):
    a byte-identical copy is counted, not written; a state that differs in anything is kept.
    The session then sends the Commands in force again (same stamps and values): written once
    too, so whether a late match happened leaves no trace in the bag; so is the controller's
    answer to a re-published state, sent again."""
    from bike_msgs.msg import Command, DriveCommand, PlantState
    from rosgraph_msgs.msg import Clock

    rec = Proc("recorder_node", ["-p", f"record_dir:={tmp_path}", "-p", "bag_name:=rep"], tmp_path)
    procs.append(rec)
    with _publisher_node("plant", ros_domain) as (node, executor):
        pub_ps = node.create_publisher(PlantState, "plant_state", _qos())
        pub_clock = node.create_publisher(Clock, "/clock", _qos())
        pub_cmd = node.create_publisher(Command, "command", _qos(latched=True))
        pub_drive = node.create_publisher(DriveCommand, "drive_command", _qos())
        assert wait_for(lambda: min(p.get_subscription_count() for p in (pub_ps, pub_clock, pub_cmd, pub_drive)) >= 1,
                        15.0), rec.err()[-2000:]
        sent = [(0, 0, 0.0), (0, 0, 0.0), (1, 1, 0.0), (1, 1, 0.0), (1, 1, 5.0), (2, 2, 5.0)]
        # (stamp ms, command): the two in force sent again after the plant's re-publication,
        # then a new value at an old stamp (kept: it is not a copy)
        commands = [(0, 0.2), (1, 0.3), (0, 0.2), (1, 0.3), (2, 0.4), (1, 0.5)]
        for (seq, t_ms, speed), (cmd_ms, cmd) in zip(sent, commands):
            clock = Clock()
            clock.clock.sec, clock.clock.nanosec = divmod(t_ms * 1_000_000, 1_000_000_000)
            pub_clock.publish(clock)
            pub_ps.publish(_stamp(PlantState(seq=seq, speed_rad_s=speed), t_ms * 1_000_000))
            pub_cmd.publish(_stamp(Command(command=cmd), cmd_ms * 1_000_000))
            if speed == 0.0:                                  # the answer to each state, sent again with it
                pub_drive.publish(_stamp(DriveCommand(seq=seq), t_ms * 1_000_000))
            time.sleep(0.02)
        pub_ps.publish(_stamp(PlantState(seq=3, end_of_run=True), 3_000_000))
        executor.spin_once(timeout_sec=0.3)
        rec.signal(signal.SIGINT)
        assert rec.wait(10.0) == 0, rec.err()[-2000:]
    from bike_session.bags import read_topic

    states = [(m.seq, m.speed_rad_s) for m in read_topic(tmp_path / "rep", "plant_state")]
    assert states == [(0, 0.0), (1, 0.0), (1, 5.0), (2, 5.0), (3, 0.0)]
    clocks = [m.clock.nanosec for m in read_topic(tmp_path / "rep", "/clock")]
    assert clocks == [0, 1_000_000, 2_000_000]
    assert [m.seq for m in read_topic(tmp_path / "rep", "drive_command")] == [0, 1]
    assert "7 re-published loop message copies not written" in rec.err()
    cmds = [(m.header.stamp.nanosec // 1_000_000, round(m.command, 6)) for m in read_topic(tmp_path / "rep", "command")]
    assert sorted(cmds) == [(0, 0.2), (1, 0.3), (1, 0.5), (2, 0.4)]     # the bag reads in log-time order
    assert "2 re-sent Command copies not written" in rec.err()


def test_recorder_puts_a_restarted_plants_run_into_a_new_bag(tmp_path, ros_domain, procs):
    """A plant restarted mid-run starts again at seq 0: the recorder closes the bag and
    writes the new run to <bag>_run2, with session_info again and the session's Commands
    from t = 0 (byte-identical to the first run's: not copies to drop)."""
    from bike_msgs.msg import Command, PlantState
    from std_msgs.msg import String

    rec = Proc("recorder_node", ["-p", f"record_dir:={tmp_path}", "-p", "bag_name:=two"], tmp_path)
    procs.append(rec)
    with _publisher_node("plant", ros_domain) as (node, executor):
        pub_ps = node.create_publisher(PlantState, "plant_state", _qos())
        pub_cmd = node.create_publisher(Command, "command", _qos(latched=True))
        pub_info = node.create_publisher(String, "session_info", _qos(depth=1, latched=True))
        assert wait_for(lambda: min(p.get_subscription_count() for p in (pub_ps, pub_cmd, pub_info)) >= 1, 15.0), \
            rec.err()[-2000:]
        pub_info.publish(String(data='{"profile": "unit"}'))
        # a writer matched is not a reader matched: the first run waits until the recorder has it
        assert wait_for(lambda: "session_info: latched message recorded" in rec.err(), 15.0), rec.err()[-2000:]
        for run in (1, 2):
            pub_cmd.publish(_stamp(Command(command=0.3), 0))
            for seq in range(3):
                last = run == 2 and seq == 2
                pub_ps.publish(_stamp(PlantState(seq=seq, speed_rad_s=float(run), end_of_run=last), seq * STEP_NS))
                time.sleep(0.02)
            time.sleep(0.2)
        executor.spin_once(timeout_sec=0.3)
        rec.signal(signal.SIGINT)
        assert rec.wait(10.0) == 0, rec.err()[-2000:]
    from bike_session.bags import read_topic

    first, second = tmp_path / "two", tmp_path / "two_run2"
    assert [(m.seq, m.speed_rad_s, m.end_of_run) for m in read_topic(first, "plant_state")] == \
        [(0, 1.0, False), (1, 1.0, False), (2, 1.0, False)]
    assert [(m.seq, m.speed_rad_s, m.end_of_run) for m in read_topic(second, "plant_state")] == \
        [(0, 2.0, False), (1, 2.0, False), (2, 2.0, True)]
    for bag in (first, second):
        assert [m.data for m in read_topic(bag, "session_info")] == ['{"profile": "unit"}']
        assert [round(m.command, 6) for m in read_topic(bag, "command")] == [0.3]
    assert "the plant restarted" in rec.err() and f"bag: {second}" in rec.out()


@contextlib.contextmanager
def _plant_at_seq_0(tmp_path, domain, procs, bag_name: str, writers_wait_s: float):
    """A recorder process (``writers_wait_s``) and the test's plant node, which has published
    PlantState seq 0 and reads recorder_progress: yields (recorder, node, executor, seqs heard)."""
    from bike_msgs.msg import PlantState
    from std_msgs.msg import UInt64

    rec = Proc("recorder_node", ["-p", f"record_dir:={tmp_path}", "-p", f"bag_name:={bag_name}",
                                 "-p", f"writers_wait_s:={writers_wait_s!r}"], tmp_path)
    procs.append(rec)
    with _publisher_node("plant", domain) as (node, executor):
        heard: list[int] = []
        node.create_subscription(UInt64, "recorder_progress", lambda m: heard.append(int(m.data)),
                                 _qos(depth=1, latched=True))
        node.pub_ps = node.create_publisher(PlantState, "plant_state", _qos())
        assert wait_for(lambda: node.pub_ps.get_subscription_count() >= 1, 15.0), rec.err()[-2000:]
        node.pub_ps.publish(_stamp(PlantState(seq=0), 0))
        yield rec, node, executor, heard


def test_seq_0_is_confirmed_once_the_sessions_writers_have_matched_the_recorder(tmp_path, ros_domain, procs):
    """Nothing else orders the session-recorder match before a lockstep run: a 1.2 s replay on a
    busy CI host ended before it and its bag had no Commands. The recorder confirms seq 0 (the
    plant holds seq 1 until then) only once the session's Command and session_info writers have
    matched it and sent it their first message (a reader counts a writer matched before the
    writer has sent it its history: a recorder stopped then lost the Command, CI 2026-12-07),
    and then the session's Commands sent before the match are in the bag."""
    from bike_msgs.msg import Command, PlantState
    from std_msgs.msg import String

    with _plant_at_seq_0(tmp_path, ros_domain, procs, "held", 60.0) as (rec, node, executor, heard):
        deadline = time.monotonic() + 1.5
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        assert heard == [], heard                        # held: no session writer has matched
        with _publisher_node("session", ros_domain) as (session, session_exec):
            pub_cmd = session.create_publisher(Command, "command", _qos(latched=True))
            pub_info = session.create_publisher(String, "session_info", _qos(depth=1, latched=True))
            pub_cmd.publish(_stamp(Command(command=0.4), 0))       # before any match: history
            t0 = time.monotonic()
            while pub_info.get_subscription_count() < 1 and time.monotonic() - t0 < 15.0:
                executor.spin_once(timeout_sec=0.05)
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.05)
            assert heard == [], heard                    # held: session_info matched, nothing sent yet
            pub_info.publish(String(data='{"profile": "unit"}'))
            t0 = time.monotonic()
            while not heard and time.monotonic() - t0 < 15.0:
                executor.spin_once(timeout_sec=0.05)
                session_exec.spin_once(timeout_sec=0.0)
            assert heard == [0], (heard, rec.err()[-2000:])
            node.pub_ps.publish(_stamp(PlantState(seq=1, end_of_run=True), STEP_NS))
            t0 = time.monotonic()
            while heard[-1] != 1 and time.monotonic() - t0 < 15.0:
                executor.spin_once(timeout_sec=0.05)
            rec.signal(signal.SIGINT)
            assert rec.wait(10.0) == 0, rec.err()[-2000:]
    from bike_session.bags import read_topic

    assert [round(m.command, 6) for m in read_topic(tmp_path / "held", "command")] == [0.4]
    assert [m.data for m in read_topic(tmp_path / "held", "session_info")] == ['{"profile": "unit"}']
    assert "have not matched" not in rec.err()


def test_a_recorder_without_a_session_confirms_seq_0_after_its_wait_and_says_so(tmp_path, ros_domain, procs):
    """A graph without a session (a plant and a controller only) is still recorded: seq 0 is
    confirmed after writers_wait_s, with one warning; a bad wait is one error, exit 2."""
    bad = Proc("recorder_node", ["-p", f"record_dir:={tmp_path}", "-p", "bag_name:=bad",
                                 "-p", "writers_wait_s:=-1.0"], tmp_path)
    assert bad.wait(30.0) == 2
    assert "writers_wait_s must be a number of seconds >= 0, got -1.0" in bad.err(), bad.err()[-2000:]
    assert "Traceback" not in bad.err()
    bad.kill()
    with _plant_at_seq_0(tmp_path, ros_domain, procs, "alone", 0.5) as (rec, _node, executor, heard):
        t0 = time.monotonic()
        while not heard and time.monotonic() - t0 < 15.0:
            executor.spin_once(timeout_sec=0.05)
        assert heard == [0] and time.monotonic() - t0 >= 0.45, (heard, time.monotonic() - t0)
        rec.signal(signal.SIGINT)
        assert rec.wait(10.0) == 0, rec.err()[-2000:]
    assert rec.err().count("the writers of /bike/command, /bike/session_info have not matched this recorder "
                           "(or sent it nothing) in 0.5s") == 1, rec.err()[-2000:]


def test_mcap_channels_carry_the_type_hash_as_rosbag2_writes_them(tmp_path):
    """rosbag2's MCAP storage writes ``topic_type_hash`` into each Channel's metadata and reads a
    topic's type_description_hash back from there (ros2 bag info of the .mcap alone, reindex).
    The hash is rosidl's (the installed <pkg>/msg/<Type>.json), in the closed bag and in one
    recovered from a killed recording."""
    import yaml
    from ament_index_python.packages import get_package_share_directory
    from mcap.reader import make_reader

    from bike_session.recorder_node import TOPICS, BagSink, build_typestore
    from bike_session.recover import recover

    def rosidl_hash(msgtype):
        pkg, _, name = msgtype.split("/")
        desc = json.loads((pathlib.Path(get_package_share_directory(pkg)) / "msg" / f"{name}.json").read_text())
        return next(h["hash_string"] for h in desc["type_hashes"] if h["type_name"] == msgtype)

    topics = [(t if t.startswith("/") else f"{NS}/{t}", msgtype, hdr, False) for t, msgtype, hdr in TOPICS]
    want = {topic: rosidl_hash(msgtype) for topic, msgtype, *_ in topics}
    assert all(h.startswith("RIHS01_") for h in want.values())

    def channel_hashes(bag):
        with open(next(bag.glob("*.mcap")), "rb") as fh:
            summary = make_reader(fh).get_summary()
        return {c.topic: c.metadata.get("topic_type_hash") for c in summary.channels.values()}

    ts = build_typestore()
    closed = BagSink(tmp_path / "closed", "mcap", ts, topics)
    closed.write(f"{NS}/session_info", 0, ts.serialize_cdr(ts.types["std_msgs/msg/String"](data="x"),
                                                           "std_msgs/msg/String"))
    closed.close()
    assert channel_hashes(tmp_path / "closed") == want
    meta = yaml.safe_load((tmp_path / "closed" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert {t["topic_metadata"]["name"]: t["topic_metadata"]["type_description_hash"]
            for t in meta["topics_with_message_count"]} == want

    killed = BagSink(tmp_path / "killed", "mcap", ts, topics)
    killed.write(f"{NS}/session_info", 0, ts.serialize_cdr(ts.types["std_msgs/msg/String"](data="x"),
                                                           "std_msgs/msg/String"))
    killed.flush()                    # then killed: no metadata.yaml, no summary
    out = pathlib.Path(recover(tmp_path / "killed")["out"])
    assert channel_hashes(out) == want


def test_a_hand_over_drops_only_what_the_old_participant_wrote_while_its_window_lasts():
    """recorder_node.HandOverLog: the durable topics are remembered always (their history comes
    again at a new reader's match), every topic from the hand-over's start; the new node's copies
    are dropped for HANDOVER_DEDUP_S, new messages never, and then only the durable topics are kept."""
    from bike_session.recorder_node import HANDOVER_DEDUP_S, HandOverLog
    log = HandOverLog({"/bike/command"})
    assert not log.again("/bike/command", b"c1", 0.0)
    log.start(["/bike/command", "/bike/plant_state"])
    assert not log.again("/bike/plant_state", b"s1", 1.0)
    log.open_window(2.0)
    assert log.again("/bike/plant_state", b"s1", 2.5) and log.again("/bike/command", b"c1", 2.5)
    assert not log.again("/bike/plant_state", b"s2", 3.0) and log.dropped == 2
    assert not log.again("/bike/plant_state", b"s3", 2.0 + HANDOVER_DEDUP_S)      # the window is over
    assert set(log.seen) == {"/bike/command"} and log.capped
    assert not log.again("/bike/command", b"c1", 10.0)                               # a copy later is not ours
