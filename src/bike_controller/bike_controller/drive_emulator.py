"""bike-drive-emulator: an ODrive-like drive (CANSimple 0.6.x) -- or a VESC (``--protocol
vesc_can``) -- on any python-can bus.

It stands in for a real drive so the plant node's ``backend: can``, a script or a test
can talk CAN without hardware. Three layers, each usable alone (no ROS imports but the optional
rider display below):

* physics of the bike from a config file (config/bldc_default.yaml by default), chosen
  with ``--physics``:

  - ``plant`` (default): the bike_plant machine models themselves behind the drive's own
    current loop, advanced in compiled batches (one numba call per ~1 ms tick, N control
    periods each). :class:`SpmsmPlantDrive`: bike_plant.spmsm (exact dq machine, average
    inverter with its hexagon voltage limit and dead time, back-EMF harmonics, cogging,
    friction, the config's shaft and load) driven by the SPMSM current loop of
    bike_controller.spmsm_control in torque mode (PI family by default: pole placement at
    controller.pi_current_pole_hz, decoupling, flux weakening / MTPV region logic within
    the drive's current limit; paper 001 section 5) -- so the voltage limit, back-EMF and
    the rider / flywheel are the plant's. Braking regenerates through the inverter (four
    quadrants, like an ODrive; the relay stays on the inverter). :class:`BldcPlantDrive`:
    bike_plant.bldc (trapezoidal BLDC, 6-switch bridge, battery + brake resistor, shaft,
    rider in the kernel) driven by bike_controller.bldc_control's hysteresis current law
    (paper 000, Fig. 7/10: commutation from the Hall state, one edge per 50 us period)
    with the current command I* = |T| / kt from the torque setpoint: motoring pattern for
    T > 0, generating (boost) pattern for T < 0 (quadrants I and II, forward rotation).
  - ``average``: :class:`AverageTorqueDrive`, the light model for slow machines: average
    torque ``T_em = kt * iq`` with a first-order closed current loop
    ``iq' = (iq* - iq) / tau``, no voltage limit, driving the same shaft and load
    (inertia + viscous and Coulomb friction; rider, prime mover, dynamometer profile or none;
    bike_plant.params.LoadParams and bike_plant.mechanics) and battery (+ brake resistor).
* :class:`DriveFirmware` -- the axis logic of an ODrive: states IDLE(1) and
  CLOSED_LOOP_CONTROL(8), torque (1) and velocity (2) control, limits, error latching,
  Clear_Errors, the watchdog, Estop (ESTOP_REQUESTED, axis IDLE).
* :class:`VescFirmware` / :class:`VescEmulator` -- the same physics behind a VESC (vedderb/bldc
  documentation/comm_can.md): SET_CURRENT / SET_CURRENT_BRAKE / SET_CURRENT_REL / SET_RPM run
  the motor at once (no arming), the command timeout (--watchdog-s) releases it without an
  error, STATUS .. STATUS_5 are broadcast every --heartbeat-ms.
* :class:`DriveEmulator` -- the CAN side: decodes host frames with the same codec as
  the host (:class:`bike_plant.can.protocol.OdriveCanSimpleCodec`), answers RTR
  requests, sends cyclic messages, and paces physics against time.monotonic in real
  time (a 1 kHz tick; plant physics: the control periods due, in one compiled batch;
  average physics: sub-steps). Its exit summary reports the real-time margin
  (physics_realtime_factor = simulated / wall time spent on physics, physics_lag_max_ms).
  The rider (plant physics' or the average model's) follows what the trainer tells him with
  ``--rider-topic`` (:class:`RiderDisplay`, the only rclpy use, imported then): a workout's
  cadence target, a spin-down's "stop pedalling", from the controller's DriveCommand; and
  with ``--heart-rate-topic`` his heart rate (bike_plant.heart) goes out once a second as a
  chest strap's would (bike_msgs/HeartRate), which the plant node puts into the PlantState.
  ``--truth-topic``: the physics' ground truth (bike_msgs/DriveTruth: the rider's true power
  and work, the shaft's true torque, speed and energy balance, next to the kt Iq it reports),
  one sample per new /clock of the plant heard, stamped with it: the plant's sim time stands
  still while the drive is not armed, this physics' clock does not, and the report puts the
  truth on the plant's time line by those stamps (bike_session.report).
  Fault injection: --silent-after-s, --garbage-rate,
  --fault-at-s / SIGUSR1 with --fault (an error that disarms the axis, or IDLE) and
  --fault-persist (Clear_Errors that do not clear it).

Modelling choices (what a host sees):
* velocities and positions are at the MOTOR shaft (rev/s, rev); crank cadence =
  motor speed / load.gear_ratio (35 for the default bike);
* measurements (plant physics): Vel_Estimate / Pos_Estimate are the plant's shaft speed
  and angle; Iq_Measured is the mean over the last batch of the plant's q current (SPMSM)
  or of the hysteresis law's feedback current (|ia| + |ib| + |ic|) / 2, signed by the
  quadrant (BLDC); Torque_Estimate = kt * Iq_Measured, as an ODrive estimates it (the
  plant's true mean torque is Mechanical_Power / speed; for the BLDC braking at 2600-2800
  r/min kt I overstates it by -1 % at 0.5 N m, +2.6 % at 1 N m, +6.6 % at 2 N m, because of
  the commutation dips, paper 000 section 4.3; SPMSM within 0.5 %); Iq_Setpoint is the
  current loop's reference (SPMSM: after the current / voltage-limit region logic;
  BLDC: the signed hysteresis command); Bus_Voltage the plant's DC link (BLDC: battery
  OCV - R i with the brake resistor; SPMSM: the 24 V battery set); Bus_Current = minus
  the plant's mean battery current (positive = discharging); Electrical_Power = bus
  voltage x bus current, Mechanical_Power = mean T_em w of the plant;
* IDLE (plant physics): gates off -- the bridge's diodes rectify into the battery when
  the line-to-line back-EMF exceeds the bus (the SPMSM of config/spmsm_*.yaml does above
  ~190 r/min at 24 V: an idle drive brakes a fast rider, as a real one would);
* current loop of the average model: an ODrive's current controller is a PI tuned to a
  bandwidth (motor.config.current_control_bandwidth, default 1000 rad/s), so the closed
  loop is first order with tau = 1 / bandwidth = 1 ms (--current-tau-s). The motor's own
  L/R (117 uH / 6 mOhm = 20 ms for the default BLDC) is the open-loop constant a PI
  cancels, not the closed-loop response. No voltage limit is modelled there; copper
  loss: BLDC 2 R_phase iq^2 (two phases conduct), SPMSM 1.5 R_s iq^2; bus: the battery of
  the config (OCV(soc), internal resistance) with the brake resistor's S0 chopper (as the
  plant's: s0_on_v / s0_off_v, never draining the pack); Bus_Current is the DC current drawn from the battery
  by the drive incl. its brake resistor (positive = discharging); Electrical_Power =
  mechanical power + copper loss;
* watchdog (0.6.x: axis.config.watchdog_timeout): fed by Set_Input_Torque,
  Set_Input_Vel and Set_Axis_State (``--watchdog-fed-by any``: by every frame addressed to
  the axis, RTR requests included, as the open 0.5.x firmware does: odriverobotics/ODrive
  Firmware/communication/can/can_simple.cpp, do_command() calls axis.watchdog_feed() before
  it looks at the command; what the closed 0.6.x firmware feeds it with is not published
  beyond the can_watchdog.py example); checked only in CLOSED_LOOP_CONTROL; on expiry the
  axis drops to IDLE with ODRIVE_ERROR_WATCHDOG_TIMER_EXPIRED = 0x01000000 (source:
  odriverobotics/ros_odrive odrive_base/include/odrive_enums.h) in Axis_Error,
  Active_Errors and Disarm_Reason, Procedure_Result DISARMED (3), torque zero;
* inputs (torque, velocity) are zeroed whenever the axis leaves closed loop, so a
  re-enabled axis starts from zero torque; entering closed loop with latched errors is
  refused (stays IDLE, Procedure_Result DISARMED); calibration states (2, 3, 4, 6, 7,
  10, 12, 13, 14) complete at once with SUCCESS (the model needs no calibration); other
  requests get INVALID_STATE;
* protections: overspeed (|v| > 1.2 vel_limit in closed loop) -> VELOCITY_LIMIT_VIOLATION;
  bus above the machine's overvoltage_v -> DC_BUS_OVER_VOLTAGE, below 0.75 of the empty
  pack voltage -> DC_BUS_UNDER_VOLTAGE; both disarm;
* torque mode limits the torque near the velocity limit like ODrive's
  enable_torque_mode_vel_limit: T in [(-v_lim - v) k_v, (v_lim - v) k_v].
"""
from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import math
import random
import signal
import sys
import threading
import time
from typing import Callable

import can
import numpy as np
from numba import njit

from bike_plant import bldc as K
from bike_plant import mechanics
from bike_plant import params as P
from bike_plant import spmsm as M
from bike_plant.can.protocol import (DRIVE_TO_HOST, ESTOP_CMD, HOST_TO_DRIVE, MALFORMED_REASONS,
                                     ODRIVE_BROADCAST_NODE_ID, PROTOCOLS, RPM_PER_REV_S, VESC_CAN_PACKET_ID_MAX,
                                     VESC_DRIVE_TO_HOST, VESC_HOST_TO_DRIVE, VESC_ID_MAX, VESC_TACHO_PER_EREV,
                                     AxisState, ControlMode, InputMode, ODriveError, OdriveCanSimple,
                                     OdriveCanSimpleCodec, ProcedureResult, VescCan, VescCanCodec, _EchoFilter,
                                     error_names)
from bike_plant.config import ConfigError, load_config, section
from bike_plant.heart import RiderHeart
from bike_plant.memory import LoadTimePageReleaser, release_clean_library_pages
from bike_plant.params import RPM_PER_RAD_S, TWO_PI, LoadParams
from bike_plant.sim import BldcPlant

from . import bldc_control as BC
from . import spmsm_control as SC
from . import bldc_params, speed_estimator, torque_command

# the batch kernels below compile the plant and control-law kernels into this module's
# numba cache: drop it when one of those modules changed (numba keys it on this file only)
K.invalidate_stale_numba_cache(__file__, [K.__file__, K._jit.__file__, P.__file__, M.__file__, SC.__file__,
                                          BC.__file__, speed_estimator.__file__, torque_command.__file__,
                                          bldc_params.__file__])

CALIBRATION_STATES = frozenset({2, 3, 4, 6, 7, 10, 12, 13, 14})
DEFAULT_CURRENT_TAU_S = 1.0e-3     # 1 / ODrive's default current_control_bandwidth (1000 rad/s)
OVERSPEED_TOLERANCE = 1.2          # ODrive controller.config.vel_limit_tolerance default
LOAD_KINDS = ("rider", "prime_mover", "dynamometer", "none")
PHYSICS = ("plant", "average")     # --physics: the bike_plant kernels | the average-torque model
DEFAULT_SPEED_OBSERVER_HZ = 160.0  # SPMSM drive's speed observer pole (~ ODrive encoder bandwidth 1000 rad/s)
CURRENT_LOOPS = ("pi", "predictive")   # SPMSM current-loop family (bike_controller.spmsm_control)
HEART_RATE_PERIOD_S = 1.0         # the emulated rider's chest strap: one reading a second
# --truth-topic: samples a late-matching reader (the recorder) still gets, 10 s at a 10 ms /clock
TRUTH_HISTORY = 1000


