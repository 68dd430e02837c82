"""Reliability suite: kill -9 of each node at a seeded random moment, real processes over DDS.

Semantics (lockstep, the default):
- under `./bike run --record` any node killed ends the run: the launcher stops the others
  (SIGINT), says which node was killed, and the bag holds every batch up to the kill
  (closed normally; a killed recorder's bag is rescued with `./bike bag recover`);
- controller killed: the plant applies no batch without an answer (sim time stops, the
  machine state is held), says so in a WARN diagnostic, and a restarted controller resumes
  the run; never restarted, the plant ends the run with one error after start_timeout_s;
- session killed: the controller proceeds with the last Command after command_wait_s (WARN
  diagnostic); a restarted session resumes the profile and finishes it (the test holds the run
  by stopping the controller until the new session follows /clock: a fast host ends the rest of
  the run before a new process is up);
- recorder killed: the plant gives it up after recorder_timeout_s (ERROR diagnostic) and runs
  on; a restarted recorder (new bag name) records the rest; the killed bag is recovered;
- plant killed: the controller says the plant went silent; the graph stays up, idle. A
  restarted plant starts a new run (its machine state died with it): the controller starts a
  new law, the session follows the clock back with one WARN diagnostic, and the run ends DONE.
(Realtime: a killed controller is in test_faults_relay.py and test_nodes_realtime.py.)
"""
from __future__ import annotations

import os
import pathlib
import random
import re
import signal
import subprocess
import sys
import time

import pytest
from node_harness import CONFIG, Collector, NodeProcess, stamp_ns, stop_all  # noqa: F401

from bike_msgs.msg import ControllerStatus, PlantState, SessionStatus  # noqa: E402
from bike_session.bags import open_bag, read_topic  # noqa: E402
from bike_session.recover import recover  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402

pytestmark = [pytest.mark.timeout(120), pytest.mark.faults]

ROOT = pathlib.Path(__file__).resolve().parents[1]
BATCH_S = 20 * 5e-5
EXE = {"plant": "plant_node", "controller": "controller_node", "session": "session_node",
       "recorder": "recorder_node"}


def _dedupe_seqs(states) -> list[int]:
    seqs = [int(m.seq) for m in states]
    return [k for i, k in enumerate(seqs) if i == 0 or k != seqs[i - 1]]


def _diag_texts(col, level=None, name=None) -> list[str]:
    return [s.message for a in col.data["/diagnostics"] for s in a.status
            if (level is None or s.level == level) and (name is None or s.name.endswith(name))]


def _children(pid: int) -> list[int]:
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as fh:
            return [int(x) for x in fh.read().split()]
    except OSError:
        return []


def _node_pid(cli_pid: int, exe: str) -> int | None:
    for child in _children(cli_pid):
        try:
            with open(f"/proc/{child}/cmdline", "rb") as fh:
                if exe.encode() in fh.read():
                    return child
        except OSError:
            pass
    return None


