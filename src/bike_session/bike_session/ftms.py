"""Fitness Machine Service (Bluetooth FTMS 1.0, service 0x1826) of an indoor bike: the bytes
a training app reads, writes and is notified of, and what its control requests mean for
this bike's Commands. No transport and no ROS here (bike_session.dircon carries it over
TCP, bike_session.ftms_node joins it to the graph).

Characteristics served (values little endian, as in BLE):

- Fitness Machine Feature 0x2ACC (read): 32-bit machine features (cadence, total distance,
  resistance level, heart rate, elapsed time, power) and 32-bit target-setting features (inclination,
  resistance, power, indoor bike simulation, spin down, targeted cadence).
- Indoor Bike Data 0x2AD2 (notify only: FTMS 1.0.1, 4 Table 4.1 lists Notify as its one
  property and excludes every other; trainers serve it so): speed 0.01 km/h, cadence 0.5 rpm, total distance m
  (uint24), resistance level (whole levels: this field has no decimal, unlike the Control
  Point's and the range's 0.1), power W, heart rate uint8 bpm (only while the PlantState has
  one: the simulated rider's, or a strap's on a CAN bike), elapsed time s.
- Training Status 0x2AD3 (read, notify; FTMS 4.10: flags uint8, status uint8, an optional
  UTF-8 string): idle before the ride, after a Reset (4.16.2.2 asks for it) and while stopped;
  watt control in ERG, heart rate control holding a heart rate, manual mode (quick start) in
  resistance and slope (a free ride, the app's grade or level); other, named by the string, in
  the modes FTMS has no status for; post-workout once the session is done. From the app's
  target in force, else the session's Command (:meth:`FtmsControl.training_status`); notified
  when it changes.
- Supported Inclination / Resistance Level / Power Range 0x2AD5 / 0x2AD6 / 0x2AD8 (read):
  the bike's Command ranges (bike_session.profiles.ModeUnits), so an app never has to guess.
- Supported Heart Rate Range 0x2AD7 (read; uint8 min, max, increment bpm): only on a bike with
  a heart rate, which alone claims the heart-rate target (FTMS 1.0, 3: mandatory with that
  target-setting feature, excluded without it).
- Fitness Machine Control Point 0x2AD9 (write; its response [0x80, op, result] is notified,
  BLE's indication) and Fitness Machine Status 0x2ADA (notify).

The Cycling Power Service 0x1818 is served beside it (Cycling Power Measurement 0x2A63 with
crank revolution data, Feature 0x2A65, Sensor Location 0x2A5D), as trainers do.

What a control request does (:class:`FtmsControl`):

| op | request | Command (mode, value) |
|---|---|---|
| 0x00 | Request Control | (none; needed before any other op, else result 5; one app at a time) |
| 0x01 | Reset | resistance 0 (brake released), control given up |
| 0x03 | Target Inclination, sint16 0.1 % | slope, grade mapped onto [grade_min, grade_max] |
| 0x04 | Target Resistance Level, uint8 or sint16, 0.1 | resistance, level / 100 (see :meth:`FtmsControl._resistance`) |
| 0x05 | Target Power, sint16 W | erg, P / erg_power_max_w |
| 0x06 | Target Heart Rate, uint8 bpm | erg holding that heart rate (Command.heart_rate_bpm: the power follows it), from the ERG power in force (else from the rider's); only on a bike with a heart rate (a rider) |
| 0x07 / 0x08 | Start or Resume / Stop or Pause | the target before the stop again / resistance 0 |
| 0x11 | Indoor Bike Simulation: wind 0.001 m/s, grade 0.01 %, Crr 1e-4, Cw 0.01 kg/m | slope at the grade, on the app's road |
| 0x13 | Spin Down Control, uint8 1 start / 2 ignore | spindown (brake released; the response carries the target speeds low / high, uint16 0.01 km/h; Status 0x14 then says stop pedalling, success or error as the controller's procedure goes) |
| 0x14 | Set Targeted Cadence, uint16 0.5 rpm | the rider's cadence target (Command.cadence_rpm): the target in force again with it, and every later one; 0: none |

Control belongs to the app that requested it (FTMS 1.0, 4.16.2.1), a ``client`` of
:meth:`FtmsControl.write` (its DIRCON connection): another app's Request Control, and any other
op from an app without it, get result 5 (control not permitted) until that app resets or
disconnects (:meth:`FtmsControl.release`); the targets it set stay in force.

A target outside the advertised range is refused with result 3 (invalid parameter) and a
message, except the simulation grade: apps send the road's grade as it comes, so a grade
beyond the bike's range is ridden at the range's end, and said (the message names both).
The simulation's wind, Crr and Cw become the Command's road (bike_msgs/Command
``road_from_command``: the slope mode's road load uses them in place of the config's modes.crr,
cda_m2 and wind_mps; Cw is rho CdA, the drag 1/2 Cw v^2, as FTMS and FE-C have it), said
once per change; all three zero, as apps that send only the grade do, keeps the config's road,
and that is said. Ops this bike does not do (target speed, wheel circumference, ...) get
result 2 (not supported), and so does a heart-rate target on a bike without a heart rate (no
rider: a prime mover or a dynamometer).
"""
from __future__ import annotations

