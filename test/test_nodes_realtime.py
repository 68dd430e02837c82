"""Realtime plant_node + controller_node as real processes: wall-clock batches, command
timeout -> safe state, recovery; and each node (controller, plant, session, recorder)
restarted onto a stale Fast DDS shared-memory port heals itself (bike_plant.shm_ports)."""
from __future__ import annotations

import os
import re
import signal
import time

import numpy as np
import pytest
from node_harness import CONFIG, ROOT, Collector, NodeProcess, domain, stamp_ns, stop_all, tool_module  # noqa: F401

from bike_msgs.msg import Command, ControllerStatus, PlantState, SessionStatus  # noqa: E402
from bike_plant import msgconv, shm_ports  # noqa: E402
from bike_plant.config import load_config  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from sensor_msgs.msg import BatteryState  # noqa: E402

pytestmark = pytest.mark.timeout(60)

CFG = load_config(CONFIG)
SPMSM_CONFIG = ROOT / "config" / "spmsm_default.yaml"
N = CFG["batch_periods"]
DT = CFG["control_period_s"]
TIMEOUT = CFG["command_timeout_s"]
RT = {"sync_mode": "realtime"}
# pace check windows (test_realtime_timeout_safe_state_and_recovery)
PACE_WINDOWS = 3
# a recorder in a graph without a session: its seq 0 waits for the session's writers, which never
# come, writers_wait_s (5 s by default) before its first recorder_progress; a realtime plant does
# not wait for that report, the tests do
NO_SESSION_RECORDER = {"writers_wait_s": 0.5}


def _peak_current(m) -> float:
    return float(np.max(np.abs(np.asarray(m.phase_current_a))))


