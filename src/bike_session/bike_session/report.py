"""Summary, charts and an HTML page of a recorded session (``./bike report BAG [--out DIR]``).

Definitions (PlantState samples i = 0..n-1 in header-time order; a sample repeated with
the same stamp and seq, e.g. republished by a lockstep plant, counts once):

- ``duration_s``           t_{n-1} - t_0 (bag time span if there is no PlantState)
- ``mean_braking_power_w`` mechanical power taken by the machine, -T_em * w: per batch
  -torque_em_nm[i] * (speed_rad_s[i-1] + speed_rad_s[i]) / 2 (torque_em_nm[i] is the mean
  over the batch ending at t_i), weighted by t_i - t_{i-1}. Positive while braking.
- ``mean_rider_power_w``   (energy_mech_in_j[n-1] - energy_mech_in_j[0]) / duration: power
  of the rider / load into the shaft, from the plant's ledger.
- ``energy_battery_j`` / ``energy_resistor_j`` / ``energy_loss_j`` / ``energy_mech_in_j``:
  last - first of the cumulative ledger; ``*_wh`` = J / 3600.
- ``peak_phase_current_a`` max |i| over phase_current_a and current_samples_a.
- ``interlock_blanked``    last interlock_blanked_count (cumulative since plant start).
- ``fault_batches``        number of PlantState messages with each FAULT_* bit set;
  ``timeouts`` = fault_batches['command_timeout'].
- ``relay_switch_overs``   SPMSM: changes of relay_state between RELAY_INVERTER and
  RELAY_RECTIFIER (the RELAY_SWITCHING interval between them skipped).
- ``messages``             number of messages per topic.
- ``can``                  plant backend ``can`` only: the CAN statistics of the plant's last
  diagnostic (frames received / sent, dropped by reason, drive lost / re-armed, setpoints,
  RTR requests, the CAN log file) and ``error_diagnostics``, the number of ERROR
  diagnostics of the CAN plant.
- ``mean_cadence_rpm``     time mean of speed_rpm / gear_ratio (gear_ratio = load.gear_ratio
  of the config recorded in session_info; 35 when the bag has none).
- ``time_in_mode_s``       batch time per Command mode. The mode (and command, mode_target)
  in force for the batch t_{i-1}..t_i is the latest ControllerStatus stamped <= t_{i-1}
  (the Command topic when the bag has no ControllerStatus).
- ``tracking``             per mode, how well the machine did what the mode asked:
  ``erg_power`` the power ERG holds, the rider's: braking power + the bike's friction
  B w^2 + Tc w (the figures of the recorded config, as the controller models them:
  bike_controller.modes.friction_figures) - mode_target [W]; ``isokinetic_cadence`` crank cadence
  (mean over the batch) - mode_target [rpm]; ``resistance_torque`` braking torque
  -T_em - Eq. 3-4 of paper 000 at the command in force and the batch's mean speed, with
  Tmax, wb, Pmax of the recorded config [N m]; ``slope_speed`` the road speed of the
  batch's mean cadence (wheel radius and virtual gear of the config) - the virtual bike's
  speed (ControllerStatus.virtual_speed_mps) [m/s]: how closely the flywheel followed the
  virtual bike (statuses without a virtual speed, from older bags, are left out);
  ``cadence_target`` (any mode, wherever a Command carries the rider's cadence target
  cadence_rpm > 0) crank cadence - that target [rpm].
  ``rms`` / ``max_abs`` / ``mean`` are over ``window_s`` windows that lie wholly in the mode
  (error averaged over the window, which removes the commutation ripple); ``rms_batch`` /
  ``max_abs_batch`` over single batches. A mode_target missing from an older bag is derived
  from the command and the config.
- ``friction``             the mode laws' friction in force, B [N m s] and Tc [N m] at the motor
  (ControllerStatus.friction_nms / dry_friction_nm): its first value and every change, each
  with the time it appeared (a spin-down, mode 5). Absent for older bags.
- ``power_accuracy``       the trainer's power estimate (braking power + the bike's friction as the
  laws model it + d(1/2 J w^2)/dt, J of the config) - the rider's (ledger), over 10 s windows where the rider gives > 20 W:
  mean / rms / max_abs [W], mean_pct (:func:`power_accuracy`); None without such a window.
  ``ledger_from_drive`` True for a drive on CAN: its ledger is made of the drive's Torque_Estimate
  and speed (bike_plant.can.backend), not the physics' truth, so an error of the drive's kt Iq
  (the BLDC's, braking: -1 % at 0.5 N m .. +7 % at 2 N m of its true torque; README) is in neither side.
  An emulated drive's truth in the bag (``drive_truth``, bike_msgs/DriveTruth from bike-drive-emulator
  --truth-topic, stamped with the plant's /clock): the figures are against the rider's true power
  (``against`` "drive_truth", ``true_rider_power_w``; the ledger's figures in ``ledger``, its own
  error against the truth in ``ledger_error_pct``), in the windows the truth covers.
- ``erg_response``         ERG target steps (a change of more than 10 W and 5 % between
  tracking windows) and the time from each until the ERG power (as ``erg_power``) stays within
  max(5 % of the target, 5 W) for 1 s (:func:`erg_response`); None without a step.
- ``shift_response``       virtual shifts in the slope mode (ControllerStatus' gear changing, a
  press or an automatic shift): the slope tracking error jumps at each (the flywheel still at the
  old gear's speed); the time until it is back within max(5 % of the jump, 0.02 m/s), and how far
  it went past zero within 1 s, in % of the jump (:func:`shift_response`; trainer users complain
  of shifts felt late or bouncing); None without a shift.
- ``mean_heart_rate_bpm`` / ``max_heart_rate_bpm``  the rider's heart rate (PlantState.heart_rate_bpm,
  the intervals where it is > 0 at both ends): time mean and largest; None without one (no rider,
  a prime mover, or a bag recorded before the field).
- ``heart_rate_erg``       heart-rate ERG (Commands in ERG with heart_rate_bpm > 0): per stretch of
  consecutive such Commands with the same target, the target, the time from the stretch's
  first Command until the heart rate (bin mean) is first within HR_TOL_BPM of it (``settle_s``),
  and from there to the stretch's end the mean and largest |heart rate - target|
  (:func:`heart_rate_erg`); None without such a Command.

Long bags: messages are decoded straight from the CDR bytes into numpy blocks of
``CHUNK`` PlantStates; only per-bin sums (``bin_s``, 10 ms for short sessions, at most
~100 000 bins), a thinned sample for the torque-speed scatter and the exact running totals
are kept, so a 1 h bag at 1 kHz (3.6 M PlantStates) needs a few tens of MB. Progress goes
to stderr every 10 % for bags of more than ``PROGRESS_MIN`` messages.
"""
from __future__ import annotations

import argparse
import base64
import html
import json
import math
import pathlib
import struct
import sys

import numpy as np

from bike_controller.modes import erg_power_w
from bike_plant.heart import HEART_RATE_TARGET_MAX_BPM, HEART_RATE_TARGET_MIN_BPM
from bike_session.bags import BagError, open_bag

# PlantState.RELAY_INVERTER, RELAY_RECTIFIER: the connected paths (RELAY_SWITCHING = 2 between them)
RELAY_PATHS = (0, 1)
FAULT_BITS = {
    "interlock": 1,
    "command_timeout": 2,
    "overvoltage": 4,
    "bad_command": 8,
    "drive_lost": 16,
    "recorder_lost": 32,
    "relay_forced": 64,
    "uncontrolled_generation": 128,
    "drive_disarmed": 256,
    "overcurrent": 512,
    "drive_stale": 1024,
    "pack_empty": 2048,
}
SESSION_STATES = {0: "WAITING", 1: "RUNNING", 2: "DONE"}
MODE_NAMES = {0: "resistance", 1: "motoring", 2: "erg", 3: "slope", 4: "isokinetic", 5: "spindown"}
MODE_RESISTANCE, MODE_MOTORING, MODE_ERG, MODE_SLOPE, MODE_ISOKINETIC, MODE_SPINDOWN = range(6)
CADENCE_TARGET = 100          # the bins of the cadence-target tracking (in force in any mode)
# tracked modes: (mode, key, unit, what is compared)
TRACKED = (
    (MODE_ERG, "erg_power", "W", "rider's power (braking + friction) vs mode_target"),
    (MODE_ISOKINETIC, "isokinetic_cadence", "rpm", "crank cadence vs mode_target"),
    (MODE_RESISTANCE, "resistance_torque", "N m", "braking torque vs Eq. 3-4 at the command"),
    (MODE_SLOPE, "slope_speed", "m/s", "road speed from the cadence vs the virtual bike's speed"),
    # not a mode: the rider's cadence target (Command.cadence_rpm) wherever one is in force
    (CADENCE_TARGET, "cadence_target", "rpm", "crank cadence vs the rider's cadence target"),
)
RPM_PER_RAD_S = 60.0 / (2.0 * math.pi)
CHUNK = 16384                 # PlantStates decoded per numpy block
PROGRESS_MIN = 200_000        # progress on stderr above this many messages
WINDOW_S = 0.1                # tracking-error window
MAX_BINS = 100_000
BIN_LADDER = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0)
SCATTER_POINTS = 20_000
PLOT_POINTS = 2000
DPI = 100

# the machine when the bag carries no config (the default BLDC bike, config/bldc_default.yaml)
DEFAULT_MACHINE = {
    "gear_ratio": 35.0,
    "tmax_nm": 2.941995,
    "base_speed_rpm": 3300.0,
    "pmax_w": 1016.68,
    "erg_power_max_w": 0.0,
    "isokinetic_cadence_min_rpm": 20.0,
    "isokinetic_cadence_max_rpm": 120.0,
    "grade_min": -0.20,
    "grade_max": 0.20,
    "wheel_radius_m": 0.335,
    "virtual_gear_ratio": 2.75,
    "brake_envelope": None,      # (motor r/min, N m) of a braking path weaker than Eq. 3-4 (SPMSM)
    # the bike's friction as ERG models it (bike_controller.modes.friction_figures)
    "friction": (1.0e-4, 0.0, 1.0),
    "inertia_kgm2": 0.01,
}
MACHINE_KEYS = {
    "gear_ratio": "load.gear_ratio",
    "tmax_nm": "controller.tmax_nm",
    "base_speed_rpm": "controller.base_speed_rpm",
    "pmax_w": "controller.pmax_w",
    "erg_power_max_w": "modes.erg_power_max_w",
    "isokinetic_cadence_min_rpm": "modes.isokinetic_cadence_min_rpm",
    "isokinetic_cadence_max_rpm": "modes.isokinetic_cadence_max_rpm",
    "grade_min": "modes.grade_min",
    "grade_max": "modes.grade_max",
    "wheel_radius_m": "modes.wheel_radius_m",
    "virtual_gear_ratio": "modes.virtual_gear_ratio",
    "inertia_kgm2": "mechanics.inertia_kgm2",
}


# ============================================================================ config

def config_params(config_text: str | None) -> dict:
    """Flat ``{'controller.tmax_nm': 2.94, ...}`` of a ROS 2 parameter file's text (all
    ``ros__parameters`` sections merged, ``/**`` first). ValueError if it is not one."""
    from bike_plant.config import YamlFileError, parse_yaml_text

    if not config_text:
        return {}
    try:
        doc = parse_yaml_text(config_text)
    except YamlFileError as exc:
        raise ValueError(f"config_text is {exc}") from None
    if not isinstance(doc, dict):
        raise ValueError("config_text is not a ROS 2 parameter file")
    flat: dict = {}
    sections = sorted(doc, key=lambda k: k != "/**")
    for name in sections:
        body = doc[name]
        if isinstance(body, dict) and isinstance(body.get("ros__parameters"), dict):
            _flatten(body["ros__parameters"], "", flat)
    return flat


def _flatten(d: dict, prefix: str, out: dict) -> None:
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            _flatten(v, key + ".", out)
        else:
            out[key] = v


def machine_from_info(info: dict | None) -> dict:
    """Machine figures the report needs, from session_info's config_text (defaults where
    missing; ``source`` and ``notes`` say which)."""
    m = dict(DEFAULT_MACHINE)
    notes = []
    text = (info or {}).get("config_text")
    try:
        params = config_params(text)
    except ValueError as exc:
        params = {}
        notes.append(str(exc))
    if not text:
        notes.append("no config_text in session_info: default machine figures assumed")
    found_pmax = False
    derived = set()
    if params.get("machine") == "spmsm":
        # the SPMSM's Tmax / wb / Pmax are derived from the machine (Kt * Imax, rated speed)
        try:
            from bike_controller.modes import machine_figures
            from bike_plant.config import unflatten
            fig = machine_figures(unflatten(params))
            m.update(tmax_nm=fig.tmax_nm, base_speed_rpm=fig.base_speed_rpm, pmax_w=fig.pmax_w,
                     gear_ratio=fig.gear_ratio, brake_envelope=fig.brake_envelope)
            derived = {"tmax_nm", "base_speed_rpm", "pmax_w", "gear_ratio"}
            found_pmax = True
        except Exception as exc:  # noqa: BLE001 - a report must still come out
            notes.append(f"SPMSM machine figures not derivable ({exc}): defaults assumed")
    for name, key in MACHINE_KEYS.items():
        if name in derived:
            continue
        v = params.get(key)
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
            m[name] = float(v)
            found_pmax |= name == "pmax_w"
        elif params:
            if name in ("gear_ratio", "tmax_nm", "base_speed_rpm"):
                notes.append(f"{key} not in the config: {m[name]:g} assumed")
    if params and not found_pmax:
        m["pmax_w"] = m["tmax_nm"] * m["base_speed_rpm"] / RPM_PER_RAD_S     # Eq. 2
    if not m["gear_ratio"] > 0:
        notes.append(f"load.gear_ratio {m['gear_ratio']:g} is not > 0: 35 assumed")
        m["gear_ratio"] = 35.0
    m["erg_power_max_w"] = m["erg_power_max_w"] or m["pmax_w"]
    if params:
        try:
            from bike_controller.modes import friction_figures
            from bike_plant.config import unflatten
            m["friction"] = friction_figures(unflatten(params))
        except Exception as exc:  # noqa: BLE001 - a report must still come out
            notes.append(f"friction figures not derivable ({exc}): {m['friction']} assumed")
    m["source"] = "session_info config_text" if params else "defaults"
    m["kind"] = str(params.get("machine", "bldc"))
    m["notes"] = notes
    return m