import dataclasses
import math
import struct

from bike_plant.heart import HEART_RATE_TARGET_MAX_BPM, HEART_RATE_TARGET_MIN_BPM, heart_rate_target_problem
from bike_plant.mechanics import rider_cadence_problem
from bike_session.profiles import MODE_NAMES, MODES, ModeUnits

# 16-bit UUIDs (Bluetooth SIG assigned numbers)
FTMS_SERVICE = 0x1826
FEATURE = 0x2ACC
INDOOR_BIKE_DATA = 0x2AD2
TRAINING_STATUS = 0x2AD3
INCLINATION_RANGE = 0x2AD5
RESISTANCE_RANGE = 0x2AD6
HEART_RATE_RANGE = 0x2AD7
POWER_RANGE = 0x2AD8
CONTROL_POINT = 0x2AD9
STATUS = 0x2ADA

# Control Point op codes
OP_REQUEST_CONTROL = 0x00
OP_RESET = 0x01
OP_TARGET_SPEED = 0x02
OP_TARGET_INCLINATION = 0x03
OP_TARGET_RESISTANCE = 0x04
OP_TARGET_POWER = 0x05
OP_TARGET_HEART_RATE = 0x06
OP_START_RESUME = 0x07
OP_STOP_PAUSE = 0x08
OP_SIMULATION = 0x11
OP_SPIN_DOWN = 0x13
OP_TARGETED_CADENCE = 0x14
OP_RESPONSE = 0x80

# Control Point result codes
RESULT_SUCCESS = 0x01
RESULT_NOT_SUPPORTED = 0x02
RESULT_INVALID_PARAMETER = 0x03
RESULT_FAILED = 0x04
RESULT_NOT_PERMITTED = 0x05

# Fitness Machine Status op codes
STATUS_RESET = 0x01
STATUS_STOPPED_PAUSED = 0x02
STATUS_STARTED_RESUMED = 0x04
STATUS_INCLINE_CHANGED = 0x06
STATUS_RESISTANCE_CHANGED = 0x07
STATUS_POWER_CHANGED = 0x08
STATUS_HEART_RATE_CHANGED = 0x09
STATUS_SIMULATION_CHANGED = 0x12
STATUS_SPIN_DOWN = 0x14           # + uint8: SPIN_DOWN_*
SPIN_DOWN_REQUESTED, SPIN_DOWN_SUCCESS, SPIN_DOWN_ERROR, SPIN_DOWN_STOP_PEDALLING = 1, 2, 3, 4
SPIN_DOWN_NAMES = {1: "spin down requested (speed up)", 2: "spin down success", 3: "spin down error",
                   4: "stop pedalling"}
STATUS_CADENCE_CHANGED = 0x15
STATUS_CONTROL_LOST = 0xFF

OP_NAMES = {0x00: "request control", 0x01: "reset", 0x02: "target speed", 0x03: "target inclination",
            0x04: "target resistance level", 0x05: "target power", 0x06: "target heart rate",
            0x07: "start or resume", 0x08: "stop or pause", 0x09: "targeted expended energy",
            0x0A: "targeted number of steps", 0x0B: "targeted number of strides", 0x0C: "targeted distance",
            0x0D: "targeted training time", 0x0E: "targeted time in two heart rate zones",
            0x0F: "targeted time in three heart rate zones", 0x10: "targeted time in five heart rate zones",
            0x11: "indoor bike simulation parameters", 0x12: "wheel circumference", 0x13: "spin down control",
            0x14: "targeted cadence"}

# Feature bits (FTMS 1.0, 4.3.1.1 / 4.3.1.2)
MACHINE_CADENCE = 1 << 1
MACHINE_TOTAL_DISTANCE = 1 << 2
MACHINE_RESISTANCE_LEVEL = 1 << 7
MACHINE_HEART_RATE = 1 << 10
MACHINE_ELAPSED_TIME = 1 << 12
MACHINE_POWER = 1 << 14
TARGET_INCLINATION = 1 << 1
TARGET_RESISTANCE = 1 << 2
TARGET_POWER = 1 << 3
TARGET_HEART_RATE = 1 << 4
TARGET_SIMULATION = 1 << 13
TARGET_SPIN_DOWN = 1 << 15
TARGET_CADENCE = 1 << 16