def test_realtime_timeout_safe_state_and_recovery(domain):
    col = Collector(domain, {"plant_state": PlantState, "/diagnostics": DiagnosticArray, "battery": BatteryState,
                             "controller_status": ControllerStatus})
    procs = []
    try:
        cmd_pub = col.publisher(Command, "command")
        plant = NodeProcess("bike_plant", "plant_node", domain, dict(RT, duration_s=0.0))
        procs.append(plant)
        ctrl = NodeProcess("bike_controller", "controller_node", domain, RT)
        procs.append(ctrl)
        col.wait_for(lambda: cmd_pub.get_subscription_count() >= 1, 20, "controller's command subscription", procs)
        states = col.data["plant_state"]

        def commanding(pred):
            # like a session: publish the Command periodically (a volatile subscription that is
            # still completing its match may miss a single message)
            def check():
                cmd_pub.publish(msgconv.command_msg(0.5, 0, 0))       # brake at half command from t = 0
                return pred()
            return check
        # closed loop running: ~34 A phase current, no faults
        col.wait_for(commanding(lambda: len(states) > 300 and all(_peak_current(m) > 10 and m.faults == 0
                                                                  for m in states[-100:])),
                     15, "braking current under realtime control", procs)
        diag_from = len(col.data["/diagnostics"])   # the loop runs (not the start's hold) from here
        # a long window: receive times jitter by tens of ms on a loaded 2-core machine
        col.wait_for(commanding(lambda: len(states) > 1100), 15, "1.1 s of realtime batches", procs)
        # wall-clock batches: sim time advances N*T per batch and follows wall time
        window = list(states[-200:])
        seqs = [int(m.seq) for m in window]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
        assert np.all(np.abs(np.diff([stamp_ns(m.header.stamp) for m in window]) - N * DT * 1e9) <= 2)
        # sim time follows wall time: the plant's own figures (its diagnostics give sim_time_s,
        # wall_s and the wall time it skipped to resynchronise after an overrun), not receipt
        # times, which a loaded test process delays by seconds (read as 0.24-0.58). Over >= 1 s:
        # never ahead of wall time, and behind it only by what it declared dropped.
        def pace(start):
            rows = [{x.key: x.value for st in arr.status for x in st.values}
                    for arr in col.data["/diagnostics"][start:]]
            rows = [r for r in rows if "wall_s" in r and "overrun_dropped_s" in r]
            if len(rows) < 2 or float(rows[-1]["wall_s"]) - float(rows[0]["wall_s"]) < 1.0:
                return None
            a, b = rows[0], rows[-1]
            d_wall = float(b["wall_s"]) - float(a["wall_s"])
            d_sim = float(b["sim_time_s"]) - float(a["sim_time_s"])
            d_drop = float(b["overrun_dropped_s"]) - float(a["overrun_dropped_s"])
            return d_sim / d_wall, (d_sim + d_drop) / d_wall, b
        # up to PACE_WINDOWS windows, each starting where the last ended: a window's end row can
        # be published while the plant is descheduled, behind by a stall it declares only at its
        # next batch (CI on an overloaded host: 0.17 s, paced 1.17). A plant that runs ahead or
        # hides a deficit fails every window.
        start = diag_from
        seen = []
        for _ in range(PACE_WINDOWS):
            col.wait_for(commanding(lambda: pace(start) is not None), 15, "diagnostics over 1 s", procs)
            ratio, paced, last_diag = pace(start)
            seen.append(f"sim / wall {ratio:.3f}, with the declared drops {paced:.3f}: {last_diag}")
            if ratio < 1.05 and 0.95 < paced < 1.05:
                break
            start = len(col.data["/diagnostics"]) - 1
        else:
            raise AssertionError("\n".join(seen))
        assert col.data["battery"], "BatteryState is published"

        # the controller dies without a word
        ctrl.signal(signal.SIGKILL)
        t_kill = time.monotonic()
        k_kill = len(states)
        col.wait_for(lambda: any(m.faults & PlantState.FAULT_COMMAND_TIMEOUT for m in states[k_kill:]),
                     5, "FAULT_COMMAND_TIMEOUT", [plant])
        i_fault = next(i for i in range(k_kill, len(states)) if states[i].faults & PlantState.FAULT_COMMAND_TIMEOUT)
        # latency in sim time, which follows wall time in realtime except when the machine
        # deschedules the plant (then it drops time instead of running ahead); wall time of
        # receipt in this process jitters by up to a second on a loaded 2-core machine
        sim_kill = stamp_ns(states[k_kill - 1].header.stamp) * 1e-9
        sim_fault = stamp_ns(states[i_fault].header.stamp) * 1e-9
        # the last state this process had at the kill lags the plant by its own receipt delay
        # (0.3 s seen on a loaded machine): a loose bound here, the tight one from the plant below
        assert 0 < sim_fault - sim_kill < TIMEOUT + 1.0, f"fault {sim_fault - sim_kill:.3f} s (sim) after the kill"
        assert col.stamps["plant_state"][i_fault] - t_kill < 5.0
        # currents decay to zero in the safe state (all gates off; back-EMF below the bus voltage)
        col.wait_for(lambda: len(states) > i_fault + 200, 5, "states after the fault", [plant])
        after = states[i_fault + 100:i_fault + 200]
        assert all(m.faults & PlantState.FAULT_COMMAND_TIMEOUT for m in after)
        assert max(_peak_current(m) for m in after) < 1e-3

        def plant_errors():
            """(stamp, status) of the plant's ERROR diagnostics received so far."""
            return [(stamp_ns(a.header.stamp), s) for a in list(col.data["/diagnostics"]) for s in a.status
                    if s.name.endswith("plant") and s.level == DiagnosticStatus.ERROR]
        # an ERROR diagnostic is published with the plant's first faulted batch (same sim stamp);
        # not necessarily the first ERROR: a saturated machine can starve the loop of DDS delivery
        # for ~1 s before the kill (README, DDS gaps in realtime mode), a timeout of its own, and
        # the kill can land inside such a safe state (beside two CPU hogs: no new ERROR after the
        # kill, the plant was already safe). The first faulted state THIS process got may be a
        # later one (a reader lagging more than the writer's history of 200 batches loses the
        # oldest; seen in CI). So the episode's start is the last ERROR at or before that state,
        # and every state this process has from there to it must be faulted
        fault_ns = stamp_ns(states[i_fault].header.stamp)

        def unfaulted_since(t_ns):
            return [int(m.seq) for m in list(states) if t_ns <= stamp_ns(m.header.stamp) <= fault_ns
                    and not m.faults & PlantState.FAULT_COMMAND_TIMEOUT]

        def episode_start():
            """The last plant ERROR at or before the faulted state, if none of the states
            received since it is unfaulted (an earlier one, of a recovered timeout, is not it)."""
            found = [(t_ns, s) for t_ns, s in plant_errors() if t_ns <= fault_ns]
            if not found:
                return None
            start = max(found, key=lambda pair: pair[0])
            return None if unfaulted_since(start[0]) else start
        # waited for: beside CPU hogs this process had the faulted states before the diagnostic
        col.wait_for(lambda: episode_start() is not None, 5, "the ERROR diagnostic of the faulted batch", [plant])
        diag_ns, diag = episode_start()
        assert "no DriveCommand" in diag.message
        first = plant_errors()[0][1]
        assert "no DriveCommand" in first.message and "safe state" in first.message
        # safe within 2 batches of command_timeout_s, in sim time measured by the plant: from the
        # batch in which the last DriveCommand arrived to the start of the first safe batch
        last_cmd_s = float({kv.key: kv.value for kv in diag.values}["last_drive_command_sim_s"])
        latency_s = diag_ns * 1e-9 - N * DT - last_cmd_s
        assert 0 < latency_s <= TIMEOUT + 2 * N * DT + 1e-9, f"safe state {latency_s:.4f} s after the last command"
        assert plant.alive()

        # a new controller: commands return, the fault clears, braking resumes
        ctrl2 = NodeProcess("bike_controller", "controller_node", domain, RT)
        procs.append(ctrl2)
        col.wait_for(lambda: cmd_pub.get_subscription_count() >= 1, 20, "second controller", procs[:1] + [ctrl2])
        k_ctrl2 = len(states)
        # any state since the new controller matched (not only the last few received: on a slow
        # host DDS gaps time the loop out now and then, 50 ms at a time, and this process gets
        # states in bursts)
        # 30 s: one CI run saw the plant leave the safe state as the new controller started, yet
        # no braking state reached this process within 15 s (a loaded host; what it did get is
        # in the message)
        try:
            col.wait_for(commanding(lambda: any(m.faults == 0 and _peak_current(m) > 10 for m in states[k_ctrl2:])),
                         30, "recovery", [plant, ctrl2])
        except AssertionError as exc:
            got = states[k_ctrl2:]
            # the known cause: the plant writes to a deleted segment of the new controller's
            # port (Fast DDS 2.14 after a kill -9 in its listener's window; test_shm_ports.py)
            stale = shm_ports.writers_to_deleted(shm_ports.own_ports(ctrl2.pid))
            raise AssertionError(
                f"processes writing to a deleted shared-memory segment of the new controller's ports "
                f"(plant pid {plant.pid}): {stale or 'none'}\n"
                f"{len(got)} states since the second controller started: faults "
                f"{sorted({int(m.faults) for m in got})}, peak current "
                f"{max((_peak_current(m) for m in got), default=0.0):.1f} A, command subscriptions "
                f"{cmd_pub.get_subscription_count()}, in this process's graph: plant_state readers "
                f"{col.node.count_subscribers('/bike/plant_state')}, drive_command writers "
                f"{col.node.count_publishers('/bike/drive_command')}\nlast states (seq, faults, speed rpm): "
                f"{[(int(m.seq), int(m.faults), round(m.speed_rpm)) for m in got[-3:]]}\nlast controller "
                f"status (seq, command, speed_est_rpm, torque_cmd_nm, current_cmd_a): "
                f"{[(int(c.seq), c.command, round(c.speed_est_rpm), c.torque_cmd_nm, c.current_cmd_a) for c in col.data['controller_status'][-3:]]}"
                f"\n{exc}") from None
        col.wait_for(lambda: any(s.name.endswith("plant") and s.level == DiagnosticStatus.OK
                                 for a in col.data["/diagnostics"][-5:] for s in a.status), 5, "OK diagnostic", [plant])

        plant.signal(signal.SIGTERM)
        assert plant.wait(10.0) == 0, plant.output()
        ctrl2.signal(signal.SIGINT)
        assert ctrl2.wait(10.0) == 0, ctrl2.output()
    finally:
        stop_all(procs)
        col.close()


