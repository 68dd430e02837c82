"""Drive protocols on CAN: a host-side interface, ODrive CANSimple (firmware 0.6.x) and VESC.

No ROS imports: the plant node's ``backend: can`` drives these objects, and so can a
script or a test.

Layers
------
* :class:`DbcCodec` -- bus-free encode / classify over a DBC with node 0's frame ids; a
  protocol subclass says how a node's id is formed. :class:`OdriveCanSimpleCodec` and
  :class:`VescCanCodec` are the two.
* :class:`OdriveCanSimpleCodec` -- bus-free codec over the DBC file next to this module
  (``odrive_cansimple_0_6.dbc``, read with cantools). It turns signal dicts into
  ``can.Message`` frames and classifies received frames: a frame is either decoded, or
  rejected with a *reason* (see :data:`MALFORMED_REASONS` / :data:`IGNORED_REASONS`).
  Both the host side (:class:`OdriveCanSimple`) and the drive emulator
  (:mod:`bike_controller.drive_emulator`) use it, so both ends speak the same layout.
* :class:`DriveProtocol` -- the abstract host side of "a drive on CAN": setpoints and
  requests out, protocol-neutral :class:`Measurement` objects in, counters, link
  supervision (heartbeat) and watchdog feeding. CANopen CiA 402 can be added as a
  further subclass without touching the node.
* :class:`OdriveCanSimple` -- the ODrive implementation.
* :class:`VescCan` -- VESC (CAN mode VESC, vedderb/bldc documentation/comm_can.md) over
  ``vesc_can.dbc``: 29-bit ids ``command_id << 8 | vesc_id``, big-endian payloads; no
  heartbeat, arming or requests (the STATUS broadcasts are the sign of life; commands feed
  the VESC's command timeout). Decode a log of any VESC ID with
  ``python -m cantools decode --frame-id-mask 0x1FFFFF00 vesc_can.dbc``.

Frame ids and the DBC
---------------------
An ODrive CANSimple id is 11 bits: ``node_id << 5 | cmd_id``. A DBC file has fixed ids,
so the shipped DBC describes node 0 (ids = cmd ids) and the codec adds ``node_id << 5``.
Users decode their own candump logs of any node with the id mask of cantools::

    candump can0 | python -m cantools decode --frame-id-mask 0x1F odrive_cansimple_0_6.dbc

or write a DBC for their node for tools without a mask (SavvyCAN, BusMaster, ...)::

    python -m bike_plant.can.protocol --export-dbc 3 odrive_node3.dbc

Decoding never raises
---------------------
Everything received goes through :meth:`DriveProtocol.receive`, which counts and drops
what it cannot use: error frames, FD or extended-id frames, other nodes' frames, unknown
command ids, wrong DLC, NaN/inf, values outside the DBC's [min|max] plausibility range,
remote frames where none is expected, and anything cantools or the bus raises.

Sources: payload layouts from odriverobotics/ros_odrive ``odrive_base/include/
can_simple_messages.hpp`` (generated from ODrive's 0.6 DBC definitions); enums incl.
``ODRIVE_ERROR_WATCHDOG_TIMER_EXPIRED = 0x01000000`` from ``odrive_base/include/
odrive_enums.h`` of the same repository; RTR requests and cyclic messages from the
ODrive CAN protocol documentation. See /work/shared/research/can-and-bags.md section 1.
"""
from __future__ import annotations

import abc
import collections
import dataclasses
import enum
import math
import pathlib
import time
from typing import Callable, Collection, Iterable, Mapping

import can
import cantools

DBC_PATH = pathlib.Path(__file__).with_name("odrive_cansimple_0_6.dbc")

RPM_PER_REV_S = 60.0

CMD_ID_BITS = 5
CMD_ID_MASK = (1 << CMD_ID_BITS) - 1     # 0x1F
NODE_ID_MAX = 0x3F                       # 6 bits of an 11-bit id
#: ODrive 0.6.x reserves node id 0x3F: it is the broadcast address (every ODrive acts on it) and the
#: id of an unaddressed drive, so a host must not command it (odriverobotics/ODriveResources
#: examples/can_enumerate.py: BROADCAST_NODE_ID = 0x3f, MAX_NODE_ID = 0x3e)
ODRIVE_BROADCAST_NODE_ID = 0x3F
ODRIVE_NODE_ID_MAX = ODRIVE_BROADCAST_NODE_ID - 1
STANDARD_ID_MAX = 0x7FF


# ---------------------------------------------------------------------------------------
# ODrive 0.6.x enums (odriverobotics/ros_odrive odrive_base/include/odrive_enums.h)
class AxisState(enum.IntEnum):
    UNDEFINED = 0
    IDLE = 1
    STARTUP_SEQUENCE = 2
    FULL_CALIBRATION_SEQUENCE = 3
    MOTOR_CALIBRATION = 4
    ENCODER_INDEX_SEARCH = 6
    ENCODER_OFFSET_CALIBRATION = 7
    CLOSED_LOOP_CONTROL = 8
    LOCKIN_SPIN = 9
    ENCODER_DIR_FIND = 10
    HOMING = 11
    ENCODER_HALL_POLARITY_CALIBRATION = 12
    ENCODER_HALL_PHASE_CALIBRATION = 13
    ANTICOGGING_CALIBRATION = 14


class ControlMode(enum.IntEnum):
    VOLTAGE_CONTROL = 0
    TORQUE_CONTROL = 1
    VELOCITY_CONTROL = 2
    POSITION_CONTROL = 3


class InputMode(enum.IntEnum):
    INACTIVE = 0
    PASSTHROUGH = 1
    VEL_RAMP = 2
    POS_FILTER = 3
    MIX_CHANNELS = 4
    TRAP_TRAJ = 5
    TORQUE_RAMP = 6
    MIRROR = 7
    TUNING = 8


class ProcedureResult(enum.IntEnum):
    SUCCESS = 0
    BUSY = 1
    CANCELLED = 2
    DISARMED = 3
    NO_RESPONSE = 4
    POLE_PAIR_CPR_MISMATCH = 5
    PHASE_RESISTANCE_OUT_OF_RANGE = 6
    PHASE_INDUCTANCE_OUT_OF_RANGE = 7
    UNBALANCED_PHASES = 8
    INVALID_MOTOR_TYPE = 9
    ILLEGAL_HALL_STATE = 10
    TIMEOUT = 11
    HOMING_WITHOUT_ENDSTOP = 12
    INVALID_STATE = 13
    NOT_CALIBRATED = 14
    NOT_CONVERGING = 15


