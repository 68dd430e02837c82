"""`./bike bench`: speed figures and ratios, printed from one run (and written as JSON).

Figures (keys of the JSON; real-time factors end in `_real_time`):
- inner_loop_bldc_real_time: plant + controller inner loop alone, BLDC switching level
  at 20 kHz, one core (compiled kernels; JIT compile time reported separately), the best of
  20 runs of a deterministic kernel (inner_loop_bldc_median_real_time: their median);
- inner_loop_spmsm_real_time / inner_loop_spmsm_switching_real_time: the SPMSM bike of
  paper 001 (predictive speed + current control, 10 kHz current loop), average and
  switching inverter model, prime mover at 200 r/min, 1 s simulated, best of 20 runs
  (inner_loop_spmsm_median_real_time / ..._switching_median_real_time: their median);
- fleet_real_time / fleet_bikes_in_real_time: 1000 independent BLDC bikes in the batched
  kernel on 2 threads (bike_controller.fleet); bikes in real time = bikes x real-time factor;
- graph_lockstep_n20_real_time / graph_lockstep_n200_real_time: the whole node graph
  (plant, controller, session: separate processes over DDS) in lockstep;
- dds_pingpong_n20_round_trips_per_s / ..._n200_...: the bare DDS round trip of the same
  message types and sizes, and the graph's share of that limit
  (graph_lockstep_n*_share_of_pingpong, target >= 80 %: ..._share_ratio_to_target): the
  median of GRAPH_ROUNDS rounds, each graph run against the ping-pongs just before and after
  it (..._share_min / _max: the spread of the rounds); for comparison only,
  dds_pingpong_tuned_n*_round_trips_per_s and graph_lockstep_n*_share_of_tuned_pingpong: the
  same round trip over the graph's own transport pieces (bytes, HotWait, busy wait);
- peers_*: the same PMSM scenario on our SPMSM and on motulator / gym-electric-motor when
  installed (`make peers`): real-time factors, speed-ups vs the targets, result differences
  (bike_session.bench_peers);
- memory_*: every node's RSS over a long recorded lockstep session (bike_session.bench_memory);
- host_cpu / host_cores / host_clock_ghz: the machine, with its effective clock measured in the
  run (bench_kernels.host_summary), and *_ns_per_period / inner_loop_bldc_cycles_per_period:
  the inner loops' cost per period, which compares across hosts better than a real-time factor.
Sections (`./bike bench --only SECTION`, repeatable or a comma list): inner, fleet, graph, can, peers, memory.
Timing assertions live here, not in the tests: this machine is shared and noisy.
"""
from __future__ import annotations

import json
import pathlib
import re
import sys
import tempfile
import threading
import time

import yaml
from bike_plant.config import absolute_file_paths, dump_ros_params

TARGET_INNER_LOOP_REAL_TIME = 1000.0
TARGET_GRAPH_SHARE_OF_PINGPONG = 0.80  # the lockstep graph vs the DDS ping-pong limit (issue 6)
# the plant's own figure at the end of a lockstep run (bike_plant.node, _run_lockstep)
PLANT_RATE_RE = re.compile(r"lockstep rate \d+ batches per wall second \(([\d.]+) x real time\)")
GRAPH_ROUNDS = 3                     # ping-pong / graph rounds per batch size; the median round is the figure
SECTIONS = ("inner", "fleet", "graph", "can", "peers", "memory")
MEMORY_SIM_S = 600.0                 # default simulated length of the memory run (--memory-s)
MEMORY_SIM_S_QUICK = 60.0
TARGET_FLEET_BIKES = 1000           # offline batched kernel, bikes in real time on this 2-core machine


def spin_in_background(executor):
    """Spin `executor` in a daemon thread; returns the function that stops it (joins <= 2 s)."""
    stop = threading.Event()
    spinner = threading.Thread(target=lambda: [executor.spin_once(timeout_sec=0.1) for _ in iter(stop.is_set, True)],
                               daemon=True)
    spinner.start()

    def stop_spinning() -> None:
        stop.set()
        spinner.join(2)
    return stop_spinning


