"""Session node: plays a workout profile as a Command timeline on sim time.

Node name ``session`` (namespace ``/bike`` by default). Parameters:

- ``session.profile`` (string): profile YAML; a relative path resolves against the
  directory of ``config_path`` when that is set, else against the working directory.
- ``session.workout`` (string, ""): a workout file (.zwo, .erg, .mrc, .fit or a profile .yaml)
  ridden instead of ``session.profile`` when set, resolved like it (bike_session.workouts); power targets
  ride in ERG mode. ``session.ftp_w`` (0 = the file's own FTP) is the rider's FTP,
  ``session.max_hr_bpm`` (0 = not given) his maximum heart rate (a FIT heart-rate target in
  percent of it) and ``session.over_range`` (warn | error) what to do with targets beyond the
  machine's range. Text events of the workout are logged at their time.
- ``session.period_s`` (0.1): Command period in sim seconds.
- ``duration_s`` (0.0): run length in sim seconds; 0 = profile length.
  ``session.duration_s`` (0.0), when > 0, takes precedence (DESIGN.md puts it there).
- ``config_path`` (string): the scenario config file, used to resolve the profile path and
  recorded verbatim in ``session_info``.

Virtual shifting: every Command carries the gear of the profile segment in force
(``gear:``, Profile.gear_at; 0 = the config's). A std_msgs/Int8 on ``shift`` (``/bike/shift``;
``./bike shift N``) moves it N gears up (or -N down) through the config's ``modes.virtual_gears``
from the next Command not yet sent, until a later segment gives a gear; at either end of the
table the node logs how many gears it took. With ``modes.erg_shift_w`` > 0 a press while the
Command is ERG moves the power target by that many watts instead (until the profile's next
segment), as stand-alone trainer shifters do. Commands sent again (a restarted plant, a re-published
state) repeat the gear they were first sent with.

Targets of the rider: every Command carries the cadence target (``cadence_rpm``,
Profile.cadence_at) and the ERG heart-rate target (``heart_rate_bpm``, Profile.heart_rate_at) of
the profile segment in force (0: none). In heart-rate ERG a shift press shifts the gear: the
power follows the heart rate there, so there is no power target to move.

Live Commands: a bike_msgs/Command on ``live_command`` (an app's target through the FTMS
bridge, bike_session.ftms_node) replaces the profile's mode, value, cadence and heart-rate
targets from the next Command not yet sent until the next live one or the run's end (a gear
other than 0 is shifted to); a bad one is one warning. Re-sent Commands repeat what they were
first sent with.

Lockstep protocol (DESIGN.md): on every ``/clock`` value t the node publishes the Command
for every tau_j = j * period_s with tau_j <= t + period_s that it has not published yet,
stamped tau_j (so at t = 0 it sends tau_0 and tau_1). The command of a tau_j at or after the
run's end is 0. One SessionStatus per period (with the rider's targets in force: the gear, the
cadence and heart-rate targets); at t >= duration a final DONE status and a
Command of 0, then the node exits with code 0. A bad profile: one error line, exit code 2.
"""
from __future__ import annotations

import array
import bisect
import datetime as _dt
import json
import math
import os
import pathlib
import signal
import subprocess
import sys
import time

from bike_session.profiles import MODE_NAMES, Profile, ProfileError, describe_command, load_profile, shifted_gear

NODE_NAME = "session"
COMMAND_QOS_DEPTH = 100
# /clock comes once per batch; the node takes it in bursts (see gather_pause_s): the reader
# keeps this many samples so that none is lost meanwhile (every value is handled, in order)
CLOCK_QOS_DEPTH = 1000
NO_CLOCK_WARN_S = 5.0          # no /clock this long after start-up: say so once [wall s]
GATHER_MAX_S = 0.02            # longest pause between bursts [wall s]
GATHER_SHARE_OF_PERIOD = 0.25  # a burst lags sim time by at most this share of session.period_s


class SetupError(Exception):
    """A start-up problem reported as one line on stderr (exit code 2)."""


def software_version() -> str:
    """``git describe`` of the source tree when available, else the package version."""
    here = pathlib.Path(__file__).resolve().parent
    try:
        out = subprocess.run(["git", "-C", str(here), "describe", "--always", "--dirty", "--tags"],
                             capture_output=True, text=True, timeout=3)
        if out.returncode == 0 and out.stdout.strip():
            return out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        pass
    try:
        from importlib.metadata import version
        return version("bike_session")
    except Exception:  # noqa: BLE001 - metadata may be missing in odd installs
        return "unknown"


def resolve_profile_path(profile: str, config_path: str = "") -> pathlib.Path:
    """Resolve ``session.profile`` against the config file's folder (or the cwd)."""
    from bike_plant.config import resolve_config_path
    return resolve_config_path(profile, config_path)