# Indoor Bike Data flags: bit 0 clear = instantaneous speed present
IBD_CADENCE = 1 << 2
IBD_DISTANCE = 1 << 4
IBD_RESISTANCE = 1 << 5
IBD_POWER = 1 << 6
IBD_HEART_RATE = 1 << 9
IBD_ELAPSED = 1 << 11
IBD_FLAGS = IBD_CADENCE | IBD_DISTANCE | IBD_RESISTANCE | IBD_POWER | IBD_ELAPSED    # always present

RESISTANCE_LEVEL_MAX = 100.0    # levels 0..100 (0.1 steps) = resistance Command 0..1
RESISTANCE_UINT8_MAX = 25.5     # the most the spec's uint8 in 0.1 steps carries (Control Point 0x04)

# Training Status values (FTMS 1.0, 4.10.1.2, Table 4.13); the ones this bike says
TS_OTHER = 0x00
TS_IDLE = 0x01
TS_HEART_RATE_CONTROL = 0x07
TS_WATT_CONTROL = 0x0C
TS_MANUAL_MODE = 0x0D
TS_POST_WORKOUT = 0x0F
TRAINING_STATUS_NAMES = {0x00: "other", 0x01: "idle", 0x02: "warming up", 0x03: "low intensity interval",
                         0x04: "high intensity interval", 0x05: "recovery interval", 0x06: "isometric",
                         0x07: "heart rate control", 0x08: "fitness test",
                         0x09: "speed outside of control region - low", 0x0A: "speed outside of control region - high",
                         0x0B: "cool down", 0x0C: "watt control", 0x0D: "manual mode (quick start)",
                         0x0E: "pre-workout", 0x0F: "post-workout"}
TS_FLAG_STRING = 1 << 0         # Training Status flags bit 0: the string is present (Table 4.12)

# the session's state (bike_msgs/SessionStatus STATE_*; no ROS here)
SESSION_WAITING, SESSION_RUNNING, SESSION_DONE = 0, 1, 2


def encode_feature(heart_rate: bool = False) -> bytes:
    """The machine and target-setting features; ``heart_rate``: the bike has one (a rider), so it
    sends it in Indoor Bike Data and takes a heart-rate target."""
    machine = (MACHINE_CADENCE | MACHINE_TOTAL_DISTANCE | MACHINE_RESISTANCE_LEVEL | MACHINE_ELAPSED_TIME
               | MACHINE_POWER | (MACHINE_HEART_RATE if heart_rate else 0))
    target = (TARGET_INCLINATION | TARGET_RESISTANCE | TARGET_POWER | TARGET_SIMULATION | TARGET_SPIN_DOWN
              | TARGET_CADENCE | (TARGET_HEART_RATE if heart_rate else 0))
    return struct.pack("<II", machine, target)


def encode_training_status(status: int, text: str = "") -> bytes:
    """Training Status (0x2AD3, FTMS 1.0, 4.10, Table 4.11): flags uint8, status uint8, then the
    Training Status String (UTF-8) when ``text`` is given (flags bit 0). The strings here are a
    mode's name, far below the MTU, so the Extended String bit (1) is never needed."""
    raw = text.encode("utf-8")
    return bytes([TS_FLAG_STRING if raw else 0, status]) + raw


def decode_training_status(data: bytes) -> tuple[int, str]:
    """(status, string or "") of a Training Status value; ValueError when it is shorter than its
    two octets."""
    if len(data) < 2:
        raise ValueError(f"Training Status of {len(data)} bytes (at least 2): {bytes(data).hex()}")
    text = bytes(data[2:]).decode("utf-8", "replace") if data[0] & TS_FLAG_STRING else ""
    return data[1], text


def training_status_text(data: bytes) -> str:
    """A Training Status value as a line says it, e.g. "watt control" or "other (spindown)"."""
    status, text = decode_training_status(data)
    name = TRAINING_STATUS_NAMES.get(status, f"status 0x{status:02x}")
    return f"{name} ({text})" if text else name


def _fit(value: float, lo: int, hi: int) -> int:
    """A telemetry value in its field's integer range (the field's ends: a bike at 0 km/h
    backwards, or past 16777 km, shows the end, as any trainer's display would)."""
    if not math.isfinite(value):
        return 0
    return int(min(max(round(value), lo), hi))


def encode_indoor_bike_data(*, speed_kmh: float, cadence_rpm: float, distance_m: float, resistance_level: float,
                            power_w: float, elapsed_s: float, heart_rate_bpm: float = 0.0) -> bytes:
    """Indoor Bike Data (0x2AD2) with every field this bike measures; the heart rate only when
    there is one (> 0), in the spec's place after the power (and the energy fields this bike
    does not send), before the elapsed time."""
    heart_bpm = _fit(heart_rate_bpm, 0, 0xFF)
    flags = IBD_FLAGS | (IBD_HEART_RATE if heart_bpm > 0 else 0)
    distance = _fit(distance_m, 0, 0xFFFFFF)
    return (struct.pack("<HHH", flags, _fit(speed_kmh * 100, 0, 0xFFFF), _fit(cadence_rpm * 2, 0, 0xFFFF))
            + distance.to_bytes(3, "little")
            + struct.pack("<hh", _fit(resistance_level, -32768, 32767), _fit(power_w, -32768, 32767))
            + (bytes([heart_bpm]) if heart_bpm > 0 else b"")
            + struct.pack("<H", _fit(elapsed_s, 0, 0xFFFF)))