@pytest.mark.timeout(120)
@pytest.mark.parametrize("config", [CONFIG, SPMSM_CONFIG], ids=["bldc", "spmsm"])
def test_a_stalled_controller_keeps_its_speed_estimate_through_the_plant_states_it_skipped(domain, config):
    """Realtime: the controller reads the newest PlantState only, so a host stall of its
    process (SIGSTOP for 30 ms, under command_timeout_s) skips PlantStates and their Hall edges.
    Its speed estimate (Eq. 1), the ERG's virtual speed and an app's km/h, fell to a few % of
    the shaft's for a batch or two after each (2-9 km/h of ~28 in the FTMS app ride); the
    SPMSM bike's speed observer rose to ~1.7x for ~0.1 s (paper 001's 1 ms batches). A loaded
    host stretches a stall past the timeout (62-75 ms seen in CI), and the SPMSM plant's safe
    state then brakes through its diodes (330 -> 250 r/min): its observer read 0.26x - 1.33x
    until it re-acquired after every gap. Every ControllerStatus must stay near the plant's own
    speed of that batch: the shaft (10 kg cm^2 behind a 35:1 gear) cannot lose 15 % in the ms
    an estimate lags. The controller's periodic diagnostic counts the gaps it answered after
    and the control periods they covered (skipped_state_gaps, skipped_periods, skipped_time_s):
    as many as the ControllerStatus seqs it skipped between two of its diagnostics."""
    col = Collector(domain, {"plant_state": PlantState, "controller_status": ControllerStatus,
                             "/diagnostics": DiagnosticArray})
    procs = []
    try:
        cmd_pub = col.publisher(Command, "command")
        plant = NodeProcess("bike_plant", "plant_node", domain, dict(RT, duration_s=0.0), config=config)
        procs.append(plant)
        ctrl = NodeProcess("bike_controller", "controller_node", domain, RT, config=config)
        procs.append(ctrl)
        col.wait_for(lambda: cmd_pub.get_subscription_count() >= 1, 20, "controller's command subscription", procs)
        states, statuses = col.data["plant_state"], col.data["controller_status"]
        pedalling_rpm = 1000.0 if config == CONFIG else 200.0    # the SPMSM's 4:1 gear: ~320 r/min at 80 rpm

        def pedalling():
            cmd_pub.publish(msgconv.command_msg(0.1, 0, 0))       # the app ride's free-ride resistance
            return len(statuses) > 500 and statuses[-1].speed_est_rpm > pedalling_rpm
        col.wait_for(pedalling, 30, "the rider pedalling under realtime control", procs)
        from_seq = int(statuses[-1].seq)
        for _ in range(5):
            ctrl.signal(signal.SIGSTOP)
            time.sleep(0.03)
            ctrl.signal(signal.SIGCONT)
            time.sleep(0.5)
        col.wait_for(lambda: int(statuses[-1].seq) > from_seq + 3000, 30, "3 s of batches after the stalls", procs)
        plant_rpm = {int(m.seq): float(m.speed_rpm) for m in states}
        # A stall that the loaded host stretched past command_timeout_s, or the late answers
        # after it, put the plant in its safe state: another scenario, with its own tests (the
        # SPMSM's diode braking, 4-6 N m, then moves the shaft while the plant ignores what the
        # controller answers late; its estimate is checked through such gaps in-process). The
        # 0.3 s after a COMMAND_TIMEOUT state are not judged here.
        timeouts = [stamp_ns(m.header.stamp) for m in states if int(m.faults) & PlantState.FAULT_COMMAND_TIMEOUT]
        judged = [m for m in statuses if int(m.seq) > from_seq and int(m.seq) in plant_rpm
                  and not any(0 <= stamp_ns(m.header.stamp) - t <= 3e8 for t in timeouts)]
        seqs, kept = [int(m.seq) for m in statuses], {int(m.seq) for m in judged}
        assert sum(1 for a, b in zip(seqs, seqs[1:]) if b - a > 1 and a in kept and b in kept) >= 1, \
            f"no stall within the timeout skipped a PlantState ({len(timeouts)} timeout states)"
        ratios = [(m.speed_est_rpm / plant_rpm[int(m.seq)], int(m.seq)) for m in judged]
        assert min(ratios)[0] > 0.85 and max(ratios)[0] < 1.15, (min(ratios), max(ratios), len(timeouts))
        _check_skipped_state_diagnostics(col, states, load_config(config)["control_period_s"])
    finally:
        stop_all(procs)
        col.close()


def _check_skipped_state_diagnostics(col, states, period_s: float) -> None:
    """Between the first periodic (OK) controller diagnostic after the test's first
    ControllerStatus and the last one, the skipped_* counts rose by the seqs the statuses
    skipped (a diagnostic goes out after the batch of its stamp was answered)."""
    statuses = sorted(col.data["controller_status"], key=lambda m: int(m.seq))
    diags = [(stamp_ns(a.header.stamp), {kv.key: kv.value for kv in s.values}) for a in list(col.data["/diagnostics"])
             for s in a.status if s.name.endswith("controller") and s.level == DiagnosticStatus.OK]
    first = stamp_ns(statuses[0].header.stamp)
    diags = [d for d in diags if d[0] > first]
    assert len(diags) >= 2, f"{len(diags)} periodic controller diagnostics"
    (s1, v1), (s2, v2) = diags[0], diags[-1]
    n = {int(m.seq): int(m.batch_periods) for m in states}
    jumps = [(int(a.seq), int(b.seq)) for a, b in zip(statuses, statuses[1:])
             if int(b.seq) - int(a.seq) > 1 and s1 < stamp_ns(b.header.stamp) <= s2]
    gaps = int(v2["skipped_state_gaps"]) - int(v1["skipped_state_gaps"])
    periods = int(v2["skipped_periods"]) - int(v1["skipped_periods"])
    assert gaps == len(jumps) >= 1, (gaps, jumps)
    assert periods == sum((b - a - 1) * n.get(a, int(states[-1].batch_periods)) for a, b in jumps), (periods, jumps)
    assert float(v2["skipped_time_s"]) == pytest.approx(int(v2["skipped_periods"]) * period_s, rel=1e-5)


def _warnings(col, node: str) -> list[str]:
    """The WARN diagnostics of one node the collector has received so far."""
    return [s.message for a in list(col.data["/diagnostics"]) for s in a.status
            if s.name.endswith(node) and s.level == DiagnosticStatus.WARN]


def test_realtime_controller_without_commands_says_so(domain):
    """A controller that joins a running realtime plant and gets no Command (no session, or
    one it does not match) rides on the config's command0 = 0: it logs a warning once, after
    command_wait_s, its periodic diagnostic is a WARN saying so while it lasts (a monitor that
    matched after the one-off warning sees it too: CI's reader did not get the one-off), and a
    Command that then comes is applied and the diagnostic is OK again."""
    col = Collector(domain, {"plant_state": PlantState, "/diagnostics": DiagnosticArray,
                             "controller_status": ControllerStatus})
    procs = []
    try:
        cmd_pub = col.publisher(Command, "command")
        # the plant starts sim time without a controller (start_timeout_s), so the controller's
        # first PlantState is past t = 0: realtime then answers without waiting for the session
        plant = NodeProcess("bike_plant", "plant_node", domain, dict(RT, duration_s=0.0, start_timeout_s=0.5))
        procs.append(plant)
        col.wait_for(lambda: any(stamp_ns(m.header.stamp) > 0 for m in col.data["plant_state"]), 20,
                     "sim time running", procs)
        ctrl = NodeProcess("bike_controller", "controller_node", domain, dict(RT, command_wait_s=0.5))
        procs.append(ctrl)
        col.wait_for(lambda: any("no Command received" in w for w in _warnings(col, "controller")), 20,
                     "the controller's warning", procs)
        assert all(c.command == 0.0 for c in col.data["controller_status"]), "command0 until a Command comes"
        col.wait_for(lambda: (cmd_pub.publish(msgconv.command_msg(0.5, 0, 0)) or
                              any(c.command == 0.5 for c in col.data["controller_status"])), 15,
                     "the Command applied", procs)
        n_diag = len(col.data["/diagnostics"])
        col.wait_for(lambda: any(s.name.endswith("controller") and s.level == DiagnosticStatus.OK
                                 for a in list(col.data["/diagnostics"])[n_diag:] for s in a.status), 10,
                     "the controller's OK diagnostic after the Command", procs)
        assert ctrl.output().count("no Command received") == 1, ctrl.output()
    finally:
        stop_all(procs)
        col.close()


