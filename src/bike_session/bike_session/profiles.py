"""Workout profiles: a timeline of Command values (0..1) and modes, read from YAML.

A profile file looks like::

    name: demo_intervals            # optional, defaults to the file name
    description: free text          # optional
    mode: resistance                # optional default mode of every segment
    segments:
      - {kind: step, duration_s: 10, command: 0.3, label: warm-up}
      - {kind: ramp, duration_s: 10, start: 0.2, end: 0.5}
      - kind: intervals
        repeat: 2
        on:  {duration_s: 10, command: 0.9, label: effort}
        off: {duration_s: 10, command: 0.4, label: recovery}
      - kind: repeat
        repeat: 3
        segments: [ ...any segments, nested... ]

Segment kinds
  step       ``duration_s``, ``command``; optional ``mode``, ``label``
  ramp       ``duration_s``, ``start``, ``end`` (linear); optional ``mode``, ``label``
  intervals  ``repeat``, ``on``, ``off`` (each a step, or a ramp with ``kind: ramp``);
             optional ``mode``/``label`` inherited by ``on``/``off``
  repeat     ``repeat``, ``segments`` (a list of any segments, nesting allowed);
             optional ``mode``/``label`` inherited by the children

Any segment may give ``gear``: the virtual bike's gear ratio (wheel turns per crank turn, 0.3 ..
8; 0: the config's ``modes.virtual_gear_ratio``) from its start on, inherited like ``mode`` by
the children of ``intervals`` / ``repeat``; it stays in force until a later segment gives
another (:meth:`Profile.gear_at`; 0 before any). It shapes slope mode's road load (virtual
shifting, bike_controller.modes) and the virtual speed of every mode.

Any segment may give ``road``: ``{crr: 0.004, cw_kg_m: 0.51, wind_mps: 3}`` (rolling resistance;
wind resistance rho CdA in kg/m as FTMS and FE-C give it, the drag 1/2 Cw v^2; head wind in m/s;
all three) or ``config`` (the config's ``modes`` road again), inherited and kept in force like
``gear`` (:meth:`Profile.road_at`; the config's before any). It shapes slope mode's road load
(and ERG's flat road with ``modes.erg_speed_from_power``); ``./bike replay`` writes the road a
training app gave.

Any segment may give ``cadence``: the rider's cadence target in rpm (10 .. 250; 0: none, the
rider's own), for that segment only (the children of ``intervals`` / ``repeat`` inherit it), as a
workout file's Cadence does (:meth:`Profile.cadence_at`). The Commands carry it; the simulated
rider pedals at it.

Any segment may give ``heart_rate_bpm``: the rider's heart-rate target (40 .. 220; 0: none) for
heart-rate ERG, for that segment only (inherited like ``cadence``), as a workout file's heart-rate
step does (:meth:`Profile.heart_rate_at`). The Commands carry it and the controller moves the ERG
power target to hold it (bike_controller.heart_erg); a step's ``command`` / ``target`` is where the
power starts, and without one the command is 0 (the controller starts from the rider's present
power). On a step in another mode than ``erg``, or on a ramp (the power follows the heart rate,
so a ramp of it would mean nothing), it is an error.

Modes are names (``resistance``, ``motoring``, ``erg``, ``slope``, ``isokinetic``, ``spindown``) mapped
to the bike_msgs/Command constants by :data:`MODES`. Commands are in [0, 1]. Instead of a
command, a step may give ``target`` and a ramp ``start_target`` / ``end_target`` in the
mode's own unit: W (erg), grade in % (slope), crank rpm (isokinetic); they are turned
into commands with the bike's ranges (:class:`ModeUnits`, from the config's ``modes`` and
``controller`` sections), so such a profile needs the config (``./bike run`` passes it).
A target outside the bike's range is an error, never clamped. A profile compiles into a flat list of leaf
segments; :meth:`Profile.command_at` is a pure function of time. Every problem raises
:class:`ProfileError` naming the file, the element (``segments[1].on.command``) and the
reason. Files are parsed with ``yaml.safe_load`` only. No rclpy import here.
"""
from __future__ import annotations

import bisect
import dataclasses
import math
import os
import pathlib
from typing import Any, Mapping

