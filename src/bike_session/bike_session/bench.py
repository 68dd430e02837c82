"""`./bike bench`: speed figures and ratios, printed from one run (and written as JSON).

Figures (keys of the JSON; real-time factors end in `_real_time`):
- inner_loop_bldc_real_time: plant + controller inner loop alone, BLDC switching level
  at 20 kHz, one core (compiled kernels; JIT compile time reported separately);
- inner_loop_spmsm_real_time / inner_loop_spmsm_switching_real_time: the SPMSM bike of
  paper 001 (predictive speed + current control, 10 kHz current loop), average and
  switching inverter model, prime mover at 200 r/min, 1 s simulated;
- graph_lockstep_n20_real_time / graph_lockstep_n200_real_time: the whole node graph
  (plant, controller, session: separate processes over DDS) in lockstep;
- dds_pingpong_n20_round_trips_per_s / ..._n200_...: the bare DDS round trip of the same
  message types and sizes, and the graph's share of that limit.
Timing assertions live here, not in the tests: this machine is shared and noisy.
"""
from __future__ import annotations

import json
import os
import pathlib
import sys
import tempfile
import threading
import time

import yaml

TARGET_INNER_LOOP_REAL_TIME = 1000.0


def _config_with(batch_periods: int, duration_s: float, base: pathlib.Path, out_dir: pathlib.Path) -> pathlib.Path:
    """A copy of the base config with another batch size (profile path made absolute)."""
    doc = yaml.safe_load(base.read_text())
    params = doc["/**"]["ros__parameters"]
    params["batch_periods"] = batch_periods
    params["duration_s"] = duration_s
    profile = params.get("session", {}).get("profile")
    if profile and not os.path.isabs(profile):
        params["session"]["profile"] = str((base.parent / profile).resolve())
    path = out_dir / f"bench_n{batch_periods}.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def graph_real_time(batch_periods: int, duration_s: float, base_config: pathlib.Path) -> dict:
    """Run the lockstep graph and measure simulated seconds per wall second from /clock."""
    import rclpy
    from rosgraph_msgs.msg import Clock

    from bike_session import launcher
    from bike_session.cli import default_launch_file

    with tempfile.TemporaryDirectory() as tmp:
        config = _config_with(batch_periods, duration_s, base_config, pathlib.Path(tmp))
        nodes = launcher.parse_launch(str(default_launch_file()),
                                      {"config": str(config), "duration": repr(float(duration_s))})
        context = rclpy.Context()
        rclpy.init(context=context)
        node = rclpy.create_node("bench_clock_watch", context=context)
        samples: list[tuple[float, float]] = []
        node.create_subscription(Clock, "/clock", lambda m: samples.append(
            (m.clock.sec + m.clock.nanosec * 1e-9, time.perf_counter())), 100)
        executor = rclpy.executors.SingleThreadedExecutor(context=context)
        executor.add_node(node)
        stop = threading.Event()
        spinner = threading.Thread(target=lambda: [executor.spin_once(timeout_sec=0.1) for _ in iter(stop.is_set, True)],
                                   daemon=True)
        spinner.start()
        with open(os.devnull, "w") as sink:
            graph = launcher.Launcher(nodes, stdout=sink)
            started = time.perf_counter()
            graph.start()
            codes = graph.wait(timeout_s=duration_s * 50 + 120)
        wall_total = time.perf_counter() - started
        stop.set()
        spinner.join(2)
        rclpy.try_shutdown(context=context)
    # Steady state: skip the first 20 % of simulated time (start-up, JIT, discovery).
    steady = [s for s in samples if s[0] >= 0.2 * duration_s]
    if len(steady) < 2:
        raise RuntimeError(f"graph produced too few clock samples ({len(samples)}); exit codes {codes}")
    sim_span = steady[-1][0] - steady[0][0]
    wall_span = steady[-1][1] - steady[0][1]
    return {"real_time": sim_span / wall_span, "wall_total_s": wall_total, "exit_codes": codes}


def spmsm_inner_loop_real_time(seconds: float = 1.0, switching: bool = False) -> tuple[float, float]:
    """(sim s per wall s, first-call seconds) of the SPMSM plant + predictive controller
    kernel (bike_controller.spmsm_control.run_spmsm_offline), prime mover at 200 r/min."""
    from bike_controller.spmsm_control import run_spmsm_offline
    from bike_plant.config import load_config

    from bike_session.cli import repo_root

    cfg = load_config(repo_root() / "config" / "spmsm_default.yaml")
    cfg["load"] = dict(cfg.get("load") or {}, kind="prime_mover", speed_rpm=200.0)
    t0 = time.perf_counter()
    run_spmsm_offline(cfg, 0.01, speed_ref_fn=lambda t: 200.0, switching=switching)
    compile_s = time.perf_counter() - t0
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        run_spmsm_offline(cfg, seconds, speed_ref_fn=lambda t: 200.0, switching=switching, record_every=1000)
        best = min(best, time.perf_counter() - t0)
    return seconds / best, compile_s


