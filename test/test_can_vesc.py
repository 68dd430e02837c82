"""VESC on CAN (vedderb/bldc documentation/comm_can.md): the codec over vesc_can.dbc, the host
side (bike_plant.can.protocol.VescCan), the plant's CanBackend with a protocol that has no
arming (link = STATUS frames), and bike-drive-emulator --protocol vesc_can, in process on a
virtual bus and as a process over udp_multicast."""
from __future__ import annotations

import math
import pathlib
import signal
import struct
import threading
import time
import uuid

import can
import cantools
import pytest

from bike_plant.can import (PROTOCOLS, VESC_DBC_PATH, VESC_DRIVE_TO_HOST, VESC_HOST_TO_DRIVE, OdriveCanSimpleCodec,
                            VescCan, VescCanCodec)
from bike_plant.can.backend import FAULT_DRIVE_LOST, CanBackend, can_params_from_config, emulator_args_from_config
from bike_plant.config import ConfigError, load_config
from bike_controller.drive_emulator import AverageTorqueDrive, DriveModelParams, VescEmulator, VescFirmware
from bike_session.bags import read_topic
from bike_session.report import summarise
from node_harness import stamp_ns
from test_can_backend import Rig
from test_can_emulator import GROUP, Emulator
from test_can_graph import _port, recorded_run, write_config

ROOT = pathlib.Path(__file__).resolve().parents[1]
VESC_CONFIG = ROOT / "config" / "bldc_vesc.yaml"
CAN_CONFIG = ROOT / "config" / "bldc_can.yaml"
KT = 5.45e-3 * 60.0 / (2.0 * math.pi)   # kt of config/bldc_default.yaml (ke 5.45e-3 V/rpm line-to-line)
POLE_PAIRS = 2


