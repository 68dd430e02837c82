"""FTMS over DIRCON without ROS: the Control Point's meaning for this bike's Commands, the
bytes of the characteristics, DIRCON framing and dispatch, the TCP server on real sockets
(a broken stream closes only its own connection), and the telemetry an app is shown."""
import contextlib
import dataclasses
import math
import os
import socket
import struct
import time

import pytest

from bike_session import dircon, ftms
from bike_session.ftms_node import Telemetry, services_for
from bike_session.profiles import MODES, ModeUnits

UNITS = ModeUnits(erg_power_max_w=1000.0, grade_min=-0.10, grade_max=0.20, cadence_min_rpm=20.0,
                  cadence_max_rpm=120.0)


def cp(op: int, fmt: str = "", *values) -> bytes:
    return bytes([op]) + (struct.pack("<" + fmt, *values) if fmt else b"")


def controlled() -> ftms.FtmsControl:
    control = ftms.FtmsControl(UNITS)
    assert control.write(cp(ftms.OP_REQUEST_CONTROL)).response == bytes([0x80, 0x00, ftms.RESULT_SUCCESS])
    return control


def test_nothing_but_request_control_is_taken_before_it():
    control = ftms.FtmsControl(UNITS)
    reply = control.write(cp(ftms.OP_TARGET_POWER, "h", 150))
    assert reply.response == bytes([0x80, ftms.OP_TARGET_POWER, ftms.RESULT_NOT_PERMITTED])
    assert reply.target is None and reply.warning and "Request Control" in reply.message


def test_target_power_is_erg_at_its_share_of_the_bikes_maximum_and_beyond_it_is_refused():
    control = controlled()
    reply = control.write(cp(ftms.OP_TARGET_POWER, "h", 150))
    assert reply.response == bytes([0x80, 0x05, 0x01])
    assert reply.target.mode == MODES["erg"] and reply.target.command == pytest.approx(0.15)
    assert reply.status == bytes([ftms.STATUS_POWER_CHANGED]) + struct.pack("<h", 150)
    for watts in (1001, -5):
        bad = control.write(cp(ftms.OP_TARGET_POWER, "h", watts))
        assert bad.response[2] == ftms.RESULT_INVALID_PARAMETER and bad.target is None
        assert f"{watts} W refused" in bad.message and "[0, 1000]" in bad.message
    short = control.write(bytes([ftms.OP_TARGET_POWER, 0x96]))
    assert short.response[2] == ftms.RESULT_INVALID_PARAMETER and "1 parameter bytes, expected 2" in short.message


def test_inclination_and_resistance_map_onto_the_mode_ranges():
    control = controlled()
    incline = control.write(cp(ftms.OP_TARGET_INCLINATION, "h", 50))          # 5.0 %
    assert incline.target.mode == MODES["slope"]
    assert incline.target.command == pytest.approx((0.05 + 0.10) / 0.30)
    assert control.write(cp(ftms.OP_TARGET_INCLINATION, "h", 250)).response[2] == ftms.RESULT_INVALID_PARAMETER
    one_byte = control.write(bytes([ftms.OP_TARGET_RESISTANCE, 200]))         # uint8: 20.0
    two_bytes = control.write(cp(ftms.OP_TARGET_RESISTANCE, "h", 455))       # sint16: 45.5
    assert one_byte.target.mode == two_bytes.target.mode == MODES["resistance"]
    assert one_byte.target.command == pytest.approx(0.200) and two_bytes.target.command == pytest.approx(0.455)
    assert control.write(cp(ftms.OP_TARGET_RESISTANCE, "h", 1001)).response[2] == ftms.RESULT_INVALID_PARAMETER


def test_a_simulation_grade_beyond_the_bike_is_ridden_at_its_end_and_said_and_the_road_is_the_apps():
    control = controlled()
    first = control.write(cp(ftms.OP_SIMULATION, "hhBB", -2500, 300, 40, 51))     # 3 %, Crr 0.004, Cw 0.51
    assert first.response[2] == ftms.RESULT_SUCCESS and not first.warning
    assert first.target.command == pytest.approx((0.03 + 0.10) / 0.30)
    assert first.target.road == pytest.approx((0.004, 0.51, -2.5))              # a 2.5 m/s tail wind
    assert "Crr 0.004" in first.message and "wind -2.5 m/s" in first.message
    steep = control.write(cp(ftms.OP_SIMULATION, "hhBB", -2500, 2500, 40, 51))    # 25 %: beyond 20 %
    assert steep.response[2] == ftms.RESULT_SUCCESS and steep.warning
    assert steep.target.command == pytest.approx(1.0)
    assert "25 % is beyond" in steep.message and "ridden at 20 %" in steep.message
    assert "Crr" not in steep.message and steep.target.road == first.target.road   # the same road: said once
    assert steep.status == bytes([ftms.STATUS_SIMULATION_CHANGED]) + struct.pack("<hhBB", -2500, 2500, 40, 51)
    # an app that sends only the grade: the config's road, said
    bare = control.write(cp(ftms.OP_SIMULATION, "hhBB", 0, 100, 0, 0))
    assert bare.target.road is None and "config's road" in bare.message
    # a stop keeps the target and its road for the resume
    control.write(cp(ftms.OP_SIMULATION, "hhBB", 1000, 100, 33, 40))
    control.write(bytes([ftms.OP_STOP_PAUSE, 2]))
    assert control.write(bytes([ftms.OP_START_RESUME])).target.road == pytest.approx((0.0033, 0.40, 1.0))


def test_a_targeted_cadence_rides_with_the_target_in_force_and_every_later_one():
    control = controlled()
    early = control.write(cp(ftms.OP_TARGETED_CADENCE, "H", 190))                 # 95 rpm before any target
    assert early.response[2] == ftms.RESULT_SUCCESS and early.target is None
    assert early.status == bytes([ftms.STATUS_CADENCE_CHANGED]) + struct.pack("<H", 190)
    assert "first target" in early.message
    first = control.write(cp(ftms.OP_TARGET_POWER, "h", 200))
    assert first.target.cadence_rpm == 95.0 and first.target.mode == MODES["erg"]
    drill = control.write(cp(ftms.OP_TARGETED_CADENCE, "H", 130))                 # 65 rpm: the 200 W again
    assert drill.target.cadence_rpm == 65.0 and drill.target.command == first.target.command
    assert control.write(cp(ftms.OP_TARGETED_CADENCE, "H", 10)).response[2] == ftms.RESULT_INVALID_PARAMETER
    assert control.write(cp(ftms.OP_TARGETED_CADENCE, "H", 0)).target.cadence_rpm == 0.0      # the rider's own
    control.write(cp(ftms.OP_TARGETED_CADENCE, "H", 180))
    control.write(bytes([ftms.OP_RESET]))
    control.write(bytes([ftms.OP_REQUEST_CONTROL]))
    assert control.write(cp(ftms.OP_TARGET_POWER, "h", 150)).target.cadence_rpm == 0.0  # a reset clears it
    assert struct.unpack("<II", ftms.encode_feature())[1] & ftms.TARGET_CADENCE


def test_stop_releases_the_brake_keeps_the_target_for_resume_and_reset_gives_up_control():
    control = controlled()
    control.write(cp(ftms.OP_TARGET_POWER, "h", 200))
    stop = control.write(bytes([ftms.OP_STOP_PAUSE, 2]))
    assert stop.target.mode == MODES["resistance"] and stop.target.command == 0.0
    assert stop.status == bytes([ftms.STATUS_STOPPED_PAUSED, 2])
    while_stopped = control.write(cp(ftms.OP_TARGET_POWER, "h", 250))
    assert while_stopped.response[2] == ftms.RESULT_SUCCESS and while_stopped.target is None
    resume = control.write(bytes([ftms.OP_START_RESUME]))
    assert resume.target.mode == MODES["erg"] and resume.target.command == pytest.approx(0.25)
    assert control.write(bytes([ftms.OP_STOP_PAUSE, 3])).response[2] == ftms.RESULT_INVALID_PARAMETER
    reset = control.write(bytes([ftms.OP_RESET]))
    assert reset.target == ftms.Target(MODES["resistance"], 0.0, reset.target.text)
    assert control.write(cp(ftms.OP_TARGET_POWER, "h", 100)).response[2] == ftms.RESULT_NOT_PERMITTED


