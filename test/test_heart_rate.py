"""The rider's heart (bike_plant.heart) and the heart-rate ERG (bike_controller.heart_erg, the
ERG law with a Command's heart-rate target), without ROS."""
import math
import re

import numpy as np
import pytest

from bike_plant.heart import (HeartParams, HeartRate, RiderHeart, heart_rate_command_problem,
                              heart_rate_reading_problem, heart_rate_target_problem)

H = HeartParams(drift_fraction=0.0)       # rest 60, max 185, 0.5 bpm/W, tau 68.7 s, no drift


def test_the_heart_follows_the_first_order_solution_for_any_batch_length():
    """tau dx/dt = K P - x from rest: x(t) = K P (1 - exp(-t / tau)); one 10 s step and 1000
    steps of 10 ms give the same rate (exact for a held power)."""
    one, many = HeartRate(H), HeartRate(H)
    one.step(150.0, 10.0)
    for _ in range(1000):
        many.step(150.0, 0.01)
    exact = 60.0 + 0.5 * 150.0 * (1.0 - math.exp(-10.0 / 68.7))
    assert one.bpm == pytest.approx(exact, abs=1e-9)
    assert many.bpm == pytest.approx(exact, abs=1e-9)
    for _ in range(100):                     # 100 tau: the steady state
        one.step(150.0, 68.7)
    assert one.bpm == pytest.approx(H.steady_bpm(150.0)) and H.steady_bpm(150.0) == pytest.approx(135.0)


def test_the_heart_stays_between_rest_and_max_and_answers_the_mean_of_a_swinging_power():
    h = HeartRate(H)
    h.step(2000.0, 3600.0)
    assert h.bpm == pytest.approx(185.0)
    h.step(-500.0, 3600.0)                   # a motor turns his legs: back to rest, not below
    assert h.bpm == pytest.approx(60.0)
    # the pedal stroke: the batch's power swings from -50 to +550 W around 250 W. The limits act
    # on the state, so the heart answers the mean (limits on the input gave ~165 bpm here)
    swing, steady = HeartRate(H), HeartRate(H)
    for k in range(200_000):
        swing.step(250.0 + 300.0 * math.sin(2.0 * math.pi * k / 60.0), 0.005)
        steady.step(250.0, 0.005)
    assert swing.bpm == pytest.approx(steady.bpm, abs=0.5) and steady.bpm > 184.0


def test_the_rider_heart_takes_the_ledgers_energy():
    r = RiderHeart(H)
    for k in range(1, 601):
        r.advance(200.0 * k * 0.5, k * 0.5)  # 200 W for 300 s in 0.5 s batches
    assert r.bpm == pytest.approx(60.0 + 100.0 * (1.0 - math.exp(-300.0 / 68.7)), abs=1e-6)
    assert r.advance(r.energy_j, r.time_s) == r.bpm      # no time passed: unchanged


def _integrated(params: HeartParams, power_w, seconds: float, dt_s: float = 0.01):
    """Both equations of bike_plant.heart by RK4 with the power a function of time (a check
    of the exact step that shares none of its algebra)."""
    p = params

    def f(t, y):
        x, d = y
        return np.array([(p.gain_bpm_per_w * power_w(t) - x) / p.time_constant_s,
                         (p.drift_fraction * x - d) / p.drift_time_constant_s])
    y, t = np.zeros(2), 0.0
    for _ in range(int(round(seconds / dt_s))):
        k1 = f(t, y)
        k2 = f(t + dt_s / 2, y + dt_s / 2 * k1)
        k3 = f(t + dt_s / 2, y + dt_s / 2 * k2)
        k4 = f(t + dt_s, y + dt_s * k3)
        y, t = y + dt_s / 6 * (k1 + 2 * k2 + 2 * k3 + k4), t + dt_s
    return p.rest_bpm + y[0] + y[1], y[1]