# ---------------------------------------------------------------- under ./bike run
@pytest.mark.parametrize("victim", ["plant", "controller", "session", "recorder"])
def test_kill_9_under_bike_run_ends_the_run_cleanly(tmp_path, victim, ros_domain):
    rng = random.Random(f"kill-{victim}")
    kill_at_seq = rng.randint(500, 1500)             # 0.5-1.5 s of sim time
    domain = ros_domain                              # claimed: no other run on this host has it
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    col = Collector(domain, {"plant_state": PlantState})
    out, err = open(tmp_path / "out.txt", "w+"), open(tmp_path / "err.txt", "w+")
    cli = subprocess.Popen([sys.executable, "-m", "bike_session.cli", "run", "--record", str(tmp_path / "rec"),
                            "--duration", "20"], cwd=ROOT, env=env, stdout=out, stderr=err)
    try:
        states = col.data["plant_state"]
        end = time.monotonic() + 90
        while not (states and states[-1].seq >= kill_at_seq):
            assert cli.poll() is None and time.monotonic() < end, (tmp_path / "out.txt").read_text()[-3000:]
            time.sleep(0.01)
        pid = _node_pid(cli.pid, EXE[victim])
        assert pid is not None, f"no {EXE[victim]} child of the launcher"
        os.kill(pid, signal.SIGKILL)
        seq_at_kill = int(states[-1].seq)
        code = cli.wait(60)
    finally:
        if cli.poll() is None:
            cli.send_signal(signal.SIGINT)
            cli.wait(30)
        col.close()
    stdout, stderr = (tmp_path / "out.txt").read_text(), (tmp_path / "err.txt").read_text()
    assert code == 1, (code, stdout[-3000:], stderr[-3000:])
    assert "Traceback" not in stdout + stderr, stdout[-5000:]
    assert f"[launcher] node '{victim}' was killed by SIGKILL: the run was stopped" in stderr, stderr
    bags = list((tmp_path / "rec").iterdir())
    bags = [b for b in bags if b.is_dir()]
    assert len(bags) == 1, bags
    bag = bags[0]
    if victim == "recorder":
        assert "./bike bag recover" in stderr
        bag = pathlib.Path(recover(bag)["out"])
    else:
        assert (bag / "metadata.yaml").exists(), "the surviving recorder closes the bag"
    with open_bag(bag) as b:
        assert b.topics
    seqs = _dedupe_seqs(read_topic(bag, "plant_state"))
    assert seqs == list(range(len(seqs))), "every batch from the start, none missing"
    # the recorded data reaches the last second before the kill
    assert seqs[-1] >= seq_at_kill - round(1.0 / BATCH_S), (seqs[-1], seq_at_kill)
    if victim != "recorder":
        assert seqs[-1] >= seq_at_kill - 60, "a live recorder keeps everything up to the stop"


# ---------------------------------------------------------------- restarts (bare processes)
def _graph(col, domain, tmp_path, duration, plant_extra=None, ctrl_extra=None, record=True, plant_last=False):
    """recorder, plant, controller, session; ``plant_last``: the plant after the others (its
    start_timeout_s then only covers the run, not the other nodes' start-up; seq 0 may be
    missed by the test)."""
    procs = {}
    if plant_last:
        procs["controller"] = NodeProcess("bike_controller", "controller_node", domain,
                                          dict({"command_wait_s": 0.5}, **(ctrl_extra or {})))
        procs["session"] = NodeProcess("bike_session", "session_node", domain,
                                       {"duration_s": duration, "config_path": str(CONFIG)})
        col.wait_for(lambda: col.subs["/diagnostics"].get_publisher_count() >= 2, 30, "controller and session",
                     list(procs.values()))
    if record:
        procs["recorder"] = NodeProcess("bike_session", "recorder_node", domain,
                                        {"record_dir": str(tmp_path), "bag_name": "run", "flush_period_s": 0.5})
    procs["plant"] = NodeProcess("bike_plant", "plant_node", domain,
                                 dict({"duration_s": duration, "republish_s": 0.3, "start_timeout_s": 30.0,
                                       "recorder_window_batches": 50 if record else 0, "recorder_timeout_s": 1.5},
                                      **(plant_extra or {})))
    if plant_last:
        return procs
    # the plant starts once a controller is there: the test's subscription first, so that it
    # sees every batch from seq 0
    col.wait_for(lambda: col.subs["plant_state"].get_publisher_count() >= 1, 30, "plant publisher",
                 list(procs.values()))
    if "/diagnostics" in col.subs:
        # the plant's diagnostics must reach the test, and the run goes on without the test's
        # reader once the controller is up (CI, a 2 s run: over before the reader matched)
        col.wait_for(lambda: col.reads_from("/diagnostics", "plant"), 30, "the test's /diagnostics reader "
                     "matched to the plant", list(procs.values()))
    # as `./bike run --record` starts it: its first answer waits until the recorder reads it
    procs["controller"] = NodeProcess("bike_controller", "controller_node", domain,
                                      dict({"command_wait_s": 0.5, "recorder_window_batches": 50 if record else 0},
                                           **(ctrl_extra or {})))
    if "controller_status" in col.subs:
        # the run starts with the session's first Command: a test that reads the controller's
        # (volatile) status must have matched it before then (CI, a 5 s lockstep run: over before
        # the test's reader matched the controller, 2026-12-05)
        col.wait_for(lambda: col.reads_from("controller_status", "controller"), 30,
                     "the test's controller_status reader matched to the controller", list(procs.values()))
    procs["session"] = NodeProcess("bike_session", "session_node", domain,
                                   {"duration_s": duration, "config_path": str(CONFIG)})
    return procs