# =======================================================================================
# physics
@dataclasses.dataclass
class DriveModelParams:
    """Everything the average-torque model needs, from either machine's config."""
    machine: str
    torque_constant_nm_per_a: float
    copper_resistance_ohm: float        # P_cu = R * iq^2
    inertia_kgm2: float
    friction_nms: float
    speed0_rpm: float
    load: LoadParams                    # kind rider / prime_mover / none (+ gear, rider, speed schedule)
    load_kind: str                      # LOAD_KINDS (dynamometer only from an SPMSM config)
    dyno_time_s: list
    dyno_torque_nm: list                # opposes positive rotation (paper 001, Eq. 3)
    v_empty_v: float
    v_full_v: float
    r_internal_ohm: float
    capacity_ah: float
    soc0: float
    r_brake_ohm: float                  # 0: no brake resistor
    s0_on_v: float
    s0_off_v: float
    overvoltage_v: float
    undervoltage_v: float
    current_limit_a: float              # drive default (Set_Limits changes it at run time)
    current_tau_s: float = DEFAULT_CURRENT_TAU_S
    dry_friction_nm: float = 0.0        # Coulomb friction (the SPMSM config's), next to the viscous B
    dry_friction_speed_rpm: float = 1.0
    dyno_brake: bool = False            # load.dyno_mode brake (SPMSM): passive, holds a stopped shaft

    @classmethod
    def from_config(cls, cfg: dict, current_tau_s: float = DEFAULT_CURRENT_TAU_S) -> "DriveModelParams":
        """From a loaded config (bike_plant.config.load_config): machine bldc or spmsm."""
        machine = cfg.get("machine", "bldc")
        path = cfg.get("_config_path")
        ctrl = section(cfg, "controller", path)
        if machine == "bldc":
            from bike_plant.params import plant_params_from_config
            p = plant_params_from_config(cfg)
            b, bt = p.bldc, p.battery
            return cls(machine="bldc", torque_constant_nm_per_a=b.kt_nm_per_a,
                       copper_resistance_ohm=2.0 * b.r_phase_ohm,
                       inertia_kgm2=p.mech.inertia_kgm2, friction_nms=p.mech.friction_nms,
                       speed0_rpm=p.mech.speed0_rpm, load=p.load, load_kind=p.load.kind,
                       dyno_time_s=[0.0], dyno_torque_nm=[0.0],
                       v_empty_v=bt.v_empty_v, v_full_v=bt.v_full_v, r_internal_ohm=bt.r_internal_ohm,
                       capacity_ah=bt.capacity_ah, soc0=bt.soc0, r_brake_ohm=bt.r_brake_ohm,
                       s0_on_v=bt.s0_on_v, s0_off_v=bt.s0_off_v, overvoltage_v=b.overvoltage_v,
                       undervoltage_v=0.75 * bt.v_empty_v,
                       current_limit_a=float(ctrl.get("current_limit_a", 60.0)), current_tau_s=current_tau_s)
        if machine == "spmsm":
            try:
                from bike_plant.spmsm import plant_params_from_config as spmsm_params
            except ImportError as exc:   # pragma: no cover - depends on the SPMSM module
                raise ConfigError(f"machine 'spmsm' needs bike_plant.spmsm ({exc})", path, "machine") from None
            p = spmsm_params(cfg)
            m, bt, ld = p.spmsm, p.battery, p.load
            # (the rider's LoadParams keeps the prime-mover speed too: --load prime_mover)
            load = dataclasses.replace(ld.rider_load_params(), speed_rpm=ld.speed_rpm,
                                       schedule_time_s=list(ld.schedule_time_s),
                                       schedule_speed_rpm=list(ld.schedule_speed_rpm)) if ld.kind == "rider" else LoadParams(
                kind=ld.kind if ld.kind in ("prime_mover", "none") else "none", speed_rpm=ld.speed_rpm,
                schedule_time_s=list(ld.schedule_time_s), schedule_speed_rpm=list(ld.schedule_speed_rpm),
                gear_ratio=ld.gear_ratio)
            # the SPMSM battery is a fixed-voltage set: no OCV curve, internal resistance assumed 50 mOhm
            return cls(machine="spmsm",
                       torque_constant_nm_per_a=m.torque_constant_nm_per_a * m.flux_scale,
                       copper_resistance_ohm=1.5 * m.rs_ohm * m.rs_scale,
                       inertia_kgm2=p.mech.inertia_kgm2, friction_nms=p.mech.friction_nms,
                       speed0_rpm=p.mech.speed0_rpm, load=load, load_kind=ld.kind,
                       dyno_time_s=list(ld.dyno_time_s), dyno_torque_nm=list(ld.dyno_torque_nm),
                       v_empty_v=bt.nominal_v, v_full_v=bt.nominal_v, r_internal_ohm=0.05,
                       capacity_ah=bt.capacity_ah, soc0=bt.soc0, r_brake_ohm=0.0,
                       s0_on_v=math.inf, s0_off_v=math.inf, overvoltage_v=p.regen.link_max_v,
                       undervoltage_v=0.75 * bt.nominal_v,
                       current_limit_a=float(ctrl.get("current_limit_a", 15.0)), current_tau_s=current_tau_s,
                       dry_friction_nm=m.dry_friction_nm, dry_friction_speed_rpm=m.dry_friction_speed_rpm,
                       dyno_brake=ld.dyno_mode == "brake")
        raise ConfigError(f"the drive emulator supports machine 'bldc' or 'spmsm', got {machine!r}", path, "machine")


class _DriveReadouts:
    """Readouts every drive model derives the same way from its state (speed_rad_s, iq_a)."""

    @property
    def speed_rev_s(self) -> float:
        return self.speed_rad_s / TWO_PI

    @property
    def torque_estimate_nm(self) -> float:
        """kt x Iq_Measured, as an ODrive estimates its torque."""
        return self.params.torque_constant_nm_per_a * self.iq_a

    @property
    def kinetic_energy_j(self) -> float:
        """1/2 J w^2 of the shaft (J of the config's mechanics)."""
        return 0.5 * self.params.inertia_kgm2 * self.speed_rad_s ** 2


class AverageTorqueDrive(_DriveReadouts):
    """Motor (average torque, first-order current loop) + shaft + load + battery.

    :meth:`step` advances ``dt_s`` with a current setpoint; everything else is state
    read by the firmware. Explicit Euler for the shaft (dt ~ 0.25 ms against a
    mechanical time constant of seconds), exact discretisation for the current loop.
    """

    def __init__(self, params: DriveModelParams):
        self.params = params
        p = params
        self.time_s = 0.0
        self.iq_a = 0.0
        self.iq_setpoint_a = 0.0
        load = p.load
        speed0_rpm = load.speed_rpm if p.load_kind == "prime_mover" else p.speed0_rpm
        if p.load_kind == "prime_mover" and load.schedule_time_s:
            speed0_rpm = self._scheduled_speed_rpm(0.0)
        self.speed_rad_s = speed0_rpm / RPM_PER_RAD_S
        self.position_rev = 0.0
        self.soc = p.soc0
        self.brake_on = False
        self.crank_angle_rad = 0.0
        self.rider_effort = load.rider_effort0
        self.rider_integrator = load.rider_effort0
        self.rider_target_rpm = load.rider_target_cadence_rpm   # set_rider_instruction moves it
        self.rider_stopped = False
        self.heart = RiderHeart(load.heart_params()) if p.load_kind == "rider" else None
        # the shaft's ledger (the truth of --truth-topic): rider (load) work, int T_em w dt, friction loss
        self.rider_energy_j = 0.0
        self.shaft_energy_j = 0.0
        self.friction_energy_j = 0.0
        self.torque_em_nm = 0.0
        self.load_torque_nm = 0.0
        self.mechanical_power_w = 0.0
        self.electrical_power_w = 0.0
        self.bus_voltage_v = self.ocv_v()
        self.bus_current_a = 0.0

    # ------------------------------------------------------------ helpers
    def ocv_v(self) -> float:
        p = self.params
        return p.v_empty_v + (p.v_full_v - p.v_empty_v) * min(max(self.soc, 0.0), 1.0)

    def _scheduled_speed_rpm(self, t_s: float) -> float:
        load = self.params.load
        speed = load.speed_rpm
        for ts, sp in zip(load.schedule_time_s, load.schedule_speed_rpm):
            if t_s + 1e-12 >= ts:
                speed = sp
        return speed

    def _dyno_torque_nm(self, t_s: float) -> float:
        p = self.params
        torque = p.dyno_torque_nm[0]
        for ts, tq in zip(p.dyno_time_s, p.dyno_torque_nm):
            if t_s + 1e-12 >= ts:
                torque = tq
        return torque

    def _rider_torque_nm(self, omega_rad_s: float, dt_s: float) -> float:
        """The rider of the sim plant (bike_plant.bldc._rider): PI effort on cadence, crank
        torque from bike_plant.mechanics, seen at the motor through the gear."""
        load = self.params.load
        cadence_rad_s = omega_rad_s / load.gear_ratio
        err = self.rider_target_rpm / RPM_PER_RAD_S - cadence_rad_s
        if self.rider_stopped:
            self.rider_effort = 0.0
        else:
            self.rider_integrator, self.rider_effort = mechanics.rider_effort_update(
                self.rider_integrator, err, load.rider_kp, load.rider_ki, dt_s)
        t_crank = mechanics.rider_crank_torque_nm(self.rider_effort, cadence_rad_s * RPM_PER_RAD_S,
                                                  self.crank_angle_rad, load)
        self.crank_angle_rad = (self.crank_angle_rad + cadence_rad_s * dt_s) % TWO_PI
        return t_crank / load.gear_ratio

    def set_rider_instruction(self, cadence_rpm: float, stop: bool) -> None:
        """What the rider is told (a workout's cadence, 0: his own; a spin-down's stop)."""
        self.rider_target_rpm = cadence_rpm if cadence_rpm > 0 else self.params.load.rider_target_cadence_rpm
        self.rider_stopped = bool(stop)

    def _friction_nm(self, omega: float) -> float:
        p = self.params
        return mechanics.friction_torque_nm(omega, p.friction_nms, p.dry_friction_nm,
                                            p.dry_friction_speed_rpm / RPM_PER_RAD_S)

    # ------------------------------------------------------------ step
    def step(self, dt_s: float, iq_setpoint_a: float, enabled: bool = True, current_limit_a: float | None = None) -> None:
        """Advance dt_s with the current setpoint (the firmware already limited it; an
        IDLE axis passes 0 and enabled False: this model does not tell them apart)."""
        p = self.params
        self.iq_setpoint_a = iq_setpoint_a
        self.iq_a += (1.0 - math.exp(-dt_s / p.current_tau_s)) * (iq_setpoint_a - self.iq_a)
        t_em = p.torque_constant_nm_per_a * self.iq_a
        omega = self.speed_rad_s
        kind = p.load_kind
        t_friction = self._friction_nm(omega)
        if kind == "prime_mover":
            # speed held exactly; the prime mover supplies whatever torque that takes
            t_load = t_friction - t_em
            omega_new = self._scheduled_speed_rpm(self.time_s + dt_s) / RPM_PER_RAD_S
            # a schedule step: the prime mover supplies the flywheel's energy too (as the plant's ledger)
            self.rider_energy_j += 0.5 * p.inertia_kgm2 * (omega_new * omega_new - omega * omega)
        else:
            if kind == "rider":
                t_load = self._rider_torque_nm(omega, dt_s)
            elif kind == "dynamometer":
                tl = self._dyno_torque_nm(self.time_s)
                if p.dyno_brake:
                    # the plant's passive brake (spmsm.brake_torque): TL shaped as the Coulomb friction,
                    # so a stopped shaft is held, never turned backwards
                    tl = mechanics.friction_torque_nm(omega, 0.0, tl, p.dry_friction_speed_rpm / RPM_PER_RAD_S)
                t_load = -tl
            else:
                t_load = 0.0
            omega_new = omega + dt_s * (t_em + t_load - t_friction) / p.inertia_kgm2
        omega_avg = 0.5 * (omega + omega_new)
        self.rider_energy_j += t_load * omega_avg * dt_s
        self.shaft_energy_j += t_em * omega_avg * dt_s
        self.friction_energy_j += t_friction * omega_avg * dt_s
        self.speed_rad_s = omega_new
        self.position_rev += omega_avg * dt_s / TWO_PI
        self.torque_em_nm = t_em
        self.load_torque_nm = t_load
        self.mechanical_power_w = t_em * omega_avg
        self.electrical_power_w = self.mechanical_power_w + p.copper_resistance_ohm * self.iq_a ** 2
        self._dc_bus(dt_s)
        self.time_s += dt_s
        if self.heart is not None:
            self.heart.advance(self.rider_energy_j, self.time_s)

    @property
    def heart_rate_bpm(self) -> float:
        """The rider's heart rate (0: no rider)."""
        return self.heart.bpm if self.heart is not None else 0.0

    def _dc_bus(self, dt_s: float) -> None:
        """Battery (OCV, R_int) || brake resistor feeding the drive's power P:
        V = OCV - R_int (P / V + i_res)  ->  with S0 fully on (i_res = V / R_brake)
        a V^2 - OCV V + R_int P = 0. S0 is a chopper (as bike_plant.bldc._s0_chopper): on above
        s0_on_v, it holds the bus at s0_off_v (never below the OCV) with the regenerated current
        the pack does not take there, at most fully on, and opens when nothing is left, so the
        resistor never takes the pack's energy."""
        p = self.params
        voc = self.ocv_v()
        v = self._bus_v(voc, 1.0)
        i_res = 0.0
        if self.brake_on:
            v_hold = max(p.s0_off_v, voc)
            if v > v_hold:
                v = max(self._bus_v(voc, 1.0 + p.r_internal_ohm / p.r_brake_ohm), v_hold)
                i_res = (voc - v) / p.r_internal_ohm - self.electrical_power_w / v
            else:
                self.brake_on = False
        elif v > p.s0_on_v and p.r_brake_ohm > 0:
            self.brake_on = True
        i_drive = self.electrical_power_w / v if v > 1e-6 else 0.0
        self.bus_voltage_v = v
        self.bus_current_a = i_drive + i_res
        self.soc -= self.bus_current_a * dt_s / (p.capacity_ah * 3600.0)

    def _bus_v(self, voc: float, a: float) -> float:
        """The bus voltage [V] solving a V^2 - OCV V + R_int P = 0 (a = 1: S0 open)."""
        disc = voc * voc - 4.0 * a * self.params.r_internal_ohm * self.electrical_power_w
        return (voc + math.sqrt(max(disc, 0.0))) / (2.0 * a)    # max(): overload collapses the bus


