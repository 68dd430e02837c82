"""README "ERG smoothing": a 150 -> 300 W ERG step on the default BLDC bike, offline (the nodes'
batch exchange, 1 ms batches), with modes.erg_ramp_w_per_s off, 100, 50 and 25 W/s. Prints the
rider's peak power over half crank turns after the step and the time after which every half
turn's mean stays within 5 % of 300 W (each half turn stamped at its end; `start`: at its start).

    source tools/env.sh && python tools/erg_ramp_step.py [end|start]
"""
import sys

import numpy as np

from bike_plant.config import load_config
from bike_controller.closed_loop import run_offline
from bike_controller.modes import MODE_ERG
from bike_controller.session_control import ModedController
from bike_session.profiles import mode_units_from_config

STAMP = sys.argv[1] if len(sys.argv) > 1 else "end"
T_STEP = 15.0            # s at 150 W first: the session's 57 rpm start is long over


def main() -> None:
    for ramp in (0.0, 100.0, 50.0, 25.0):
        cfg = load_config("config/bldc_default.yaml")
        cfg["modes"] = dict(cfg.get("modes") or {}, erg_ramp_w_per_s=ramp)
        pmax = mode_units_from_config(cfg).erg_power_max_w
        gear = float(cfg["load"]["gear_ratio"])
        out = run_offline(cfg, T_STEP + 12.0, lambda t: ((150.0 if t < T_STEP else 300.0) / pmax, MODE_ERG),
                          batch_periods=20, record_every=1, controller=ModedController(cfg, batch_periods=20))
        t, e, rpm = out["time_s"], out["energy_mech_in_j"], out["speed_rpm"]
        turns = np.concatenate([[0.0], np.cumsum(0.5 * (rpm[1:] + rpm[:-1]) / gear / 60.0 * np.diff(t))])
        edges = np.flatnonzero(np.diff(np.floor(turns * 2.0))) + 1
        stamp = np.array([t[b] if STAMP == "end" else t[a] for a, b in zip(edges[:-1], edges[1:])])
        power = np.array([(e[b] - e[a]) / (t[b] - t[a]) for a, b in zip(edges[:-1], edges[1:])])
        after = stamp > T_STEP
        outside = after & (np.abs(power - 300.0) > 0.05 * 300.0)
        settle = stamp[outside].max() - T_STEP if outside.any() else 0.0
        print(f"ramp {ramp:3.0f} W/s: peak {power[after].max():.0f} W, within 5 % for good after {settle:.1f} s")


if __name__ == "__main__":
    main()
