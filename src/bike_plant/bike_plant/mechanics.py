"""Shaft loads of the bike (reference formulas; the per-period versions live in bldc.step_period).

Rider model (ARCHITECTURE.md, mechanical load): crank torque from a torque-cadence line
with two torque peaks per crank turn (one per leg),
    T_crank = effort * T0 * (1 - cadence / cadence_max) * (1 + 0.5 cos(2 crank_angle)),
seen by the motor through the gear ratio (motor / crank ~ 35): T_motor = T_crank / ratio.
The rider holds a target cadence by adjusting effort (0..1) with a PI on the cadence error
(gains for a wanted cadence response: :func:`rider_pi_gains`).
A prime mover (paper 000, section 5) holds the speed exactly and supplies any torque.
"""
from __future__ import annotations

import math

import numpy as np

from .params import RPM_PER_RAD_S, LoadParams


# virtual gears (wheel turns per crank turn) a Command or a profile may give: wide enough for
# any road or track gear (34/34 = 1.0 .. 56/11 = 5.1) and the apps' virtual gear tables
VIRTUAL_GEAR_MIN = 0.3
VIRTUAL_GEAR_MAX = 8.0


def virtual_gear_problem(ratio, allow_default: bool = True) -> str | None:
    """Why ``ratio`` is not a virtual gear (None if it is): a number in [VIRTUAL_GEAR_MIN,
    VIRTUAL_GEAR_MAX], or 0 (the config's gear) where ``allow_default``."""
    if isinstance(ratio, bool) or not isinstance(ratio, (int, float)) or not math.isfinite(ratio):
        return f"a gear ratio must be a finite number, got {ratio!r}"
    if allow_default and ratio == 0:
        return None
    if not VIRTUAL_GEAR_MIN <= ratio <= VIRTUAL_GEAR_MAX:
        return (f"gear ratio {ratio!r} outside [{VIRTUAL_GEAR_MIN:g}, {VIRTUAL_GEAR_MAX:g}] wheel turns per crank turn"
                + (" (0: the config's gear)" if allow_default else ""))
    return None


# a road a Command may give (FTMS Indoor Bike Simulation carries Crr in 1e-4 up to 0.0255, Cw
# in 0.01 kg/m up to 2.55 and wind in mm/s up to 32.8 m/s; these bounds hold any real road)
ROAD_CRR_MAX = 0.05
ROAD_CW_MAX_KG_M = 3.0
ROAD_WIND_MAX_MPS = 40.0


# a cadence target a Command may give the rider (0: none); the workout readers take the same rule
RIDER_CADENCE_MIN_RPM = 10.0
RIDER_CADENCE_MAX_RPM = 250.0


def rider_cadence_problem(cadence_rpm) -> str | None:
    """Why ``cadence_rpm`` is not a rider's cadence target (None if it is): 0 (none) or a
    finite number in [RIDER_CADENCE_MIN_RPM, RIDER_CADENCE_MAX_RPM]."""
    if isinstance(cadence_rpm, bool) or not isinstance(cadence_rpm, (int, float)) or not math.isfinite(cadence_rpm):
        return f"cadence target must be a finite number, got {cadence_rpm!r}"
    if cadence_rpm != 0 and not RIDER_CADENCE_MIN_RPM <= cadence_rpm <= RIDER_CADENCE_MAX_RPM:
        return (f"cadence target {cadence_rpm!r} rpm outside [{RIDER_CADENCE_MIN_RPM:g}, {RIDER_CADENCE_MAX_RPM:g}] "
                "(0: none)")
    return None