# =======================================================================================
# physics: the bike_plant machine models behind the drive's own current loop
# sums over a batch's periods, filled by the batch kernels
(A_TEM, A_IQ, A_ID, A_IBATT, A_OMEGA, A_TLOAD, A_PMECH, A_VDC, A_PSHAFT) = range(9)
A_SIZE = 9
# A_PSHAFT: T_em x the period's mean speed, the plant's own ledger form, so that the truth's shaft,
# rider, friction and kinetic energies balance (A_PMECH takes the speed at the period's end)


@njit(**M.JIT)
def spmsm_drive_batch(state, p, cs, q, n, enabled, ws, acc):
    """``n`` control periods of the SPMSM drive: its current loop
    (bike_controller.spmsm_control.control_period in torque mode: measured currents ->
    dq PI with decoupling -> voltage limit -> SVPWM duties, paper 001 Eq. 25-65 / section
    5) then the plant (bike_plant.spmsm.step_period, exact dq solution over the period).
    enabled False: the controller does not run and the bridge is off (the caller set the
    plant's gates-off state). The relay stays on the inverter. acc += the A_* sums."""
    for _ in range(n):
        if enabled:
            da, db, dc, _relay, bd = SC.control_period(cs, q, state)
        else:
            da = 0.5
            db = 0.5
            dc = 0.5
            bd = 1.0
        w0 = state[M.S_OMEGA]
        M.step_period(state, p, da, db, dc, 0.0, bd, ws)
        acc[A_PSHAFT] += state[M.S_TEM] * 0.5 * (w0 + state[M.S_OMEGA])
        acc[A_TEM] += state[M.S_TEM]
        acc[A_IQ] += state[M.S_IQ]
        acc[A_ID] += state[M.S_ID]
        acc[A_IBATT] += state[M.S_IBATT]
        acc[A_OMEGA] += state[M.S_OMEGA]
        acc[A_TLOAD] += state[M.S_TLOAD]
        acc[A_PMECH] += state[M.S_TEM] * state[M.S_OMEGA]
        acc[A_VDC] += p[M.P_VDC]


@njit(cache=True, error_model="numpy")
def bldc_drive_batch(state, p, cs, q, n, acc):
    """``n`` 50 us periods of the BLDC drive: the hysteresis current law of paper 000
    (bike_controller.bldc_control.closed_loop_period: Hall commutation, feedback
    (|ia| + |ib| + |ic|) / 2, one switching edge per period, Hall edges -> Eq. 1 speed)
    on the plant's own state, then the plant step (bike_plant.bldc). The current command
    is cs[C_ICMD] (0: all gates off). acc += the A_* sums; A_IQ is the feedback current
    signed by the quadrant (+ motoring, - generating)."""
    ws = np.empty(K.WS_SIZE)
    wi = np.empty(6, np.int64)
    ec = np.empty(4, np.uint64)
    es = np.empty(4, np.uint8)
    c = K.plant_constants(p)
    sign = 1.0 if cs[BC.C_MODE] == torque_command.MODE_MOTORING else -1.0
    for _ in range(n):
        w0 = state[K.S_OMEGA]
        BC.closed_loop_period(cs, q, state, p, c, ws, wi, ec, es)
        acc[A_PSHAFT] += state[K.S_TEM] * 0.5 * (w0 + state[K.S_OMEGA])
        acc[A_TEM] += state[K.S_TEM]
        acc[A_IQ] += sign * 0.5 * (abs(state[K.S_IA]) + abs(state[K.S_IB]) + abs(state[K.S_IC]))
        acc[A_IBATT] += state[K.S_IBATT]
        acc[A_OMEGA] += state[K.S_OMEGA]
        acc[A_TLOAD] += state[K.S_TLOAD]
        acc[A_PMECH] += state[K.S_TEM] * state[K.S_OMEGA]
        acc[A_VDC] += state[K.S_VDC]


class _PlantDrive(_DriveReadouts):
    """What the firmware and the CAN side read of a drive model (the names of
    :class:`AverageTorqueDrive`), for the plant-kernel drives. :meth:`step` advances the
    control periods that fit in the time given (fractions carried to the next call), in
    one compiled batch; the outputs are the batch's means (Iq, torque, bus current,
    powers) or its end state (speed, position, bus voltage)."""

    def __init__(self, params: DriveModelParams, period_s: float):
        self.params = params
        self.period_s = float(period_s)
        self.periods = 0
        self._requested_s = 0.0
        self.acc = np.zeros(A_SIZE)
        self.iq_a = 0.0
        self.id_a = 0.0
        self.iq_setpoint_a = 0.0
        self.torque_em_nm = 0.0
        self.load_torque_nm = 0.0
        self.mechanical_power_w = 0.0
        self.electrical_power_w = 0.0
        self.bus_current_a = 0.0
        self.position_rev = 0.0
        self.enabled = False
        self.current_limit_a = params.current_limit_a
        self.shaft_energy_j = 0.0          # int T_em w dt (the truth's; the plant's ledger has no such sum)

    def set_rider_instruction(self, cadence_rpm: float, stop: bool) -> None:
        """What the rider is told (a workout's cadence, 0: his own; a spin-down's stop)."""
        self.plant.set_rider_cadence(cadence_rpm, stop=stop)

    @property
    def time_s(self) -> float:
        return self.periods * self.period_s

    def step(self, dt_s: float, iq_setpoint_a: float, enabled: bool = True, current_limit_a: float | None = None) -> None:
        """Advance ``dt_s`` (whole control periods; the remainder is carried) with the
        current setpoint [A, + = motoring torque]; enabled False = the axis is IDLE."""
        self._requested_s += dt_s
        n = int(math.floor(self._requested_s / self.period_s + 1e-9)) - self.periods
        if current_limit_a is not None:
            self.current_limit_a = current_limit_a
        if n <= 0:
            return
        if not math.isfinite(iq_setpoint_a):
            iq_setpoint_a = 0.0
        self.acc[:] = 0.0
        self._advance(n, float(iq_setpoint_a), bool(enabled))
        self.periods += n
        a = self.acc / n
        self.iq_a = float(a[A_IQ])
        self.id_a = float(a[A_ID])
        self.torque_em_nm = float(a[A_TEM])
        self.load_torque_nm = float(a[A_TLOAD])
        self.mechanical_power_w = float(a[A_PMECH])
        self.bus_current_a = -float(a[A_IBATT])
        self.electrical_power_w = float(a[A_VDC]) * self.bus_current_a
        self.shaft_energy_j += float(self.acc[A_PSHAFT]) * self.period_s
        self.position_rev = self._position_rev(float(a[A_OMEGA]) * n * self.period_s)
        self.plant.advance_heart()     # the kernels step the plant's state, not its step_batch

    @property
    def heart_rate_bpm(self) -> float:
        """The rider's heart rate (the plant's own rider; 0: no rider)."""
        return self.plant.heart.bpm if self.plant.heart is not None else 0.0

    @property
    def rider_energy_j(self) -> float:
        """The rider's (load's) work into the shaft: the plant kernel's own ledger, exact per period."""
        return float(self.plant.state[self._S_E_MECH])

    @property
    def friction_energy_j(self) -> float:
        return float(self.plant.state[self._S_E_FRIC])

    def _position_rev(self, dtheta_rad: float) -> float:
        return self.position_rev + dtheta_rad / TWO_PI

    def _advance(self, n: int, iq_setpoint_a: float, enabled: bool) -> None:
        raise NotImplementedError


class SpmsmPlantDrive(_PlantDrive):
    """SPMSM drive: bike_plant.spmsm's plant + bike_controller.spmsm_control's current loop
    (torque mode, ``current_loop`` family: 'pi' pole placement or 'predictive'), see
    :func:`spmsm_drive_batch`. The torque setpoint reaches the current loop as its iq
    demand (iq* = T / kt), limited by the region logic to the drive's current limit and
    the voltage the 24 V inverter can make at the present speed (flux weakening, MTPV)."""

    _S_E_MECH, _S_E_FRIC = M.S_E_MECH, M.S_E_FRIC

    def __init__(self, cfg: dict, params: DriveModelParams, *, current_loop: str = "pi", load_kind: str | None = None,
                 speed_observer_hz: float = DEFAULT_SPEED_OBSERVER_HZ):
        if current_loop not in CURRENT_LOOPS:
            raise ValueError(f"current loop must be one of {', '.join(CURRENT_LOOPS)}, got {current_loop!r}")
        if not (math.isfinite(speed_observer_hz) and speed_observer_hz > 0):
            raise ValueError(f"speed observer pole must be > 0 Hz, got {speed_observer_hz!r}")
        pp = M.plant_params_from_config(cfg)
        if load_kind is not None:
            pp.load = dataclasses.replace(pp.load, kind=load_kind)
            pp.load.validate()
        super().__init__(params, pp.control_period_s)
        self.plant = M.SpmsmPlant(pp)
        ctrl = SC.SpmsmController(cfg, family=current_loop)
        self.cp = ctrl.cp
        self.q = ctrl.q.copy()
        # the drive's own speed estimate (decoupling, flux-weakening region): the controller's
        # encoder-angle observer with the torque fed forward, but at the bandwidth of a drive's
        # encoder PLL (ODrive encoder.config.bandwidth 1000 rad/s ~ 160 Hz), not the 5 Hz the
        # paper's speed loop was calibrated with: with a rider's crank-torque ripple (+-50 %
        # at 2 x cadence) a 5 Hz observer lags the speed by ~100 r/min, the decoupling and the
        # region logic then work on the wrong speed and the current loop loses the current
        self.q[SC.Q_OBSERVER] = 1.0
        self.q[SC.Q_MMETHOD] = 0.0
        self.q[SC.Q_SPEED_KF] = 0.0
        self.q[SC.Q_OBS_L1], self.q[SC.Q_OBS_L2], self.q[SC.Q_OBS_L3] = SC.observer_gains(
            speed_observer_hz, pp.control_period_s)
        self.speed_observer_hz = float(speed_observer_hz)
        self.kt_control_nm_per_a = float(self.q[SC.Q_KT])
        self.cs = np.zeros(SC.C_SIZE)
        self.ws = np.zeros(M.WS_SIZE)
        self.plant.set_safe_state()              # IDLE: gates off
        self.bus_voltage_v = float(self.plant.p[M.P_VDC])

    @property
    def speed_rad_s(self) -> float:
        return float(self.plant.state[M.S_OMEGA])

    def _position_rev(self, dtheta_rad: float) -> float:
        s = self.plant.state
        return float(s[M.S_REV] + s[M.S_THETA_M] / TWO_PI)

    def warm_up(self) -> None:
        """Compile the batch kernel (a zero-period call: no state changes)."""
        spmsm_drive_batch(self.plant.state, self.plant.p, self.cs, self.q, 0, False, self.ws, self.acc)

    def _advance(self, n: int, iq_setpoint_a: float, enabled: bool) -> None:
        plant = self.plant
        if enabled and not self.enabled:
            # arming: bumpless start of the current loop from the measured state
            plant.clear_safe_state()
            self.cs = SC.init_controller_state(self.q, self.cp, plant.state)
            self.cs[SC.C_TORQUE_MODE] = 1.0
        elif not enabled and self.enabled:
            plant.set_safe_state()
        self.enabled = enabled
        if enabled:
            self.q[SC.Q_IMAX] = max(float(self.current_limit_a), 1e-3)
            self.cs[SC.C_TORQUE_CMD] = iq_setpoint_a * self.kt_control_nm_per_a
        plant.before_batch(n)
        plant.state[M.S_FAULTS] = 0.0
        spmsm_drive_batch(plant.state, plant.p, self.cs, self.q, n, enabled, self.ws, self.acc)
        self.iq_setpoint_a = float(self.cs[SC.C_IQ_REF]) if enabled else 0.0


