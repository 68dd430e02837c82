"""FTMS bridge node ``ftms``: the bike as a smart trainer on the network, so that a training
app (Zwift, FulGaz, Rouvy, Wahoo SYSTM, MyWhoosh, QZ, ...) rides it over Wahoo Direct Connect
(bike_session.dircon: FTMS's GATT over TCP, port 36866).

- The app's Control Point requests (bike_session.ftms.FtmsControl: target power, inclination,
  resistance level, simulation grade, stop / resume, reset) become live Commands on
  ``live_command``, which the session node puts in its timeline from the next Command not
  yet sent (so one writer of ``command`` stays, and the bag and ``./bike replay`` have them).
- Every ``ftms.notify_period_s`` wall seconds the app is notified of Indoor Bike Data from the
  graph: power = the trainer's own estimate of the rider's power, as a trainer reports it
  (:class:`TrainerPowerMeter`: braking power + the bike's friction as the controller models it
  + the flywheel's energy change; exact when that model is, off when its friction figure is,
  until a spin-down), cadence = flywheel speed
  / load.gear_ratio, speed and distance = the virtual bike's (ControllerStatus.virtual_speed_mps,
  which follows the virtual gear), heart rate = the PlantState's (the rider's; left out of
  the data while it is 0), elapsed = the session's.
- The Training Status (FTMS 4.10, bike_session.ftms.FtmsControl.training_status) follows the
  session (SessionStatus: waiting, running the Command of a mode, done) and the app's target,
  stop and reset; it is notified when it changes (checked with the Control Point's poll).

Parameters: ``config_path`` (the bike's ranges and gear), ``ftms.host`` (127.0.0.1: only this
host, like DDS discovery; 0.0.0.0 to let an app on the network in), ``ftms.port`` (36866;
0 = any free port, logged), ``ftms.notify_period_s`` (0.25), ``ftms.advertise`` (auto | true |
false: the mDNS record apps discover a DIRCON trainer by, ``_wahoo-fitness-tnp._tcp``; auto =
when the host is not loopback), ``ftms.name`` (the advertised name; "" = "bike <namespace>").

An app should ride in real time (``./bike run --ftms`` sets sync_mode realtime). Plant state
and controller status come once per batch (1 kHz): their readers belong to a second node
that no executor serves (depth 1), and the latest of each is taken and decoded only when the
app is notified (bike_plant.cdr). Served by the executor, every batch woke the node twice and
it took 34 % of a core, more than the plant.
"""
from __future__ import annotations

import math
import sys

from bike_session import dircon, ftms

NODE_NAME = "ftms"


class SetupError(Exception):
    """A start-up problem reported as one line on stderr (exit code 2)."""


def services_for(control: ftms.FtmsControl, on_control_point) -> dict:
    """The GATT table served over DIRCON: the Fitness Machine Service and the Cycling Power
    Service, each characteristic with the properties FTMS 1.0.1, 4 (Table 4.1) gives it."""
    C, R, W, N = dircon.Characteristic, dircon.PROP_READ, dircon.PROP_WRITE, dircon.PROP_NOTIFY
    # the heart-rate range with the heart-rate target it bounds (a bike with a rider's heart rate)
    heart = [C(ftms.HEART_RATE_RANGE, R, read=control.encode_heart_rate_range)] if control.heart_rate else []
    return {ftms.FTMS_SERVICE: [
        C(ftms.FEATURE, R, read=control.encode_feature),
        # notify only: Table 4.1 excludes a read (it was served; no app reads it, trainers refuse it)
        C(ftms.INDOOR_BIKE_DATA, N),
        C(ftms.TRAINING_STATUS, R | N, read=control.encode_training_status),
        C(ftms.INCLINATION_RANGE, R, read=control.encode_inclination_range),
        C(ftms.RESISTANCE_RANGE, R, read=control.encode_resistance_range),
        *heart,
        C(ftms.POWER_RANGE, R, read=control.encode_power_range),
        C(ftms.CONTROL_POINT, W | N, write=on_control_point),
        C(ftms.STATUS, N),
    ], ftms.CPS_SERVICE: [
        C(ftms.CPS_MEASUREMENT, N),
        C(ftms.CPS_FEATURE, R, read=ftms.encode_cps_feature),
        C(ftms.SENSOR_LOCATION, R, read=lambda: bytes([ftms.SENSOR_LOCATION_OTHER])),
    ]}


