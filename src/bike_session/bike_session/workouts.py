"""Import the workout files riders already have (.zwo, .erg, .mrc, .fit) as session profiles.

``load_workout(path, ftp_w=..., pmax_w=...)`` picks the reader from the file extension and
returns a :class:`Workout`, a :class:`~bike_session.profiles.Profile` subclass: the session
node rides it through ``command_at(t)`` exactly like a YAML profile. ``.yaml``/``.yml``
files go to :func:`bike_session.profiles.load_profile` unchanged (they already hold
Commands, so ``ftp_w``/``pmax_w`` do not apply). Nothing is added to ``profiles.py``.

Formats (see /work/shared/research/trainers.md, section 1)

  .zwo  Zwift XML. Blocks of ``<workout>``, durations in seconds, power as a fraction of
        FTP. ``Warmup``, ``Ramp``: linear ramp PowerLow -> PowerHigh as written.
        ``Cooldown``: linear ramp that always descends (max -> min of PowerLow/PowerHigh,
        as GoldenCheetah does; Zwift's own files write the start in PowerLow).
        ``SteadyState`` / ``SolidState``: Power, or the mean of PowerLow/PowerHigh (as GC).
        ``IntervalsT``: Repeat (default 1) x (on, off); on = OnPower or the ramp
        PowerOnLow -> PowerOnHigh for OnDuration, off likewise; the off part is skipped when
        OffDuration is 0; Cadence applies to the on part, CadenceResting to the off part.
        ``FreeRide`` / ``Freeride`` and ``MaxEffort``: no power target, see below.
        ``textevent`` / ``TextEvent`` / ``TextNotification`` (children of a block):
        kept as :class:`TextEvent` at block start + timeoffset (IntervalsT: start of the
        whole block, as GC). ``gameplayevent`` children are ignored. Tag and attribute names
        are matched case-insensitively; ``mssage`` (a typo found in Zwift's built-in files)
        is accepted for ``message``. Unknown *metadata* elements under ``<workout_file>``
        and unknown attributes are ignored (they cannot change the ride); an unknown element
        in ``<workout>`` or in a block is an error. ``sportType`` other than bike and
        ``durationType`` distance are refused. Text is UTF-8, UTF-16 with a byte order mark or
        the encoding the XML declaration names; a file meant as UTF-8 that is not (a Windows
        editor's ANSI code page) is read as cp1252, as the .erg reader does. Blank lines before
        the XML declaration are allowed.
  .erg  Text in UTF-8 (a BOM is fine), UTF-16 with a BOM, else cp1252.
        ``[COURSE HEADER]`` (``FTP = W`` optional; ``FTP =`` or ``FTP = 0`` is none, with a
        warning; ``MINUTES WATTS``), ``[COURSE DATA]`` of
        "minutes watts" points, ``[END COURSE DATA]``, optional ``[COURSE TEXT]``
        ("seconds <tab> message <tab> duration"). Points are piecewise linear: two points at
        the same time are a step; consecutive points with different values a ramp. A value
        ending in ``%`` is percent of FTP (as GC). ``<minutes> LAP <name>`` lines become text
        events; ``;`` starts a comment. Times must not decrease. When the
        first point is after minute 0 its value holds from 0.
  .mrc  as .erg with ``MINUTES PERCENT`` (values in percent of FTP).
  .fit  Garmin FIT workout (binary; decoded with Garmin's FIT SDK): time steps, repeats,
        power ranges in % FTP or watts, heart-rate ranges in bpm or % of the rider's maximum
        (heart-rate ERG), open / cadence steps ridden free (:mod:`bike_session.fit_workout` has
        the rules). Only FIT has heart-rate targets: .zwo, .erg and .mrc carry none.

Power -> Command (the choices, all explicit parameters)

- FTP: every relative target is scaled by the *rider's* FTP ``ftp_w``. An .erg written for
  ``FTP = F`` is rescaled by ``ftp_w / F`` (GoldenCheetah's rule: a workout written for a
  250 W rider keeps its intensity for a 200 W rider); without an FTP header its watts are
  ridden as written. ``use_file_ftp=True`` rides the file's FTP instead (.erg: watts as
  written; .zwo ``<ftpOverride>``: fractions x that FTP). With ``ftp_w=None`` the file's FTP
  is used when there is one, else relative targets are an error.
- Power targets ride in ERG mode (``bike_msgs/Command.MODE_ERG``, bike_controller.modes):
  a target of W watts is ``Command = W / pmax_w`` and the controller holds that power at
  any cadence above its minimum (closing the loop on the measured torque). ``pmax_w`` is
  the machine's ERG power range: ``modes.erg_power_max_w`` of the config, else
  ``controller.pmax_w`` (1016.68 W by default; :func:`pmax_w_from_config`). ``mode`` can
  name another Command mode (e.g. ``resistance``, where W / pmax_w is the paper's Command
  and the power is exact only above the base speed).
- Out of range: a target above ``pmax_w`` is *not* silently clamped. With
  ``over_range="warn"`` (default) the Command saturates at 1.0 from the moment the target
  crosses Pmax (ramps are split there) and one :class:`WorkoutWarning` per file element
  names the file, the element, the highest target, Pmax and the seconds affected; the
  texts stay in ``Workout.warnings``. ``over_range="error"`` refuses the file instead.
- FreeRide and MaxEffort have no power target (``target_w_at`` is None). They are ridden
  in ``resistance`` mode at a fixed Command: ``freeride_command`` (0.2, a light level:
  0.2 x Tmax at the motor is about 21 N m at the crank with the default 35:1 gear) and
  ``maxeffort_command`` (0.5). The rider sets the effort with cadence.
- Cadence targets (``Cadence``, the mean of ``CadenceLow``/``CadenceHigh``,
  ``CadenceResting``) are kept per segment: ``cadence_at(t)``; 0 means none.
- Heart-rate targets (FIT only) ride in ERG mode whatever ``mode`` says (the Command's
  ``heart_rate_bpm`` is ERG's), at Command 0: the controller moves the power target to hold
  the heart rate, starting from the rider's present power; ``heart_rate_at(t)``. A target in
  percent of the rider's maximum heart rate needs ``max_hr_bpm`` (``session.max_hr_bpm``).

Safety: a file is read only if it is a regular file of at most ``MAX_WORKOUT_BYTES``. XML
is parsed with expat directly: any ``<!DOCTYPE>`` (hence any entity declaration, internal
or external) is refused, so no entity expansion can happen; element count and depth are
bounded. Every expansion is bounded by ``profiles.MAX_REPEAT`` and
``profiles.MAX_LEAF_SEGMENTS`` and the total by ``MAX_WORKOUT_S``. Every problem raises
one :class:`WorkoutError` (a ``ProfileError``, hence a ``ValueError``) naming the file,
the line and element, and what is wrong; nothing is returned. No rclpy import here.
"""
from __future__ import annotations

import dataclasses
import math
import os
import pathlib
import re
import warnings
from typing import Any, Iterable, Mapping
from xml.parsers import expat