class Clock:
    def __init__(self, t: float = 100.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


class Cmd:
    def __init__(self, torque_nm: float):
        self.torque_cmd_nm = torque_nm
        self.current_cmd_a = 0.0


# ----------------------------------------------------------------------------- codec and DBC
def test_the_docs_example_51_a_to_vesc_23():
    """comm_can.md: SET_CURRENT 51 A to VESC ID 23 is extended id 0x0117 with data 00 00 C7 38."""
    msg = VescCanCodec(23).encode("Set_Current", {"Current": 51.0})
    assert msg.is_extended_id and msg.arbitration_id == 0x0117
    assert bytes(msg.data) == bytes.fromhex("0000C738")
    assert VescCanCodec(23).message_name(0x0117) == "Set_Current"
    assert VescCanCodec(22).message_name(0x0117) is None


def test_dbc_ids_are_command_ids_shifted_by_8_for_vesc_id_0():
    db = cantools.database.load_file(str(VESC_DBC_PATH))
    ids = {m.name: m.frame_id for m in db.messages}
    assert ids == {"Set_Duty": 0x000, "Set_Current": 0x100, "Set_Current_Brake": 0x200, "Set_Rpm": 0x300,
                   "Set_Pos": 0x400, "Set_Current_Rel": 0xA00, "Status": 0x900, "Status_2": 0xE00,
                   "Status_3": 0xF00, "Status_4": 0x1000, "Status_5": 0x1B00}
    assert all(m.is_extended_frame for m in db.messages)
    assert set(ids) == VESC_HOST_TO_DRIVE | VESC_DRIVE_TO_HOST


def test_status_byte_layouts_are_big_endian_with_the_docs_scales():
    codec = VescCanCodec(5)
    status = codec.encode("Status", {"Erpm": -12345, "Current": -12.3, "Duty_Cycle": 0.456})
    assert status.arbitration_id == (9 << 8) | 5
    assert bytes(status.data) == struct.pack(">ihh", -12345, -123, 456)
    status4 = codec.encode("Status_4", {"Temp_Fet": 31.5, "Temp_Motor": -4.2, "Current_In": 7.1, "Pid_Pos": 180.0})
    assert bytes(status4.data) == struct.pack(">hhhh", 315, -42, 71, 9000)
    status5 = codec.encode("Status_5", {"Tachometer": -70000, "Voltage_In": 48.3, "Reserved": 0})
    assert status5.arbitration_id == (27 << 8) | 5 and bytes(status5.data) == struct.pack(">ihh", -70000, 483, 0)
    status2 = codec.encode("Status_2", {"Amp_Hours": 1.2345, "Amp_Hours_Charged": 0.5})
    assert bytes(status2.data) == struct.pack(">ii", 12345, 5000)
    rpm = codec.encode("Set_Rpm", {"Erpm": -3000})
    assert rpm.arbitration_id == (3 << 8) | 5 and bytes(rpm.data) == struct.pack(">i", -3000)


def test_a_dbc_for_one_vesc_id_for_tools_without_an_id_mask(tmp_path):
    from bike_plant.can.protocol import main
    out = tmp_path / "vesc23.dbc"
    assert main(["--protocol", "vesc_can", "--export-dbc", "23", str(out)]) == 0
    db = cantools.database.load_file(str(out))
    current = db.get_message_by_name("Set_Current")
    assert current.frame_id == 0x0117 and current.is_extended_frame
    assert current.decode(bytes.fromhex("0000C738"))["Current"] == pytest.approx(51.0)
    assert db.get_message_by_name("Status_5").frame_id == (27 << 8) | 23
    assert "VESC ID 23 (already added)" in out.read_text()
    with pytest.raises(SystemExit):
        main(["--protocol", "vesc_can", "--export-dbc", "255", str(out)])      # the broadcast id: refused


@pytest.mark.parametrize("name", sorted(VESC_HOST_TO_DRIVE | VESC_DRIVE_TO_HOST))
def test_every_message_round_trips(name):
    codec = VescCanCodec(200)
    message = codec.messages[name]
    # a value inside each signal's range, on its resolution
    signals = {s.name: round((s.minimum + (s.maximum - s.minimum) * 0.3) / s.scale) * s.scale
               for s in message.signals}
    msg = codec.encode(name, signals)
    receives = VESC_HOST_TO_DRIVE if name in VESC_HOST_TO_DRIVE else VESC_DRIVE_TO_HOST
    decoded = codec.classify(msg, frozenset(receives), answers_requests=False)
    assert decoded.name == name
    for sig, value in signals.items():
        assert decoded.signals[sig] == pytest.approx(value, abs=message.get_signal_by_name(sig).scale)


def test_bad_setpoints_raise_one_clear_error():
    codec = VescCanCodec(0)
    with pytest.raises(ValueError, match="outside"):
        codec.encode("Set_Current", {"Current": 5000.0})
    with pytest.raises(ValueError, match="finite"):
        codec.encode("Set_Current", {"Current": math.nan})
    with pytest.raises(ValueError, match="node_id"):
        VescCanCodec(255)            # the broadcast id would command every VESC
    with pytest.raises(ValueError, match="pole_pairs"):
        VescCan(None, 0, pole_pairs=0, torque_constant_nm_per_a=KT)
    with pytest.raises(ValueError, match="torque_constant"):
        VescCan(None, 0, pole_pairs=2, torque_constant_nm_per_a=-1.0)


# ----------------------------------------------------------------------------- host side
@pytest.fixture
def buses():
    channel = uuid.uuid4().hex
    host_bus = can.Bus(interface="virtual", channel=channel)
    drive_bus = can.Bus(interface="virtual", channel=channel)
    yield host_bus, drive_bus
    host_bus.shutdown()
    drive_bus.shutdown()


def test_status_frames_become_neutral_measurements(buses):
    host_bus, _ = buses
    clock = Clock()
    vesc = VescCan(host_bus, 7, pole_pairs=POLE_PAIRS, torque_constant_nm_per_a=KT, clock=clock)
    codec = VescCanCodec(7)
    assert not vesc.enabled and not vesc.link_alive()
    vesc.receive(codec.encode("Status", {"Erpm": 6000, "Current": -20.0, "Duty_Cycle": 0.4}))
    vesc.receive(codec.encode("Status_4", {"Temp_Fet": 30.0, "Temp_Motor": 40.0, "Current_In": -3.5,
                                           "Pid_Pos": 0.0}))
    vesc.receive(codec.encode("Status_5", {"Tachometer": 30, "Voltage_In": 50.2, "Reserved": 0}))
    v = vesc.values()
    assert v["speed_rev_s"] == pytest.approx(6000 / POLE_PAIRS / 60.0)              # ERPM / pole pairs
    assert v["torque_estimate_nm"] == pytest.approx(-20.0 * KT)                     # kt x motor current
    assert v["iq_measured_a"] == pytest.approx(-20.0)
    assert v["position_rev"] == pytest.approx(30 / (6 * POLE_PAIRS))                # 6 counts per e-rev
    assert v["bus_voltage_v"] == pytest.approx(50.2) and v["bus_current_a"] == pytest.approx(-3.5)
    assert vesc.enabled and vesc.link_alive() and vesc.active_errors == 0
    assert vesc.counters["rx:Status"] == 1 and vesc.counters["decoded"] == 3
    clock.t += 0.6
    assert not vesc.link_alive(), "no STATUS for the timeout: the link is down"


def test_malformed_and_foreign_frames_are_counted_never_raised(buses):
    host_bus, _ = buses
    vesc = VescCan(host_bus, 7, pole_pairs=POLE_PAIRS, torque_constant_nm_per_a=KT)
    codec = VescCanCodec(7)
    status_id = codec.arbitration_id("Status")
    frames = {
        "standard_id": can.Message(arbitration_id=0x123, data=bytes(8), is_extended_id=False),
        "bad_dlc": can.Message(arbitration_id=status_id, data=bytes(5), is_extended_id=True),
        "other_node": VescCanCodec(8).encode("Status", {"Erpm": 1, "Current": 1.0, "Duty_Cycle": 0.0}),
        "unknown_cmd": can.Message(arbitration_id=(100 << 8) | 7, data=bytes(8), is_extended_id=True),
        # STATUS_6 (58, vedderb/bldc datatypes.h): a valid packet this plant does not use, not malformed
        "unused_message": can.Message(arbitration_id=(58 << 8) | 7, data=bytes(8), is_extended_id=True),
        "unexpected_rtr": can.Message(arbitration_id=status_id, is_remote_frame=True, dlc=8, is_extended_id=True),
        "error_frame": can.Message(is_error_frame=True, arbitration_id=0, data=bytes(8)),
        "fd_frame": can.Message(arbitration_id=status_id, data=bytes(12), is_fd=True, is_extended_id=True),
        "other_direction": codec.encode("Set_Current", {"Current": 3.0}),   # another host's command
    }
    for reason, msg in frames.items():
        assert vesc.receive(msg) == [], reason
        assert vesc.counters[reason] == 1, reason
    weird = can.Message(arbitration_id=status_id, data=bytes(8), is_extended_id=True)
    weird.arbitration_id = "garbage"                                       # anything a driver might hand us
    assert vesc.receive(weird) == []
    assert vesc.counters["decoded"] == 0 and "status" not in vesc.last
    assert vesc.dropped == sum(vesc.counters[r] for r in ("standard_id", "bad_dlc", "unknown_cmd",
                                                           "unexpected_rtr", "error_frame", "fd_frame", "unknown_id"))


def test_torque_goes_out_as_set_current_and_keepalive_feeds_the_timeout(buses):
    host_bus, drive_bus = buses
    clock = Clock()
    vesc = VescCan(host_bus, 23, pole_pairs=POLE_PAIRS, torque_constant_nm_per_a=KT, clock=clock,
                   watchdog_feed_interval_s=0.1)
    codec = VescCanCodec(23)
    assert vesc.set_torque(51.0 * KT)
    sent = drive_bus.recv(1.0)
    assert sent.arbitration_id == 0x0117 and bytes(sent.data) == bytes.fromhex("0000C738")
    assert vesc.set_torque(-1.0)                       # braking: negative current (regenerates)
    decoded = codec.classify(drive_bus.recv(1.0), VESC_HOST_TO_DRIVE, answers_requests=True)
    assert decoded.name == "Set_Current" and decoded.signals["Current"] == pytest.approx(-1.0 / KT, abs=1e-3)
    clock.t += 0.05
    assert not vesc.keepalive()
    clock.t += 0.06
    assert vesc.keepalive()                            # resent: the VESC stops after 0.5 s without one
    again = codec.classify(drive_bus.recv(1.0), VESC_HOST_TO_DRIVE, answers_requests=True)
    assert again.signals["Current"] == pytest.approx(-1.0 / KT, abs=1e-3)
    assert vesc.disable()
    released = codec.classify(drive_bus.recv(1.0), VESC_HOST_TO_DRIVE, answers_requests=True)
    assert released.name == "Set_Current" and released.signals["Current"] == 0.0
    clock.t += 1.0
    assert not vesc.keepalive(), "after disable nothing is repeated"
    assert vesc.set_velocity(25.0)                     # 25 rev/s x 60 x 2 pole pairs = 3000 ERPM
    rpm = codec.classify(drive_bus.recv(1.0), VESC_HOST_TO_DRIVE, answers_requests=True)
    assert rpm.name == "Set_Rpm" and rpm.signals["Erpm"] == 3000
    assert not vesc.request("status") and vesc.counters["unsupported:request"] == 1


def test_odrive_codec_is_unchanged_by_the_generalisation():
    codec = OdriveCanSimpleCodec(3)
    msg = codec.encode("Set_Input_Torque", {"Input_Torque": 1.5})
    assert msg.arbitration_id == (3 << 5) | 0x0E and not msg.is_extended_id
    assert bytes(msg.data) == struct.pack("<f", 1.5) + bytes(4)
    assert codec.classify(can.Message(arbitration_id=0x61, data=bytes(8), is_extended_id=True), frozenset(),
                          False) == "extended_id"
    assert set(PROTOCOLS) == {"odrive_cansimple_0.6", "vesc_can"}


# ----------------------------------------------------------------------------- the plant's backend
class VescRig(Rig):
    """CanBackend with protocol vesc_can and the VESC's end of a virtual bus (scripted STATUS)."""

    def __init__(self, clock=None, **can_changes):
        super().__init__(clock, VESC_CONFIG, VescCanCodec, **can_changes)

    def status(self, erpm: int = 4000, current_a: float = 0.0) -> None:
        self.send("Status", Erpm=erpm, Current=current_a, Duty_Cycle=0.3)

    def currents(self) -> list[float]:
        out = []
        for name, signals in self.host_frames():
            assert name == "Set_Current", name
            out.append(signals["Current"])
        return out


@pytest.fixture
def vesc_rig():
    made = []

    def make(clock=None, **changes) -> VescRig:
        r = VescRig(clock, **changes)
        made.append(r)
        return r

    yield make
    for r in made:
        r.close()


def test_backend_link_is_status_frames_lost_then_back(vesc_rig):
    clock = Clock()
    r = vesc_rig(clock)
    b = r.backend
    b.service()
    assert b.time_frozen and not b.seen
    assert "waiting for the drive's Status" in b.diagnostic()[1][0]
    r.status(erpm=4000, current_a=2.0)
    b.service()
    assert b.drive_enabled and not b.time_frozen and b.faults == 0, "no arming: STATUS is enough"
    assert r.currents() == [], "nothing is sent to arm a VESC"
    assert b.submit(Cmd(-1.0))
    assert r.currents() == [pytest.approx(-1.0 / KT, abs=1e-3)]
    b.apply(Cmd(-1.0))                                 # every batch's command goes out: the VESC's timeout
    assert r.currents() == [pytest.approx(-1.0 / KT, abs=1e-3)]
    snap = b.snapshot()
    assert snap["speed_rpm"] == pytest.approx(4000 / POLE_PAIRS)
    assert snap["torque_em_nm"] == pytest.approx(2.0 * KT) and math.isnan(snap["dc_bus_v"])
    t_alive = b.time_s
    assert t_alive > 0
    clock.t += 0.12
    b.service()                                        # keepalive: SET_CURRENT again before the VESC's timeout
    assert r.currents() == [pytest.approx(-1.0 / KT, abs=1e-3)]
    clock.t += 0.2                                     # 0.32 s without STATUS > heartbeat_timeout_s 0.3
    b.service()
    assert b.lost and b.faults & FAULT_DRIVE_LOST and b.time_frozen
    assert r.currents() == [0.0], "zero current commanded when the VESC goes silent"
    events = b.pop_events()
    assert events[-1][0] == "error" and "no Status for" in events[-1][1] and "FAULT_DRIVE_LOST" in events[-1][1]
    for _ in range(5):
        clock.t += 0.1
        b.apply(Cmd(-1.0))
        b.service()
    assert b.time_s == t_alive and r.currents() == [], "nothing fed while lost, sim time stands"
    r.status(erpm=3000)
    b.service()
    assert not b.lost and b.faults == 0 and b.drive_enabled
    b.apply(Cmd(-0.5))
    assert r.currents()[-1] == pytest.approx(-0.5 / KT, abs=1e-3) and b.time_s > t_alive
    stats = b.stats()
    assert stats["drive_lost"] == 1 and stats["drive_back"] == 1 and stats["heartbeats"] == 2
    assert stats["enable_attempts"] == 0 and stats["taken_over"] == 0
    level, reasons, values = b.diagnostic()
    assert level == 0 and reasons == [] and values["can_axis_state"] == "none"


def test_no_status_of_our_vesc_id_names_the_ids_that_are_on_the_bus(vesc_rig):
    clock = Clock()
    r = vesc_rig(clock)
    other = VescCanCodec(9)
    for _ in range(3):
        r.drive_bus.send(other.encode("Status", {"Erpm": 100, "Current": 0.0, "Duty_Cycle": 0.0}))
    r.backend.service()
    clock.t += 2.5
    r.backend.service()
    assert not r.backend.seen and r.backend.stats()["other_node"] == 3
    warnings = [text for level, text in r.backend.pop_events() if level == "warning"]
    assert warnings and "Status frames on the bus from node 9, none from node 0" in warnings[-1]
    assert "controller ID" in warnings[-1]


def test_backend_garbage_on_the_bus_is_counted(vesc_rig):
    r = vesc_rig()
    b = r.backend
    r.status()
    r.drive_bus.send(can.Message(arbitration_id=0x900, data=bytes(3), is_extended_id=True))      # short STATUS
    r.drive_bus.send(can.Message(arbitration_id=0x7FF, data=bytes(8), is_extended_id=False))     # 11-bit id
    r.drive_bus.send(VescCanCodec(0).encode("Set_Current", {"Current": 1.0}))                    # another host
    b.service()
    stats = b.stats()
    assert stats["dropped_bad_dlc"] == 1 and stats["dropped_standard_id"] == 1 and stats["decoded"] == 1
    assert b.counters["foreign_commands"] == 1, "another host commanding our VESC is noticed"


def test_config_checks_and_emulator_arguments(tmp_path):
    cfg = load_config(VESC_CONFIG)
    p = can_params_from_config(cfg)
    assert p.protocol == "vesc_can" and p.request == []
    args = emulator_args_from_config(cfg)
    assert args[args.index("--protocol") + 1] == "vesc_can"
    assert args[args.index("--heartbeat-ms") + 1] == "10"
    assert "--protocol" not in emulator_args_from_config(load_config(CAN_CONFIG)), "ODrive args unchanged"
    for changes, key in (({"request": ["bus"]}, "request"), ({"current_limit_a": 10.0, "velocity_limit_rev_s": 50.0},
                                                              "current_limit_a"), ({"node_id": 255}, "node_id")):
        bad = load_config(VESC_CONFIG)
        bad["can"].update(changes)
        with pytest.raises(ConfigError, match=key):
            can_params_from_config(bad)
    ok = load_config(VESC_CONFIG)
    ok["can"]["node_id"] = 200                         # a VESC ID above ODrive's 63
    assert can_params_from_config(ok).node_id == 200
    odrive = load_config(CAN_CONFIG)
    odrive["can"]["node_id"] = 200
    with pytest.raises(ConfigError, match="node_id"):
        can_params_from_config(odrive)


def test_the_vesc_config_is_the_can_config_but_for_its_can_section():
    import yaml
    vesc = yaml.safe_load(VESC_CONFIG.read_text())["/**"]["ros__parameters"]
    odrive = yaml.safe_load(CAN_CONFIG.read_text())["/**"]["ros__parameters"]
    assert {k: v for k, v in vesc.items() if k != "can"} == {k: v for k, v in odrive.items() if k != "can"}
    assert vesc["can"]["port"] != odrive["can"]["port"], "one udp_multicast port per bike: both can run on one host"


def test_a_machine_without_a_bldc_kt_needs_the_torque_constant():
    cfg = load_config(ROOT / "config" / "spmsm_can.yaml")
    cfg["can"].update(protocol="vesc_can", request=[], current_limit_a=0.0, velocity_limit_rev_s=0.0,
                      interface="virtual", channel=uuid.uuid4().hex)
    with pytest.raises(ConfigError, match="torque_constant_nm_per_a"):
        CanBackend(cfg)
    cfg["can"]["torque_constant_nm_per_a"] = 0.001       # 1000 A (SET_CURRENT's range) = 1 N m < Tmax
    with pytest.raises(ConfigError, match="exceeds what vesc_can can command"):
        CanBackend(cfg)
    cfg["can"]["torque_constant_nm_per_a"] = 0.1
    b = CanBackend(cfg)
    try:
        assert b.drive.torque_constant_nm_per_a == 0.1 and b.drive.pole_pairs == 6
    finally:
        b.close()


# ----------------------------------------------------------------------------- emulator
def test_backend_against_the_vesc_emulator_in_process(vesc_rig):
    r = vesc_rig()
    params = DriveModelParams.from_config(r.cfg)
    fw = VescFirmware(AverageTorqueDrive(params), pole_pairs=POLE_PAIRS)
    emu = VescEmulator(r.drive_bus, fw, 0, cyclic_s={name: 0.01 for name in VescEmulator.default_cyclic_s})
    stop = threading.Event()
    thread = threading.Thread(target=emu.run, args=(stop,), daemon=True)
    thread.start()
    b = r.backend
    seen = {}
    try:
        for torque in (-1.0, 0.6):
            end = time.monotonic() + 1.0
            while time.monotonic() < end:
                msg = Cmd(torque)
                b.submit(msg)
                b.service()
                b.apply(msg)
                time.sleep(0.005)
            seen[torque] = b.snapshot()
    finally:
        stop.set()
        thread.join(5.0)
    brake, motor = seen[-1.0], seen[0.6]
    # STATUS current has 0.1 A resolution: kt x 0.05 A = 2.6 mN m
    assert brake["torque_em_nm"] == pytest.approx(-1.0, abs=0.02)
    assert motor["torque_em_nm"] == pytest.approx(0.6, abs=0.02)
    assert brake["battery_current_a"] > 0 > motor["battery_current_a"], "regenerating while braking"
    assert brake["speed_rpm"] > 500 and 40 < brake["dc_bus_v"] < 60
    assert b.stats()["dropped"] == 0 and emu.counters.get("rx:Set_Current", 0) >= 100
    assert fw.charge_regenerated_ah > 0 and fw.charge_drawn_ah > 0


def test_the_emulated_vesc_releases_the_motor_after_its_command_timeout():
    params = DriveModelParams.from_config(load_config(VESC_CONFIG))
    fw = VescFirmware(AverageTorqueDrive(params), pole_pairs=POLE_PAIRS, watchdog_timeout_s=0.5)
    fw.set_current(-10.0, now_s=0.0)
    assert fw.armed and fw.input_torque_nm == pytest.approx(-10.0 * params.torque_constant_nm_per_a)
    assert not fw.check_watchdog(0.4)
    assert fw.check_watchdog(0.6) and not fw.armed and fw.active_errors == 0, "released, no error latched"
    fw.set_current(5.0, now_s=0.7)
    assert fw.armed, "the next command runs the motor again (no arming)"


# ----------------------------------------------------------------------------- the emulator as a process
def _vesc_host(bus, node_id):
    return VescCan(bus, node_id, pole_pairs=POLE_PAIRS, torque_constant_nm_per_a=KT)


@pytest.mark.slow
def test_vesc_emulator_process_over_udp_multicast(tmp_path):
    """bike-drive-emulator --protocol vesc_can as its own process: STATUS broadcasts at the rate,
    SET_CURRENT followed, garbage counted by the host, the command timeout releases the motor."""
    emu = Emulator(tmp_path, "--protocol", "vesc_can", "--physics", "average", "--heartbeat-ms", "10",
                   "--garbage-rate", "20", "--node-id", "42", config=VESC_CONFIG, host_factory=_vesc_host,
                   node_id=42)
    host = emu.host
    try:
        statuses = []
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            statuses += [m.received_s for m in host.poll(0.05) if m.kind == "status"]
        assert len(statuses) >= 50, f"STATUS every 10 ms expected, got {len(statuses)} in 1 s"
        assert 20.0 < host.values()["speed_rev_s"] < 60.0      # the emulated rider pedals
        assert 40.0 < host.values()["bus_voltage_v"] < 60.0
        host.set_torque(-1.0)
        assert emu.wait_for(lambda h: h.values().get("torque_estimate_nm", 0.0) < -0.9, 5.0, feed=True)
        # stop sending: the VESC's 0.5 s timeout releases the motor, its STATUS keeps coming
        host.forget_setpoint()
        assert emu.wait_for(lambda h: abs(h.values()["torque_estimate_nm"]) < 0.01, 3.0)
        assert host.link_alive()
        assert host.dropped > 0 and host.counters["other_node"] > 0, "the garbage was counted, not raised"
    finally:
        rc, summary = emu.stop(signal.SIGTERM)
    assert rc == 0
    assert summary["rx:Set_Current"] >= 1 and summary["tx:Status"] >= 50 and summary["tx:garbage"] > 0


# ----------------------------------------------------------------------------- the whole bike on a VESC
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_workout_on_a_vesc_through_the_can_path_end_to_end(tmp_path, ros_domain):
    """`./bike run --config config/bldc_vesc.yaml` starts the emulator in VESC mode, rides,
    records and reports: braking torque as asked, SET_CURRENT / STATUS frames in the CAN log."""
    port = _port()
    profile = {"name": "vesc_smoke", "segments": [
        {"kind": "step", "duration_s": 4.0, "command": 0.5, "mode": "resistance", "label": "resistance"}]}
    config = write_config(tmp_path, port, emulator=True, profile=profile, base=VESC_CONFIG)
    result, out, bag = recorded_run(tmp_path, config, 4, timeout=150)
    assert "protocol=vesc_can" in out and "drive alive (Status arriving" in out
    states = read_topic(bag, "plant_state")
    status = read_topic(bag, "controller_status")
    assert states[-1].end_of_run and all(m.measured_by_drive and m.backend == "can" for m in states)
    t = lambda m: stamp_ns(m.header.stamp) * 1e-9  # noqa: E731
    res = [m for m in states if 1.0 < t(m) < 3.9 and not m.faults]
    res_cmd = [s for s in status if 1.0 < t(s) < 3.9]
    asked = sum(s.torque_cmd_nm for s in res_cmd) / len(res_cmd)
    got = -sum(m.torque_em_nm for m in res) / len(res)
    assert 0.5 < asked < 1.6 and got == pytest.approx(asked, rel=0.05), (asked, got)
    assert states[-1].dc_bus_v > 40 and states[-1].energy_battery_j > 0, "regenerated into the battery"
    can_stats = summarise(bag)["can"]
    assert can_stats["protocol"] == "vesc_can" and can_stats["dropped"] == "0"
    assert int(can_stats["setpoints"]) > 300 and int(can_stats["heartbeats"]) > 200
    logged = list(can.LogReader(can_stats["log_file"]))
    ids = {m.arbitration_id for m in logged if m.is_extended_id}
    assert {0x100, 0x900, 0x1000, 0x1B00} <= ids, "SET_CURRENT and STATUS / _4 / _5 of VESC ID 0 in the log"
    assert "(vesc_can)" in result.stdout and "status frames" in result.stdout, "the report's CAN section"


@pytest.mark.slow
def test_the_backend_loses_a_vesc_process_that_falls_silent(tmp_path):
    """The plant's backend against the emulated VESC as a process (udp_multicast): alive on its
    STATUS frames, FAULT_DRIVE_LOST with sim time stopped once they stop (--silent-after-s)."""
    emu = Emulator(tmp_path, "--protocol", "vesc_can", "--physics", "average", "--heartbeat-ms", "10",
                   "--silent-after-s", "3", config=VESC_CONFIG, host_factory=_vesc_host)
    cfg = load_config(VESC_CONFIG)
    cfg["can"].update(interface="udp_multicast", channel=GROUP, port=emu.port, emulator=False)
    b = CanBackend(cfg)
    try:
        end = time.monotonic() + 2.5
        while not b.drive_enabled and time.monotonic() < end:
            b.service()
            time.sleep(0.005)
        assert b.drive_enabled, b.diagnostic()
        end = time.monotonic() + 6.0
        while not b.lost and time.monotonic() < end:
            msg = Cmd(-0.5)
            b.submit(msg)
            b.service()
            b.apply(msg)
            time.sleep(0.005)
        assert b.lost and b.faults & FAULT_DRIVE_LOST and b.time_frozen
        t_lost = b.time_s
        b.apply(Cmd(-0.5))
        assert t_lost > 0 and b.time_s == t_lost, "sim time ran while alive and stands while lost"
        assert b.stats()["setpoints"] > 50 and b.stats()["dropped"] == 0
        assert any("no Status for" in text for _, text in b.pop_events())
    finally:
        b.close()
        rc, summary = emu.stop()
    assert rc == 0 and summary["tx_suppressed"] > 0 and summary["rx:Set_Current"] > 50
