"""The BLDC controller with every session mode: :mod:`.modes` on top of the batched loop.

:class:`ModedController` has the interface of :class:`.bldc_control.BatchController`
(``set_command``, ``decide``, ``status``) and accepts all five Command modes. Per batch:

1. the mode law (:class:`.modes.ModeLaw`) turns (Command, mode, speed estimate) into a
   signed braking torque, rate-limited at mode switches;
2. RESISTANCE with the ramp settled goes to the paper-000 law unchanged (Eq. 2-9, updated
   at every Hall edge inside the batch), so the paper's curves are exactly those of
   :class:`BatchController`; every other case hands the current loop a fixed current for
   the batch: I* = T / ktg(w) (Eq. 8-9) braking, I* = |T| / kt motoring (k = 1 there).

The speed estimate used is the one at the end of the previous batch (1 batch late: 1 ms at
N = 20), the hysteresis current loop itself stays at 50 us.

Torque trim: Eq. 6-9 with the paper's speed-only k(w) leaves the mean torque 7-12 % off the
command at the currents of a workout (the commutation dip depends on the current level
too). ERG, slope and motoring promise a power or a torque, so outside the paper's
resistance mode a slow integral trim (:class:`.modes.TorqueTrim`) closes the loop on the
measured mean torque of the last batch.

A drive on CAN (PlantState.measured_by_drive): the drive's firmware owns the current loop,
so there are no gates to decide. :class:`DriveTorqueLaw` runs the same mode law on the
measured speed, trims on the drive's torque estimate, and the controller answers with a
torque setpoint only (empty gate arrays; the node puts it in DriveCommand.torque_cmd_nm,
motoring positive). Time is the PlantState stamp, so the law holds while the plant's sim
time stands still (drive not armed); while the drive is lost (FAULT_DRIVE_LOST) it answers
zero torque and restarts with a ramp from zero when the drive is back.
"""
from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np

from bike_plant.heart import heart_rate_command_problem
from bike_plant.mechanics import road_problem
from bike_plant.params import PACK_EMPTY_SOC

from .bldc_control import C_COMMAND, C_ICMD, C_IOVERRIDE, C_MODE, C_NC, C_SPEED_EST, BatchController
from .modes import (BRAKE_ONLY_MODES, MODE_MOTORING, MODE_NAMES, MODE_RESISTANCE, MODE_SPINDOWN, ModeLaw,
                    ModeOutput, TorqueTrim, modes_from_config)

FAULT_DRIVE_LOST = 16        # bike_msgs/PlantState.FAULT_DRIVE_LOST (this module imports no ROS)
FAULT_DRIVE_DISARMED = 256   # bike_msgs/PlantState.FAULT_DRIVE_DISARMED: held like a lost drive
FAULT_DRIVE_STALE = 1024     # bike_msgs/PlantState.FAULT_DRIVE_STALE: the drive's estimates are old, hold
HELD_MEASUREMENT_S = 0.05    # speed and torque bit-identical this long (stamp time): a held value, not fresh
MAX_SKIPPED_S = 0.5          # the most skipped time the mode laws' clocks count at once (skipped_time_s)


_log = logging.getLogger("bike_controller.session_control")


class EmptyPackGuard:
    """No assist from an empty pack. A real pack's BMS opens its discharge path at the empty
    mark (undervoltage cut-off) and still takes charge, so motoring torque (brake < 0) is held
    at zero while PlantState.battery_soc <= ``empty_soc``; braking, which charges the pack, is
    untouched. Without it a motoring session drove the model's state of charge below zero.
    Each held step is counted (``holds``); the first of an episode is logged."""

    def __init__(self, empty_soc: float = PACK_EMPTY_SOC):
        self.empty_soc = float(empty_soc)
        self.holds = 0
        self.active = False

    def empty(self, battery_soc) -> bool:
        return battery_soc is not None and math.isfinite(battery_soc) and battery_soc <= self.empty_soc

    def hold(self, battery_soc, what: str) -> None:
        """Count one held step; log the first of an episode."""
        self.holds += 1
        if not self.active:
            _log.warning("battery empty (state of charge %.4f <= %.4f): %s held at 0 until the pack is charged",
                         battery_soc, self.empty_soc, what)
        self.active = True

    def hold_while_empty(self, battery_soc, what: str) -> None:
        """For a law that holds the assist itself (the SPMSM isokinetic speed loop): count a
        held step while the pack is empty, end the episode once it is not."""
        if self.empty(battery_soc):
            self.hold(battery_soc, what)
        else:
            self.active = False

    def limit(self, brake_torque_nm: float, battery_soc) -> float:
        empty = self.empty(battery_soc)
        if empty and brake_torque_nm < 0.0:
            self.hold(battery_soc, f"assist of {-brake_torque_nm:.3f} N m")
            return 0.0
        self.active = self.active and empty
        return brake_torque_nm