def _restart(victim, domain, tmp_path, duration):
    if victim == "controller":
        return NodeProcess("bike_controller", "controller_node", domain, {"command_wait_s": 0.5})
    if victim == "session":
        return NodeProcess("bike_session", "session_node", domain, {"duration_s": duration, "config_path": str(CONFIG)})
    return NodeProcess("bike_session", "recorder_node", domain,
                       {"record_dir": str(tmp_path), "bag_name": "run2", "flush_period_s": 0.5})


@pytest.mark.parametrize("victim", ["controller", "session", "recorder"])
def test_kill_9_and_restart_resumes_the_session(tmp_path, victim, ros_domain):
    # the rest must outlast a new node's start-up; the recorder's also the test's reaction to the
    # plant's give-up, after which the run goes on unrecorded at full speed (~10x real time) until
    # the test holds it (it reads the give-up from the plant's log every 10 ms: held at the next
    # batch here, seq 581 of a kill at 529), and leave the new recorder seconds of the run
    duration = {"controller": 2.0, "session": 5.0, "recorder": 5.0}[victim]
    rng = random.Random(f"restart-{victim}")
    kill_at_seq = rng.randint(300, 1200)
    domain = ros_domain                              # claimed: no other run on this host has it
    topics = {"plant_state": PlantState, "/diagnostics": DiagnosticArray, "session_status": SessionStatus}
    if victim == "session":
        topics["controller_status"] = ControllerStatus
    col = Collector(domain, topics)
    # recorder: 3 s to give a silent recorder up, not 1.5. The plant applies the same timeout
    # to the restarted one, and a new recorder starved for 1.5 s on a loaded 2-core machine (six
    # busy processes) was given up on again: its bag then had a hole (CI: 122 states)
    procs = _graph(col, domain, tmp_path, duration,
                   plant_extra={"recorder_timeout_s": 3.0} if victim == "recorder" else None)
    everyone = list(procs.values())
    try:
        states = col.data["plant_state"]
        col.wait_for(lambda: states and states[-1].seq >= kill_at_seq, 60, f"seq {kill_at_seq}", everyone)
        if victim == "session":
            # the session must be in the loop when it dies: its Commands in force at the controller
            # (the profile starts at 0.2, the config's command0 is 0). Its DDS match with the
            # controller has taken seconds on a loaded machine; the controller then runs on
            # command0 from the start, and killing a session it never heard tests nothing (seen
            # once in CI: no 'session silent' after the kill, the first one came at t = 0)
            col.wait_for(lambda: any(m.command > 0.0 for m in col.data["controller_status"]), 30,
                         "the session's Commands at the controller", everyone)
        if victim == "session":
            # the controller's 'session silent' below must reach the test (the plant's: _graph)
            col.wait_for(lambda: col.reads_from("/diagnostics", "controller"), 10,
                         "the test's /diagnostics reader matched to the controller", everyone)
        def silent_diags() -> int:
            return sum("session silent" in t for t in _diag_texts(col, DiagnosticStatus.WARN, "controller"))
        silent_before = silent_diags()
        procs[victim].signal(signal.SIGKILL)
        procs[victim].wait(5.0)
        seq_at_kill = int(states[-1].seq)
        others = [p for name, p in procs.items() if name != victim]
        if victim == "controller":
            # no answer, no batch: the run is held where it was, and the plant says why. The
            # test's reader is not in the loop and lags the lockstep graph by hundreds of batches
            # on a loaded machine, so the held seq is the plant's own word (its diagnostic), and
            # the test then waits until it has caught up with it
            def held_at() -> int:
                """seq of the newest 'run held' diagnostic (-1: none); a plant that started
                before its controller was held at seq 0 too"""
                return max((int(t.split("for seq ")[1].split()[0])
                            for t in _diag_texts(col, DiagnosticStatus.WARN, "plant") if "run held" in t), default=-1)
            col.wait_for(lambda: held_at() >= seq_at_kill, 10, "the plant's 'run held' diagnostic", others)
            held = held_at()
            col.wait_for(lambda: int(states[-1].seq) >= held, 10, f"the test's reader at seq {held}", others)
            time.sleep(0.5)
            assert seq_at_kill <= held and int(states[-1].seq) == held, \
                f"no batch may run without the controller (held at {held}, last state {states[-1].seq})"
        elif victim == "session":
            # without it the controller goes on after command_wait_s, saying so
            col.wait_for(lambda: silent_diags() > silent_before, 10,
                         "the controller's 'session silent' diagnostic after the kill", [procs["controller"]])
            # The run then goes at the graph's full speed: on a fast host (4.5 GHz, ~10x real time)
            # its last seconds were over before a new session process was up (imports, discovery:
            # 1-2 s), and that session waited for a /clock that never came. To test the resume
            # itself, the test holds the run meanwhile: a stopped controller answers nothing, so the
            # plant holds sim time and re-publishes its state and /clock every republish_s, which
            # the restarted session follows as soon as it is up
            procs["controller"].signal(signal.SIGSTOP)
            try:
                status_before = len(col.data["session_status"])
                restarted = _restart(victim, domain, tmp_path, duration)
                everyone.append(restarted)
                col.wait_for(lambda: any(s.state == SessionStatus.STATE_RUNNING
                                         for s in col.data["session_status"][status_before:]), 30,
                             "the restarted session following the held run's /clock", [restarted])
            finally:
                procs["controller"].signal(signal.SIGCONT)
        else:
            # The plant waits recorder_timeout_s for the dead recorder, then gives it up and runs
            # on unrecorded. The new recorder (under a new bag name; the same name again is
            # refused) starts only then: started at once, it reported within the timeout on a fast
            # host, the plant never gave the dead one up and the test saw no FAULT_RECORDER_LOST
            # (ci35, 2026-12-07). From the give-up on the run is held until the plant hears the new
            # one (a stopped controller answers nothing; the waiting plant takes the reports), else
            # its rest can end before a new recorder is up (imports, discovery, or a stale
            # shared-memory port, healed 3 s after its start: CI 2026-12-05). The give-up is read
            # from the plant's log, which is written at once; the test's reader lags the run.
            again = NodeProcess("bike_session", "recorder_node", domain,
                                {"record_dir": str(tmp_path), "bag_name": "run"})
            everyone.append(again)
            col.wait_for(lambda: "going on without waiting for it" in procs["plant"].output(), 15,
                         "the plant giving the dead recorder up", others)
            procs["controller"].signal(signal.SIGSTOP)
            try:
                col.wait_for(lambda: any(m.faults & PlantState.FAULT_RECORDER_LOST for m in states), 10,
                             "FAULT_RECORDER_LOST", others)
                col.wait_for(lambda: any("recorder went silent" in t
                                         for t in _diag_texts(col, DiagnosticStatus.ERROR, "plant")),
                             5, "the plant's ERROR diagnostic", others)
                assert again.wait(30) == 2 and "already exists" in again.output()
                restarted = _restart(victim, domain, tmp_path, duration)
                everyone.append(restarted)
                col.wait_for(lambda: "a recorder reports again" in procs["plant"].output(), 20,
                             "the plant's 'a recorder reports again'", [procs["plant"], restarted])
            finally:
                procs["controller"].signal(signal.SIGCONT)
        if victim == "controller":
            restarted = _restart(victim, domain, tmp_path, duration)
            everyone.append(restarted)
        col.wait_for(lambda: any(m.end_of_run for m in states), 60, "end_of_run after the restart",
                     others + [restarted])
        assert procs["plant"].wait(10) == 0, procs["plant"].output()
        if victim == "recorder":
            plant_log = procs["plant"].output()
            assert "a recorder reports again" in plant_log, \
                f"{plant_log[-3000:]}\nnew recorder:\n{restarted.output()[-2000:]}"
            assert not states[-1].faults & PlantState.FAULT_RECORDER_LOST, \
                f"cleared once the new recorder reports; plant log:\n{plant_log[-3000:]}\nnew recorder:\n" \
                f"{restarted.output()[-2000:]}"
        if victim == "session":
            col.wait_for(lambda: any(s.state == SessionStatus.STATE_DONE for s in col.data["session_status"]),
                         10, "the restarted session's DONE", [restarted])
            assert restarted.wait(10) == 0, restarted.output()
        # the test's own reader is not in the loop: the lockstep graph does not wait for it, and
        # under load it can fall more than the writer's history (LOOP_QOS depth) behind and miss
        # states (CI: 93 in a row while the restarted session started). The run's continuity is
        # read from the bag below: the recorder holds the plant to its pace.
        seqs = _dedupe_seqs(states)
        assert states[-1].end_of_run
        assert abs(stamp_ns(states[-1].header.stamp) * 1e-9 - duration) < 1e-6
        assert not any(m.faults & PlantState.FAULT_BAD_COMMAND for m in states)
    finally:
        stop_all(everyone)
        col.close()
    if victim == "recorder":
        first = pathlib.Path(recover(tmp_path / "run")["out"])
        s1 = _dedupe_seqs(read_topic(first, "plant_state"))
        assert s1 == list(range(len(s1))) and s1[-1] >= seq_at_kill - round(1.0 / BATCH_S)
        s2 = _dedupe_seqs(read_topic(tmp_path / "run2", "plant_state"))
        # no holes from the new recorder's first progress report on: the plant waits for it
        # from there. Before it, DDS can hand the new reader a state (a re-published copy)
        # ahead of the writer's side of the match, and the states until the match completes
        # miss it (seen on a slow host: 831, then 899 on)
        reported = int(re.search(r"a recorder reports again \(written up to seq (\d+)", plant_log).group(1))
        tail = [x for x in s2 if x >= reported]
        holes = [(a, b) for a, b in zip(tail, tail[1:]) if b != a + 1]
        assert s2 and reported in s2 and not holes, \
            f"reported {reported}, first seqs {s2[:5]}, holes after it {holes[:5]}; plant log:\n{plant_log[-3000:]}"
        assert tail[-1] == seqs[-1]
    else:
        recorded = _dedupe_seqs(read_topic(tmp_path / "run", "plant_state"))
        assert recorded == list(range(len(recorded))) and recorded[-1] == seqs[-1], \
            "the run resumed, and the recorder kept every batch across the restart"
        assert set(seqs) <= set(recorded)