def test_a_controller_fed_nothing_by_a_matched_plant_state_writer_says_so(domain):
    """A plant_state writer matched but silent (here the test's own, which publishes nothing at
    first; in CI once a restarted controller that got no PlantState from a running plant): the
    controller logs and publishes one WARN naming it, instead of waiting without a word, and
    re-creates its subscription, which then receives. SIGUSR1 prints every thread's stack while
    the node runs on (how a quiet node is diagnosed: blocked, or spinning with nothing delivered)."""
    col = Collector(domain, {"/diagnostics": DiagnosticArray})
    procs = []
    try:
        state_pub = col.publisher(PlantState, "plant_state")      # matched, publishes nothing at first
        ctrl = NodeProcess("bike_controller", "controller_node", domain, RT)
        procs.append(ctrl)
        col.wait_for(lambda: any("no PlantState" in w for w in _warnings(col, "controller")), 30,
                     "the controller's warning", procs)
        assert "(1 matched)" in next(w for w in _warnings(col, "controller") if "no PlantState" in w)
        stacks = ctrl.stacks()
        assert "Current thread" in stacks and "in run" in stacks, stacks      # the main thread in its loop
        assert ctrl.alive()
        # the re-created subscription receives: a state now published is the controller's first
        col.wait_for(lambda: state_pub.publish(PlantState()) or "first PlantState (seq 0" in ctrl.output(), 10,
                     "the state on the re-created subscription", procs)
        assert "(on the re-created subscription)" in ctrl.output()
        assert ctrl.output().count("no PlantState") == 1, ctrl.output()
    finally:
        stop_all(procs)
        col.close()


def test_realtime_without_controller_stays_safe_and_ends(domain):
    """No controller at all: t = 0 held for start_timeout_s, then gates off, a WARN diagnostic,
    end_of_run at duration_s."""
    duration = 2.0           # longer than the test reader's discovery on a starved machine (>1 s)
    col = Collector(domain, {"plant_state": PlantState, "/diagnostics": DiagnosticArray})
    procs = []
    try:
        # the hold's WARN goes out every diagnostics_period_s (1 s) while it lasts: 4 s, because
        # this reader of the volatile /diagnostics matched the plant 2-3 s late at times (1 run
        # in 4 with a 2 s hold: no held diagnostic received)
        plant = NodeProcess("bike_plant", "plant_node", domain, dict(RT, duration_s=duration, start_timeout_s=4.0))
        procs.append(plant)
        col.wait_for(lambda: any(m.end_of_run for m in col.data["plant_state"]), 20, "end_of_run", procs)
        assert plant.wait(5.0) == 0, plant.output()
        states = col.data["plant_state"]
        assert abs(stamp_ns(states[-1].header.stamp) * 1e-9 - duration) < 1e-6
        assert all(_peak_current(m) == 0.0 for m in states)
        warns = [s for a in col.data["/diagnostics"] for s in a.status if s.level == DiagnosticStatus.WARN]
        assert any("waiting for the first DriveCommand" in s.message for s in warns)
        assert any("sim time held at 0" in s.message for s in warns), "the start hold says so"
        assert "sim time starts without a controller" in plant.output()
    finally:
        stop_all(procs)
        col.close()


def test_realtime_start_holds_t0_until_a_late_session_is_heard(domain):
    """A session that joins late still rides its profile from t = 0: the plant holds sim time
    at 0 (seq 0 re-published) until the controller's first answer, and the controller's first
    answer waits for the session's Command for t = 0. Before, sim time ran from the plant's
    start and the first seconds were ridden on the config's command0."""
    duration = 1.0
    col = Collector(domain, {"plant_state": PlantState, "controller_status": ControllerStatus})
    procs = []
    try:
        procs.append(NodeProcess("bike_plant", "plant_node", domain, dict(RT, duration_s=duration)))
        procs.append(NodeProcess("bike_controller", "controller_node", domain, RT))
        states = col.data["plant_state"]
        col.wait_for(lambda: len(states) > 0, 20, "the held PlantState", procs)
        # the session is later than command_wait_s (2 s): nothing may run meanwhile (discovery
        # matched a late participant 2-3 s late here)
        time.sleep(3.0)
        early = list(states)
        assert {int(m.seq) for m in early} == {0} and {stamp_ns(m.header.stamp) for m in early} == {0}, \
            "sim time held at 0 without a session"
        assert not col.data["controller_status"], "the controller waits for the session's first Command"
        # ... and says so once command_wait_s has passed (a graph with no session stays there)
        col.wait_for(lambda: "holding t = 0 for the session" in procs[1].output(), 10,
                     "the controller's t = 0 hold warning", procs)
        procs.append(NodeProcess("bike_session", "session_node", domain,
                                 {"duration_s": duration, "config_path": str(CONFIG)}))
        col.wait_for(lambda: any(m.end_of_run for m in states), 30, "end_of_run", procs)
        status = col.data["controller_status"]
        first = min(status, key=lambda s: s.seq)
        assert first.seq == 0 and first.command == pytest.approx(0.2), "the profile from t = 0 (warm-up at 0.2)"
        assert all(s.command > 0.0 for s in status), "never the config's command0 = 0"
        t_end = stamp_ns(states[-1].header.stamp) * 1e-9
        assert t_end == pytest.approx(duration, abs=1e-6)
    finally:
        stop_all(procs)
        col.close()