def test_ops_this_bike_does_not_do_are_not_supported_and_an_empty_write_is_invalid():
    control = controlled()
    for op in (ftms.OP_TARGET_SPEED, ftms.OP_TARGET_HEART_RATE, 0x12, 0x42):
        reply = control.write(bytes([op, 0, 0]))
        assert reply.response == bytes([0x80, op, ftms.RESULT_NOT_SUPPORTED]) and reply.target is None
        assert reply.message
    assert control.write(b"").response[2] == ftms.RESULT_INVALID_PARAMETER


def test_spin_down_control_starts_the_procedure_and_its_status_follows_the_controller():
    """0x13 start: the spindown Command (brake released), the response with the target speeds
    (uint16 0.01 km/h, low then high), the status "spin down requested"; then, as the
    controller's statuses give the procedure's phase, "stop pedalling" at the coast and
    "success" at the end, each once. 2 ignores; anything else is refused; before any request
    the controller's phases are not reported."""
    units = dataclasses.replace(UNITS, spindown_kmh=(20.5, 29.04))
    control = ftms.FtmsControl(units)
    assert control.spin_down_progress(MODES["spindown"], 2.0) == []
    control.write(cp(ftms.OP_REQUEST_CONTROL))
    reply = control.write(bytes([ftms.OP_SPIN_DOWN, 1]))
    assert reply.response == bytes([0x80, 0x13, ftms.RESULT_SUCCESS]) + struct.pack("<HH", 2050, 2904)
    assert reply.status == bytes([ftms.STATUS_SPIN_DOWN, ftms.SPIN_DOWN_REQUESTED])
    assert reply.target.mode == MODES["spindown"] and "29.0 km/h" in reply.message
    assert struct.unpack("<II", ftms.encode_feature())[1] & ftms.TARGET_SPIN_DOWN
    assert control.spin_down_progress(MODES["erg"], 2.0) == []              # the live Command not in force yet
    assert control.spin_down_progress(MODES["spindown"], 1.0) == []          # spinning up: said already
    assert control.spin_down_progress(MODES["spindown"], 2.0) == [bytes([0x14, ftms.SPIN_DOWN_STOP_PEDALLING])]
    assert control.spin_down_progress(MODES["spindown"], 2.0) == []
    assert control.spin_down_progress(MODES["spindown"], 3.0) == [bytes([0x14, ftms.SPIN_DOWN_SUCCESS])]
    assert control.spin_down_progress(MODES["spindown"], 3.0) == []          # done: said once
    control.write(bytes([ftms.OP_SPIN_DOWN, 1]))
    assert control.spin_down_progress(MODES["spindown"], 4.0) == [bytes([0x14, ftms.SPIN_DOWN_ERROR])]
    # a coast between two notifications: "stop pedalling" still comes before the success
    control.write(bytes([ftms.OP_SPIN_DOWN, 1]))
    assert control.spin_down_progress(MODES["spindown"], 3.0) == [bytes([0x14, ftms.SPIN_DOWN_STOP_PEDALLING]),
                                                                  bytes([0x14, ftms.SPIN_DOWN_SUCCESS])]
    ignore = control.write(bytes([ftms.OP_SPIN_DOWN, 2]))
    assert ignore.response == bytes([0x80, 0x13, ftms.RESULT_SUCCESS]) and ignore.target is None
    for bad in (bytes([ftms.OP_SPIN_DOWN, 3]), bytes([ftms.OP_SPIN_DOWN])):
        assert control.write(bad).response == bytes([0x80, 0x13, ftms.RESULT_INVALID_PARAMETER])


def test_a_target_heart_rate_is_erg_holding_it_from_the_power_in_force_on_a_bike_with_a_rider():
    """Op 0x06 (uint8 bpm): ERG with Command.heart_rate_bpm, starting from the ERG target in force
    (a plain power target after it is plain ERG again); refused outside 40..220 bpm and on a bike
    without a heart rate (result 2: not supported there)."""
    control = ftms.FtmsControl(UNITS, heart_rate=True)
    control.write(bytes([ftms.OP_REQUEST_CONTROL]))
    power = control.write(bytes([ftms.OP_TARGET_POWER]) + struct.pack("<h", 150))
    reply = control.write(bytes([ftms.OP_TARGET_HEART_RATE, 140]))
    assert reply.response == bytes([0x80, 0x06, ftms.RESULT_SUCCESS])
    assert reply.status == bytes([ftms.STATUS_HEART_RATE_CHANGED, 140])
    assert (reply.target.mode, reply.target.command, reply.target.heart_rate_bpm) == (MODES["erg"], 0.15, 140.0)
    assert power.target.heart_rate_bpm == 0.0
    assert control.write(bytes([ftms.OP_TARGET_POWER]) + struct.pack("<h", 200)).target.heart_rate_bpm == 0.0
    for bad in (0, 30, 230):
        refused = control.write(bytes([ftms.OP_TARGET_HEART_RATE, bad]))
        assert refused.response[2] == ftms.RESULT_INVALID_PARAMETER and refused.target is None, bad
        assert f"{bad} bpm refused" in refused.message
    assert control.write(bytes([ftms.OP_TARGET_HEART_RATE])).response[2] == ftms.RESULT_INVALID_PARAMETER
    none = ftms.FtmsControl(UNITS)                      # a prime mover or a dynamometer: no heart
    none.write(bytes([ftms.OP_REQUEST_CONTROL]))
    refused = none.write(bytes([ftms.OP_TARGET_HEART_RATE, 140]))
    assert refused.response[2] == ftms.RESULT_NOT_SUPPORTED and "no rider's heart rate" in refused.message


def test_characteristic_values_are_the_specs_bytes():
    machine, target = struct.unpack("<II", ftms.encode_feature())
    assert machine & ftms.MACHINE_POWER and machine & ftms.MACHINE_CADENCE and machine & ftms.MACHINE_TOTAL_DISTANCE
    assert target & ftms.TARGET_POWER and target & ftms.TARGET_SIMULATION and target & ftms.TARGET_INCLINATION
    control = ftms.FtmsControl(UNITS)
    assert struct.unpack("<hhH", control.encode_power_range()) == (0, 1000, 1)
    assert struct.unpack("<hhH", control.encode_inclination_range()) == (-100, 200, 1)      # 0.1 % steps
    assert struct.unpack("<hhH", control.encode_resistance_range()) == (0, 1000, 1)
    # a range beyond the sint16 field says its end (it raised struct.error: the app's read closed its connection)
    strong = ftms.FtmsControl(dataclasses.replace(UNITS, erg_power_max_w=40000.0))
    assert struct.unpack("<hhH", strong.encode_power_range()) == (0, 32767, 1)
    data = ftms.encode_indoor_bike_data(speed_kmh=31.456, cadence_rpm=88.6, distance_m=1234.4,
                                        resistance_level=12.3, power_w=-20.4, elapsed_s=61.2)
    # flags (speed present: bit 0 clear), speed 0.01 km/h, cadence 0.5 rpm, uint24 m, level 1, W, s
    assert data[:2] == struct.pack("<H", 0x0874)
    assert ftms.decode_indoor_bike_data(data) == ftms.IndoorBikeData(31.46, 88.5, 1234, 12, -20, 61)
    # another trainer's field set (a KICKR-like speed, cadence, power; then average power, energy, HR)
    other = struct.pack("<HHHh", 0x0044, 2510, 180, 201)
    assert ftms.parse_indoor_bike_data(other) == {"speed_kmh": 25.1, "cadence_rpm": 90.0, "power_w": 201}
    more = struct.pack("<HhhHHBB", 0x07C1, 180, 175, 512, 300, 6, 142) + b"\x32"
    assert ftms.parse_indoor_bike_data(more) == {"power_w": 180, "average_power_w": 175, "energy_kcal": 512,
                                                 "heart_rate_bpm": 142, "metabolic_equivalent": 5.0}
    # the values as a --csv file writes them: the field's decimals, not raw * 0.01's round-off
    odd = struct.pack("<HHH", 0x0002, 2781, 2781)
    assert [repr(v) for v in ftms.parse_indoor_bike_data(odd).values()] == ["27.81", "27.81"]
    with pytest.raises(ValueError, match="shorter than its flags say"):
        ftms.parse_indoor_bike_data(other[:-1])