def test_the_drift_is_the_exact_solution_of_the_slow_equation_for_any_batch_length():
    """tau_d dd/dt = g x - d on top of the first order: one 600 s step, 60000 steps of 10 ms and
    an RK4 integration of both equations agree, at a held power and across a step of it."""
    D = HeartParams()                                   # the defaults: g 0.25, tau_d 1800 s
    one, many = HeartRate(D), HeartRate(D)
    one.step(170.0, 600.0)
    for _ in range(60_000):
        many.step(170.0, 0.01)
    bpm, drift = _integrated(D, lambda t: 170.0, 600.0, dt_s=0.05)
    assert one.bpm == pytest.approx(bpm, abs=1e-6) and many.bpm == pytest.approx(bpm, abs=1e-6)
    assert one.drift_bpm == pytest.approx(drift, abs=1e-6) and drift > 3.0
    # a step down to 100 W at 600 s, in 1 s batches: both parts follow it
    for _ in range(600):
        one.step(100.0, 1.0)
    bpm, drift = _integrated(D, lambda t: 170.0 if t < 600.0 - 1e-9 else 100.0, 1200.0, dt_s=0.05)
    assert one.bpm == pytest.approx(bpm, abs=1e-4) and one.drift_bpm == pytest.approx(drift, abs=1e-4)


def test_the_drift_matches_the_measured_rise_from_minute_10_to_30():
    """At a constant power the heart keeps rising after the first minutes: measured +8 +- 4 bpm
    from minute 10 to 30 at ~150 bpm (bike_plant.heart). The recreational rider at 170 W (x = 85
    bpm) rises 7.7 bpm, the trained preset's heart (half the drift fraction) 3.7; without drift
    it is flat. After the ride the drift unwinds."""
    from bike_plant.params import RIDER_PRESETS

    def rise(drift_fraction):
        h = HeartRate(HeartParams(drift_fraction=drift_fraction))
        h.step(170.0, 600.0)
        at_10 = h.bpm
        h.step(170.0, 1200.0)
        return h.bpm - at_10, h
    recreational, h = rise(RIDER_PRESETS["recreational"]["rider_hr_drift_fraction"])
    trained, _ = rise(RIDER_PRESETS["trained"]["rider_hr_drift_fraction"])
    assert recreational == pytest.approx(7.7, abs=0.1) and 4.0 <= recreational <= 12.0
    assert trained == pytest.approx(3.7, abs=0.1)
    assert rise(0.0)[0] == pytest.approx(0.0, abs=0.02)        # the first order's tail only
    h.step(0.0, 3.0 * 1800.0)                            # three drift time constants of rest
    assert h.drift_bpm < 0.05 * 0.25 * 85.0 and h.bpm < 62.0


@pytest.mark.parametrize("kwargs, words", [
    ({"drift_fraction": -0.1}, "drift_fraction must be a number in [0, 1] (0: no drift)"),
    ({"drift_fraction": 1.5}, "drift_fraction must be a number in [0, 1] (0: no drift)"),
    ({"drift_time_constant_s": 60.0}, "drift_time_constant_s (60) must be above time_constant_s (68.7)"),
    ({"rest_bpm": 190.0}, "rest_bpm (190) must be below max_bpm"),
    ({"gain_bpm_per_w": 0.0}, "gain_bpm_per_w must be a number > 0"),
    ({"time_constant_s": float("nan")}, "time_constant_s must be a number > 0"),
])
def test_a_bad_heart_is_one_error(kwargs, words):
    with pytest.raises(ValueError, match=re.escape(words)):
        HeartRate(HeartParams(**kwargs))


def test_a_bad_heart_in_the_config_is_one_error_naming_the_keys(tmp_path):
    from bike_plant.config import ConfigError, load_config
    from bike_plant.params import plant_params_from_config

    cfg = load_config("config/bldc_default.yaml")
    cfg["load"] = dict(cfg["load"], rider_preset="custom", rider_max_hr_bpm=50.0)
    with pytest.raises((ConfigError, ValueError), match="rider_max_hr_bpm"):
        plant_params_from_config(cfg)


