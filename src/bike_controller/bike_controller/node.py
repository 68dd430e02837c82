"""controller_node: the batched inner-loop torque controller as a ROS 2 node (thin adapter).

Topics (relative names, namespace /bike by default; docs/DESIGN.md):
  subscribes plant_state (bike_msgs/PlantState), command (bike_msgs/Command),
             session_status (bike_msgs/SessionStatus)
  publishes  drive_command (bike_msgs/DriveCommand, one per PlantState, same seq),
             controller_status (bike_msgs/ControllerStatus, one per batch while a reader is matched),
             /diagnostics (WARN on a rejected Command, OK every ``diagnostics_period_s``;
             realtime: skipped_state_gaps / skipped_periods / skipped_time_s count the PlantStates
             skipped while the process was descheduled)

The law is bike_controller.session_control.ModedController: the session modes of
bike_controller.modes on top of bldc_control.BatchController (nominal params from the config).
A PlantState with ``measured_by_drive`` (plant backend ``can``: the drive's firmware owns the
current loop) gets a torque-only answer: the mode torque from the measured speed, trimmed on
the drive's torque estimate, in DriveCommand.torque_cmd_nm (motoring positive), no gates or
duties (session_control.DriveTorqueLaw).

Commands: a Command that is not finite, outside [0, 1], of an unknown mode or with a virtual gear
outside [0.3, 8] (0: the config's gear), or a heart-rate target outside 40..220 bpm or outside ERG, is rejected
(WARN diagnostic, ControllerStatus.command_rejected = true until the next valid one); the
previous command stays in force. Valid Commands go into a timeline sorted by header.stamp,
kept whole (a stamp and an index into the distinct Commands' contents, 12 bytes a Command:
~0.4 MB for an hour at 10 Hz), so that a
plant restarted mid-run (seq 0 again) gets the same Commands from t = 0 as the first run.

Determinism (lockstep, docs/DESIGN.md, Lockstep protocol): for the PlantState of batch k
at sim time t_k the controller applies the newest Command with stamp <= t_k. It does not
answer batch k until it holds the Command for j = floor(t_k / session.period_s + 1e-9),
i.e. a Command stamped >= j * period (the session publishes in stamp order on a reliable
topic, so everything up to tau_j is then in) and one stamped <= t_k (what was written before
this reader matched never arrives; the session sends it again), unless a SessionStatus DONE was seen or
nothing arrived for ``command_wait_s`` wall seconds (then it proceeds with the last / zero
command, logs once, and stops waiting until a new Command arrives). A re-published
PlantState that was already answered gets the cached answer again (decide() is never run
twice for one seq). realtime: the same timeline rule; only the first answer of a run, to the
plant's held t = 0 (plant_node holds sim time until that answer), waits for the Command for
t = 0 as lockstep does (the held state is re-published every 0.1 s, and with it the session
sends its first Commands again, so a Command reader matched late still gets them; a
session-less graph runs once the plant's start_timeout_s ends the hold); with
``recorder_window_batches`` > 0 it also waits for the recorder's readers. Later batches never
wait.
"""
from __future__ import annotations

import array
import bisect
import math
import sys
import time

from bike_msgs.msg import Command, ControllerStatus, DriveCommand, PlantState, SessionStatus
from bike_plant import msgconv, shm_ports
from bike_plant.config import ConfigError, sync_mode_of
from bike_plant.loop import (AUX_QOS, LOCKSTEP_BUSY_WAIT_S, LOOP_QOS, BusyWaitGuard, HotWait, loop_reader_qos,
                             recorder_reads, say_stale_peer_and_start_over, take_sim_time_from_messages)
from bike_plant.node import run_loop_node, warm_up_kernels
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from .modes import MODE_NAMES, MODE_SPINDOWN
from .node_params import controller_node_numbers

