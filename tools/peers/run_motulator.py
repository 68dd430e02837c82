"""The benchmark's PMSM scenario on motulator 0.18 (Python 3.12; `make peers`).

    $BIKE_PEERS_DIR/motulator/bin/python tools/peers/run_motulator.py SCENARIO.json OUT.json

motulator's continuous-time drive model (SynchronousMachine with the parameters of paper
001, MechanicalSystem with J, viscous B and the load-torque step, VoltageSourceConverter
on a stiff DC link, average model: pwm=False, no computational delay: delay=0) under its
own Simulation (scipy solve_ivp, motulator's default RK45 settings), with the project's PI
as the discrete-time control system (peer_common.ProjectPI) sampled every 100 us.
Writes wall time and the traces at the sample periods (peer_common.write_result).
"""
from __future__ import annotations

import sys

from peer_common import ProjectPI, Trace, clock, elapsed, load_scenario, piecewise, write_result


class ProjectControl:
    """motulator's control-system protocol (ctrl(mdl) -> (T_s, duty ratios)) around ProjectPI."""

    def __init__(self, pi: ProjectPI, trace: Trace):
        self.pi = pi
        self.trace = trace
        self.k = 0
        self.t = 0.0

    def get_enable(self) -> bool:
        return True

    def __call__(self, mdl):
        k = self.k
        ia, ib, ic = mdl.machine.meas_currents()
        i_dq = complex(mdl.machine.out.i_s_dq)
        self.trace.maybe(k, mdl.mechanics.meas_speed(), i_dq.real, i_dq.imag)
        d = self.pi(k, float(ia), float(ib), float(ic), float(mdl.mechanics.meas_position()))
        self.k += 1
        return self.pi.dt_s, [d[0], d[1], d[2]]

    def post_process(self):
        return None


def run_once(scenario: dict):
    """One simulation of the scenario: (wall seconds, trace, sim)."""
    from motulator.drive import model

    m = scenario["machine"]
    pi = ProjectPI(scenario)
    trace = Trace(scenario)
    par = model.SynchronousMachinePars(n_p=int(m["pole_pairs"]), R_s=m["rs_ohm"], L_d=m["inductance_h"],
                                       L_q=m["inductance_h"], psi_f=m["flux_linkage_vs"])
    machine = model.SynchronousMachine(par)
    mechanics = model.MechanicalSystem(J=m["inertia_kgm2"], B_L=m["friction_nms"])
    times, torques = scenario["load_time_s"], scenario["load_torque_nm"]
    mechanics.set_external_load_torque(lambda t: piecewise(times, torques, t))
    converter = model.VoltageSourceConverter(u_dc=m["dc_link_v"])
    mdl = model.Drive(machine, mechanics, converter, pwm=False, delay=0)
    ctrl = ProjectControl(pi, trace)
    sim = model.Simulation(mdl, ctrl, show_progress=False)
    t0 = clock()
    # runs until the first sampling instant after t_stop: + dt/2 makes the last control call
    # (which records the final sample) happen at t = duration
    res = sim.simulate(t_stop=float(scenario["duration_s"]) + 0.5 * pi.dt_s)
    wall_cpu = elapsed(t0)
    if not res.success:
        raise RuntimeError("motulator: the simulation stopped early")
    return wall_cpu, trace, sim


def main(argv: list[str]) -> int:
    scenario, out = load_scenario(argv)
    import motulator

    walls, cpus = [], []
    for _ in range(max(1, int(scenario.get("peer_repeats", 1)))):
        (wall, cpu), trace, sim = run_once(scenario)
        walls.append(wall)
        cpus.append(cpu)
    write_result(out, "motulator", getattr(motulator, "__version__", "") or _version("motulator"), min(walls),
                 min(cpus), scenario, trace, solver=sim.cfg.method, repeats=len(walls))
    return 0


def _version(dist: str) -> str:
    from importlib.metadata import version
    return version(dist)


if __name__ == "__main__":
    sys.exit(main(sys.argv))
