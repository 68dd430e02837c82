"""BLDC controller (paper 000): Eq. 1-9 with the paper's numbers, commutation, validation."""
from __future__ import annotations

import math
import pathlib

import numpy as np
import pytest

from bike_controller import bldc_control as C
from bike_controller.closed_loop import run_offline
from bike_controller.speed_estimator import HallSpeedEstimator, pulses_per_rev, speed_rpm_from_counts
from bike_controller.bldc_params import KGF_CM_TO_NM
from bike_controller.torque_command import pmax_w, torque_command_nm
from bike_plant import bldc as K
from bike_plant.config import config_variant, load_config

ROOT = pathlib.Path(__file__).resolve().parents[1]
CFG_PATH = ROOT / "config" / "bldc_default.yaml"
TMAX = 30 * KGF_CM_TO_NM


def msg_fields(name):
    fields = []
    for line in (ROOT / "src" / "bike_msgs" / "msg" / f"{name}.msg").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line and "=" not in line and line.split()[1] != "header":
            fields.append(line.split()[1])
    return fields


@pytest.fixture(scope="module")
def cfg():
    """The default bike with the paper's load: a prime mover (the demo rides a rider model)."""
    c = load_config(CFG_PATH)
    c["load"] = dict(c["load"], kind="prime_mover")
    return c


@pytest.fixture
def paper_cfg(cfg):
    """The paper's own k table: 0.8 below 4500 rpm, 1.0 above (section 5)."""
    return config_variant(cfg, controller={"k_speed_rpm": [0.0, 4500.0], "k_factor": [0.8, 1.0], "k_interp": "step",
                                           "k_command": []})


def test_eq1_speed_from_capture_counts():
    assert pulses_per_rev(2) == 12
    # 3000 rpm -> 12 edges per rev -> 600 edges/s -> 2083.3 counts at 1.25 MHz
    assert speed_rpm_from_counts(2083, 1.25e6, 2) == pytest.approx(60 * 1.25e6 / (12 * 2083))
    assert speed_rpm_from_counts(2083, 1.25e6, 2) == pytest.approx(3000.48, abs=0.01)
    assert speed_rpm_from_counts(1157, 1.25e6, 2) == pytest.approx(5401.9, abs=0.1)
    assert speed_rpm_from_counts(0, 1.25e6, 2) == 0.0
    est = HallSpeedEstimator(1.25e6, 2)
    est.edge(1000)
    assert est.edge(1000 + 2500) == pytest.approx(2500.0)


def test_eq1_takes_no_interval_across_edges_it_did_not_see():
    """A realtime controller that skipped PlantStates lost their Hall edges: Eq. 1 over the
    gap would be 11 intervals long (1/11 of the speed). The first edge after it only starts an
    interval; the speed holds until the second."""
    nc = 2260                                    # 2765 rpm at 1.25 MHz, 2 pole pairs
    est = HallSpeedEstimator(1.25e6, 2)
    for k in range(5):
        est.edge(k * nc)
    held_rpm = est.speed_rpm
    assert held_rpm == pytest.approx(speed_rpm_from_counts(nc, 1.25e6, 2))
    # edges 5..14 lost with the skipped states; the state taken carries edges from count 15 nc - 100
    est.edges_lost_before(15 * nc - 100)
    assert est.edge(15 * nc) == held_rpm         # not Eq. 1 of 11 nc
    assert est.edge(16 * nc) == pytest.approx(held_rpm)
    # no loss said: the interval is taken as it comes (what lockstep, which sees every edge, does)
    plain = HallSpeedEstimator(1.25e6, 2)
    plain.edge(0)
    assert plain.edge(11 * nc) == pytest.approx(held_rpm / 11)


