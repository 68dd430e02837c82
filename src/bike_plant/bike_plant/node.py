"""plant_node: the machine side of the bike as a ROS 2 node (thin adapter, no physics here).

Topics (relative names, namespace /bike by default; docs/DESIGN.md):
  publishes  /clock (rosgraph_msgs/Clock, every ``clock_period_s`` of sim time),
             plant_state (bike_msgs/PlantState),
             battery (sensor_msgs/BatteryState, every ``battery_every`` batches),
             /diagnostics (diagnostic_msgs/DiagnosticArray: on fault changes and every
             ``diagnostics_period_s`` wall seconds)
  subscribes drive_command (bike_msgs/DriveCommand)

sync_mode lockstep: publish PlantState(seq=k) (and /clock = t_k when due), wait for DriveCommand(seq=k),
  validate, apply with step_batch, repeat. The first state goes out once the controller is
  matched (a plant_state subscriber and a drive_command publisher); the pending state is
  re-published every ``republish_s`` wall seconds without an answer (late joiners, a lost
  first message). The loop is single-threaded: ``executor.spin_once`` until the answer is
  in (measured faster than a spinning thread + threading.Event). With
  ``recorder_window_batches`` > 0 (set by ``./bike run --record``) the plant first waits for
  the recorder too, and never runs more than that many batches ahead of the last seq the
  recorder reports on ``recorder_progress``: a slow recorder slows the run instead of losing
  messages. A recorder silent for ``recorder_timeout_s`` is given up on (ERROR diagnostic,
  the run goes on unrecorded rather than hanging).
sync_mode realtime: one batch per wall-clock batch period (with ``recorder_window_batches`` > 0
  the first waits for the recorder, at most ``recorder_timeout_s``). Sim time starts when the loop
  is closed: t = 0 is held (seq 0 and /clock 0 re-published every 0.1 s, no batch applied) until
  the controller's first DriveCommand, at most ``start_timeout_s``, then runs without one (safe
  state) and says so. The newest valid DriveCommand is
  applied; without a new one the last one is held (re-used); with none for
  ``command_timeout_s`` the plant goes to its safe state (all gates off) with
  FAULT_COMMAND_TIMEOUT and an ERROR diagnostic, cleared when commands return. Sim time
  (/clock, stamps) advances by one batch per tick, i.e. it follows wall time.
A DriveCommand that cannot be applied (lengths != batch_periods, split not finite / outside
[0, 1], gate values >= 64) is rejected: FAULT_BAD_COMMAND, a diagnostic, all gates off for
that batch. At ``duration_s`` of sim time (0 = forever) the node publishes a last PlantState
with end_of_run = true, lingers ``end_linger_s`` so subscribers receive it, and exits 0.
SIGINT / SIGTERM end the node cleanly (exit 0).

Backends: ``backend: sim`` (BldcPlant / SpmsmPlant) and ``backend: can`` (a real or emulated
drive on a python-can bus, ODrive CANSimple 0.6.x: bike_plant.can.backend.CanBackend; realtime
only). With ``can`` the drive's firmware owns the current loop: each DriveCommand's
``torque_cmd_nm`` goes out as a torque setpoint the moment it arrives, PlantState carries the
drive's measurements (``measured_by_drive``), and sim time stands still (no /clock, PlantState
keeps its stamp) while the drive is not armed or lost (FAULT_DRIVE_LOST after the
heartbeat timeout, an ERROR diagnostic, zero torque) or alive but disarmed
(FAULT_DRIVE_DISARMED: tripped, errors, IDLE; re-armed with a bounded retry policy), so the
session pauses; it resumes when the drive is back and re-armed. CAN statistics are part of
the plant's diagnostic (``can_*``).
"""
from __future__ import annotations

import functools
import math
import os
import signal
import sys
import time

import rclpy
from bike_msgs.msg import DriveCommand, HeartRate, PlantState
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import BatteryState

from . import msgconv, shm_ports
from .config import ConfigError
from .config import (BATCH_PERIODS, CLOCK_PERIOD_S, CONTROL_PERIOD_S, check_backend_sync_mode, check_batch_length,
                     check_clock_period, plant_number, recorder_window_batches, sync_mode_of)
from .heart import heart_rate_reading_problem
from .loop import (AUX_QOS, LOCKSTEP_BUSY_WAIT_S, LOOP_QOS, BusyWaitGuard, HotWait, loop_reader_qos,
                   recorder_progress, recorder_reads, say_stale_peer_and_start_over, start_over_on_fresh_ports,
                   take_sim_time_from_messages, wait_for_new_matches)
from .memory import LoadTimePageReleaser

# the start-up wait for a recorder: matching its reader took ~3 s on a loaded 2-core machine,
# longer than a recorder_timeout_s chosen to notice a lost recorder quickly
RECORDER_START_MIN_S = 10.0
FIRST_STATE_REPUBLISH_S = 0.1    # recording: seq 0 again this often until the recorder reports it [wall s]
LATE_READER_WAIT_S = 1.0         # lockstep: at most this long for listed /clock and battery readers to match
PROGRESS_EVERY_S = 10.0          # lockstep: a progress line this often [wall s]
PLANT_DEFAULTS = {
    "backend": "sim",
    "sync_mode": "lockstep",
    "batch_periods": BATCH_PERIODS,
    "control_period_s": CONTROL_PERIOD_S,
    "command_timeout_s": 0.05,
    "duration_s": 0.0,
    "seed": 0,
    "republish_s": 1.0,
    "end_linger_s": 0.1,
    "battery_every": 10,
    "clock_period_s": CLOCK_PERIOD_S,
    "busy_wait_s": LOCKSTEP_BUSY_WAIT_S,
    "diagnostics_period_s": 1.0,
    "recorder_window_batches": 0,
    "recorder_timeout_s": 10.0,
    "start_timeout_s": 120.0,
    "can_log_file": "",
}
# the end_of_run PlantState's acknowledgment by every reliable reader is awaited this long at
# most (longer than Fast DDS's 3 s heartbeat period, which is when a lost last sample is repaired)
END_ACK_TIMEOUT_S = 4.0
HEART_RATE_TIMEOUT_S = 5.0       # CAN backend: a strap silent this long -> no heart rate (it sends ~1 Hz) [wall s]

PLANT_DESCRIPTIONS = {
    "republish_s": "lockstep: re-publish the pending PlantState after this many wall seconds without an answer",
    "end_linger_s": "wall seconds to keep running after the end_of_run PlantState so subscribers receive it",
    "battery_every": "publish sensor_msgs/BatteryState every this many batches",
    "busy_wait_s": ("lockstep: poll for the DriveCommand this many wall seconds before blocking (0 = block at once; "
                    "held at 0 while a third node reads plant_state)"),
    "clock_period_s": "publish /clock when sim time reaches the next multiple of this many sim seconds "
                      "(0 = with every PlantState); the first and the last state always carry one",
    "diagnostics_period_s": "publish a diagnostic at least this often [wall s]",
    "recorder_window_batches": "lockstep: wait for the recorder and stay at most this many batches ahead of it; "
                               "realtime: > 0 waits for the recorder before the first batch "
                               "(0 = do not wait for a recorder)",
    "recorder_timeout_s": "give up waiting for a silent or absent recorder after this many wall seconds",
    "start_timeout_s": "lockstep: exit with an error when no controller appears, or none answers a PlantState, "
                       "within this many wall seconds; realtime: hold t = 0 at most this long for the controller's "
                       "first DriveCommand, then run in the safe state (0 = wait forever)",
    "can_log_file": "backend can: log every CAN frame to this .asc / .blf file (overrides can.log_file; "
                    "./bike run --record puts it beside the bag)",
}