def road_problem(crr, cw_kg_m, wind_mps) -> str | None:
    """Why (crr, cw_kg_m, wind_mps) is not a road a Command may give (None if it is)."""
    for name, value, lo, hi in (("crr", crr, 0.0, ROAD_CRR_MAX), ("cw_kg_m", cw_kg_m, 0.0, ROAD_CW_MAX_KG_M),
                                ("wind_mps", wind_mps, -ROAD_WIND_MAX_MPS, ROAD_WIND_MAX_MPS)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            return f"road {name} must be a finite number, got {value!r}"
        if not lo <= value <= hi:
            return f"road {name} {value!r} outside [{lo:g}, {hi:g}]"
    return None


def rider_crank_torque_nm(effort: float, cadence_rpm: float, crank_angle_rad: float, load: LoadParams) -> float:
    """Crank torque of the rider (>= 0: a rider pedals, never brakes)."""
    line = max(0.0, 1.0 - cadence_rpm / load.rider_cadence_max_rpm)
    return min(max(effort, 0.0), 1.0) * load.rider_t0_nm * line * (1.0 + 0.5 * math.cos(2.0 * crank_angle_rad))


def rider_motor_torque_nm(effort: float, motor_speed_rad_s: float, crank_angle_rad: float, load: LoadParams) -> float:
    """The rider's torque on the motor shaft (through the gear)."""
    cadence_rpm = motor_speed_rad_s / load.gear_ratio * RPM_PER_RAD_S
    return rider_crank_torque_nm(effort, cadence_rpm, crank_angle_rad, load) / load.gear_ratio


def rider_effort_update(integ: float, err_rad_s: float, kp: float, ki: float, dt_s: float) -> tuple[float, float]:
    """One step of the rider's effort PI on the cadence error (target - cadence, crank rad/s):
    (integral, effort in 0..1). Conditional integration: while the effort is pinned at 0 and the
    cadence is still too high (or at 1 and still too low) the integral holds. Without it a rider
    told to drop from 95 to 65 rpm banked the whole overspeed as negative effort, stopped pushing
    for 2 s and sank to 53 rpm; a rider eases off, then pushes again. The BLDC kernel
    (bike_plant.bldc._rider) does the same inline."""
    new = min(max(integ + ki * err_rad_s * dt_s, -1.0), 1.0)
    raw = kp * err_rad_s + new
    if (raw < 0.0 and err_rad_s < 0.0) or (raw > 1.0 and err_rad_s > 0.0):
        new = integ
    return new, min(max(kp * err_rad_s + new, 0.0), 1.0)


def rider_pi_gains(inertia_at_crank_kgm2: float, load: LoadParams, damping: float = 0.7,
                   natural_rad_s: float = 2.0) -> tuple[float, float]:
    """(rider_kp [1/(rad/s)], rider_ki [1/rad]) that give the rider's cadence loop the wanted
    damping and natural frequency in ERG, the hardest case.

    Why ERG: its load P / w falls with cadence exactly as steeply as the rider's torque line at
    the power apex (c = Cmax / 2, the recreational preset's 80 rpm of 160), so the two slopes
    cancel and the PI alone must damp the crank inertia J:
        J dw = T0 (1 - c*/Cmax) (kp e + ki int e),  e = w* - w
    is a second-order loop with wn^2 = ki K / J and 2 zeta wn = kp K / J, K = T0 (1 - c*/Cmax).
    The defaults (zeta 0.7, wn 2 rad/s) put the cadence back within 2-3 s of an ERG step, as a
    rider does; the gains once in the configs (0.05, 0.1) gave the BLDC bike's 12 kg m^2 at
    the crank zeta 0.18 and a 9 s ring (+-20 % rider power after a step).
    """
    k_nm = load.rider_t0_nm * max(1.0 - load.rider_target_cadence_rpm / load.rider_cadence_max_rpm, 1e-3)
    return (2.0 * damping * natural_rad_s * inertia_at_crank_kgm2 / k_nm,
            natural_rad_s ** 2 * inertia_at_crank_kgm2 / k_nm)


def friction_torque_nm(speed_rad_s: float, friction_nms: float, dry_friction_nm: float = 0.0,
                       dry_friction_speed_rad_s: float = 0.1) -> float:
    """Friction opposing the rotation [N m]: viscous B w (paper 000 / 001, Eq. 3 of 001) plus
    Coulomb Tc tanh(w / w_s), the plants' model (``spmsm.friction_torque`` is its numba twin;
    the BLDC bike has no Coulomb term). The mode laws take it with the controller's nominal
    figures, as a trainer's power meter models its own losses."""
    f = friction_nms * speed_rad_s
    if isinstance(speed_rad_s, np.ndarray) or isinstance(dry_friction_nm, np.ndarray):   # the report's arrays
        return f + dry_friction_nm * np.tanh(speed_rad_s / dry_friction_speed_rad_s)
    if dry_friction_nm:
        f += dry_friction_nm * math.tanh(speed_rad_s / dry_friction_speed_rad_s)
    return f


def prime_mover_torque_nm(torque_em_nm: float, friction_nms: float, speed_rad_s: float) -> float:
    """Torque a prime mover supplies to hold the speed: it balances T_em and friction."""
    return friction_nms * speed_rad_s - torque_em_nm
