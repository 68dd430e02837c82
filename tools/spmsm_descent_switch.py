"""README "Paper 001 reproduced": the SPMSM virtual bike's slope tracking, offline (the nodes'
batch exchange, no ROS). ``all_modes``: config/profiles/all_modes.yaml's segments (the rider
told the isokinetic segment's 70 rpm), the slope's error over 0.1 s windows wholly in the slope
as ./bike report takes it (rms, worst windows); ``trace``: also the -5 % descent's first second
every 10 ms (relay, true / estimated / virtual speed, rider / asked / braked torque, trim, the
slope law's integral). The graph's ride (./bike run --config config/spmsm_default.yaml
--workout config/profiles/all_modes.yaml --record DIR) reports the same 0.222 / 0.65 m/s (2026-12-07). ``descents``: ERG 180 W for 4 s, then -4/-5/-6/-8 % for 10 s, rms over the
last 7 s (test_spmsm_virtual_bike_descent_tracks_with_the_light_assist's ride).

    source tools/env.sh && python tools/spmsm_descent_switch.py [all_modes|descents|trace]
"""
import math
import pathlib
import sys

import numpy as np

from bike_controller.modes import MODE_ERG, MODE_ISOKINETIC, MODE_RESISTANCE, MODE_SLOPE
from bike_controller.spmsm_session import ModedSpmsmController
from bike_plant import spmsm as M
from bike_plant.config import load_config
from bike_plant.params import RPM_PER_RAD_S

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _new():
    cfg = load_config(ROOT / "config" / "spmsm_default.yaml")
    return M.SpmsmPlant(M.plant_params_from_config(cfg)), ModedSpmsmController(cfg)


def _batch(plant, ctrl):
    snap = plant.snapshot()
    snap.update(batch_periods=ctrl.batch_periods)
    duties, relay, buck, _ = ctrl.decide(snap)
    return plant.step_batch(duties, relay, buck)


def _grade_cmd(law, grade):
    return (grade - law.mp.grade_min) / (law.mp.grade_max - law.mp.grade_min)


def all_modes(trace: bool = False):
    plant, ctrl = _new()
    law = ctrl.law
    iso = (70.0 - law.mp.isokinetic_cadence_min_rpm) / (law.mp.isokinetic_cadence_max_rpm
                                                        - law.mp.isokinetic_cadence_min_rpm)
    dt = ctrl.batch_periods * plant.params.control_period_s
    n_seg = int(round(4.0 / dt))
    err, t_err, rows = [], [], []
    for k in range(5 * n_seg):
        seg, i = divmod(k, n_seg)
        if seg == 0:
            ctrl.set_command(0.2 + 0.2 * i / n_seg, MODE_RESISTANCE)
        elif i == 0:
            cmd = [None, (180.0 / law.erg_power_max_w, MODE_ERG), (_grade_cmd(law, 0.04), MODE_SLOPE),
                   (iso, MODE_ISOKINETIC), (_grade_cmd(law, -0.05), MODE_SLOPE)][seg]
            ctrl.set_command(*cmd)
            plant.set_rider_cadence(70.0 if seg == 3 else 0.0)
        res = _batch(plant, ctrl)
        if seg in (2, 4):
            err.append(plant.state[M.S_OMEGA] * law.mps_per_rad_s - ctrl.last_out.virtual_speed_mps)
            t_err.append(plant.time_s)
        if seg == 4 and i * dt < 1.0 and trace and i % 10 == 0:
            est_mps = ctrl.inner.status()["speed_est_rpm"] / RPM_PER_RAD_S * law.mps_per_rad_s
            rows.append((plant.time_s, "inv rect drain".split()[int(plant.state[M.S_RELAY])],
                         plant.state[M.S_OMEGA] * law.mps_per_rad_s, est_mps, ctrl.last_out.virtual_speed_mps,
                         res.load_torque_nm, ctrl.last_out.brake_torque_nm, -res.torque_em_nm, ctrl.trim.trim_nm,
                         law.integral_nm, bool(ctrl.last_out.saturated)))
    w = int(round(0.1 / dt))
    e = np.array(err).reshape(-1, w).mean(axis=1)
    te = np.array(t_err).reshape(-1, w)[:, -1]
    worst = np.argsort(-np.abs(e))[:3]
    print(f"all_modes slope: {math.sqrt(np.mean(e ** 2)):.3f} m/s rms over {e.size} windows of 0.1 s "
          f"(climb {math.sqrt(np.mean(e[:40] ** 2)):.3f}, descent {math.sqrt(np.mean(e[40:] ** 2)):.3f}); worst "
          + ", ".join(f"{e[j]:+.2f} m/s ({te[j] - 0.1:.1f}-{te[j]:.1f} s)" for j in worst)
          + f"; without the worst {math.sqrt(np.mean(np.delete(e, worst[0]) ** 2)):.3f}")
    if rows:
        print("  t [s]  relay  flywheel / estimate / virtual bike [m/s]  rider / asked / braked [N m]  trim / integral "
              "[N m]  flagged")
    for r in rows:
        print("  %5.2f  %-5s  %5.2f / %5.2f / %5.2f  %+5.2f / %+5.2f / %+5.2f  %+5.2f / %+5.2f  %d" % r)


def descent(grade: float) -> float:
    plant, ctrl = _new()
    law = ctrl.law
    ctrl.set_command(180.0 / law.erg_power_max_w, MODE_ERG)
    err = []
    for k in range(14000):
        if k == 4000:
            ctrl.set_command(_grade_cmd(law, grade), MODE_SLOPE)
        _batch(plant, ctrl)
        if k >= 7000:
            err.append(plant.state[M.S_OMEGA] * law.mps_per_rad_s - ctrl.last_out.virtual_speed_mps)
    return math.sqrt(np.mean(np.square(err)))


if __name__ == "__main__":
    what = sys.argv[1] if len(sys.argv) > 1 else "all_modes"
    if what in ("all_modes", "trace"):
        all_modes(trace=what == "trace")
    if what == "descents":
        print("descents: " + ", ".join(f"{g:+.0%} {descent(g):.3f}" for g in (-0.04, -0.05, -0.06, -0.08)) + " m/s rms")