def test_kill_9_of_the_plant_and_restart_the_session_follows_the_new_run(tmp_path, ros_domain):
    """A restarted plant starts a new run from seq 0 (its machine state died with it). The
    controller starts a new law, and the session follows the plant's clock back with one
    WARN diagnostic (it used to log every /clock message until the new run caught up), so
    the new run gets the profile from its start and ends with the session DONE. The recorder
    puts the new run into a bag of its own (<bag>_run2), from seq 0 to its end_of_run.
    The runs are read from the bags: the recorder holds the plant to its pace, while this
    test's own reader may match the new plant seconds late (seen: it missed the whole run)."""
    duration = 3.0
    rng = random.Random("restart-plant")
    kill_at_seq = rng.randint(800, 1600)
    domain = ros_domain                              # claimed: no other run on this host has it
    col = Collector(domain, {"plant_state": PlantState, "/diagnostics": DiagnosticArray})
    # command_wait_s long: the comparison needs both runs to wait for the session's Commands.
    # With the graph's 0.5 s a loaded host (CI once; 3 runs of 8 beside two CPU hogs) let the
    # first run's t = 0 go ahead with the zero command while the session was still starting
    # ("no Command for t=0s within command_wait_s"), and the runs then differed from seq 1 on:
    # the controller's documented give-up, not a restart fault
    procs = _graph(col, domain, tmp_path, duration, ctrl_extra={"command_wait_s": 20.0})
    everyone = list(procs.values())
    try:
        states = col.data["plant_state"]
        col.wait_for(lambda: states and states[-1].seq >= kill_at_seq, 60, f"seq {kill_at_seq}", everyone)
        procs["plant"].signal(signal.SIGKILL)
        procs["plant"].wait(5.0)
        plant2 = NodeProcess("bike_plant", "plant_node", domain,
                             {"duration_s": duration, "republish_s": 0.3, "start_timeout_s": 30.0,
                              "recorder_window_batches": 50, "recorder_timeout_s": 1.5})
        everyone.append(plant2)
        assert plant2.wait(60) == 0, plant2.output()
        assert procs["session"].wait(15) == 0, procs["session"].output()
        procs["recorder"].signal(signal.SIGINT)
        assert procs["recorder"].wait(15) == 0, procs["recorder"].output()
    finally:
        rest = [name for name in procs if name != "plant"]
        codes = dict(zip(rest, stop_all(procs[name] for name in rest)))
        stop_all(everyone[len(procs):])
        col.close()
    assert codes["controller"] == 0, codes
    # two bags: the first run up to the kill (no end_of_run: the plant died), the new run whole
    run1 = read_topic(tmp_path / "run", "plant_state")
    run2 = read_topic(tmp_path / "run_run2", "plant_state")
    assert not any(m.end_of_run for m in run1) and run1[-1].seq >= kill_at_seq - 60
    # every batch up to the kill: the plant runs at most recorder_window_batches ahead of the
    # recorder (and the comparison below pairs the runs batch by batch)
    gaps = [(a.seq, b.seq) for a, b in zip(run1, run1[1:]) if b.seq != a.seq + 1]
    assert run1[0].seq == 0 and not gaps, f"the first run's bag misses batches: {gaps[:5]}"
    assert [m.seq for m in run2] == list(range(round(duration / BATCH_S) + 1)) and run2[-1].end_of_run
    assert "the new run goes to" in procs["recorder"].output()
    # the new run rides the profile from t = 0 exactly as the first did (same seed, a fresh
    # law, the Commands of the same stamps): batch for batch identical
    def key(m):
        return (stamp_ns(m.header.stamp), tuple(m.phase_current_a), m.speed_rad_s, m.dc_bus_v, m.energy_battery_j,
                m.energy_mech_in_j)
    differ = [(a, b) for a, b in zip(run1, run2) if key(a) != key(b)]
    gave_up = [line for line in procs["controller"].output().splitlines() if "no Command for" in line]
    assert not differ, (f"the new run differs from the first from seq {differ[0][0].seq} on ({len(differ)} "
                        f"batches): first run {key(differ[0][0])}, new run {key(differ[0][1])}; "
                        f"the controller gave up waiting: {gave_up}")
    assert read_topic(tmp_path / "run_run2", "session_info"), "session_info in the new run's bag too"
    # the session's Commands for the new run: the same stamps and values as the first run's
    commands = read_topic(tmp_path / "run_run2", "command")
    first_run = {stamp_ns(c.header.stamp): (c.command, c.mode) for c in read_topic(tmp_path / "run", "command")}
    assert commands and all(first_run.get(stamp_ns(c.header.stamp), (c.command, c.mode)) == (c.command, c.mode)
                            for c in commands)
    # at most one warning from the session, not one per /clock message of the new run. None
    # when the session's reader matched the new plant only after its run had passed the old
    # one's last time (CI: the lockstep run does not wait for the session): the profile is a
    # function of sim time, so nothing was missed (checked above). The warning itself:
    # test_session_follows_the_clock_back_with_one_warning
    session_log = procs["session"].output()
    assert session_log.count("went back") <= 1, session_log[-2000:]
    assert "the plant restarted, starting a new run" in procs["controller"].output()
    # the session's progress restarted with the new run and ran to its end
    status = read_topic(tmp_path / "run_run2", "session_status")
    assert status and status[-1].state == SessionStatus.STATE_DONE and status[-1].elapsed_s >= duration - 1e-9