@pytest.mark.parametrize("skipped", [5, 30, 200])
def test_a_controller_that_skipped_plant_states_keeps_its_speed_estimate(cfg, skipped):
    """Realtime: the controller reads the newest PlantState only, so one descheduled for
    ``skipped`` batches (the plant runs on with the held DriveCommand) never sees their Hall
    edges. Its speed estimate, the ERG's virtual speed and an app's km/h, fell to 3-30 % of the
    shaft's for a batch or two (seen: 2-9 km/h of ~28 at 79 rpm cadence): the interval of the
    first edge after the gap spanned every lost edge, and the speed bound counted the gap as
    time without an edge. No physical deceleration does that in a few ms."""
    from bike_plant import params as P
    from bike_plant.sim import BldcPlant
    speed_rpm = 79.0 * 35.0                           # the app ride's cadence on the 35:1 gear
    c = config_variant(cfg, load={"speed_rpm": speed_rpm})
    plant = BldcPlant(P.plant_params_from_config(c))
    ctrl = C.BatchController(c)
    ctrl.set_command(0.1, 0)
    seen, estimates = 0, []
    for k in range(150 + skipped):
        if 60 <= k < 60 + skipped:
            plant.step_batch(ga, gb, sp)                 # held command, the state goes unread
            continue
        ga, gb, sp, status = ctrl.decide(plant.snapshot())
        seen += 1
        if seen > 20:                                    # past the first Hall intervals
            # what the ControllerStatus says and what the mode laws take next (end of batch)
            estimates += [status["speed_est_rpm"], float(ctrl.cs[C.C_SPEED_EST])]
        plant.step_batch(ga, gb, sp)
    assert min(estimates) > 0.97 * speed_rpm and max(estimates) < 1.03 * speed_rpm, \
        (min(estimates), max(estimates))
    assert ctrl.skipped_state_gaps == 1               # the gap was seen as one


def test_eq2_pmax_and_the_printed_value():
    assert TMAX == pytest.approx(2.942, abs=1e-3)
    p = pmax_w(TMAX, 3300.0)
    assert p == pytest.approx(1016.6, abs=0.2)
    assert abs(p - 964.68) > 50          # the paper's printed Pmax contradicts its Eq. 2


def test_eq3_eq4_torque_command(cfg):
    ctrl = C.BatchController(cfg)
    assert ctrl.torque_command_nm(2000.0) == pytest.approx(TMAX)
    assert ctrl.torque_command_nm(4500.0) == pytest.approx(1016.68 / (4500 * 2 * math.pi / 60))
    assert ctrl.torque_command_nm(4500.0) == pytest.approx(2.1575, abs=1e-3)
    assert ctrl.torque_command_nm(2000.0, 0.5) == pytest.approx(TMAX / 2)
    # continuous at the base speed with Pmax from Eq. 2
    below = torque_command_nm(1.0, 3299.999, TMAX, 3300.0, 1016.68)
    above = torque_command_nm(1.0, 3300.0, TMAX, 3300.0, 1016.68)
    assert above == pytest.approx(below, rel=1e-4)


def test_eq8_eq9_ktg_with_paper_table(paper_cfg):
    ctrl = C.BatchController(paper_cfg)
    kt = 5.45e-3 * 60 / (2 * math.pi)
    assert ctrl.k_factor(2000.0) == 0.8
    assert ctrl.ktg(2000.0) == pytest.approx(0.8 * kt)
    assert ctrl.ktg(2000.0) == pytest.approx(0.04163, abs=1e-5)
    assert ctrl.k_factor(4500.0) == 1.0
    assert ctrl.ktg(4500.0) == pytest.approx(0.05204, abs=1e-5)


COMMAND_TABLE = {"k_speed_rpm": [0.0, 2000.0], "k_command": [0.2, 0.4, 0.8], "k_interp": "linear",
                 "k_factor": [1.10, 1.00, 0.90, 0.80, 0.70, 0.60]}     # rows of Command 0.2, 0.4, 0.8


