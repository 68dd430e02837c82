"""The emulated dynamometer: a drive's torque map measured on the drive emulator's physics.

A drive on CAN reports its torque as kt x its measured current (Torque_Estimate). On the BLDC
of paper 000 that overstates the shaft's true mean torque by a share that grows with the
current: the commutation dips and the (|ia| + |ib| + |ic|) / 2 current feedback (section
4.3), the same effect the paper corrects with its factor k (Eq. 7, the torque per ampere it
measured). :func:`measure_torque_map` measures it as a test stand would: a prime mover holds
the shaft at each speed of a grid, the drive is given each torque setpoint of a grid, and once
settled the drive's mean reported torque and the shaft's mean true torque (the physics' own
electromagnetic torque, where a real stand has a torque sensor) are written into a
:class:`bike_plant.can.torque_map.TorqueMap`, which the plant's CAN backend uses
(``can.torque_map_file``) to report the true torque and to ask for the setpoint that gives a
wanted one.

The physics is the emulator's (:func:`bike_controller.drive_emulator.make_drive_model`,
``plant`` physics with a prime-mover load): the BLDC's hysteresis current law on the
bike_plant.bldc kernel, or the SPMSM's current loop on bike_plant.spmsm. The torque setpoint
reaches it as the emulated firmware turns it into a current (iq* = T / kt, kt of
:class:`~bike_controller.drive_emulator.DriveModelParams`, the one
:meth:`DriveFirmware.step` divides by and Torque_Estimate multiplies with).

No rclpy here: ``./bike torque-map`` (bike_session.cli) and the tests call it directly.
"""
from __future__ import annotations

import copy
import dataclasses
import math
import time

import numpy as np

from bike_plant.can.torque_map import EMULATED_SOURCE_MARK, MAX_POINTS, TorqueMap
from bike_controller.drive_emulator import RPM_PER_RAD_S, DriveModelParams, make_drive_model, pole_pairs_of

DEFAULT_SETTLE_S = 0.05       # current loop and bus settle (BLDC ~ms; the SPMSM's PI at its pole, tens of ms)
DEFAULT_WINDOW_S = 0.1        # at least this long, rounded up to an even number of electrical revolutions
MAX_SECONDS = 10.0            # per point, settle or window: more is a typo, not a measurement
MAX_EXTRA_SETTLE_S = 1.0      # a drifting point is measured again for at most this much longer
DRIFT_ABS_NM = 0.005          # settled: the halves of the window agree within these (drift_tolerance_nm)
DRIFT_REL = 0.005
# delivered: the drive's reported torque within these of the setpoint (the BLDC's hysteresis band
# leaves <= 0.1 N m short; beyond, the current or voltage limit holds it and the inverse would lie)
SHORTFALL_ABS_NM = 0.15
SHORTFALL_REL = 0.1
TICK_S = 1.0e-3               # the emulator's tick: speed samples, and batches of the compiled kernel
# default speed grid: the rider's cadence span (bike_plant rider 40-120 r/min, some margin) x the gear
DEFAULT_CADENCE_RPM = (30.0, 125.0)
# ~140 steps (25 rpm on config/bldc_can.yaml): the BLDC's true / reported ratio is no smooth function
# of speed; at a torque-dependent speed it steps by up to 3 % within 20 rpm (0.5 N m braking: 1.032 at
# 2600 rpm, 1.002 at 2620), and a 500 rpm grid read a 2800 rpm ERG ride's brake 1-2 % high. The step
# sits at a number of 50 us control periods per commutation sector (with 45 us it moves x 50/45): the
# one-edge-per-period current law's pattern, not measurement noise
DEFAULT_SPEED_STEPS = 140
DEFAULT_SETPOINT_STEPS = 10   # ~10 setpoints on each side of 0 up to the drive's torque clamp
# finer near zero: there the hysteresis band is a large, fast-changing share of the current (braking at
# 2800 rpm the ratio is 1.19 at 0.25 N m, 1.01 at 0.5; a straight line from 0.4 to 0.5 N m is 0.4 % off
# at 0.47); every FINE step of ~clamp / 80 (0.05 N m) from FINE_FIRST steps (0.2 N m) up to clamp / 6
# (0.6 N m). Not closer to zero: the drive delivers nothing below ~0.08 N m (a setpoint within the
# band), a flat row without an inverse
FINE_SETPOINT_STEPS = 80
FINE_FIRST = 4
FINE_SETPOINT_SHARE = 1.0 / 6.0
# the setpoint grid reaches this x the shaft's torque clamp: the BLDC braking at Tmax needs 1.12 x
# (true / reported 0.89 there); a grid that stops at the clamp leaves Tmax out of the map's reach
SETPOINT_HEADROOM = 1.25
NICE_STEPS = (1.0, 2.0, 2.5, 5.0, 10.0)


