"""`./bike bench` memory block: the whole node graph (plant, controller, session, recorder:
separate processes over DDS) in lockstep with a large batch for a long simulated session,
with every node's resident memory sampled over time.

Figures (issue 6: every node under 200 MB RSS and flat over a 1 h simulated session,
recorder memory bounded, compile time apart from steady state):
- memory_<node>_max_rss_mb: the largest RSS of the node's process tree [MB]: the larger of the
  sampled RSS and the processes' own peak (VmHWM, last read while they ran);
- memory_<node>_rss_slope_mb_per_sim_h: least-squares slope of RSS against simulated time
  over the steady part (after the first 20 % of simulated time: imports, JIT compile / cache
  load, DDS discovery and the first allocations are over), in MB per simulated hour;
- memory_<node>_max_rss_ratio_to_limit: max RSS / 200 MB (<= 1 meets the target);
- memory_sim_s, memory_wall_s, memory_real_time (steady state), memory_startup_s (wall time
  from launch to the first simulated second: process start, imports, JIT compile or numba
  cache load, discovery), memory_bag_mb.
RSS is read from /proc/<pid>/status (VmRSS) for each node's process and its children.
- memory_<node>_max_pss_mb / _max_uss_mb: the node process's largest PSS (shared pages divided
  among the processes that map them) and USS (its private pages), from smaps_rollup: what the
  node costs the host, where RSS counts every shared library page it has mapped in full. The
  loop nodes drop numba's code generator (LLVM, ~65 MB of RSS) once their kernels are loaded
  (bike_plant.memory).
"""
from __future__ import annotations

import os
import pathlib
import tempfile
import threading
import time

TARGET_RSS_MB = 200.0
CLEAN_EXIT = (0, -2, 130)             # as bike_session.launcher.run: 0 or stopped by SIGINT
SLOPE_MIN_SIM_S = 600.0               # shorter runs: the slope is start-up settling, not a trend
SAMPLE_EVERY_WALL_S = 1.0
STEADY_FROM = 0.2


def _children(pid: int) -> list[int]:
    out = []
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            try:
                with open(f"/proc/{pid}/task/{task}/children") as f:
                    out += [int(x) for x in f.read().split()]
            except OSError:
                pass
    except OSError:
        pass
    return out


def status_mb(pid: int, fields=("VmRSS",)) -> tuple[float, ...]:
    """Memory fields of /proc/<pid>/status [MB], each summed over the process and its
    descendants (0 if it is gone), from one read of each status file. "VmRSS": resident set
    size; "VmHWM": its peak so far (the kernel's high-water mark, which a 1 s sampling of
    VmRSS can miss: a node's start-up peak lasts a fraction of a second)."""
    totals_kb = [0] * len(fields)
    prefixes = tuple(f + ":" for f in fields)
    stack = [pid]
    seen = set()
    while stack:
        p = stack.pop()
        if p in seen:
            continue
        seen.add(p)
        try:
            with open(f"/proc/{p}/status") as f:
                for line in f:
                    if line.startswith(prefixes):
                        totals_kb[prefixes.index(line[:line.index(":") + 1])] += int(line.split()[1])
        except OSError:
            continue
        stack += _children(p)
    return tuple(kb / 1024.0 for kb in totals_kb)


def rss_mb(pid: int, field: str = "VmRSS") -> float:
    """status_mb of one field: the resident set size (default) of a process and its descendants."""
    return status_mb(pid, (field,))[0]


def slope_per_hour(samples: list[tuple[float, float]]) -> float:
    """Least-squares slope of (sim_s, value) pairs, per simulated hour (0 with < 2 points)."""
    if len(samples) < 2:
        return 0.0
    n = len(samples)
    mx = sum(s for s, _ in samples) / n
    my = sum(v for _, v in samples) / n
    sxx = sum((s - mx) ** 2 for s, _ in samples)
    if sxx <= 0.0:
        return 0.0
    sxy = sum((s - mx) * (v - my) for s, v in samples)
    return sxy / sxx * 3600.0


