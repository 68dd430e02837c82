"""The drive's torque map against the emulated drive's truth: where does a CAN ride's power go wrong?

    python tools/torque_map_truth.py bag BAG [--windows 0:10,10:20,20:30] [--skip-s 4] [--targets 150,300,450]
    python tools/torque_map_truth.py scan [--map FILE] [--speeds-rpm 2500:3000:20] [--setpoints-nm=-1.5,-1,-0.47]

``bag``: a ride recorded with ``./bike run --config config/bldc_can.yaml ... --record DIR`` (the bag holds
/bike/drive_truth). Per window (sim time, the first ``--skip-s`` left out: the ERG step's settling) the
rider's true power (drive_truth's rider_energy_j over the physics time, a pause left out as the report
does), the true brake power and the
plant's (PlantState torque_em_nm x speed: the map's shaft torque), and the torques: the asked (the
DriveCommands' shaft torque, before the map's inverse), the plant's mean,
the truth's mean T_em, the drive's mean kt Iq, and the map applied to those kt Iq samples at their speed
and to their mean (the two agree when the ride's torque / speed ripple does not matter). The torques are
means of 10 ms samples of ~1 ms means (~0.3 % noise at 450 W: the commutation ripple); the powers are
exact (the physics' energies). ``scan``: the
map's shaft torque against a direct measurement on the emulated dynamometer (a prime mover holding each
speed, bike_controller.drive_torque_map) at speeds and setpoints between its rows.

Found with it (README "A drive's torque map"): a 2800 rpm ERG ride's true T_em / kt Iq is what the
dynamometer measures at 2800 rpm (1.009 at 0.47 N m), but the map of 8 speeds 500 rpm apart
interpolated 1.032 there: the ratio steps by ~3 % between 2600 and 2640 rpm.
"""
from __future__ import annotations

import argparse
import pathlib

import numpy as np

from bike_plant.can.torque_map import load_torque_map
from bike_plant.config import load_config
from bike_session.bags import open_bag

ROOT = pathlib.Path(__file__).resolve().parents[1]
MAP = ROOT / "config" / "bldc_can_torque_map.yaml"
PAUSE_S = 0.1        # the report's (bike_session.report power_accuracy): physics this much ahead of sim time


def _stamp_s(msg) -> float:
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


def read_bag(path) -> tuple[dict, dict, dict]:
    """(plant, truth, asked): arrays of the PlantStates (sim time of the batch, torque, speed), of the
    DriveTruth samples (their /clock stamp and the physics' figures) and of the DriveCommands (the
    shaft torque the controller asked)."""
    plant = {k: [] for k in ("t", "torque_nm", "speed_rad_s")}
    asked = {k: [] for k in ("t", "torque_nm")}
    truth = {k: [] for k in ("t", "physics_s", "true_nm", "est_nm", "rpm", "rider_j", "shaft_j")}
    with open_bag(path) as bag:
        for topic, _, m in bag.messages(["plant_state", "drive_truth", "drive_command"]):
            if topic.endswith("drive_command"):
                asked["t"].append(_stamp_s(m))
                asked["torque_nm"].append(m.torque_cmd_nm)
            elif topic.endswith("plant_state"):
                for k, v in zip(plant, (_stamp_s(m), m.torque_em_nm, m.speed_rad_s)):
                    plant[k].append(v)
            else:
                for k, v in zip(truth, (_stamp_s(m), m.physics_time_s, m.shaft_torque_nm, m.torque_estimate_nm,
                                        m.speed_rpm, m.rider_energy_j, m.shaft_energy_j)):
                    truth[k].append(v)
    return tuple({k: np.asarray(v) for k, v in d.items()} for d in (plant, truth, asked))


def _true_powers(truth: dict, i: int, j: int) -> tuple[float, float, float]:
    """(rider's, brake's) true mean power over samples i..j-1 and the physics time left out: as the
    report counts it, each pair of samples' mean power over their physics time weighted by the sim time
    between their stamps, a pair whose physics ran PAUSE_S longer than sim time left out (a stalled
    plant, the drive holding its setpoint or released: no part of the ride's power)."""
    d_sim = np.diff(truth["t"][i:j])
    d_phys = np.diff(truth["physics_s"][i:j])
    ok = (d_sim > 0) & (d_phys > 0) & (d_phys < d_sim + PAUSE_S)
    rider = np.diff(truth["rider_j"][i:j])[ok] / d_phys[ok] * d_sim[ok]
    brake = -np.diff(truth["shaft_j"][i:j])[ok] / d_phys[ok] * d_sim[ok]
    span = float(np.sum(d_sim[ok]))
    return float(np.sum(rider)) / span, float(np.sum(brake)) / span, float(np.sum(d_phys[~ok]))