class ODriveError(enum.IntFlag):
    """ODrive.Error (0.6.x): the Heartbeat's Axis_Error and Get_Error's fields."""
    NONE = 0
    INITIALIZING = 0x00000001
    SYSTEM_LEVEL = 0x00000002
    TIMING_ERROR = 0x00000004
    MISSING_ESTIMATE = 0x00000008
    BAD_CONFIG = 0x00000010
    DRV_FAULT = 0x00000020
    MISSING_INPUT = 0x00000040
    DC_BUS_OVER_VOLTAGE = 0x00000100
    DC_BUS_UNDER_VOLTAGE = 0x00000200
    DC_BUS_OVER_CURRENT = 0x00000400
    DC_BUS_OVER_REGEN_CURRENT = 0x00000800
    CURRENT_LIMIT_VIOLATION = 0x00001000
    MOTOR_OVER_TEMP = 0x00002000
    INVERTER_OVER_TEMP = 0x00004000
    VELOCITY_LIMIT_VIOLATION = 0x00008000
    POSITION_LIMIT_VIOLATION = 0x00010000
    WATCHDOG_TIMER_EXPIRED = 0x01000000
    ESTOP_REQUESTED = 0x02000000
    SPINOUT_DETECTED = 0x04000000
    BRAKE_RESISTOR_DISARMED = 0x08000000
    THERMISTOR_DISCONNECTED = 0x10000000
    CALIBRATION_ERROR = 0x40000000


def error_names(bits: int) -> list[str]:
    """Names of the ODriveError flags set in ``bits`` (unknown bits as hex)."""
    names = [flag.name for flag in ODriveError if flag.value and bits & flag.value]
    rest = bits & ~sum(flag.value for flag in ODriveError)
    if rest:
        names.append(f"0x{rest:08x}")
    return names


# ---------------------------------------------------------------------------------------
# message roles
HOST_TO_DRIVE = frozenset({"Set_Axis_State", "Set_Controller_Mode", "Set_Input_Vel", "Set_Input_Torque",
                           "Set_Limits", "Clear_Errors"})
DRIVE_TO_HOST = frozenset({"Heartbeat", "Get_Error", "Get_Encoder_Estimates", "Get_Iq",
                           "Get_Bus_Voltage_Current", "Get_Torques", "Get_Powers"})
#: Messages a host may request with an RTR frame (0.6.x answers any Get_* / Heartbeat).
REQUESTABLE = DRIVE_TO_HOST
#: Host messages that feed the drive's watchdog (ODriveResources examples/can_watchdog.py).
WATCHDOG_FEEDING = frozenset({"Set_Axis_State", "Set_Input_Vel", "Set_Input_Torque"})
#: Shortest payload a receiver accepts. Senders commonly pack only the used bytes
#: (ODrive's own python-can example sends Set_Axis_State as struct.pack('<I', 8)); 0.5.x
#: sent Clear_Errors empty. Everything else must be the full DBC length.
MIN_DLC = {"Set_Axis_State": 4, "Set_Input_Torque": 4, "Clear_Errors": 0}

#: Protocol-neutral measurement kinds and value names (what DriveProtocol users see).
MEASUREMENT_OF: dict[str, tuple[str, dict[str, str]]] = {
    "Heartbeat": ("status", {"Axis_Error": "axis_error", "Axis_State": "axis_state",
                             "Procedure_Result": "procedure_result", "Trajectory_Done_Flag": "trajectory_done"}),
    "Get_Error": ("errors", {"Active_Errors": "active_errors", "Disarm_Reason": "disarm_reason"}),
    "Get_Encoder_Estimates": ("motion", {"Pos_Estimate": "position_rev", "Vel_Estimate": "speed_rev_s"}),
    "Get_Iq": ("current", {"Iq_Setpoint": "iq_setpoint_a", "Iq_Measured": "iq_measured_a"}),
    "Get_Bus_Voltage_Current": ("bus", {"Bus_Voltage": "bus_voltage_v", "Bus_Current": "bus_current_a"}),
    "Get_Torques": ("torque", {"Torque_Target": "torque_target_nm", "Torque_Estimate": "torque_estimate_nm"}),
    "Get_Powers": ("power", {"Electrical_Power": "electrical_power_w", "Mechanical_Power": "mechanical_power_w"}),
}
MEASUREMENT_KINDS = tuple(kind for kind, _ in MEASUREMENT_OF.values())
MESSAGE_OF_KIND = {kind: name for name, (kind, _) in MEASUREMENT_OF.items()}

#: Reasons a received frame is dropped because it is broken or not allowed here.
MALFORMED_REASONS = ("error_frame", "fd_frame", "extended_id", "unknown_id", "unknown_cmd", "bad_dlc",
                     "non_finite", "out_of_range", "unexpected_rtr", "decode_error", "bus_error", "standard_id")
#: Reasons a received frame is ignored although nothing is wrong with it.
IGNORED_REASONS = ("other_node", "other_direction", "echo", "unused_message")

#: CANSimple 0.6.x messages that are valid on the bus but not used here (cmd id -> name): a drive
#: sends Get_Temperature / Get_Version cyclically when its temperature_msg_rate_ms / version_msg_rate_ms
#: are set (ros_odrive's /odrive_status needs temperature), other hosts send the rest. Ignored, not
#: malformed. Sources: odriverobotics/ros_odrive odrive_base/include/can_simple_messages.hpp (generated
#: from the 0.6 DBC) and the message table of docs.odriverobotics.com/v/latest/manual/can-protocol.html
#: (RxSdo 0x04, TxSdo 0x05).
#: Estop (no payload): the drive latches ESTOP_REQUESTED and drops to IDLE. Never sent by this
#: plant, which never clears it either (can.backend); the drive emulator acts on it.
ESTOP_CMD = 0x02
ODRIVE_UNUSED_MESSAGES = {0x00: "Get_Version", ESTOP_CMD: "Estop", 0x04: "RxSdo", 0x05: "TxSdo", 0x06: "Address",
                          0x0C: "Set_Input_Pos", 0x11: "Set_Traj_Vel_Limit", 0x12: "Set_Traj_Accel_Limits",
                          0x13: "Set_Traj_Inertia", 0x15: "Get_Temperature", 0x16: "Reboot",
                          0x19: "Set_Absolute_Position", 0x1A: "Set_Pos_Gain", 0x1B: "Set_Vel_Gains",
                          0x1F: "Enter_DFU_Mode"}


@dataclasses.dataclass(frozen=True)
class Measurement:
    """One decoded drive -> host message in protocol-neutral names.

    kind: one of MEASUREMENT_KINDS ('status', 'errors', 'motion', 'current', 'bus',
    'torque', 'power'); values: e.g. {'speed_rev_s': 46.7, 'position_rev': 12.3};
    received_s: host clock (time.monotonic by default) when it was decoded;
    bus_timestamp_s: the frame's timestamp from the bus driver (clock of the driver);
    message: the protocol's own message name (e.g. 'Get_Encoder_Estimates').
    """
    kind: str
    values: Mapping[str, float | int]
    received_s: float
    bus_timestamp_s: float
    message: str


@dataclasses.dataclass(frozen=True)
class Decoded:
    """A classified frame: signals of ``name`` (DBC names), or an RTR request for it."""
    name: str
    signals: Mapping[str, float | int]
    is_request: bool = False