def skipped_time_s(gap_periods: int, control_period_s: float) -> float:
    """The time of the plant states skipped before the one answered (realtime: the controller
    reads the newest plant state only, and skips what came while it was descheduled; the inner
    laws count them, ``gap_periods``), which the mode laws' clocks count
    (:meth:`.modes.ModeLaw.step`'s ``skipped_s``). Before, a stall stopped them: the
    spin-down's clock and its coast's time axis (the BLDC bike's) fell behind by every stall.
    At most MAX_SKIPPED_S: a longer jump of the period count is no host stall (the plant has
    been in its safe state since its command timeout, 0.05 s in sim, 0.25 s on CAN), and one
    step must not run out a spin-down's timeout or the automatic shifting's hold. 0 without
    a gap (lockstep, always): the laws step as before, bit for bit."""
    if gap_periods <= 0:
        return 0.0
    return min(gap_periods * control_period_s, MAX_SKIPPED_S)


def validate_session_command(command, mode) -> None:
    """Command in [0, 1] and one of the modes (MODE_NAMES); ValueError otherwise."""
    if isinstance(command, bool) or not isinstance(command, (int, float)) or not math.isfinite(command):
        raise ValueError(f"command must be a finite number, got {command!r}")
    if not 0.0 <= command <= 1.0:
        raise ValueError(f"command must be in [0, 1], got {command!r}")
    if isinstance(mode, bool) or int(mode) != mode or int(mode) not in MODE_NAMES:
        names = ", ".join(f"{k} {v}" for k, v in MODE_NAMES.items())
        raise ValueError(f"unknown mode {mode!r} ({names})")


