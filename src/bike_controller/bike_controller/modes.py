"""Session modes: what a Command in [0, 1] asks of the machine (batch rate, no rclpy).

The 20 kHz current loop turns a torque into gate patterns; this module decides the torque,
once per batch (1 ms), from the Command, the mode and the estimated speed. Sign
convention: ``brake_torque_nm`` > 0 opposes the rider (generating quadrant, energy into the
battery), < 0 assists (motoring quadrant, paper 001's downhill assist). All torques and
speeds are at the MOTOR shaft; ``gear_ratio`` = motor speed / crank cadence.

Modes (``bike_msgs/Command``):

- RESISTANCE (0): paper 000 Eq. 2-5, Tcmd = C*Tmax below wb, C*Pmax/w above: C times the
  machine's braking envelope. A machine whose braking path is weaker than Tmax / Pmax at some
  speeds (the SPMSM's diode rectifier + buck of paper 001, Fig. 8: nothing below ~215 r/min,
  6 N m at 320 r/min against Pmax/w = 10 N m) gives the law its own envelope
  (``brake_envelope``, motor r/min -> N m): Tcmd = C * min(Eq. 3-4, envelope), so every
  Command is a torque the bike can brake, and C = 1 is its strongest brake at that speed.
- MOTORING (1): assist torque C*Tmax (quadrant I, paper 000 section 3).
- ERG (2): hold the rider's power P* = C * ``erg_power_max_w``, the power his pedals put
  into the bike (what power pedals read): the brake takes T = P*/max(w, w_min) - T_f(w),
  the bike's own friction T_f (viscous + Coulomb, :func:`mechanics.friction_torque_nm` with
  the controller's nominal figures, as a trainer's power meter models its losses) the rest.
  A brake that took all of P* made the rider give P* + 8-9 W on the BLDC bike at 80 rpm
  (3.4 %, beyond the +-2 % trainers state) and 9 % more on the SPMSM bike at 100 W. A target
  below the friction's own power is flagged ``saturated``. Below the minimum
  cadence the torque stops rising (it stays at P*/w_min, so power falls with cadence):
  the rider who slows down is not pushed into the "spiral of death" of trainers that hold
  power down to standstill (research notes, trainers.md section 5). T is capped at Tmax;
  when that cap binds, or a machine's braking envelope lies below T, the output says so
  (``saturated``), the target is not met silently. Its virtual speed is the gear's
  (cadence x gear x wheel) unless ``erg_speed_from_power``: then a virtual bike on the flat
  driven by the rider's power (:meth:`ModeLaw._erg_speed_mps`), so distance does not depend
  on the gear. ERG smoothing (``erg_ramp_w_per_s`` > 0; research notes section 5: "max
  resistance change per step", QZ PR #3965, a resistance filter, QZ #230): the power the brake
  takes moves towards a new target at most this fast, while ``target`` reports the target
  itself, so the report's ERG response counts the ramp as the rider feels it. Heart-rate ERG:
  a Command with ``heart_rate_bpm`` > 0 holds the rider's heart rate there instead; P* is then
  the output of a slow PI on the PlantState's heart rate
  (:mod:`bike_controller.heart_erg`, tuned on ``hr_gain_bpm_per_w``, ``hr_time_constant_s``,
  ``hr_closed_loop_s``), starting from C * ``erg_power_max_w`` (C = 0: the rider's power then);
  flagged ``saturated`` at 0 W or the top, and while there is no heart rate to follow.
- SLOPE (3): virtual terrain. Grade G = grade_min + C*(grade_max - grade_min) (C = 0.5
  is flat with the default +-20 %). Road load at the virtual speed v (from cadence,
  virtual gear and wheel radius):
      F = m g (sin a + Crr cos a) + 1/2 rho CdA (v + v_wind)|v + v_wind|,  a = atan(G)
  reflected to the motor: T = F * r_wheel * gear_virtual / gear_ratio. With
  ``virtual_inertia`` the rider also feels the mass of rider + bike, J_eq = m (r_wheel
  gear_virtual / gear_ratio)^2 at the motor (about 6x the real flywheel). Feeding back a
  measured acceleration cannot do this: with any delay, derivative feedback stronger than
  the real inertia is unstable, and a low-pass makes it dissipative (+20 % power at 5 %
  grade with 50 ms). Instead the law runs a virtual bike: a disturbance observer estimates
  the rider's torque T_r = J dw/dt + T_brake + B w (low-pass ``observer_tau_s``; T_brake
  the batch's measured torque where the caller gives it, else the law's request), the
  virtual speed follows J_eq dw_v/dt = T_r - T_road(w_v), and the flywheel is made to
  follow w_v: T_brake = T_r - B w - J (T_r - T_road)/J_eq (feedforward; the derivative
  part has gain 1 - J/J_eq < 1 so a delay cannot destabilise it) + PI on w - w_v (the
  isokinetic gains). Negative F (downhill)
  gives assist torque, at most ``assist_max_nm`` and only above ``assist_min_cadence_rpm``
  (the motor never starts turning the cranks of a rider who stopped).
  The road (Crr, Cw = rho CdA as FTMS and FE-C define it, wind) is the config's, or the Command's where it gives one
  (``road_from_command``: a training app's Indoor Bike Simulation, :meth:`ModeLaw.set_road`).
  Virtual shifting: a Command may carry a ``virtual_gear_ratio`` (0: the config's). A shift
  keeps the virtual bike's road speed, v = w_v r_wheel gear_virtual / gear_ratio, so the
  virtual motor speed w_v jumps by gear_old / gear_new, and the flywheel is then made to follow
  it: after an upshift on a climb the brake holds the cranks back until the cadence has fallen
  to the new gear's, as the chain would on a road bike (at most Tmax, flagged saturated where
  that binds); J_eq follows the gear squared. Other modes only report the new virtual speed.
  Automatic shifting (``auto_shift``, research notes section 5: QZ #2236): a cadence outside
  ``auto_shift_low_cadence_rpm`` .. ``auto_shift_high_cadence_rpm`` for ``auto_shift_hold_s``
  shifts one gear of ``virtual_gears`` down or up the same way (:meth:`ModeLaw._auto_shift`);
  a new gear in the Commands (the shifter's press) then moves the gear in force by as many
  table steps as it moved the Commands' gear, and the automatic shifting goes on from there.
- ISOKINETIC (4): constant cadence c* = cadence_min + C*(cadence_max - cadence_min) by a
  PI speed loop (pole placement on J: both poles at -``isokinetic_bandwidth_rad_s``,
  kp = 2 J wn, ki = J wn^2), braking above c*, assisting below, with integrator clamping.
  Clinical slow / intermediate / fast tests are Commands of this mode.
- SPINDOWN (5): spin-down calibration (:mod:`bike_controller.spindown`, FTMS op 0x13): the
  brake lets go, the rider is asked to spin up past ``spindown_high_cadence_rpm`` and then to stop
  pedalling; the coast down to ``spindown_low_cadence_rpm`` gives the bike's friction B, Tc,
  which the laws take from then on (:meth:`ModeLaw.set_friction`). The Command's value only
  tags the request: a new value while in this mode starts another spin-down once the last one is
  over (an app's retry); ``target`` is the procedure's phase (spindown.SPIN_UP .. FAILED),
  saturated when it failed.

Mode switches are smooth: at a switch the difference between the old torque and the new
mode's torque becomes an offset that decays at ``torque_rate_nm_per_s`` (a ramp, never a
step). ERG and resistance are brake-only: a ramp that starts from a brake (or from zero)
never crosses into motoring, even when the target falls faster than the ramp rises (it
holds at zero, counted in ``brake_only_holds``). Only the switch is ramped: a mode's own
dynamics (the speed loops, the virtual bike
answering the pedal stroke) pass unthrottled, and the resistance mode of the paper is
passed straight through once the ramp is over, so the paper's curves are unchanged.
"""
from __future__ import annotations