@pytest.mark.faults
@pytest.mark.timeout(180)
def _restart_onto_a_stale_port(repro, victim, restart, verdict, ready, col, live, procs):
    """Kill ``victim`` in its shared-memory listener's window (tools/shm_stale_port_repro.py's
    way) and start ``restart()`` on its port; ``verdict(new)`` says "deaf" (it found itself on
    the stale port) or "heard" (it was reached at once) or None (not yet). About 1 kill in 15
    in the window still leaves the writer on the live segment: the premise did not happen, so
    it is forced again (after ``ready()``), up to 3 times. Returns the deaf process."""
    for attempt in range(3):
        ports = shm_ports.own_ports(victim.pid)
        hit = repro.find_data_listener(ports)
        assert hit, f"no active shared-memory listener in {victim.name}'s data port ({ports})"
        assert repro.kill_in_window(victim.pid, *hit[1], 60.0) is not None, "the window was not caught in 60 s"
        victim.proc.wait(10)
        time.sleep(1.0)
        victim = restart()
        procs.append(victim)
        said = []
        col.wait_for(lambda: said.append(verdict(victim)) or said[-1], 30,
                     f"the restarted {victim.name}'s first input or its stale-port warning", live + [victim])
        if said[-1] == "deaf":
            return victim
        col.wait_for(ready, 30, f"the loop closed again after restart {attempt + 1}", live + [victim])
    raise AssertionError("no kill in the window left the restarted node deaf in 3 attempts "
                         "(has a Fast DDS update fixed the stale port? see test_shm_ports.py)")


def _started_over(node, writer_pid: int, stop: bool = True) -> str:
    """The node's log names ``writer_pid`` among the writers to a deleted segment of its ports
    and says it started over on fresh ports (the test process, which sent it messages, may be
    among the writers too); with ``stop``, a Ctrl-C then ends it with exit code 0. Returns the log."""
    out = node.output()
    writers = re.search(r"pid\(s\) ([\d, ]+) still write to a deleted segment", out)
    assert writers and str(writer_pid) in writers.group(1).split(", "), out[-3000:]
    assert "starting over with a new DDS participant on fresh ports" in out, out[-3000:]
    assert "on fresh shared-memory ports" in out, out[-3000:]
    if stop:
        node.signal(signal.SIGINT)
        assert node.wait(15.0) == 0, node.output()[-3000:]
    return out


def test_a_controller_restarted_on_a_stale_shared_memory_port_starts_over_on_fresh_ports(domain):
    """The Fast DDS stale port, forced: the first controller is killed while its shared-memory
    listener is in use but neither waiting nor processing, so the running plant keeps writing
    PlantStates into that port's old segment, and a second controller, which takes the same
    port, gets none. It says so, names the plant as the writer to a deleted segment, starts
    over with a new DDS participant on fresh ports (bike_plant.loop.start_over_on_fresh_ports), and the
    loop closes again: braking resumes."""
    repro = tool_module("shm_stale_port_repro")
    col = Collector(domain, {"plant_state": PlantState, "controller_status": ControllerStatus})
    procs = []
    try:
        cmd_pub = col.publisher(Command, "command")
        plant = NodeProcess("bike_plant", "plant_node", domain, dict(RT, duration_s=0.0))
        ctrl = NodeProcess("bike_controller", "controller_node", domain, RT)
        procs += [plant, ctrl]
        states = col.data["plant_state"]

        def braking():
            cmd_pub.publish(msgconv.command_msg(0.5, 0, 0))
            return len(states) > 50 and all(m.faults == 0 and _peak_current(m) > 10 for m in states[-20:])
        col.wait_for(braking, 30, "braking under the first controller", procs)

        def verdict(c):
            out = c.output()
            first = out.find("first PlantState")
            warned = out.find("starting over")
            return "deaf" if warned >= 0 and (first < 0 or warned < first) else "heard" if first >= 0 else None
        ctrl2 = _restart_onto_a_stale_port(
            repro, ctrl, lambda: NodeProcess("bike_controller", "controller_node", domain, RT), verdict, braking,
            col, [plant], procs)
        k = len(states)
        col.wait_for(lambda: braking() and len(states) > k + 50, 60, "braking again", [plant, ctrl2])
        _started_over(ctrl2, plant.pid)
    finally:
        stop_all(procs)
        col.close()


def _braking_under_a_controller(col, domain, procs):
    """A realtime plant and controller (added to ``procs``), the test as the session, braking:
    (plant, controller, the PlantStates heard, braking(since=0)), where braking(k) re-sends the
    Command and says whether the states since index k brake with current and no fault."""
    cmd_pub = col.publisher(Command, "command")
    plant = NodeProcess("bike_plant", "plant_node", domain, dict(RT, duration_s=0.0))
    ctrl = NodeProcess("bike_controller", "controller_node", domain, RT)
    procs += [plant, ctrl]
    states = col.data["plant_state"]

    def braking(since=0):
        cmd_pub.publish(msgconv.command_msg(0.5, 0, 0))
        new = states[since:]
        return len(new) > 50 and all(m.faults == 0 and _peak_current(m) > 10 for m in new[-20:])
    col.wait_for(braking, 30, "braking under the controller", procs)
    return plant, ctrl, states, braking


def test_a_plant_restarted_on_a_stale_shared_memory_port_starts_over_on_fresh_ports(domain):
    """The same failure the other way round: a plant killed in its listener's window and
    restarted (a new run, t = 0 held for the first DriveCommand) gets none of the running
    controller's DriveCommands, which go to the old segment. Nothing has run yet, so it starts
    over on fresh ports (bike_plant.node.PlantNode._check_deaf_start), names the controller,
    and the new run brakes under it."""
    repro = tool_module("shm_stale_port_repro")
    col = Collector(domain, {"plant_state": PlantState})
    procs = []
    try:
        plant, ctrl, states, braking = _braking_under_a_controller(col, domain, procs)
        marks = []

        def restart():
            marks.append(len(states))
            return NodeProcess("bike_plant", "plant_node", domain, dict(RT, duration_s=0.0))

        def verdict(p):
            if "starting over" in p.output():
                return "deaf"
            # the new run's t = 0 is held until its first DriveCommand: later seqs mean it heard one
            return "heard" if any(m.seq > 20 for m in states[marks[-1]:]) else None
        plant2 = _restart_onto_a_stale_port(repro, plant, restart, verdict, lambda: braking(marks[-1]),
                                            col, [ctrl], procs)
        # the restarted plant is the one on the stale port: nobody writes to a deleted segment of
        # the running controller's (its lock was held all along), which stays reachable
        assert not shm_ports.writers_to_deleted(shm_ports.own_ports(ctrl.pid))
        k = len(states)
        col.wait_for(lambda: braking(k) and states[-1].seq > 50, 60, "the new run braking", [ctrl, plant2])
        _started_over(plant2, ctrl.pid)
    finally:
        stop_all(procs)
        col.close()