@dataclasses.dataclass
class TorqueMapMeasurement:
    """A measured grid with what the map file does not keep: how well the speed was held, how long it took."""
    speed_rpm: np.ndarray           # (n,) the prime mover's speeds
    setpoint_nm: np.ndarray         # (m,) the torque setpoints, 0 among them
    reported_nm: np.ndarray         # (n, m) mean Torque_Estimate (kt Iq)
    true_nm: np.ndarray             # (n, m) mean T_em of the physics (the shaft's torque sensor)
    drift_nm: np.ndarray            # (n, m) reported torque: mean of the window's 2nd half - of its 1st
    settled_s: np.ndarray           # (n, m) time before the window (settle_s, more where it drifted)
    speed_spread_rpm: np.ndarray    # (n, m) max - min of the speed sampled every tick over the window
    speed_error_rpm: np.ndarray     # (n, m) mean speed over the window - the speed asked
    window_s: np.ndarray            # (n,) the averaging window used (an even number of electrical revolutions)
    settle_s: float
    kt_nm_per_a: float
    machine: str
    wall_s: float = 0.0

    @property
    def ratio(self) -> np.ndarray:
        """true / reported (1 where nothing was reported: setpoint 0)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            r = self.true_nm / self.reported_nm
        return np.where(np.abs(self.reported_nm) > 1e-9, r, 1.0)

    def problem(self) -> str | None:
        """Why these points make no map (the first reason, a message), or None."""
        return self.delivery_problem() or self.settle_problem() or self.rising_problem()

    def delivery_problem(self) -> str | None:
        """The first point where the drive falls short of its setpoint beyond the hysteresis band's
        share: the current or voltage limit holds it there (a map would ask it for more than it has)."""
        short = np.abs(self.setpoint_nm[None, :] - self.reported_nm)
        bad = np.argwhere(short > np.maximum(SHORTFALL_ABS_NM, SHORTFALL_REL * np.abs(self.setpoint_nm))[None, :])
        if not bad.size:
            return None
        i, j = (int(x) for x in bad[0])
        return (f"at {self.speed_rpm[i]:g} rpm the drive does not deliver setpoint {self.setpoint_nm[j]:g} N m "
                f"(reports {self.reported_nm[i, j]:.4g} N m: current or voltage limit; leave that speed out or "
                "narrow the setpoints)")

    def settle_problem(self) -> str | None:
        """The first point whose torque still drifted after the longest settling (it has no steady mean)."""
        tol = np.maximum(DRIFT_ABS_NM, DRIFT_REL * np.abs(self.reported_nm))
        bad = np.argwhere(np.abs(self.drift_nm) > tol)
        if not bad.size:
            return None
        i, j = (int(x) for x in bad[0])
        return (f"at {self.speed_rpm[i]:g} rpm and {self.setpoint_nm[j]:g} N m the torque still drifts "
                f"({self.drift_nm[i, j]:+.4g} N m within the window after {self.settled_s[i, j]:.3g} s): no steady "
                "mean (a longer --settle-s, or leave the point out)")

    def rising_problem(self) -> str | None:
        """The first row whose reported or true torque does not rise with the setpoint (the drive
        does not deliver the larger setpoints there: current or voltage limit), as a message; None."""
        for i, speed in enumerate(self.speed_rpm):
            for name in ("reported_nm", "true_nm"):
                row = getattr(self, name)[i]
                bad = np.flatnonzero(np.diff(row) <= 0)
                if bad.size:
                    j = int(bad[0])
                    return (f"at {speed:g} rpm the drive does not deliver the setpoints beyond "
                            f"{self.setpoint_nm[j]:g} .. {self.setpoint_nm[j + 1]:g} N m: its {name.split('_')[0]} "
                            f"torque goes {row[j]:.4g} -> {row[j + 1]:.4g} N m (leave that speed out or narrow "
                            "the setpoints)")
        return None

    def to_map(self, source: str) -> TorqueMap:
        return TorqueMap(self.speed_rpm, self.setpoint_nm, self.reported_nm, self.true_nm, source=source)


# ---------------------------------------------------------------------------------------- grids
def parse_grid(tokens, name: str) -> list[float]:
    """Numbers from command-line tokens: each a number, a comma-separated list, or START:STOP:STEP
    (STOP included when on the grid). ValueError naming the option on anything else."""
    values: list[float] = []
    for token in tokens:
        for part in str(token).replace(",", " ").split():
            values += _range(part, name) if ":" in part else [_number(part, name)]
    if not values:
        raise ValueError(f"{name}: no values given")
    return values


def _number(text: str, name: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{name}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise ValueError(f"{name}: {text!r} is not a finite number")
    return value


def _range(text: str, name: str) -> list[float]:
    parts = text.split(":")
    if len(parts) != 3:
        raise ValueError(f"{name}: {text!r} is not START:STOP:STEP")
    start, stop, step = (_number(p, name) for p in parts)
    if step <= 0 or stop < start:
        raise ValueError(f"{name}: {text!r} needs STEP > 0 and STOP >= START")
    count = int(math.floor((stop - start) / step + 1e-9)) + 1
    if count > MAX_POINTS:
        raise ValueError(f"{name}: {text!r} gives {count} values, more than {MAX_POINTS}")
    return [round(start + k * step, 9) for k in range(count)]


def check_times(settle_s: float, window_s: float, names=("settle_s", "window_s")) -> None:
    """ValueError unless both times are in (0, MAX_SECONDS] s (``names``: how the caller calls them)."""
    for name, value in zip(names, (settle_s, window_s)):
        if not (math.isfinite(value) and 0 < value <= MAX_SECONDS):
            raise ValueError(f"{name} must be in (0, {MAX_SECONDS:g}] s, got {value!r}")


def _speed_refusal(speed_rpm: float) -> str | None:
    """Why no drive's map holds ``speed_rpm`` (a message), or None: speeds are finite and > 0 (braking
    needs forward rotation; the map is looked up by |speed|). check_grid's guard, which check_speeds shares."""
    if not math.isfinite(speed_rpm):
        return "speeds must be finite numbers"
    if speed_rpm <= 0:
        return "speeds must be > 0 rpm: braking needs forward rotation"
    return None