# ---------------------------------------------------------------------------------------
# DBC helpers
def load_database(node_id: int = 0, dbc_path: str | pathlib.Path | None = None, protocol: str | None = None):
    """The cantools database of the DBC with the frame ids of ``node_id`` (node 0 = the file);
    ``protocol``: a key of :data:`CODECS` (default ODrive CANSimple)."""
    codec = CODECS[protocol or DEFAULT_PROTOCOL](node_id, dbc_path)
    if node_id:
        ids = {m.name: codec.arbitration_id(m.name) for m in codec.db.messages}
        for message in codec.db.messages:
            message.frame_id = ids[message.name]
        codec.db.refresh()
    return codec.db


def export_dbc(node_id: int, path: str | pathlib.Path, dbc_path: str | pathlib.Path | None = None,
               protocol: str | None = None) -> pathlib.Path:
    """Write a DBC with the ids of ``node_id`` (for CAN tools that cannot mask ids)."""
    codec_class = CODECS[protocol or DEFAULT_PROTOCOL]
    db = load_database(node_id, dbc_path, protocol)
    db.version = codec_class.dbc_version.format(node_id=node_id)
    text = db.as_dbc_string().replace(codec_class.dbc_node0_note, codec_class.dbc_node_note.format(node_id=node_id))
    out = pathlib.Path(path)
    out.write_text(text)
    return out


def _check_node_id(node_id: int, node_id_max: int = NODE_ID_MAX, note: str = "") -> None:
    if isinstance(node_id, bool) or not isinstance(node_id, int) or not 0 <= node_id <= node_id_max:
        raise ValueError(f"node_id must be an integer in 0..{node_id_max}, got {node_id!r}{note}")


class _EchoFilter:
    """Recognises our own frames coming back (udp_multicast echoes every sender's frames).

    A frame we sent is remembered for ``horizon_s``; the first identical frame received
    within that time is taken as its echo. On buses that do not echo (SocketCAN, virtual)
    entries simply expire. Only frames this side would ignore anyway can collide with
    an echo entry (a side never acts on the frame kinds it sends), so a false match
    cannot swallow a command or a measurement.
    """

    def __init__(self, horizon_s: float = 1.0, max_entries: int = 20000):
        self.horizon_s = horizon_s
        self.max_entries = max_entries
        self._pending: dict[tuple, collections.deque] = {}
        self._count = 0

    @staticmethod
    def _key(msg: can.Message) -> tuple:
        return (msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, msg.is_error_frame, msg.is_fd,
                msg.dlc, bytes(msg.data))

    def sent(self, msg: can.Message, now_s: float) -> None:
        self._count += 1
        if self._count >= 256 or len(self._pending) > self.max_entries:
            self._purge(now_s)
        self._pending.setdefault(self._key(msg), collections.deque()).append(now_s)

    def is_echo(self, msg: can.Message, now_s: float) -> bool:
        times = self._pending.get(self._key(msg))
        while times:
            t = times.popleft()
            if now_s - t <= self.horizon_s:
                return True
        return False

    def _purge(self, now_s: float) -> None:
        self._count = 0
        limit = now_s - self.horizon_s
        for key in list(self._pending):
            times = self._pending[key]
            while times and times[0] < limit:
                times.popleft()
            if not times:
                del self._pending[key]


# ---------------------------------------------------------------------------------------
class DbcCodec:
    """Bus-free codec of one drive's messages over a DBC whose frame ids are those of node 0.

    Subclasses say how a node's frame id is formed (:meth:`compose_id` / :meth:`split_id`), which
    id format the protocol uses (``extended_id``), which messages each side sends and which
    the host may request by RTR. Encoding checks every signal against the DBC's [min|max];
    :meth:`classify` turns any frame python-can can construct into a :class:`Decoded` or the
    reason (MALFORMED_REASONS / IGNORED_REASONS) it is dropped, and never raises.
    """

    default_dbc: pathlib.Path = DBC_PATH
    extended_id = False
    id_max = STANDARD_ID_MAX
    node_id_max = NODE_ID_MAX
    cmd_max = CMD_ID_MASK
    host_to_drive: frozenset = frozenset()
    drive_to_host: frozenset = frozenset()
    requestable: frozenset = frozenset()
    min_dlc: Mapping[str, int] = {}
    #: command ids of the protocol's messages that are not in the DBC (valid, not used): "unused_message"
    unused_cmds: Collection[int] = frozenset()

    def __init__(self, node_id: int = 0, dbc_path: str | pathlib.Path | None = None):
        _check_node_id(node_id, self.node_id_max)
        self.node_id = node_id
        self.db = cantools.database.load_file(str(dbc_path or self.default_dbc))
        self.messages = {m.name: m for m in self.db.messages}
        missing = (self.host_to_drive | self.drive_to_host) - set(self.messages)
        if missing:
            raise ValueError(f"DBC lacks message(s) {', '.join(sorted(missing))}")
        self._by_cmd = {self.command_id_of(m.frame_id): m for m in self.db.messages}
        if any(cmd > self.cmd_max for cmd in self._by_cmd):
            raise ValueError(f"DBC frame ids must be node-0 ids (command ids 0..{self.cmd_max:#x})")
        self._signals = {m.name: [(s.name, s.is_float, s.minimum, s.maximum) for s in m.signals]
                         for m in self.db.messages}
        # integer signals whose physical value is the raw one (scale 1, offset 0): the value must be an
        # integer; scaled integer signals (VESC's x1000 current, ...) are rounded to their resolution
        self._unscaled_int = {(m.name, s.name) for m in self.db.messages for s in m.signals
                              if not s.is_float and s.scale == 1 and s.offset == 0}

    # ------------------------------------------------------------ id scheme (per protocol)
    def command_id_of(self, node0_frame_id: int) -> int:
        """The command id of a DBC frame id (the DBC holds node 0's ids)."""
        return node0_frame_id

    def compose_id(self, cmd: int) -> int:
        """This node's frame id of command ``cmd``."""
        raise NotImplementedError

    def split_id(self, arbitration_id: int) -> tuple[int, int]:
        """(node id, command id) of a frame id of this protocol's format."""
        raise NotImplementedError

    # ------------------------------------------------------------ encode
    def arbitration_id(self, name: str) -> int:
        """Frame id of message ``name`` for this node."""
        return self.compose_id(self.command_id_of(self.messages[name].frame_id))

    def message_name(self, arbitration_id) -> str | None:
        """The name of this node's message with id ``arbitration_id`` (None: another
        node's, or no message of the DBC); the inverse of :meth:`arbitration_id`."""
        if not isinstance(arbitration_id, int) or not 0 <= arbitration_id <= self.id_max:
            return None
        node, cmd = self.split_id(arbitration_id)
        if node != self.node_id:
            return None
        message = self._by_cmd.get(cmd)
        return message.name if message is not None else None

    def encode(self, name: str, signals: Mapping[str, float | int]) -> can.Message:
        """A data frame of ``name``; raises ValueError for missing, non-finite or out-of-range values."""
        message = self.messages[name]
        clean = {}
        for sig_name, is_float, lo, hi in self._signals[name]:
            if sig_name not in signals:
                raise ValueError(f"{name}: missing signal {sig_name}")
            value = signals[sig_name]
            if isinstance(value, bool):
                value = int(value)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"{name}.{sig_name} must be a finite number, got {value!r}")
            if (lo is not None and value < lo) or (hi is not None and value > hi):
                raise ValueError(f"{name}.{sig_name} = {value!r} is outside [{lo}, {hi}]")
            if (name, sig_name) in self._unscaled_int:
                if float(value) != int(value):
                    raise ValueError(f"{name}.{sig_name} must be an integer, got {value!r}")
                value = int(value)
            clean[sig_name] = value
        data = message.encode(clean, scaling=True, padding=False, strict=True)
        return can.Message(arbitration_id=self.arbitration_id(name), data=data, is_extended_id=self.extended_id)

    def encode_request(self, name: str) -> can.Message:
        """An RTR frame requesting ``name`` (DLC = the message length, no data)."""
        if name not in self.requestable:
            raise ValueError(f"{name} cannot be requested; requestable: {', '.join(sorted(self.requestable))}")
        return can.Message(arbitration_id=self.arbitration_id(name), is_remote_frame=True,
                           dlc=self.messages[name].length, is_extended_id=self.extended_id)

    # ------------------------------------------------------------ decode
    def classify(self, msg: can.Message, receives: frozenset[str], answers_requests: bool) -> Decoded | str:
        """Decode ``msg`` for a side that receives ``receives`` messages.

        answers_requests: True for the drive side (RTR frames of requestable messages
        are requests), False for the host (RTR frames are other hosts' requests or our
        own echoes). Returns a :class:`Decoded` or the reason (a string) the frame is
        dropped. Never raises for a frame that python-can could construct.
        """
        if msg.is_error_frame:
            return "error_frame"
        if msg.is_fd:
            return "fd_frame"
        if bool(msg.is_extended_id) != self.extended_id:
            return "extended_id" if msg.is_extended_id else "standard_id"
        arb = msg.arbitration_id
        if not isinstance(arb, int) or arb < 0 or arb > self.id_max:
            return "unknown_id"
        node, cmd = self.split_id(arb)
        if node != self.node_id:
            return "other_node"
        message = self._by_cmd.get(cmd)
        if message is None:
            return "unused_message" if cmd in self.unused_cmds else "unknown_cmd"
        name = message.name
        if msg.is_remote_frame:
            if name in self.requestable:
                return Decoded(name, {}, is_request=True) if answers_requests else "other_direction"
            return "unexpected_rtr"
        if name not in receives:
            return "other_direction"
        data = bytes(msg.data)
        if msg.dlc != len(data) or len(data) < self.min_dlc.get(name, message.length) or len(data) > 8:
            return "bad_dlc"
        if len(data) < message.length:
            data = data + bytes(message.length - len(data))   # accepted short payload: zero-fill
        try:
            raw = message.decode(data[:message.length], decode_choices=False, scaling=True)
        except Exception:  # noqa: BLE001 -- the decode path must not raise
            return "decode_error"
        for sig_name, is_float, lo, hi in self._signals[name]:
            value = raw[sig_name]
            if is_float and not math.isfinite(value):
                return "non_finite"
            if (lo is not None and value < lo) or (hi is not None and value > hi):
                return "out_of_range"
        return Decoded(name, raw)