def test_lockstep_controller_killed_for_good_ends_the_run_with_one_error(tmp_path, ros_domain):
    """Without a restart the plant ends the run after start_timeout_s (short here): exit
    code 2, one error line, an ERROR diagnostic naming the missing DriveCommand."""
    rng = random.Random("for-good")
    kill_at_seq = rng.randint(300, 900)
    domain = ros_domain                              # claimed: no other run on this host has it
    col = Collector(domain, {"plant_state": PlantState, "/diagnostics": DiagnosticArray})
    procs = _graph(col, domain, tmp_path, 30.0, plant_extra={"start_timeout_s": 4.0}, record=False,
                   plant_last=True)
    try:
        states = col.data["plant_state"]
        col.wait_for(lambda: states and states[-1].seq >= kill_at_seq, 60, f"seq {kill_at_seq}", procs.values())
        procs["controller"].signal(signal.SIGKILL)
        t_kill = time.monotonic()
        code = procs["plant"].wait(20)
        waited = time.monotonic() - t_kill
        out = procs["plant"].output()
        assert code == 2, out[-3000:]
        assert 4.0 <= waited < 12.0, waited
        assert "Traceback" not in out
        errors = [line for line in out.splitlines() if "error:" in line]
        assert len(errors) == 1 and "no DriveCommand for seq" in errors[0], out[-3000:]
        time.sleep(0.3)
        assert any("start_timeout_s" in t and "run ends" in t for t in _diag_texts(col, DiagnosticStatus.ERROR,
                                                                                   "plant"))
        assert procs["session"].alive(), "the session waits (its clock stopped); it is not crashed"
    finally:
        stop_all(procs.values())
        col.close()