class DriveTorqueLaw:
    """Torque-only answer for a drive that owns its current loop (measured_by_drive).

    Per PlantState: dt = stamp - previous stamp (the nominal batch time for the first, 0
    while the plant's sim time stands still, at most 10 batches); mode torque from the
    measured speed (:class:`.modes.ModeLaw`), trimmed on the measured torque
    (:class:`.modes.TorqueTrim`). Returns the braking torque (> 0 brakes) and the law's
    output. With FAULT_DRIVE_LOST: zero, and the next step ramps up from zero like a mode
    switch (no torque step for the rider when the drive comes back).

    Stale measurements (FAULT_DRIVE_STALE, or speed and torque repeated bit for bit for
    ``HELD_MEASUREMENT_S`` of stamp time, i.e. a plant that holds its last frame without
    saying so): the trim holds (no integration on a frozen value); with the flag the law's
    own integrators hold too (dt = 0). ERG and the resistance mode are brake-only: the trim
    never turns their brake into motoring (:class:`.modes.TorqueTrim`, counted and
    reported as a saturation)."""

    def __init__(self, law: ModeLaw, trim: TorqueTrim, batch_s: float):
        self.law = law
        self.trim = trim
        self.pack = EmptyPackGuard()
        self.batch_s = float(batch_s)
        self.last_stamp_ns: int | None = None
        self.lost = False
        self.stale_steps = 0                     # steps held on a stale / repeated measurement
        self._last_meas = None                   # (speed_rpm, torque_em_nm) of the last step
        self._meas_since_ns: int | None = None   # stamp when that pair last changed

    def step(self, command: float, mode: int, snapshot: dict) -> tuple[float, ModeOutput]:
        stamp = snapshot.get("stamp_ns")
        if stamp is None or self.last_stamp_ns is None:
            dt = self.batch_s
        else:
            dt = min(max((int(stamp) - self.last_stamp_ns) * 1e-9, 0.0), 10.0 * self.batch_s)
        if stamp is not None:
            self.last_stamp_ns = int(stamp)
        if int(snapshot.get("faults", 0)) & (FAULT_DRIVE_LOST | FAULT_DRIVE_DISARMED):
            if not self.lost:
                self.lost = True
                self.law.reset(0.0)
                self.law.last_mode = -1          # not a mode: the next step is a switch, ramped from 0
                self.trim.reset()
            return 0.0, ModeOutput(0.0, 0.0, command, 0.0, False, True)
        self.lost = False
        speed_rpm = float(snapshot.get("speed_rpm", 0.0))
        flagged = bool(int(snapshot.get("faults", 0)) & FAULT_DRIVE_STALE)
        held = self._held(snapshot, speed_rpm, stamp)    # tracked while flagged too
        fresh = not (flagged or held)
        if not fresh:
            self.stale_steps += 1
        # a flagged stale speed: the law's own integrators (speed loops, virtual bike) hold too
        measured = snapshot.get("torque_em_nm")
        out = self.law.step(command, mode, speed_rpm, 0.0 if flagged else dt, speed_valid=math.isfinite(speed_rpm),
                            measured_em_torque_nm=measured if fresh else None,
                            heart_rate_bpm=snapshot.get("heart_rate_bpm", 0.0))
        brake = self.trim.correct(out.brake_torque_nm, measured, dt, fresh=fresh, brake_only=mode in BRAKE_ONLY_MODES,
                                  saturated=out.saturated, released=mode == MODE_SPINDOWN)
        brake = self.pack.limit(brake, snapshot.get("battery_soc"))
        if (self.trim.clamped or self.pack.active) and not out.saturated:
            out = dataclasses.replace(out, saturated=True)
        return brake, out

    def _held(self, snapshot: dict, speed_rpm: float, stamp) -> bool:
        """Speed and torque estimate have not changed for HELD_MEASUREMENT_S of stamp time."""
        meas = (speed_rpm, snapshot.get("torque_em_nm"))
        if stamp is not None and (meas != self._last_meas or self._meas_since_ns is None):
            self._last_meas, self._meas_since_ns = meas, int(stamp)
        held = (stamp is not None and self._meas_since_ns is not None
                and (int(stamp) - self._meas_since_ns) * 1e-9 > HELD_MEASUREMENT_S)
        return held


def drive_status(base: dict, brake_nm: float, out: ModeOutput, speed_rpm: float, kt: float,
                 base_speed_rpm: float, trim_nm: float) -> dict:
    """ControllerStatus fields of a torque-only answer (``base``: command, mode, ...)."""
    status = dict(base)
    status.update({
        "speed_est_rpm": float(speed_rpm), "torque_cmd_nm": abs(brake_nm), "k_factor": 1.0,
        "ktg_nm_per_a": float(kt), "current_cmd_a": abs(brake_nm) / kt if kt > 0 else 0.0,
        "region": 0 if speed_rpm < base_speed_rpm else 1,
        "quadrant": 2 if brake_nm >= 0.0 else 1,            # ControllerStatus.QUADRANT_*
        "prediction_error_a": 0.0,
        "mode_target": float(out.target), "mode_saturated": bool(out.saturated),
        "mode_ramping": bool(out.ramping), "virtual_speed_mps": float(out.virtual_speed_mps),
        "torque_trim_nm": float(trim_nm),
        "family": "", "speed_ref_rpm": 0.0, "id_a": 0.0, "iq_a": 0.0, "id_ref_a": 0.0, "iq_ref_a": 0.0,
        "vd_v": 0.0, "vq_v": 0.0,
    })
    return status