# Indoor Bike Data fields in their order: (flag bit, name, struct code, steps per unit); bit 0 is
# "more data", the instantaneous speed being present when it is clear. A field is its raw value /
# steps, so that 2781 reads 27.81 km/h, not 27.810000000000002 (raw * 0.01), in a --csv file
_IBD_FIELDS = ((1, "average_speed_kmh", "H", 100), (2, "cadence_rpm", "H", 2),
               (3, "average_cadence_rpm", "H", 2), (4, "distance_m", "u24", 1),
               (5, "resistance_level", "h", 1), (6, "power_w", "h", 1), (7, "average_power_w", "h", 1),
               (8, "energy_kcal", "HHB", 1), (9, "heart_rate_bpm", "B", 1), (10, "metabolic_equivalent", "B", 10),
               (11, "elapsed_s", "H", 1), (12, "remaining_s", "H", 1))


def parse_indoor_bike_data(data: bytes) -> dict:
    """Every field any trainer's Indoor Bike Data carries, by its flags (FTMS 4.9); the
    expended energy as its total kcal. ValueError: shorter than its flags say."""
    try:
        (flags,) = struct.unpack_from("<H", data)
        out, pos = {}, 2
        if not flags & 1:
            out["speed_kmh"] = struct.unpack_from("<H", data, pos)[0] / 100
            pos += 2
        for bit, name, code, steps in _IBD_FIELDS:
            if not flags & (1 << bit):
                continue
            if code == "u24":
                if pos + 3 > len(data):
                    raise struct.error("short")
                out[name], pos = int.from_bytes(data[pos:pos + 3], "little"), pos + 3
                continue
            values = struct.unpack_from("<" + code, data, pos)
            pos += struct.calcsize("<" + code)
            out[name] = values[0] / steps if steps != 1 else values[0]
    except struct.error:
        raise ValueError(f"Indoor Bike Data shorter than its flags say: {bytes(data).hex()}") from None
    return out


@dataclasses.dataclass(frozen=True)
class IndoorBikeData:
    speed_kmh: float
    cadence_rpm: float
    distance_m: int
    resistance_level: float
    power_w: int
    elapsed_s: int
    heart_rate_bpm: int = 0          # 0: not in the data


def decode_indoor_bike_data(data: bytes) -> IndoorBikeData:
    """The fields :func:`encode_indoor_bike_data` writes (an app's view; ValueError otherwise)."""
    flags = struct.unpack_from("<H", data)[0] if len(data) >= 2 else None
    if (flags, len(data)) not in ((IBD_FLAGS, 15), (IBD_FLAGS | IBD_HEART_RATE, 16)):
        raise ValueError(f"not this bike's Indoor Bike Data: {bytes(data).hex()}")
    f = parse_indoor_bike_data(data)
    return IndoorBikeData(round(f["speed_kmh"], 2), f["cadence_rpm"], f["distance_m"], f["resistance_level"],
                          f["power_w"], f["elapsed_s"], int(f.get("heart_rate_bpm", 0)))


# ------------------------------------------------------------------ Cycling Power Service
# Served beside FTMS, as trainers do (a KICKR announces both): several apps take power and
# cadence from a "power meter" they pair on its own, and derive cadence from crank events.
CPS_SERVICE = 0x1818
CPS_MEASUREMENT = 0x2A63       # notify: flags, power W, crank revolution data
CPS_FEATURE = 0x2A65           # read: uint32 feature bits
SENSOR_LOCATION = 0x2A5D       # read: uint8
CPS_FEATURE_CRANK_DATA = 1 << 3
CPS_FLAG_CRANK_DATA = 1 << 5
SENSOR_LOCATION_OTHER = 0      # a trainer's power is measured at its own brake, not on the bike


def encode_cps_feature() -> bytes:
    return struct.pack("<I", CPS_FEATURE_CRANK_DATA)


def encode_cps_measurement(power_w: float, crank_revs: int, crank_event_s: float) -> bytes:
    """Cycling Power Measurement: instantaneous power and the crank revolution data (cumulative
    revolutions, uint16, and the time of the last one in 1/1024 s, uint16; both wrap, as the
    spec has apps expect)."""
    return struct.pack("<HhHH", CPS_FLAG_CRANK_DATA, _fit(power_w, -32768, 32767), int(crank_revs) & 0xFFFF,
                       int(math.floor(crank_event_s * 1024.0)) & 0xFFFF if math.isfinite(crank_event_s) else 0)