def test_eq7_k_over_speed_and_command(cfg):
    """A k table with a Command axis: rows interpolated linearly in the Command, clamped at both
    ends, each row over the speed as before; the controller's kernel and the plain-Python law
    agree."""
    from bike_controller.bldc_params import k_factor as k_law
    ctrl = C.BatchController(config_variant(cfg, controller=COMMAND_TABLE))
    assert ctrl.k_factor(0.0, 0.4) == pytest.approx(0.90)
    assert ctrl.k_factor(2000.0, 0.8) == pytest.approx(0.60)
    assert ctrl.k_factor(1000.0, 0.4) == pytest.approx(0.85)                 # along the speed
    assert ctrl.k_factor(0.0, 0.3) == pytest.approx(1.00)                    # between two rows
    assert ctrl.k_factor(1000.0, 0.6) == pytest.approx(0.5 * (0.85 + 0.65))  # bilinear
    assert ctrl.k_factor(0.0, 0.1) == pytest.approx(1.10)                    # clamped below
    assert ctrl.k_factor(3000.0) == pytest.approx(0.60)                      # and above (Command 1)
    assert ctrl.k_factor(-1000.0, 0.6) == ctrl.k_factor(1000.0, 0.6)
    xs, cs, ys = ctrl.cp.k_table()
    rng = np.random.default_rng(3)
    for speed, command in zip(rng.uniform(-3000, 3000, 50), rng.uniform(0, 1, 50)):
        assert ctrl.k_factor(speed, command) == pytest.approx(k_law(speed, command, xs, ys, len(xs), True, cs, len(cs)),
                                                              rel=1e-12)   # the kernel may fuse a multiply-add


def test_eq7_the_command_row_sets_the_current_command(cfg):
    """I* = Tcmd / (k(w, Command) kt) (Eq. 3-9): the row of the Command in force, not Command
    = 1's; a torque the modes ask (ERG, slope) takes the row of the Command that asks it."""
    ctrl = C.BatchController(config_variant(cfg, controller=COMMAND_TABLE))
    kt = 5.45e-3 * 60 / (2 * math.pi)
    ctrl.cs[C.C_SPEED_EST] = 1000.0
    for command in (0.1, 0.3, 0.6):
        ctrl.set_command(command, 0)
        tcmd = command * TMAX
        assert ctrl.cs[C.C_TCMD] == pytest.approx(tcmd)
        assert ctrl.cs[C.C_K] == pytest.approx(ctrl.k_factor(1000.0, command))
        assert ctrl.cs[C.C_ICMD] == pytest.approx(tcmd / (ctrl.k_factor(1000.0, command) * kt))
        assert ctrl.ktg(1000.0, tcmd) == pytest.approx(ctrl.k_factor(1000.0, command) * kt)
    assert ctrl.ktg(1000.0) == pytest.approx(0.65 * kt)


@pytest.mark.parametrize("table, message", [
    ({"k_factor": [0.8, 0.9]}, "k_factor must hold 6 values, one row of 2 per Command"),
    ({"k_factor": [0.8, 0.9] * 3 + [0.9]}, "k_factor must hold 6 values"),
    ({"k_command": [0.4, 0.2, 0.8]}, "strictly increasing Commands in (0, 1]"),
    ({"k_command": [0.0, 0.5, 1.0]}, "strictly increasing Commands in (0, 1]"),
    ({"k_command": [0.2, 0.5, 1.5]}, "strictly increasing Commands in (0, 1]"),
    ({"k_factor": [0.8, 0.9, 0.8, 2.5, 0.8, 0.9]}, "k_factor row of Command 0.4 entries must be in [1e-06, 2.0]"),
    ({"k_factor": [[0.8, 0.9], [0.8, 0.9], [0.8, 0.9]]}, "list items must be numbers"),
    ({"k_command": [], "k_factor": [0.8, 1.2]}, "in [1e-06, 1.0]"),       # the paper's one row: k <= 1
    ({"k_command": [i / 13 for i in range(1, 14)], "k_factor": [0.8, 0.9] * 13}, "at most 12 k_command points"),
    ({"k_command": []}, "with k_command: [] k_factor is the paper's one row over k_speed_rpm and must hold 2 "
                        "values, one per speed; got 6 (rows for several Commands need their k_command)"),
    # k is read at |speed|: a point below 0 was taken and never used
    ({"k_speed_rpm": [-1000.0, 2000.0]}, "k_speed_rpm must be speeds >= 0"),
    ({"k_command": [], "k_speed_rpm": [-1000.0, 0.0], "k_factor": [0.8, 1.0]}, "k_speed_rpm must be speeds >= 0"),
])
def test_a_bad_k_table_is_one_config_error(cfg, table, message):
    from bike_plant.config import ConfigError
    with pytest.raises(ConfigError, match="controller") as err:
        C.controller_params_from_config(config_variant(cfg, controller=dict(COMMAND_TABLE, **table)))
    assert message in str(err.value)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -0.01, 1.01, "0.5", None, True])
