"""Garmin FIT workout files (.fit) as session profiles, decoded with Garmin's own FIT SDK.

Called by :func:`bike_session.workouts.parse_workout_bytes` (``load_workout`` picks it for a
``.fit`` extension); it returns the same :class:`~bike_session.workouts.Workout`, so a FIT
workout rides, records and reports like a .zwo. The format (FIT SDK profile 21.x; Garmin's
"workout file type" article and cookbook; /work/shared/research/trainers.md section 1.3):

  file_id      ``type`` must be ``workout`` (an activity or a course is refused by name).
  workout      ``wkt_name`` names the profile; ``sport`` must be cycling or generic/training.
  workout_step one per step, in ``message_index`` order (0, 1, ... without gaps).

Per step (the choices, in the order the reader applies them):

- Duration: ``time`` (``duration_value`` in ms). ``open`` (until the lap button) has no
  length on a time base: it is ridden for ``OPEN_STEP_S`` and a warning says so. A step
  ended by distance, heart rate, power, calories ... is refused: a testbed session is a
  function of sim time.
- ``repeat_until_steps_cmplt``: the steps from ``duration_value`` (a message_index before
  this step) up to this one are ridden ``target_value`` times in all (the block once as
  written plus target_value - 1 repeats; nested repeats work, as on a head unit). Other
  repeat kinds (until a time, distance, heart rate ...) are refused.
- Target ``power`` (and ``power_3s`` / ``power_10s`` / ``power_30s`` / ``power_lap``):
  ``target_value`` 0 means a custom range ``custom_target_value_low..high``, each value
  <= 1000 in percent of FTP, > 1000 in watts + 1000 (the FIT ``workout_power`` rule). The
  range's mean is ridden in ERG mode (FIT has no ramps; a range is a band, as the ZWO
  reader rides SteadyState's PowerLow/PowerHigh). A power ZONE (target_value 1-7) needs the
  rider's zone table, which the file does not carry: refused.
- Target ``heart_rate``: heart-rate ERG. ``target_value`` 0 means a custom range
  ``custom_target_value_low..high``, each value > 100 in bpm + 100, 1..100 in percent of the
  rider's maximum heart rate (the FIT ``workout_hr`` rule; percent needs ``max_hr_bpm``,
  ``session.max_hr_bpm``). The middle of the range is the Command's ``heart_rate_bpm`` (40..220,
  bike_plant.heart), ridden in ERG at Command 0: the controller moves the power target to hold
  it, starting from the rider's present power. A heart-rate ZONE (target_value 1-5) rides the
  middle of that zone of Garmin's default zones in percent of the maximum heart rate (1: 50-60,
  2: 60-70, 3: 70-80, 4: 80-90, 5: 90-100 %; the file carries no zone table of its own, so a
  warning says so); it needs ``max_hr_bpm`` like a percent target.
- Target ``open`` or ``cadence``: no power target, ridden in resistance mode at
  ``freeride_command`` like a ZWO FreeRide; a custom cadence range (rpm) is kept as the
  segment's cadence, as is a secondary cadence target (of a power, heart-rate or free step).
- Secondary targets: a step whose primary target is open, cadence or unmodelled and whose
  ``secondary_target_type`` is power or heart rate (Garmin Connect lets a cadence target be the
  primary one) rides the secondary target by the rules above, read from
  ``secondary_target_value`` / ``secondary_custom_target_value_low/high``.
- Other targets (speed, grade, resistance, ...): ridden free as above, with one warning per
  target kind naming the steps (nothing here models them).
- ``wkt_step_name`` labels the segment; ``notes`` become a text event at the step's start.
- A percent-of-FTP value needs the rider's FTP (``ftp_w``): FIT files carry none; likewise a
  percent-of-max heart rate the rider's maximum heart rate (``max_hr_bpm``).

Safety: the file is at most ``MAX_FIT_BYTES`` (real workouts are a few hundred bytes; the
SDK decodes the whole file into Python objects). The decoder checks the header and both
CRCs; any problem it reports, and any step that cannot be ridden, is one
:class:`~bike_session.workouts.WorkoutError` naming the file and the step. Repeats are bounded
by ``profiles.MAX_REPEAT`` and ``profiles.MAX_LEAF_SEGMENTS``, the ride by
``workouts.MAX_WORKOUT_S``. No rclpy import here.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

from bike_plant.heart import heart_rate_target_problem
from bike_plant.mechanics import rider_cadence_problem
from bike_session.profiles import MAX_LEAF_SEGMENTS, MAX_REPEAT
from bike_session.workouts import (FTP_HINT, MAX_CADENCE_RPM, MAX_FTP_FRACTION, MAX_TEXT_EVENTS, TextEvent,
                                   Workout, WorkoutError, _Options, _Timeline)

MAX_FIT_BYTES = 256 * 1024
MAX_FIT_STEPS = 0x0FFF            # message_index 0..4094 (12 bits; 0x0FFF is the invalid value)
OPEN_STEP_S = 300.0               # an 'open' step (until the lap button), ridden on a time base
POWER_TARGETS = {"power", "power_3s", "power_10s", "power_30s", "power_lap"}
FREE_TARGETS = {"open", "cadence"}
BIKE_SPORTS = {"cycling", "generic", "training"}
WATTS_OFFSET = 1000               # FIT workout_power: values above it are watts + 1000
BPM_OFFSET = 100                  # FIT workout_hr: values above it are bpm + 100, else % of max


@dataclasses.dataclass(frozen=True)
class _Step:
    """One ridable step: its length, its power or heart-rate target (both None: free) and what
    labels it."""

    duration_s: float
    target_w: float | None
    cadence_rpm: float | None
    label: str
    block: str
    notes: str
    heart_rate_bpm: float | None = None


def parse_fit(data: bytes, source: str, default_name: str, opts: _Options) -> Workout:
    """Decode a FIT workout and expand it into a Workout (module docstring for the rules)."""
    if len(data) > MAX_FIT_BYTES:
        raise WorkoutError(f"FIT file too large ({len(data)} bytes > {MAX_FIT_BYTES}; workouts are a few "
                           "hundred bytes)", source)
    messages = _decode(data, source)
    file_ids = messages.get("file_id_mesgs") or []
    if not file_ids:
        raise WorkoutError("FIT file without a file_id message: not a workout file", source)
    kind = file_ids[0].get("type")
    if kind != "workout":
        raise WorkoutError(f"FIT file of type {kind!r}, not a workout (an activity is a recorded ride, a course a "
                           "route; export the workout itself)", source, "file_id")
    workouts = messages.get("workout_mesgs") or []
    head: dict[str, Any] = workouts[0] if workouts else {}
    sport = head.get("sport")
    if sport is not None and sport not in BIKE_SPORTS:
        raise WorkoutError(f"sport {sport!r} is not a bike workout (expected one of {', '.join(sorted(BIKE_SPORTS))})",
                           source, "workout")
    raw_steps = messages.get("workout_step_mesgs") or []
    if not raw_steps:
        raise WorkoutError("FIT workout without workout_step messages", source)
    steps = _in_order(raw_steps, source)
    ftp = opts.effective_ftp(None)
    notes: dict[str, list[int]] = {}
    ridable: dict[int, _Step] = {}
    leaves: list[tuple[int, str]] = []          # (step index, repeat path) in riding order
    first_leaf: dict[int, int] = {}
    for i, step in enumerate(steps):
        first_leaf[i] = len(leaves)
        if step.get("duration_type") == "repeat_until_steps_cmplt":
            _repeat(i, step, leaves, first_leaf, source)
            continue
        if str(step.get("duration_type", "")).startswith("repeat_"):
            raise WorkoutError(f"repeat kind {step['duration_type']!r} cannot be ridden on a time base (only "
                               "repeat_until_steps_cmplt)", source, f"step {i}")
        ridable[i] = _ridable(i, step, ftp, opts, notes, source)
        leaves.append((i, ""))
    tl = _Timeline(source, opts)
    events: list[TextEvent] = []
    for i, rep in leaves:
        st = ridable[i]
        where = f"step {i}"
        path = where + rep
        if st.notes and len(events) < MAX_TEXT_EVENTS:
            events.append(TextEvent(tl.t, st.notes, 0.0, path))
        if st.heart_rate_bpm is not None:
            tl.heart_rate(st.duration_s, st.heart_rate_bpm, label=st.label, path=path, where=where,
                          cadence=st.cadence_rpm, block=st.block)
        elif st.target_w is None:
            tl.free(st.duration_s, opts.freeride_command, label=st.label, path=path, where=where,
                    cadence=st.cadence_rpm, block=st.block)
        else:
            tl.power(st.duration_s, st.target_w, st.target_w, label=st.label, path=path, where=where,
                     cadence=st.cadence_rpm, block=st.block)
    for text, idx in notes.items():
        shown = ", ".join(str(k) for k in idx[:10]) + (f" and {len(idx) - 10} more" if len(idx) > 10 else "")
        tl.notes.append(f"{source}: step{'s' if len(idx) > 1 else ''} {shown}: {text}")
    name = head.get("wkt_name")
    name = name.strip() if isinstance(name, str) and name.strip() else default_name
    return Workout(name, tl.leaves, source=source, text=_summary(steps), fmt="fit", ftp_w=ftp, file_ftp_w=None,
                   pmax_w=opts.pmax_w, mode=opts.mode, events=events, warnings_=tl.warnings(),
                   max_hr_bpm=opts.max_hr_bpm)


def _decode(data: bytes, source: str) -> dict:
    """The file's messages, by the FIT SDK (header and CRCs checked); one WorkoutError otherwise."""
    try:
        from garmin_fit_sdk import Decoder, Stream
    except ImportError:
        raise WorkoutError("reading FIT files needs Garmin's FIT SDK: pip install garmin-fit-sdk "
                           "(make setup installs it)", source) from None

    try:
        if not Decoder(Stream.from_byte_array(bytearray(data))).is_fit():
            raise WorkoutError("not a FIT file (no '.FIT' file header)", source)
        messages, errors = Decoder(Stream.from_byte_array(bytearray(data))).read()
    except WorkoutError:
        raise
    except Exception as exc:  # noqa: BLE001 - a third-party decoder on hostile bytes: one clear error
        raise WorkoutError(f"corrupt FIT file: truncated or damaged, Garmin's FIT SDK could not decode it "
                           f"(the SDK reports {type(exc).__name__}: {exc})", source) from None
    if errors:
        # the SDK's own error on a damaged file reads like a bug of ours ("TypeError: can only
        # concatenate str ..." on a truncated one): say what it means first, and keep it after
        first = errors[0]
        raise WorkoutError(f"corrupt FIT file: truncated or damaged, Garmin's FIT SDK could not decode it "
                           f"(the SDK reports {type(first).__name__}: {first})", source)
    return messages


