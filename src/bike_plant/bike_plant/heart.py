"""The rider's heart rate: a first-order response to the power he puts into the pedals, with a
slow cardiovascular drift on top (no rclpy).

Model (K. J. Hunt et al., "Identification and comparison of heart-rate dynamics during cycle
ergometer and treadmill exercise", 2019, data: figshare 9720008): around a
working point the heart rate answers the work rate as a linear first-order system,

    HR = HR_rest + min(x + d, HR_max - HR_rest),    tau dx/dt = K P - x,    x held in [0, HR_max - HR_rest],

with tau = 68.7 +- 21.5 s on the cycle ergometer (25 men, "somewhat hard" intensity, Borg 13).
Without drift (d = 0) a power held long enough settles at HR_ss(P) = HR_rest + min(K max(P, 0),
HR_max - HR_rest). The steady-state line K [bpm/W] is the rider's own; it stops at HR_max. The
input is the power of each batch, which swings with the pedal stroke (the flywheel takes and
gives back energy): the limits act on the filtered state x, not on the input, so the heart
answers the mean power (limits on the input cut the stroke's peaks: at 248 W mean, 165 bpm
instead of 184).

Cardiovascular drift, d: at a constant work rate the heart rate keeps rising slowly after the
first ~10 min (stroke volume falls as the body heats up). Measured: +8 +- 4 and +9 +- 7 bpm
between minutes 10 and 30 at the individual anaerobic threshold (~150 bpm; ACSM abstract,
"cardiovascular drift ... CPT", 7 young adults); +6 / 8 / 9 bpm over 35 min at 95 / 100 / 105 %
of the maximal lactate steady state in competitive cyclists (Murphy, Winger, Stavrianeas, ACSM
2009); within 5 % of W/bpm over an easy hour in riders with a good aerobic base (J. Friel, The
Cyclist's Training Bible). Modelled as the slow component of two-component heart-rate kinetics,

    tau_d dd/dt = g x - d,

a fraction g of the exercise heart rate reached with tau_d >> tau. The defaults (g 0.25,
tau_d 1800 s) give +7.7 bpm between minutes 10 and 30 at 170 W (x = 85 bpm); the ``trained``
preset's 0.12 gives +3.7. It unwinds the same way when the rider stops. K then describes the heart
in the first minutes of a power; g = 0 turns the drift off. The dead time that Hunt and Wang
add (F1000Research 13:894, 2024) is not modelled. Power into the pedals only: while a motor
drives his legs (P < 0) the heart goes back to rest.

The same code serves the simulated rider (the plant, ``load.rider_*hr*`` figures) and the
trainer's heart-rate ERG (bike_controller.heart_erg, which tunes its PI on the nominal figures
of ``modes.hr_*``; its integral takes up the drift): two parameter sets, one model.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

# a heart-rate target a Command or a workout may give (0: none)
HEART_RATE_TARGET_MIN_BPM = 40.0
HEART_RATE_TARGET_MAX_BPM = 220.0
MODE_ERG = 2                      # bike_msgs/Command.MODE_ERG (no message import in physics code)


def _number(value) -> bool:
    """A finite int or float (not a bool)."""
    return not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)


def heart_rate_target_problem(bpm) -> str | None:
    """Why ``bpm`` is not a heart-rate target (None if it is): 0 (none) or a finite number in
    [HEART_RATE_TARGET_MIN_BPM, HEART_RATE_TARGET_MAX_BPM]."""
    if not _number(bpm):
        return f"heart-rate target must be a finite number, got {bpm!r}"
    if bpm != 0 and not HEART_RATE_TARGET_MIN_BPM <= bpm <= HEART_RATE_TARGET_MAX_BPM:
        return (f"heart-rate target {bpm!r} bpm outside [{HEART_RATE_TARGET_MIN_BPM:g}, "
                f"{HEART_RATE_TARGET_MAX_BPM:g}] (0: none)")
    return None


HEART_RATE_MAX_BPM = 250.0   # no heart beats faster: a reading or a rider's maximum above it is a mistake


def heart_rate_reading_problem(bpm) -> str | None:
    """Why a sensor's reading (bike_msgs/HeartRate) is not a heart rate (None if it is): a finite
    number in [0, HEART_RATE_MAX_BPM] (0: the strap has no contact)."""
    if not _number(bpm) or not 0.0 <= bpm <= HEART_RATE_MAX_BPM:
        return f"heart rate {bpm!r} bpm is not a reading (0..{HEART_RATE_MAX_BPM:g})"
    return None


def heart_rate_command_problem(bpm, mode: int) -> str | None:
    """A Command's heart-rate target: :func:`heart_rate_target_problem`, and only in ERG
    (Command.MODE_ERG = 2; other modes have no power to follow it with)."""
    problem = heart_rate_target_problem(bpm)
    if problem is None and bpm != 0 and mode != MODE_ERG:
        problem = f"a heart-rate target ({bpm:g} bpm) applies to ERG (mode 2) only, got mode {mode!r}"
    return problem


@dataclass
class HeartParams:
    """A rider's heart: resting and maximal rate, the steady-state gain, the time constant and
    the drift (fraction of the exercise heart rate, time constant).

    Defaults: a recreational rider (bike_plant.params.RIDER_PRESETS) whose heart beats at 90 % of
    its maximum at his FTP of 207 W (research notes trainers.md section 4: 2.7 W/kg after a few
    months of riding), (0.9 * 185 - 60) / 207 = 0.51 bpm/W; tau from Hunt et al. 2019; the drift
    from the module docstring."""
    rest_bpm: float = 60.0
    max_bpm: float = 185.0
    gain_bpm_per_w: float = 0.5
    time_constant_s: float = 68.7
    drift_fraction: float = 0.25
    drift_time_constant_s: float = 1800.0

    def validate(self) -> None:
        for name in ("rest_bpm", "max_bpm", "gain_bpm_per_w", "time_constant_s", "drift_fraction",
                     "drift_time_constant_s"):
            value = getattr(self, name)
            if name == "drift_fraction":
                if not _number(value) or not 0.0 <= value <= 1.0:
                    raise ValueError(f"drift_fraction must be a number in [0, 1] (0: no drift), got {value!r}")
            elif not _number(value) or value <= 0:
                raise ValueError(f"{name} must be a number > 0, got {value!r}")
        if not self.rest_bpm < self.max_bpm:
            raise ValueError(f"rest_bpm ({self.rest_bpm:g}) must be below max_bpm ({self.max_bpm:g})")
        if self.drift_fraction > 0 and not self.drift_time_constant_s > self.time_constant_s:
            raise ValueError(f"drift_time_constant_s ({self.drift_time_constant_s:g}) must be above "
                             f"time_constant_s ({self.time_constant_s:g}): the drift is the slow part")

    def steady_bpm(self, power_w: float) -> float:
        """HR_ss(P) without drift: the rate a power held for some minutes settles at."""
        return self.rest_bpm + min(self.gain_bpm_per_w * max(power_w, 0.0), self.max_bpm - self.rest_bpm)


class HeartRate:
    """The model above, stepped once per batch with the batch's mean power."""

    def __init__(self, params: HeartParams):
        params.validate()
        self.params = params
        self.x_bpm = 0.0              # at rest
        self.drift_bpm = 0.0

    @property
    def bpm(self) -> float:
        p = self.params
        return p.rest_bpm + min(self.x_bpm + self.drift_bpm, p.max_bpm - p.rest_bpm)

    def step(self, power_w: float, dt_s: float) -> float:
        """Advance ``dt_s`` with ``power_w`` held: the exact solution of both equations for a held
        input (so a batch of any length gives the same rate at the same time while x stays in
        its limits), the states then held in theirs."""
        p = self.params
        if dt_s > 0.0 and math.isfinite(power_w):
            target = p.gain_bpm_per_w * power_w
            a = self.x_bpm - target
            e_x = math.exp(-dt_s / p.time_constant_s)
            if p.drift_fraction > 0.0:
                # x = target + a e^(-t/tau) drives tau_d d' = g x - d: a particular part g target +
                # b e^(-t/tau), b = g a tau / (tau - tau_d), plus the free decay towards it
                b = p.drift_fraction * a * p.time_constant_s / (p.time_constant_s - p.drift_time_constant_s)
                settled = p.drift_fraction * target
                d = settled + b * e_x + (self.drift_bpm - settled - b) * math.exp(-dt_s / p.drift_time_constant_s)
                self.drift_bpm = max(d, 0.0)
            self.x_bpm = min(max(target + a * e_x, 0.0), p.max_bpm - p.rest_bpm)
        return self.bpm


class RiderHeart:
    """The simulated rider's heart inside a plant: it takes the energy the rider has put into the
    shaft so far (the ledger's ``energy_mech_in_j``) and the plant's time after every batch, so
    its input is the batch's exact mean power (the plants' ``advance_heart``)."""

    def __init__(self, params: HeartParams):
        self.heart = HeartRate(params)
        self.energy_j = 0.0
        self.time_s = 0.0

    @property
    def bpm(self) -> float:
        return self.heart.bpm

    def advance(self, energy_mech_in_j: float, time_s: float) -> float:
        dt_s = time_s - self.time_s
        if dt_s > 0.0:
            self.heart.step((energy_mech_in_j - self.energy_j) / dt_s, dt_s)
        self.energy_j, self.time_s = float(energy_mech_in_j), float(time_s)
        return self.heart.bpm