import yaml
from bike_plant.config import MAX_SIM_TIME_S, YamlFileError, parse_yaml_text
from bike_plant.heart import heart_rate_target_problem
from bike_plant.mechanics import rider_cadence_problem, road_problem, virtual_gear_problem

# name -> bike_msgs/msg/Command mode constant (bike_controller.modes)
MODES: dict[str, int] = {"resistance": 0, "motoring": 1, "erg": 2, "slope": 3, "isokinetic": 4, "spindown": 5}
MODE_NAMES: dict[int, str] = {v: k for k, v in MODES.items()}

MAX_PROFILE_BYTES = 1 << 20   # a profile is a few kB; refuse absurd files before parsing
MAX_LEAF_SEGMENTS = 100_000   # guards against nested repeats exploding in memory
MAX_REPEAT = 10_000
MAX_DEPTH = 16
KINDS = ("step", "ramp", "intervals", "repeat")

_COMMON = {"kind", "mode", "label", "gear", "road", "cadence", "heart_rate_bpm"}
ROAD_KEYS = ("crr", "cw_kg_m", "wind_mps")
_KEYS = {
    "step": _COMMON | {"duration_s", "command", "target"},
    "ramp": _COMMON | {"duration_s", "start", "end", "start_target", "end_target"},
    "intervals": _COMMON | {"repeat", "on", "off"},
    "repeat": _COMMON | {"repeat", "segments"},
}
_REQUIRED = {
    "step": ("duration_s",),
    "ramp": ("duration_s",),
    "intervals": ("repeat", "on", "off"),
    "repeat": ("repeat", "segments"),
}
_TOP_KEYS = {"name", "description", "mode", "segments"}


@dataclasses.dataclass(frozen=True)
class ModeUnits:
    """The bike's ranges that map a mode's target to a Command in [0, 1] (the inverse of
    bike_controller.modes: P = C * erg_power_max_w, grade = min + C (max - min), ...)."""

    erg_power_max_w: float
    grade_min: float
    grade_max: float
    cadence_min_rpm: float
    cadence_max_rpm: float
    # a spin-down's (low, high) road speeds in the config's virtual gear [km/h] (FTMS Spin Down
    # Control's target speeds); (0, 0): not known
    spindown_kmh: tuple[float, float] = (0.0, 0.0)

    def to_command(self, mode: int, target: float) -> tuple[float, str]:
        """(command, unit) for a target of ``mode``; ValueError when out of range."""
        if mode == MODES["erg"]:
            lo, hi, unit, value = 0.0, self.erg_power_max_w, "W", target
            c = value / hi
        elif mode == MODES["slope"]:
            lo, hi, unit, value = 100 * self.grade_min, 100 * self.grade_max, "% grade", target
            c = (value / 100 - self.grade_min) / (self.grade_max - self.grade_min)
        elif mode == MODES["isokinetic"]:
            lo, hi, unit, value = self.cadence_min_rpm, self.cadence_max_rpm, "rpm", target
            c = (value - lo) / (hi - lo)
        else:
            raise ValueError(f"mode {MODE_NAMES.get(mode, mode)} has no target unit: give 'command' (0..1)")
        if not lo - 1e-9 <= value <= hi + 1e-9:
            raise ValueError(f"target {target!r} {unit} outside this bike's range [{lo:g}, {hi:g}] {unit}")
        return min(max(c, 0.0), 1.0), unit

    def target_of(self, mode: int, command: float) -> tuple[float, str] | None:
        """The inverse of :meth:`to_command`: (target, unit) of a Command ("W", "%" grade,
        "rpm"); None for a mode without a target unit."""
        if mode == MODES["erg"]:
            return command * self.erg_power_max_w, "W"
        if mode == MODES["slope"]:
            return 100 * (self.grade_min + command * (self.grade_max - self.grade_min)), "%"
        if mode == MODES["isokinetic"]:
            return self.cadence_min_rpm + command * (self.cadence_max_rpm - self.cadence_min_rpm), "rpm"
        return None