def test_set_command_rejects_bad_values(cfg, bad):
    ctrl = C.BatchController(cfg)
    ctrl.set_command(0.5, 0)
    with pytest.raises(ValueError, match="command"):
        ctrl.set_command(bad, 0)
    assert ctrl.command_rejected
    assert ctrl.status()["command"] == 0.5           # the last valid command stays
    ctrl.set_command(0.7, 0)
    assert not ctrl.command_rejected


def test_set_command_rejects_bad_mode(cfg):
    ctrl = C.BatchController(cfg)
    with pytest.raises(ValueError, match="mode"):
        ctrl.set_command(0.5, 3)


def test_commutation_patterns_fig5():
    # sector 0 (U at +E, V at -E): generating modulates Q2 (U low), motoring Q1 with Q4 on
    assert C.patterns(0, 0) == (0b000010, 0)
    assert C.patterns(0, 1) == (0b001001, 0b001000)
    for sector in range(6):
        on, off = C.patterns(sector, 0)
        assert bin(on).count("1") == 1 and on & 0b101010     # one low switch only
        for pat in C.patterns(sector, 1):
            assert K.blank_interlock(pat)[1] == 0


def test_pattern_table_is_patterns_by_hall_code():
    for motoring, mode in ((0, 0), (1, 1)):
        for hall in range(8):
            sector = int(K.HALL_TO_SECTOR[hall])
            want = C.patterns(sector, mode) if sector >= 0 else (-1, -1)
            assert tuple(C.PATTERN_TABLE[motoring, hall]) == want


@pytest.mark.parametrize("speed_rpm", [300.0, 3000.0])
def test_other_pattern_trial_held_at_zero_matches_the_exact_split(cfg, speed_rpm):
    """The controller's trial of the other pattern holds a diode leg that would cross zero
    at zero (trial_sym hold_at_zero) instead of splitting the step at the crossing: over a
    generating run's crossing trials it agrees with the exact split (two diode legs in
    series reach zero together and the bridge blocks)."""
    from bike_plant import params as P
    c = config_variant(cfg, load={"speed_rpm": speed_rpm})
    pp = P.plant_params_from_config(c)
    p = P.pack_params(pp)
    state = K.new_state(p, speed_rpm, pp.battery.soc0)
    ctrl = C.BatchController(c, pp, 1)
    ctrl.set_command(1.0)
    kc = K.plant_constants(p)
    ws = np.empty(K.WS_SIZE)
    wi = np.empty(6, np.int64)
    crossings = 0
    for _ in range(2000):
        C.run_fused(state, p, ctrl.cs, ctrl.q, 1, np.zeros((1, 3)), 0, np.zeros(1))
        emf = K.emf_sym(state, p)
        for pat in C.PATTERN_TABLE[0, int(state[K.S_HALL]) & 7]:
            if pat < 0:
                continue
            legs = K.legs_of(state[0], state[1], state[2], int(pat), state[K.S_VDC], emf, kc)
            exact, _ = K.trial_sym(state, int(pat), emf, legs, kc, ws, wi, False)
            held, _ = K.trial_sym(state, int(pat), emf, legs, kc, ws, wi, True)
            j = [state[x] + kc[K.KC_G_DT] * legs[5 + x] for x in range(3)]
            if any(K._crossing(int(pat), state[0], state[1], state[2], *j)):
                crossings += 1
                assert abs(held - exact) <= 1e-6 * max(1.0, exact), (speed_rpm, exact, held)
    assert crossings > 100


def test_status_fields_and_decide_shapes(cfg):
    from bike_plant import params as P
    from bike_plant.sim import BldcPlant
    plant = BldcPlant(P.plant_params_from_config(cfg))
    ctrl = C.BatchController(cfg)
    ctrl.set_command(1.0, 0)
    ga, gb, sp, status = ctrl.decide(plant.snapshot())
    assert len(ga) == len(gb) == len(sp) == cfg["batch_periods"]
    assert set(status) < set(msg_fields("ControllerStatus"))
    assert status["quadrant"] == C.QUADRANT_GENERATING
    # the node's law (session modes on top) fills every field of the message, in order
    from bike_controller.session_control import ModedController
    moded = ModedController(cfg)
    moded.set_command(0.5, 2)
    *_, status = moded.decide(plant.snapshot())
    assert list(status) == msg_fields("ControllerStatus")