import bisect
import logging
import math
from dataclasses import dataclass

import numpy as np

from bike_plant.mechanics import VIRTUAL_GEAR_MAX, VIRTUAL_GEAR_MIN, virtual_gear_problem  # noqa: F401
from bike_plant.heart import HeartParams, heart_rate_target_problem
from bike_plant.mechanics import (ROAD_CRR_MAX, ROAD_CW_MAX_KG_M, ROAD_WIND_MAX_MPS, friction_torque_nm,
                                  road_problem)
from bike_plant.params import RPM_PER_RAD_S, MechParams, friction_problem

from .heart_erg import HeartRateErg
from .spindown import COAST, DONE, FAILED, SpinDown, SpinDownParams

MODE_RESISTANCE = 0
MODE_MOTORING = 1
MODE_ERG = 2
MODE_SLOPE = 3
MODE_ISOKINETIC = 4
MODE_SPINDOWN = 5
MODE_NAMES = {MODE_RESISTANCE: "resistance", MODE_MOTORING: "motoring", MODE_ERG: "erg",
              MODE_SLOPE: "slope", MODE_ISOKINETIC: "isokinetic", MODE_SPINDOWN: "spindown"}
G_MPS2 = 9.80665
BRAKE_ONLY_MODES = (MODE_RESISTANCE, MODE_ERG)   # laws whose torque is a brake by design (>= 0)
AUTO_SHIFT_MIN_CADENCE_RPM = 20.0   # below: the rider has stopped pedalling, the auto shifting waits
RIDER_POWER_AVG_S = 2.0            # the rider's averaged power (heart-rate ERG start): a few pedal strokes
_log = logging.getLogger(__name__)

# the default table of the session's shift buttons: 24 gears in equal steps (x 1.0904) over
# Zwift's virtual-gear span 0.75 .. 5.49 (research notes, trainers.md section 3); gear 16
# (2.747) is about the default virtual_gear_ratio 2.75
DEFAULT_VIRTUAL_GEARS = tuple(round(0.75 * (5.49 / 0.75) ** (k / 23), 4) for k in range(24))


@dataclass(frozen=True)
class ModeParams:
    """Config section ``modes`` (plus machine figures passed in by the caller)."""
    torque_rate_nm_per_s: float = 20.0       # motor shaft: Tmax (2.94 N m) in ~0.15 s
    erg_power_max_w: float = 0.0             # 0 -> the machine's Pmax (Eq. 2)
    erg_min_cadence_rpm: float = 40.0
    grade_min: float = -0.20
    grade_max: float = 0.20
    rider_mass_kg: float = 75.0
    bike_mass_kg: float = 10.0
    crr: float = 0.004
    cda_m2: float = 0.32
    air_density_kg_m3: float = 1.204
    wind_mps: float = 0.0                    # head wind positive
    wheel_radius_m: float = 0.335
    virtual_gear_ratio: float = 2.75         # wheel turns per crank turn (e.g. 50/18); a Command may shift
    virtual_gears: tuple = DEFAULT_VIRTUAL_GEARS   # the session's shift buttons step through these
    erg_shift_w: float = 0.0                 # > 0: in ERG a shift press moves the target this many W (not the gear)
    erg_speed_from_power: bool = False       # ERG's virtual speed from the rider's power on the flat, not the gear
    erg_ramp_w_per_s: float = 0.0            # > 0: ERG's brake power moves to a new target at most this fast
    # automatic virtual shifting in the slope mode: a cadence outside the band for hold_s moves
    # the gear one step of virtual_gears (down below the band, up above it)
    auto_shift: bool = False
    auto_shift_low_cadence_rpm: float = 70.0
    auto_shift_high_cadence_rpm: float = 95.0
    auto_shift_hold_s: float = 1.5
    virtual_inertia: bool = True
    observer_tau_s: float = 0.005            # rider-torque observer low-pass
    assist_max_nm: float = 0.0               # 0 -> Tmax
    assist_min_cadence_rpm: float = 15.0
    isokinetic_cadence_min_rpm: float = 20.0
    isokinetic_cadence_max_rpm: float = 120.0
    isokinetic_bandwidth_rad_s: float = 20.0
    # the bike's own friction as the laws model it (ERG leaves it to the rider, the virtual
    # bike's observer counts it); None: the machine's (mechanics.friction_nms, the SPMSM's
    # spmsm.dry_friction_nm). Set to model a trainer whose loss figures are off
    friction_nms: float | None = None
    dry_friction_nm: float | None = None
    # spin-down calibration (bike_controller.spindown): coast from / to these crank cadences
    spindown_high_cadence_rpm: float = 85.0
    spindown_low_cadence_rpm: float = 60.0
    spindown_spin_up_timeout_s: float = 30.0
    spindown_coast_timeout_s: float = 120.0
    # heart-rate ERG (bike_controller.heart_erg): the rider's heart as the trainer assumes it
    # (bike_plant.heart's model, its nominal figures) and the closed loop's time constant
    hr_gain_bpm_per_w: float = 0.5
    hr_time_constant_s: float = 68.7
    hr_closed_loop_s: float = 60.0

    def __post_init__(self):
        for name in ("torque_rate_nm_per_s", "erg_min_cadence_rpm", "rider_mass_kg", "wheel_radius_m",
                     "virtual_gear_ratio", "observer_tau_s", "isokinetic_bandwidth_rad_s",
                     "isokinetic_cadence_max_rpm", "auto_shift_low_cadence_rpm", "auto_shift_high_cadence_rpm",
                     "auto_shift_hold_s", "hr_gain_bpm_per_w", "hr_time_constant_s", "hr_closed_loop_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a number > 0, got {v!r}")
        for name in ("erg_power_max_w", "bike_mass_kg", "crr", "cda_m2", "air_density_kg_m3", "assist_max_nm",
                     "assist_min_cadence_rpm", "isokinetic_cadence_min_rpm", "erg_shift_w", "erg_ramp_w_per_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a number >= 0, got {v!r}")
        for name in ("friction_nms", "dry_friction_nm"):
            v = getattr(self, name)
            problem = None if v is None else friction_problem(name, v)
            if problem:
                raise ValueError(problem)
        if not (isinstance(self.wind_mps, (int, float)) and math.isfinite(self.wind_mps)):
            raise ValueError(f"wind_mps must be a finite number, got {self.wind_mps!r}")
        # the bounds of a road a Command or a profile may give (mechanics.road_problem: any real
        # road): the config's road was ridden as given, Crr 0.5 that a profile's road refuses
        # (a percentage taken for the fraction) or a wind in km/h
        for name, value, lo, hi in (("crr", self.crr, 0.0, ROAD_CRR_MAX),
                                    ("wind_mps", self.wind_mps, -ROAD_WIND_MAX_MPS, ROAD_WIND_MAX_MPS)):
            if not lo <= value <= hi:
                raise ValueError(f"{name} {value!r} outside [{lo:g}, {hi:g}] (a real road)")
        cw_kg_m = self.air_density_kg_m3 * self.cda_m2
        if cw_kg_m > ROAD_CW_MAX_KG_M:
            raise ValueError(f"air_density_kg_m3 x cda_m2 = {cw_kg_m:g} kg/m (Cw = rho CdA) above "
                             f"{ROAD_CW_MAX_KG_M:g} kg/m (a real road: 0.3-0.9)")
        if not (-1.0 <= self.grade_min < self.grade_max <= 1.0):
            raise ValueError(f"need -1 <= grade_min < grade_max <= 1, got {self.grade_min!r}, {self.grade_max!r}")
        if not self.isokinetic_cadence_min_rpm < self.isokinetic_cadence_max_rpm:
            raise ValueError("isokinetic_cadence_min_rpm must be below isokinetic_cadence_max_rpm")
        self.spindown_params()             # checks the spindown_* keys
        problem = virtual_gear_problem(self.virtual_gear_ratio, allow_default=False)
        if problem:
            raise ValueError(f"virtual_gear_ratio: {problem}")
        gears = self.virtual_gears
        if not isinstance(gears, (tuple, list)) or len(gears) < 2:
            raise ValueError(f"virtual_gears must be a list of at least 2 gear ratios, got {gears!r}")
        for g in gears:
            problem = virtual_gear_problem(g, allow_default=False)
            if problem:
                raise ValueError(f"virtual_gears: {problem}")
        if any(b <= a for a, b in zip(gears, gears[1:])):
            raise ValueError(f"virtual_gears must rise from gear to gear, got {list(gears)!r}")
        if not isinstance(self.auto_shift, bool):
            raise ValueError(f"auto_shift must be true or false, got {self.auto_shift!r}")
        # one shift changes the cadence by the gear step: a band narrower than the widest step
        # would shift back and forth across it
        step = max(b / a for a, b in zip(gears, gears[1:]))
        if self.auto_shift and self.auto_shift_high_cadence_rpm < step * self.auto_shift_low_cadence_rpm:
            raise ValueError(f"auto_shift_high_cadence_rpm must be at least the widest virtual_gears step ({step:.4g}) "
                             f"times auto_shift_low_cadence_rpm ({self.auto_shift_low_cadence_rpm:g} rpm), got "
                             f"{self.auto_shift_high_cadence_rpm:g} rpm")

    def heart_params(self) -> HeartParams:
        """The nominal heart the heart-rate ERG is tuned on (rest and max do not enter the PI; nor
        does the drift, which the PI's integral takes up)."""
        return HeartParams(gain_bpm_per_w=self.hr_gain_bpm_per_w, time_constant_s=self.hr_time_constant_s,
                           drift_fraction=0.0)

    def spindown_params(self) -> SpinDownParams:
        return SpinDownParams(self.spindown_high_cadence_rpm, self.spindown_low_cadence_rpm,
                              self.spindown_spin_up_timeout_s, self.spindown_coast_timeout_s)