FAULT_NAMES = {
    PlantState.FAULT_INTERLOCK: "INTERLOCK",
    PlantState.FAULT_COMMAND_TIMEOUT: "COMMAND_TIMEOUT",
    PlantState.FAULT_OVERVOLTAGE: "OVERVOLTAGE",
    PlantState.FAULT_BAD_COMMAND: "BAD_COMMAND",
    PlantState.FAULT_DRIVE_LOST: "DRIVE_LOST",
    PlantState.FAULT_RECORDER_LOST: "RECORDER_LOST",
    PlantState.FAULT_RELAY_FORCED: "RELAY_FORCED",
    PlantState.FAULT_UNCONTROLLED_GENERATION: "UNCONTROLLED_GENERATION",
    PlantState.FAULT_DRIVE_DISARMED: "DRIVE_DISARMED",
    PlantState.FAULT_OVERCURRENT: "OVERCURRENT",      # WARN: the trip already blanked the gates
    PlantState.FAULT_DRIVE_STALE: "DRIVE_STALE",      # WARN: the controller holds its trim meanwhile
    PlantState.FAULT_PACK_EMPTY: "PACK_EMPTY",        # WARN: the session holds assist at 0 meanwhile
}
ERROR_FAULTS = (PlantState.FAULT_COMMAND_TIMEOUT | PlantState.FAULT_OVERVOLTAGE | PlantState.FAULT_DRIVE_LOST
                | PlantState.FAULT_RECORDER_LOST | PlantState.FAULT_DRIVE_DISARMED)


def fault_text(bits: int) -> str:
    return "|".join(name for bit, name in FAULT_NAMES.items() if bits & bit) or "none"


class StartupTimeout(ConfigError):
    """Lockstep: the graph never came together (reported as one error, exit code 2)."""

    def __init__(self, message: str):
        Exception.__init__(self, message)


# ---------------------------------------------------------------- backends
class SimBackend:
    """The simulated BLDC bike (bike_plant.sim.BldcPlant) behind the node's backend interface:
    time_s, snapshot(), problem(msg, n), apply(msg, held), safe_batch(n), set_safe(on)."""

    name = "sim"
    measured_by_drive = False
    # the CAN backend's optional hooks, absent here: the node's getattr(backend, name, None) per
    # batch then finds them at once (a missing attribute raised and caught an AttributeError)
    submit = diagnostic_level = None
    time_frozen = False

    def problem(self, msg, n: int) -> str | None:
        return msgconv.drive_command_problem(msg, n)

    def apply(self, msg, held: bool = False) -> None:
        """A DriveCommand that passed problem(): its arrays go to the kernel as they are; held
        (realtime: the loop re-applies last batch's command) relative to the rotor
        (BldcPlant.step_held_batch)."""
        self.plant.set_rider_cadence(msg.rider_cadence_rpm, stop=bool(msg.rider_stops_pedalling))
        if held and self.plant.last_inputs is not None:
            self.plant.step_held_batch()
            return
        self.plant.step_batch(*msgconv.drive_arrays(msg), checked=True)

    def __init__(self, cfg: dict, seed: int):
        from .params import plant_params_from_config
        from .sim import BldcPlant

        self.plant = BldcPlant(plant_params_from_config(cfg), seed=seed)

    @property
    def time_s(self) -> float:
        return self.plant.time_s

    def snapshot(self) -> dict:
        return self.plant.snapshot()

    def safe_batch(self, n: int) -> None:
        self.plant.step_batch(*self.plant.safe_gates(n))

    def warm_up(self, n: int) -> None:
        """_warm_up_twin with all gates off."""
        import numpy as np
        _warm_up_twin(self, msgconv.drive_command_cdr(
            0, np.zeros(n, np.uint8), np.zeros(n, np.uint8), np.zeros(n, np.float32), 0), n)

    def set_safe(self, on: bool) -> None:
        if on:
            self.plant.set_safe_state()
        else:
            self.plant.clear_safe_state()


class SpmsmSimBackend:
    """The simulated SPMSM bike (bike_plant.spmsm.SpmsmPlant, paper 001), same interface."""

    name = "sim"
    measured_by_drive = False
    submit = diagnostic_level = None        # as SimBackend's
    time_frozen = False

    def __init__(self, cfg: dict, seed: int):  # noqa: ARG002 - the SPMSM model has no random part
        from . import spmsm as M

        try:
            self.plant = M.SpmsmPlant(M.plant_params_from_config(cfg))
        except ValueError as exc:
            raise ConfigError(str(exc), cfg.get("_config_path")) from None
        self.n_last = 0
        # the model's own fault bits -> the PlantState bits (the numbers differ), looked up once
        self._fault_bits = ((M.FAULT_RELAY_FORCED, PlantState.FAULT_RELAY_FORCED),
                            (M.FAULT_OVERSPEED_DIODES, PlantState.FAULT_UNCONTROLLED_GENERATION),
                            (M.FAULT_PACK_OVERCHARGE, PlantState.FAULT_OVERVOLTAGE),
                            (M.FAULT_PACK_EMPTY, PlantState.FAULT_PACK_EMPTY))

    @property
    def time_s(self) -> float:
        return self.plant.time_s

    def snapshot(self) -> dict:
        snap = self.plant.snapshot()
        snap["relay_state"] = min(int(snap.get("relay_state", 0)), PlantState.RELAY_SWITCHING)
        model_faults = int(snap.get("faults", 0))
        faults = 0
        if model_faults:
            for model_bit, bit in self._fault_bits:
                if model_faults & model_bit:
                    faults |= bit
        snap["faults"] = faults
        return snap

    def problem(self, msg, n: int) -> str | None:
        return msgconv.spmsm_drive_problem(msg, n)

    def apply(self, msg, held: bool = False) -> None:
        """As SimBackend.apply; held keeps the command's rotor-frame voltage (SpmsmPlant.step_held_batch)."""
        self.plant.set_rider_cadence(msg.rider_cadence_rpm, stop=bool(msg.rider_stops_pedalling))
        if held and self.plant.last_inputs is not None:
            self.plant.step_held_batch()
            return
        # checked: problem() passed the arrays, and their conversions are new (the plant may keep them)
        self.plant.step_batch(*msgconv.spmsm_drive_arrays(msg), checked=True)

    def safe_batch(self, n: int) -> None:
        self.plant.set_safe_state()
        try:
            self.plant.step_safe_batch(n)
        finally:
            if not self._safe:
                self.plant.clear_safe_state()

    _safe = False

    def warm_up(self, n: int) -> None:
        """_warm_up_twin with duties 0.5 and the relay on the inverter."""
        import numpy as np
        _warm_up_twin(self, msgconv.spmsm_drive_cdr(
            0, np.full((n, 3), 0.5, np.float32), np.zeros(n, np.float32), np.ones(n, np.float32), 0), n)

    def set_safe(self, on: bool) -> None:
        self._safe = bool(on)
        if on:
            self.plant.set_safe_state()
        else:
            self.plant.clear_safe_state()


def _warm_up_twin(backend, raw: bytes, n: int) -> None:
    """Run the node's per-batch path once on a copy of ``backend``'s plant: the DriveCommand
    ``raw`` through the CDR view, the check, a batch, the same batch held; the safe batch; the
    snapshot. numba then compiles or loads the kernels now, not inside the run."""
    import copy
    twin = copy.copy(backend)
    twin.plant = copy.deepcopy(backend.plant)
    view = msgconv.DriveCommandView(raw)
    if twin.problem(view, n) is None:
        twin.apply(view)
        twin.apply(view, held=True)             # (the SPMSM plant turns held duties in a kernel of its own)
    twin.safe_batch(n)
    twin.snapshot()