def collect_seeds(config_path: str) -> dict:
    """Every parameter whose name ends in 'seed' in the config file (for reproducibility)."""
    if not config_path:
        return {}
    try:
        from bike_plant.config import flatten, load_config
        cfg = load_config(config_path)
    except Exception:  # noqa: BLE001 - the metadata must never stop a session
        return {}
    return {k: v for k, v in flatten(cfg).items() if k.split(".")[-1].endswith("seed")}


def _read_text(path: str | os.PathLike, limit: int = 1 << 20) -> str | None:
    try:
        with open(path, "rb") as fh:
            return fh.read(limit).decode("utf-8", "replace")
    except OSError:
        return None


def build_session_info(profile: Profile, profile_path: pathlib.Path, config_path: str, *,
                       period_s: float, duration_s: float, namespace: str) -> dict:
    return {
        "profile_name": profile.name,
        "profile_path": str(profile_path),
        "profile_text": profile.text,
        "profile_duration_s": profile.duration_s,
        "config_path": config_path or None,
        "config_text": _read_text(config_path) if config_path else None,
        "software_version": software_version(),
        "start_wall_time": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds"),
        "seeds": collect_seeds(config_path),
        "period_s": period_s,
        "duration_s": duration_s,
        "namespace": namespace,
        "modes": MODE_NAMES,
        "workout": profile.info() if hasattr(profile, "info") else None,
    }


def _bike_config(config_path: str) -> dict | None:
    """The loaded config, read once for the mode ranges and the gear table; None without a
    config or when it is bad (the config's problems are the other nodes' to report: the
    controller does not start)."""
    if not config_path:
        return None
    from bike_plant.config import ConfigError, load_config
    try:
        return load_config(config_path)
    except ConfigError:
        return None


def _mode_params(cfg: dict | None):
    """The config's ``modes`` section (its virtual gear and gear table); the defaults without a
    (good) config."""
    from bike_controller.modes import ModeParams, mode_params_from_config
    if cfg is not None:
        try:
            return mode_params_from_config(cfg)
        except ValueError:
            pass
    return ModeParams()


def _units(cfg: dict | None):
    """The bike's mode ranges for profile targets; None without a config or when the
    config does not give them (a profile that uses targets then gets its own clear error)."""
    if cfg is None:
        return None
    from bike_session.profiles import mode_units_from_config
    try:
        return mode_units_from_config(cfg)
    except ValueError:
        return None