def decode_cps_measurement(data: bytes) -> tuple[int, int, int]:
    """(power W, cumulative crank revolutions, last crank event in 1/1024 s) of this bike's
    measurement; ValueError otherwise."""
    if len(data) != 8 or struct.unpack_from("<H", data)[0] != CPS_FLAG_CRANK_DATA:
        raise ValueError(f"not this bike's Cycling Power Measurement: {bytes(data).hex()}")
    _, power, revs, event = struct.unpack("<HhHH", data)
    return power, revs, event


@dataclasses.dataclass(frozen=True)
class Target:
    """What the app asked for, as the session's live Command (bike_msgs/Command)."""

    mode: int
    command: float
    text: str          # for the log, e.g. "target power 150 W"
    road: tuple[float, float, float] | None = None    # (crr, cw_kg_m, wind_mps); None: the config's
    cadence_rpm: float = 0.0                          # the rider's cadence target; 0: none
    heart_rate_bpm: float = 0.0                       # ERG's heart-rate target; 0: none (hold the power)


@dataclasses.dataclass
class Reply:
    """The outcome of one Control Point write."""

    response: bytes                 # notified on the Control Point: [0x80, op, result]
    status: bytes | None = None     # notified on Fitness Machine Status
    target: Target | None = None    # a new Command for the session
    message: str | None = None      # a line for the log (refusals and clamps: a warning)
    warning: bool = False


