"""Batched inner loop (ARCHITECTURE.md): N = 1 == N = 20 with a matched model; a mismatched
plant is measured and reported; the energy ledger closes over a 10 s session."""
from __future__ import annotations

import copy
import dataclasses
import pathlib

import numpy as np
import pytest

from bike_controller.bldc_control import BatchController
from bike_controller.closed_loop import compare_batch_sizes, run_offline
from bike_plant import bldc as K
from bike_plant import params as P
from bike_plant.config import load_config
from bike_plant.sim import BldcPlant

ROOT = pathlib.Path(__file__).resolve().parents[1]
CFG_PATH = ROOT / "config" / "bldc_default.yaml"


@pytest.fixture(scope="module")
def cfg():
    """The default bike with the paper's load: a prime mover (the demo rides a rider model)."""
    c = load_config(CFG_PATH)
    c["load"] = dict(c["load"], kind="prime_mover")
    return c


@pytest.mark.parametrize("speed_rpm,command,mode", [(3000.0, 1.0, 0), (4800.0, 0.6, 0), (1500.0, 0.4, 1)])
def test_matched_model_n1_equals_n20(cfg, speed_rpm, command, mode):
    c = copy.deepcopy(cfg)
    c["load"] = dict(c["load"], kind="prime_mover", speed_rpm=speed_rpm)
    rep = compare_batch_sizes(c, 0.04, (1, 20), command=command, mode=mode)
    r20 = rep["per_n"][20]
    assert r20["max_current_diff_a"] <= 1e-9
    assert abs(r20["torque_diff_nm"]) <= 1e-9
    assert r20["prediction_error_max_a"] <= 1e-9


@pytest.mark.parametrize("change", [{"inductance_variation": 0.2}, {"r_phase_ohm": 0.006 * 1.3}])
def test_mismatched_plant_difference_is_reported(cfg, change):
    cfg = dict(cfg, load=dict(cfg["load"], kind="prime_mover"))
    nominal = P.plant_params_from_config(cfg)
    actual = P.plant_params_from_config(cfg)
    actual.bldc = dataclasses.replace(actual.bldc, **change)
    rep = compare_batch_sizes(cfg, 0.04, (1, 5, 20), plant_params=actual, nominal_params=nominal)
    per = rep["per_n"]
    assert per[20]["max_current_diff_a"] > 0.1
    assert per[20]["prediction_error_mean_a"] > per[5]["prediction_error_mean_a"] > per[1]["prediction_error_mean_a"] > 0
    # the loop still regulates: the mean braking torque moves by a few percent at most
    assert abs(per[20]["torque_diff_nm"]) < 0.05 * abs(per[1]["torque_em_nm"])


def test_controller_output_never_shorts_a_leg(cfg):
    plant = BldcPlant(P.plant_params_from_config(cfg))
    ctrl = BatchController(cfg)
    for k in range(200):
        ctrl.set_command(float(k % 11) / 10.0, k // 100)
        ga, gb, sp, _ = ctrl.decide(plant.snapshot())
        for g in np.concatenate([ga, gb]):
            assert K.blank_interlock(int(g))[1] == 0
        assert np.all((sp >= 0) & (sp <= 1))
        # DriveCommand carries split as float32: the controller predicted with exactly that
        assert np.array_equal(sp, sp.astype(np.float32).astype(np.float64))
        plant.step_batch(ga, gb, sp)
    assert plant.snapshot()["interlock_blanked_count"] == 0


def test_energy_ledger_closes_over_10s_session(cfg):
    c = copy.deepcopy(cfg)
    c["load"] = dict(c["load"], schedule_time_s=[0.0, 3.0, 6.0], schedule_speed_rpm=[2000.0, 4500.0, 3000.0])

    def profile(t):
        return (0.3 + 0.7 * (int(t) % 2), 0) if t < 8.0 else (0.5, 1)

    out = run_offline(c, 10.0, profile, record_every=100)
    led = out["ledger"]
    assert out["time_s"][-1] == pytest.approx(10.0, abs=0.1)
    scale = abs(led["energy_mech_in_j"]) + abs(led["energy_battery_j"])
    assert scale > 1000.0                      # ~1 kJ regenerated: a real session
    assert abs(led["residual_j"]) < 0.01 * scale
    assert abs(led["residual_j"]) < 1e-6 * scale      # what the kernel actually achieves
    assert led["energy_battery_j"] > 0.0


def test_rider_load_speed_held_prediction_is_measured_and_small(cfg):
    """With a rider the predictor holds the speed inside a batch: the difference to N = 1 is
    reported (prediction error > 0) and stays far below the current ripple."""
    c = dict(cfg, load=dict(cfg["load"], kind="rider"), mechanics=dict(cfg["mechanics"], speed0_rpm=2500.0))
    per = compare_batch_sizes(c, 0.1, (1, 20), command=0.5, mode=0)["per_n"]
    assert per[1]["prediction_error_max_a"] == 0.0
    assert 0.0 < per[20]["prediction_error_max_a"] < 0.1
    assert abs(per[20]["torque_diff_nm"]) < 0.01 * abs(per[1]["torque_em_nm"])
