"""Reliability suite: message loss and delay between controller and plant (realtime mode).

A test-only relay node in its own process (test/fault_relay.py) sits between the controller
(its drive_command remapped to drive_command_raw) and the plant, and follows a seeded
schedule: clean, 30 % loss, 10 ms delay, 20 % loss + 25 ms delay, blackout, clean again.
Then the controller is killed with SIGKILL. Expected: lost commands are held (the last one
re-used), delays below command_timeout_s cause no fault, the phase current stays bounded
(no runaway), a blackout or a dead controller puts the plant in its safe state within 2
batches of the timeout (in sim time, measured by the plant), the ERROR diagnostic says
why, and commands coming back clear the fault."""
from __future__ import annotations

import json
import os
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from node_harness import (CONFIG, ROOT, Collector, NodeProcess, domain,  # noqa: F401
                          log_file, publish_wall_times, stamp_ns, stop_all)

from bike_msgs.msg import Command, PlantState  # noqa: E402
from bike_plant import msgconv  # noqa: E402
from bike_plant.config import load_config  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402

pytestmark = [pytest.mark.timeout(120), pytest.mark.faults]

CFG = load_config(CONFIG)
BATCH_S = CFG["batch_periods"] * CFG["control_period_s"]
# command_timeout_s for this test. On this 2-core machine the test's four busy processes
# saturate both cores, and DDS then at times delivers nothing to one reader for ~1 s while the
# writer goes on (the plant's DriveCommands: 0.92-0.98 s gaps measured, over shared memory and
# over UDP alike, with the nodes of before the HotWait change too, while the test process got
# the relay's output without a gap). The plant rightly times out on such a gap; what this test
# checks is that injected loss and delay alone never make it do so.
TIMEOUT_S = 1.5
FAULT = PlantState.FAULT_COMMAND_TIMEOUT
# [t_start_s, drop probability, delay_s] from the relay's origin (first braking DriveCommand);
# the blackout outlasts the timeout by 0.5 s
SCHEDULE = [[0.0, 0.0, 0.0], [1.0, 0.3, 0.0], [2.0, 0.0, 0.010], [3.0, 0.2, 0.025], [4.0, 1.0, 0.0],
            [6.0, 0.0, 0.0]]
# after the blackout: the fault must clear within CLEAR_WITHIN_S (wall), then hold for BACK_S
CLEAR_WITHIN_S = 10.0
BACK_S = 0.7
LIMIT_A = CFG["controller"]["current_limit_a"]
TRIP_A = CFG["bldc"]["overcurrent_trip_a"]
OVERCURRENT = PlantState.FAULT_OVERCURRENT
# one period of di/dt above the trip (checked at period starts): a phase sees at most
# 2/3 (v_dc + E_LL) across L, with v_dc up to Voc + R_batt * trip (no DC-link capacitor: a
# blanked period's freewheeling current lifts the bus) and E_LL at 5400 rpm
V_MAX = CFG["battery"]["v_full_v"] + CFG["battery"]["r_internal_ohm"] * TRIP_A
E_LL_MAX = CFG["bldc"]["ke_v_per_rpm"] * 5400.0
BOUND_A = TRIP_A + CFG["control_period_s"] * 2.0 / 3.0 * (V_MAX + E_LL_MAX) / CFG["bldc"]["inductance_h"]


class Relay(NodeProcess):
    dumps_stacks = False          # a plain script (no SIGUSR1 handler: the signal would end it)

    def __init__(self, domain: int, schedule, seed: int):
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                   PYTHONUNBUFFERED="1")
        self.log = log_file("relay")
        self.name = "fault_relay"
        self.proc = subprocess.Popen([sys.executable, str(pathlib.Path(__file__).with_name("fault_relay.py")),
                                      json.dumps(schedule), str(seed)], stdout=self.log, stderr=subprocess.STDOUT,
                                     env=env, cwd=str(ROOT), start_new_session=True)


def _peak(m) -> float:
    return float(np.max(np.abs(np.asarray(m.current_samples_a)))) if len(m.current_samples_a) else \
        float(np.max(np.abs(np.asarray(m.phase_current_a))))


def _safe_state_latency(col, states, stamps, after_wall: float):
    """(sim seconds from the last DriveCommand received to the start of the first safe batch,
    index of the first faulted state) for the first timeout after ``after_wall``."""
    i = next(i for i in range(len(states)) if stamps[i] > after_wall and states[i].faults & FAULT)
    t_batch_start = stamp_ns(states[i].header.stamp) * 1e-9 - BATCH_S
    t_fault_ns = stamp_ns(states[i].header.stamp)
    for arr in col.data["/diagnostics"]:
        for s in arr.status:
            if (s.name.endswith("plant") and s.level == DiagnosticStatus.ERROR
                    and stamp_ns(arr.header.stamp) == t_fault_ns):
                values = {kv.key: kv.value for kv in s.values}
                assert "no DriveCommand" in s.message and "safe state" in s.message, s.message
                return t_batch_start - float(values["last_drive_command_sim_s"]), i
    raise AssertionError("no ERROR diagnostic with the faulted state's stamp")