class BldcPlantDrive(_PlantDrive):
    """BLDC drive: bike_plant.bldc's plant + bike_controller.bldc_control's hysteresis
    current law (see :func:`bldc_drive_batch`). Current command I* = |iq*| (the firmware's
    iq* = T / kt): T > 0 motoring (upper switch of the positive phase modulated), T < 0
    generating (its lower switch: the winding boosts into the battery; forward rotation
    only, as the paper's quadrants I and II -- at standstill or backwards no braking
    current is commanded). The hysteresis band is controller.hysteresis_a."""

    _S_E_MECH, _S_E_FRIC = K.S_E_MECH, K.S_E_FRIC

    def __init__(self, cfg: dict, params: DriveModelParams, *, load_kind: str | None = None):
        pp = P.plant_params_from_config(cfg)
        if load_kind is not None:
            if load_kind not in P.LOAD_KINDS:
                raise ValueError(f"load {load_kind!r} needs an SPMSM config (BLDC loads: {', '.join(P.LOAD_KINDS)})")
            pp.load = dataclasses.replace(pp.load, kind=load_kind)
        super().__init__(params, pp.control_period_s)
        self.plant = BldcPlant(pp)
        self.controller = BC.BatchController(cfg)
        self.cs = self.controller.cs
        self.q = self.controller.q

    @property
    def speed_rad_s(self) -> float:
        return float(self.plant.state[K.S_OMEGA])

    @property
    def bus_voltage_v(self) -> float:
        return float(self.plant.state[K.S_VDC])

    def warm_up(self) -> None:
        bldc_drive_batch(self.plant.state, self.plant.p, self.cs, self.q, 0, self.acc)

    def _advance(self, n: int, iq_setpoint_a: float, enabled: bool) -> None:
        plant = self.plant
        cs = self.cs
        self.enabled = enabled
        icmd = min(abs(iq_setpoint_a), max(float(self.current_limit_a), 0.0)) if enabled else 0.0
        if iq_setpoint_a > 0.0:
            cs[BC.C_MODE] = torque_command.MODE_MOTORING
        else:
            cs[BC.C_MODE] = torque_command.MODE_RESISTANCE
            if self.speed_rad_s <= 0.0:
                icmd = 0.0                       # generating needs forward rotation
        cs[BC.C_IOVERRIDE] = icmd
        self.q[BC.Q_ILIM] = max(icmd, float(self.current_limit_a))
        BC.update_command(cs, self.q)
        load = plant.params.load
        if load.kind == "prime_mover" and load.schedule_time_s:
            speed = load.speed_rpm
            for ts, sp in zip(load.schedule_time_s, load.schedule_speed_rpm):
                if self.time_s + 1e-12 >= ts:
                    speed = sp
            plant.state[K.S_SPEED_TARGET] = speed / RPM_PER_RAD_S
        bldc_drive_batch(plant.state, plant.p, cs, self.q, n, self.acc)
        self.iq_setpoint_a = math.copysign(float(cs[BC.C_ICMD]), 1.0 if iq_setpoint_a > 0.0 else -1.0) \
            if cs[BC.C_ICMD] > 0.0 else 0.0


def make_drive_model(cfg: dict, physics: str = "plant", *, load_kind: str | None = None,
                     current_tau_s: float = DEFAULT_CURRENT_TAU_S, current_loop: str = "pi",
                     speed_observer_hz: float = DEFAULT_SPEED_OBSERVER_HZ):
    """The drive's physics for a loaded config: ``physics`` 'plant' (:class:`SpmsmPlantDrive`
    or :class:`BldcPlantDrive` by the config's machine) or 'average'
    (:class:`AverageTorqueDrive`); ``load_kind`` overrides load.kind. ValueError /
    ConfigError on bad input."""
    if physics not in PHYSICS:
        raise ValueError(f"physics must be one of {', '.join(PHYSICS)}, got {physics!r}")
    params = DriveModelParams.from_config(cfg, current_tau_s=current_tau_s)
    if load_kind is not None and load_kind not in LOAD_KINDS:
        raise ValueError(f"load must be one of {', '.join(LOAD_KINDS)}, got {load_kind!r}")
    if physics == "average":
        if load_kind is not None:
            params.load_kind = load_kind
            params.load = dataclasses.replace(params.load, kind=load_kind if load_kind != "dynamometer" else "none")
        return AverageTorqueDrive(params)
    if params.machine == "spmsm":
        return SpmsmPlantDrive(cfg, params, current_loop=current_loop, load_kind=load_kind,
                               speed_observer_hz=speed_observer_hz)
    return BldcPlantDrive(cfg, params, load_kind=load_kind)


# =======================================================================================
# firmware
#: What feeds the emulated axis's watchdog (see the module doc): 'commands' or 'any' frame to the axis
WATCHDOG_FED_BY = ("commands", "any")


class DriveFirmware:
    """ODrive-like axis logic (no CAN, no clock: callers pass monotonic times in seconds)."""

    def __init__(self, model: AverageTorqueDrive, *, watchdog_timeout_s: float = 0.5,
                 velocity_limit_rev_s: float = 100.0, current_limit_a: float | None = None,
                 vel_gain_nm_per_rev_s: float = 0.5, vel_integrator_gain_nm_per_rev: float = 2.0,
                 vel_ramp_rate_rev_s2: float = 50.0, watchdog_fed_by: str = "commands",
                 log: Callable[[str], None] | None = None):
        if watchdog_fed_by not in WATCHDOG_FED_BY:
            raise ValueError(f"watchdog_fed_by must be one of {', '.join(WATCHDOG_FED_BY)}, got {watchdog_fed_by!r}")
        self.model = model
        self.watchdog_timeout_s = float(watchdog_timeout_s)     # 0: watchdog disabled
        # 'commands': Set_Input_Torque / Set_Input_Vel / Set_Axis_State feed it (the 0.6.x example);
        # 'any': every frame to the axis does, RTR requests included (0.5.x can_simple.cpp)
        self.watchdog_fed_by = watchdog_fed_by
        self.velocity_limit_rev_s = float(velocity_limit_rev_s)
        self.current_limit_a = float(current_limit_a if current_limit_a is not None
                                     else model.params.current_limit_a)
        self.vel_gain = vel_gain_nm_per_rev_s
        self.vel_integrator_gain = vel_integrator_gain_nm_per_rev
        self.vel_ramp_rate_rev_s2 = vel_ramp_rate_rev_s2
        self.log = log or (lambda text: None)
        self.axis_state = int(AxisState.IDLE)
        self.active_errors = 0
        self.disarm_reason = 0
        self.procedure_result = int(ProcedureResult.SUCCESS)
        self.control_mode = int(ControlMode.TORQUE_CONTROL)
        self.input_mode = int(InputMode.PASSTHROUGH)
        self.input_torque_nm = 0.0
        self.input_vel_rev_s = 0.0
        self.input_torque_ff_nm = 0.0
        self.vel_setpoint_rev_s = 0.0
        self.vel_integrator_nm = 0.0
        self.torque_setpoint_nm = 0.0
        self.last_feed_s = -math.inf
        self.sticky_errors = 0          # injected fault that survives Clear_Errors ...
        self.sticky_clears_left = 0     # ... this many more times (-1: forever)

    @property
    def armed(self) -> bool:
        return self.axis_state == AxisState.CLOSED_LOOP_CONTROL

    # ------------------------------------------------------------ host commands
    def feed_watchdog(self, now_s: float) -> None:
        self.last_feed_s = now_s

    def request_state(self, state: int, now_s: float) -> None:
        self.feed_watchdog(now_s)
        if state == AxisState.CLOSED_LOOP_CONTROL:
            if self.active_errors:
                self.procedure_result = int(ProcedureResult.DISARMED)
                self.log(f"closed loop refused: active errors {error_names(self.active_errors)}")
                return
            if not self.armed:
                self._reset_inputs()
                self.vel_setpoint_rev_s = self.model.speed_rev_s if self.control_mode == ControlMode.VELOCITY_CONTROL \
                    else 0.0
                self.axis_state = int(AxisState.CLOSED_LOOP_CONTROL)
                self.procedure_result = int(ProcedureResult.BUSY)
                self.log("axis state CLOSED_LOOP_CONTROL")
        elif state == AxisState.IDLE:
            if self.armed:
                self.log("axis state IDLE (requested)")
                self.procedure_result = int(ProcedureResult.SUCCESS)
            self._to_idle()
        elif state in CALIBRATION_STATES:
            self._to_idle()
            self.procedure_result = int(ProcedureResult.SUCCESS)
        else:
            self.procedure_result = int(ProcedureResult.INVALID_STATE)

    def set_controller_mode(self, control_mode: int, input_mode: int) -> bool:
        if control_mode not in (ControlMode.TORQUE_CONTROL, ControlMode.VELOCITY_CONTROL) or \
                input_mode not in (InputMode.PASSTHROUGH, InputMode.VEL_RAMP):
            return False
        if control_mode != self.control_mode:
            self.vel_integrator_nm = 0.0
            self.vel_setpoint_rev_s = self.model.speed_rev_s
        self.control_mode = int(control_mode)
        self.input_mode = int(input_mode)
        return True

    def set_input_torque(self, torque_nm: float, now_s: float) -> None:
        self.feed_watchdog(now_s)
        self.input_torque_nm = float(torque_nm)

    def set_input_vel(self, speed_rev_s: float, torque_ff_nm: float, now_s: float) -> None:
        self.feed_watchdog(now_s)
        self.input_vel_rev_s = float(speed_rev_s)
        self.input_torque_ff_nm = float(torque_ff_nm)

    def set_limits(self, velocity_limit_rev_s: float, current_limit_a: float) -> None:
        self.velocity_limit_rev_s = float(velocity_limit_rev_s)
        self.current_limit_a = float(current_limit_a)

    def clear_errors(self) -> None:
        if self.sticky_errors and self.sticky_clears_left != 0:
            if self.sticky_clears_left > 0:
                self.sticky_clears_left -= 1
            self.active_errors = self.sticky_errors     # the cause is still there: it latches again
            self.log(f"Clear_Errors: {error_names(self.sticky_errors)} persists")
            return
        self.sticky_errors = 0
        if self.active_errors:
            self.log(f"errors cleared: {error_names(self.active_errors)}")
        self.active_errors = 0
        self.disarm_reason = 0

    def inject_fault(self, error: int, persist: int = 0) -> None:
        """Test fault: ``error`` (ODriveError bits) disarms the axis like a real trip; 0 drops
        to IDLE without an error (someone else set the axis IDLE). ``persist``: the next this
        many Clear_Errors do not clear it (-1: none does; a fault whose cause stays)."""
        if error:
            self.sticky_errors = int(error) if persist else 0
            self.sticky_clears_left = int(persist)
            self.disarm(int(error))
        else:
            if self.armed:
                self.log("axis state IDLE (injected, no error)")
            self._to_idle()

    def estop(self) -> None:
        """An Estop frame: ESTOP_REQUESTED latched and the axis IDLE, armed or not, as the
        ODrive does it; Clear_Errors clears it (the bike's plant never sends that for it)."""
        if not self.active_errors & ODriveError.ESTOP_REQUESTED:
            self.log("Estop frame: ESTOP_REQUESTED, axis IDLE until Clear_Errors")
        self.disarm(int(ODriveError.ESTOP_REQUESTED))

    # ------------------------------------------------------------ supervision
    def disarm(self, error: int) -> None:
        """Latch ``error``, drop to IDLE, zero torque."""
        self.active_errors |= int(error)
        if self.armed:
            self.disarm_reason = int(error)
            self.procedure_result = int(ProcedureResult.DISARMED)
            self.log(f"disarmed: {error_names(int(error))}")
        self._to_idle()

    def check_watchdog(self, now_s: float) -> bool:
        """Trip if armed and not fed for the timeout; returns True when it tripped now."""
        if self.armed and self.watchdog_timeout_s > 0 and now_s - self.last_feed_s > self.watchdog_timeout_s:
            self.disarm(ODriveError.WATCHDOG_TIMER_EXPIRED)
            return True
        return False

    def _reset_inputs(self) -> None:
        self.input_torque_nm = 0.0
        self.input_vel_rev_s = 0.0
        self.input_torque_ff_nm = 0.0
        self.vel_integrator_nm = 0.0
        self.torque_setpoint_nm = 0.0

    def _to_idle(self) -> None:
        self.axis_state = int(AxisState.IDLE)
        self._reset_inputs()

    # ------------------------------------------------------------ control + physics
    def step(self, dt_s: float) -> None:
        """One sub-step: controller (if armed) -> iq setpoint -> physics -> protections."""
        m = self.model
        kt = m.params.torque_constant_nm_per_a
        if self.armed:
            vel = m.speed_rev_s
            vlim = self.velocity_limit_rev_s
            if self.control_mode == ControlMode.VELOCITY_CONTROL:
                target = min(max(self.input_vel_rev_s, -vlim), vlim)
                if self.input_mode == InputMode.VEL_RAMP:
                    step = self.vel_ramp_rate_rev_s2 * dt_s
                    self.vel_setpoint_rev_s += min(max(target - self.vel_setpoint_rev_s, -step), step)
                else:
                    self.vel_setpoint_rev_s = target
                err = self.vel_setpoint_rev_s - vel
                torque_max = self.current_limit_a * kt
                # integrator clamped to the torque range (anti-windup)
                self.vel_integrator_nm = min(max(self.vel_integrator_nm + self.vel_integrator_gain * err * dt_s,
                                                 -torque_max), torque_max)
                torque = self.vel_gain * err + self.vel_integrator_nm + self.input_torque_ff_nm
            else:
                torque = self.input_torque_nm
                # ODrive enable_torque_mode_vel_limit: fade torque out at the velocity limit
                torque = min(max(torque, (-vlim - vel) * self.vel_gain), (vlim - vel) * self.vel_gain)
            iq_sp = min(max(torque / kt, -self.current_limit_a), self.current_limit_a)
            self.torque_setpoint_nm = iq_sp * kt
        else:
            iq_sp = 0.0
            self.torque_setpoint_nm = 0.0
        m.step(dt_s, iq_sp, enabled=self.armed, current_limit_a=self.current_limit_a)
        p = m.params
        if self.armed and abs(m.speed_rev_s) > OVERSPEED_TOLERANCE * self.velocity_limit_rev_s:
            self.disarm(ODriveError.VELOCITY_LIMIT_VIOLATION)
        if m.bus_voltage_v > p.overvoltage_v:
            self.disarm(ODriveError.DC_BUS_OVER_VOLTAGE)
        elif m.bus_voltage_v < p.undervoltage_v:
            self.disarm(ODriveError.DC_BUS_UNDER_VOLTAGE)

    # ------------------------------------------------------------ what goes on the bus
    def signals(self, name: str) -> dict[str, float | int]:
        """DBC signal values of drive -> host message ``name``."""
        m = self.model
        if name == "Heartbeat":
            return {"Axis_Error": self.active_errors, "Axis_State": self.axis_state,
                    "Procedure_Result": self.procedure_result, "Trajectory_Done_Flag": 1}
        if name == "Get_Error":
            return {"Active_Errors": self.active_errors, "Disarm_Reason": self.disarm_reason}
        if name == "Get_Encoder_Estimates":
            return {"Pos_Estimate": m.position_rev, "Vel_Estimate": m.speed_rev_s}
        if name == "Get_Iq":
            return {"Iq_Setpoint": m.iq_setpoint_a, "Iq_Measured": m.iq_a}
        if name == "Get_Bus_Voltage_Current":
            return {"Bus_Voltage": m.bus_voltage_v, "Bus_Current": m.bus_current_a}
        if name == "Get_Torques":
            return {"Torque_Target": self.torque_setpoint_nm, "Torque_Estimate": m.torque_estimate_nm}
        if name == "Get_Powers":
            return {"Electrical_Power": m.electrical_power_w, "Mechanical_Power": m.mechanical_power_w}
        raise KeyError(name)