def test_indoor_bike_data_carries_the_heart_rate_when_there_is_one():
    """Flags bit 9 and a uint8 bpm after the power (no energy fields here), before the elapsed
    time (FTMS 4.9.1); left out at 0 (no rider's heart) and for what is no heart rate."""
    base = dict(speed_kmh=30.0, cadence_rpm=90.0, distance_m=1000.0, resistance_level=0.0, power_w=200.0,
                elapsed_s=60.0)
    data = ftms.encode_indoor_bike_data(**base, heart_rate_bpm=142.4)
    assert struct.unpack_from("<H", data)[0] == 0x0874 | ftms.IBD_HEART_RATE == 0x0A74
    assert len(data) == 16 and data[13] == 142 and struct.unpack_from("<H", data, 14)[0] == 60
    assert struct.unpack_from("<h", data, 11)[0] == 200, "power just before the heart rate"
    assert ftms.parse_indoor_bike_data(data)["heart_rate_bpm"] == 142
    assert ftms.decode_indoor_bike_data(data) == ftms.IndoorBikeData(30.0, 90.0, 1000, 0, 200, 60, 142)
    for none in (0.0, 0.4, -5.0, float("nan")):
        plain = ftms.encode_indoor_bike_data(**base, heart_rate_bpm=none)
        assert plain == ftms.encode_indoor_bike_data(**base) and len(plain) == 15
        assert ftms.decode_indoor_bike_data(plain).heart_rate_bpm == 0
    assert ftms.encode_indoor_bike_data(**base, heart_rate_bpm=300.0)[13] == 255       # the field's end
    machine, target = struct.unpack("<II", ftms.encode_feature(heart_rate=True))
    assert machine & ftms.MACHINE_HEART_RATE == 1 << 10 and target & ftms.TARGET_HEART_RATE == 1 << 4
    machine, target = struct.unpack("<II", ftms.encode_feature())         # a bike without a rider
    assert not machine & ftms.MACHINE_HEART_RATE and not target & ftms.TARGET_HEART_RATE
    with pytest.raises(ValueError, match="not this bike's"):
        ftms.decode_indoor_bike_data(data[:-1])
    tel = Telemetry(gear_ratio=35.0)
    tel.update(stamp_ns=0, energy_mech_in_j=0.0, speed_rpm=3150.0, virtual_speed_mps=8.0, resistance_level=0.0,
               elapsed_s=1.0, heart_rate_bpm=131.0)
    assert ftms.decode_indoor_bike_data(tel.encode()).heart_rate_bpm == 131
    tel.update(stamp_ns=1, energy_mech_in_j=0.0, speed_rpm=3150.0, virtual_speed_mps=8.0, resistance_level=0.0,
               elapsed_s=1.0)                                   # a prime mover: no heart rate
    assert len(tel.encode()) == 15


def test_telemetry_power_is_the_ledgers_mean_over_a_second_and_distance_the_virtual_speed():
    tel = Telemetry(gear_ratio=35.0, power_window_s=1.0)
    for k in range(9):                 # every 0.25 s: 200 J/s, plus a pulse the window averages out
        t_ns = k * 250_000_000
        tel.update(stamp_ns=t_ns, energy_mech_in_j=200.0 * k * 0.25 + (5.0 if k % 2 else 0.0),
                   speed_rpm=3150.0, virtual_speed_mps=10.0, resistance_level=0.0, elapsed_s=k * 0.25)
    assert tel.power_w == pytest.approx(200.0)
    assert tel.cadence_rpm == pytest.approx(90.0)
    assert tel.distance_m == pytest.approx(20.0)
    assert ftms.decode_indoor_bike_data(tel.encode()).speed_kmh == pytest.approx(36.0)
    # 90 rpm for 2 s: 3 crank turns, the last at 2.0 s (1/1024 s units), in the Cycling Power Measurement
    assert tel.crank_revs == pytest.approx(3.0) and tel.crank_event_s == pytest.approx(2.0)
    assert ftms.decode_cps_measurement(tel.encode_cps()) == (200, 3, 2048)
    tel.update(stamp_ns=0, energy_mech_in_j=0.0, speed_rpm=0.0, virtual_speed_mps=0.0, resistance_level=0.0,
               elapsed_s=0.0)                                   # the plant started over
    assert tel.distance_m == 0.0 and tel.crank_revs == 0.0
    # wrapping fields, as the spec has apps expect
    assert ftms.decode_cps_measurement(ftms.encode_cps_measurement(150.4, 65537, 64.0 + 1 / 1024)) == (150, 1, 1)


def _pedal(tel, seconds, cadence_rpm, power_w, t0_s=0.0, e0_j=0.0, notify=None):
    """1 kHz plant states of a rider whose crank torque pulses twice a turn (1 + 0.5 cos 2 crank,
    the plant's rider): energy = P t + (P / w) (0.25 sin 2 crank). Every 0.25 s: notify(t)."""
    w = cadence_rpm * math.pi / 30.0
    for k in range(int(round(seconds * 1000)) + 1):
        t = t0_s + k * 1e-3
        crank = w * (t - t0_s)
        e = e0_j + power_w * (t - t0_s) + power_w / w * 0.25 * math.sin(2.0 * crank)
        tel.add_sample(int(round(t * 1e9)), e, cadence_rpm * 35.0)
        if notify is not None and k % 250 == 0 and k:
            notify(int(round(t * 1e9)), e)
    return e


@pytest.mark.parametrize("cadence_rpm", [80.0, 73.0, 100.0])
def test_telemetry_power_is_over_whole_crank_half_turns_so_the_pedal_pulse_cancels(cadence_rpm):
    tel = Telemetry(gear_ratio=35.0, power_window_s=1.0)
    shown, plain = [], []

    def notify(t_ns, e):
        tel.update(stamp_ns=t_ns, energy_mech_in_j=e, speed_rpm=cadence_rpm * 35.0, virtual_speed_mps=8.0,
                   resistance_level=0.0, elapsed_s=t_ns * 1e-9)
        if t_ns >= 2e9:
            shown.append(tel.power_w)
            # what a plain 1 s window of the same samples reads
            t0, e0, _ = next(x for x in reversed(tel.samples) if x[0] <= t_ns - 1e9)
            plain.append((e - e0) / ((t_ns - t0) * 1e-9))

    _pedal(tel, 6.0, cadence_rpm, 258.0, notify=notify)
    assert max(abs(p - 258.0) for p in shown) < 0.01 * 258.0, (min(shown), max(shown))
    assert max(abs(p - 258.0) for p in plain) > 0.03 * 258.0, "the test's pulse shows in a plain window"
    assert tel.crank_revs == pytest.approx(6.0 * cadence_rpm / 60.0, abs=1e-6)


def test_telemetry_power_of_a_crank_that_barely_turns_takes_the_time_window():
    tel = Telemetry(gear_ratio=35.0, power_window_s=1.0)
    e = _pedal(tel, 2.0, 5.0, 20.0)                 # 5 rpm: a sixth of a turn in a second
    tel.update(stamp_ns=2_000_000_000, energy_mech_in_j=e, speed_rpm=175.0, virtual_speed_mps=0.5,
               resistance_level=0.0, elapsed_s=2.0)
    t0, e0, _ = next(x for x in reversed(tel.samples) if x[0] <= 1_000_000_000)
    assert tel.power_w == pytest.approx((e - e0) / 1.0)
    assert len(tel.samples) <= 2 * Telemetry.HISTORY_S * 1000 + 1


def _connection():
    control = ftms.FtmsControl(UNITS)
    return dircon.DirconConnection(services_for(
        control, lambda data, client: [(ftms.CONTROL_POINT, control.write(data, client).response)]))


