"""`./bike bench` peers block: the same PMSM scenario on our SPMSM and on motulator 0.18 and
gym-electric-motor 3.0 (optional extras in their own virtual environments: `make peers`).

Scenario (:func:`scenario`): the surface PMSM of paper 001 (section 6 parameters from
config/spmsm_default.yaml: 6 pole pairs, Rs, Ld = Lq, lambda, J, B, 24 V link), the ideal
Eq. 1-6 machine (no EMF harmonics, cogging, Coulomb friction or dead time: the peers model
none of them), average inverter model, from standstill: speed command 150 r/min at t = 0
(inside the constant-torque region, so the comparison tests the machine models rather than
the flux-weakening logic's reaction to voltage saturation), 1 N m load-torque step at
t = 0.5 s (the paper's load step), 1 s simulated, current loop 100 us, speed loop 1 ms.
Control: the project's PI family (bike_controller.spmsm_control, pole placement) on both
sides - our offline runner on our plant (bike_plant.spmsm), and the same kernel imported
by the peer scripts (tools/peers/) driving the peer's machine model each 100 us (GEM's
bundled controllers do not run on this machine, and the same law on both sides makes the
result difference a property of the plant models alone).

Figures: real-time factor of each side (wall clock, `*_real_time`, and per CPU second of
the simulating thread, `*_cpu_real_time`), speed-up = ours / peer vs the issue's targets
(>= 100x gym-electric-motor, >= 1000x motulator), and the result difference vs the 5 %
target. The speed-up is taken on CPU time: this machine is shared, and a peer's run of
several seconds cannot pick a quiet moment the way a best-of-N of our 3 ms run can (both
are single-threaded, so on an idle machine CPU and wall time agree). Result difference: speed, max over t = 0.2..1 s of |w_peer - w_ours| / |w_ours|; currents, max over all
sample times of |i_dq,peer - i_dq,ours| / max_t |i_dq,ours| (the current is near zero at
no load, so it is compared against its peak).
"""
from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np

PEERS = {
    # name: (display name, venv directory under BIKE_PEERS_DIR, runner in tools/peers/, speed-up target)
    "motulator": ("motulator", "motulator", "run_motulator.py", 1000.0),
    "gem": ("gym-electric-motor", "gem", "run_gem.py", 100.0),
}
TARGET_RESULT_DIFF = 0.05
SPEED_COMPARE_FROM_S = 0.2
SAMPLE_EVERY_PERIODS = 500          # 50 ms
TRACE_KEYS = ("t_s", "speed_rpm", "id_a", "iq_a")


def repo_root() -> pathlib.Path:
    from bike_session.cli import repo_root as root
    return root()


def peers_dir() -> pathlib.Path:
    return pathlib.Path(os.environ.get("BIKE_PEERS_DIR", pathlib.Path.home() / ".cache" / "bike-peers"))


def scenario_config(base: pathlib.Path | None = None) -> dict:
    """config/spmsm_default.yaml turned into the peer scenario: ideal machine, average
    inverter, dynamometer load step, start at rest, PI family."""
    from bike_plant.config import load_config

    cfg = load_config(base or repo_root() / "config" / "spmsm_default.yaml")
    cfg["spmsm"] = dict(cfg.get("spmsm") or {}, emf_harmonic_5=0.0, emf_harmonic_7=0.0, cogging_torque_nm=0.0,
                        dry_friction_nm=0.0, rs_scale=1.0, inductance_scale=1.0, flux_scale=1.0)
    cfg["inverter"] = dict(cfg.get("inverter") or {}, model="average", dead_time_s=0.0)
    cfg["mechanics"] = dict(cfg.get("mechanics") or {}, speed0_rpm=0.0)
    cfg["controller"] = dict(cfg.get("controller") or {}, family="pi", speed_ref0_rpm=0.0)
    return cfg