def describe_command(mode: int, command: float, units: ModeUnits | None, heart_rate_bpm: float = 0.0) -> str:
    """A Command in its mode's unit where the bike's ranges are known ("erg 150 W",
    "slope 5.0 %", "isokinetic 80 rpm"), else its value ("resistance 0.1"); with a heart-rate
    target, that target and where the power starts ("erg heart rate 140 bpm, from 150 W")."""
    name = MODE_NAMES.get(mode, str(mode))
    target = units.target_of(mode, command) if units is not None else None
    if target is None:
        text = f"{name} {command:.4g}"
    else:
        value, unit = target
        text = f"{name} {value:.1f} {unit}" if unit == "%" else f"{name} {value:.0f} {unit}"
    if heart_rate_bpm:
        start = "the rider's power" if command == 0 else text[len(name) + 1:]
        text = f"{name} heart rate {heart_rate_bpm:.0f} bpm, from {start}"
    return text


def mode_units_from_config(cfg: Mapping) -> ModeUnits:
    """ModeUnits of a loaded config (bike_plant.config.load_config)."""
    from bike_controller.modes import machine_figures, mode_params_from_config

    mp = mode_params_from_config(cfg)
    pmax = mp.erg_power_max_w or machine_figures(cfg, with_envelope=False).pmax_w
    kmh_per_rpm = mp.virtual_gear_ratio * 2.0 * math.pi * mp.wheel_radius_m / 60.0 * 3.6
    return ModeUnits(pmax, mp.grade_min, mp.grade_max, mp.isokinetic_cadence_min_rpm,
                     mp.isokinetic_cadence_max_rpm,
                     (mp.spindown_low_cadence_rpm * kmh_per_rpm, mp.spindown_high_cadence_rpm * kmh_per_rpm))


class ProfileError(ValueError):
    """A problem in a profile, naming the file and the element it concerns."""

    def __init__(self, message: str, source: str | os.PathLike | None = None, where: str | None = None):
        text = str(source) if source else "<profile>"
        if where:
            text += f": {where}"
        super().__init__(f"{text}: {message}")
        self.source = source
        self.where = where
        self.reason = message


@dataclasses.dataclass(frozen=True)
class Segment:
    """One leaf of the compiled timeline: a constant or a linear ramp."""

    index: int          # position in the flat timeline (SessionStatus.segment_index)
    path: str           # where it came from in the file, e.g. segments[1].on (repeat 2)
    start_s: float
    duration_s: float
    start: float        # command at start_s
    end: float          # command at start_s + duration_s (== start for a step)
    mode: int
    label: str

    @property
    def end_s(self) -> float:
        return self.start_s + self.duration_s

    def value_at(self, t_s: float) -> float:
        if self.start == self.end:
            return self.start
        frac = min(max((t_s - self.start_s) / self.duration_s, 0.0), 1.0)
        return self.start + (self.end - self.start) * frac


