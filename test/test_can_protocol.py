"""ODrive CANSimple 0.6.x codec and host side (bike_plant.can.protocol), in-process.

Reference layouts are struct.pack formats written from the 0.6.x message table
(/work/shared/research/can-and-bags.md, section 1), independent of the DBC file.
"""
from __future__ import annotations

import math
import struct
import subprocess
import sys

import can
import cantools
import pytest

from bike_plant.can import (DBC_PATH, DRIVE_TO_HOST, HOST_TO_DRIVE, MALFORMED_REASONS, AxisState, ODriveError,
                            OdriveCanSimple, OdriveCanSimpleCodec, error_names, export_dbc, load_database)

# name -> (cmd_id, struct format of the payload, values, DBC signal names); the values are
# exactly representable in float32 so round trips compare with ==
REFERENCE = {
    "Heartbeat": (0x01, "<IBBBx", (0x01000000, 8, 3, 1),
                  ("Axis_Error", "Axis_State", "Procedure_Result", "Trajectory_Done_Flag")),
    "Get_Error": (0x03, "<II", (0x01000100, 0x01000000), ("Active_Errors", "Disarm_Reason")),
    "Set_Axis_State": (0x07, "<Ixxxx", (8,), ("Axis_Requested_State",)),
    "Get_Encoder_Estimates": (0x09, "<ff", (-12.25, 46.5), ("Pos_Estimate", "Vel_Estimate")),
    "Set_Controller_Mode": (0x0B, "<II", (1, 1), ("Control_Mode", "Input_Mode")),
    "Set_Input_Vel": (0x0D, "<ff", (12.5, -0.75), ("Input_Vel", "Input_Torque_FF")),
    "Set_Input_Torque": (0x0E, "<fxxxx", (-1.625,), ("Input_Torque",)),
    "Set_Limits": (0x0F, "<ff", (90.0, 60.5), ("Velocity_Limit", "Current_Limit")),
    "Get_Iq": (0x14, "<ff", (19.25, -18.75), ("Iq_Setpoint", "Iq_Measured")),
    "Get_Bus_Voltage_Current": (0x17, "<ff", (50.875, -6.5), ("Bus_Voltage", "Bus_Current")),
    "Clear_Errors": (0x18, "<B", (1,), ("Identify",)),
    "Get_Torques": (0x1C, "<ff", (1.0, 0.96875), ("Torque_Target", "Torque_Estimate")),
    "Get_Powers": (0x1D, "<ff", (310.5, -304.25), ("Electrical_Power", "Mechanical_Power")),
}


def frame(arb_id, data=b"", **kw):
    kw.setdefault("is_extended_id", False)
    return can.Message(arbitration_id=arb_id, data=data, **kw)


@pytest.fixture
def vbus():
    """Two ends of one in-process virtual bus (a unique channel per test)."""
    import uuid
    channel = f"test_can_protocol_{uuid.uuid4().hex}"
    host = can.Bus(interface="virtual", channel=channel)
    drive = can.Bus(interface="virtual", channel=channel)
    yield host, drive
    host.shutdown()
    drive.shutdown()


def test_dbc_loads_and_decodes_set_input_vel_like_struct():
    db = cantools.database.load_file(str(DBC_PATH))
    assert {m.name for m in db.messages} == set(REFERENCE)
    data = struct.pack("<ff", 12.5, -0.75)
    assert db.decode_message(0x0D, data) == {"Input_Vel": 12.5, "Input_Torque_FF": -0.75}
    assert db.encode_message("Set_Input_Vel", {"Input_Vel": 12.5, "Input_Torque_FF": -0.75}) == data
    for name, (cmd, fmt, _values, signals) in REFERENCE.items():
        message = db.get_message_by_name(name)
        assert message.frame_id == cmd, name                        # node 0 ids = command ids
        assert message.length == struct.calcsize(fmt), name
        assert [s.name for s in message.signals] == list(signals), name
        assert all(s.byte_order == "little_endian" for s in message.signals), name


@pytest.mark.parametrize("name", sorted(REFERENCE))
@pytest.mark.parametrize("node_id", [0, 3, 0x3F])
def test_round_trip_against_struct_layout(name, node_id):
    cmd, fmt, values, signals = REFERENCE[name]
    codec = OdriveCanSimpleCodec(node_id)
    reference = struct.pack(fmt, *values)
    msg = codec.encode(name, dict(zip(signals, values)))
    assert msg.arbitration_id == (node_id << 5) | cmd
    assert not msg.is_extended_id and not msg.is_remote_frame
    assert bytes(msg.data) == reference
    side = DRIVE_TO_HOST if name in DRIVE_TO_HOST else HOST_TO_DRIVE
    decoded = codec.classify(frame((node_id << 5) | cmd, reference), side, answers_requests=side is HOST_TO_DRIVE)
    assert not isinstance(decoded, str), decoded
    assert decoded.name == name and not decoded.is_request
    assert dict(decoded.signals) == dict(zip(signals, values))