class SessionCommand:
    """The session's Command in force (validated), shared by the machines' moded laws."""

    command: float = 0.0
    mode: int = MODE_RESISTANCE
    command_rejected: bool = False

    @property
    def skipped_state_gaps(self) -> int:
        """Decides after skipped plant states (realtime; counted by the inner law)."""
        return self.inner.skipped_state_gaps

    @property
    def skipped_periods(self) -> int:
        """Control periods the skipped plant states covered."""
        return self.inner.skipped_periods

    def set_command(self, command: float, mode: int = MODE_RESISTANCE, virtual_gear_ratio: float = 0.0,
                    road: tuple[float, float, float] | None = None, heart_rate_bpm: float = 0.0) -> None:
        """The Command in force; ``virtual_gear_ratio`` shifts the virtual bike
        (:meth:`ModeLaw.set_virtual_gear`, 0: the config's gear), ``road`` is its road
        (:meth:`ModeLaw.set_road`, None: the config's), ``heart_rate_bpm`` an ERG's heart-rate
        target (:meth:`ModeLaw.set_heart_rate_target`, 0: none). ValueError: nothing changes."""
        try:
            validate_session_command(command, mode)
            problem = heart_rate_command_problem(heart_rate_bpm, mode)
            if problem:
                raise ValueError(problem)
            if road is not None:
                problem = road_problem(*road)
                if problem:
                    raise ValueError(problem)
            self.law.set_virtual_gear(virtual_gear_ratio)     # checks the gear; shifts only if it is good
            self.law.set_road(road)
            self.law.set_heart_rate_target(heart_rate_bpm)
        except ValueError:
            self.command_rejected = True
            raise
        self.command_rejected = False
        self.command = float(command)
        self.mode = int(mode)