class Profile:
    """A compiled workout: ``command_at(t)`` is a pure function of time.

    Time is relative to the session start (sim time 0). Segments are half-open
    intervals [start, end). Before 0 the first segment's initial value applies; from
    ``duration_s`` on the workout is over: command 0, mode of the last segment,
    ``segment_index == len(segments)``, label ``"end"``.
    """

    def __init__(self, name: str, segments: list[Segment], source: str = "<profile>", text: str = "",
                 gears: Mapping[int, float] | None = None, roads: Mapping[int, tuple | None] | None = None,
                 cadences: Mapping[int, float] | None = None, heart_rates: Mapping[int, float] | None = None):
        if not segments:
            raise ProfileError("a profile needs at least one segment", source, "segments")
        self.name = name
        self.segments = segments
        self.source = source
        self.text = text
        self._starts = [s.start_s for s in segments]
        self.duration_s = segments[-1].end_s
        # the gear in force in each leaf: the last one given at or before it (0: none yet)
        self.gears_given = dict(gears or {})
        self._gear_in_force = []
        gear = 0.0
        for seg in segments:
            gear = self.gears_given.get(seg.index, gear)
            self._gear_in_force.append(gear)
        self._cadences = dict(cadences or {})     # leaf index -> the rider's cadence target
        self._heart_rates = dict(heart_rates or {})   # leaf index -> the ERG heart-rate target
        # the road in force in each leaf, the same way (None: the config's)
        roads = dict(roads or {})
        self._road_in_force = []
        road = None
        for seg in segments:
            road = roads.get(seg.index, road)
            self._road_in_force.append(road)

    def __repr__(self) -> str:
        return f"Profile({self.name!r}, {len(self.segments)} segments, {self.duration_s:g} s)"

    def segment_at(self, t_s: float) -> Segment | None:
        """The leaf segment active at ``t_s`` (None past the end)."""
        if not math.isfinite(t_s):
            raise ValueError(f"time must be finite, got {t_s!r}")
        if t_s >= self.duration_s:
            return None
        i = bisect.bisect_right(self._starts, t_s) - 1
        return self.segments[max(i, 0)]

    def command_at(self, t_s: float) -> tuple[float, int, int, str]:
        """(command, mode, segment_index, label) at time ``t_s`` seconds."""
        seg = self.segment_at(t_s)
        if seg is None:
            last = self.segments[-1]
            return 0.0, last.mode, len(self.segments), "end"
        value = seg.value_at(t_s)
        return min(max(value, 0.0), 1.0), seg.mode, seg.index, seg.label

    def gear_at(self, t_s: float) -> float:
        """The virtual gear ratio in force at ``t_s`` (0: the config's gear); past the end,
        the last one."""
        seg = self.segment_at(t_s)
        return self._gear_in_force[-1 if seg is None else seg.index]

    def cadence_at(self, t_s: float) -> float | None:
        """The rider's cadence target [rpm] of the segment at ``t_s`` (None: none)."""
        seg = self.segment_at(t_s)
        return self._cadences.get(seg.index) if seg is not None else None

    def heart_rate_at(self, t_s: float) -> float | None:
        """The heart-rate target [bpm] of the (ERG) segment at ``t_s`` (None: none)."""
        seg = self.segment_at(t_s)
        return self._heart_rates.get(seg.index) if seg is not None else None

    def road_at(self, t_s: float) -> tuple[float, float, float] | None:
        """The road (crr, cw_kg_m, wind_mps) in force at ``t_s``, None for the config's; past the
        end, the last one."""
        seg = self.segment_at(t_s)
        return self._road_in_force[-1 if seg is None else seg.index]

    def timeline(self, period_s: float, duration_s: float | None = None) -> list[tuple[float, float, int]]:
        """[(tau_j, command, mode)] for tau_j = j * period_s, j = 0 .. floor(duration / period)."""
        if not (period_s > 0 and math.isfinite(period_s)):
            raise ValueError(f"period_s must be > 0, got {period_s!r}")
        duration = self.duration_s if duration_s is None else duration_s
        n = int(math.floor(duration / period_s + 1e-9))
        out = []
        for j in range(n + 1):
            tau = j * period_s
            cmd, mode, _, _ = self.command_at(tau)
            if tau >= duration:
                cmd = 0.0
            out.append((tau, cmd, mode))
        return out


# --------------------------------------------------------------------------- parsing


def load_profile(path: str | os.PathLike, units: ModeUnits | None = None) -> Profile:
    """Read and compile a profile file; ProfileError for any problem (nothing starts)."""
    path = pathlib.Path(path)
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise ProfileError(f"cannot read profile ({exc.strerror})", path) from None
    if not path.is_file():
        raise ProfileError("not a regular file", path)
    if size > MAX_PROFILE_BYTES:
        raise ProfileError(f"file too large ({size} bytes > {MAX_PROFILE_BYTES})", path)
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise ProfileError("not a text file (not UTF-8)", path) from None
    except OSError as exc:
        raise ProfileError(f"cannot read profile ({exc.strerror})", path) from None
    return parse_profile_text(text, source=str(path), default_name=path.stem, units=units)


def parse_profile_text(text: str, source: str = "<profile>", default_name: str = "profile",
                       units: ModeUnits | None = None) -> Profile:
    """Compile profile YAML text (``yaml.safe_load``)."""
    if len(text.encode("utf-8", "surrogatepass")) > MAX_PROFILE_BYTES:
        raise ProfileError(f"profile too large (> {MAX_PROFILE_BYTES} bytes)", source)
    try:
        doc = parse_yaml_text(text)
    except YamlFileError as exc:
        raise ProfileError(str(exc), source) from None
    profile = parse_profile(doc, source=source, default_name=default_name, units=units)
    profile.text = text
    return profile