from bike_plant.config import MAX_SIM_TIME_S
from bike_plant.heart import HEART_RATE_MAX_BPM
from bike_plant.mechanics import RIDER_CADENCE_MAX_RPM, rider_cadence_problem
from bike_session.profiles import (MAX_LEAF_SEGMENTS, MAX_REPEAT, MODES, Profile, ProfileError, Segment,
                                   load_profile)

MAX_WORKOUT_BYTES = 1 << 20        # real workout files are a few kB
MAX_XML_ELEMENTS = 50_000
MAX_XML_DEPTH = 16
MAX_TEXT_EVENTS = 10_000
MAX_WORKOUT_S = 24 * 3600.0        # one day; anything longer is a broken file
MAX_FTP_FRACTION = 5.0             # 500 % FTP: larger values are percent written as fractions
MAX_FTP_W = 2000.0
MAX_HR_BPM = HEART_RATE_MAX_BPM    # a rider's maximum heart rate beyond this is a typo
MAX_CADENCE_RPM = RIDER_CADENCE_MAX_RPM      # what a Command may give the rider (bike_plant.mechanics)
DEFAULT_FREERIDE_COMMAND = 0.2
FTP_HINT = "(session.ftp_w; ./bike run --ftp W)"     # where a rider gives his FTP
OVER_RANGE_CHOICES = ("warn", "error")      # what to do with a target beyond the machine's range
DEFAULT_MAXEFFORT_COMMAND = 0.5

FORMATS = {".zwo": "zwo", ".erg": "erg", ".mrc": "mrc", ".fit": "fit", ".yaml": "yaml", ".yml": "yaml"}

_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?\Z")


def over_range_problem(over_range) -> str | None:
    """What is wrong with an over_range setting (load_workout's, a config's session.over_range),
    None when it is one of OVER_RANGE_CHOICES. The session node and ./bike run (before a node
    starts) check the config's with it."""
    if isinstance(over_range, str) and over_range in OVER_RANGE_CHOICES:
        return None
    return f"must be {' or '.join(repr(c) for c in OVER_RANGE_CHOICES)}, got {over_range!r}"


# the config's session: keys the nodes read (the session node's session.* parameters; the plant
# and the controller read period_s too): ./bike run refuses another, a typo that changes nothing
SESSION_KEYS = ("profile", "period_s", "duration_s", "workout", "ftp_w", "max_hr_bpm", "over_range")


def session_number_problem(name: str, value) -> str | None:
    """What is wrong with the session node's number parameter ``name`` (session.period_s,
    duration_s, session.duration_s, session.ftp_w, session.max_hr_bpm), None when it is good:
    each a finite number, the period > 0, the durations >= 0, both at most MAX_SIM_TIME_S, the FTP and maximum heart rate
    0 (not given) up to what load_workout takes. The session node and ./bike
    run (before a node starts) check them with it."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return f"must be a finite number, got {value!r}"
    if name == "session.period_s" and value <= 0:
        return f"must be > 0, got {value!r}"
    if name.endswith("duration_s") and value < 0:
        return f"must be >= 0 (0 = profile length), got {value!r}"
    if value > MAX_SIM_TIME_S and (name.endswith("duration_s") or name == "session.period_s"):
        # the session counts its time in int64 nanoseconds: 1e300 was an OverflowError traceback
        return f"must be at most {MAX_SIM_TIME_S:g} s (the ROS clock's int64 nanoseconds), got {value!r}"
    # the rider's figures ./bike run also reads from the config (0: not given; else load_workout's bounds)
    upper = {"session.ftp_w": (MAX_FTP_W, "W"), "session.max_hr_bpm": (MAX_HR_BPM, "bpm")}.get(name)
    if upper is not None and not 0 <= value <= upper[0]:
        return f"must be in [0, {upper[0]:g}] {upper[1]} (0 = not given), got {value!r}"
    return None


class WorkoutError(ProfileError):
    """A problem in a workout file: ``<file>: line N <Element>: what is wrong``."""

    def __init__(self, message: str, source: str | os.PathLike | None = None, where: str | None = None,
                 line: int | None = None):
        super().__init__(message, source, where)
        self.line = line


class WorkoutWarning(UserWarning):
    """A workout that can be ridden but not as written (e.g. a target above Pmax)."""


@dataclasses.dataclass(frozen=True)
class WorkoutSegment(Segment):
    """A profile segment that also remembers the file's power, cadence and heart-rate targets."""

    target_start_w: float | None = None    # ERG target at start_s (None: no target, e.g. FreeRide)
    target_end_w: float | None = None
    cadence_rpm: float | None = None
    block: str = ""                         # file element: SteadyState, IntervalsT, erg, ...
    heart_rate_bpm: float | None = None     # heart-rate ERG target (then no power target)

    def target_w_at(self, t_s: float) -> float | None:
        if self.target_start_w is None or self.target_end_w is None:
            return None
        if self.target_start_w == self.target_end_w:
            return self.target_start_w
        frac = min(max((t_s - self.start_s) / self.duration_s, 0.0), 1.0)
        return self.target_start_w + (self.target_end_w - self.target_start_w) * frac


@dataclasses.dataclass(frozen=True)
class TextEvent:
    """An on-screen cue of the file, at ``time_s`` from the session start."""

    time_s: float
    message: str
    duration_s: float = 0.0
    where: str = ""


class Workout(Profile):
    """A Profile built from a workout file, with its power targets, cadence and text events."""

    def __init__(self, name: str, segments: list[WorkoutSegment], *, source: str, text: str, fmt: str,
                 ftp_w: float | None, file_ftp_w: float | None, pmax_w: float, mode: int,
                 events: list[TextEvent], warnings_: list[str], description: str = "", author: str = "",
                 max_hr_bpm: float | None = None):
        super().__init__(name, segments, source=source, text=text,
                         cadences={seg.index: seg.cadence_rpm for seg in segments if seg.cadence_rpm},
                         heart_rates={seg.index: seg.heart_rate_bpm for seg in segments if seg.heart_rate_bpm})
        self.format = fmt
        self.ftp_w = ftp_w                  # FTP the relative targets were scaled with
        self.file_ftp_w = file_ftp_w        # FTP declared in the file (ERG FTP=, ZWO ftpOverride)
        self.pmax_w = pmax_w
        self.max_hr_bpm = max_hr_bpm        # the rider's maximum heart rate (% of max targets; None: not given)
        self.mode = mode
        self.events = sorted(events, key=lambda e: e.time_s)
        self.warnings = warnings_
        self.description = description
        self.author = author

    def __repr__(self) -> str:
        return (f"Workout({self.name!r}, {self.format}, {len(self.segments)} segments, {self.duration_s:g} s, "
                f"FTP {self.ftp_w if self.ftp_w is not None else '-'} W, Pmax {self.pmax_w:g} W)")

    def target_w_at(self, t_s: float) -> float | None:
        """The file's power target in watts at ``t_s`` (None: free segment or past the end)."""
        seg = self.segment_at(t_s)
        return seg.target_w_at(t_s) if seg is not None else None

    def events_between(self, t0_s: float, t1_s: float) -> list[TextEvent]:
        """Text events with t0 <= time < t1 (for logging them as the session passes them)."""
        return [e for e in self.events if t0_s <= e.time_s < t1_s]

    def info(self) -> dict[str, Any]:
        """JSON-ready facts for session_info / the report."""
        return {
            "workout_format": self.format,
            "ftp_w": self.ftp_w,
            "file_ftp_w": self.file_ftp_w,
            "pmax_w": self.pmax_w,
            "max_hr_bpm": self.max_hr_bpm,
            "command_rule": "command = target_w / pmax_w (exact at speeds >= base speed)",
            "description": self.description,
            "author": self.author,
            "events": [dataclasses.asdict(e) for e in self.events],
            "warnings": list(self.warnings),
        }


