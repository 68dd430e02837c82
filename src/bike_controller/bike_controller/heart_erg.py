"""Heart-rate ERG: the power target that holds the rider's heart rate at a target (no rclpy).

A trainer feature riders ask for (SmartSpin2k #471, research notes trainers.md section 5): in ERG
the target is a heart rate; the power follows it. The loop is slow (the heart answers the power
with tau ~ 69 s), so it runs inside the ERG law once per batch on the PlantState's heart rate.

Tuning by internal model control on the first-order heart of bike_plant.heart (the nominal
figures ``modes.hr_gain_bpm_per_w`` and ``modes.hr_time_constant_s``: two parameter sets, one
model), G(s) = K / (tau s + 1): the PI

    P = Kp e + Ki integral(e),   Kp = tau / (K lambda),   Ki = 1 / (K lambda),

cancels the pole and leaves the closed loop 1 / (lambda s + 1), lambda =
``modes.hr_closed_loop_s``. The power stays in [0, ``erg_power_max_w``]; the integral stops
while the power sits at a limit (no wind-up), and holds while there is no heart rate (0: no
rider's heart in the PlantState, e.g. a strap that fell silent). Asked beyond what the bike can
take (the SPMSM's brake at its envelope), the power still rises freely below the target, which
keeps that brake at its strongest; above the target it comes down from the power the bike takes,
not from the integral wound up beyond it.
"""
from __future__ import annotations

import math

from bike_plant.heart import HeartParams


class HeartRateErg:
    """The PI above. :meth:`start` sets the power it starts from (bumpless), :meth:`step` the
    power for the next batch."""

    def __init__(self, heart: HeartParams, closed_loop_s: float, power_max_w: float):
        heart.validate()
        if not (math.isfinite(closed_loop_s) and closed_loop_s > 0.0):
            raise ValueError(f"hr_closed_loop_s must be > 0, got {closed_loop_s!r}")
        k_lambda = heart.gain_bpm_per_w * closed_loop_s
        self.kp_w_per_bpm = heart.time_constant_s / k_lambda
        self.ki_w_per_bpm_s = 1.0 / k_lambda
        self.power_max_w = float(power_max_w)
        self.integral_w = 0.0
        self.power_w = 0.0
        self.saturated = False
        self.started = False

    def start(self, power_w: float) -> None:
        """Begin at ``power_w`` (clamped to the range): the first step adds only Kp e to it."""
        self.integral_w = min(max(float(power_w), 0.0), self.power_max_w)
        self.power_w = self.integral_w
        self.saturated = False
        self.started = True

    def step(self, target_bpm: float, heart_rate_bpm: float, dt_s: float, taken_w: float | None = None) -> float:
        """The power [W] for the next ``dt_s`` from the heart rate measured now; ``taken_w``:
        the power the bike takes now (the rider's, averaged) while it cannot take more."""
        if not (heart_rate_bpm > 0.0 and math.isfinite(heart_rate_bpm)):
            self.saturated = True                 # nothing to follow: hold the power, flagged
            return self.power_w
        err_bpm = target_bpm - heart_rate_bpm      # below the target -> more power
        if err_bpm < 0.0 and taken_w is not None and math.isfinite(taken_w):
            # above the target the power comes down from what the bike takes, not from an
            # integral wound up beyond it (a brake at its envelope: 300 W asked of an SPMSM bike
            # that took 200, unwound at 0.35 W/s, and the heart overshot by ~5 bpm)
            self.integral_w = min(self.integral_w, max(float(taken_w), 0.0))
        integral = self.integral_w + self.ki_w_per_bpm_s * err_bpm * max(dt_s, 0.0)
        raw = integral + self.kp_w_per_bpm * err_bpm
        self.power_w = min(max(raw, 0.0), self.power_max_w)
        self.saturated = raw != self.power_w
        if not self.saturated:
            self.integral_w = integral            # conditional integration
        return self.power_w