def parse_profile(doc: Any, source: str = "<profile>", default_name: str = "profile",
                  units: ModeUnits | None = None) -> Profile:
    """Compile an already-parsed profile document (a mapping)."""
    if not isinstance(doc, Mapping):
        raise ProfileError(f"expected a mapping with 'segments', got {_tname(doc)}", source)
    unknown = sorted(str(k) for k in set(doc) - _TOP_KEYS)
    if unknown:
        raise ProfileError(f"unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(_TOP_KEYS))}", source)
    name = doc.get("name", default_name)
    if not isinstance(name, str) or not name.strip():
        raise ProfileError(f"expected a non-empty string, got {name!r}", source, "name")
    if "description" in doc and not isinstance(doc["description"], str):
        raise ProfileError(f"expected a string, got {_tname(doc['description'])}", source, "description")
    mode = _mode(doc["mode"], source, "mode") if "mode" in doc else MODES["resistance"]
    if "segments" not in doc:
        raise ProfileError("missing key 'segments'", source)
    builder = _Builder(source, units)
    builder.segment_list(doc["segments"], "segments", mode, None, 0, "")
    if not builder.leaves:
        raise ProfileError("a profile needs at least one segment", source, "segments")
    return Profile(name, builder.leaves, source=source, gears=builder.gears, roads=builder.roads,
                   cadences=builder.cadences, heart_rates=builder.heart_rates)


