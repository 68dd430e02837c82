"""Drive emulator (bike_plant.can.emulator): physics and firmware in-process, and the
bike-drive-emulator as a separate PROCESS over python-can's udp_multicast bus.

Each process test uses its own UDP port (isolation from parallel runs) and generous
timeouts: the machine has 2 shared cores, so nothing asserts tight timing.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import pathlib
import random
import signal
import struct
import subprocess
import sys
import time
import uuid

import can
import pytest

from bike_plant.can import AxisState, ODriveError, OdriveCanSimple, ProcedureResult
from bike_plant.can.emulator import AverageTorqueDrive, DriveEmulator, DriveFirmware, DriveModelParams
from bike_plant.config import load_config

ROOT = pathlib.Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config" / "bldc_default.yaml"
GROUP = "239.74.163.2"          # IPv4 multicast group (measured reliable on this machine)
WATCHDOG = int(ODriveError.WATCHDOG_TIMER_EXPIRED)


@pytest.fixture(scope="module")
def params() -> DriveModelParams:
    return DriveModelParams.from_config(load_config(CONFIG))


def model_with(params, **changes) -> AverageTorqueDrive:
    p = dataclasses.replace(params, **changes)
    if "load_kind" in changes and changes["load_kind"] in ("prime_mover", "none"):
        p.load = dataclasses.replace(p.load, kind=changes["load_kind"])
    return AverageTorqueDrive(p)


# =======================================================================================
# in-process: physics and firmware
def test_current_loop_is_first_order(params):
    model = model_with(params, load_kind="none", current_tau_s=1e-3)
    for _ in range(4):                    # one time constant in 0.25 ms steps
        model.step(0.25e-3, 10.0)
    assert model.iq_a == pytest.approx(10.0 * (1 - math.exp(-1)), rel=1e-9)
    assert model.torque_estimate_nm == pytest.approx(params.torque_constant_nm_per_a * model.iq_a)


def test_velocity_control_reaches_its_setpoint(params):
    fw = DriveFirmware(model_with(params, load_kind="none", speed0_rpm=0.0), watchdog_timeout_s=0.0)
    assert fw.set_controller_mode(2, 1)
    fw.request_state(AxisState.CLOSED_LOOP_CONTROL, 0.0)
    fw.set_input_vel(20.0, 0.0, 0.0)
    for _ in range(int(3.0 / 0.25e-3)):
        fw.step(0.25e-3)
    assert fw.armed and fw.model.speed_rev_s == pytest.approx(20.0, rel=0.01)


def test_bus_sags_when_motoring_and_rises_when_braking(params):
    for torque_nm, sign in ((2.0, 1.0), (-2.0, -1.0)):
        fw = DriveFirmware(model_with(params, load_kind="prime_mover"), watchdog_timeout_s=0.0)
        fw.request_state(AxisState.CLOSED_LOOP_CONTROL, 0.0)
        fw.set_input_torque(torque_nm, 0.0)
        for _ in range(200):
            fw.step(0.25e-3)
        m = fw.model
        assert m.torque_estimate_nm == pytest.approx(torque_nm, rel=1e-3)
        assert sign * m.bus_current_a > 0 and sign * (m.ocv_v() - m.bus_voltage_v) > 0
        assert m.electrical_power_w == pytest.approx(
            m.mechanical_power_w + params.copper_resistance_ohm * m.iq_a ** 2)


def test_firmware_watchdog_refusal_and_recovery(params):
    fw = DriveFirmware(model_with(params, load_kind="prime_mover"), watchdog_timeout_s=0.5)
    fw.request_state(AxisState.CLOSED_LOOP_CONTROL, 10.0)
    fw.set_input_torque(1.0, 10.2)
    assert not fw.check_watchdog(10.69) and fw.armed
    assert fw.check_watchdog(10.71)
    assert fw.axis_state == AxisState.IDLE and fw.active_errors == WATCHDOG and fw.disarm_reason == WATCHDOG
    assert fw.procedure_result == ProcedureResult.DISARMED and fw.input_torque_nm == 0.0
    fw.step(0.25e-3)
    assert fw.torque_setpoint_nm == 0.0
    fw.request_state(AxisState.CLOSED_LOOP_CONTROL, 11.0)          # refused: errors latched
    assert fw.axis_state == AxisState.IDLE
    fw.clear_errors()
    fw.request_state(AxisState.CLOSED_LOOP_CONTROL, 11.1)
    assert fw.armed and fw.active_errors == 0 and fw.procedure_result == ProcedureResult.BUSY


def test_injected_faults_disarm_and_persist_through_clear_errors(params):
    from bike_plant.can.emulator import parse_fault

    drv = int(ODriveError.DRV_FAULT)
    assert parse_fault("drv_fault") == drv and parse_fault("IDLE") == 0 and parse_fault("0x40") == 0x40
    with pytest.raises(ValueError, match="unknown 'NOPE'"):
        parse_fault("NOPE")
    fw = DriveFirmware(model_with(params, load_kind="prime_mover"), watchdog_timeout_s=0.0)
    fw.request_state(AxisState.CLOSED_LOOP_CONTROL, 0.0)
    fw.set_input_torque(1.0, 0.0)
    fw.inject_fault(0)                                   # IDLE without an error
    assert fw.axis_state == AxisState.IDLE and fw.active_errors == 0 and fw.input_torque_nm == 0.0
    fw.request_state(AxisState.CLOSED_LOOP_CONTROL, 0.1)
    fw.inject_fault(drv, persist=2)                      # a fault whose cause stays for 2 Clear_Errors
    assert fw.axis_state == AxisState.IDLE and fw.active_errors == drv and fw.disarm_reason == drv
    for _ in range(2):
        fw.clear_errors()
        fw.request_state(AxisState.CLOSED_LOOP_CONTROL, 0.2)
        assert not fw.armed and fw.active_errors == drv
    fw.clear_errors()
    fw.request_state(AxisState.CLOSED_LOOP_CONTROL, 0.3)
    assert fw.armed and fw.active_errors == 0
    fw.inject_fault(drv, persist=-1)                     # never clears
    for _ in range(5):
        fw.clear_errors()
    assert fw.active_errors == drv


def test_emulator_answers_requests_in_process(params):
    channel = uuid.uuid4().hex
    drive_bus = can.Bus(interface="virtual", channel=channel)
    host_bus = can.Bus(interface="virtual", channel=channel)
    try:
        emu = DriveEmulator(drive_bus, DriveFirmware(AverageTorqueDrive(params)), 0)
        host = OdriveCanSimple(host_bus, 0)
        emu.tick(0.0)                        # first tick: heartbeat + encoder are due
        host.clear_errors()
        host.enable("torque")
        host.set_input_torque(0.5)
        for _ in range(4):
            emu.handle(drive_bus.recv(1.0), 0.001)
        emu.tick(0.002)                      # the controller runs: torque target = input
        host.request("torque")
        emu.handle(drive_bus.recv(1.0), 0.003)
        got = {m.kind: m for m in host.poll(0.5)}
        got.update({m.kind: m for m in host.poll(0.05)})
        assert {"status", "motion", "torque"} <= set(got)
        assert got["torque"].values["torque_target_nm"] == pytest.approx(0.5, rel=1e-6)
        assert emu.dropped() == 0 and host.dropped == 0
    finally:
        drive_bus.shutdown()
        host_bus.shutdown()


# =======================================================================================
# the emulator as a process over udp_multicast
def _port() -> int:
    return random.SystemRandom().randint(41000, 48999)


class Emulator:
    """bike-drive-emulator in its own process (python -m; the console entry is the same main)."""

    def __init__(self, tmp_path: pathlib.Path, *args: str, node_id: int = 0):
        self.port = _port()
        self.out_path = tmp_path / f"emulator_{self.port}.out"
        self.err_path = tmp_path / f"emulator_{self.port}.err"
        self._out = open(self.out_path, "w")
        self._err = open(self.err_path, "w")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "bike_plant.can.emulator", "--interface", "udp_multicast", "--channel", GROUP,
             "--port", str(self.port), "--node-id", str(node_id), "--config", str(CONFIG), *args],
            stdout=self._out, stderr=self._err, stdin=subprocess.DEVNULL, start_new_session=True)
        self.bus = can.Bus(interface="udp_multicast", channel=GROUP, port=self.port)
        self.host = OdriveCanSimple(self.bus, node_id)
        end = time.monotonic() + 30.0
        while "ready" not in self.out_path.read_text():
            assert self.proc.poll() is None, self.err_path.read_text()
            assert time.monotonic() < end, "emulator did not start"
            time.sleep(0.05)
        assert self.wait_for(lambda h: "status" in h.last, 10.0), "no heartbeat"

    def wait_for(self, predicate, timeout_s: float, requests: tuple[str, ...] = (), feed: bool = False) -> bool:
        """Poll (and optionally request / keep the watchdog fed) until predicate(host)."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            for what in requests:
                self.host.request(what)
            if feed:
                self.host.keepalive()
            self.host.poll(0.02)
            if predicate(self.host):
                return True
        return False

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 15.0) -> tuple[int, dict]:
        """Signal the process; return its exit code and its exit summary (counters)."""
        if self.proc.poll() is None:
            os.kill(self.proc.pid, sig)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                os.kill(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self.bus.shutdown()
        self._out.close()
        self._err.close()
        summary = {}
        for line in self.err_path.read_text().splitlines():
            if line.startswith("bike-drive-emulator: exit "):
                summary = json.loads(line[len("bike-drive-emulator: exit "):])
        return self.proc.returncode, summary


@pytest.fixture
def emulator_factory(tmp_path):
    started: list[Emulator] = []

    def start(*args: str, node_id: int = 0) -> Emulator:
        emu = Emulator(tmp_path, *args, node_id=node_id)
        started.append(emu)
        return emu

    yield start
    for emu in started:
        if emu.proc.poll() is None:
            emu.stop()


def test_heartbeat_and_encoder_rates(emulator_factory):
    emu = emulator_factory()
    host = emu.host
    heartbeats, encoders = [], 0
    end = time.monotonic() + 2.0
    while time.monotonic() < end:
        for m in host.poll(0.05):
            if m.kind == "status":
                heartbeats.append(m.received_s)
            elif m.kind == "motion":
                encoders += 1
    intervals = [b - a for a, b in zip(heartbeats, heartbeats[1:])]
    mean_s = sum(intervals) / len(intervals)
    print(f"heartbeat: {len(heartbeats)} in 2 s, mean {mean_s * 1e3:.1f} ms, "
          f"min {min(intervals) * 1e3:.1f} ms, max {max(intervals) * 1e3:.1f} ms; encoder frames {encoders}")
    assert len(heartbeats) >= 12 and 0.08 <= mean_s <= 0.13
    assert encoders >= 100                    # 10 ms cycle: ~200 expected
    values = host.values()
    assert values["axis_state"] == AxisState.IDLE and values["axis_error"] == 0
    assert 20.0 < values["speed_rev_s"] < 60.0           # the rider pedals (motor side: cadence * 35)
    rc, summary = emu.stop()
    assert rc == 0 and summary["tx:Heartbeat"] >= 12


def test_torque_command_is_followed(emulator_factory, params):
    emu = emulator_factory("--iq-ms", "20")
    host = emu.host
    host.clear_errors()
    host.enable("torque")
    assert emu.wait_for(lambda h: h.enabled, 5.0)
    kt = params.torque_constant_nm_per_a
    for torque_nm in (1.0, -0.5):
        host.set_input_torque(torque_nm)

        def follows(h):
            t, i = h.last.get("torque"), h.last.get("current")
            return (t is not None and i is not None and t.values["torque_target_nm"] == pytest.approx(torque_nm)
                    and abs(t.values["torque_estimate_nm"] - torque_nm) < 0.01
                    and abs(i.values["iq_measured_a"] - torque_nm / kt) < 0.01 / kt)

        assert emu.wait_for(follows, 5.0, requests=("torque",), feed=True), host.values()
    assert host.enabled and host.active_errors == 0
    host.request("bus")
    assert emu.wait_for(lambda h: "bus" in h.last, 5.0, feed=True)
    assert 40.0 < host.values()["bus_voltage_v"] < 56.0
    host.disable()
    assert emu.wait_for(lambda h: h.axis_state == AxisState.IDLE, 5.0)
    rc, _ = emu.stop()
    assert rc == 0


def test_velocity_control_over_the_bus_and_an_injected_fault(emulator_factory):
    """Set_Controller_Mode(velocity) + Set_Input_Vel across processes; SIGUSR1 injects --fault:
    the axis drops to IDLE with the error latched, Clear_Errors + closed loop re-arm it."""
    emu = emulator_factory("--load", "none", "--fault", "MOTOR_OVER_TEMP")
    host = emu.host
    host.clear_errors()
    host.enable("velocity")
    host.set_velocity(15.0)
    assert emu.wait_for(lambda h: h.enabled and abs(h.values().get("speed_rev_s", 0.0) - 15.0) < 0.3, 10.0,
                        feed=True), host.values()
    os.kill(emu.proc.pid, signal.SIGUSR1)
    over_temp = int(ODriveError.MOTOR_OVER_TEMP)
    assert emu.wait_for(lambda h: h.axis_state == AxisState.IDLE and h.active_errors == over_temp, 3.0, feed=True)
    host.clear_errors()
    host.enable("velocity")
    host.set_velocity(10.0)
    assert emu.wait_for(lambda h: h.enabled and abs(h.values().get("speed_rev_s", 0.0) - 10.0) < 0.3, 10.0,
                        feed=True), host.values()
    rc, summary = emu.stop()
    assert rc == 0 and summary["faults_injected"] == 1 and summary["rx:Set_Input_Vel"] >= 2


def test_watchdog_trips_and_clear_errors_recovers(emulator_factory):
    emu = emulator_factory("--watchdog-s", "0.5")
    host = emu.host
    host.clear_errors()
    host.enable("torque")
    host.set_input_torque(0.5)
    assert emu.wait_for(lambda h: h.enabled, 5.0, feed=True)
    assert not emu.wait_for(lambda h: not h.enabled, 0.6, feed=True), "tripped although fed"
    t_stop = time.monotonic()               # stop feeding (last feed <= 0.1 s ago: keepalive interval)
    assert emu.wait_for(lambda h: h.axis_state == AxisState.IDLE, 0.5 + 2.5)
    tripped_after_s = time.monotonic() - t_stop
    print(f"watchdog seen tripped {tripped_after_s * 1e3:.0f} ms after the host stopped feeding")
    assert tripped_after_s >= 0.3
    assert host.active_errors & WATCHDOG
    host.request("errors")
    host.request("torque")
    assert emu.wait_for(lambda h: "errors" in h.last and "torque" in h.last, 5.0)
    assert host.last["errors"].values["disarm_reason"] == WATCHDOG
    assert host.last["torque"].values["torque_target_nm"] == 0.0
    assert host.last["status"].values["procedure_result"] == ProcedureResult.DISARMED
    # enabling without clearing the error is refused
    host.set_axis_state(AxisState.CLOSED_LOOP_CONTROL)
    assert not emu.wait_for(lambda h: h.enabled, 0.5)
    # Clear_Errors + Set_Axis_State(8) recovers
    host.clear_errors()
    host.set_axis_state(AxisState.CLOSED_LOOP_CONTROL)
    assert emu.wait_for(lambda h: h.enabled and h.active_errors == 0, 5.0, feed=True)
    rc, summary = emu.stop()
    assert rc == 0 and summary["axis_state"] == AxisState.CLOSED_LOOP_CONTROL


def _garbage(rng: random.Random) -> can.Message:
    """Malformed frames for node 0 and arbitrary frames of other nodes (never a valid
    node-0 command, so the axis must stay IDLE)."""
    kind = rng.randrange(9)
    if kind == 0:
        node = rng.randrange(1, 64)
        return can.Message(arbitration_id=(node << 5) | rng.randrange(32), data=rng.randbytes(rng.randrange(9)),
                           is_extended_id=False)
    if kind == 1:
        return can.Message(arbitration_id=0x0E, data=struct.pack("<ff", math.nan, 0.0), is_extended_id=False)
    if kind == 2:
        return can.Message(arbitration_id=0x07, data=struct.pack("<I", rng.choice([200, 2 ** 31])),
                           is_extended_id=False)
    if kind == 3:
        return can.Message(arbitration_id=0x0D, data=rng.randbytes(rng.randrange(4)), is_extended_id=False)
    if kind == 4:
        return can.Message(arbitration_id=rng.choice([0x1E, 0x1F, 0x10, 0x05]), data=rng.randbytes(8),
                           is_extended_id=False)
    if kind == 5:
        return can.Message(arbitration_id=0x0E, is_remote_frame=True, dlc=8, is_extended_id=False)
    if kind == 6:
        return can.Message(is_error_frame=True, arbitration_id=0x4, data=bytes(8))
    if kind == 7:
        return can.Message(arbitration_id=rng.randrange(1 << 29), data=rng.randbytes(8), is_extended_id=True)
    return can.Message(arbitration_id=0x0F, data=struct.pack("<ff", math.inf, -3.0), is_extended_id=False)


def test_garbage_frames_do_not_crash_it(emulator_factory):
    emu = emulator_factory()
    rng = random.Random(1234)
    for _ in range(400):                    # ~1k frames/s at most: below the UDP loss region
        emu.bus.send(_garbage(rng))
        emu.host.poll(0.0)                  # keep our own socket drained (we get our frames back)
        time.sleep(0.001)
    assert emu.wait_for(lambda h: "current" in h.last, 5.0, requests=("current",)), "no answer after garbage"
    assert emu.proc.poll() is None
    heartbeats = emu.host.counters["rx:Heartbeat"]
    assert emu.wait_for(lambda h: h.counters["rx:Heartbeat"] >= heartbeats + 3, 5.0)
    assert emu.host.axis_state == AxisState.IDLE and emu.host.active_errors == 0
    rc, summary = emu.stop()
    assert rc == 0
    dropped = {k: v for k, v in summary.items() if k in ("other_node", "non_finite", "out_of_range", "bad_dlc",
                                                           "unknown_cmd", "unexpected_rtr", "error_frame",
                                                           "extended_id")}
    print("emulator dropped:", dropped)
    assert sum(dropped.values()) >= 300 and len(dropped) >= 6


def test_host_survives_an_emulator_injecting_garbage(emulator_factory):
    emu = emulator_factory("--garbage-rate", "300", "--seed", "7")
    host = emu.host
    start = host.counters["rx:Heartbeat"]
    assert emu.wait_for(lambda h: h.dropped >= 100 and h.counters["rx:Heartbeat"] >= start + 10, 10.0), \
        dict(host.counters)
    assert host.link_alive() and host.active_errors == 0
    print("host counters under garbage:", {k: v for k, v in host.counters.items() if not k.startswith("rx:")})
    rc, summary = emu.stop()
    assert rc == 0 and summary["tx:garbage"] >= 100


def test_silent_after_s_loses_the_link_but_keeps_running_and_sigint_exits_zero(emulator_factory):
    emu = emulator_factory("--silent-after-s", "1.0")
    host = emu.host
    assert emu.wait_for(lambda h: not h.link_alive(), 1.0 + 0.5 + 3.0)
    assert emu.proc.poll() is None
    host.poll(0.3)
    assert not host.link_alive()
    rc, summary = emu.stop(signal.SIGINT)
    assert rc == 0 and summary["tx_suppressed"] > 0