class OdriveCanSimpleCodec(DbcCodec):
    """Bus-free ODrive CANSimple 0.6.x codec for one node over the DBC (node 0 ids + node_id << 5)."""

    # export_dbc: the version string and the DBC comment's note on the ids, for a node
    dbc_version = "bike_plant odrive-cansimple 0.6.x node{node_id}"
    dbc_node0_note = "Frame ids in this file are for NODE 0: on the bus"
    dbc_node_note = "Frame ids in this file are for NODE {node_id} (already shifted): on the bus"

    default_dbc = DBC_PATH
    host_to_drive = HOST_TO_DRIVE
    drive_to_host = DRIVE_TO_HOST
    requestable = REQUESTABLE
    min_dlc = MIN_DLC
    unused_cmds = ODRIVE_UNUSED_MESSAGES

    def compose_id(self, cmd: int) -> int:
        return (self.node_id << CMD_ID_BITS) | cmd

    def split_id(self, arbitration_id: int) -> tuple[int, int]:
        return arbitration_id >> CMD_ID_BITS, arbitration_id & CMD_ID_MASK


# ---------------------------------------------------------------------------------------
class DriveProtocol(abc.ABC):
    """Host side of one drive on a python-can bus (abstract).

    Out: setpoints (torque, velocity), mode changes, limits, error clearing and
    requests; each returns True if the frame was handed to the bus (a full TX queue
    or a closed bus counts ``tx_failed`` and returns False, it does not raise).
    Setpoint values that cannot be encoded (NaN, out of range) raise ValueError: that
    is a bug of the caller, not of the bus.

    In: :meth:`poll` / :meth:`receive` turn frames into :class:`Measurement` objects;
    :attr:`last` keeps the newest measurement of each kind; :attr:`counters` counts
    every frame by outcome (see MALFORMED_REASONS / IGNORED_REASONS; 'decoded',
    'rx_frames', 'tx_frames', 'tx_failed', 'rx:<message>', 'tx:<message>').

    Link and watchdog semantics (the same for every protocol):
    * the drive proves it is alive with a periodic status message; :meth:`link_alive`
      is False when none arrived for ``heartbeat_timeout_s`` (our rule, not the drive's);
    * the drive stops (safe state) when the host stops sending for the drive's own
      watchdog timeout; :meth:`keepalive` re-sends the last setpoint when nothing that
      feeds the watchdog went out for ``watchdog_feed_interval_s``. Mode changes are
      never repeated by keepalive, so a tripped drive stays disarmed until the host
      clears errors and enables it again.

    Not thread-safe: use one object from one thread (e.g. the node's timer callback);
    ``poll(0.0)`` never blocks.
    """

    protocol_name = "abstract"
    #: the message whose arrival proves the drive alive (measurement kind 'status')
    status_message = "status"
    #: False: the drive has no armed / idle state of its own (it runs whatever setpoint arrives
    #: while its command timeout is fed): :attr:`enabled` is True whenever its status arrives
    has_arming = True
    #: False: the drive sends everything cyclically (:meth:`request` sends nothing)
    can_request = True
    #: True: the constructor takes ``pole_pairs`` and ``torque_constant_nm_per_a`` (the drive
    #: speaks electrical rpm and amperes, not rev/s and N m)
    uses_motor_constants = False
    #: largest node id a host may command (the id scheme's largest, less a broadcast id)
    node_id_max = NODE_ID_MAX
    #: why ids above node_id_max are refused (appended to the error)
    node_id_note = ""
    #: the frames' codec (set by the subclass's constructor): its id format (``extended_id``),
    #: messages and which side sends which (``host_to_drive``)
    codec: DbcCodec

    @classmethod
    def node_id_problem(cls, node_id: int) -> str | None:
        """Why ``node_id`` is no id a host may command with this protocol, None when it is one
        (the plant's config check and the emulator's --node-id say it after the key's name)."""
        if 0 <= node_id <= cls.node_id_max:
            return None
        return f"must be in 0..{cls.node_id_max} for {cls.protocol_name}, got {node_id}{cls.node_id_note}"

    def __init__(self, bus: can.BusABC, node_id: int, *, heartbeat_timeout_s: float = 0.5,
                 watchdog_feed_interval_s: float = 0.1, clock: Callable[[], float] = time.monotonic,
                 filter_echo: bool = True):
        if not heartbeat_timeout_s > 0 or not watchdog_feed_interval_s > 0:
            raise ValueError("heartbeat_timeout_s and watchdog_feed_interval_s must be > 0")
        self.bus = bus
        self.node_id = node_id
        self.heartbeat_timeout_s = float(heartbeat_timeout_s)
        self.watchdog_feed_interval_s = float(watchdog_feed_interval_s)
        self.clock = clock
        self.counters: collections.Counter = collections.Counter()
        self.last: dict[str, Measurement] = {}
        self._echo = _EchoFilter() if filter_echo else None
        self._last_feed_s = -math.inf
        self._feed_frame: can.Message | None = None
        self._feed_name: str | None = None

    # ------------------------------------------------------------ protocol-neutral commands
    @abc.abstractmethod
    def enable(self, control: str = "torque") -> bool:
        """Enter closed-loop control in 'torque' or 'velocity' control."""

    def select_control(self, control: str = "torque") -> bool:
        """Put a drive that is already in closed-loop control into 'torque' or 'velocity'
        control (its mode is not known: someone else armed it). Protocols without a separate
        mode command re-enable."""
        return self.enable(control)

    @abc.abstractmethod
    def disable(self) -> bool:
        """Put the drive in its idle (no torque) state."""

    @abc.abstractmethod
    def set_torque(self, torque_nm: float) -> bool:
        """Torque setpoint at the motor shaft [N m]; feeds the watchdog."""

    @abc.abstractmethod
    def set_velocity(self, speed_rev_s: float, torque_ff_nm: float = 0.0) -> bool:
        """Velocity setpoint at the motor shaft [rev/s]; feeds the watchdog."""

    @abc.abstractmethod
    def set_limits(self, velocity_limit_rev_s: float, current_limit_a: float) -> bool:
        """Velocity and current limits of the drive."""

    @abc.abstractmethod
    def clear_errors(self) -> bool:
        """Clear the drive's latched errors (does not re-enable it)."""

    @abc.abstractmethod
    def request(self, what: str) -> bool:
        """Ask the drive to send measurement kind ``what`` (or a protocol message name) now."""

    @abc.abstractmethod
    def decode(self, msg: can.Message, now_s: float) -> list[Measurement] | str:
        """Measurements in ``msg`` or the reason it is dropped; may raise (receive() guards)."""

    @property
    def max_torque_nm(self) -> float:
        """Largest |torque setpoint| the protocol can encode (inf: the drive limits it)."""
        return math.inf

    @property
    @abc.abstractmethod
    def active_errors(self) -> int:
        """Latest error bits reported by the drive (0 = none or unknown)."""

    @property
    @abc.abstractmethod
    def enabled(self) -> bool:
        """True if the latest status says closed-loop control."""

    # ------------------------------------------------------------ transmit
    def send(self, msg: can.Message, name: str, feeds_watchdog: bool = False, repeat: bool = False) -> bool:
        """Hand ``msg`` to the bus; count it; remember it for echo filtering and keepalive."""
        now = self.clock()
        if self._echo is not None:
            self._echo.sent(msg, now)
        try:
            self.bus.send(msg, timeout=0.01)
        except Exception:  # noqa: BLE001 -- a full queue or a closed bus must not kill the caller
            self.counters["tx_failed"] += 1
            return False
        self.counters["tx_frames"] += 1
        self.counters[f"tx:{name}"] += 1
        if feeds_watchdog:
            self._last_feed_s = now
            if repeat:
                self._feed_frame, self._feed_name = msg, name
        return True

    def keepalive(self, now_s: float | None = None) -> bool:
        """Re-send the last setpoint if the watchdog has not been fed for the feed interval."""
        now = self.clock() if now_s is None else now_s
        if self._feed_frame is None or now - self._last_feed_s < self.watchdog_feed_interval_s:
            return False
        frame = can.Message(arbitration_id=self._feed_frame.arbitration_id, data=bytes(self._feed_frame.data),
                            is_extended_id=self._feed_frame.is_extended_id)
        self.counters["keepalive"] += 1
        return self.send(frame, self._feed_name or "keepalive", feeds_watchdog=True, repeat=True)

    def forget_setpoint(self) -> None:
        """Stop keepalive repeating the last setpoint (e.g. after disable)."""
        self._feed_frame = None
        self._feed_name = None

    # ------------------------------------------------------------ receive
    def receive(self, msg: can.Message, now_s: float | None = None) -> list[Measurement]:
        """Decode one frame into measurements; counts and drops anything unusable. Never raises."""
        now = self.clock() if now_s is None else now_s
        self.counters["rx_frames"] += 1
        try:
            if self._echo is not None and self._echo.is_echo(msg, now):
                self.counters["echo"] += 1
                return []
            result = self.decode(msg, now)
        except Exception:  # noqa: BLE001 -- the decode path must not raise
            self.counters["decode_error"] += 1
            return []
        if isinstance(result, str):
            self.counters[result] += 1
            return []
        for m in result:
            self.last[m.kind] = m
        for name in dict.fromkeys(m.message for m in result):   # once per frame, also for several kinds
            self.counters[f"rx:{name}"] += 1
        self.counters["decoded"] += 1
        return result

    def poll(self, timeout_s: float = 0.0, max_frames: int = 1000) -> list[Measurement]:
        """Receive for up to ``timeout_s``: returns as soon as at least one measurement
        arrived (after draining what is already queued), or empty at the timeout."""
        deadline = self.clock() + max(0.0, timeout_s)
        out: list[Measurement] = []
        for _ in range(max_frames):
            wait = 0.0 if out else max(0.0, deadline - self.clock())
            try:
                msg = self.bus.recv(timeout=wait)
            except Exception:  # noqa: BLE001 -- e.g. udp_multicast cannot unpack a datagram
                self.counters["bus_error"] += 1
                break
            if msg is None:
                if out or self.clock() >= deadline:
                    break
                continue
            out.extend(self.receive(msg))
        return out

    # ------------------------------------------------------------ supervision
    def heartbeat_age_s(self, now_s: float | None = None) -> float:
        """Seconds since the last status message (inf if none yet)."""
        status = self.last.get("status")
        if status is None:
            return math.inf
        return (self.clock() if now_s is None else now_s) - status.received_s

    def link_alive(self, now_s: float | None = None) -> bool:
        return self.heartbeat_age_s(now_s) <= self.heartbeat_timeout_s

    def values(self, now_s: float | None = None) -> dict[str, float | int]:
        """Latest value of every measured quantity plus '<kind>_age_s' per kind."""
        now = self.clock() if now_s is None else now_s
        flat: dict[str, float | int] = {}
        for kind, m in self.last.items():
            flat.update(m.values)
            flat[f"{kind}_age_s"] = now - m.received_s
        return flat

    @property
    def dropped(self) -> int:
        """Frames dropped as malformed (sum over MALFORMED_REASONS)."""
        return sum(self.counters[r] for r in MALFORMED_REASONS)