class VescFirmware(DriveFirmware):
    """What a VESC does with CAN commands (vedderb/bldc documentation/comm_can.md), on the axis
    logic above: there is no armed state on the bus -- any SET_CURRENT / SET_RPM runs the motor
    (the axis enters closed loop, a fault the protections latched is dropped as a VESC's clears
    itself) -- and when no command arrived for the command timeout (``watchdog_timeout_s``; a real
    VESC's app timeout is 1 s by default, vedderb/bldc appconf/appconf_default.h APPCONF_TIMEOUT_MSEC)
    the motor is released (gates off) without an error.

    Readouts of the status broadcasts: ERPM = motor rpm x pole pairs; tachometer = 6 counts
    per electrical revolution; amp / watt hours integrated from the bus current (drawn when
    positive, charged when negative); duty cycle approximated as the back-EMF over the bus
    voltage (kt w / V, the model has no modulator); temperatures are a constant 25 degC (no
    thermal model).
    """

    def __init__(self, model: AverageTorqueDrive, *, pole_pairs: int, **kwargs):
        super().__init__(model, **kwargs)
        if pole_pairs < 1:
            raise ValueError(f"pole_pairs must be >= 1, got {pole_pairs}")
        self.pole_pairs = int(pole_pairs)
        self.charge_drawn_ah = 0.0
        self.charge_regenerated_ah = 0.0
        self.energy_drawn_wh = 0.0
        self.energy_regenerated_wh = 0.0

    def _run(self, now_s: float, control_mode: int) -> None:
        if not self.armed or self.control_mode != control_mode:
            self.active_errors = 0           # a VESC fault clears itself: the next command runs again
            self.sticky_errors = 0
            self.set_controller_mode(control_mode, InputMode.PASSTHROUGH)
            self.request_state(AxisState.CLOSED_LOOP_CONTROL, now_s)

    def set_current(self, current_a: float, now_s: float) -> None:
        """SET_CURRENT: motor current [A], signed (negative brakes, regenerating)."""
        self._run(now_s, ControlMode.TORQUE_CONTROL)
        self.set_input_torque(current_a * self.model.params.torque_constant_nm_per_a, now_s)

    def set_rpm(self, speed_erpm: float, now_s: float) -> None:
        """SET_RPM: electrical rpm (the velocity loop of the axis logic)."""
        self._run(now_s, ControlMode.VELOCITY_CONTROL)
        self.set_input_vel(speed_erpm / self.pole_pairs / RPM_PER_REV_S, 0.0, now_s)

    def check_watchdog(self, now_s: float) -> bool:
        """The command timeout: release the motor (no error latched, as a VESC)."""
        if self.armed and self.watchdog_timeout_s > 0 and now_s - self.last_feed_s > self.watchdog_timeout_s:
            self.log("command timeout: motor released")
            self._to_idle()
            return True
        return False

    def step(self, dt_s: float) -> None:
        super().step(dt_s)
        m = self.model
        i_a, v = m.bus_current_a, m.bus_voltage_v
        if i_a >= 0.0:
            self.charge_drawn_ah += i_a * dt_s / 3600.0
            self.energy_drawn_wh += v * i_a * dt_s / 3600.0
        else:
            self.charge_regenerated_ah -= i_a * dt_s / 3600.0
            self.energy_regenerated_wh -= v * i_a * dt_s / 3600.0

    def signals(self, name: str) -> dict[str, float | int]:
        """DBC signal values of VESC status message ``name``."""
        m = self.model
        if name == "Status":
            v = m.bus_voltage_v
            duty = m.params.torque_constant_nm_per_a * m.speed_rev_s * TWO_PI / v if v > 0 else 0.0
            return {"Erpm": round(m.speed_rev_s * RPM_PER_REV_S * self.pole_pairs), "Current": m.iq_a,
                    "Duty_Cycle": min(max(duty, -1.0), 1.0) if self.armed else 0.0}
        if name == "Status_2":
            return {"Amp_Hours": self.charge_drawn_ah, "Amp_Hours_Charged": self.charge_regenerated_ah}
        if name == "Status_3":
            return {"Watt_Hours": self.energy_drawn_wh, "Watt_Hours_Charged": self.energy_regenerated_wh}
        if name == "Status_4":
            return {"Temp_Fet": 25.0, "Temp_Motor": 25.0, "Current_In": m.bus_current_a,
                    "Pid_Pos": (m.position_rev % 1.0) * 360.0}
        if name == "Status_5":
            return {"Tachometer": round(m.position_rev * VESC_TACHO_PER_EREV * self.pole_pairs),
                    "Voltage_In": m.bus_voltage_v, "Reserved": 0}
        raise KeyError(name)