def test_a_session_restarted_on_a_stale_shared_memory_port_starts_over_on_fresh_ports(domain):
    """The stale port under the session: killed in its listener's window and restarted, it
    gets none of the running plant's /clock (which goes to the old segment) and would wait
    for good. Nothing is played yet, so it says so, names the plant, starts over on fresh
    ports (session_node._check_deaf_start) and follows the ride again."""
    repro = tool_module("shm_stale_port_repro")
    col = Collector(domain, {"session_status": SessionStatus})
    procs = []
    try:
        plant = NodeProcess("bike_plant", "plant_node", domain, dict(RT, duration_s=0.0))
        ctrl = NodeProcess("bike_controller", "controller_node", domain, RT)
        session_params = {"duration_s": 600.0, "config_path": str(CONFIG)}
        session = NodeProcess("bike_session", "session_node", domain, session_params)
        procs += [plant, ctrl, session]
        statuses = col.data["session_status"]
        marks = [0]

        def running():
            return any(m.state == SessionStatus.STATE_RUNNING for m in statuses[marks[-1]:])
        col.wait_for(running, 30, "the session running", procs)

        def restart():
            marks.append(len(statuses))
            return NodeProcess("bike_session", "session_node", domain, session_params)

        def verdict(s):
            return "deaf" if "starting over" in s.output() else "heard" if running() else None
        session2 = _restart_onto_a_stale_port(repro, session, restart, verdict, running, col, [plant, ctrl], procs)
        # the deaf one published WAITING only: RUNNING since the restart is the started-over node's
        col.wait_for(running, 30, "the restarted session running again", [plant, ctrl, session2])
        _started_over(session2, plant.pid)
    finally:
        stop_all(procs)
        col.close()


def _unlink_port_segments(pid: int) -> list:
    """Force the stale-port signature on a running node without the kill: map its data port's
    segment and remove its name, as the new participant that takes a killed one's port does
    (its writers then map a deleted segment, and a writer that opens the port later makes a new
    segment the node never reads). The data port is the highest: the other one is the domain's
    shared discovery port (tools/shm_stale_port_repro.find_data_listener). Returns the map
    (close it at the end)."""
    import mmap
    ports = shm_ports.own_ports(pid)
    assert ports, f"the shared-memory ports of pid {pid}"
    maps = []
    for port in ports[-1:]:
        path = os.path.join(shm_ports.SHM_DIR, f"fastrtps_port{port}")
        with open(path, "r+b") as f:
            maps.append(mmap.mmap(f.fileno(), 0))
        os.unlink(path)
    return maps


def _end(procs, col, maps) -> None:
    stop_all(procs)
    col.close()
    for m in maps:
        m.close()


def _force_a_stale_peer(node, col, procs, maps) -> str:
    """_unlink_port_segments on a running ``node`` (its maps added to ``maps``), then wait for
    it to start over; returns its log, which names this test process among the writers."""
    maps += _unlink_port_segments(node.pid)
    col.wait_for(lambda: "on fresh shared-memory ports" in node.output(), 30,
                 f"the {node.name} starting over on fresh ports", procs)
    return _started_over(node, os.getpid(), stop=False)


def test_a_running_session_that_its_peers_cannot_reach_starts_over_on_fresh_ports(domain):
    """Running, the session hears the plant's /clock, yet a peer writes to a deleted segment of
    its port: after a kill -9 a restarted session took the killed one's port, the plant's
    watchdog re-opened it but the test's reader never did, and its SessionStatus never reached
    the test (CI, 2026-12-07). The signature is forced here without the kill: the test process
    maps the running session's port segments and removes their names, as the new participant
    that takes a killed one's port does (the plant and controller, which write to it, then map
    a deleted segment too). Seen at two looks in a row (DEAF_CHECK_S apart) it is no healing
    watchdog's: the session says so, names the writers, starts over on fresh ports and goes on
    following /clock: its statuses and Commands reach the test again."""
    col = Collector(domain, {"session_status": SessionStatus, "command": Command})
    procs = []
    maps = []
    try:
        plant = NodeProcess("bike_plant", "plant_node", domain, dict(RT, duration_s=0.0))
        ctrl = NodeProcess("bike_controller", "controller_node", domain, RT)
        session = NodeProcess("bike_session", "session_node", domain,
                              {"duration_s": 600.0, "config_path": str(CONFIG)})
        procs += [plant, ctrl, session]
        statuses = col.data["session_status"]
        col.wait_for(lambda: any(m.state == SessionStatus.STATE_RUNNING for m in statuses), 30,
                     "the session running", procs)
        _force_a_stale_peer(session, col, procs, maps)
        mark, commands = len(statuses), col.data["command"]
        command_mark = len(commands)
        col.wait_for(lambda: any(m.state == SessionStatus.STATE_RUNNING for m in statuses[mark:]), 30,
                     "the started-over session's RUNNING status at the test", procs)
        col.wait_for(lambda: len(commands) > command_mark + 10, 30, "the started-over session's Commands", procs)
        _started_over(session, plant.pid)
    finally:
        _end(procs, col, maps)


def test_a_running_controller_that_a_peer_cannot_reach_starts_over_on_fresh_ports(domain):
    """A controller restarted after a kill -9 that hears the plant while another peer (the
    session here) still writes to the killed one's deleted segment: the plant's watchdog
    re-opened the port, the session's did not. Forced as for the session (_unlink_port_segments):
    seen at two looks in a row the controller says so once (log and a WARN diagnostic naming
    the writers), starts over on fresh ports, and the lockstep exchange resumes: braking again."""
    col = Collector(domain, {"plant_state": PlantState, "/diagnostics": DiagnosticArray})
    procs = []
    maps = []
    try:
        plant, ctrl, states, braking = _braking_under_a_controller(col, domain, procs)
        out = _force_a_stale_peer(ctrl, col, procs, maps)
        assert out.count("after it was first seen: starting over") == 1, out[-3000:]
        warns = [st.message for arr in col.data["/diagnostics"] for st in arr.status
                 if st.level == DiagnosticStatus.WARN and "after it was first seen" in st.message]
        assert warns and str(plant.pid) in warns[0], warns
        k = len(states)
        col.wait_for(lambda: braking(k) and len(states) > k + 100, 30, "braking again after the start over", procs)
        _started_over(ctrl, plant.pid)
    finally:
        _end(procs, col, maps)



