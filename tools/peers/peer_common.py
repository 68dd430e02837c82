"""Shared by the peer runners (run_motulator.py, run_gem.py): the scenario, the project's own
PI control law driving a peer's machine model, and the JSON result.

The runners execute in the peers' own virtual environments (`make peers`), not in the
project's: they import the control law straight from src/ (bike_controller.spmsm_control
needs only numpy, numba and PyYAML, installed next to each peer). Every 100 us the peer's
model is sampled like our plant is (phase currents at the period start, encoder count of
the unwrapped mechanical angle), the SAME kernel as `./bike` runs
(spmsm_control.control_period, PI family, pole placement) computes three duty cycles, and
the peer integrates its own machine model over the period with the phase voltages
(d - 1/2) Vdc held (average inverter, no computational delay: as our offline runner).
The scenario (parameters of paper 001, section 6, speed and load profiles, sample times)
comes from bike_session.bench_peers.scenario() as JSON.
"""
from __future__ import annotations

import json
import math
import os
import pathlib
import sys
import time

TWO_PI = 2.0 * math.pi


def load_scenario(argv: list[str]) -> tuple[dict, pathlib.Path]:
    """`run_X.py SCENARIO.json OUT.json` -> (scenario, out path); puts src/ on sys.path."""
    if len(argv) != 3:
        raise SystemExit(f"usage: {argv[0]} SCENARIO.json OUT.json")
    scenario = json.loads(pathlib.Path(argv[1]).read_text())
    root = pathlib.Path(scenario["repo_root"])
    for pkg in ("bike_plant", "bike_controller"):
        path = str(root / "src" / pkg)
        if path not in sys.path:
            sys.path.insert(0, path)
    # numba caches of another Python / numba version must not land in the project's tree
    os.environ.setdefault("NUMBA_CACHE_DIR", str(pathlib.Path(sys.prefix) / "numba-cache"))
    return scenario, pathlib.Path(argv[2])


def piecewise(times: list[float], values: list[float], t: float) -> float:
    """Piecewise-constant profile: the value of the last point with time <= t (0 before)."""
    out = 0.0
    for tk, vk in zip(times, values):
        if t + 1e-12 >= tk:
            out = vk
    return out


class ProjectPI:
    """The project's SPMSM control law (PI family) fed with a peer's measurements."""

    def __init__(self, scenario: dict):
        import numpy as np
        from bike_controller import spmsm_control as SC
        from bike_plant import spmsm as M

        self.np, self.SC, self.M = np, SC, M
        self.scenario = scenario
        self.ctrl = SC.SpmsmController(scenario["config"], family="pi")
        self.meas = np.zeros(M.S_SIZE)
        self.meas[M.S_RELAY] = M.REL_INVERTER
        self.meas[M.S_RELAY_FROM] = M.REL_INVERTER
        self.ctrl.reset_from(self.meas)          # at rest, as our plant starts
        self.cpr = float(self.ctrl.q[SC.Q_CPR])
        self.ns = int(self.ctrl.q[SC.Q_NS])
        self.dt_s = float(scenario["control_period_s"])
        self._theta_m = 0.0                       # unwrapped mechanical angle [rad]
        self._wrapped_prev = 0.0
        self.warm_up()

    def warm_up(self) -> None:
        """Compile (or load from the numba cache) the kernel before any timing."""
        cs = self.ctrl.cs.copy()
        self.SC.control_period(cs, self.ctrl.q, self.meas.copy())

    def track_angle(self, theta_m_wrapped: float) -> float:
        """Unwrap a peer's wrapped mechanical angle (steps are far below pi per 100 us)."""
        d = (theta_m_wrapped - self._wrapped_prev + math.pi) % TWO_PI - math.pi
        self._wrapped_prev = theta_m_wrapped
        self._theta_m += d
        return self._theta_m

    def __call__(self, k: int, ia: float, ib: float, ic: float, theta_m_wrapped: float):
        """Duty cycles (da, db, dc) for period k from the phase currents [A] and the peer's
        mechanical angle [rad] at the period start."""
        SC, M, cs = self.SC, self.M, self.ctrl.cs
        if k % self.ns == 0:
            s = self.scenario
            t = k * self.dt_s
            t_next = (k + self.ns) * self.dt_s
            cs[SC.C_SPEED_REF] = piecewise(s["speed_ref_time_s"], s["speed_ref_rpm"], t) * TWO_PI / 60.0
            cs[SC.C_SPEED_REF_NEXT] = piecewise(s["speed_ref_time_s"], s["speed_ref_rpm"], t_next) * TWO_PI / 60.0
        m = self.meas
        th = self.track_angle(theta_m_wrapped)
        m[M.S_IA], m[M.S_IB], m[M.S_IC] = ia, ib, ic
        m[M.S_COUNT] = math.floor(th * self.cpr / TWO_PI)
        m[M.S_PERIODS] = k
        da, db, dc, _, _ = SC.control_period(cs, self.ctrl.q, m)
        return da, db, dc


class Trace:
    """Samples (t, speed, id, iq) at the scenario's sample periods."""

    def __init__(self, scenario: dict):
        self.periods = set(int(k) for k in scenario["sample_periods"])
        self.dt_s = float(scenario["control_period_s"])
        self.t_s: list[float] = []
        self.speed_rpm: list[float] = []
        self.id_a: list[float] = []
        self.iq_a: list[float] = []

    def maybe(self, k: int, speed_rad_s: float, id_a: float, iq_a: float) -> None:
        if k in self.periods:
            self.t_s.append(k * self.dt_s)
            self.speed_rpm.append(float(speed_rad_s) * 60.0 / TWO_PI)
            self.id_a.append(float(id_a))
            self.iq_a.append(float(iq_a))


def write_result(out: pathlib.Path, peer: str, version: str, wall_s: float, cpu_s: float, scenario: dict,
                 trace: Trace, **extra) -> None:
    """wall_s / cpu_s: the best wall time and the best CPU time of the simulating thread."""
    sim_s = float(scenario["duration_s"])
    doc = {"peer": peer, "version": version, "python": sys.version.split()[0], "wall_s": wall_s, "sim_s": sim_s,
           "real_time": sim_s / wall_s, "cpu_s": cpu_s, "cpu_real_time": sim_s / cpu_s, "t_s": trace.t_s, "speed_rpm": trace.speed_rpm, "id_a": trace.id_a,
           "iq_a": trace.iq_a, **extra}
    out.write_text(json.dumps(doc, indent=1))


def clock() -> tuple[float, float]:
    """(wall, CPU time of this thread) [s]."""
    return time.perf_counter(), time.thread_time()


def elapsed(start: tuple[float, float]) -> tuple[float, float]:
    now = clock()
    return now[0] - start[0], now[1] - start[1]
