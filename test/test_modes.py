"""Session modes (bike_controller.modes): ERG, slope / virtual terrain, isokinetic, switching."""
from __future__ import annotations

import math

import pytest

from bike_controller.modes import (MODE_ERG, MODE_ISOKINETIC, MODE_MOTORING, MODE_RESISTANCE, MODE_SLOPE,
                                   G_MPS2, ModeLaw, ModeParams, mode_params_from_config)
from bike_controller.torque_command import RPM_PER_RAD_S

GEAR = 35.0
TMAX = 2.941995
PMAX = 1016.68
WB = 3300.0
J = 0.01
DT = 1e-3


def law(**kw) -> ModeLaw:
    return ModeLaw(ModeParams(**kw), gear_ratio=GEAR, inertia_kgm2=J, tmax_nm=TMAX, pmax_w=PMAX,
                   base_speed_rpm=WB)


def settle(m: ModeLaw, command, mode, speed_rpm, n=400):
    out = None
    for _ in range(n):
        out = m.step(command, mode, speed_rpm, DT)
    return out


def test_resistance_and_motoring_follow_paper_000():
    m = law()
    out = settle(m, 0.5, MODE_RESISTANCE, 2000.0)
    assert out.brake_torque_nm == pytest.approx(0.5 * TMAX)                 # Eq. 3
    out = settle(m, 0.5, MODE_RESISTANCE, 5000.0)
    assert out.brake_torque_nm == pytest.approx(0.5 * PMAX / (5000.0 / RPM_PER_RAD_S))   # Eq. 4
    out = settle(m, 0.4, MODE_MOTORING, 1000.0)
    assert out.brake_torque_nm == pytest.approx(-0.4 * TMAX)


def test_erg_holds_power_and_avoids_the_spiral_of_death():
    m = law(erg_min_cadence_rpm=40.0)
    p_target = 0.25 * PMAX
    for cadence in (60.0, 80.0, 100.0):
        w = cadence * GEAR / RPM_PER_RAD_S
        out = settle(m, 0.25, MODE_ERG, cadence * GEAR)
        assert out.brake_torque_nm * w == pytest.approx(p_target, rel=1e-9)
        assert out.target == pytest.approx(p_target) and not out.saturated
    # below the minimum cadence the torque stops rising: a slowing rider is not pinned down
    t40 = settle(m, 0.25, MODE_ERG, 40.0 * GEAR).brake_torque_nm
    t20 = settle(m, 0.25, MODE_ERG, 20.0 * GEAR).brake_torque_nm
    t5 = settle(m, 0.25, MODE_ERG, 5.0 * GEAR).brake_torque_nm
    assert t20 == pytest.approx(t40) and t5 == pytest.approx(t40)
    # a target beyond the torque limit is reported, not silently missed
    out = settle(m, 1.0, MODE_ERG, 50.0 * GEAR)
    assert out.saturated and out.brake_torque_nm == pytest.approx(TMAX)


def test_slope_road_load_uphill_brakes_downhill_assists():
    m = law(virtual_inertia=False)
    mp = m.mp
    cadence = 80.0
    w = cadence * GEAR / RPM_PER_RAD_S
    v = w * mp.wheel_radius_m * mp.virtual_gear_ratio / GEAR
    # command 0.5 = flat with the default +-20 %: rolling + aero only
    flat = settle(m, 0.5, MODE_SLOPE, cadence * GEAR)
    f_flat = (mp.rider_mass_kg + mp.bike_mass_kg) * G_MPS2 * mp.crr + 0.5 * mp.air_density_kg_m3 * mp.cda_m2 * v * v
    assert flat.target == pytest.approx(0.0)
    assert flat.virtual_speed_mps == pytest.approx(v)
    # power at the wheel equals the road power: torque * w = F * v
    assert flat.brake_torque_nm * w == pytest.approx(f_flat * v, rel=1e-9)
    up = settle(m, 0.5 + 0.05 / 0.4, MODE_SLOPE, cadence * GEAR)             # +5 %
    assert up.target == pytest.approx(0.05)
    f_up = m.road_force_n(0.05, v)
    assert up.brake_torque_nm * w == pytest.approx(f_up * v, rel=1e-9) and up.brake_torque_nm > flat.brake_torque_nm
    down = settle(m, 0.5 - 0.08 / 0.4, MODE_SLOPE, cadence * GEAR)           # -8 %: assist (motoring quadrant)
    assert down.brake_torque_nm < 0
    # a rider who stopped is never driven by the motor
    stopped = settle(m, 0.5 - 0.08 / 0.4, MODE_SLOPE, 5.0 * GEAR)
    assert stopped.brake_torque_nm == 0.0