class _Builder:
    def __init__(self, source: str, units: ModeUnits | None = None):
        self.source = source
        self.units = units
        self.leaves: list[Segment] = []
        self.gears: dict[int, float] = {}      # leaf index -> the gear it gives (or inherits)
        self.roads: dict[int, tuple | None] = {}   # ... and the road (None: the config's again)
        self.cadences: dict[int, float] = {}       # ... and the rider's cadence target (> 0)
        self.heart_rates: dict[int, float] = {}    # ... and the heart-rate target (> 0, ERG only)
        self.t = 0.0

    def err(self, where: str, message: str) -> ProfileError:
        return ProfileError(message, self.source, where)

    def segment_list(self, items, where, mode, label, depth, rep, gear=None, road=None, cadence=None,
                     heart_rate=None):
        if not isinstance(items, list):
            raise self.err(where, f"expected a list of segments, got {_tname(items)}")
        if not items:
            raise self.err(where, "empty list of segments")
        for i, item in enumerate(items):
            self.segment(item, f"{where}[{i}]", mode, label, depth, rep, gear=gear, road=road, cadence=cadence,
                         heart_rate=heart_rate)

    def segment(self, seg, where, mode, label, depth, rep, default_kind=None, gear=None, road=None, cadence=None,
                heart_rate=None):
        # road: None when not given; "config" or (crr, cw_kg_m, wind_mps) when given
        # heart_rate: None when not given; (bpm, where it was given) when given (bpm 0: none)
        if depth > MAX_DEPTH:
            raise self.err(where, f"segments nested deeper than {MAX_DEPTH} levels")
        if not isinstance(seg, Mapping):
            raise self.err(where, f"expected a mapping, got {_tname(seg)}")
        seg = _yaml11_keys(seg)
        kind = seg.get("kind", default_kind)
        if kind is None:
            raise self.err(where, f"missing key 'kind' (one of {', '.join(KINDS)})")
        if not isinstance(kind, str) or kind not in KINDS:
            raise self.err(f"{where}.kind", f"unknown kind {kind!r}; expected one of {', '.join(KINDS)}")
        unknown = sorted(str(k) for k in set(seg) - _KEYS[kind])
        if unknown:
            raise self.err(where, f"unknown key(s) {', '.join(unknown)} for kind {kind}; known: {', '.join(sorted(_KEYS[kind]))}")
        for key in _REQUIRED[kind]:
            if key not in seg:
                raise self.err(where, f"missing key '{key}' for kind {kind}")
        if "mode" in seg:
            mode = _mode(seg["mode"], self.source, f"{where}.mode")
        if "label" in seg:
            label = seg["label"]
            if not isinstance(label, str):
                raise self.err(f"{where}.label", f"expected a string, got {_tname(label)}")
        if "gear" in seg:
            gear = self.number(seg["gear"], f"{where}.gear")
            problem = virtual_gear_problem(gear)
            if problem:
                raise self.err(f"{where}.gear", problem)
        if "road" in seg:
            road = self.road(seg["road"], f"{where}.road")
        if "cadence" in seg:
            cadence = self.number(seg["cadence"], f"{where}.cadence")
            problem = rider_cadence_problem(cadence)
            if problem:
                raise self.err(f"{where}.cadence", problem)
        if "heart_rate_bpm" in seg:
            bpm = self.number(seg["heart_rate_bpm"], f"{where}.heart_rate_bpm")
            problem = heart_rate_target_problem(bpm)
            if problem:
                raise self.err(f"{where}.heart_rate_bpm", problem)
            heart_rate = (bpm, f"{where}.heart_rate_bpm")
        if kind in ("step", "ramp"):
            bpm, bpm_where = heart_rate or (0.0, "")
            if bpm:
                # checked on the leaf: a mode or kind inherited from above is refused here too
                given = "" if bpm_where == f"{where}.heart_rate_bpm" else f" (given at {bpm_where})"
                if mode != MODES["erg"]:
                    raise self.err(where, f"heart_rate_bpm {bpm:g}{given} needs mode erg (it moves the ERG power "
                                          f"target); this segment rides in mode {MODE_NAMES[mode]}")
                if kind == "ramp":
                    raise self.err(where, f"heart_rate_bpm {bpm:g}{given} on a ramp: the power follows the heart "
                                          "rate, so give it on a step")
            duration = self.number(seg["duration_s"], f"{where}.duration_s")
            if duration <= 0:
                raise self.err(f"{where}.duration_s", f"must be > 0, got {seg['duration_s']!r}")
            if kind == "step":
                start = end = self.value(seg, "command", "target", mode, where, no_value_ok=bool(bpm))
            else:
                start = self.value(seg, "start", "start_target", mode, where)
                end = self.value(seg, "end", "end_target", mode, where)
            if len(self.leaves) >= MAX_LEAF_SEGMENTS:
                raise self.err(where, f"profile expands to more than {MAX_LEAF_SEGMENTS} segments")
            if gear is not None:
                self.gears[len(self.leaves)] = gear
            if road is not None:
                self.roads[len(self.leaves)] = None if road == "config" else road
            if cadence:
                self.cadences[len(self.leaves)] = cadence
            if bpm:
                self.heart_rates[len(self.leaves)] = bpm
            self.leaves.append(Segment(len(self.leaves), where + rep, self.t, duration, start, end, mode,
                                       label if label is not None else kind))
            self.t += duration
            if not self.t <= MAX_SIM_TIME_S:
                # the session counts its time in int64 nanoseconds: an OverflowError traceback
                raise self.err(where, f"total duration beyond {MAX_SIM_TIME_S:g} s (the ROS clock's int64 "
                                      f"nanoseconds), got {self.t:g} s")
            return
        count = self.repeat(seg["repeat"], f"{where}.repeat")
        if kind == "intervals":
            for part in ("on", "off"):
                body = seg[part]
                if isinstance(body, Mapping) and body.get("kind", "step") not in ("step", "ramp"):
                    raise self.err(f"{where}.{part}.kind", f"must be step or ramp, got {body.get('kind')!r}")
            for r in range(count):
                r_tag = f"{rep} (repeat {r + 1}/{count})" if count > 1 else rep
                self.segment(seg["on"], f"{where}.on", mode, label, depth + 1, r_tag, "step", gear=gear, road=road,
                             cadence=cadence, heart_rate=heart_rate)
                self.segment(seg["off"], f"{where}.off", mode, label, depth + 1, r_tag, "step", gear=gear,
                             road=road, cadence=cadence, heart_rate=heart_rate)
        else:
            for r in range(count):
                r_tag = f"{rep} (repeat {r + 1}/{count})" if count > 1 else rep
                self.segment_list(seg["segments"], f"{where}.segments", mode, label, depth + 1, r_tag, gear=gear,
                                  road=road, cadence=cadence, heart_rate=heart_rate)

    def road(self, value, where):
        """A segment's ``road``: "config", or a mapping of exactly crr, cw_kg_m, wind_mps."""
        if value == "config":
            return "config"
        if not isinstance(value, Mapping):
            raise self.err(where, f"expected 'config' or a mapping of {', '.join(ROAD_KEYS)}, got {_tname(value)}")
        keys = set(_yaml11_keys(value))
        if keys != set(ROAD_KEYS):
            raise self.err(where, f"a road gives exactly {', '.join(ROAD_KEYS)}; got {', '.join(sorted(map(str, keys)))}")
        road = tuple(self.number(value[k], f"{where}.{k}") for k in ROAD_KEYS)
        problem = road_problem(*road)
        if problem:
            raise self.err(where, problem)
        return road

    def number(self, value, where) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.err(where, f"expected a number, got {_tname(value)} {value!r}")
        if not math.isfinite(value):
            raise self.err(where, f"must be finite, got {value!r}")
        return float(value)

    def value(self, seg, key, target_key, mode, where, no_value_ok=False) -> float:
        """The command of ``seg[key]``, or of ``seg[target_key]`` in the mode's unit; 0 when
        neither is given and ``no_value_ok`` (a heart-rate step: the power starts where it is)."""
        if key in seg and target_key in seg:
            raise self.err(where, f"give either '{key}' or '{target_key}', not both")
        if key in seg:
            return self.command(seg[key], f"{where}.{key}")
        if target_key not in seg and (mode == MODES["spindown"] or no_value_ok):
            return 0.0                         # the spin-down takes no value; heart-rate ERG may not
        if target_key not in seg:
            raise self.err(where, f"missing key '{key}' (command 0..1) or '{target_key}' (in the mode's unit)")
        target = self.number(seg[target_key], f"{where}.{target_key}")
        if self.units is None:
            raise self.err(f"{where}.{target_key}", "a target needs the bike's ranges: ride the profile with "
                                                    "./bike run (which passes the config)")
        try:
            return self.units.to_command(mode, target)[0]
        except ValueError as exc:
            raise self.err(f"{where}.{target_key}", str(exc)) from None

    def command(self, value, where) -> float:
        x = self.number(value, where)
        if not 0.0 <= x <= 1.0:
            raise self.err(where, f"command must be in [0, 1], got {value!r}")
        return x

    def repeat(self, value, where) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and math.isfinite(value) and value.is_integer():
                value = int(value)
            else:
                raise self.err(where, f"expected an integer, got {_tname(value)} {value!r}")
        if not 1 <= value <= MAX_REPEAT:
            raise self.err(where, f"must be in [1, {MAX_REPEAT}], got {value!r}")
        return value