def check_grid(speeds_rpm, setpoints_nm, max_setpoint_nm: float,
               names: tuple[str, str] = ("speeds", "setpoints")) -> tuple[np.ndarray, np.ndarray]:
    """Sorted speeds and setpoints (0 added: the map's zero is measured too), or ValueError
    starting with the grid's name (``names``: the CLI's --speeds-rpm / --setpoints-nm): speeds
    must be > 0 (braking needs forward rotation; the map is looked up by |speed|), no value
    twice, no setpoint beyond what the drive's current limit lets through (the firmware clamps it:
    a flat row, no inverse)."""
    speeds = np.asarray([float(s) for s in speeds_rpm], dtype=float)
    setpoints = np.asarray(sorted({float(t) for t in setpoints_nm} | {0.0}), dtype=float)
    if speeds.size == 0:
        raise ValueError(f"{names[0]}: at least one speed is needed")
    for speed in speeds:
        reason = _speed_refusal(float(speed))
        if reason:
            raise ValueError(f"{names[0]}: {reason}, got {speed:g} rpm")
    if not np.all(np.isfinite(setpoints)):
        raise ValueError(f"{names[1]}: setpoints must be finite numbers")
    speeds = np.sort(speeds)
    if np.any(np.diff(speeds) == 0):
        raise ValueError(f"{names[0]}: speed {speeds[np.flatnonzero(np.diff(speeds) == 0)[0]]:g} rpm is given twice")
    if setpoints.size < 2:
        raise ValueError(f"{names[1]}: at least one setpoint besides 0 is needed")
    if speeds.size * setpoints.size > MAX_POINTS:
        raise ValueError(f"{speeds.size} x {setpoints.size} points, more than {MAX_POINTS}")
    worst = float(np.max(np.abs(setpoints)))
    if worst > max_setpoint_nm * (1.0 + 1e-9):
        raise ValueError(f"{names[1]}: setpoint {worst:g} N m is beyond the drive's current limit "
                         f"({max_setpoint_nm:.4g} N m): it would be clamped there")
    return speeds, setpoints