def make_backend(kind: str, cfg: dict, seed: int):
    machine = str(cfg.get("machine", "bldc"))
    if machine not in ("bldc", "spmsm"):
        raise ConfigError(f"unknown machine {machine!r} (bldc | spmsm)", cfg.get("_config_path"), "machine")
    if kind == "sim":
        return SpmsmSimBackend(cfg, seed) if machine == "spmsm" else SimBackend(cfg, seed)
    if kind == "can":
        check_backend_sync_mode(kind, str(cfg.get("sync_mode", "lockstep")), cfg.get("_config_path"))
        from .can.backend import CanBackend
        return CanBackend(cfg, log_file=str(cfg.get("can_log_file") or "") or None)
    raise ConfigError(f"unknown backend {kind!r} (sim | can)", cfg.get("_config_path"), "backend")


# ---------------------------------------------------------------- the node
# what a running plant's new node on fresh ports takes over from the old one (PlantNode.hand_over):
# the simulation (the backend: model state, a CAN drive's bus) and the run's bookkeeping
RUN_STATE = ("backend", "k", "next_clock_ns", "clock_ns", "recorder_seq", "recorder_rx", "recorder_window",
             "node_faults", "stats", "wall0", "problem", "heart_rate", "drive_heard", "latest", "latest_rx",
             "latest_rx_sim_s", "_last_snap", "_last_stamp", "_last_state")


