"""Plant + controller without ROS: the lockstep loop of the nodes, in one process.

Same objects as the nodes (bike_plant.sim.BldcPlant, BatchController), same batch
exchange (snapshot -> decide -> step_batch), so offline results (paper figures,
benchmark, tests) are what a lockstep ROS run records.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from bike_plant import params as P
from bike_plant.sim import BldcPlant

from .bldc_control import BatchController

RECORD_KEYS = ("time_s", "speed_rpm", "torque_em_nm", "load_torque_nm", "ia_a", "ib_a", "ic_a", "i_fb_a",
               "dc_bus_v", "soc", "brake_on", "battery_current_a", "speed_est_rpm", "torque_cmd_nm",
               "current_cmd_a", "k_factor", "prediction_error_a", "energy_mech_in_j", "energy_battery_j",
               "energy_resistor_j", "energy_loss_j", "energy_stored_j", "residual_j")


def run_offline(cfg: dict, duration_s: float, command_fn: Callable[[float], tuple] | None = None,
                batch_periods: int | None = None, record_every: int = 1, *,
                plant_params: P.PlantParams | None = None, nominal_params: P.PlantParams | None = None,
                current_override_a: float | None = None, record_samples: bool = False,
                plant: BldcPlant | None = None, controller: BatchController | None = None) -> dict:
    """Run `duration_s` of simulated time. command_fn(t) -> (command, mode) is read at every
    batch start (None: the controller's command0/mode0). Records one row every
    `record_every` batches (batch means for torques, batch-end values otherwise).

    Returns a dict of numpy arrays (keys RECORD_KEYS), plus 'samples_a' (periods x 3 phase
    currents, if record_samples), 'ledger' (final), 'plant', 'controller'.
    """
    if not (duration_s > 0 and math.isfinite(duration_s)):
        raise ValueError(f"duration_s must be > 0, got {duration_s!r}")
    plant_params = plant_params or P.plant_params_from_config(cfg)
    plant = plant or BldcPlant(plant_params)
    ctrl = controller or BatchController(cfg, nominal_params, batch_periods)
    if current_override_a is not None:
        ctrl.set_current_override(current_override_a)
    n = ctrl.batch_periods
    dt = plant.params.control_period_s
    n_batches = int(math.ceil(duration_s / (n * dt) - 1e-9))
    n_rec = n_batches // max(record_every, 1) + 1
    rec = {k: np.zeros(n_rec) for k in RECORD_KEYS}
    samples = np.zeros((n_batches * n, 3)) if record_samples else None
    last_cmd = None
    instructed = False
    r = 0
    for b in range(n_batches):
        snap = plant.snapshot()
        if command_fn is not None:
            cmd = tuple(command_fn(plant.time_s))
            if cmd != last_cmd:
                ctrl.set_command(*cmd)
                last_cmd = cmd
        ga, gb, sp, status = ctrl.decide(snap)
        law = getattr(ctrl, "law", None)         # a moded controller (a bare BatchController has no modes)
        rider = law.rider_instruction() if law is not None else None
        if rider is not None or instructed:
            # a spin-down tells the rider what to do, as the controller node does through DriveCommand
            plant.set_rider_cadence(*(rider or (0.0, False)))
            instructed = rider is not None
        res = plant.step_batch(ga, gb, sp)
        if samples is not None:
            samples[b * n:(b + 1) * n] = res.current_samples_a
        if b % record_every == 0 and r < n_rec:
            s = plant.state
            led = plant.ledger()
            cur = s[0:3]
            row = {
                "time_s": plant.time_s, "speed_rpm": s[4] * P.RPM_PER_RAD_S, "torque_em_nm": res.torque_em_nm,
                "load_torque_nm": res.load_torque_nm, "ia_a": cur[0], "ib_a": cur[1], "ic_a": cur[2],
                "i_fb_a": 0.5 * float(np.abs(res.current_samples_a).sum(axis=1).mean()),
                "dc_bus_v": s[5], "soc": s[6], "brake_on": s[7], "battery_current_a": res.battery_current_a,
                "speed_est_rpm": status["speed_est_rpm"], "torque_cmd_nm": status["torque_cmd_nm"],
                "current_cmd_a": status["current_cmd_a"], "k_factor": status["k_factor"],
                "prediction_error_a": status["prediction_error_a"],
                "energy_mech_in_j": led["energy_mech_in_j"], "energy_battery_j": led["energy_battery_j"],
                "energy_resistor_j": led["energy_resistor_j"], "energy_loss_j": led["energy_loss_j"],
                "energy_stored_j": led["energy_stored_j"], "residual_j": led["residual_j"],
            }
            for k, v in row.items():
                rec[k][r] = v
            r += 1
    out = {k: v[:r] for k, v in rec.items()}
    if samples is not None:
        out["samples_a"] = samples
    out["ledger"] = plant.ledger()
    out["plant"] = plant
    out["controller"] = ctrl
    return out


def steady_mean(values: np.ndarray, time_s: np.ndarray, t_from: float) -> float:
    """Mean of a recorded series after t_from (settled part of a run)."""
    sel = time_s >= t_from
    return float(np.mean(values[sel])) if np.any(sel) else float("nan")


def compare_batch_sizes(cfg: dict, duration_s: float = 0.05, batch_sizes=(1, 20), *,
                        plant_params: P.PlantParams | None = None, nominal_params: P.PlantParams | None = None,
                        command: float = 1.0, mode: int = 0, current_override_a: float | None = None) -> dict:
    """Run the same session with several batch sizes N and report how far they drift apart.

    With a matched model (nominal == plant) the batched loop equals the per-period loop
    (differences ~0); with a mismatched plant (e.g. position-dependent inductance or a
    different resistance) the controller's open-loop prediction inside a batch is wrong and
    the difference grows with N. Returned (not hidden): per N the mean/max prediction error
    at batch starts, the mean current and torque, and the max differences to the first N.
    """
    runs = {}
    for n in batch_sizes:
        out = run_offline(cfg, duration_s, lambda t: (command, mode), batch_periods=n,
                          plant_params=plant_params, nominal_params=nominal_params,
                          current_override_a=current_override_a, record_samples=True)
        s = out["samples_a"]
        runs[n] = {
            "samples_a": s,
            "torque_em_nm": float(np.mean(out["torque_em_nm"])),
            "current_fb_mean_a": float(0.5 * np.abs(s).sum(axis=1).mean()),
            "prediction_error_mean_a": float(np.mean(out["prediction_error_a"])),
            "prediction_error_max_a": float(np.max(out["prediction_error_a"])),
        }
    ref = runs[batch_sizes[0]]
    report = {"batch_sizes": list(batch_sizes), "per_n": {}}
    for n, r in runs.items():
        m = min(len(r["samples_a"]), len(ref["samples_a"]))
        report["per_n"][n] = {
            "torque_em_nm": r["torque_em_nm"],
            "current_fb_mean_a": r["current_fb_mean_a"],
            "prediction_error_mean_a": r["prediction_error_mean_a"],
            "prediction_error_max_a": r["prediction_error_max_a"],
            "max_current_diff_a": float(np.max(np.abs(r["samples_a"][:m] - ref["samples_a"][:m]))),
            "torque_diff_nm": r["torque_em_nm"] - ref["torque_em_nm"],
        }
    return report