def resistance_torque_nm(command, speed_rpm, machine: dict):
    """Eq. 3-4 of paper 000 (braking torque magnitude) for arrays of command and motor speed;
    with the machine's ``brake_envelope``, C * min(Eq. 3-4 at C = 1, envelope), as the
    controller's mode law (bike_controller.modes, RESISTANCE)."""
    command = np.asarray(command, dtype=float)
    rpm = np.abs(np.asarray(speed_rpm, dtype=float))
    w = np.maximum(rpm, 1e-9) / RPM_PER_RAD_S
    full = np.where(rpm < machine["base_speed_rpm"], machine["tmax_nm"], machine["pmax_w"] / w)
    envelope = machine.get("brake_envelope")
    if envelope is not None:
        full = np.minimum(full, np.interp(rpm, envelope[0], envelope[1]))
    return command * full


def target_from_command(mode, command, machine: dict):
    """mode_target as the controller defines it (for bags whose ControllerStatus has none)."""
    mode = np.asarray(mode)
    c = np.asarray(command, dtype=float)
    out = c.copy()
    out = np.where(mode == MODE_ERG, c * machine["erg_power_max_w"], out)
    out = np.where(mode == MODE_SLOPE, machine["grade_min"] + c * (machine["grade_max"] - machine["grade_min"]), out)
    lo, hi = machine["isokinetic_cadence_min_rpm"], machine["isokinetic_cadence_max_rpm"]
    return np.where(mode == MODE_ISOKINETIC, lo + c * (hi - lo), out)


# ============================================================================ fast CDR fields

_PRIM = {"bool": ("?", 1), "byte": ("B", 1), "char": ("B", 1), "uint8": ("B", 1), "int8": ("b", 1),
         "int16": ("h", 2), "uint16": ("H", 2), "int32": ("i", 4), "uint32": ("I", 4),
         "int64": ("q", 8), "uint64": ("Q", 8), "float32": ("f", 4), "float64": ("d", 8)}


class _Unsupported(Exception):
    pass


def _absmax(values) -> float:
    return max(max(values), -min(values)) if len(values) else 0.0


class _Codegen:
    """Python source that walks one CDR (XCDR1, little endian) message and unpacks only
    the wanted fields; runs of fields at a statically known alignment become one
    struct.unpack_from. Arrays and sequences of messages / strings are not supported
    (the caller then decodes with the typestore)."""

    def __init__(self, typestore, wanted: dict):
        self.ts = typestore
        self.wanted = wanted            # path -> (var, kind)
        self.found = set()
        self.lines: list[str] = []
        self.m, self.r = 8, 0           # pos = r (mod m) at the start of the pending run
        self.fmt: list[str] = []
        self.size = 0
        self.assign: list[tuple] = []
        self.nvals = 0
        self.tmp = 0

    def _align(self, a: int) -> None:
        if a <= 1:
            return
        if a <= self.m:
            pad = (-(self.r + self.size)) % a
            if pad:
                self.fmt.append(f"{pad}x")
                self.size += pad
        else:
            self.flush()
            self.lines.append(f"pos = (pos + {a - 1}) & -{a}")
            self.m, self.r = a, 0

    def flush(self) -> None:
        if not self.size:
            return
        if self.assign:
            self.lines.append(f"_v = unpack_from('<{''.join(self.fmt)}', body, pos)")
            for var, kind, idx, count in self.assign:
                if kind == "absmax":
                    self.lines.append(f"{var} = _absmax(_v[{idx}:{idx + count}])")
                else:
                    self.lines.append(f"{var} = _v[{idx}]")
        self.lines.append(f"pos += {self.size}")
        self.r = (self.r + self.size) % self.m
        self.fmt, self.size, self.assign, self.nvals = [], 0, [], 0

    def _prim(self, typ: str, var=None, count: int = 1, kind: str = "value") -> None:
        fmt, size = _PRIM[typ]
        self._align(size)
        if var is None:
            self.fmt.append(f"{size * count}x")
        else:
            self.fmt.append(f"{count}{fmt}" if count > 1 else fmt)
            self.assign.append((var, kind, self.nvals, count))
            self.nvals += count
        self.size += size * count

    def _count(self) -> str:
        self.tmp += 1
        var = f"_n{self.tmp}"
        self._prim("uint32", var)
        self.flush()
        return var

    def message(self, msgtype: str, prefix: str = "") -> None:
        for name, (nodetype, desc) in self.ts.fielddefs[msgtype][1]:
            path = prefix + name
            want = self.wanted.get(path)
            var = want[0] if want else None
            if want:
                self.found.add(path)
            nt = int(nodetype)
            if nt == 2:                                     # NAME: nested message
                self.message(desc, path + ".")
            elif nt == 1:                                   # BASE
                typ = desc[0]
                if typ == "string":
                    n = self._count()
                    if var:
                        self.lines.append(f"{var} = bytes(body[pos:pos + max({n} - 1, 0)])"
                                          ".decode('utf-8', 'replace')")
                    self.lines.append(f"pos += {n}")
                    self.m, self.r = 1, 0
                elif typ in _PRIM:
                    self._prim(typ, var)
                else:
                    raise _Unsupported(typ)
            elif nt in (3, 4):                              # ARRAY / SEQUENCE
                sub, count = desc
                if int(sub[0]) != 1 or sub[1][0] not in _PRIM:
                    raise _Unsupported(path)
                typ = sub[1][0]
                fmt, size = _PRIM[typ]
                kind = want[1] if want else "value"
                if var and kind != "absmax":
                    raise _Unsupported(f"{path}: only absmax of an array")
                if nt == 3:
                    self._prim(typ, var, count, kind)
                else:
                    n = self._count()
                    if size > 4:
                        self.lines.append(f"if {n}: pos = (pos + {size - 1}) & -{size}")
                    if var:
                        self.lines.append(f"{var} = _absmax(unpack_from('<%d{fmt}' % {n}, body, pos)) if {n} else 0.0")
                    self.lines.append(f"pos += {n} * {size}")
                    self.m, self.r = min(size, 4), 0
            else:
                raise _Unsupported(path)


class FieldReader:
    """Selected fields of one message type straight from CDR bytes: ``reader(raw)`` -> tuple
    in ``spec`` order. ``spec`` = [(dotted path, kind, default)], kind 'value' or 'absmax'
    (max |x| of a numeric array, 0 when empty); a field the embedded definition lacks (an
    older bag) gives its default. Falls back to the typestore's decoder for big-endian
    data or layouts the generator does not handle."""

    def __init__(self, typestore, msgtype: str, spec):
        self.typestore, self.msgtype, self.spec = typestore, msgtype, list(spec)
        self.fast = None
        try:
            self.fast = self._compile()
        except (_Unsupported, KeyError):
            self.fast = None

    def _compile(self):
        wanted = {path: (f"f{i}", kind) for i, (path, kind, _d) in enumerate(self.spec)}
        gen = _Codegen(self.typestore, wanted)
        gen.message(self.msgtype)
        gen.flush()
        consts = {}
        for i, (path, _kind, default) in enumerate(self.spec):
            if path not in gen.found:
                consts[f"f{i}"] = default
        src = ["def extract(raw):",
               "    if raw[0] != 0 or raw[1] != 1:",
               "        return generic(raw)",
               "    body = memoryview(raw)[4:]",
               "    pos = 0"]
        src += ["    " + line for line in gen.lines]
        src.append("    return (" + "".join(f"f{i}, " for i in range(len(self.spec))) + ")")
        ns = {"unpack_from": struct.unpack_from, "_absmax": _absmax, "generic": self.generic, **consts}
        exec("\n".join(src), ns)  # noqa: S102 - generated from the bag's message definition
        return ns["extract"]

    def generic(self, raw) -> tuple:
        msg = self.typestore.deserialize_cdr(raw, self.msgtype)
        out = []
        for path, kind, default in self.spec:
            obj = msg
            for part in path.split("."):
                obj = getattr(obj, part, _MISSING)
                if obj is _MISSING:
                    break
            if obj is _MISSING:
                out.append(default)
            elif kind == "absmax":
                arr = np.abs(np.asarray(obj, dtype=float))
                out.append(float(arr.max()) if arr.size else 0.0)
            else:
                out.append(obj)
        return tuple(out)

    def __call__(self, raw) -> tuple:
        return (self.fast or self.generic)(raw)


_MISSING = object()
NAN = float("nan")
PLANT_SPEC = (
    ("header.stamp.sec", "value", 0), ("header.stamp.nanosec", "value", 0), ("seq", "value", 0),
    ("end_of_run", "value", False), ("speed_rpm", "value", NAN), ("speed_rad_s", "value", NAN),
    ("torque_em_nm", "value", NAN), ("load_torque_nm", "value", NAN), ("dc_bus_v", "value", NAN),
    ("battery_ocv_v", "value", NAN), ("battery_soc", "value", NAN), ("battery_current_a", "value", NAN),
    ("energy_mech_in_j", "value", NAN), ("energy_battery_j", "value", NAN), ("energy_resistor_j", "value", NAN),
    ("energy_loss_j", "value", NAN), ("faults", "value", 0), ("interlock_blanked_count", "value", 0),
    ("phase_current_a", "absmax", 0.0), ("current_samples_a", "absmax", 0.0), ("relay_state", "value", 0),
    ("heart_rate_bpm", "value", 0.0),            # 0 (none) in bags recorded before the field
    ("measured_by_drive", "value", False),       # a drive (on CAN) supplies the data
)
(P_SEC, P_NSEC, P_SEQ, P_EOR, P_RPM, P_W, P_TEM, P_TLOAD, P_VBUS, P_OCV, P_SOC, P_IBAT, P_EMECH, P_EBAT, P_ERES,
 P_ELOSS, P_FAULTS, P_ILOCK, P_IPH, P_ISMP, P_RELAY, P_HR, P_DRIVE) = range(len(PLANT_SPEC))
STATUS_SPEC = (("header.stamp.sec", "value", 0), ("header.stamp.nanosec", "value", 0), ("mode", "value", 0),
               ("command", "value", NAN), ("mode_target", "value", NAN), ("mode_saturated", "value", False),
               ("virtual_speed_mps", "value", NAN), ("virtual_gear_ratio", "value", NAN),
               ("friction_nms", "value", NAN), ("dry_friction_nm", "value", NAN))
STATUS_COLUMNS = 9            # t, mode, command, target, saturated, virtual speed, virtual gear, B, Tc
COMMAND_SPEC = (("header.stamp.sec", "value", 0), ("header.stamp.nanosec", "value", 0), ("mode", "value", 0),
                ("command", "value", NAN), ("virtual_gear_ratio", "value", 0.0), ("cadence_rpm", "value", 0.0),
                ("heart_rate_bpm", "value", 0.0))
BATTERY_SPEC = (("header.stamp.sec", "value", 0), ("header.stamp.nanosec", "value", 0), ("voltage", "value", NAN),
                ("current", "value", NAN), ("percentage", "value", NAN))
TRUTH_SPEC = (("header.stamp.sec", "value", 0), ("header.stamp.nanosec", "value", 0), ("physics_time_s", "value", NAN),
              ("rider_energy_j", "value", NAN))


# ============================================================================ streaming analysis

def auto_bin_s(span_s: float) -> float:
    """Base bin of the time series: 10 ms for short sessions, coarser so that there are at
    most MAX_BINS bins."""
    need = max(span_s, 0.0) / MAX_BINS
    for b in BIN_LADDER:
        if b >= need:
            return b
    return float(math.ceil(need))


def window_bins(bin_s: float) -> int:
    """Base bins per tracking window (WINDOW_S, or one bin when bins are coarser)."""
    return max(1, int(round(max(WINDOW_S, bin_s) / bin_s)))


BIN_SUMS = ["dt", "e_brake", "e_erg", "e_est", "e_mech", "tq_dt", "rpm_dt", "road_m", "vbus_dt", "ocv_dt", "soc_dt", "ibat_dt",
            "bat_v", "bat_v_n", "bat_pct", "bat_pct_n", "bat_i", "hr_dt", "hr_t",
            *[f"mode_dt{m}" for m in (*MODE_NAMES, CADENCE_TARGET)],
            *[f"target_dt{m}" for m in (*MODE_NAMES, CADENCE_TARGET)],
            *[f"sat_dt{m}" for m in (*MODE_NAMES, CADENCE_TARGET)],
            *[f"trk_dt{m}" for m, *_ in TRACKED], *[f"err_dt{m}" for m, *_ in TRACKED],
            *[f"err2_dt{m}" for m, *_ in TRACKED],
            "e_true", "t_true", "t_truth"]     # an emulated drive's truth (_Analyser._truth_block)
