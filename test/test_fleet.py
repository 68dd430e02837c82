"""Offline fleet kernel (bike_controller.fleet): the same physics as run_fused, bike by bike."""
import numpy as np
import pytest

from bike_controller import bldc_control as BC
from bike_controller import fleet
from bike_plant import bldc as K
from bike_plant import params as P
from bike_plant.config import load_config


@pytest.fixture(scope="module")
def cfg():
    return load_config(None)


def test_fleet_of_three_is_bit_identical_to_three_single_runs(cfg):
    fleet.set_threads(2)
    f = fleet.make_fleet(cfg, 3, seed=7)
    # three different bikes: different commands, riders and start speeds
    assert len(set(f.command)) == 3 and len(set(f.ps[:, P.P_RIDER_T0])) == 3 and len(set(f.speed0_rpm)) == 3
    singles = [(f.states[b].copy(), f.ps[b].copy(), f.css[b].copy(), f.qs[b].copy()) for b in range(3)]
    n = 2345                                    # not a multiple of the chunk: the tail chunk is covered
    res = fleet.run(f, n * f.control_period_s, chunk_periods=500)
    assert res["periods"] == n
    for b, (st, p, cs, q) in enumerate(singles):
        BC.run_fused(st, p, cs, q, n, np.zeros((1, 3)), 0, np.zeros(1))
        assert np.array_equal(f.states[b], st), f"bike {b}: plant state differs from run_fused"
        assert np.array_equal(f.css[b], cs), f"bike {b}: controller state differs from run_fused"
        assert st[K.S_PERIODS] == n
    # the bikes really differ (not one bike copied three times)
    assert len({f.states[b, K.S_OMEGA] for b in range(3)}) == 3
    # the cadence trace: one sample per chunk, the last one the final speed
    assert res["speed_trace_rad_s"].shape == (3, 5)
    assert np.array_equal(res["speed_trace_rad_s"][:, -1], f.states[:, K.S_OMEGA])


def test_fleet_summaries_are_physical(cfg):
    f = fleet.make_fleet(cfg, 6, seed=1)
    res = fleet.run(f, 0.2)
    per_bike = fleet.bike_summaries(f, res["sim_s"], res["speed_trace_rad_s"])
    assert [b["bike"] for b in per_bike] == list(range(1, 7))
    for b in per_bike:
        assert b["mean_rider_power_w"] > 0.0                 # the rider pedals
        assert b["mean_battery_power_w"] > 0.0               # resistance mode charges the battery
        assert abs(b["ledger_residual_j"]) < 0.05            # energy balance of each bike
        assert 20.0 < b["mean_cadence_rpm"] < 120.0
        assert b["faults"] == 0
    # a higher Command brakes harder: more charging power for the same rider, other things equal
    same = fleet.make_fleet(cfg, 2, spread=False)
    same.css[0, BC.C_COMMAND] = 0.3
    BC.update_command(same.css[0], same.qs[0])
    r2 = fleet.run(same, 0.2)
    s2 = fleet.bike_summaries(same, r2["sim_s"], r2["speed_trace_rad_s"])
    assert s2[1]["mean_battery_power_w"] > s2[0]["mean_battery_power_w"] + 20.0
    agg = fleet.aggregate(per_bike)
    assert agg["mean_rider_power_w"]["min"] <= agg["mean_rider_power_w"]["mean"] <= agg["mean_rider_power_w"]["max"]


def test_fleet_figures_keys(cfg):
    r = fleet.fleet_real_time(4, 0.01, threads=2)
    assert r["bikes"] == 4 and r["threads"] >= 1
    assert r["bikes_in_real_time"] == pytest.approx(4 * r["real_time"])
    assert r["wall_s"] > 0 and r["jit_compile_s"] >= 0


@pytest.mark.parametrize("bikes, seconds", [(0, 1.0), (-3, 1.0), (2.5, 1.0), (True, 1.0), (2, 0.0), (2, float("nan")),
                                            (2, -1.0), (2, "1")])
def test_fleet_bad_input_is_one_clear_error(cfg, bikes, seconds):
    with pytest.raises(ValueError, match="bikes|seconds"):
        fleet.fleet_real_time(bikes, seconds)


@pytest.mark.parametrize("check, value, message", [
    (fleet.check_bikes, 0, "--bikes must be an integer in [1, 1000000], got 0"),
    (fleet.check_seconds, float("inf"), "--seconds must be a number in (0, 3600], got inf"),
    (fleet.check_threads, 0, "--threads must be an integer >= 1, got 0"),
    (fleet.check_seed, -1, "--seed must be an integer >= 0, got -1")])
def test_fleet_checks_name_what_the_caller_calls_the_argument(check, value, message):
    """The CLI's option names come through the checks (as the torque map's check_grid takes them):
    before, the CLI prefixed "--" to a message's first word when it looked like an argument."""
    with pytest.raises(ValueError) as info:
        check(value, message.split(" ", 1)[0])
    assert str(info.value) == message


@pytest.mark.parametrize("machine_cfg", [
    {"machine": "spmsm", "battery": {"nominal_v": 24.0}},      # it said "battery: unknown parameter(s) nominal_v"
    {"machine": "spmsm"},                                      # it rode the BLDC bike's defaults without a word
    {"machine": "foo"}])
def test_a_config_of_another_machine_is_refused_naming_the_key(cfg, machine_cfg):
    from bike_plant.config import ConfigError
    other = dict(cfg, **machine_cfg)
    with pytest.raises(ConfigError, match=rf"machine: the offline fleet is the BLDC bike's batched kernel "
                                          rf"\(paper 000\), and this config is a '{machine_cfg['machine']}' bike$"):
        fleet.make_fleet(other, 2)


def test_less_than_one_control_period_is_refused_naming_the_argument(cfg):
    """--seconds 1e-5 (a tenth of a 50 us period) ran no period and ended in a ZeroDivisionError
    traceback (ns per bike-period); one period runs."""
    with pytest.raises(ValueError) as info:
        fleet.fleet_real_time(2, 1e-5, threads=2, names={"seconds": "--seconds"})
    assert str(info.value) == "--seconds must be at least one control period (5e-05 s), got 1e-05"
    f = fleet.make_fleet(cfg, 2)
    with pytest.raises(ValueError, match=r"^seconds must be at least one control period \(5e-05 s\), got 1e-09$"):
        fleet.run(f, 1e-9)
    assert fleet.run(f, f.control_period_s)["periods"] == 1