def test_dircon_discovery_read_subscribe_and_a_write_answered_with_its_notification():
    conn = _connection()
    out = conn.feed(dircon.encode(dircon.MSG_DISCOVER_SERVICES, 7))
    assert out == dircon.encode(dircon.MSG_DISCOVER_SERVICES, 7, dircon.uuid128(0x1826) + dircon.uuid128(0x1818))
    assert dircon.uuid128(0x1826).hex() == "0000182600001000800000805f9b34fb"
    out = conn.feed(dircon.encode(dircon.MSG_DISCOVER_CHARACTERISTICS, 8, dircon.uuid128(0x1826)))
    (msg,) = dircon.split_messages(bytearray(out))
    records = msg.data[16:]
    chars = {struct.unpack(">I", records[i:i + 4])[0]: records[i + 16] for i in range(0, len(records), 17)}
    assert chars[ftms.CONTROL_POINT] == dircon.PROP_WRITE | dircon.PROP_NOTIFY
    assert chars[ftms.POWER_RANGE] == dircon.PROP_READ
    (msg,) = dircon.split_messages(bytearray(conn.feed(dircon.encode(dircon.MSG_READ, 9,
                                                                     dircon.uuid128(ftms.POWER_RANGE)))))
    assert msg.code == dircon.RESP_SUCCESS and struct.unpack("<hhH", msg.data[16:]) == (0, 1000, 1)
    # without a subscription the write is answered, the Control Point response not notified
    only = dircon.split_messages(bytearray(conn.feed(dircon.encode(
        dircon.MSG_WRITE, 10, dircon.uuid128(ftms.CONTROL_POINT) + b"\x00"))))
    assert [m.msg_type for m in only] == [dircon.MSG_WRITE]
    conn.feed(dircon.encode(dircon.MSG_ENABLE_NOTIFICATIONS, 11, dircon.uuid128(ftms.CONTROL_POINT) + b"\x01"))
    # sent a byte at a time: framing holds across reads
    request = dircon.encode(dircon.MSG_WRITE, 12, dircon.uuid128(ftms.CONTROL_POINT) + cp(5, "h", 150))
    out = b"".join(conn.feed(request[i:i + 1]) for i in range(len(request)))
    write, note = dircon.split_messages(bytearray(out))
    assert (write.msg_type, write.seq, write.code) == (dircon.MSG_WRITE, 12, dircon.RESP_SUCCESS)
    assert (note.msg_type, note.seq) == (dircon.MSG_NOTIFICATION, 0)
    assert note.data == dircon.uuid128(ftms.CONTROL_POINT) + bytes([0x80, 0x05, 0x01])


def _characteristics(conn, service):
    """{characteristic uuid: DIRCON properties} of ``service`` as an app discovers them."""
    (msg,) = dircon.split_messages(bytearray(conn.feed(dircon.encode(dircon.MSG_DISCOVER_CHARACTERISTICS, 5,
                                                                     dircon.uuid128(service)))))
    records = msg.data[16:]
    return {struct.unpack(">I", records[i:i + 4])[0]: records[i + 16] for i in range(0, len(records), 17)}


def test_a_heart_rate_target_comes_with_its_supported_heart_rate_range_and_only_with_it():
    """FTMS 1.0, 3 (C.5): Supported Heart Rate Range 0x2AD7 is mandatory with the Heart Rate
    Target Setting feature and excluded without it: uint8 min, max, increment in bpm, the
    targets the Control Point takes (40..220 bpm, bike_plant.heart)."""
    for heart_rate in (True, False):
        control = ftms.FtmsControl(UNITS, heart_rate=heart_rate)
        conn = dircon.DirconConnection(services_for(control, lambda data, client: []))
        chars = _characteristics(conn, ftms.FTMS_SERVICE)
        claims = bool(struct.unpack("<II", control.encode_feature())[1] & ftms.TARGET_HEART_RATE)
        assert claims == heart_rate and (ftms.HEART_RATE_RANGE in chars) == heart_rate
        if not heart_rate:
            continue
        assert chars[ftms.HEART_RATE_RANGE] == dircon.PROP_READ
        (msg,) = dircon.split_messages(bytearray(conn.feed(dircon.encode(dircon.MSG_READ, 6,
                                                                         dircon.uuid128(ftms.HEART_RATE_RANGE)))))
        assert msg.code == dircon.RESP_SUCCESS and struct.unpack("<BBB", msg.data[16:]) == (40, 220, 1)
        control.write(bytes([ftms.OP_REQUEST_CONTROL]))
        for bpm, result in ((40, ftms.RESULT_SUCCESS), (220, ftms.RESULT_SUCCESS),
                            (39, ftms.RESULT_INVALID_PARAMETER), (221, ftms.RESULT_INVALID_PARAMETER)):
            assert control.write(bytes([ftms.OP_TARGET_HEART_RATE, bpm])).response[2] == result, bpm


@pytest.mark.parametrize("msg_type,data,code", [
    (9, b"", dircon.RESP_UNKNOWN_TYPE),
    (dircon.MSG_READ, b"\x00" * 5, dircon.RESP_GENERIC_ERROR),
    (dircon.MSG_READ, dircon.uuid128(0x2A37), dircon.RESP_CHARACTERISTIC_NOT_FOUND),
    (dircon.MSG_DISCOVER_CHARACTERISTICS, dircon.uuid128(0x180D), dircon.RESP_SERVICE_NOT_FOUND),
    (dircon.MSG_READ, dircon.uuid128(ftms.STATUS), dircon.RESP_NOT_SUPPORTED),
    (dircon.MSG_WRITE, dircon.uuid128(ftms.POWER_RANGE) + b"\x01", dircon.RESP_NOT_SUPPORTED),
    (dircon.MSG_ENABLE_NOTIFICATIONS, dircon.uuid128(ftms.FEATURE) + b"\x01", dircon.RESP_NOT_SUPPORTED),
    (dircon.MSG_ENABLE_NOTIFICATIONS, dircon.uuid128(ftms.STATUS) + b"\x07", dircon.RESP_GENERIC_ERROR),
])
def test_a_request_the_table_cannot_serve_gets_its_code_and_is_said(msg_type, data, code):
    conn = _connection()
    (msg,) = dircon.split_messages(bytearray(conn.feed(dircon.encode(msg_type, 3, data))))
    assert (msg.msg_type, msg.seq, msg.code) == (msg_type, 3, code)
    assert len(conn.log) == 1 and "refused" in conn.log[0]
    # and the connection goes on
    assert conn.feed(dircon.encode(dircon.MSG_DISCOVER_SERVICES, 4))


@pytest.mark.parametrize("stream,why", [
    (b"\x02\x01\x00\x00\x00\x00", "protocol version 2"),
    (b"GET / HTTP/1.1\r\n\r\n", "protocol version 71"),
    (b"\x01\x04\x01\x00\xff\xff", "65535 data bytes"),
])
def test_a_stream_that_is_not_dircon_cannot_be_framed(stream, why):
    with pytest.raises(dircon.DirconError, match=why):
        _connection().feed(stream)


def test_the_server_closes_only_a_broken_connection_and_drops_an_app_that_reads_nothing():
    logs = []
    control = ftms.FtmsControl(UNITS)
    tel = Telemetry(35.0)
    server = dircon.DirconServer("127.0.0.1", 0, services_for(control, lambda d, client: []),
                                 lambda text, warning: logs.append((text, warning)))
    stop = [False]
    import threading
    pump = threading.Thread(target=lambda: [server.poll(0.01) for _ in iter(lambda: stop[0], True)])
    pump.start()
    try:
        good = dircon.DirconClient("127.0.0.1", server.port)
        assert good.request(dircon.MSG_DISCOVER_SERVICES).data[:16] == dircon.uuid128(0x1826)
        bad = socket.create_connection(("127.0.0.1", server.port))
        bad.sendall(b"\x07garbage")
        bad.settimeout(5)
        assert bad.recv(100) == b""                          # closed by the server
        assert any("not a DIRCON stream" in t and w for t, w in logs)
        assert good.read(ftms.POWER_RANGE) == control.encode_power_range()      # still served
        good.subscribe(ftms.INDOOR_BIKE_DATA)
        server.broadcast(ftms.INDOOR_BIKE_DATA, tel.encode())
        assert good.wait_notification(ftms.INDOOR_BIKE_DATA) == tel.encode()
        # an app that subscribes and never reads: dropped once its backlog passes the limit
        deaf = dircon.DirconClient("127.0.0.1", server.port)
        deaf.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        deaf.subscribe(ftms.INDOOR_BIKE_DATA)
        end = time.monotonic() + 10
        while not any("reads nothing" in t for t, _ in logs) and time.monotonic() < end:
            server.broadcast(ftms.INDOOR_BIKE_DATA, tel.encode() * 30)
            time.sleep(0.001)
        assert any("reads nothing" in t and w for t, w in logs), logs
        good.close()
        deaf.close()
    finally:
        stop[0] = True
        pump.join()
        server.close()