def test_heart_rate_targets_and_commands():
    assert heart_rate_target_problem(0) is None and heart_rate_target_problem(140.0) is None
    for bad in (39.0, 221.0, float("nan"), float("inf"), True, "140"):
        assert heart_rate_target_problem(bad), bad
    assert heart_rate_command_problem(140.0, 2) is None
    assert "ERG (mode 2) only" in heart_rate_command_problem(140.0, 3)
    assert heart_rate_command_problem(0.0, 3) is None
    # a strap's reading (the CAN plant node drops a bad one with a warning)
    assert heart_rate_reading_problem(0.0) is None and heart_rate_reading_problem(142.0) is None
    for bad in (-1.0, 251.0, float("nan"), float("inf")):
        assert "is not a reading" in heart_rate_reading_problem(bad), bad


def test_a_command_with_a_heart_rate_target_outside_erg_is_rejected_whole():
    from bike_msgs.msg import Command

    from bike_plant import msgconv
    from bike_plant.config import load_config
    from bike_controller.session_control import ModedController

    msg = msgconv.command_msg(0.2, Command.MODE_SLOPE)
    msg.heart_rate_bpm = 140.0
    assert "ERG (mode 2) only" in msgconv.command_problem(msg)
    msg.mode, msg.heart_rate_bpm = Command.MODE_ERG, 250.0
    assert "outside [40, 220]" in msgconv.command_problem(msg)
    ctrl = ModedController(load_config("config/bldc_default.yaml"), batch_periods=200)
    ctrl.set_command(0.1, Command.MODE_ERG)
    with pytest.raises(ValueError, match="ERG"):
        ctrl.set_command(0.3, Command.MODE_SLOPE, 0.0, None, 140.0)
    assert (ctrl.command, ctrl.mode, ctrl.law.heart_rate_target_bpm) == (0.1, Command.MODE_ERG, 0.0)


# ------------------------------------------------------------------ the heart-rate ERG
def _closed_loop(erg, heart, target_bpm, seconds, dt_s=1.0):
    """The PI against the model heart alone: (times, rates, powers)."""
    ts, hrs, ps = [], [], []
    for k in range(int(seconds / dt_s)):
        p = erg.step(target_bpm, heart.bpm, dt_s)
        heart.step(p, dt_s)
        ts.append((k + 1) * dt_s)
        hrs.append(heart.bpm)
        ps.append(p)
    return np.array(ts), np.array(hrs), np.array(ps)


def test_the_heart_rate_erg_is_the_internal_model_pi():
    """Kp = tau / (K lambda), Ki = 1 / (K lambda): on the nominal heart the closed loop is
    1 / (lambda s + 1), so a 40 bpm step of the target is 1 - 1/e done after lambda."""
    from bike_controller.heart_erg import HeartRateErg

    erg = HeartRateErg(H, 60.0, 1000.0)
    assert erg.kp_w_per_bpm == pytest.approx(68.7 / 30.0) and erg.ki_w_per_bpm_s == pytest.approx(1.0 / 30.0)
    heart = HeartRate(H)
    heart.step(100.0, 3600.0)                    # settled at 110 bpm on 100 W
    erg.start(100.0)
    t, hr, p = _closed_loop(erg, heart, 150.0, 600.0, dt_s=0.1)
    at_lambda = hr[np.searchsorted(t, 60.0)]
    assert at_lambda == pytest.approx(110.0 + 40.0 * (1.0 - math.exp(-1.0)), abs=0.5)
    assert hr[-1] == pytest.approx(150.0, abs=0.05) and hr.max() < 150.1      # no overshoot
    assert p[-1] == pytest.approx(180.0, abs=0.5)                          # (150 - 60) / 0.5


def test_the_heart_rate_erg_holds_at_its_limits_without_wind_up_and_without_a_heart_rate():
    from bike_controller.heart_erg import HeartRateErg

    erg = HeartRateErg(H, 60.0, 150.0)           # 150 W at most: HR_ss 135
    heart = HeartRate(H)
    erg.start(100.0)
    _, hr, p = _closed_loop(erg, heart, 170.0, 900.0)
    assert p[-1] == 150.0 and erg.saturated and hr[-1] == pytest.approx(135.0, abs=0.5)
    # no wind-up: a reachable target takes the power off the limit in the next step
    p_next = erg.step(120.0, heart.bpm, 1.0)
    assert p_next < 150.0 and not erg.saturated
    held = erg.power_w
    assert erg.step(120.0, 0.0, 1.0) == held and erg.saturated     # no heart rate: held, flagged