def _in_order(raw_steps: list[dict], source: str) -> list[dict]:
    """The steps by message_index, which repeats refer to: 0, 1, ... without gaps or doubles.
    A FIT message_index is the low 12 bits of its field (0x0FFF, the SDK's 'mask'; 0x8000
    marks a 'selected' message), so a workout has at most MAX_FIT_STEPS steps."""
    if len(raw_steps) > MAX_FIT_STEPS:
        raise WorkoutError(f"{len(raw_steps)} workout steps: more than a FIT workout can index "
                           f"({MAX_FIT_STEPS}, message_index is 12 bits)", source)
    indices = [s.get("message_index") for s in raw_steps]
    if all(k is None for k in indices):
        return list(raw_steps)
    indices = [k & 0x0FFF if isinstance(k, int) else k for k in indices]
    if any(not isinstance(k, int) for k in indices) or sorted(indices) != list(range(len(raw_steps))):
        raise WorkoutError(f"workout_step message_index values must be 0..{len(raw_steps) - 1}, each once; got "
                           f"{indices[:20]}", source)
    order = sorted(range(len(raw_steps)), key=indices.__getitem__)
    return [raw_steps[k] for k in order]


def _repeat(i: int, step: dict, leaves: list, first_leaf: dict, source: str) -> None:
    """Ride the steps from duration_value to i - 1 target_value times in all (nesting included)."""
    where = f"step {i}"
    start = step.get("duration_value")
    count = step.get("target_value")
    if not isinstance(start, int) or not 0 <= start < i:
        raise WorkoutError(f"repeat must point back to an earlier step (duration_value < {i}), got {start!r}",
                           source, where)
    if not isinstance(count, int) or not 1 <= count <= MAX_REPEAT:
        raise WorkoutError(f"repeat count (target_value) must be an integer in [1, {MAX_REPEAT}], got {count!r}",
                           source, where)
    block = leaves[first_leaf[start]:]
    if not block:
        raise WorkoutError(f"repeat of steps {start}..{i - 1}, which ride nothing", source, where)
    if len(leaves) + len(block) * (count - 1) > MAX_LEAF_SEGMENTS:
        raise WorkoutError(f"workout expands to more than {MAX_LEAF_SEGMENTS} segments", source, where)
    for r in range(2, count + 1):
        leaves.extend((k, f"{rep} [{where}: {r}/{count}]") for k, rep in block)