def test_slope_virtual_flywheel_resists_acceleration():
    m = law(virtual_inertia=True)
    steady = settle(m, 0.5, MODE_SLOPE, 2800.0, n=600).brake_torque_nm
    # accelerate at 300 rpm/s (motor) for 0.3 s: the emulated rider + bike mass pushes back
    speed = 2800.0
    for _ in range(300):
        speed += 300.0 * DT
        out = m.step(0.5, MODE_SLOPE, speed, DT)
    alpha = 300.0 / RPM_PER_RAD_S
    expected_extra = (m.j_virtual_kgm2 - J) * alpha
    f_now = m.road_force_n(0.0, speed / RPM_PER_RAD_S * m.mps_per_rad_s) * m.mps_per_rad_s
    assert out.brake_torque_nm - f_now == pytest.approx(expected_extra, rel=0.05)
    assert out.brake_torque_nm > steady


def test_isokinetic_holds_cadence_against_the_rider():
    """Closed loop on the flywheel J dw/dt = T_rider - T_brake: the rider pushes harder and
    softer; the cadence returns to the target either way."""
    m = law(isokinetic_bandwidth_rad_s=20.0)
    command = 0.4                                     # 20 + 0.4 * 100 = 60 rpm crank
    target_rpm = 60.0
    w = 50.0 * GEAR / RPM_PER_RAD_S                   # starts below the target: assist
    m.reset()
    log = []
    for k in range(6000):
        t = k * DT
        rider = 0.5 if t < 2.0 else (1.5 if t < 4.0 else 0.2)   # N m at the motor shaft
        out = m.step(command, MODE_ISOKINETIC, w * RPM_PER_RAD_S, DT)
        w += (rider - out.brake_torque_nm) / J * DT
        log.append((t, w * RPM_PER_RAD_S / GEAR, out))
    assert log[0][2].target == pytest.approx(target_rpm)
    for t_check in (1.9, 3.9, 5.9):
        cadence = next(c for t, c, _ in log if t >= t_check)
        assert cadence == pytest.approx(target_rpm, abs=0.2), (t_check, cadence)
    # the law brakes a strong rider and assists a weak one
    assert next(o for t, _, o in log if t >= 3.9).brake_torque_nm == pytest.approx(1.5, abs=0.02)
    assert next(o for t, _, o in log if t >= 5.9).brake_torque_nm == pytest.approx(0.2, abs=0.02)


def test_mode_switch_ramps_instead_of_stepping():
    m = law(torque_rate_nm_per_s=20.0)
    settle(m, 0.1, MODE_RESISTANCE, 2800.0)
    before = m.torque_nm
    outs = [m.step(1.0, MODE_ERG, 2800.0, DT) for _ in range(300)]
    steps = [abs(b.brake_torque_nm - a.brake_torque_nm) for a, b in zip(outs, outs[1:])]
    assert abs(outs[0].brake_torque_nm - before) <= 20.0 * DT + 1e-12
    assert max(steps) <= 20.0 * DT + 1e-12
    assert outs[0].ramping and not outs[-1].ramping
    assert outs[-1].brake_torque_nm == pytest.approx(outs[-1].wanted_torque_nm)


def test_bad_commands_and_config_are_refused():
    m = law()
    for bad in (math.nan, -0.1, 1.5, math.inf):
        with pytest.raises(ValueError, match="command"):
            m.step(bad, MODE_ERG, 1000.0, DT)
    with pytest.raises(ValueError, match="unknown mode"):
        m.step(0.5, 9, 1000.0, DT)
    with pytest.raises(ValueError, match="unknown key"):
        mode_params_from_config({"modes": {"crr_typo": 0.1}})
    with pytest.raises(ValueError, match="crr"):
        mode_params_from_config({"modes": {"crr": "fast"}})
    with pytest.raises(ValueError, match="grade"):
        mode_params_from_config({"modes": {"grade_min": 0.3, "grade_max": 0.2}})
    with pytest.raises(ValueError, match="rider_mass_kg"):
        mode_params_from_config({"modes": {"rider_mass_kg": -70}})
    assert mode_params_from_config({"modes": {"crr": 0.005}}).crr == 0.005