def speed_range_rpm(cfg: dict) -> tuple[float, float, str]:
    """(lowest, highest, why) motor speeds the emulated dynamometer measures on this config.
    Lowest: two electrical revolutions (the shortest window, :func:`window_for`) within
    MAX_SECONDS. Highest (excluded), the BLDC's: the speed whose line-to-line back-EMF reaches the
    empty pack's voltage (bike_plant.params.emf_speed_limit_rpm: above it the bridge's diodes brake
    whatever the setpoint, and the plant refuses the prime mover's speed); the SPMSM's config sets
    none (a speed its voltage cannot reach fails as a point not delivered). ConfigError for a bad config."""
    from bike_plant import params as P

    lowest = 2.0 * 60.0 / (pole_pairs_of(cfg) * MAX_SECONDS)
    if cfg.get("machine", "bldc") != "bldc":
        return lowest, math.inf, ""
    p = P.plant_params_from_config(prime_mover_config(cfg, 0.0))
    why = (f"at {P.emf_speed_limit_rpm(p):.0f} rpm its back-EMF ({p.bldc.ke_v_per_rpm:g} V/rpm) reaches the empty "
           f"pack's {p.battery.v_empty_v:g} V and the bridge diodes brake beyond any setpoint")
    return lowest, P.emf_speed_limit_rpm(p), why


def check_speeds(speeds_rpm, cfg: dict, name: str = "speeds") -> None:
    """ValueError naming ``name`` (the CLI's --speeds-rpm) and the range for a speed outside
    :func:`speed_range_rpm`: before, 1e9 rpm failed in the plant's check of the prime mover, naming
    its config key load.speed_rpm, and 0.0001 rpm measured a 300000 s window. A speed no map holds
    (:func:`_speed_refusal`: not finite, <= 0) says so: inf on the SPMSM (no upper limit) ended in "()"."""
    lowest, highest, why = speed_range_rpm(cfg)
    span = f"{lowest:g} .. {math.floor(highest):g} rpm" if math.isfinite(highest) else f"from {lowest:g} rpm"
    for speed in speeds_rpm:
        reason = _speed_refusal(speed)
        if reason and not math.isfinite(speed):
            raise ValueError(f"{name}: {reason}, got {speed:g} rpm")       # no range it is outside of
        if reason is None:
            if speed < lowest:
                reason = (f"below {lowest:g} rpm two electrical revolutions, the shortest window, take over "
                          f"{MAX_SECONDS:g} s")
            elif speed >= highest:
                reason = why
        if reason:
            raise ValueError(f"{name}: {speed:g} rpm is outside this drive's range, {span} ({reason})")


def setpoint_top_nm(cfg: dict, kt_nm_per_a: float, current_limit_a: float) -> float:
    """The largest setpoint the map should cover: SETPOINT_HEADROOM x the shaft torque the plant
    asks at most (can.torque_limit_nm, else controller.tmax_nm: the CAN backend's clamp, which a
    map makes the shaft's, so the setpoint for it is larger where the drive falls short), within
    the drive's current limit x kt (can.current_limit_a when set)."""
    can = cfg.get("can") if isinstance(cfg.get("can"), dict) else {}
    ctrl = cfg.get("controller") if isinstance(cfg.get("controller"), dict) else {}
    limit_a = _positive(can.get("current_limit_a")) or current_limit_a
    drive_nm = limit_a * kt_nm_per_a
    asked = _positive(can.get("torque_limit_nm")) or _positive(ctrl.get("tmax_nm"))
    return min(asked * SETPOINT_HEADROOM, drive_nm) if asked else drive_nm