@contextlib.contextmanager
def _served_control():
    """(FtmsControl, DirconServer) on a free port of 127.0.0.1, its Control Point answered by the
    control, served by a thread until the block ends."""
    import threading
    control = ftms.FtmsControl(UNITS)
    server = dircon.DirconServer("127.0.0.1", 0, services_for(
        control, lambda data, client: [(ftms.CONTROL_POINT, control.write(data, client).response)]),
        lambda text, warning: None, on_close=control.release)
    stop = [False]
    pump = threading.Thread(target=lambda: [server.poll(0.01) for _ in iter(lambda: stop[0], True)])
    pump.start()
    try:
        yield control, server
    finally:
        stop[0] = True
        pump.join()
        server.close()


def test_control_is_one_apps_until_it_resets_or_disconnects():
    """FTMS 1.0, 4.16.2.1: a Request Control while another client has control gets result 5
    (control not permitted), and so does any op of a client that does not have it; control
    lasts as long as its holder's connection. Two apps on real sockets: the second is refused
    until the first disconnects, then takes over; the first's target stayed in force meanwhile."""
    control = ftms.FtmsControl(UNITS)
    a, b = object(), object()
    assert control.write(bytes([ftms.OP_REQUEST_CONTROL]), a).response[2] == ftms.RESULT_SUCCESS
    assert control.write(bytes([ftms.OP_REQUEST_CONTROL]), a).response[2] == ftms.RESULT_SUCCESS   # again: still its
    refused = control.write(bytes([ftms.OP_REQUEST_CONTROL]), b)
    assert refused.response == bytes([0x80, 0x00, ftms.RESULT_NOT_PERMITTED]) and "another app" in refused.message
    taken = control.write(cp(ftms.OP_TARGET_POWER, "h", 200), b)
    assert taken.response[2] == ftms.RESULT_NOT_PERMITTED and taken.target is None and taken.status is None
    assert control.write(bytes([ftms.OP_RESET]), b).response[2] == ftms.RESULT_NOT_PERMITTED
    assert control.write(cp(ftms.OP_TARGET_POWER, "h", 200), a).response[2] == ftms.RESULT_SUCCESS
    assert control.release(b) is None                     # b never had it
    assert "disconnected" in control.release(a)
    assert control.write(cp(ftms.OP_TARGET_POWER, "h", 150), b).response[2] == ftms.RESULT_NOT_PERMITTED
    assert control.write(bytes([ftms.OP_REQUEST_CONTROL]), b).response[2] == ftms.RESULT_SUCCESS
    control.write(bytes([ftms.OP_RESET]), b)              # a reset gives it up too
    assert control.write(bytes([ftms.OP_REQUEST_CONTROL]), a).response[2] == ftms.RESULT_SUCCESS

    def ask(app, data):
        assert app.write(ftms.CONTROL_POINT, data).code == dircon.RESP_SUCCESS
        return app.wait_notification(ftms.CONTROL_POINT)[2]

    with _served_control() as (control, server):
        first, second = (dircon.DirconClient("127.0.0.1", server.port) for _ in range(2))
        for app in (first, second):
            app.subscribe(ftms.CONTROL_POINT)
        assert ask(first, bytes([ftms.OP_REQUEST_CONTROL])) == ftms.RESULT_SUCCESS
        assert ask(first, cp(ftms.OP_TARGET_POWER, "h", 180)) == ftms.RESULT_SUCCESS
        assert ask(second, bytes([ftms.OP_REQUEST_CONTROL])) == ftms.RESULT_NOT_PERMITTED
        assert ask(second, cp(ftms.OP_TARGET_POWER, "h", 120)) == ftms.RESULT_NOT_PERMITTED
        assert control.running_target.text == "target power 180 W"
        first.close()
        end = time.monotonic() + 5
        while control.controlled and time.monotonic() < end:
            time.sleep(0.01)
        assert ask(second, bytes([ftms.OP_REQUEST_CONTROL])) == ftms.RESULT_SUCCESS
        assert ask(second, cp(ftms.OP_TARGET_POWER, "h", 120)) == ftms.RESULT_SUCCESS
        second.close()


def test_bike_trainer_says_a_refused_request_in_one_error_line():
    """A trainer's refusal (--level 500 beyond its 0..100: invalid parameter; another app in
    control: control not permitted) was one more line on stdout, no 'error:', exit 1. Now the
    one error line on stderr, exit 1; the trainer's description stays on stdout."""
    from conftest import bike_command
    with _served_control() as (_control, server):
        port = str(server.port)
        for args, words in ((["--level", "500"], "error: resistance level 500: the trainer answered invalid parameter"),
                            (["--power", "150"], "error: request control: the trainer answered control not "
                                                 "permitted")):
            holder = None
            if "--power" in args:              # another app holds control
                holder = dircon.DirconClient("127.0.0.1", server.port)
                holder.subscribe(ftms.CONTROL_POINT)
                holder.write(ftms.CONTROL_POINT, bytes([ftms.OP_REQUEST_CONTROL]))
                assert holder.wait_notification(ftms.CONTROL_POINT)[2] == ftms.RESULT_SUCCESS
            result = bike_command("trainer", "--port", port, "--seconds", "1", *args, timeout=60)
            lines = [line for line in result.stderr.splitlines() if line.strip()]
            assert result.returncode == 1 and lines == [words], (result.stdout, result.stderr)
            assert "resistance level range 0 .. 100" in result.stdout and "error" not in result.stdout
            if holder is not None:
                holder.close()


def test_the_bike_is_advertised_by_mdns_the_way_apps_look_for_a_dircon_trainer():
    from zeroconf import IPVersion, Zeroconf
    logs = []
    adv = dircon.Advertiser("bike test", ["127.0.0.1"], 36999, "bike-36999", lambda t, w: logs.append((t, w)))
    app = None
    try:
        assert adv.done.wait(20) and adv.error is None, logs
        app = Zeroconf(interfaces=["127.0.0.1"], ip_version=IPVersion.V4Only)
        info = app.get_service_info(dircon.MDNS_SERVICE, f"bike test.{dircon.MDNS_SERVICE}", timeout=5000)
        assert info is not None and info.port == 36999 and info.parsed_addresses() == ["127.0.0.1"]
        assert info.properties[b"ble-service-uuids"] == b"0x1826,0x1818"
        assert info.properties[b"mac-address"] == dircon.local_mac("bike-36999").encode()
        assert dircon.local_mac("bike-36999") != dircon.local_mac("bike-36998")     # two bikes differ
        assert dircon.local_mac("x").startswith("02-")
    finally:
        if app is not None:
            app.close()
        adv.close()
    assert dircon.host_addresses("10.1.2.3") == ["10.1.2.3"]
    assert all(not a.startswith("127.") for a in dircon.host_addresses("0.0.0.0")) or \
        dircon.host_addresses("0.0.0.0") == ["127.0.0.1"]


# host B's bike in test_a_second_bike_of_the_same_name_...: advertised under a name host A's bike
# holds, then an app there resolving both; prints the outcome as JSON
_SECOND_BIKE = r"""
import json, sys
from zeroconf import IPVersion, Zeroconf
from bike_session import dircon
name, address, logs = sys.argv[1], sys.argv[2], []
second = dircon.Advertiser(name, [address], 36998, "bike-36998", lambda t, w: logs.append([t, w]))
out = {"logs": logs, "second": [second.done.wait(20), second.error, second.advertised_name]}
app = Zeroconf(interfaces=[address], ip_version=IPVersion.V4Only)
try:
    out["ports"] = [getattr(app.get_service_info(dircon.MDNS_SERVICE, f"{n}.{dircon.MDNS_SERVICE}", timeout=5000),
                            "port", None) for n in (name, f"{name}-2")]
finally:
    app.close()
    second.close()
print(json.dumps(out))
"""