def _nearest_gear(gears, ratio: float) -> int:
    """Index of the table gear nearest ``ratio`` (by ratio, i.e. in cadence)."""
    return min(range(len(gears)), key=lambda i: abs(math.log(gears[i] / ratio)))


def _interp(x: float, xp: list, fp: list) -> float:
    """float(np.interp(x, xp, fp)) for one x, bit for bit (numpy's arithmetic: the same slope,
    the same product and sum, fp[j] at a grid point, the ends held), on lists: np.interp took
    ~1.3 us of the SPMSM law's ~20 us a batch for one value, this ~0.5. ``xp`` strictly
    increasing, ``fp`` finite (the brake envelope is checked so), so numpy's fallback for a nan
    slope never applies."""
    if x != x:
        return x
    j = bisect.bisect_right(xp, x) - 1
    if j < 0:
        return fp[0]
    if j >= len(xp) - 1:
        return fp[-1]
    x0 = xp[j]
    if x0 == x:
        return fp[j]
    y0 = fp[j]
    return (fp[j + 1] - y0) / (xp[j + 1] - x0) * (x - x0) + y0


@dataclass
class ModeOutput:
    brake_torque_nm: float     # to the current loop (after the rate limit); > 0 brakes, < 0 assists
    wanted_torque_nm: float    # what the mode law asked for (before the rate limit)
    target: float              # W (erg), grade (slope), crank rpm (isokinetic), Command otherwise
    virtual_speed_mps: float
    saturated: bool            # a torque limit binds: the mode's target is not met
    ramping: bool              # a mode switch is being ramped