# ---------------------------------------------------------------------------------------
class OdriveCanSimple(DriveProtocol):
    """ODrive CANSimple 0.6.x host side for the axis with ``node_id`` on ``bus``.

    Typical use from a node::

        drive = OdriveCanSimple(bus, node_id=0)
        drive.clear_errors(); drive.enable("torque")    # Set_Controller_Mode(1, 1) + Set_Axis_State(8)
        every batch: drive.set_input_torque(torque_nm); drive.poll(0.0)
                     state = drive.values(); ok = drive.link_alive() and drive.enabled
        on shutdown: drive.disable()

    All velocities are at the MOTOR shaft in rev/s (crank cadence = speed / gear ratio).
    """

    protocol_name = "odrive_cansimple_0.6"
    status_message = "Heartbeat"
    node_id_max = ODRIVE_NODE_ID_MAX
    node_id_note = (f" ({ODRIVE_BROADCAST_NODE_ID} = 0x{ODRIVE_BROADCAST_NODE_ID:X} is the ODrive broadcast id: "
                    "commands to it reach every ODrive on the bus)")

    def __init__(self, bus: can.BusABC, node_id: int = 0, *, heartbeat_timeout_s: float = 0.5,
                 watchdog_feed_interval_s: float = 0.1, dbc_path: str | pathlib.Path | None = None,
                 clock: Callable[[], float] = time.monotonic, filter_echo: bool = True):
        _check_node_id(node_id, self.node_id_max, self.node_id_note)
        super().__init__(bus, node_id, heartbeat_timeout_s=heartbeat_timeout_s,
                         watchdog_feed_interval_s=watchdog_feed_interval_s, clock=clock, filter_echo=filter_echo)
        self.codec = OdriveCanSimpleCodec(node_id, dbc_path)

    # ------------------------------------------------------------ ODrive messages
    def _send(self, name: str, signals: Mapping[str, float | int], repeat: bool = False) -> bool:
        msg = self.codec.encode(name, signals)
        return self.send(msg, name, feeds_watchdog=name in WATCHDOG_FEEDING, repeat=repeat)

    def set_axis_state(self, state: int) -> bool:
        """Set_Axis_State (0x07): 1 IDLE, 8 CLOSED_LOOP_CONTROL, ... (feeds the watchdog)."""
        if int(state) == AxisState.IDLE:
            self.forget_setpoint()
        return self._send("Set_Axis_State", {"Axis_Requested_State": int(state)})

    def set_controller_mode(self, control_mode: int, input_mode: int = InputMode.PASSTHROUGH) -> bool:
        """Set_Controller_Mode (0x0B): control 1 torque / 2 velocity; input 1 passthrough."""
        return self._send("Set_Controller_Mode", {"Control_Mode": int(control_mode), "Input_Mode": int(input_mode)})

    def set_input_torque(self, torque_nm: float) -> bool:
        """Set_Input_Torque (0x0E) [N m at the motor]; feeds the watchdog; repeated by keepalive."""
        return self._send("Set_Input_Torque", {"Input_Torque": torque_nm}, repeat=True)

    def set_input_vel(self, speed_rev_s: float, torque_ff_nm: float = 0.0) -> bool:
        """Set_Input_Vel (0x0D) [rev/s at the motor, N m feed-forward]; feeds the watchdog."""
        return self._send("Set_Input_Vel", {"Input_Vel": speed_rev_s, "Input_Torque_FF": torque_ff_nm}, repeat=True)

    def set_limits(self, velocity_limit_rev_s: float, current_limit_a: float) -> bool:
        """Set_Limits (0x0F): velocity limit [rev/s], current limit [A]."""
        return self._send("Set_Limits", {"Velocity_Limit": velocity_limit_rev_s, "Current_Limit": current_limit_a})

    def clear_errors(self, identify: bool = False) -> bool:
        """Clear_Errors (0x18); identify=True also blinks the drive's LED."""
        return self._send("Clear_Errors", {"Identify": 1 if identify else 0})

    def request(self, what: str) -> bool:
        """RTR request of a measurement kind ('motion', 'current', 'bus', 'torque', 'power',
        'status', 'errors') or a message name ('Get_Iq', ...)."""
        name = MESSAGE_OF_KIND.get(what, what)
        return self.send(self.codec.encode_request(name), f"request:{name}")

    # ------------------------------------------------------------ neutral interface
    def enable(self, control: str = "torque") -> bool:
        ok = self.select_control(control)
        return self.set_axis_state(AxisState.CLOSED_LOOP_CONTROL) and ok

    def select_control(self, control: str = "torque") -> bool:
        """Set_Controller_Mode (torque or velocity control, passthrough input) only: an ODrive
        switches modes in closed loop without disarming."""
        modes = {"torque": ControlMode.TORQUE_CONTROL, "velocity": ControlMode.VELOCITY_CONTROL}
        if control not in modes:
            raise ValueError(f"control must be 'torque' or 'velocity', got {control!r}")
        return self.set_controller_mode(modes[control], InputMode.PASSTHROUGH)

    def disable(self) -> bool:
        return self.set_axis_state(AxisState.IDLE)

    def set_torque(self, torque_nm: float) -> bool:
        return self.set_input_torque(torque_nm)

    def set_velocity(self, speed_rev_s: float, torque_ff_nm: float = 0.0) -> bool:
        return self.set_input_vel(speed_rev_s, torque_ff_nm)

    def decode(self, msg: can.Message, now_s: float) -> list[Measurement] | str:
        result = self.codec.classify(msg, DRIVE_TO_HOST, answers_requests=False)
        if isinstance(result, str):
            return result
        kind, names = MEASUREMENT_OF[result.name]
        values = {names[k]: v for k, v in result.signals.items()}
        if kind == "status":
            values["trajectory_done"] = bool(values["trajectory_done"])
        stamp = msg.timestamp if isinstance(msg.timestamp, (int, float)) else 0.0
        return [Measurement(kind, values, now_s, float(stamp), result.name)]

    @property
    def active_errors(self) -> int:
        status = self.last.get("status")
        return int(status.values["axis_error"]) if status else 0

    @property
    def axis_state(self) -> int:
        """Latest Heartbeat axis state (0 UNDEFINED if none yet)."""
        status = self.last.get("status")
        return int(status.values["axis_state"]) if status else int(AxisState.UNDEFINED)

    @property
    def enabled(self) -> bool:
        return self.axis_state == AxisState.CLOSED_LOOP_CONTROL


