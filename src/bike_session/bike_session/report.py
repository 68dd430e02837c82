"""Summary of a recorded session: energies, powers, peaks, faults, message counts.

Definitions (PlantState samples i = 0..n-1 sorted by header time t_i):

- ``duration_s``           t_{n-1} - t_0 (bag time span if there is no PlantState)
- ``mean_braking_power_w`` mechanical power taken by the machine, -T_em * w: per batch
  -torque_em_nm[i] * (speed_rad_s[i-1] + speed_rad_s[i]) / 2 (torque_em_nm[i] is the mean
  over the batch ending at t_i), weighted by t_i - t_{i-1}. Positive while braking.
- ``mean_rider_power_w``   (energy_mech_in_j[n-1] - energy_mech_in_j[0]) / duration: power
  of the rider / load into the shaft, from the plant's ledger.
- ``energy_battery_j`` / ``energy_resistor_j`` / ``energy_loss_j`` / ``energy_mech_in_j``:
  last - first of the cumulative ledger; ``*_wh`` = J / 3600.
- ``peak_phase_current_a`` max |i| over phase_current_a and current_samples_a.
- ``interlock_blanked``    last interlock_blanked_count (cumulative since plant start).
- ``fault_batches``        number of PlantState messages with each FAULT_* bit set;
  ``timeouts`` = fault_batches['command_timeout'].
- ``messages``             number of messages per topic.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

from bike_session.bags import BagError, open_bag, plant_state_array, plant_state_rows, read_topic_stamped

FAULT_BITS = {
    "interlock": 1,
    "command_timeout": 2,
    "overvoltage": 4,
    "bad_command": 8,
    "drive_lost": 16,
    "recorder_lost": 32,
}
SESSION_STATES = {0: "WAITING", 1: "RUNNING", 2: "DONE"}


def summarise(bag_path) -> dict:
    """Numbers of one recorded session (see the module docstring). Raises BagError."""
    with open_bag(bag_path) as bag:
        counts = bag.message_counts()
        plant_topic = _find(bag, "plant_state")
        status_topic = _find(bag, "session_status")
        ps = plant_state_rows(m for _, _, m in bag.messages([plant_topic])) if plant_topic else plant_state_rows([])
        last_status = None
        if status_topic:
            for _, _, m in bag.messages([status_topic]):
                last_status = m
        bag_duration = bag.duration_s

    out: dict = {
        "bag": str(bag_path),
        "messages": dict(sorted(counts.items())),
        "plant_states": int(ps.size),
        "duration_s": bag_duration,
        "mean_braking_power_w": None,
        "mean_rider_power_w": None,
        "energy_mech_in_j": None,
        "energy_battery_j": None,
        "energy_battery_wh": None,
        "energy_resistor_j": None,
        "energy_resistor_wh": None,
        "energy_loss_j": None,
        "peak_phase_current_a": None,
        "interlock_blanked": None,
        "timeouts": None,
        "fault_batches": None,
        "end_of_run": False,
        "final_soc": None,
        "session_state": SESSION_STATES.get(last_status.state, str(last_status.state)) if last_status else None,
        "profile_name": last_status.profile_name if last_status else None,
    }
    if ps.size == 0:
        return out
    t = ps["time_s"]
    duration = float(t[-1] - t[0])
    out["duration_s"] = duration
    if ps.size > 1 and duration > 0:
        dt = np.diff(t)
        w_mid = 0.5 * (ps["speed_rad_s"][1:] + ps["speed_rad_s"][:-1])
        p_brake = -ps["torque_em_nm"][1:] * w_mid
        out["mean_braking_power_w"] = float(np.sum(p_brake * dt) / duration)
        out["mean_rider_power_w"] = float((ps["energy_mech_in_j"][-1] - ps["energy_mech_in_j"][0]) / duration)
    for key in ("energy_mech_in_j", "energy_battery_j", "energy_resistor_j", "energy_loss_j"):
        out[key] = float(ps[key][-1] - ps[key][0])
    out["energy_battery_wh"] = out["energy_battery_j"] / 3600.0
    out["energy_resistor_wh"] = out["energy_resistor_j"] / 3600.0
    out["peak_phase_current_a"] = float(np.max(ps["phase_current_peak_a"]))
    out["interlock_blanked"] = int(ps["interlock_blanked_count"][-1])
    out["fault_batches"] = {name: int(np.count_nonzero(ps["faults"] & bit)) for name, bit in FAULT_BITS.items()}
    out["timeouts"] = out["fault_batches"]["command_timeout"]
    out["end_of_run"] = bool(np.any(ps["end_of_run"]))
    out["final_soc"] = float(ps["battery_soc"][-1])
    return out


def _find(bag, name: str) -> str | None:
    try:
        return bag.resolve(name)
    except BagError:
        return None


def _fmt(value, unit: str = "", digits: int = 3) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        return f"{value:.{digits}f}{(' ' + unit) if unit else ''}"
    return f"{value}{(' ' + unit) if unit else ''}"


def format_summary(summary: dict) -> str:
    """Human-readable text of :func:`summarise`'s dict."""
    s = summary
    lines = [f"bag: {s.get('bag')}"]
    if s.get("profile_name") is not None:
        lines.append(f"profile: {s['profile_name']}  (session {s.get('session_state')})")
    lines += [
        f"duration:              {_fmt(s.get('duration_s'), 's')}  ({s.get('plant_states', 0)} plant states,"
        f" end_of_run {'yes' if s.get('end_of_run') else 'no'})",
        f"mean braking power:    {_fmt(s.get('mean_braking_power_w'), 'W', 2)}",
        f"mean rider power:      {_fmt(s.get('mean_rider_power_w'), 'W', 2)}",
        f"energy into battery:   {_fmt(s.get('energy_battery_j'), 'J', 2)}  ({_fmt(s.get('energy_battery_wh'), 'Wh', 4)})",
        f"energy into resistor:  {_fmt(s.get('energy_resistor_j'), 'J', 2)}  ({_fmt(s.get('energy_resistor_wh'), 'Wh', 4)})",
        f"energy losses:         {_fmt(s.get('energy_loss_j'), 'J', 2)}",
        f"peak phase current:    {_fmt(s.get('peak_phase_current_a'), 'A', 2)}",
        f"final battery SOC:     {_fmt(s.get('final_soc'), '', 4)}",
        f"interlock blanked:     {_fmt(s.get('interlock_blanked'))}",
        f"command timeouts:      {_fmt(s.get('timeouts'))} batches",
    ]
    faults = s.get("fault_batches") or {}
    active = {k: v for k, v in faults.items() if v}
    lines.append("fault batches:         " + (", ".join(f"{k} {v}" for k, v in active.items()) if active else "none"))
    lines.append("messages:")
    for topic, count in (s.get("messages") or {}).items():
        lines.append(f"  {topic:<32} {count}")
    return "\n".join(lines)


