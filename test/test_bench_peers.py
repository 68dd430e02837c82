"""The peers benchmark's harness (bike_session.bench_peers, tools/peers/peer_common.py) and
the memory block's helpers (bike_session.bench_memory). No timing is asserted here: the
figures themselves are `./bike bench` output."""
import math
import os
import pathlib
import sys

import numpy as np
import pytest

from bike_session import bench_memory, bench_peers

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def short_run():
    sc = bench_peers.scenario(duration_s=0.2, load_step_s=0.1, sample_every_periods=100)
    return sc, bench_peers.run_ours(sc, repeats=1)


def test_scenario_is_the_paper_machine_ideal_and_json(short_run):
    sc, _ = short_run
    m = sc["machine"]
    assert (m["pole_pairs"], m["inductance_h"], m["flux_linkage_vs"], m["inertia_kgm2"], m["dc_link_v"]) == \
        (6, 9.8e-3, 0.122, 0.01, 24.0)
    cfg = sc["config"]
    assert cfg["controller"]["family"] == "pi"
    assert cfg["spmsm"]["cogging_torque_nm"] == 0.0 and cfg["inverter"]["dead_time_s"] == 0.0
    assert cfg["load"]["kind"] == "dynamometer" and cfg["load"]["dyno_torque_nm"] == [0.0, 1.0]
    assert sc["sample_periods"] == list(range(100, 2001, 100))


def test_our_runner_documented_shape(short_run):
    sc, ours = short_run
    for key in ("peer", "wall_s", "sim_s", "real_time", "cpu_s", "cpu_real_time", "compile_s"):
        assert key in ours
    assert ours["sim_s"] == 0.2 and ours["wall_s"] > 0 and ours["real_time"] > 0
    n = len(sc["sample_periods"])
    for key in bench_peers.TRACE_KEYS:
        assert len(ours[key]) == n and all(math.isfinite(v) for v in ours[key])
    assert ours["t_s"] == pytest.approx([k * 1e-4 for k in sc["sample_periods"]])
    speed = np.asarray(ours["speed_rpm"])
    assert 0.0 < speed[0] < speed[9] < 150.0          # accelerating towards the 150 r/min command
    iq = np.asarray(ours["iq_a"])
    assert iq[-1] > iq[9] + 0.5                        # the 1 N m load step at 0.1 s (Kt = 1.1 N m/A)


def test_compare_zero_on_itself_and_sees_a_difference(short_run):
    _, ours = short_run
    assert bench_peers.compare(ours, ours) == {"speed_max_rel_diff": 0.0, "current_max_rel_diff": 0.0}
    other = dict(ours, speed_rpm=[v * 1.06 for v in ours["speed_rpm"]])
    assert bench_peers.compare(ours, other)["speed_max_rel_diff"] == pytest.approx(0.06)
    with pytest.raises(ValueError, match="sample times"):
        bench_peers.compare(ours, dict(ours, t_s=ours["t_s"][:-1]))


def test_peer_adapter_on_our_plant_reproduces_our_runner(short_run):
    """tools/peers/peer_common.ProjectPI (what drives motulator and GEM) driving OUR plant
    kernel period by period gives our runner's traces: the adapter (measurement, encoder
    count from the unwrapped angle, reference timing) is the runner's closed loop."""
    sc, ours = short_run
    sys.path.insert(0, str(ROOT / "tools" / "peers"))
    try:
        import peer_common as PC
    finally:
        sys.path.remove(str(ROOT / "tools" / "peers"))
    from bike_controller import spmsm_control as SC
    from bike_plant import spmsm as M

    pi = PC.ProjectPI(sc)
    trace = PC.Trace(sc)
    params = M.plant_params_from_config(sc["config"])
    params.inverter.model = "average"
    plant = M.SpmsmPlant(params)
    ws = np.zeros(M.WS_SIZE)
    n = int(round(sc["duration_s"] / sc["control_period_s"]))
    for k in range(n + 1):
        st = plant.state
        trace.maybe(k, st[M.S_OMEGA], st[M.S_ID], st[M.S_IQ])
        if k == n:
            break
        da, db, dc = pi(k, st[M.S_IA], st[M.S_IB], st[M.S_IC], st[M.S_THETA_M])
        M.step_period(st, plant.p, da, db, dc, 0.0, pi.ctrl.cs[SC.C_BUCK_DUTY], ws)
    assert trace.t_s == pytest.approx(ours["t_s"])
    for key in ("speed_rpm", "id_a", "iq_a"):
        assert getattr(trace, key) == pytest.approx(ours[key], rel=1e-6, abs=1e-6)


