"""Reliability suite: fuzzed Command values published to a running controller process.

Every invalid Command (NaN, +-inf, negative, > 1, an unknown mode, a virtual gear that is not
finite or outside [0.3, 8]) gets exactly one WARN
diagnostic naming the problem; valid ones in between get none; the node stays alive and
ends cleanly on SIGINT."""
from __future__ import annotations

import math
import random
import signal
import time

import pytest
from node_harness import CONFIG, Collector, NodeProcess, domain  # noqa: F401

from bike_msgs.msg import Command  # noqa: E402
from bike_plant import msgconv  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402

pytestmark = pytest.mark.timeout(60)


def _fuzzed_commands(seed: int, count: int):
    """[(value, mode, virtual gear, expected problem word or None, road)], about one in three
    valid; a road ((crr, cw_kg_m, wind_mps) or None), good or bad, on some otherwise valid ones."""
    rng = random.Random(seed)
    out = []
    for _ in range(count):
        kind = rng.randrange(10)
        if kind == 8:
            gear = rng.choice([math.nan, math.inf, -math.inf, -2.75, 0.1, 0.29, 8.01, 1e9])
            out.append((rng.random(), rng.randrange(5), gear, "gear"))
            continue
        if kind == 9:
            out.append((rng.random(), rng.randrange(5), rng.choice([0.0, 0.3, 2.7471, 8.0]), None))
            continue
        if kind == 0:
            out.append((rng.random(), rng.randrange(5), None))
        elif kind == 1:
            out.append((math.nan, rng.randrange(5), "not finite"))
        elif kind == 2:
            out.append((rng.choice([math.inf, -math.inf]), rng.randrange(5), "not finite"))
        elif kind == 3:
            out.append((-rng.uniform(1e-6, 1e6), rng.randrange(5), "outside [0, 1]"))
        elif kind == 4:
            out.append((1.0 + rng.uniform(1e-6, 1e6), rng.randrange(5), "outside [0, 1]"))
        elif kind == 5:
            out.append((rng.random(), rng.randrange(6, 256), "unknown mode"))
        elif kind == 6:
            out.append((rng.choice([0.0, 1.0]), rng.randrange(5), None))
        else:
            out.append((-rng.random(), rng.randrange(6, 256), None))      # two problems: still one diagnostic
    out = [c if len(c) == 4 else (c[0], c[1], 0.0, c[2]) for c in out]
    roads = random.Random(seed + 1000)
    with_road = []
    for value, mode, gear, word in out:
        road, kind = None, roads.randrange(10)
        if word is None and value >= 0 and kind < 3:
            road = roads.choice([(math.nan, 0.5, 0.0), (0.004, -1.0, 0.0), (0.004, 0.5, 99.0), (0.2, 0.5, 0.0),
                                 (0.004, 0.5, math.inf)])
            word = "road"
        elif kind < 6:
            road = (roads.uniform(0, 0.02), roads.uniform(0, 1.5), roads.uniform(-10, 10))
        with_road.append((value, mode, gear, word, road))
    return with_road


def _ends_cleanly_on_sigint(proc) -> None:
    """Alive after the fuzzing, then a clean exit (code 0, no traceback) on SIGINT."""
    assert proc.alive()
    proc.signal(signal.SIGINT)
    assert proc.wait(10) == 0, proc.output()
    assert "Traceback" not in proc.output()


def test_fuzzed_commands_one_diagnostic_each(domain):
    col = Collector(domain, {"/diagnostics": DiagnosticArray})
    ctrl = NodeProcess("bike_controller", "controller_node", domain, {"diagnostics_period_s": 1000.0})
    try:
        pub = col.publisher(Command, "command")
        col.wait_for(lambda: pub.get_subscription_count() >= 1, 30, "controller's command subscription", [ctrl])
        time.sleep(0.3)                       # the controller's side of the match (volatile QoS)
        commands = _fuzzed_commands(seed=6, count=60)
        for j, (value, mode, gear, _, road) in enumerate(commands):
            pub.publish(msgconv.command_msg(value, mode, msgconv.seconds_to_ns(0.1 * j), gear, road))
            time.sleep(0.005)
        bad = [c for c in commands if c[3] is not None or c[0] < 0]
        assert 20 < len(bad) < 60

        def rejections():
            return [s.message for a in col.data["/diagnostics"] for s in a.status
                    if s.name.endswith("controller") and "Command rejected" in s.message]
        col.wait_for(lambda: len(rejections()) >= len(bad), 20, f"{len(bad)} rejections", [ctrl])
        time.sleep(0.5)
        msgs = rejections()
        assert len(msgs) == len(bad), "exactly one diagnostic per invalid Command"
        assert all(s.level == DiagnosticStatus.WARN for a in col.data["/diagnostics"] for s in a.status
                   if "Command rejected" in s.message)
        assert sum(c[3] == "gear" for c in bad) >= 3 and sum(c[3] == "road" for c in bad) >= 3
        for (value, mode, gear, word, _), text in zip(bad, msgs):
            assert word is None or word in text, (value, mode, gear, text)
        _ends_cleanly_on_sigint(ctrl)
    finally:
        ctrl.stop()
        col.close()


def test_fuzzed_live_commands_to_the_session_one_warning_each_and_the_last_good_one_rides(domain):
    """The session's live_command (what the FTMS bridge writes): every invalid one gets one WARN
    diagnostic naming the problem and changes nothing; the last valid one before the first
    /clock is in the Commands the session then sends."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock

    col = Collector(domain, {"/diagnostics": DiagnosticArray, "command": Command})
    session = NodeProcess("bike_session", "session_node", domain, {"duration_s": 5.0, "config_path": str(CONFIG)})
    try:
        live = col.node.create_publisher(Command, "live_command", QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        clock = col.node.create_publisher(Clock, "/clock", 10)
        col.wait_for(lambda: live.get_subscription_count() >= 1 and clock.get_subscription_count() >= 1, 30,
                     "the session's subscriptions", [session])
        time.sleep(0.3)
        commands = _fuzzed_commands(seed=11, count=40)
        for j, (value, mode, gear, _, road) in enumerate(commands):
            live.publish(msgconv.command_msg(value, mode, 0, gear, road))
            time.sleep(0.005)
        bad = [c for c in commands if c[3] is not None or c[0] < 0]
        good = [c for c in commands if c not in bad]
        assert 10 < len(bad) < 40 and good

        def rejections():
            return [s.message for a in col.data["/diagnostics"] for s in a.status
                    if s.name.endswith("session") and "live Command rejected" in s.message]
        col.wait_for(lambda: len(rejections()) >= len(bad), 20, f"{len(bad)} rejections", [session])
        time.sleep(0.5)
        assert len(rejections()) == len(bad), "exactly one diagnostic per invalid live Command"
        for (value, mode, gear, word, _), text in zip(bad, rejections()):
            assert word is None or word in text, (value, mode, gear, text)
        clock.publish(Clock())                    # t = 0: the session sends tau_0 and tau_1
        col.wait_for(lambda: len(col.data["command"]) >= 2, 20, "the first Commands", [session])
        value, mode, gear, _, road = good[-1]
        first = col.data["command"][0]
        assert (first.command, first.mode) == (value, mode)
        assert first.virtual_gear_ratio == (gear or first.virtual_gear_ratio)
        assert msgconv.command_road(first) == road, "the live Command's road rides with it"
        _ends_cleanly_on_sigint(session)
    finally:
        session.stop()
        col.close()