def _ridable(i: int, step: dict, ftp: float | None, opts: _Options, notes: dict, source: str) -> _Step:
    where = f"step {i}"

    def err(message: str) -> WorkoutError:
        return WorkoutError(message, source, where)

    kind = step.get("duration_type")
    if kind == "time":
        ms = step.get("duration_value")
        if not isinstance(ms, (int, float)) or not ms > 0:
            raise err(f"time step needs duration_value > 0 ms, got {ms!r}")
        duration = ms / 1000.0
    elif kind == "open":
        duration = OPEN_STEP_S
        notes.setdefault(f"'open' duration (until the lap button) ridden for {OPEN_STEP_S:g} s", []).append(i)
    else:
        raise err(f"duration {kind!r} cannot be ridden on a time base (time and open steps only)")
    target = step.get("target_type", "open")
    intensity = step.get("intensity")
    block = intensity if isinstance(intensity, str) else "step"
    name = step.get("wkt_step_name")
    label = name.strip() if isinstance(name, str) and name.strip() else block
    text = step.get("notes")
    text = text.strip() if isinstance(text, str) else ""
    cadence = None
    target_w, heart_rate = _power_or_heart_rate(target, step, ftp, opts, notes, i, err)
    secondary = step.get("secondary_target_type")
    if target == "cadence" and not step.get("target_value"):
        cadence = _cadence(step.get("custom_target_value_low"), step.get("custom_target_value_high"))
    use_secondary = target_w is None and heart_rate is None and (secondary in POWER_TARGETS
                                                                   or secondary == "heart_rate")
    if target not in POWER_TARGETS | FREE_TARGETS | {"heart_rate"}:
        ridden = (f"the step's secondary {secondary} target is ridden" if use_secondary
                  else f"free ride at Command {opts.freeride_command:g}")
        notes.setdefault(f"{target!r} targets are not ridden (no model of them here): {ridden}", []).append(i)
    if use_secondary:
        # a cadence / open (or unmodelled) primary target with a power or heart-rate secondary
        # target (Garmin Connect lets either be primary): the secondary one is the ERG target
        fields = {"target_value": step.get("secondary_target_value"),
                  "custom_target_value_low": step.get("secondary_custom_target_value_low"),
                  "custom_target_value_high": step.get("secondary_custom_target_value_high")}
        target_w, heart_rate = _power_or_heart_rate(secondary, fields, ftp, opts, notes, i, err, "secondary ")
    if secondary == "cadence" and cadence is None:
        cadence = _cadence(step.get("secondary_custom_target_value_low"),
                           step.get("secondary_custom_target_value_high"))
    return _Step(duration, target_w, cadence, label, block, text, heart_rate)