def scenario(duration_s: float = 1.0, speed_ref_rpm: float = 150.0, load_step_s: float = 0.5,
             load_torque_nm: float = 1.0, sample_every_periods: int = SAMPLE_EVERY_PERIODS) -> dict:
    """The scenario both sides run, as plain JSON-able data (the peer scripts read it)."""
    cfg = scenario_config()
    # a torque source (dyno_mode drive), as the peers' load is: the passive brake's steep slope at
    # standstill would also put the shaft on its slower stiff path for the whole run
    cfg["load"] = dict(cfg.get("load") or {}, kind="dynamometer", dyno_mode="drive", dyno_time_s=[0.0, load_step_s],
                       dyno_torque_nm=[0.0, load_torque_nm])
    cfg = json.loads(json.dumps(cfg, default=str))
    dt = float(cfg.get("control_period_s", 1e-4))
    n = int(round(duration_s / dt))
    m, inv, mech = cfg["spmsm"], cfg["inverter"], cfg["mechanics"]
    return {
        "repo_root": str(repo_root()),
        "duration_s": float(duration_s),
        "control_period_s": dt,
        "speed_loop_periods": int(cfg["controller"].get("speed_loop_periods", 10)),
        "speed_ref_time_s": [0.0],
        "speed_ref_rpm": [float(speed_ref_rpm)],
        "load_time_s": [0.0, float(load_step_s)],
        "load_torque_nm": [0.0, float(load_torque_nm)],
        "sample_periods": list(range(sample_every_periods, n + 1, sample_every_periods)),
        "machine": {
            "pole_pairs": int(m["pole_pairs"]), "rs_ohm": float(m["rs_ohm"]),
            "inductance_h": float(m["inductance_h"]), "flux_linkage_vs": float(m["flux_linkage_vs"]),
            "inertia_kgm2": float(mech.get("inertia_kgm2", 0.01)), "friction_nms": float(mech.get("friction_nms", 0.005)),
            "dc_link_v": float(inv["dc_link_v"]),
        },
        "config": cfg,
    }


def _piecewise_fn(times, values):
    times = np.asarray(times, dtype=float)
    values = np.asarray(values, dtype=float)

    def fn(t):
        idx = np.searchsorted(times, np.asarray(t, dtype=float) + 1e-12, side="right") - 1
        return np.where(idx >= 0, values[np.clip(idx, 0, None)], 0.0)
    return fn


def run_ours(sc: dict, repeats: int = 3) -> dict:
    """Our SPMSM (bike_plant.spmsm) under our PI on the scenario: the result document of
    the peer scripts (peer, wall_s, sim_s, real_time, t_s, speed_rpm, id_a, iq_a) plus
    compile_s (first call: JIT compile or cache load, excluded from wall_s)."""
    from bike_controller.spmsm_control import run_spmsm_offline

    cfg = sc["config"]
    ref = _piecewise_fn(sc["speed_ref_time_s"], sc["speed_ref_rpm"])
    dur = sc["duration_s"]
    t0 = time.perf_counter()
    run_spmsm_offline(cfg, min(0.01, dur), speed_ref_fn=ref, controller="pi", record_every=1000)
    compile_s = time.perf_counter() - t0
    out = run_spmsm_offline(cfg, dur, speed_ref_fn=ref, controller="pi", record_every=1)
    best = best_cpu = float("inf")
    for _ in range(max(1, repeats)):
        t0, c0 = time.perf_counter(), time.thread_time()
        run_spmsm_offline(cfg, dur, speed_ref_fn=ref, controller="pi", record_every=1_000_000)
        best = min(best, time.perf_counter() - t0)
        best_cpu = min(best_cpu, time.thread_time() - c0)
    # row r is the state after period r, i.e. at t = (r + 1) T: the state at k T is row k - 1
    rows = np.asarray(sc["sample_periods"], dtype=int) - 1
    return {"peer": "bike (ours)", "version": "", "python": sys.version.split()[0], "wall_s": best, "sim_s": dur,
            "real_time": dur / best, "cpu_s": best_cpu, "cpu_real_time": dur / best_cpu, "compile_s": compile_s,
            "t_s": [float(x) for x in (rows + 1) * sc["control_period_s"]],
            "speed_rpm": [float(x) for x in out["speed_rpm"][rows]],
            "id_a": [float(x) for x in out["id"][rows]],
            "iq_a": [float(x) for x in out["iq"][rows]]}


def compare(ours: dict, peer: dict) -> dict:
    """Max relative differences of a peer's traces against ours (module docstring)."""
    t = np.asarray(ours["t_s"])
    if len(peer.get("t_s", [])) != len(t) or not np.allclose(peer["t_s"], t, atol=1e-9):
        raise ValueError(f"{peer.get('peer')}: sample times differ from ours")
    w_o, w_p = np.asarray(ours["speed_rpm"]), np.asarray(peer["speed_rpm"])
    sel = t >= SPEED_COMPARE_FROM_S - 1e-9
    speed = float(np.max(np.abs(w_p[sel] - w_o[sel]) / np.maximum(np.abs(w_o[sel]), 1e-9)))
    i_o = np.asarray(ours["id_a"]) + 1j * np.asarray(ours["iq_a"])
    i_p = np.asarray(peer["id_a"]) + 1j * np.asarray(peer["iq_a"])
    current = float(np.max(np.abs(i_p - i_o)) / max(float(np.max(np.abs(i_o))), 1e-9))
    return {"speed_max_rel_diff": speed, "current_max_rel_diff": current}


def peer_python(name: str) -> pathlib.Path | None:
    py = peers_dir() / PEERS[name][1] / "bin" / "python"
    return py if py.exists() else None