CONTROLLER_DEFAULTS = {
    "sync_mode": "lockstep",
    "batch_periods": 20,
    "control_period_s": 5.0e-5,
    "command_wait_s": 2.0,
    "diagnostics_period_s": 1.0,
    "session": {"period_s": 0.1},
    "recorder_window_batches": 0,
    "busy_wait_s": LOCKSTEP_BUSY_WAIT_S,
    "calibration_file": "",
}
CONTROLLER_DESCRIPTIONS = {
    "busy_wait_s": ("lockstep: poll for the next PlantState this many wall seconds before blocking (0 = block at once; "
                    "held at 0 while a third node reads drive_command or controller_status)"),
    "diagnostics_period_s": "publish an OK diagnostic at least this often [wall s]",
    "calibration_file": ("write a successful spin-down's friction into this file (bike_controller.calibration; "
                         "./bike run --calibration); empty: nowhere"),
    "recorder_window_batches": "lockstep, > 0 while recording (./bike run --record): the first answer waits until the "
                               "recorder's readers of drive_command and controller_status are matched",
}
RECORDER_MATCH_WAIT_S = 5.0  # then the run goes on, saying the bag may miss the first answers
PLANT_SILENT_S = 3.0         # wall seconds without a PlantState mid-run before saying so (> republish_s)
STAMP_TOL_NS = 1000          # 1 us: stamps are sim times computed in floating point