def test_plant_killed_the_controller_says_so_and_stays_up(tmp_path, ros_domain):
    rng = random.Random("plant")
    kill_at_seq = rng.randint(300, 900)
    domain = ros_domain                              # claimed: no other run on this host has it
    col = Collector(domain, {"plant_state": PlantState, "/diagnostics": DiagnosticArray})
    procs = _graph(col, domain, tmp_path, 30.0, record=False)
    try:
        states = col.data["plant_state"]
        col.wait_for(lambda: states and states[-1].seq >= kill_at_seq, 60, f"seq {kill_at_seq}", procs.values())
        procs["plant"].signal(signal.SIGKILL)
        others = [procs["controller"], procs["session"]]
        col.wait_for(lambda: any("no PlantState" in t and "plant stopped" in t
                                 for t in _diag_texts(col, DiagnosticStatus.WARN, "controller")),
                     10, "the controller's 'plant stopped' diagnostic", others)
        assert all(p.alive() for p in others)
    finally:
        rest = [name for name in procs if name != "plant"]
        codes = dict(zip(rest, stop_all(procs[name] for name in rest)))
        col.close()
    assert codes == {"controller": 0, "session": 0}, codes


def test_session_follows_the_clock_back_with_one_warning(ros_domain):
    """The session node alone, the test publishing its /clock: after 1 s of a run, time goes
    back to 0 (a restarted plant). The session says so once (log and WARN diagnostic), sends
    the profile's Commands from t = 0 again with the same stamps and values, and ends DONE at
    the run's end (one warning, not one per /clock message of the new run)."""
    from bike_msgs.msg import Command
    from bike_plant.loop import LOOP_QOS
    from builtin_interfaces.msg import Time
    from rosgraph_msgs.msg import Clock

    col = Collector(ros_domain, {"command": Command, "/diagnostics": DiagnosticArray})
    clock = col.node.create_publisher(Clock, "/clock", LOOP_QOS)
    session = NodeProcess("bike_session", "session_node", ros_domain, {"duration_s": 2.0, "config_path": str(CONFIG)})
    try:
        col.wait_for(lambda: clock.get_subscription_count() >= 1 and col.reads_from("command", "session"), 30,
                     "the session matched", [session])

        def ride(t0_s, t1_s):
            for k in range(round(t0_s / 0.01), round(t1_s / 0.01) + 1):
                t_ns = k * 10_000_000
                clock.publish(Clock(clock=Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)))
                time.sleep(0.002)

        def stamps():
            return [stamp_ns(c.header.stamp) for c in col.data["command"]]

        ride(0.0, 1.0)
        col.wait_for(lambda: max(stamps(), default=-1) >= 1_000_000_000, 10, "Commands up to t = 1 s", [session])
        first = {stamp_ns(c.header.stamp): (c.command, c.mode) for c in col.data["command"]}
        n_first = len(col.data["command"])
        ride(0.0, 2.0)
        assert session.wait(15) == 0, session.output()
        col.wait_for(lambda: any("plant restarted" in st.message for a in col.data["/diagnostics"] for st in a.status),
                     5, "the session's WARN diagnostic", [])
    finally:
        session.stop()
        col.close()
    log = session.output()
    assert log.count("went back") == 1 and "/clock went back from 1 s to 0 s" in log, log[-2000:]
    warns = [st.message for a in col.data["/diagnostics"] for st in a.status
             if st.level == DiagnosticStatus.WARN and "plant restarted" in st.message]
    assert warns == ["plant restarted: the profile follows it from t = 0 s"], warns
    # the profile again from t = 0: the same stamps and values as in the first run
    again = {}
    for c in col.data["command"][n_first:]:
        again.setdefault(stamp_ns(c.header.stamp), set()).add((c.command, c.mode))
    assert 0 in again and all(v == {first[t]} for t, v in again.items() if t in first), again
    assert max(again) >= 2_000_000_000 and "session done" in log