def test_a_running_recorder_that_a_peer_cannot_reach_goes_on_in_the_same_bag_on_fresh_ports(domain, tmp_path):
    """A recorder restarted after a kill -9 that hears the plant while another peer still
    writes to the killed one's deleted segment would miss that peer's data for good. Forced as
    for the session (_unlink_port_segments): seen at two looks in a row it says so once (log and
    a WARN diagnostic naming the writers) and hands the bag over to a new participant on fresh
    ports (recorder_node._hand_over). The same bag goes on, nothing lost or written twice: the
    PlantState seqs in it are contiguous and each once, and so are the controller's answers."""
    from std_msgs.msg import UInt64

    from bike_session.bags import read_topic
    col = Collector(domain, {"plant_state": PlantState, "recorder_progress": UInt64, "/diagnostics": DiagnosticArray})
    procs = []
    maps = []
    try:
        plant, ctrl, states, braking = _braking_under_a_controller(col, domain, procs)
        rec = NodeProcess("bike_session", "recorder_node", domain,
                          dict(NO_SESSION_RECORDER, record_dir=str(tmp_path), bag_name="run1"))
        procs.append(rec)
        progress = col.data["recorder_progress"]
        col.wait_for(lambda: braking() and len(progress) > 3, 30, "the recorder's progress", procs)
        out = _force_a_stale_peer(rec, col, procs, maps)
        assert out.count("after it was first seen: starting over") == 1, out[-3000:]
        col.wait_for(lambda: f"recording on into {tmp_path / 'run1'}" in rec.output(), 10, "the hand-over", procs)
        warns = [st.message for arr in col.data["/diagnostics"] for st in arr.status
                 if st.level == DiagnosticStatus.WARN and "after it was first seen" in st.message]
        assert warns and str(plant.pid) in warns[0], warns
        k = len(progress)
        col.wait_for(lambda: braking() and len(progress) > k + 3, 30, "the recorder's progress after the hand-over",
                     procs)
        plant.stop()                  # the recorder drains until the graph falls silent
        _started_over(rec, plant.pid)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["run1"]
        seqs = [m.seq for m in read_topic(tmp_path / "run1", "plant_state")]
        assert len(seqs) > 200 and seqs == list(range(seqs[0], seqs[0] + len(seqs))), seqs
        answered = [m.seq for m in read_topic(tmp_path / "run1", "controller_status")]
        assert len(answered) == len(set(answered)) and len(answered) > 200
        assert any("after it was first seen" in st.message for arr in read_topic(tmp_path / "run1", "/diagnostics")
                   for st in arr.status)
    finally:
        _end(procs, col, maps)


def test_a_running_plant_that_a_peer_cannot_reach_starts_over_on_fresh_ports_and_runs_on(domain, tmp_path):
    """A plant restarted after a kill -9 that hears the controller while another peer (a
    recorder, a session) still writes to the killed one's deleted segment: what that peer sends
    the plant goes there (its readers' acknowledgments and repair requests, its data; measured
    in docs/RELIABILITY.md: a lost state is never repaired, the end_of_run state waits the whole
    END_ACK_TIMEOUT_S; the lockstep test below shows the progress reports lost). Forced without
    the kill (_unlink_port_segments): the recorder started afterwards opens the plant's port by
    its name, a new segment the plant never reads, as the stale writer's handle does. Realtime
    here: seen at two looks in a row the plant says
    so once (log and a WARN diagnostic naming the writers) and starts over on fresh ports with
    its simulation as it was (PlantNode.hand_over): the seqs go on without a gap or a repeat at
    the test around the start over and in the bag from then on, and the energy ledger goes on
    from where it was (no physics reset)."""
    from std_msgs.msg import UInt64

    from bike_session.bags import read_topic
    col = Collector(domain, {"plant_state": PlantState, "recorder_progress": UInt64, "/diagnostics": DiagnosticArray})
    procs = []
    maps = []
    try:
        plant, ctrl, states, braking = _braking_under_a_controller(col, domain, procs)
        maps += _unlink_port_segments(plant.pid)
        rec = NodeProcess("bike_session", "recorder_node", domain,
                          dict(NO_SESSION_RECORDER, record_dir=str(tmp_path), bag_name="run1"))
        procs.append(rec)
        col.wait_for(lambda: "on fresh shared-memory ports" in plant.output(), 30,
                     "the plant starting over on fresh ports", procs)
        out = _started_over(plant, ctrl.pid, stop=False)
        assert out.count("after it was first seen: starting over") == 1, out[-3000:]
        warns = [st.message for arr in col.data["/diagnostics"] for st in arr.status
                 if st.level == DiagnosticStatus.WARN and "after it was first seen" in st.message]
        assert warns and str(ctrl.pid) in warns[0], warns
        k = len(states)
        progress = col.data["recorder_progress"]
        col.wait_for(lambda: braking(k) and len(states) > k + 200 and len(progress) > 3, 30,
                     "braking on, and recorded, after the start over", procs)
        run = [m for m in states if m.seq > 0]           # (t = 0 is re-published until the first DriveCommand)
        seqs = [m.seq for m in run]
        assert all(b > a for a, b in zip(seqs, seqs[1:])), "no seq again, none back (no new run)"
        handed_over_at = int(re.search(r"going on with the run at seq (\d+)", plant.output()).group(1))
        around = [m for m in run if abs(m.seq - handed_over_at) <= 100]
        assert [m.seq for m in around] == list(range(handed_over_at - 100, handed_over_at + 101)), \
            "every state around the start over reached the test"
        # the energy ledger is cumulative since the start: a new simulation would begin it again at 0
        jumps = [(a.seq, a.energy_mech_in_j, b.energy_mech_in_j) for a, b in zip(around, around[1:])
                 if abs(b.energy_mech_in_j - a.energy_mech_in_j) > 10.0]
        assert around[-1].energy_mech_in_j > 100.0 and not jumps, (around[-1].energy_mech_in_j, jumps)
        plant.stop()                  # the recorder drains until the graph falls silent
        assert rec.stop(15.0) == 0, rec.output()[-3000:]
        bagged = [m.seq for m in read_topic(tmp_path / "run1", "plant_state")]
        assert bagged[0] > 0, "the run went on: no seq 0 again"
        # from the new participant's first state on: before it, a state lost on the way to the
        # recorder was never sent again (its repair requests went to the unread segment: seen,
        # a hole of 248 states), which is the loss the start over ends
        new = [seq for seq in bagged if seq > handed_over_at]
        assert len(new) > 200 and new == list(range(handed_over_at + 1, handed_over_at + 1 + len(new))), new[:20]
    finally:
        _end(procs, col, maps)