# --------------------------------------------------------------------------- entry points


def pmax_w_from_config(cfg: Mapping) -> float:
    """The ERG power range of a loaded config: ``modes.erg_power_max_w`` when set (> 0),
    else the machine's Pmax (bike_controller.modes.machine_figures: the controller's rule)."""
    from bike_controller.modes import machine_figures

    modes = cfg.get("modes") if isinstance(cfg, Mapping) else None
    erg = modes.get("erg_power_max_w") if isinstance(modes, Mapping) else None
    if isinstance(erg, (int, float)) and not isinstance(erg, bool) and math.isfinite(erg) and erg > 0:
        return float(erg)
    try:
        return machine_figures(dict(cfg), with_envelope=False).pmax_w
    except (ValueError, TypeError) as exc:
        raise WorkoutError(str(exc), cfg.get("_config_path") if isinstance(cfg, Mapping) else None,
                           "controller.pmax_w") from None


def load_workout(path: str | os.PathLike, *, ftp_w: float | None = None, pmax_w: float | None = None,
                 mode: str = "erg", over_range: str = "warn", use_file_ftp: bool = False,
                 freeride_command: float = DEFAULT_FREERIDE_COMMAND,
                 maxeffort_command: float = DEFAULT_MAXEFFORT_COMMAND, units=None,
                 max_hr_bpm: float | None = None) -> Profile:
    """Read a workout (.zwo/.erg/.mrc/.fit, or a .yaml profile) into a Profile; WorkoutError on any problem.
    ``units`` (profiles.ModeUnits) lets a .yaml profile give targets in W / % / rpm; ``max_hr_bpm``
    is the rider's maximum heart rate (for a FIT target in percent of it; None: not known)."""
    path = pathlib.Path(path)
    fmt = FORMATS.get(path.suffix.lower())
    if fmt is None and path.is_dir():
        # a folder without a suffix was "unsupported workout extension '(none)'"
        raise WorkoutError("not a regular file (a directory)", path)
    if fmt is None:
        known = ", ".join(sorted(FORMATS))
        raise WorkoutError(f"unsupported workout extension {path.suffix or '(none)'!r}; expected one of {known}",
                           path)
    if fmt == "yaml":
        return load_profile(path, units=units)
    data = read_bounded(path)
    return parse_workout_bytes(data, fmt, source=str(path), default_name=path.stem, ftp_w=ftp_w, pmax_w=pmax_w,
                               mode=mode, over_range=over_range, use_file_ftp=use_file_ftp,
                               freeride_command=freeride_command, maxeffort_command=maxeffort_command,
                               max_hr_bpm=max_hr_bpm)


def read_bounded(path: pathlib.Path, limit: int = MAX_WORKOUT_BYTES) -> bytes:
    """The file's bytes, refusing non-regular, unreadable, empty and over-size files."""
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise WorkoutError(f"cannot read workout ({exc.strerror})", path) from None
    if not path.is_file():
        raise WorkoutError("not a regular file", path)
    if size > limit:
        raise WorkoutError(f"file too large ({size} bytes > {limit})", path)
    try:
        with open(path, "rb") as fh:
            data = fh.read(limit + 1)
    except OSError as exc:
        raise WorkoutError(f"cannot read workout ({exc.strerror})", path) from None
    if len(data) > limit:
        raise WorkoutError(f"file too large (> {limit} bytes)", path)
    if not data.strip():
        raise WorkoutError("empty file", path)
    return data


def parse_workout_bytes(data: bytes | str, fmt: str, *, source: str = "<workout>", default_name: str = "workout",
                        ftp_w: float | None = None, pmax_w: float | None = None, mode: str = "erg",
                        over_range: str = "warn", use_file_ftp: bool = False,
                        freeride_command: float = DEFAULT_FREERIDE_COMMAND,
                        maxeffort_command: float = DEFAULT_MAXEFFORT_COMMAND,
                        max_hr_bpm: float | None = None) -> Workout:
    """Parse a workout of format ``zwo``, ``erg``, ``mrc`` or ``fit`` (see the module docstring)."""
    if isinstance(data, str):
        data = data.encode("utf-8")
    if len(data) > MAX_WORKOUT_BYTES:
        raise WorkoutError(f"workout too large (> {MAX_WORKOUT_BYTES} bytes)", source)
    if not data.strip():
        raise WorkoutError("empty file", source)
    opts = _Options.make(source, ftp_w=ftp_w, pmax_w=pmax_w, mode=mode, over_range=over_range,
                         use_file_ftp=use_file_ftp, freeride_command=freeride_command,
                         maxeffort_command=maxeffort_command, max_hr_bpm=max_hr_bpm)
    if fmt == "zwo":
        workout = _parse_zwo(data, source, default_name, opts)
    elif fmt in ("erg", "mrc"):
        workout = _parse_erg(data, source, default_name, opts, fmt)
    elif fmt == "fit":
        from bike_session.fit_workout import parse_fit     # (the FIT SDK loads only for .fit files)
        workout = parse_fit(data, source, default_name, opts)
    else:
        raise WorkoutError(f"unknown workout format {fmt!r}; expected zwo, erg, mrc or fit", source)
    for text in workout.warnings:
        warnings.warn(text, WorkoutWarning, stacklevel=3)
    return workout


# --------------------------------------------------------------------------- options and timeline