class FtmsControl:
    """The Control Point of one bike: who has control and what it asked for."""

    def __init__(self, units: ModeUnits, heart_rate: bool = False):
        self.units = units
        self.heart_rate = heart_rate                  # the bike has a rider's heart rate to follow
        self.controlled = False
        self.controller = None                        # the client that has control (a DIRCON connection)
        self.running_target: Target | None = None    # the target a Stop keeps for a Resume
        self.stopped = False
        self.simulation_extra = None                  # (wind, crr, cw) last said
        self.cadence_rpm = 0.0                        # Set Targeted Cadence: rides with every target
        self.spindown_said: int | None = None         # the last spin-down status sent; None: none running
        self.spindown_tag = 0.0                       # the spindown Command's value: a new one per request
        # Training Status: the session's (state, mode, heart-rate target) and whether the app put
        # the bike at rest (Reset, Stop or Pause: idle whatever it rides), and the value last notified
        self.session: tuple[int, int | None, float] = (SESSION_WAITING, None, 0.0)
        self.at_rest = False
        self.training_said: bytes | None = None

    # ---- the read-only characteristics
    def encode_feature(self) -> bytes:
        return encode_feature(self.heart_rate)

    def encode_power_range(self) -> bytes:
        # sint16 W: a bike stronger than 32767 W (a config's erg_power_max_w) shows the field's end
        return struct.pack("<hhH", 0, _fit(math.floor(self.units.erg_power_max_w), 0, 0x7FFF), 1)

    def encode_inclination_range(self) -> bytes:
        return struct.pack("<hhH", math.ceil(self.units.grade_min * 1000 - 1e-9),
                           math.floor(self.units.grade_max * 1000 + 1e-9), 1)

    def encode_resistance_range(self) -> bytes:
        return struct.pack("<hhH", 0, int(RESISTANCE_LEVEL_MAX * 10), 1)

    # ---- Training Status (FTMS 1.0, 4.10)
    def follow_session(self, state: int, mode: int, heart_rate_bpm: float) -> None:
        """The session's progress (SessionStatus: its state, the Command in force's mode and ERG
        heart-rate target), which the Training Status follows when no app target is in force."""
        self.session = (int(state), int(mode), float(heart_rate_bpm))

    def training_status(self) -> tuple[int, str]:
        """(Training Status value, string) now (Table 4.13): post-workout once the session is
        done; idle before it runs and while the app has the bike at rest (a Reset sets Idle,
        4.16.2.2; a Stop or Pause releases the brake); else by the mode of the app's target in
        force, or the session's Command when the app set none: ERG is watt control, or heart
        rate control with a heart-rate target; resistance and slope are manual mode (quick
        start: the rider rides the level or the road, no program holds a figure); the modes
        FTMS has no value for (isokinetic, motoring, spindown) are other, named by the string."""
        state, mode, heart_rate_bpm = self.session
        if state == SESSION_DONE:
            return TS_POST_WORKOUT, ""
        if state != SESSION_RUNNING or self.at_rest:
            return TS_IDLE, ""
        target = self.running_target
        if target is not None:
            mode, heart_rate_bpm = target.mode, target.heart_rate_bpm
        if mode == MODES["erg"]:
            return (TS_HEART_RATE_CONTROL if heart_rate_bpm > 0 else TS_WATT_CONTROL), ""
        if mode in (MODES["resistance"], MODES["slope"]):
            return TS_MANUAL_MODE, ""
        return TS_OTHER, MODE_NAMES.get(mode, f"mode {mode}")

    def encode_training_status(self) -> bytes:
        """The Training Status characteristic's value now (what a read returns)."""
        return encode_training_status(*self.training_status())

    def training_status_change(self) -> bytes | None:
        """The Training Status value to notify when it differs from the one last notified (4.10.1:
        notified when a new training status is available), else None."""
        value = self.encode_training_status()
        if value == self.training_said:
            return None
        self.training_said = value
        return value

    def encode_heart_rate_range(self) -> bytes:
        """The heart-rate targets Set Target Heart Rate takes (bike_plant.heart), whole bpm."""
        return struct.pack("<BBB", math.ceil(HEART_RATE_TARGET_MIN_BPM), math.floor(HEART_RATE_TARGET_MAX_BPM), 1)

    # ---- the Control Point
    def release(self, client) -> str | None:
        """``client`` is gone (its connection closed): the control it had is free again (FTMS
        1.0, 4.16.2.1: it lasts as long as the connection). A line for the log, None if it had none."""
        if not self.controlled or self.controller is not client:
            return None
        self.controlled, self.controller = False, None
        return "control released: the app that had it disconnected (its targets stay in force)"

    def write(self, data: bytes, client=None) -> Reply:
        """One Control Point write by ``client`` (who wrote it: its DIRCON connection; None for
        the one caller of a test)."""
        if not data:
            return Reply(bytes([OP_RESPONSE, 0, RESULT_INVALID_PARAMETER]), message="empty Control Point write",
                         warning=True)
        op, param = data[0], bytes(data[1:])
        name = OP_NAMES.get(op, f"op 0x{op:02x}")

        def result(code: int, message: str | None = None, *, warning: bool = True, **kw) -> Reply:
            return Reply(bytes([OP_RESPONSE, op, code]), message=message, warning=warning, **kw)

        if op == OP_REQUEST_CONTROL:
            if self.controlled and self.controller is not client:
                return result(RESULT_NOT_PERMITTED, "request control refused: another app has control")
            self.controlled, self.controller = True, client
            return result(RESULT_SUCCESS, "control granted", warning=False)
        if op not in OP_NAMES:
            return result(RESULT_NOT_SUPPORTED, f"unknown Control Point op 0x{op:02x} ({len(param)} parameter bytes)")
        if not self.controlled:
            return result(RESULT_NOT_PERMITTED, f"{name} before Request Control: refused")
        if self.controller is not client:
            return result(RESULT_NOT_PERMITTED, f"{name} refused: another app has control")
        handler = {OP_RESET: self._reset, OP_TARGET_INCLINATION: self._inclination,
                   OP_TARGET_RESISTANCE: self._resistance, OP_TARGET_POWER: self._power,
                   OP_TARGET_HEART_RATE: self._heart_rate,
                   OP_START_RESUME: self._start, OP_STOP_PAUSE: self._stop, OP_SIMULATION: self._simulation,
                   OP_TARGETED_CADENCE: self._cadence, OP_SPIN_DOWN: self._spin_down}.get(op)
        if handler is None:
            return result(RESULT_NOT_SUPPORTED, f"{name}: not supported by this bike")
        return handler(op, name, param)

    def _sized(self, op, name, param, sizes) -> Reply | None:
        if len(param) not in sizes:
            want = " or ".join(str(s) for s in sizes)
            return Reply(bytes([OP_RESPONSE, op, RESULT_INVALID_PARAMETER]), warning=True,
                         message=f"{name}: {len(param)} parameter bytes, expected {want}")
        return None

    def _set(self, op, target: Target, status: bytes, message: str | None = None, warning: bool = False) -> Reply:
        target = dataclasses.replace(target, cadence_rpm=self.cadence_rpm)
        self.running_target = target
        self.at_rest = self.stopped
        if self.stopped:          # a new target while stopped is kept for the Resume
            return Reply(bytes([OP_RESPONSE, op, RESULT_SUCCESS]), status=status, message=message or
                         f"{target.text} (kept: stopped until Start or Resume)", warning=warning)
        return Reply(bytes([OP_RESPONSE, op, RESULT_SUCCESS]), status=status, target=target,
                     message=message or target.text, warning=warning)

    def _refuse(self, op, message: str) -> Reply:
        return Reply(bytes([OP_RESPONSE, op, RESULT_INVALID_PARAMETER]), message=message, warning=True)

    def _ranged(self, op, name, param, mode: int, value: float, text: str, status_op: int) -> Reply:
        """A target in one of the bike's ranges (ModeUnits.to_command), or refused naming it."""
        try:
            command, _ = self.units.to_command(mode, value)
        except ValueError as exc:
            return self._refuse(op, f"{name} {text} refused: {exc}")
        return self._set(op, Target(mode, command, f"{name} {text}"), bytes([status_op]) + param)

    def _power(self, op, name, param) -> Reply:
        bad = self._sized(op, name, param, (2,))
        if bad:
            return bad
        (watts,) = struct.unpack("<h", param)
        return self._ranged(op, name, param, MODES["erg"], float(watts), f"{watts} W", STATUS_POWER_CHANGED)

    def _heart_rate(self, op, name, param) -> Reply:
        """ERG holding a heart rate: the power follows it (bike_controller.heart_erg), starting
        from the ERG power in force (else from the rider's own)."""
        if not self.heart_rate:
            return Reply(bytes([OP_RESPONSE, op, RESULT_NOT_SUPPORTED]), warning=True,
                         message=f"{name}: this bike has no rider's heart rate to follow")
        bad = self._sized(op, name, param, (1,))
        if bad:
            return bad
        bpm = param[0]
        problem = heart_rate_target_problem(float(bpm)) or ("0 bpm is no target" if bpm == 0 else None)
        if problem:
            return self._refuse(op, f"{name} {bpm} bpm refused: {problem}")
        running = self.running_target
        start = running.command if running is not None and running.mode == MODES["erg"] else 0.0
        return self._set(op, Target(MODES["erg"], start, f"{name} {bpm} bpm", heart_rate_bpm=float(bpm)),
                         bytes([STATUS_HEART_RATE_CHANGED, bpm]))

    def _inclination(self, op, name, param) -> Reply:
        bad = self._sized(op, name, param, (2,))
        if bad:
            return bad
        (tenths,) = struct.unpack("<h", param)
        return self._ranged(op, name, param, MODES["slope"], tenths / 10, f"{tenths / 10:g} %",
                            STATUS_INCLINE_CHANGED)

    def _resistance(self, op, name, param) -> Reply:
        """Set Target Resistance Level (FTMS 1.0, 4.16.2.5, Table 4.15): the spec's parameter is a
        uint8 in 0.1 steps, so it ends at 25.5, below this bike's 0..100 (the range 0x2AD6 is
        sint16 in 0.1); GoldenCheetah and QZ write a sint16 instead to reach it, and both are
        taken. Fitness Machine Status 0x07 echoes the new target in the width the app wrote: a
        uint8 as FTMS 1.0 gives that op code's parameter (Table 4.26; every uint8 level fits),
        a sint16 as FTMS 1.0.1 does. A level above 25.5 was echoed as 25.5 (min(tenths, 255)):
        the app was told another target than the one in force. Beyond 0..100: result 3."""
        bad = self._sized(op, name, param, (1, 2))
        if bad:
            return bad
        tenths = param[0] if len(param) == 1 else struct.unpack("<h", param)[0]
        level = tenths / 10
        if not 0.0 <= level <= RESISTANCE_LEVEL_MAX:
            return self._refuse(op, f"{name} {level:g} refused: outside [0, {RESISTANCE_LEVEL_MAX:g}]")
        # the app's own bytes: a uint8 stays one byte, a sint16 two (Status 0x07 of 1.0 / 1.0.1)
        return self._set(op, Target(MODES["resistance"], level / RESISTANCE_LEVEL_MAX,
                                    f"target resistance level {level:g}"),
                         bytes([STATUS_RESISTANCE_CHANGED]) + param)

    def _simulation(self, op, name, param) -> Reply:
        bad = self._sized(op, name, param, (6,))
        if bad:
            return bad
        wind_mm_s, grade_hundredths, crr, cw = struct.unpack("<hhBB", param)
        grade_pct = grade_hundredths / 100
        lo, hi = 100 * self.units.grade_min, 100 * self.units.grade_max
        ridden = min(max(grade_pct, lo), hi)
        notes = []
        if ridden != grade_pct:
            notes.append(f"grade {grade_pct:g} % is beyond this bike's [{lo:g}, {hi:g}] %: ridden at {ridden:g} %")
        extra = (wind_mm_s, crr, cw)
        road = None if extra == (0, 0, 0) else (crr / 1e4, cw / 100, wind_mm_s / 1000)
        if extra != self.simulation_extra:
            self.simulation_extra = extra
            notes.append("no wind, Crr or Cw given: the config's road (modes.*)" if road is None else
                         f"road: wind {road[2]:g} m/s, Crr {road[0]:g}, Cw {road[1]:g} kg/m")
        command, _ = self.units.to_command(MODES["slope"], ridden)
        target = Target(MODES["slope"], command, f"simulation grade {grade_pct:g} %", road)
        message = target.text + ("; " + "; ".join(notes) if notes else "")
        return self._set(op, target, bytes([STATUS_SIMULATION_CHANGED]) + param, message,
                         warning=ridden != grade_pct)

    def _cadence(self, op, name, param) -> Reply:
        """The rider's cadence target: with the target in force (sent again with it) and every
        later one; before any target it waits for the first."""
        bad = self._sized(op, name, param, (2,))
        if bad:
            return bad
        (halves,) = struct.unpack("<H", param)
        rpm = halves / 2
        problem = rider_cadence_problem(rpm)
        if problem:
            return self._refuse(op, f"{name} {rpm:g} rpm refused: {problem}")
        self.cadence_rpm = rpm
        status = bytes([STATUS_CADENCE_CHANGED]) + param
        text = f"{name} {rpm:g} rpm" if rpm else f"{name} cleared (the rider's own)"
        if self.running_target is None:
            return Reply(bytes([OP_RESPONSE, op, RESULT_SUCCESS]), status=status,
                         message=f"{text}: rides with the first target")
        return self._set(op, self.running_target, status, f"{text}, with {self.running_target.text}")

    def _spin_down(self, op, name, param) -> Reply:
        """Start (1): the spin-down procedure of the controller (Command mode spindown); the
        response carries the target speeds, the status says "speed up". Ignore (2): nothing."""
        bad = self._sized(op, name, param, (1,))
        if bad:
            return bad
        if param[0] == 2:
            return Reply(bytes([OP_RESPONSE, op, RESULT_SUCCESS]), message=f"{name}: ignore")
        if param[0] != 1:
            return self._refuse(op, f"{name}: parameter {param[0]} (1 start, 2 ignore)")
        low, high = self.units.spindown_kmh
        # the value tags the request: a retry while the last spin-down's Command is still in force
        # starts a new one (bike_controller.modes, SPINDOWN)
        self.spindown_tag = 1.0 - self.spindown_tag
        target = Target(MODES["spindown"], self.spindown_tag,
                        f"spin down: brake released; speed up past {high:.1f} km/h, then stop pedalling "
                        f"(coast to {low:.1f} km/h)")
        reply = self._set(op, target, bytes([STATUS_SPIN_DOWN, SPIN_DOWN_REQUESTED]))
        reply.response += struct.pack("<HH", _fit(low * 100, 0, 0xFFFF), _fit(high * 100, 0, 0xFFFF))
        self.spindown_said = SPIN_DOWN_REQUESTED
        return reply

    def spin_down_progress(self, mode: int, phase: float) -> list[bytes]:
        """The Fitness Machine Status notifications for the controller's spin-down
        (ControllerStatus: mode spindown, mode_target its phase, bike_controller.spindown):
        "stop pedalling" at the coast, then success or error; each once, and only after an app
        asked for it. A coast shorter than the notification period (the SPMSM bike's 0.4 s)
        still gets its "stop pedalling" before the success."""
        if self.spindown_said is None or mode != MODES["spindown"]:
            return []
        value = {2: SPIN_DOWN_STOP_PEDALLING, 3: SPIN_DOWN_SUCCESS, 4: SPIN_DOWN_ERROR}.get(int(phase))
        if value is None or value == self.spindown_said:
            return []
        out = []
        if value == SPIN_DOWN_SUCCESS and self.spindown_said != SPIN_DOWN_STOP_PEDALLING:
            out.append(bytes([STATUS_SPIN_DOWN, SPIN_DOWN_STOP_PEDALLING]))
        self.spindown_said = None if value in (SPIN_DOWN_SUCCESS, SPIN_DOWN_ERROR) else value
        return out + [bytes([STATUS_SPIN_DOWN, value])]

    def _reset(self, op, name, param) -> Reply:
        self.controlled, self.controller = False, None
        self.cadence_rpm = 0.0
        self.stopped = False
        self.running_target = None
        self.at_rest = True             # Training Status Idle (FTMS 1.0, 4.16.2.2) until a new target
        target = Target(MODES["resistance"], 0.0, "reset: brake released, control given up")
        return Reply(bytes([OP_RESPONSE, op, RESULT_SUCCESS]), status=bytes([STATUS_RESET]), target=target,
                     message=target.text)

    def _stop(self, op, name, param) -> Reply:
        bad = self._sized(op, name, param, (1,))
        if bad:
            return bad
        if param[0] not in (1, 2):
            return self._refuse(op, f"{name}: parameter {param[0]} (1 stop, 2 pause)")
        self.stopped = self.at_rest = True
        word = "stop" if param[0] == 1 else "pause"
        return Reply(bytes([OP_RESPONSE, op, RESULT_SUCCESS]), status=bytes([STATUS_STOPPED_PAUSED, param[0]]),
                     target=Target(MODES["resistance"], 0.0, f"{word}: brake released"),
                     message=f"{word}: brake released")

    def _start(self, op, name, param) -> Reply:
        self.stopped = self.at_rest = False
        target = self.running_target
        return Reply(bytes([OP_RESPONSE, op, RESULT_SUCCESS]), status=bytes([STATUS_STARTED_RESUMED]),
                     target=target, message="start or resume" + (f": {target.text}" if target else ""))