def test_the_heart_rate_erg_comes_down_from_the_power_the_bike_takes():
    """A bike that takes less than the PI asks (the SPMSM's brake at its envelope): below the
    target the power still rises freely (the brake is asked past its envelope, its strongest),
    above it the integral is no higher than the power taken, so the power comes down at once,
    not from the wound-up integral at the integral gain's pace."""
    from bike_controller.heart_erg import HeartRateErg

    erg = HeartRateErg(H, 60.0, 1000.0)
    erg.start(300.0)
    assert erg.step(150.0, 140.0, 1.0, taken_w=200.0) > 300.0          # below the target: unchanged law
    wound = erg.integral_w
    p_over = erg.step(150.0, 152.0, 1.0, taken_w=200.0)
    assert erg.integral_w < 200.0 and p_over < 200.0 - 2.0 * erg.kp_w_per_bpm + 1e-9
    free = HeartRateErg(H, 60.0, 1000.0)
    free.start(wound)
    assert free.step(150.0, 152.0, 1.0) > 290.0                         # without it: ~wound - 2 Kp


def test_an_spmsm_heart_rate_erg_beyond_its_brake_does_not_overshoot_the_target():
    """The SPMSM bike with its rider at 80 rpm takes at most ~200 W (its rectifier path's
    envelope through the pedal stroke); a 150 bpm target asks more. The power target wound up to
    300 W, unwound at 0.35 W/s once the heart passed the target, and the heart went on to
    154.6 bpm at 200 s (past 150.5 from 153 s on, 152.5 at the 170 s ridden here). Now it comes
    down from what the bike takes: at most 150.1 bpm (148.9 at 170 s)."""
    import pathlib

    from bike_controller.modes import MODE_ERG
    from bike_controller.spmsm_session import ModedSpmsmController
    from bike_plant import spmsm as M
    from bike_plant.config import load_config

    cfg = load_config(pathlib.Path(__file__).resolve().parents[1] / "config" / "spmsm_default.yaml")
    plant, ctrl = M.SpmsmPlant(M.plant_params_from_config(cfg)), ModedSpmsmController(cfg)
    ctrl.set_command(100.0 / ctrl.law.erg_power_max_w, MODE_ERG, heart_rate_bpm=150.0)
    hr_bpm, saturated = [], []
    while plant.time_s < 170.0:
        snap = plant.snapshot()
        snap.update(batch_periods=ctrl.batch_periods)
        *cmd, status = ctrl.decide(snap)
        plant.step_batch(*cmd)
        hr_bpm.append(snap["heart_rate_bpm"])
        saturated.append(status["mode_saturated"])
    assert np.mean(saturated[:20000]) > 0.9, "the test needs a target beyond what the brake takes"
    assert max(hr_bpm) < 150.5 and hr_bpm[-1] > 147.0, (max(hr_bpm), hr_bpm[-1])


def test_bad_tuning_is_one_error():
    from bike_controller.heart_erg import HeartRateErg
    from bike_controller.modes import ModeParams

    with pytest.raises(ValueError, match="hr_closed_loop_s"):
        HeartRateErg(H, 0.0, 100.0)
    with pytest.raises(ValueError, match="hr_time_constant_s must be a number > 0"):
        ModeParams(hr_time_constant_s=-1.0)


@pytest.mark.parametrize("rider", [{}, {"rider_preset": "custom", "rider_hr_gain_bpm_per_w": 0.35,
                                        "rider_hr_time_constant_s": 90.0}])