def test_closed_loop_gates_never_short_and_speed_estimate(cfg):
    c = config_variant(cfg, load={"speed_rpm": 4200.0})
    out = run_offline(c, 0.05, lambda t: (1.0, 0))
    ctrl, plant = out["controller"], out["plant"]
    assert plant.snapshot()["interlock_blanked_count"] == 0
    assert out["speed_est_rpm"][-1] == pytest.approx(4200.0, rel=2e-3)
    assert out["current_cmd_a"][-1] == pytest.approx(
        ctrl.torque_command_nm(4200.0) / ctrl.ktg(4200.0), rel=1e-2)
    assert out["k_factor"][-1] == pytest.approx(ctrl.k_factor(4200.0), rel=1e-2)


def test_motoring_quadrant_one(cfg):
    c = config_variant(cfg, load={"speed_rpm": 1000.0})
    out = run_offline(c, 0.06, lambda t: (0.5, 1))
    t_em = np.mean(out["torque_em_nm"][out["time_s"] > 0.02])
    assert t_em > 0.0                                       # motoring: torque along the speed
    assert t_em == pytest.approx(0.5 * TMAX, rel=0.15)      # k = 1 in motoring, commutation dip
    assert out["battery_current_a"][-1] < 0.0               # battery discharging


def test_current_hysteresis_mean_35a_at_3000rpm(cfg):
    c = config_variant(cfg, load={"speed_rpm": 3000.0})
    out = run_offline(c, 0.06, lambda t: (1.0, 0), current_override_a=35.0, record_samples=True)
    s = out["samples_a"][400:]
    i_fb = 0.5 * np.abs(s).sum(axis=1)
    assert i_fb.mean() == pytest.approx(35.0, rel=0.05)


def test_a_current_limit_below_what_tmax_needs_on_the_configured_machine_is_refused():
    """A BLDC with half the default ke needs Tmax / (k kt) = 138 A for Command = 1, and the
    controller clamped I* to current_limit_a (120 A) without a word. One error naming the key."""
    from bike_controller.bldc_params import controller_params_from_config, peak_current_command_a
    from bike_plant.config import ConfigError

    cfg = load_config(pathlib.Path(__file__).resolve().parents[1] / "config" / "bldc_default.yaml")
    need_a, _ = peak_current_command_a(controller_params_from_config(cfg), 5.45e-3 * 60.0 / (2.0 * math.pi))
    assert 68.0 < need_a < 70.0                   # the README's "~70 A the paper's Tmax needs"
    half_ke = config_variant(cfg, bldc={"ke_v_per_rpm": 2.725e-3})
    with pytest.raises(ConfigError, match=r"controller.current_limit_a: Command = 1 asks for 137.8 A .* "
                                          r"current_limit_a is 120 A"):
        controller_params_from_config(half_ke)
    controller_params_from_config(config_variant(half_ke, controller={"current_limit_a": 150.0},
                                                 bldc={"overcurrent_trip_a": 190.0}))
    controller_params_from_config(config_variant(half_ke, controller={"tmax_nm": 2.5, "pmax_w": 863.9}))


def test_an_overcurrent_trip_inside_the_controllers_current_band_is_refused():
    """current_limit_a raised to 200 A with the bridge's trip left at 150 A: the trip would blank
    the gates of the controller's own commands. One error naming bldc.overcurrent_trip_a."""
    from bike_controller.bldc_params import controller_params_from_config
    from bike_plant.config import ConfigError

    cfg = load_config(pathlib.Path(__file__).resolve().parents[1] / "config" / "bldc_default.yaml")
    with pytest.raises(ConfigError, match=r"bldc.overcurrent_trip_a: 150 A must be above "
                                          r"controller.current_limit_a \+ hysteresis_a = 201.5 A"):
        controller_params_from_config(config_variant(cfg, controller={"current_limit_a": 200.0}))
    controller_params_from_config(config_variant(cfg, controller={"current_limit_a": 200.0},
                                                 bldc={"overcurrent_trip_a": 250.0}))