class ModeLaw:
    """Per-batch torque law of every mode, with the switch-over rate limit."""

    def __init__(self, mp: ModeParams, *, gear_ratio: float, inertia_kgm2: float, tmax_nm: float,
                 pmax_w: float, base_speed_rpm: float, friction_nms: float = 0.0,
                 dry_friction_nm: float = 0.0, dry_friction_speed_rpm: float = 1.0,
                 brake_envelope: tuple | None = None):
        # Eq. 2-5 is a numba kernel: imported by the law only, so that the session node, which
        # reads ModeParams' figures, does not load numba and its code generator
        from .torque_command import torque_command_nm
        self._torque_command_nm = torque_command_nm
        self.mp = mp
        # (motor r/min grid, N m): the strongest steady brake of the machine's braking path,
        # when it is weaker than Tmax / Pmax somewhere (None: Eq. 3-4 is the envelope)
        self.envelope_rpm = self.envelope_nm = None
        if brake_envelope is not None:
            rpm, nm = (np.asarray(v, dtype=float) for v in brake_envelope)
            if rpm.ndim != 1 or rpm.shape != nm.shape or rpm.size < 2 or not np.all(np.diff(rpm) > 0) \
                    or not np.all(np.isfinite(nm)) or np.any(nm < 0):
                raise ValueError("brake_envelope must be (increasing speeds, torques >= 0) of equal length >= 2")
            self.envelope_rpm, self.envelope_nm = rpm, nm
            # as lists for brake_cap_nm's per-batch look-up (_interp)
            self._envelope = (rpm.tolist(), nm.tolist())
        # the machine's friction (nominal figures): the ERG brake leaves it to the rider, the
        # virtual bike's observer counts it as the rider's torque
        self.friction_nms = float(friction_nms)
        self.dry_friction_nm = float(dry_friction_nm)
        self.dry_friction_speed_rad_s = float(dry_friction_speed_rpm) / RPM_PER_RAD_S
        self.gear_ratio = float(gear_ratio)
        self.inertia_kgm2 = float(inertia_kgm2)
        self.tmax_nm = float(tmax_nm)
        self.pmax_w = float(pmax_w)
        self.base_speed_rpm = float(base_speed_rpm)
        self.erg_power_max_w = mp.erg_power_max_w or self.pmax_w
        self.assist_max_nm = mp.assist_max_nm or self.tmax_nm
        self.m_total_kg = mp.rider_mass_kg + mp.bike_mass_kg
        self._set_gear(mp.virtual_gear_ratio)
        self.commanded_gear = self.virtual_gear_ratio   # the Commands' gear (auto shifting leaves it)
        self.auto_low_s = self.auto_high_s = 0.0        # time below / above the auto-shift band
        self.auto_shifts = 0
        self.set_road(None)
        wn = mp.isokinetic_bandwidth_rad_s
        self.kp = 2.0 * self.inertia_kgm2 * wn
        self.ki = self.inertia_kgm2 * wn * wn
        self.brake_only_holds = 0             # ramp steps of ERG / resistance held at 0 instead of motoring
        self.spindown = SpinDown(mp.spindown_params(), self.inertia_kgm2, self.gear_ratio)
        self.measured_em_torque_nm = 0.0      # of the batch that led to the speed in hand
        self.sensor_sample = None             # (time, speed) of the machine's speed sensor, that batch
        self.spindown_command = None          # the value that tagged the last spin-down request
        self.hr_erg = HeartRateErg(mp.heart_params(), mp.hr_closed_loop_s, self.erg_power_max_w)
        self.heart_rate_target_bpm = 0.0      # the Command's (0: plain ERG)
        self.heart_rate_bpm = 0.0             # the rider's, measured with the batch's speed
        self.erg_ke_j = 0.0                   # ERG with erg_speed_from_power: the virtual bike's kinetic energy
        self.last_mode = None
        self.reset()

    def reset(self, torque_nm: float = 0.0) -> None:
        self.torque_nm = float(torque_nm)     # last output (rate-limited)
        self.offset_nm = 0.0                  # what is left of a mode switch's step
        self.integral_nm = 0.0
        self.integral_step_nm = 0.0           # what the last step added to integral_nm (hold_integral)
        erg_was_in_force = self.last_mode == MODE_ERG
        self.last_mode = None
        self.obs_w = None                     # observer: low-passed speed ...
        self.obs_tb = float(torque_nm)        # ... and low-passed applied braking torque
        self.rider_torque_nm = 0.0            # observer output
        self.rider_power_avg_w = 0.0          # its power, averaged over RIDER_POWER_AVG_S
        self.rider_power_weight = 0.0         # ... of which the observer's time makes up this much (-> 1)
        self.erg_brake_limited = False        # the last ERG batch asked past the braking envelope
        self.virtual_w = 0.0                  # virtual bike, motor-equivalent rad/s
        self.observed_s = 0.0                 # the rider-torque observer's time since it started
        # ERG with erg_speed_from_power: the virtual bike's kinetic energy is kept across a reset
        # (a lost drive): it rolled on meanwhile, and rolls on when ERG comes back (_start_erg_bike)
        self.erg_bike_rolling = erg_was_in_force
        self.erg_ramp_w = None                # ERG smoothing: the power the brake takes now (None: the target)
        # (the heart-rate ERG keeps its power across a reset, e.g. a lost drive: the switch ramp
        # brings the torque back, the heart has not changed)

    def hold_integral(self) -> None:
        """The last step's torque turned out, after its batch, to be beyond what the power stage
        could give (the SPMSM inverter's region logic clipped iq* = T / Kt at its voltage or
        current limit, paper 001 Eq. 8 and the flux-weakening limits): undo that step's
        integration, as the law's own limits do (conditional integration). Integrated, the
        shortfall of an assist the 24 V link cannot give wound the slope law's integral from
        -1.46 to -2.75 N m within 0.07 s of a -6 % descent's switch to the inverter, and the
        flywheel then overshot the virtual bike by 1.2 m/s (tools/spmsm_descent_switch.py)."""
        self.integral_nm -= self.integral_step_nm
        self.integral_step_nm = 0.0

    def set_heart_rate_target(self, bpm: float) -> None:
        """The Command's heart-rate target (ERG; 0: none, plain ERG). A new target keeps the
        power in force (the PI goes on from it); ValueError: unchanged."""
        problem = heart_rate_target_problem(bpm)
        if problem:
            raise ValueError(problem)
        self.heart_rate_target_bpm = float(bpm)

    def _set_gear(self, ratio: float) -> None:
        self.virtual_gear_ratio = float(ratio)
        # v = w_motor * mps_per_rad_s; J_eq = m * mps_per_rad_s^2 (kinetic energy of rider + bike)
        self.mps_per_rad_s = self.mp.wheel_radius_m * self.virtual_gear_ratio / self.gear_ratio
        self.j_virtual_kgm2 = self.m_total_kg * self.mps_per_rad_s ** 2

    def set_virtual_gear(self, ratio: float) -> None:
        """Shift the virtual bike to ``ratio`` wheel turns per crank turn (0: the config's
        gear), keeping its road speed: the virtual motor speed scales by old / new (module
        docstring). ValueError outside [VIRTUAL_GEAR_MIN, VIRTUAL_GEAR_MAX]."""
        problem = virtual_gear_problem(ratio)
        if problem:
            raise ValueError(problem)
        new = float(ratio) or self.mp.virtual_gear_ratio
        # every Command carries its gear: only a change is a shift (so it does not undo the
        # automatic shifts)
        if new == self.commanded_gear:
            return
        old, self.commanded_gear = self.commanded_gear, new
        if self.mp.auto_shift:
            # the automatic shifting owns the gear: a press (a new Command gear) moves it by as
            # many table steps as it moved the Commands' gear, from the gear in force
            gears = self.mp.virtual_gears
            steps = _nearest_gear(gears, new) - _nearest_gear(gears, old)
            if steps == 0:
                return
            new = gears[min(max(_nearest_gear(gears, self.virtual_gear_ratio) + steps, 0), len(gears) - 1)]
        self._shift_to(new)

    def _shift_to(self, new: float) -> None:
        if new == self.virtual_gear_ratio:
            return
        self.virtual_w *= self.virtual_gear_ratio / new
        self._set_gear(new)
        self.auto_low_s = self.auto_high_s = 0.0

    def _auto_shift(self, w: float, dt_s: float) -> None:
        """Automatic virtual shifting (slope mode, ``auto_shift``): a crank cadence below
        ``auto_shift_low_cadence_rpm`` for ``auto_shift_hold_s`` shifts one gear of
        ``virtual_gears`` down (an easier gear), above ``auto_shift_high_cadence_rpm`` one up,
        as a rider keeps his cadence on a climb and a descent; the hold starts again after
        every shift. A rider below AUTO_SHIFT_MIN_CADENCE_RPM has stopped: no shift."""
        mp = self.mp
        cadence_rpm = w * RPM_PER_RAD_S / self.gear_ratio
        low = AUTO_SHIFT_MIN_CADENCE_RPM <= cadence_rpm < mp.auto_shift_low_cadence_rpm
        high = cadence_rpm > mp.auto_shift_high_cadence_rpm
        self.auto_low_s = self.auto_low_s + dt_s if low else 0.0
        self.auto_high_s = self.auto_high_s + dt_s if high else 0.0
        if max(self.auto_low_s, self.auto_high_s) < mp.auto_shift_hold_s:
            return
        # one step from the table's gear nearest the one in force (which a Command may have
        # set off the table, like the config's 2.75 between 2.747 and 2.995)
        gears = mp.virtual_gears
        k = _nearest_gear(gears, self.virtual_gear_ratio) + (-1 if low else 1)
        if not 0 <= k < len(gears):          # at the table's end: stay, and wait another hold
            self.auto_low_s = self.auto_high_s = 0.0
            return
        self._shift_to(gears[k])
        self.auto_shifts += 1

    def set_road(self, road: tuple[float, float, float] | None) -> None:
        """The road of the slope mode and of ERG's flat road: (crr, cw_kg_m, wind_mps) as a
        Command gives it (Cw = rho CdA, the FTMS Indoor Bike Simulation's and FE-C's wind
        resistance coefficient: Zwift's 0.51 kg/m is 1.275 kg/m^3 x 0.40 m^2, research notes 2.2,
        GoldenCheetah #3800; the drag is 1/2 Cw v^2), or None for the config's
        (crr, air_density_kg_m3 cda_m2, wind_mps). ValueError: unchanged."""
        if road is None:
            mp = self.mp
            road = (mp.crr, mp.air_density_kg_m3 * mp.cda_m2, mp.wind_mps)
            self.road_from_command = False
        else:
            problem = road_problem(*road)
            if problem:
                raise ValueError(problem)
            self.road_from_command = True
        self.crr, self.cw_kg_m, self.wind_mps = (float(x) for x in road)

    def _observe(self, w: float, dt_s: float, brake_nm: float) -> None:
        """Rider torque T_r = J dw/dt + T_brake + B w, all through one low-pass (the
        derivative as J (w - w_lp) / tau: no differentiation of the quantised estimate)."""
        if self.obs_w is None:
            self.obs_w = w
        self.observed_s += dt_s
        tau = self.mp.observer_tau_s
        a = dt_s / (tau + dt_s)
        self.obs_w += a * (w - self.obs_w)
        self.obs_tb += a * (brake_nm - self.obs_tb)
        self.rider_torque_nm = (self.inertia_kgm2 * (w - self.obs_w) / tau + self.obs_tb
                                + self.friction_nm(self.obs_w))
        # his power over a few pedal strokes (the torque swings +-50 % within one): where a
        # heart-rate ERG without a power of its own starts
        a_avg = dt_s / (RIDER_POWER_AVG_S + dt_s)
        self.rider_power_avg_w += a_avg * (self.rider_torque_nm * w - self.rider_power_avg_w)
        self.rider_power_weight += a_avg * (1.0 - self.rider_power_weight)

    def _rider_power_mean_w(self) -> float:
        """The rider's mean power over the last RIDER_POWER_AVG_S (the EMA over the observer's time
        so far, its start-up weight divided out: unbiased from the first batch on)."""
        return self.rider_power_avg_w / self.rider_power_weight if self.rider_power_weight > 0.0 else 0.0

    def set_friction(self, friction_nms: float, dry_friction_nm: float) -> None:
        """The bike's friction from now on (a spin-down's figures); ValueError: unchanged."""
        for name, v in (("friction_nms", friction_nms), ("dry_friction_nm", dry_friction_nm)):
            problem = friction_problem(name, v)
            if problem:
                raise ValueError(problem)
        self.friction_nms, self.dry_friction_nm = float(friction_nms), float(dry_friction_nm)

    def rider_instruction(self) -> tuple[float, bool] | None:
        """What the spin-down asks of the simulated rider, (cadence target [rpm], stop
        pedalling), while it runs; None: the Command's cadence target holds."""
        if self.last_mode == MODE_SPINDOWN and self.spindown.running:
            return self.spindown.rider_instruction()
        return None

    def status_fields(self) -> dict:
        """ControllerStatus fields of the law: the friction in force."""
        return {"friction_nms": self.friction_nms, "dry_friction_nm": self.dry_friction_nm}

    def _spindown_step(self, w: float, dt_s: float) -> int:
        sd = self.spindown
        before = sd.phase
        phase = sd.step(w, dt_s, self.measured_em_torque_nm, released=self.offset_nm == 0.0,
                        sample=self.sensor_sample)
        if phase != before and phase == DONE:
            old = (self.friction_nms, self.dry_friction_nm)
            r = sd.result
            self.set_friction(r.friction_nms, r.dry_friction_nm)
            _log.warning("spin-down done: %s; the laws' friction was B %.3e N m s, Tc %.4f N m",
                         r.describe(self.gear_ratio), *old)
        elif phase != before and phase == FAILED:
            _log.warning("spin-down failed: %s; the laws' friction is unchanged", sd.reason)
        elif phase != before and phase == COAST:
            _log.warning("spin-down: %.1f rpm reached, the rider stops pedalling (coast to %g rpm)",
                         w * RPM_PER_RAD_S / self.gear_ratio, sd.params.low_cadence_rpm)
        return phase

    def friction_nm(self, w: float) -> float:
        """The machine's own friction at motor speed ``w`` [rad/s] (nominal figures)."""
        return friction_torque_nm(w, self.friction_nms, self.dry_friction_nm, self.dry_friction_speed_rad_s)

    def brake_cap_nm(self, w: float) -> float:
        """The strongest brake at motor speed ``w`` [rad/s]: Tmax, or less where the
        machine's braking envelope is lower (held at its last value beyond the table)."""
        if self.envelope_rpm is None:
            return self.tmax_nm
        return min(self.tmax_nm, _interp(w * RPM_PER_RAD_S, *self._envelope))

    # ---------------------------------------------------------------- the laws
    def road_force_n(self, grade: float, v_mps: float) -> float:
        """Road load of section 3 of the research notes (Gribble), drivetrain loss left out,
        on the road in force (:meth:`set_road`)."""
        a = math.atan(grade)
        va = v_mps + self.wind_mps
        return (self.m_total_kg * G_MPS2 * (math.sin(a) + self.crr * math.cos(a))
                + 0.5 * self.cw_kg_m * va * abs(va))

    def _erg_speed_mps(self, w: float, dt_s: float) -> float:
        """ERG with ``erg_speed_from_power``: the virtual bike's speed from the rider's power on a
        flat road, so that distance does not depend on the gear (GoldenCheetah #3712; in ERG the
        brake, not the road, sets the load). Kinetic energy integrated as GoldenCheetah's
        BicycleSim does (research notes section 3): d(1/2 m v^2)/dt = P_r - F_road(0, v) v, with
        P_r = T_r w from the rider-torque observer. Its start at the switch into ERG:
        :meth:`_start_erg_bike`."""
        p_rider_w = self.rider_torque_nm * w
        v = math.sqrt(2.0 * self.erg_ke_j / self.m_total_kg)
        self.erg_ke_j = max(self.erg_ke_j + (p_rider_w - self.road_force_n(0.0, v) * v) * dt_s, 0.0)
        return math.sqrt(2.0 * self.erg_ke_j / self.m_total_kg)

    def _start_erg_bike(self, from_slope: bool, target_w: float) -> None:
        """ERG's virtual bike at the switch into ERG: the slope mode's virtual bike rolls on when
        that came before, and ERG's own when a reset (a lost drive) interrupted ERG; else it
        starts at the flat road's steady speed for the rider's power then (not the gear's speed,
        which would put the gear into the distance for the ~20 s the bike's mass takes to
        settle), his mean over the last RIDER_POWER_AVG_S (the EMA's start-up weight divided
        out), a few pedal strokes. The stroke's instant swings +-50 %: from it, the plant's
        rider at 170-182 W (33 km/h) started the bike at 24.5-37.3 km/h, as the switch fell in
        the stroke. Where the observer has not seen RIDER_POWER_AVG_S yet (a ride's start, after
        a reset) the bike starts at the speed of the ERG target ``target_w``, the power the brake
        will hold him at: from the fresh observer's friction, a ride that started in ERG at 200 W
        rode off at 7.4 km/h (34.4 km/h for 200 W), and a lost drive took ERG's bike there."""
        if from_slope:
            v0 = self.virtual_w * self.mps_per_rad_s
        elif self.erg_bike_rolling:
            return
        elif self.observed_s < RIDER_POWER_AVG_S:
            v0 = self._flat_speed_mps(target_w)
        else:
            v0 = self._flat_speed_mps(self._rider_power_mean_w())
        self.erg_ke_j = 0.5 * self.m_total_kg * v0 * v0

    def _flat_speed_mps(self, p_w: float) -> float:
        """The speed at which ``p_w`` holds the flat road's load, F_road(0, v) v = p_w (bisection:
        the load's power rises with v)."""
        lo, hi = 0.0, 40.0
        if p_w <= 0.0:
            return 0.0
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            if self.road_force_n(0.0, mid) * mid < p_w:
                lo = mid
            else:
                hi = mid
        return 0.5 * (lo + hi)

    def _wanted(self, command: float, mode: int, w: float, dt_s: float, clock_s: float | None = None):
        """``dt_s``: the step of the integrators and ramps; ``clock_s``: of the clocks (the
        spin-down's, the heart-rate ERG's), ``dt_s`` + skipped time (:meth:`step`; None: ``dt_s``)."""
        mp = self.mp
        clock_s = dt_s if clock_s is None else clock_s
        cadence_rpm = w * RPM_PER_RAD_S / self.gear_ratio
        v = w * self.mps_per_rad_s
        if mode == MODE_RESISTANCE:
            t = self._torque_command_nm(command, w * RPM_PER_RAD_S, self.tmax_nm, self.base_speed_rpm, self.pmax_w)
            if self.envelope_rpm is not None:
                # C times the lower of Eq. 3-4 and the envelope (both linear in C)
                t = min(t, command * self.brake_cap_nm(w))
            return t, command, v, False
        if mode == MODE_MOTORING:
            return -command * self.tmax_nm, command, v, False
        if mode == MODE_ERG:
            p_w = command * self.erg_power_max_w
            hr_sat = False
            if self.heart_rate_target_bpm > 0.0:
                if not self.hr_erg.started:
                    # C = 0: the rider's mean power, the EMA's start-up weight divided out (a rider at
                    # 200 W for 3 s of a ride had it start at 155 W, the EMA's 1 - e^-1.5 of his power)
                    self.hr_erg.start(p_w if p_w > 0.0 else self._rider_power_mean_w())
                # while the brake could not take the power (the last batch at its envelope), the
                # rider's power is what the bike takes (heart_erg: no unwinding from beyond it)
                p_w = self.hr_erg.step(self.heart_rate_target_bpm, self.heart_rate_bpm, clock_s,
                                       taken_w=self.rider_power_avg_w if self.erg_brake_limited else None)
                hr_sat = self.hr_erg.saturated
            else:
                self.hr_erg.started = False
            p_brake_w = p_w
            if mp.erg_ramp_w_per_s > 0.0:
                # smoothing: towards the target at most erg_ramp_w_per_s (from the target itself
                # at the switch into ERG, which the switch ramp already smooths)
                ramp = p_w if self.erg_ramp_w is None else self.erg_ramp_w
                step_w = mp.erg_ramp_w_per_s * dt_s
                p_brake_w = self.erg_ramp_w = min(max(p_w, ramp - step_w), ramp + step_w)
            w_min = mp.erg_min_cadence_rpm * self.gear_ratio / RPM_PER_RAD_S
            t_rider = p_brake_w / max(w, w_min)    # the crank torque (at the motor) that gives P*
            t = t_rider - self.friction_nm(w)       # the bike's friction takes its share
            below_friction = t < 0.0 and p_brake_w > 0.0
            t = max(t, 0.0)
            # flagged where the braking envelope binds, but asked for uncapped (up to Tmax): the
            # SPMSM's rectifier path then brakes at buck duty 1 through the pedal stroke. Capped
            # at the envelope of the speed estimate, the duty followed the stroke and the
            # all_modes ERG 180 W braked 4.1-4.7 N m instead of 5.0-5.7
            self.erg_brake_limited = t > self.brake_cap_nm(w)
            if mp.erg_speed_from_power:
                v = self._erg_speed_mps(w, dt_s)
            return min(t, self.tmax_nm), p_w, v, self.erg_brake_limited or below_friction or hr_sat
        if mode == MODE_SLOPE:
            grade = mp.grade_min + command * (mp.grade_max - mp.grade_min)
            k = self.mps_per_rad_s
            if mp.virtual_inertia:
                t_r = self.rider_torque_nm
                t_road = self.road_force_n(grade, self.virtual_w * k) * k
                self.virtual_w = max(self.virtual_w + (t_r - t_road) / self.j_virtual_kgm2 * dt_s, 0.0)
                err = w - self.virtual_w
                t_ff = t_r - self.friction_nm(w) - self.inertia_kgm2 * (t_r - t_road) / self.j_virtual_kgm2
                integral = self.integral_nm + self.ki * err * dt_s
                t = t_ff + self.kp * err + integral
                v = self.virtual_w * k
            else:
                integral = None
                # the machine's own friction is part of the load already: the rider feels the road
                t = self.road_force_n(grade, v) * k - self.friction_nm(w)
            sat = False
            if t < 0.0:
                if cadence_rpm < mp.assist_min_cadence_rpm:
                    t = 0.0
                elif t < -self.assist_max_nm:
                    t, sat = -self.assist_max_nm, True
            # flagged beyond the braking envelope (the trim holds on it), asked up to Tmax, like ERG
            if t > self.tmax_nm:
                t, sat = self.tmax_nm, True
            elif t > self.brake_cap_nm(w):
                sat = True
            if integral is not None and not sat:
                self.integral_nm = integral     # conditional integration
            return t, grade, v, sat
        if mode == MODE_SPINDOWN:
            phase = self._spindown_step(w, clock_s)
            return 0.0, float(phase), v, phase == FAILED
        if mode == MODE_ISOKINETIC:
            target_rpm = mp.isokinetic_cadence_min_rpm + command * (mp.isokinetic_cadence_max_rpm
                                                                    - mp.isokinetic_cadence_min_rpm)
            w_ref = target_rpm * self.gear_ratio / RPM_PER_RAD_S
            err = w - w_ref                      # faster than the target -> brake
            t_p = self.kp * err
            integral = self.integral_nm + self.ki * err * dt_s
            t = t_p + integral
            # Tmax, not the envelope: the SPMSM's isokinetic speed loop brakes on the inverter
            lo, hi = -self.assist_max_nm, self.tmax_nm
            sat = not (lo <= t <= hi)
            if not sat:
                self.integral_nm = integral     # conditional integration: no wind-up at a limit
            t = min(max(t, lo), hi)
            return t, target_rpm, v, sat
        raise ValueError(f"unknown mode {mode!r}")

    def step(self, command: float, mode: int, speed_rpm: float, dt_s: float,
             speed_valid: bool = True, measured_em_torque_nm: float | None = None,
             sensor_sample: tuple[float, float] | None = None, heart_rate_bpm: float = 0.0,
             skipped_s: float = 0.0) -> ModeOutput:
        """One batch: the torque for the next ``dt_s`` seconds from the speed estimate.

        ``speed_valid`` False (no speed estimate yet, e.g. before the second Hall edge):
        the output holds and no mode starts, so the speed loops and the virtual bike start
        from a real speed, not from 0. ``measured_em_torque_nm``: the electromagnetic torque
        measured over the batch that led to ``speed_rpm`` (PlantState.torque_em_nm, motoring
        positive, as :meth:`TorqueTrim.correct` takes it); the virtual bike's rider-torque
        observer brakes with its negative, so a brake the machine could not give is not taken
        for the rider's torque. None (or not finite): the law's own last output.
        ``sensor_sample``: (time [s], motor speed [rad/s]) measured by the machine's speed sensor
        over the batch (spindown.EncoderSpeed), which the spin-down's fit takes when given.
        ``heart_rate_bpm``: the rider's heart rate (PlantState.heart_rate_bpm; 0: none), which
        the heart-rate ERG follows.

        ``skipped_s``: the time of the plant states skipped before this one (realtime: a
        controller descheduled for it reads the newest only; ModedController and
        ModedSpmsmController take it from the plant state's period count, bounded by
        session_control.MAX_SKIPPED_S). The clocks count it: the spin-down's (its timeouts,
        and the coast's time axis where no speed sensor dates the samples: the BLDC bike's),
        the automatic shifting's hold and the heart-rate ERG's slow PI (the heart beat on
        through the stall). The rest steps ``dt_s``, the batch's time: the switch ramp and ERG's
        ramp limit what the rider feels, and through the stall he felt the command held (or
        the plant's safe state), not their progress, so stepping the stall's time made a step
        of rate x stall (20 N m/s x 0.1 s = 2 N m of the BLDC's 2.94); the virtual bike and the
        speed loops' integrators would take the rider-torque estimate and the speed error at
        the stall's end for all of it, and the flywheel ran without the law then (the BLDC's
        virtual bike on a climb, stepped over 0.1 s stalls: 0.06 - 0.09 m/s off what the rider's
        work against the road gave, 0.03 m/s held; 0.2 s stalls: 0.13 against 0.05)."""
        if not (math.isfinite(command) and 0.0 <= command <= 1.0):
            raise ValueError(f"command must be in [0, 1], got {command!r}")
        if mode not in MODE_NAMES:
            raise ValueError(f"unknown mode {mode!r}")
        if not speed_valid:
            return ModeOutput(self.torque_nm, self.torque_nm, command, 0.0, False, False)
        w = max(speed_rpm, 0.0) / RPM_PER_RAD_S
        clock_s = dt_s + max(skipped_s, 0.0)
        measured = measured_em_torque_nm is not None and math.isfinite(measured_em_torque_nm)
        self.measured_em_torque_nm = float(measured_em_torque_nm) if measured else -self.torque_nm
        self.sensor_sample = sensor_sample
        self.heart_rate_bpm = float(heart_rate_bpm or 0.0)
        if dt_s > 0:
            self._observe(w, dt_s, -self.measured_em_torque_nm)
        switched = self.last_mode is not None and mode != self.last_mode
        if switched and self.last_mode == MODE_SPINDOWN and self.spindown.running:
            self.spindown.abandon(f"the Command changed to {MODE_NAMES[mode]} before it was done")
            _log.warning("spin-down abandoned: %s; the laws' friction is unchanged", self.spindown.reason)
        if mode != self.last_mode:
            if mode == MODE_ISOKINETIC:
                self.integral_nm = self.torque_nm   # bumpless entry from the torque in force
            elif mode == MODE_SLOPE:
                self.integral_nm = 0.0              # the virtual bike starts at the real speed
                self.virtual_w = w
            elif mode == MODE_ERG and self.mp.erg_speed_from_power:
                self._start_erg_bike(self.last_mode == MODE_SLOPE, command * self.erg_power_max_w)
            self.hr_erg.started = False           # a heart-rate ERG starts from this Command's power
            self.erg_ramp_w = None                # ERG smoothing starts at the target
            self.erg_bike_rolling = False         # only the first mode after a reset may roll on
        if mode == MODE_SPINDOWN and (mode != self.last_mode or (command != self.spindown_command
                                                                and not self.spindown.running)):
            self.spindown.start()
            _log.warning("spin-down: the brake lets go; the rider spins up past %g rpm",
                         self.spindown.params.high_cadence_rpm)
        self.spindown_command = command
        if mode == MODE_SLOPE and self.mp.auto_shift:
            if mode != self.last_mode:
                self.auto_low_s = self.auto_high_s = 0.0
            self._auto_shift(w, clock_s)
        self.last_mode = mode
        integral_before_nm = self.integral_nm
        wanted, target, v, sat = self._wanted(command, mode, w, dt_s, clock_s)
        self.integral_step_nm = self.integral_nm - integral_before_nm
        if switched:
            self.offset_nm = self.torque_nm - wanted
        max_step = self.mp.torque_rate_nm_per_s * dt_s
        self.offset_nm = math.copysign(max(abs(self.offset_nm) - max_step, 0.0), self.offset_nm)
        ramping = self.offset_nm != 0.0
        torque = wanted + self.offset_nm
        if mode in BRAKE_ONLY_MODES and torque < 0.0 <= self.torque_nm and wanted >= 0.0:
            # a brake-only law ramping up from a brake (e.g. from zero after a lost drive) whose
            # target fell faster than the ramp: the offset would make it motor. Hold at zero.
            self.offset_nm = -wanted
            torque = 0.0
            self.brake_only_holds += 1
        self.torque_nm = torque
        return ModeOutput(self.torque_nm, wanted, target, v, sat, ramping)