def test_node_id_shift_examples():
    assert OdriveCanSimpleCodec(3).arbitration_id("Set_Input_Vel") == 0x06D     # the ODrive docs' example
    assert OdriveCanSimpleCodec(0x3F).arbitration_id("Heartbeat") == 0x7E1
    with pytest.raises(ValueError):
        OdriveCanSimpleCodec(64)


def test_the_odrive_broadcast_node_id_is_refused_for_a_host(vbus):
    """ODrive 0.6.x: node id 0x3F is the broadcast address and the id of unaddressed drives
    (odriverobotics/ODriveResources examples/can_enumerate.py), so a host commanding it would
    drive every such ODrive on the bus. The bus-free codec still reads that id's frames."""
    host, _ = vbus
    assert OdriveCanSimple.node_id_max == 0x3E
    OdriveCanSimple(host, node_id=0x3E)
    with pytest.raises(ValueError, match=r"0\.\.62, got 63 \(63 = 0x3F is the ODrive broadcast id"):
        OdriveCanSimple(host, node_id=0x3F)
    hb = struct.pack("<IBBBx", 0, 1, 0, 1)
    assert OdriveCanSimpleCodec(0x3F).classify(frame(0x7E1, hb), DRIVE_TO_HOST, False).name == "Heartbeat"


def test_short_payloads_senders_use_are_accepted_by_the_drive_side():
    codec = OdriveCanSimpleCodec(0)
    d = codec.classify(frame(0x07, struct.pack("<I", 8)), HOST_TO_DRIVE, True)        # ODrive's python example
    assert d.name == "Set_Axis_State" and d.signals["Axis_Requested_State"] == 8
    d = codec.classify(frame(0x0E, struct.pack("<f", 0.5)), HOST_TO_DRIVE, True)
    assert d.signals["Input_Torque"] == 0.5
    d = codec.classify(frame(0x18, b""), HOST_TO_DRIVE, True)                           # 0.5.x style
    assert d.name == "Clear_Errors" and d.signals["Identify"] == 0
    assert codec.classify(frame(0x0D, struct.pack("<f", 1.0)), HOST_TO_DRIVE, True) == "bad_dlc"


def test_rtr_requests():
    codec = OdriveCanSimpleCodec(2)
    req = codec.encode_request("Get_Iq")
    assert req.is_remote_frame and req.arbitration_id == (2 << 5) | 0x14 and req.dlc == 8
    d = codec.classify(req, HOST_TO_DRIVE, answers_requests=True)
    assert d.is_request and d.name == "Get_Iq"
    assert codec.classify(req, DRIVE_TO_HOST, answers_requests=False) == "other_direction"
    with pytest.raises(ValueError):
        codec.encode_request("Set_Input_Torque")


# frames a host must drop, with the counter each one must land in
HOST_BAD_FRAMES = [
    ("error_frame", can.Message(is_error_frame=True, arbitration_id=0x4, data=bytes(8))),
    ("fd_frame", frame(0x09, struct.pack("<ff", 1, 2), is_fd=True)),
    ("extended_id", can.Message(arbitration_id=0x09, data=struct.pack("<ff", 1, 2), is_extended_id=True)),
    ("unknown_id", can.Message(arbitration_id=0x909, data=bytes(8), is_extended_id=False, check=False)),
    ("other_node", frame(0x29, struct.pack("<ff", 1, 2))),
    ("unknown_cmd", frame(0x1E, bytes(8))),
    ("bad_dlc", frame(0x09, struct.pack("<f", 1))),
    ("bad_dlc", frame(0x01, bytes(7))),
    ("bad_dlc", can.Message(arbitration_id=0x09, data=bytes(12), is_extended_id=False, check=False)),
    ("non_finite", frame(0x09, struct.pack("<ff", math.nan, 2))),
    ("non_finite", frame(0x14, struct.pack("<ff", 1, math.inf))),
    ("non_finite", frame(0x1C, struct.pack("<ff", -math.inf, 0))),
    ("out_of_range", frame(0x09, struct.pack("<ff", 0, 1.0e6))),
    ("out_of_range", frame(0x01, struct.pack("<IBBBx", 0, 200, 0, 0))),
    ("out_of_range", frame(0x17, struct.pack("<ff", -5.0, 0))),
    ("other_direction", frame(0x0E, struct.pack("<fxxxx", 1.0))),         # a host command (or our echo)
    ("other_direction", frame(0x09, is_remote_frame=True, dlc=8)),          # another host's request
    ("unexpected_rtr", frame(0x0E, is_remote_frame=True, dlc=8)),
]