# ---------------------------------------------------------------------------------------
# VESC (vedderb/bldc documentation/comm_can.md, CAN mode "VESC")
VESC_DBC_PATH = pathlib.Path(__file__).with_name("vesc_can.dbc")
VESC_CMD_SHIFT = 8                       # id = command_id << 8 | vesc_id (29-bit extended)
VESC_ID_MASK = (1 << VESC_CMD_SHIFT) - 1
VESC_ID_MAX = 254                        # 255 is the VESC broadcast id: it would command every VESC on the bus
EXTENDED_ID_MAX = 0x1FFFFFFF
#: Tachometer counts per electrical revolution (firmware mc_interface_get_tachometer_value: motor
#: revolutions = tachometer / (3 x motor poles) = tachometer / (6 x pole pairs))
VESC_TACHO_PER_EREV = 6

VESC_HOST_TO_DRIVE = frozenset({"Set_Duty", "Set_Current", "Set_Current_Brake", "Set_Rpm", "Set_Pos",
                                "Set_Current_Rel"})
VESC_DRIVE_TO_HOST = frozenset({"Status", "Status_2", "Status_3", "Status_4", "Status_5"})
#: Every command resets the VESC's command timeout; STATUS_5's two reserved bytes are not required.
VESC_MIN_DLC = {"Status_5": 6}
#: Every id 0..68 is a VESC CAN packet (vedderb/bldc datatypes.h CAN_PACKET_ID: buffer forwarding 5-8 of
#: VESC Tool, PING / PONG 17 / 18, NOTIFY_BOOT 57, STATUS_6 58, BMS, IO board, GNSS ...): those not in
#: vesc_can.dbc are valid, not used here ("unused_message"), not malformed.
VESC_CAN_PACKET_ID_MAX = 68
VESC_UNUSED_MESSAGES = frozenset(range(VESC_CAN_PACKET_ID_MAX + 1))
#: Measurement kinds and neutral value names of the VESC status broadcasts. STATUS also yields
#: 'motion' (speed_rev_s), 'torque' (torque_estimate_nm = kt x motor current) and 'current'
#: (iq_measured_a = motor current), STATUS_5 also 'position' (position_rev from the tachometer).
VESC_MEASUREMENT_OF: dict[str, tuple[str, dict[str, str]]] = {
    "Status": ("status", {"Erpm": "erpm", "Current": "motor_current_a", "Duty_Cycle": "duty"}),
    "Status_2": ("charge", {"Amp_Hours": "charge_drawn_ah", "Amp_Hours_Charged": "charge_regenerated_ah"}),
    "Status_3": ("energy", {"Watt_Hours": "energy_drawn_wh", "Watt_Hours_Charged": "energy_regenerated_wh"}),
    "Status_4": ("input", {"Temp_Fet": "fet_temp_c", "Temp_Motor": "motor_temp_c", "Current_In": "bus_current_a",
                           "Pid_Pos": "pid_pos_deg"}),
    "Status_5": ("bus", {"Voltage_In": "bus_voltage_v", "Tachometer": "tachometer"}),
}


