"""The plant node's ``backend: can``: a real (or emulated) drive on a python-can bus.

No ROS imports: :class:`CanBackend` has the plant node's backend interface (``time_s``,
``snapshot()``, ``problem(msg, n)``, ``apply(msg)``, ``safe_batch(n)``, ``set_safe(on)``,
``measured_by_drive``) plus what a drive on a bus needs (``service()``, ``submit()``,
``time_frozen``, ``diagnostic()``, ``pop_events()``, ``close()``). A DriveCommand is any
object with ``torque_cmd_nm`` / ``current_cmd_a`` attributes, so tests and scripts can use
it without rclpy.

What it does
------------
* Opens the bus (``can.interface``: socketcan, virtual, udp_multicast, pcan, ... any
  python-can interface; ``channel``, ``bitrate``, ``port`` for udp_multicast) and speaks
  ODrive CANSimple 0.6.x through :class:`bike_plant.can.protocol.OdriveCanSimple`, or VESC
  (``protocol: vesc_can``, :class:`bike_plant.can.protocol.VescCan`): a drive without arming,
  whose STATUS broadcasts are its heartbeat; the torque setpoint goes out as SET_CURRENT =
  T / kt (``torque_constant_nm_per_a``, 0: the bldc section's kt); arming, take-over, RTR
  requests and Set_Limits do not apply (``request: []``, limits 0), so its only faults are
  FAULT_DRIVE_LOST and FAULT_DRIVE_STALE. The rest of this description is the ODrive's.
* Setpoints: the firmware of the drive owns the current loop, so per batch the
  controller's ``DriveCommand.torque_cmd_nm`` (N m at the motor shaft, motoring positive,
  the same sign as ODrive's torque) goes out as ``Set_Input_Torque``, clamped to
  ``torque_limit_nm``. It is sent the moment the DriveCommand arrives (:meth:`submit`,
  called from the node's subscription callback), not at the next batch tick, and repeated
  every ``watchdog_feed_s`` so the drive's watchdog stays fed. After the drive (re-)arms the
  setpoint ramps up from zero at ``arm_ramp_nm_per_s`` (no torque step for the rider).
  With a torque map (``torque_map_file``, :mod:`bike_plant.can.torque_map`) the controller's
  torque is the shaft's: ``torque_limit_nm`` clamps it, and the setpoint is the map's inverse
  at the drive's speed, within the setpoints the map was measured at.
* Measurements -> PlantState (``measured_by_drive`` true, no gate-level data):
  speed from Get_Encoder_Estimates (motor rev/s -> rad/s and rpm), rotor angle from the
  position (mechanical = 2 pi frac(pos), electrical = pole_pairs x that), torque_em_nm =
  Get_Torques' Torque_Estimate (motoring positive; through the torque map if one is given:
  the shaft's torque for that estimate at that speed), dc_bus_v = Bus_Voltage,
  battery_current_a = -Bus_Current (ODrive: positive = drawn from the bus; PlantState:
  charging positive). Messages that are not cyclic on the drive are requested by RTR every
  ``request_period_s`` (``request``: torque, bus, current; a kind that arrives cyclically
  on its own is not requested). phase_current_a is a reconstruction from Get_Iq
  (id = 0, Iq at the encoder's electrical angle: the amplitude is |Iq|, the phase is
  nominal because the drive's encoder offset is not on the bus); current_samples_a,
  Hall and timer fields stay empty / zero; battery_soc and battery_ocv_v are NaN (a drive
  does not know them).
* Energy ledger, integrated over the batches while sim time runs (J):
  battery = int V I_charge dt; stored = 1/2 J (w^2 - w0^2); mech_in = int (-T_em w + T_f(w) w)
  dt + stored, T_f = B w + Tc tanh(w / w_s) (bike_plant.mechanics.friction_torque_nm; J, B
  from ``mechanics`` of the config, Tc the SPMSM's ``spmsm.dry_friction_nm``: the bike's
  physics, not the laws' figures); loss = mech_in - battery - stored (copper, inverter and
  friction losses); resistor = 0 (not observable on CAN). The rider's work is not on the
  bus: mech_in is the host's figure from the drive's Torque_Estimate (kt Iq, or the torque
  map's shaft torque) and Vel_Estimate, not the physics' truth, so the report's trainer power
  error compares it with an estimate made of the same measurements (an error of kt Iq, e.g. the
  BLDC's commutation dips, shows in neither; the emulator's DriveTruth shows it, and a torque
  map measured on the drive removes it).
* Time: sim time advances one batch per :meth:`apply` / :meth:`safe_batch` only while the
  drive is alive and in closed-loop control (:attr:`time_frozen` is False). The node then
  stops /clock, so the session node (which plays on /clock) pauses by itself.
* Safety:
  - the drive's watchdog stops torque when setpoints stop (host dead, cable cut);
  - the host treats a drive without Heartbeat for ``heartbeat_timeout_s`` (3 heartbeat
    periods by default) as lost: FAULT_DRIVE_LOST, zero torque commanded (in case only
    our receive path broke), the watchdog is no longer fed; once heartbeats return and
    DriveCommands flow, Clear_Errors + closed-loop torque control re-arm it. Supervision runs
    on receipt times: a frame's own wall-clock receive stamp (the kernel's on socketcan /
    udp_multicast) dates it when it waited in the queue, so a gap between two Heartbeats
    longer than the timeout is a lost drive even when this loop, delayed itself (a loaded
    machine), only drains both afterwards: FAULT_DRIVE_LOST for that batch (zero torque, the
    controller drops its trim), back at the next, counted (``heartbeat_gaps``,
    ``heartbeat_gap_max_ms``) and logged. The stamps go onto the host clock by one pair of
    readings (host clock, wall clock) per :meth:`service`, so a frame that came while the queue
    was drained (the loop preempted mid-drain) is dated when it came, not earlier;
  - stale measurements: while the drive is armed and its newest speed (Get_Encoder_Estimates)
    or torque estimate (Get_Torques, if it arrives at all) is older than
    ``measurement_timeout_s`` (heartbeats may still be on time: a stalled drive or emulator),
    FAULT_DRIVE_STALE (WARN diagnostic, ``stale_episodes`` / ``stale_batches``): the
    controller holds its torque trim rather than integrate on a frozen value;
  - a drive that is alive (Heartbeats) but not in closed-loop control although it should be
    (it tripped or reports errors, someone set it IDLE, arming fails): FAULT_DRIVE_DISARMED,
    an ERROR diagnostic, sim time stops (the session pauses); the plant re-arms it
    (Clear_Errors + Set_Controller_Mode + Set_Axis_State, Set_Limits if configured) with a
    bounded policy: ``enable_retry_s`` doubling per failed attempt, at most
    ``enable_max_attempts`` in a row (an arm that does not hold for ``armed_stable_s``
    counts as failed), then it gives up until the drive's errors change, it reaches closed
    loop by other means, or it was lost and is back (a reboot; not a late gap, a blip seen
    only after the fact), or in a new run; DriveCommands that stop and resume (a stalled
    controller) change nothing at the drive, so they neither restart nor add to the count.
    An emergency stop (ESTOP_REQUESTED) is never cleared or re-armed by the plant: it waits
    until someone clears it on the drive;
  - :meth:`set_safe` (the node's DriveCommand timeout): zero torque and Set_Axis_State IDLE
    (again whenever a Heartbeat shows the axis armed while it lasts), and the watchdog is no
    longer fed; re-armed when commands return. The plant does not leave the disarming to the
    drive's watchdog: the RTR requests it keeps sending would feed that watchdog on a firmware
    that feeds it on every frame to the axis (the open 0.5.x firmware does:
    odriverobotics/ODrive Firmware/communication/can/can_simple.cpp, do_command(); what feeds
    the closed 0.6.x firmware's is not published), keeping the drive armed at zero torque.
    A VESC has no IDLE: its SET_CURRENT 0 is not repeated, so its command timeout releases it;
  - a bus that raised on a receive call and brought no frame for RX_FAILING_REOPEN_S since (an
    adapter unplugged: the kernel unbinds a SocketCAN socket from an interface that goes away,
    with one ENODEV, so it stays silent when the adapter is back) is reopened, again every
    RX_FAILING_REOPEN_S until it opens (a bus this plant opened itself);
  - frames that are error frames, of unknown ids, of the wrong length, NaN / inf or
    outside the DBC's ranges are counted and ignored by the protocol layer, never raised.
* Statistics (:meth:`stats`), shown in the plant's diagnostic (keys ``can_*``) and by
  ``./bike report``; an optional log of every frame sent and received in python-can's
  ``.asc`` or ``.blf`` format (``log_file``; the suffix picks the writer).

Config section ``can:`` of a bike config: see :class:`CanParams`.
"""
from __future__ import annotations

import collections
import dataclasses
import math
import pathlib
import time
from typing import Callable

import can

from .. import mechanics
from ..config import ConfigError, build_dataclass, resolve_config_path, section
from .protocol import (DRIVE_TO_HOST, MALFORMED_REASONS, MEASUREMENT_KINDS, MESSAGE_OF_KIND,
                       PROTOCOLS, AxisState, ODriveError, ProcedureResult, error_names)
from .torque_map import EMULATED_SOURCE_MARK, TorqueMap, TorqueMapError, load_torque_map

TWO_PI = 2.0 * math.pi
RPM_PER_REV_S = 60.0
RPM_PER_RAD_S = 60.0 / TWO_PI

# PlantState fault bits (bike_msgs/PlantState; numbers duplicated so this module stays ROS-free)
FAULT_OVERVOLTAGE = 4
FAULT_DRIVE_LOST = 16
FAULT_DRIVE_DISARMED = 256
FAULT_DRIVE_STALE = 1024

