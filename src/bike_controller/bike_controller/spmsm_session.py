"""The SPMSM bike (paper 001) in a session: session modes on top of the SPMSM control law.

:class:`ModedSpmsmController` is to :class:`.spmsm_control.SpmsmController` what
:class:`.session_control.ModedController` is to the BLDC law: same ``set_command`` /
``decide`` / ``status`` interface, all five Command modes, per batch:

- the mode law (:class:`.modes.ModeLaw`, the same code as the BLDC bike's) turns
  (Command, mode, speed) into a signed braking torque, ramped at mode switches;
- braking (torque >= 0 on the mean): the relay selects the rectifier + buck + charger path
  and the buck duty sets the braking torque (paper 001, Fig. 2/8: "generating: braking
  torque when it goes uphill");
- assist (torque < 0 on the mean, downhill or motoring) and ISOKINETIC: the relay selects
  the inverter; isokinetic runs the paper's speed loop (predictive or PI) at the target
  cadence, assist hands the current loops iq* = T / Kt
  (:meth:`SpmsmController.set_torque_command`), which brake as well when the torque turns
  within a pedal stroke;
- "on the mean": :class:`RelayPath` switches on the sign of the torque's running mean, at
  most once per ``controller.relay_hold_s``, not on every batch's sign.

Machine figures for the mode law: gear = ``load.gear_ratio`` (motor / crank), Tmax =
``controller.tmax_nm`` or Kt * current limit, base speed = the rated speed (200 r/min),
Pmax = Tmax * wb (the resistance curve of paper 000, Eq. 2-4, on this machine).

The controller sees the PlantState measurement; the predictor's model vector is rebuilt
from it (:func:`model_state_from_snapshot`): currents, encoder, angle, speed, relay, SOC.
"""
from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np

from bike_plant import spmsm as M
from bike_plant.params import RPM_PER_RAD_S

from .modes import (BRAKE_ONLY_MODES, MODE_ISOKINETIC, MODE_RESISTANCE, MODE_SPINDOWN, ModeLaw, ModeOutput, TorqueTrim,
                    machine_figures, modes_from_config)
from .session_control import DriveTorqueLaw, EmptyPackGuard, SessionCommand, drive_status, skipped_time_s
from .spmsm_control import (C_IQ_REF, C_SPEED_EST, C_TORQUE_MODE, Q_LINK_MAX, Q_PP, SpmsmController, brake_torque_nm,
                            controller_params_from_config)
from .spindown import EncoderSpeed

_log = logging.getLogger(__name__)


# the plant-state layout, bound once: the model vector is rebuilt for every batch, and its ~20
# module attribute look-ups and a generator were ~0.4 of its ~3.8 us (same values, same arithmetic)
_S_IA, _S_IB, _S_IC, _S_ID, _S_IQ = M.S_IA, M.S_IB, M.S_IC, M.S_ID, M.S_IQ
_S_COUNT, _S_REV, _S_EDGE_TICKS, _S_PERIODS = M.S_COUNT, M.S_REV, M.S_EDGE_TICKS, M.S_PERIODS
_S_RELAY, _S_RELAY_TO, _S_SPEED_TARGET, _S_OMEGA = M.S_RELAY, M.S_RELAY_TO, M.S_SPEED_TARGET, M.S_OMEGA
_P_PP, _P_CPR = M.P_PP, M.P_CPR
_REL_PATHS = (M.REL_INVERTER, M.REL_RECTIFIER)
_SQRT3 = math.sqrt(3.0)
_TWO_PI = 2.0 * math.pi