class VescCanCodec(DbcCodec):
    """Bus-free VESC CAN codec for one VESC ID over ``vesc_can.dbc`` (VESC ID 0 ids + vesc_id).

    29-bit extended ids ``command_id << 8 | vesc_id``; payloads big-endian signed integers
    with the scales of vedderb/bldc documentation/comm_can.md (e.g. SET_CURRENT 51 A to VESC
    23: id 0x0117, data 00 00 C7 38).
    """

    default_dbc = VESC_DBC_PATH
    dbc_version = "bike_plant vesc-can id{node_id}"
    dbc_node0_note = "the ids in this file are for VESC ID 0 (the command ids shifted by 8)"
    dbc_node_note = "the ids in this file are for VESC ID {node_id} (already added)"
    extended_id = True
    id_max = EXTENDED_ID_MAX
    node_id_max = VESC_ID_MAX
    cmd_max = EXTENDED_ID_MAX >> VESC_CMD_SHIFT
    host_to_drive = VESC_HOST_TO_DRIVE
    drive_to_host = VESC_DRIVE_TO_HOST
    min_dlc = VESC_MIN_DLC
    unused_cmds = VESC_UNUSED_MESSAGES     # (the DBC's own ids are matched first)

    def command_id_of(self, node0_frame_id: int) -> int:
        return node0_frame_id >> VESC_CMD_SHIFT

    def compose_id(self, cmd: int) -> int:
        return (cmd << VESC_CMD_SHIFT) | self.node_id

    def split_id(self, arbitration_id: int) -> tuple[int, int]:
        return arbitration_id & VESC_ID_MASK, arbitration_id >> VESC_CMD_SHIFT


