"""The benchmark's PMSM scenario on gym-electric-motor 3.0 (`make peers`).

    $BIKE_PEERS_DIR/gem/bin/python tools/peers/run_gem.py SCENARIO.json OUT.json

GEM's continuous speed-control PMSM environment ('Cont-SC-PMSM-v0': PermanentMagnetSynchronousMotor
with the parameters of paper 001, continuous B6 bridge on an ideal 24 V supply,
PolynomialStaticLoad with the viscous B and the constant term switched to the load-torque
step at its time, GEM's default ODE solver for this environment (scipy dopri5), tau =
100 us), stepped through env.step like an agent would. GEM's bundled controllers do not run
on this machine, so the agent is the project's PI (peer_common.ProjectPI): GEM's B6C action
in [-1, 1] per leg is 2 d - 1 for our duty cycle d (leg voltage (d - 1/2) Vdc).
"""
from __future__ import annotations

import math
import sys

from peer_common import TWO_PI, ProjectPI, Trace, clock, elapsed, load_scenario, piecewise, write_result


def run_once(scenario: dict):
    """One episode of the scenario: (wall seconds, trace, solver name)."""
    import warnings

    import numpy as np
    warnings.filterwarnings("ignore", message=".*Box observation space maximum and minimum.*")
    import gym_electric_motor as gem
    from gym_electric_motor.reference_generators import ConstReferenceGenerator

    m = scenario["machine"]
    pp = int(m["pole_pairs"])
    dt = float(scenario["control_period_s"])
    n_periods = int(round(scenario["duration_s"] / dt))
    pi = ProjectPI(scenario)
    trace = Trace(scenario)
    w_limit = 100.0       # rad/s (955 r/min): observation scaling only, no constraint is set
    limits = dict(omega=w_limit, torque=20.0, i=30.0, epsilon=math.pi, u=m["dc_link_v"])
    env = gem.make(
        "Cont-SC-PMSM-v0",
        motor=dict(motor_parameter=dict(p=pp, r_s=m["rs_ohm"], l_d=m["inductance_h"], l_q=m["inductance_h"],
                                        psi_p=m["flux_linkage_vs"], j_rotor=0.0),
                   limit_values=limits, nominal_values=limits),
        # the whole J on the load side (GEM divides by the load inertia when it is built)
        load=dict(load_parameter=dict(a=0.0, b=m["friction_nms"], c=0.0, j_load=m["inertia_kgm2"])),
        supply=dict(u_nominal=m["dc_link_v"]),
        reference_generator=ConstReferenceGenerator(
            reference_state="omega", reference_value=scenario["speed_ref_rpm"][-1] * TWO_PI / 60.0 / w_limit),
        constraints=(),
        visualization=(),
        tau=dt,
    )
    env.reset(seed=0)
    ps = env.unwrapped.physical_system
    names = list(ps.state_names)
    lim = np.asarray(ps.limits, dtype=float)
    i_w, i_d, i_q, i_eps = (names.index(s) for s in ("omega", "i_sd", "i_sq", "epsilon"))
    i_a, i_b, i_c = (names.index(s) for s in ("i_a", "i_b", "i_c"))
    load = ps.mechanical_load
    times, torques = scenario["load_time_s"], scenario["load_torque_nm"]

    def set_load_torque(tl):
        # PolynomialStaticLoad: T = sign(w) (c w^2 + a) + b w, constant term linearised near 0 r/min
        load._a = tl
        load._omega_lim = load._a / load._j_total * load.tau_decay

    state = np.asarray(ps.system_state, dtype=float)
    eps_prev = float(state[i_eps])
    eps_unwrapped = eps_prev
    tl_now = None
    t0 = clock()
    for k in range(n_periods + 1):
        trace.maybe(k, state[i_w], state[i_d], state[i_q])
        if k == n_periods:
            break
        tl = piecewise(times, torques, k * dt)
        if tl != tl_now:
            set_load_torque(tl)
            tl_now = tl
        eps = float(state[i_eps])
        eps_unwrapped += (eps - eps_prev + math.pi) % TWO_PI - math.pi
        eps_prev = eps
        da, db, dc = pi(k, float(state[i_a]), float(state[i_b]), float(state[i_c]), eps_unwrapped / pp)
        (obs, _ref), _reward, terminated, truncated, _info = env.step(np.array([2 * da - 1, 2 * db - 1, 2 * dc - 1]))
        if terminated:
            raise RuntimeError(f"gym-electric-motor: episode terminated at period {k}")
        state = np.asarray(obs, dtype=float) * lim
    wall_cpu = elapsed(t0)
    env.close()
    return wall_cpu, trace, type(ps._ode_solver).__name__


def main(argv: list[str]) -> int:
    scenario, out = load_scenario(argv)
    from importlib.metadata import version

    walls, cpus = [], []
    for _ in range(max(1, int(scenario.get("peer_repeats", 1)))):
        (wall, cpu), trace, solver = run_once(scenario)
        walls.append(wall)
        cpus.append(cpu)
    write_result(out, "gym-electric-motor", version("gym-electric-motor"), min(walls), min(cpus), scenario, trace,
                 solver=solver, repeats=len(walls))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