def model_state_from_snapshot(p_nom: np.ndarray, snap: dict) -> np.ndarray:
    """The plant-model state vector (bike_plant.spmsm.S_*) from a PlantState snapshot."""
    get = snap.get
    theta_m = float(get("rotor_angle_mech_rad", 0.0))
    s = M.new_state(p_nom, float(snap["speed_rpm"]), float(get("battery_soc", 0.5)), theta_m)
    ia, ib, ic = map(float, snap["phase_current_a"])
    s[_S_IA] = ia
    s[_S_IB] = ib
    s[_S_IC] = ic
    # Park with the electrical angle: amplitude-invariant Clarke, as the plant's model
    th_e = p_nom[_P_PP] * theta_m
    i_al = (2.0 * ia - ib - ic) / 3.0
    i_be = (ib - ic) / _SQRT3
    c, sn = math.cos(th_e), math.sin(th_e)
    s[_S_ID] = c * i_al + sn * i_be
    s[_S_IQ] = -sn * i_al + c * i_be
    count = float(get("encoder_count", s[_S_COUNT]))
    s[_S_COUNT] = count
    # whole revolutions: the model's count is rev * cpr + floor(theta cpr / 2 pi)
    cpr = p_nom[_P_CPR]
    s[_S_REV] = float(math.floor((count - math.floor(theta_m * cpr / _TWO_PI)) / cpr + 0.5))
    s[_S_EDGE_TICKS] = float(get("encoder_edge_ticks", 0))
    s[_S_PERIODS] = float(int(get("seq", 0)) * int(get("batch_periods", 0) or 0))
    relay = int(get("relay_state", 0))
    if relay in _REL_PATHS:
        s[_S_RELAY] = s[_S_RELAY_TO] = relay
    else:
        s[_S_RELAY] = M.REL_DRAIN
        s[_S_RELAY_TO] = M.REL_INVERTER
    s[_S_SPEED_TARGET] = s[_S_OMEGA]
    return s


class RelayPath:
    """Which path of paper 001's Fig. 2 carries the mode law's torque: the rectifier + buck +
    charger brakes ("uphill"), the inverter assists ("downhill") and, through its current
    loops, can brake as well (into the battery).

    The relay follows the sign of the torque's running mean (time constant ``hold_s``), not
    of each batch's torque, and stays at least ``hold_s`` on a path. The virtual bike's
    torque changes sign within a pedal stroke (the mass of rider and bike carries the cranks
    through the dead spots). Following that sign switched the relay at every stroke: on a 4 %
    climb at ~300 r/min, 83 switch-overs in 4 s. 41 of them opened the relay under current,
    because at that speed the inverter's diodes conduct and its current cannot be drained.
    A relay is a mechanical part, and every switch-over leaves the machine unpowered for its
    dead interval.

    On the rectifier path an assist the law wants is not given (the caller clips it and says
    so). The inverter serves both signs. ``band_nm``: the mean must pass +-band to switch.

    Leaving the inverter, the control kernel takes iq to zero before it asks the relay to move
    (:func:`.spmsm_control.control_period`, ``relay_predrain_s``): not here, on the batch's
    torque, but per period on the measured current, for every caller of ``set_relay``. Asked at
    once, the isokinetic loop's brake (~340 r/min) was -3.2 N m when the relay was forced open."""

    def __init__(self, hold_s: float, band_nm: float):
        self.hold_s = float(hold_s)
        self.band_nm = float(band_nm)
        self.rectifier: bool | None = None    # None: no torque yet; the first one decides
        self.mean_nm = 0.0                    # running mean of the wanted braking torque
        self.since_s = 0.0                    # time on the present path
        self.switches = 0

    def force(self, rectifier: bool) -> None:
        """A mode that needs one path (the isokinetic speed loop: the inverter) takes it now;
        the next mode's mean starts afresh."""
        if self.rectifier is not None and rectifier != self.rectifier:
            self.switches += 1
        self.rectifier = bool(rectifier)
        self.mean_nm = 0.0
        self.since_s = 0.0

    def choose(self, brake_torque_nm: float, dt_s: float, skipped_s: float = 0.0) -> bool:
        """True: the rectifier path for the next ``dt_s``, False: the inverter. ``skipped_s``:
        the time of plant states skipped before this one (realtime), which the relay spent on its
        path (its hold counts it; the mean, of the torques asked, does not).

        No torque asked (exactly 0: the resistance mode at Command 0, a spin-down's coast, an assist
        an empty pack holds) with the mean inside the band: the rectifier path, whose buck at duty 0
        carries no current. The inverter's zero torque costs current above the base speed (the
        flux-weakening id): after a motoring Command, resistance 0 at 80 rpm kept the inverter for
        good, and it drew 41 W from the battery into its copper while the rider pedalled freely."""
        if self.rectifier is None:
            self.rectifier = brake_torque_nm >= 0.0
            self.mean_nm = brake_torque_nm
            return self.rectifier
        self.since_s += dt_s + skipped_s
        k = min(dt_s / self.hold_s, 1.0) if self.hold_s > 0.0 else 1.0
        self.mean_nm += k * (brake_torque_nm - self.mean_nm)
        if self.since_s >= self.hold_s - 1e-9:
            if self.rectifier and self.mean_nm < -self.band_nm:
                self.force(False)
            elif not self.rectifier and (self.mean_nm > self.band_nm
                                         or (brake_torque_nm == 0.0 and abs(self.mean_nm) <= self.band_nm)):
                self.force(True)
            else:
                return self.rectifier
            self.mean_nm = brake_torque_nm
        return self.rectifier