class VescCan(DriveProtocol):
    """VESC host side (CAN mode VESC) for the controller with ``node_id`` (its VESC ID) on ``bus``.

    Source: vedderb/bldc documentation/comm_can.md. A VESC has no heartbeat, no axis state
    and no request / response: it broadcasts STATUS .. STATUS_5 at its CAN status rate and
    runs the last command until none arrived for its app timeout (1 s by default: vedderb/bldc
    appconf/appconf_default.h APPCONF_TIMEOUT_MSEC 1000), then releases the motor. So:

    * link alive = STATUS frames arriving (the 'status' measurement; ``heartbeat_timeout_s``);
    * :attr:`enabled` is True once a STATUS arrived (nothing to arm); :meth:`enable`,
      :meth:`clear_errors` send nothing; :meth:`disable` sends SET_CURRENT 0 (motor released);
    * :meth:`set_torque` sends SET_CURRENT = torque / kt (signed: negative brakes and
      regenerates), repeated by :meth:`keepalive` to feed the command timeout;
    * :meth:`set_velocity` sends SET_RPM in electrical rpm (motor rev/s x 60 x pole pairs);
    * measurements: speed = ERPM / pole pairs; position = tachometer / (6 x pole pairs)
      (1/12 rev steps for 2 pole pairs); torque_estimate_nm = kt x motor current (VESC's
      STATUS current is the motor current); bus voltage (STATUS_5), bus current (STATUS_4
      input current, positive = drawn from the battery, as ODrive's Bus_Current).
      Not reported: torque target, Iq setpoint, error bits (active_errors stays 0), power.
    """

    protocol_name = "vesc_can"
    status_message = "Status"
    has_arming = False
    can_request = False
    uses_motor_constants = True
    node_id_max = VESC_ID_MAX
    node_id_note = " (255 is the VESC broadcast id: commands to it reach every VESC on the bus)"

    def __init__(self, bus: can.BusABC, node_id: int = 0, *, pole_pairs: int, torque_constant_nm_per_a: float,
                 heartbeat_timeout_s: float = 0.5, watchdog_feed_interval_s: float = 0.1,
                 dbc_path: str | pathlib.Path | None = None, clock: Callable[[], float] = time.monotonic,
                 filter_echo: bool = True):
        if isinstance(pole_pairs, bool) or not isinstance(pole_pairs, int) or pole_pairs < 1:
            raise ValueError(f"pole_pairs must be an integer >= 1, got {pole_pairs!r}")
        kt = torque_constant_nm_per_a
        if isinstance(kt, bool) or not isinstance(kt, (int, float)) or not (math.isfinite(kt) and kt > 0):
            raise ValueError(f"torque_constant_nm_per_a must be a finite number > 0, got {kt!r}")
        super().__init__(bus, node_id, heartbeat_timeout_s=heartbeat_timeout_s,
                         watchdog_feed_interval_s=watchdog_feed_interval_s, clock=clock, filter_echo=filter_echo)
        self.codec = VescCanCodec(node_id, dbc_path)
        self.pole_pairs = pole_pairs
        self.torque_constant_nm_per_a = float(kt)

    def _send(self, name: str, signals: Mapping[str, float | int], repeat: bool = False) -> bool:
        msg = self.codec.encode(name, signals)
        return self.send(msg, name, feeds_watchdog=name in VESC_HOST_TO_DRIVE, repeat=repeat)

    def set_current(self, current_a: float) -> bool:
        """SET_CURRENT (1) [A, motor current, signed]; repeated by keepalive (command timeout)."""
        return self._send("Set_Current", {"Current": current_a}, repeat=True)

    def set_rpm(self, speed_erpm: float) -> bool:
        """SET_RPM (3) [electrical rpm]; repeated by keepalive."""
        return self._send("Set_Rpm", {"Erpm": round(speed_erpm)}, repeat=True)

    # ------------------------------------------------------------ neutral interface
    def enable(self, control: str = "torque") -> bool:
        """Nothing to send: a VESC runs whatever command arrives (no armed state)."""
        if control not in ("torque", "velocity"):
            raise ValueError(f"control must be 'torque' or 'velocity', got {control!r}")
        return True

    def disable(self) -> bool:
        """SET_CURRENT 0, not repeated: the VESC releases the motor (it coasts)."""
        self.forget_setpoint()
        return self._send("Set_Current", {"Current": 0.0})

    def set_torque(self, torque_nm: float) -> bool:
        return self.set_current(float(torque_nm) / self.torque_constant_nm_per_a)

    def set_velocity(self, speed_rev_s: float, torque_ff_nm: float = 0.0) -> bool:
        if torque_ff_nm:
            raise ValueError("VESC SET_RPM has no torque feed-forward; torque_ff_nm must be 0")
        return self.set_rpm(float(speed_rev_s) * RPM_PER_REV_S * self.pole_pairs)

    def set_limits(self, velocity_limit_rev_s: float, current_limit_a: float) -> bool:  # noqa: ARG002
        """Not sent: a VESC's limits are its motor configuration (VESC Tool). Counted, False."""
        self.counters["unsupported:set_limits"] += 1
        return False

    def clear_errors(self) -> bool:
        """Nothing to send: a VESC fault clears itself once its cause is gone."""
        return True

    def request(self, what: str) -> bool:  # noqa: ARG002
        """Not possible: a VESC only broadcasts. Counted, False."""
        self.counters["unsupported:request"] += 1
        return False

    def decode(self, msg: can.Message, now_s: float) -> list[Measurement] | str:
        result = self.codec.classify(msg, VESC_DRIVE_TO_HOST, answers_requests=False)
        if isinstance(result, str):
            return result
        kind, names = VESC_MEASUREMENT_OF[result.name]
        values = {names[k]: v for k, v in result.signals.items() if k in names}
        stamp = float(msg.timestamp) if isinstance(msg.timestamp, (int, float)) else 0.0
        out = [Measurement(kind, values, now_s, stamp, result.name)]
        if result.name == "Status":
            current_a = float(values["motor_current_a"])
            speed_rev_s = float(values["erpm"]) / self.pole_pairs / RPM_PER_REV_S
            out += [Measurement("motion", {"speed_rev_s": speed_rev_s}, now_s, stamp, result.name),
                    Measurement("torque", {"torque_estimate_nm": self.torque_constant_nm_per_a * current_a},
                                now_s, stamp, result.name),
                    Measurement("current", {"iq_measured_a": current_a}, now_s, stamp, result.name)]
        elif result.name == "Status_5":
            position_rev = float(values["tachometer"]) / (VESC_TACHO_PER_EREV * self.pole_pairs)
            out.append(Measurement("position", {"position_rev": position_rev}, now_s, stamp, result.name))
        return out

    @property
    def max_torque_nm(self) -> float:
        """kt x the largest current SET_CURRENT carries in the DBC (its plausibility range)."""
        return self.torque_constant_nm_per_a * self.codec.messages["Set_Current"].get_signal_by_name("Current").maximum

    @property
    def active_errors(self) -> int:
        """Always 0: the VESC status broadcasts carry no fault code."""
        return 0

    @property
    def enabled(self) -> bool:
        return "status" in self.last


#: Bus-free codecs by protocol name (export_dbc, load_database)
CODECS: dict[str, type[DbcCodec]] = {"odrive_cansimple_0.6": OdriveCanSimpleCodec, "vesc_can": VescCanCodec}
DEFAULT_PROTOCOL = "odrive_cansimple_0.6"

#: Host-side protocols by name (the ``can.protocol`` parameter of the plant's backend). A
#: second protocol (VESC, CANopen CiA 402) is a DriveProtocol subclass registered here.
PROTOCOLS: dict[str, type[DriveProtocol]] = {OdriveCanSimple.protocol_name: OdriveCanSimple,
                                              VescCan.protocol_name: VescCan}


def main(argv: Iterable[str] | None = None) -> int:
    """``python -m bike_plant.can.protocol [--protocol vesc_can] --export-dbc NODE_ID OUT.dbc``."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m bike_plant.can.protocol",
                                     description="ODrive CANSimple 0.6.x and VESC DBC tools")
    parser.add_argument("--export-dbc", nargs=2, metavar=("NODE_ID", "OUT"), required=True,
                        help="write a DBC whose frame ids are those of NODE_ID (ODrive: node_id << 5 | cmd_id; "
                             "VESC: cmd_id << 8 | vesc_id)")
    parser.add_argument("--protocol", choices=sorted(CODECS), default=DEFAULT_PROTOCOL,
                        help="the protocol's DBC (default odrive_cansimple_0.6)")
    args = parser.parse_args(list(argv) if argv is not None else None)
    try:
        node_id = int(args.export_dbc[0], 0)
        out = export_dbc(node_id, args.export_dbc[1], protocol=args.protocol)
    except (ValueError, OSError) as exc:
        parser.error(str(exc))
    print(out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