class TrainerPowerMeter:
    """What a trainer knows of the rider's energy: its brake's, its modelled losses and its
    flywheel's kinetic energy, E = int (-T_em w + T_f(w) w) dt + 1/2 J w^2 (T_f: the friction
    the controller's laws use, bike_controller.modes.erg_power_w; J: the config's inertia). The
    rider's own is the plant's ledger (energy_mech_in_j); the report's trainer power error
    compares the two. Plain numbers in (tested without ROS)."""

    def __init__(self, inertia_kgm2: float, friction: tuple[float, float, float]):
        from bike_controller.modes import erg_power_w
        self._erg_power_w = erg_power_w          # once, not per plant state (1 kHz)
        self.inertia_kgm2 = float(inertia_kgm2)
        self.friction = friction             # (B, Tc, w_s [r/min]): set_friction follows the controller
        self.energy_j = 0.0
        self.last: tuple[int, float, float] | None = None    # (stamp_ns, T_em, w) of the last state
        self.running = False                 # the stamp has advanced since the start (of this run)

    def set_friction(self, friction_nms: float, dry_friction_nm: float) -> None:
        self.friction = (float(friction_nms), float(dry_friction_nm), self.friction[2])

    def add(self, stamp_ns: int, torque_em_nm: float, speed_rad_s: float) -> float:
        """One plant state (in order; T_em the mean over the batch ending at it): the cumulative
        estimate [J]. A stamp going back (a new run) starts again from there. Until the stamp first
        advances (sim time runs) the newest state is the start, and the flywheel counts from the end
        of that first batch: a drive on CAN not yet heard gives states with speed 0, and its first
        speed (at t = 0, or within the first batch) is no energy of the rider's."""
        if not (math.isfinite(torque_em_nm) and math.isfinite(speed_rad_s)):
            return self.energy_j
        if self.last is not None and stamp_ns < self.last[0]:
            self.running = False
        if self.last is not None and stamp_ns > self.last[0]:
            t0, _, w0 = self.last
            w_mid = 0.5 * (w0 + speed_rad_s)
            # the flywheel from the end of the first batch (a VESC is heard within it, as the CAN ledger has it)
            flywheel_j = 0.5 * self.inertia_kgm2 * (speed_rad_s * speed_rad_s - w0 * w0) if self.running else 0.0
            self.energy_j += float(self._erg_power_w(torque_em_nm, w_mid, self.friction)) * (stamp_ns - t0) * 1e-9 \
                + flywheel_j
            self.running = True
        if self.last is None or stamp_ns != self.last[0] or not self.running:
            self.last = (stamp_ns, torque_em_nm, speed_rad_s)
        return self.energy_j


