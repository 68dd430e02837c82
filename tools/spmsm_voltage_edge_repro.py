"""Reproduction: the SPMSM drive emulator (config/spmsm_can.yaml, the drive physics of
./bike torque-map) on a prime mover at a fixed speed, torque setpoint stepped at t = 0.

    python tools/spmsm_voltage_edge_repro.py 500 1 3 0.1    # speed r/min, setpoint N m, s, print step s

Columns (window means of the torque / currents: the 6th-harmonic torque ripple, ~0.7 N m at
id = -11 A, aliases if sampled; |v|/vmax is the window's max): reported kt Iq, the true T_em,
iq, id, the region logic's iq* / id*, region (0 constant torque, 1 flux weakening, 2 MTPV),
limits (1 current, 2 voltage), the plan's margin dv [V] and its floor, |v|/vmax, the drive's
speed estimate and the shaft's speed. Before cea0d8f, 500 r/min +1 N m collapsed at ~0.85 s to
0.42 N m (region 2, id -8.8 A against id* -11.86 A)."""
import sys, math
import numpy as np
from pathlib import Path
from bike_plant.config import load_config
from bike_controller.drive_emulator import make_drive_model
from bike_controller import drive_torque_map as DTM
from bike_controller import spmsm_control as SC
from bike_plant import spmsm as M

ROOT = Path(__file__).resolve().parents[1]
cfg = load_config(ROOT / "config" / "spmsm_can.yaml")

def run(speed, setpoint, dur=3.0, every=0.05, quiet=False):
    model = make_drive_model(DTM.prime_mover_config(cfg, speed), "plant", load_kind="prime_mover")
    iq = setpoint / model.params.torque_constant_nm_per_a
    q = model.q
    vmax = q[SC.Q_VMAX]
    rows = []
    n = int(round(dur / 1e-3))
    acc_t = []
    for k in range(n):
        model.step(1e-3, iq, enabled=True)
        cs = model.cs
        st = model.plant.state
        rows.append((k * 1e-3 + 1e-3, model.torque_estimate_nm, model.torque_em_nm, model.iq_a, model.id_a,
                     cs[SC.C_IQ_REF], cs[SC.C_ID_REF], cs[SC.C_REGION], cs[SC.C_LIMITS], cs[SC.C_DV],
                     cs[SC.C_DV_FLOOR_V], math.hypot(cs[SC.C_VD], cs[SC.C_VQ]) / vmax,
                     cs[SC.C_SPEED_EST] * 9.5492966, st[M.S_OMEGA] * 9.5492966))
    a = np.array(rows)
    if not quiet:
        print(f"--- {speed} r/min, setpoint {setpoint:+} N m ---")
        print("(T_rep T_true iq id: window means; |v|/vm: window max)")
        print("   t   T_rep  T_true   iq     id    iq*    id*   reg lim  dv    floor |v|/vm spd_est  spd")
        step = int(round(every / 1e-3))
        for j in range(step - 1, len(a), step):
            r = a[j].copy()
            r[1:5] = a[j - step + 1:j + 1, 1:5].mean(axis=0)   # window means (torque ripple aliases)
            r[11] = a[j - step + 1:j + 1, 11].max()
            print(f"{r[0]:5.2f} {r[1]:6.3f} {r[2]:6.3f} {r[3]:6.3f} {r[4]:6.2f} {r[5]:6.3f} {r[6]:6.2f} "
                  f"{int(r[7]):3d} {int(r[8]):3d} {r[9]:5.3f} {r[10]:5.3f} {r[11]:5.3f} {r[12]:7.2f} {r[13]:7.2f}")
    return a


if __name__ == "__main__":
    args = [float(x) for x in sys.argv[1:]]
    speed, sp = args[0], args[1]
    dur = args[2] if len(args) > 2 else 3.0
    every = args[3] if len(args) > 3 else 0.05
    run(speed, sp, dur, every)
