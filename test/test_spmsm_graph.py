"""The SPMSM bike (paper 001) in the node graph: `./bike run --config <spmsm config>` works
exactly like the BLDC one (plant, controller, session, recorder processes over DDS), and a
recorded session replays against the other controller family."""
import json
import pathlib

import numpy as np
import pytest
import yaml

from conftest import bike_command, mean_erg_power_w

from bike_msgs.msg import PlantState
from bike_session.bags import read_topic
from bike_session.replay import command_timeline
from bike_session.report import main as report_main

ROOT = pathlib.Path(__file__).resolve().parents[1]
PROFILE = """
name: spmsm_modes
segments:
  - {kind: step, duration_s: 2, command: 0.3, mode: resistance, label: resistance}
  - {kind: step, duration_s: 3, target: 150, mode: erg, label: ERG 150 W}
  - {kind: step, duration_s: 2, target: 60, mode: isokinetic, label: isokinetic 60 rpm}
  - {kind: step, duration_s: 2, target: 4, mode: slope, label: climb 4 %}
  - {kind: step, duration_s: 2, target: -6, mode: slope, label: descent -6 %}
"""


# 5 ms batches (5 speed-loop periods), not the default 1 ms: the ride runs about 3x faster
# (conftest.FAST_BATCHES); the default N is ridden by the app's spin-down over FTMS (test_ftms_graph)
SPMSM_BATCH_PERIODS = 50


def _bike_config(tmp_path: pathlib.Path, family: str) -> pathlib.Path:
    doc = yaml.safe_load((ROOT / "config" / "spmsm_default.yaml").read_text())
    params = doc["/**"]["ros__parameters"]
    (tmp_path / "profile.yaml").write_text(PROFILE)
    params["session"]["profile"] = str(tmp_path / "profile.yaml")
    params["load"].update(kind="rider", gear_ratio=4.0)
    params["mechanics"]["speed0_rpm"] = 240.0
    params["controller"]["family"] = family
    params["batch_periods"] = SPMSM_BATCH_PERIODS
    # road load without the virtual bike's mass: the downhill assist shows within 2 s
    params["modes"] = dict(params.get("modes") or {}, virtual_inertia=False)
    path = tmp_path / f"spmsm_{family}.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def _window(msgs, t0, t1):
    return [m for m in msgs if t0 <= m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 < t1]


@pytest.mark.slow
def test_spmsm_session_in_the_node_graph_and_replay_with_pi(tmp_path, ros_domain):
    cfg = _bike_config(tmp_path, "predictive")
    res = bike_command("run", "--config", str(cfg), "--duration", "11", "--record", str(tmp_path / "pred"))
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    bag = next(p for p in (tmp_path / "pred").iterdir() if p.is_dir())
    states = read_topic(bag, "plant_state")
    status = read_topic(bag, "controller_status")
    assert states[0].machine == "spmsm" and len(states) >= 11.0 / (SPMSM_BATCH_PERIODS * 1e-4) - 1
    assert {s.family for s in status} == {"predictive"}
    # braking through the rectifier + buck path, isokinetic through the inverter (paper 001, Fig. 2)
    assert np.mean([m.relay_state for m in _window(states, 1.0, 2.0)]) == pytest.approx(1.0)
    assert np.mean([m.relay_state for m in _window(states, 6.0, 7.0)]) == pytest.approx(0.0)
    erg = _window(states, 4.0, 5.0)
    assert mean_erg_power_w(erg, cfg) == pytest.approx(150.0, rel=0.08)
    assert erg[-1].energy_battery_j > 0
    iso = [s for s in _window(status, 6.0, 7.0)]
    assert {s.mode for s in iso} == {4} and all(s.speed_ref_rpm == pytest.approx(240.0) for s in iso)
    # virtual terrain (paper 001): braking uphill through the rectifier, assist downhill
    # through the inverter (motoring torque)
    up, down = _window(states, 8.5, 9.0), _window(states, 10.5, 11.0)
    assert np.mean([m.relay_state for m in up]) == pytest.approx(1.0)
    assert np.mean([m.torque_em_nm for m in up]) < -0.5
    assert np.mean([m.relay_state for m in down]) == pytest.approx(0.0)
    assert np.mean([m.torque_em_nm for m in down]) > 0.1
    # switching inverter -> rectifier above ~200 r/min: the back-EMF keeps current flowing
    # through the diodes, so the relay opens under current after its drain timeout (reported)
    faults = [m.faults for m in states if m.faults]
    assert set(faults) <= {PlantState.FAULT_RELAY_FORCED} and len(faults) <= 5, faults
    # the report counts the path changes as the decoded relay states say: the plant starts on the
    # inverter, then rectifier (resistance, ERG) -> inverter (isokinetic) -> rectifier (climb) ->
    # inverter (descent)
    conn = [m.relay_state for m in states if m.relay_state in (PlantState.RELAY_INVERTER, PlantState.RELAY_RECTIFIER)]
    changes = sum(a != b for a, b in zip(conn, conn[1:]))
    assert report_main([str(bag), "--out", str(tmp_path / "report")]) == 0
    summary = json.loads((tmp_path / "report" / "summary.json").read_text())
    assert summary["relay_switch_overs"] == changes and 3 <= changes <= 4 and summary["machine"]["kind"] == "spmsm"
    assert f"relay switch-overs:    {changes}" in res.stdout

    # the same Commands and rider against the PI family
    res = bike_command("replay", str(bag), "--config", str(_bike_config(tmp_path, "pi")),
                       "--record", str(tmp_path / "pi"))
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    bag_pi = next(p for p in (tmp_path / "pi").iterdir() if p.is_dir())
    assert command_timeline(bag_pi)[0] == command_timeline(bag)[0]
    assert {s.family for s in read_topic(bag_pi, "controller_status")} == {"pi"}
    res = bike_command("compare", str(bag), str(bag_pi), "--out", str(tmp_path / "ab"))
    assert res.returncode == 0, res.stderr[-2000:]
    assert (tmp_path / "ab" / "compare.html").exists()
