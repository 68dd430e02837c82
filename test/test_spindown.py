"""Spin-down calibration (bike_controller.spindown, mode 5): the fit, the procedure's phases and
failures, and the bike learning its own friction in closed loop with the plant (no ROS)."""
import copy
import math
import pathlib

import numpy as np
import pytest

from bike_controller.modes import MODE_ERG, MODE_SPINDOWN
from bike_controller.spindown import COAST, DONE, FAILED, SPIN_UP, SpinDown, SpinDownParams, fit_coast

ROOT = pathlib.Path(__file__).resolve().parents[1]
RPM_PER_RAD_S = 60.0 / (2.0 * math.pi)


def coast(b_nms, tc_nm, j=0.01, w0=36.0, seconds=0.6, dt=1e-4, tem=lambda t: 0.0):
    """J dw/dt = T_em - B w - Tc, fine Euler steps, sampled every 1 ms."""
    t, w, ts, ws, tems = 0.0, w0, [], [], []
    k = 0
    while t < seconds:
        if k % 10 == 0:
            ts.append(t), ws.append(w), tems.append(tem(t))
        w += dt * (tem(t) - b_nms * w - tc_nm) / j
        t += dt
        k += 1
    return np.array(ts), np.array(ws), np.array(tems)


def test_the_fit_finds_viscous_and_coulomb_friction_through_noise_and_em_torque():
    t, w, tem = coast(0.005, 0.1, tem=lambda t: -0.2 if t < 0.1 else 0.0)     # diodes braking at first
    noisy = w + np.random.default_rng(1).normal(0.0, 0.05, w.size)
    r = fit_coast(t, noisy, tem, 0.01)
    assert r.friction_nms == pytest.approx(0.005, rel=0.02) and r.dry_friction_nm == pytest.approx(0.1, rel=0.02)
    assert r.samples == t.size and r.coast_s == pytest.approx(t[-1])
    # leaving the EM torque out of the fit would blame it on the friction
    wrong = fit_coast(t, noisy, np.zeros_like(tem), 0.01)
    assert abs(wrong.dry_friction_nm - 0.1) > 0.01 or abs(wrong.friction_nms - 0.005) > 1e-4


def test_a_bike_without_coulomb_friction_gets_none_not_a_negative_one():
    """The BLDC bike's flywheel: B only, a 20 s coast 311 -> 254 rad/s. With this noise the
    free fit's Tc comes out negative; it is refitted as 0 (a friction never pushes). Over the
    coast's narrow speed range B and Tc trade off; the loss they give there is exact."""
    t, w, tem = coast(1e-4, 0.0, w0=311.0, seconds=20.0)
    noisy = w + np.random.default_rng(3).normal(0.0, 0.5, w.size)
    r = fit_coast(t, noisy, tem, 0.01)
    assert r.dry_friction_nm == 0.0 and r.friction_nms == pytest.approx(1e-4, rel=0.01)
    for seed in range(3):
        r = fit_coast(t, w + np.random.default_rng(seed).normal(0.0, 0.5, w.size), tem, 0.01)
        assert r.dry_friction_nm >= 0.0 and r.friction_nms == pytest.approx(1e-4, rel=0.03)
        assert r.friction_nms * 280.0 ** 2 + r.dry_friction_nm * 280.0 == pytest.approx(1e-4 * 280.0 ** 2, rel=1e-3)
    with pytest.raises(ValueError, match="too short"):
        fit_coast(t[:5], w[:5], tem[:5], 0.01)
    with pytest.raises(ValueError, match="did not slow down"):
        fit_coast(t, np.full_like(t, 300.0) + 0.01 * t, tem, 0.01)


def test_the_procedure_spins_up_coasts_and_fails_with_a_reason():
    gear = 35.0
    rad = lambda cadence: cadence * gear / RPM_PER_RAD_S  # noqa: E731
    sd = SpinDown(SpinDownParams(high_cadence_rpm=85.0, low_cadence_rpm=60.0, spin_up_timeout_s=2.0), 0.01, gear)
    sd.start()
    assert sd.rider_instruction() == (90.0, False)
    # a pedal stroke's peak above the mark is no spin-up: it must hold 0.5 s, brake released
    assert sd.step(rad(88.0), 0.1) == SPIN_UP and sd.step(rad(80.0), 0.1) == SPIN_UP
    for _ in range(6):
        sd.step(rad(88.0), 0.1, released=False)
    assert sd.phase == SPIN_UP
    for _ in range(5):
        sd.step(rad(88.0), 0.1)
    assert sd.phase == COAST and sd.rider_instruction() == (0.0, True)
    # the rider pedalled during the coast
    sd.step(rad(84.0), 0.1)
    assert sd.step(rad(86.0), 0.1) == FAILED and "pedalled" in sd.reason and sd.rider_instruction() == (0.0, False)
    # never reaching the mark
    sd.start()
    for _ in range(25):
        sd.step(rad(80.0), 0.1)
    assert sd.phase == FAILED and "did not reach 85 rpm" in sd.reason
    sd.start()
    sd.abandon("the Command changed")
    assert sd.phase == FAILED and sd.reason.startswith("spin up: the Command changed")
    with pytest.raises(ValueError, match="below"):
        SpinDownParams(high_cadence_rpm=60.0, low_cadence_rpm=60.0)