def _positive(value) -> float:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0 else 0.0


def nice_step(span: float, steps: int) -> float:
    """A round step (1, 2, 2.5 or 5 x 10^k) giving about ``steps`` steps over ``span``."""
    raw = span / steps
    decade = 10.0 ** math.floor(math.log10(raw))
    return min((n * decade for n in NICE_STEPS), key=lambda s: abs(s - raw))


def default_speeds_rpm(cfg: dict) -> list[float]:
    """Motor speeds over the rider's cadence span (DEFAULT_CADENCE_RPM x load.gear_ratio) on a
    round step (DEFAULT_SPEED_STEPS): config/bldc_can.yaml 1050..4375 every 25 rpm."""
    gear = _positive((cfg.get("load") or {}).get("gear_ratio")) or 1.0
    lo, hi = (c * gear for c in DEFAULT_CADENCE_RPM)
    step = nice_step(hi - lo, DEFAULT_SPEED_STEPS)
    first = max(step, math.floor(lo / step) * step)
    last = math.ceil(hi / step - 1e-9) * step
    return [round(first + k * step, 6) for k in range(int(round((last - first) / step)) + 1)]


def default_setpoints_nm(top_nm: float) -> list[float]:
    """Both signs up to the torque clamp on a round step, the clamp itself (to 3 decimals, down)
    last, and a finer step near zero (FINE_SETPOINT_STEPS): config/bldc_can.yaml -3.677, -3.5 .. 3.5,
    3.677 every 0.25 N m, and 0.2 .. 0.6 every 0.05 N m of either sign."""
    if not (math.isfinite(top_nm) and top_nm > 0):
        raise ValueError(f"the drive's torque clamp must be > 0 N m (controller.tmax_nm, can.torque_limit_nm, "
                         f"the current limit x kt), got {top_nm:g}: give --setpoints-nm")
    step = nice_step(top_nm, DEFAULT_SETPOINT_STEPS)
    top = math.floor(top_nm * 1000.0 + 1e-6) / 1000.0
    side = [round(k * step, 9) for k in range(1, int(math.floor(top / step + 1e-9)) + 1)]
    if top - (side[-1] if side else 0.0) > 0.2 * step:
        side.append(top)
    fine = nice_step(top_nm, FINE_SETPOINT_STEPS)
    last = int(math.floor(FINE_SETPOINT_SHARE * top / fine + 1e-9))
    side = sorted(set(side) | {round(k * fine, 9) for k in range(FINE_FIRST, last + 1)})
    return sorted([-s for s in side] + [0.0] + side)


# ---------------------------------------------------------------------------------------- measurement
def prime_mover_config(cfg: dict, speed_rpm: float) -> dict:
    """The config with its load a prime mover at ``speed_rpm`` (no schedule): the kernels start
    there and hold the shaft at S_SPEED_TARGET exactly, whatever torque the drive makes."""
    cfg = copy.deepcopy(cfg)
    load = dict(cfg.get("load") or {})
    load.update(kind="prime_mover", speed_rpm=float(speed_rpm), schedule_time_s=[], schedule_speed_rpm=[])
    cfg["load"] = load
    return cfg


def window_for(speed_rpm: float, pole_pairs: int, window_s: float) -> float:
    """At least ``window_s``, an even number of electrical revolutions (the commutation pattern
    repeats per revolution, part of one biases the mean by its dips; each half is whole too, so
    the halves' means compare: :attr:`TorqueMapMeasurement.drift_nm`)."""
    rev_s = 60.0 / (abs(speed_rpm) * pole_pairs)
    return 2 * max(1, math.ceil(window_s / (2.0 * rev_s) - 1e-9)) * rev_s


@dataclasses.dataclass
class _Point:
    reported_nm: float
    true_nm: float
    drift_nm: float
    settled_s: float
    speed_spread_rpm: float
    speed_error_rpm: float