def _power_or_heart_rate(target: Any, step: dict, ftp: float | None, opts: _Options, notes: dict, i: int, err,
                         prefix: str = "") -> tuple[float | None, float | None]:
    """(power W, heart rate bpm) of a target of kind ``target`` whose target_value and custom range
    are in ``step`` (a primary target, or a secondary one under the primary names); (None, None)
    for any other kind."""
    if target in POWER_TARGETS:
        return _custom_mean(step, f"{prefix}power", lambda v: _watts(v, ftp, err), err), None
    if target != "heart_rate":
        return None, None
    if step.get("target_value"):
        heart_rate = _hr_zone_bpm(step.get("target_value"), opts.max_hr_bpm, err)
        notes.setdefault("heart-rate zones ridden as Garmin's default zones (50-60 .. 90-100 % of the maximum "
                         "heart rate; the file carries no zone table)", []).append(i)
    else:
        heart_rate = _custom_mean(step, f"{prefix}heart-rate", lambda v: _bpm(v, opts.max_hr_bpm, err), err)
    problem = heart_rate_target_problem(heart_rate)
    if problem:
        raise err(problem)
    return None, heart_rate


def _custom_mean(step: dict, what: str, convert, err) -> float:
    """The mean of a step's custom target range (either end may be missing), each end through
    ``convert``; a zone (``target_value``) is refused: the file carries no zone table."""
    zone = step.get("target_value") or 0
    if zone != 0:
        raise err(f"{what} zone {zone} needs the rider's zone table, which a FIT workout does not carry "
                  "(write the step as a custom range)")
    lo, hi = step.get("custom_target_value_low"), step.get("custom_target_value_high")
    if lo is None and hi is None:
        raise err(f"{what} step without custom_target_value_low/high")
    values = [convert(v) for v in (lo, hi) if v is not None]
    return sum(values) / len(values)