def test_a_second_bike_of_the_same_name_is_advertised_as_name_2_and_both_are_found(host_b):
    """Two testbeds with one namespace on a network: the second bike's name is taken, so it is
    advertised as "bike twin-2" (mDNS's rename), says so, and an app finds both at their ports.
    Before, the second registration failed (NonUniqueNameException): no advert at all.

    The two bikes are on two hosts, as on a lab's network: this one and a network namespace
    joined to it by a veth pair (made by the test, as test_fleet_graph's). Two responders of one
    host share port 5353, and the answer to the second one's first probe (QU: unicast to port
    5353) reached either socket as the kernel picked: on one host the rename came in 2 runs of
    4, and on a CI host (eth0 192.0.2.2, lo without MULTICAST) never."""
    import json
    import subprocess
    import sys

    name = f"bike twin{os.getpid()}"
    logs = []
    first = dircon.Advertiser(name, [host_b["addr_a"]], 36997, "bike-36997", lambda t, w: logs.append((t, w)))
    try:
        assert first.done.wait(20) and first.error is None and first.advertised_name == name, logs
        run = subprocess.run(["ip", "netns", "exec", host_b["netns"], sys.executable, "-c", _SECOND_BIKE, name,
                              host_b["addr_b"]], capture_output=True, text=True, timeout=120)
    finally:
        first.close()
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    second_logs = [tuple(x) for x in out["logs"]]
    assert out["second"] == [True, None, f"{name}-2"], second_logs
    assert (f"advertised as '{name}-2' ({dircon.MDNS_SERVICE} on {host_b['addr_b']}); '{name}' is taken on this "
            "network", True) in second_logs
    assert out["ports"] == [36997, 36998]


def test_two_bikes_of_one_name_on_one_host_are_advertised_as_name_and_name_2():
    """Two testbeds of one namespace on ONE host (a developer's two sessions): the second is
    advertised as "<name>-2". Both responders share port 5353, and mDNS's probes are QU
    questions whose unicast answer reaches only one of the sockets: before, the second bike
    often held the name too (an app found one of the two). A multicast question before the
    probes (its answer reaches both) finds the holder."""
    from zeroconf import IPVersion, Zeroconf
    name = f"bike one-host{os.getpid()}"
    logs = []
    first = dircon.Advertiser(name, ["127.0.0.1"], 36995, "bike-36995", lambda t, w: logs.append((t, w)))
    second = app = None
    try:
        assert first.done.wait(20) and first.advertised_name == name, logs
        second = dircon.Advertiser(name, ["127.0.0.1"], 36996, "bike-36996", lambda t, w: logs.append((t, w)))
        assert second.done.wait(20) and second.error is None, logs
        assert second.advertised_name == f"{name}-2", logs
        app = Zeroconf(interfaces=["127.0.0.1"], ip_version=IPVersion.V4Only)
        assert [getattr(app.get_service_info(dircon.MDNS_SERVICE, f"{n}.{dircon.MDNS_SERVICE}", timeout=5000),
                        "port", None) for n in (name, f"{name}-2")] == [36995, 36996]
    finally:
        if app is not None:
            app.close()
        for adv in (second, first):
            if adv is not None:
                adv.close()


def test_fuzzed_dircon_streams_and_control_point_writes_never_raise_anything_else():
    """400 seeded random streams (valid headers with random bodies, and raw junk), and random
    Control Point writes: a stream either frames into answered messages or raises DirconError
    (its connection is closed); every write is answered [0x80, op, result], and a target it
    gives is a valid Command."""
    import random
    rng = random.Random(20261205)
    uuids = [dircon.uuid128(u) for u in (ftms.FTMS_SERVICE, ftms.CONTROL_POINT, ftms.STATUS, ftms.POWER_RANGE,
                                         ftms.INDOOR_BIKE_DATA, 0x2A63)]
    for k in range(400):
        conn = _connection()
        conn.feed(dircon.encode(dircon.MSG_DISCOVER_SERVICES, 1))
        try:
            if k % 2:      # well framed, random type / body
                body = rng.choice(uuids + [b""]) + bytes(rng.randrange(256) for _ in range(rng.randrange(8)))
                stream = dircon.encode(rng.randrange(9), rng.randrange(256), body)
            else:
                stream = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64)))
            out = conn.feed(stream)
        except dircon.DirconError:
            continue
        for msg in dircon.split_messages(bytearray(out)):
            assert msg.msg_type in range(9)
    control = ftms.FtmsControl(UNITS)
    for k in range(2000):
        data = bytes([rng.choice([0, 1, 3, 4, 5, 7, 8, 0x11, 0x13, rng.randrange(256)])]) + \
            bytes(rng.randrange(256) for _ in range(rng.randrange(8)))
        reply = control.write(data)
        assert reply.response[:2] == bytes([0x80, data[0]]) and 1 <= reply.response[2] <= 5
        if reply.target is not None:
            assert 0.0 <= reply.target.command <= 1.0 and reply.target.mode in MODES.values()
        if reply.response[2] != ftms.RESULT_SUCCESS:
            assert reply.message


def test_erg_steps_and_their_settle_times_by_the_reports_rule():
    from bike_session.trainer_probe import erg_steps
    t = [0.25 * k for k in range(40)]
    target = [150.0] * 8 + [250.0] * 32
    # the power reaches 250 W +- 5 % 2 s after the step, one excursion at 3 s restarts the hold
    power = [150.0] * 8 + [200.0] * 8 + [245.0] * 4 + [200.0] + [252.0] * 19
    ((at, to, settle),) = erg_steps(t, target, power)
    assert (at, to) == (2.0, 250.0) and settle == pytest.approx(3.25)
    assert erg_steps(t, target, [150.0] * 40)[0][2] is None          # never there: not settled
    assert erg_steps(t, [150.0] * 40, power) == []                   # no step


def test_bike_trainer_refuses_a_road_or_cadence_the_ftms_fields_cannot_carry(tmp_path, capsys):
    """A road a profile may give (Crr up to 0.05) beyond the Simulation's field (0.0255): one
    error before anything is sent, not a struct error mid-ride; the CLI's --crr / --cadence too."""
    import types

    from conftest import bike_command

    from bike_session import trainer_probe

    class Trainer:                                      # the two range reads ride_workout makes first
        def read(self, uuid):
            return struct.pack("<hhH", -200, 200, 1) if uuid == ftms.INCLINATION_RANGE else struct.pack("<hhH", 0, 1000, 1)

    prof = tmp_path / "steep.yaml"
    prof.write_text("mode: slope\nsegments:\n  - {kind: step, duration_s: 5, target: 3}\n"
                    "  - {kind: step, duration_s: 5, target: 3, road: {crr: 0.03, cw_kg_m: 0.5, wind_mps: 0}}\n")
    opts = types.SimpleNamespace(workout=str(prof), ftp=None, seconds_given=False, road=trainer_probe.DEFAULT_ROAD,
                                 csv=None)
    assert trainer_probe.ride_workout(Trainer(), opts, print) == 2
    err = capsys.readouterr().err
    assert "segments[1]: road crr 0.03 outside [0, 0.0255]" in err, err
    for args, words in ((["--crr", "0.1", "--grade", "3"], "--crr 0.1 outside"),
                        (["--cadence", "-5", "--power", "100"], "--cadence -5 outside"),
                        (["--difficulty", "150", "--grade", "3"], "--difficulty 150 outside"),
                        # the road goes with a grade: with --power it was dropped without a word
                        (["--power", "200", "--crr", "0.005", "--wind", "2"],
                         "--crr, --wind: only with --grade or --workout"),
                        (["--level", "5", "--difficulty", "50"], "--difficulty: only with --grade or --workout")):
        result = bike_command("trainer", "--port", "1", *args, timeout=60)
        assert result.returncode == 2 and words in result.stderr, result.stderr


