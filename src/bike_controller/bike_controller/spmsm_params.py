"""The SPMSM controller's parameters (the ``controller:`` section of an SPMSM config; paper
001, sections 3-5, 7). Plain dataclasses, no numba: ./bike run's checks and the mode ranges
read them without the kernels of :mod:`bike_controller.spmsm_control`, which re-exports them."""
from __future__ import annotations

import math
from dataclasses import dataclass

from bike_plant.config import build_dataclass, require_positive, section

FAMILIES = ("predictive", "pi")


@dataclass
class SpmsmControllerParams:
    """controller: section of an SPMSM config (paper 001, sections 3-5, 7).

    Weights (SI units: speed in rad/s, current in A, voltage in V):
    speed_weight_r [(rad/s)^2/A^2] = 0.008 -> beta_s = b^2/(b^2 + r) = 0.60 (b = 0.11 rad/s per A);
    current_weight_r [A^2/V^2] = 4.2e-5 -> beta_c = 0.70 (b = 0.00985 A/V).
    speed_reference_pole_hz = 10 (reference trajectory, module doc). Without a trajectory
    the law needs beta_s ~ 0.15: larger values limit-cycle once the measurement delay (M/T
    estimate, ~half a speed sample) and the current loop are in the loop (beta 0.6: 2 A of
    iq ripple at 100 r/min), smaller ones ring (zeta = sqrt(beta)/2) and recover more
    slowly. With the 10 Hz trajectory beta 0.6 holds steady with either speed estimate.
    PI poles: double real poles at pi_speed_pole_hz / pi_current_pole_hz (see module doc).
    """
    family: str = "predictive"
    speed_loop_periods: int = 10          # 1 ms speed loop / 100 us current loop (section 7)
    speed_weight_r: float = 0.008
    current_weight_r: float = 4.2e-5
    pi_speed_pole_hz: float = 1.5
    pi_current_pole_hz: float = 200.0
    current_limit_a: float = 15.0
    voltage_margin: float = 0.95
    flux_weakening: bool = True
    angle_compensation: bool = True       # inverse Park at the period's mid angle
    speed_estimator: str = "observer"     # observer | mt (M/T method from the encoder capture)
    observer_pole_hz: float = 5.0         # triple pole of the speed observer (config comment)
    observer_reacquire_pole_hz: float = 40.0  # ... while it re-acquires after skipped plant states
    isokinetic_observer_pole_hz: float = 40.0  # ... while a session's isokinetic speed loop runs
    speed_delay_compensation: bool = False  # mt only: extrapolate the M/T estimate by half a sample
    speed_filter_hz: float = 0.0          # first-order low-pass on the speed the speed law sees (0: off)
    speed_reference_pole_hz: float = 10.0  # predictive: first-order path towards the command (0: off)
    computation_delay_periods: int = 0    # 1: duties computed in period k are applied in k + 1 (DSP)
    current_sensor_lsb_a: float = 0.0     # ADC step of the phase-current measurement (0: exact)
    speed_ref0_rpm: float = 0.0
    brake_torque0_nm: float = 0.0
    model: str = "nominal"
    # session modes: time constant of the torque's running mean whose sign picks the relay path,
    # and the least time on a path (spmsm_session.RelayPath; 0: follow every batch's sign)
    relay_hold_s: float = 0.5
    # a switch-over from the inverter to the rectifier path (paper 001, Fig. 2/8): the inverter
    # first takes iq to zero, and only then asks the relay to move, for at most this long (0: the
    # request goes to the relay at once; spmsm_control.control_period)
    relay_predrain_s: float = 0.05

    def validate(self) -> None:
        if self.family not in FAMILIES:
            raise ValueError(f"family must be one of {', '.join(FAMILIES)}, got {self.family!r}")
        require_positive(self, "speed_loop_periods", "pi_speed_pole_hz", "pi_current_pole_hz", "current_limit_a",
                         "voltage_margin")
        if self.speed_weight_r < 0 or self.current_weight_r < 0:
            raise ValueError("speed_weight_r and current_weight_r must be >= 0")
        if self.voltage_margin > 1.0:
            raise ValueError(f"voltage_margin must be in (0, 1], got {self.voltage_margin!r}")
        if self.model not in ("nominal", "actual"):
            raise ValueError(f"model must be 'nominal' or 'actual', got {self.model!r}")
        if self.speed_estimator not in ("observer", "mt", "m"):
            raise ValueError(f"speed_estimator must be 'observer', 'mt' or 'm', got {self.speed_estimator!r}")
        if self.computation_delay_periods not in (0, 1):
            raise ValueError(f"computation_delay_periods must be 0 or 1, got {self.computation_delay_periods!r}")
        if not 0.0 <= self.current_sensor_lsb_a <= 1.0:
            raise ValueError(f"current_sensor_lsb_a must be in [0, 1] A, got {self.current_sensor_lsb_a!r}")
        if not self.speed_filter_hz >= 0.0:
            raise ValueError(f"speed_filter_hz must be >= 0, got {self.speed_filter_hz!r}")
        if not (math.isfinite(self.speed_reference_pole_hz) and self.speed_reference_pole_hz >= 0.0):
            raise ValueError(f"speed_reference_pole_hz must be a finite number >= 0, got {self.speed_reference_pole_hz!r}")
        require_positive(self, "observer_pole_hz")
        require_positive(self, "observer_reacquire_pole_hz")
        require_positive(self, "isokinetic_observer_pole_hz")
        if self.brake_torque0_nm < 0:
            raise ValueError("brake_torque0_nm must be >= 0")
        if not (math.isfinite(self.relay_hold_s) and self.relay_hold_s >= 0.0):
            raise ValueError(f"relay_hold_s must be a finite number >= 0, got {self.relay_hold_s!r}")
        if not (math.isfinite(self.relay_predrain_s) and self.relay_predrain_s >= 0.0):
            raise ValueError(f"relay_predrain_s must be a finite number >= 0, got {self.relay_predrain_s!r}")


def controller_params_from_config(cfg: dict) -> SpmsmControllerParams:
    path = cfg.get("_config_path")
    return build_dataclass(SpmsmControllerParams, section(cfg, "controller", path), "controller", path)