@pytest.mark.parametrize("reason,msg", HOST_BAD_FRAMES, ids=[r for r, _ in HOST_BAD_FRAMES])
def test_host_drops_and_counts_each_bad_frame(vbus, reason, msg):
    host = OdriveCanSimple(vbus[0], 0, filter_echo=False)
    assert host.receive(msg) == []
    assert host.counters[reason] == 1, dict(host.counters)
    assert host.counters["decoded"] == 0 and host.last == {}


def test_valid_odrive_messages_the_plant_does_not_use_are_not_malformed(vbus):
    """A 0.6.x drive with temperature_msg_rate_ms set sends Get_Temperature (0x15, two floats:
    ros_odrive can_simple_messages.hpp); Get_Version, Address, Set_Input_Pos, Reboot ... are valid
    CANSimple too. They are counted as unused_message (ignored), not as malformed frames."""
    host = OdriveCanSimple(vbus[0], 3, filter_echo=False)
    assert host.receive(frame(3 << 5 | 0x15, struct.pack("<ff", 41.5, 35.0))) == []
    assert host.receive(frame(3 << 5 | 0x00, bytes([2, 4, 4, 58, 0, 6, 10, 0]))) == []       # Get_Version
    assert host.receive(frame(3 << 5 | 0x15, is_remote_frame=True, dlc=8)) == []            # another host asks
    assert host.counters["unused_message"] == 3 and host.dropped == 0, dict(host.counters)
    assert host.receive(frame(3 << 5 | 0x1E, bytes(8))) == [] and host.counters["unknown_cmd"] == 1
    drive = OdriveCanSimpleCodec(3)
    assert drive.classify(frame(3 << 5 | 0x0C, bytes(8)), HOST_TO_DRIVE, True) == "unused_message"  # Set_Input_Pos


def test_drive_side_classification_of_bad_frames():
    codec = OdriveCanSimpleCodec(0)
    assert codec.classify(frame(0x0E, is_remote_frame=True, dlc=8), HOST_TO_DRIVE, True) == "unexpected_rtr"
    assert codec.classify(frame(0x01, bytes(8)), HOST_TO_DRIVE, True) == "other_direction"
    assert codec.classify(frame(0x0E, struct.pack("<ff", math.nan, 0)), HOST_TO_DRIVE, True) == "non_finite"
    assert codec.classify(frame(0x0E, struct.pack("<ff", 5000.0, 0)), HOST_TO_DRIVE, True) == "out_of_range"
    assert codec.classify(frame(0x0B, struct.pack("<II", 9, 1)), HOST_TO_DRIVE, True) == "out_of_range"
    assert codec.classify(frame(0x0F, struct.pack("<ff", -1.0, 10.0)), HOST_TO_DRIVE, True) == "out_of_range"


def test_receive_never_raises_even_for_garbage_objects(vbus):
    host = OdriveCanSimple(vbus[0], 0)
    for junk in (None, object(), "frame", can.Message(arbitration_id=-1, check=False)):
        assert host.receive(junk) == []
    assert host.dropped == 4


class _RaisingBus(can.BusABC):
    """A bus whose receive fails, like udp_multicast given an undecodable datagram."""

    def __init__(self):
        super().__init__(channel="raising")

    def _recv_internal(self, timeout):
        raise can.CanOperationError("could not unpack received message")

    def send(self, msg, timeout=None):
        raise can.CanOperationError("bus down")


def test_bus_errors_are_counted_not_raised():
    host = OdriveCanSimple(_RaisingBus(), 0)
    assert host.poll(0.01) == []
    assert host.counters["bus_error"] == 1
    assert host.set_input_torque(1.0) is False and host.counters["tx_failed"] == 1


def test_poll_decodes_good_frames_between_bad_ones(vbus):
    host_bus, drive_bus = vbus
    host = OdriveCanSimple(host_bus, 0)
    for _reason, bad in HOST_BAD_FRAMES:
        drive_bus.send(bad)
    drive_bus.send(frame(0x01, struct.pack("<IBBBx", 0, 8, 1, 1)))
    drive_bus.send(frame(0x09, struct.pack("<ff", 10.0, 46.5)))
    got = []
    for _ in range(20):
        got += host.poll(0.2)
        if len(got) >= 2:
            break
    assert [m.kind for m in got] == ["status", "motion"]
    assert host.enabled and host.link_alive() and host.active_errors == 0
    values = host.values()
    assert values["speed_rev_s"] == 46.5 and values["axis_state"] == AxisState.CLOSED_LOOP_CONTROL
    for reason, _msg in HOST_BAD_FRAMES:
        assert host.counters[reason] == sum(r == reason for r, _ in HOST_BAD_FRAMES), reason
    assert host.counters["rx_frames"] == len(HOST_BAD_FRAMES) + 2