@dataclass(frozen=True)
class MachineFigures:
    """What the mode laws need to know about the bike's machine (motor shaft figures)."""
    machine: str
    tmax_nm: float
    base_speed_rpm: float
    pmax_w: float
    gear_ratio: float            # motor speed / crank cadence
    # (motor r/min grid, N m): the braking path's strongest steady brake where it is weaker
    # than Tmax / Pmax (the SPMSM's rectifier path); None: Eq. 3-4 is the envelope
    brake_envelope: tuple | None = None


def machine_figures(cfg: dict, with_envelope: bool = True) -> MachineFigures:
    """Tmax, base speed, Pmax (= Tmax wb, Eq. 2 of paper 000) and gear of either machine:
    BLDC from ``controller`` (paper 000's Tmax / wb / Pmax); SPMSM: ``controller.tmax_nm``
    or Kt * current limit, the rated speed as wb, and the rectifier path's braking envelope
    (spmsm_control.brake_envelope; not for a drive on CAN). ValueError names what is missing.
    ``with_envelope=False``: no envelope (None), and no numba kernel loaded, for what needs
    only the figures (the mode ranges of the session and FTMS nodes: ~110 MB less there)."""
    machine = str(cfg.get("machine", "bldc"))
    ctrl = cfg.get("controller") or {}
    load = cfg.get("load") or {}
    if machine == "spmsm":
        from bike_plant.spmsm_params import nominal_params_from_config

        from .spmsm_params import controller_params_from_config
        nominal = nominal_params_from_config(cfg)
        tmax = float(ctrl.get("tmax_nm") or nominal.spmsm.torque_constant_nm_per_a
                     * controller_params_from_config(cfg).current_limit_a)
        base = float(nominal.spmsm.rated_speed_rpm)
        envelope = None
        if with_envelope and cfg.get("backend", "sim") != "can":
            # braking goes through the relay's rectifier path (a drive on CAN brakes through its inverter)
            from .spmsm_control import brake_envelope, pack_controller
            envelope = brake_envelope(pack_controller(controller_params_from_config(cfg), nominal))
        return MachineFigures("spmsm", tmax, base, tmax * base / RPM_PER_RAD_S, float(nominal.load.gear_ratio),
                              envelope)
    if machine != "bldc":
        raise ValueError(f"unknown machine {machine!r} (bldc | spmsm)")
    values = []
    for key in ("tmax_nm", "base_speed_rpm", "pmax_w"):
        v = ctrl.get(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
            raise ValueError(f"controller.{key} must be a number > 0, got {v!r}")
        values.append(float(v))
    gear = load.get("gear_ratio", 35.0)
    return MachineFigures("bldc", *values, float(gear))


def friction_figures(cfg: dict) -> tuple[float, float, float]:
    """The bike's own friction as the mode laws model it, (B [N m s/rad], Tc [N m], w_s
    [r/min]) of :func:`mechanics.friction_torque_nm` at the motor shaft: ``modes.friction_nms``
    / ``modes.dry_friction_nm`` where the config gives them (a trainer whose loss figures are
    off), else the machine's: ``mechanics.friction_nms`` (the plant's default 1e-4 when absent),
    the SPMSM's ``spmsm.dry_friction_nm`` / ``dry_friction_speed_rpm``. The controllers and the
    report's ERG power take it from here. ValueError names a bad key."""
    mp = mode_params_from_config(cfg)

    def figure(section: str, key: str, default: float) -> float:
        v = (cfg.get(section) or {}).get(key, default)
        if key in ("friction_nms", "dry_friction_nm"):
            problem = friction_problem(key, v)
        elif isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v >= 0):
            problem = f"{key} must be a number >= 0, got {v!r}"
        else:
            problem = None
        if problem:
            raise ValueError(f"{section}.{problem}")
        return float(v)

    spmsm = cfg.get("machine") == "spmsm"
    b = figure("mechanics", "friction_nms", MechParams.friction_nms) if mp.friction_nms is None else mp.friction_nms
    tc = (figure("spmsm", "dry_friction_nm", 0.0) if spmsm else 0.0) if mp.dry_friction_nm is None \
        else mp.dry_friction_nm
    ws = figure("spmsm", "dry_friction_speed_rpm", 1.0) if spmsm else 1.0
    return b, tc, ws if ws > 0 else 1.0