def shifted_gear(gears, current: float, steps: int) -> tuple[float, int]:
    """Shift ``steps`` gears (> 0 up, to a bigger ratio) through the rising table ``gears``
    from ``current``, which need not be in it (a profile's gear: the first step goes to the
    next gear of the table in that direction). Returns (new gear, steps taken): fewer than
    asked at either end of the table, the caller says so."""
    tol = 1e-6 * current
    if steps > 0:
        ahead = [g for g in gears if g > current + tol]
        taken = min(steps, len(ahead))
        return (ahead[taken - 1] if taken else current), taken
    behind = [g for g in gears if g < current - tol][::-1]
    taken = min(-steps, len(behind))
    return (behind[taken - 1] if taken else current), -taken


def _yaml11_keys(seg: Mapping) -> dict:
    # yaml.safe_load follows YAML 1.1, where the bare keys `on` / `off` are booleans.
    return {("on" if k is True else "off" if k is False else k): v for k, v in seg.items()}


def _mode(value, source, where) -> int:
    if not isinstance(value, str) or value not in MODES:
        raise ProfileError(f"unknown mode {value!r}; expected one of {', '.join(MODES)}", source, where)
    return MODES[value]


def _tname(value) -> str:
    if value is None:
        return "nothing (null)"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, Mapping):
        return "a mapping"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, (int, float)):
        return "a number"
    return type(value).__name__


def step(duration_s: float, command: float, mode: str = "resistance", label: str = "step") -> Profile:
    """A one-segment profile (constant command), handy for tests and quick runs."""
    return parse_profile({"name": label, "mode": mode,
                          "segments": [{"kind": "step", "duration_s": duration_s, "command": command, "label": label}]},
                         source="<step>")