class Telemetry:
    """Indoor Bike Data from the plant states, controller status and session status (plain
    numbers in, so it is tested without ROS).

    Power is the mean over whole crank half-turns, the fewest that span ``power_window_s`` of
    sim time, of the energy it is given (the trainer's estimate of the rider's, from
    :class:`TrainerPowerMeter`; the plant's ledger would do as well): the crank torque pulses
    twice a turn, and a window of any other length catches part of a pulse (a 1 s window at
    80 rpm holds 2.67 pulses and read 251-273 W for a steady 258 W). Power meters average over
    whole turns for the same reason. The turns are the cadence integrated over every plant
    state (:meth:`add_sample`); a crank that barely turns gets the plain time window."""

    HISTORY_S = 3.0                     # longest window kept (a half-turn at 10 rpm)

    def __init__(self, gear_ratio: float, power_window_s: float = 1.0):
        self.gear_ratio = gear_ratio
        self.window_ns = int(power_window_s * 1e9)
        # (stamp_ns, energy_mech_in_j, crank_revs) of every plant state, oldest first
        self.samples: list[tuple[int, float, float]] = []
        self.power_w = 0.0
        self.distance_m = 0.0
        self.speed_mps = 0.0
        self.cadence_rpm = 0.0
        self.level = 0.0
        self.elapsed_s = 0.0
        self.heart_rate_bpm = 0.0           # the rider's (PlantState); 0: none, not sent
        self.crank_revs = 0.0               # cumulative crank revolutions (the cadence integrated)
        self.crank_event_s = 0.0            # sim time of the last whole revolution
        self.notified_ns: int | None = None

    def add_sample(self, stamp_ns: int, energy_mech_in_j: float, speed_rpm: float) -> None:
        """One plant state (in order): the ledger's energy and the crank turns so far."""
        cadence_rpm = speed_rpm / self.gear_ratio if math.isfinite(speed_rpm) else 0.0
        if self.samples and stamp_ns < self.samples[-1][0]:
            self.samples.clear()           # a new run of the plant (restarted): a new ride
            self.distance_m = self.crank_revs = self.crank_event_s = 0.0
            self.notified_ns = None
        if self.samples and stamp_ns == self.samples[-1][0]:
            return
        if self.samples:
            t_prev_s, dt_s = self.samples[-1][0] * 1e-9, (stamp_ns - self.samples[-1][0]) * 1e-9
            # a crank sensor counts forward turns
            rate_prev, rate = max(self.cadence_rpm, 0.0) / 60.0, max(cadence_rpm, 0.0) / 60.0
            revs = self.crank_revs + 0.5 * (rate_prev + rate) * dt_s
            if math.floor(revs) > math.floor(self.crank_revs):
                # when the last whole turn was reached, on the interval's linear cadence
                k = math.floor(revs)
                self.crank_event_s = t_prev_s + dt_s * (k - self.crank_revs) / (revs - self.crank_revs)
            self.crank_revs = revs
        self.cadence_rpm = cadence_rpm
        self.samples.append((stamp_ns, energy_mech_in_j, self.crank_revs))
        if stamp_ns - self.samples[0][0] > 2 * self.HISTORY_S * 1e9:
            keep = stamp_ns - int(self.HISTORY_S * 1e9)
            self.samples = [x for x in self.samples if x[0] >= keep]

    def _window_start(self) -> tuple[int, float, float]:
        """The sample the power window starts at (see the class docstring)."""
        t1, _, r1 = self.samples[-1]
        by_time = self.samples[0]
        for x in reversed(self.samples):
            if x[0] <= t1 - self.window_ns:
                by_time = x
                break
        span = r1 - by_time[2]
        if span < 0.5:                      # under half a turn in the window: no pulse to cancel
            return by_time
        want = r1 - 0.5 * math.ceil(span / 0.5 - 1e-6)
        best = by_time
        for x in reversed(self.samples):    # revs only grow: stop once past the wanted turn
            if abs(x[2] - want) < abs(best[2] - want):
                best = x
            if x[2] < want:
                break
        return best

    def update(self, *, stamp_ns: int, energy_mech_in_j: float, speed_rpm: float, virtual_speed_mps: float,
               resistance_level: float, elapsed_s: float, heart_rate_bpm: float = 0.0) -> None:
        """At a notification: the newest plant state (added if not yet) and the rest."""
        self.add_sample(stamp_ns, energy_mech_in_j, speed_rpm)
        speed = virtual_speed_mps if math.isfinite(virtual_speed_mps) else 0.0
        if self.notified_ns is not None and stamp_ns > self.notified_ns:
            self.distance_m += 0.5 * (self.speed_mps + speed) * (stamp_ns - self.notified_ns) * 1e-9
        if self.notified_ns is None or stamp_ns > self.notified_ns:
            self.notified_ns = stamp_ns
            t0, e0, _ = self._window_start()
            if stamp_ns > t0:
                self.power_w = (energy_mech_in_j - e0) / ((stamp_ns - t0) * 1e-9)
        self.speed_mps = speed
        self.level = resistance_level
        self.elapsed_s = elapsed_s
        self.heart_rate_bpm = heart_rate_bpm if math.isfinite(heart_rate_bpm) else 0.0

    def encode_cps(self) -> bytes:
        return ftms.encode_cps_measurement(self.power_w, int(self.crank_revs), self.crank_event_s)

    def encode(self) -> bytes:
        return ftms.encode_indoor_bike_data(speed_kmh=3.6 * self.speed_mps, cadence_rpm=self.cadence_rpm,
                                            distance_m=self.distance_m, resistance_level=self.level,
                                            power_w=self.power_w, elapsed_s=self.elapsed_s,
                                            heart_rate_bpm=self.heart_rate_bpm)


