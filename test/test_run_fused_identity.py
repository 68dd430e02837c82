"""run_fused (the benchmark's fused loop, also called by the fleet kernel) equals, bit for
bit, the step-by-step closed loop of closed_loop_period on the state vector (control_batch
runs exactly that), at operating points that exercise every branch of the period: generating
at 3000 rpm, motoring, a rider load, low-speed discontinuous conduction, S0 switching (about
1200 toggles in 20000 periods) and the general (position-dependent L) machine. The guard
for any specialised form of run_fused (e.g. a register-resident period loop)."""
import numpy as np
import pytest

from bike_controller import bldc_control as BC
from bike_plant import bldc as K
from bike_plant import params as P
from bike_plant.config import load_config


def _bike(kind, speed_rpm, command, mode, soc0=None, eps=None, s0_on=None):
    cfg = load_config(None)
    cfg["load"] = dict(cfg.get("load") or {}, kind=kind, speed_rpm=float(speed_rpm))
    pp = P.plant_params_from_config(cfg)
    p = P.pack_params(pp)
    if eps is not None:
        p[P.P_EPS] = eps
    state = K.new_state(p, speed_rpm, pp.battery.soc0 if soc0 is None else soc0)
    if s0_on is not None:        # brake resistor threshold just above the bus: S0 switches
        p[P.P_S0_ON] = state[K.S_VDC] + s0_on
        p[P.P_S0_OFF] = state[K.S_VDC] + 0.5 * s0_on
    ctrl = BC.BatchController(cfg, pp, 1)
    ctrl.cs[BC.C_COMMAND] = command
    ctrl.cs[BC.C_MODE] = mode
    BC.update_command(ctrl.cs, ctrl.q)
    return p, state, ctrl.cs, ctrl.q


CASES = {
    "generating_3000rpm": dict(kind="prime_mover", speed_rpm=3000.0, command=1.0, mode=0),
    "motoring_1500rpm": dict(kind="prime_mover", speed_rpm=1500.0, command=0.5, mode=1),
    "rider": dict(kind="rider", speed_rpm=1200.0, command=0.7, mode=0),
    "low_speed_dcm": dict(kind="prime_mover", speed_rpm=150.0, command=1.0, mode=0),
    "s0_switching": dict(kind="prime_mover", speed_rpm=3000.0, command=1.0, mode=0, soc0=0.98, s0_on=0.3),
    "position_dependent_L": dict(kind="prime_mover", speed_rpm=2500.0, command=1.0, mode=0, eps=0.1),
}


def _reference(p, state, cs, q, n):
    """n periods of closed_loop_period, in chunks (control_batch is its loop)."""
    ec = np.zeros(4, np.uint64)
    es = np.zeros(4, np.uint8)
    m = 5000
    done = 0
    while done < n:
        k = min(m, n - done)
        BC.control_batch(cs, q, state, p, np.zeros(k, np.uint8), np.zeros(k, np.uint8), np.zeros(k), ec, es)
        done += k


@pytest.mark.parametrize("name", list(CASES))
def test_run_fused_is_bit_identical_to_closed_loop_period(name):
    n = 20000
    p, st_ref, cs_ref, q = _bike(**CASES[name])
    st, cs = st_ref.copy(), cs_ref.copy()
    s0_before = st_ref[K.S_S0]
    _reference(p, st_ref, cs_ref, q, n)
    BC.run_fused(st, p, cs, q, n, np.zeros((1, 3)), 0, np.zeros(1))
    assert st[K.S_PERIODS] == n
    assert np.array_equal(st, st_ref), f"{name}: plant state differs at {np.nonzero(st != st_ref)[0]}"
    assert np.array_equal(cs, cs_ref), f"{name}: controller state differs at {np.nonzero(cs != cs_ref)[0]}"
    assert np.all(np.isfinite(st))
    if name == "s0_switching":       # the case really exercises the brake resistor
        assert st[K.S_E_RES] > 0.0 and (st[K.S_S0] != s0_before or st[K.S_E_RES] > 0.0)
    if name == "low_speed_dcm":      # discontinuous conduction: some phase current exactly 0
        assert cs[BC.C_ICMD] > 0.0 and st[K.S_E_BATT] > 0.0


def test_run_fused_records_the_same_samples():
    p, st_ref, cs_ref, q = _bike(**CASES["rider"])
    st, cs = st_ref.copy(), cs_ref.copy()
    n, every = 600, 7
    rows = (n + every - 1) // every
    samples = np.zeros((rows, 3))
    tem = np.zeros(rows)
    BC.run_fused(st, p, cs, q, n, samples, every, tem)
    ref = np.zeros((rows, 3))
    ref_tem = np.zeros(rows)
    for k in range(n):
        _reference(p, st_ref, cs_ref, q, 1)
        if k % every == 0:
            ref[k // every] = st_ref[0:3]
            ref_tem[k // every] = st_ref[K.S_TEM]
    assert np.array_equal(samples, ref) and np.array_equal(tem, ref_tem)
    assert np.array_equal(st, st_ref) and np.array_equal(cs, cs_ref)
    assert np.any(tem != 0.0)