def modes_from_config(cfg: dict) -> tuple[ModeParams, tuple[float, float, float]]:
    """(:func:`mode_params_from_config`, :func:`friction_figures`) of a config; a ConfigError
    naming the config and the section, as the controllers and ./bike run's check give it (their
    three copies named 'modes' twice, or not at all: --set modes.erg_power_max_w=-1 said
    "error: --set: erg_power_max_w must be ...")."""
    from bike_plant.config import ConfigError

    path = cfg.get("_config_path")
    try:
        mp = mode_params_from_config(cfg)
    except ValueError as exc:
        text = str(exc)           # ModeParams' own checks name the key alone
        raise ConfigError(text, path, None if text.startswith("modes") else "modes") from None
    try:
        return mp, friction_figures(cfg)
    except ValueError as exc:
        raise ConfigError(str(exc), path) from None     # it names its section.key


def erg_power_w(torque_em_nm, speed_rad_s, friction: tuple[float, float, float]):
    """The power ERG holds, the rider's: braking power -T_em w plus the bike's friction
    (``friction``: :func:`friction_figures`) times w. Scalars or numpy arrays."""
    b_nms, dry_nm, dry_rpm = friction
    return (friction_torque_nm(speed_rad_s, b_nms, dry_nm, dry_rpm / RPM_PER_RAD_S) - torque_em_nm) * speed_rad_s