# measurement kinds whose age makes a PlantState stale (speed and torque: what the controller closes loops on)
STALE_KINDS = ("motion", "torque")
# armed this long without a single speed (Get_Encoder_Estimates): stale, and the diagnostic says why
SPEED_MISSING_AFTER_S = 0.5
# a frame's own receive timestamp (wall clock, e.g. the kernel's on socketcan / udp_multicast) is
# trusted for the receipt time when it is at most this old and not in the future
RX_STAMP_MAX_AGE_S = 5.0
# a frame read within this of its receive stamp is dated at the loop's own time (no jitter)
RX_STAMP_PROMPT_S = 1e-3

# diagnostic levels (diagnostic_msgs/DiagnosticStatus)
OK, WARN, ERROR = 0, 1, 2

# a receive call failed and no frame came since for this long (an adapter unplugged: a SocketCAN
# socket reports ENODEV once and is unbound by the kernel, so it stays silent even when the adapter is
# back; other interfaces fail on every call): the plant reopens a bus it opened itself, then tries
# again every RX_FAILING_REOPEN_S until one opens
RX_FAILING_REOPEN_S = 1.0

# no Heartbeat of our node this long (at start, or since the drive was lost): log what the bus
# does carry (other nodes' heartbeats, our node's dropped heartbeats, nothing at all, ...)
LINK_HINT_AFTER_S = 2.0

LOG_SUFFIXES = (".asc", ".blf")
REQUEST_KINDS = tuple(k for k in MEASUREMENT_KINDS if k != "status")