def _config_with(batch_periods: int, duration_s: float, base: pathlib.Path, out_dir: pathlib.Path) -> pathlib.Path:
    """A copy of the base config with another batch size (its file paths made absolute)."""
    doc = yaml.safe_load(base.read_text())
    params = doc["/**"]["ros__parameters"]
    params["batch_periods"] = batch_periods
    params["duration_s"] = duration_s
    absolute_file_paths(params, base.parent)
    path = out_dir / f"bench_n{batch_periods}.yaml"
    path.write_text(dump_ros_params(doc))
    return path


def graph_real_time(batch_periods: int, duration_s: float, base_config: pathlib.Path, attempts: int = 2) -> dict:
    """Run the lockstep graph and measure simulated seconds per wall second from the sim-time
    stamps of the plant's BatteryState (``battery_every`` batches apart, 10 by default). The
    watch does not follow /clock: a reader of a per-batch topic in the bench process would
    take a share of the two cores the graph runs on, once per batch. A short run can end
    before discovery has matched the watch (seen: the watch matched 4 s into a 5 s run, or
    not at all): then the plant's own figure of the same run is taken, the rate it logs at
    the end ("lockstep rate ... x real time", from its first answer to its last batch, the
    kernels warmed before), and ``source`` says so. Only with neither is it run again,
    ``attempts`` in all."""
    for attempt in range(attempts):
        result = _graph_run(batch_periods, duration_s, base_config)
        # steady state: skip the first 20 % of simulated time (start-up, JIT, discovery)
        steady = [s for s in result.pop("samples") if s[0] >= 0.2 * duration_s]
        if len(steady) >= 2:
            sim_span = steady[-1][0] - steady[0][0]
            wall_span = steady[-1][1] - steady[0][1]
            return dict(result, real_time=sim_span / wall_span, source="battery watch")
        if result["plant_real_time"] is not None:
            return dict(result, real_time=result["plant_real_time"], source="the plant's own rate")
    raise RuntimeError(f"graph produced too few battery samples after the first 20 % of the run "
                       f"({len(steady)}, {attempts} runs) and the plant logged no rate; exit codes "
                       f"{result['exit_codes']}")


def _graph_run(batch_periods: int, duration_s: float, base_config: pathlib.Path) -> dict:
    import rclpy
    from sensor_msgs.msg import BatteryState

    from bike_session import launcher
    from bike_session.cli import default_launch_file

    with tempfile.TemporaryDirectory() as tmp:
        config = _config_with(batch_periods, duration_s, base_config, pathlib.Path(tmp))
        nodes = launcher.parse_launch(str(default_launch_file()),
                                      {"config": str(config), "duration": repr(float(duration_s))})
        context = rclpy.Context()
        rclpy.init(context=context)
        node = rclpy.create_node("bench_graph_watch", context=context)
        samples: list[tuple[float, float]] = []
        node.create_subscription(BatteryState, "/bike/battery", lambda m: samples.append(
            (m.header.stamp.sec + m.header.stamp.nanosec * 1e-9, time.perf_counter())), 100)
        executor = rclpy.executors.SingleThreadedExecutor(context=context)
        executor.add_node(node)
        stop_spinning = spin_in_background(executor)
        log_path = pathlib.Path(tmp) / "graph.log"
        with open(log_path, "w") as sink:
            graph = launcher.Launcher(nodes, stdout=sink)
            started = time.perf_counter()
            graph.start()
            codes = graph.wait(timeout_s=duration_s * 50 + 120)
        wall_total = time.perf_counter() - started
        stop_spinning()
        rclpy.try_shutdown(context=context)
        rates = PLANT_RATE_RE.findall(log_path.read_text())
    return {"samples": samples, "wall_total_s": wall_total, "exit_codes": codes,
            "plant_real_time": float(rates[-1]) if rates else None}