def summarise(series: dict[str, list[tuple[float, float]]], sim_s: float, shares: dict | None = None) -> dict[str, dict]:
    """Per node: max RSS, steady-state slope (MB per simulated hour), first / last steady RSS,
    and from shares[node] = {'pss': max, 'uss': max, 'hwm': peak RSS} (NaN without) the largest
    PSS and USS; the max RSS takes the peak when it is larger than every sample.
    series[node] = [(sim_s, rss_mb), ...]."""
    out = {}
    for name, pts in series.items():
        peak = (shares or {}).get(name, {})
        live = [(s, v) for s, v in pts if v > 0.0]
        steady = [(s, v) for s, v in live if s >= STEADY_FROM * sim_s]
        out[name] = {
            "max_rss_mb": max([v for _, v in live] + [peak.get("hwm", 0.0)], default=0.0),
            "slope_mb_per_sim_h": slope_per_hour(steady),
            "steady_first_mb": steady[0][1] if steady else 0.0,
            "steady_last_mb": steady[-1][1] if steady else 0.0,
            "samples": len(live),
            "max_pss_mb": peak.get("pss", float("nan")),
            "max_uss_mb": peak.get("uss", float("nan")),
        }
    return out


def run_memory(sim_s: float, batch_periods: int = 200, config: pathlib.Path | None = None,
               progress=None) -> dict:
    """Run the recorded lockstep graph for sim_s simulated seconds, sampling RSS."""
    import rclpy
    from rosgraph_msgs.msg import Clock

    from bike_plant.config import default_config_path
    from bike_plant.memory import memory_mb

    from bike_session import launcher
    from bike_session.bench import _config_with, spin_in_background
    from bike_session.cli import RECORDER_WINDOW_BATCHES, default_launch_file

    base = pathlib.Path(config or default_config_path())
    # a private DDS domain, as `./bike run` takes: another graph on this host must not drive
    # this one's /clock
    from bike_session import domains
    domains.ensure_private_domain("memory bench")
    clock = {"sim": 0.0}
    first_progress = {}
    with tempfile.TemporaryDirectory(prefix="bike_bench_memory_") as tmp:
        tmp_path = pathlib.Path(tmp)
        cfg_path = _config_with(batch_periods, sim_s, base, tmp_path)
        nodes = launcher.parse_launch(str(default_launch_file()), {
            "config": str(cfg_path), "duration": repr(float(sim_s)), "record": "true", "record_dir": str(tmp_path),
            "bag_name": "memory", "recorder_window": str(RECORDER_WINDOW_BATCHES)})
        context = rclpy.Context()
        rclpy.init(context=context)
        node = rclpy.create_node("bench_memory_clock", context=context)

        def on_clock(m):
            clock["sim"] = m.clock.sec + m.clock.nanosec * 1e-9
            if "t" not in first_progress and clock["sim"] >= 1.0:
                first_progress["t"] = time.perf_counter()

        node.create_subscription(Clock, "/clock", on_clock, 10)
        executor = rclpy.executors.SingleThreadedExecutor(context=context)
        executor.add_node(node)
        stop_spinning = spin_in_background(executor)
        series: dict[str, list[tuple[float, float]]] = {}
        shares: dict[str, dict] = {}
        walls: list[tuple[float, float]] = []
        codes = {}
        log_path = tmp_path / "nodes.log"
        with open(log_path, "w") as sink:
            graph = launcher.Launcher(nodes, stdout=sink)
            started = time.perf_counter()
            graph.start()
            done = threading.Event()
            result = {}

            def waiter():
                result["codes"] = graph.wait(timeout_s=sim_s * 10 + 600)
                done.set()

            threading.Thread(target=waiter, daemon=True).start()
            last_report = started
            while not done.wait(SAMPLE_EVERY_WALL_S):
                now = time.perf_counter()
                sim = clock["sim"]
                walls.append((now, sim))
                for name, proc in graph.procs.items():
                    if proc.poll() is None:
                        rss, hwm = status_mb(proc.pid, ("VmRSS", "VmHWM"))
                        series.setdefault(name, []).append((sim, rss))
                        m = memory_mb(proc.pid)
                        if m:
                            peak = shares.setdefault(name, {"pss": 0.0, "uss": 0.0, "hwm": 0.0})
                            peak["pss"] = max(peak["pss"], m["pss"])
                            peak["uss"] = max(peak["uss"], m["uss"])
                            peak["hwm"] = max(peak["hwm"], hwm)
                if progress is not None and now - last_report >= 30.0:
                    last_report = now
                    progress(f"  memory run: {sim:.0f} / {sim_s:.0f} s simulated, {now - started:.0f} s wall")
            codes = result.get("codes", {})
        wall_total = time.perf_counter() - started
        stop_spinning()
        rclpy.try_shutdown(context=context)
        log_tail = log_path.read_text(errors="replace").splitlines()[-8:]
        bag = tmp_path / "memory"
        bag_mb = sum(f.stat().st_size for f in bag.rglob("*") if f.is_file()) / 1e6 if bag.exists() else 0.0
    steady = [(w, s) for w, s in walls if s >= STEADY_FROM * sim_s]
    real_time = ((steady[-1][1] - steady[0][1]) / (steady[-1][0] - steady[0][0])
                 if len(steady) >= 2 and steady[-1][0] > steady[0][0] else float("nan"))
    return {
        "sim_s": float(clock["sim"]), "requested_sim_s": float(sim_s), "batch_periods": batch_periods,
        "wall_s": wall_total, "real_time": real_time,
        "startup_s": first_progress.get("t", float("nan")) - started,
        "bag_mb": bag_mb, "exit_codes": codes, "nodes": summarise(series, sim_s, shares), "log_tail": log_tail,
    }