class PlantNode(Node):
    def __init__(self, carry=None, **kwargs):
        """``carry``: the running plant this node goes on from on fresh ports (hand_over)."""
        super().__init__("plant", **kwargs)
        from .rosparams import declare_config

        self.cfg = cfg = declare_config(self, PLANT_DEFAULTS, PLANT_DESCRIPTIONS)
        path = cfg.get("_config_path")
        self.sync_mode = sync_mode_of(cfg, path)
        self.n = plant_number(cfg, "batch_periods", path)
        self.dt = plant_number(cfg, "control_period_s", path)
        self.duration_s = plant_number(cfg, "duration_s", path)
        self.command_timeout_s = plant_number(cfg, "command_timeout_s", path)
        self.republish_s = plant_number(cfg, "republish_s", path)
        self.end_linger_s = plant_number(cfg, "end_linger_s", path)
        self.battery_every = plant_number(cfg, "battery_every", path)
        self.busy_wait_s = plant_number(cfg, "busy_wait_s", path) if self.sync_mode == "lockstep" else 0.0
        # /clock at a sim-time rate, not per batch: at 1 ms batches a /clock per batch woke the
        # session's process 1000 times per sim second, about 5 % of a core taken from the loop
        # (measured: lockstep 2.2x -> 2.4x real time at N = 20). The session publishes its
        # Commands a period (0.1 s) ahead, so a 10 ms clock still keeps them ahead of the loop.
        clock_period_s = plant_number(cfg, "clock_period_s", path)
        check_clock_period(clock_period_s, (cfg.get("session") or {}).get("period_s"), path)
        check_batch_length(self.n, self.dt, (cfg.get("session") or {}).get("period_s"), path)
        self.clock_period_ns = round(clock_period_s * 1e9)
        self.next_clock_ns = 0       # the next /clock goes out at the first stamp >= this
        self.clock_ns = None         # the last /clock value published
        self.diag_period_s = plant_number(cfg, "diagnostics_period_s", path)
        self.batch_s = self.n * self.dt
        self.recorder_window = recorder_window_batches(cfg, path)       # below the LOOP_QOS history
        self.recorder_window_cfg = self.recorder_window        # restored when a lost recorder reports again
        self.recorder_timeout_s = plant_number(cfg, "recorder_timeout_s", path)
        self.start_timeout_s = plant_number(cfg, "start_timeout_s", path)
        self.backend = carry.backend if carry is not None else make_backend(
            str(cfg.get("backend")), cfg, plant_number(cfg, "seed", path))
        from .params import rider_preset_overrides
        preset_note = rider_preset_overrides(cfg["load"]) if isinstance(cfg.get("load"), dict) else None
        if preset_note and carry is None:
            self.get_logger().warning(preset_note)
        if hasattr(self.backend, "warm_up") and carry is None:
            # before the node joins the graph: a compile inside the run held its first batches
            # for ~30 s and made the controller report a stopped plant
            warm_up_kernels(self.get_logger(), lambda: self.backend.warm_up(self.n))
        # The plant is the clock source: its stamps are the model's time.
        take_sim_time_from_messages(self)

        self.pub_clock = self.create_publisher(Clock, "/clock", LOOP_QOS)
        self.pub_state = self.create_publisher(PlantState, "plant_state", LOOP_QOS)
        self.pub_battery = self.create_publisher(BatteryState, "battery", AUX_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", AUX_QOS)
        # taken serialized, decoded by msgconv.DriveCommandView (bike_plant.cdr: the hot path)
        self.sub_drive = self.create_subscription(DriveCommand, "drive_command", self._on_drive,
                                                  loop_reader_qos(self.sync_mode), raw=True)
        # a drive on CAN has no rider model of its own: the rider's heart rate comes from his chest
        # strap (or the drive emulator's rider) on heart_rate, the newest fresh one into the state
        self.heart_rate = (0.0, -math.inf)      # (bpm, monotonic receipt time)
        if self.backend.measured_by_drive:
            self.sub_heart_rate = self.create_subscription(HeartRate, "heart_rate", self._on_heart_rate, AUX_QOS)
        self.recorder_seq = -1       # last plant_state seq the recorder reports written
        self.recorder_rx = 0.0
        # lockstep: seq 0's /clock and BatteryState as sent, each with its writer's matched
        # readers then (_resend_seq_0_to_late_readers)
        self._seq0_sent: list = []
        if self.recorder_window > 0:
            from std_msgs.msg import UInt64
            self.sub_progress = self.create_subscription(
                UInt64, "recorder_progress", self._on_progress,
                QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.executor_ = SingleThreadedExecutor(context=self.context)     # a started-over node's own
        self.executor_.add_node(self)
        self.hot = HotWait(self.executor_, [self.sub_drive] + ([self.sub_progress] if self.recorder_window > 0 else []),
                           self.context, logger=self.get_logger())
        self.busy = BusyWaitGuard(self, [self.pub_state], "drive_command", self.busy_wait_s)

        self.diag_name = f"{self.get_namespace().rstrip('/')}/{self.get_name()}".lstrip("/") or "plant"
        self.stop_requested = False
        self.drive_heard = False     # any DriveCommand bytes yet (_check_deaf_start)
        self.deaf_watch = shm_ports.StalePortWatch()     # from the wait for the first DriveCommand
        self.peer_watch = shm_ports.StalePeerWatch()     # running: from the first DriveCommand (_check_stale_peers)
        self.carry_on = False        # fresh ports wanted for a running plant: run_loop_node hands over
        self.carried = carry is not None
        self.k = 0                   # batches applied
        self.pending_seq = -1        # lockstep: seq we wait for
        self.answer = None           # lockstep: DriveCommand(seq=pending_seq)
        self.latest = None           # realtime: newest DriveCommand received
        self.latest_rx = None        # realtime: wall time it arrived
        self.latest_rx_sim_s = math.nan  # realtime: sim time of the batch during which it arrived
        self.holding_start = False       # realtime: t = 0 held for the first DriveCommand (_hold_start)
        self.wait_reason = ""        # lockstep: why the run is held (no answer), for the diagnostic
        # the last published state's snapshot and stamp, for diagnostics; empty before the first
        # (a deaf start found while lockstep still waits for the controller's match says so too)
        self._last_snap, self._last_stamp = {}, 0
        self.wait_level = _level(DiagnosticStatus.WARN)
        self.node_faults = 0
        self.last_faults = -1
        self.last_drive_level = 0
        self.last_diag_wall = 0.0
        self.wall0 = time.monotonic()  # diagnostics give wall_s beside sim_time_s: the plant's own pace
        self.problem = ""            # why the last bad command was rejected
        # overruns / overrun_dropped_s (realtime): resynchronisations after falling behind wall
        # time, and the wall time they skipped (sim time lags wall time by exactly that)
        self.stats = {"stale_commands": 0, "bad_commands": 0, "republished": 0, "held_batches": 0,
                      "timeout_batches": 0, "overruns": 0, "overrun_dropped_s": 0.0}
        if carry is not None:
            for name in RUN_STATE:
                setattr(self, name, getattr(carry, name))
            self.peer_watch.fired = True     # once per process (shm_ports.stale_port_check)
            self.get_logger().info(f"going on with the run at seq {self.k}, t={self.backend.time_s:.6f}s")
            return
        self.get_logger().info(
            f"plant: backend={self.backend.name} sync_mode={self.sync_mode} N={self.n} "
            f"T={self.dt:g}s duration={self.duration_s:g}s config={path}")

    # ------------------------------------------------------------ callbacks
    def _on_drive(self, raw: bytes) -> None:
        self.drive_heard = True
        try:
            msg = msgconv.DriveCommandView(raw)
        except msgconv.CdrError as exc:
            # not a DriveCommand at all (a foreign writer): its seq is unknown, so it answers
            # no batch; lockstep re-publishes the state and waits on, realtime holds or times out
            self.stats["bad_commands"] += 1
            if not self.node_faults & PlantState.FAULT_BAD_COMMAND:
                self.get_logger().warning(f"undecodable DriveCommand ({len(raw)} bytes) dropped: {exc}")
            self.node_faults |= PlantState.FAULT_BAD_COMMAND
            return
        if self.sync_mode == "lockstep":
            if msg.seq == self.pending_seq and self.answer is None:
                self.answer = msg
            else:
                self.stats["stale_commands"] += 1
        else:
            self.latest = msg
            self.latest_rx = time.monotonic()
            self.latest_rx_sim_s = self.backend.time_s
            submit = getattr(self.backend, "submit", None)
            if submit is not None:               # CAN: the setpoint goes out now, not at the next tick
                submit(msg, self.n)

    def _on_progress(self, msg) -> None:
        self.recorder_seq = recorder_progress(self.recorder_seq, int(msg.data), self.k)
        self.recorder_rx = time.monotonic()
        if (self.sync_mode == "lockstep" and self.recorder_window <= 0 < self.recorder_window_cfg
                and self.node_faults & PlantState.FAULT_RECORDER_LOST):
            # a recorder reports again (restarted, or the slow one caught up): flow control
            # resumes, else a loop faster than the recorder would overrun the writer's history
            # and the new bag would have holes
            self.recorder_window = self.recorder_window_cfg
            self.node_faults &= ~PlantState.FAULT_RECORDER_LOST
            self.get_logger().info(f"a recorder reports again (written up to seq {int(msg.data)}, plant at "
                                   f"{self.k}): waiting for it again, at most {self.recorder_window} batches ahead")

    def _recorder_behind(self) -> bool:
        """More than the window behind, or seq 0 not yet confirmed before seq 1 goes out."""
        return self.k - self.recorder_seq > self.recorder_window or (self.k >= 1 and self.recorder_seq < 0)

    def _wait_for_recorder(self) -> None:
        """Lockstep flow control: block while the recorder is more than the window behind.

        Seq 1 also waits until the recorder has reported seq 0, which is re-published
        meanwhile (the recorder writes a copy once): on a starved machine a reader can match
        after the writer saw the graph list it, and seq 0 would be missing from the bag."""
        if self.recorder_window <= 0 or not self._recorder_behind():
            self._resend_seq_0_to_late_readers()
            return
        since = sent = time.monotonic()
        while not self.stop_requested and self._recorder_behind():
            self._spin(0.05)
            if self._check_stale_peers():    # (a restarted recorder whose reports go to a deleted segment)
                return
            if self.recorder_seq < 0 and time.monotonic() - sent > FIRST_STATE_REPUBLISH_S:
                # the state only: /clock again would make the session send its Commands again
                # (and say so) ten times a second; the controller answers with its cached reply
                self._republish(clock=False)
                sent = time.monotonic()
            if time.monotonic() - max(self.recorder_rx, since) > self.recorder_timeout_s:
                self.get_logger().error(
                    f"the recorder reported nothing for {self.recorder_timeout_s:g}s (last seq "
                    f"{self.recorder_seq}, plant at {self.k}): going on without waiting for it")
                self.node_faults |= PlantState.FAULT_RECORDER_LOST
                self.recorder_window = 0
                return
        self._resend_seq_0_to_late_readers()

    def _resend_seq_0_to_late_readers(self) -> None:
        """Lockstep, once the recorder has confirmed seq 0: seq 0's /clock and BatteryState
        again, each only if its writer has matched a reader since it went out.

        The recorder confirms seq 0 once every writer the graph lists has matched it, but
        DDS matches endpoint by endpoint: its PlantState reader can match in time (the plant
        waits for that one) and its /clock or battery reader just after t = 0 went out, and
        the bag would lack them (and differ from a run's twin). Nothing else sends them again.
        The recorder drops a copy it already has (byte-identical); the session takes /clock 0
        again as a held plant and sends its Commands in force again, which the recorder drops
        too. Graph queries: once per run, up to LATE_READER_WAIT_S while a listed reader is
        still unmatched."""
        if not self._seq0_sent or self.recorder_seq < 0:
            return
        sent, self._seq0_sent = self._seq0_sent, []
        deadline = time.monotonic() + LATE_READER_WAIT_S
        for pub, msg, readers_then in sent:
            listed = len(self.get_subscriptions_info_by_topic(pub.topic_name))
            while pub.get_subscription_count() < listed and time.monotonic() < deadline and not self.stop_requested:
                self._spin(0.02)
            if pub.get_subscription_count() > readers_then:
                pub.publish(msg)
                self.stats["republished"] += 1

    def _on_heart_rate(self, msg) -> None:
        bpm = float(msg.heart_rate_bpm)
        problem = heart_rate_reading_problem(bpm)
        if problem:
            self.get_logger().warning(f"heart_rate dropped: {problem}", throttle_duration_sec=10.0)
            return
        self.heart_rate = (bpm, time.monotonic())

    # ------------------------------------------------------------ publishing
    def _publish_state(self, end_of_run: bool = False) -> None:
        snap = self.backend.snapshot()
        if self.backend.measured_by_drive:
            bpm, rx_s = self.heart_rate
            snap["heart_rate_bpm"] = bpm if time.monotonic() - rx_s <= HEART_RATE_TIMEOUT_S else 0.0
        snap["seq"] = self.k
        snap["batch_periods"] = self.n
        snap["backend"] = self.backend.name
        snap["measured_by_drive"] = self.backend.measured_by_drive
        snap["end_of_run"] = end_of_run
        faults = int(snap.get("faults", 0)) | self.node_faults
        snap["faults"] = faults
        stamp = msgconv.seconds_to_ns(self.backend.time_s)
        state = msgconv.plant_state_cdr(snap, stamp)      # serialized: no message object on the hot path
        # the state first: lockstep waits for its answer, and the controller computes it on
        # the other core while this process publishes /clock, the battery and diagnostics
        # (measured: 7 % more batches per second than the state last)
        self.pub_state.publish(state)
        first = self.k == 0 and self.recorder_window > 0 and not self._seq0_sent
        if (stamp >= self.next_clock_ns or end_of_run) and not getattr(self.backend, "time_frozen", False):
            # (CAN: no /clock while the drive is not armed)
            self._publish_clock(stamp)
            if first:
                self._seq0_sent.append((self.pub_clock, msgconv.clock_cdr(stamp),
                                        self.pub_clock.get_subscription_count()))
        self._last_snap, self._last_stamp, self._last_state = snap, stamp, state
        if self.k % self.battery_every == 0 or end_of_run:
            battery = self._publish_battery(snap, stamp)
            if first:
                self._seq0_sent.append((self.pub_battery, battery, self.pub_battery.get_subscription_count()))
        now = time.monotonic()
        drive_level_of = getattr(self.backend, "diagnostic_level", None)
        drive_level = drive_level_of() if drive_level_of is not None else 0
        changed = faults != self.last_faults or drive_level != self.last_drive_level or end_of_run
        if self._diag_if_due(snap, stamp, faults, now, changed):
            self.last_faults = faults
            self.last_drive_level = drive_level

    def _diag_if_due(self, snap: dict, stamp: int, faults: int, now: float, changed: bool = False) -> bool:
        """The diagnostic every ``diagnostics_period_s`` of wall time, or at once on a change."""
        if not (changed or now - self.last_diag_wall >= self.diag_period_s):
            return False
        self._publish_diag(snap, stamp, faults)
        self.last_diag_wall = now
        return True

    def _publish_clock(self, stamp: int) -> None:
        self.pub_clock.publish(msgconv.clock_cdr(stamp))
        self.clock_ns = stamp
        p = self.clock_period_ns
        self.next_clock_ns = (stamp // p + 1) * p if p > 0 else stamp + 1

    def _republish(self, clock: bool = True) -> None:
        """The pending state again, with the last /clock value again (the session then sends
        the Commands in force from that time again; the recorder drops both copies)."""
        if clock:
            if self.clock_ns is None:
                self._publish_clock(self._last_stamp)      # none yet (a CAN drive not armed): t = 0
            else:
                self.pub_clock.publish(msgconv.clock_cdr(self.clock_ns))
        self.pub_state.publish(self._last_state)
        self.stats["republished"] += 1

    def _publish_battery(self, snap: dict, stamp: int) -> BatteryState:
        msg = BatteryState()
        msg.header.stamp = msgconv.time_msg(stamp)
        msg.voltage = float(snap.get("dc_bus_v", math.nan))
        msg.current = float(snap.get("battery_current_a", math.nan))     # ROS: charging positive
        msg.percentage = float(snap.get("battery_soc", math.nan))
        msg.charge = math.nan
        msg.capacity = math.nan
        msg.design_capacity = math.nan
        msg.temperature = math.nan
        msg.power_supply_status = (BatteryState.POWER_SUPPLY_STATUS_CHARGING if msg.current > 0
                                   else BatteryState.POWER_SUPPLY_STATUS_DISCHARGING)
        msg.power_supply_health = BatteryState.POWER_SUPPLY_HEALTH_GOOD
        msg.power_supply_technology = BatteryState.POWER_SUPPLY_TECHNOLOGY_LION
        msg.present = True
        self.pub_battery.publish(msg)
        return msg

    def _publish_diag(self, snap: dict, stamp: int, faults: int) -> None:
        status = DiagnosticStatus()
        status.name = self.diag_name
        status.hardware_id = f"bike_plant/{self.backend.name}"
        if faults & ERROR_FAULTS:
            status.level = DiagnosticStatus.ERROR
        elif faults:
            status.level = DiagnosticStatus.WARN
        else:
            status.level = DiagnosticStatus.OK
        reasons = []
        if faults & PlantState.FAULT_COMMAND_TIMEOUT:
            reasons.append(f"no DriveCommand for more than command_timeout_s={self.command_timeout_s:g}s: "
                           f"safe state, {self.safe_state_text}")
        if faults & PlantState.FAULT_BAD_COMMAND:
            reasons.append(f"DriveCommand rejected: {self.problem}; all gates off for that batch")
        if faults & PlantState.FAULT_INTERLOCK:
            reasons.append("gate pattern with both switches of a leg on was blanked")
        if faults & PlantState.FAULT_OVERVOLTAGE:
            if snap.get("machine") == "spmsm":
                reasons.append("a full pack charged through the inverter (no dump on that path: a BMS would open)")
            elif float(snap.get("battery_soc", 0.0)) > 1.0:
                reasons.append(f"DC bus over the configured limit, or a full pack charged on (SOC "
                               f"{float(snap['battery_soc']):.3f}: the brake resistor cannot take the regenerated "
                               "power; a BMS would open)")
            else:
                reasons.append("DC bus over the configured limit")
        if faults & PlantState.FAULT_OVERCURRENT:
            reasons.append(f"overcurrent trip: a phase current above bldc.overcurrent_trip_a, gates blanked for "
                           f"{int(snap.get('overcurrent_trip_count', 0))} periods in total (stale gate decisions?)")
        if faults & PlantState.FAULT_RELAY_FORCED:
            reasons.append("relay opened under current after its drain timeout (energy booked as loss)")
        if faults & PlantState.FAULT_UNCONTROLLED_GENERATION:
            reasons.append("gates off but the inverter diodes conduct: uncontrolled generation (overspeed)"
                           if snap.get("machine") == "spmsm" else
                           "the back-EMF is above the DC bus: the bridge diodes brake whatever the gates do "
                           "(uncontrolled generation, overspeed)")
        if faults & PlantState.FAULT_PACK_EMPTY:
            reasons.append(f"battery empty (state of charge {float(snap.get('battery_soc', 0.0)):.4f}): no assist "
                           "from it, the session holds assist at 0 (a BMS's undervoltage cut-off); braking charges it")
        if faults & PlantState.FAULT_RECORDER_LOST:
            reasons.append(f"the recorder went silent for recorder_timeout_s={self.recorder_timeout_s:g}s: "
                           "the rest of the run is not recorded")
        if self.wait_reason:                        # lockstep: the controller stopped answering
            status.level = bytes([max(_level(status.level), self.wait_level)])
            reasons.append(self.wait_reason)
        if self.sync_mode == "realtime" and self.latest_rx is None and not faults:
            status.level = DiagnosticStatus.WARN
            reasons.append("waiting for the first DriveCommand ("
                           + ("drive idle" if self.backend.measured_by_drive else "gates off")
                           + (", sim time held at 0" if self.holding_start else "") + ")")
        drive_values = {}
        drive_diag = getattr(self.backend, "diagnostic", None)
        if drive_diag is not None:                  # CAN: link, drive errors, statistics
            level, drive_reasons, drive_values = drive_diag()
            current = status.level[0] if isinstance(status.level, (bytes, bytearray)) else int(status.level)
            status.level = bytes([max(current, level)])       # diagnostic_msgs' level is a byte
            reasons.extend(r for r in drive_reasons if r not in reasons)
        status.message = "; ".join(reasons) if reasons else "running"
        values = {
            "faults": str(faults), "fault_names": fault_text(faults), "seq": str(self.k),
            "sim_time_s": f"{stamp * 1e-9:.6f}", "wall_s": f"{time.monotonic() - self.wall0:.6f}",
            "sync_mode": self.sync_mode,
            "speed_rpm": f"{float(snap.get('speed_rpm', 0.0)):.1f}",
            "dc_bus_v": f"{float(snap.get('dc_bus_v', 0.0)):.2f}",
        }
        if self.sync_mode == "realtime":
            # the safe-state latency in sim time: the batch that went safe vs the last command
            values["last_drive_command_sim_s"] = f"{self.latest_rx_sim_s:.6f}"
        values.update({k: f"{v:.6f}" if isinstance(v, float) else str(v) for k, v in self.stats.items()})
        values.update(drive_values)
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        arr = DiagnosticArray()
        arr.header.stamp = msgconv.time_msg(stamp)
        arr.status = [status]
        self.pub_diag.publish(arr)

    # ------------------------------------------------------------ applying commands
    def _apply(self, msg: DriveCommand | None, held: bool = False) -> bool:
        """Apply batch k: a valid DriveCommand, or all gates off (None / a rejected command);
        ``held``: ``msg`` is last batch's command again (realtime, no new one came).
        Returns False if ``msg`` was rejected."""
        try:
            if msg is None:
                self.backend.safe_batch(self.n)
                return True
            # a held command is last batch's, which passed the check then
            problem = None if held else self.backend.problem(msg, self.n)
            if problem is None:
                try:
                    self.backend.apply(msg, held)
                    self.node_faults &= ~PlantState.FAULT_BAD_COMMAND
                    return True
                except ValueError as exc:       # the model's own validation
                    problem = str(exc)
            self.problem = problem
            self.stats["bad_commands"] += 1
            if not self.node_faults & PlantState.FAULT_BAD_COMMAND:
                self.get_logger().warning(f"DriveCommand seq={msg.seq} rejected: {problem}")
            self.node_faults |= PlantState.FAULT_BAD_COMMAND
            self.backend.safe_batch(self.n)
            return False
        finally:
            self.k += 1

    def _finished(self) -> bool:
        return self.duration_s > 0 and self.backend.time_s >= self.duration_s - 1e-9

    def _spin(self, timeout: float) -> None:
        self.hot.spin(max(timeout, 0.0))

    # ------------------------------------------------------------ loops
    def run(self) -> int:
        try:
            if self.sync_mode == "lockstep":
                self._run_lockstep()
            else:
                self._run_realtime()
        finally:
            if not self.carry_on:                # (a new node goes on with it: hand_over)
                self.close_backend()
        return 0

    def close_backend(self) -> None:
        close = getattr(self.backend, "close", None)
        if close is not None:                    # CAN: zero torque + IDLE, close the log and the bus
            close()

    def _end_of_run(self) -> None:
        self._publish_state(end_of_run=True)
        self.get_logger().info(f"end of run at t={self.backend.time_s:.6f}s after {self.k} batches")
        close = getattr(self.backend, "close", None)
        if close is not None:                    # CAN: zero torque + IDLE now, not after the linger
            close()
        end = time.monotonic() + self.end_linger_s
        # a reliable reader (recorder, fleet monitor) that lost a datagram of the last states
        # learns of it only from the writer's next heartbeat (Fast DDS: every 3 s by default,
        # 100 ms with config/fastdds.xml, which tools/env.sh selects), possibly after the
        # linger would have closed the writer: wait for its acknowledgment, up to
        # END_ACK_TIMEOUT_S, spinning in between (a Ctrl-C still ends it). The linger after
        # that is short (0.1 s): every reliable reader has the state by then, and a best-effort
        # one got it when it was written or never will (0.5 s made every run 0.4 s longer).
        acked_by = time.monotonic() + max(self.end_linger_s, END_ACK_TIMEOUT_S)
        while not self.stop_requested and time.monotonic() < acked_by:
            if self.pub_state.wait_for_all_acked(Duration(seconds=0.05)):
                break
            self._spin(0.0)
        while not self.stop_requested and time.monotonic() < end:
            self._spin(min(0.05, end - time.monotonic()))

    def _run_lockstep(self) -> None:
        log = self.get_logger()
        next_log = time.monotonic() + 5.0
        def waiting() -> bool:
            controller = self.pub_state.get_subscription_count() >= 1 and self.sub_drive.get_publisher_count() >= 1
            recorder = self.recorder_window <= 0 or self._recorder_ready()
            return not (controller and recorder)
        start = time.monotonic()
        while not self.stop_requested and waiting():
            self._spin(0.05)
            if self._check_deaf_start():       # discovery data goes to a stale port too
                return
            if self.start_timeout_s > 0 and time.monotonic() - start > self.start_timeout_s:
                raise StartupTimeout(f"no controller after start_timeout_s={self.start_timeout_s:g}s (no plant_state "
                                     "subscriber / drive_command publisher on this ROS_DOMAIN_ID and namespace)")
            if time.monotonic() > next_log:
                log.info("waiting for the controller (plant_state subscriber and drive_command publisher)"
                         + (" and the recorder" if self.recorder_window > 0 else ""))
                next_log = time.monotonic() + 5.0
            self._recorder_absent(start)
        t1 = None                    # wall time of the first answer (rate excludes start-up waits) ...
        k1 = 1                       # ... and the batches applied then (a carried run: hand_over)
        if self.carried:
            t1, k1 = time.monotonic(), self.k
        next_progress = time.monotonic() + PROGRESS_EVERY_S
        while not self.stop_requested:
            if self.k == 1:
                t1 = time.monotonic()
            if time.monotonic() >= next_progress:
                # long runs show progress (sim time, share of the run, speed)
                next_progress = time.monotonic() + PROGRESS_EVERY_S
                done = f" of {self.duration_s:g} s ({100.0 * self.backend.time_s / self.duration_s:.0f} %)" \
                    if self.duration_s > 0 else ""
                rate = (self.k - k1) / max(time.monotonic() - t1, 1e-9) * self.batch_s if t1 and self.k > k1 else 0.0
                log.info(f"t = {self.backend.time_s:.1f} s{done}, {rate:.2f} x real time")
            if self._finished():
                if t1 is not None and self.k > k1:
                    rate = (self.k - k1) / max(time.monotonic() - t1, 1e-9)
                    log.info(f"lockstep rate {rate:.0f} batches per wall second "
                             f"({rate * self.batch_s:.2f} x real time)")
                self._end_of_run()
                return
            if self._check_stale_peers():
                return
            self._wait_for_recorder()
            if self.stop_requested:          # (a Ctrl-C, or the look there)
                return
            self.pending_seq = self.k
            self.answer = None
            self._publish_state()
            sent = first = time.monotonic()
            while self.answer is None and not self.stop_requested:
                self.hot.spin(0.1, self.busy.busy_s())
                if self._check_deaf_start():
                    return
                if self.answer is None and time.monotonic() - sent > self.republish_s:
                    self._republish()
                    sent = time.monotonic()
                    # say why the run does not advance (no batch is applied without an answer:
                    # sim time stands still, the machine state is held as it was)
                    self.wait_reason = (f"no DriveCommand for seq {self.k} for {sent - first:.1f}s: run held "
                                        "(sim time stopped, no batch applied)")
                    if self.start_timeout_s > 0 and sent - first > self.start_timeout_s:
                        # never hang: a controller that does not answer is an error of the run
                        self.wait_reason = (f"no DriveCommand for seq {self.k} within start_timeout_s="
                                            f"{self.start_timeout_s:g}s: the run ends (controller gone or stuck)")
                        self.wait_level = _level(DiagnosticStatus.ERROR)
                        self._publish_diag(self._last_snap, self._last_stamp, max(self.last_faults, 0))
                        linger = time.monotonic() + min(self.end_linger_s, 0.5)     # let it reach subscribers
                        while time.monotonic() < linger and not self.stop_requested:
                            self._spin(0.05)
                        raise StartupTimeout(f"no DriveCommand for seq {self.k} within start_timeout_s="
                                             f"{self.start_timeout_s:g}s (controller stuck or not matched)")
                    self._publish_diag(self._last_snap, self._last_stamp, max(self.last_faults, 0))
            if self.wait_reason and self.answer is not None:
                self.wait_reason = ""
                self.last_faults = -1        # the next state's diagnostic says it runs again
            if self.answer is None:
                return
            msg, self.answer = self.answer, None
            self.pending_seq = -1
            self._apply(msg)

    def _service_backend(self) -> None:
        """CAN: receive frames, supervise the drive, (re-)arm, request; log its events."""
        service = getattr(self.backend, "service", None)
        if service is None:
            return
        service()
        log = self.get_logger()
        for level, text in self.backend.pop_events():
            # one call site per severity: rclpy refuses a severity change at a call site
            if level == "error":
                log.error(text)
            elif level == "warning":
                log.warning(text)
            else:
                log.info(text)

    def _wait_for_recorder_start(self) -> None:
        """Realtime with a recorder: its first batch waits (at most ``recorder_timeout_s``) until
        the recorder is matched, so that a bag holds the run from seq 0 on a slow start-up too.
        Wall-clock batches then run free (no flow control; the recorder keeps up or says so)."""
        start = time.monotonic()
        while (not self.stop_requested and self.recorder_window > 0
               and not self._recorder_ready() and not self._recorder_absent(start)):
            self._service_backend()
            self._spin(0.05)
            if self._check_deaf_start():
                return
        self.recorder_window = 0

    def _hold_start(self) -> None:
        """Realtime: hold t = 0 (no batch applied) until the controller's first DriveCommand,
        at most ``start_timeout_s``. Sim time that ran before the loop was closed would be ridden
        without the session: its first Commands can reach a controller whose reader matched late
        only when the session sees /clock 0 again (it then sends the Commands in force again).
        So seq 0 and /clock 0 go out again every FIRST_STATE_REPUBLISH_S; /clock 0 also while a
        CAN drive is not armed yet (arming waits for DriveCommands)."""
        self.holding_start = True                # the first state's diagnostic says so
        self._publish_state()
        start = time.monotonic()
        again = start + FIRST_STATE_REPUBLISH_S
        while not self.stop_requested and self.latest_rx is None:
            self._service_backend()
            self._spin(0.02)
            if self._check_deaf_start():
                return
            now = time.monotonic()
            if self.start_timeout_s > 0 and now - start > self.start_timeout_s:
                self.get_logger().warning(f"no DriveCommand within start_timeout_s={self.start_timeout_s:g}s: "
                                          "sim time starts without a controller (safe state)")
                break
            if now >= again and self.latest_rx is None:
                again = now + FIRST_STATE_REPUBLISH_S
                self._republish()
                self._diag_if_due(self._last_snap, self._last_stamp, max(self.last_faults, 0), now)
        self.holding_start = False
        if self.latest_rx is not None and time.monotonic() - start > 1.0:
            self.get_logger().info(f"first DriveCommand after {time.monotonic() - start:.1f}s: sim time starts")

    def _check_deaf_start(self) -> bool:
        """A plant that has heard no DriveCommand at all DEAF_CHECK_S after it began waiting
        for one, while a live process writes to a deleted segment of its shared-memory ports, is
        a plant restarted after a kill -9 on the killed one's port (Fast DDS's stale port,
        bike_plant.shm_ports): the controller's DriveCommands (and its discovery data, so the
        writer may not even show as matched) go to the old segment, for good. Nothing has run
        yet (seq 0 is held), so starting over loses nothing: say so, name the writers, and stop;
        run_loop_node starts the node again with a new participant on fresh ports (once per
        process). Looked for every shm_ports.DEAF_CHECK_S while nothing is heard; True when
        stopping."""
        why = "" if self.drive_heard else self.deaf_watch.start_over()
        if not why:
            return False
        text = (f"no DriveCommand in the {self.deaf_watch.waited_s():.0f}s since this run began waiting for one: "
                f"{why}; starting over with a new DDS participant on fresh ports (seq 0 held, nothing lost)")
        self.get_logger().warning(text)
        self.wait_reason = text
        self._publish_diag(self._last_snap, self._last_stamp, max(self.last_faults, 0))
        self.fresh_ports_wanted = True
        self.stop_requested = True
        return True

    def _check_stale_peers(self) -> bool:
        """Running, and hearing the controller, yet a peer still cannot reach this plant (a
        plant restarted after a kill -9 whose controller re-opened the killed one's port while
        the recorder, or the session, did not: shm_ports.StalePeerWatch). Measured with the
        signature forced (docs/RELIABILITY.md): discovery does not go that way (the plant's
        writers still match that peer's readers and deliver), but the rest that peer sends
        this plant goes into the deleted segment: its readers' acknowledgments and repair
        requests (a sample lost on the way, e.g. a full port queue, is never sent again: a
        hole in the bag; the end_of_run state waits its full END_ACK_TIMEOUT_S) and its data (the recorder's progress: lockstep flow control gives
        the recorder up after recorder_timeout_s and the run goes on unthrottled, with an
        ERROR; a CAN rig's heart rate). Say so once (log and WARN diagnostic, naming the
        writers) and stop between two batches: run_loop_node goes on with the same simulation
        in a new participant on fresh ports (hand_over). Looked for every DEAF_CHECK_S;
        True when stopping."""
        if not self.drive_heard or self.peer_watch.finished:
            return False

        def say(text: str) -> None:
            self.wait_reason = text
            self._publish_diag(self._last_snap, self._last_stamp, max(self.last_faults, 0))
            self.wait_reason = ""
        if not say_stale_peer_and_start_over(self, self.peer_watch, say,
                                             f" (the run goes on from seq {self.k}, nothing reset or lost)"):
            return False
        self.carry_on = self.stop_requested = True
        return True

    def hand_over(self, new) -> None:
        """Before this participant leaves (start_over_on_fresh_ports' before_leaving), with the
        run stopped between two batches: the new node's endpoints match as many peers as this
        one's (HANDOVER_WAIT_S at most), so that its first state reaches every reader this one
        had (the recorder's bag goes on without a hole). Realtime: the wall time this takes is
        not sim time (the batches resume from now; the held DriveCommand's timeout too)."""
        pairs = [(self.pub_state, new.pub_state), (self.pub_clock, new.pub_clock), (self.pub_battery, new.pub_battery),
                 (self.pub_diag, new.pub_diag), (self.sub_drive, new.sub_drive)]
        if self.recorder_window_cfg > 0:
            pairs.append((self.sub_progress, new.sub_progress))
        late = wait_for_new_matches(pairs, stop=lambda: getattr(self, "signalled", False))
        if late:
            new.get_logger().warning(f"the new participant's {', '.join(late)} did not match every peer of the old "
                                     "one in time: those peers may miss what it sends until they do")

    @property
    def safe_state_text(self) -> str:
        """What the safe state does on this backend, for the diagnostic and the log (a drive on
        CAN says its own; the simulated bridges switch all gates off)."""
        return getattr(self.backend, "safe_state_text", "all gates off")

    def _recorder_ready(self) -> bool:
        """The recorder is up and this plant's PlantState writer has matched its reader (seq 0
        sent before that match would be missing from the bag)."""
        return self.sub_progress.get_publisher_count() >= 1 and recorder_reads(self, self.pub_state)

    def _recorder_absent(self, since: float) -> bool:
        """A recorder is expected but none matched within ``recorder_timeout_s`` (at least
        RECORDER_START_MIN_S) of ``since``: say so once (ERROR, FAULT_RECORDER_LOST) and run
        unrecorded rather than hang."""
        timeout_s = max(self.recorder_timeout_s, RECORDER_START_MIN_S)
        if self.recorder_window <= 0 or time.monotonic() - since <= timeout_s or self._recorder_ready():
            return False
        self.get_logger().error(f"no recorder after {timeout_s:g}s: running unrecorded")
        self.node_faults |= PlantState.FAULT_RECORDER_LOST
        self.recorder_window = 0
        return True

    def _run_realtime(self) -> None:
        log = self.get_logger()
        applied = self.latest if self.carried else None     # (carried: held on, as it was)
        timed_out = bool(self.node_faults & PlantState.FAULT_COMMAND_TIMEOUT)     # (carried: hand_over)
        self._wait_for_recorder_start()
        if self.stop_requested:
            return
        self._service_backend()
        if not self.carried:
            self._hold_start()
        elif self.latest_rx is not None:
            self.latest_rx = time.monotonic()    # the hand-over's pause is not the controller's silence
        next_tick = time.monotonic() + self.batch_s
        while not self.stop_requested:
            now = time.monotonic()
            if now < next_tick:
                self._spin(next_tick - now)
                continue
            if now - next_tick > max(20 * self.batch_s, 0.02):
                self.stats["overruns"] += 1
                self.stats["overrun_dropped_s"] += now - next_tick
                next_tick = now              # fell far behind (suspend, GC): resynchronise
            next_tick += self.batch_s
            # take what DDS already holds before judging a timeout (the loop itself may have
            # been descheduled; a command waiting in the queue is not a missing command)
            for _ in range(8):
                before = self.latest_rx
                self._spin(0.0)
                if self.latest_rx is before:
                    break
            self._service_backend()
            now = time.monotonic()
            # choose this batch's command
            msg = None
            if self.latest_rx is not None:
                # wall time as a drive's watchdog, or sim time (= wall time when the loop keeps
                # up): a descheduled loop must not add batches to the promised safe-state latency
                if (now - self.latest_rx > self.command_timeout_s
                        or self.backend.time_s - self.latest_rx_sim_s > self.command_timeout_s + 1e-9):
                    if not timed_out:
                        log.error(f"no DriveCommand for {now - self.latest_rx:.3f}s wall / "
                                  f"{self.backend.time_s - self.latest_rx_sim_s:.3f}s sim > command_timeout_s="
                                  f"{self.command_timeout_s:g}s: safe state "
                                  f"({self.safe_state_text}; last seq "
                                  f"{self.latest.seq if self.latest is not None else -1} at batch {self.k}, "
                                  f"overruns {self.stats['overruns']})")
                        self.backend.set_safe(True)
                        self.node_faults |= PlantState.FAULT_COMMAND_TIMEOUT
                        timed_out = True
                    self.stats["timeout_batches"] += 1
                else:
                    if timed_out:
                        log.info("DriveCommands are back: leaving the safe state")
                        self.backend.set_safe(False)
                        self.node_faults &= ~PlantState.FAULT_COMMAND_TIMEOUT
                        timed_out = False
                    msg = self.latest
            held = msg is not None and msg is applied
            if held:
                self.stats["held_batches"] += 1
            applied = msg
            if not self._apply(msg, held) and self.latest is msg:
                self.latest = None           # do not hold a rejected command
            if self._finished():
                self._end_of_run()
                return
            self._publish_state()
            if self._check_stale_peers():
                return


def _level(level) -> int:
    """diagnostic_msgs' level is a byte in rclpy: as an int."""
    return level[0] if isinstance(level, (bytes, bytearray)) else int(level)


def install_signal_handlers(node) -> None:
    """SIGINT / SIGTERM ask the loop to stop (checked at least every 0.1 s)."""
    def handler(signum, frame):
        node.stop_requested = True
        node.signalled = True
    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)


# a warm-up longer than this was a compile, not a load from numba's cache
COMPILED_AFTER_S = 5.0


# warm_up_kernels says "compiling ..." when the warm-up takes longer than this
SLOW_WARM_UP_S = 2.0
WAIT_POLL_S = 0.05

# the finished events of warm-up threads left compiling by a Ctrl-C (warm_up_kernels):
# run_loop_node exits without waiting for them
_abandoned_warm_ups: list = []


def warm_up_kernels(logger, warm_up) -> float:
    """Run ``warm_up`` (a node's per-batch path on throw-away data) and log how long numba
    took: the first run after installing or editing a kernel compiles for tens of seconds,
    later runs load the cache in a fraction of a second. Returns the seconds.

    The warm-up runs in a worker thread while this (main) thread waits. CPython runs signal
    handlers in the main thread only, so a Ctrl-C during the compile raises KeyboardInterrupt
    here, in the wait, and ends the node at once, as anywhere else before its loop runs. It
    never lands inside numba: there, in llvmlite's ctypes object-cache callback, ctypes
    swallowed it (CI), and numba then failed with an unrelated error or compiled on for tens
    of seconds, past the launcher's 10 s grace. The interrupted compile is left to its daemon
    thread, and run_loop_node exits without waiting for it (numba writes a cache file under a
    temporary name and renames it when complete, so none is left half-written)."""
    import threading

    outcome = []
    finished = threading.Event()

    def run():
        try:
            # the kernel then delivers SIGINT / SIGTERM to the main thread: its wait returns
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
            warm_up()
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread below
            outcome.append(exc)
        finally:
            finished.set()

    # (LLVM's library pages, touched to load the kernels, are dropped as they load by the
    # LoadTimePageReleaser that run_loop_node makes the node in: bike_plant.memory)
    worker = threading.Thread(target=run, name="numba-warm-up", daemon=True)
    t0 = time.perf_counter()
    worker.start()
    said = False
    try:
        # short waits: back in Python often, where a pending signal's handler runs. An Event,
        # not Thread.join: a join interrupted by KeyboardInterrupt marks the thread as stopped
        # while it runs on (CPython gh-90882), and run_loop_node must see it running.
        while not finished.wait(WAIT_POLL_S):
            if not said and time.perf_counter() - t0 > SLOW_WARM_UP_S:
                # said only when it is slow: a load from the cache takes a fraction of a second
                logger.info("compiling the numba kernels (the first run after an install or a kernel edit: up "
                            "to a minute; cached for the next runs)")
                said = True
    except KeyboardInterrupt:
        _abandoned_warm_ups.append(finished)
        raise
    took_s = time.perf_counter() - t0
    if outcome:
        failure = outcome[0]
        if not isinstance(failure, Exception):
            raise failure
        # a warm-up never keeps a node from running (e.g. a CAN config whose machine section
        # a simulated twin cannot be built from)
        logger.warning(f"numba kernel warm-up failed ({type(failure).__name__}: {failure}): they compile at "
                       "first use")
        return took_s
    logger.info(f"numba kernels ready in {took_s:.1f} s" + (" (compiled)" if took_s > COMPILED_AFTER_S else ""))
    return took_s


def exit_if_a_warm_up_is_left(code: int) -> None:
    """After a Ctrl-C during warm_up_kernels: end the process now, with `code`, instead of
    finalising the interpreter while the abandoned compile runs on in its thread (inside
    llvmlite, which calls back into Python). The node is already shut down; stdio is flushed."""
    if not all(finished.is_set() for finished in _abandoned_warm_ups):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def run_loop_node(node_factory, label: str, args=None) -> int:
    """Shared main() of the loop nodes: init without rclpy's signal handlers, run the node's
    own loop, turn a ConfigError into one line and exit code 2, always shut down cleanly."""
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    code = 0
    try:
        # the node loads (or compiles) its kernels as it is made, running LLVM (numba's code
        # generator) through ~65 MB of its library that nothing needs afterwards: dropped as it
        # goes, so they are never all resident at once (the node's peak RSS: 175-183 MB on
        # Python 3.11, ~221 MB on 3.12, now ~125 MB; bike_plant.memory)
        with LoadTimePageReleaser():
            node = node_factory()
        install_signal_handlers(node)
        code = node.run()
        while getattr(node, "fresh_ports_wanted", False) and not getattr(node, "signalled", False):
            old = node
            if getattr(old, "carry_on", False):     # a running plant: the new node goes on with its run
                node = start_over_on_fresh_ports(functools.partial(node_factory, carry=old), old, args,
                                                 before_leaving=old.hand_over)
            else:
                node = start_over_on_fresh_ports(node_factory, old, args)
            install_signal_handlers(node)
            if getattr(old, "signalled", False):
                # a Ctrl-C while the new node was made went to the old one's handler: not lost
                node.stop_requested = node.signalled = True
            code = node.run()
    except StartupTimeout as exc:
        print(f"{label}: error: {exc}", file=sys.stderr)
        code = 2
    except ConfigError as exc:
        print(f"{label}: configuration error: {exc}", file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        code = 0
    finally:
        if node is not None:
            if getattr(node, "carry_on", False):         # a Ctrl-C came before the hand-over (PlantNode.hand_over)
                node.close_backend()
            node.executor_.remove_node(node)
            # its guard conditions now, while the context lives: left to Executor.__del__ at
            # interpreter exit, Python 3.12 printed an InvalidHandle traceback (context gone)
            node.executor_.shutdown()
            node.destroy_node()
            if node.context is not rclpy.get_default_context():       # started over (loop.start_over_on_fresh_ports)
                rclpy.try_shutdown(context=node.context)
        rclpy.try_shutdown()
    exit_if_a_warm_up_is_left(code)
    return code


def main(args=None) -> int:
    return run_loop_node(PlantNode, "plant_node", args)


if __name__ == "__main__":
    sys.exit(main())