def _sim_s(m) -> float:
    return stamp_ns(m.header.stamp) * 1e-9


def _cleared(states) -> int | None:
    """Index of the first state without the timeout fault after the first one with it (the
    blackout's, as no phase before it may time out), or None."""
    f = next((f for f, m in enumerate(states) if m.faults & FAULT), None)
    if f is None:
        return None
    return next((k for k in range(f, len(states)) if not states[k].faults & FAULT), None)


def _relay_t0(relay) -> float | None:
    """time.monotonic() of the first DriveCommand the relay received (its schedule's origin)."""
    for line in relay.output().splitlines():
        if line.startswith("relay t0 "):
            return float(line.split()[2])
    return None


def _largest_gap(stamps, a: float, b: float):
    """(largest gap between consecutive stamps in [a, b], where it starts, relative to b) [s]"""
    inside = [t for t in stamps if a <= t <= b]
    if len(inside) < 2:
        return (round(b - a, 3), None)
    d = np.diff(inside)
    k = int(np.argmax(d))
    return (round(float(d[k]), 3), round(inside[k] - b, 3))


def test_loss_and_delay_hold_setpoints_and_time_out_to_safe_state(domain):
    # the test follows the plant only: the relay reports when the controller's stream began
    col = Collector(domain, {"plant_state": PlantState, "/diagnostics": DiagnosticArray})
    procs = []
    try:
        cmd_pub = col.publisher(Command, "command")
        rt = {"sync_mode": "realtime"}
        procs.append(NodeProcess("bike_plant", "plant_node", domain,
                                 dict(rt, duration_s=0.0, command_timeout_s=TIMEOUT_S)))
        relay = Relay(domain, SCHEDULE, seed=6)
        procs.append(relay)
        # the controller publishes on drive_command_raw, which the relay forwards
        ctrl = NodeProcess("bike_controller", "controller_node", domain, rt,
                           remaps={"drive_command": "drive_command_raw"})
        procs.append(ctrl)
        col.wait_for(lambda: cmd_pub.get_subscription_count() >= 1, 30, "controller's command subscription", procs)
        states, stamps = col.data["plant_state"], col.stamps["plant_state"]
        # the realtime plant holds t = 0 until the first answer, and the controller answers only
        # once a Command came: this reader sees the run from its start if it matched first
        # (matching took ~3 s at times: the clean phase went unseen)
        col.wait_for(lambda: len(states) > 0, 30, "the plant's held first state", procs)

        def commanding(pred):
            def check():
                cmd_pub.publish(msgconv.command_msg(0.5, 0, 0))
                return pred()
            return check
        col.wait_for(commanding(lambda: _relay_t0(relay) is not None), 30, "the first DriveCommand", procs)
        t0 = _relay_t0(relay)
        col.wait_for(commanding(lambda: time.monotonic() > t0 + SCHEDULE[-1][0]), 15, "the schedule", procs)

        def braking_again():
            """the plant left the blackout's safe state and ran BACK_S on (sim time: the test
            process can get states seconds late, so receipt times say little here)"""
            k = _cleared(states)
            return k is not None and stamp_ns(states[-1].header.stamp) * 1e-9 >= _sim_s(states[k]) + BACK_S
        # commands are back: the fault clears once they reach the plant (a loaded machine can
        # hold a reader's samples back ~1 s, see TIMEOUT_S: the wait is bounded, not fixed)
        col.wait_for(commanding(braking_again), CLEAR_WITHIN_S, "the fault to clear after the blackout", procs)
        # the controller dies: the plant times out again, by itself
        t_kill = time.monotonic()
        ctrl.signal(signal.SIGKILL)
        n_kill = len(states)
        col.wait_for(lambda: sum(1 for m in states[n_kill:] if m.faults & FAULT) > 100, 15,
                     "100 safe batches after the controller died", procs[:2])
        assert procs[0].alive() and relay.alive()
        states, received = list(states), list(stamps)
    finally:
        stop_all(procs)
        col.close()
    print(relay.output())
    # when the plant made each state, on the wall clock, not when the test got it: the test
    # process is one of the busy ones and at times gets nothing for ~1 s, then a burst
    stamps = publish_wall_times(states, received)

    def window(a, b):
        """states the plant made in [t0 + a + 0.15, t0 + b] (the phase, its first 0.15 s trimmed)"""
        return [m for m, t in zip(states, stamps) if t0 + a + 0.15 <= t <= t0 + b]

    # the whole clean phase (a reliable reader can still lose states: the plant's writer keeps
    # the last 200, and DDS at times delivers nothing to a reader for ~1 s, see TIMEOUT_S)
    clean = window(0.0, 1.0)
    seen = f"{len(clean)} states, plant log:\n{procs[0].output()[-1500:]}"
    assert clean and all(m.faults & ~OVERCURRENT == 0 for m in clean), seen
    assert max(_peak(m) for m in clean) > 3.0, f"the loop brakes at half command (about 34 A); {seen}"
    # No runaway: in realtime a BLDC gate sequence is applied batches after the state it was
    # computed for (late or held; round trips are several batches on a loaded machine) and the
    # hysteresis loop runs open meanwhile (100-210 A peaks were measured before the trip,
    # limit 120 A). The plant's cycle-by-cycle overcurrent trip bounds it to the trip + one
    # period of rise, and says so (FAULT_OVERCURRENT, overcurrent_trip_count).
    bound = BOUND_A
    for (a, drop, delay), (b, _, _) in zip(SCHEDULE[1:4], SCHEDULE[2:5]):
        ph = window(a, b)
        assert len(ph) > 30, (a, len(ph))
        timeouts = [round(t - t0, 3) for m, t in zip(states, stamps)
                    if m.faults & FAULT and t0 + a + 0.15 <= t <= t0 + b]
        if timeouts:
            t_f = t0 + timeouts[0]
            raise AssertionError(f"no timeout with {drop:.0%} loss and {delay * 1e3:g} ms delay: {timeouts[:5]}; "
                                 f"largest PlantState gap in the second before, as the test received them: "
                                 f"{_largest_gap(received, t_f - 1.0, t_f)} s\n--- plant:\n{procs[0].output()[-2000:]}"
                                 f"\n--- controller:\n{ctrl.output()[-2000:]}")
        assert not any(m.faults & PlantState.FAULT_INTERLOCK for m in ph)
        print(f"phase {drop:.0%} loss, {delay * 1e3:g} ms: peak {max(_peak(m) for m in ph):.1f} A, "
              f"mean {np.mean([_peak(m) for m in ph]):.1f} A, {len(ph)} states")
        assert all(np.all(np.isfinite(m.current_samples_a)) for m in ph)
        assert max(_peak(m) for m in ph) <= bound, f"current runaway with {drop:.0%} loss / {delay * 1e3:g} ms"
    # the plant counted held batches (lost / late commands re-used)
    held = [int(kv.value) for a in col.data["/diagnostics"] for s in a.status if s.name.endswith("plant")
            for kv in s.values if kv.key == "held_batches"]
    assert held and max(held) > 10, held[-3:]
    # blackout: safe state within 2 batches of the timeout (sim time, measured by the plant)
    latency, i = _safe_state_latency(col, states, stamps, t0 + SCHEDULE[4][0])
    assert 0 < latency <= TIMEOUT_S + 2 * BATCH_S + 1e-9, latency
    j = next((j for j in range(i, len(states)) if not states[j].faults & FAULT), len(states))
    safe = states[i:j]                  # the safe-state stretch, until commands are back
    assert len(safe) >= 30, len(safe)
    assert max(_peak(m) for m in safe[20:]) < 1e-3, "all gates off: the current decays to 0"
    # commands back: the fault clears and stays clear, braking again
    k = _cleared(states)
    assert k is not None and k > i
    print(f"fault cleared {stamps[k] - t0 - SCHEDULE[5][0]:.3f} s after the blackout ended")
    back = [m for m in states[k:] if _sim_s(m) <= _sim_s(states[k]) + BACK_S]
    assert back and not any(m.faults & FAULT for m in back), \
        f"the fault came back after clearing\n--- plant:\n{procs[0].output()[-2000:]}"
    assert max(_peak(m) for m in back) > 3.0
    # the controller killed: the same again
    latency, i = _safe_state_latency(col, states, stamps, t_kill)
    assert 0 < latency <= TIMEOUT_S + 2 * BATCH_S + 1e-9, latency
    assert states[i + 50:] and max(_peak(m) for m in states[i + 50:]) < 1e-3
    assert max(_peak(m) for m in states) <= bound
    # the trip shows up whenever a current went past it (and only then, up to one period)
    tripped = [m for m in states if m.faults & OVERCURRENT]
    if max(_peak(m) for m in states) > TRIP_A + 1e-9:
        assert tripped and states[-1].overcurrent_trip_count > 0
    assert states[-1].overcurrent_trip_count >= len(tripped)
    for m in tripped:
        assert m.overcurrent_trip_count > 0
    print(f"overcurrent trips: {states[-1].overcurrent_trip_count} periods in {len(tripped)} batches, "
          f"peak {max(_peak(m) for m in states):.1f} A (trip {TRIP_A:g} A, bound {bound:.1f} A)")