def main(argv=None) -> int:
    """``bike report BAG [--json]``: print the summary; BagError -> one error line, exit 2."""
    parser = argparse.ArgumentParser(prog="bike report", description="Summarise a recorded bike session.")
    parser.add_argument("bag", help="bag directory (rosbag2, MCAP or sqlite3) or .mcap file")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--out", help="also write summary.json, summary.txt and charts (PNG) into this folder")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        summary = summarise(args.bag)
        written = write_outputs(args.bag, summary, args.out) if args.out else []
    except BagError as exc:
        print(f"bike report: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"bike report: error: cannot write to {args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(json.dumps(summary, indent=2) if args.json else format_summary(summary))
    for path in written:
        print(f"wrote {path}")
    return 0


def write_outputs(bag_path, summary: dict, out_dir) -> list[pathlib.Path]:
    """summary.json, summary.txt and session.png (time series of the plant and the command)."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    (out / "summary.txt").write_text(format_summary(summary) + "\n")
    written += [out / "summary.json", out / "summary.txt"]
    ps = plant_state_array(bag_path) if summary.get("plant_states") else None
    try:
        commands = read_topic_stamped(bag_path, "command")
    except BagError:
        commands = []
    if ps is None and not commands:
        return written
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 1, figsize=(9, 10), sharex=True)
    if commands:
        tc = [t * 1e-9 for t, _ in commands]
        axes[0].step(tc, [m.command for _, m in commands], where="post", label="command")
        axes[0].set_ylabel("command [0..1]")
    if ps is not None:
        t = ps["time_s"]
        axes[1].plot(t, ps["speed_rpm"], label="speed")
        axes[1].set_ylabel("speed [rpm]")
        axes[2].plot(t, ps["torque_em_nm"], label="T_em")
        axes[2].plot(t, ps["load_torque_nm"], label="T_load")
        axes[2].set_ylabel("torque [N m]")
        axes[2].legend(loc="best")
        for key in ("energy_mech_in_j", "energy_battery_j", "energy_resistor_j", "energy_loss_j"):
            axes[3].plot(t, ps[key] - ps[key][0], label=key.replace("energy_", "").replace("_j", ""))
        axes[3].set_ylabel("energy [J]")
        axes[3].legend(loc="best")
    axes[-1].set_xlabel("sim time [s]")
    fig.suptitle(f"{summary.get('profile_name') or ''} {pathlib.Path(str(bag_path)).name}")
    fig.tight_layout()
    fig.savefig(out / "session.png", dpi=100)
    plt.close(fig)
    written.append(out / "session.png")
    return written


if __name__ == "__main__":
    sys.exit(main())