BIN_LAST = ["E_mech", "E_bat", "E_res", "E_loss"]
BIN_MAX = ["ipk", "hrmax", *[f"errmax{m}" for m, *_ in TRACKED]]


class Bins:
    """Per-bin accumulators on t = origin_s + k * bin_s: sums, last values and maxima."""

    def __init__(self, origin_s: float, bin_s: float, n_hint: int = 1024):
        self.origin_s, self.bin_s = float(origin_s), float(bin_s)
        n = max(int(n_hint), 16)
        self.a = {k: np.zeros(n) for k in BIN_SUMS}
        self.a.update({k: np.full(n, np.nan) for k in BIN_LAST + BIN_MAX})
        self.used = 0

    def index(self, t) -> np.ndarray:
        b = np.floor((np.asarray(t, dtype=float) - self.origin_s) / self.bin_s)
        b = np.clip(np.nan_to_num(b, nan=0.0), 0, 1e9).astype(np.int64)
        if b.size:
            top = int(b.max()) + 1
            if top > len(self.a["dt"]):
                self._grow(top)
            self.used = max(self.used, top)
        return b

    def _grow(self, need: int) -> None:
        n = max(need, 2 * len(self.a["dt"]))
        for k, v in self.a.items():
            fill = 0.0 if k in BIN_SUMS else np.nan
            self.a[k] = np.concatenate([v, np.full(n - len(v), fill)])

    def add(self, name: str, b: np.ndarray, w) -> None:
        if not b.size:
            return
        lo, hi = int(b.min()), int(b.max())
        self.a[name][lo:hi + 1] += np.bincount(b - lo, weights=np.broadcast_to(w, b.shape), minlength=hi - lo + 1)

    def last(self, name: str, b: np.ndarray, v: np.ndarray) -> None:
        if not b.size:
            return
        ends = np.r_[b[1:] != b[:-1], True]       # b is non-decreasing
        self.a[name][b[ends]] = v[ends]

    def max(self, name: str, b: np.ndarray, v: np.ndarray) -> None:
        if b.size:
            np.fmax.at(self.a[name], b, v)

    def trimmed(self) -> dict:
        return {k: v[:self.used].copy() for k, v in self.a.items()}