def _bike_figures(config_path: str):
    """(ModeUnits, gear ratio, TrainerPowerMeter, has a heart rate) of the config; SetupError
    names what is wrong. A heart rate: a rider (his simulated heart, or a strap's on a CAN bike)."""
    from bike_plant.config import ConfigError, load_config

    from bike_controller.modes import friction_figures, machine_figures
    from bike_session.profiles import mode_units_from_config
    try:
        cfg = load_config(config_path or None)
        inertia = float((cfg.get("mechanics") or {}).get("inertia_kgm2", 0.01))
        heart_rate = str((cfg.get("load") or {}).get("kind", "")) == "rider" or cfg.get("backend") == "can"
        return (mode_units_from_config(cfg), machine_figures(cfg, with_envelope=False).gear_ratio,
                TrainerPowerMeter(inertia, friction_figures(cfg)), heart_rate)
    except (ConfigError, ValueError, TypeError) as exc:
        raise SetupError(f"bad config: {exc}") from None


def _unused(_msg) -> None:
    """The telemetry readers' callback: never called (no executor serves their node)."""


def _take_all(sub) -> list:
    """Every serialized message waiting on ``sub``, oldest first."""
    out = []
    with sub.handle:
        while True:
            taken = sub.handle.take_message(sub.msg_type, sub.raw)
            if taken is None:
                return out
            out.append(taken[0])