def _bldc(modes: dict):
    from bike_controller.session_control import ModedController
    from bike_plant.config import load_config
    cfg = copy.deepcopy(load_config(ROOT / "config" / "bldc_default.yaml"))
    cfg["modes"] = dict(cfg.get("modes") or {}, **modes)
    return cfg, ModedController(cfg)


def test_the_bldc_bike_learns_its_friction_and_erg_then_holds_the_riders_power(caplog):
    """The controller's friction figure is half the flywheel's (modes.friction_nms 5e-5 against
    1e-4): ERG lets the rider give 4 W more than 200 W. A spin-down (the plant's rider spins up,
    stops pedalling, the flywheel coasts 85 -> 70 rpm) finds B within 1 %; ERG then holds 200 W.
    The statuses carry the laws' friction before and after."""
    from bike_controller.closed_loop import run_offline
    cfg, ctrl = _bldc({"friction_nms": 5e-5, "spindown_low_cadence_rpm": 70.0})
    pmax = ctrl.law.erg_power_max_w

    def rider_w(r, t0, t1):
        t, e = r["time_s"], r["energy_mech_in_j"]
        i0, i1 = np.searchsorted(t, t0), np.searchsorted(t, t1) - 1
        return (e[i1] - e[i0]) / (t[i1] - t[i0])

    before = run_offline(cfg, 6.0, lambda t: (200.0 / pmax, MODE_ERG), controller=ctrl)
    assert rider_w(before, 3.0, 6.0) == pytest.approx(204.3, abs=1.0)
    assert ctrl.status()["friction_nms"] == 5e-5
    with caplog.at_level("WARNING", logger="bike_controller.modes"):
        run_offline(cfg, 40.0, lambda t: (0.0, MODE_SPINDOWN), plant=before["plant"], controller=ctrl)
    sd = ctrl.law.spindown
    assert sd.phase == DONE, sd.reason
    assert ctrl.law.friction_nms == pytest.approx(1e-4, rel=0.01) and ctrl.law.dry_friction_nm < 1e-3
    assert ctrl.status()["friction_nms"] == ctrl.law.friction_nms
    assert any("spin-down done" in r.message for r in caplog.records)
    assert ctrl.law.rider_instruction() is None, "the rider pedals on his own again"
    after = run_offline(cfg, 8.0, lambda t: (200.0 / pmax, MODE_ERG), plant=before["plant"], controller=ctrl)
    t0 = after["time_s"][0]
    assert rider_w(after, t0 + 2.0, t0 + 8.0) == pytest.approx(200.0, abs=1.0)


@pytest.mark.parametrize("ride_first_s", [0.0, 2.0])
def test_the_spmsm_bike_learns_viscous_and_coulomb_friction(ride_first_s):
    """The SPMSM bike (J 0.01, B 0.005, Tc 0.1) coasts 85 -> 60 rpm in under half a second; a
    controller told B 0.0025 and no Coulomb friction learns both within 1 %, also after a ride
    in the resistance mode (the rider then overshoots less, to ~92 rpm, and the coast begins
    0.1 s after he stops: fitted on the speed observer, which lags his stopping, that gave
    B 0.0074 and Tc 0.031; the fit takes the encoder's M/T speed)."""
    from bike_controller.modes import MODE_RESISTANCE
    from bike_controller.spmsm_session import ModedSpmsmController
    from bike_plant import spmsm as M
    from bike_plant.config import load_config
    cfg = copy.deepcopy(load_config(ROOT / "config" / "spmsm_default.yaml"))
    cfg["modes"] = dict(cfg.get("modes") or {}, friction_nms=0.0025, dry_friction_nm=0.0)
    plant = M.SpmsmPlant(M.plant_params_from_config(cfg))
    ctrl = ModedSpmsmController(cfg)
    ride = round(ride_first_s / (ctrl.batch_periods * 1e-4))
    ctrl.set_command(0.1, MODE_RESISTANCE)
    for k in range(ride + 6000):
        if k == ride:
            ctrl.set_command(0.0, MODE_SPINDOWN)
        snap = plant.snapshot()
        snap.update(batch_periods=ctrl.batch_periods)
        duties, relay, buck, status = ctrl.decide(snap)
        plant.set_rider_cadence(*(ctrl.law.rider_instruction() or (0.0, False)))
        plant.step_batch(duties, relay, buck)
        if k >= ride and ctrl.law.spindown.phase in (DONE, FAILED):
            break
    assert ctrl.law.spindown.phase == DONE, ctrl.law.spindown.reason
    assert ctrl.law.friction_nms == pytest.approx(0.005, rel=0.01)
    assert ctrl.law.dry_friction_nm == pytest.approx(0.1, rel=0.01)