class RiderDisplay:
    """The emulated rider's view of what the trainer tells him (``--rider-topic``): the
    controller's DriveCommand carries it for the simulated plant's rider (a workout's cadence
    target, a spin-down's "stop pedalling"), and a drive on CAN never sees it -- a real rider
    reads it off a screen. This reads it off the ROS topic, in a thread of its own (rclpy only
    here, imported on use); :attr:`latest` is (cadence target [rpm], 0 = his own; stop).
    ``heart_rate_topic``: his chest strap, :meth:`publish_heart_rate`. ``truth_topic``: the
    physics' ground truth (bike_msgs/DriveTruth, :meth:`publish_truth`), stamped with the plant's
    /clock, which this then follows (:attr:`sim_clock_ns`: the newest heard, None before one).
    Any topic may be None."""

    def __init__(self, topic: str | None, heart_rate_topic: str | None = None, truth_topic: str | None = None):
        import rclpy
        from bike_msgs.msg import DriveCommand, DriveTruth, HeartRate
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from rclpy.signals import SignalHandlerOptions
        from rosgraph_msgs.msg import Clock

        self.latest = (0.0, False)
        self.sim_clock_ns: int | None = None
        self.context = rclpy.Context()
        # the emulator's own SIGINT / SIGTERM handlers stay in charge
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("drive_emulator_rider", context=self.context)
        if topic:
            self.node.create_subscription(DriveCommand, topic, self._on_drive,
                                          QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
        self._heart_rate_msg = HeartRate
        self.heart_rate_pub = (self.node.create_publisher(HeartRate, heart_rate_topic, 10)
                               if heart_rate_topic else None)
        self._truth_msg = DriveTruth
        self.truth_pub = None
        if truth_topic:
            # transient_local: a recorder whose reader matches late still gets the first samples
            self.truth_pub = self.node.create_publisher(DriveTruth, truth_topic, QoSProfile(
                depth=TRUTH_HISTORY, reliability=ReliabilityPolicy.RELIABLE,
                durability=DurabilityPolicy.TRANSIENT_LOCAL))
            # the plant's sim time (it stands still while the drive is not armed): the truth's stamps
            self.node.create_subscription(Clock, "/clock", self._on_clock,
                                          QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, name="rider-display", daemon=True)
        self.thread.start()

    def _on_drive(self, msg) -> None:
        cadence = float(msg.rider_cadence_rpm)
        if math.isfinite(cadence) and cadence >= 0.0:        # the controller checked it; a bad one is ignored
            self.latest = (cadence, bool(msg.rider_stops_pedalling))

    def _on_clock(self, msg) -> None:
        self.sim_clock_ns = int(msg.clock.sec) * 1_000_000_000 + int(msg.clock.nanosec)

    def publish_truth(self, stamp_ns: int, fields: dict) -> None:
        """One DriveTruth stamped ``stamp_ns`` (the plant's sim time); ``fields`` by name."""
        if self.truth_pub is None:
            return
        msg = self._truth_msg()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
        for name, value in fields.items():
            setattr(msg, name, value)
        self.truth_pub.publish(msg)

    def publish_heart_rate(self, bpm: float) -> None:
        """One strap reading (a no-op without ``heart_rate_topic``)."""
        if self.heart_rate_pub is None:
            return
        msg = self._heart_rate_msg()
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.heart_rate_bpm = float(bpm)
        self.heart_rate_pub.publish(msg)

    def _spin(self) -> None:
        try:
            while self.context.ok():
                self.executor.spin_once(timeout_sec=0.1)
        except Exception:  # noqa: BLE001 -- the context shut down under it
            pass

    def close(self) -> None:
        """Shut the context down (which ends the spinning thread), then join it before the
        node goes: a thread still in rcl at exit aborts the process."""
        import rclpy
        rclpy.try_shutdown(context=self.context)
        self.thread.join(timeout=2.0)
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()


# =======================================================================================
# CAN side
class DriveEmulator:
    """An ODrive CANSimple 0.6.x node on ``bus`` whose axis is ``firmware``.

    cyclic_s: period [s] per drive -> host message name (0 or absent: only on RTR).
    Call :meth:`run` (blocking, real time) or drive it yourself with :meth:`handle`
    and :meth:`tick` (tests). Subclasses speak another protocol (:class:`VescEmulator`).
    """

    codec_class = OdriveCanSimpleCodec
    host_to_drive = HOST_TO_DRIVE
    drive_to_host = DRIVE_TO_HOST
    default_cyclic_s = {"Heartbeat": 0.1, "Get_Encoder_Estimates": 0.01}
    # CANSimple's Estop (cmd 0x02, no payload): from an e-stop node or any host, to this axis
    estop_cmd: int | None = ESTOP_CMD

    def __init__(self, bus: can.BusABC, firmware: DriveFirmware, node_id: int = 0, *,
                 cyclic_s: dict[str, float] | None = None, tick_s: float = 1.0e-3, substeps: int = 4,
                 silent_after_s: float | None = None, garbage_rate_hz: float = 0.0, seed: int = 0,
                 fault_at_s: list[float] | tuple[float, ...] = (), fault_error: int = int(ODriveError.DRV_FAULT),
                 fault_persist: int = 0, rider: "RiderDisplay | None" = None,
                 clock: Callable[[], float] = time.monotonic, log: Callable[[str], None] | None = None):
        if not tick_s > 0 or substeps < 1:
            raise ValueError("tick_s must be > 0 and substeps >= 1")
        self.bus = bus
        self.firmware = firmware
        self.rider = rider                  # what the controller tells the rider (None: nothing)
        self.rider_told = (0.0, False)
        self.next_heart_rate_s = 0.0        # physics time of the rider's next strap reading
        self.truth_clock_ns = None          # the /clock value the last truth sample was stamped with
        self._truth_prev = None             # (physics time, rider energy) of the last truth sample
        self.codec = self.codec_class(node_id)
        self.node_id = node_id
        cyclic = dict(self.default_cyclic_s) if cyclic_s is None else dict(cyclic_s)
        unknown = set(cyclic) - self.drive_to_host
        if unknown:
            raise ValueError(f"not drive -> host messages: {', '.join(sorted(unknown))}")
        self.cyclic_s = {name: float(period) for name, period in cyclic.items() if period and period > 0}
        self.tick_s = tick_s
        self.substep_s = tick_s / substeps
        # physics quantum: a plant model's control period (a tick's periods go in one compiled
        # batch per firmware step), else the average model's sub-step (one firmware step each)
        period = getattr(firmware.model, "period_s", None)
        self.quantum_s = float(period) if period else self.substep_s
        self.batch_quanta = max(1, int(round(tick_s / self.quantum_s))) if period else 1
        self.physics_s = 0.0              # simulated time advanced since start
        self.physics_wall_s = 0.0         # wall time spent advancing it
        self.physics_lag_max_s = 0.0      # largest lag of the physics behind the clock at a tick
        self.silent_after_s = silent_after_s
        self.garbage_rate_hz = max(0.0, float(garbage_rate_hz))
        self.rng = random.Random(seed)
        self.clock = clock
        self.log = log or (lambda text: None)
        self.counters: dict[str, int] = {}
        self._echo = _EchoFilter()
        self._t0: float | None = None
        self._due: dict[str, float] = {}
        self._next_garbage_s = math.inf
        self._silent_logged = False
        self.fault_error = int(fault_error)
        self.fault_persist = int(fault_persist)
        self._fault_times = sorted(float(t) for t in fault_at_s)
        # inject_fault_soon() runs in a signal handler, between any two bytecodes of this
        # thread: it only bumps a count, and the tick compares counts. An Event lost a request
        # that came between its is_set() and clear(), or deadlocked on its lock inside clear().
        self._fault_requests = 0
        self._fault_requests_done = 0
        # (min, max, whether the value goes out as is: floats and scaled integers, which the codec rounds)
        self._signal_ranges = {m.name: {s.name: (s.minimum, s.maximum, s.is_float or s.scale != 1)
                                        for s in m.signals} for m in self.codec.db.messages}

    def _count(self, key: str, n: int = 1) -> None:
        self.counters[key] = self.counters.get(key, 0) + n

    # ------------------------------------------------------------ time
    def start(self, now_s: float) -> None:
        self._t0 = now_s
        self._due = {name: now_s for name in self.cyclic_s}
        if self.garbage_rate_hz > 0:
            self._next_garbage_s = now_s + self.rng.expovariate(self.garbage_rate_hz)

    def inject_fault_soon(self) -> None:
        """Inject the configured fault at the next tick (safe to call from a signal handler)."""
        self._fault_requests += 1

    def _faults_due(self, now_s: float) -> None:
        elapsed = now_s - self._t0
        requests = self._fault_requests
        due = requests != self._fault_requests_done
        self._fault_requests_done = requests
        while self._fault_times and elapsed >= self._fault_times[0]:
            self._fault_times.pop(0)
            due = True
        if due:
            self._count("faults_injected")
            self.log(f"fault injected: {error_names(self.fault_error) or ['IDLE (no error)']}"
                     + (f", persists {self.fault_persist} Clear_Errors" if self.fault_persist else ""))
            self.firmware.inject_fault(self.fault_error, self.fault_persist)

    def silent(self, now_s: float) -> bool:
        return self.silent_after_s is not None and self._t0 is not None and now_s - self._t0 >= self.silent_after_s

    # ------------------------------------------------------------ transmit
    def _send(self, msg: can.Message, now_s: float, what: str) -> bool:
        if self.silent(now_s):
            if not self._silent_logged:
                self._silent_logged = True
                self.log("silent: no longer transmitting (--silent-after-s)")
            self._count("tx_suppressed")
            return False
        self._echo.sent(msg, now_s)
        try:
            self.bus.send(msg, timeout=0.01)
        except Exception:  # noqa: BLE001 -- a full TX queue must not stop the drive
            self._count("tx_failed")
            return False
        self._count("tx_frames")
        self._count(f"tx:{what}")
        return True

    def send_message(self, name: str, now_s: float) -> bool:
        """Send drive -> host message ``name`` with the current values (clamped to the DBC range)."""
        values = {}
        for sig, value in self.firmware.signals(name).items():
            lo, hi, is_float = self._signal_ranges[name][sig]
            if not math.isfinite(value):
                self._count("tx_nonfinite_replaced")
                value = 0.0
            clamped = min(max(value, lo), hi)
            values[sig] = clamped if is_float else int(clamped)
        return self._send(self.codec.encode(name, values), now_s, name)

    # ------------------------------------------------------------ receive
    def handle(self, msg: can.Message, now_s: float) -> None:
        """Act on one received frame; counts and ignores anything unusable. Never raises."""
        self._count("rx_frames")
        try:
            if self._echo.is_echo(msg, now_s):
                self._count("echo")
                return
            if self._is_estop(msg):
                self._count("rx:Estop")
                self.firmware.estop()
                return
            result = self.codec.classify(msg, self.host_to_drive, answers_requests=True)
            if self.firmware.watchdog_fed_by == "any" and self._addressed_to_axis(msg):
                self.firmware.feed_watchdog(now_s)      # 0.5.x: before the command is even looked at
            if isinstance(result, str):
                self._count(result)
                return
            self._count(f"rx:{result.name}{'?' if result.is_request else ''}")
            if result.is_request:
                self.send_message(result.name, now_s)
                return
            self._apply(result.name, result.signals, now_s)
        except Exception:  # noqa: BLE001 -- a frame must never crash the drive
            self._count("decode_error")

    def _node_and_cmd(self, msg: can.Message) -> tuple[int, int] | None:
        """(node id, command) of a data or RTR frame in the protocol's id format, else None."""
        arb = msg.arbitration_id
        if msg.is_error_frame or bool(msg.is_extended_id) != self.codec.extended_id or \
                not isinstance(arb, int) or not 0 <= arb <= self.codec.id_max:
            return None
        return self.codec.split_id(arb)

    def _addressed_to_axis(self, msg: can.Message) -> bool:
        """A data or RTR frame with this axis's node id (what an ODrive's CAN filter hands to
        the axis), whatever its command."""
        ids = self._node_and_cmd(msg)
        return ids is not None and ids[0] == self.node_id

    def _is_estop(self, msg: can.Message) -> bool:
        """A data frame of the Estop command to this axis or to every ODrive (node 0x3F, the
        broadcast id); any payload, the firmware reads none."""
        ids = None if self.estop_cmd is None or msg.is_remote_frame else self._node_and_cmd(msg)
        return ids is not None and ids[1] == self.estop_cmd and ids[0] in (self.node_id, ODRIVE_BROADCAST_NODE_ID)

    def _apply(self, name: str, s, now_s: float) -> None:
        fw = self.firmware
        if name == "Set_Axis_State":
            fw.request_state(int(s["Axis_Requested_State"]), now_s)
        elif name == "Set_Input_Torque":
            fw.set_input_torque(s["Input_Torque"], now_s)
        elif name == "Set_Input_Vel":
            fw.set_input_vel(s["Input_Vel"], s["Input_Torque_FF"], now_s)
        elif name == "Set_Controller_Mode":
            if not fw.set_controller_mode(int(s["Control_Mode"]), int(s["Input_Mode"])):
                self._count("unsupported_mode")
        elif name == "Set_Limits":
            fw.set_limits(s["Velocity_Limit"], s["Current_Limit"])
        elif name == "Clear_Errors":
            fw.clear_errors()

    # ------------------------------------------------------------ periodic work
    def tick(self, now_s: float) -> None:
        """Advance physics to ``now_s``, check the watchdog, send what is due."""
        if self._t0 is None:
            self.start(now_s)
        fw = self.firmware
        elapsed = now_s - self._t0
        q = self.quantum_s
        lag = elapsed - self.physics_s
        if lag > self.physics_lag_max_s:
            self.physics_lag_max_s = lag
        n = int(lag / q + 1e-9)
        if self.rider is not None and self.rider.latest != self.rider_told:
            self.rider_told = self.rider.latest
            fw.model.set_rider_instruction(*self.rider_told)
            self._count("rider_instructions")
        if self.rider is not None and self.physics_s >= self.next_heart_rate_s:
            # a chest strap sends about once a second
            self.rider.publish_heart_rate(fw.model.heart_rate_bpm)
            self.next_heart_rate_s = self.physics_s + HEART_RATE_PERIOD_S
        max_steps = int(round(0.1 / q))      # at most 100 ms of catch-up per tick
        if n > max_steps:
            self._count("physics_skipped_ms", int((n - max_steps) * q * 1000))
            self.physics_s += (n - max_steps) * q
            if isinstance(fw.model, AverageTorqueDrive):
                fw.model.time_s += (n - max_steps) * q
            n = max_steps
        if n > 0:
            t_wall = time.perf_counter()
            while n > 0:
                k = min(n, self.batch_quanta)
                fw.step(k * q)
                n -= k
                self.physics_s += k * q
            self.physics_wall_s += time.perf_counter() - t_wall
        if self.rider is not None:
            # one truth sample per new /clock of the plant (none while its sim time stands still)
            clock_ns = self.rider.sim_clock_ns
            if clock_ns is not None and clock_ns != self.truth_clock_ns:
                self.truth_clock_ns = clock_ns
                try:
                    self.rider.publish_truth(clock_ns, self.truth_sample())
                except Exception:  # noqa: BLE001 -- telemetry (a stamp out of range, rclpy closing) never stops it
                    self._count("truth_not_published")
        self._faults_due(now_s)
        fw.check_watchdog(now_s)
        for name, period in self.cyclic_s.items():
            due = self._due[name]
            if now_s >= due:
                self.send_message(name, now_s)
                due += period
                if due <= now_s:            # fell behind (loaded machine): resynchronise
                    self._count("cyclic_late")
                    due = now_s + period
                self._due[name] = due
        while now_s >= self._next_garbage_s:
            self._send(self._garbage_frame(), now_s, "garbage")
            self._next_garbage_s += self.rng.expovariate(self.garbage_rate_hz)

    def truth_sample(self) -> dict:
        """The physics as they are now (bike_msgs/DriveTruth's fields but the header):
        rider_power_w is the rider's mean power since the previous sample (the first: since the
        start), the energies are cumulative since the start."""
        m = self.firmware.model
        energy = float(m.rider_energy_j)
        prev_s, prev_j = self._truth_prev if self._truth_prev is not None else (0.0, 0.0)
        span_s = self.physics_s - prev_s
        power = (energy - prev_j) / span_s if span_s > 0 else float(m.load_torque_nm * m.speed_rad_s)
        self._truth_prev = (self.physics_s, energy)
        return {"physics_time_s": float(self.physics_s), "armed": bool(self.firmware.armed),
                "speed_rpm": float(m.speed_rad_s * RPM_PER_RAD_S), "shaft_torque_nm": float(m.torque_em_nm),
                "torque_estimate_nm": float(m.torque_estimate_nm), "rider_torque_nm": float(m.load_torque_nm),
                "rider_power_w": float(power), "rider_energy_j": energy, "shaft_energy_j": float(m.shaft_energy_j),
                "friction_energy_j": float(m.friction_energy_j), "kinetic_energy_j": float(m.kinetic_energy_j)}

    def _garbage_frame(self) -> can.Message:
        """A random malformed or foreign frame. Never a valid command for any node: the
        only host -> drive ids used are this node's own (as RTR), so it is bench-safe."""
        rng = self.rng
        node = self.node_id << 5
        kind = rng.randrange(8)
        if kind == 0:       # unknown command id of this node (no CANSimple message: never a real command)
            known = {m.frame_id for m in self.codec.db.messages} | set(self.codec.unused_cmds)
            cmd = rng.choice([c for c in range(32) if c not in known])
            return can.Message(arbitration_id=node | cmd, data=rng.randbytes(rng.randrange(9)), is_extended_id=False)
        if kind == 1:       # measurement with the wrong length
            cmd = self.codec.messages[rng.choice(sorted(DRIVE_TO_HOST))].frame_id
            return can.Message(arbitration_id=node | cmd, data=rng.randbytes(rng.randrange(8)), is_extended_id=False)
        if kind == 2:       # NaN / inf estimates
            bad = rng.choice([math.nan, math.inf, -math.inf])
            data = (bytes(4) + _f32(bad)) if rng.random() < 0.5 else (_f32(bad) + bytes(4))
            return can.Message(arbitration_id=node | 0x09, data=data, is_extended_id=False)
        if kind == 3:       # heartbeat with an axis state out of range
            data = bytes(4) + bytes([rng.randrange(15, 256)]) + bytes(3)
            return can.Message(arbitration_id=node | 0x01, data=data, is_extended_id=False)
        if kind == 4:
            return can.Message(is_error_frame=True, arbitration_id=0x4, data=bytes(8), dlc=8)
        if kind == 5:       # extended id
            return can.Message(arbitration_id=rng.randrange(0x800, 1 << 29), data=rng.randbytes(8),
                               is_extended_id=True)
        if kind == 6:       # RTR of one of this node's commands
            cmd = self.codec.messages[rng.choice(sorted(HOST_TO_DRIVE))].frame_id
            return can.Message(arbitration_id=node | cmd, is_remote_frame=True, dlc=8, is_extended_id=False)
        # a phantom node's heartbeat (drive -> host: no drive acts on it)
        other = rng.choice([n for n in range(64) if n != self.node_id])
        return can.Message(arbitration_id=(other << 5) | 0x01, data=rng.randbytes(8), is_extended_id=False)

    # ------------------------------------------------------------ main loop
    def run(self, stop: threading.Event | None = None, duration_s: float | None = None) -> None:
        """Real-time loop until ``stop`` is set or ``duration_s`` passed."""
        stop = stop or threading.Event()
        now = self.clock()
        self.start(now)
        end = math.inf if duration_s is None else now + duration_s
        next_tick = now
        while not stop.is_set():
            now = self.clock()
            if now >= end:
                break
            if now >= next_tick:
                self.tick(now)
                next_tick += self.tick_s
                if next_tick <= now:
                    self._count("tick_overrun")
                    next_tick = now + self.tick_s
                continue
            try:
                msg = self.bus.recv(timeout=next_tick - now)
            except Exception:  # noqa: BLE001 -- e.g. an undecodable datagram on udp_multicast
                self._count("bus_error")
                time.sleep(0.001)
                continue
            if msg is not None:
                self.handle(msg, self.clock())

    def dropped(self) -> int:
        return sum(self.counters.get(r, 0) for r in MALFORMED_REASONS)

    def realtime_stats(self) -> dict[str, float]:
        """Real-time margin of the physics: simulated seconds per wall second spent on them
        (>1: keeps up; the rest of the core serves the bus), the largest lag behind the
        clock seen at a tick, and the simulated time."""
        factor = self.physics_s / self.physics_wall_s if self.physics_wall_s > 0 else math.inf
        return {"physics_sim_s": round(self.physics_s, 4), "physics_wall_s": round(self.physics_wall_s, 4),
                "physics_realtime_factor": round(factor, 1) if math.isfinite(factor) else None,
                "physics_lag_max_ms": round(self.physics_lag_max_s * 1e3, 2)}


class VescEmulator(DriveEmulator):
    """A VESC (CAN mode VESC, vedderb/bldc documentation/comm_can.md) on ``bus`` whose motor is
    ``firmware`` (a :class:`VescFirmware`): decodes SET_CURRENT, SET_CURRENT_BRAKE,
    SET_CURRENT_REL and SET_RPM with the host's codec (:class:`VescCanCodec`, 29-bit ids
    ``cmd << 8 | vesc_id``), broadcasts STATUS .. STATUS_5 every ``cyclic_s`` (VESC Tool's default
    CAN status rate is 50 Hz), answers nothing (VESC has no request). SET_DUTY and SET_POS are
    counted (``unsupported:<name>``) and feed the timeout only.
    """

    codec_class = VescCanCodec
    host_to_drive = VESC_HOST_TO_DRIVE
    drive_to_host = VESC_DRIVE_TO_HOST
    estop_cmd = None                     # VESC's CAN has no emergency stop command
    default_cyclic_s = {name: 0.02 for name in sorted(VESC_DRIVE_TO_HOST)}

    def _apply(self, name: str, s, now_s: float) -> None:
        fw = self.firmware
        speed = fw.model.speed_rev_s
        if name == "Set_Current":
            fw.set_current(s["Current"], now_s)
        elif name == "Set_Current_Brake":
            # brake current opposes the rotation whatever its sign (regenerative braking)
            fw.set_current(-math.copysign(abs(s["Current_Brake"]), speed) if speed else 0.0, now_s)
        elif name == "Set_Current_Rel":
            fw.set_current(s["Current_Rel"] * fw.current_limit_a, now_s)
        elif name == "Set_Rpm":
            fw.set_rpm(s["Erpm"], now_s)
        else:
            self._count(f"unsupported:{name}")
            fw.feed_watchdog(now_s)

    def _garbage_frame(self) -> can.Message:
        """A random malformed or foreign frame; never a command to any VESC (bench-safe)."""
        rng = self.rng
        vid = self.node_id
        kind = rng.randrange(6)
        if kind == 0:       # unknown command id of this VESC (no VESC CAN packet: never a real command)
            cmd = rng.randrange(VESC_CAN_PACKET_ID_MAX + 1, 256)
            return can.Message(arbitration_id=(cmd << 8) | vid, data=rng.randbytes(rng.randrange(9)),
                               is_extended_id=True)
        if kind == 1:       # status with the wrong length
            cmd = self.codec.messages[rng.choice(sorted(VESC_DRIVE_TO_HOST))].frame_id
            return can.Message(arbitration_id=cmd | vid, data=rng.randbytes(rng.randrange(5)), is_extended_id=True)
        if kind == 2:
            return can.Message(is_error_frame=True, arbitration_id=0x4, data=bytes(8), dlc=8)
        if kind == 3:       # standard id
            return can.Message(arbitration_id=rng.randrange(0x800), data=rng.randbytes(8), is_extended_id=False)
        if kind == 4:       # RTR of a status (a VESC has no request)
            return can.Message(arbitration_id=self.codec.arbitration_id("Status"), is_remote_frame=True, dlc=8,
                               is_extended_id=True)
        # another VESC's status (drive -> host: nobody acts on it)
        other = rng.choice([n for n in range(VESC_ID_MAX + 1) if n != vid])
        return can.Message(arbitration_id=(9 << 8) | other, data=rng.randbytes(8), is_extended_id=True)


def benchmark_physics(model, sim_s: float, *, tick_s: float = 1.0e-3, substeps: int = 4,
                      torque_nm: float = -1.0) -> dict:
    """Real-time factor of a drive model without the bus: the axis armed in torque control
    at ``torque_nm`` (braking), advanced ``sim_s`` simulated seconds in the batches the
    emulator's tick makes (one firmware step per tick for plant physics), as fast as the
    machine allows. Returns simulated / wall seconds and the wall time per 1 ms tick."""
    fw = DriveFirmware(model, watchdog_timeout_s=0.0)
    fw.request_state(AxisState.CLOSED_LOOP_CONTROL, 0.0)
    fw.set_input_torque(torque_nm, 0.0)
    period = getattr(model, "period_s", None)
    quantum = period if period else tick_s / substeps
    per_step = max(1, int(round(tick_s / quantum))) if period else 1
    steps = int(math.ceil(sim_s / (per_step * quantum)))
    t0 = time.perf_counter()
    c0 = time.process_time()
    for _ in range(steps):
        fw.step(per_step * quantum)
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0
    simulated = steps * per_step * quantum
    ticks = simulated / tick_s
    return {"machine": model.params.machine, "physics": "average" if isinstance(model, AverageTorqueDrive) else "plant",
            "sim_s": round(simulated, 4), "wall_s": round(wall, 4), "cpu_s": round(cpu, 4),
            "realtime_factor": round(simulated / wall, 1), "realtime_factor_cpu": round(simulated / cpu, 1),
            "us_per_tick": round(wall / ticks * 1e6, 2), "speed_rpm": round(model.speed_rad_s * RPM_PER_RAD_S, 1),
            "torque_estimate_nm": round(model.torque_estimate_nm, 4)}


def _f32(value: float) -> bytes:
    import struct
    return struct.pack("<f", value)


# =======================================================================================
# command line
def option_number(convert=float, low: float | None = None, *, above: bool = False, high: float | None = None):
    """argparse ``type=`` of a numeric option: ``convert`` (float or int) of the text, finite and
    >= ``low`` (> with ``above``, <= ``high``), else an ArgumentTypeError naming the bound. In the
    parser, not after it: ./bike run checks can.emulator_args with this parser before any node
    starts, and --watchdog-s nan passed it, to be refused once the graph was up."""
    bounds = ([f"{'>' if above else '>='} {low:g}"] if low is not None else []) + (
        [f"<= {high:g}"] if high is not None else [])
    want = ("an integer" if convert is int else "a finite number") + (f" {' and '.join(bounds)}" if bounds else "")

    def parse(text: str):
        try:
            value = convert(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {want}, got {text!r}") from None
        if not (math.isfinite(value) and (low is None or (value > low if above else value >= low))
                and (high is None or value <= high)):
            raise argparse.ArgumentTypeError(f"must be {want}, got {text!r}")
        return value
    parse.__name__ = convert.__name__
    return parse


_POSITIVE = option_number(float, 0.0, above=True)
_AT_LEAST_0 = option_number(float, 0.0)


def build_arg_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="bike-drive-emulator",
        description="An ODrive CANSimple 0.6.x drive emulator on a python-can bus; physics from a bike config.")
    bus = ap.add_argument_group("bus")
    bus.add_argument("--interface", default="virtual",
                     help="python-can interface: virtual (same process), udp_multicast (across processes), "
                          "socketcan, pcan, ... (default: virtual)")
    bus.add_argument("--channel", default=None,
                     help="channel, e.g. can0; for udp_multicast a multicast group such as 239.74.163.2 "
                          "(default: the interface's default)")
    bus.add_argument("--port", type=option_number(int, 1, high=65535), default=None,
                     help="udp_multicast UDP port (one per test / bench)")
    bus.add_argument("--bitrate", type=option_number(int, 0, above=True), default=1000000,
                     help="CAN bitrate (real interfaces)")
    bus.add_argument("--node-id", type=option_number(int, 0), default=0,
                     help="ODrive node id 0..62 / VESC ID 0..254, not the broadcast id (default 0)")
    bus.add_argument("--protocol", choices=sorted(EMULATED_PROTOCOLS), default=OdriveCanSimple.protocol_name,
                     help="what the drive speaks: odrive_cansimple_0.6 (default) or vesc_can (a VESC: STATUS .. "
                          "STATUS_5 broadcast every --heartbeat-ms, SET_CURRENT / SET_RPM, --watchdog-s is its "
                          "command timeout)")
    phys = ap.add_argument_group("physics")
    phys.add_argument("--config", default=None, help="bike config (default: config/bldc_default.yaml)")
    phys.add_argument("--physics", choices=PHYSICS, default="plant",
                      help="plant (default): the bike_plant machine model (bldc.py / spmsm.py kernels) behind the "
                           "drive's own current loop, in compiled batches; average: the light average-torque model "
                           "(first-order current loop, no voltage limit) for machines too slow for the plant")
    phys.add_argument("--current-loop", choices=CURRENT_LOOPS, default="pi",
                      help="SPMSM plant physics: the current-loop family of bike_controller.spmsm_control "
                           "(pi: pole placement at controller.pi_current_pole_hz; predictive: paper 001's one-step "
                           "law). The BLDC drive uses the paper 000 hysteresis law")
    phys.add_argument("--speed-observer-hz", type=_POSITIVE, default=DEFAULT_SPEED_OBSERVER_HZ,
                      help="SPMSM plant physics: pole of the drive's encoder speed observer (default 160 Hz, about "
                           "an ODrive's 1000 rad/s encoder bandwidth)")
    phys.add_argument("--load", choices=("config",) + LOAD_KINDS, default="config",
                      help="override the config's load.kind")
    phys.add_argument("--current-tau-s", type=_POSITIVE, default=DEFAULT_CURRENT_TAU_S,
                      help="average physics: closed current-loop time constant (default 1 ms = 1/1000 rad/s)")
    phys.add_argument("--physics-hz", type=_POSITIVE, default=1000.0,
                      help="real-time tick rate (default 1000): plant physics advance the control periods due in "
                           "one compiled batch per tick")
    phys.add_argument("--substeps", type=option_number(int, 1), default=4,
                      help="average physics: sub-steps per tick (default 4)")
    phys.add_argument("--bench-s", type=_POSITIVE, default=None, metavar="S",
                      help="no bus: advance S simulated seconds of the armed drive as fast as possible in tick-"
                           "sized batches, print the real-time factor as JSON and exit")
    drv = ap.add_argument_group("drive")
    drv.add_argument("--heartbeat-ms", type=_AT_LEAST_0, default=100.0,
                     help="Heartbeat period (default 100; 0 off); vesc_can: the period of each status broadcast")
    drv.add_argument("--encoder-ms", type=_AT_LEAST_0, default=10.0,
                     help="Get_Encoder_Estimates period (default 10; 0 off)")
    for name, flag in (("Get_Iq", "iq"), ("Get_Bus_Voltage_Current", "bus"), ("Get_Torques", "torques"),
                       ("Get_Powers", "powers"), ("Get_Error", "error")):
        drv.add_argument(f"--{flag}-ms", type=_AT_LEAST_0, default=0.0, help=f"{name} period (default 0: RTR only)")
    drv.add_argument("--watchdog-s", type=_AT_LEAST_0, default=0.5, help="watchdog timeout (default 0.5; 0 disables)")
    drv.add_argument("--watchdog-fed-by", choices=WATCHDOG_FED_BY, default="commands",
                     help="what feeds the watchdog: commands (default: Set_Input_Torque, Set_Input_Vel, "
                          "Set_Axis_State, as ODrive's 0.6.x can_watchdog.py example says) or any frame to the axis, "
                          "RTR requests included (the open 0.5.x firmware's can_simple.cpp)")
    drv.add_argument("--current-limit-a", type=_POSITIVE, default=None,
                     help="initial current limit (default: controller.current_limit_a of the config)")
    drv.add_argument("--velocity-limit-rev-s", type=_POSITIVE, default=100.0,
                     help="initial velocity limit (motor)")
    drv.add_argument("--vel-gain", type=_POSITIVE, default=0.5,
                     help="velocity gain [N m/(rev/s)] of velocity control and of the torque-mode velocity limiter "
                          "(ODrive controller.config.vel_gain; default 0.5): torque mode allows T in "
                          "[(-v_lim - v) k, (v_lim - v) k], so a machine with large torques needs a larger one")
    drv.add_argument("--vel-integrator-gain", type=_AT_LEAST_0, default=2.0,
                     help="velocity integrator gain [N m/rev] (controller.config.vel_integrator_gain; default 2)")
    fault = ap.add_argument_group("test faults")
    fault.add_argument("--silent-after-s", type=_AT_LEAST_0, default=None,
                       help="stop transmitting after this many seconds but keep running")
    fault.add_argument("--garbage-rate", type=_AT_LEAST_0, default=0.0,
                       help="inject this many random malformed/foreign frames per second")
    fault.add_argument("--seed", type=option_number(int), default=0, help="random seed of the garbage")
    fault.add_argument("--fault-at-s", type=_AT_LEAST_0, action="append", default=[], metavar="T",
                       help="inject --fault T seconds after start (repeatable); SIGUSR1 injects it at once")
    fault.add_argument("--fault", default="DRV_FAULT",
                       help="the injected fault: an ODrive error name (DRV_FAULT, MOTOR_OVER_TEMP, ...; the axis "
                            "disarms with it latched) or IDLE (drop to IDLE without an error). Default DRV_FAULT")
    fault.add_argument("--fault-persist", type=option_number(int, -1), default=0, metavar="N",
                       help="the injected error survives the next N Clear_Errors (-1: all of them; default 0)")
    ap.add_argument("--rider-topic", default=None, metavar="TOPIC",
                    help="let the emulated rider follow the trainer's instructions on this DriveCommand topic "
                         "(e.g. /bike/drive_command: a workout's cadence, a spin-down's stop; ./bike run sets it)")
    ap.add_argument("--heart-rate-topic", default=None, metavar="TOPIC",
                    help="publish the emulated rider's heart rate (bike_msgs/HeartRate, once a second, as a chest "
                         "strap) on this topic (e.g. /bike/heart_rate, where the plant node reads it; ./bike run "
                         "sets it)")
    ap.add_argument("--truth-topic", default=None, metavar="TOPIC",
                    help="publish the physics' ground truth (bike_msgs/DriveTruth: the rider's true power and work, "
                         "the shaft's true torque and speed; e.g. /bike/drive_truth, which the recorder records and "
                         "the report compares the trainer's power with; ./bike run sets it), one sample per /clock "
                         "of the plant, stamped with it")
    ap.add_argument("--duration-s", type=_POSITIVE, default=None,
                    help="exit 0 after this many seconds")
    ap.add_argument("--quiet", action="store_true", help="no event log on stderr")
    return ap


#: --protocol: the emulator class of each host protocol it can stand in for
EMULATED_PROTOCOLS = {OdriveCanSimple.protocol_name: DriveEmulator, VescCan.protocol_name: VescEmulator}


def pole_pairs_of(cfg: dict) -> int:
    """The machine section's pole_pairs (VESC speaks electrical rpm), absent: the plant's default
    (its loader's, BldcParams / SpmsmParams; a config without it said "got None"); ConfigError if bad."""
    machine = cfg.get("machine", "bldc")
    path = cfg.get("_config_path")
    value = section(cfg, machine, path).get("pole_pairs")
    if value is None:
        value = (M.SpmsmParams if machine == "spmsm" else P.BldcParams).pole_pairs
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"pole_pairs must be an integer >= 1, got {value!r}", path, f"{machine}.pole_pairs")
    return value