def spmsm_inner_loop_real_time(seconds: float = 1.0, switching: bool = False,
                               repeats: int = 20) -> tuple[float, float, float, float]:
    """(sim s per wall s, first-call seconds, control period s, median sim s per wall s) of the
    SPMSM plant + predictive controller kernel (bike_controller.spmsm_control.run_spmsm_offline),
    prime mover at 200 r/min. The wall time is the fused closed loop's own (run_kernel: plant
    step + control law per 100 us period, ``wall_s`` of the result), best of `repeats` runs
    as for the BLDC figure (bench_kernels.FUSED_REPEATS: on a shared machine the minimum is
    the least disturbed run, the median says how much the load takes away); the Python set-up
    of the run (parameter packing, reference sampling, ~0.3-0.5 ms) is not inner loop."""
    from bike_controller.spmsm_control import run_spmsm_offline
    from bike_plant.config import load_config

    from bike_session.cli import repo_root

    cfg = load_config(repo_root() / "config" / "spmsm_default.yaml")
    cfg["load"] = dict(cfg.get("load") or {}, kind="prime_mover", speed_rpm=200.0)
    t0 = time.perf_counter()
    run_spmsm_offline(cfg, 0.01, speed_ref_fn=lambda t: 200.0, switching=switching)
    compile_s = time.perf_counter() - t0
    walls = sorted(run_spmsm_offline(cfg, seconds, speed_ref_fn=lambda t: 200.0, switching=switching,
                                     record_every=1000)["wall_s"] for _ in range(repeats))
    return seconds / walls[0], compile_s, float(cfg["control_period_s"]), seconds / walls[len(walls) // 2]


def main(json_path: str | None = None, quick: bool = False, only=None, memory_s: float | None = None) -> int:
    from bike_plant.config import default_config_path

    from bike_session import pingpong

    if only is not None:
        # "--only inner,fleet" as well as "--only inner --only fleet" (a comma list was one unknown name)
        only = [name.strip() for item in only for name in str(item).split(",")]
    unknown = set(only or ()) - set(SECTIONS)
    if "" in unknown:
        print(f"error: --only: an empty section name (choose from {', '.join(SECTIONS)})", file=sys.stderr)
        return 2
    if unknown:
        print(f"error: unknown bench section(s) {', '.join(sorted(unknown))} (choose from {', '.join(SECTIONS)})",
              file=sys.stderr)
        return 2
    from bike_plant.config import MAX_SIM_TIME_S
    if memory_s is not None and not 0 < memory_s <= MAX_SIM_TIME_S:
        # inf / 1e300: the memory run's session refused it, "the run did not complete", exit 0
        print(f"error: --memory-s must be > 0 and at most {MAX_SIM_TIME_S:g} (the ROS clock's int64 nanoseconds), "
              f"got {memory_s}", file=sys.stderr)
        return 2
    if memory_s is not None and only and "memory" not in only:
        # it was dropped without a word
        print(f"error: --memory-s: only with the memory section (--only memory), not --only {' '.join(only)}",
              file=sys.stderr)
        return 2

    def want(section: str) -> bool:
        return not only or section in only

    # a private DDS domain, as `./bike run` takes: the graph runs and the ping-pong must not
    # meet another graph's /clock or topics on this host
    from bike_session import domains
    domains.ensure_private_domain("bench")

    figures: dict[str, float] = {}
    lines: list[str] = []

    def show(text: str) -> None:
        print(text, flush=True)
        lines.append(text)

    show("bike bench (2-core shared machine: figures are noisy; compare ratios within one run)")
    try:
        from bike_session.bench_kernels import FUSED_REPEATS, host_summary, inner_loop_real_time
    except ImportError as exc:  # pragma: no cover - reported, not hidden
        inner_loop_real_time = host_summary = None
        show(f"inner loop: unavailable ({exc})")
    clock_ghz = float("nan")
    if host_summary is not None:
        # the kernels' figures follow the host's clock and core: say which host they are from
        host = host_summary()
        clock_ghz = host["clock_ghz"]
        figures["host_cpu"] = host["cpu"]
        figures["host_cores"] = host["cores"]
        figures["host_clock_ghz"] = clock_ghz
        show(f"host: {host['cpu']}, {host['cores']} cores{', virtual machine' if host['virtual'] else ''}; "
             f"effective clock {clock_ghz:.2f} GHz now (a two-cycle dependency chain)")
    if want("inner") and inner_loop_real_time is not None:
        inner = inner_loop_real_time(seconds=0.5 if quick else 2.0)
        figures["inner_loop_bldc_real_time"] = inner["real_time"]
        figures["inner_loop_bldc_median_real_time"] = inner["fused_real_time_median"]
        figures["inner_loop_bldc_compile_s"] = inner.get("compile_s", float("nan"))
        ns = inner["fused_ns_per_period"]
        figures["inner_loop_bldc_ns_per_period"] = ns
        figures["inner_loop_bldc_cycles_per_period"] = ns * clock_ghz
        show(f"inner loop, BLDC 20 kHz, one core: {inner['real_time']:.0f}x real time, best of "
             f"{FUSED_REPEATS} runs (median {inner['fused_real_time_median']:.0f}x) "
             f"(target >= {TARGET_INNER_LOOP_REAL_TIME:.0f}x: ratio {inner['real_time'] / TARGET_INNER_LOOP_REAL_TIME:.2f}); "
             f"{ns:.0f} ns = {ns * clock_ghz:.0f} cycles per period (the target allows "
             f"{inner['control_period_s'] * 1e9 / TARGET_INNER_LOOP_REAL_TIME:.0f} ns); "
             f"JIT compile {figures['inner_loop_bldc_compile_s']:.1f} s")
    # fleet: 1000 independent BLDC bikes (plant + controller inner loop each, riders and commands
    # spread) in the batched numba kernel on 2 threads (bike_controller.fleet; ./bike fleet)
    if want("fleet"):
        from bike_controller.fleet import fleet_real_time
        fleet = max((fleet_real_time(TARGET_FLEET_BIKES, seconds=0.25 if quick else 1.0, threads=2)
                     for _ in range(1 if quick else 2)), key=lambda r: r["bikes_in_real_time"])
        figures["fleet_real_time"] = fleet["real_time"]
        figures["fleet_bikes_in_real_time"] = fleet["bikes_in_real_time"]
        figures["fleet_compile_s"] = fleet["jit_compile_s"]
        show(f"fleet, {fleet['bikes']} BLDC bikes on {fleet['threads']} threads: {fleet['real_time']:.2f}x real time = "
             f"{fleet['bikes_in_real_time']:.0f} bikes in real time (target >= {TARGET_FLEET_BIKES}: ratio "
             f"{fleet['bikes_in_real_time'] / TARGET_FLEET_BIKES:.2f}); {fleet['ns_per_bike_period']:.0f} ns per bike-period")
    for key, switching in (("inner_loop_spmsm_real_time", False), ("inner_loop_spmsm_switching_real_time", True)):
        if not want("inner"):
            break
        repeats = 5 if quick else 20
        rt, compile_s, spmsm_period_s, rt_median = spmsm_inner_loop_real_time(
            seconds=0.5 if quick else 1.0, switching=switching, repeats=repeats)
        figures[key] = rt
        figures[key.replace("_real_time", "_median_real_time")] = rt_median
        figures[key.replace("_real_time", "_compile_s")] = compile_s
        ns = spmsm_period_s / rt * 1e9
        figures[key.replace("_real_time", "_ns_per_period")] = ns
        show(f"inner loop, SPMSM 10 kHz ({'switching' if switching else 'average'} inverter), one core: "
             f"{rt:.0f}x real time, best of {repeats} runs (median {rt_median:.0f}x) "
             f"(target >= {TARGET_INNER_LOOP_REAL_TIME:.0f}x: ratio "
             f"{rt / TARGET_INNER_LOOP_REAL_TIME:.2f}); {ns:.0f} ns = {ns * clock_ghz:.0f} cycles per period; "
             f"JIT compile / cache load {compile_s:.1f} s")
    base = default_config_path()
    period_s = float(yaml.safe_load(base.read_text())["/**"]["ros__parameters"]["control_period_s"])
    if want("peers"):
        from bike_session.bench_peers import bench_peers
        bench_peers(show, figures, quick=quick)
    for n in (20, 200):
        if not want("graph"):
            break
        # rounds of ping-pong, graph, ping-pong: each graph run is compared with the mean of the
        # ping-pongs just before and after it (the machine's load drifts, and the share compares
        # two measurements that should see the same load); the figure is the median round.
        # ~7 s of wall time per graph run: the watch's discovery of the plant can take ~3 s
        # (Fast DDS announcement period), and shorter steady spans read +-20 %
        rounds = 1 if quick else GRAPH_ROUNDS
        pings = [pingpong.measure(n, round_trips=500 if quick else 2000)]
        results = []
        for _ in range(rounds):
            graph = graph_real_time(n, duration_s=(16.0 if n == 20 else 120.0) * (0.5 if quick else 1.0),
                                    base_config=base)
            pings.append(pingpong.measure(n, round_trips=500 if quick else 2000))
            ping = {key: (pings[-2][key] + pings[-1][key]) / 2 for key in ("round_trips_per_s", "p50_us")}
            limit_real_time = ping["round_trips_per_s"] * n * period_s
            results.append((graph["real_time"] / limit_real_time, graph["real_time"], ping, limit_real_time,
                            graph["source"]))
        results.sort(key=lambda r: r[0])
        ratio, real_time, ping, limit_real_time, source = results[len(results) // 2]
        figures[f"dds_pingpong_n{n}_round_trips_per_s"] = ping["round_trips_per_s"]
        figures[f"dds_pingpong_n{n}_p50_us"] = ping["p50_us"]
        figures[f"dds_pingpong_n{n}_limit_real_time"] = limit_real_time
        figures[f"graph_lockstep_n{n}_real_time"] = real_time
        figures[f"graph_lockstep_n{n}_share_of_pingpong"] = ratio
        figures[f"graph_lockstep_n{n}_share_ratio_to_target"] = ratio / TARGET_GRAPH_SHARE_OF_PINGPONG
        figures[f"graph_lockstep_n{n}_share_min"] = results[0][0]
        figures[f"graph_lockstep_n{n}_share_max"] = results[-1][0]
        spread = (f"; {rounds} rounds: {', '.join(f'{r[0] * 100:.0f}' for r in results)} %, median shown"
                  if rounds > 1 else "")
        show(f"node graph lockstep, N={n}: {real_time:.2f}x real time ({source}); DDS ping-pong of the same "
             f"messages between plain rclpy processes (executor, message objects) "
             f"{ping['round_trips_per_s']:.0f} round trips/s (p50 {ping['p50_us']:.0f} us) = "
             f"{limit_real_time:.2f}x limit; graph reaches {ratio * 100:.0f} % of it (target >= "
             f"{TARGET_GRAPH_SHARE_OF_PINGPONG * 100:.0f} %: ratio {ratio / TARGET_GRAPH_SHARE_OF_PINGPONG:.2f}){spread}")
        # not the target's reference (that is the plain rclpy ping-pong above): the same round
        # trip over the graph's own transport pieces, i.e. what is left for the nodes' work
        tuned = pingpong.measure(n, round_trips=500 if quick else 2000, tuned=True)
        tuned_limit = tuned["round_trips_per_s"] * n * period_s
        figures[f"dds_pingpong_tuned_n{n}_round_trips_per_s"] = tuned["round_trips_per_s"]
        figures[f"graph_lockstep_n{n}_share_of_tuned_pingpong"] = real_time / tuned_limit
        show(f"  for comparison, the same ping-pong over the graph's own transport (bytes, HotWait, lockstep "
             f"busy wait): {tuned['round_trips_per_s']:.0f} round trips/s (p50 {tuned['p50_us']:.0f} us) = "
             f"{tuned_limit:.2f}x; the graph's batch adds its work to that round trip: "
             f"{real_time / tuned_limit * 100:.0f} % of it")
    lat = None
    if want("can"):
        try:
            from bike_session.can_latency import can_latency
            lat = can_latency(n=200 if quick else 500)
        except Exception as exc:  # noqa: BLE001 - reported, not hidden
            show(f"CAN latency: unavailable ({exc})")
    if lat is not None:
        for key in ("p50_ms", "p99_ms", "max_ms"):
            figures[f"can_drive_command_to_frame_{key}"] = float(lat[key])
        show(f"DriveCommand -> CAN frame (plant node, backend can, udp_multicast): p50 {lat['p50_ms']:.2f} ms, "
             f"p99 {lat['p99_ms']:.2f} ms, max {lat['max_ms']:.2f} ms ({lat.get('received', '?')}/{lat.get('n', '?')})")
    if want("memory"):
        from bike_session.bench_memory import bench_memory
        sim_s = memory_s if memory_s is not None else (MEMORY_SIM_S_QUICK if quick else MEMORY_SIM_S)
        if sim_s < 3600.0:
            show(f"memory: {sim_s:g} s simulated, not the full hour (the recorded graph runs at a few x real time "
                 f"here: `./bike bench --only memory --memory-s 3600` takes the hour)")
        bench_memory(show, figures, sim_s)
    if json_path:
        from bike_session.cli import write_output
        if not write_output(json_path, json.dumps(figures, indent=2, sort_keys=True), "--json"):
            return 2
        show(f"figures written to {json_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else None))