def envelope_summary(envelope, gear_ratio: float) -> str:
    """One line on what the rectifier path can brake (said once at start-up: a resistance
    that is zero at low cadence is the path's physics, not a fault)."""
    rpm, nm = envelope
    onset = next((r for r, t in zip(rpm, nm) if t > 0.0), None)
    if onset is None:
        return "rectifier braking envelope: the path cannot brake at any speed up to %g r/min" % rpm[-1]
    k = max(range(len(nm)), key=nm.__getitem__)
    return (f"rectifier braking envelope: no brake below {onset:g} r/min (cadence {onset / gear_ratio:.0f} rpm), "
            f"strongest {nm[k]:.2f} N m at {rpm[k]:g} r/min; the resistance mode is Command x this envelope "
            "where it is below Eq. 3-4")


class ModedSpmsmController(SessionCommand):
    """SpmsmController + session modes (same decide/status interface as ModedController)."""

    def __init__(self, cfg: dict, nominal_params=None, batch_periods: int | None = None):
        self.inner = SpmsmController(cfg, nominal_params, batch_periods=batch_periods)
        nominal = self.inner.nominal
        cp = controller_params_from_config(cfg)
        # the observer's pole: the paper's (fitted to Table 1's load step), and the isokinetic
        # speed loop's (see _apply_mode)
        self.observer_poles_hz = (cp.observer_pole_hz, cp.isokinetic_observer_pole_hz)
        self.speed_loop_active = False
        self.kt = float(nominal.spmsm.torque_constant_nm_per_a)
        fig = machine_figures(cfg)
        tmax, base = fig.tmax_nm, fig.base_speed_rpm
        mp, (b_nms, dry_nm, dry_rpm) = modes_from_config(cfg)
        self.gear = float(nominal.load.gear_ratio)
        self.law = ModeLaw(mp, gear_ratio=self.gear, inertia_kgm2=nominal.mech.inertia_kgm2, tmax_nm=tmax,
                           pmax_w=fig.pmax_w, base_speed_rpm=base,
                           # the machine's friction with its Coulomb part (the predictor's
                           # nominal model is the paper's ideal machine, without it)
                           friction_nms=b_nms, dry_friction_nm=dry_nm, dry_friction_speed_rpm=dry_rpm,
                           brake_envelope=fig.brake_envelope)
        # the encoder as the spin-down's speed sensor (its fit must not see the observer's lag)
        self.encoder_speed = EncoderSpeed(nominal.encoder.counts_per_rev, nominal.encoder.capture_timer_hz)
        # for the node's log at start-up
        self.startup_note = envelope_summary(fig.brake_envelope, self.gear) if fig.brake_envelope else ""
        self.family = cp.family
        self.command = 0.0
        self.mode = MODE_RESISTANCE
        self.command_rejected = False
        self.last_out: ModeOutput | None = None
        self.started = False
        self.trim = TorqueTrim(tmax)
        # below 1 % of Tmax an assist the rectifier path cannot give is not worth a saturated
        # flag, nor a mean torque worth a switch-over
        self.clip_tolerance_nm = 0.01 * tmax
        self.relay = RelayPath(cp.relay_hold_s, self.clip_tolerance_nm)
        self.pack = EmptyPackGuard()
        self.battery_soc = None          # of the last PlantState: no assist from an empty pack
        # a full pack (the charger's dump threshold): the inverter puts braking energy straight
        # into the pack, so braking goes through the rectifier path, whose dump resistor takes it
        self.full_soc = float(nominal.battery.dump_above_soc)
        self.full_holds = 0              # batches whose braking the inverter path held at zero
        self.full_active = False
        self.base_speed_rpm = base
        # modes.assist_max_nm (0: Tmax) holds the isokinetic speed loop's assist as it holds the mode law's:
        # the paper's loop motored up to the current limit whatever it said (1.26 N m for 0.5)
        self.inner.set_assist_cap(mp.assist_max_nm / self.kt if mp.assist_max_nm > 0.0 else 0.0)
        # the last batch's torque command on the inverter was beyond its reach (the region logic
        # clipped iq* at the voltage / current limit: assist above ~150 r/min on the 24 V link)
        self.inverter_limited = False
        # a drive on CAN (measured_by_drive): torque setpoints only, see session_control
        self.drive_law = DriveTorqueLaw(self.law, self.trim, self.inner.batch_periods * nominal.control_period_s)

    @property
    def batch_periods(self) -> int:
        return self.inner.batch_periods

    def _apply_mode(self, speed_rpm: float, dt_s: float, measured_em_torque_nm, sensor_sample=None,
                    heart_rate_bpm: float = 0.0, skipped_s: float = 0.0) -> None:
        """``dt_s``: the batch's time; ``skipped_s``: of the plant states skipped before this one
        (:func:`.session_control.skipped_time_s`), which the mode law's clocks and the relay's
        hold count."""
        inner = self.inner
        out = self.law.step(self.command, self.mode, speed_rpm, dt_s, measured_em_torque_nm=measured_em_torque_nm,
                            sensor_sample=sensor_sample, heart_rate_bpm=heart_rate_bpm, skipped_s=skipped_s)
        self.last_out = out
        inner.set_no_assist(self.pack.empty(self.battery_soc))
        full = self._pack_full()
        speed_loop = self.mode == MODE_ISOKINETIC and not out.ramping and not full
        if speed_loop != self.speed_loop_active:
            # The speed loop closes on the observer's estimate, and the rider's pedal strokes (a
            # 2-5 Hz load torque) reach the estimate through the observer's pole: at the paper's
            # 5 Hz the estimate lagged the shaft by 24 r/min rms at 80 rpm; at 50 rpm (a rider
            # who wants 80) by 93, and the loop held the estimate at 200 r/min while the shaft
            # ran 150-440. The other modes' laws were tuned on the 5 Hz estimate (a faster one
            # makes the virtual bike's descent track 0.20 m/s rms for 0.14), so they keep it.
            self.speed_loop_active = speed_loop
            inner.set_observer_pole(self.observer_poles_hz[int(speed_loop)])
        if speed_loop:
            self.trim.reset()
            # the speed loop may brake (charging) but not motor: held inside its 1 ms law
            self.pack.hold_while_empty(self.battery_soc, "the isokinetic speed loop's assist")
            self.relay.force(False)
            inner.set_relay(False)
            target = out.target * self.gear
            inner.set_speed_ref(target, target)
            self._torque_command(None)
            # the mode law's isokinetic PI (the full-pack fallback below) is kept at the torque in
            # force, so a switch to it continues from there (before: a step of 7.5 N m to Tmax)
            in_force_nm = -self.kt * float(inner.cs[C_IQ_REF])
            self.law.integral_nm = in_force_nm - self.law.kp * (speed_rpm - target) / RPM_PER_RAD_S
            return
        # (a full pack: the isokinetic mode brakes with the mode law's PI below, through the
        # relay like the other modes, instead of the paper's speed loop on the inverter)
        # ERG and resistance are brake-only: a trim wound up on a bad torque reading must not
        # turn their brake into assist (clamped, counted and logged by the trim)
        if self.inverter_limited:
            # the shortfall of a torque the inverter could not reach is no model error: a trim
            # wound up on it (to its 30 % of Tmax) gave 2.6x the assist asked once the speed fell
            self.trim.hold_last()
        # after skipped plant states the measured torque is of a batch the plant ran on the held
        # command or in its safe state, not on the torque asked: no trim on it
        torque = self.trim.correct(out.brake_torque_nm, measured_em_torque_nm, dt_s, fresh=skipped_s == 0.0,
                                   brake_only=self.mode in BRAKE_ONLY_MODES, saturated=out.saturated,
                                   released=self.mode == MODE_SPINDOWN)
        torque = self.pack.limit(torque, self.battery_soc)
        if torque <= 0.0 and not self.relay.rectifier and self.pack.empty(self.battery_soc):
            # an empty pack's BMS has opened its discharge path: the rectifier path now, not after
            # the relay's hold. The inverter's zero torque above the base speed still drew the
            # flux-weakening current from the pack: 2-5 A (~80 W) at 330-490 r/min, a 0.5 mAh pack
            # emptied under assist went on to SOC -3.4 within 2 s with the assist held at 0
            self.relay.force(True)
        clipped = False
        if self.relay.choose(torque, dt_s, skipped_s):
            # the rectifier path brakes only: an assist wanted before the relay may switch is not given
            clipped = torque < -self.clip_tolerance_nm
            torque = max(torque, 0.0)
            # ... nor a brake below the path's least: with the buck at its lowest duty (the link at
            # regen.link_max_v) the diodes still conduct once the back-EMF passes that link (about
            # 510 r/min with the paper's machine): a rider at 150 rpm, at resistance 0 or asking
            # less than that floor, was braked 4.9 N m while the status said 0 and nothing was flagged
            clipped = clipped or self.rectifier_floor_nm(speed_rpm) > torque + self.clip_tolerance_nm
            inner.set_relay(True)
            inner.set_brake_torque(torque)
            self._torque_command(None)
        else:
            if full and torque > 0.0:
                # until the relay's mean moves it to the rectifier: no braking into a full pack
                clipped = torque > self.clip_tolerance_nm
                torque = 0.0
                self.full_holds += 1
            inner.set_relay(False)
            if not self._torque_command(torque):
                inner.set_speed_ref(speed_rpm, speed_rpm)
        if (self.trim.clamped or self.pack.active or clipped) and not out.saturated:
            self.last_out = out = dataclasses.replace(out, saturated=True)

    def rectifier_floor_nm(self, speed_rpm: float) -> float:
        """The least braking torque of the rectifier path at ``speed_rpm`` (motor): the steady state
        of Fig. 8 with the buck at its lowest duty, the link at regen.link_max_v (0 below the
        speed at which the back-EMF passes it)."""
        q = self.inner.q
        return float(brake_torque_nm(q[Q_LINK_MAX], q[Q_PP] * speed_rpm / RPM_PER_RAD_S, q))

    def _pack_full(self) -> bool:
        soc = self.battery_soc
        full = soc is not None and math.isfinite(soc) and soc >= self.full_soc
        if full and not self.full_active:
            _log.warning("battery full (state of charge %.4f >= %.4f): braking goes through the rectifier "
                         "path and its dump resistor, not into the pack", soc, self.full_soc)
        self.full_active = full
        return full

    def _torque_command(self, brake_torque_nm: float | None) -> bool:
        """Assist through the current loops when the law has a torque input."""
        setter = getattr(self.inner, "set_torque_command", None)
        if setter is None:
            return False
        setter(None if brake_torque_nm is None else -brake_torque_nm)
        return True

    def decide(self, snapshot: dict, n: int | None = None):
        """(duties N x 3, relay N, buck N, status) answering a PlantState snapshot."""
        if snapshot.get("measured_by_drive"):
            return self._decide_torque(snapshot)
        inner = self.inner
        n_eff = inner.batch_periods if n is None else int(n)
        model = model_state_from_snapshot(inner.p, snapshot)
        if not self.started:
            inner.reset_from(model)            # bumpless: the drive starts at the measured speed
            self.started = True
        gap = inner.gap_periods(model)
        if gap:
            # after skipped plant states the estimate is of the shaft before them (the observer
            # re-acquires inside this batch): the law steps on the gap's mean speed, from the
            # encoder (a 50 ms safe state braked 330 r/min to 250)
            speed_rpm = inner.gap_mean_speed_rad_s(gap, float(model[M.S_COUNT])) * RPM_PER_RAD_S
        else:
            # the speed estimate alone (status_of's value): the whole status dict cost ~1.5 us a batch
            speed_rpm = float(inner.cs[C_SPEED_EST] * RPM_PER_RAD_S)
        self.battery_soc = snapshot.get("battery_soc")
        sample = None
        if self.mode == MODE_SPINDOWN:         # only the spin-down's fit takes the encoder's speed
            sample = self.encoder_speed.sample(snapshot.get("encoder_count", 0), snapshot.get("encoder_edge_ticks", 0))
        else:
            self.encoder_speed.ref = None      # its next spin-down starts from a fresh edge
        period_s = inner.nominal.control_period_s
        self._apply_mode(speed_rpm, n_eff * period_s, snapshot.get("torque_em_nm"), sample,
                         snapshot.get("heart_rate_bpm", 0.0), skipped_time_s(gap, period_s))
        duties, relay, buck, status = inner.decide(model, n_eff)
        # beyond reach: the region logic clipped iq* (not the current loop's saturated periods:
        # near the voltage edge the trim still gets more torque out of them, 4.96 N m for 4.94 at
        # 100 r/min, where holding it there gave 4.84)
        self.inverter_limited = bool(inner.cs[C_TORQUE_MODE]) and int(status["limits"]) != 0
        if self.inverter_limited:
            # the law's integrators hold on it as the trim does (hold_last): no wind-up on an
            # assist the 24 V link cannot give
            self.law.hold_integral()
        # ... and so is the isokinetic speed loop's torque, which the region logic clipped at the
        # current or the link's voltage limit: a rider who outpushes the brake (one who wants 80
        # rpm held at 50 averaged 75 rpm, and nothing said so)
        limited = self.inverter_limited or (self.speed_loop_active and (int(status["limits"]) != 0
                                                                        or inner.assist_capped()))
        if limited and self.last_out is not None and not self.last_out.saturated:
            self.last_out = dataclasses.replace(self.last_out, saturated=True)
        return duties, relay, buck, self._status(status)

    def _decide_torque(self, snapshot: dict):
        """A drive on CAN owns the current loop: a torque setpoint, no duties / relay / buck."""
        brake, out = self.drive_law.step(self.command, self.mode, snapshot)
        self.last_out = out
        base = {"seq": int(snapshot.get("seq", 0)), "command": self.command, "mode": self.mode,
                "command_rejected": self.command_rejected, "virtual_gear_ratio": self.law.virtual_gear_ratio}
        status = drive_status(base, brake, out, float(snapshot.get("speed_rpm", 0.0)), self.kt,
                              self.base_speed_rpm, self.trim.trim_nm)
        status.update(self.law.status_fields())
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0), status

    def _status(self, st: dict) -> dict:
        out = self.last_out
        speed = st["speed_est_rpm"]
        if self.speed_loop_active:
            # the isokinetic speed loop's torque is its iq* (braking positive), not the mode law's: it
            # brakes a rider who outpushes the cadence, and that is the generating quadrant (it was
            # reported as motoring throughout: all_modes' 70 rpm segment braked ~75 W as quadrant I)
            brake = -self.kt * float(st["iq_ref_a"])
        else:
            brake = out.brake_torque_nm if out is not None else 0.0
        region = int(st["region"])
        status = {
            "command": self.command, "mode": self.mode, "command_rejected": self.command_rejected,
            "speed_est_rpm": speed, "torque_cmd_nm": abs(brake), "k_factor": 1.0, "ktg_nm_per_a": self.kt,
            "current_cmd_a": st["iq_ref_a"], "region": region,
            "quadrant": 2 if (out is not None and brake >= 0.0) else 1,
            "prediction_error_a": 0.0,
            "mode_target": float(out.target) if out is not None else self.command,
            "mode_saturated": bool(out is not None and out.saturated) or self.trim.saturated,
            "mode_ramping": bool(out is not None and out.ramping),
            "virtual_speed_mps": float(out.virtual_speed_mps) if out is not None else 0.0,
            "virtual_gear_ratio": self.law.virtual_gear_ratio,
            "torque_trim_nm": float(self.trim.trim_nm),
            "family": self.family, "speed_ref_rpm": st["speed_ref_rpm"], "id_a": st["id_a"], "iq_a": st["iq_a"],
            "id_ref_a": st["id_ref_a"], "iq_ref_a": st["iq_ref_a"], "vd_v": st["vd_v"], "vq_v": st["vq_v"],
        }
        status.update(self.law.status_fields())     # in place: `|` copied the ~30 entries into a third dict
        return status

    def status(self, seq: int = 0, prediction_error_a: float = 0.0) -> dict:  # noqa: ARG002
        st = self._status(self.inner.status())
        st["seq"] = int(seq)
        return st