def main(json_path: str | None = None, quick: bool = False) -> int:
    from bike_plant.config import default_config_path

    from bike_session import pingpong

    figures: dict[str, float] = {}
    lines: list[str] = []

    def show(text: str) -> None:
        print(text, flush=True)
        lines.append(text)

    show("bike bench (2-core shared machine: figures are noisy; compare ratios within one run)")
    try:
        from bike_session.bench_kernels import inner_loop_real_time
    except ImportError as exc:  # pragma: no cover - reported, not hidden
        show(f"inner loop: unavailable ({exc})")
    else:
        inner = inner_loop_real_time(seconds=0.5 if quick else 2.0)
        figures["inner_loop_bldc_real_time"] = inner["real_time"]
        figures["inner_loop_bldc_compile_s"] = inner.get("compile_s", float("nan"))
        show(f"inner loop, BLDC 20 kHz, one core: {inner['real_time']:.0f}x real time "
             f"(target >= {TARGET_INNER_LOOP_REAL_TIME:.0f}x: ratio {inner['real_time'] / TARGET_INNER_LOOP_REAL_TIME:.2f}); "
             f"JIT compile {figures['inner_loop_bldc_compile_s']:.1f} s")
    for key, switching in (("inner_loop_spmsm_real_time", False), ("inner_loop_spmsm_switching_real_time", True)):
        rt, compile_s = spmsm_inner_loop_real_time(seconds=0.5 if quick else 1.0, switching=switching)
        figures[key] = rt
        figures[key.replace("_real_time", "_compile_s")] = compile_s
        show(f"inner loop, SPMSM 10 kHz ({'switching' if switching else 'average'} inverter), one core: "
             f"{rt:.0f}x real time (target >= {TARGET_INNER_LOOP_REAL_TIME:.0f}x: ratio "
             f"{rt / TARGET_INNER_LOOP_REAL_TIME:.2f}); JIT compile / cache load {compile_s:.1f} s")
    base = default_config_path()
    period_s = float(yaml.safe_load(base.read_text())["/**"]["ros__parameters"]["control_period_s"])
    for n in (20, 200):
        ping = pingpong.measure(n, round_trips=500 if quick else 2000)
        figures[f"dds_pingpong_n{n}_round_trips_per_s"] = ping["round_trips_per_s"]
        figures[f"dds_pingpong_n{n}_p50_us"] = ping["p50_us"]
        limit_real_time = ping["round_trips_per_s"] * n * period_s
        figures[f"dds_pingpong_n{n}_limit_real_time"] = limit_real_time
        graph = graph_real_time(n, duration_s=(2.0 if n == 20 else 10.0) * (0.5 if quick else 1.0), base_config=base)
        figures[f"graph_lockstep_n{n}_real_time"] = graph["real_time"]
        ratio = graph["real_time"] / limit_real_time
        figures[f"graph_lockstep_n{n}_share_of_pingpong"] = ratio
        show(f"node graph lockstep, N={n}: {graph['real_time']:.2f}x real time; DDS ping-pong of the same "
             f"messages {ping['round_trips_per_s']:.0f} round trips/s (p50 {ping['p50_us']:.0f} us) = "
             f"{limit_real_time:.2f}x limit; graph reaches {ratio * 100:.0f} % of it")
    try:
        from bike_plant.can.latency import can_latency
        lat = can_latency(n=200 if quick else 500)
    except Exception as exc:  # noqa: BLE001 - reported, not hidden
        show(f"CAN latency: unavailable ({exc})")
    else:
        for key in ("p50_ms", "p99_ms", "max_ms"):
            figures[f"can_drive_command_to_frame_{key}"] = float(lat[key])
        show(f"DriveCommand -> CAN frame (plant node, backend can, udp_multicast): p50 {lat['p50_ms']:.2f} ms, "
             f"p99 {lat['p99_ms']:.2f} ms, max {lat['max_ms']:.2f} ms ({lat.get('received', '?')}/{lat.get('n', '?')})")
    if json_path:
        pathlib.Path(json_path).write_text(json.dumps(figures, indent=2, sort_keys=True))
        show(f"figures written to {json_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else None))