def test_commands_on_the_bus_match_struct_layouts(vbus):
    host_bus, drive_bus = vbus
    host = OdriveCanSimple(host_bus, 5)
    host.clear_errors()
    host.enable("torque")
    host.set_input_torque(-1.625)
    host.set_input_vel(12.5, -0.75)
    host.set_limits(90.0, 60.5)
    host.request("motion")
    host.disable()
    seen = [drive_bus.recv(1.0) for _ in range(8)]
    node = 5 << 5
    assert [(m.arbitration_id, bytes(m.data), m.is_remote_frame) for m in seen] == [
        (node | 0x18, struct.pack("<B", 0), False),
        (node | 0x0B, struct.pack("<II", 1, 1), False),
        (node | 0x07, struct.pack("<Ixxxx", 8), False),
        (node | 0x0E, struct.pack("<fxxxx", -1.625), False),
        (node | 0x0D, struct.pack("<ff", 12.5, -0.75), False),
        (node | 0x0F, struct.pack("<ff", 90.0, 60.5), False),
        (node | 0x09, b"", True),
        (node | 0x07, struct.pack("<Ixxxx", 1), False),
    ]
    with pytest.raises(ValueError):
        host.set_input_torque(math.nan)      # a caller bug is loud; the receive path never is


def test_own_frames_echoed_back_are_recognised():
    import uuid
    bus = can.Bus(interface="virtual", channel=uuid.uuid4().hex, receive_own_messages=True)
    try:
        host = OdriveCanSimple(bus, 0)
        host.set_input_torque(0.5)
        host.request("torque")
        assert host.poll(0.2) == []
        assert host.counters["echo"] == 2 and host.dropped == 0
    finally:
        bus.shutdown()


def test_keepalive_and_link_supervision_with_a_fake_clock(vbus):
    host_bus, drive_bus = vbus
    now = [100.0]
    host = OdriveCanSimple(host_bus, 0, heartbeat_timeout_s=0.3, watchdog_feed_interval_s=0.1, clock=lambda: now[0])
    assert not host.link_alive() and host.heartbeat_age_s() == math.inf
    assert host.keepalive() is False                    # nothing to repeat yet
    host.set_input_torque(0.75)
    now[0] += 0.05
    assert host.keepalive() is False                    # fed recently
    now[0] += 0.06
    assert host.keepalive() is True
    frames = [drive_bus.recv(1.0) for _ in range(2)]
    assert [bytes(f.data) for f in frames] == [struct.pack("<fxxxx", 0.75)] * 2
    host.receive(frame(0x01, struct.pack("<IBBBx", 0, 8, 1, 1)))
    assert host.link_alive()
    now[0] += 0.31
    assert not host.link_alive()
    host.disable()                                      # IDLE: keepalive must not re-send torque
    now[0] += 1.0
    assert host.keepalive() is False


def test_export_dbc_for_a_node_and_cantools_cli_with_id_mask(tmp_path):
    out = export_dbc(3, tmp_path / "node3.dbc")
    db = cantools.database.load_file(str(out))
    assert db.decode_message(0x06D, struct.pack("<ff", 12.5, -0.75)) == {"Input_Vel": 12.5, "Input_Torque_FF": -0.75}
    assert load_database(3).get_message_by_name("Heartbeat").frame_id == 0x061
    # a candump line of node 3, decoded with the shipped node-0 DBC and an id mask
    line = "  can0  06D   [8]  00 00 48 41 00 00 40 BF\n"
    res = subprocess.run([sys.executable, "-m", "cantools", "decode", "--single-line", "--frame-id-mask", "0x1F",
                          str(DBC_PATH)], input=line, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert "Set_Input_Vel" in res.stdout and "Input_Vel: 12.5" in res.stdout and "Input_Torque_FF: -0.75" in res.stdout


def test_error_names():
    assert error_names(0x01000000) == ["WATCHDOG_TIMER_EXPIRED"]
    assert error_names(ODriveError.DC_BUS_OVER_VOLTAGE | 0x80000000) == ["DC_BUS_OVER_VOLTAGE", "0x80000000"]
    assert set(MALFORMED_REASONS).isdisjoint({"other_node", "other_direction", "echo"})