@dataclasses.dataclass
class CanParams:
    """The ``can:`` section of a bike config."""
    interface: str = "socketcan"        # any python-can interface: socketcan, virtual, udp_multicast, pcan, ...
    channel: str = "can0"               # can0 / a virtual channel name / a multicast group (239.74.163.2)
    port: int = 0                       # udp_multicast UDP port (0: python-can's default 43113)
    bitrate: int = 1000000              # interfaces that set it (pcan, kvaser, ...); socketcan: `ip link`
    node_id: int = 0                    # ODrive axis node id 0..62 / VESC ID 0..254 (not broadcast)
    protocol: str = "odrive_cansimple_0.6"   # bike_plant.can.protocol.PROTOCOLS (odrive_cansimple_0.6, vesc_can)
    torque_constant_nm_per_a: float = 0.0    # vesc_can: torque -> SET_CURRENT; 0: the bldc section's kt
    heartbeat_period_s: float = 0.1     # the drive's heartbeat_msg_rate_ms (a slower drive is logged, with the fix)
    heartbeat_timeout_s: float = 0.3    # no Heartbeat this long -> FAULT_DRIVE_LOST (3 periods)
    measurement_timeout_s: float = 0.05  # speed / torque estimate older than this -> FAULT_DRIVE_STALE (5 x 10 ms)
    watchdog_feed_s: float = 0.1        # re-send the setpoint at least this often (drive watchdog)
    request_period_s: float = 0.01      # RTR period of the measurements in `request`
    request: list = dataclasses.field(default_factory=lambda: ["torque", "bus", "current"])
    enable_retry_s: float = 0.5         # re-arm retry (Clear_Errors + closed loop) after this; doubles per attempt
    enable_max_attempts: int = 5        # failed arming attempts in a row before giving up (0: never give up)
    armed_stable_s: float = 2.0         # closed loop this long resets the attempt count (bounds arm/trip cycles)
    disarm_grace_s: float = 0.5         # first arming: not yet a fault while it takes less than this
    arm_ramp_nm_per_s: float = 20.0     # after (re-)arming, |setpoint| <= this x time in closed loop (0: no ramp)
    torque_limit_nm: float = 0.0        # clamp of the torque setpoint (with a torque map: of the shaft's
                                        # torque); 0: controller.tmax_nm (none if absent)
    torque_map_file: str = ""           # the drive's torque map (bike_plant.can.torque_map), relative to the
                                        # config file; "" = the drive's kt Iq is the shaft's torque
    current_limit_a: float = 0.0        # > 0: Set_Limits at arming (with velocity_limit_rev_s; both or neither)
    velocity_limit_rev_s: float = 0.0   # > 0: Set_Limits at arming (with current_limit_a)
    log_file: str = ""                  # .asc or .blf: log every frame sent / received ("" = off)
    log_format: str = "asc"             # ./bike run --record: log beside the bag as asc | blf | none
    idle_on_exit: bool = True           # on shutdown: zero torque + IDLE
    emulator: bool = False              # ./bike run also starts bike-drive-emulator on this bus
    emulator_watchdog_s: float = 0.5    # the emulator's watchdog timeout (--watchdog-s)
    emulator_args: list = dataclasses.field(default_factory=list)   # more bike-drive-emulator options

    def validate(self) -> None:
        if not self.interface:
            raise ValueError("interface must not be empty")
        if self.protocol not in PROTOCOLS:
            raise ValueError(f"protocol: unknown {self.protocol!r} (known: {', '.join(sorted(PROTOCOLS))})")
        drive = PROTOCOLS[self.protocol]
        problem = drive.node_id_problem(self.node_id)
        if problem:
            raise ValueError(f"node_id {problem}")
        if not (math.isfinite(self.torque_constant_nm_per_a) and self.torque_constant_nm_per_a >= 0):
            raise ValueError(f"torque_constant_nm_per_a must be >= 0, got {self.torque_constant_nm_per_a!r}")
        if not drive.can_request and self.request:
            raise ValueError(f"request: {self.protocol} drives only broadcast (nothing can be requested), "
                             f"set request: [] (got {self.request})")
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port must be in 0..65535, got {self.port}")
        if self.interface == "udp_multicast" and not _is_multicast(self.channel):
            # python-can's UdpMulticastBus joins a group: channel nope failed in the plant and the drive
            # emulator once the graph had started ("Name or service not known", two nodes)
            raise ValueError(f"channel: udp_multicast takes a multicast group address (IPv4 224.0.0.0/4 or IPv6 "
                             f"ff00::/8, e.g. 239.74.163.2), got {self.channel!r}")
        for name in ("heartbeat_period_s", "heartbeat_timeout_s", "measurement_timeout_s", "watchdog_feed_s",
                     "request_period_s",
                     "enable_retry_s", "bitrate"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("torque_limit_nm", "current_limit_a", "velocity_limit_rev_s", "emulator_watchdog_s",
                     "enable_max_attempts", "armed_stable_s", "disarm_grace_s", "arm_ramp_nm_per_s"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if self.heartbeat_timeout_s <= self.heartbeat_period_s:
            raise ValueError(f"heartbeat_timeout_s ({self.heartbeat_timeout_s:g}) must be longer than "
                             f"heartbeat_period_s ({self.heartbeat_period_s:g}), the drive's Heartbeat period: "
                             "else every gap between two Heartbeats is a lost drive (3 periods is usual)")
        if self.emulator and self.emulator_watchdog_s and self.watchdog_feed_s >= self.emulator_watchdog_s:
            raise ValueError(f"watchdog_feed_s ({self.watchdog_feed_s:g}) must be shorter than the drive's "
                             f"watchdog, emulator_watchdog_s ({self.emulator_watchdog_s:g})")
        if not drive.has_arming and (self.current_limit_a > 0 or self.velocity_limit_rev_s > 0):
            raise ValueError(f"current_limit_a / velocity_limit_rev_s: {self.protocol} has no limits command on "
                             "CAN (set the limits in the drive's own configuration), set both to 0")
        if (self.current_limit_a > 0) != (self.velocity_limit_rev_s > 0):
            # CANSimple's Set_Limits always sets both: a placeholder for the one left at 0 would
            # overwrite that limit on the drive (e.g. its motor's current limit with 1000 A)
            raise ValueError(f"current_limit_a ({self.current_limit_a:g}) and velocity_limit_rev_s "
                             f"({self.velocity_limit_rev_s:g}) go together: Set_Limits sets both on the drive, "
                             "so give both, or 0 and 0 to leave the drive's own limits")
        unknown = [k for k in self.request if k not in REQUEST_KINDS]
        if unknown:
            raise ValueError(f"request: unknown kind(s) {unknown} (known: {', '.join(REQUEST_KINDS)})")
        if self.log_file and pathlib.Path(self.log_file).suffix.lower() not in LOG_SUFFIXES:
            raise ValueError(f"log_file must end in .asc or .blf, got {self.log_file!r}")
        if self.log_format not in ("asc", "blf", "none"):
            raise ValueError(f"log_format must be asc, blf or none, got {self.log_format!r}")
        if not all(isinstance(a, str) for a in self.emulator_args):
            raise ValueError("emulator_args must be a list of strings")

    def bus_kwargs(self) -> dict:
        """Keyword arguments of ``can.Bus``."""
        kwargs = {"interface": self.interface, "channel": self.channel, "bitrate": self.bitrate}
        if self.interface == "udp_multicast" and self.port:
            kwargs["port"] = self.port
        return kwargs

    def describe(self) -> str:
        port = f" port {self.port}" if self.interface == "udp_multicast" and self.port else ""
        return f"node {self.node_id} on {self.interface} {self.channel}{port}"


def _is_multicast(channel) -> bool:
    import ipaddress
    try:
        return ipaddress.ip_address(str(channel)).is_multicast
    except ValueError:
        return False


def can_params_from_config(cfg: dict) -> CanParams:
    """The ``can:`` section (every key optional); ConfigError names the key."""
    path = cfg.get("_config_path")
    return build_dataclass(CanParams, section(cfg, "can", path), "can", path)


def torque_map_of(cfg: dict, p: CanParams) -> TorqueMap | None:
    """The drive's torque map of ``can.torque_map_file`` (relative: to the config file's folder),
    None without one; ConfigError naming the key for a map that cannot be used."""
    if not p.torque_map_file:
        return None
    path = cfg.get("_config_path")
    try:
        return load_torque_map(resolve_config_path(p.torque_map_file, path))
    except TorqueMapError as exc:
        raise ConfigError(str(exc), path, "can.torque_map_file") from None


def emulator_args_from_config(cfg: dict) -> list[str]:
    """bike-drive-emulator options for the bus and node of a config's ``can:`` section
    (``./bike run`` starts the emulator with these plus ``--config``)."""
    p = can_params_from_config(cfg)
    args = ["--interface", p.interface, "--channel", p.channel, "--bitrate", str(p.bitrate),
            "--node-id", str(p.node_id), "--heartbeat-ms", f"{p.heartbeat_period_s * 1000:g}",
            "--watchdog-s", f"{p.emulator_watchdog_s:g}"]
    if p.protocol != CanParams.protocol:
        args += ["--protocol", p.protocol]
    if p.interface == "udp_multicast" and p.port:
        args += ["--port", str(p.port)]
    return args + list(p.emulator_args)


def torque_constant_of(cfg: dict, p: CanParams) -> float:
    """kt [N m/A] for protocols that command current: ``can.torque_constant_nm_per_a``, or
    (0) the BLDC section's (bike_plant.params.BldcParams.kt_nm_per_a); ConfigError otherwise."""
    path = cfg.get("_config_path")
    if p.torque_constant_nm_per_a > 0:
        return float(p.torque_constant_nm_per_a)
    if cfg.get("machine", "bldc") == "bldc":
        from ..params import plant_params_from_config
        return plant_params_from_config(cfg).bldc.kt_nm_per_a
    raise ConfigError(f"{p.protocol} commands the motor current: give the motor's torque constant "
                      f"(machine {cfg.get('machine')!r} has no bldc section to take it from)",
                      path, "can.torque_constant_nm_per_a")


def _number(cfg: dict, dotted: str, default: float) -> float:
    node = cfg
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return default
        node = node[part]
    if isinstance(node, bool) or not isinstance(node, (int, float)) or not math.isfinite(node):
        return default
    return float(node)


def _open_hint(p: CanParams, exc: BaseException) -> str:
    """What to do about the commonest reasons a bus does not open."""
    err = getattr(exc, "errno", None)
    if err is None and isinstance(getattr(exc, "__cause__", None) or getattr(exc, "__context__", None), OSError):
        err = (exc.__cause__ or exc.__context__).errno
    if p.interface == "socketcan" and err == 97:
        return (" (this kernel has no SocketCAN: on a machine without it, ride the emulator on "
                "interface udp_multicast or virtual with can.emulator true)")
    if p.interface == "socketcan" and err == 19:
        return (f" (no interface {p.channel}: plug the adapter in, then sudo ip link set {p.channel} up type can "
                f"bitrate {p.bitrate})")
    return ""


class _BusTap:
    """The bus as the protocol sees it: frames sent also go to the CAN log (Tx)."""

    def __init__(self, bus: can.BusABC, backend: "CanBackend"):
        self._bus = bus
        self._backend = backend

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._bus.send(msg, timeout=timeout)
        self._backend._log(msg, rx=False)

    def recv(self, timeout: float | None = None):
        return self._bus.recv(timeout=timeout)


class CanBackend:
    """A drive on CAN behind the plant node's backend interface (see the module doc)."""

    name = "can"
    measured_by_drive = True

    @property
    def safe_state_text(self) -> str:
        """What the node's diagnostic says the safe state is on this drive."""
        if self.drive.has_arming:
            return "zero torque and the drive set IDLE"
        return "zero torque, not repeated: the drive's command timeout releases the motor"

    def __init__(self, cfg: dict, *, bus: can.BusABC | None = None, log_file: str | None = None,
                 clock: Callable[[], float] = time.monotonic, wall_clock: Callable[[], float] = time.time):
        path = cfg.get("_config_path")
        self.params = p = can_params_from_config(cfg)
        if log_file:
            p.log_file = str(log_file)
            try:
                p.validate()
            except ValueError as exc:
                raise ConfigError(str(exc), path, "can.log_file") from None
        self.machine = str(cfg.get("machine", "bldc"))
        self.batch_periods = int(cfg.get("batch_periods", 20))
        self.control_period_s = float(cfg.get("control_period_s", 5e-5))
        self.pole_pairs = int(_number(cfg, f"{self.machine}.pole_pairs", 1.0))
        self.inertia_kgm2 = _number(cfg, "mechanics.inertia_kgm2", 0.0)
        self.friction_nms = _number(cfg, "mechanics.friction_nms", 0.0)
        # Coulomb friction: the SPMSM bike's (spmsm.dry_friction_nm, as bike_plant.spmsm and the drive
        # emulator's physics have it); the BLDC model has none
        spmsm = self.machine == "spmsm"
        self.dry_friction_nm = _number(cfg, "spmsm.dry_friction_nm", 0.0) if spmsm else 0.0
        dry_rpm = _number(cfg, "spmsm.dry_friction_speed_rpm", 1.0) if spmsm else 1.0
        self.dry_friction_speed_rad_s = dry_rpm / RPM_PER_RAD_S
        limit = p.torque_limit_nm or _number(cfg, "controller.tmax_nm", 0.0)
        self.torque_limit_nm = limit if limit > 0 else math.inf
        self.torque_map = torque_map_of(cfg, p)
        self.clock = clock
        # the clock of the frames' receive stamps (python-can: wall time); with an injected `clock`,
        # inject this one too, or a frame's real queueing delay is subtracted from a fake time
        self.wall_clock = wall_clock
        self._own_bus = bus is None
        if bus is None:
            try:
                bus = can.Bus(**p.bus_kwargs())
            except Exception as exc:  # noqa: BLE001 -- any interface problem is a set-up error
                raise ConfigError(f"cannot open the CAN bus {p.bus_kwargs()}: {exc}{_open_hint(p, exc)}",
                                  path, "can") from None
        self.bus = bus
        self.logger = None
        self.log_path = None
        self.log_frames = 0
        if p.log_file:
            self.log_path = pathlib.Path(p.log_file).expanduser().resolve()
            try:
                self.log_path.parent.mkdir(parents=True, exist_ok=True)
                self.logger = can.Logger(str(self.log_path))
            except Exception as exc:  # noqa: BLE001
                self._shutdown_bus()
                raise ConfigError(f"cannot write the CAN log {self.log_path}: {exc}", path, "can.log_file") from None
        drive_cls = PROTOCOLS[p.protocol]
        motor = {}
        if drive_cls.uses_motor_constants:   # e.g. VESC: electrical rpm and amperes on the bus
            try:
                motor = {"pole_pairs": self.pole_pairs, "torque_constant_nm_per_a": torque_constant_of(cfg, p)}
            except ConfigError:
                self._shutdown_bus()
                raise
        self._tap = _BusTap(bus, self)
        self.drive = drive_cls(self._tap, p.node_id, heartbeat_timeout_s=p.heartbeat_timeout_s,
                               watchdog_feed_interval_s=p.watchdog_feed_s, clock=clock, **motor)
        if self.torque_limit_nm > self.drive.max_torque_nm:
            # a setpoint the protocol cannot encode would raise in the node's callback: refuse at start
            self._shutdown_bus()
            raise ConfigError(f"the torque clamp ({self.torque_limit_nm:g} N m: can.torque_limit_nm, else "
                              f"controller.tmax_nm) exceeds what {p.protocol} can command "
                              f"({self.drive.max_torque_nm:g} N m); set can.torque_limit_nm", path,
                              "can.torque_limit_nm")
        if self.torque_map is not None:
            sp = self.torque_map.setpoint_nm
            self.setpoint_range_nm = (max(float(sp[0]), -self.drive.max_torque_nm),
                                      min(float(sp[-1]), self.drive.max_torque_nm))
        self.counters: collections.Counter = collections.Counter()
        self.events: list[tuple[str, str]] = []
        if self.torque_map is not None:
            self._event("info", f"setpoints and torque through the drive's {self.torque_map.describe()}")
            if not p.emulator and EMULATED_SOURCE_MARK in self.torque_map.source:
                self._event("warning", f"the torque map {self.torque_map.path} was measured on the drive emulator "
                            "(its source says so), not on this drive (can.emulator is false): its corrections are "
                            "the emulated machine's; measure your drive's, or set can.torque_map_file: \"\"")
        # link / arming state
        self.seen = False              # a heartbeat arrived once
        self.lost = False              # seen, then silent for heartbeat_timeout_s
        self.safe = False              # the node's DriveCommand timeout
        self.safe_idle_s = -math.inf   # when the safe state last sent Set_Axis_State IDLE
        self.commanded = False         # valid DriveCommands are flowing: the drive should be armed
        self.was_enabled = False
        self.configured = False        # Set_Controller_Mode (torque) sent since the link came up
        self.last_enable_s = -math.inf
        # bounded re-arming (see _arming): failed attempts in a row, give-up latch
        self.arm_attempts = 0
        self.gave_up = False
        self.gave_up_errors = 0        # drive errors when we gave up (a change starts a new episode)
        self.estop = False             # the drive reports ESTOP_REQUESTED: never cleared here
        self.errors_seen = None        # the last Get_Error answer looked at
        self.disarm_reason = 0         # its Disarm_Reason
        self.ever_armed = False        # the drive was in closed loop at least once
        self.armed_since_s = None
        self.first_attempt_s = None
        self.ramping = False           # the last setpoint was cut by the arming ramp
        self.last_request_s = {k: -math.inf for k in p.request}
        self.rx_at_request: dict[str, int] = {}
        self.clamp_msg = None          # DriveCommand whose torque was last converted
        self.clamp_nm = 0.0
        self.setpoint_nm = 0.0
        self.sent_msg = None           # DriveCommand whose setpoint went out last
        self.started_s = clock()
        self.lost_since_s = None
        self.lost_late = False         # the current loss is a late gap (seen only after the drive was back)
        self.arm_errors_logged = None
        # supervision on receipt times (a frame's own wall-clock timestamp when the loop was late)
        self.last_heartbeat_rx_s = None    # receipt time of the newest Heartbeat (host clock)
        self.heartbeat_gap_max_s = 0.0     # longest gap between two Heartbeats seen while the link was up
        self.late_gap_s = None             # a gap > heartbeat_timeout_s found only when its frames were drained
        self.recent_heartbeat_gaps_s: collections.deque = collections.deque(maxlen=8)   # the drive's actual rate
        self.heartbeat_period_warned = False
        self.foreign_warned_s = -math.inf
        self.lost_gap_s = None             # that gap, while the loss it caused is reported
        self.stale = False                 # speed / torque estimates older than measurement_timeout_s
        self.stale_age_s = 0.0
        self.speed_missing = False         # armed for a while, and not one Get_Encoder_Estimates
        self.last_stale_event_s = -math.inf
        # what the bus carries while there is no link (reset whenever the link comes up): for the
        # diagnostic and a logged hint (a drive on another node id, heartbeats we drop, silence)
        self._reset_bus_watch()
        self._closed = False
        self.rx_failing_since_s = None     # a receive call failed then, and no frame came since
        self.rx_error = ""                 # the last one's error
        self.last_reopen_s = -math.inf
        # sim time and ledger
        self.time_s = 0.0
        self.omega0 = None
        self.e_battery_j = 0.0
        self.e_shaft_j = 0.0           # int (-T_em w) dt: mechanical power into the machine
        self.e_friction_j = 0.0
        # latency of submit(): DriveCommand callback -> frame handed to the bus
        self.submit_latency_s: collections.deque = collections.deque(maxlen=2000)

    # ------------------------------------------------------------------ CAN log
    def _log(self, msg: can.Message, rx: bool) -> None:
        if self.logger is None:
            return
        try:
            if not rx:
                msg = can.Message(timestamp=time.time(), arbitration_id=msg.arbitration_id, data=bytes(msg.data),
                                  dlc=msg.dlc, is_extended_id=msg.is_extended_id,
                                  is_remote_frame=msg.is_remote_frame, is_error_frame=msg.is_error_frame,
                                  is_rx=False, channel=0)
            else:
                msg.channel = 0                   # one channel in the log, whatever the interface calls it
                if not msg.timestamp:
                    msg.timestamp = time.time()
            self.logger.on_message_received(msg)
            self.log_frames += 1
        except Exception:  # noqa: BLE001 -- a logging problem must not stop the drive
            self.counters["log_errors"] += 1

    # ------------------------------------------------------------------ events for the node's log
    def _event(self, level: str, text: str) -> None:
        self.events.append((level, text))

    def pop_events(self) -> list[tuple[str, str]]:
        """(level 'info' | 'warning' | 'error', text) since the last call."""
        out, self.events = self.events, []
        return out

    # ------------------------------------------------------------------ state
    def _axis_text(self) -> str:
        """'axis state 1 (IDLE)', plus the procedure result when it says why the axis did not do
        what was asked (e.g. 'procedure result 14 (NOT_CALIBRATED)': a refused closed loop often
        has no error bit, only this)."""
        if not self.drive.has_arming:
            return f"{self.params.protocol}: no axis state"
        state = int(self.drive.axis_state)
        name = AxisState(state).name if state in AxisState._value2member_map_ else "unknown"
        text = f"axis state {state} ({name})"
        status = self.drive.last.get("status")
        result = int(status.values.get("procedure_result", 0)) if status is not None else 0
        if result not in (ProcedureResult.SUCCESS, ProcedureResult.BUSY):
            rname = ProcedureResult(result).name if result in ProcedureResult._value2member_map_ else "unknown"
            text += f", procedure result {result} ({rname})"
        return text

    @property
    def link_alive(self) -> bool:
        return self.seen and not self.lost

    @property
    def drive_enabled(self) -> bool:
        return self.link_alive and self.drive.enabled

    @property
    def time_frozen(self) -> bool:
        """True while sim time must not advance: no drive yet, drive lost, or not armed."""
        return not self.drive_enabled

    @property
    def disarmed(self) -> bool:
        """The drive is alive but not in closed-loop control although it should be (or was):
        it has errors, it was armed before (tripped, or set IDLE by someone else), arming
        it failed for longer than ``disarm_grace_s``, or the plant gave up re-arming it.
        A fresh drive that is simply idle before the first DriveCommand is not a fault."""
        if not self.link_alive or self.drive.enabled or self._closed:
            return False
        if self.drive.active_errors or self.ever_armed or self.gave_up:
            return True
        return self.first_attempt_s is not None and self.clock() - self.first_attempt_s > self.params.disarm_grace_s

    @property
    def faults(self) -> int:
        bits = FAULT_DRIVE_LOST if self.lost else 0
        if self.disarmed:
            bits |= FAULT_DRIVE_DISARMED
        if self.stale and not self.lost:
            bits |= FAULT_DRIVE_STALE
        if self.seen and self.drive.active_errors & ODriveError.DC_BUS_OVER_VOLTAGE:
            bits |= FAULT_OVERVOLTAGE
        return bits

    # ------------------------------------------------------------------ periodic work
    def service(self, now_s: float | None = None, max_frames: int = 2000) -> None:
        """Receive what the bus holds, supervise the link, (re-)arm, request, keep alive.
        Call once per batch tick; never blocks, never raises for bus trouble."""
        now = self.clock() if now_s is None else now_s
        self._receive(now, self.wall_clock(), max_frames)
        self._reopen_if_gone(now)
        drive = self.drive
        alive = drive.link_alive(now)
        late_gap, self.late_gap_s = self.late_gap_s, None
        if late_gap is not None and self.seen and not self.lost:
            # the heartbeats came back before this loop looked (it was delayed itself): the drive
            # was silent longer than the timeout all the same. FAULT_DRIVE_LOST for this batch
            # (zero torque, the controller drops its trim and ramps up again), back at the next.
            self._on_lost(now, late_gap, late=True)
            self._update_stale(now)
            return
        if not alive and not self.link_alive:
            self._log_link_hint(now)
        if not self.seen and alive:
            self.seen = True
            self.configured = False
            self._reset_bus_watch()
            self._event("info", f"drive found: {self.params.describe()}, {self._axis_text()}, "
                                f"errors {error_names(drive.active_errors) or 'none'}")
        if self.seen:
            if not alive and not self.lost:
                self._on_lost(now)
            elif not alive:
                self.lost_late = False       # still silent now that this loop looks: seen live
            elif self.lost:
                self.lost = False
                self.configured = False      # it may have rebooted, into a mode of its own
                self._reset_bus_watch()
                self.counters["drive_back"] += 1
                gone = now - self.lost_since_s if self.lost_since_s is not None else math.nan
                if self.lost_late:
                    # a blip this loop found only after the drive was back (it stalled itself, as
                    # under load): no sign of a reboot, so the arming count and a give-up stand
                    self._event("info", f"the drive is back after {gone:.2f}s (a late gap, no reboot assumed: "
                                        + ("still given up on arming)" if self.gave_up else "arming count kept)"))
                else:
                    self._event("info", f"the drive is back after {gone:.2f}s ({self._axis_text()}, errors "
                                        f"{error_names(drive.active_errors) or 'none'}): re-arming when "
                                        "DriveCommands flow")
                    self._new_arming_episode("the drive is back")
        if self.link_alive:
            enabled = drive.enabled
            if enabled and not self.was_enabled:
                # armed, but not by this plant's arming: it had not configured it since the link came
                # up, or it had stopped arming it (given up, or an e-stop held): someone else did
                by_others = "after this plant gave up arming it" if self.gave_up else \
                    "while an emergency stop held it" if self.estop else ""
                if (not self.configured or by_others) and drive.has_arming:
                    self._take_over_armed_drive(by_others)
                self.configured = True
                self.counters["armed"] += 1
                self.ever_armed = True
                self.armed_since_s = now
                self._event("info", "drive in closed-loop torque control" if drive.has_arming else
                            f"drive alive ({drive.status_message} arriving; {self.params.protocol} has no arming): "
                            "torque setpoints go out")
                if self.commanded and not self.safe:
                    self._send_setpoint(self.setpoint_nm)
            elif not enabled and self.was_enabled:
                self.counters["disarmed"] += 1
                self.armed_since_s = None
                if drive.has_arming:
                    # why: the Heartbeat carries the errors active now, Get_Error's Disarm_Reason the one
                    # that disarmed it (gone already after a transient); asked before Clear_Errors clears it
                    drive.request("errors")
                errors = error_names(drive.active_errors)
                self._event("error", f"drive alive but left closed-loop control ({self._axis_text()}"
                                     + (f", errors {', '.join(errors)}" if errors else ", no error") +
                                     "): FAULT_DRIVE_DISARMED, sim time paused")
            self.was_enabled = enabled
            self._note_disarm_reason()
            self._arming(now, enabled)
            if self.safe and enabled and now - self.safe_idle_s >= self.params.heartbeat_period_s:
                # armed in the safe state (an arming still in flight, or armed by other means): IDLE
                # again, once per heartbeat period at most
                self._idle_for_safe_state(now)
            self._request(now)
        self._update_stale(now)
        if self.link_alive:
            if not self.safe:
                if drive.keepalive(now):
                    self.counters["keepalive"] += 1

    def _reopen_if_gone(self, now: float) -> None:
        """A receive call failed and no frame came for RX_FAILING_REOPEN_S since: the interface went
        away (an adapter unplugged, perhaps back under the same name; the kernel unbinds a SocketCAN
        socket from an interface that goes away, with one ENODEV). Reopen a bus this plant opened
        itself, every RX_FAILING_REOPEN_S until it opens; the drive was lost meanwhile (no
        Heartbeat) and is back by the usual path."""
        since = self.rx_failing_since_s
        if not self._own_bus or self._closed or since is None or now - since < RX_FAILING_REOPEN_S or \
                now - self.last_reopen_s < RX_FAILING_REOPEN_S:
            return
        self.last_reopen_s = now
        p = self.params
        try:
            bus = can.Bus(**p.bus_kwargs())
        except Exception as exc:  # noqa: BLE001 -- still gone: try again later
            self._event("warning", f"the CAN bus {p.describe()} fails ({self.rx_error}) for {now - since:.0f}s and "
                                   f"does not reopen yet: {exc}{_open_hint(p, exc)}")
            return
        self._shutdown_bus()
        self.bus = self._tap._bus = bus
        self.rx_failing_since_s = None
        self.counters["bus_reopened"] += 1
        self._event("warning", f"the CAN bus {p.describe()} failed for {now - since:.1f}s ({self.rx_error}): "
                               "reopened")

    def _receipt_s(self, msg: can.Message, now: float, wall_now_s: float) -> float:
        """When ``msg`` arrived, on the host clock: its own receive stamp (wall clock: the kernel's
        on socketcan / udp_multicast, python-can's on virtual) moved onto the host clock by the
        pair (``now``, ``wall_now_s``) read when :meth:`service` began. So a frame that waited in
        the queue (this loop was late) is dated before ``now``, and one that came while the queue
        was drained (the loop preempted mid-drain) after it: not by the time it was read, which
        would date it too early by the preemption and make the drive look silent at the next
        service. Within RX_STAMP_PROMPT_S of ``wall_now_s``: ``now``. Stamps in the future (read
        at the frame) or older than RX_STAMP_MAX_AGE_S (hardware clocks of other interfaces) are
        not trusted: ``now``."""
        stamp = getattr(msg, "timestamp", 0.0) or 0.0
        waited_s = wall_now_s - stamp
        if abs(waited_s) <= RX_STAMP_PROMPT_S or waited_s > RX_STAMP_MAX_AGE_S:
            return now
        if waited_s < 0.0 and stamp > self.wall_clock():
            return now
        return now - waited_s

    def _receive(self, now: float, wall_now_s: float, max_frames: int) -> None:
        drive = self.drive
        for _ in range(max_frames):
            try:
                msg = self.bus.recv(timeout=0.0)
            except Exception as exc:  # noqa: BLE001 -- e.g. udp_multicast cannot unpack a datagram
                drive.counters["bus_error"] += 1
                if self.rx_failing_since_s is None:
                    self.rx_failing_since_s = now
                self.rx_error = str(exc) or type(exc).__name__
                return
            if msg is None:
                return
            self.rx_failing_since_s = None
            echoes = drive.counters["echo"]
            rx_s = self._receipt_s(msg, now, wall_now_s)
            measurements = drive.receive(msg, rx_s)
            for m in measurements:
                if m.kind == "status":
                    self._heartbeat_at(rx_s)
            if drive.counters["echo"] == echoes:
                self._log(msg, rx=True)
                if not self.link_alive:
                    self._watch_bus(msg, bool(measurements))
                if not measurements and not msg.is_remote_frame and \
                        bool(msg.is_extended_id) == drive.codec.extended_id:
                    self._foreign_command(msg, now)

    def _reset_bus_watch(self) -> None:
        self.watch_frames = 0                          # frames received (not our own echoes)
        self.watch_error_frames = 0
        self.watch_extended_heartbeats = 0
        self.watch_other_heartbeats: dict[int, int] = {}   # node id -> Heartbeat-shaped frames
        self.watch_own_drops: collections.Counter = collections.Counter()   # our Heartbeat id: reason
        self.watch_tx_failed0 = self.drive.counters["tx_failed"]
        self.watch_bus_errors0 = self.drive.counters["bus_error"]
        self.link_hint_key = None
        self.link_hint_logged_s = -math.inf

    def _watch_bus(self, msg: can.Message, decoded: bool) -> None:
        """While there is no link: note what the bus carries (cheap; frames we did not use)."""
        self.watch_frames += 1
        if msg.is_error_frame:
            self.watch_error_frames += 1
            return
        codec = self.drive.codec
        if decoded or msg.is_remote_frame or msg.is_fd:
            return
        if "Heartbeat" not in codec.messages:
            self._watch_other_status(msg, codec)
            return
        arb = msg.arbitration_id
        heartbeat = codec.messages["Heartbeat"]
        if msg.is_extended_id:
            # a drive set to 29-bit ids (node_id << 5 | cmd_id as an extended id)
            if isinstance(arb, int) and arb == (self.params.node_id << 5 | heartbeat.frame_id):
                self.watch_extended_heartbeats += 1
            return
        if not isinstance(arb, int) or not 0 <= arb <= 0x7FF:
            return
        if arb & 0x1F != heartbeat.frame_id:
            return
        node = arb >> 5
        if node != self.params.node_id:
            if len(msg.data) == heartbeat.length and (node in self.watch_other_heartbeats
                                                      or len(self.watch_other_heartbeats) < 64):
                self.watch_other_heartbeats[node] = self.watch_other_heartbeats.get(node, 0) + 1
            return
        reason = codec.classify(msg, DRIVE_TO_HOST, answers_requests=False)
        self.watch_own_drops[reason if isinstance(reason, str) else "decode_error"] += 1

    def _status_plural(self) -> str:
        status = self.drive.status_message
        return "Heartbeats" if status == "Heartbeat" else f"{status} frames"

    def _watch_other_status(self, msg: can.Message, codec) -> None:
        """Protocols other than ODrive: status frames of other node ids (a VESC with another ID)."""
        arb = msg.arbitration_id
        if bool(msg.is_extended_id) != codec.extended_id or not isinstance(arb, int) or \
                not 0 <= arb <= codec.id_max:
            return
        node, cmd = codec.split_id(arb)
        status = codec.messages.get(self.drive.status_message)
        if status is None or cmd != codec.command_id_of(status.frame_id) or node == self.params.node_id:
            return
        if node in self.watch_other_heartbeats or len(self.watch_other_heartbeats) < 64:
            self.watch_other_heartbeats[node] = self.watch_other_heartbeats.get(node, 0) + 1

    def _foreign_command(self, msg: can.Message, now: float) -> None:
        """A command frame to our node that this plant did not send (its own echoes are already
        filtered): another host drives the same axis (a script, ros_odrive, a second plant).
        Counted; warned about at most every 10 s."""
        codec = self.drive.codec
        name = codec.message_name(msg.arbitration_id)
        if name not in codec.host_to_drive:
            return
        self.counters["foreign_commands"] += 1
        if now - self.foreign_warned_s >= 10.0:
            self.foreign_warned_s = now
            self._event("warning", f"another host sends {name} to {self.params.describe()} "
                                   f"({self.counters['foreign_commands']} such frames so far): two controllers on "
                                   "one drive; stop the other one")

    def _link_hint(self) -> tuple[tuple, str]:
        """(shape, text) of what the bus carried while there was no link: '' when nothing helps."""
        p = self.params
        parts, key = [], []
        if self.watch_other_heartbeats:
            nodes = sorted(self.watch_other_heartbeats)
            key.append(("nodes", tuple(nodes)))
            status = self.drive.status_message
            which = ("the drive's odrv.axis0.config.can.node_id" if status == "Heartbeat"
                     else "the VESC's controller ID (VESC Tool, App Settings, General)")
            parts.append(f"{self._status_plural()} on the bus from node {', '.join(map(str, nodes))}, none from node "
                         f"{p.node_id} (can.node_id must be {which})")
        if self.watch_extended_heartbeats:
            key.append(("extended",))
            parts.append(f"{self.watch_extended_heartbeats} Heartbeats of node {p.node_id} with a 29-bit (extended) "
                         "id: CANSimple here uses 11-bit ids, set the drive to standard ids")
        if self.watch_own_drops:
            reasons = ", ".join(f"{r} {n}" for r, n in sorted(self.watch_own_drops.items()))
            key.append(("drops", tuple(sorted(self.watch_own_drops))))
            parts.append(f"{sum(self.watch_own_drops.values())} Heartbeat frames of node {p.node_id} dropped "
                         f"({reasons}): not the {p.protocol} layout?")
        others = sorted({m.message for k, m in self.drive.last.items() if k != "status"})   # (VESC: 2 kinds a frame)
        if not self.seen and others and not self.watch_own_drops:
            key.append(("no_heartbeat", tuple(others)))
            status = self.drive.status_message
            parts.append(f"node {p.node_id} sends {', '.join(others)} but no {status} "
                         + ("(heartbeat_msg_rate_ms = 0 on the drive?)" if status == "Heartbeat"
                            else f"(is {status} among the drive's broadcast status messages?)"))
        if self.watch_frames == self.watch_error_frames:
            key.append(("silent", self.watch_error_frames > 0))
            parts.append("nothing received on the bus" + (f" but {self.watch_error_frames} error frames"
                                                          if self.watch_error_frames else "")
                         + " (drive powered? wiring, termination, bitrate?)")
        elif self.watch_error_frames:
            key.append(("error_frames",))
            parts.append(f"{self.watch_error_frames} error frames on the bus (bitrate, termination?)")
        rx_errors = self.drive.counters["bus_error"] - self.watch_bus_errors0
        if rx_errors:
            key.append(("rx_errors",))
            parts.append(f"{rx_errors} receive calls failed in the interface ({self.params.interface} "
                         f"{self.params.channel} down, or unplugged?)")
        failed = self.drive.counters["tx_failed"] - self.watch_tx_failed0
        if failed:
            key.append(("tx_failed",))
            parts.append(f"{failed} frames could not be sent (bus-off, interface down or no node acknowledging?)")
        return tuple(key), "; ".join(parts)

    def _no_link_since(self) -> float:
        return self.lost_since_s if self.lost and self.lost_since_s is not None else self.started_s

    def _log_link_hint(self, now: float) -> None:
        """No link for LINK_HINT_AFTER_S: log what the bus carries, again when that changes."""
        since = self._no_link_since()
        if now - since < LINK_HINT_AFTER_S:
            return
        key, text = self._link_hint()
        if key == self.link_hint_key or now - self.link_hint_logged_s < 1.0:
            return
        self.link_hint_key, self.link_hint_logged_s = key, now
        what = f"no {self.drive.status_message} yet" if not self.seen else "the drive is still silent"
        self._event("warning", f"{what} from {self.params.describe()} after {now - since:.0f}s: "
                               f"{text or 'nothing on the bus explains why'}; sim time paused")

    def _heartbeat_at(self, rx_s: float) -> None:
        """Link supervision on receipt times: a gap between two Heartbeats longer than
        heartbeat_timeout_s is a lost drive even when this loop, delayed itself, only sees
        both after the fact (then :meth:`service` raises FAULT_DRIVE_LOST for one batch)."""
        prev, self.last_heartbeat_rx_s = self.last_heartbeat_rx_s, rx_s
        if prev is not None and rx_s > prev:
            self.recent_heartbeat_gaps_s.append(rx_s - prev)
            self._check_heartbeat_period()
        if prev is None or not self.seen or self.lost:
            return
        gap = rx_s - prev
        self.heartbeat_gap_max_s = max(self.heartbeat_gap_max_s, gap)
        if gap > self.params.heartbeat_timeout_s:
            self.counters["heartbeat_gaps"] += 1
            self.late_gap_s = max(gap, self.late_gap_s or 0.0)

    def heartbeat_period_hint(self) -> str:
        """'' or why the drive's Heartbeat rate does not fit the config: the median of the
        last gaps (RTR answers only shorten gaps) beyond 1.5 x heartbeat_period_s."""
        gaps = sorted(self.recent_heartbeat_gaps_s)
        if len(gaps) < 5:
            return ""
        period = gaps[len(gaps) // 2]
        p = self.params
        if period <= 1.5 * p.heartbeat_period_s:
            return ""
        status = self.drive.status_message
        text = (f"the drive's {self._status_plural()} come every {period:.2f}s, not every "
                f"can.heartbeat_period_s={p.heartbeat_period_s:g}s")
        fix = (f"heartbeat_msg_rate_ms = {p.heartbeat_period_s * 1000:g}" if status == "Heartbeat"
               else f"its CAN status rate to {1.0 / p.heartbeat_period_s:g} Hz")
        if period > p.heartbeat_timeout_s:
            return text + (f", longer than heartbeat_timeout_s={p.heartbeat_timeout_s:g}s, so the link cannot "
                           f"hold: set {fix} on the drive")
        return text + (f" (little margin below heartbeat_timeout_s={p.heartbeat_timeout_s:g}s): set "
                       f"{fix} on the drive, or the can: keys to match")

    def _check_heartbeat_period(self) -> None:
        """Log once (again after it fits for a while) when the Heartbeat rate does not fit."""
        hint = self.heartbeat_period_hint()
        if hint and not self.heartbeat_period_warned:
            self.heartbeat_period_warned = True
            self._event("warning", hint)
        elif not hint and len(self.recent_heartbeat_gaps_s) == self.recent_heartbeat_gaps_s.maxlen:
            self.heartbeat_period_warned = False

    def _update_stale(self, now: float) -> None:
        """FAULT_DRIVE_STALE while the drive is armed and its newest speed or torque estimate
        (of the kinds that arrive at all) is older than measurement_timeout_s: the controller
        must not integrate on a held value. Counted; logged at most once per second."""
        last = self.drive.last
        ages = [now - last[k].received_s for k in STALE_KINDS if k in last]
        # no speed at all since the drive armed (encoder_msg_rate_ms 0 and motion not requested):
        # the PlantState would read 0 rpm however fast the flywheel turns
        armed_s = now - self.armed_since_s if self.armed_since_s is not None else 0.0
        self.speed_missing = "motion" not in last and armed_s > max(SPEED_MISSING_AFTER_S,
                                                                    self.params.measurement_timeout_s)
        if self.speed_missing:
            ages.append(armed_s)
        self.stale_age_s = max(ages) if ages else 0.0
        stale = self.drive_enabled and self.stale_age_s > self.params.measurement_timeout_s
        if stale and not self.stale:
            self.counters["stale_episodes"] += 1
            if now - self.last_stale_event_s >= 1.0:
                self.last_stale_event_s = now
                self._event("warning", self._stale_text() + f": FAULT_DRIVE_STALE, the controller holds its trim "
                                       f"({self.counters['stale_episodes']} episodes so far)")
        self.stale = stale

    def _stale_text(self) -> str:
        if self.speed_missing:
            return (f"no Get_Encoder_Estimates from the drive in the {self.stale_age_s:.1f}s since it armed, so "
                    "the speed reads 0: set encoder_msg_rate_ms = 10 on the drive, or add motion to can.request")
        return (f"drive measurements stale: speed / torque estimate {self.stale_age_s * 1e3:.0f} ms old > "
                f"measurement_timeout_s={self.params.measurement_timeout_s:g}s")

    def _on_lost(self, now: float, gap_s: float | None = None, late: bool = False) -> None:
        self.lost = True
        self.lost_since_s = now
        self.lost_late = late
        self.was_enabled = False
        self.armed_since_s = None
        self.counters["drive_lost"] += 1
        self._reset_bus_watch()
        age = gap_s if gap_s is not None else self.drive.heartbeat_age_s(now)
        self.lost_gap_s = gap_s
        seen_late = (" (seen late: the heartbeats had resumed before this loop, itself delayed, looked; "
                     "back at the next batch)") if late else ""
        self._event("error", f"drive silent: no {self.drive.status_message} for {age:.3f}s > heartbeat_timeout_s="
                             f"{self.params.heartbeat_timeout_s:g}s ({self.params.describe()}){seen_late}: "
                             "FAULT_DRIVE_LOST, zero torque, sim time paused")
        # zero torque in case only our receive path broke, then stop feeding the watchdog
        self._send_setpoint(0.0)
        self.drive.forget_setpoint()
        self.sent_msg = None

    def _new_arming_episode(self, why: str) -> None:
        """Forget failed attempts (and a give-up): the situation changed."""
        if self.gave_up:
            self._event("info", f"re-arming again: {why}")
        self.arm_attempts = 0
        self.gave_up = False
        self.first_attempt_s = None
        self.last_enable_s = -math.inf

    def retry_interval_s(self) -> float:
        """Wait after failed attempt number ``arm_attempts``: enable_retry_s, doubling each time."""
        return self.params.enable_retry_s * 2.0 ** max(self.arm_attempts - 1, 0)

    def _arming(self, now: float, enabled: bool) -> None:
        """Bounded re-arming of a drive that is alive but not in closed-loop control.

        While DriveCommands flow (and not in the safe state), an unarmed drive gets
        Clear_Errors + Set_Controller_Mode + Set_Axis_State(CLOSED_LOOP_CONTROL) at once,
        then again after enable_retry_s, 2x, 4x, ... as long as it does not arm. After
        ``enable_max_attempts`` attempts in a row that did not hold (the drive refused, or
        tripped again within ``armed_stable_s``) the plant gives up: FAULT_DRIVE_DISARMED
        stays, an ERROR diagnostic says why, no more frames are sent to arm it. It starts
        over only on a change at the drive: its error bits change (cleared or changed by
        someone else), it reaches closed loop by other means, or it was lost and is back
        (rebooted, replugged; a late gap is a blip, not a reboot) -- or in a new run (a new
        plant). Not when DriveCommands stop and resume: a controller stalled under load for
        command_timeout_s changes nothing at the drive, and restarting there let a loaded
        machine re-arm a refusing drive again and again (see :meth:`set_safe`).
        """
        p = self.params
        drive = self.drive
        if enabled:
            self.estop = False               # (cleared and armed on the drive by someone else)
            if self.gave_up:
                self._new_arming_episode("the drive is in closed-loop control")
            if self.arm_attempts and self.armed_since_s is not None and now - self.armed_since_s >= p.armed_stable_s:
                self.arm_attempts = 0            # it held: a later trip starts a new count
                self.first_attempt_s = None
            return
        if self.gave_up:
            if drive.active_errors != self.gave_up_errors:
                self._new_arming_episode(f"the drive's errors changed to {error_names(drive.active_errors) or 'none'}")
            else:
                return
        if self._estop_held(drive.active_errors):
            return
        if not self.commanded or self.safe:
            return
        if now - self.last_enable_s < self.retry_interval_s():
            return
        if p.enable_max_attempts and self.arm_attempts >= p.enable_max_attempts:
            self.gave_up = True
            self.gave_up_errors = drive.active_errors
            self.counters["arm_gave_up"] += 1
            errors = ", ".join(error_names(drive.active_errors)) or "none"
            self._event("error", f"gave up arming the drive after {self.arm_attempts} attempts ("
                                 f"{self._axis_text()}, errors {errors}): "
                                 "FAULT_DRIVE_DISARMED stays, sim time paused; fix the drive, then the plant re-arms "
                                 "when its errors change or after it reboots (or in a new run), or takes it over "
                                 "when it is armed by other means (odrivetool)")
            return
        self._arm(now)

    def _note_disarm_reason(self) -> None:
        """Log the drive's Disarm_Reason once per new Get_Error answer that names one."""
        m = self.drive.last.get("errors")
        if m is None or m is self.errors_seen:
            return
        self.errors_seen = m
        reason = int(m.values.get("disarm_reason", 0))
        if reason and reason != self.disarm_reason:
            self._event("warning", f"the drive's disarm reason (Get_Error): {', '.join(error_names(reason))}")
        self.disarm_reason = reason

    def _estop_held(self, errors: int) -> bool:
        """An emergency stop (ESTOP_REQUESTED: an Estop frame from an e-stop node or another host)
        is someone's decision, not a trip: this plant never clears it (Clear_Errors would, and the
        closed loop after it would give the rider the torque back at once). True while it holds;
        logged once; when it is cleared on the drive, a new arming episode starts."""
        estop = bool(errors & ODriveError.ESTOP_REQUESTED)
        if estop and not self.estop:
            self._event("error", f"emergency stop on the drive ({self._axis_text()}, errors "
                                 f"{', '.join(error_names(errors))}): this plant never clears it; FAULT_DRIVE_DISARMED,"
                                 " sim time paused; clear it on the drive (odrivetool: odrv0.clear_errors()) to go on")
        elif self.estop and not estop:
            self._new_arming_episode("the emergency stop was cleared on the drive")
        self.estop = estop
        return estop

    def _take_over_armed_drive(self, by_others: str = "") -> None:
        """The drive is in closed-loop control, but not because this plant armed it (left armed by
        a previous run or odrivetool, it arms itself at boot, or someone armed it ``by_others``:
        after this plant stopped arming it): its control and input modes and its input torque are
        unknown, e.g. velocity control, where Input_Torque is only a feed-forward. Zero torque
        first, then the limits and torque control / passthrough; the setpoint then ramps up from
        zero as after any arming."""
        p = self.params
        self.configured = True
        self.counters["taken_over"] += 1
        self._send_setpoint(0.0)
        if p.current_limit_a > 0 and p.velocity_limit_rev_s > 0:
            self.drive.set_limits(p.velocity_limit_rev_s, p.current_limit_a)
        self.drive.select_control("torque")
        sent = "zero torque, then " + ("Set_Limits and " if p.current_limit_a > 0 else "") + \
            "Set_Controller_Mode torque / passthrough"
        if by_others:
            self._event("warning", f"drive armed by other means {by_others} (its control mode unknown): {sent}")
        elif self.ever_armed:
            self._event("info", f"drive back in closed-loop control (it may have rebooted into a mode of its "
                                f"own): {sent}")
        else:
            self._event("warning", f"drive found already in closed-loop control, not armed by this plant (its "
                                   f"control mode unknown): {sent}")

    def _arm(self, now: float) -> None:
        drive = self.drive
        p = self.params
        self.configured = True           # Set_Controller_Mode goes out with every arming
        self.last_enable_s = now
        self.arm_attempts += 1
        if self.first_attempt_s is None:
            self.first_attempt_s = now
        self.counters["enable_attempts"] += 1
        if drive.active_errors and drive.active_errors != self.arm_errors_logged:
            self._event("info", f"Clear_Errors ({', '.join(error_names(drive.active_errors))})")
        self.arm_errors_logged = drive.active_errors
        drive.clear_errors()
        if p.current_limit_a > 0 and p.velocity_limit_rev_s > 0:    # both or neither (CanParams.validate)
            drive.set_limits(p.velocity_limit_rev_s, p.current_limit_a)
        drive.enable("torque")
        drive.request("status")              # the answer tells us at once that we are armed
        self._send_setpoint(self.setpoint_nm)

    def _request(self, now: float) -> None:
        period = self.params.request_period_s
        counters = self.drive.counters
        for kind, t in self.last_request_s.items():
            if now - t < period:
                continue
            received = counters[f"rx:{MESSAGE_OF_KIND[kind]}"]
            self.last_request_s[kind] = now
            if received - self.rx_at_request.get(kind, 0) >= 2:
                self.rx_at_request[kind] = received   # it arrived twice since the last look: cyclic
                continue
            self.rx_at_request[kind] = received
            if self.drive.request(kind):
                self.counters["requests"] += 1

    def _send_setpoint(self, torque_nm: float) -> bool:
        """Set_Input_Torque; within ``arm_ramp_nm_per_s`` x the time since the drive armed, so a
        (re-)armed drive never steps to the held setpoint (the rider feels a ramp from zero)."""
        torque_nm = float(torque_nm)
        rate = self.params.arm_ramp_nm_per_s
        self.ramping = False
        if rate > 0 and torque_nm != 0.0:
            since = self.armed_since_s
            allowed = rate * max(self.clock() - since, 0.0) if since is not None else 0.0
            if abs(torque_nm) > allowed:
                torque_nm = math.copysign(allowed, torque_nm)
                self.ramping = True
                self.counters["ramped_setpoints"] += 1
        ok = self.drive.set_torque(torque_nm)
        if ok:
            self.counters["setpoints"] += 1
        return ok

    # ------------------------------------------------------------------ commands
    def _torque_of(self, msg) -> float:
        if msg is self.clamp_msg:
            return self.clamp_nm
        t = float(msg.torque_cmd_nm)
        lim = self.torque_limit_nm
        if abs(t) > lim:
            self.counters["torque_clamped"] += 1
            t = math.copysign(lim, t)
        if self.torque_map is not None and t != 0.0:
            # the clamp is of the shaft's torque (the machine's rating); the setpoint the drive
            # needs for it at today's speed is the map's inverse, within the setpoints the map
            # was measured at (what the drive is known to deliver) and what the protocol encodes
            speed_rpm = float(self.drive.values().get("speed_rev_s", 0.0)) * RPM_PER_REV_S
            t = self.torque_map.setpoint_nm_for(speed_rpm, t)
            lo, hi = self.setpoint_range_nm
            if not lo <= t <= hi:
                self.counters["torque_clamped"] += 1
                t = min(max(t, lo), hi)
        self.clamp_msg, self.clamp_nm = msg, t
        return t

    def problem(self, msg, n: int) -> str | None:  # noqa: ARG002 -- a setpoint has no per-period arrays
        """Why a DriveCommand cannot be applied (None: it can). Never raises. Gate / duty
        arrays are ignored: the drive's firmware owns the current loop."""
        try:
            for name in ("torque_cmd_nm", "current_cmd_a"):
                if not math.isfinite(float(getattr(msg, name))):
                    return f"{name} is not finite"
        except Exception as exc:  # noqa: BLE001
            return f"unreadable DriveCommand ({exc})"
        return None

    def submit(self, msg, n: int | None = None) -> bool:
        """Send the setpoint of DriveCommand ``msg`` now (called when it arrives).
        Returns True if a frame went out. Invalid commands, the safe state, a lost or
        unarmed drive: nothing is sent (the batch tick decides)."""
        t0 = self.clock()
        if self._closed or self.safe or self.problem(msg, n or self.batch_periods) is not None:
            return False
        self.setpoint_nm = self._torque_of(msg)
        self.commanded = True
        if not self.drive_enabled or (msg is self.sent_msg and not self.ramping):
            return False
        self.sent_msg = msg
        ok = self._send_setpoint(self.setpoint_nm)
        if ok:
            self.submit_latency_s.append(self.clock() - t0)
        return ok

    def apply(self, msg, held: bool = False) -> None:  # noqa: ARG002
        """One batch with DriveCommand ``msg`` (validated by :meth:`problem`). ``held`` needs
        nothing here: the drive's own current loop holds a torque setpoint, and a setpoint is
        sent once (again only while ramping or after it was cleared)."""
        self.setpoint_nm = self._torque_of(msg)
        self.commanded = True
        if self.drive_enabled and (msg is not self.sent_msg or self.ramping):
            self.sent_msg = msg
            self._send_setpoint(self.setpoint_nm)
        self._advance()

    def safe_batch(self, n: int) -> None:  # noqa: ARG002
        """One batch without a (valid) DriveCommand."""
        if self.commanded and not self.safe and self.drive_enabled and self.setpoint_nm != 0.0:
            self.setpoint_nm = 0.0               # a rejected command: zero torque until the next good one
            self.sent_msg = None
            self._send_setpoint(0.0)
        self._advance()

    def set_safe(self, on: bool) -> None:
        """The node's DriveCommand timeout: zero torque, Set_Axis_State IDLE (not left to the
        drive's watchdog, which this plant's RTR requests may feed; see the module doc), and
        the setpoint is no longer repeated; off: re-arm with the next command.

        A stalled controller is no news about the drive: a drive armed when the safe state
        begins is released by this plant (its IDLE is no failed attempt), so its
        count starts over; one that was refusing keeps its count and backoff, and a give-up
        stands when DriveCommands resume (see :meth:`_arming`)."""
        if on and not self.safe:
            if self.drive_enabled:
                self.arm_attempts = 0
                self.first_attempt_s = None
                self.last_enable_s = -math.inf
            self.safe = True
            self.commanded = False
            self.setpoint_nm = 0.0
            self.sent_msg = None
            if self.link_alive:
                self._send_setpoint(0.0)
                self._idle_for_safe_state(self.clock())
            self.drive.forget_setpoint()
            self.counters["safe_state"] += 1
        elif not on and self.safe:
            self.safe = False

    def _idle_for_safe_state(self, now: float) -> None:
        """Set_Axis_State IDLE (drives with an armed state): the safe state does not rely on the
        drive's watchdog, which this plant's own RTR requests may feed (see the module doc)."""
        if not self.drive.has_arming:
            return
        self.safe_idle_s = now
        if self.drive.disable():
            self.counters["safe_idle"] += 1

    # ------------------------------------------------------------------ time and ledger
    def _advance(self) -> None:
        if self.time_frozen:
            self.counters["frozen_batches"] += 1
            return
        if self.stale:
            self.counters["stale_batches"] += 1
        dt = self.batch_periods * self.control_period_s
        v = self.drive.values()
        w = float(v.get("speed_rev_s", 0.0)) * TWO_PI
        if self.omega0 is None:
            self.omega0 = w
        t_em = self._shaft_torque_nm(v)
        if "bus_voltage_v" in v and "bus_current_a" in v:   # (VESC: two status messages)
            self.e_battery_j += float(v["bus_voltage_v"]) * -float(v["bus_current_a"]) * dt
        self.e_shaft_j += -t_em * w * dt
        self.e_friction_j += mechanics.friction_torque_nm(w, self.friction_nms, self.dry_friction_nm,
                                                          self.dry_friction_speed_rad_s) * w * dt
        self.time_s += dt

    def _shaft_torque_nm(self, v: dict) -> float:
        """The shaft's torque: the drive's estimate (kt Iq), through the torque map if there is one."""
        t = float(v.get("torque_estimate_nm", 0.0))
        if self.torque_map is None or t == 0.0:
            return t
        return self.torque_map.true_nm_at(float(v.get("speed_rev_s", 0.0)) * RPM_PER_REV_S, t)

    # ------------------------------------------------------------------ PlantState
    def snapshot(self) -> dict:
        v = self.drive.values()
        rev_s = float(v.get("speed_rev_s", 0.0))
        w = rev_s * TWO_PI
        pos = float(v.get("position_rev", 0.0))
        theta_m = TWO_PI * (pos - math.floor(pos))
        theta_e = (self.pole_pairs * theta_m) % TWO_PI
        iq = float(v.get("iq_measured_a", 0.0))
        ia = -iq * math.sin(theta_e)
        ib = -iq * math.sin(theta_e - TWO_PI / 3.0)
        ic = -iq * math.sin(theta_e + TWO_PI / 3.0)
        stored = 0.5 * self.inertia_kgm2 * (w * w - self.omega0 * self.omega0) if self.omega0 is not None else 0.0
        mech_in = self.e_shaft_j + self.e_friction_j + stored
        vbus = float(v.get("bus_voltage_v", math.nan))
        ibat = -float(v["bus_current_a"]) if "bus_current_a" in v else math.nan
        return {
            "machine": self.machine,
            "control_period_s": self.control_period_s,
            "phase_current_a": [ia, ib, ic],
            "rotor_angle_elec_rad": theta_e,
            "rotor_angle_mech_rad": theta_m,
            "speed_rad_s": w,
            "speed_rpm": rev_s * RPM_PER_REV_S,
            "hall_state": 0,
            "timer_count": 0,
            "dc_bus_v": vbus,
            "brake_resistor_on": False,
            "hall_edge_counts": [],
            "hall_edge_states": [],
            "torque_em_nm": self._shaft_torque_nm(v),
            "load_torque_nm": math.nan,
            "current_samples_a": [],
            "battery_ocv_v": math.nan,
            "battery_soc": math.nan,
            "battery_current_a": ibat,
            "energy_mech_in_j": mech_in,
            "energy_battery_j": self.e_battery_j,
            "energy_resistor_j": 0.0,
            "energy_loss_j": mech_in - self.e_battery_j - stored,
            "energy_stored_j": stored,
            "faults": self.faults,
            "interlock_blanked_count": 0,
        }

    # ------------------------------------------------------------------ statistics and diagnostics
    def stats(self) -> dict:
        """CAN statistics: frames (rx without our own frames echoed by the bus), drops by
        reason, requests, setpoints, link events."""
        c = self.drive.counters
        out = {
            "rx_frames": c["rx_frames"] - c["echo"], "tx_frames": c["tx_frames"], "decoded": c["decoded"],
            "dropped": self.drive.dropped, "echo": c["echo"], "other_node": c["other_node"],
            "other_direction": c["other_direction"], "tx_failed": c["tx_failed"],
            "heartbeats": c[f"rx:{self.drive.status_message}"], "requests": self.counters["requests"],
            "setpoints": self.counters["setpoints"], "keepalive": self.counters["keepalive"],
            "torque_clamped": self.counters["torque_clamped"], "drive_lost": self.counters["drive_lost"],
            "drive_back": self.counters["drive_back"], "armed": self.counters["armed"],
            "disarmed": self.counters["disarmed"], "enable_attempts": self.counters["enable_attempts"],
            "safe_state": self.counters["safe_state"], "safe_idle": self.counters["safe_idle"],
            "frozen_batches": self.counters["frozen_batches"],
            "arm_gave_up": self.counters["arm_gave_up"], "ramped_setpoints": self.counters["ramped_setpoints"],
            "heartbeat_gaps": self.counters["heartbeat_gaps"], "taken_over": self.counters["taken_over"],
            "foreign_commands": self.counters["foreign_commands"], "bus_reopened": self.counters["bus_reopened"],
            "heartbeat_gap_max_ms": round(self.heartbeat_gap_max_s * 1e3, 1),
            "stale_episodes": self.counters["stale_episodes"], "stale_batches": self.counters["stale_batches"],
        }
        for reason in MALFORMED_REASONS:
            if c[reason]:
                out[f"dropped_{reason}"] = c[reason]
        if c["unused_message"]:       # valid frames this plant has no use for (e.g. Get_Temperature)
            out["unused_message"] = c["unused_message"]
        if self.logger is not None:
            out["log_frames"] = self.log_frames
        if self.counters["log_errors"]:
            out["log_errors"] = self.counters["log_errors"]
        if self.torque_map is not None:
            out["torque_map_outside"] = self.torque_map.outside
        if self.submit_latency_s:
            lat = sorted(self.submit_latency_s)
            out["submit_latency_p50_us"] = round(lat[len(lat) // 2] * 1e6, 1)
            out["submit_latency_max_us"] = round(lat[-1] * 1e6, 1)
        return out

    def diagnostic_level(self) -> int:
        """The level :meth:`diagnostic` would report (cheap: for change detection per batch)."""
        if not self.seen:
            return WARN
        if self.lost or self.drive.active_errors or self.disarmed:
            return ERROR
        return OK if self.drive.enabled and not self.stale else WARN

    def diagnostic(self, now_s: float | None = None) -> tuple[int, list[str], dict[str, str]]:
        """(level, reasons, key/values) for the plant's DiagnosticStatus."""
        now = self.clock() if now_s is None else now_s
        drive = self.drive
        p = self.params
        reasons: list[str] = []
        level = OK
        if not self.seen:
            level = WARN
            hint = self._link_hint()[1] if now - self.started_s >= LINK_HINT_AFTER_S else ""
            reasons.append(f"waiting for the drive's {drive.status_message} ({p.describe()}, "
                           f"{now - self.started_s:.0f}s)" + (f": {hint}" if hint else "") + ": sim time paused")
        elif self.lost:
            level = ERROR
            silent = max(drive.heartbeat_age_s(now), self.lost_gap_s or 0.0)
            hint = self._link_hint()[1] if self.lost_since_s is not None and \
                now - self.lost_since_s >= LINK_HINT_AFTER_S else ""
            hint = "; ".join(h for h in (self.heartbeat_period_hint(), hint) if h)
            reasons.append(f"drive silent for {silent:.2f}s (heartbeat_timeout_s="
                           f"{p.heartbeat_timeout_s:g}s)" + (f": {hint}" if hint else "")
                           + ": zero torque commanded, sim time paused")
        else:
            errors = error_names(drive.active_errors)
            if errors:
                level = ERROR
                reasons.append(f"drive errors: {', '.join(errors)}")
            if not drive.enabled:
                disarmed = self.disarmed
                level = max(level, ERROR if disarmed else WARN)
                max_attempts = p.enable_max_attempts or "unlimited"
                if self.estop:
                    why = ("emergency stop (ESTOP_REQUESTED): this plant never clears it; clear it on the drive "
                           "(odrivetool: odrv0.clear_errors()) and it re-arms")
                elif self.gave_up:
                    why = (f"gave up re-arming after {self.arm_attempts} attempts; the plant tries again when the "
                           "drive's errors change or after it reboots (or in a new run), or takes it over when it "
                           "is armed by other means")
                elif self.commanded and not self.safe:
                    why = (f"re-arming (Clear_Errors + closed loop), attempt {self.arm_attempts} of {max_attempts}, "
                           f"next in {max(0.0, self.last_enable_s + self.retry_interval_s() - now):.1f}s")
                elif self.safe and drive.has_arming:
                    why = "set IDLE by this plant: no DriveCommands (safe state), re-armed when they are back"
                else:
                    why = "waiting for DriveCommands"
                because = f", disarm reason {', '.join(error_names(self.disarm_reason))}" if self.disarm_reason else ""
                reasons.append(f"drive {'disarmed' if disarmed else 'idle'}: alive but not in closed-loop control "
                               f"({self._axis_text()}{because}): {why}; sim time paused")
            if self.stale:
                level = max(level, WARN)
                reasons.append(self._stale_text() + ": the controller holds its trim")
        values = {f"can_{k}": str(v) for k, v in self.stats().items()}
        v = drive.values(now)
        values.update({
            "can_interface": p.interface, "can_channel": p.channel, "can_node_id": str(p.node_id),
            "can_link": "lost" if self.lost else ("alive" if self.seen else "waiting"),
            "can_arming": ("estop" if self.estop and not self.drive_enabled else "gave_up" if self.gave_up
                           else "armed" if self.drive_enabled
                           else f"attempt {self.arm_attempts}" if self.arm_attempts else "idle"),
            "can_axis_state": str(drive.axis_state) if drive.has_arming else "none",
            "can_axis_error": "|".join(error_names(drive.active_errors)) or "none",
            "can_heartbeat_age_ms": f"{drive.heartbeat_age_s(now) * 1e3:.0f}" if self.seen else "inf",
            "can_torque_setpoint_nm": f"{self.setpoint_nm:.4f}",
        })
        if drive.has_arming:
            values["can_disarm_reason"] = "|".join(error_names(self.disarm_reason)) or "none"
        if p.protocol != CanParams.protocol:      # (the default, ODrive, keeps its diagnostic as it was)
            values["can_protocol"] = p.protocol
        if "torque_target_nm" in v:
            values["can_torque_target_nm"] = f"{v['torque_target_nm']:.4f}"
        if self.torque_map is not None:
            values["can_torque_map"] = self.torque_map.describe()
            values["can_torque_estimate_nm"] = f"{float(v.get('torque_estimate_nm', 0.0)):.4f}"
        if self.log_path is not None:
            values["can_log_file"] = str(self.log_path)
        return level, reasons, values

    # ------------------------------------------------------------------ shutdown
    def close(self) -> None:
        """Zero torque and IDLE (``idle_on_exit``), close the log and the bus. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            if self.params.idle_on_exit and self.seen:
                self._send_setpoint(0.0)
                self.drive.disable()
        except Exception:  # noqa: BLE001
            pass
        if self.logger is not None:
            try:
                self.logger.stop()
            except Exception:  # noqa: BLE001
                pass
        self._shutdown_bus()

    def _shutdown_bus(self) -> None:
        if self._own_bus and self.bus is not None:
            try:
                self.bus.shutdown()
            except Exception:  # noqa: BLE001
                pass