def test_missing_peer_is_reported_not_raised(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("BIKE_PEERS_DIR", str(tmp_path))
    assert bench_peers.peer_python("motulator") is None
    with pytest.raises(FileNotFoundError):
        bench_peers.run_peer("gem", {})


def test_memory_helpers():
    assert bench_memory.rss_mb(os.getpid()) > 10.0
    assert bench_memory.rss_mb(2 ** 22 + 12345) == 0.0       # no such process
    pts = [(s, 100.0 + 0.01 * s) for s in range(0, 600, 10)]   # +0.01 MB per simulated second
    assert bench_memory.slope_per_hour(pts) == pytest.approx(36.0)
    # a start-up peak counts in the maximum, not in the steady-state slope (first 20 % skipped)
    s = bench_memory.summarise({"plant": [(0.0, 150.0)] + pts}, sim_s=600.0)["plant"]
    assert s["max_rss_mb"] == 150.0 and s["slope_mb_per_sim_h"] == pytest.approx(36.0)
    # a peak between two samples (the processes' VmHWM) counts too, and PSS / USS are passed on
    peak = {"plant": {"pss": 90.0, "uss": 80.0, "hwm": 170.0}}
    s = bench_memory.summarise({"plant": [(0.0, 150.0)] + pts}, sim_s=600.0, shares=peak)["plant"]
    assert (s["max_rss_mb"], s["max_pss_mb"], s["max_uss_mb"]) == (170.0, 90.0, 80.0)
    assert bench_memory.rss_mb(os.getpid(), "VmHWM") >= bench_memory.rss_mb(os.getpid())


def test_bench_rejects_bad_sections_and_lengths(capsys):
    from bike_session import bench
    assert bench.main(only=["peers", "bogus"]) == 2
    assert "unknown bench section(s) bogus" in capsys.readouterr().err
    # a comma list is split ("nope,inner" was one unknown name), an empty name is refused (it ran everything)
    assert bench.main(only=["nope,inner"]) == 2
    assert "unknown bench section(s) nope (choose from" in capsys.readouterr().err
    assert bench.main(only=["inner,"]) == 2
    assert capsys.readouterr().err.startswith("error: --only: an empty section name")
    assert bench.main(only=["inner, fleet"], memory_s=5.0) == 2       # both names taken, neither is memory
    assert capsys.readouterr().err.strip().endswith("not --only inner fleet")
    assert bench.main(only=["memory"], memory_s=-5.0) == 2
    assert "--memory-s must be > 0" in capsys.readouterr().err
    # inf: the memory run's session refused it, "the run did not complete", and the bench exited 0
    assert bench.main(only=["memory"], memory_s=math.inf) == 2
    assert "--memory-s must be > 0 and at most 9.2e+09" in capsys.readouterr().err
    assert bench.main(only=["inner"], memory_s=5.0) == 2            # was dropped without a word
    assert capsys.readouterr().err.strip() == "error: --memory-s: only with the memory section (--only memory), " \
                                              "not --only inner"


def test_the_graph_figure_falls_back_on_the_plants_own_rate(monkeypatch):
    """A lockstep graph run over before discovery matched the bench's battery watch (seen: no
    sample in a 5 s run) still gives its figure: the rate the plant logs at the end of the
    same run, and the figure says where it came from."""
    from bike_session import bench

    line = "[plant] [INFO] [1.0] [bike.plant]: lockstep rate 6290 batches per wall second (6.29 x real time)"
    assert bench.PLANT_RATE_RE.findall(line) == ["6.29"]
    runs = iter([{"samples": [], "exit_codes": {}, "plant_real_time": 6.29},
                 {"samples": [(4.0, 10.0), (16.0, 12.0)], "exit_codes": {}, "plant_real_time": 6.0}])
    monkeypatch.setattr(bench, "_graph_run", lambda *a: next(runs))
    got = bench.graph_real_time(20, 16.0, None)
    assert (got["real_time"], got["source"]) == (6.29, "the plant's own rate")
    got = bench.graph_real_time(20, 16.0, None)
    assert (got["real_time"], got["source"]) == (6.0, "battery watch")
    monkeypatch.setattr(bench, "_graph_run", lambda *a: {"samples": [], "exit_codes": {}, "plant_real_time": None})
    with pytest.raises(RuntimeError, match="the plant logged no rate"):
        bench.graph_real_time(20, 16.0, None)
