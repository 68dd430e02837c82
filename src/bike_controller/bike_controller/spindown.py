"""Spin-down calibration: the bike measures its own friction from a coast-down (no rclpy).

A smart trainer reports the rider's power as its brake's plus its own losses, and those losses
drift (belt tension, bearing temperature, a wheel-on tyre's pressure): the spin-down is how
trainers re-learn them (FTMS Spin Down Control, op 0x13; research notes, trainers.md sections 2
and 5: ~10 % error on magnetic trainers without it). The procedure, batch by batch:

1. SPIN_UP: the brake lets go and the rider is asked to spin the flywheel up past the top
   cadence ``high_cadence_rpm`` (he is told ``high_cadence_rpm`` + ``SPIN_UP_MARGIN_RPM`` and
   must stay above half that margin for ``SPIN_UP_HOLD_S`` with the brake fully released: a
   pedal stroke's peak or a speed estimate's transient as the brake lets go is no spin-up);
2. COAST: once there, he is told to stop pedalling; from the top cadence down to
   ``low_cadence_rpm`` the shaft obeys only its friction and whatever electromagnetic torque
   the machine still makes (measured, e.g. diodes conducting):
       J dw/dt = T_em - B w - Tc          (paper 000 / 001, Eq. 3 of 001, with Coulomb Tc)
3. DONE: B and Tc from a least-squares fit of the integral of that equation,
       w_k = w_0 - (B / J) int_0^t_k w dt - (Tc / J) t_k + (1 / J) int_0^t_k T_em dt,
   linear in (w_0, B, Tc): integrals of the measured speed, no differentiation of a quantised
   estimate, and a speed estimate's constant lag scales w_0 and the integral alike. J is the
   controller's nominal inertia. A negative coefficient (noise on a bike without Coulomb
   friction) is refitted as 0. The samples are the machine's speed sensor where the law has
   one (:class:`EncoderSpeed`: the SPMSM bike's encoder), not its speed observer: an observer
   lags a torque it does not model, and the rider's stopping is one (the SPMSM's 5 Hz observer
   read 1 % high for 0.15 s after it, and a coast that began 0.1 s later gave B 57 % high and
   Tc 81 % low). The BLDC bike's Hall-edge estimate is itself such a measurement.
   FAILED: the rider did not reach the top cadence within ``spin_up_timeout_s``, the coast
   took longer than ``coast_timeout_s``, or the flywheel sped up while coasting (the rider
   pedalled): nothing is learnt, and the reason is given.

The mode laws then take the fitted friction (:meth:`bike_controller.modes.ModeLaw.set_friction`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bike_plant.params import RPM_PER_RAD_S

IDLE, SPIN_UP, COAST, DONE, FAILED = range(5)
PHASE_NAMES = {IDLE: "idle", SPIN_UP: "spin up", COAST: "coast", DONE: "done", FAILED: "failed"}
SPIN_UP_MARGIN_RPM = 5.0        # the rider is asked this much above the top cadence
SPIN_UP_HOLD_S = 0.5            # ... and must hold half of that margin for this long, brake released
SPED_UP_RPM = 1.0               # a coast whose cadence rises this far above its lowest was pedalled
MIN_SAMPLES = 20


@dataclass(frozen=True)
class SpinDownParams:
    """Config section ``modes`` (keys ``spindown_*``), crank cadences."""
    high_cadence_rpm: float = 85.0
    low_cadence_rpm: float = 60.0
    spin_up_timeout_s: float = 30.0
    coast_timeout_s: float = 120.0

    def __post_init__(self):
        for name in ("high_cadence_rpm", "low_cadence_rpm", "spin_up_timeout_s", "coast_timeout_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"spindown_{name} must be a number > 0, got {v!r}")
        if not self.low_cadence_rpm < self.high_cadence_rpm:
            raise ValueError("spindown_low_cadence_rpm must be below spindown_high_cadence_rpm")


@dataclass(frozen=True)
class SpinDownResult:
    friction_nms: float           # viscous B [N m s/rad], motor shaft
    dry_friction_nm: float        # Coulomb Tc [N m], motor shaft
    coast_s: float                # duration of the fitted coast
    samples: int
    rms_residual_rpm: float       # fit residual, motor r/min

    def describe(self, gear_ratio: float) -> str:
        return (f"B {self.friction_nms:.3e} N m s, Tc {self.dry_friction_nm:.4f} N m (motor shaft) from a "
                f"{self.coast_s:.1f} s coast, {self.samples} samples, residual "
                f"{self.rms_residual_rpm / gear_ratio:.3f} rpm at the crank")


def fit_coast(time_s, speed_rad_s, torque_em_nm, inertia_kgm2: float) -> SpinDownResult:
    """B and Tc of J dw/dt = T_em - B w - Tc from a coast (module docstring, step 3).
    ValueError with fewer than MIN_SAMPLES samples or a coast that does not slow down."""
    t = np.asarray(time_s, dtype=float)
    w = np.asarray(speed_rad_s, dtype=float)
    tem = np.asarray(torque_em_nm, dtype=float)
    if t.size < MIN_SAMPLES:
        raise ValueError(f"a coast of {t.size} samples is too short to fit (at least {MIN_SAMPLES})")
    dt = np.diff(t)
    t_rel = t - t[0]
    w_int = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * dt)])
    tem_int = np.concatenate([[0.0], np.cumsum(0.5 * (tem[1:] + tem[:-1]) * dt)])
    y = w - tem_int / inertia_kgm2
    # columns: w_0, B / J, Tc / J; a negative coefficient is refitted as 0
    cols = (np.ones_like(t), -w_int, -t_rel)

    def solve(keep):
        coef, *_ = np.linalg.lstsq(np.column_stack([cols[k] for k in keep]), y, rcond=None)
        values = dict.fromkeys((0, 1, 2), 0.0)
        values.update(zip(keep, (float(c) for c in coef)))
        return values

    values = solve((0, 1, 2))
    if values[1] < 0.0:
        values = solve((0, 2))
    elif values[2] < 0.0:
        values = solve((0, 1))
    if values[1] <= 0.0 and values[2] <= 0.0:
        raise ValueError("the coast did not slow down: no friction to fit")
    values[1], values[2] = max(values[1], 0.0), max(values[2], 0.0)
    fitted = values[0] - values[1] * w_int - values[2] * t_rel
    rms = float(np.sqrt(np.mean((y - fitted) ** 2))) * RPM_PER_RAD_S
    return SpinDownResult(float(values[1] * inertia_kgm2), float(values[2] * inertia_kgm2),
                          float(t_rel[-1]), int(t.size), rms)


class EncoderSpeed:
    """The M/T speed of an incremental encoder, batch to batch: the counts between the last
    edge of this batch and the last edge before it, over their capture-timer times (the
    drive's own clock, bike_plant.spmsm's ``encoder_edge_ticks``). A measurement (to the
    timer's tick), dated at the middle of its interval, for the spin-down's fit."""

    def __init__(self, counts_per_rev: int, capture_timer_hz: float):
        self.rad_per_count = 2.0 * math.pi / counts_per_rev
        self.capture_timer_hz = float(capture_timer_hz)
        self.ref: tuple[int, int] | None = None      # (count, ticks) of the last edge used

    def sample(self, count: int, edge_ticks: int) -> tuple[float, float] | None:
        """(time [s] on the timer's clock, mean speed [rad/s]) since the last edge used; None
        for the first call and for a batch without a new edge."""
        ref, self.ref = self.ref, (count, edge_ticks)
        if ref is None:
            return None
        if count == ref[0] or edge_ticks <= ref[1]:
            self.ref = ref                           # no new edge: keep the old one
            return None
        span_s = (edge_ticks - ref[1]) / self.capture_timer_hz
        return 0.5 * (edge_ticks + ref[1]) / self.capture_timer_hz, (count - ref[0]) * self.rad_per_count / span_s


class SpinDown:
    """The procedure's state machine at batch rate (module docstring); :meth:`step` per batch."""

    def __init__(self, params: SpinDownParams, inertia_kgm2: float, gear_ratio: float):
        self.params = params
        self.inertia_kgm2 = float(inertia_kgm2)
        self.gear_ratio = float(gear_ratio)
        self.phase = IDLE
        self.result: SpinDownResult | None = None
        self.reason = ""

    def start(self) -> None:
        self.phase = SPIN_UP
        self.elapsed_s = 0.0
        self.phase_s = 0.0
        self.result, self.reason = None, ""
        self.t: list[float] = []
        self.w: list[float] = []
        self.tem: list[float] = []
        self.min_cadence_rpm = math.inf
        self.above_s = 0.0
        self.sensed = False           # the coast is sampled by a speed sensor (:meth:`step`'s sample)

    @property
    def running(self) -> bool:
        return self.phase in (SPIN_UP, COAST)

    def rider_instruction(self) -> tuple[float, bool]:
        """(cadence target [rpm], 0 = none; stop pedalling) for the simulated rider."""
        if self.phase == SPIN_UP:
            return self.params.high_cadence_rpm + SPIN_UP_MARGIN_RPM, False
        if self.phase == COAST:
            return 0.0, True
        return 0.0, False

    def abandon(self, reason: str) -> None:
        """The procedure stops unfinished (the Command moved on): FAILED, nothing learnt."""
        if self.running:
            self._fail(f"{PHASE_NAMES[self.phase]}: {reason}")

    def _fail(self, reason: str) -> int:
        self.phase, self.reason = FAILED, reason
        return self.phase

    def step(self, speed_rad_s: float, dt_s: float, torque_em_nm: float = 0.0, released: bool = True,
             sample: tuple[float, float] | None = None) -> int:
        """One batch: the motor speed estimate and the mean electromagnetic torque (motoring
        positive) of the batch that led to it; ``released``: the brake has let go (no ramp
        left); ``sample``: (time [s], motor speed [rad/s]) from a speed sensor
        (:class:`EncoderSpeed`), which the coast then takes instead of the estimate and the
        procedure's clock; once a run had one, a batch without one adds no sample. Returns the
        phase."""
        if not self.running:
            return self.phase
        p = self.params
        self.elapsed_s += dt_s
        self.phase_s += dt_s
        cadence_rpm = speed_rad_s * RPM_PER_RAD_S / self.gear_ratio
        if self.phase == SPIN_UP:
            if released and cadence_rpm >= p.high_cadence_rpm + 0.5 * SPIN_UP_MARGIN_RPM:
                self.above_s += dt_s
            else:
                self.above_s = 0.0
            if self.above_s >= SPIN_UP_HOLD_S:
                self.phase, self.phase_s = COAST, 0.0
            elif self.phase_s > p.spin_up_timeout_s:
                return self._fail(f"the rider did not reach {p.high_cadence_rpm:g} rpm within "
                                  f"{p.spin_up_timeout_s:g} s (he rode at {cadence_rpm:.1f} rpm)")
            return self.phase
        # COAST: samples from the top cadence down to the bottom one
        t_s = self.elapsed_s
        if sample is not None:
            self.sensed = True
            t_s, speed_rad_s = sample
            cadence_rpm = speed_rad_s * RPM_PER_RAD_S / self.gear_ratio
        elif self.sensed:
            return self._coast_timeout(cadence_rpm) or self.phase
        if cadence_rpm > self.min_cadence_rpm + SPED_UP_RPM:
            return self._fail(f"the flywheel sped up while coasting ({self.min_cadence_rpm:.1f} -> "
                              f"{cadence_rpm:.1f} rpm): the rider pedalled")
        if self._coast_timeout(cadence_rpm):
            return self.phase
        if cadence_rpm <= p.high_cadence_rpm:
            self.min_cadence_rpm = min(self.min_cadence_rpm, cadence_rpm)
            self.t.append(t_s)
            self.w.append(speed_rad_s)
            self.tem.append(torque_em_nm)
        if cadence_rpm <= p.low_cadence_rpm:
            try:
                self.result = fit_coast(self.t, self.w, self.tem, self.inertia_kgm2)
            except ValueError as exc:
                return self._fail(str(exc))
            self.phase = DONE
        return self.phase

    def _coast_timeout(self, cadence_rpm: float) -> int:
        """FAILED when the coast has lasted too long, else 0."""
        p = self.params
        if self.phase_s > p.coast_timeout_s:
            return self._fail(f"the coast from {p.high_cadence_rpm:g} to {p.low_cadence_rpm:g} rpm took "
                              f"more than {p.coast_timeout_s:g} s (at {cadence_rpm:.1f} rpm)")
        return 0