def test_the_bike_holds_the_riders_heart_rate_in_erg(rider):
    """The BLDC bike with its rider, offline (the nodes' batch exchange): 60 s of ERG at about
    100 W, then a heart-rate target of 140 bpm. The rider's heart settles there and his power at
    (140 - rest - drift) / gain: the heart-rate ERG takes the power down as the heart drifts.
    Second case: a rider whose heart is 30 % less steep and 30 % slower than the trainer's
    nominal one (modes.hr_*), which the loop must still hold."""
    from bike_plant.config import load_config
    from bike_plant.sim import BldcPlant
    from bike_plant.params import plant_params_from_config
    from bike_controller.closed_loop import run_offline
    from bike_controller.modes import MODE_ERG
    from bike_controller.session_control import ModedController

    cfg = load_config("config/bldc_default.yaml")
    cfg["load"] = dict(cfg["load"], **rider)
    plant = BldcPlant(plant_params_from_config(cfg))
    ctrl = ModedController(cfg, batch_periods=200)
    out = run_offline(cfg, 600.0, lambda t: (0.1, MODE_ERG) if t < 60.0 else (0.0, MODE_ERG, 0.0, None, 140.0),
                      batch_periods=200, record_every=100, plant=plant, controller=ctrl)
    assert plant.snapshot()["heart_rate_bpm"] == plant.heart.bpm
    # within 1 bpm; the mismatched heart's slower loop lags the drift's ramp by 1.0 bpm
    assert plant.heart.bpm == pytest.approx(140.0, abs=1.0 if not rider else 1.5)
    drift_bpm = plant.heart.heart.drift_bpm
    assert 3.0 < drift_bpm < 6.0                 # 0.25 of ~80 bpm, a third of the way after 10 min
    t, e = out["time_s"], out["energy_mech_in_j"]
    last = t >= 540.0
    power_w = (e[last][-1] - e[last][0]) / (t[last][-1] - t[last][0])
    gain = plant.params.load.rider_hr_gain_bpm_per_w
    assert power_w == pytest.approx((140.0 - 60.0 - drift_bpm) / gain, rel=0.03)
    assert ctrl.last_out.target == pytest.approx(power_w, rel=0.03)     # the ERG's power in force
    first = (t >= 240.0) & (t < 300.0)                                  # settled, minute 4-5
    power_early_w = (e[first][-1] - e[first][0]) / (t[first][-1] - t[first][0])
    assert power_early_w - power_w > 3.0                                # the drift, taken off


HR_PROFILE = """name: hr_erg_test
mode: erg
segments:
  - {kind: step, duration_s: 4, target: 100}
  - {kind: step, duration_s: 16, heart_rate_bpm: 120}
"""


@pytest.mark.slow
def test_heart_rate_erg_in_the_node_graph(tmp_path, ros_domain):
    """`./bike run` on the default bike with a profile whose second step holds 120 bpm: the
    Commands carry the target, the plant's rider has a heart (PlantState.heart_rate_bpm), and the
    controller moves the ERG power until it beats at 120 -- at (120 - 60) / 0.5 = 120 W. The
    rider's heart (and the trainer's nominal one) is made 35x faster than a real one (tau 2 s,
    closed loop 2 s) so that 16 s show what a real ride shows in minutes. The report counts the
    stretch as settled."""
    from conftest import FAST_BATCHES, bike_command

    from bike_session.bags import read_topic, stamp_s

    profile = tmp_path / "hr.yaml"
    profile.write_text(HR_PROFILE)
    result = bike_command("run", "--workout", str(profile), "--set", "load.rider_hr_time_constant_s=2",
                          "--set", "modes.hr_time_constant_s=2", "--set", "modes.hr_closed_loop_s=2",
                          "--record", str(tmp_path / "rec"), *FAST_BATCHES)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    bag = next((tmp_path / "rec").iterdir())
    targets = {(stamp_s(c) >= 4.0 - 1e-9, c.heart_rate_bpm) for c in read_topic(bag, "command") if stamp_s(c) < 20.0}
    assert targets == {(False, 0.0), (True, 120.0)}, targets
    beats = np.array([(stamp_s(m), m.heart_rate_bpm) for m in read_topic(bag, "plant_state")])
    assert beats[0, 1] == 60.0                                       # at rest when the ride starts
    late = beats[beats[:, 0] >= 12.0, 1]
    assert np.all(np.abs(late - 120.0) < 3.0), (late.min(), late.max())
    power_w = np.array([s.mode_target for s in read_topic(bag, "controller_status") if stamp_s(s) >= 18.0])
    assert power_w.mean() == pytest.approx(120.0, rel=0.05)
    assert "heart-rate ERG:        1 target stretch(es), 1 settled" in result.stdout, result.stdout[-3000:]