def _watts(value: Any, ftp: float | None, err) -> float:
    """A FIT workout_power value: <= 1000 percent of FTP, > 1000 watts + 1000."""
    if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise err(f"power value must be a number >= 0, got {value!r}")
    if value > WATTS_OFFSET:
        return float(value - WATTS_OFFSET)
    if value > MAX_FTP_FRACTION * 100:
        raise err(f"{value:g} % of FTP is beyond {MAX_FTP_FRACTION * 100:g} %")
    if ftp is None:
        raise err(f"percent-of-FTP target: pass the rider's ftp_w {FTP_HINT}; a FIT workout carries no FTP")
    return value / 100.0 * ftp


def _bpm(value: Any, max_hr_bpm: float | None, err) -> float:
    """A FIT workout_hr value: > 100 bpm + 100, 1..100 percent of the rider's maximum heart rate."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise err(f"heart-rate value must be a number > 0 (1..100 % of max, > 100 bpm + 100), got {value!r}")
    if value > BPM_OFFSET:
        return float(value - BPM_OFFSET)
    if max_hr_bpm is None:
        raise err(f"{value:g} % of the maximum heart rate: give the rider's maximum heart rate "
                  "(session.max_hr_bpm; ./bike run --max-hr BPM); a FIT workout carries none")
    return value / 100.0 * max_hr_bpm


# Garmin's default heart-rate zones, in percent of the maximum heart rate (Garmin's watch manuals,
# "Heart Rate Zone Calculations"): zone -> (low, high)
HR_ZONES_PCT_MAX = {1: (50.0, 60.0), 2: (60.0, 70.0), 3: (70.0, 80.0), 4: (80.0, 90.0), 5: (90.0, 100.0)}


def _hr_zone_bpm(zone: Any, max_hr_bpm: float | None, err) -> float:
    """The middle of heart-rate zone ``zone`` (1..5, :data:`HR_ZONES_PCT_MAX`) for this rider."""
    if isinstance(zone, bool) or zone not in HR_ZONES_PCT_MAX:
        raise err(f"heart-rate zone {zone!r}: zones 1..5 only")
    if max_hr_bpm is None:
        raise err(f"heart-rate zone {zone}: give the rider's maximum heart rate (session.max_hr_bpm; "
                  "./bike run --max-hr BPM); a FIT workout carries none")
    lo, hi = HR_ZONES_PCT_MAX[zone]
    return 0.5 * (lo + hi) / 100.0 * max_hr_bpm


def _cadence(lo: Any, hi: Any) -> float | None:
    values = [float(v) for v in (lo, hi) if isinstance(v, (int, float)) and 0 < v <= MAX_CADENCE_RPM]
    mean = sum(values) / len(values) if values else None
    # a target the Command could not carry to the rider (under 10 rpm) is no target
    return mean if mean is not None and rider_cadence_problem(mean) is None else None


def _summary(steps: list[dict]) -> str:
    """A text form of the decoded steps, kept as the profile's text (session_info, reports)."""
    keys = ("message_index", "wkt_step_name", "duration_type", "duration_value", "target_type", "target_value",
            "custom_target_value_low", "custom_target_value_high", "intensity", "notes")
    return "\n".join(", ".join(f"{k}={s[k]!r}" for k in keys if s.get(k) is not None) for s in steps)