def parse_fault(name: str) -> int:
    """ODriveError bits of ``name`` ('DRV_FAULT', 'drv_fault', 'IDLE' = 0, or a number)."""
    text = str(name).strip()
    if text.upper() == "IDLE":
        return 0
    try:
        return int(ODriveError[text.upper()])
    except KeyError:
        pass
    try:
        value = int(text, 0)
    except ValueError:
        known = ", ".join(f.name for f in ODriveError if f.value)
        raise ValueError(f"--fault: unknown {name!r} (IDLE or one of {known})") from None
    if not 0 <= value < 2 ** 32:
        raise ValueError(f"--fault must fit in 32 bits, got {name!r}")
    return value


def _bus_kwargs(args) -> dict:
    kwargs = {"interface": args.interface, "bitrate": args.bitrate}
    if args.channel is not None:
        kwargs["channel"] = args.channel
    elif args.interface == "virtual":
        kwargs["channel"] = "bike_can"
    if args.port is not None:
        kwargs["port"] = args.port
    return kwargs


def main(argv: list[str] | None = None) -> int:
    """Console entry ``bike-drive-emulator``; SIGINT / SIGTERM end it with exit code 0."""
    args = build_arg_parser().parse_args(argv)
    # the ROS topics the emulator may use (RiderDisplay), by flag
    topic_flags = (("--rider-topic", args.rider_topic), ("--heart-rate-topic", args.heart_rate_topic),
                   ("--truth-topic", args.truth_topic))
    stop = threading.Event()

    def on_signal(signum, _frame):
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)

    def log(text: str) -> None:
        if not args.quiet:
            print(f"bike-drive-emulator: {text}", file=sys.stderr, flush=True)

    try:
        problem = PROTOCOLS[args.protocol].node_id_problem(args.node_id)
        if problem:
            raise ValueError(f"--node-id {problem}")
        # the numbers' ranges: the parser's (option_number)
        fault_error = parse_fault(args.fault)
        if args.watchdog_fed_by != "commands" and EMULATED_PROTOCOLS[args.protocol] is VescEmulator:
            raise ValueError("--watchdog-fed-by any: a VESC resets its command timeout on commands only "
                             "(vedderb/bldc comm_can.c: timeout_reset() after SET_CURRENT, SET_RPM, ...)")
        topics = {}
        for flag, topic in topic_flags:
            if topic:
                # one message type per topic (the node has no namespace: a relative name is absolute)
                full = topic if topic.startswith("/") else "/" + topic
                if full in topics or full == "/clock":
                    raise ValueError(f"{flag} {topic!r}: the topic of {topics.get(full, 'the plant /clock')} too "
                                     "(each carries its own message type)")
                topics[full] = flag
        cfg = load_config(args.config)
        model = make_drive_model(cfg, args.physics, load_kind=None if args.load == "config" else args.load,
                                 current_tau_s=args.current_tau_s, current_loop=args.current_loop,
                                 speed_observer_hz=args.speed_observer_hz)
        params = model.params
        pole_pairs = pole_pairs_of(cfg)
    except (ConfigError, ValueError) as exc:
        print(f"bike-drive-emulator: {exc}", file=sys.stderr)
        return 2
    rider = None
    if any(topic for _, topic in topic_flags) and args.bench_s is None:
        # before the warm-up: DDS discovery (~0.5 s) then overlaps it, and the truth's first sample
        # (at the first /clock heard) comes as the plant's sim time starts, not 0.3-0.6 s into it
        try:
            rider = RiderDisplay(args.rider_topic, args.heart_rate_topic, args.truth_topic)
        except Exception as exc:  # noqa: BLE001 -- rclpy's error for a bad topic name or an init failure
            given = " / ".join(f"{name} {value!r}" for name, value in topic_flags if value)
            print(f"bike-drive-emulator: {given}: {str(exc).splitlines()[0]}", file=sys.stderr)
            return 2
    if hasattr(model, "warm_up"):
        # compile (or load from numba's cache) before serving the bus, LLVM's library pages
        # dropped as it goes, as the nodes do (bike_plant.memory)
        with LoadTimePageReleaser():
            model.warm_up()
    else:
        # nothing runs LLVM from here on: drop its clean library pages, as the nodes do
        release_clean_library_pages()
    if args.bench_s is not None:
        print(json.dumps(benchmark_physics(model, args.bench_s, tick_s=1.0 / args.physics_hz,
                                           substeps=args.substeps)), flush=True)
        return 0
    firmware_kwargs = dict(watchdog_timeout_s=args.watchdog_s, velocity_limit_rev_s=args.velocity_limit_rev_s,
                           current_limit_a=args.current_limit_a, vel_gain_nm_per_rev_s=args.vel_gain,
                           vel_integrator_gain_nm_per_rev=args.vel_integrator_gain,
                           watchdog_fed_by=args.watchdog_fed_by, log=log)
    emulator_class = EMULATED_PROTOCOLS[args.protocol]
    if emulator_class is VescEmulator:
        firmware = VescFirmware(model, pole_pairs=pole_pairs, **firmware_kwargs)
        cyclic = {name: args.heartbeat_ms for name in VescEmulator.default_cyclic_s}
    else:
        firmware = DriveFirmware(model, **firmware_kwargs)
        cyclic = {"Heartbeat": args.heartbeat_ms, "Get_Encoder_Estimates": args.encoder_ms, "Get_Iq": args.iq_ms,
                  "Get_Bus_Voltage_Current": args.bus_ms, "Get_Torques": args.torques_ms,
                  "Get_Powers": args.powers_ms, "Get_Error": args.error_ms}
    try:
        bus = can.Bus(**_bus_kwargs(args))
    except Exception as exc:  # noqa: BLE001 -- report any interface problem as a usage error
        print(f"bike-drive-emulator: cannot open bus {_bus_kwargs(args)}: {exc}", file=sys.stderr)
        if rider is not None:
            rider.close()
        return 2
    try:
        emu = emulator_class(bus, firmware, args.node_id, cyclic_s={k: v / 1000.0 for k, v in cyclic.items()},
                            tick_s=1.0 / args.physics_hz, substeps=args.substeps,
                            silent_after_s=args.silent_after_s, garbage_rate_hz=args.garbage_rate,
                            seed=args.seed, fault_at_s=args.fault_at_s, fault_error=fault_error,
                            fault_persist=args.fault_persist, rider=rider, log=log)
        signal.signal(signal.SIGUSR1, lambda signum, frame: emu.inject_fault_soon())
        channel = _bus_kwargs(args).get("channel", "default")
        print(f"bike-drive-emulator ready: protocol={args.protocol} node_id={args.node_id} "
              f"interface={args.interface} channel={channel} "
              f"port={args.port} machine={params.machine} physics={args.physics} load={params.load_kind} "
              f"kt={params.torque_constant_nm_per_a:.5f}Nm/A watchdog_s={args.watchdog_s}", flush=True)
        # a full collection of the ~120 000 objects numba, python-can and cantools leave behind
        # takes ~40 ms here (several times that on a loaded laptop): a stall of the heartbeats
        # and encoder frames. Collect once now and freeze them out of every later collection.
        gc.collect()
        gc.freeze()
        emu.run(stop, duration_s=args.duration_s)
    finally:
        try:
            bus.shutdown()
        except Exception:  # noqa: BLE001
            pass
        if rider is not None:
            rider.close()
    summary = dict(sorted(emu.counters.items()))
    summary["axis_state"] = firmware.axis_state
    summary["active_errors"] = firmware.active_errors
    summary.update(emu.realtime_stats())
    log("exit " + json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