class ModedController(SessionCommand):
    """BatchController + session modes (same decide/status interface)."""

    def __init__(self, cfg: dict, nominal_params=None, batch_periods: int | None = None):
        self.inner = BatchController(cfg, nominal_params, batch_periods)
        mp, (b_nms, dry_nm, dry_rpm) = modes_from_config(cfg)
        nominal = self.inner.nominal
        self.law = ModeLaw(mp, gear_ratio=nominal.load.gear_ratio, inertia_kgm2=nominal.mech.inertia_kgm2,
                           tmax_nm=self.inner.cp.tmax_nm, pmax_w=self.inner.cp.pmax_w,
                           base_speed_rpm=self.inner.cp.base_speed_rpm,
                           friction_nms=b_nms, dry_friction_nm=dry_nm, dry_friction_speed_rpm=dry_rpm)
        self.kt = float(nominal.bldc.kt_nm_per_a)
        self.mode_ktg: float | None = None     # a mode's current override: its ktg (None: Eq. 2-9 inside)
        self.command = float(self.inner.cs[C_COMMAND])
        self.mode = int(self.inner.cs[C_MODE])
        self.command_rejected = False
        self.last_out: ModeOutput | None = None
        self.trim = TorqueTrim(self.inner.cp.tmax_nm)
        self.pack = EmptyPackGuard()
        self.law.reset()
        self.drive_law = DriveTorqueLaw(self.law, self.trim,
                                        self.inner.batch_periods * nominal.control_period_s)

    @property
    def batch_periods(self) -> int:
        return self.inner.batch_periods

    @property
    def cs(self):
        return self.inner.cs

    def _apply_mode(self, dt_s: float, snapshot: dict, skipped_s: float = 0.0) -> None:
        """``dt_s``: the batch's time; ``skipped_s``: of the plant states skipped before this one
        (:func:`skipped_time_s`), which the mode law's clocks count."""
        inner = self.inner
        speed_rpm = float(inner.cs[C_SPEED_EST])
        measured = snapshot.get("torque_em_nm")
        out = self.law.step(self.command, self.mode, speed_rpm, dt_s, speed_valid=inner.cs[C_NC] > 0,
                            measured_em_torque_nm=measured, heart_rate_bpm=snapshot.get("heart_rate_bpm", 0.0),
                            skipped_s=skipped_s)
        self.last_out = out
        if self.mode == MODE_RESISTANCE and not out.ramping:
            self.trim.reset()
            self.mode_ktg = None
            inner.cs[C_IOVERRIDE] = -1.0                         # no override: Eq. 2-9 inside the batch
            inner.set_command(self.command, MODE_RESISTANCE)
            return
        # after skipped plant states the measured torque is of a batch the plant ran on the held
        # command or in its safe state, not on the torque asked: no trim on it
        torque = self.trim.correct(out.brake_torque_nm, measured, dt_s, fresh=skipped_s == 0.0,
                                   brake_only=self.mode in BRAKE_ONLY_MODES, saturated=out.saturated,
                                   released=self.mode == MODE_SPINDOWN)
        torque = self.pack.limit(torque, snapshot.get("battery_soc"))
        if self.pack.active and not out.saturated:
            self.last_out = out = dataclasses.replace(out, saturated=True)
        if torque >= 0.0:
            inner.set_command(self.command if self.mode == MODE_RESISTANCE else 0.0, MODE_RESISTANCE)
            self.mode_ktg = inner.ktg(speed_rpm, torque)        # k of the Command that asks this torque
        else:
            inner.set_command(0.0, MODE_MOTORING)
            self.mode_ktg = self.kt
        current = abs(torque) / self.mode_ktg
        inner.set_current_override(current)

    def decide(self, snapshot: dict, n: int | None = None):
        if snapshot.get("measured_by_drive"):
            return self._decide_torque(snapshot)
        n_eff = self.inner.batch_periods if n is None else int(n)
        period_s = self.inner.nominal.control_period_s
        self._apply_mode(n_eff * period_s, snapshot, skipped_time_s(self.inner.gap_periods(snapshot), period_s))
        ga, gb, sp, status = self.inner.decide(snapshot, n)
        return ga, gb, sp, self._status(status)

    def _decide_torque(self, snapshot: dict):
        """A drive on CAN: no gates, a torque setpoint (see :class:`DriveTorqueLaw`)."""
        brake, out = self.drive_law.step(self.command, self.mode, snapshot)
        self.last_out = out
        speed = float(snapshot.get("speed_rpm", 0.0))
        base = {"seq": int(snapshot.get("seq", 0)), "command": self.command, "mode": self.mode,
                "command_rejected": self.command_rejected, "virtual_gear_ratio": self.law.virtual_gear_ratio}
        status = drive_status(base, brake, out, speed, self.kt, self.inner.cp.base_speed_rpm, self.trim.trim_nm)
        status.update(self.law.status_fields())
        empty = np.zeros(0, np.uint8)
        return empty, empty.copy(), np.zeros(0), status

    def _inside_the_band(self) -> bool:
        """The resistance mode's brake (Eq. 3-9, no override) whose current command lies inside
        the hysteresis half band (Command 0.03 at 5250 rpm: 1.3 A against 1.5 A) brakes nothing:
        the switch closes only below I* - h < 0, and a generating winding's current does not go
        negative. Said, not given silently. (The closed-loop modes' overrides are left to their
        own flags: a descent's 0.03-0.08 N m asks inside the band tracked the virtual bike to
        0.002 m/s.)"""
        cs = self.inner.cs
        return bool(cs[C_MODE] == MODE_RESISTANCE and cs[C_IOVERRIDE] < 0.0
                    and 0.0 < cs[C_ICMD] <= self.inner.cp.hysteresis_a)

    def _status(self, status: dict) -> dict:
        out = self.last_out
        status = dict(status)
        status["command"] = self.command
        status["mode"] = self.mode
        status["command_rejected"] = self.command_rejected
        if out is not None and not (self.mode == MODE_RESISTANCE and not out.ramping):
            status["torque_cmd_nm"] = abs(out.brake_torque_nm)
        if self.mode_ktg is not None:
            # the current override's Eq. 8-9 constant (the inner law's cs holds Command 0's row)
            status["ktg_nm_per_a"] = float(self.mode_ktg)
            status["k_factor"] = float(self.mode_ktg / self.kt)
        status["mode_target"] = float(out.target) if out is not None else self.command
        status["mode_saturated"] = bool(out is not None and out.saturated) or self.trim.saturated \
            or self._inside_the_band()
        status["mode_ramping"] = bool(out is not None and out.ramping)
        status["virtual_speed_mps"] = float(out.virtual_speed_mps) if out is not None else 0.0
        status["virtual_gear_ratio"] = self.law.virtual_gear_ratio
        status["torque_trim_nm"] = float(self.trim.trim_nm)
        # the SPMSM's dq telemetry does not apply to this machine
        status.update(family="", speed_ref_rpm=0.0, id_a=0.0, iq_a=0.0, id_ref_a=0.0, iq_ref_a=0.0, vd_v=0.0, vq_v=0.0)
        status.update(self.law.status_fields())
        return status

    def status(self, seq: int = 0, prediction_error_a: float = 0.0) -> dict:
        return self._status(self.inner.status(seq, prediction_error_a))