def _make_node_class():
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.node import Node

    from bike_msgs.msg import Command, ControllerStatus, PlantState, SessionStatus
    from bike_plant.cdr import Codec, CdrError
    import rclpy
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from bike_plant.msgconv import PlantStateView, set_command_road
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    from bike_session.session_node import live_qos

    any_type = ParameterDescriptor(dynamic_typing=True)
    status_codec = Codec(ControllerStatus)

    class FtmsNode(Node):
        def __init__(self, **kwargs):
            super().__init__(NODE_NAME, **kwargs)
            config_path = self.declare_parameter("config_path", "").value
            host = self.declare_parameter("ftms.host", "127.0.0.1").value
            port = self.declare_parameter("ftms.port", dircon.DEFAULT_PORT, any_type).value
            period = self.declare_parameter("ftms.notify_period_s", 0.25, any_type).value
            # `-p ftms.advertise:=true` arrives as a bool, auto as a string
            advertise = str(self.declare_parameter("ftms.advertise", "auto", any_type).value).lower()
            name = self.declare_parameter("ftms.name", "").value
            if advertise not in ("auto", "true", "false"):
                raise SetupError(f"parameter ftms.advertise must be auto, true or false, got {advertise!r}")
            if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
                raise SetupError(f"parameter ftms.port must be an integer 0..65535, got {port!r}")
            if isinstance(period, bool) or not isinstance(period, (int, float)) or not 0.02 <= period <= 10:
                raise SetupError(f"parameter ftms.notify_period_s must be 0.02..10 s, got {period!r}")
            units, gear_ratio, self.meter, heart_rate = _bike_figures(config_path)
            self.control = ftms.FtmsControl(units, heart_rate)
            self.telemetry = Telemetry(gear_ratio)
            self.pending_status: list[bytes] = []
            self._Command = Command
            self._Diag, self._DiagStatus, self._KeyValue = DiagnosticArray, DiagnosticStatus, KeyValue
            # the app's latest target stays with the writer (transient local): a session that
            # matches later (an app connected at start-up, a restarted session) still gets it
            self.pub_live = self.create_publisher(Command, "live_command", live_qos())
            self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
            # once per batch from the plant and the controller: read through a node no executor
            # serves (best effort), taken when the app is notified. The controller's newest is
            # enough; every plant state is kept (1 kHz in real time: a notification's 250, up
            # to 600) for the power over whole crank turns
            latest = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.BEST_EFFORT)
            every = QoSProfile(depth=600, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.BEST_EFFORT)
            # its own name: the launcher's `-r __node:=NAME` applies to every node of the process,
            # and a node-local remap takes precedence over it (else two nodes NAME in the graph)
            taps_name = f"{self.get_name()}_taps"
            self.taps = rclpy.create_node(taps_name, namespace=self.get_namespace(), context=self.context,
                                          cli_args=["--ros-args", "-r", f"__node:={taps_name}"])
            self.sub_plant = self.taps.create_subscription(PlantState, "plant_state", _unused, every, raw=True)
            self.sub_status = self.taps.create_subscription(ControllerStatus, "controller_status", _unused, latest,
                                                            raw=True)
            self.plant_view = self.status_raw = None
            self.session_elapsed_s = 0.0
            self.create_subscription(SessionStatus, "session_status", self._on_session, 10)
            self._PlantStateView, self._status_codec, self._CdrError = PlantStateView, status_codec, CdrError
            self._set_road = set_command_road
            try:
                self.server = dircon.DirconServer(host, int(port), services_for(
                    self.control, self._on_control_point), self._log, self._on_app_gone)
            except OSError as exc:
                raise SetupError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
            # apps find a trainer by mDNS; on loopback only (the default) nobody else could reach it
            self.advertiser = None
            if advertise == "true" or (advertise == "auto" and not str(host).startswith("127.")):
                self.advertiser = dircon.Advertiser(name or f"bike {self.get_namespace().strip('/') or 'sim'}",
                                                    dircon.host_addresses(str(host)), self.server.port,
                                                    self._serial(), self._log)
            from rclpy.clock import Clock as RosClock
            from rclpy.clock import ClockType
            steady = RosClock(clock_type=ClockType.STEADY_TIME)
            # wall-clock timers: the app lives on the wall clock, whatever sim time does
            self.create_timer(0.01, self._poll, clock=steady)
            self.create_timer(float(period), self._notify, clock=steady)
            self.get_logger().info(f"FTMS over DIRCON on {self.server.host}:{self.server.port} "
                                   f"(service {dircon.MDNS_SERVICE}); power 0..{units.erg_power_max_w:g} W, "
                                   f"grade {100 * units.grade_min:g}..{100 * units.grade_max:g} %")
            self._diag("listening", self._DiagStatus.OK)

        def _serial(self) -> str:
            """This bike's serial number for the apps: host, namespace and port (unique per bike)."""
            import socket
            return f"{socket.gethostname()}{self.get_namespace().rstrip('/')}:{self.server.port}"

        # ---- ROS side
        def _on_session(self, msg) -> None:
            self.session_elapsed_s = float(msg.elapsed_s)
            self.control.follow_session(int(msg.state), int(msg.mode), float(msg.heart_rate_bpm))

        def _log(self, text: str, warning: bool) -> None:
            if warning:      # one call site per severity (rclpy's logger insists)
                self.get_logger().warning(text)
                self._diag(text, self._DiagStatus.WARN)
            else:
                self.get_logger().info(text)

        def _diag(self, message: str, level) -> None:
            st = self._DiagStatus(level=level, name=self.get_fully_qualified_name(), message=message,
                                  hardware_id=self.get_namespace())
            server = getattr(self, "server", None)      # None while it is being made
            st.values = [self._KeyValue(key="port", value=str(server.port) if server else ""),
                         self._KeyValue(key="apps", value=str(len(server.conns)) if server else "0")]
            self.pub_diag.publish(self._Diag(status=[st]))

        # ---- app side
        def _on_app_gone(self, conn) -> None:
            released = self.control.release(conn)
            if released:
                self._log(f"FTMS {released}", False)

        def _on_control_point(self, data: bytes, client) -> list:
            reply = self.control.write(data, client)
            if reply.message:
                self._log(f"FTMS {reply.message}", reply.warning)
            if reply.target is not None:
                msg = self._Command()
                msg.command = float(reply.target.command)
                msg.mode = int(reply.target.mode)
                self._set_road(msg, reply.target.road)
                msg.cadence_rpm = float(reply.target.cadence_rpm)
                msg.heart_rate_bpm = float(reply.target.heart_rate_bpm)
                self.pub_live.publish(msg)
            if reply.status is not None:
                self.pending_status.append(reply.status)
            return [(ftms.CONTROL_POINT, reply.response)]

        def _poll(self) -> None:
            self.server.poll(0.0)
            while self.pending_status:            # after the writer's response: to every app
                self.server.broadcast(ftms.STATUS, self.pending_status.pop(0))
            # a new training status (the app's target, its stop or reset, the session's progress)
            training = self.control.training_status_change()
            if training is not None:
                self._log(f"FTMS training status: {ftms.training_status_text(training)}", False)
                self.server.broadcast(ftms.TRAINING_STATUS, training)

        def _notify(self) -> None:
            states = _take_all(self.sub_plant)
            self.status_raw = (_take_all(self.sub_status) or [self.status_raw])[-1]
            try:
                st = self._status_codec.decode(self.status_raw)[3] if self.status_raw is not None else {}
            except self._CdrError as exc:
                self._log(f"a controller status that does not decode: {exc}", True)
                st = {}
            if "friction_nms" in st:              # the laws' friction in force (a spin-down moves it)
                self.meter.set_friction(float(st["friction_nms"]), float(st.get("dry_friction_nm", 0.0)))
            bad = None
            for raw in states:
                try:
                    view = self._PlantStateView(raw)
                except self._CdrError as exc:
                    bad = exc
                    continue
                energy = self.meter.add(view.stamp_ns, float(view.snap["torque_em_nm"]),
                                        float(view.snap["speed_rad_s"]))
                self.telemetry.add_sample(view.stamp_ns, energy, float(view.snap["speed_rpm"]))
                self.plant_view = view
            if bad is not None:
                self._log(f"a plant state that does not decode: {bad}", True)
            if self.plant_view is None:
                return
            # the controller's spin-down moved on: to every app
            for progress in self.control.spin_down_progress(int(st.get("mode", 0)), float(st.get("mode_target", 0.0))):
                self._log(f"FTMS {ftms.SPIN_DOWN_NAMES[progress[1]]}", progress[1] == ftms.SPIN_DOWN_ERROR)
                self.server.broadcast(ftms.STATUS, progress)
            view = self.plant_view
            state = view.snap
            level = 100.0 * st.get("command", 0.0) if st.get("mode", 0) == 0 else 0.0
            self.telemetry.update(stamp_ns=view.stamp_ns, energy_mech_in_j=self.meter.energy_j,
                                  speed_rpm=float(state["speed_rpm"]),
                                  virtual_speed_mps=float(st.get("virtual_speed_mps", 0.0)),
                                  resistance_level=level, elapsed_s=self.session_elapsed_s,
                                  heart_rate_bpm=float(state.get("heart_rate_bpm", 0.0)))
            self.server.broadcast(ftms.INDOOR_BIKE_DATA, self.telemetry.encode())
            self.server.broadcast(ftms.CPS_MEASUREMENT, self.telemetry.encode_cps())

    return FtmsNode


def main(args=None) -> int:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from bike_session.session_node import stop_on_signals

    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    asked = stop_on_signals()            # a flag, read between spins (as the other nodes)
    node = executor = None
    rc = 0
    try:
        node = _make_node_class()()
        executor = SingleThreadedExecutor(context=node.context)
        executor.add_node(node)
        while asked["signum"] is None and rclpy.ok(context=node.context):
            executor.spin_once(timeout_sec=0.1)
    except SetupError as exc:
        print(f"ftms_node: error: {exc}", file=sys.stderr, flush=True)
        rc = 2
    finally:
        if node is not None and hasattr(node, "server"):
            node.server.close()
        if node is not None and getattr(node, "advertiser", None) is not None:
            node.advertiser.close()
        if executor is not None:
            executor.remove_node(node)
            executor.shutdown()
        if node is not None:
            if hasattr(node, "taps"):
                node.taps.destroy_node()
            node.destroy_node()
        rclpy.try_shutdown()
    return rc


if __name__ == "__main__":
    sys.exit(main())