def drift_tolerance_nm(reported_nm: float) -> float:
    """Settled: the window's halves agree to 0.5 % of the torque or 5 mN m (the BLDC's ripple
    leaves < 2.5 mN m between halves of whole revolutions)."""
    return max(DRIFT_ABS_NM, DRIFT_REL * abs(reported_nm))


def _window_means(model, iq_a: float, window_s: float) -> tuple[float, float, float, list[float]]:
    """(reported, true, drift of reported from the 1st half to the 2nd, speed samples) over one window."""
    sums = np.zeros((2, 3))         # per half: periods, periods x reported, periods x true
    speeds = []
    ticks = 2 * max(1, int(round(window_s / (2.0 * TICK_S))))
    for k in range(ticks):
        before = model.periods
        # tick ends at fractions of the window: the model carries the remainder, the window ends on time
        model.step(window_s * (k + 1) / ticks - window_s * k / ticks, iq_a, enabled=True)
        n = model.periods - before
        sums[2 * k // ticks] += n * np.array([1.0, model.torque_estimate_nm, model.torque_em_nm])
        speeds.append(model.speed_rad_s * RPM_PER_RAD_S)
    total = sums.sum(axis=0)
    halves = sums[:, 1] / np.maximum(sums[:, 0], 1.0)
    return (float(total[1] / max(total[0], 1.0)), float(total[2] / max(total[0], 1.0)),
            float(halves[1] - halves[0]), speeds)


def measure_point(cfg: dict, speed_rpm: float, setpoint_nm: float, settle_s: float, window_s: float) -> _Point:
    """One point on a fresh model (no history from the previous setpoint: no bus voltage, brake
    resistor or controller state carried over): settle, then period-weighted means over the window.
    While the window's halves disagree (the SPMSM's current loop and speed observer take ~0.1 s
    above 200 r/min) the window is measured again, up to MAX_EXTRA_SETTLE_S more."""
    model = make_drive_model(prime_mover_config(cfg, speed_rpm), "plant", load_kind="prime_mover")
    iq_a = setpoint_nm / model.params.torque_constant_nm_per_a
    model.step(settle_s, iq_a, enabled=True)
    settled_s = settle_s
    while True:
        reported, true, drift, speeds = _window_means(model, iq_a, window_s)
        if abs(drift) <= drift_tolerance_nm(reported) or settled_s - settle_s >= MAX_EXTRA_SETTLE_S:
            break
        settled_s += window_s
    return _Point(reported_nm=reported, true_nm=true, drift_nm=drift, settled_s=settled_s,
                  speed_spread_rpm=float(np.ptp(speeds)), speed_error_rpm=float(np.mean(speeds) - speed_rpm))


def measure_grid(cfg: dict, speeds_rpm, setpoints_nm, *, settle_s: float = DEFAULT_SETTLE_S,
                 window_s: float = DEFAULT_WINDOW_S) -> TorqueMapMeasurement:
    """Every (speed, setpoint) of the grid on the emulator's physics (see :func:`measure_torque_map`).
    ValueError / ConfigError on bad input; points not delivered, still drifting, or rows that do not
    rise are left to the caller (:meth:`TorqueMapMeasurement.problem`)."""
    check_times(settle_s, window_s)
    drive = DriveModelParams.from_config(cfg)
    kt = drive.torque_constant_nm_per_a
    check_speeds([float(s) for s in speeds_rpm], cfg)
    speeds, setpoints = check_grid(speeds_rpm, setpoints_nm, drive.current_limit_a * kt)
    pole_pairs = pole_pairs_of(cfg)
    shape = (speeds.size, setpoints.size)
    out = {key: np.zeros(shape) for key in ("reported_nm", "true_nm", "drift_nm", "settled_s", "speed_spread_rpm",
                                            "speed_error_rpm")}
    windows = np.array([window_for(s, pole_pairs, window_s) for s in speeds])
    t0 = time.perf_counter()
    for i, speed in enumerate(speeds):
        for j, setpoint in enumerate(setpoints):
            point = measure_point(cfg, float(speed), float(setpoint), settle_s, float(windows[i]))
            for key in out:
                out[key][i, j] = getattr(point, key)
    return TorqueMapMeasurement(speed_rpm=speeds, setpoint_nm=setpoints, window_s=windows, settle_s=float(settle_s),
                                kt_nm_per_a=float(kt), machine=drive.machine,
                                wall_s=time.perf_counter() - t0, **out)


def measure_torque_map(cfg: dict, speeds_rpm, setpoints_nm, *, settle_s: float = DEFAULT_SETTLE_S,
                       window_s: float = DEFAULT_WINDOW_S, source: str | None = None) -> TorqueMap:
    """The drive's torque map on the emulated dynamometer (paper 000 section 4.3; the map is the
    paper's Eq. 7 factor k measured per speed and torque): for each speed a prime mover holds the
    shaft (a fresh ``make_drive_model(cfg, "plant", load_kind="prime_mover")`` per point), the drive
    steps with iq* = setpoint / kt, enabled; after ``settle_s`` the mean reported torque
    (``torque_estimate_nm``: kt Iq, what Torque_Estimate carries) and the mean true torque
    (``torque_em_nm``: the physics' T_em) over ``window_s`` rounded up to whole electrical revolutions.

    A point whose torque still drifts between the halves of its window is measured again, up to
    MAX_EXTRA_SETTLE_S longer. Setpoint 0 is always measured (added when not given). ValueError for
    a bad grid (speeds <= 0, setpoints beyond the drive's current limit), a point the drive does not
    deliver (the current or voltage limit at that speed), one that never settles, or a row whose
    reported or true torque does not rise; ConfigError for a config the emulator cannot run."""
    m = measure_grid(cfg, speeds_rpm, setpoints_nm, settle_s=settle_s, window_s=window_s)
    problem = m.problem()
    if problem:
        raise ValueError(problem)
    return m.to_map(source if source is not None else describe_source(m, cfg.get("_config_path")))


def describe_source(m: TorqueMapMeasurement, config_name) -> str:
    """The map file's ``source``: what measured it and how."""
    return (f"./bike torque-map: {EMULATED_SOURCE_MARK} ({m.machine}, bike_controller.drive_emulator) "
            f"of {config_name or 'a config'}, prime mover holding each speed, a fresh model per point: "
            f"settle {m.settle_s:g} s (longer while the torque drifted), then means over >= "
            f"{float(np.min(m.window_s)):.3g} s (whole electrical revolutions); reported = kt Iq "
            f"(kt {m.kt_nm_per_a:.5g} N m/A), true = the physics' mean T_em")


def summary_table(m: TorqueMapMeasurement, columns: int = 8, rows: int = 15) -> str:
    """Per speed (at most ``rows`` of them, evenly picked, the last always), true / reported at a few
    setpoints (the largest and about 2/3, 1/3, 1/6 of it, both signs)."""
    top = float(np.max(np.abs(m.setpoint_nm)))
    picked = []
    for f in (-1.0, -2 / 3, -1 / 3, -1 / 6, 1 / 6, 1 / 3, 2 / 3, 1.0):
        j = int(np.argmin(np.abs(m.setpoint_nm - f * top)))
        if m.setpoint_nm[j] != 0.0 and j not in picked:
            picked.append(j)
    picked = sorted(picked)[:columns]
    head = "  speed rpm | true / reported at setpoint [N m]: " + " ".join(f"{m.setpoint_nm[j]:>7.3g}" for j in picked)
    lines = [head]
    ratio = m.ratio
    pad = len("  speed rpm | true / reported at setpoint [N m]: ")
    every = max(1, math.ceil(m.speed_rpm.size / rows))
    shown = sorted(set(range(0, m.speed_rpm.size, every)) | {m.speed_rpm.size - 1})
    if every > 1:
        lines[0] += f"  (one speed in {every})"
    for i in shown:
        speed = m.speed_rpm[i]
        cells = " ".join(f"{ratio[i, j]:>7.4f}" for j in picked)
        lines.append(f"  {speed:>9g} |".ljust(pad) + cells)
    return "\n".join(lines)