class _Progress:
    def __init__(self, total: int, label: str, path):
        self.total, self.label, self.path = total, label, path
        self.on = total > PROGRESS_MIN
        self.step = max(total // 10, 1)
        self.next = self.step

    def __call__(self, n: int) -> None:
        while self.on and n >= self.next:
            pct = min(100, round(100 * self.next / self.total))
            print(f"{self.label}: {self.path}: {pct} % ({n} of {self.total} messages)", file=sys.stderr, flush=True)
            self.next += self.step


class SessionData:
    """Everything the report and the A/B comparison draw on, from one pass over a bag."""

    def __init__(self, path, summary: dict, bins: dict, bin_s: float, origin_s: float, machine: dict,
                 info: dict, scatter: dict, res_commands: dict, commands: np.ndarray, first: dict,
                 shifts: list | None = None, hr_stretches: list | None = None):
        self.path = path
        self.summary = summary
        self.bins = bins
        self.bin_s = bin_s
        self.origin_s = origin_s
        self.machine = machine
        self.info = info
        self.scatter = scatter
        self.res_commands = res_commands
        self.commands = commands          # (n, 3): t_s, mode, command
        self.first = first                # ledger values of the first PlantState
        self.shifts = shifts or []        # slope-mode shifts (t, old gear, new gear, mode): shift_response
        self.hr_stretches = hr_stretches or []    # heart-rate ERG (start t, end t, target bpm): heart_rate_erg

    @property
    def n_bins(self) -> int:
        dt = self.bins["dt"]
        nz = np.flatnonzero(dt > 0)
        return int(nz[-1]) + 1 if nz.size else 0

    @property
    def name(self) -> str:
        return pathlib.Path(str(self.path)).name


class _Analyser:
    def __init__(self, bag, bin_s: float | None, progress_label: str | None):
        self.bag = bag
        counts = bag.message_counts()
        self.topic = {}
        for key in ("plant_state", "controller_status", "command", "battery", "session_status", "session_info",
                    "drive_truth"):
            try:
                self.topic[key] = bag.resolve(key)
            except BagError:
                self.topic[key] = None
        self.use_status = bool(self.topic["controller_status"] and counts.get(self.topic["controller_status"]))
        span = bag.duration_s
        self.bin_s = float(bin_s) if bin_s else auto_bin_s(span)
        self.origin_s = bag.start_ns * 1e-9
        self.bins = Bins(self.origin_s, self.bin_s, int(span / self.bin_s) + 2)
        n_plant = counts.get(self.topic["plant_state"], 0) if self.topic["plant_state"] else 0
        self.stride = max(1, n_plant // SCATTER_POINTS)
        wanted = [t for t in self.topic.values() if t]
        try:                                     # CAN statistics live in the plant's diagnostics
            self.topic_diag = bag.resolve("/diagnostics")
            wanted.append(self.topic_diag)
        except BagError:
            self.topic_diag = None
        self.can: dict = {}
        self.can_errors = 0
        self.wanted = wanted
        self.progress = _Progress(sum(counts.get(t, 0) for t in wanted), progress_label,
                                  bag.path) if progress_label else None
        self.readers = {}
        ts = bag.typestore
        for key, spec in (("plant_state", PLANT_SPEC), ("controller_status", STATUS_SPEC),
                          ("command", COMMAND_SPEC), ("battery", BATTERY_SPEC), ("drive_truth", TRUTH_SPEC)):
            t = self.topic[key]
            if t:
                self.readers[t] = FieldReader(ts, bag.topics[t][0], spec)
        self.plant_rows: list = []
        self.status_rows: list = []
        self.command_rows: list = []
        self.battery_rows: list = []
        self.truth_rows: list = []                # an emulated drive's physics (bike_msgs/DriveTruth)
        self.truth_carry = None
        self.truth_samples = 0
        self.command_blocks: list = []
        self.cadence_blocks: list = []            # (t, the rider's cadence target; 0: none) per Command
        self.hr_target_blocks: list = []          # (t, the heart-rate ERG target; 0: none) per Command
        self.plant_carry = None
        self.status_carry = None
        self.gear_shifts = 0                      # changes of the virtual gear in force
        self.shift_events: list = []              # (t, old gear, new gear, mode) of each
        self.friction_seen: list = []             # (t, B, Tc): the laws' friction, first and each change
        self.gear_first = None
        self.gear_range = (math.inf, -math.inf)
        self.machine = machine_from_info(None)
        self.info: dict = {}
        self.last_status_raw = None
        # exact running totals
        self.n_plant = 0
        self.dups = 0
        self.conflicts = 0
        self.out_of_order = 0
        self.first = None
        self.last = None
        self.e_brake = 0.0
        self.peak = -np.inf
        self.fault_counts = {k: 0 for k in FAULT_BITS}
        self.relay_last = None          # last connected path (RELAY_INVERTER / RELAY_RECTIFIER)
        self.relay_switch_overs = 0
        self.end_of_run = False
        self.n_intervals = 0
        self.sim_time_ran = 0          # 1: an interval with dt > 0 seen, the flywheel term counts after it
        self.scatter = {k: [] for k in ("rpm", "torque", "mode", "command")}
        self.res_commands: dict = {}

    # ---------------------------------------------------------------- reading
    def run(self) -> None:
        tp, tcs, tcmd = self.topic["plant_state"], self.topic["controller_status"], self.topic["command"]
        tbat, tss, tinfo = self.topic["battery"], self.topic["session_status"], self.topic["session_info"]
        ttruth = self.topic["drive_truth"]
        tdiag = self.topic_diag
        rd = self.readers
        n = 0
        prog = self.progress
        next_prog = prog.next if prog and prog.on else None
        topic = None
        t_ns = 0
        try:
            for topic, t_ns, raw in self.bag.messages(self.wanted, raw=True):
                n += 1
                if next_prog is not None and n >= next_prog:
                    prog(n)
                    next_prog = prog.next
                if topic == tp:
                    self.plant_rows.append(rd[tp](raw))
                    if len(self.plant_rows) >= CHUNK:
                        self.flush()
                elif topic == tcs:
                    self.status_rows.append(rd[tcs](raw))
                    if len(self.status_rows) >= 4 * CHUNK:
                        self.flush()
                elif topic == tcmd:
                    self.command_rows.append(rd[tcmd](raw))
                    if len(self.command_rows) >= 4 * CHUNK:
                        self.flush()
                elif topic == tbat:
                    self.battery_rows.append(rd[tbat](raw))
                    if len(self.battery_rows) >= 4 * CHUNK:
                        self.flush()
                elif topic == ttruth:
                    self.truth_rows.append(rd[ttruth](raw))
                    if len(self.truth_rows) >= 4 * CHUNK:
                        self.flush()
                elif topic == tss:
                    self.last_status_raw = raw
                elif topic == tinfo:
                    self._session_info(raw)
                elif topic == tdiag:
                    self._diagnostic(raw)
        except BagError:
            raise
        except Exception as exc:  # noqa: BLE001 - struct.error, rosbags' decoder errors, ...
            raise BagError(f"cannot decode a {topic} message at t = {t_ns * 1e-9:.6f} s: "
                           f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__}", self.bag.path) from None
        self.flush()
        if prog and prog.on and n < prog.total:
            prog.next = prog.total
            prog(prog.total)

    def _session_info(self, raw) -> None:
        if self.info.get("config_text"):
            return                                   # the first complete one wins
        try:
            msg = self.bag.typestore.deserialize_cdr(raw, self.bag.topics[self.topic["session_info"]][0])
            info = json.loads(msg.data)
        except Exception:  # noqa: BLE001 - a broken info message is not fatal for the report
            return
        if isinstance(info, dict) and (not self.info or info.get("config_text")):
            self.info = info
            self.machine = machine_from_info(info)

    def _diagnostic(self, raw) -> None:
        """Keep the newest CAN statistics of the plant (hardware_id bike_plant/can)."""
        try:
            msg = self.bag.typestore.deserialize_cdr(raw, self.bag.topics[self.topic_diag][0])
        except Exception:  # noqa: BLE001 - a broken diagnostic is not fatal for the report
            return
        for status in msg.status:
            if status.hardware_id != "bike_plant/can":
                continue
            self.can = {kv.key[4:]: kv.value for kv in status.values if kv.key.startswith("can_")}
            if int(status.level) >= 2:
                self.can_errors += 1

    # ---------------------------------------------------------------- one block
    def flush(self) -> None:
        bins = self.bins
        if self.command_rows:
            c = np.array(self.command_rows, dtype=float).reshape(-1, len(COMMAND_SPEC))
            self.command_rows.clear()
            block = np.column_stack([c[:, 0] + c[:, 1] * 1e-9, c[:, 2], c[:, 3]])
            self.command_blocks.append(block)
            self.cadence_blocks.append(np.column_stack([block[:, 0], c[:, 5]]))
            # a heart-rate target rules ERG only (bike_msgs/Command), and only in the range the
            # controller takes (it rejects the whole Command otherwise)
            hr = c[:, 6]
            taken = (c[:, 2] == MODE_ERG) & (hr >= HEART_RATE_TARGET_MIN_BPM) & (hr <= HEART_RATE_TARGET_MAX_BPM)
            hr_target = np.where(taken, hr, 0.0)
            self.hr_target_blocks.append(np.column_stack([block[:, 0], hr_target]))
            if not self.use_status:
                self.status_rows.extend((r[0], r[1], r[2], NAN, False, NAN, g, NAN, NAN)
                                        for r, g in zip(block, c[:, 4]))
        if self.battery_rows:
            b = np.array(self.battery_rows, dtype=float).reshape(-1, len(BATTERY_SPEC))
            self.battery_rows.clear()
            bi = bins.index(b[:, 0] + b[:, 1] * 1e-9)
            for col, key in ((2, "bat_v"), (4, "bat_pct")):
                ok = np.isfinite(b[:, col])
                bins.add(key, bi[ok], b[ok, col])
                bins.add(key + "_n", bi[ok], 1.0)
            okc = np.isfinite(b[:, 3])
            bins.add("bat_i", bi[okc], b[okc, 3])
        if self.truth_rows:
            self._truth_block()
        status = self._status_block()
        if not self.plant_rows:
            return
        p = np.array(self.plant_rows, dtype=float).reshape(-1, len(PLANT_SPEC))
        self.plant_rows.clear()
        t = p[:, P_SEC] + p[:, P_NSEC] * 1e-9
        p = np.column_stack([t, p])            # column 0: time; field k at k + 1
        C = 1
        if self.plant_carry is not None:
            p = np.vstack([self.plant_carry, p])
        t, seq = p[:, 0], p[:, C + P_SEQ]
        keep = np.ones(len(p), dtype=bool)
        if len(p) > 1:
            run_max = np.maximum.accumulate(t)[:-1]
            same = (t[1:] == t[:-1]) & (seq[1:] == seq[:-1])
            ooo = t[1:] < run_max
            keep[1:] = ~(same | ooo)
            self.dups += int(np.count_nonzero(same))
            self.out_of_order += int(np.count_nonzero(ooo & ~same))
            if same.any():
                a, b = p[1:][same], p[:-1][same]
                cols = [C + P_EMECH, C + P_TEM, C + P_RPM]
                self.conflicts += int(np.count_nonzero(np.any((a[:, cols] != b[:, cols])
                                                              & ~(np.isnan(a[:, cols]) & np.isnan(b[:, cols])), axis=1)))
        q = p[keep]
        new = q[1:] if self.plant_carry is not None else q
        self.plant_carry = q[-1:].copy()
        if self.first is None and len(new):
            self.first = new[0].copy()
            # the first sample's peak in the bin of its stamp; later ones with their batch
            self.bins.max("ipk", self.bins.index(new[:1, 0]), np.maximum(new[:1, C + P_IPH], new[:1, C + P_ISMP]))
        if len(new):
            self._rows(new)
        if len(q) > 1:
            self._intervals(q, status)

    def _truth_block(self) -> None:
        """An emulated drive's truth (DriveTruth, stamped with the plant's /clock as the emulator
        heard it) onto the plant's time line: between two samples, the rider's mean power over
        the emulator's physics time (its own clock, which runs on while the plant's sim time
        stands still) counts for the sim time between their stamps (``e_true`` / ``t_true``). A
        stretch in which sim time stood still (drive not armed: the emulator hears no /clock) is
        left out, as in the plant's ledger: the physics ran TRUTH_PAUSE_S longer than sim time
        between the two (also a stall of the machine: 0.26 s of physics in 10 ms of sim time once
        in a 60 s ride here); it still counts as covered (``t_truth``), the truth was there. A
        sim time that runs slower or faster than the physics (a loaded plant: 1.4 % slower in a
        15 s ride here) changes no power. Samples out of order (a restarted emulator) are skipped."""
        r = np.array(self.truth_rows, dtype=float).reshape(-1, len(TRUTH_SPEC))
        self.truth_rows.clear()
        self.truth_samples += len(r)
        r = np.column_stack([r[:, 0] + r[:, 1] * 1e-9, r[:, 2], r[:, 3]])     # stamp, physics time, energy
        if self.truth_carry is not None:
            r = np.vstack([self.truth_carry, r])
        self.truth_carry = r[-1:].copy()
        if len(r) < 2:
            return
        d_stamp, d_phys, d_energy = np.diff(r[:, 0]), np.diff(r[:, 1]), np.diff(r[:, 2])
        ordered = (d_stamp > 0) & (d_phys > 0) & np.isfinite(d_energy)
        if not ordered.any():
            return
        b = self.bins.index(0.5 * (r[:-1, 0] + r[1:, 0])[ordered])
        self.bins.add("t_truth", b, d_stamp[ordered])
        ran = (d_phys - d_stamp < TRUTH_PAUSE_S)[ordered]
        self.bins.add("e_true", b[ran], (d_energy / d_phys * d_stamp)[ordered][ran])
        self.bins.add("t_true", b[ran], d_stamp[ordered][ran])

    def _status_block(self) -> np.ndarray:
        """Statuses (t, mode, command, target, saturated, virtual speed, virtual gear: 0 or NaN
        for the config's) read so far, the carried one first; counts the gear shifts."""
        if self.status_rows:
            s = np.array(self.status_rows, dtype=float).reshape(
                -1, STATUS_COLUMNS if not self.use_status else len(STATUS_SPEC))
            self.status_rows.clear()
            if self.use_status:
                s = np.column_stack([s[:, 0] + s[:, 1] * 1e-9, s[:, 2:10]])
            if self.status_carry is not None:
                s = np.vstack([self.status_carry, s])
            s = s[np.argsort(s[:, 0], kind="stable")]
            gear = np.where(np.isfinite(s[:, 6]) & (s[:, 6] > 0), s[:, 6], self.machine["virtual_gear_ratio"])
            changed = np.nonzero(np.diff(gear))[0]
            self.gear_shifts += int(changed.size)
            self.shift_events += [(float(s[i + 1, 0]), float(gear[i]), float(gear[i + 1]), int(s[i + 1, 1]))
                                  for i in changed]
            if self.status_carry is None:
                self.gear_first = float(gear[0])
            self.gear_range = (min(self.gear_range[0], float(gear.min())), max(self.gear_range[1], float(gear.max())))
            self._friction_changes(s)
            self.status_carry = s[-1:].copy()
            return s
        return self.status_carry if self.status_carry is not None else np.zeros((0, STATUS_COLUMNS))

    def _cadence_targets(self, t0: np.ndarray) -> np.ndarray:
        """The rider's cadence target in force at each t0 (the latest Command stamped <= t0; 0:
        none, or no Command yet). Commands are stamped ahead of the batches they rule."""
        if len(self.cadence_blocks) > 1:
            self.cadence_blocks = [np.vstack(self.cadence_blocks)]
        if not self.cadence_blocks or not len(self.cadence_blocks[0]):
            return np.zeros(len(t0))
        c = self.cadence_blocks[0]
        if np.any(np.diff(c[:, 0]) < 0):
            c = self.cadence_blocks[0] = c[np.argsort(c[:, 0], kind="stable")]
        idx = np.searchsorted(c[:, 0], t0, side="right") - 1
        return np.where(idx >= 0, c[np.maximum(idx, 0), 1], 0.0)

    def _friction_changes(self, s: np.ndarray) -> None:
        """The laws' friction (B, Tc) as the statuses give it: its first value and each change
        (a spin-down), as (t, B, Tc). Statuses of older bags have none."""
        f = s[np.isfinite(s[:, 7]) & np.isfinite(s[:, 8])][:, [0, 7, 8]]
        if not len(f):
            return
        # vectorised: a status per batch (3.6 M in an hour's bag), a change once in a while
        change = np.ones(len(f), dtype=bool)
        change[1:] = (f[1:, 1] != f[:-1, 1]) | (f[1:, 2] != f[:-1, 2])
        if self.friction_seen:
            change[0] = (float(f[0, 1]), float(f[0, 2])) != self.friction_seen[-1][1:]
        self.friction_seen.extend((float(t), float(b), float(tc)) for t, b, tc in f[change])

    def _rows(self, r: np.ndarray) -> None:
        C = 1
        self.n_plant += len(r)
        self.last = r[-1].copy()
        peak = np.maximum(r[:, C + P_IPH], r[:, C + P_ISMP])
        self.peak = max(self.peak, float(np.max(peak)))
        faults = r[:, C + P_FAULTS].astype(np.int64)
        for name, bit in FAULT_BITS.items():
            self.fault_counts[name] += int(np.count_nonzero(faults & bit))
        # SPMSM: path changes, the break-before-make interval (RELAY_SWITCHING) in between skipped
        rel = r[:, C + P_RELAY]
        conn = rel[np.isin(rel, RELAY_PATHS)]
        if len(conn):
            if self.relay_last is not None:
                conn = np.concatenate([[self.relay_last], conn])
            self.relay_switch_overs += int(np.count_nonzero(conn[1:] != conn[:-1]))
            self.relay_last = float(conn[-1])
        self.end_of_run |= bool(np.any(r[:, C + P_EOR]))

    def _intervals(self, q: np.ndarray, status: np.ndarray) -> None:
        C = 1
        mc = self.machine
        bins = self.bins
        t0, t1 = q[:-1, 0], q[1:, 0]
        dt = t1 - t0
        w_mid = 0.5 * (q[:-1, C + P_W] + q[1:, C + P_W])
        rpm_mid = 0.5 * (q[:-1, C + P_RPM] + q[1:, C + P_RPM])
        t_brake = -q[1:, C + P_TEM]
        p_brake = t_brake * w_mid
        self.e_brake += float(np.sum(p_brake * dt))
        b = bins.index(0.5 * (t0 + t1))
        bins.add("dt", b, dt)
        bins.add("e_brake", b, p_brake * dt)
        bins.add("e_mech", b, q[1:, C + P_EMECH] - q[:-1, C + P_EMECH])
        bins.add("tq_dt", b, t_brake * dt)
        bins.add("rpm_dt", b, rpm_mid * dt)
        for col, key in ((P_VBUS, "vbus_dt"), (P_OCV, "ocv_dt"), (P_SOC, "soc_dt"), (P_IBAT, "ibat_dt")):
            bins.add(key, b, 0.5 * (q[:-1, C + col] + q[1:, C + col]) * dt)
        for col, key in ((P_EMECH, "E_mech"), (P_EBAT, "E_bat"), (P_ERES, "E_res"), (P_ELOSS, "E_loss")):
            bins.last(key, b, q[1:, C + col])
        # currents of a PlantState are measured during the batch that ends at its stamp
        bins.max("ipk", b, np.maximum(q[1:, C + P_IPH], q[1:, C + P_ISMP]))
        # the rider's heart rate where both ends have one (0: none; NaN compares False)
        hr0, hr1 = q[:-1, C + P_HR], q[1:, C + P_HR]
        has_hr = (hr0 > 0) & (hr1 > 0) & np.isfinite(hr0) & np.isfinite(hr1)
        if has_hr.any():
            bins.add("hr_dt", b[has_hr], 0.5 * (hr0 + hr1)[has_hr] * dt[has_hr])
            bins.add("hr_t", b[has_hr], dt[has_hr])
            bins.max("hrmax", b[has_hr], np.maximum(hr0, hr1)[has_hr])
        # the mode in force: latest status stamped <= t_{i-1}
        if len(status):
            idx = np.searchsorted(status[:, 0], t0, side="right") - 1
            has = idx >= 0
            idx = np.maximum(idx, 0)
            mode = np.where(has, status[idx, 1], -1).astype(np.int64)
            command = np.where(has, status[idx, 2], np.nan)
            target = np.where(has, status[idx, 3], np.nan)
            sat = np.where(has, status[idx, 4], 0.0) > 0
            virtual_mps = np.where(has, status[idx, 5], np.nan)
            gear = np.where(has, status[idx, 6], np.nan)
            b_nms = np.where(has, status[idx, 7], np.nan)
            dry_nm = np.where(has, status[idx, 8], np.nan)
        else:
            mode = np.full(len(dt), -1, dtype=np.int64)
            command = target = virtual_mps = gear = b_nms = dry_nm = np.full(len(dt), np.nan)
            sat = np.zeros(len(dt), dtype=bool)
        # ERG holds the rider's power: the brake's plus the bike's friction as the laws had it
        # (the statuses' figures, which a spin-down changes; the config's for older bags)
        cfg_b, cfg_dry, ws_rpm = mc["friction"]
        friction = (np.where(np.isfinite(b_nms), b_nms, cfg_b), np.where(np.isfinite(dry_nm), dry_nm, cfg_dry), ws_rpm)
        p_erg = erg_power_w(-t_brake, w_mid, friction)
        bins.add("e_erg", b, p_erg * dt)
        # the trainer's estimate of the rider's power adds the flywheel's energy change (inertia
        # compensated, as direct-drive trainers report it), from where the ledger starts. A drive's
        # (bike_plant.can.backend) starts at the speed of its first batch in which sim time runs:
        # before it, the drive may not be heard yet (PlantStates with speed 0, its first speed at
        # t = 0 or within that batch), which is no change of the flywheel's energy (it made the
        # first 10 s window of a CAN ride read ~+7 %). The simulated plant's starts at t = 0.
        w0, w1 = q[:-1, C + P_W], q[1:, C + P_W]
        ran = self.sim_time_ran + np.cumsum(dt > 0)
        self.sim_time_ran = int(ran[-1] > 0)
        drive = q[1:, C + P_DRIVE] > 0
        running = np.where(drive, (ran - (dt > 0)) > 0, True)
        flywheel_j = np.where(running, 0.5 * mc["inertia_kgm2"] * (w1 * w1 - w0 * w0), 0.0)
        bins.add("e_est", b, p_erg * dt + flywheel_j)
        # the road speed: the controller's virtual speed (in slope mode the virtual bike's, which
        # a shift does not change while the brake takes the flywheel to the new gear), else the
        # flywheel's through the gear in force (0 / NaN: the config's; an older bag has none)
        gear = np.where(np.isfinite(gear) & (gear > 0), gear, mc["virtual_gear_ratio"])
        mps_per_rad_s = mc["wheel_radius_m"] * gear / mc["gear_ratio"]
        road_mps = np.where(np.isfinite(virtual_mps), np.abs(virtual_mps),
                            np.abs(rpm_mid) / RPM_PER_RAD_S * mps_per_rad_s)
        bins.add("road_m", b, road_mps * dt)
        missing = ~np.isfinite(target)
        if missing.any():
            target = np.where(missing, target_from_command(mode, command, mc), target)
        cadence_mid = rpm_mid / mc["gear_ratio"]
        cad_target = self._cadence_targets(t0)
        has_cad = cad_target > 0
        if has_cad.any():
            bins.add(f"mode_dt{CADENCE_TARGET}", b[has_cad], dt[has_cad])
            bins.add(f"target_dt{CADENCE_TARGET}", b[has_cad], cad_target[has_cad] * dt[has_cad])
        for m in MODE_NAMES:
            sel = mode == m
            if not sel.any():
                continue
            bins.add(f"mode_dt{m}", b[sel], dt[sel])
            bins.add(f"target_dt{m}", b[sel], target[sel] * dt[sel])
            if sat[sel].any():
                s2 = sel & sat
                bins.add(f"sat_dt{m}", b[s2], dt[s2])
        for m, *_ in TRACKED:
            sel = has_cad if m == CADENCE_TARGET else (mode == m) & np.isfinite(target)
            if m == MODE_SLOPE:
                sel &= np.isfinite(virtual_mps)
            if not sel.any():
                continue
            if m == MODE_SLOPE:
                err = rpm_mid[sel] / RPM_PER_RAD_S * mps_per_rad_s[sel] - virtual_mps[sel]
            elif m == MODE_ERG:
                err = p_erg[sel] - target[sel]
            elif m == MODE_ISOKINETIC:
                err = cadence_mid[sel] - target[sel]
            elif m == CADENCE_TARGET:
                err = cadence_mid[sel] - cad_target[sel]
            else:
                err = t_brake[sel] - resistance_torque_nm(command[sel], rpm_mid[sel], mc)
                cmds, inv = np.unique(np.round(command[sel], 4), return_inverse=True)
                wsum = np.bincount(inv, weights=dt[sel])
                for c, w in zip(cmds.tolist(), wsum.tolist()):
                    self.res_commands[c] = self.res_commands.get(c, 0.0) + w
            bins.add(f"trk_dt{m}", b[sel], dt[sel])
            bins.add(f"err_dt{m}", b[sel], err * dt[sel])
            bins.add(f"err2_dt{m}", b[sel], err * err * dt[sel])
            bins.max(f"errmax{m}", b[sel], np.abs(err))
        # thinned sample for the torque-speed scatter
        k = (self.n_intervals + np.arange(len(dt))) % self.stride == 0
        self.n_intervals += len(dt)
        for key, v in (("rpm", rpm_mid), ("torque", t_brake), ("mode", mode), ("command", command)):
            self.scatter[key].append(v[k])

    # ---------------------------------------------------------------- result
    def result(self, bag_path, counts: dict, bag_duration: float) -> SessionData:
        C = 1
        last_status = None
        if self.last_status_raw is not None:
            try:
                last_status = self.bag.typestore.deserialize_cdr(self.last_status_raw,
                                                                 self.bag.topics[self.topic["session_status"]][0])
            except Exception:  # noqa: BLE001
                last_status = None
        mc = self.machine
        info = self.info
        out: dict = {
            "bag": str(bag_path),
            "messages": dict(sorted(counts.items())),
            "plant_states": int(self.n_plant),
            "duration_s": bag_duration,
            "mean_braking_power_w": None,
            "mean_rider_power_w": None,
            "energy_mech_in_j": None,
            "energy_battery_j": None,
            "energy_battery_wh": None,
            "energy_resistor_j": None,
            "energy_resistor_wh": None,
            "energy_loss_j": None,
            "peak_phase_current_a": None,
            "interlock_blanked": None,
            "timeouts": None,
            "fault_batches": None,
            "end_of_run": False,
            "final_soc": None,
            "session_state": (SESSION_STATES.get(last_status.state, str(last_status.state))
                              if last_status is not None else None),
            "profile_name": (last_status.profile_name if last_status is not None else info.get("profile_name")),
            "software_version": info.get("software_version"),
            "config_path": info.get("config_path"),
            "machine": {k: mc[k] for k in ("gear_ratio", "tmax_nm", "base_speed_rpm", "pmax_w")}
            | {"source": mc["source"], "kind": mc["kind"]},
            "relay_switch_overs": None,
            "plant_state_duplicates": int(self.dups),
            "plant_state_conflicts": int(self.conflicts),
            "plant_state_out_of_order": int(self.out_of_order),
            "mean_cadence_rpm": None,
            "mean_heart_rate_bpm": None,
            "max_heart_rate_bpm": None,
            "time_in_mode_s": {},
            "tracking": {},
            "warnings": list(mc["notes"]),
        }
        if self.can:
            out["can"] = dict(self.can, error_diagnostics=self.can_errors)
        if self.conflicts:
            out["warnings"].append(f"{self.conflicts} PlantStates share stamp and seq with a different one: "
                                   "the bag holds more than one plant (two runs in one ROS domain?)")
        if self.out_of_order:
            out["warnings"].append(f"{self.out_of_order} PlantStates out of time order were skipped")
        bins = self.bins.trimmed()
        if self.n_plant:
            first, last = self.first, self.last
            duration = float(last[0] - first[0])
            out["duration_s"] = duration
            if self.n_plant > 1 and duration > 0:
                out["mean_braking_power_w"] = float(self.e_brake / duration)
                out["mean_rider_power_w"] = float((last[C + P_EMECH] - first[C + P_EMECH]) / duration)
            for key, col in (("energy_mech_in_j", P_EMECH), ("energy_battery_j", P_EBAT),
                             ("energy_resistor_j", P_ERES), ("energy_loss_j", P_ELOSS)):
                out[key] = float(last[C + col] - first[C + col])
            out["energy_battery_wh"] = out["energy_battery_j"] / 3600.0
            out["energy_resistor_wh"] = out["energy_resistor_j"] / 3600.0
            out["peak_phase_current_a"] = float(self.peak)
            out["interlock_blanked"] = int(last[C + P_ILOCK])
            out["fault_batches"] = dict(self.fault_counts)
            out["relay_switch_overs"] = int(self.relay_switch_overs)
            out["timeouts"] = self.fault_counts["command_timeout"]
            out["end_of_run"] = bool(self.end_of_run)
            # a drive on CAN has no battery model (NaN): n/a, and no bare NaN in the JSON
            soc = float(last[C + P_SOC])
            out["final_soc"] = soc if math.isfinite(soc) else None
            dtot = float(bins["dt"].sum())
            if dtot > 0:
                out["mean_cadence_rpm"] = float(bins["rpm_dt"].sum() / dtot / mc["gear_ratio"])
            out["time_in_mode_s"] = {MODE_NAMES[m]: float(bins[f"mode_dt{m}"].sum()) for m in MODE_NAMES
                                     if bins[f"mode_dt{m}"].sum() > 0}
            out["distance_m"] = float(bins["road_m"].sum())
            if self.gear_first is not None:
                out["virtual_gear"] = {"first": self.gear_first, "shifts": self.gear_shifts,
                                       "min": self.gear_range[0], "max": self.gear_range[1]}
            out["tracking"] = tracking(bins, self.bin_s)
            out["erg_response"] = erg_response(bins, self.bin_s)
            out["shift_response"] = shift_response(bins, self.origin_s, self.bin_s, self.slope_shifts())
            out["power_accuracy"] = power_accuracy(bins, self.bin_s)
            if out["power_accuracy"] and self.can:
                # a drive on CAN: the ledger is the host's, from the drive's own estimates (backend docs)
                out["power_accuracy"]["ledger_from_drive"] = True
            if out["power_accuracy"] and self.truth_samples:
                out["power_accuracy"]["truth_samples"] = int(self.truth_samples)
            out["mean_heart_rate_bpm"], out["max_heart_rate_bpm"] = heart_rate_figures(bins)
            out["heart_rate_erg"] = heart_rate_erg(bins, self.origin_s, self.bin_s, self.hr_stretches())
            if self.friction_seen:
                out["friction"] = [{"t": t, "friction_nms": b, "dry_friction_nm": tc} for t, b, tc in self.friction_seen]
        first = {}
        if self.first is not None:
            first = {"t": float(self.first[0]), "E_mech": float(self.first[C + P_EMECH]),
                     "E_bat": float(self.first[C + P_EBAT]), "E_res": float(self.first[C + P_ERES]),
                     "E_loss": float(self.first[C + P_ELOSS])}
        scatter = {k: (np.concatenate(v) if v else np.zeros(0)) for k, v in self.scatter.items()}
        scatter["stride"] = int(self.stride)
        commands = np.vstack(self.command_blocks) if self.command_blocks else np.zeros((0, 3))
        return SessionData(bag_path, out, bins, self.bin_s, self.origin_s, mc, info, scatter,
                           dict(sorted(self.res_commands.items())), commands, first, self.slope_shifts(),
                           self.hr_stretches())

    def slope_shifts(self) -> list:
        return [e for e in self.shift_events if e[3] == MODE_SLOPE]

    def hr_stretches(self) -> list:
        """Heart-rate ERG stretches (start t, end t, target bpm): consecutive Commands with the
        same target > 0; the end is the next Command's stamp (inf: the end of the ride)."""
        if not self.hr_target_blocks:
            return []
        c = np.vstack(self.hr_target_blocks)
        c = c[np.argsort(c[:, 0], kind="stable")]
        starts = np.flatnonzero(np.r_[True, c[1:, 1] != c[:-1, 1]])
        ends = [float(c[i, 0]) for i in starts[1:]] + [math.inf]
        return [(float(c[i, 0]), end, float(c[i, 1])) for i, end in zip(starts, ends) if c[i, 1] > 0]


def analyse(bag_path, bin_s: float | None = None, progress: str | None = None) -> SessionData:
    """One pass over the bag (see the module docstring). ``progress``: label of the progress
    lines on stderr (None: quiet). Raises BagError."""
    with open_bag(bag_path) as bag:
        counts = bag.message_counts()
        an = _Analyser(bag, bin_s, progress)
        an.run()
        return an.result(bag_path, counts, bag.duration_s)


def summarise(bag_path) -> dict:
    """Numbers of one recorded session (see the module docstring). Raises BagError."""
    return analyse(bag_path).summary


# ============================================================================ derived series

def _rebin(a: np.ndarray, k: int, how: str) -> np.ndarray:
    if k <= 1:
        return a.copy()
    n = len(a)
    pad = (-n) % k
    fill = 0.0 if how == "sum" else np.nan
    x = np.concatenate([a, np.full(pad, fill)]).reshape(-1, k)
    if how == "sum":
        return x.sum(axis=1)
    if how == "max":
        with np.errstate(all="ignore"):
            ok = np.isfinite(x).any(axis=1)
            return np.where(ok, np.nanmax(np.where(np.isfinite(x), x, -np.inf), axis=1), np.nan)
    # last finite value of each group
    ok = np.isfinite(x)
    idx = np.where(ok.any(axis=1), k - 1 - np.argmax(ok[:, ::-1], axis=1), 0)
    vals = x[np.arange(len(x)), idx]
    return np.where(ok.any(axis=1), vals, np.nan)


def _div(a, b):
    with np.errstate(all="ignore"):
        return np.where(b > 0, a / np.where(b > 0, b, 1.0), np.nan)


def _ffill(a: np.ndarray) -> np.ndarray:
    ok = np.isfinite(a)
    if not ok.any():
        return a
    idx = np.where(ok, np.arange(len(a)), 0)
    np.maximum.accumulate(idx, out=idx)
    out = a[idx]
    out[: int(np.argmax(ok))] = np.nan
    return out


def series(data: SessionData, n_bins: int | None = None, points: int | None = PLOT_POINTS,
           merge: int | None = None) -> dict:
    """Time series (bin means) of one session on bins 0..n_bins-1, ``merge`` bins per point
    (default: enough for at most ``points`` points). ``t`` = time since the start of the
    recording [s]."""
    n = data.n_bins if n_bins is None else int(n_bins)
    raw = {k: v[:n] for k, v in data.bins.items()}
    k = merge or (max(1, math.ceil(n / points)) if points else 1)
    b = {}
    for key, v in raw.items():
        how = "sum" if key in BIN_SUMS else ("max" if key in BIN_MAX else "last")
        b[key] = _rebin(v, k, how)
    width = data.bin_s * k
    mc = data.machine
    dt = b["dt"]
    out = {"t": (np.arange(len(dt)) + 0.5) * width, "bin_s": width,
           "p_brake": _div(b["e_brake"], dt), "p_rider": _div(b["e_mech"], dt),
           "torque": _div(b["tq_dt"], dt), "motor_rpm": _div(b["rpm_dt"], dt), "road_mps": _div(b["road_m"], dt),
           "vbus": _div(b["vbus_dt"], dt), "ocv": _div(b["ocv_dt"], dt), "soc": _div(b["soc_dt"], dt),
           "ibat": _div(b["ibat_dt"], dt),
           "bat_v": _div(b["bat_v"], b["bat_v_n"]), "bat_pct": _div(b["bat_pct"], b["bat_pct_n"]),
           "ipk": b["ipk"], "heart_rate": _div(b["hr_dt"], b["hr_t"])}
    out["cadence"] = out["motor_rpm"] / mc["gear_ratio"]
    full = lambda m: (b[f"mode_dt{m}"] > 0) & (b[f"mode_dt{m}"] >= dt * (1 - 1e-9))  # noqa: E731
    any_ = lambda m: b[f"mode_dt{m}"] > 0                                            # noqa: E731
    out["erg_target"] = np.where(any_(MODE_ERG), _div(b[f"target_dt{MODE_ERG}"], b[f"mode_dt{MODE_ERG}"]), np.nan)
    out["iso_target"] = np.where(any_(MODE_ISOKINETIC), _div(b[f"target_dt{MODE_ISOKINETIC}"],
                                                            b[f"mode_dt{MODE_ISOKINETIC}"]), np.nan)
    out["in_erg"] = full(MODE_ERG)
    first = data.first
    for key in ("E_mech", "E_bat", "E_res", "E_loss"):
        out[key] = _ffill(b[key]) - first.get(key, np.nan) if first else np.full(len(dt), np.nan)
    return out


def tracking(bins: dict, bin_s: float, n_bins: int | None = None) -> dict:
    """Tracking error per mode (see the module docstring) on bins 0..n_bins-1."""
    n = len(bins["dt"]) if n_bins is None else int(n_bins)
    k = window_bins(bin_s)
    dt = _rebin(bins["dt"][:n], k, "sum")
    out = {}
    for m, key, unit, what in TRACKED:
        t_in = float(bins[f"mode_dt{m}"][:n].sum())
        trk_raw = bins[f"trk_dt{m}"][:n]          # time in the mode with something to compare
        t_trk = float(trk_raw.sum())
        if not (t_in > 0 and t_trk > 0):
            continue
        mdt = _rebin(trk_raw, k, "sum")
        err = _rebin(bins[f"err_dt{m}"][:n], k, "sum")
        full = (mdt > 0) & (mdt >= dt * (1 - 1e-9))
        e_w = err[full] / mdt[full]
        err2 = float(bins[f"err2_dt{m}"][:n].sum())
        emax = bins[f"errmax{m}"][:n]
        r = {
            "unit": unit,
            "compares": what,
            "time_s": t_in,
            "window_s": bin_s * k,
            "windows": int(full.sum()),
            "rms": float(np.sqrt(np.mean(e_w ** 2))) if e_w.size else None,
            "max_abs": float(np.max(np.abs(e_w))) if e_w.size else None,
            "mean": float(np.mean(e_w)) if e_w.size else None,
            "rms_batch": float(math.sqrt(max(err2, 0.0) / t_trk)),
            "max_abs_batch": float(np.nanmax(emax)) if np.isfinite(emax).any() else None,
            "mean_target": float(bins[f"target_dt{m}"][:n].sum() / t_in),
            "saturated_fraction": float(bins[f"sat_dt{m}"][:n].sum() / t_in),
        }
        out[key] = r
    return out


ERG_STEP_W = 10.0             # a target change larger than this (and ERG_TOL of it) between windows is a step
ERG_TOL = 0.05                # settled: ERG power within this fraction of the target ...
ERG_TOL_MIN_W = 5.0           # ... or of this many watts, whichever is larger
ERG_HOLD_S = 1.0              # ... for this long


ACCURACY_WINDOW_S = 10.0      # power accuracy: windows long enough that the flywheel's energy swings average out
ACCURACY_MIN_W = 20.0         # ... in which the rider pedals
TRUTH_COVERAGE = 0.98         # ... and, against a drive's truth (DriveTruth), that covers this much of the window
# between two truth samples the physics ran this much longer than sim time: the plant paused (a drive
# lost or not armed: its ledger stood still too; the heartbeat timeout alone is 0.3 s), not jitter
TRUTH_PAUSE_S = 0.1


def power_accuracy(bins: dict, bin_s: float, n_bins: int | None = None) -> dict | None:
    """How well the trainer knows the rider's power: its estimate, braking power + the bike's
    friction as the laws model it + the flywheel's energy change (1/2 J w^2 with the config's J,
    inertia compensated as a direct-drive trainer reports it), against the rider's
    own from the plant's ledger, over ACCURACY_WINDOW_S windows in which the rider gave more
    than ACCURACY_MIN_W. A friction figure that is off (before a spin-down) shows here; trainers
    state +-1..2 %. None without such a window.

    With an emulated drive's truth in the bag (``e_true`` / ``t_true``, :meth:`_Analyser._truth_block`)
    the figures are against the rider's true power instead, in those of the windows that the
    truth covers, each from its first to its last truth (at least half of the window, TRUTH_COVERAGE
    of that span covered): ``against`` "drive_truth" (else "ledger"), ``true_rider_power_w``,
    ``ledger`` (the estimate against the ledger over the same spans), ``ledger_error_pct`` (the
    ledger's own error against the truth: on CAN the drive's kt Iq), ``compared_s`` (the spans' sim
    time), ``windows_without_truth``."""
    n = len(bins["dt"]) if n_bins is None else int(n_bins)
    k = max(1, int(round(ACCURACY_WINDOW_S / bin_s)))
    dt = _rebin(bins["dt"][:n], k, "sum")
    full = dt >= 0.999 * k * bin_s
    est = _div(_rebin(bins["e_est"][:n], k, "sum"), dt)
    rider = _div(_rebin(bins["e_mech"][:n], k, "sum"), dt)
    sel = full & np.isfinite(est) & np.isfinite(rider) & (rider > ACCURACY_MIN_W)
    if not sel.any():
        return None

    def figures(estimate: np.ndarray, against: np.ndarray, where: np.ndarray) -> dict:
        err = estimate[where] - against[where]
        return {"windows": int(where.sum()), "window_s": k * bin_s, "mean_w": float(err.mean()),
                "rms_w": float(np.sqrt(np.mean(err ** 2))), "max_abs_w": float(np.abs(err).max()),
                "mean_pct": float(100.0 * err.mean() / against[where].mean())}

    out = figures(est, rider, sel) | {"against": "ledger"}
    t_truth = bins["t_truth"][:n] if "t_truth" in bins else np.zeros(n)
    if not t_truth.sum() > 0:
        return out
    # each window from its first to its last base bin with the truth (the emulator's first sample
    # comes when it first hears the plant's /clock: 0.3 s into a ride here), if that is half of it
    # and the truth covers it; the estimate and the ledger over the same span
    est_t, rider_t, true_t, span_t = (np.full(len(dt), np.nan) for _ in range(4))
    for j in np.flatnonzero(sel):
        has = np.flatnonzero(t_truth[j * k:(j + 1) * k] > 0)
        if not has.size:
            continue
        lo, hi = j * k + has[0], j * k + has[-1] + 1
        span = bins["dt"][lo:hi].sum()
        if (span >= 0.5 * k * bin_s and t_truth[lo:hi].sum() >= TRUTH_COVERAGE * span
                and bins["t_true"][lo:hi].sum() > 0):
            span_t[j] = span
            est_t[j] = bins["e_est"][lo:hi].sum() / span
            rider_t[j] = bins["e_mech"][lo:hi].sum() / span
            true_t[j] = bins["e_true"][lo:hi].sum() / bins["t_true"][lo:hi].sum()
    covered = sel & np.isfinite(true_t)
    out["windows_without_truth"] = without = int(sel.sum() - covered.sum())
    if covered.any():
        out = figures(est_t, true_t, covered) | {
            "against": "drive_truth", "windows_without_truth": without,
            "true_rider_power_w": float(true_t[covered].mean()), "ledger": figures(est_t, rider_t, covered),
            "ledger_error_pct": float(100.0 * (rider_t[covered] - true_t[covered]).mean() / true_t[covered].mean()),
            "compared_s": float(np.nansum(np.where(covered, span_t, np.nan)))}
    return out


def erg_response(bins: dict, bin_s: float, n_bins: int | None = None) -> dict | None:
    """How fast ERG reaches a new power target (the figure trainer reviews quote: high-end
    trainers 3-5 s). On ``window_s`` windows wholly in ERG: a step is a target change of more
    than ERG_STEP_W and ERG_TOL; it settles at the first window from which the ERG power
    (braking + the bike's friction, the rider's power that ERG holds)
    stays within max(ERG_TOL x target, ERG_TOL_MIN_W) for ERG_HOLD_S, before the next step
    or the end of ERG. ``settle_s`` per step from the first window at the new target (None:
    not settled). None when the session has no step."""
    n = len(bins["dt"]) if n_bins is None else int(n_bins)
    k = window_bins(bin_s)
    width = bin_s * k
    dt = _rebin(bins["dt"][:n], k, "sum")
    mdt = _rebin(bins[f"mode_dt{MODE_ERG}"][:n], k, "sum")
    full = (mdt > 0) & (mdt >= dt * (1 - 1e-9))
    target = _div(_rebin(bins[f"target_dt{MODE_ERG}"][:n], k, "sum"), mdt)
    power = _div(_rebin(bins["e_erg"][:n], k, "sum"), dt)
    hold = max(1, int(round(ERG_HOLD_S / width)))
    steps = [i for i in range(1, len(dt)) if full[i] and full[i - 1]
             and abs(target[i] - target[i - 1]) > max(ERG_STEP_W, ERG_TOL * abs(target[i - 1]))]
    if not steps:
        return None
    settle: list[float | None] = []
    starts = set(steps)
    for i in steps:
        end = i
        while end < len(dt) and full[end] and (end == i or end not in starts):
            end += 1
        ok = np.abs(power[i:end] - target[i:end]) <= np.maximum(ERG_TOL * np.abs(target[i:end]), ERG_TOL_MIN_W)
        # the first window from which `hold` windows in a row are within the band
        run = np.convolve(ok.astype(int), np.ones(hold, dtype=int), "valid") == hold if ok.size >= hold else []
        first = int(np.argmax(run)) if np.any(run) else None
        settle.append(None if first is None else first * width)
    done = [x for x in settle if x is not None]
    return {"steps": len(steps), "settled": len(done), "settle_s": settle, "window_s": width,
            "median_s": float(np.median(done)) if done else None, "max_s": float(max(done)) if done else None,
            "tolerance": f"max({100 * ERG_TOL:g} % of the target, {ERG_TOL_MIN_W:g} W) for {ERG_HOLD_S:g} s"}


SHIFT_TOL = 0.05              # a shift is felt: the flywheel within this fraction of the gear change ...
SHIFT_TOL_MIN_MPS = 0.02      # ... or of this road speed, whichever is larger
SHIFT_BEFORE_S = 0.2          # the road speed before a shift: its mean over this long
SHIFT_WITHIN_S = 3.0          # ... and it must be felt within this long
SHIFT_OVERSHOOT_S = 1.0       # how far the flywheel went past the new gear's speed, over this long


def shift_response(bins: dict, origin_s: float, bin_s: float, shifts: list, n_bins: int | None = None) -> dict | None:
    """How fast a virtual shift reaches the cranks (trainer users: resistance changing up to
    ~20 s late, shifts that bounce; research notes section 5). ``shifts``: (t, old gear, new
    gear, mode). A shift keeps the virtual bike's road speed v, and the flywheel, still turning
    at the old gear's speed, reads v x new / old in the new gear: the slope tracking error
    (``slope_speed``: the flywheel's road speed - the virtual bike's) jumps by
    v (new / old - 1), as a chain's cadence would jump the other way. ``settle_s`` per shift: the
    time until that error is first within max(SHIFT_TOL of the jump, SHIFT_TOL_MIN_MPS) (None:
    not within SHIFT_WITHIN_S); ``overshoot_pct``: how far it went past zero, away from the
    jump, within SHIFT_OVERSHOOT_S, in % of the jump. The rider's own answer to the new gear
    (he pedals on at his effort) is not in it. None without a shift (in bins 0..``n_bins`` - 1)."""
    n = len(bins["dt"]) if n_bins is None else int(n_bins)
    shifts = [e for e in shifts if e[0] < origin_s + n * bin_s]
    if not shifts:
        return None
    dt = bins["dt"][:n]
    t = origin_s + (np.arange(n) + 0.5) * bin_s
    road = _div(bins["road_m"][:n], dt)
    err = _div(bins[f"err_dt{MODE_SLOPE}"][:n], bins[f"trk_dt{MODE_SLOPE}"][:n])
    settle: list[float | None] = []
    overshoot: list[float] = []
    for t_s, g_old, g_new, _mode in shifts:
        before = np.isfinite(road) & (t >= t_s - SHIFT_BEFORE_S) & (t < t_s)
        after = np.isfinite(err) & (t > t_s) & (t < t_s + SHIFT_WITHIN_S)
        if not before.any() or not after.any():
            settle.append(None)
            continue
        jump = float(road[before].mean()) * (g_new / g_old - 1.0)
        near = np.abs(err[after]) <= max(SHIFT_TOL * abs(jump), SHIFT_TOL_MIN_MPS)
        settle.append(float(t[after][np.argmax(near)] - t_s) if near.any() else None)
        soon = after & (t < t_s + SHIFT_OVERSHOOT_S)
        if jump != 0.0 and soon.any():
            overshoot.append(100.0 * max(float((-np.sign(jump) * err[soon]).max()), 0.0) / abs(jump))
    done = [x for x in settle if x is not None]
    return {"shifts": len(shifts), "settled": len(done), "settle_s": settle,
            "median_s": float(np.median(done)) if done else None, "max_s": float(max(done)) if done else None,
            "overshoot_pct_max": max(overshoot) if overshoot else None,
            "tolerance": f"max({100 * SHIFT_TOL:g} % of the jump, {SHIFT_TOL_MIN_MPS:g} m/s) within {SHIFT_WITHIN_S:g} s"}


HR_TOL_BPM = 3.0              # heart-rate ERG: settled once the heart rate is this close to the target


def heart_rate_figures(bins: dict, n_bins: int | None = None) -> tuple[float | None, float | None]:
    """(mean, max) heart rate [bpm] on bins 0..n_bins-1 where the PlantStates carry one; (None,
    None) without."""
    n = len(bins["dt"]) if n_bins is None else int(n_bins)
    t_hr = float(bins["hr_t"][:n].sum())
    if not t_hr > 0:
        return None, None
    hr_max = bins["hrmax"][:n]
    return (float(bins["hr_dt"][:n].sum() / t_hr),
            float(np.nanmax(hr_max)) if np.isfinite(hr_max).any() else None)


def heart_rate_erg(bins: dict, origin_s: float, bin_s: float, stretches: list,
                   n_bins: int | None = None) -> dict | None:
    """How well heart-rate ERG holds its target. ``stretches``: (start t, end t, target bpm),
    consecutive Commands with the same target. Per stretch, on the bins whose middle lies in it
    (bins 0..``n_bins`` - 1) and carry a heart rate: ``settle_s`` from the stretch's start to the
    start of the first bin whose mean heart rate is within HR_TOL_BPM of the target (None:
    never; the heart answers the power with tau ~ 69 s, so minutes are expected), then from that
    bin on the time-weighted mean |heart rate - target| (``mae_bpm``) and the largest
    (``max_abs_bpm``). ``start_s``: the stretch's first Command's stamp (sim time);
    ``hr_time_s``: the stretch's time with a heart rate (0: none in the bag). None without a
    stretch."""
    n = len(bins["dt"]) if n_bins is None else int(n_bins)
    stretches = [e for e in stretches if e[0] < origin_s + n * bin_s]
    if not stretches:
        return None
    t_left = origin_s + np.arange(n) * bin_s
    middle = t_left + 0.5 * bin_s
    dt, w_hr = bins["dt"][:n], bins["hr_t"][:n]
    hr = _div(bins["hr_dt"][:n], w_hr)
    per: list[dict] = []
    abs_sum = abs_t = 0.0
    for start, end, target in stretches:
        inside = (middle >= start) & (middle < end)
        has = inside & np.isfinite(hr)
        err = np.abs(hr - target)
        near = has & (err <= HR_TOL_BPM)
        r = {"start_s": start, "target_bpm": target, "duration_s": float(dt[inside].sum()),
             "hr_time_s": float(w_hr[has].sum()), "settle_s": None, "mae_bpm": None, "max_abs_bpm": None}
        if near.any():
            k = int(np.argmax(near))
            after = has & (np.arange(n) >= k)
            r["settle_s"] = max(float(t_left[k] - start), 0.0)
            r["mae_bpm"] = float(np.sum(err[after] * w_hr[after]) / np.sum(w_hr[after]))
            r["max_abs_bpm"] = float(err[after].max())
            abs_sum += float(np.sum(err[after] * w_hr[after]))
            abs_t += float(np.sum(w_hr[after]))
        per.append(r)
    done = [r["settle_s"] for r in per if r["settle_s"] is not None]
    worst = [r["max_abs_bpm"] for r in per if r["max_abs_bpm"] is not None]
    return {"stretches": len(per), "settled": len(done),
            "median_settle_s": float(np.median(done)) if done else None, "max_settle_s": max(done) if done else None,
            "mae_bpm": abs_sum / abs_t if abs_t > 0 else None, "max_abs_bpm": max(worst) if worst else None,
            "tolerance_bpm": HR_TOL_BPM, "bin_s": bin_s, "per_stretch": per}


# ============================================================================ text

def _fmt(value, unit: str = "", digits: int = 3) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        return f"{value:.{digits}f}{(' ' + unit) if unit else ''}"
    return f"{value}{(' ' + unit) if unit else ''}"


def format_summary(summary: dict) -> str:
    """Human-readable text of :func:`summarise`'s dict."""
    s = summary
    lines = [f"bag: {s.get('bag')}"]
    if s.get("profile_name") is not None:
        lines.append(f"profile: {s['profile_name']}"
                     + (f"  (session {s['session_state']})" if s.get("session_state") else ""))
    dups = s.get("plant_state_duplicates") or 0
    lines += [
        f"duration:              {_fmt(s.get('duration_s'), 's')}  ({s.get('plant_states', 0)} plant states"
        + (f" + {dups} repeated" if dups else "") + f", end_of_run {'yes' if s.get('end_of_run') else 'no'})",
        f"mean braking power:    {_fmt(s.get('mean_braking_power_w'), 'W', 2)}",
        f"mean rider power:      {_fmt(s.get('mean_rider_power_w'), 'W', 2)}",
        f"mean cadence:          {_fmt(s.get('mean_cadence_rpm'), 'rpm', 1)}"
        + (f"  (gear ratio {s['machine']['gear_ratio']:g})" if s.get("machine") else ""),
        f"energy into battery:   {_fmt(s.get('energy_battery_j'), 'J', 2)}  ({_fmt(s.get('energy_battery_wh'), 'Wh', 4)})",
        f"energy into resistor:  {_fmt(s.get('energy_resistor_j'), 'J', 2)}  ({_fmt(s.get('energy_resistor_wh'), 'Wh', 4)})",
        f"energy losses:         {_fmt(s.get('energy_loss_j'), 'J', 2)}",
        f"peak phase current:    {_fmt(s.get('peak_phase_current_a'), 'A', 2)}",
        f"final battery SOC:     {_fmt(s.get('final_soc'), '', 4)}",
        f"interlock blanked:     {_fmt(s.get('interlock_blanked'))}",
        f"command timeouts:      {_fmt(s.get('timeouts'))} batches",
    ]
    faults = s.get("fault_batches") or {}
    active = {k: v for k, v in faults.items() if v}
    lines.append("fault batches:         " + (", ".join(f"{k} {v}" for k, v in active.items()) if active else "none"))
    if (s.get("machine") or {}).get("kind") == "spmsm" or s.get("relay_switch_overs"):
        lines.append(f"relay switch-overs:    {_fmt(s.get('relay_switch_overs'))}  (inverter <-> rectifier path)")
    can = s.get("can")
    if can:
        dropped = ", ".join(f"{k[len('dropped_'):]} {v}" for k, v in can.items() if k.startswith("dropped_"))
        protocol = f" ({can['protocol']})" if can.get("protocol") else ""    # absent: ODrive CANSimple
        lines.append(f"CAN:                   {can.get('interface', '?')} {can.get('channel', '?')}, node "
                     f"{can.get('node_id', '?')}{protocol}: rx {can.get('rx_frames', '?')} frames, "
                     f"tx {can.get('tx_frames', '?')}, "
                     f"dropped {can.get('dropped', '?')}" + (f" ({dropped})" if dropped else ""))
        alive = "status frames" if can.get("protocol") == "vesc_can" else "heartbeats"
        lines.append(f"                       {alive} {can.get('heartbeats', '?')}, setpoints "
                     f"{can.get('setpoints', '?')}, RTR requests {can.get('requests', '?')}, drive lost "
                     f"{can.get('drive_lost', '?')}x, armed {can.get('armed', '?')}x, disarmed {can.get('disarmed', 0)}x, "
                     f"gave up arming {can.get('arm_gave_up', 0)}x, ERROR diagnostics "
                     f"{can.get('error_diagnostics', 0)}, last axis error {can.get('axis_error', '?')}")
        if can.get("torque_map"):
            lines.append(f"                       {can['torque_map']}; {can.get('torque_map_outside', '?')} lookups "
                         "outside it (nearest speed row / last ratio held)")
        if can.get("log_file"):
            lines.append(f"CAN log:               {can['log_file']} ({can.get('log_frames', '?')} frames)")
    modes = s.get("time_in_mode_s") or {}
    if modes:
        lines.append("time in mode:          " + ", ".join(f"{k} {v:.2f} s" for k, v in modes.items()))
    gear = s.get("virtual_gear")
    if gear:
        shifted = (f", {gear['shifts']} shift(s), {gear['min']:g} .. {gear['max']:g}" if gear["shifts"] else "")
        lines.append(f"virtual gear:          {gear['first']:g}{shifted}; distance {s.get('distance_m', 0.0):.0f} m")
    acc = s.get("power_accuracy")
    if acc:
        drive_torque = "the drive's torque map" if (can or {}).get("torque_map") else "the drive's kt Iq"
        against = "rider's true power" if acc.get("against") == "drive_truth" else "rider's ledger power"
        lines.append(f"trainer power error:   mean {acc['mean_w']:+.2f} W ({acc['mean_pct']:+.2f} %), rms "
                     f"{acc['rms_w']:.2f} W over {acc['windows']} {acc['window_s']:g} s windows (brake + modelled "
                     f"friction + flywheel energy, against the {against})")
        if acc.get("against") == "drive_truth":
            led = acc["ledger"]
            lines.append(f"                       true rider power {acc['true_rider_power_w']:.2f} W (drive_truth: the "
                         "drive emulator's physics); against the plant's")
            lines.append(f"                       ledger ({drive_torque} and speed) it reads {led['mean_w']:+.2f} W "
                         f"({led['mean_pct']:+.2f} %), the ledger {acc['ledger_error_pct']:+.2f} % off the truth"
                         + (f"; {acc['windows_without_truth']} window(s) without the truth left out"
                            if acc.get("windows_without_truth") else ""))
        elif acc.get("ledger_from_drive") and (can or {}).get("torque_map"):
            lines.append("                       drive on CAN: the ledger is the plant's, from the drive's torque "
                         "estimate through its torque map and speed:")
            lines.append("                       the rider's power as well as the map is measured (README, \"Trainer "
                         "power on CAN\")" + ("; drive_truth covers no whole window"
                                              if acc.get("windows_without_truth") else ""))
        elif acc.get("ledger_from_drive"):
            lines.append("                       drive on CAN: the ledger is the plant's, from the drive's torque "
                         "estimate (kt Iq) and speed,")
            lines.append("                       not the rider's true power: an error of kt Iq (the BLDC's: -1 % at "
                         "0.5 N m .. +7 % at 2 N m) is in neither (README, \"Trainer power on CAN\")"
                         + ("; drive_truth covers no whole window" if acc.get("windows_without_truth") else ""))
    friction = s.get("friction") or []
    if len(friction) > 1:                       # a spin-down changed the laws' friction
        changes = ", ".join(f"B {f['friction_nms']:.3e} N m s, Tc {f['dry_friction_nm']:.4f} N m from {f['t']:.1f} s"
                            for f in friction[1:])
        lines.append(f"friction (the laws'): B {friction[0]['friction_nms']:.3e} N m s, Tc "
                     f"{friction[0]['dry_friction_nm']:.4f} N m; then {changes}")
        last = friction[-1]
        # the controller forgets a spin-down when it stops: a config keeps it
        lines.append(f"  (to keep it, in the config: modes: {{friction_nms: {last['friction_nms']:.4g}, "
                     f"dry_friction_nm: {last['dry_friction_nm']:.4g}}})")
    for key, r in (s.get("tracking") or {}).items():
        lines.append(f"tracking {key + ':':<19} rms {_fmt(r.get('rms'), r['unit'], 3)}, max {_fmt(r.get('max_abs'), r['unit'], 3)}"
                     f" ({r['window_s']:g} s windows; per batch rms {_fmt(r.get('rms_batch'), '', 3)},"
                     f" max {_fmt(r.get('max_abs_batch'), '', 3)}; saturated {100 * r['saturated_fraction']:.1f} %)")
    erg = s.get("erg_response")
    if erg:
        lines.append(f"erg response:          {erg['steps']} target steps, {erg['settled']} settled (ERG power "
                     f"within {erg['tolerance']}) after median {_fmt(erg['median_s'], 's', 2)}, max "
                     f"{_fmt(erg['max_s'], 's', 2)} ({erg['window_s']:g} s windows; trainer reviews: 3-5 s)")
    shift = s.get("shift_response")
    if shift:
        lines.append(f"shift response:        {shift['shifts']} slope shifts, {shift['settled']} felt (the flywheel at "
                     f"the new gear's speed, {shift['tolerance']}) after median {_fmt(shift['median_s'], 's', 2)}, "
                     f"max {_fmt(shift['max_s'], 's', 2)}; past it by at most "
                     f"{_fmt(shift['overshoot_pct_max'], '%', 0)} of the jump")
    if s.get("mean_heart_rate_bpm") is not None:
        lines.append(f"heart rate:            mean {s['mean_heart_rate_bpm']:.1f} bpm, max "
                     f"{_fmt(s.get('max_heart_rate_bpm'), 'bpm', 1)}")
    hr_erg = s.get("heart_rate_erg")
    if hr_erg:
        lines += _heart_rate_erg_lines(hr_erg, s.get("mean_heart_rate_bpm") is not None)
    if s.get("software_version"):
        lines.append(f"software:              {s['software_version']}")
    for w in s.get("warnings") or []:
        lines.append(f"warning: {w}")
    lines.append("messages:")
    for topic, count in (s.get("messages") or {}).items():
        if count == 0 and topic.rsplit("/", 1)[-1] in ONLY_WHEN_THERE:
            continue
        lines.append(f"  {topic:<32} {count}")
    return "\n".join(lines)


# topics the recorder always subscribes to but only some rides have (an emulated drive's truth):
# the text lists them when they have messages (the summary's "messages" keeps every count)
ONLY_WHEN_THERE = ("drive_truth",)
HR_ERG_LINES = 8              # stretches listed one by one in the text (a workout may have many)


def _heart_rate_erg_lines(r: dict, has_hr: bool) -> list[str]:
    lines = [f"heart-rate ERG:        {r['stretches']} target stretch(es), {r['settled']} settled (within "
             f"{r['tolerance_bpm']:g} bpm) after median {_fmt(r['median_settle_s'], 's', 1)}, max "
             f"{_fmt(r['max_settle_s'], 's', 1)}; then mean |error| {_fmt(r['mae_bpm'], 'bpm', 1)}, max "
             f"{_fmt(r['max_abs_bpm'], 'bpm', 1)}" + ("" if has_hr else " (no heart rate in the bag)")]
    for x in r["per_stretch"][:HR_ERG_LINES]:
        head = f"  {x['target_bpm']:g} bpm from {x['start_s']:.1f} s ({x['duration_s']:.1f} s): "
        if not x["hr_time_s"] > 0:
            lines.append(head + "no heart rate")
        elif x["settle_s"] is None:
            lines.append(head + f"never within {r['tolerance_bpm']:g} bpm")
        else:
            lines.append(head + f"settled after {x['settle_s']:.1f} s, then mean |error| {x['mae_bpm']:.1f} bpm, "
                                f"max {x['max_abs_bpm']:.1f} bpm")
    if len(r["per_stretch"]) > HR_ERG_LINES:
        lines.append(f"  ... {len(r['per_stretch']) - HR_ERG_LINES} more (summary.json)")
    return lines


# ============================================================================ charts

def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def time_axis(t: np.ndarray, span_s: float) -> tuple[np.ndarray, str]:
    """Seconds, or minutes for sessions longer than 20 min."""
    return (t / 60.0, "min") if span_s > 1200 else (t, "s")


def _save(fig, path: pathlib.Path, written: list) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    _plt().close(fig)
    written.append(path)


def _title(data: SessionData) -> str:
    name = data.summary.get("profile_name") or ""
    return f"{name}  [{data.name}]" if name else data.name


def plot_session(data: SessionData, out: pathlib.Path) -> list[pathlib.Path]:
    """power.png, cadence.png, torque_speed.png, battery.png, energy.png and the overview
    session.png of one session."""
    plt = _plt()
    written: list[pathlib.Path] = []
    s = series(data)
    span = data.n_bins * data.bin_s
    t, unit = time_axis(s["t"] + data.origin_s, span)
    xlabel = f"sim time [{unit}]"
    title = _title(data)
    has_plant = data.summary.get("plant_states", 0) > 0

    # power
    fig, ax = plt.subplots(figsize=(10, 4.5))
    ax.plot(t, s["p_brake"], label="braking power -T_em w", color="tab:blue", lw=1.2)
    ax.plot(t, s["p_rider"], label="rider power (ledger dE_mech/dt)", color="tab:green", lw=1.0, alpha=0.8)
    if np.isfinite(s["erg_target"]).any():
        ax.plot(t, s["erg_target"], label="ERG target (mode_target)", color="black", ls="--", lw=1.2)
    ax.set(title=f"Power - {title}", xlabel=xlabel, ylabel="power [W]")
    _finish(ax)
    _save(fig, out / "power.png", written)

    # cadence
    fig, ax = plt.subplots(figsize=(10, 4.5))
    ax.plot(t, s["cadence"], label=f"crank cadence (motor rpm / {data.machine['gear_ratio']:g})", color="tab:purple")
    if np.isfinite(s["iso_target"]).any():
        ax.plot(t, s["iso_target"], label="isokinetic target", color="black", ls="--")
    ax.set(title=f"Cadence - {title}", xlabel=xlabel, ylabel="cadence [rpm]")
    _finish(ax)
    _save(fig, out / "cadence.png", written)

    # torque against speed with Eq. 3-4
    fig, ax = plt.subplots(figsize=(8, 6))
    plot_torque_speed(ax, data)
    ax.set_title(f"Braking torque vs speed - {title}")
    _save(fig, out / "torque_speed.png", written)

    # battery
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    if np.isfinite(s["bat_v"]).any():
        a1.plot(t, s["bat_v"], label="BatteryState voltage (samples)", color="tab:red", lw=0.7, alpha=0.5)
    if np.isfinite(s["vbus"]).any():
        a1.plot(t, s["vbus"], label="PlantState dc_bus_v (mean per bin)", color="tab:orange", lw=1.4)
    if np.isfinite(s["ocv"]).any():
        a1.plot(t, s["ocv"], label="open-circuit voltage", color="gray", ls="--", lw=0.9)
    a1.set(title=f"Battery - {title}", ylabel="voltage [V]")
    _finish(a1)
    if np.isfinite(s["bat_pct"]).any():
        a2.plot(t, 100 * s["bat_pct"], label="BatteryState percentage", color="tab:red")
    if np.isfinite(s["soc"]).any():
        a2.plot(t, 100 * s["soc"], label="PlantState battery_soc", color="tab:orange", lw=0.9, ls="--")
    a2.set(xlabel=xlabel, ylabel="state of charge [%]")
    a2.ticklabel_format(axis="y", useOffset=False)
    _finish(a2)
    _save(fig, out / "battery.png", written)

    # energy
    fig, ax = plt.subplots(figsize=(10, 4.5))
    e_max = np.nanmax(np.abs(np.concatenate([s[k] for k in ("E_mech", "E_bat", "E_res", "E_loss")]))) \
        if has_plant and np.isfinite(s["E_mech"]).any() else 0.0
    scale, eunit = (3600.0, "Wh") if e_max > 3600 else (1.0, "J")
    for key, label, color in (("E_mech", "from the rider (mech in)", "tab:green"),
                              ("E_bat", "into the battery", "tab:red"),
                              ("E_res", "into the brake resistor", "tab:brown"),
                              ("E_loss", "losses", "gray")):
        ax.plot(t, s[key] / scale, label=label, color=color)
    ax.set(title=f"Energy since start - {title}", xlabel=xlabel, ylabel=f"energy [{eunit}]")
    _finish(ax)
    _save(fig, out / "energy.png", written)

    # overview
    fig, axes = plt.subplots(4, 1, figsize=(10, 10), sharex=True)
    c = data.commands
    if len(c):
        tc, _ = time_axis(c[:, 0], span)
        axes[0].step(tc, c[:, 2], where="post", label="command", color="tab:blue")
        ax2 = axes[0].twinx()
        ax2.step(tc, c[:, 1], where="post", color="tab:gray", lw=0.8, alpha=0.7, label="mode (right axis)")
        ax2.legend(loc="upper left", fontsize=8)
        ax2.set_yticks(list(MODE_NAMES), [MODE_NAMES[m] for m in MODE_NAMES], fontsize=7)
        ax2.set_ylim(-0.5, max(MODE_NAMES) + 0.5)
    axes[0].set(ylabel="command [0..1]", title=f"Session - {title}")
    axes[1].plot(t, s["p_brake"], label="braking", color="tab:blue")
    axes[1].plot(t, s["p_rider"], label="rider", color="tab:green", alpha=0.8)
    if np.isfinite(s["erg_target"]).any():
        axes[1].plot(t, s["erg_target"], label="ERG target", color="black", ls="--")
    axes[1].set_ylabel("power [W]")
    axes[2].plot(t, s["cadence"], label="cadence", color="tab:purple")
    if np.isfinite(s["iso_target"]).any():
        axes[2].plot(t, s["iso_target"], label="isokinetic target", color="black", ls="--")
    axes[2].set_ylabel("cadence [rpm]")
    for key, label, color in (("E_mech", "mech in", "tab:green"), ("E_bat", "battery", "tab:red"),
                              ("E_res", "resistor", "tab:brown"), ("E_loss", "losses", "gray")):
        axes[3].plot(t, s[key] / scale, label=label, color=color)
    axes[3].set(ylabel=f"energy [{eunit}]", xlabel=xlabel)
    for a in axes:
        _finish(a)
    _save(fig, out / "session.png", written)
    return written


def _finish(ax) -> None:
    ax.grid(True, alpha=0.3)
    handles, _labels = ax.get_legend_handles_labels()
    if handles:
        ax.legend(loc="best", fontsize=8)


def curve_commands(res_commands: dict, most: int = 6) -> list[float]:
    """Commands to draw Eq. 3-4 for: all when few, else time-weighted quantiles."""
    cmds = [c for c in res_commands if c > 0]
    if len(cmds) <= most:
        return cmds
    c = np.array(cmds)
    w = np.array([res_commands[x] for x in cmds])
    cw = np.cumsum(w) / w.sum()
    picks = {float(c[min(np.searchsorted(cw, q), len(c) - 1)]) for q in (0.0, 0.25, 0.5, 0.75, 1.0)}
    return sorted(picks | {float(c[-1]), float(c[0])})


MODE_COLORS = {0: "tab:blue", 1: "tab:green", 2: "tab:red", 3: "tab:olive", 4: "tab:purple", -1: "lightgray"}


def data_stride(data: SessionData) -> int:
    return int(data.scatter.get("stride", 1))


def plot_torque_speed(ax, data: SessionData) -> None:
    sc = data.scatter
    mc = data.machine
    # resistance last (on top): the curves below are about that mode
    for m in sorted(set(sc["mode"].astype(int).tolist()), key=lambda m: (m == MODE_RESISTANCE, m)):
        sel = sc["mode"] == m
        ax.scatter(sc["rpm"][sel], sc["torque"][sel], s=4, alpha=0.5 if m == MODE_RESISTANCE else 0.25,
                   color=MODE_COLORS.get(m, "k"), rasterized=True,
                   label=f"{MODE_NAMES.get(m, 'no status')} ({int(sel.sum())} batches"
                         + (f", 1 in {data_stride(data)} shown)" if data_stride(data) > 1 else ")"))
    top = max(float(np.nanmax(sc["rpm"])) if sc["rpm"].size else 0.0, mc["base_speed_rpm"]) * 1.15
    rpm = np.linspace(max(top / 400, 1.0), top, 400)
    cmap = _plt().get_cmap("viridis")
    cmds = curve_commands(data.res_commands)
    law = "Eq. 3-4" if mc.get("brake_envelope") is None else "Eq. 3-4 in the brake envelope"
    for i, c in enumerate(cmds):
        ax.plot(rpm, resistance_torque_nm(c, rpm, mc), color=cmap(i / max(len(cmds) - 1, 1)), lw=1.4,
                label=f"{law}, C = {c:g}")
    ax.plot(rpm, resistance_torque_nm(1.0, rpm, mc), color="black", lw=0.8, ls=":", label=f"{law}, C = 1")
    ax.axvline(mc["base_speed_rpm"], color="gray", lw=0.6, ls="--")
    ax.set(xlabel="motor speed [rpm]", ylabel="braking torque -T_em [N m]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=7, markerscale=3)
    sec = ax.secondary_xaxis("top", functions=(lambda x: x / mc["gear_ratio"], lambda x: x * mc["gear_ratio"]))
    sec.set_xlabel("crank cadence [rpm]")


# ============================================================================ files

def img_tag(path: pathlib.Path) -> str:
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return f'<figure><img alt="{html.escape(path.name)}" src="data:image/png;base64,{data}"><figcaption>{html.escape(path.name)}</figcaption></figure>'


HTML_STYLE = ("body{font-family:sans-serif;max-width:1100px;margin:1em auto;padding:0 1em}"
              "pre{background:#f6f6f6;padding:.6em;overflow-x:auto}table{border-collapse:collapse}"
              "td,th{border:1px solid #ccc;padding:2px 8px;text-align:right}td:first-child,th:first-child{text-align:left}"
              "img{max-width:100%}figure{margin:1em 0}")


def write_html(path: pathlib.Path, title: str, body: str) -> None:
    path.write_text(f"<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>"
                    f"<style>{HTML_STYLE}</style></head><body>\n{body}\n</body></html>\n")


def write_outputs(bag_path, summary: dict | SessionData, out_dir) -> list[pathlib.Path]:
    """summary.json, summary.txt, the charts (PNG) and summary.html (charts embedded)."""
    data = summary if isinstance(summary, SessionData) else analyse(bag_path)
    summary = data.summary
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    text = format_summary(summary)
    (out / "summary.txt").write_text(text + "\n")
    written += [out / "summary.json", out / "summary.txt"]
    pngs = plot_session(data, out) if summary.get("plant_states") or len(data.commands) else []
    written += pngs
    body = [f"<h1>Session report: {html.escape(_title(data))}</h1>", f"<pre>{html.escape(text)}</pre>"]
    body += [img_tag(p) for p in pngs]
    write_html(out / "summary.html", f"bike report {data.name}", "\n".join(body))
    written.append(out / "summary.html")
    return written


def main(argv=None) -> int:
    """``bike report BAG [--json] [--out DIR] [--fit FILE]``: print the summary; BagError -> one
    error line, exit 2."""
    parser = argparse.ArgumentParser(prog="bike report", description="Summarise a recorded bike session.")
    parser.add_argument("bag", help="bag directory (rosbag2, MCAP or sqlite3) or .mcap file")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--out", help="also write summary.json/.txt/.html and charts (PNG) into this folder")
    parser.add_argument("--fit", metavar="FILE", help="also write the ride as a FIT activity (1 s records of power, "
                                                     "cadence, speed, distance) for Garmin Connect, Strava, "
                                                     "intervals.icu or GoldenCheetah")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if args.fit:
        from bike_session.cli import output_file_ok, output_spares_inputs
        if not output_spares_inputs(args.fit, [args.bag], "--fit"):     # the recording itself
            return 2
        if not output_file_ok(args.fit, "--fit"):       # before the bag is read: one error, no work lost
            return 2
    if args.out:
        from bike_session.cli import output_dir
        if output_dir(args.out, "--out") is None:       # the same (it was found after the analysis)
            return 2
    target = args.out
    try:
        data = analyse(args.bag, progress="bike report")
        written = write_outputs(args.bag, data, args.out) if args.out else []
        fit_totals = None
        if args.fit:
            from bike_session.fit_export import export_fit
            target = args.fit
            fit_totals = export_fit(args.bag, args.fit, data)
    except BagError as exc:
        print(f"bike report: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"bike report: error: cannot write to {target}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(json.dumps(data.summary, indent=2) if args.json else format_summary(data.summary))
    for path in written:
        print(f"wrote {path}")
    if fit_totals is not None:
        from bike_session.fit_export import format_totals
        # (with --json, stdout stays one JSON document)
        print(f"wrote {args.fit}: FIT activity, {format_totals(fit_totals)}",
              file=sys.stderr if args.json else sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