def run_peer(name: str, sc: dict, timeout_s: float = 900.0) -> dict:
    """Run tools/peers/<runner> in the peer's venv; its JSON document. Raises
    FileNotFoundError when the peer is not installed, RuntimeError when it fails."""
    py = peer_python(name)
    if py is None:
        raise FileNotFoundError(str(peers_dir() / PEERS[name][1]))
    script = repo_root() / "tools" / "peers" / PEERS[name][2]
    with tempfile.TemporaryDirectory() as tmp:
        sc_path = pathlib.Path(tmp) / "scenario.json"
        out_path = pathlib.Path(tmp) / "result.json"
        sc_path.write_text(json.dumps(sc))
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME")}
        proc = subprocess.run([str(py), str(script), str(sc_path), str(out_path)], capture_output=True, text=True,
                              timeout=timeout_s, env=env, cwd=str(script.parent))
        if proc.returncode != 0 or not out_path.exists():
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-5:]
            raise RuntimeError(f"{script.name} exited with {proc.returncode}: " + " | ".join(tail))
        return json.loads(out_path.read_text())


def bench_peers(show, figures: dict, quick: bool = False) -> None:
    """Print and store the peers block (see module docstring). Timing on a shared machine:
    our side is timed (best of 3) before AND after the peers run and the best is kept; each
    peer runs the scenario twice in its process (best kept; once with quick)."""
    sc = scenario()
    sc["peer_repeats"] = 1 if quick else 2
    ours = run_ours(sc, repeats=2 if quick else 3)
    results = {}
    for name, (label, env_dir, _script, _target) in PEERS.items():
        try:
            results[name] = run_peer(name, sc)
        except FileNotFoundError:
            results[name] = (f"  {label}: skipped (not installed; `make peers` installs it into "
                             f"{peers_dir() / env_dir}; BIKE_PEERS_DIR to change)")
        except (RuntimeError, subprocess.TimeoutExpired) as exc:
            results[name] = f"  {label}: failed ({exc})"
    if any(isinstance(r, dict) for r in results.values()):
        again = run_ours(sc, repeats=2 if quick else 3)
        for key, rt in (("wall_s", "real_time"), ("cpu_s", "cpu_real_time")):
            if again[rt] > ours[rt]:
                ours.update({key: again[key], rt: again[rt]})
    figures["peers_ours_pi_real_time"] = ours["real_time"]
    figures["peers_ours_pi_cpu_real_time"] = ours["cpu_real_time"]
    figures["peers_ours_pi_compile_s"] = ours["compile_s"]
    show(f"peers: same scenario (paper 001 SPMSM, ideal machine, average inverter, our PI on every side, 150 r/min "
         f"from rest, 1 N m at 0.5 s, {sc['duration_s']:g} s): ours {ours['real_time']:.0f}x real time "
         f"({ours['cpu_real_time']:.0f}x per CPU second; JIT compile / cache load {ours['compile_s']:.1f} s, not "
         f"included)")
    for name, (label, _env_dir, _script, target) in PEERS.items():
        peer = results[name]
        if not isinstance(peer, dict):
            show(peer)
            continue
        diff = compare(ours, peer)
        speedup = ours["cpu_real_time"] / peer["cpu_real_time"]
        figures[f"peers_{name}_real_time"] = peer["real_time"]
        figures[f"peers_{name}_cpu_real_time"] = peer["cpu_real_time"]
        figures[f"peers_{name}_speedup"] = speedup
        figures[f"peers_{name}_speedup_ratio_to_target"] = speedup / target
        figures[f"peers_{name}_speed_max_rel_diff"] = diff["speed_max_rel_diff"]
        figures[f"peers_{name}_current_max_rel_diff"] = diff["current_max_rel_diff"]
        worst = max(diff.values())
        show(f"  {label} {peer.get('version', '')} (Python {peer.get('python', '?')}, {peer.get('solver', '?')}): "
             f"{peer['real_time']:.3f}x real time ({peer['cpu_real_time']:.3f}x per CPU second); ours is "
             f"{speedup:.0f}x faster per CPU second (target >= {target:.0f}x: ratio "
             f"{speedup / target:.2f}); results: speed max {diff['speed_max_rel_diff'] * 100:.2f} % "
             f"(t = {SPEED_COMPARE_FROM_S:g}..{sc['duration_s']:g} s), currents max "
             f"{diff['current_max_rel_diff'] * 100:.2f} % of peak (target <= {TARGET_RESULT_DIFF * 100:.0f} %: ratio "
             f"{worst / TARGET_RESULT_DIFF:.2f})")


if __name__ == "__main__":  # pragma: no cover - manual run
    bench_peers(print, {})