@pytest.mark.parametrize("args,words", [
    (["--power", "nan"], "--power nan outside [0, 32767] W"), (["--power", "40000"], "--power 40000 outside"),
    (["--power", "-5"], "--power -5 outside"), (["--grade", "500"], "--grade 500 outside [-327.68, 327.67] %"),
    (["--grade", "700", "--difficulty", "50"], "--grade 700 (sent as 350) outside"),
    (["--level", "nan"], "--level nan outside [0, 3276.7]"), (["--level", "-1"], "--level -1 outside"),
    (["--port", "70000", "--power", "100"], "--port must be 1..65535, got 70000"),
    (["--port", "-1", "--power", "100"], "--port must be 1..65535, got -1"),
    # the option's own error, as ./bike run's ("bad workout: FILE: ftp_w: parameter ftp_w must be ..."), and a
    # .yaml profile (no relative targets) connected with --ftp 5000 / --max-hr -1 without a word
    (["--workout", "test/data/workouts/over_unders.zwo", "--ftp", "nan"],
     "error: --ftp must be in (0, 2000] W, got nan"),
    (["--workout", "config/profiles/demo_intervals.yaml", "--ftp", "5000"], "error: --ftp must be in (0, 2000] W"),
    (["--workout", "config/profiles/demo_intervals.yaml", "--max-hr", "-1"],
     "error: --max-hr must be in (0, 250] bpm, got -1.0"),
    (["--workout", "test/data/workouts/over_unders.zwo"], "power targets are fractions of FTP: pass the rider's ftp_w"),
    (["--workout", "no_such_workout.erg"], "bad workout: no_such_workout.erg: cannot read workout"),
    (["--workout", "README.md"], "bad workout: README.md: unsupported workout extension '.md'")])
def test_bike_trainer_refuses_a_target_or_port_the_fields_cannot_carry_before_connecting(bike_cli, args, words):
    """--power / --grade / --level are written as sint16 fields: NaN or a value beyond the field
    ended in a ValueError / struct.error traceback once connected (and, with no trainer there,
    in "no trainer" rather than the bad value); a --port beyond 1..65535 was tried as one. A
    --workout no trainer can ride (or its --ftp) was found only once one answered. One error
    naming the option, exit 2, before connecting (--port 1: nothing listens there)."""
    full = args if "--port" in args else ["--port", "1", *args]
    result = bike_cli("trainer", *full, timeout=60)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 2 and len(lines) == 1 and words in lines[0], result.stderr


@pytest.mark.parametrize("args,words", [
    (["--port", "1", "--power", "100", "--ftp", "200"], "--ftp: only with --workout"),
    (["--port", "1", "--max-hr", "180"], "--max-hr: only with --workout"),
    (["--find", "--seconds", "1", "--power", "0"], "--power: not with --find"),
    (["--find", "--seconds", "1", "--host", "10.0.0.9", "--port", "5"], "--host, --port: not with --find")])
def test_bike_trainer_refuses_an_option_that_means_nothing_with_the_others(args, words):
    """--ftp / --max-hr without a workout, or a trainer's address and target with --find (which
    connects to none), were dropped without a word. One error naming them, exit 2."""
    from conftest import bike_command
    result = bike_command("trainer", *args, timeout=60)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 2 and len(lines) == 1 and words in lines[0], result.stderr
    assert result.stdout == ""


@pytest.mark.parametrize("args", [["--find", "--seconds", "1e300"], ["--port", "1", "--seconds", "1e300"]])
def test_bike_trainer_refuses_seconds_no_clock_counts(args):
    """--find --seconds 1e300 ended in time.sleep's OverflowError traceback."""
    from conftest import bike_command
    result = bike_command("trainer", *args, timeout=60)
    assert result.returncode == 2 and result.stdout == "", result.stderr
    assert result.stderr == "error: --seconds must be at most 9.2e+09 (a clock's int64 nanoseconds), got 1e+300\n"


def test_bike_trainer_sends_grades_as_zwift_does_at_a_trainer_difficulty():
    """Zwift's trainer difficulty (research notes, trainers.md section 3): the grade scaled by it,
    descents halved again (-10 % -> -2.5 % at 50 %); none given: the grade as it is. A profile's
    spindown segment is sent as Spin Down Control."""
    from bike_session import trainer_probe
    from bike_session.profiles import MODES
    assert trainer_probe.sent_grade_pct(-10.0, 50.0) == -2.5 and trainer_probe.sent_grade_pct(8.0, 50.0) == 4.0
    assert trainer_probe.sent_grade_pct(-10.0, None) == -10.0 and trainer_probe.sent_grade_pct(6.0, 100.0) == 6.0
    units = ModeUnits(1000.0, -0.2, 0.2, 20.0, 120.0)
    op, param, text = trainer_probe._target_write(MODES["slope"], 0.25, units, difficulty_pct=50.0)  # -10 %
    assert op == ftms.OP_SIMULATION and struct.unpack("<hhBB", param)[1] == -250
    assert "-2.50 % (-10.0 % at difficulty 50 %)" in text
    assert trainer_probe._target_write(MODES["spindown"], 0.0, units)[:2] == (ftms.OP_SPIN_DOWN, b"\x01")


def test_the_trainers_power_meter_counts_brake_friction_and_flywheel():
    """E = int (-T_em w + (B w + Tc) w) dt + 1/2 J w^2: a 100 W brake at 100 rad/s with B 1e-3
    (10 W) for 1 s is 110 J; spinning up to 110 rad/s adds 1/2 J (110^2 - 100^2) = 10.5 J; a
    spin-down's new figure counts from then on; a stamp going back (a new run) adds nothing."""
    from bike_session.ftms_node import TrainerPowerMeter
    meter = TrainerPowerMeter(0.01, (1e-3, 0.0, 1.0))
    for k in range(1001):
        e = meter.add(k * 1_000_000, -1.0, 100.0)
    assert e == pytest.approx(110.0, rel=1e-9)
    e0 = e
    e = meter.add(1_001_000_000, 0.0, 110.0)
    assert e - e0 == pytest.approx(0.5 * 0.01 * (110.0 ** 2 - 100.0 ** 2) + 1e-3 * 105.0 ** 2 * 1e-3, rel=1e-9)
    meter.set_friction(2e-3, 0.0)
    e1 = meter.add(1_002_000_000, 0.0, 110.0)
    assert e1 - e == pytest.approx(2e-3 * 110.0 ** 2 * 1e-3, rel=1e-9)
    assert meter.add(5_000_000, -1.0, 50.0) == e1 and meter.add(5_000_000, math.nan, 50.0) == e1


@pytest.mark.parametrize("heard_in_first_batch", [False, True])
def test_the_trainers_power_meter_starts_from_the_speed_at_which_sim_time_starts(heard_in_first_batch):
    """A drive on CAN: states at t = 0 with speed 0 before the plant hears the drive, then its
    first speed (100 rad/s) at t = 0 (an ODrive) or with the first batch (a VESC): 1 s of a 100 W
    brake is 100 J (less 0.05 J for the first batch's mean speed of 50 rad/s in the VESC's case),
    not 100 J + 1/2 J w^2 (50 J, an app's power spike at the start). The same after a stamp
    going back (a new run)."""
    from bike_session.ftms_node import TrainerPowerMeter
    for new_run in (False, True):
        meter = TrainerPowerMeter(0.01, (0.0, 0.0, 1.0))
        if new_run:                          # a first run, then a new one from t = 0
            meter.add(2_000_000_000, 0.0, 80.0)
            meter.add(3_000_000_000, 0.0, 80.0)
        e_before = meter.energy_j
        for w in (0.0, 0.0, 0.0 if heard_in_first_batch else 100.0):
            meter.add(0, 0.0, w)
        for k in range(1, 1001):
            e = meter.add(k * 1_000_000, -1.0, 100.0)
        assert e - e_before == pytest.approx(100.0 - (0.05 if heard_in_first_batch else 0.0), rel=1e-9)


def test_bike_trainer_sends_a_heart_rate_steps_target_and_a_bike_with_a_rider_takes_it():
    """`./bike trainer --workout`: an ERG step with heart_rate_bpm goes out as Set Target Heart
    Rate (not as its starting power), which this bike's Control Point takes as heart-rate ERG."""
    from bike_session.trainer_probe import _target_write

    op, param, text = _target_write(MODES["erg"], 0.15, UNITS, heart_rate_bpm=140.0)
    assert (op, param, text) == (ftms.OP_TARGET_HEART_RATE, bytes([140]), "target heart rate 140 bpm")
    assert _target_write(MODES["erg"], 0.15, UNITS)[0] == ftms.OP_TARGET_POWER
    control = ftms.FtmsControl(UNITS, heart_rate=True)
    control.write(bytes([ftms.OP_REQUEST_CONTROL]))
    assert control.write(bytes([op]) + param).target.heart_rate_bpm == 140.0