@pytest.mark.timeout(120)
def test_a_running_lockstep_plant_that_a_restarted_recorder_cannot_reach_starts_over_and_keeps_pace(ros_domain,
                                                                                                   tmp_path):
    """What a running plant loses to a peer that cannot reach it, recorded in lockstep: the
    recorder's progress reports. Forced (_unlink_port_segments) with a second recorder started
    mid-run: it opens the plant's port by its name, a new segment the plant never reads, as a
    stale writer's handle after a kill -9 does. It records every state, but once the first
    recorder is gone, its reports reach the plant no more: without the running look the plant
    stops its window ahead of the first one's last report, hears nothing for recorder_timeout_s,
    says "the recorder reported nothing ... going on without waiting for it" (ERROR,
    FAULT_RECORDER_LOST) and runs on unthrottled. With it the
    plant says so once, names the writers to its deleted segment, starts over on fresh ports
    with the same run (PlantNode.hand_over), and the new recorder's reports pace it to the end:
    no RECORDER_LOST, the seqs at the test only go on (no seq 0 again),
    and the new bag holds every state from the start over to the end_of_run."""
    from bike_session.bags import read_topic
    from test_faults_kill import _graph
    col = Collector(ros_domain, {"plant_state": PlantState})
    maps = []
    # recorder_timeout_s: the plant's default (the look fires 3-6 s after the signature appears)
    procs = _graph(col, ros_domain, tmp_path, 10.0, plant_extra={"recorder_timeout_s": 10.0})
    everyone = list(procs.values())
    plant, rec = procs["plant"], procs["recorder"]
    try:
        states = col.data["plant_state"]
        col.wait_for(lambda: states and states[-1].seq >= 300, 60, "seq 300", everyone)
        maps += _unlink_port_segments(plant.pid)
        rec2 = NodeProcess("bike_session", "recorder_node", ros_domain,
                           {"record_dir": str(tmp_path), "bag_name": "run2", "flush_period_s": 0.5})
        everyone.append(rec2)
        readers = len(col.node.get_subscriptions_info_by_topic("/bike/plant_state"))
        col.wait_for(lambda: len(col.node.get_subscriptions_info_by_topic("/bike/plant_state")) > readers, 30,
                     "the second recorder's plant_state reader", everyone)
        mark = len(states)
        col.wait_for(lambda: len(states) > mark + 1000, 30, "the run going on with two recorders", everyone)
        rec.signal(signal.SIGINT)
        time.sleep(0.3)
        rec.signal(signal.SIGINT)             # a second one stops it now (no drain)
        assert rec.wait(15) == 0, rec.output()[-3000:]
        assert plant.wait(90) == 0, plant.output()[-3000:]
        out = _started_over(plant, procs["controller"].pid, stop=False)
        assert out.count("after it was first seen: starting over") == 1, out[-3000:]
        assert "reported nothing" not in out, out[-3000:]
        assert procs["session"].wait(15) == 0, procs["session"].output()[-3000:]
        rec2.signal(signal.SIGINT)
        assert rec2.wait(15) == 0, rec2.output()[-3000:]
    finally:
        stop_all(everyone)
        col.close()
        for m in maps:
            m.close()
    assert not any(m.faults & PlantState.FAULT_RECORDER_LOST for m in states)
    seqs = [m.seq for i, m in enumerate(states) if i == 0 or m.seq != states[i - 1].seq]   # (re-published copies)
    assert all(b > a for a, b in zip(seqs, seqs[1:])) and states[-1].end_of_run, "one run, no seq again, none back"
    # from the new participant's first state on (before it, what the second recorder lost on the
    # way was never sent again: test_a_running_plant_that_a_peer_cannot_reach_...)
    handed_over_at = int(re.search(r"going on with the run at seq (\d+)", out).group(1))
    bagged = read_topic(tmp_path / "run2", "plant_state")
    assert [m.seq for m in bagged if m.seq >= handed_over_at] == list(range(handed_over_at, 10001))
    assert bagged[-1].end_of_run


def test_a_session_without_a_plant_says_waiting_every_second(domain):
    """Before the first /clock the session re-publishes its WAITING status every second (and
    looks for a stale port then): its timer runs on the steady clock, because under the
    configs' use_sim_time a ROS-time timer would wait for the very /clock that is missing.
    After NO_CLOCK_WARN_S it says once that it waits for a plant."""
    col = Collector(domain, {"session_status": SessionStatus})
    session = NodeProcess("bike_session", "session_node", domain, {"duration_s": 10.0, "config_path": str(CONFIG)})
    try:
        statuses = col.data["session_status"]
        col.wait_for(lambda: len(statuses) >= 4, 20, "four WAITING statuses", [session])
        assert {m.state for m in statuses} == {SessionStatus.STATE_WAITING}
        # and it says once why nothing happens (no plant on this domain)
        col.wait_for(lambda: "no /clock in the" in session.output(), 20, "the session's no-/clock warning",
                     [session])
        assert "waiting for a plant on this ROS_DOMAIN_ID" in session.output()
        assert "use_sim_time: true" in CONFIG.read_text()
    finally:
        session.stop()
        col.close()


def test_a_recorder_restarted_on_a_stale_shared_memory_port_starts_over_on_fresh_ports(domain, tmp_path):
    """The stale port under the recorder: killed in its listener's window and restarted into a
    new bag, it gets nothing from the running graph (the plant, the controller and this test
    write into the old segment). Its bag still empty, it says so, names the plant, removes the
    empty bag, starts over on fresh ports (recorder_node._start_over) and records the ride
    into the same bag, which reads back after a Ctrl-C."""
    from std_msgs.msg import UInt64

    from bike_session.bags import read_topic
    repro = tool_module("shm_stale_port_repro")
    col = Collector(domain, {"recorder_progress": UInt64})
    procs = []
    try:
        plant = NodeProcess("bike_plant", "plant_node", domain, dict(RT, duration_s=0.0))
        ctrl = NodeProcess("bike_controller", "controller_node", domain, RT)
        rec = NodeProcess("bike_session", "recorder_node", domain,
                          dict(NO_SESSION_RECORDER, record_dir=str(tmp_path), bag_name="run1"))
        procs += [plant, ctrl, rec]
        progress = col.data["recorder_progress"]
        cmd_pub = col.publisher(Command, "command")      # the session's part: t = 0 waits for it
        marks = [0]

        def recording():
            cmd_pub.publish(msgconv.command_msg(0.5, 0, 0))
            return len(progress) > marks[-1] + 5
        col.wait_for(recording, 30, "the recorder's progress", procs)
        names = iter(f"run{n}" for n in range(2, 10))

        def restart():
            marks.append(len(progress))
            return NodeProcess("bike_session", "recorder_node", domain,
                               dict(NO_SESSION_RECORDER, record_dir=str(tmp_path), bag_name=next(names)))

        def verdict(r):
            return "deaf" if "starting over" in r.output() else "heard" if recording() else None
        rec2 = _restart_onto_a_stale_port(repro, rec, restart, verdict, recording, col, [plant, ctrl], procs)
        # the deaf one recorded nothing: progress since the restart is the started-over node's
        col.wait_for(recording, 30, "the restarted recorder recording", [plant, ctrl, rec2])
        plant.stop()                  # the recorder drains until the graph falls silent
        out = _started_over(rec2, plant.pid)
        bag = re.search(r"the empty bag (\S+) is made again", out).group(1)
        assert len(read_topic(bag, "plant_state")) > 50, rec2.output()[-3000:]
    finally:
        stop_all(procs)
        col.close()