def mode_params_from_config(cfg: dict) -> ModeParams:
    """``modes`` section of a bike config (every key optional); ValueError names the key."""
    section = cfg.get("modes") or {}
    if not isinstance(section, dict):
        raise ValueError("modes must be a mapping")
    known = ModeParams.__dataclass_fields__
    unknown = sorted(set(section) - set(known))
    if unknown:
        raise ValueError(f"modes: unknown key(s) {', '.join(unknown)}")
    kwargs = {}
    for k, v in section.items():
        if k == "virtual_gears":
            if not isinstance(v, list) or not all(isinstance(g, (int, float)) and not isinstance(g, bool) for g in v):
                raise ValueError(f"modes.virtual_gears must be a list of numbers, got {v!r}")
            kwargs[k] = tuple(float(g) for g in v)
            continue
        if isinstance(known[k].default, bool):
            if not isinstance(v, bool):
                raise ValueError(f"modes.{k} must be true or false, got {v!r}")
        elif isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ValueError(f"modes.{k} must be a number, got {v!r}")
        kwargs[k] = v if isinstance(v, bool) else float(v)
    return ModeParams(**kwargs)


class TorqueTrim:
    """Slow integral trim closing the torque loop on the measured mean torque of the last
    batch (PlantState.torque_em_nm: the model's torque in sim, the drive's estimate on
    CAN). The mode laws promise a power or a torque; the machine's torque-per-current is
    not exact (paper 000: k(w) depends on speed only; the SPMSM's rectifier path is
    controlled through a buck duty), so the requested torque is corrected by
    ``trim``, clamped to +-``max_fraction`` * Tmax. Time constant ``tau_s``.

    Robustness (a drive on CAN whose estimates stop arriving for a while):

    * the trim integrates over fresh measurement time only: with ``fresh`` False (the
      plant flags the measurement stale, or it repeats a held value) it holds, so it does
      not wind up on a frozen torque estimate (``held_steps`` counts those steps); so does
      the answer after skipped plant states (realtime), whose measurement is of a batch
      the plant ran on the held command or in its safe state;
    * ``brake_only`` (ERG and the resistance mode: the laws' torque is a brake, >= 0 by
      design, Eq. 2-5 of paper 000 and P*/w): the trimmed torque never becomes motoring.
      The trim is clamped so that brake + trim >= 0 and the clamp is counted
      (``sign_clamps``), reported as a saturation (:attr:`clamped`) and logged (the first
      one, then every 1000th), never silent."""

    LOG_EVERY = 1000

    def __init__(self, tmax_nm: float, tau_s: float = 0.3, max_fraction: float = 0.3):
        self.limit_nm = max_fraction * tmax_nm
        self.tau_s = tau_s
        self.trim_nm = 0.0
        self.asked_nm: float | None = None
        self.asked_saturated = False    # the last request was flagged saturated: no trim on its shortfall
        self.sign_clamps = 0         # steps whose brake torque the trim would have turned into motoring
        self.held_steps = 0          # steps on a stale measurement: no integration
        self.clamped = False         # the last step was clamped

    def reset(self) -> None:
        self.trim_nm = 0.0
        self.asked_nm = None
        self.asked_saturated = False
        self.clamped = False

    def correct(self, brake_torque_nm: float, measured_em_torque_nm, dt_s: float, *, fresh: bool = True,
                brake_only: bool = False, saturated: bool = False, released: bool = False) -> float:
        """The torque to request for ``brake_torque_nm``, given the measured mean
        electromagnetic torque of the last batch (motoring positive; None: unknown).
        ``fresh`` False: the measurement is stale (held), the trim holds. ``brake_only``:
        the result stays a brake (>= 0), see the class doc. ``saturated``: the law flagged the
        request (ModeOutput.saturated: at a limit, or beyond a braking envelope); the shortfall
        measured for it is no model error, so the trim holds on it (conditional integration: a
        trim wound up there over-brakes once the speed lets the path deliver). ``released``: the
        law lets go of the machine (a spin-down): the trim starts afresh with the next brake."""
        if released:
            self.reset()
            return brake_torque_nm
        # a request of zero asks for no torque (a spin-down's free coast, a brake held at zero):
        # what the machine makes then (diodes conducting) is not the law's error to trim
        if (self.asked_nm and measured_em_torque_nm is not None
                and math.isfinite(measured_em_torque_nm) and not self.asked_saturated):
            if fresh:
                err = self.asked_nm - (-float(measured_em_torque_nm))
                self.trim_nm = min(max(self.trim_nm + err * dt_s / self.tau_s, -self.limit_nm), self.limit_nm)
            else:
                self.held_steps += 1
        self.asked_nm = brake_torque_nm
        self.asked_saturated = saturated
        self.clamped = False
        if brake_torque_nm == 0.0:
            return 0.0
        torque = brake_torque_nm + self.trim_nm
        if brake_only and brake_torque_nm > 0.0 and torque < 0.0:
            # a brake-only law (ERG, resistance) never motors: the trim (wound up on a
            # measurement artefact) gives way, counted and logged
            self.trim_nm = -brake_torque_nm
            self.clamped = True
            self.sign_clamps += 1
            if self.sign_clamps % self.LOG_EVERY == 1:
                _log.warning("torque trim clamped: it would have turned the brake torque %.3f N m of a brake-only "
                             "mode into motoring (%.3f N m); held at 0 N m (%d clamps so far)",
                             brake_torque_nm, torque, self.sign_clamps)
            torque = 0.0
        return torque

    def hold_last(self) -> None:
        """The last request turned out, after its batch, to be beyond what the machine could
        give (the SPMSM inverter's region logic clipped iq* at its voltage or current limit):
        like a request the law flagged, its shortfall is no model error and the trim holds on it
        at the next :meth:`correct`."""
        self.asked_saturated = True

    @property
    def saturated(self) -> bool:
        """The trim is at its limit (or clamped to keep a brake a brake): the machine cannot
        deliver the asked torque here."""
        return self.clamped or abs(self.trim_nm) >= 0.999 * self.limit_nm
