"""Conversions between the physics/control dicts and arrays and the bike_msgs messages.

Shared by the plant node, the controller node and the session tools. Array fields are
filled from bytes (``array.array(code, ndarray.tobytes())``) and read back without a copy
(``numpy.frombuffer``) so that a batch of 200 periods costs microseconds, not a Python
loop per element. Field lists come from the message classes, so a field added to a .msg
is converted without touching this file.
"""
from __future__ import annotations

import array
import math
import struct

import numpy as np
from bike_msgs.msg import Command, ControllerStatus, DriveCommand, PlantState
from builtin_interfaces.msg import Time

from .cdr import CdrError as CdrError  # re-exported: the nodes catch it
from .cdr import Codec
from .heart import heart_rate_command_problem
from .mechanics import rider_cadence_problem, road_problem, virtual_gear_problem

GATE_LIMIT = 64          # 6 gate bits: values 0..63

_SEQ_CODES = {
    "sequence<float>": ("f", np.float32), "sequence<double>": ("d", np.float64),
    "sequence<uint8>": ("B", np.uint8), "sequence<int8>": ("b", np.int8),
    "sequence<uint16>": ("H", np.uint16), "sequence<int16>": ("h", np.int16),
    "sequence<uint32>": ("I", np.uint32), "sequence<int32>": ("i", np.int32),
    "sequence<uint64>": ("Q", np.uint64), "sequence<int64>": ("q", np.int64),
}
_SCALAR_INT = {"uint8", "int8", "uint16", "int16", "uint32", "int32", "uint64", "int64", "octet"}
_SCALAR_FLOAT = {"float", "double"}
_FIXED = {"double": np.float64, "float": np.float32, "uint8": np.uint8, "int32": np.int32,
          "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64}


# ---------------------------------------------------------------- time
def stamp_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def time_msg(ns: int) -> Time:
    ns = int(ns)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def seconds_to_ns(t: float) -> int:
    return int(round(float(t) * 1e9))


# ---------------------------------------------------------------- generic field conversion
def _setter(ftype: str):
    if ftype in _SEQ_CODES:
        code, dtype = _SEQ_CODES[ftype]

        def conv(v):
            if isinstance(v, array.array) and v.typecode == code:
                return v
            return array.array(code, np.ascontiguousarray(v, dtype=dtype).tobytes())
        return conv
    if ftype in _SCALAR_FLOAT:
        return float
    if ftype in _SCALAR_INT:
        return int
    if ftype == "boolean":
        return bool
    if ftype == "string":
        return str
    if "[" in ftype and ftype.endswith("]"):
        base = ftype.split("[", 1)[0]
        dtype = _FIXED.get(base)
        if dtype is not None:
            return lambda v: np.asarray(v, dtype=dtype)
    return None


def _getter(ftype: str):
    if ftype in _SEQ_CODES:
        dtype = _SEQ_CODES[ftype][1]
        return lambda v: np.frombuffer(v, dtype=dtype) if len(v) else np.zeros(0, dtype)
    if "[" in ftype and ftype.endswith("]"):
        return np.asarray
    return None


class _Converter:
    """dict <-> message for one message type (header handled separately)."""

    def __init__(self, cls):
        self.cls = cls
        fields = cls.get_fields_and_field_types()
        self.set = {}
        self.get = {}
        for name, ftype in fields.items():
            if name == "header":
                continue
            conv = _setter(ftype)
            if conv is not None:
                self.set[name] = conv
            self.get[name] = _getter(ftype)

    def to_msg(self, values: dict, stamp: int | None = None, frame_id: str = ""):
        msg = self.cls()
        setters = self.set
        for key, value in values.items():
            conv = setters.get(key)
            if conv is not None:
                setattr(msg, key, conv(value))
        if stamp is not None:
            msg.header.stamp = time_msg(stamp)
            msg.header.frame_id = frame_id
        return msg

    def to_dict(self, msg) -> dict:
        out = {}
        for key, conv in self.get.items():
            value = getattr(msg, key)
            out[key] = conv(value) if conv is not None else value
        return out


_PLANT = _Converter(PlantState)
_STATUS = _Converter(ControllerStatus)


def plant_state_msg(snapshot: dict, stamp: int, frame_id: str = "") -> PlantState:
    """BldcPlant.snapshot() dict (+ any overrides) -> PlantState, header.stamp = ``stamp`` [ns]."""
    return _PLANT.to_msg(snapshot, stamp, frame_id)


def snapshot_from_msg(msg: PlantState) -> dict:
    """PlantState -> the snapshot dict BatchController.decide() takes (arrays as numpy)."""
    return _PLANT.to_dict(msg)


# ---------------------------------------------------------------- the loop's hot path: bytes
# The plant and the controller publish and take PlantState / DriveCommand serialized
# (bike_plant.cdr): dict -> bytes and bytes -> dict without building message objects.
_PLANT_CDR = Codec(PlantState)
_DRIVE_CDR = Codec(DriveCommand)


class PlantStateView:
    """A PlantState taken as bytes: the fields the loop reads, and the snapshot dict."""

    __slots__ = ("seq", "end_of_run", "batch_periods", "stamp_ns", "snap")

    def __init__(self, raw) -> None:
        sec, nanosec, _, snap = _PLANT_CDR.decode(raw)
        self.seq = snap["seq"]
        self.end_of_run = snap["end_of_run"]
        self.batch_periods = snap["batch_periods"]
        self.stamp_ns = sec * 1_000_000_000 + nanosec
        self.snap = snap


class DriveCommandView:
    """A DriveCommand taken as bytes: every field as an attribute (arrays as numpy views),
    so the plant's checks and backends read it like the message; ``stamp_ns`` for the header."""

    def __init__(self, raw) -> None:
        sec, nanosec, _, fields = _DRIVE_CDR.decode(raw)
        self.__dict__.update(fields)
        self.stamp_ns = sec * 1_000_000_000 + nanosec


def plant_state_cdr(snapshot: dict, stamp: int, frame_id: str = "") -> bytes:
    """plant_state_msg(), serialized, without the message object (CdrError: a value that does
    not fit its field)."""
    sec, nanosec = divmod(int(stamp), 1_000_000_000)
    return _PLANT_CDR.encode(snapshot, sec, nanosec, frame_id)


_CLOCK_CDR = struct.Struct("<4siI")        # encapsulation (CDR little endian), sec, nanosec


def clock_cdr(stamp: int) -> bytes:
    """rosgraph_msgs/Clock at ``stamp`` [ns], serialized: the plant publishes one per batch,
    and the message object with rclpy's conversion cost half of that publish (~50 of ~100 us
    per batch measured in the N = 200 graph)."""
    sec, nanosec = divmod(int(stamp), 1_000_000_000)
    return _CLOCK_CDR.pack(b"\x00\x01\x00\x00", sec, nanosec)


def _drive_cdr(seq: int, arrays: dict, stamp: int, torque_cmd_nm: float, current_cmd_a: float,
               rider_cadence_rpm: float, rider_stops_pedalling: bool) -> bytes:
    sec, nanosec = divmod(int(stamp), 1_000_000_000)
    return _DRIVE_CDR.encode({"seq": int(seq), **arrays, "torque_cmd_nm": float(torque_cmd_nm),
                              "current_cmd_a": float(current_cmd_a), "rider_cadence_rpm": float(rider_cadence_rpm),
                              "rider_stops_pedalling": bool(rider_stops_pedalling)},
                             sec, nanosec)


def drive_command_cdr(seq: int, gates_a, gates_b, split, stamp: int, torque_cmd_nm: float = 0.0,
                      current_cmd_a: float = 0.0, rider_cadence_rpm: float = 0.0,
                      rider_stops_pedalling: bool = False) -> bytes:
    """drive_command_msg(), serialized."""
    return _drive_cdr(seq, {"gates_a": gates_a, "gates_b": gates_b, "split": split}, stamp, torque_cmd_nm,
                      current_cmd_a, rider_cadence_rpm, rider_stops_pedalling)


def spmsm_drive_cdr(seq: int, duties, relay, buck, stamp: int, torque_cmd_nm: float = 0.0,
                    current_cmd_a: float = 0.0, rider_cadence_rpm: float = 0.0,
                    rider_stops_pedalling: bool = False) -> bytes:
    """spmsm_drive_msg(), serialized."""
    return _drive_cdr(seq, {"duty_abc": duties, "relay_request": relay, "buck_duty": buck}, stamp, torque_cmd_nm,
                      current_cmd_a, rider_cadence_rpm, rider_stops_pedalling)


_STATUS_CDR = Codec(ControllerStatus)


def controller_status_cdr(status: dict, stamp: int) -> bytes:
    """controller_status_msg(), serialized; the values pass the same per-field conversions
    (int(), float(), str(), ...), keys that are not fields are ignored."""
    setters = _STATUS.set
    values = {key: setters[key](value) for key, value in status.items() if key in setters}
    sec, nanosec = divmod(int(stamp), 1_000_000_000)
    return _STATUS_CDR.encode(values, sec, nanosec)


def controller_status_msg(status: dict, stamp: int) -> ControllerStatus:
    return _STATUS.to_msg(status, stamp)


def controller_status_dict(msg: ControllerStatus) -> dict:
    return _STATUS.to_dict(msg)


# ---------------------------------------------------------------- drive commands
def drive_command_msg(seq: int, gates_a, gates_b, split, stamp: int,
                      torque_cmd_nm: float = 0.0, current_cmd_a: float = 0.0) -> DriveCommand:
    msg = DriveCommand()
    msg.header.stamp = time_msg(stamp)
    msg.seq = int(seq)
    msg.gates_a = array.array("B", np.ascontiguousarray(gates_a, dtype=np.uint8).tobytes())
    msg.gates_b = array.array("B", np.ascontiguousarray(gates_b, dtype=np.uint8).tobytes())
    msg.split = array.array("f", np.ascontiguousarray(split, dtype=np.float32).tobytes())
    msg.torque_cmd_nm = float(torque_cmd_nm)
    msg.current_cmd_a = float(current_cmd_a)
    return msg


def drive_arrays(msg: DriveCommand):
    """(gates_a uint8[N], gates_b uint8[N], split float64[N]) views of a DriveCommand (or a
    DriveCommandView)."""
    ga = np.frombuffer(msg.gates_a, dtype=np.uint8) if len(msg.gates_a) else np.zeros(0, np.uint8)
    gb = np.frombuffer(msg.gates_b, dtype=np.uint8) if len(msg.gates_b) else np.zeros(0, np.uint8)
    sp = np.frombuffer(msg.split, dtype=np.float32).astype(np.float64) if len(msg.split) else np.zeros(0)
    return ga, gb, sp


def spmsm_drive_msg(seq: int, duties, relay, buck, stamp: int, torque_cmd_nm: float = 0.0,
                    current_cmd_a: float = 0.0) -> DriveCommand:
    """SPMSM batch: duties (N x 3), relay requests (N), buck duties (N)."""
    msg = DriveCommand()
    msg.header.stamp = time_msg(stamp)
    msg.seq = int(seq)
    msg.duty_abc = array.array("f", np.ascontiguousarray(duties, dtype=np.float32).tobytes())
    msg.relay_request = array.array("f", np.ascontiguousarray(relay, dtype=np.float32).tobytes())
    msg.buck_duty = array.array("f", np.ascontiguousarray(buck, dtype=np.float32).tobytes())
    msg.torque_cmd_nm = float(torque_cmd_nm)
    msg.current_cmd_a = float(current_cmd_a)
    return msg


def _f64(v) -> np.ndarray:
    """A float32 sequence field as a new float64 array."""
    return np.frombuffer(v, dtype=np.float32).astype(np.float64) if len(v) else np.zeros(0)


def spmsm_drive_arrays(msg: DriveCommand):
    """(duties float64[N, 3], relay float64[N], buck float64[N]) of an SPMSM DriveCommand (new
    arrays: SpmsmPlant.step_batch(..., checked=True) may keep them)."""
    return _f64(msg.duty_abc).reshape(-1, 3), _f64(msg.relay_request), _f64(msg.buck_duty)


_unit_interval_check = None     # bike_plant.spmsm.unit_interval_check, imported at first use
_gate_split_check = None        # bike_plant.bldc.gate_split_check, the same


def spmsm_drive_problem(msg: DriveCommand, batch_periods: int) -> str | None:
    """Why an SPMSM DriveCommand cannot be applied (None: it can). Never raises. One compiled
    pass checks the arrays (the plant runs this on every batch); numpy words the problem."""
    global _unit_interval_check
    if _unit_interval_check is None:
        # numba: imported at first use and kept, as in drive_command_problem
        from .spmsm import unit_interval_check as _unit_interval_check
    try:
        n = int(batch_periods)
        duty_abc, relay_request, buck_duty = msg.duty_abc, msg.relay_request, msg.buck_duty
        if len(duty_abc) != 3 * n:
            return f"duty_abc has {len(duty_abc)} entries, 3 x batch_periods is {3 * n}"
        for name in ("relay_request", "buck_duty"):
            if len(getattr(msg, name)) != n:
                return f"{name} has {len(getattr(msg, name))} entries, batch_periods is {n}"
        if _unit_interval_check(np.frombuffer(duty_abc, np.float32), np.frombuffer(relay_request, np.float32),
                                np.frombuffer(buck_duty, np.float32)):
            return _drive_scalars_problem(msg)
        duties, relay, buck = spmsm_drive_arrays(msg)
        for name, a in (("duty_abc", duties), ("relay_request", relay), ("buck_duty", buck)):
            if a.size and not np.all(np.isfinite(a)):
                return f"{name} holds a non-finite value"
            if a.size and (float(a.min()) < 0.0 or float(a.max()) > 1.0):
                return f"{name} outside [0, 1] ({float(a.min())} .. {float(a.max())})"
        return _drive_scalars_problem(msg)
    except Exception as exc:  # a malformed message must never take the node down
        return f"unreadable DriveCommand ({exc})"


def _drive_scalars_problem(msg) -> str | None:
    """The scalar fields every DriveCommand carries (either machine's): finite setpoints and a
    rider's cadence target (bike_plant.mechanics.rider_cadence_problem)."""
    for name in ("torque_cmd_nm", "current_cmd_a"):
        if not math.isfinite(getattr(msg, name)):
            return f"{name} is not finite"
    problem = rider_cadence_problem(float(msg.rider_cadence_rpm))
    if problem is not None:
        return f"rider_cadence_rpm: {problem}"
    return None


def drive_command_problem(msg: DriveCommand, batch_periods: int) -> str | None:
    """Why a (BLDC) DriveCommand cannot be applied (None: it can). Never raises. One compiled
    pass checks the arrays (the plant runs this on every batch); numpy words the problem."""
    # the check is a numba kernel: imported at first use, so that the session and FTMS nodes
    # (which use this module's other conversions) never load numba, 0.4 s of CPU at the run's
    # start; kept (an import statement per batch cost a microsecond)
    global _gate_split_check
    if _gate_split_check is None:
        from .bldc import gate_split_check as _gate_split_check
    try:
        n = int(batch_periods)
        for name in ("gates_a", "gates_b", "split"):
            if len(getattr(msg, name)) != n:
                return f"{name} has {len(getattr(msg, name))} entries, batch_periods is {n}"
        ga = np.frombuffer(msg.gates_a, dtype=np.uint8) if n else np.zeros(0, np.uint8)
        gb = np.frombuffer(msg.gates_b, dtype=np.uint8) if n else np.zeros(0, np.uint8)
        sp = np.frombuffer(msg.split, dtype=np.float32) if n else np.zeros(0, np.float32)
        code = _gate_split_check(ga, gb, sp, GATE_LIMIT)
        if code == 1:
            return f"gates_a holds {int(ga.max())} (gate values must be < {GATE_LIMIT})"
        if code == 2:
            return f"gates_b holds {int(gb.max())} (gate values must be < {GATE_LIMIT})"
        if code == 3:
            return "split holds a non-finite value"
        if code == 4:
            return f"split outside [0, 1] ({float(sp.min())} .. {float(sp.max())})"
        return _drive_scalars_problem(msg)
    except Exception as exc:  # a malformed message must never take the node down
        return f"unreadable DriveCommand ({exc})"


# ---------------------------------------------------------------- user commands
def command_problem(msg: Command) -> str | None:
    """Why a Command is rejected (Eq. 5: finite, 0..1, a known mode); None if valid."""
    value = msg.command
    if not math.isfinite(value):
        return f"command {value!r} is not finite"
    if value < 0.0 or value > 1.0:
        return f"command {value!r} outside [0, 1]"
    if msg.mode not in (Command.MODE_RESISTANCE, Command.MODE_MOTORING, Command.MODE_ERG, Command.MODE_SLOPE,
                        Command.MODE_ISOKINETIC, Command.MODE_SPINDOWN):
        return f"unknown mode {msg.mode} (0 resistance, 1 motoring, 2 erg, 3 slope, 4 isokinetic, 5 spindown)"
    if msg.road_from_command:
        problem = road_problem(msg.crr, msg.cw_kg_m, msg.wind_mps)
        if problem is not None:
            return problem
    problem = rider_cadence_problem(msg.cadence_rpm) or heart_rate_command_problem(msg.heart_rate_bpm, msg.mode)
    if problem is not None:
        return problem
    return virtual_gear_problem(msg.virtual_gear_ratio)


def command_road(msg: Command) -> tuple[float, float, float] | None:
    """(crr, cw_kg_m, wind_mps) of a Command that gives its road, else None (the config's)."""
    return (float(msg.crr), float(msg.cw_kg_m), float(msg.wind_mps)) if msg.road_from_command else None


def set_command_road(msg: Command, road: tuple[float, float, float] | None) -> Command:
    """Put ``road`` ((crr, cw_kg_m, wind_mps) or None: the config's) into ``msg``."""
    msg.road_from_command = road is not None
    msg.crr, msg.cw_kg_m, msg.wind_mps = (float(x) for x in road) if road is not None else (0.0, 0.0, 0.0)
    return msg


def command_msg(value: float, mode: int = 0, stamp: int = 0, virtual_gear_ratio: float = 0.0,
                road: tuple[float, float, float] | None = None, cadence_rpm: float = 0.0) -> Command:
    msg = Command()
    msg.header.stamp = time_msg(stamp)
    msg.command = float(value)
    msg.mode = int(mode)
    msg.virtual_gear_ratio = float(virtual_gear_ratio)
    msg.cadence_rpm = float(cadence_rpm)
    return set_command_road(msg, road)
