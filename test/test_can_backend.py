"""The plant's CAN backend (bike_plant.can.backend.CanBackend) without ROS, on python-can's
in-process ``virtual`` bus: scripted drive frames (a fake clock where timing matters) and the
drive emulator in a thread. Also the controller's torque-only answer to a drive's PlantState."""
from __future__ import annotations

import math
import pathlib
import struct
import threading
import time
import uuid

import can
import pytest

from bike_plant.can import AxisState, ODriveError, OdriveCanSimpleCodec
from bike_plant.can.backend import (FAULT_DRIVE_DISARMED, FAULT_DRIVE_LOST, FAULT_DRIVE_STALE, CanBackend,
                                    can_params_from_config,
                                    emulator_args_from_config)
from bike_controller.drive_emulator import AverageTorqueDrive, DriveEmulator, DriveFirmware, DriveModelParams
from bike_plant.can.torque_map import TorqueMap
from bike_plant.config import ConfigError, load_config

ROOT = pathlib.Path(__file__).resolve().parents[1]
CAN_CONFIG = ROOT / "config" / "bldc_can.yaml"
TMAX = 2.941995
WATCHDOG = int(ODriveError.WATCHDOG_TIMER_EXPIRED)


class Clock:
    def __init__(self, t: float = 100.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


class Cmd:
    """What the backend reads of a bike_msgs/DriveCommand."""

    def __init__(self, torque_nm: float, current_a: float = 0.0):
        self.torque_cmd_nm = torque_nm
        self.current_cmd_a = current_a


class FakeWallClock:
    """The wall clock of a fake-clock rig: the frames' receive stamps, on another timebase than the
    host clock (as time.time and time.monotonic are) but running with it. Without it, a frame's real
    queueing delay (a preempted test thread) would be subtracted from the fake time."""

    OFFSET_S = 1.7e9

    def __init__(self, clock: Clock):
        self.host = clock

    def __call__(self) -> float:
        return self.host.t + self.OFFSET_S


class Rig:
    """A CanBackend and the drive's end of the same virtual bus (scripted frames). With a fake
    clock, frames sent by :meth:`send` carry receive stamps of the fake wall clock; frames sent
    straight on ``drive_bus`` carry none and are dated at the backend's own time."""

    def __init__(self, clock=None, config=CAN_CONFIG, codec_class=OdriveCanSimpleCodec, **can_changes):
        self.cfg = load_config(config)
        self.channel = uuid.uuid4().hex
        can_changes.setdefault("arm_ramp_nm_per_s", 0.0)   # exact setpoints; the ramp has its own test
        can_changes.setdefault("torque_map_file", "")       # the drive's figures as they are; the map: its tests
        self.cfg["can"].update(interface="virtual", channel=self.channel, **can_changes)
        self.wall = FakeWallClock(clock) if clock else None
        self.drive_bus = can.Bus(interface="virtual", channel=self.channel, preserve_timestamps=bool(clock))
        self.codec = codec_class(0)
        self.backend = CanBackend(self.cfg, **({"clock": clock, "wall_clock": self.wall} if clock else {}))

    def send(self, name: str, **signals) -> None:
        msg = self.codec.encode(name, signals)
        if self.wall is not None:
            msg.timestamp = self.wall()
        self.drive_bus.send(msg)

    def heartbeat(self, state: int = AxisState.CLOSED_LOOP_CONTROL, error: int = 0) -> None:
        self.send("Heartbeat", Axis_Error=error, Axis_State=int(state), Procedure_Result=0, Trajectory_Done_Flag=1)

    def host_frames(self) -> list[tuple[str, object]]:
        """(message name, signals | 'RTR') of everything the host sent since the last call."""
        out = []
        while True:
            msg = self.drive_bus.recv(timeout=0.0)
            if msg is None:
                return out
            r = self.codec.classify(msg, self.codec.host_to_drive, answers_requests=True)
            assert not isinstance(r, str), f"host sent a frame the drive rejects: {r} {msg}"
            out.append((r.name, "RTR" if r.is_request else dict(r.signals)))

    def torques(self) -> list[float]:
        return [s["Input_Torque"] for name, s in self.host_frames() if name == "Set_Input_Torque"]

    def close(self) -> None:
        self.backend.close()
        self.backend.bus.shutdown()
        self.drive_bus.shutdown()


@pytest.fixture
def rig():
    made = []

    def make(clock=None, **changes) -> Rig:
        r = Rig(clock, **changes)
        made.append(r)
        return r

    yield make
    for r in made:
        r.close()


def armed(rig_factory, clock=None, **changes) -> Rig:
    """A rig whose drive is in closed-loop control and has been commanded once."""
    r = rig_factory(clock, **changes)
    r.heartbeat()
    r.backend.service()
    assert r.backend.drive_enabled and not r.backend.time_frozen
    r.host_frames()
    return r


# ----------------------------------------------------------------------------- mapping
def test_drive_measurements_become_a_plant_state_with_plant_signs(rig):
    r = armed(rig)
    b = r.backend
    r.send("Get_Encoder_Estimates", Pos_Estimate=3.25, Vel_Estimate=40.0)
    r.send("Get_Torques", Torque_Target=-1.0, Torque_Estimate=-0.9)            # braking
    r.send("Get_Bus_Voltage_Current", Bus_Voltage=50.0, Bus_Current=-4.0)      # ODrive: -4 A drawn = charging
    r.send("Get_Iq", Iq_Setpoint=-19.0, Iq_Measured=-17.3)
    b.service()
    s = b.snapshot()
    assert b.measured_by_drive and b.name == "can" and s["machine"] == "bldc"
    assert s["speed_rad_s"] == pytest.approx(40.0 * 2 * math.pi)
    assert s["speed_rpm"] == pytest.approx(2400.0)
    assert s["rotor_angle_mech_rad"] == pytest.approx(math.pi / 2)
    assert s["rotor_angle_elec_rad"] == pytest.approx(math.pi)                  # 2 pole pairs
    assert s["torque_em_nm"] == pytest.approx(-0.9)                            # motoring positive
    assert s["dc_bus_v"] == 50.0 and s["battery_current_a"] == 4.0              # charging positive
    ia, ib, ic = s["phase_current_a"]
    assert ia + ib + ic == pytest.approx(0.0, abs=1e-9)
    assert math.sqrt((ia * ia + ib * ib + ic * ic) / 1.5) == pytest.approx(17.3, rel=1e-6)   # amplitude |Iq|
    assert s["current_samples_a"] == [] and s["hall_edge_counts"] == []
    assert math.isnan(s["battery_soc"]) and math.isnan(s["battery_ocv_v"]) and math.isnan(s["load_torque_nm"])
    assert s["faults"] == 0
    # energy ledger over 50 batches of 5 ms at constant speed: battery 50 V x 4 A, shaft 0.9 N m x w
    for _ in range(50):
        b.apply(Cmd(-1.0))
    dt = 50 * 100 * 5e-5
    w = 40.0 * 2 * math.pi
    s = b.snapshot()
    assert b.time_s == pytest.approx(dt)
    assert s["energy_battery_j"] == pytest.approx(200.0 * dt)
    friction = 1e-4 * w * w * dt
    assert s["energy_mech_in_j"] == pytest.approx(0.9 * w * dt + friction)
    assert s["energy_stored_j"] == pytest.approx(0.0)
    assert s["energy_loss_j"] == pytest.approx(s["energy_mech_in_j"] - s["energy_battery_j"])


def test_ledger_of_an_spmsm_bike_has_its_coulomb_friction(rig):
    """spmsm_can.yaml's bike has Coulomb friction (spmsm.dry_friction_nm 0.1 N m) next to B
    (0.005 N m s): the ledger's friction term is the physics' T_f(w) w, not B w^2 alone (which
    left the report's trainer power error at +0.1 N m x w, +2.5 % on that bike's ride)."""
    r = armed(rig, config=ROOT / "config" / "spmsm_can.yaml")
    b = r.backend
    r.send("Get_Encoder_Estimates", Pos_Estimate=0.0, Vel_Estimate=4.0)
    r.send("Get_Torques", Torque_Target=-1.0, Torque_Estimate=-1.0)
    b.service()
    for _ in range(50):
        b.apply(Cmd(-1.0))
    w = 4.0 * 2 * math.pi
    dt = b.time_s
    s = b.snapshot()
    assert dt > 0
    friction_nm = 0.005 * w + 0.1 * math.tanh(w / (2 * math.pi / 60))      # w_s: 1 r/min
    assert s["energy_mech_in_j"] == pytest.approx((1.0 + friction_nm) * w * dt)


def test_setpoints_go_out_at_once_clamped_and_bad_ones_are_refused(rig):
    r = armed(rig)
    b = r.backend
    assert b.submit(Cmd(-0.7))
    assert r.torques() == [pytest.approx(-0.7)]
    msg = Cmd(0.3)
    assert b.submit(msg)
    b.apply(msg)                                       # the same command at the tick: not sent twice
    assert r.torques() == [pytest.approx(0.3)]
    assert b.submit(Cmd(-100.0))
    assert r.torques() == [pytest.approx(-TMAX)]       # clamped to controller.tmax_nm
    assert b.stats()["torque_clamped"] == 1
    for bad in (Cmd(math.nan), Cmd(math.inf), Cmd(0.1, math.nan)):
        assert b.problem(bad, 100) is not None
        assert not b.submit(bad)
    assert r.torques() == []
    assert b.problem(Cmd(0.2), 100) is None


def _torque_map_file(tmp_path) -> pathlib.Path:
    """A drive whose shaft torque is 0.9 x its estimate at 1200 rpm and 0.8 x at 3600 rpm (both
    signs), its estimate 1.02 x the setpoint."""
    sp = [-3.0, -1.0, 0.0, 1.0, 3.0]
    m = TorqueMap([1200.0, 3600.0], sp, [[1.02 * x for x in sp]] * 2,
                  [[0.9 * 1.02 * x for x in sp], [0.8 * 1.02 * x for x in sp]], source="test")
    m.save(tmp_path / "map.yaml")
    return tmp_path / "map.yaml"


def test_a_torque_map_makes_the_setpoint_and_the_reported_torque_the_shafts(rig, tmp_path):
    """With can.torque_map_file the controller's torque is the shaft's: the setpoint is the map's
    inverse at the drive's speed, and the PlantState's torque and the ledger are the map's shaft
    torque for the drive's estimate; lookups outside the map are counted and the diagnostic
    names the map (bike_plant.can.torque_map)."""
    _torque_map_file(tmp_path)
    r = armed(rig, torque_map_file=str(tmp_path / "map.yaml"))
    b = r.backend
    events = b.pop_events()
    assert ("info", f"setpoints and torque through the drive's {b.torque_map.describe()}") in events
    assert not any("torque map" in text for level, text in events if level == "warning")   # not the emulator's
    r.send("Get_Encoder_Estimates", Pos_Estimate=0.0, Vel_Estimate=40.0)        # 2400 rpm: ratio 0.85
    r.send("Get_Torques", Torque_Target=-1.0, Torque_Estimate=-1.2)
    b.service()
    assert b.submit(Cmd(-0.85))
    assert r.torques() == [pytest.approx(-0.85 / (0.85 * 1.02))]                # the setpoint for -0.85 at the shaft
    assert b.snapshot()["torque_em_nm"] == pytest.approx(-1.2 * 0.85)
    for _ in range(10):
        b.apply(Cmd(-0.85))
    w = 40.0 * 2 * math.pi
    assert b.snapshot()["energy_mech_in_j"] == pytest.approx((1.2 * 0.85 + 1e-4 * w) * w * b.time_s)
    assert b.stats()["torque_map_outside"] == 0
    # beyond the map: the nearest row (3600 rpm) and its end ratio hold, counted
    r.send("Get_Encoder_Estimates", Pos_Estimate=0.0, Vel_Estimate=80.0)        # 4800 rpm
    r.send("Get_Torques", Torque_Target=-1.0, Torque_Estimate=-3.5)
    b.service()
    assert b.snapshot()["torque_em_nm"] == pytest.approx(-3.5 * 0.8)
    assert b.stats()["torque_map_outside"] >= 2
    _, _, values = b.diagnostic()
    assert "map.yaml: 2 speeds 1200-3600 rpm" in values["can_torque_map"]
    assert values["can_torque_estimate_nm"] == "-3.5000"
    # the clamp is of the shaft's torque (Tmax), and the setpoint stays within the map's: -2.9 N m
    # at the shaft needs -3.34 from this drive at 2400 rpm, beyond the -3 N m it was measured at
    r.send("Get_Encoder_Estimates", Pos_Estimate=0.0, Vel_Estimate=40.0)
    b.service()
    r.host_frames()
    clamped = b.stats()["torque_clamped"]
    assert b.submit(Cmd(-2.5))
    assert r.torques() == [pytest.approx(-2.5 / (0.85 * 1.02))]                 # -2.88: more than asked
    assert b.submit(Cmd(-2.9))
    assert b.submit(Cmd(-5.0))
    assert r.torques() == [pytest.approx(-3.0)] * 2
    assert b.stats()["torque_clamped"] == clamped + 3                            # -5: twice (shaft, setpoint)


def test_the_emulators_torque_map_on_a_real_drive_is_warned_about(rig):
    """config/bldc_can.yaml's map was measured on the drive emulator: copied for a real drive
    (can.emulator false) it would correct that drive with the emulated BLDC's figures."""
    shipped = str(ROOT / "config" / "bldc_can_torque_map.yaml")
    for emulator in (True, False):
        b = rig(torque_map_file=shipped, emulator=emulator, emulator_watchdog_s=0.0).backend
        warnings = [text for level, text in b.pop_events() if level == "warning" and "torque map" in text]
        assert bool(warnings) == (not emulator), warnings
    assert "measured on the drive emulator" in warnings[0] and 'torque_map_file: ""' in warnings[0]


def test_a_torque_map_that_cannot_be_used_is_one_config_error(rig, tmp_path):
    """Missing, malformed, or without an inverse: one ConfigError naming can.torque_map_file and
    what is wrong, before the bus is opened."""
    good = _torque_map_file(tmp_path).read_text()
    cases = {"missing.yaml": None, "junk.yaml": "drive_torque_map: [1, 2",
             "flat.yaml": good.replace("true_nm: [-2.754", "true_nm: [2.754"),
             "short.yaml": good.replace("speed_rpm: [1200.0, 3600.0]", "speed_rpm: [1200.0, 2400.0, 3600.0]")}
    for name, text in cases.items():
        if text is not None:
            assert text != good
            (tmp_path / name).write_text(text)
        with pytest.raises(ConfigError) as err:
            rig(torque_map_file=str(tmp_path / name))
        text = str(err.value)
        assert "can.torque_map_file" in text and name in text and "\n" not in text, text
    cfg = load_config(CAN_CONFIG)       # relative paths resolve against the config file's folder
    cfg["can"]["torque_map_file"] = "no_such_map.yaml"
    bus = can.Bus(interface="virtual", channel=uuid.uuid4().hex)
    try:
        with pytest.raises(ConfigError, match="config/no_such_map.yaml: cannot read it"):
            CanBackend(cfg, bus=bus)
    finally:
        bus.shutdown()


def test_arming_clear_errors_closed_loop_then_the_setpoint(rig):
    r = rig()
    b = r.backend
    b.apply(Cmd(-0.5))                     # commands flow, but there is no drive yet
    b.service()
    assert b.time_frozen and b.time_s == 0.0 and r.host_frames() == []
    level, reasons, values = b.diagnostic()
    assert level == 1 and "waiting for the drive's Heartbeat" in reasons[0] and values["can_link"] == "waiting"
    r.heartbeat(AxisState.IDLE, error=WATCHDOG)        # the drive is there, disarmed with a latched error
    b.service()
    frames = r.host_frames()
    names = [n for n, _ in frames]
    assert names[:4] == ["Clear_Errors", "Set_Limits", "Set_Controller_Mode", "Set_Axis_State"]
    assert frames[1][1] == {"Velocity_Limit": 100.0, "Current_Limit": 120.0}, "the config's limits"
    assert frames[2][1] == {"Control_Mode": 1, "Input_Mode": 1} and frames[3][1] == {"Axis_Requested_State": 8}
    assert ("Heartbeat", "RTR") in frames
    b.apply(Cmd(-0.5))
    assert b.time_s == 0.0, "sim time stands still until the drive reports closed loop"
    r.heartbeat()
    b.service()
    assert b.drive_enabled and r.torques() == [pytest.approx(-0.5)]
    b.apply(Cmd(-0.5))
    assert b.time_s == pytest.approx(5e-3)
    assert b.diagnostic()[0] == 0


def test_malformed_frames_are_counted_and_ignored(rig):
    r = armed(rig)
    b = r.backend
    r.send("Get_Encoder_Estimates", Pos_Estimate=1.0, Vel_Estimate=30.0)
    b.service()
    bad = [
        can.Message(is_error_frame=True, arbitration_id=0x4, data=bytes(8)),
        can.Message(arbitration_id=0x1E, data=bytes(8), is_extended_id=False),                  # unknown cmd
        can.Message(arbitration_id=0x09, data=bytes(4), is_extended_id=False),                  # wrong DLC
        can.Message(arbitration_id=0x09, data=struct.pack("<ff", 0.0, math.nan), is_extended_id=False),
        can.Message(arbitration_id=0x09, data=struct.pack("<ff", 0.0, 5000.0), is_extended_id=False),
        can.Message(arbitration_id=0x01, data=bytes(4) + bytes([200, 0, 0, 0]), is_extended_id=False),
        can.Message(arbitration_id=(5 << 5) | 0x09, data=struct.pack("<ff", 0.0, -7.0), is_extended_id=False),
        can.Message(arbitration_id=0x12345, data=bytes(8), is_extended_id=True),
        can.Message(arbitration_id=0x0E, is_remote_frame=True, dlc=8, is_extended_id=False),     # RTR of a command
        can.Message(arbitration_id=0x09, is_remote_frame=True, dlc=8, is_extended_id=False),     # another host asks
    ]
    for msg in bad:
        r.drive_bus.send(msg)
    b.service()
    stats = b.stats()
    assert stats["dropped"] == 8 and stats["other_node"] == 1 and stats["other_direction"] == 1
    for reason in ("error_frame", "unknown_cmd", "bad_dlc", "non_finite", "out_of_range", "extended_id",
                   "unexpected_rtr"):
        assert stats[f"dropped_{reason}"] >= 1, reason
    s = b.snapshot()
    assert s["speed_rpm"] == pytest.approx(1800.0) and s["faults"] == 0 and b.drive_enabled
    assert b.diagnostic()[2]["can_dropped"] == "8"
    # a drive with temperature_msg_rate_ms set: valid Get_Temperature frames are not malformed ones
    r.drive_bus.send(can.Message(arbitration_id=0x15, data=struct.pack("<ff", 40.0, 30.0), is_extended_id=False))
    b.service()
    assert b.stats()["dropped"] == 8 and b.stats()["unused_message"] == 1


def test_no_heartbeat_of_our_node_says_what_the_bus_carries(rig):
    """A real bus without a link: the drive on another node id, heartbeats off, heartbeats we
    drop, or silence. After 2 s the log and the diagnostic say which (before: "waiting for the
    drive's Heartbeat" and nothing in the log, forever)."""
    clock = Clock()
    r = rig(clock)
    b = r.backend
    node3 = OdriveCanSimpleCodec(3)
    hb = {"Axis_Error": 0, "Axis_State": 1, "Procedure_Result": 0, "Trajectory_Done_Flag": 1}
    for _ in range(3):
        r.drive_bus.send(node3.encode("Heartbeat", hb))
        b.service()
    assert b.pop_events() == [] and "node 3" not in b.diagnostic()[1][0], "not before 2 s"
    clock.t += 2.5
    b.service()
    events = b.pop_events()
    assert len(events) == 1 and events[0][0] == "warning"
    assert "from node 3, none from node 0" in events[0][1] and "can.node_id" in events[0][1]
    level, reasons, _ = b.diagnostic()
    assert level == 1 and "from node 3, none from node 0" in reasons[0] and not b.seen
    clock.t += 0.5
    b.service()
    assert b.pop_events() == [], "logged again only when the picture changes"
    # our node sends estimates but no heartbeat (heartbeat_msg_rate_ms = 0)
    r2 = rig(clock)
    r2.send("Get_Encoder_Estimates", Pos_Estimate=0.0, Vel_Estimate=0.0)
    clock.t += 2.5
    r2.backend.service()
    assert "sends Get_Encoder_Estimates but no Heartbeat" in r2.backend.pop_events()[0][1]
    # our node's heartbeats, in a layout we drop (a DLC of 4)
    r3 = rig(clock)
    r3.drive_bus.send(can.Message(arbitration_id=0x01, data=bytes(4), is_extended_id=False))
    clock.t += 2.5
    r3.backend.service()
    assert "Heartbeat frames of node 0 dropped (bad_dlc 1)" in r3.backend.pop_events()[0][1]
    # our node's heartbeats with 29-bit ids (a drive set to extended ids)
    r6 = rig(clock)
    r6.drive_bus.send(can.Message(arbitration_id=0x01, data=bytes(8), is_extended_id=True))
    clock.t += 2.5
    r6.backend.service()
    assert "with a 29-bit (extended) id" in r6.backend.pop_events()[0][1]
    # the interface fails (socketcan: the link set down, the adapter unplugged)
    r7 = rig(clock)

    def broken_recv(timeout=None):
        raise can.CanOperationError("Network is down [Error Code 100]")
    r7.backend.bus.recv = broken_recv
    clock.t += 2.5
    r7.backend.service()
    assert "receive calls failed in the interface" in r7.backend.pop_events()[0][1]
    # nothing at all
    r4 = rig(clock)
    clock.t += 2.5
    r4.backend.service()
    assert "nothing received on the bus" in r4.backend.pop_events()[0][1]
    assert "nothing received on the bus" in r4.backend.diagnostic()[1][0]
    # a drive lost, then back on another node id (rebooted with another config)
    r5 = armed(rig, clock)
    clock.t += 0.4
    r5.backend.service()
    assert r5.backend.lost
    r5.backend.pop_events()
    r5.drive_bus.send(node3.encode("Heartbeat", hb))
    clock.t += 2.0
    r5.backend.service()
    events = r5.backend.pop_events()
    assert len(events) == 1 and "still silent" in events[0][1] and "from node 3" in events[0][1]
    assert "from node 3" in r5.backend.diagnostic()[1][0]
    r5.heartbeat()
    r5.backend.service()
    assert not r5.backend.lost and r5.backend.diagnostic()[1] == []


def test_heartbeats_slower_than_configured_are_named_as_such(rig):
    """A drive whose heartbeat_msg_rate_ms is not the config's: at 500 ms with a 0.3 s timeout the
    link drops and returns twice a second; the log says the rate is the cause (before: only
    "drive silent" / "back" over and over). At 250 ms it holds, with a warning; at 100 ms nothing."""
    def ride(period_s: float, seconds: float = 4.0):
        clock = Clock()
        r = rig(clock)
        b = r.backend
        t_next = clock.t
        events = []
        while clock.t < 100.0 + seconds:
            if clock.t >= t_next - 1e-9:
                r.heartbeat()
                t_next += period_s
            b.service()
            b.apply(Cmd(-0.2))
            events += b.pop_events()
            clock.t += 0.01
        return b, [text for level, text in events if level == "warning" and "Heartbeat" in text]

    b, warnings = ride(0.5)
    rate = [w for w in warnings if "Heartbeats come every 0.50s" in w]
    assert len(rate) == 1 and "link cannot hold" in rate[0] and "heartbeat_msg_rate_ms = 100" in rate[0]
    assert b.stats()["drive_lost"] >= 3
    b.clock.t += 0.6                                     # no heartbeat: lost for sure
    b.service()
    assert b.lost and "Heartbeats come every 0.50s" in b.diagnostic()[1][0]
    b, warnings = ride(0.25)
    assert len(warnings) == 1 and "every 0.25s" in warnings[0] and "little margin" in warnings[0]
    assert b.stats()["drive_lost"] == 0
    b, warnings = ride(0.1)
    assert warnings == [] and b.stats()["drive_lost"] == 0


def test_a_drive_found_already_in_closed_loop_is_put_in_torque_control_first(rig):
    """A drive left in closed loop (odrivetool, a previous run, startup_closed_loop_control) may
    be in velocity control, where Input_Torque is only a feed-forward: the plant sends zero
    torque, Set_Limits and Set_Controller_Mode(torque, passthrough) before any setpoint. Before,
    it took the heartbeat's CLOSED_LOOP_CONTROL as its own torque control and sent setpoints only."""
    clock = Clock()
    r = rig(clock, arm_ramp_nm_per_s=20.0)
    b = r.backend
    r.heartbeat()                                     # closed loop, not armed by us
    b.service()
    frames = r.host_frames()
    names = [n for n, _ in frames]
    assert names[:3] == ["Set_Input_Torque", "Set_Limits", "Set_Controller_Mode"]
    assert frames[0][1] == {"Input_Torque": 0.0} and frames[2][1] == {"Control_Mode": 1, "Input_Mode": 1}
    assert "Set_Axis_State" not in names, "no re-entry into closed loop (that would reset the drive's state)"
    assert any("not armed by this plant" in text for _, text in b.pop_events())
    clock.t += 0.02
    b.submit(Cmd(-1.0))
    assert r.torques() == [pytest.approx(-0.4)], "then the setpoint, ramped from zero (20 N m/s x 0.02 s)"
    for _ in range(3):                                 # still armed: nothing re-sent
        clock.t += 0.05
        r.heartbeat()
        b.service()
    assert "Set_Controller_Mode" not in [n for n, _ in r.host_frames()]
    # lost, then back in closed loop (rebooted into its own startup mode): torque control again
    clock.t += 0.4
    b.service()
    assert b.lost
    r.heartbeat()
    b.service()
    names = [n for n, _ in r.host_frames()]
    assert "Set_Controller_Mode" in names and "Set_Axis_State" not in names
    # a drive the plant armed itself is not taken over again
    r2 = rig(clock)
    r2.heartbeat(AxisState.IDLE)
    r2.backend.apply(Cmd(-0.5))
    r2.backend.service()
    assert [n for n, _ in r2.host_frames()].count("Set_Controller_Mode") == 1
    r2.heartbeat()
    r2.backend.service()
    assert "Set_Controller_Mode" not in [n for n, _ in r2.host_frames()]
    assert r2.backend.stats()["taken_over"] == 0


def test_a_refused_arming_names_the_axis_state_and_the_procedure_result(rig):
    """An uncalibrated ODrive refuses closed loop with no error bit, only a procedure result:
    the diagnostic and the log name it (before: 'axis state 1', errors none, and no why)."""
    clock = Clock()
    r = rig(clock, enable_retry_s=0.2, enable_max_attempts=2)
    b = r.backend
    b.apply(Cmd(-0.5))
    for _ in range(40):
        r.send("Heartbeat", Axis_Error=0, Axis_State=int(AxisState.IDLE), Procedure_Result=14,
               Trajectory_Done_Flag=1)
        b.service()
        clock.t += 0.05
    assert b.gave_up
    level, reasons, _ = b.diagnostic()
    assert level == 2 and "axis state 1 (IDLE), procedure result 14 (NOT_CALIBRATED)" in reasons[0]
    assert any("procedure result 14 (NOT_CALIBRATED)" in text for _, text in b.pop_events())


def test_another_host_commanding_our_drive_is_warned_about(rig):
    """Set_Input_Torque to our node that this plant did not send: a second controller on the
    drive. Counted and logged (before: counted only as other_direction, with RTRs)."""
    r = armed(rig)
    b = r.backend
    b.submit(Cmd(-0.5))
    b.service()
    assert b.stats()["foreign_commands"] == 0, "our own frames are not foreign (virtual: no echo)"
    r.drive_bus.send(can.Message(arbitration_id=0x09, is_remote_frame=True, dlc=8, is_extended_id=False))
    b.service()
    assert b.stats()["foreign_commands"] == 0, "another host's request is harmless"
    for _ in range(3):
        r.drive_bus.send(OdriveCanSimpleCodec(0).encode("Set_Input_Torque", {"Input_Torque": 1.5}))
    b.service()
    assert b.stats()["foreign_commands"] == 3
    warnings = [text for level, text in b.pop_events() if level == "warning" and "another host" in text]
    assert len(warnings) == 1 and "another host sends Set_Input_Torque to node 0" in warnings[0]


def test_a_drive_that_sends_no_speed_is_stale_and_says_why(rig):
    """Heartbeats and torques but no Get_Encoder_Estimates (encoder_msg_rate_ms left at 0, motion
    not requested): before, no fault at all and a PlantState reading 0 rpm however fast the
    flywheel turned; now FAULT_DRIVE_STALE after 0.5 s armed, and the diagnostic says what to set."""
    clock = Clock()
    r = armed(rig, clock)
    b = r.backend
    for _ in range(20):
        r.heartbeat()
        r.send("Get_Torques", Torque_Target=-0.5, Torque_Estimate=-0.5)
        b.apply(Cmd(-0.5))
        b.service()
        clock.t += 0.05
    assert b.faults & FAULT_DRIVE_STALE and b.snapshot()["speed_rpm"] == 0.0
    level, reasons, _ = b.diagnostic()
    assert level == 1 and "no Get_Encoder_Estimates" in reasons[0] and "encoder_msg_rate_ms = 10" in reasons[0]
    assert any("no Get_Encoder_Estimates" in text for _, text in b.pop_events())
    r.send("Get_Encoder_Estimates", Pos_Estimate=1.0, Vel_Estimate=20.0)
    r.heartbeat()
    b.service()
    assert not b.faults & FAULT_DRIVE_STALE and b.snapshot()["speed_rpm"] == pytest.approx(1200.0)


# ----------------------------------------------------------------------------- link loss, safe state
def test_silent_drive_is_lost_after_three_heartbeat_periods_then_recovers(rig):
    clock = Clock()
    r = armed(rig, clock)
    b = r.backend
    assert b.submit(Cmd(-0.8)) and r.torques() == [pytest.approx(-0.8)]
    b.apply(Cmd(-0.8))
    clock.t += 0.29
    b.service()
    assert not b.lost and b.faults == 0
    clock.t += 0.02                                      # 0.31 s > 3 x 100 ms without a heartbeat
    b.service()
    assert b.lost and b.faults & FAULT_DRIVE_LOST and b.snapshot()["faults"] & FAULT_DRIVE_LOST
    assert r.torques()[-1] == 0.0, "zero torque commanded when the drive goes silent"
    events = b.pop_events()
    assert events[-1][0] == "error" and "FAULT_DRIVE_LOST" in events[-1][1]
    level, reasons, _ = b.diagnostic()
    assert level == 2 and "drive silent" in reasons[0]
    t_before = b.time_s
    for _ in range(10):                                   # commands keep coming: nothing is sent, time stands
        clock.t += 0.05
        b.apply(Cmd(0.0))
        b.service()
    assert b.time_s == t_before and b.time_frozen
    assert r.host_frames() == [], "the watchdog is no longer fed while the drive is lost"
    # the drive is back, its watchdog tripped meanwhile
    r.heartbeat(AxisState.IDLE, error=WATCHDOG)
    b.service()
    assert not b.lost and b.faults == FAULT_DRIVE_DISARMED, "alive, but disarmed with an error"
    names = [n for n, _ in r.host_frames()]
    assert names[:4] == ["Clear_Errors", "Set_Limits", "Set_Controller_Mode", "Set_Axis_State"]
    r.heartbeat()
    b.service()
    assert b.faults == 0
    b.apply(Cmd(-0.4))
    assert r.torques() == [0.0, pytest.approx(-0.4)] and not b.time_frozen
    assert b.stats()["drive_lost"] == 1 and b.stats()["drive_back"] == 1


def test_a_heartbeat_gap_seen_late_by_a_delayed_loop_is_still_a_lost_drive(rig):
    """The host loop itself stalls across a gap in the drive's heartbeats (a loaded machine):
    when it looks again the heartbeats are back, yet the gap between their receipt times
    exceeded heartbeat_timeout_s: FAULT_DRIVE_LOST for one batch (zero torque), counted,
    then back. Fake clock: the loop's own time; then the wall-clock receipt stamps of the frames."""
    clock = Clock()
    r = armed(rig, clock)
    b = r.backend
    b.apply(Cmd(-0.8))
    r.host_frames()
    clock.t += 0.39                                        # no service() for 390 ms, then one heartbeat
    r.heartbeat()
    b.service()
    assert b.lost and b.faults & FAULT_DRIVE_LOST, "a 390 ms gap > 300 ms: lost although the drive is back"
    assert r.torques() == [0.0], "zero torque commanded"
    events = b.pop_events()
    assert any(level == "error" and "seen late" in text and "0.390s" in text for level, text in events), events
    assert b.stats()["heartbeat_gaps"] == 1 and b.stats()["heartbeat_gap_max_ms"] == pytest.approx(390.0)
    clock.t += 0.005
    b.service()
    assert not b.lost and b.faults == 0 and b.stats()["drive_back"] == 1
    # both heartbeats wait in the queue (the loop stalls across them): their receive stamps tell the gap
    clock.t += 0.05
    r.heartbeat()
    clock.t += 0.35
    r.heartbeat()
    clock.t += 0.05
    b.pop_events()
    b.service()
    assert b.lost and b.faults & FAULT_DRIVE_LOST and b.stats()["heartbeat_gaps"] == 2
    events = b.pop_events()
    assert any("seen late" in text and "0.350s" in text for _, text in events), "the gap by the stamps: " + \
        str(events)
    # a gap within the timeout is not a loss, also when the loop sees it late
    r.heartbeat()
    b.service()
    clock.t += 0.2
    r.heartbeat()
    b.service()
    clock.t += 0.25
    r.heartbeat()
    clock.t += 0.25
    r.heartbeat()
    clock.t += 0.1
    b.service()
    assert not b.lost and b.stats()["heartbeat_gaps"] == 2
    # the same with real time (python-can's wall-clock stamps): a 350 ms gap only grows under load
    r2 = armed(rig)
    b2 = r2.backend
    time.sleep(0.05)
    r2.heartbeat()
    time.sleep(0.35)
    r2.heartbeat()
    b2.service()
    assert b2.lost and b2.faults & FAULT_DRIVE_LOST and b2.stats()["heartbeat_gaps"] == 1


def test_heartbeats_that_come_while_a_preempted_loop_drains_the_queue_are_dated_when_they_came(rig):
    """The loop loses the CPU for 350 ms while it drains the queue (a loaded plant host) and the
    drive's heartbeats go on meanwhile: they are dated by their receive stamps, after the loop's
    own time, so at the next service the newest is 60 ms old. Dated by the time they were read,
    they were 350 ms too old: FAULT_DRIVE_LOST, zero torque, for a drive that never paused."""
    clock = Clock()
    r = armed(rig, clock)
    b = r.backend
    recv = b.bus.recv
    stalls = []

    def preempted_recv(timeout=None):
        msg = recv(timeout=timeout)
        if not stalls:                                  # after the first frame: 350 ms without the CPU
            stalls.append(clock.t)
            for _ in range(3):
                clock.t += 0.1
                r.heartbeat()
            clock.t += 0.05
        return msg

    b.bus.recv = preempted_recv
    b.submit(Cmd(-0.8))
    r.host_frames()
    clock.t += 0.09
    r.heartbeat()
    b.service()
    assert stalls and not b.lost
    clock.t += 0.01                                     # the next batch: 360 ms after the last service began
    b.service()
    b.apply(Cmd(-0.8))
    assert not b.lost and b.faults == 0, "the newest heartbeat came 60 ms ago"
    assert b.stats()["drive_lost"] == 0 and b.stats()["heartbeat_gaps"] == 0
    assert b.stats()["heartbeat_gap_max_ms"] == pytest.approx(100.0)
    assert b.diagnostic()[2]["can_heartbeat_age_ms"] == "60"
    assert 0.0 not in r.torques(), "no zero-torque setpoint"


def test_old_speed_and_torque_estimates_flag_the_state_stale(rig):
    """Encoder / torque estimates older than measurement_timeout_s (heartbeats still flowing):
    FAULT_DRIVE_STALE (a WARN diagnostic, counted); fresh frames clear it."""
    clock = Clock()
    r = armed(rig, clock, measurement_timeout_s=0.05)
    b = r.backend
    for _ in range(4):
        clock.t += 0.01
        r.send("Get_Encoder_Estimates", Pos_Estimate=1.0, Vel_Estimate=40.0)
        r.send("Get_Torques", Torque_Target=-1.0, Torque_Estimate=-0.9)
        b.service()
        b.apply(Cmd(-1.0))
    assert b.faults == 0 and b.diagnostic()[0] == 0
    for _ in range(6):                                     # 60 ms: heartbeats, no estimates
        clock.t += 0.01
        r.heartbeat()
        b.service()
        b.apply(Cmd(-1.0))
    assert b.faults == FAULT_DRIVE_STALE and b.snapshot()["faults"] == FAULT_DRIVE_STALE and not b.time_frozen
    level, reasons, values = b.diagnostic()
    assert level == 1 and "stale" in reasons[0] and values["can_stale_episodes"] == "1"
    assert int(values["can_stale_batches"]) >= 1
    assert any("FAULT_DRIVE_STALE" in text for _, text in b.pop_events())
    r.send("Get_Encoder_Estimates", Pos_Estimate=1.1, Vel_Estimate=40.0)
    r.send("Get_Torques", Torque_Target=-1.0, Torque_Estimate=-0.95)
    b.service()
    assert b.faults == 0


def _ride(r, clock, seconds: float, state=AxisState.IDLE, error: int = 0, step_s: float = 0.05,
          cmd: float = -0.5) -> list[tuple[float, str, object]]:
    """Advance the fake clock with heartbeats of (state, error) and DriveCommands; the host's
    frames as (time, name, signals) -- RTR requests left out."""
    out = []
    end = clock.t + seconds
    while clock.t < end - 1e-9:
        clock.t += step_s
        r.heartbeat(state, error=error)
        r.backend.submit(Cmd(cmd))
        r.backend.service()
        r.backend.apply(Cmd(cmd))
        out += [(clock.t, n, v) for n, v in r.host_frames() if v != "RTR"]
    return out


def _arm_times(frames) -> list[float]:
    return [t for t, n, v in frames if n == "Set_Axis_State" and v["Axis_Requested_State"] == 8]


DRV_FAULT = int(ODriveError.DRV_FAULT)


def test_a_disarmed_drive_is_a_fault_and_re_arming_is_bounded(rig):
    """Alive but not in closed loop (tripped with an error): FAULT_DRIVE_DISARMED, ERROR
    diagnostic, time stands; re-arm at once, then after 0.2, 0.4 s (doubling), give up after
    3 attempts; start over when the drive's errors change; armed again -> no fault."""
    clock = Clock()
    r = armed(rig, clock, enable_retry_s=0.2, enable_max_attempts=3, current_limit_a=40.0,
              velocity_limit_rev_s=90.0)
    b = r.backend
    _ride(r, clock, 0.5, AxisState.CLOSED_LOOP_CONTROL)
    assert b.faults == 0 and b.time_s > 0
    b.pop_events()
    t_frozen = b.time_s
    frames = _ride(r, clock, 0.05, AxisState.IDLE, DRV_FAULT)          # the drive trips
    assert b.faults == FAULT_DRIVE_DISARMED and b.snapshot()["faults"] == FAULT_DRIVE_DISARMED
    assert not b.lost and b.time_frozen
    events = b.pop_events()
    assert any(level == "error" and "FAULT_DRIVE_DISARMED" in text and "DRV_FAULT" in text for level, text in events)
    level, reasons, values = b.diagnostic()
    assert level == 2 and any("disarmed" in x and "attempt 1 of 3" in x for x in reasons), reasons
    assert values["can_arming"] == "attempt 1" and values["can_axis_error"] == "DRV_FAULT"
    names = [n for _, n, _ in frames]
    names = names[names.index("Clear_Errors"):]
    assert names[:5] == ["Clear_Errors", "Set_Limits", "Set_Controller_Mode", "Set_Axis_State", "Set_Input_Torque"]
    limits = next(v for _, n, v in frames if n == "Set_Limits")
    assert limits == {"Velocity_Limit": 90.0, "Current_Limit": 40.0}, "Set_Limits sent when arming"
    frames += _ride(r, clock, 3.0, AxisState.IDLE, DRV_FAULT)         # the error stays: refused every time
    arms = _arm_times(frames)
    assert len(arms) == 3, arms
    assert [b - a for a, b in zip(arms, arms[1:])] == [pytest.approx(0.2, abs=0.051), pytest.approx(0.4, abs=0.051)]
    assert b.gave_up and b.stats()["arm_gave_up"] == 1 and b.faults == FAULT_DRIVE_DISARMED
    level, reasons, values = b.diagnostic()
    assert level == 2 and any("gave up" in x for x in reasons) and values["can_arming"] == "gave_up"
    assert any("gave up arming the drive after 3 attempts" in text for _, text in b.pop_events())
    assert b.time_s == t_frozen, "sim time stands the whole time"
    # someone fixes the drive (errors cleared on the drive): a new episode, armed at once
    frames = _ride(r, clock, 0.05, AxisState.IDLE, 0)
    assert len(_arm_times(frames)) == 1 and not b.gave_up
    _ride(r, clock, 0.1, AxisState.CLOSED_LOOP_CONTROL)
    assert b.faults == 0 and b.time_s > t_frozen and b.diagnostic()[0] == 0


def test_a_drive_armed_by_other_means_after_the_give_up_is_taken_over(rig):
    """After the plant gave up (or while an e-stop holds it) it sends no arming frame, so a drive
    that reaches closed loop then was armed by someone else (odrivetool), in a control mode of
    their choosing: the plant said it takes it over, but it sent torques straight away (in
    velocity control Input_Torque is only a feed-forward). Now zero torque and
    Set_Controller_Mode torque / passthrough first, as for a drive found armed at start."""
    for error in (DRV_FAULT, ESTOP):
        clock = Clock()
        r = armed(rig, clock, enable_retry_s=0.2, enable_max_attempts=3)
        b = r.backend
        _ride(r, clock, 0.2, AxisState.CLOSED_LOOP_CONTROL)
        _ride(r, clock, 3.0, AxisState.IDLE, error)
        assert b.gave_up or b.estop
        taken_over = b.stats()["taken_over"]             # (1: the rig's drive was found armed)
        frames = [(n, v) for _, n, v in _ride(r, clock, 0.2, AxisState.CLOSED_LOOP_CONTROL)]   # errors cleared
        names = [n for n, _ in frames]
        assert "Set_Controller_Mode" in names, f"not taken over (error {error:#x}): {names}"
        first_mode = names.index("Set_Controller_Mode")
        assert frames[first_mode][1] == {"Control_Mode": 1, "Input_Mode": 1}
        assert all(v["Input_Torque"] == 0.0 for n, v in frames[:first_mode] if n == "Set_Input_Torque")
        assert b.stats()["taken_over"] == taken_over + 1 and b.faults == 0
        assert any("armed by other means" in text for _, text in b.pop_events())


def test_a_drive_that_leaves_closed_loop_is_asked_why(rig):
    """ODrive 0.6.x keeps the error that disarmed the axis in Get_Error's Disarm_Reason; the
    Heartbeat's Axis_Error carries the errors active now, so a trip whose cause is already gone
    (a regenerative current spike) read "no error" in the plant's log and diagnostic. The plant
    now requests Get_Error when the drive leaves closed loop (before its Clear_Errors, which
    clears the reason) and names the disarm reason."""
    clock = Clock()
    r = armed(rig, clock)
    b = r.backend
    _ride(r, clock, 0.2, AxisState.CLOSED_LOOP_CONTROL)
    b.pop_events()
    clock.t += 0.05
    r.heartbeat(AxisState.IDLE, error=0)
    b.service()
    names = [n for n, v in r.host_frames()]
    assert "Get_Error" in names and names.index("Get_Error") < names.index("Clear_Errors"), names
    r.send("Get_Error", Active_Errors=0, Disarm_Reason=int(ODriveError.DC_BUS_OVER_REGEN_CURRENT))
    clock.t += 0.01
    b.service()
    level, reasons, values = b.diagnostic()
    assert values["can_disarm_reason"] == "DC_BUS_OVER_REGEN_CURRENT"
    assert any("disarm reason DC_BUS_OVER_REGEN_CURRENT" in x for x in reasons), reasons
    assert any("DC_BUS_OVER_REGEN_CURRENT" in text for _, text in b.pop_events())


ESTOP = int(ODriveError.ESTOP_REQUESTED)
ESTOP = int(ODriveError.ESTOP_REQUESTED)


def test_an_emergency_stop_is_never_cleared_by_the_plant(rig):
    """A drive disarmed with ESTOP_REQUESTED (an Estop frame from an e-stop node or another host)
    is held: the plant's re-arming sent Clear_Errors and closed loop at once, so the rider had the
    torque back one batch after the emergency stop. FAULT_DRIVE_DISARMED and an ERROR that say so;
    armed again when the e-stop is cleared on the drive (its errors change)."""
    clock = Clock()
    r = armed(rig, clock, enable_retry_s=0.2, enable_max_attempts=3)
    b = r.backend
    _ride(r, clock, 0.2, AxisState.CLOSED_LOOP_CONTROL)
    b.pop_events()
    frames = _ride(r, clock, 3.0, AxisState.IDLE, ESTOP)
    assert [n for _, n, _ in frames if n in ("Clear_Errors", "Set_Axis_State")] == [], "the e-stop was cleared"
    assert b.faults == FAULT_DRIVE_DISARMED and b.time_frozen
    level, reasons, values = b.diagnostic()
    assert level == 2 and any("emergency stop" in x and "never clears" in x for x in reasons), reasons
    assert values["can_arming"] == "estop" and values["can_axis_error"] == "ESTOP_REQUESTED"
    events = b.pop_events()
    assert sum(level == "error" and "emergency stop" in text for level, text in events) == 1, events
    frames = _ride(r, clock, 3.0, AxisState.IDLE, ESTOP | DRV_FAULT)      # with another error: still held
    assert [n for _, n, _ in frames if n in ("Clear_Errors", "Set_Axis_State")] == []
    frames = _ride(r, clock, 0.05, AxisState.IDLE, 0)                    # cleared on the drive: re-armed
    assert len(_arm_times(frames)) == 1
    _ride(r, clock, 0.1, AxisState.CLOSED_LOOP_CONTROL)
    assert b.faults == 0 and b.stats()["arm_gave_up"] == 0


def _flaky_drive(r, clock, seconds: float, hold_s: float, step_s: float = 0.05) -> list[float]:
    """A scripted drive that arms when the host asks (Clear_Errors + Set_Axis_State 8) and
    trips with DRV_FAULT after ``hold_s`` in closed loop. Returns the host's arm times."""
    state, error, armed_at, arms = AxisState.IDLE, DRV_FAULT, None, []
    end = clock.t + seconds
    while clock.t < end - 1e-9:
        clock.t += step_s
        if state == AxisState.CLOSED_LOOP_CONTROL and clock.t - armed_at >= hold_s - 1e-9:
            state, error = AxisState.IDLE, DRV_FAULT
        r.heartbeat(state, error=error)
        r.backend.submit(Cmd(-0.5))
        r.backend.service()
        r.backend.apply(Cmd(-0.5))
        for name, v in r.host_frames():
            if name == "Clear_Errors":
                error = 0
            elif name == "Set_Axis_State" and v["Axis_Requested_State"] == 8 and not error:
                state, armed_at = AxisState.CLOSED_LOOP_CONTROL, clock.t
                arms.append(clock.t)
    return arms


def test_a_re_armed_drive_gets_a_torque_ramp_from_zero(rig):
    """After (re-)arming, |setpoint| <= arm_ramp_nm_per_s x time in closed loop: the held
    DriveCommand is not stepped onto the rider."""
    clock = Clock()
    r = armed(rig, clock, arm_ramp_nm_per_s=20.0)
    frames = _ride(r, clock, 0.3, AxisState.CLOSED_LOOP_CONTROL, step_s=0.005, cmd=-2.0)
    torques = [v["Input_Torque"] for _, n, v in frames if n == "Set_Input_Torque"]
    assert torques[0] == pytest.approx(-0.1) and torques[-1] == pytest.approx(-2.0)
    assert all(-0.1 - 1e-6 <= b - a <= 0 for a, b in zip(torques, torques[1:])), "0.1 N m per 5 ms at most"
    assert len(torques) >= 20 and r.backend.stats()["ramped_setpoints"] >= 19
    frames = _ride(r, clock, 0.05, AxisState.IDLE, DRV_FAULT, step_s=0.005, cmd=-2.0)   # trips, re-armed
    after = _ride(r, clock, 0.1, AxisState.CLOSED_LOOP_CONTROL, step_s=0.005, cmd=-2.0)
    torques = [v["Input_Torque"] for _, n, v in frames + after if n == "Set_Input_Torque"]
    first = torques.index(0.0)
    assert max(abs(x) for x in torques[first:]) <= 20.0 * 0.1 + 1e-6 and abs(torques[-1]) > 1.0


def test_arm_and_trip_cycles_are_bounded_too(rig):
    """A drive that arms but trips again before armed_stable_s counts as a failed attempt;
    one that holds for armed_stable_s resets the count."""
    clock = Clock()
    r = armed(rig, clock, enable_retry_s=0.2, enable_max_attempts=3, armed_stable_s=1.0)
    r.heartbeat(AxisState.IDLE, error=DRV_FAULT)
    arms = _flaky_drive(r, clock, 10.0, hold_s=0.3)
    assert len(arms) == 3 and r.backend.gave_up, arms
    assert r.backend.faults == FAULT_DRIVE_DISARMED
    r2 = armed(rig, clock, enable_retry_s=0.2, enable_max_attempts=3, armed_stable_s=1.0)
    arms = _flaky_drive(r2, clock, 10.0, hold_s=1.2)
    assert len(arms) >= 6 and not r2.backend.gave_up, arms


def _controller_stall(r, clock, seconds: float, state=AxisState.IDLE, error: int = DRV_FAULT) -> None:
    """The node's DriveCommand timeout (a controller stalled under load): the safe state for
    ``seconds`` of batches with heartbeats, then DriveCommands resume."""
    b = r.backend
    b.set_safe(True)
    end = clock.t + seconds
    while clock.t < end - 1e-9:
        clock.t += 0.05
        r.heartbeat(state, error=error)
        b.service()
        b.safe_batch(1)
    b.set_safe(False)


def test_a_give_up_stands_through_a_controller_stall_and_a_late_gap_until_the_drive_reboots(rig):
    """After the give-up the plant stays disarmed with one ERROR until something changes at the
    drive: DriveCommands that stop for 0.25 s and resume (a controller stalled under load) send
    no arming frame, nor does a heartbeat gap the stalled loop finds only late; a drive silent
    while the loop looks and back with the same error (a reboot) gets a new bounded episode."""
    clock = Clock()
    r = armed(rig, clock, enable_retry_s=0.2, enable_max_attempts=3)
    b = r.backend
    _ride(r, clock, 0.2, AxisState.CLOSED_LOOP_CONTROL)
    frames = _ride(r, clock, 3.0, AxisState.IDLE, DRV_FAULT)              # trips, refuses 3 times
    assert len(_arm_times(frames)) == 3 and b.gave_up
    b.pop_events()
    _controller_stall(r, clock, 0.25)
    frames = _ride(r, clock, 3.0, AxisState.IDLE, DRV_FAULT)
    assert _arm_times(frames) == [], "a controller stall restarted arming after the give-up"
    assert b.gave_up and b.faults == FAULT_DRIVE_DISARMED and b.diagnostic()[2]["can_arming"] == "gave_up"
    clock.t += 0.39                                        # this loop stalls across a heartbeat gap
    r.heartbeat(AxisState.IDLE, error=DRV_FAULT)
    b.service()
    assert b.lost, "a late gap: lost for one batch"
    frames = _ride(r, clock, 3.0, AxisState.IDLE, DRV_FAULT)
    assert _arm_times(frames) == [] and b.gave_up and not b.lost
    events = b.pop_events()
    assert not any("gave up" in text or "re-arming again" in text for _, text in events), events
    assert b.stats()["arm_gave_up"] == 1 and b.stats()["enable_attempts"] == 3
    for _ in range(8):                                     # silent while the loop looks: lost, then back
        clock.t += 0.05
        b.service()
    assert b.lost
    frames = _ride(r, clock, 3.0, AxisState.IDLE, DRV_FAULT)
    assert len(_arm_times(frames)) == 3 and b.gave_up and b.stats()["arm_gave_up"] == 2
    assert any("re-arming again: the drive is back" in text for _, text in b.pop_events())
    # a stall while armed: the watchdog trip that follows is this plant's doing, not a failed attempt
    r2 = armed(rig, clock, enable_retry_s=0.2, enable_max_attempts=3)
    b2 = r2.backend
    frames = _ride(r2, clock, 0.3, AxisState.IDLE, DRV_FAULT)            # refused twice ...
    frames += _ride(r2, clock, 0.3, AxisState.CLOSED_LOOP_CONTROL)        # ... then armed (not yet stable)
    assert len(_arm_times(frames)) == 2 and b2.drive_enabled
    _controller_stall(r2, clock, 0.25, AxisState.IDLE, WATCHDOG)
    frames = _ride(r2, clock, 0.05, AxisState.IDLE, WATCHDOG)
    assert len(_arm_times(frames)) == 1 and b2.diagnostic()[2]["can_arming"] == "attempt 1"


def test_an_idle_drive_is_only_a_fault_when_it_should_be_armed(rig):
    clock = Clock()
    r = rig(clock)
    b = r.backend
    r.heartbeat(AxisState.IDLE)                           # a fresh drive, no DriveCommand yet
    b.service()
    assert b.faults == 0 and b.diagnostic()[0] == 1
    assert [n for n, v in r.host_frames() if v != "RTR"] == [], "not armed before DriveCommands flow"
    frames = _ride(r, clock, 0.4, AxisState.IDLE, 0)     # commanded: arming, within disarm_grace_s
    assert _arm_times(frames) and b.faults == 0
    _ride(r, clock, 0.2, AxisState.IDLE, 0)               # 0.6 s > grace 0.5 s and still not armed
    assert b.faults == FAULT_DRIVE_DISARMED
    _ride(r, clock, 0.1, AxisState.CLOSED_LOOP_CONTROL)
    assert b.faults == 0
    frames = _ride(r, clock, 0.05, AxisState.IDLE, 0)    # someone set it IDLE (no error)
    assert b.faults == FAULT_DRIVE_DISARMED
    frames += _ride(r, clock, 2.0, AxisState.IDLE, 0)
    assert _arm_times(frames) and b.faults == FAULT_DRIVE_DISARMED
    b.set_safe(True)                                      # no DriveCommands: nothing is sent to arm it
    assert r.torques() == [0.0]
    for _ in range(10):                                   # 1 s of an alive, idle drive
        clock.t += 0.1
        r.heartbeat(AxisState.IDLE)
        b.service()
    assert [n for n, v in r.host_frames() if v != "RTR"] == [] and b.faults == FAULT_DRIVE_DISARMED


def test_a_bus_that_goes_away_is_reopened(rig):
    """A USB adapter unplugged and plugged back: a receive raised (python-can's CanOperationError)
    and the plant's bus object never brought a frame again (the kernel unbinds a SocketCAN socket
    from an interface that goes away; here the closed bus raises on every call), so the drive
    stayed lost until the plant was restarted. Now RX_FAILING_REOPEN_S after a failed receive
    with no frame since, the plant reopens its bus (every second until it opens): the drive is
    back."""
    clock = Clock()
    r = armed(rig, clock)
    b = r.backend
    old = b.bus
    old.shutdown()                                        # the adapter is gone: every call raises
    for _ in range(40):                                   # 2 s
        clock.t += 0.05
        r.heartbeat()
        b.service()
    assert b.bus is not old and b.stats()["bus_reopened"] == 1
    assert b.link_alive and b.stats()["drive_back"] == 1
    events = b.pop_events()
    assert any(level == "warning" and "reopened" in text and "Cannot operate on a closed bus" in text
               for level, text in events), events


def test_safe_state_zero_torque_and_no_more_watchdog_feeding(rig):
    clock = Clock()
    r = armed(rig, clock, watchdog_feed_s=0.1)
    b = r.backend
    b.apply(Cmd(-1.2))
    assert r.torques() == [pytest.approx(-1.2)]
    clock.t += 0.05
    r.heartbeat()
    b.service()
    assert r.torques() == []
    clock.t += 0.06                                       # 0.11 s since the setpoint: keepalive
    r.heartbeat()
    b.service()
    assert r.torques() == [pytest.approx(-1.2)]
    b.set_safe(True)                                      # the node's DriveCommand timeout
    b.safe_batch(100)
    assert r.torques() == [0.0]
    for _ in range(10):
        clock.t += 0.05
        r.heartbeat()
        b.service()
        b.safe_batch(100)
    assert r.host_frames() == [] or all(n != "Set_Input_Torque" for n, _ in r.host_frames())
    b.set_safe(False)
    b.apply(Cmd(-0.6))
    assert r.torques() == [pytest.approx(-0.6)]


def test_can_log_in_asc_and_blf_and_a_clean_close(rig, tmp_path):
    for suffix in ("asc", "blf"):
        path = tmp_path / f"traffic.{suffix}"
        r = rig(log_file=str(path))
        r.heartbeat()
        r.backend.service()
        r.send("Get_Encoder_Estimates", Pos_Estimate=0.5, Vel_Estimate=10.0)
        r.backend.submit(Cmd(-0.25))
        r.backend.service()
        r.backend.close()
        frames = r.host_frames()
        assert frames[-2:] == [("Set_Input_Torque", {"Input_Torque": 0.0}),
                               ("Set_Axis_State", {"Axis_Requested_State": 1})], "close(): zero torque + IDLE"
        logged = list(can.LogReader(str(path)))
        rx = [m for m in logged if m.is_rx]
        tx = [m for m in logged if not m.is_rx]
        assert {m.arbitration_id for m in rx} == {0x01, 0x09}
        assert 0x0E in {m.arbitration_id for m in tx} and 0x07 in {m.arbitration_id for m in tx}
        assert len(logged) == r.backend.log_frames
        stamps = [m.timestamp for m in logged]               # rx: the bus's receive time, tx: the send time
        assert max(stamps) - min(stamps) < 5.0 and len({m.channel for m in logged}) == 1


# ----------------------------------------------------------------------------- against the emulator
def test_against_the_drive_emulator_in_process(rig):
    r = rig()
    params = DriveModelParams.from_config(r.cfg)
    emu = DriveEmulator(r.drive_bus, DriveFirmware(AverageTorqueDrive(params)), 0)
    stop = threading.Event()
    thread = threading.Thread(target=emu.run, args=(stop,), daemon=True)
    thread.start()
    b = r.backend
    seen = {}
    try:
        for torque in (-1.0, 0.6):
            # 1 s and 100 batches at least: a loaded machine runs fewer 5 ms batches a second
            end, batches, give_up = time.monotonic() + 1.0, 0, time.monotonic() + 30.0
            while (time.monotonic() < end or batches < 100) and time.monotonic() < give_up:
                msg = Cmd(torque)
                b.submit(msg)
                b.service()
                b.apply(msg)
                batches += 1
                time.sleep(0.005)
            seen[torque] = (b.snapshot(), b.time_s)
    finally:
        stop.set()
        thread.join(5.0)
    brake, t1 = seen[-1.0]
    motor, t2 = seen[0.6]
    assert brake["torque_em_nm"] == pytest.approx(-1.0, abs=0.02)
    assert brake["battery_current_a"] > 0 and motor["battery_current_a"] < 0     # charging while braking
    assert motor["torque_em_nm"] == pytest.approx(0.6, abs=0.02)
    assert brake["energy_battery_j"] > 0 and brake["speed_rpm"] > 500
    assert 0 < t1 < t2 and b.stats()["dropped"] == 0 and b.stats()["armed"] == 1
    assert emu.counters.get("rx:Set_Input_Torque", 0) >= 100


def _batches_until(b, torque_nm, done, seconds: float = 30.0) -> None:
    """Batches of 5 ms with DriveCommand ``torque_nm`` (None: the safe state's) until ``done()``."""
    give_up = time.monotonic() + seconds
    while not done():
        assert time.monotonic() < give_up, "timed out"
        b.service()
        if torque_nm is None:
            b.safe_batch(1)
        else:
            msg = Cmd(torque_nm)
            b.submit(msg)
            b.apply(msg)
        time.sleep(0.005)


def test_the_safe_state_idles_the_drive_whatever_feeds_its_watchdog(rig):
    """A drive whose watchdog every frame to the axis feeds (the open 0.5.x firmware does, RTR
    requests included; what feeds 0.6.x's is not published) stayed armed through the safe state:
    the plant's RTR requests fed it, so "the drive disarms itself" did not hold. The plant now
    sets it IDLE when the safe state begins (and again if it shows armed), re-arms it when
    DriveCommands are back, and leaves it IDLE when it closes."""
    r = rig(watchdog_feed_s=0.1)
    params = DriveModelParams.from_config(r.cfg)
    fw = DriveFirmware(AverageTorqueDrive(params), watchdog_timeout_s=0.5, watchdog_fed_by="any")
    emu = DriveEmulator(r.drive_bus, fw, 0)
    stop = threading.Event()
    thread = threading.Thread(target=emu.run, args=(stop,), daemon=True)
    thread.start()
    b = r.backend
    try:
        _batches_until(b, -0.5, lambda: b.drive_enabled and fw.input_torque_nm == pytest.approx(-0.5))
        b.set_safe(True)                                  # the node's DriveCommand timeout
        requests = emu.counters.get("rx:Get_Torques?", 0)
        end = time.monotonic() + 1.0                      # twice the drive's watchdog timeout
        _batches_until(b, None, lambda: time.monotonic() > end)
        assert emu.counters.get("rx:Get_Torques?", 0) > requests + 20, "the plant kept requesting"
        assert fw.axis_state == AxisState.IDLE, "the safe state left the drive armed"
        assert not fw.active_errors & WATCHDOG, "IDLE by request, not a watchdog trip"
        assert b.faults == FAULT_DRIVE_DISARMED and b.time_frozen
        b.set_safe(False)                                 # DriveCommands are back: re-armed
        _batches_until(b, -0.5, lambda: b.drive_enabled and fw.input_torque_nm == pytest.approx(-0.5))
        assert fw.armed and b.faults == 0 and b.stats()["arm_gave_up"] == 0
        b.close()                                         # end of run / Ctrl-C
        end = time.monotonic() + 0.2
        while time.monotonic() < end and fw.armed:
            time.sleep(0.01)
        assert fw.axis_state == AxisState.IDLE, "a clean shutdown leaves the drive IDLE"
    finally:
        stop.set()
        thread.join(5.0)


# ----------------------------------------------------------------------------- config
def test_config_section_and_emulator_arguments(tmp_path):
    cfg = load_config(CAN_CONFIG)
    p = can_params_from_config(cfg)
    assert (p.interface, p.node_id, p.heartbeat_timeout_s) == ("udp_multicast", 0, pytest.approx(0.3))
    args = emulator_args_from_config(cfg)
    assert args[args.index("--port") + 1] == str(p.port) and args[args.index("--heartbeat-ms") + 1] == "100"
    for key, value, text in (("node_id", 64, "node_id"), ("log_file", "x.txt", ".asc or .blf"),
                             # ODrive 0.6.x: 0x3F is the broadcast id (ODriveResources examples/can_enumerate.py)
                             ("node_id", 63, r"0\.\.62 for odrive_cansimple_0\.6, got 63 \(63 = 0x3F is the ODrive "
                                             "broadcast id"),
                             ("request", ["torque", "nope"], "unknown kind"), ("bogus", 1, "unknown parameter"),
                             ("heartbeat_timeout_s", 0.0, "> 0"), ("protocol", "vesc", "unknown 'vesc'"),
                             ("enable_max_attempts", -1, ">= 0"), ("arm_ramp_nm_per_s", -5.0, ">= 0"),
                             # Set_Limits sets both: a one-sided limit would overwrite the other on the drive
                             ("velocity_limit_rev_s", 0.0, "go together"), ("current_limit_a", 0.0, "go together"),
                             # a drive at heartbeat_msg_rate_ms 500 told in the config, the timeout left at 0.3 s
                             ("heartbeat_period_s", 0.5, "must be longer than heartbeat_period_s"),
                             ("watchdog_feed_s", 0.5, "must be shorter than the drive's watchdog"),
                             # it failed in the plant and the drive emulator once the graph had started
                             ("channel", "nope", r"channel: udp_multicast takes a multicast group address .*, "
                                                 "got 'nope'"),
                             ("channel", "10.0.0.1", "got '10.0.0.1'")):
        bad = load_config(CAN_CONFIG)
        bad["can"][key] = value
        with pytest.raises(ConfigError, match=text):
            can_params_from_config(bad)
    from bike_plant.node import make_backend
    lockstep = load_config(CAN_CONFIG)
    lockstep["sync_mode"] = "lockstep"
    with pytest.raises(ConfigError, match="realtime"):
        make_backend("can", lockstep, 0)


# ----------------------------------------------------------------------------- the controller's answer
def _drive_snapshot(speed_rpm, torque_em=0.0, faults=0, stamp_ns=0, seq=0):
    return {"measured_by_drive": True, "speed_rpm": speed_rpm, "speed_rad_s": speed_rpm / 9.549296585513721,
            "torque_em_nm": torque_em, "faults": faults, "stamp_ns": stamp_ns, "seq": seq}


def test_controller_answers_a_drive_with_a_torque_only(tmp_path):
    from bike_controller.session_control import ModedController
    from bike_plant.params import nominal_params_from_config

    cfg = load_config(CAN_CONFIG)
    ctrl = ModedController(cfg, nominal_params_from_config(cfg))
    ctrl.set_command(0.2, 2)                                  # ERG: 0.2 x Pmax = 203.3 W
    batch_ns = 5_000_000
    ga, gb, sp, st = ctrl.decide(_drive_snapshot(2800.0, stamp_ns=0), 100)
    assert len(ga) == len(gb) == len(sp) == 0
    w = 2800.0 / 9.549296585513721
    # the brake leaves the bike's friction (1e-4 N m s x w) to the rider: ERG holds his power
    assert st["torque_cmd_nm"] == pytest.approx(0.2 * 1016.68 / w - 1e-4 * w, rel=1e-6) and st["quadrant"] == 2
    assert st["speed_est_rpm"] == 2800.0 and st["mode_target"] == pytest.approx(0.2 * 1016.68)
    t_ns = 0
    for k in range(1, 40):                                     # the drive delivers only 90 %: the trim raises it
        t_ns = k * batch_ns
        _, _, _, st = ctrl.decide(_drive_snapshot(2800.0, -0.9 * st["torque_cmd_nm"], stamp_ns=t_ns), 100)
    assert st["torque_trim_nm"] > 0 and st["torque_cmd_nm"] > 0.2 * 1016.68 / w - 1e-4 * w
    held = st["torque_cmd_nm"]
    _, _, _, st = ctrl.decide(_drive_snapshot(2800.0, -0.9 * held, stamp_ns=t_ns), 100)   # stamp frozen: holds
    assert st["torque_cmd_nm"] == pytest.approx(held)
    _, _, _, st = ctrl.decide(_drive_snapshot(2800.0, faults=FAULT_DRIVE_LOST, stamp_ns=t_ns), 100)
    assert st["torque_cmd_nm"] == 0.0
    torques = []
    for k in range(1, 6):                                      # back: ramped up from zero (20 N m/s)
        _, _, _, st = ctrl.decide(_drive_snapshot(2800.0, stamp_ns=t_ns + k * batch_ns), 100)
        torques.append(st["torque_cmd_nm"])
        assert st["mode_ramping"]
    assert torques[0] == pytest.approx(0.1)                     # 20 N m/s x 5 ms (+ the trim, slowly)
    assert all(0.09 < b - a < 0.13 for a, b in zip(torques, torques[1:]))
    ctrl.set_command(0.5, 1)                                   # motoring: assist torque, quadrant I
    for k in range(6, 200):
        em = st["torque_cmd_nm"] * (-1 if st["quadrant"] == 2 else 1)   # the drive delivers what it is asked
        _, _, _, st = ctrl.decide(_drive_snapshot(2800.0, em, stamp_ns=t_ns + k * batch_ns), 100)
    assert st["quadrant"] == 1 and st["torque_cmd_nm"] == pytest.approx(0.5 * TMAX, rel=0.05)


def test_the_controller_holds_its_trim_on_stale_measurements_and_erg_never_motors():
    """A drive whose estimates froze (the emulator stalled for ~350 ms): the ERG trim must not
    wind up on the frozen torque, and whatever the trim did, ERG never asks for motoring torque."""
    from bike_controller.session_control import ModedController
    from bike_plant.params import nominal_params_from_config

    cfg = load_config(CAN_CONFIG)
    batch_ns = 5_000_000
    ctrl = ModedController(cfg, nominal_params_from_config(cfg))
    ctrl.set_command(0.2, 2)                                   # ERG 203 W
    _, _, _, st = ctrl.decide(_drive_snapshot(2800.0, stamp_ns=0), 100)
    for k in range(1, 20):                                      # the drive follows
        _, _, _, st = ctrl.decide(_drive_snapshot(2800.0, -st["torque_cmd_nm"] - 1e-3 * k, stamp_ns=k * batch_ns), 100)
    trim0 = st["torque_trim_nm"]
    frozen = -3.0                                               # a frozen (huge) braking estimate, flagged stale
    for k in range(20, 90):                                     # 350 ms of stale frames
        _, _, _, st = ctrl.decide(_drive_snapshot(2800.0, frozen, faults=FAULT_DRIVE_STALE, stamp_ns=k * batch_ns), 100)
    assert st["torque_trim_nm"] == pytest.approx(trim0), "held on stale measurements"
    assert ctrl.drive_law.stale_steps == 70
    for k in range(90, 160):                                    # repeated bit for bit, not flagged: held too
        _, _, _, st = ctrl.decide(_drive_snapshot(2800.0, frozen, stamp_ns=k * batch_ns), 100)
    assert abs(st["torque_trim_nm"] - trim0) < 0.05 and st["quadrant"] == 2
    # a trim that wound up anyway (e.g. a plant that does not flag): ERG stays a brake, counted
    ctrl.trim.trim_nm = -0.3 * TMAX
    _, _, _, st = ctrl.decide(_drive_snapshot(2800.0, -0.5, stamp_ns=161 * batch_ns), 100)
    assert st["quadrant"] == 2 and st["torque_cmd_nm"] == 0.0 and st["mode_saturated"]
    assert ctrl.trim.sign_clamps == 1
    for k in range(162, 400):                                   # the drive delivers what it is asked: trim recovers
        em = -st["torque_cmd_nm"] if st["quadrant"] == 2 else st["torque_cmd_nm"]
        _, _, _, st = ctrl.decide(_drive_snapshot(2800.0 + k % 3, em, stamp_ns=k * batch_ns), 100)
        assert st["quadrant"] == 2, "ERG never motors"
    w = 2800.0 / 9.549296585513721
    assert st["torque_cmd_nm"] == pytest.approx(0.2 * 1016.68 / w - 1e-4 * w, rel=0.05)   # less the friction


def test_spmsm_controller_answers_a_drive_with_a_torque_only():
    from bike_controller.spmsm_session import ModedSpmsmController

    # the CAN config: its drive brakes on its inverter, so no rectifier envelope (zero brake at
    # 200 r/min) limits the law
    cfg = load_config(ROOT / "config" / "spmsm_can.yaml")
    ctrl = ModedSpmsmController(cfg)
    ctrl.set_command(0.5, 0)
    duties, relay, buck, st = ctrl.decide(_drive_snapshot(200.0), 10)
    assert duties.shape == (0, 3) and len(relay) == len(buck) == 0
    assert st["torque_cmd_nm"] > 0 and st["quadrant"] == 2 and st["family"] == ""


def test_the_launch_file_starts_the_emulator_with_the_bus_of_the_config(tmp_path):
    """config/launch/bike.launch.yaml: the ROS 2 YAML `executable` action (cmd, if) as ./bike run
    fills it for a config with can.emulator: true."""
    import shlex

    from bike_session.launcher import ExecutableSpec, LaunchError, NodeSpec, parse_launch

    launch = ROOT / "config" / "launch" / "bike.launch.yaml"
    args = " ".join(shlex.quote(a) for a in emulator_args_from_config(load_config(CAN_CONFIG)))
    specs = parse_launch(str(launch), {"config": str(CAN_CONFIG), "emulator": "true", "emulator_args": args,
                                       "can_log": "/tmp/x.can.asc"})
    emu = specs[0]
    assert isinstance(emu, ExecutableSpec) and emu.name == "drive_emulator"
    assert emu.argv[0].endswith("lib/bike_controller/bike-drive-emulator") and not emu.shutdown_on_exit
    assert emu.argv[emu.argv.index("--config") + 1] == str(CAN_CONFIG)
    assert emu.argv[emu.argv.index("--port") + 1] == "43213" and emu.argv[emu.argv.index("--node-id") + 1] == "0"
    plant = specs[1]
    assert isinstance(plant, NodeSpec) and plant.params["can_log_file"] == "/tmp/x.can.asc"
    assert [s.name for s in parse_launch(str(launch), {"config": str(CAN_CONFIG)})] == \
        ["plant", "controller", "session"], "no emulator unless asked"
    bad = tmp_path / "x.launch.yaml"
    bad.write_text("launch:\n- executable: {cmd: '', name: e}\n")
    with pytest.raises(LaunchError, match="'cmd' is required"):
        parse_launch(str(bad))
    bad.write_text("launch:\n- executable: {cmd: no-such-program-here --x 1}\n")
    with pytest.raises(LaunchError, match="not found on PATH"):
        parse_launch(str(bad))[0].command()


def test_socketcan_on_a_kernel_without_it_is_one_config_error_that_says_so():
    """A config for a real drive on a machine without SocketCAN (this one): one ConfigError
    naming the cause and the way out, not only '[Errno 97] Address family not supported'."""
    import socket
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
        pytest.skip("this kernel has SocketCAN")
    except (OSError, AttributeError):
        pass
    cfg = load_config(CAN_CONFIG)
    cfg["can"].update(interface="socketcan", channel="can0", emulator=False)
    with pytest.raises(ConfigError, match="this kernel has no SocketCAN") as info:
        CanBackend(cfg)
    assert str(info.value).count("error:") == 0 and "can0" in str(info.value)