def test_the_encoder_speed_is_the_mean_between_edges_dated_at_their_middle():
    from bike_controller.spindown import EncoderSpeed
    enc = EncoderSpeed(10000, 1.0e6)
    assert enc.sample(100, 5000) is None                    # the first edge: a reference only
    t, w = enc.sample(150, 6000)                            # 50 counts in 1 ms
    assert t == pytest.approx(5.5e-3) and w == pytest.approx(50 * 2 * math.pi / 10000 / 1e-3)
    assert enc.sample(150, 6000) is None and enc.ref == (150, 6000)   # no new edge: the old one kept
    t, w = enc.sample(140, 8000)                            # backwards
    assert t == pytest.approx(7.0e-3) and w == pytest.approx(-10 * 2 * math.pi / 10000 / 2e-3)


def test_a_new_command_value_in_the_spindown_mode_starts_another_once_the_last_is_over():
    """An app's retry: the spindown Command's value tags the request. The same value again (a
    profile's Commands every period) starts nothing; a new one does, once the last is over."""
    from bike_controller.modes import ModeLaw, ModeParams
    law = ModeLaw(ModeParams(spindown_spin_up_timeout_s=0.05), gear_ratio=35.0, inertia_kgm2=0.01, tmax_nm=2.94,
                  pmax_w=1016.68, base_speed_rpm=3300.0, friction_nms=1e-4)
    rpm = 80.0 * 35.0
    law.step(1.0, MODE_SPINDOWN, rpm, 1e-3)
    assert law.spindown.phase == SPIN_UP
    law.step(1.0, MODE_SPINDOWN, rpm, 0.1)
    assert law.spindown.phase == FAILED and "did not reach" in law.spindown.reason
    law.step(1.0, MODE_SPINDOWN, rpm, 1e-3)
    assert law.spindown.phase == FAILED, "the same request again starts nothing"
    law.step(0.0, MODE_SPINDOWN, rpm, 1e-3)
    assert law.spindown.phase == SPIN_UP, "a new request (a retry) starts another"
    law.step(1.0, MODE_SPINDOWN, rpm, 1e-3)
    assert law.spindown.phase == SPIN_UP, "one running is not restarted"
    law.step(0.3, MODE_ERG, rpm, 1e-3)
    assert law.spindown.phase == FAILED and "changed to erg" in law.spindown.reason


def test_a_bldc_spindown_through_host_stalls_finds_the_same_friction():
    """Realtime: a controller descheduled for 40 ms every 0.15 s skips those plant states. The
    BLDC bike's coast is dated by the spin-down's clock (no speed sensor of its own), which
    stepped the batch's time only: each stall shortened the time axis by 40 ms, and the coast's
    deceleration came out steeper, B 1.36e-4 for the flywheel's 1e-4 (+36 %; 1.15e-4 with a
    stall every 0.3 s). Its clock counts the skipped time now (session_control.skipped_time_s)."""
    from bike_plant.params import plant_params_from_config
    from bike_plant.sim import BldcPlant
    cfg, ctrl = _bldc({"friction_nms": 5e-5, "spindown_low_cadence_rpm": 70.0})
    plant = BldcPlant(plant_params_from_config(cfg))
    ctrl.set_command(0.2, MODE_ERG)
    stalled_until = -1
    for k in range(45000):
        if k == 3000:
            ctrl.set_command(0.0, MODE_SPINDOWN)
        if k > 3000 and k % 150 == 0:
            stalled_until = k + 40                   # the plant runs on with the held DriveCommand
        if k >= stalled_until:
            answer = ctrl.decide(plant.snapshot())[:3]
            plant.set_rider_cadence(*(ctrl.law.rider_instruction() or (0.0, False)))
            if k > 3000 and not ctrl.law.spindown.running:
                break
        plant.step_batch(*answer)
    sd = ctrl.law.spindown
    assert sd.phase == DONE, sd.reason
    assert ctrl.skipped_state_gaps > 100 and ctrl.skipped_periods == 40 * 20 * ctrl.skipped_state_gaps
    assert ctrl.law.friction_nms == pytest.approx(1e-4, rel=0.01)