class ControllerNode(Node):
    def __init__(self, **kwargs):
        super().__init__("controller", **kwargs)
        from bike_plant.params import nominal_params_from_config
        from bike_plant.rosparams import declare_config

        from .session_control import ModedController

        self.cfg = cfg = declare_config(self, CONTROLLER_DEFAULTS, CONTROLLER_DESCRIPTIONS)
        path = cfg.get("_config_path")
        self.sync_mode = sync_mode_of(cfg, path)
        numbers = controller_node_numbers(cfg, path)          # ./bike run checks them too
        self.command_wait_s = numbers["command_wait_s"]
        self.period_s = numbers["session.period_s"]
        self.diag_period_s = numbers["diagnostics_period_s"]
        busy = numbers["busy_wait_s"]
        self.busy_wait_s = busy if self.sync_mode == "lockstep" else 0.0     # realtime never polls
        self.calibration_file = str(cfg.get("calibration_file") or "")
        self.saved_spindown = None         # the spin-down result last written there
        self.machine = str(cfg.get("machine", "bldc"))
        if self.machine == "spmsm":
            from .spmsm_session import ModedSpmsmController
            self._make_law = lambda: ModedSpmsmController(cfg)
        elif self.machine == "bldc":
            self._make_law = lambda: ModedController(cfg, nominal_params_from_config(cfg))
        else:
            raise ConfigError(f"unknown machine {self.machine!r} (bldc | spmsm)", path, "machine")
        try:
            self.ctrl = self._make_law()
        except ValueError as exc:
            raise ConfigError(str(exc), path) from None
        self.n = self.ctrl.batch_periods
        self.build_drive = msgconv.spmsm_drive_cdr if self.machine == "spmsm" else msgconv.drive_command_cdr
        # before the node joins the graph (see the plant's warm-up)
        warm_up_kernels(self.get_logger(), lambda: warm_up_law(self._make_law, cfg, self.machine, self.n))
        take_sim_time_from_messages(self)

        self.pub_drive = self.create_publisher(DriveCommand, "drive_command", LOOP_QOS)
        self.pub_status = self.create_publisher(ControllerStatus, "controller_status", LOOP_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", AUX_QOS)
        subs = [self.create_subscription(Command, "command", self._on_command, LOOP_QOS),
                self.create_subscription(SessionStatus, "session_status", self._on_session, AUX_QOS),
                self._state_subscription()]
        self.sub_state = subs[2]
        self.executor_ = SingleThreadedExecutor(context=self.context)
        self.executor_.add_node(self)
        # the loop waits on its three topics directly (bike_plant.loop.HotWait); Commands are
        # taken before the PlantState that may need them
        self.hot = HotWait(self.executor_, subs, self.context, logger=self.get_logger())
        self.busy = BusyWaitGuard(self, [self.pub_drive, self.pub_status], "plant_state", self.busy_wait_s)

        self.diag_name = f"{self.get_namespace().rstrip('/')}/{self.get_name()}".lstrip("/") or "controller"
        self.stop_requested = False
        self.stamps = array.array("q")     # timeline of valid Commands, sorted by stamp [ns]
        self.entry_ids = array.array("I")  # what each says: an index into self.entries
        self.entries: list[tuple] = []     # the distinct Commands' content (Command.command, mode, gear,
        self._entry_ids: dict = {}         # road, cadence target, heart-rate target) and its index
        self.rider_cadence_rpm = 0.0       # the cadence target in force (0: none), for the plant's rider
        self.applied_index = -1            # timeline entry in force (-1: config command0/mode0)
        self.rejected = False              # last received Command was invalid
        self.reject_reason = ""
        self.session_done = False
        self.no_session = False            # gave up waiting (command_wait_s); cleared by a new Command
        self.pending = None                # (PlantState, wall time received) not yet answered
        self.last_seq = -1
        self.cached = None                 # (seq, DriveCommand, ControllerStatus)
        self.last_diag_wall = 0.0
        self.state_rx = None               # wall time of the last PlantState (plant-silence diagnostic)
        self.plant_silent = False
        self.started_s = time.monotonic()
        self.first_state_s = None          # when the first PlantState came (logged: diagnosis, matched?)
        self.commandless_warned = False    # realtime: one warning when no Command came at all
        self.t0_hold_warned = False        # realtime: one warning while t = 0 is held for a session
        self.state_writer_since = None     # before the first PlantState: since when a plant_state writer matched
        self.stateless_warned = False      # ... and one warning when it delivered nothing
        self.unmatched_watch = shm_ports.StalePortWatch(PLANT_SILENT_S, since=time.monotonic())   # no writer matched
        self.peer_watch = shm_ports.StalePeerWatch(since=self.started_s)   # hearing the plant (_check_stale_peers)
        # the plant waits for the recorder's reader of plant_state, not for its readers of this
        # node's topics; a graph that runs at 2x (or a realtime run) would otherwise ride its
        # first seconds before discovery matched them (a bag without ControllerStatus). Both
        # modes hold the first answer; the plant holds its first batch until it comes.
        self.await_recorder = int(cfg.get("recorder_window_batches") or 0) > 0
        self.recorder_wait_since = None
        self.stats = {"answered": 0, "rejected_commands": 0, "duplicates": 0, "waits": 0, "undecodable_states": 0}
        self.get_logger().info(
            f"controller: sync_mode={self.sync_mode} N={self.n} session.period_s={self.period_s:g} "
            f"command_wait_s={self.command_wait_s:g} config={path}")
        if getattr(self.ctrl, "startup_note", ""):
            self.get_logger().info(self.ctrl.startup_note)

    def _state_subscription(self):
        # taken serialized, decoded by msgconv.PlantStateView (bike_plant.cdr: the hot path)
        return self.create_subscription(PlantState, "plant_state", self._on_state, loop_reader_qos(self.sync_mode),
                                        raw=True)

    # ------------------------------------------------------------ inputs
    def _on_command(self, msg: Command) -> None:
        problem = msgconv.command_problem(msg)
        if problem is not None:
            self.rejected = True
            self.reject_reason = problem
            self.stats["rejected_commands"] += 1
            self.get_logger().warning(f"Command rejected: {problem}; keeping the previous command")
            self._publish_diag(DiagnosticStatus.WARN, f"Command rejected: {problem}; previous command kept")
            return
        self.rejected = False
        stamp = msgconv.stamp_ns(msg.header.stamp)
        i = bisect.bisect_right(self.stamps, stamp)
        entry = (float(msg.command), int(msg.mode), float(msg.virtual_gear_ratio), msgconv.command_road(msg),
                 float(msg.cadence_rpm), float(msg.heart_rate_bpm))
        entry_id = self._entry_ids.get(entry)
        if entry_id is None:
            entry_id = self._entry_ids[entry] = len(self.entries)
            self.entries.append(entry)
        if i > 0 and self.stamps[i - 1] == stamp:       # same stamp: the newer one replaces it
            self.entry_ids[i - 1] = entry_id
            if self.applied_index == i - 1:
                self.applied_index = -2                  # force re-application
        else:
            self.stamps.insert(i, stamp)
            self.entry_ids.insert(i, entry_id)
            if self.applied_index >= i:
                self.applied_index += 1
        self.no_session = False
        self._try_answer()

    def _on_session(self, msg: SessionStatus) -> None:
        self.session_done = msg.state == SessionStatus.STATE_DONE
        self._try_answer()

    def _on_state(self, raw: bytes) -> None:
        try:
            msg = msgconv.PlantStateView(raw)
        except msgconv.CdrError as exc:
            self.stats["undecodable_states"] += 1
            if self.stats["undecodable_states"] == 1 or self.stats["undecodable_states"] % 1000 == 0:
                self.get_logger().warning(f"undecodable PlantState ({len(raw)} bytes) dropped "
                                          f"({self.stats['undecodable_states']} so far): {exc}")
            return
        seq = int(msg.seq)
        self.state_rx = None if msg.end_of_run else time.monotonic()
        if self.first_state_s is None:
            self.first_state_s = time.monotonic()
            self.get_logger().info(f"first PlantState (seq {seq}, t={msg.stamp_ns * 1e-9:.3f}s) "
                                   f"{time.monotonic() - self.started_s:.1f}s after start"
                                   + (" (on the re-created subscription)" if self.stateless_warned else ""))
        if self.plant_silent:
            self.plant_silent = False
            self.get_logger().info(f"PlantState seq {seq} received: the plant is back")
        if msg.end_of_run:
            self.get_logger().info(f"end of run at seq {msg.seq}; ready for a new run")
            self._new_run()
            return
        if seq == 0 and self.last_seq > 0:
            self.get_logger().info("PlantState seq 0 again: the plant restarted, starting a new run")
            self._new_run()
        if self.cached is not None and seq == self.cached[0]:
            self.stats["duplicates"] += 1                 # re-published state: same answer again
            self.pub_drive.publish(self.cached[1])
            if self.cached[2] is not None:
                self.pub_status.publish(self.cached[2])
            return
        if seq <= self.last_seq and self.last_seq - seq < 1000:
            return                                        # stale copy of an older state
        # once the session has been heard from, a re-published copy of the state already waiting
        # keeps its first arrival time: the plant re-publishes every republish_s, which must not
        # restart command_wait_s (a dead session would stall the run for ever). Before the first
        # Command it does restart it: a session node still starting up is waited for.
        received = (self.pending[1] if self.pending is not None and int(self.pending[0].seq) == seq
                    and len(self.stamps) > 0 else None)
        self.pending = (msg, received if received is not None else time.monotonic())
        self._try_answer()

    def _new_run(self) -> None:
        """Fresh law (estimator, predictor) for a new plant run; the Command timeline stays
        (whole: the new run applies it from t = 0 like the first run did)."""
        self.ctrl = self._make_law()
        self.applied_index = -1
        self.pending = None
        self.cached = None
        self.last_seq = -1
        # a give-up of the old run (its plant died with a batch waiting) does not carry over:
        # the new run waits for the session again (command_wait_s) like the first did
        self.no_session = False

    # ------------------------------------------------------------ the batch
    def _holds_command_for(self, t_ns: int) -> bool:
        """The Command for j = floor(t / period) is in (a stamp >= tau_j), and so is one in force
        at t: the oldest stamp held is <= t. The second part matters when this reader matched
        the session's writer between two of its Commands: the session publishes a period ahead
        (tau_0 and tau_1 together at t = 0), a volatile reader gets nothing written before the
        match, and tau_1 alone used to pass for 'everything up to tau_0 is in'. Batch 0 then
        ran on no Command (seen under load: a run that differed from a second run of the same
        config). The session sends them again while the plant re-publishes the held state."""
        j = math.floor(t_ns * 1e-9 / self.period_s + 1e-9)
        need = int(round(j * self.period_s * 1e9))
        # (the timeline is sorted and keeps every stamp: its ends are the oldest and newest held)
        return (len(self.stamps) > 0 and self.stamps[-1] >= need - STAMP_TOL_NS
                and self.stamps[0] <= t_ns + STAMP_TOL_NS)

    def _try_answer(self) -> None:
        if self.pending is None:
            return
        msg, received = self.pending
        t_ns = msg.stamp_ns
        # lockstep waits at every batch; realtime only for the run's first answer, to the held t = 0
        may_wait = self.sync_mode == "lockstep" or (self.cached is None and t_ns == 0)
        if self.await_recorder and may_wait:
            if self.recorder_wait_since is None:
                self.recorder_wait_since = time.monotonic()
            if recorder_reads(self, self.pub_drive) and recorder_reads(self, self.pub_status):
                self.await_recorder = False
            elif time.monotonic() - self.recorder_wait_since < RECORDER_MATCH_WAIT_S:
                return                                    # run() calls again within 0.1 s
            else:
                self.await_recorder = False
                self.get_logger().warning(
                    f"recording, but no recorder matched drive_command / controller_status within "
                    f"{RECORDER_MATCH_WAIT_S:g}s: answering anyway (the bag may miss the first batches)")
        if (may_wait and not self.session_done and not self.no_session
                and not self._holds_command_for(t_ns)):
            if time.monotonic() - received < self.command_wait_s:
                self._say_t0_held(t_ns)
                return                                    # wait for the session
            self.no_session = True
            j = math.floor(t_ns * 1e-9 / self.period_s + 1e-9)
            text = (f"no Command for t={j * self.period_s:g}s within command_wait_s={self.command_wait_s:g}s: "
                    "proceeding with the last command (the run is no longer a pure function of the config)")
            self.get_logger().warning(text)
            self._publish_diag(DiagnosticStatus.WARN, f"session silent: {text}", t_ns)
            self.stats["waits"] += 1
        elif (not may_wait and len(self.stamps) == 0 and not self.session_done and not self.commandless_warned
                and time.monotonic() - self.first_state_s > self.command_wait_s):
            # realtime does not wait for the session: say so when none of its Commands came
            # (a session not running, or not matched: zero torque, and nothing else tells why)
            self.commandless_warned = True
            text = (f"no Command received in the {self.command_wait_s:g}s (command_wait_s) since the first "
                    "PlantState: riding on the config's command0 / mode0")
            self.get_logger().warning(text)
            self._publish_diag(DiagnosticStatus.WARN, f"session silent: {text}", t_ns)
        self._apply_timeline(t_ns)
        snap = msg.snap
        snap["stamp_ns"] = t_ns                            # a drive on CAN: the law's time base
        n = int(msg.batch_periods) or self.n               # answer the batch length the plant asks for
        a, b, c, status = self.ctrl.decide(snap, n)
        status["seq"] = msg.seq
        status["command_rejected"] = self.rejected
        torque = float(status.get("torque_cmd_nm", 0.0))
        if int(status.get("quadrant", 0)) == ControllerStatus.QUADRANT_GENERATING:
            torque = -torque                              # motoring positive, like torque_em_nm
        # the rider is told the Command's cadence, or what a spin-down asks of him
        rider = self.ctrl.law.rider_instruction() or (self.rider_cadence_rpm, False)
        drive = self.build_drive(msg.seq, a, b, c, t_ns, torque, float(status.get("current_cmd_a", 0.0)), *rider)
        self.pub_drive.publish(drive)
        # ControllerStatus is volatile: with no reader matched (the bare graph, no recorder) it
        # is neither built nor sent (about 20 us per batch)
        stat = None
        if self.pub_status.get_subscription_count():
            stat = msgconv.controller_status_cdr(status, t_ns)
            self.pub_status.publish(stat)
        self.cached = (int(msg.seq), drive, stat)
        self.last_seq = int(msg.seq)
        if self.calibration_file and self.ctrl.law.spindown.result is not self.saved_spindown:
            self._save_calibration(t_ns)
        self.pending = None
        self.stats["answered"] += 1
        now = time.monotonic()
        if now - self.last_diag_wall >= self.diag_period_s:
            level = DiagnosticStatus.WARN if self.rejected else DiagnosticStatus.OK
            text = f"last Command rejected: {self.reject_reason}" if self.rejected else "running"
            if self.commandless_warned and len(self.stamps) == 0:
                # repeated while it lasts: a monitor that matched after the one-off warning sees it too
                level, text = DiagnosticStatus.WARN, "session silent: no Command received; riding on command0 / mode0"
            self._publish_diag(level, text, t_ns)

    def _save_calibration(self, t_ns: int) -> None:
        """A spin-down just succeeded: keep its friction for the next run, as a trainer does. A
        file that cannot be written is said (ERROR log, WARN diagnostic); the ride goes on."""
        from .calibration import write_calibration

        result = self.saved_spindown = self.ctrl.law.spindown.result
        if result is None:                # a new procedure started: nothing learnt yet
            return
        try:
            path = write_calibration(self.calibration_file, self.machine, result, sim_time_s=t_ns * 1e-9,
                                     config_path=str(self.cfg.get("_config_path") or ""))
        except OSError as exc:
            text = f"spin-down calibration not saved to {self.calibration_file}: {exc.strerror or exc}"
            self.get_logger().error(text)
            self._publish_diag(DiagnosticStatus.WARN, text, t_ns)
            return
        self.get_logger().info(f"spin-down calibration saved to {path} (B {result.friction_nms:.4g} N m s, "
                               f"Tc {result.dry_friction_nm:.4g} N m): ./bike run --calibration {path} rides with it")

    def _say_t0_held(self, t_ns: int) -> None:
        """Realtime, no Command at all: the plant re-publishes the held t = 0 every 0.1 s, and
        each copy restarts command_wait_s (a session still starting up is waited for, however
        long), so a graph with no session stays at t = 0 until the plant's start_timeout_s.
        Say so once, after command_wait_s, in the log and as a WARN diagnostic."""
        if (self.t0_hold_warned or self.sync_mode != "realtime" or len(self.stamps) > 0
                or time.monotonic() - self.first_state_s <= self.command_wait_s):
            return
        self.t0_hold_warned = True
        text = (f"holding t = 0 for the session: no Command in the {self.command_wait_s:g}s (command_wait_s) "
                "since the first PlantState; the run starts at its first Command (or, with no controller "
                "answer, when the plant's start_timeout_s runs out)")
        self.get_logger().warning(text)
        self._publish_diag(DiagnosticStatus.WARN, f"session silent: {text}", t_ns)

    def _apply_timeline(self, t_ns: int) -> None:
        """Put the newest Command with stamp <= t_k in force (set_command only on change)."""
        i = bisect.bisect_right(self.stamps, t_ns + STAMP_TOL_NS) - 1
        if i < 0 or i == self.applied_index:
            return
        value, mode, gear, road, cadence_rpm, heart_rate_bpm = self.entries[self.entry_ids[i]]
        try:
            self.ctrl.set_command(value, mode, gear, road, heart_rate_bpm)
            self.rider_cadence_rpm = cadence_rpm          # the plant's rider is told with each batch
        except ValueError as exc:                         # the law's own validation
            self.rejected = True
            self.reject_reason = str(exc)
            self._publish_diag(DiagnosticStatus.WARN, f"Command rejected: {exc}; previous command kept")
        # older entries stay: a restarted plant's new run goes back to them
        self.applied_index = i

    def _publish_diag(self, level: int, message: str, stamp: int | None = None) -> None:
        status = DiagnosticStatus(level=level, name=self.diag_name, message=message,
                                  hardware_id="bike_controller")
        cmd = self.ctrl.status()
        values = {"command": f"{cmd['command']:g}", "mode": str(cmd["mode"]),
                  "command_rejected": str(self.rejected).lower(), "last_seq": str(self.last_seq)}
        values.update({k: str(v) for k, v in self.stats.items()})
        # realtime: answers that followed PlantStates skipped while this process was descheduled
        # (the law reads the newest only), and the control periods / sim time those covered. A
        # count, not a WARN: the laws bridge a gap (speed estimate, mode laws' time step), and a
        # stall past the plant's command_timeout_s is the plant's WARN. 0 in lockstep.
        values.update(skipped_state_gaps=str(self.ctrl.skipped_state_gaps),
                      skipped_periods=str(self.ctrl.skipped_periods),
                      skipped_time_s=f"{self.ctrl.skipped_periods * self.ctrl.inner.nominal.control_period_s:.6g}")
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        arr = DiagnosticArray(status=[status])
        if stamp is not None:
            arr.header.stamp = msgconv.time_msg(stamp)
        self.pub_diag.publish(arr)
        self.last_diag_wall = time.monotonic()

    def _check_stateless(self) -> None:
        """Before the first PlantState: a plant_state writer matched for PLANT_SILENT_S that
        delivered nothing is not a plant still starting (a plant joins the graph after its
        warm-up and re-publishes a held state every republish_s). Say so once, with what
        this node sees: nothing else would tell why the plant stays in its safe state, and
        name any process that still writes to a deleted shared-memory segment of this node's
        ports (the Fast DDS stale-port failure, bike_plant.shm_ports). That failure is healed
        by a new participant on fresh ports: the node stops and run_loop_node starts it over
        in a new context (once per process). Otherwise try a new reader: the subscription is
        re-created once; it costs nothing where all is well. With no writer matched at all,
        the signature is looked for every PLANT_SILENT_S: the writers' discovery data goes into
        the stale segment too (a deaf session never saw the /clock writer)."""
        now = time.monotonic()
        if self.sub_state.get_publisher_count() == 0:
            self.state_writer_since = None
            why = self.unmatched_watch.start_over(now)
            if why:
                text = (f"no plant_state writer matched and no PlantState: {why}; starting over with a new "
                        "DDS participant on fresh ports")
                self.get_logger().warning(text)
                self._publish_diag(DiagnosticStatus.WARN, text)
                self.fresh_ports_wanted = True
                self.stop_requested = True
            return
        if self.state_writer_since is None:
            self.state_writer_since = now
        elif now - self.state_writer_since > PLANT_SILENT_S:
            self.stateless_warned = True
            # that failure needs new ports: a new participant (bike_plant.loop.start_over_on_fresh_ports),
            # once per process
            why, fresh = shm_ports.stale_port_check()
            text = (f"no PlantState in the {PLANT_SILENT_S:g}s since a plant_state writer matched "
                    f"({self.sub_state.get_publisher_count()} matched): nothing delivered to this node, "
                    f"nothing to answer{'; ' + why if why else ''}; "
                    + ("starting over with a new DDS participant on fresh ports" if fresh
                       else "re-creating the subscription"))
            self.get_logger().warning(text)
            self._publish_diag(DiagnosticStatus.WARN, text)
            if fresh:
                self.fresh_ports_wanted = True
                self.stop_requested = True
                return
            old = self.sub_state
            self.sub_state = self._state_subscription()
            self.hot.replace(old, self.sub_state)
            self.destroy_subscription(old)

    def _check_stale_peers(self) -> None:
        """Hearing the plant, yet a peer still cannot reach this node (a controller restarted
        after a kill -9 whose session, or recorder, kept its handle on the killed one's port:
        shm_ports.StalePeerWatch). Say so once and start over on fresh ports (run_loop_node):
        the lockstep exchange resumes, the plant re-publishes its unanswered state and the
        session re-sends the Commands in force."""
        if say_stale_peer_and_start_over(self, self.peer_watch,
                                         lambda text: self._publish_diag(DiagnosticStatus.WARN, text)):
            self.stop_requested = True

    def run(self) -> int:
        while not self.stop_requested:
            self.hot.spin(0.1, self.busy.busy_s())
            if self.first_state_s is None:
                if not self.stateless_warned:
                    self._check_stateless()
            elif not self.peer_watch.finished:
                self._check_stale_peers()
            if self.pending is not None:
                self._try_answer()                         # command_wait_s expiry
            if (self.state_rx is not None and not self.plant_silent
                    and time.monotonic() - self.state_rx > PLANT_SILENT_S):
                # mid-run and no PlantState: the plant stopped or died (nothing to answer)
                self.plant_silent = True
                text = (f"no PlantState for {PLANT_SILENT_S:g}s after seq {self.last_seq}: the plant stopped "
                        "or paused mid-run (no batch to answer; a restarted plant starts a new run)")
                self.get_logger().warning(text)
                self._publish_diag(DiagnosticStatus.WARN, text)
        return 0


def warm_up_law(make_law, cfg: dict, machine: str, n: int, batches: int = 5) -> None:
    """Close the loop for a few batches in every mode, throw-away laws on a throw-away
    simulated plant, through the node's own paths (PlantState and DriveCommand as CDR
    views, ControllerStatus encoded), so numba compiles or loads the law's kernels before
    the node joins the graph. A compile inside the run held a lockstep run for tens of
    seconds; in realtime it would time the plant out at a mode's first use (or its first
    Hall edge: the config's rider starts pedalling, so edges come in the first batches)."""
    from bike_plant.node import make_backend

    build = msgconv.spmsm_drive_cdr if machine == "spmsm" else msgconv.drive_command_cdr
    # a drive on CAN: its states say measured_by_drive, and the law answers torque only
    measured = str(cfg.get("backend", "sim")) == "can"
    for mode in sorted(MODE_NAMES):
        if mode == MODE_SPINDOWN:
            continue                                  # no kernel of its own (a released brake), and it would log
        law = make_law()
        try:
            law.set_command(0.5, mode)
        except ValueError:
            continue                                  # a mode this machine's law does not take
        plant = make_backend("sim", cfg, 0)
        for k in range(batches):
            snap = plant.snapshot()
            snap.update(seq=k, batch_periods=n, backend="sim", measured_by_drive=measured, end_of_run=False)
            stamp = msgconv.seconds_to_ns(plant.time_s)
            view = msgconv.PlantStateView(msgconv.plant_state_cdr(snap, stamp))
            a, b, c, status = law.decide(dict(view.snap, stamp_ns=stamp), n)
            raw = build(k, a, b, c, stamp, float(status.get("torque_cmd_nm", 0.0)),
                        float(status.get("current_cmd_a", 0.0)))
            msgconv.controller_status_cdr(dict(status, seq=k, command_rejected=False), stamp)
            drive = msgconv.DriveCommandView(raw)
            if plant.problem(drive, n) is None:
                plant.apply(drive)
            else:                                     # a torque-only answer: the twin still moves
                plant.safe_batch(n)


def main(args=None) -> int:
    return run_loop_node(ControllerNode, "controller_node", args)


if __name__ == "__main__":
    sys.exit(main())