def live_qos(depth: int = 1):
    """live_command's QoS: reliable and transient local, so that a target written before the
    session matched (an app connected at start-up, a restarted session) still reaches it; the
    writer keeps its latest (depth 1), the session reads with depth 100 so that targets
    written close together are all taken, also when a writer of a deeper history (a script,
    a test) matched this reader only after writing them: they then arrive as one burst (10
    kept 10 of a fuzz test's 40 when the session's side of the match came 0.4 s late). A
    writer of its own must be transient local too (`ros2 topic pub --qos-durability
    transient_local ...`): DDS does not match a volatile writer with this reader."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _make_node_class():
    # rclpy is imported lazily so that the module's helpers import without ROS.
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    from bike_msgs.msg import Command, SessionStatus
    from bike_plant.loop import say_stale_peer_and_start_over, take_sim_time_from_messages
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from rosgraph_msgs.msg import Clock
    from std_msgs.msg import Int8, String

    any_type = ParameterDescriptor(dynamic_typing=True)

    class SessionNode(Node):
        def __init__(self, **kwargs):
            super().__init__(NODE_NAME, **kwargs)
            p = {}
            from bike_session.workouts import over_range_problem, session_number_problem
            for name, default in (("session.profile", ""), ("config_path", ""), ("session.workout", "")):
                p[name] = self.declare_parameter(name, default).value
            # any type: a config's over_range: 5 is this error, not rclpy's type exception
            p["session.over_range"] = self.declare_parameter("session.over_range", "warn", any_type).value
            if over_range_problem(p["session.over_range"]):
                raise SetupError(f"parameter session.over_range {over_range_problem(p['session.over_range'])}")
            for name, default in (("session.period_s", 0.1), ("duration_s", 0.0), ("session.duration_s", 0.0),
                                  ("session.ftp_w", 0.0), ("session.max_hr_bpm", 0.0)):
                value = self.declare_parameter(name, default, any_type).value
                if session_number_problem(name, value):
                    raise SetupError(f"parameter {name} {session_number_problem(name, value)}")
                p[name] = float(value)
            if not p["session.profile"] and not p["session.workout"]:
                raise SetupError("parameters session.profile and session.workout are empty: give a profile "
                                 "or workout file")
            config_path = p["config_path"]
            cfg = _bike_config(config_path)
            if p["session.workout"]:
                # like session.profile: against the config's folder (./bike run gives it absolute)
                profile_path = resolve_profile_path(p["session.workout"], config_path).resolve()
                self.profile = self._load_workout(profile_path, config_path, p, _units(cfg))
            else:
                profile_path = resolve_profile_path(p["session.profile"], config_path)
                try:
                    self.profile = load_profile(profile_path, units=_units(cfg))
                except ProfileError as exc:
                    raise SetupError(f"bad profile: {exc}") from None

            self.period_ns = int(round(p["session.period_s"] * 1e9))
            if self.period_ns <= 0:
                raise SetupError(f"parameter session.period_s too small: {p['session.period_s']!r}")
            self.period_s = self.period_ns * 1e-9
            duration = p["session.duration_s"] or p["duration_s"] or self.profile.duration_s
            self.duration_s = duration
            self.duration_ns = int(round(duration * 1e9))

            # reliable, keep_last 100; transient_local so that a subscriber matched late (the
            # recorder, a controller started after the first /clock) still gets the first
            # commands. Compatible with volatile subscriptions.
            cmd_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=COMMAND_QOS_DEPTH,
                                 reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
            latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                                 reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
            clock_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=CLOCK_QOS_DEPTH,
                                   reliability=ReliabilityPolicy.RELIABLE)
            self._Command, self._SessionStatus = Command, SessionStatus
            self._DiagnosticArray, self._DiagnosticStatus, self._KeyValue = DiagnosticArray, DiagnosticStatus, KeyValue
            self.pub_command = self.create_publisher(Command, "command", cmd_qos)
            self.pub_status = self.create_publisher(SessionStatus, "session_status", cmd_qos)
            self.pub_info = self.create_publisher(String, "session_info", latched)
            self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
            self.sub_clock = self.create_subscription(Clock, "/clock", self._on_clock, clock_qos)
            take_sim_time_from_messages(self)
            # virtual shifting: +n / -n gears through the config's modes.virtual_gears
            modes = _mode_params(cfg)
            self.config_gear = modes.virtual_gear_ratio
            self.gear_table = tuple(modes.virtual_gears)
            self.sub_shift = self.create_subscription(Int8, "shift", self._on_shift, 10)
            self.live_gear = None        # the gear of the last shift, until a segment gives one
            self.live_leaf = -1          # the profile leaf in force when it was shifted
            self.sent_gears = array.array("d")   # the gear of each published tau index j
            self.shifts = 0
            # live Commands (_on_live_command) and ERG bumps (_bump_erg): from tau index
            # live_from_j[k] on, live_targets[k] = (command, mode, label, until tau index, road, cadence,
            # heart rate)
            self.sub_live = self.create_subscription(Command, "live_command", self._on_live_command, live_qos(100))
            self.live_from_j: list[int] = []
            self.live_targets: list[tuple[float, int, str, int, tuple | None, float, float]] = []
            self.live_commands = 0
            self.erg_shift_w = modes.erg_shift_w
            self.units = units = _units(cfg)
            self.erg_max_w = units.erg_power_max_w if units is not None else 0.0
            self.erg_bumps = 0

            self.next_j = 0              # next tau index to publish
            self.last_status_k = -1      # last period index a status was published for
            self.last_t_ns = None
            self.resent_at_ns = None     # /clock value whose Commands were last sent again
            self.state = SessionStatus.STATE_WAITING
            self.done = False
            self.fresh_ports_wanted = False  # deaf on a stale shared-memory port (_check_deaf_start)
            self.started_wall = time.monotonic()
            from bike_plant import shm_ports
            self.deaf_watch = shm_ports.StalePortWatch(since=self.started_wall)
            self.peer_watch = shm_ports.StalePeerWatch(since=self.started_wall)   # running (_check_stale_peers)
            self.no_clock_warned = False
            self.commands_published = 0
            self.readers_at_publish = 0      # matched Command readers when the last Command went out
            self._rate_mark = None           # (sim ns, wall s) at the last burst (gather_pause_s)

            info = build_session_info(self.profile, profile_path, config_path, period_s=self.period_s,
                                      duration_s=self.duration_s, namespace=self.get_namespace())
            self.pub_info.publish(String(data=json.dumps(info, sort_keys=True)))
            self._publish_status(0, SessionStatus.STATE_WAITING)
            self._publish_diag("waiting for /clock")
            # on the steady clock: under use_sim_time (the configs) a ROS-time timer waits for a
            # /clock that has not come, and this one is for exactly that time
            from rclpy.clock import Clock as RosClock
            from rclpy.clock import ClockType
            self.wait_timer = self.create_timer(1.0, self._on_wait_timer,
                                                clock=RosClock(clock_type=ClockType.STEADY_TIME))
            self.get_logger().info(
                f"profile {self.profile.name!r} ({self.profile.duration_s:g} s, {len(self.profile.segments)} segments) "
                f"from {profile_path}; run {self.duration_s:g} s, period {self.period_s:g} s")

        def _load_workout(self, path: pathlib.Path, config_path: str, p: dict, units) -> Profile:
            import warnings

            from bike_plant.config import ConfigError, load_config
            from bike_session.workouts import WorkoutWarning, load_workout, pmax_w_from_config
            try:
                pmax_w = pmax_w_from_config(load_config(config_path or None))
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", WorkoutWarning)     # logged below, once each
                    profile = load_workout(path, ftp_w=p["session.ftp_w"] or None, pmax_w=pmax_w,
                                           over_range=p["session.over_range"], units=units,
                                           max_hr_bpm=p["session.max_hr_bpm"] or None)
            except (ProfileError, ConfigError) as exc:
                raise SetupError(f"bad workout: {exc}") from None
            for text in getattr(profile, "warnings", []):
                self.get_logger().warning(text)
            return profile

        # ---------------------------------------------------------------- timeline
        def command_for(self, tau_ns: int) -> tuple[float, int, int, str]:
            cmd, mode, index, label = self.profile.command_at(tau_ns * 1e-9)
            live = self._live_at(tau_ns // self.period_ns)
            if live is not None:
                cmd, mode, label = live[:3]
            if tau_ns >= self.duration_ns:
                cmd = 0.0
            return cmd, mode, index, label

        def _live_at(self, j: int):
            """The latest live target from before tau_j that has not ended (an ERG bump ends
            where the profile's next segment begins; the one it bumped then holds again), or None."""
            for k in range(bisect.bisect_right(self.live_from_j, j) - 1, -1, -1):
                if j < self.live_targets[k][3]:
                    return self.live_targets[k]
            return None

        def road_for(self, j: int):
            """The road (crr, cw_kg_m, wind_mps) of the Command at tau_j: a live target's, else the
            profile's; None: the config's."""
            live = self._live_at(j)
            return self.profile.road_at(j * self.period_s) if live is None else live[4]

        def cadence_for(self, j: int) -> float:
            """The rider's cadence target of the Command at tau_j: a live target's, else the
            profile's (a workout's Cadence); 0: none."""
            live = self._live_at(j)
            return (self.profile.cadence_at(j * self.period_s) or 0.0) if live is None else live[5]

        def heart_rate_for(self, j: int) -> float:
            """The ERG heart-rate target of the Command at tau_j: a live target's, else the
            profile's (a FIT heart-rate step's); 0: none."""
            live = self._live_at(j)
            return (self.profile.heart_rate_at(j * self.period_s) or 0.0) if live is None else live[6]

        def _add_live(self, j: int, command: float, mode: int, label: str, until_j: int, road=None,
                      cadence_rpm: float = 0.0, heart_rate_bpm: float = 0.0) -> None:
            """A live target from tau index j (not sent yet) until until_j, on ``road``, with the
            rider's cadence and heart-rate targets."""
            target = (command, mode, label, until_j, road, cadence_rpm, heart_rate_bpm)
            if self.live_from_j and self.live_from_j[-1] == j:     # not sent yet: replaced
                self.live_targets[-1] = target
            else:
                self.live_from_j.append(j)
                self.live_targets.append(target)

        def _segment_end_j(self, j: int) -> int:
            """The first tau index of the profile leaf after the one in force at tau_j."""
            seg = self.profile.segment_at(j * self.period_s)
            if seg is None:
                return 1 << 62
            return math.ceil(seg.end_s / self.period_s - 1e-9)

        def _leaf_at(self, t_s: float) -> int:
            """The profile leaf in force at t_s (the last one past the end)."""
            seg = self.profile.segment_at(t_s)
            return len(self.profile.segments) - 1 if seg is None else seg.index

        def _set_live_gear(self, gear: float, t_s: float) -> None:
            """A gear from t_s on, until a later profile leaf gives one (gear_for)."""
            self.live_leaf = self._leaf_at(t_s)
            self.live_gear = gear

        def _bump_erg(self, steps: int, j: int) -> bool:
            """A shift press in ERG with modes.erg_shift_w > 0: the target moves steps x that
            many W from tau_j until the profile's next segment (SmartSpin2k-style shifters);
            within 0 .. erg_power_max_w, else the press takes what fits and says so. False
            when the Command at tau_j is not ERG (the press shifts the gear)."""
            cmd, mode, _, _ = self.command_for(j * self.period_ns)
            if mode != self._Command.MODE_ERG or self.erg_shift_w <= 0.0 or self.erg_max_w <= 0.0:
                return False
            if self.heart_rate_for(j):
                return False        # heart-rate ERG: the command is only where the power started
            old_w = cmd * self.erg_max_w
            new_w = min(max(old_w + steps * self.erg_shift_w, 0.0), self.erg_max_w)
            t_s = j * self.period_s
            if new_w != old_w + steps * self.erg_shift_w:
                self.get_logger().warning(
                    f"shift {steps:+d} in ERG at t = {t_s:g} s: target {old_w:.0f} W -> {new_w:.0f} W, the "
                    f"{'top' if steps > 0 else 'bottom'} of the power range (0 .. {self.erg_max_w:g} W)")
            if new_w == old_w:
                return True
            label = f"ERG {new_w:.0f} W (shifted {new_w - old_w:+.0f} W)"
            self._add_live(j, new_w / self.erg_max_w, self._Command.MODE_ERG, label, self._segment_end_j(j),
                           self.road_for(j), self.cadence_for(j))
            self.erg_bumps += 1
            self.get_logger().info(f"shift {steps:+d} in ERG: target {old_w:.0f} W -> {new_w:.0f} W from "
                                   f"t = {t_s:g} s until the next profile segment")
            return True

        def _on_live_command(self, msg) -> None:
            """A live Command (an app's target through bike_session.ftms_node, or anything on
            ``live_command``): its mode and value replace the profile's from the next Command
            not yet sent until the next live Command or the run's end; a gear other than 0 is
            shifted to as ``shift`` would. The header is not read. A bad one: one warning, nothing
            changes."""
            if self.done:
                return
            from bike_plant.msgconv import command_problem, command_road
            problem = command_problem(msg)
            if problem is not None:
                text = f"live Command rejected: {problem}; the Commands go on unchanged"
                self.get_logger().warning(text)
                self._publish_diag(text, self._DiagnosticStatus.WARN)
                return
            j = self.next_j
            label = f"live: {describe_command(int(msg.mode), float(msg.command), self.units, msg.heart_rate_bpm)}"
            road = command_road(msg)
            self._add_live(j, float(msg.command), int(msg.mode), label, 1 << 62, road, float(msg.cadence_rpm),
                           float(msg.heart_rate_bpm))
            if msg.virtual_gear_ratio > 0.0:
                self._set_live_gear(float(msg.virtual_gear_ratio), j * self.period_s)
            self.live_commands += 1
            self.get_logger().info(f"{label} from t = {j * self.period_s:g} s"
                                   + (f", virtual gear {msg.virtual_gear_ratio:g}" if msg.virtual_gear_ratio else "")
                                   + (f", road Crr {road[0]:g}, Cw {road[1]:g} kg/m, wind {road[2]:g} m/s"
                                      if road is not None else ""))

        def gear_for(self, j: int) -> float:
            """The virtual gear of the Command at tau_j (0: the config's): the one it was sent
            with, else the last shift's until a later profile segment gives a gear, else the
            profile's (Profile.gear_at)."""
            if j < len(self.sent_gears):
                return self.sent_gears[j]
            tau_s = j * self.period_s
            if self.live_gear is not None:
                leaf = self._leaf_at(tau_s)
                if not any(i in self.profile.gears_given for i in range(self.live_leaf + 1, leaf + 1)):
                    return self.live_gear
                self.live_gear = None
            return self.profile.gear_at(tau_s)

        def _on_shift(self, msg) -> None:
            """A shifter's press: ``msg.data`` gears up (> 0) or down, from the next Command
            not yet sent (at most 2 session periods after the press)."""
            steps = int(msg.data)
            if steps == 0 or self.done:
                return
            j = self.next_j
            if self._bump_erg(steps, j):
                return
            current = self.gear_for(j) or self.config_gear
            new, taken = shifted_gear(self.gear_table, current, steps)
            t_s = j * self.period_s
            if taken != steps:
                end = "top" if steps > 0 else "bottom"
                self.get_logger().warning(
                    f"shift {steps:+d} at t = {t_s:g} s: {abs(taken)} gear(s) taken from {current:g}, the {end} of "
                    f"the table (modes.virtual_gears: {len(self.gear_table)} gears, "
                    f"{self.gear_table[0]:g} .. {self.gear_table[-1]:g})")
            if taken == 0:
                return
            self._set_live_gear(new, t_s)
            self.shifts += 1
            self.get_logger().info(f"shift {taken:+d}: virtual gear {current:g} -> {new:g} from t = {t_s:g} s")

        def _publish_command(self, j: int) -> None:
            tau_ns = j * self.period_ns
            cmd, mode, _, _ = self.command_for(tau_ns)
            gear = self.gear_for(j)
            while len(self.sent_gears) <= j:          # re-sent Commands repeat their gear
                self.sent_gears.append(gear)
            msg = self._Command()
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(tau_ns, 1_000_000_000)
            msg.command = float(cmd)
            msg.mode = int(mode)
            msg.virtual_gear_ratio = float(gear)
            from bike_plant.msgconv import set_command_road
            set_command_road(msg, self.road_for(j))
            msg.cadence_rpm = float(self.cadence_for(j))
            msg.heart_rate_bpm = float(self.heart_rate_for(j))
            self.pub_command.publish(msg)
            self.commands_published += 1
            self.readers_at_publish = self.pub_command.get_subscription_count()

        def _publish_status(self, t_ns: int, state: int) -> None:
            SessionStatus = self._SessionStatus
            msg = SessionStatus()
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(max(t_ns, 0), 1_000_000_000)
            msg.profile_name = self.profile.name
            msg.state = state
            elapsed = max(t_ns, 0) * 1e-9
            msg.elapsed_s = elapsed
            msg.duration_s = self.duration_s
            msg.progress = min(max(elapsed / self.duration_s, 0.0), 1.0) if self.duration_s > 0 else 1.0
            # the command in force at t is the one of the last tau_j <= t
            tau_ns = (max(t_ns, 0) // self.period_ns) * self.period_ns
            cmd, mode, index, label = self.command_for(tau_ns)
            if state == SessionStatus.STATE_DONE:
                cmd = 0.0
            msg.segment_index = int(index)
            msg.segment_label = label
            msg.command = float(cmd)
            msg.mode = int(mode)
            if state != SessionStatus.STATE_DONE:       # the rider's targets in force (DONE: none)
                j = tau_ns // self.period_ns
                msg.virtual_gear_ratio = float(self.gear_for(j))
                msg.cadence_rpm = float(self.cadence_for(j))
                msg.heart_rate_bpm = float(self.heart_rate_for(j))
            self.pub_status.publish(msg)

        def _publish_diag(self, message: str, level: int | None = None, t_ns: int | None = None) -> None:
            """A diagnostic stamped with sim time ``t_ns`` (default: the last /clock)."""
            st = self._DiagnosticStatus()
            st.level = self._DiagnosticStatus.OK if level is None else level
            st.name = f"{self.get_fully_qualified_name()}"
            st.message = message
            st.hardware_id = self.get_namespace()
            st.values = [self._KeyValue(key="profile", value=self.profile.name),
                         self._KeyValue(key="commands_published", value=str(self.commands_published))]
            arr = self._DiagnosticArray()
            stamp = self.last_t_ns if t_ns is None else t_ns
            arr.header.stamp.sec, arr.header.stamp.nanosec = divmod(max(stamp or 0, 0), 1_000_000_000)
            arr.status = [st]
            self.pub_diag.publish(arr)

        def _on_wait_timer(self) -> None:
            if self.state == self._SessionStatus.STATE_RUNNING:
                self._check_stale_peers()
            elif self.state == self._SessionStatus.STATE_WAITING:
                self._publish_status(0, self._SessionStatus.STATE_WAITING)
                self._check_deaf_start()
                waited_s = time.monotonic() - self.started_wall
                if not self.no_clock_warned and waited_s > NO_CLOCK_WARN_S and not self.fresh_ports_wanted:
                    # a plant that is not running (or ended its run before this session came) sends
                    # no /clock, and the profile is played on its sim time
                    self.no_clock_warned = True
                    text = (f"no /clock in the {waited_s:.0f}s since start-up: waiting for a plant on this "
                            f"ROS_DOMAIN_ID and namespace ({self.sub_clock.get_publisher_count()} /clock writer(s) "
                            "matched); the profile is played on the plant's sim time")
                    self.get_logger().warning(text)
                    self._publish_diag(text, self._DiagnosticStatus.WARN)

        def _check_deaf_start(self) -> None:
            """No /clock DEAF_CHECK_S after start-up while a live process writes to a deleted
            segment of this node's shared-memory ports: a session restarted after a kill -9 on
            the killed one's port (Fast DDS's stale port, bike_plant.shm_ports), deaf to the
            plant for good (its discovery data goes there too, so the /clock writer may not
            even show as matched). Nothing has been played yet, so it says so and starts over
            with a new participant on fresh ports (main(), once per process). Looked for
            every shm_ports.DEAF_CHECK_S while waiting."""
            why = self.deaf_watch.start_over()
            if not why:
                return
            text = (f"no /clock in the {self.deaf_watch.waited_s():.0f}s since start-up: {why}; starting over "
                    "with a new DDS participant on fresh ports (nothing played yet)")
            self.get_logger().warning(text)
            self._publish_diag(text, self._DiagnosticStatus.WARN)
            self.fresh_ports_wanted = True

        def _check_stale_peers(self) -> None:
            """Running: a peer that still cannot reach this node (shm_ports.StalePeerWatch: a
            live process writing to a deleted segment of its ports at two looks in a row). Seen
            once in CI: a restarted session that followed the plant's /clock but whose
            SessionStatus never reached the test's reader (most likely its handle, and with it
            its discovery data, stayed on the deleted segment). It says so and starts over on
            fresh ports (main()): the profile is a function of sim time, so the new participant
            follows /clock with the same Commands."""
            if self.fresh_ports_wanted or say_stale_peer_and_start_over(
                    self, self.peer_watch, lambda text: self._publish_diag(text, self._DiagnosticStatus.WARN),
                    " (the profile follows /clock on)"):
                return
            if self.peer_watch.finished:
                self.wait_timer.cancel()

        def _on_clock(self, msg) -> None:
            if self.done:
                return
            t_ns = msg.clock.sec * 1_000_000_000 + msg.clock.nanosec
            if self.last_t_ns is not None and t_ns < self.last_t_ns:
                # one writer delivers /clock in order: time going back is a new run of the plant
                # (restarted after a crash). The profile is a function of sim time, so the
                # session follows it: the Commands from the one in force at t again (same stamps
                # and values as before, so the controller's timeline does not change)
                self.get_logger().warning(
                    f"/clock went back from {self.last_t_ns * 1e-9:g} s to {t_ns * 1e-9:g} s: the plant "
                    f"restarted (a new run); the profile follows it from t = {t_ns * 1e-9:g} s")
                self._publish_diag(f"plant restarted: the profile follows it from t = {t_ns * 1e-9:g} s",
                                   self._DiagnosticStatus.WARN, t_ns)
                self.last_t_ns = None
                self.next_j = t_ns // self.period_ns
                self.last_status_k = self.next_j - 1
            previous_ns = self.last_t_ns
            self.last_t_ns = t_ns
            if previous_ns == t_ns:
                # The plant re-published an unanswered state. A volatile reader (the controller)
                # matched after our Commands went out gets no history from this transient-local
                # writer and would wait for them forever; the reader count does not always show
                # it (the writer may see the reader before the reader sees the writer: the
                # intermittent seq-0 stall). Send the ones in force again: same stamps and
                # values, so the controller's timeline does not change.
                for j in range(t_ns // self.period_ns, self.next_j):
                    self._publish_command(j)
                if self.resent_at_ns != t_ns:             # a held realtime start repeats t = 0 often
                    self.resent_at_ns = t_ns
                    self.get_logger().info(f"/clock {t_ns * 1e-9:g} s again (the plant waits for an answer): "
                                           f"Commands from t = {t_ns * 1e-9:g} s sent again")
                return
            events_between = getattr(self.profile, "events_between", None)
            if events_between is not None:
                t0 = -1e-9 if previous_ns is None else previous_ns * 1e-9
                for ev in events_between(t0, t_ns * 1e-9):
                    self.get_logger().info(f"workout t={ev.time_s:g}s: {ev.message}")
            SessionStatus = self._SessionStatus
            if self.state == SessionStatus.STATE_WAITING:
                self.state = SessionStatus.STATE_RUNNING     # the wait timer now looks for stale peers
                self._publish_diag("running")
            # ahead of time: every tau_j <= t + period not yet published
            horizon = t_ns + self.period_ns
            while self.next_j * self.period_ns <= horizon:
                self._publish_command(self.next_j)
                self.next_j += 1
            if t_ns >= self.duration_ns:
                self._publish_command(self.next_j)   # the final Command of 0
                self.next_j += 1
                self.state = SessionStatus.STATE_DONE
                self._publish_status(t_ns, SessionStatus.STATE_DONE)
                self._publish_diag("done")
                self.done = True
                self.get_logger().info(f"session done at t = {t_ns * 1e-9:g} s ({self.commands_published} commands"
                                       + (f", {self.shifts} shift(s) on {self.sub_shift.topic_name}" if self.shifts
                                          else "")
                                       + (f", {self.live_commands} live Command(s) on {self.sub_live.topic_name}"
                                          if self.live_commands else "")
                                       + (f", {self.erg_bumps} ERG target shift(s)" if self.erg_bumps else "") + ")")
                return
            k = t_ns // self.period_ns
            if k > self.last_status_k:
                self.last_status_k = k
                self._publish_status(t_ns, SessionStatus.STATE_RUNNING)

        def gather_pause_s(self, wall_s: float) -> float:
            """Wall seconds to let /clock samples gather before the next burst is taken.

            Waking for every batch costs the session a wake-up, a wait and a take per batch
            (a share of the 2 cores the plant and the controller need); taken in bursts each
            value still goes through _on_clock, in order, so Commands, statuses and their
            stamps are the same. The pause keeps the Commands ahead of the controller: at
            the measured sim rate the burst lags sim time by at most
            GATHER_SHARE_OF_PERIOD x session.period_s (they are published a period ahead)."""
            t_ns = self.last_t_ns
            prev = self._rate_mark
            self._rate_mark = (t_ns, wall_s)
            if t_ns is None or prev is None or prev[0] is None or wall_s <= prev[1] or t_ns <= prev[0]:
                return 0.0
            rate = (t_ns - prev[0]) * 1e-9 / (wall_s - prev[1])      # sim s per wall s
            return min(GATHER_MAX_S, GATHER_SHARE_OF_PERIOD * self.period_s / rate)

        def flush(self, timeout_s: float = 2.0) -> None:
            """Wait (at most timeout_s in all) until the readers acknowledged what was sent."""
            import time as _time

            from rclpy.duration import Duration
            end = _time.monotonic() + timeout_s
            for pub in (self.pub_command, self.pub_status, self.pub_diag):
                left = end - _time.monotonic()
                if left <= 0.0:
                    break
                try:
                    pub.wait_for_all_acked(Duration(seconds=left))
                except Exception:  # noqa: BLE001 - best effort on the way out
                    pass

    return SessionNode


def stop_on_signals() -> dict:
    """SIGINT / SIGTERM only ask the loop to stop (checked at least every 0.1 s), as in the
    loop nodes (bike_plant.node.install_signal_handlers) and the recorder. rclpy's own handlers
    (rclpy.init's default) shut the context down from their signal thread while this thread may
    be inside rcl (a take, a publish, a wait), and raise KeyboardInterrupt wherever Python is,
    also inside rclpy's message conversion (bike_plant.loop.HotWait). A CI run's session
    outlived SIGINT and SIGTERM that way and was killed (2026-12-05, cause not seen:
    the launcher now prints a stuck node's stacks); here the stop is one flag read between
    waits, on this thread."""
    asked = {"signum": None}

    def handler(signum, _frame):
        asked["signum"] = signum
    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return asked


def main(args=None) -> int:
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = stop_on_signals()
    node = None
    executor = None
    rc = 0
    try:
        from bike_plant.loop import HotWait, start_over_on_fresh_ports
        from rclpy.executors import SingleThreadedExecutor

        node_class = _make_node_class()
        node = node_class()
        # the mode figures (bike_controller.modes) brought in numba and its code generator, which
        # the session does not run again: drop LLVM's pages from its RSS (bike_plant.memory)
        from bike_plant.memory import release_clean_library_pages
        released_mb = release_clean_library_pages() / 2**20
        if released_mb >= 1.0:
            node.get_logger().info(f"released {released_mb:.0f} MB of LLVM library pages")
        while True:
            executor = SingleThreadedExecutor(context=node.context)
            executor.add_node(node)
            # /clock comes every batch: taken straight from a wait set (bike_plant.loop.HotWait),
            # the timer and parameter services through the executor. The live Commands and the
            # shifter too, before /clock: the executor would serve them one per turn (at most
            # every 50 ms), and an app's targets written close together would wait or, past the
            # reader's depth, be lost
            hot = HotWait(executor, [node.sub_live, node.sub_shift, node.sub_clock], node.context,
                          logger=node.get_logger())
            while (stop["signum"] is None and rclpy.ok(context=node.context) and not node.done
                   and not node.fresh_ports_wanted):
                if hot.spin(0.1) and not node.done:
                    pause = node.gather_pause_s(time.monotonic())
                    if pause > 0.0:
                        time.sleep(pause)
            if stop["signum"] is not None or not node.fresh_ports_wanted:
                break
            old_executor, executor = executor, None      # a stale port: a new participant
            node = start_over_on_fresh_ports(node_class, node, args, old_executor)
        if node.done:
            node.flush()
    except SetupError as exc:
        print(f"session_node: error: {exc}", file=sys.stderr, flush=True)
        rc = 2
    except KeyboardInterrupt:      # a Ctrl-C before the handlers above were set
        rc = 0
    finally:
        if executor is not None:
            executor.remove_node(node)
            executor.shutdown()                 # see bike_plant.node.run_loop_node
        if node is not None:
            node.destroy_node()
            if node.context is not rclpy.get_default_context():   # started over (start_over_on_fresh_ports)
                rclpy.try_shutdown(context=node.context)
        rclpy.try_shutdown()
    return rc


if __name__ == "__main__":
    sys.exit(main())