@dataclasses.dataclass(frozen=True)
class _Options:
    ftp_w: float | None
    pmax_w: float
    mode: int
    over_range: str
    use_file_ftp: bool
    freeride_command: float
    maxeffort_command: float
    max_hr_bpm: float | None = None

    @classmethod
    def make(cls, source, *, ftp_w, pmax_w, mode, over_range, use_file_ftp, freeride_command, maxeffort_command,
             max_hr_bpm=None):
        def positive(name, value, upper=math.inf):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or not 0 < value <= upper:
                bound = f" and <= {upper:g}" if math.isfinite(upper) else ""
                raise WorkoutError(f"parameter {name} must be a number > 0{bound}, got {value!r}", source, name)
            return float(value)

        if pmax_w is None:
            raise WorkoutError("parameter pmax_w (the machine's power range in W, controller.pmax_w of the "
                               "config) is required to turn watts into a Command", source, "pmax_w")
        pmax = positive("pmax_w", pmax_w)
        ftp = None if ftp_w is None else positive("ftp_w", ftp_w, MAX_FTP_W)
        max_hr = None if max_hr_bpm is None else positive("max_hr_bpm", max_hr_bpm, MAX_HR_BPM)
        if not isinstance(mode, str) or mode not in MODES:
            raise WorkoutError(f"unknown mode {mode!r}; expected one of {', '.join(MODES)}", source, "mode")
        if over_range_problem(over_range):
            raise WorkoutError(f"over_range {over_range_problem(over_range)}", source, "over_range")
        for name, value in (("freeride_command", freeride_command), ("maxeffort_command", maxeffort_command)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
                raise WorkoutError(f"parameter {name} must be in [0, 1], got {value!r}", source, name)
        return cls(ftp, pmax, MODES[mode], over_range, bool(use_file_ftp), float(freeride_command),
                   float(maxeffort_command), max_hr)

    def effective_ftp(self, file_ftp: float | None) -> float | None:
        if file_ftp is not None and (self.use_file_ftp or self.ftp_w is None):
            return file_ftp
        return self.ftp_w


class _Timeline:
    """Accumulates WorkoutSegments, turning watts into Commands and tracking Pmax overruns."""

    def __init__(self, source: str, opts: _Options):
        self.source = source
        self.opts = opts
        self.leaves: list[WorkoutSegment] = []
        self.t = 0.0
        self.over: dict[str, list[float]] = {}     # where -> [max target W, seconds above Pmax]
        self.order: list[str] = []
        self.notes: list[str] = []

    def err(self, where: str, message: str, line: int | None = None) -> WorkoutError:
        return WorkoutError(message, self.source, where, line)

    def _append(self, duration, c0, c1, mode, label, path, where, w0, w1, cadence, block, heart_rate_bpm=None):
        if len(self.leaves) >= MAX_LEAF_SEGMENTS:
            raise self.err(where, f"workout expands to more than {MAX_LEAF_SEGMENTS} segments")
        self.leaves.append(WorkoutSegment(len(self.leaves), path, self.t, duration, c0, c1, mode, label,
                                          w0, w1, cadence, block, heart_rate_bpm))
        self.t += duration

    def power(self, duration: float, w0: float, w1: float, *, label: str, path: str, where: str,
              cadence: float | None, block: str) -> None:
        """A segment with an ERG target ramping w0 -> w1 watts (a step when equal)."""
        self._check_duration(duration, where)
        pmax, mode = self.opts.pmax_w, self.opts.mode
        c0, c1 = w0 / pmax, w1 / pmax
        if max(c0, c1) <= 1.0:
            self._append(duration, c0, c1, mode, label, path, where, w0, w1, cadence, block)
            return
        if self.opts.over_range == "error":
            raise self.err(where, f"target {max(w0, w1):.0f} W exceeds the machine's power range "
                                  f"(pmax_w = {pmax:g} W)")
        if where not in self.over:
            self.over[where] = [0.0, 0.0]
            self.order.append(where)
        rec = self.over[where]
        rec[0] = max(rec[0], w0, w1)
        if c0 == c1 or (c0 >= 1.0 and c1 >= 1.0):
            rec[1] += duration
            self._append(duration, min(c0, 1.0), min(c1, 1.0), mode, label, path, where, w0, w1, cadence, block)
            return
        # a ramp crossing Pmax: ramp up to Command 1 where it crosses, hold 1 for the rest
        f = (1.0 - c0) / (c1 - c0)
        d_cross = duration * f
        w_cross = pmax
        parts = [(d_cross, c0, 1.0, w0, w_cross), (duration - d_cross, 1.0, 1.0, w_cross, w1)] if c0 < 1.0 else \
                [(d_cross, 1.0, 1.0, w0, w_cross), (duration - d_cross, 1.0, c1, w_cross, w1)]
        for k, (d, a, b, wa, wb) in enumerate(parts):
            if d <= 0:
                continue
            if a >= 1.0 and b >= 1.0:
                rec[1] += d
            self._append(d, a, b, mode, label, f"{path} [part {k + 1}/2]", where, wa, wb, cadence, block)

    def free(self, duration: float, command: float, *, label: str, path: str, where: str,
             cadence: float | None, block: str) -> None:
        """A segment without power target: fixed resistance-mode Command."""
        self._check_duration(duration, where)
        self._append(duration, command, command, MODES["resistance"], label, path, where, None, None, cadence, block)

    def heart_rate(self, duration: float, bpm: float, *, label: str, path: str, where: str,
                   cadence: float | None, block: str) -> None:
        """A heart-rate ERG segment: ERG (the only mode with a heart-rate target) at Command 0,
        so that the controller starts from the rider's present power."""
        self._check_duration(duration, where)
        self._append(duration, 0.0, 0.0, MODES["erg"], label, path, where, None, None, cadence, block, bpm)

    def _check_duration(self, duration, where):
        if not (math.isfinite(duration) and duration > 0):
            raise self.err(where, f"duration must be > 0, got {duration!r}")
        if self.t + duration > MAX_WORKOUT_S:
            raise self.err(where, f"workout longer than {MAX_WORKOUT_S / 3600:g} h")

    def warnings(self) -> list[str]:
        out = list(self.notes)
        pmax = self.opts.pmax_w
        for where in self.order:
            top, seconds = self.over[where]
            out.append(f"{self.source}: {where}: target {top:.0f} W exceeds the machine's power range "
                       f"Pmax = {pmax:g} W (Command {top / pmax:.2f} > 1); Command held at 1.0 (= {pmax:g} W) "
                       f"for {seconds:g} s")
        return out


# --------------------------------------------------------------------------- numbers


def _comma_hint(text: str) -> str:
    """A hint for a number written with a decimal comma ('0,75', as a European locale writes it)."""
    t = text.strip()
    return " (numbers take a decimal point, not a comma)" if re.fullmatch(r"[+-]?\d*,\d+", t) else ""


def _number(text: str | None) -> float | None:
    if text is None:
        return None
    s = text.strip()
    if not _NUMBER.match(s):
        return None
    value = float(s)
    return value if math.isfinite(value) else None


# --------------------------------------------------------------------------- ZWO (XML)


class _Node:
    __slots__ = ("tag", "attrs", "line", "children", "text")

    def __init__(self, tag: str, attrs: dict[str, str], line: int):
        self.tag = tag
        self.attrs = attrs
        self.line = line
        self.children: list[_Node] = []
        self.text: list[str] = []

    @property
    def key(self) -> str:
        return self.tag.lower()

    def where(self, attr: str | None = None) -> str:
        return f"line {self.line} <{self.tag}>" + (f" attribute {attr}" if attr else "")


def _parse_xml(data: bytes, source: str) -> _Node:
    parser = expat.ParserCreate()
    parser.buffer_text = True
    stack: list[_Node] = []
    root: list[_Node] = []
    count = [0]

    def refuse(*_args):
        raise WorkoutError("DOCTYPE / entity declarations are not allowed in a workout file "
                           "(entity expansion guard)", source, f"line {parser.CurrentLineNumber}",
                           parser.CurrentLineNumber)

    def start(tag, attrs):
        count[0] += 1
        line = parser.CurrentLineNumber
        if count[0] > MAX_XML_ELEMENTS:
            raise WorkoutError(f"more than {MAX_XML_ELEMENTS} XML elements", source, f"line {line}", line)
        if len(stack) >= MAX_XML_DEPTH:
            raise WorkoutError(f"XML nested deeper than {MAX_XML_DEPTH} levels", source, f"line {line} <{tag}>", line)
        node = _Node(tag, attrs, line)
        if stack:
            stack[-1].children.append(node)
        else:
            root.append(node)
        stack.append(node)

    def end(_tag):
        stack.pop()

    def chars(text):
        if stack:
            stack[-1].text.append(text)

    parser.StartDoctypeDeclHandler = refuse
    parser.EntityDeclHandler = refuse
    parser.UnparsedEntityDeclHandler = refuse
    parser.ExternalEntityRefHandler = refuse
    parser.StartElementHandler = start
    parser.EndElementHandler = end
    parser.CharacterDataHandler = chars
    parser.SetParamEntityParsing(expat.XML_PARAM_ENTITY_PARSING_NEVER)
    try:
        parser.Parse(data, True)
    except expat.ExpatError as exc:
        hint = ""
        if exc.code == expat.errors.codes[expat.errors.XML_ERROR_TAG_MISMATCH] and stack:
            hint = f"; <{stack[-1].tag}> opened at line {stack[-1].line} is not closed"
        elif exc.code == expat.errors.codes[expat.errors.XML_ERROR_NO_ELEMENTS] and stack:
            hint = f"; <{stack[-1].tag}> opened at line {stack[-1].line} is not closed (file truncated?)"
        raise WorkoutError(f"not well-formed XML: {expat.ErrorString(exc.code)} (column {exc.offset + 1}){hint}",
                           source, f"line {exc.lineno}", exc.lineno) from None
    except RecursionError:
        raise WorkoutError("XML nested too deeply", source) from None
    except WorkoutError:
        raise
    except (LookupError, ValueError) as exc:
        # the declaration names an encoding Python does not know ('U-8': LookupError) or expat
        # cannot read ('shift_jis', 'utf-32': ValueError); both were tracebacks
        declared = _XML_ENCODING.match(data)
        name = declared.group(1).decode("ascii", "replace") if declared else "?"
        raise WorkoutError(f"the XML declaration names encoding {name!r}, which this reader cannot read ({exc}); "
                           "save the file as UTF-8", source, "line 1", 1) from None
    if not root:
        raise WorkoutError("no XML element found", source)
    return root[0]


_ZWO_STEADY = {"steadystate", "solidstate"}
_ZWO_RAMPS = {"warmup", "ramp", "cooldown"}
_ZWO_FREE = {"freeride", "maxeffort"}
_ZWO_BLOCKS = _ZWO_STEADY | _ZWO_RAMPS | _ZWO_FREE | {"intervalst"}
_ZWO_EVENTS = {"textevent", "textnotification"}
_ZWO_IGNORED_CHILDREN = {"gameplayevent"}
_BLOCK_NAMES = "Warmup, SteadyState, SolidState, IntervalsT, Ramp, Cooldown, FreeRide, MaxEffort"


class _Zwo:
    def __init__(self, source: str, opts: _Options, ftp: float | None):
        self.source = source
        self.opts = opts
        self.ftp = ftp
        self.tl = _Timeline(source, opts)
        self.events: list[TextEvent] = []

    def err(self, node: _Node, message: str, attr: str | None = None) -> WorkoutError:
        return WorkoutError(message, self.source, node.where(attr), node.line)

    # attribute access: case-insensitive, refusing the same name twice in different case
    def attr(self, node: _Node, *names: str) -> tuple[str, str] | None:
        lower = {}
        for k, v in node.attrs.items():
            if k.lower() in lower:
                raise self.err(node, f"attribute given twice ({lower[k.lower()][0]} and {k})", k)
            lower[k.lower()] = (k, v)
        for name in names:
            if name.lower() in lower:
                return lower[name.lower()]
        return None

    def num(self, node: _Node, *names: str, required: bool = False, default: float | None = None,
            minimum: float = 0.0, allow_equal: bool = True) -> float | None:
        found = self.attr(node, *names)
        if found is None:
            if required:
                raise self.err(node, f"missing attribute {names[0]}")
            return default
        name, raw = found
        value = _number(raw)
        if value is None:
            raise self.err(node, f"expected a number, got {raw!r}{_comma_hint(raw)}", name)
        if value < minimum or (not allow_equal and value == minimum):
            raise self.err(node, f"must be {'>=' if allow_equal else '>'} {minimum:g}, got {raw!r}", name)
        return value

    def duration(self, node: _Node, *names: str, zero_ok: bool = False) -> float:
        value = self.num(node, *names, required=True, allow_equal=zero_ok)
        if value > MAX_WORKOUT_S:
            raise self.err(node, f"longer than {MAX_WORKOUT_S:g} s, got {value:g}", names[0])
        return value

    def power(self, node: _Node, *names: str, required: bool = True) -> float | None:
        value = self.num(node, *names, required=required)
        if value is None:
            return None
        if value > MAX_FTP_FRACTION:
            name = self.attr(node, *names)[0]
            raise self.err(node, f"{value:g} is {value * 100:g} % of FTP; ZWO powers are FTP fractions "
                                 f"(0.75 = 75 %), at most {MAX_FTP_FRACTION:g}", name)
        if self.ftp is None:
            raise self.err(node, "power targets are fractions of FTP: pass the rider's ftp_w "
                                 f"{FTP_HINT}", names[0])
        return value * self.ftp

    def pair(self, node: _Node, single: str, low: str, high: str) -> tuple[float, float]:
        """(start W, end W) from ``single`` or ``low``/``high`` (one of them alone = constant)."""
        if self.attr(node, single) is not None:
            w = self.power(node, single)
            return w, w
        lo, hi = self.power(node, low, required=False), self.power(node, high, required=False)
        if lo is None and hi is None:
            raise self.err(node, f"missing attribute {single} (or {low}/{high})")
        lo = hi if lo is None else lo
        hi = lo if hi is None else hi
        return lo, hi

    def cadence(self, node: _Node, *names: str) -> float | None:
        value = self.num(node, *names)
        # the rule of the Command that carries it to the rider: a value the controller would
        # refuse is refused here, naming the attribute, not ride by ride
        problem = rider_cadence_problem(value) if value is not None else None
        if problem:
            raise self.err(node, problem, names[0])
        return value or None

    def block_cadence(self, node: _Node) -> float | None:
        c = self.cadence(node, "Cadence")
        if c is None:
            lo, hi = self.cadence(node, "CadenceLow"), self.cadence(node, "CadenceHigh")
            if lo is not None and hi is not None:
                c = (lo + hi) / 2
            else:
                c = lo if lo is not None else hi
        return c

    # blocks
    def block(self, node: _Node, index: int) -> None:
        key = node.key
        if key not in _ZWO_BLOCKS:
            raise self.err(node, f"unknown element <{node.tag}> in <workout>; expected one of {_BLOCK_NAMES}")
        start_t = self.tl.t
        tag = node.tag
        path = f"workout[{index}] {node.where()}"
        where = node.where()
        if key == "intervalst":
            self.intervals(node, path)
        else:
            dur = self.duration(node, "Duration")
            cad = self.block_cadence(node)
            if key in _ZWO_FREE:
                command = self.opts.freeride_command if key == "freeride" else self.opts.maxeffort_command
                self.tl.free(dur, command, label=tag, path=path, where=where, cadence=cad, block=tag)
            elif key in _ZWO_STEADY:
                lo, hi = self.pair(node, "Power", "PowerLow", "PowerHigh")
                w = (lo + hi) / 2
                self.tl.power(dur, w, w, label=tag, path=path, where=where, cadence=cad, block=tag)
            else:
                w0, w1 = self.pair(node, "Power", "PowerLow", "PowerHigh")
                if key == "cooldown" and w0 < w1:
                    w0, w1 = w1, w0
                self.tl.power(dur, w0, w1, label=tag, path=path, where=where, cadence=cad, block=tag)
        for child in node.children:
            self.child(child, node, start_t)

    def intervals(self, node: _Node, path: str) -> None:
        found = self.attr(node, "Repeat")
        count = 1
        if found is not None:
            value = _number(found[1])
            if value is None or not value.is_integer():
                raise self.err(node, f"expected an integer, got {found[1]!r}", found[0])
            count = int(value)
            if not 1 <= count <= MAX_REPEAT:
                raise self.err(node, f"must be in [1, {MAX_REPEAT}], got {found[1]!r}", found[0])
        on_d = self.duration(node, "OnDuration")
        off_d = self.duration(node, "OffDuration", zero_ok=True)
        if len(self.tl.leaves) + count * 2 > MAX_LEAF_SEGMENTS:
            raise self.err(node, f"workout expands to more than {MAX_LEAF_SEGMENTS} segments", "Repeat")
        if self.tl.t + count * (on_d + off_d) > MAX_WORKOUT_S:
            raise self.err(node, f"workout longer than {MAX_WORKOUT_S / 3600:g} h", "Repeat")
        on = self.pair(node, "OnPower", "PowerOnLow", "PowerOnHigh")
        off = self.pair(node, "OffPower", "PowerOffLow", "PowerOffHigh") if off_d > 0 else None
        on_cad = self.block_cadence(node)
        off_cad = self.cadence(node, "CadenceResting")
        where, tag = node.where(), node.tag
        for r in range(count):
            tag_r = f" (repeat {r + 1}/{count})" if count > 1 else ""
            self.tl.power(on_d, *on, label=f"{tag} on", path=f"{path} on{tag_r}", where=where, cadence=on_cad,
                          block=tag)
            if off is not None:
                self.tl.power(off_d, *off, label=f"{tag} off", path=f"{path} off{tag_r}", where=where,
                              cadence=off_cad, block=tag)

    def child(self, node: _Node, parent: _Node, block_start: float) -> None:
        key = node.key
        if key in _ZWO_IGNORED_CHILDREN:
            return
        if key not in _ZWO_EVENTS:
            raise self.err(node, f"unknown element <{node.tag}> in <{parent.tag}>; expected textevent")
        if len(self.events) >= MAX_TEXT_EVENTS:
            raise self.err(node, f"more than {MAX_TEXT_EVENTS} text events")
        if self.attr(node, "timeoffset") is None and self.attr(node, "distoffset") is not None:
            raise self.err(node, "distance-based text events (distoffset) are not supported", "distoffset")
        offset = self.num(node, "timeoffset", required=True)
        msg = self.attr(node, "message", "mssage", "text")
        if msg is None or not msg[1].strip():
            raise self.err(node, "missing attribute message")
        dur = self.num(node, "duration", default=0.0)
        self.events.append(TextEvent(block_start + offset, msg[1].strip(), dur, node.where()))


_ZWO_META = {"author", "name", "description", "category", "subcategory", "categoryindex", "sporttype", "tags",
             "ftpoverride", "durationtype"}


_XML_ENCODING = re.compile(rb'\A\s*<\?xml[^>]*?\bencoding\s*=\s*["\']([A-Za-z0-9._-]+)["\']')


def _windows_text_as_utf8(data: bytes) -> bytes:
    """An XML file that should be UTF-8 (no BOM, no encoding declared or UTF-8 declared) but is
    not, as UTF-8: a .zwo saved by a Windows editor in its ANSI code page (cp1252, latin-1 where
    cp1252 has no character) has a description or text event 'Caf\xe9'; expat refused the whole
    file with 'not well-formed (invalid token)'. The .erg reader reads such text the same way."""
    if data.startswith((b"\xef\xbb\xbf", b"\xff\xfe", b"\xfe\xff")):
        return data                      # a byte order mark says what it is
    declared = _XML_ENCODING.match(data)
    if declared and declared.group(1).lower().replace(b"_", b"-") not in (b"utf-8", b"utf8"):
        return data                      # expat reads the declared encoding (or names it)
    return _windows_text(data, "utf-8").encode("utf-8")


def _windows_text(data: bytes, encoding: str) -> str:
    """Text in ``encoding`` (a UTF-8 codec) or, failing that, in a Windows ANSI code page: cp1252, then
    latin-1, which decodes any byte (old Windows tools write descriptions in their code page)."""
    for name in (encoding, "cp1252"):
        try:
            return data.decode(name)
        except UnicodeDecodeError:
            pass
    return data.decode("latin-1")


_XML_DECLARATION_LATE = re.compile(rb"(\xef\xbb\xbf)?([ \t\r\n]+)(<\?xml[ \t][^>\r\n]*\?>)")


def _xml_declaration_first(data: bytes) -> bytes:
    """Blank lines before the XML declaration (a web page's template writes them) moved after it:
    expat refuses a declaration that is not the first thing in the file ('XML or text declaration
    not at start of entity'). The lines keep their numbers."""
    m = _XML_DECLARATION_LATE.match(data)
    if m is None:
        return data
    return (m.group(1) or b"") + m.group(3) + m.group(2) + data[m.end():]


def _parse_zwo(data: bytes, source: str, default_name: str, opts: _Options) -> Workout:
    data = _xml_declaration_first(_windows_text_as_utf8(data))
    root = _parse_xml(data, source)
    if root.key != "workout_file":
        raise WorkoutError(f"root element is <{root.tag}>, expected <workout_file>", source, root.where(), root.line)
    meta: dict[str, _Node] = {}
    workouts = []
    for child in root.children:
        if child.key == "workout":
            workouts.append(child)
        elif child.key in _ZWO_META:
            meta.setdefault(child.key, child)
    if not workouts:
        raise WorkoutError("missing <workout> element", source, root.where(), root.line)
    if len(workouts) > 1:
        raise WorkoutError("more than one <workout> element", source, workouts[1].where(), workouts[1].line)

    def text_of(key: str) -> str:
        node = meta.get(key)
        return "".join(node.text).strip() if node is not None else ""

    sport = text_of("sporttype")
    if sport and sport.lower() != "bike":
        n = meta["sporttype"]
        raise WorkoutError(f"sportType is {sport!r}: not a cycling workout", source, n.where(), n.line)
    dtype = text_of("durationtype")
    if dtype and dtype.lower() != "time":
        n = meta["durationtype"]
        raise WorkoutError(f"durationType {dtype!r} is not supported (only time-based workouts)", source,
                           n.where(), n.line)
    file_ftp = None
    if "ftpoverride" in meta:
        n = meta["ftpoverride"]
        file_ftp = _number(text_of("ftpoverride"))
        if file_ftp is None or not 0 < file_ftp <= MAX_FTP_W:
            raise WorkoutError(f"expected an FTP in W in (0, {MAX_FTP_W:g}], got {text_of('ftpoverride')!r}",
                               source, n.where(), n.line)
    ftp = opts.effective_ftp(file_ftp)
    zwo = _Zwo(source, opts, ftp)
    blocks = workouts[0].children
    if not blocks:
        w = workouts[0]
        raise WorkoutError("<workout> has no blocks", source, w.where(), w.line)
    for i, node in enumerate(blocks):
        zwo.block(node, i)
    notes = zwo.tl.warnings()
    for e in zwo.events:
        if e.time_s > zwo.tl.t:
            notes.append(f"{source}: {e.where}: text event at {e.time_s:g} s is after the end of the workout "
                         f"({zwo.tl.t:g} s)")
    name = text_of("name") or default_name
    return Workout(name, zwo.tl.leaves, source=source, text=data.decode("utf-8", "replace"), fmt="zwo",
                   ftp_w=ftp, file_ftp_w=file_ftp, pmax_w=opts.pmax_w, mode=opts.mode, events=zwo.events,
                   warnings_=notes, description=text_of("description"), author=text_of("author"))


# --------------------------------------------------------------------------- ERG / MRC (text)

_SECTIONS = ("course header", "end course header", "course data", "end course data", "course text",
             "end course text")


def _parse_erg(data: bytes, source: str, default_name: str, opts: _Options, fmt: str) -> Workout:
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        # UTF-16 with a byte order mark: what Windows PowerShell 5's '>' and Notepad's 'Unicode' write
        try:
            text = data.decode("utf-16")
        except UnicodeDecodeError:
            raise WorkoutError("starts with a UTF-16 byte order mark but is not UTF-16 text", source) from None
        if "\x00" in text:
            raise WorkoutError("binary file (NUL characters), not a text workout", source)
    elif b"\x00" in data:
        raise WorkoutError("binary file (NUL bytes), not a text workout", source)
    else:
        text = _windows_text(data, "utf-8-sig")

    def err(line_no: int | None, message: str) -> WorkoutError:
        return WorkoutError(message, source, f"line {line_no}" if line_no else None, line_no)

    header: dict[str, tuple[str, int]] = {}
    units = None                       # "watts" | "percent"
    points: list[tuple[float, float, bool, int]] = []    # (minutes, value, is_percent, line)
    events: list[TextEvent] = []
    seen: dict[str, int] = {}
    state = "start"
    lines = text.splitlines()
    for n, raw in enumerate(lines, start=1):
        line = raw.strip()
        if not line or line.startswith(";"):
            continue
        if line.startswith("[") and line.endswith("]"):
            name = " ".join(line[1:-1].lower().split())
            if name not in _SECTIONS:
                raise err(n, f"unknown section {line}; expected one of "
                             + ", ".join(f"[{s.upper()}]" for s in _SECTIONS))
            if name in seen:
                raise err(n, f"section {line} repeated (first at line {seen[name]})")
            seen[name] = n
            expected = {"course header": "start", "end course header": "header", "course data": "after-header",
                        "end course data": "data", "course text": "after-data", "end course text": "text"}[name]
            if state != expected:
                raise err(n, f"section {line} out of place")
            state = {"course header": "header", "end course header": "after-header", "course data": "data",
                     "end course data": "after-data", "course text": "text", "end course text": "end"}[name]
            continue
        if state == "header":
            if "=" in line:
                key, _, value = line.partition("=")
                header[" ".join(key.upper().split())] = (value.strip(), n)
                continue
            cols = line.upper().split()
            if cols in (["MINUTES", "WATTS"], ["MINUTE", "WATTS"]):
                units = "watts"
            elif cols in (["MINUTES", "PERCENT"], ["MINUTES", "FTP"], ["MINUTE", "PERCENT"]):
                units = "percent"
            elif cols and cols[0] in ("DISTANCE", "MINUTES", "MINUTE"):
                raise err(n, f"columns {line!r} are not supported (only MINUTES WATTS or MINUTES PERCENT; "
                             "slope/distance courses are not workouts)")
            else:
                raise err(n, f"unrecognised header line {line!r} (expected KEY = VALUE or MINUTES WATTS|PERCENT)")
            continue
        if state == "data":
            parts = line.split(";", 1)[0].split()          # "2.00  150  ; comment" is fine
            if len(parts) >= 2 and parts[1].upper() == "LAP":
                minutes = _number(parts[0])
                if minutes is None or minutes < 0:
                    raise err(n, f"expected a time in minutes >= 0, got {parts[0]!r}")
                if len(events) >= MAX_TEXT_EVENTS:
                    raise err(n, f"more than {MAX_TEXT_EVENTS} text events")
                events.append(TextEvent(minutes * 60.0, " ".join(parts[1:]), 0.0, f"line {n}"))
                continue
            if len(parts) != 2:
                raise err(n, f"expected '<minutes> <{'percent' if units == 'percent' else 'watts'}>', got {line!r}")
            minutes = _number(parts[0])
            if minutes is None:
                raise err(n, f"time is not a number: {parts[0]!r}{_comma_hint(parts[0])}")
            if minutes < 0:
                raise err(n, f"time must be >= 0 minutes, got {parts[0]!r}")
            if minutes * 60.0 > MAX_WORKOUT_S:
                raise err(n, f"time {parts[0]} min is beyond {MAX_WORKOUT_S / 3600:g} h")
            is_pct = parts[1].endswith("%")
            value = _number(parts[1][:-1] if is_pct else parts[1])
            if value is None:
                raise err(n, f"{'percent' if (is_pct or units == 'percent') else 'watts'} value is not a number: "
                             f"{parts[1]!r}{_comma_hint(parts[1].rstrip('%'))}")
            if value < 0:
                raise err(n, f"value must be >= 0, got {parts[1]!r}")
            if points and minutes < points[-1][0]:
                raise err(n, f"time goes backwards: {minutes:g} min after {points[-1][0]:g} min at line "
                             f"{points[-1][3]} (times must not decrease)")
            if len(points) >= MAX_LEAF_SEGMENTS:
                raise err(n, f"more than {MAX_LEAF_SEGMENTS} data points")
            points.append((minutes, value, is_pct or units == "percent", n))
            continue
        if state == "text":
            parts = [p for p in re.split(r"\t+", line) if p.strip()]
            if len(parts) < 2:
                parts = line.split(None, 1)
            t_s = _number(parts[0]) if parts else None
            if t_s is None or t_s < 0 or len(parts) < 2:
                raise err(n, f"expected '<seconds> <message> [<duration>]' in [COURSE TEXT], got {line!r}")
            duration = 0.0
            if len(parts) >= 3 and _number(parts[-1]) is not None and _number(parts[-1]) >= 0:
                duration = _number(parts[-1])
                parts = parts[:-1]
            if len(events) >= MAX_TEXT_EVENTS:
                raise err(n, f"more than {MAX_TEXT_EVENTS} text events")
            events.append(TextEvent(t_s, " ".join(p.strip() for p in parts[1:]), duration, f"line {n}"))
            continue
        where_text = {"start": "before [COURSE HEADER]", "after-header": "between the header and [COURSE DATA]",
                      "after-data": "after [END COURSE DATA]", "end": "after [END COURSE TEXT]"}[state]
        raise err(n, f"unexpected line {where_text}: {line!r}")

    for name, label in (("course header", "[COURSE HEADER]"), ("end course header", "[END COURSE HEADER]"),
                        ("course data", "[COURSE DATA]"), ("end course data", "[END COURSE DATA]")):
        if name not in seen:
            raise err(len(lines), f"missing {label}" + (" (file truncated?)" if name == "end course data" else ""))
    if "course text" in seen and "end course text" not in seen:
        raise err(len(lines), "missing [END COURSE TEXT] (file truncated?)")
    if units is None:
        units = "percent" if fmt == "mrc" else "watts"
    if fmt == "mrc" and units == "watts":
        raise err(seen["course header"], "an .mrc file holds percent of FTP, but the header says MINUTES WATTS")
    if len(points) < 2:
        raise err(seen["course data"], f"[COURSE DATA] needs at least two points, got {len(points)}")
    if points[-1][0] <= points[0][0]:
        raise err(points[-1][3], "the workout has no duration (all points at the same time)")

    file_ftp = None
    header_notes = []
    if "FTP" in header:
        raw, n = header["FTP"]
        file_ftp = _number(raw)
        if not raw.strip() or file_ftp == 0:
            # an exporter that writes 'FTP = {its FTP}' without one writes 'FTP =' or 'FTP = 0':
            # no FTP, the watts as written (GoldenCheetah reads it so); other apps ride such files
            file_ftp = None
            ridden = "the watts are ridden as written" if units == "watts" else "the percent take the rider's FTP"
            header_notes.append(f"{source}: line {n}: '{('FTP = ' + raw.strip()).strip()}' names no FTP: {ridden}")
        elif file_ftp is None or not 0 < file_ftp <= MAX_FTP_W:
            raise err(n, f"FTP must be a number of watts in (0, {MAX_FTP_W:g}], got {raw!r}{_comma_hint(raw)}")
    ftp = opts.effective_ftp(file_ftp)
    scale = ftp / file_ftp if (file_ftp is not None and ftp is not None) else 1.0

    def watts(value: float, is_pct: bool, n: int) -> float:
        if is_pct:
            if value > MAX_FTP_FRACTION * 100:
                raise err(n, f"{value:g} % of FTP is beyond {MAX_FTP_FRACTION * 100:g} %")
            if ftp is None:
                raise err(n, f"percent-of-FTP value: pass the rider's ftp_w {FTP_HINT}")
            return value / 100.0 * ftp
        return value * scale

    tl = _Timeline(source, opts)
    tl.notes.extend(header_notes)
    label = fmt
    first_m, first_v, first_pct, first_n = points[0]
    if first_m > 0:
        w = watts(first_v, first_pct, first_n)
        tl.power(first_m * 60.0, w, w, label=label, path=f"line {first_n} (held from 0)",
                 where=f"line {first_n}", cadence=None, block=fmt)
        tl.notes.append(f"{source}: line {first_n}: the first point is at {first_m:g} min; its value holds from 0")
    for (m0, v0, p0, n0), (m1, v1, p1, n1) in zip(points, points[1:]):
        if m1 == m0:
            continue
        tl.t = m0 * 60.0
        w0, w1 = watts(v0, p0, n0), watts(v1, p1, n1)
        where = f"line {n0}" if w0 == w1 else f"lines {n0}-{n1}"
        tl.power(m1 * 60.0 - m0 * 60.0, w0, w1, label=label, path=f"lines {n0}-{n1}", where=where, cadence=None,
                 block=fmt)
    desc = header.get("DESCRIPTION", ("", 0))[0]
    name = header.get("FILE NAME", ("", 0))[0]
    if name:
        # FILE NAME as Windows tools write it ("C:\\Workouts\\Sweet Spot.erg"): the file's name,
        # without its .erg / .mrc only ("Over-unders 2.5" keeps its ".5")
        name = pathlib.PureWindowsPath(name).name
        stem, dot, ext = name.rpartition(".")
        name = stem if dot and stem and ext.lower() in ("erg", "mrc") else name
    return Workout(name or default_name, tl.leaves, source=source, text=text, fmt=fmt, ftp_w=ftp,
                   file_ftp_w=file_ftp, pmax_w=opts.pmax_w, mode=opts.mode, events=events,
                   warnings_=tl.warnings(), description=desc)


def describe(workout: Profile, limit: int = 40) -> str:
    """A few lines for a terminal: segments with times, targets and Commands, events, warnings."""
    out = [repr(workout)]
    segs: Iterable[Segment] = workout.segments
    for i, s in enumerate(segs):
        if i >= limit:
            out.append(f"  ... {len(workout.segments) - limit} more segments")
            break
        tgt = ""
        if isinstance(s, WorkoutSegment):
            if s.heart_rate_bpm:
                tgt = f"HR {s.heart_rate_bpm:.0f} bpm"
            elif s.target_start_w is None:
                tgt = "free"
            elif s.target_start_w == s.target_end_w:
                tgt = f"{s.target_start_w:.0f} W"
            else:
                tgt = f"{s.target_start_w:.0f}->{s.target_end_w:.0f} W"
            if s.cadence_rpm:
                tgt += f" @{s.cadence_rpm:g} rpm"
        cmd = f"{s.start:.3f}" if s.start == s.end else f"{s.start:.3f}->{s.end:.3f}"
        out.append(f"  {s.start_s:8.1f}-{s.end_s:8.1f} s  {s.label:<16} {tgt:<22} command {cmd}")
    for e in getattr(workout, "events", []):
        out.append(f"  text {e.time_s:8.1f} s  {e.message}")
    for w in getattr(workout, "warnings", []):
        out.append(f"  warning: {w}")
    return "\n".join(out)