def bench_memory(show, figures: dict, sim_s: float, batch_periods: int = 200) -> None:
    """Print and store the memory block."""
    show(f"memory: node graph in lockstep with the recorder, N = {batch_periods}, {sim_s:g} s simulated "
         f"({sim_s / 3600:.2f} h; RSS sampled every {SAMPLE_EVERY_WALL_S:g} s wall) ...")
    r = run_memory(sim_s, batch_periods, progress=show)
    figures["memory_sim_s"] = r["sim_s"]
    figures["memory_wall_s"] = r["wall_s"]
    figures["memory_real_time"] = r["real_time"]
    figures["memory_startup_s"] = r["startup_s"]
    figures["memory_bag_mb"] = r["bag_mb"]
    show(f"  ran {r['sim_s']:.0f} s simulated in {r['wall_s']:.0f} s wall: start-up (imports, JIT compile / cache "
         f"load, discovery) {r['startup_s']:.1f} s, then {r['real_time']:.1f}x real time; bag {r['bag_mb']:.0f} MB; "
         f"exit codes {r['exit_codes']}")
    if any(code not in CLEAN_EXIT for code in r["exit_codes"].values()) or r["sim_s"] < 0.99 * sim_s:
        show("  the run did not complete: node output ends with")
        for line in r["log_tail"]:
            show(f"    {line}")
    worst = 0.0
    for name, s in sorted(r["nodes"].items()):
        ratio = s["max_rss_mb"] / TARGET_RSS_MB
        worst = max(worst, ratio)
        figures[f"memory_{name}_max_rss_mb"] = s["max_rss_mb"]
        figures[f"memory_{name}_rss_slope_mb_per_sim_h"] = s["slope_mb_per_sim_h"]
        figures[f"memory_{name}_max_rss_ratio_to_limit"] = ratio
        figures[f"memory_{name}_max_pss_mb"] = s["max_pss_mb"]
        figures[f"memory_{name}_max_uss_mb"] = s["max_uss_mb"]
        show(f"  {name:<11} max RSS {s['max_rss_mb']:6.1f} MB (target < {TARGET_RSS_MB:.0f} MB: ratio {ratio:.2f}); "
             f"steady {s['steady_first_mb']:.1f} -> {s['steady_last_mb']:.1f} MB, slope "
             f"{s['slope_mb_per_sim_h']:+.1f} MB per simulated hour; max PSS {s['max_pss_mb']:.1f}, "
             f"private (USS) {s['max_uss_mb']:.1f} MB"
             + (" (indicative only: run shorter than "
                f"{SLOPE_MIN_SIM_S:g} s)" if r["sim_s"] < SLOPE_MIN_SIM_S else ""))
    figures["memory_max_rss_ratio_to_limit"] = worst