def test_a_resistance_level_is_echoed_in_the_width_the_app_wrote_never_clamped():
    """FTMS 1.0, Table 4.15: Set Target Resistance Level takes a uint8 in 0.1 steps (at most 25.5);
    Fitness Machine Status 0x07 is a uint8 in FTMS 1.0 and a sint16 in 1.0.1 (Table 4.26). This
    bike's levels go to 100, which apps (GoldenCheetah, QZ) reach with a sint16: the status
    echoes each app's own width. Before, 45.5 written as a sint16 was echoed as the uint8 25.5,
    a target the bike was not riding."""
    control = controlled()
    top_uint8 = control.write(bytes([ftms.OP_TARGET_RESISTANCE, 255]))            # 25.5: the uint8's end
    assert top_uint8.response[2] == ftms.RESULT_SUCCESS and top_uint8.target.command == pytest.approx(0.255)
    assert top_uint8.status == bytes([ftms.STATUS_RESISTANCE_CHANGED, 255])
    for tenths in (256, 455, 1000):                                              # 25.6, 45.5, 100: sint16
        reply = control.write(cp(ftms.OP_TARGET_RESISTANCE, "h", tenths))
        assert reply.response[2] == ftms.RESULT_SUCCESS and reply.target.command == pytest.approx(tenths / 1000)
        assert reply.status == bytes([ftms.STATUS_RESISTANCE_CHANGED]) + struct.pack("<h", tenths), tenths
    assert control.write(cp(ftms.OP_TARGET_RESISTANCE, "h", 20)).status == bytes([0x07]) + struct.pack("<h", 20)
    for tenths in (1001, -1):                                                   # beyond 0..100: refused, said
        bad = control.write(cp(ftms.OP_TARGET_RESISTANCE, "h", tenths))
        assert bad.response[2] == ftms.RESULT_INVALID_PARAMETER and bad.status is None and bad.target is None
        assert "refused: outside [0, 100]" in bad.message


def test_the_training_status_follows_the_session_and_the_apps_target_stop_and_reset():
    """FTMS 1.0, 4.10 (Training Status: flags, status, string), Table 4.13, and 4.16.2.2 (a Reset
    sets it to Idle): idle before the ride; the session's Command when the app set no target
    (its free ride is manual mode, a workout's ERG watt control); the app's target when it set
    one; idle while stopped and after a reset; post-workout once the session is done. Notified
    once per change."""
    control = ftms.FtmsControl(UNITS, heart_rate=True)
    assert control.encode_training_status() == bytes([0x00, ftms.TS_IDLE])            # no session yet
    assert control.training_status_change() == bytes([0x00, ftms.TS_IDLE])
    assert control.training_status_change() is None                                     # said once
    control.follow_session(ftms.SESSION_WAITING, MODES["resistance"], 0.0)
    assert control.training_status_change() is None
    control.follow_session(ftms.SESSION_RUNNING, MODES["resistance"], 0.0)              # the app ride's free ride
    assert control.training_status_change() == bytes([0x00, ftms.TS_MANUAL_MODE])
    for mode, bpm, want in ((MODES["erg"], 0.0, ftms.TS_WATT_CONTROL),
                            (MODES["erg"], 140.0, ftms.TS_HEART_RATE_CONTROL),
                            (MODES["slope"], 0.0, ftms.TS_MANUAL_MODE)):
        control.follow_session(ftms.SESSION_RUNNING, mode, bpm)                      # a workout the session rides
        assert control.training_status() == (want, ""), (mode, bpm)
    control.follow_session(ftms.SESSION_RUNNING, MODES["isokinetic"], 0.0)
    assert control.encode_training_status() == bytes([ftms.TS_FLAG_STRING, ftms.TS_OTHER]) + b"isokinetic"
    assert ftms.training_status_text(control.encode_training_status()) == "other (isokinetic)"
    # the app's target wins over the session's Command it has not reached yet
    control.follow_session(ftms.SESSION_RUNNING, MODES["resistance"], 0.0)
    control.write(bytes([ftms.OP_REQUEST_CONTROL]))
    assert control.training_status() == (ftms.TS_MANUAL_MODE, "")
    control.write(cp(ftms.OP_TARGET_POWER, "h", 150))
    assert control.training_status() == (ftms.TS_WATT_CONTROL, "")
    control.write(bytes([ftms.OP_TARGET_HEART_RATE, 130]))
    assert control.training_status() == (ftms.TS_HEART_RATE_CONTROL, "")
    control.write(cp(ftms.OP_SIMULATION, "hhBB", 0, 300, 40, 51))
    assert control.training_status() == (ftms.TS_MANUAL_MODE, "")
    control.write(bytes([ftms.OP_STOP_PAUSE, 2]))
    assert control.training_status() == (ftms.TS_IDLE, "")
    control.write(cp(ftms.OP_TARGET_POWER, "h", 200))                                # kept for the resume: idle
    assert control.training_status() == (ftms.TS_IDLE, "")
    control.write(bytes([ftms.OP_START_RESUME]))
    assert control.training_status() == (ftms.TS_WATT_CONTROL, "")
    control.write(bytes([ftms.OP_SPIN_DOWN, 1]))
    assert control.training_status() == (ftms.TS_OTHER, "spindown")
    control.training_status_change()
    control.write(bytes([ftms.OP_RESET]))
    assert control.training_status_change() == bytes([0x00, ftms.TS_IDLE])            # 4.16.2.2
    control.follow_session(ftms.SESSION_RUNNING, MODES["resistance"], 0.0)              # the reset's brake release
    assert control.training_status() == (ftms.TS_IDLE, "")
    control.write(bytes([ftms.OP_REQUEST_CONTROL]))
    control.write(cp(ftms.OP_TARGET_POWER, "h", 120))
    assert control.training_status_change() == bytes([0x00, ftms.TS_WATT_CONTROL])
    control.follow_session(ftms.SESSION_DONE, MODES["erg"], 0.0)
    assert control.training_status_change() == bytes([0x00, ftms.TS_POST_WORKOUT])
    assert ftms.decode_training_status(bytes([0x00, ftms.TS_POST_WORKOUT])) == (ftms.TS_POST_WORKOUT, "")
    with pytest.raises(ValueError, match="at least 2"):
        ftms.decode_training_status(b"\x00")


def test_indoor_bike_data_is_notify_only_and_the_training_status_is_read_and_notify():
    """FTMS 1.0.1, 4, Table 4.1: Indoor Bike Data's one property is Notify (every other is
    excluded; a read is refused as a characteristic that cannot be read), Training Status's are
    Read and Notify. An app discovers them so, subscribes, and reads the training status."""
    conn = _connection()
    chars = _characteristics(conn, ftms.FTMS_SERVICE)
    assert chars[ftms.INDOOR_BIKE_DATA] == dircon.PROP_NOTIFY
    assert chars[ftms.TRAINING_STATUS] == dircon.PROP_READ | dircon.PROP_NOTIFY
    (read,) = dircon.split_messages(bytearray(conn.feed(dircon.encode(dircon.MSG_READ, 3,
                                                                      dircon.uuid128(ftms.INDOOR_BIKE_DATA)))))
    assert read.code == dircon.RESP_NOT_SUPPORTED and "cannot be read" in conn.log[-1]
    for uuid in (ftms.INDOOR_BIKE_DATA, ftms.TRAINING_STATUS):
        (sub,) = dircon.split_messages(bytearray(conn.feed(dircon.encode(dircon.MSG_ENABLE_NOTIFICATIONS, 4,
                                                                         dircon.uuid128(uuid) + b"\x01"))))
        assert sub.code == dircon.RESP_SUCCESS
    (status,) = dircon.split_messages(bytearray(conn.feed(dircon.encode(dircon.MSG_READ, 5,
                                                                        dircon.uuid128(ftms.TRAINING_STATUS)))))
    assert status.code == dircon.RESP_SUCCESS and status.data[16:] == bytes([0x00, ftms.TS_IDLE])