def bag_windows(path, windows, skip_s: float, targets, map_path) -> None:
    tmap = load_torque_map(map_path)
    plant, truth, asked = read_bag(path)
    for k, (start, end) in enumerate(windows):
        a, b = start + skip_s, end
        p = (plant["t"] >= a) & (plant["t"] < b)
        i, j = np.searchsorted(truth["t"], a), np.searchsorted(truth["t"], b)
        if not p.any() or j - i < 2:
            print(f"{start:g}-{end:g} s: no data")
            continue
        rider_w, brake_true_w, paused_s = _true_powers(truth, i, j)
        span_w = (truth["rider_j"][j - 1] - truth["rider_j"][i]) / (truth["physics_s"][j - 1] - truth["physics_s"][i])
        brake_plant_w = float(np.mean(-plant["torque_nm"][p] * plant["speed_rad_s"][p]))
        asked_nm = float(np.mean(asked["torque_nm"][(asked["t"] >= a) & (asked["t"] < b)]))
        s = slice(i + 1, j)       # a sample's T_em and kt Iq are of the physics batch before it
        est, rpm = truth["est_nm"][s], truth["rpm"][s]
        mapped = np.mean([tmap.true_nm_at(r, e) for r, e in zip(rpm, est)])
        target = (f" target {targets[k]:g} W: {100.0 * (rider_w / targets[k] - 1.0):+.2f} % (over the whole "
                  f"physics span {100.0 * (span_w / targets[k] - 1.0):+.2f} %)" if k < len(targets) else "")
        print(f"{a:g}-{b:g} s: rider's true power {rider_w:.2f} W{target}; brake true {brake_true_w:.2f} W, "
              f"plant's {brake_plant_w:.2f} W ({100.0 * (brake_plant_w / brake_true_w - 1.0):+.2f} %); "
              f"{np.mean(rpm):.0f} rpm (sd {np.std(rpm):.0f})"
              + (f"; {paused_s:.2f} s paused, left out" if paused_s else ""))
        true_nm = float(np.mean(truth["true_nm"][s]))
        print(f"    torque [N m]: asked {asked_nm:+.4f} (true {100.0 * (true_nm / asked_nm - 1.0):+.2f} %), "
              f"plant {np.mean(plant['torque_nm'][p]):+.4f}, true {true_nm:+.4f}, "
              f"kt Iq {np.mean(est):+.4f} (sd {np.std(est):.3f}); map of the samples {mapped:+.4f}, of their mean "
              f"{tmap.true_nm_at(float(np.mean(rpm)), float(np.mean(est))):+.4f}")


def scan(map_path, speeds, setpoints) -> None:
    from bike_controller import drive_torque_map as DTM

    tmap = load_torque_map(map_path)
    m = DTM.measure_grid(load_config(ROOT / "config" / "bldc_can.yaml"), speeds, setpoints)
    cols = [j for j, t in enumerate(m.setpoint_nm) if t != 0.0]
    print("   rpm | per setpoint: measured true / kt Iq, the map's error " + "  ".join(f"{m.setpoint_nm[j]:g} N m"
                                                                               for j in cols))
    for i, speed in enumerate(m.speed_rpm):
        cells = []
        for j in cols:
            rep, true = m.reported_nm[i, j], m.true_nm[i, j]
            cells.append(f"{true / rep:.4f} {100.0 * (tmap.true_nm_at(speed, rep) / true - 1.0):+.2f} %")
        print(f"  {speed:5.0f} | " + "   ".join(cells))


def main() -> None:
    from bike_controller.drive_torque_map import parse_grid

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    b = sub.add_parser("bag")
    b.add_argument("bag")
    b.add_argument("--windows", default="0:10,10:20,20:30", help="START:END sim-time windows [s], comma separated")
    b.add_argument("--skip-s", type=float, default=4.0, help="left out at each window's start (settling)")
    b.add_argument("--targets", default="", help="ERG targets [W] of the windows, comma separated")
    b.add_argument("--map", default=str(MAP))
    s = sub.add_parser("scan")
    s.add_argument("--map", default=str(MAP))
    s.add_argument("--speeds-rpm", default="2500:3000:20")
    s.add_argument("--setpoints-nm", default="-1.5,-1,-0.47")
    opts = ap.parse_args()
    if opts.what == "bag":
        windows = [tuple(float(x) for x in w.split(":")) for w in opts.windows.split(",")]
        targets = [float(x) for x in opts.targets.split(",")] if opts.targets else []
        bag_windows(opts.bag, windows, opts.skip_s, targets, opts.map)
    else:
        scan(opts.map, parse_grid([opts.speeds_rpm], "--speeds-rpm"), parse_grid([opts.setpoints_nm], "--setpoints-nm"))


if __name__ == "__main__":
    main()
