"""Bag reading and the session summary, on bags written here with rosbags (no DDS)."""
import atexit
import json
import math
import os
import pathlib
import shutil
import tempfile

import numpy as np
import pytest

from bike_session import domains
from bike_session.bags import BagError, open_bag, plant_state_array, read_topic, read_topic_stamped
from bike_session.recorder_node import TOPICS, BagSink, build_typestore
from bike_session.report import FAULT_BITS, format_summary, main, summarise
from conftest import ROOT, bike_command

NS = "/bike"
N = 11           # PlantState at t = 0.0, 0.1, ..., 1.0
DT_NS = 100_000_000


def _full(topic):
    return topic if topic.startswith("/") else f"{NS}/{topic}"


def _plant_state(i):
    from bike_msgs.msg import PlantState

    m = PlantState()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(i * DT_NS, 1_000_000_000)
    m.seq = i
    m.batch_periods = 20
    m.control_period_s = 5e-5
    m.machine, m.backend = "bldc", "sim"
    m.end_of_run = i == N - 1
    m.speed_rad_s = 10.0
    m.speed_rpm = 10.0 * 60 / (2 * np.pi)
    m.torque_em_nm = -2.0 if i else 0.0          # braking: 2 N m at 10 rad/s = 20 W
    m.load_torque_nm = 2.5
    m.phase_current_a = [1.0, -0.5, -0.5]
    m.current_samples_a = [0.0] * 60
    if i == 5:
        m.current_samples_a = [0.0] * 59 + [-7.5]
    m.dc_bus_v = 36.0
    m.battery_soc = 0.5 + 0.001 * i
    m.battery_current_a = 0.3
    t = i * 0.1
    m.energy_mech_in_j = 25.0 * t                # 25 W of rider power
    m.energy_battery_j = 12.0 * t
    m.energy_resistor_j = 3.0 * t
    m.energy_loss_j = 5.0 * t
    m.faults = {3: 2, 4: 2, 6: 1}.get(i, 0)       # two timeout batches, one interlock batch
    m.interlock_blanked_count = 4 if i >= 6 else 0
    return m


def write_bag(path, storage="mcap"):
    """A small bag as the recorder would write it (rclpy messages serialized to CDR)."""
    from bike_msgs.msg import Command, SessionStatus
    from rclpy.serialization import serialize_message
    from rosgraph_msgs.msg import Clock
    from std_msgs.msg import String

    topics = [(_full(t), m, h, t == "session_info") for t, m, h in TOPICS]
    sink = BagSink(path, storage, build_typestore(), topics)
    sink.write(_full("session_info"), 0, serialize_message(String(data=json.dumps({"profile_name": "x"}))))
    for i in range(N):
        c = Clock()
        c.clock.sec, c.clock.nanosec = divmod(i * DT_NS, 1_000_000_000)
        sink.write("/clock", i * DT_NS, serialize_message(c))
        sink.write(_full("plant_state"), i * DT_NS, serialize_message(_plant_state(i)))
    for j, value in enumerate((0.2, 0.4, 0.0)):
        cmd = Command(command=value, mode=Command.MODE_MOTORING if j == 1 else Command.MODE_RESISTANCE)
        cmd.header.stamp.nanosec = j * 500_000_000
        sink.write(_full("command"), j * 500_000_000, serialize_message(cmd))
    st = SessionStatus(profile_name="unit", state=SessionStatus.STATE_DONE, elapsed_s=1.0, duration_s=1.0, progress=1.0)
    st.header.stamp.sec = 1
    sink.write(_full("session_status"), 1_000_000_000, serialize_message(st))
    sink.close()
    return path


def test_the_report_counts_every_plant_fault_bit():
    """Each PlantState.FAULT_* bit has its fault-batch count under its own name (FAULT_PACK_EMPTY
    came without one: a ride on an empty pack said "fault batches: none")."""
    from bike_msgs.msg import PlantState

    bits = {name[len("FAULT_"):].lower(): getattr(PlantState, name) for name in dir(PlantState)
            if name.startswith("FAULT_")}
    assert FAULT_BITS == bits
    assert FAULT_BITS["pack_empty"] == 2048


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_summary_numbers(tmp_path, storage):
    bag = write_bag(tmp_path / "bag", storage)
    s = summarise(bag)
    assert s["plant_states"] == N
    assert s["duration_s"] == pytest.approx(1.0, abs=1e-12)
    assert s["mean_braking_power_w"] == pytest.approx(20.0, rel=1e-12)
    assert s["mean_rider_power_w"] == pytest.approx(25.0, rel=1e-12)
    assert s["energy_battery_j"] == pytest.approx(12.0, rel=1e-12)
    assert s["energy_battery_wh"] == pytest.approx(12.0 / 3600, rel=1e-12)
    assert s["energy_resistor_j"] == pytest.approx(3.0, rel=1e-12)
    assert s["energy_resistor_wh"] == pytest.approx(3.0 / 3600, rel=1e-12)
    assert s["energy_loss_j"] == pytest.approx(5.0, rel=1e-12)
    assert s["energy_mech_in_j"] == pytest.approx(25.0, rel=1e-12)
    assert s["peak_phase_current_a"] == 7.5
    assert s["interlock_blanked"] == 4
    assert s["timeouts"] == 2
    assert s["fault_batches"] == dict({k: 0 for k in FAULT_BITS}, interlock=1, command_timeout=2)
    assert s["end_of_run"] is True
    assert s["final_soc"] == pytest.approx(0.51)
    assert s["session_state"] == "DONE" and s["profile_name"] == "unit"
    expected = {"/clock": N, "/bike/plant_state": N, "/bike/command": 3, "/bike/session_status": 1,
                "/bike/session_info": 1, "/bike/drive_command": 0, "/bike/controller_status": 0,
                "/bike/battery": 0, "/diagnostics": 0, "/bike/drive_truth": 0}
    assert s["messages"] == expected
    text = format_summary(s)
    assert "20.00 W" in text and "12.00 J" in text and "7.50 A" in text and "command_timeout 2" in text
    assert "/bike/battery" in text and "drive_truth" not in text, "an empty optional topic is not listed"


def test_read_helpers(tmp_path):
    bag = write_bag(tmp_path / "bag")
    cmds = read_topic(bag, "command")                  # relative name
    assert [c.command for c in cmds] == [0.2, 0.4, 0.0]
    assert [c.mode for c in cmds] == [0, 1, 0]
    stamped = read_topic_stamped(bag, "/bike/command")
    assert [t for t, _ in stamped] == [0, 500_000_000, 1_000_000_000]
    ps = plant_state_array(bag)
    assert ps.dtype.names[0] == "time_s" and ps.size == N
    assert np.allclose(ps["time_s"], np.arange(N) * 0.1)
    assert list(ps["seq"]) == list(range(N))
    assert ps["phase_current_peak_a"][5] == 7.5 and ps["phase_current_peak_a"][0] == 1.0
    with open_bag(bag) as b:
        assert b.topics["/bike/plant_state"] == ("bike_msgs/msg/PlantState", N)
        assert b.duration_s == pytest.approx(1.0)
        info = [m for _, _, m in b.messages(["session_info"])]
        assert json.loads(info[0].data) == {"profile_name": "x"}
        with pytest.raises(BagError, match="no topic"):
            b.resolve("nope")


def test_bare_mcap_file(tmp_path):
    bag = write_bag(tmp_path / "bag")
    mcap_file = next(bag.glob("*.mcap"))
    assert [c.command for c in read_topic(mcap_file, "command")] == [0.2, 0.4, 0.0]
    assert summarise(mcap_file)["mean_braking_power_w"] == pytest.approx(20.0)


def test_corrupt_inputs(tmp_path, capsys):
    good = write_bag(tmp_path / "good")
    # 1. missing path
    with pytest.raises(BagError, match="does not exist"):
        summarise(tmp_path / "missing")
    # 2. a plain file that is no bag
    junk = tmp_path / "junk.txt"
    junk.write_text("hello")
    with pytest.raises(BagError, match="not a bag"):
        summarise(junk)
    # 3. garbage .mcap
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"\x89MCAP0\r\n" + b"\x00garbage" * 10)
    with pytest.raises(BagError):
        summarise(garbage)
    # 4. unclosed recording: data file but no metadata.yaml
    unclosed = tmp_path / "unclosed"
    shutil.copytree(good, unclosed)
    (unclosed / "metadata.yaml").unlink()
    with pytest.raises(BagError, match="not closed properly; ./bike bag recover .*unclosed rescues"):
        summarise(unclosed)
    # 4b. the folder a run records into (`./bike report runs` after make demo): its bags named
    runs = tmp_path / "runs"
    shutil.copytree(good, runs / "session_1")
    with pytest.raises(BagError, match=f"a folder holding the bag {runs / 'session_1'}: give that"):
        summarise(runs)
    shutil.copytree(good, runs / "session_2")
    with pytest.raises(BagError, match=f"a folder holding 2 bags: give one, e.g. {runs / 'session_2'}"):
        summarise(runs)
    # 5. metadata.yaml that is not a rosbag2 metadata file
    badmeta = tmp_path / "badmeta"
    shutil.copytree(good, badmeta)
    (badmeta / "metadata.yaml").write_text("just: [a, broken")
    with pytest.raises(BagError, match="cannot open bag"):
        summarise(badmeta)
    # 6. truncated data file
    trunc = tmp_path / "trunc"
    shutil.copytree(good, trunc)
    data = next(trunc.glob("*.mcap"))
    raw = data.read_bytes()
    data.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(BagError):
        summarise(trunc)
    # 7. the CLI entry: one error line, exit code 2, no traceback
    capsys.readouterr()
    assert main([str(trunc)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bike report: error: ") and err.count("\n") == 1 and "Traceback" not in err
    assert main([str(good)]) == 0
    assert "energy into battery" in capsys.readouterr().out
    assert main([str(good), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["timeouts"] == 2


def test_report_out_folder(tmp_path, capsys):
    good = write_bag(tmp_path / "good")
    out = tmp_path / "out"
    assert main([str(good), "--out", str(out)]) == 0
    assert json.loads((out / "summary.json").read_text())["energy_battery_j"] == pytest.approx(12.0)
    assert "energy into battery" in (out / "summary.txt").read_text()
    for name in CHARTS:
        assert (out / name).stat().st_size > 1000, name
    page = (out / "summary.html").read_text()
    assert page.count("data:image/png;base64,") == len(CHARTS) and "energy into battery" in page
    assert "wrote " + str(out / "summary.html") in capsys.readouterr().out


# ---------------------------------------------------------------- a session with modes (synthetic, exact)

CHARTS = ("power.png", "cadence.png", "torque_speed.png", "battery.png", "energy.png", "session.png")
RPM_PER_RAD_S = 60.0 / (2.0 * np.pi)
CONFIG_TEXT = """/**:
  ros__parameters:
    load:
      gear_ratio: 10.0
    controller:
      tmax_nm: 1.8
      base_speed_rpm: 3000.0
      pmax_w: 565.4866776461628
    mechanics:
      friction_nms: 0.0          # ERG power = braking power (test_erg_power_counts_the_bikes_friction)
"""
PMAX = 565.4866776461628
W = 100.0                      # motor speed [rad/s]
CADENCE = W * RPM_PER_RAD_S / 10.0
ROAD_MPS = W * 0.335 * 2.75 / 10.0   # the controller's virtual speed: gear 10, virtual gear 2.75, wheel 0.335 m


def session_mode(k, erg_targets=(90.0, 120.0)):
    """(mode, command, mode_target, saturated) decided at t = k ms: ERG 0-0.4 s (two targets),
    isokinetic 90 rpm 0.4-0.7 s (saturated), resistance C = 0.5 from 0.7 s."""
    if k < 400:
        target = erg_targets[0] if k < 200 else erg_targets[1]
        return 2, target / PMAX, target, False
    if k < 700:
        return 4, 0.7, 90.0, True                # 20 + 0.7 * (120 - 20) rpm
    return 0, 0.5, 0.5, False


def write_session_bag(path, n=1001, storage="mcap", config_text=CONFIG_TEXT, erg_targets=(90.0, 120.0),
                      status=True, plant_dups=False, conflict_at=None, typestore=None, status_type=None,
                      modes=None, virtual_mps=None, segment=None, friction=None, cadence=None, heart=None,
                      hr_target=None, lead=0, heard_at=None, truth=None, config_path=None):
    """A 1 kHz session of n PlantStates (t = i ms; with ``lead``, a drive on CAN: t = (i - lead) ms
    after ``lead`` PlantStates at t = 0, at speed 0 before the ``heard_at``-th): 100 rad/s, 1 N m
    of braking (100 W),
    rider 150 W, battery 80 W, resistor 5 W, losses 15 W (ledger); modes as session_mode()
    (or ``modes(k)``), ControllerStatus.virtual_speed_mps ``virtual_mps(k)`` when given (else
    ROAD_MPS, what a controller reports for 100 rad/s on CONFIG_TEXT's bike);
    with ``segment(k)``, a RUNNING SessionStatus every 100 ms in that profile segment;
    ``friction(k)``: the laws' (B, Tc) the statuses carry (else 0, 0); ``cadence(k)``: the
    Commands' rider cadence target (else 0); ``heart(k)``: the PlantStates' heart rate and
    ``hr_target(k)`` the Commands' heart-rate target (else 0, none); ``truth(k)``: an emulated
    drive's DriveTruth every 10 ms, (physics time [s], rider energy [J]) or None (no sample)."""
    from bike_msgs.msg import Command, ControllerStatus, PlantState, SessionStatus
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import BatteryState
    from std_msgs.msg import String

    topics = [(_full(t), m, h, t == "session_info") for t, m, h in TOPICS]
    sink = BagSink(path, storage, typestore or build_typestore(), topics)
    info = {"profile_name": "modes", "software_version": "test-1", "config_text": config_text}
    if config_path is not None:
        info["config_path"] = str(config_path)
    sink.write(_full("session_info"), 0, serialize_message(String(data=json.dumps(info))))
    ms = 1_000_000
    for i in range(n):
        t_ns = max(i - lead, 0) * ms
        m = PlantState()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
        m.seq = i
        m.machine, m.backend = ("bldc", "can") if lead else ("bldc", "sim")
        m.measured_by_drive = bool(lead)
        m.end_of_run = i == n - 1
        m.speed_rad_s = W if i >= (heard_at or 0) else 0.0
        m.speed_rpm = m.speed_rad_s * RPM_PER_RAD_S
        m.torque_em_nm = -1.0 if i else 0.0
        m.phase_current_a = [1.0, -0.5, -0.5]
        m.current_samples_a = [0.0] * 60
        if i == 333:
            m.current_samples_a = [0.0] * 30 + [-9.0] + [0.0] * 29
        m.hall_edge_counts = [i, i + 1] if i % 3 == 0 else []
        m.hall_edge_states = [1, 3] if i % 3 == 0 else []
        m.dc_bus_v = 50.0
        m.battery_soc = 0.5 + 0.01 * i / 1000
        t = t_ns * 1e-9
        m.energy_mech_in_j, m.energy_battery_j = 150.0 * t, 80.0 * t
        m.energy_resistor_j, m.energy_loss_j = 5.0 * t, 15.0 * t
        m.faults = 2 if i in (3, 4) else 0
        m.heart_rate_bpm = float(heart(i)) if heart else 0.0
        data = serialize_message(m)
        sink.write(_full("plant_state"), t_ns, data)
        if plant_dups:
            sink.write(_full("plant_state"), t_ns, data)
        if conflict_at == i:
            m.energy_mech_in_j += 1.0
            sink.write(_full("plant_state"), t_ns, serialize_message(m))
        if i < n - 1:
            mode, command, target, sat = modes(i) if modes else session_mode(i, erg_targets)
            if i % 100 == 0:
                c = Command(command=command, mode=mode, cadence_rpm=cadence(i) if cadence else 0.0,
                            heart_rate_bpm=float(hr_target(i)) if hr_target else 0.0)
                c.header.stamp = m.header.stamp
                sink.write(_full("command"), t_ns, serialize_message(c))
            if status:
                if status_type is not None:
                    sink.write(_full("controller_status"), t_ns, status_type(m.header.stamp, i, mode, command))
                else:
                    b_nms, dry_nm = friction(i) if friction else (0.0, 0.0)
                    s = ControllerStatus(seq=i, command=command, mode=mode, mode_target=target, mode_saturated=sat,
                                         virtual_speed_mps=virtual_mps(i) if virtual_mps else ROAD_MPS,
                                         friction_nms=b_nms, dry_friction_nm=dry_nm)
                    s.header.stamp = m.header.stamp
                    sink.write(_full("controller_status"), t_ns, serialize_message(s))
        if segment is not None and i % 100 == 0 and i < n - 1:
            st = SessionStatus(profile_name="modes", state=SessionStatus.STATE_RUNNING, segment_index=segment(i))
            st.header.stamp = m.header.stamp
            sink.write(_full("session_status"), t_ns, serialize_message(st))
        if truth is not None and i % 10 == 0 and truth(i) is not None:
            from bike_msgs.msg import DriveTruth
            physics_s, energy_j = truth(i)
            d = DriveTruth(physics_time_s=float(physics_s), rider_energy_j=float(energy_j))
            d.header.stamp = m.header.stamp
            sink.write(_full("drive_truth"), t_ns, serialize_message(d))
        if i % 10 == 0:
            b = BatteryState(voltage=50.0, current=1.6, percentage=m.battery_soc)
            b.header.stamp = m.header.stamp
            sink.write(_full("battery"), t_ns, serialize_message(b))
    sink.close()
    return path


SQRT250 = float(np.sqrt(250.0))       # ERG errors +10 W (0-0.2 s), -20 W (0.2-0.4 s)


def check_modes_summary(s):
    assert s["plant_states"] == 1001 and s["duration_s"] == pytest.approx(1.0)
    assert s["mean_braking_power_w"] == pytest.approx(100.0, rel=1e-9)
    assert s["mean_rider_power_w"] == pytest.approx(150.0, rel=1e-9)
    assert s["mean_cadence_rpm"] == pytest.approx(CADENCE, rel=1e-9)
    assert s["machine"]["gear_ratio"] == 10.0 and s["machine"]["tmax_nm"] == 1.8
    assert s["peak_phase_current_a"] == 9.0 and s["timeouts"] == 2
    modes = s["time_in_mode_s"]
    assert set(modes) == {"erg", "isokinetic", "resistance"}
    assert (modes["erg"], modes["isokinetic"], modes["resistance"]) == pytest.approx((0.4, 0.3, 0.3))
    tr = s["tracking"]
    erg, iso, res = tr["erg_power"], tr["isokinetic_cadence"], tr["resistance_torque"]
    assert erg["windows"] == 4 and erg["window_s"] == pytest.approx(0.1)
    assert erg["rms"] == pytest.approx(SQRT250, rel=1e-9) and erg["max_abs"] == pytest.approx(20.0, rel=1e-9)
    assert erg["mean"] == pytest.approx(-5.0, rel=1e-9) and erg["rms_batch"] == pytest.approx(SQRT250, rel=1e-9)
    assert erg["max_abs_batch"] == pytest.approx(20.0) and erg["mean_target"] == pytest.approx(105.0)
    assert iso["windows"] == 3 and iso["rms"] == pytest.approx(CADENCE - 90.0, rel=1e-9)
    assert iso["mean_target"] == pytest.approx(90.0)
    # Eq. 3 at C = 0.5 below wb: 0.5 * 1.8 = 0.9 N m; the machine brakes with 1.0 N m
    assert res["windows"] == 3 and res["rms"] == pytest.approx(0.1, rel=1e-9) and res["mean"] == pytest.approx(0.1)
    return tr


def test_slope_tracking_is_the_road_speed_against_the_virtual_bike(tmp_path):
    """slope_speed: the road speed of the cadence (wheel radius x virtual gear / gear ratio of
    the config) minus the virtual bike's speed, per 0.1 s window; statuses without a virtual
    speed (NaN) are left out rather than read as zero error."""
    from bike_session.report import analyse

    road_mps = W * 0.3 * 2.5 / 10.0
    config = CONFIG_TEXT + "    modes:\n      wheel_radius_m: 0.3\n      virtual_gear_ratio: 2.5\n"
    slope = lambda k: (3, 0.6, 0.04, k >= 500)                           # noqa: E731
    d = analyse(write_session_bag(tmp_path / "a", config_text=config, modes=slope,
                                  virtual_mps=lambda k: road_mps - (0.3 if k < 500 else -0.1)))
    tr = d.summary["tracking"]["slope_speed"]
    assert tr["unit"] == "m/s" and tr["windows"] == 10
    assert tr["rms"] == pytest.approx(np.sqrt(0.05), rel=1e-9) and tr["mean"] == pytest.approx(0.1, rel=1e-9)
    assert tr["max_abs"] == pytest.approx(0.3, rel=1e-9) and tr["saturated_fraction"] == pytest.approx(0.5)
    assert "tracking slope_speed:" in format_summary(d.summary)
    d = analyse(write_session_bag(tmp_path / "b", config_text=config, modes=slope,
                                  virtual_mps=lambda k: float("nan") if k < 500 else road_mps - 0.2))
    tr = d.summary["tracking"]["slope_speed"]
    assert tr["windows"] == 5 and tr["rms"] == pytest.approx(0.2, rel=1e-9) and tr["time_s"] == pytest.approx(1.0)
    d = analyse(write_session_bag(tmp_path / "c", config_text=config, modes=slope,
                                  virtual_mps=lambda k: float("nan")))
    assert "slope_speed" not in d.summary["tracking"] and d.summary["time_in_mode_s"]["slope"] == pytest.approx(1.0)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_modes_and_tracking_exact(tmp_path, storage):
    from bike_session.report import analyse

    d = analyse(write_session_bag(tmp_path / "bag", storage=storage))
    tr = check_modes_summary(d.summary)
    assert tr["isokinetic_cadence"]["saturated_fraction"] == pytest.approx(1.0)
    assert tr["erg_power"]["saturated_fraction"] == 0.0
    assert d.res_commands == {0.5: pytest.approx(0.3)}
    assert d.summary["software_version"] == "test-1" and d.summary["warnings"] == []
    text = format_summary(d.summary)
    assert "tracking erg_power:" in text and "rms 15.811 W" in text and "max 20.000 W" in text
    assert "mean cadence:          95.5 rpm  (gear ratio 10)" in text


def test_erg_power_counts_the_bikes_friction(tmp_path):
    """ERG holds the rider's power, so the report compares braking power + the bike's friction
    (the recorded config's figures) with the target: B 5e-4 N m s at 100 rad/s adds 5 W to the
    100 W brake, and the errors against 90 / 120 W become +15 / -15 W (+10 / -20 without it).
    The statuses carry the laws' figures (a spin-down changes them); an older bag's statuses
    have none, and the config's modes.friction_nms (the trainer's own loss figure) wins over
    the machine's."""
    from bike_session.report import analyse

    # the statuses say which friction the laws had (they win over the config's 0)
    s = analyse(write_session_bag(tmp_path / "a", friction=lambda k: (5.0e-4, 0.0))).summary
    erg = s["tracking"]["erg_power"]
    assert erg["rms"] == pytest.approx(15.0, rel=1e-9) and erg["mean"] == pytest.approx(0.0, abs=1e-9)
    assert s["friction"] == [{"t": 0.0, "friction_nms": 5.0e-4, "dry_friction_nm": 0.0}]
    # a spin-down at 0.2 s: B 0 -> 1e-3 (10 W at 100 rad/s): errors +10 W, then -20 + 10 W
    s = analyse(write_session_bag(tmp_path / "b", friction=lambda k: (0.0, 0.0) if k < 200 else (1.0e-3, 0.02))).summary
    erg = s["tracking"]["erg_power"]
    tc_w = 0.02 * np.tanh(100.0 / (1.0 / RPM_PER_RAD_S)) * 100.0      # Tc w: 2 W
    assert erg["mean"] == pytest.approx(0.5 * (10.0 + (-10.0 + tc_w)), rel=1e-9)
    assert [f["t"] for f in s["friction"]] == [0.0, 0.2]
    text = format_summary(s)
    assert "friction (the laws'): B 0.000e+00 N m s, Tc 0.0000 N m; then B 1.000e-03 N m s, Tc 0.0200 N m from 0.2 s" in text
    assert "(to keep it, in the config: modes: {friction_nms: 0.001, dry_friction_nm: 0.02})" in text
    # an older bag's statuses have no friction: the config's figures, modes.friction_nms first
    config = CONFIG_TEXT.replace("friction_nms: 0.0", "friction_nms: 5.0e-4")
    erg = analyse(_old_status_bag(tmp_path / "c", config_text=config)).summary["tracking"]["erg_power"]
    assert erg["rms"] == pytest.approx(15.0, rel=1e-9)
    config += "    modes:\n      friction_nms: 1.0e-3\n"
    erg = analyse(_old_status_bag(tmp_path / "d", config_text=config)).summary["tracking"]["erg_power"]
    assert erg["mean"] == pytest.approx(5.0, rel=1e-9)        # +20 / -10 W


def test_tracking_from_commands_when_there_is_no_controller_status(tmp_path):
    """No ControllerStatus (or one without mode_target): the mode and command come from the
    Command topic and the target from the config, with the same numbers."""
    s = summarise(write_session_bag(tmp_path / "bag", status=False))
    assert s["messages"]["/bike/controller_status"] == 0
    check_modes_summary(s)


def _old_status_bag(path, **kw):
    """write_session_bag with a ControllerStatus definition from before mode_target (and the
    fields after it)."""
    from bike_session.recorder_node import bike_msgs_msg_dir

    msg_dir = path.parent / f"{path.name}_msg"
    msg_dir.mkdir()
    for f in bike_msgs_msg_dir().glob("*.msg"):
        text = f.read_text()
        if f.stem == "ControllerStatus":
            text = text[:text.index("float64 mode_target")]
        (msg_dir / f.name).write_text(text)
    ts = build_typestore(msg_dir)
    cls = ts.types["bike_msgs/msg/ControllerStatus"]
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]

    def old_status(stamp, seq, mode, command):
        msg = cls(header=Header(stamp=Time(sec=stamp.sec, nanosec=stamp.nanosec), frame_id=""), seq=seq,
                  command=command, mode=mode, command_rejected=False, speed_est_rpm=0.0, torque_cmd_nm=0.0,
                  k_factor=0.8, ktg_nm_per_a=0.04, current_cmd_a=0.0, region=0, quadrant=2, prediction_error_a=0.0)
        return bytes(ts.serialize_cdr(msg, "bike_msgs/msg/ControllerStatus"))

    return write_session_bag(path, typestore=ts, status_type=old_status, **kw)


def test_older_controller_status_without_mode_target(tmp_path):
    """A bag recorded before ControllerStatus had mode_target: the embedded (older) definition
    decodes, the missing fields get their defaults and the target comes from the config."""
    bag = _old_status_bag(tmp_path / "bag")
    with open_bag(bag) as b:
        assert "mode_target" not in b.typestore.types["bike_msgs/msg/ControllerStatus"].__dataclass_fields__
    s = summarise(bag)
    assert s["messages"]["/bike/controller_status"] == 1000
    tr = check_modes_summary(s)
    assert tr["isokinetic_cadence"]["saturated_fraction"] == 0.0     # unknown in the old bag


def test_fast_field_reader_matches_the_typestore(tmp_path):
    """The CDR walker gives what rosbags' full decoder gives, field by field (strings of odd
    length, empty and full uint64 sequences in front of the wanted fields)."""
    from bike_session.report import BATTERY_SPEC, COMMAND_SPEC, PLANT_SPEC, STATUS_SPEC, FieldReader

    bag = write_session_bag(tmp_path / "bag", n=40)
    with open_bag(bag) as b:
        for topic, spec in (("plant_state", PLANT_SPEC), ("controller_status", STATUS_SPEC),
                            ("command", COMMAND_SPEC), ("battery", BATTERY_SPEC)):
            full = b.resolve(topic)
            reader = FieldReader(b.typestore, b.topics[full][0], spec)
            assert reader.fast is not None, topic
            raws = [raw for _, _, raw in b.messages([full], raw=True)]
            assert raws
            for raw in raws:
                assert reader.fast(raw) == reader.generic(raw), topic
    from bike_msgs.msg import PlantState
    from rclpy.serialization import serialize_message

    reader = FieldReader(build_typestore(), "bike_msgs/msg/PlantState", PLANT_SPEC)
    for machine, edges in (("b", []), ("bldc-x", [7]), ("spmsm", [1, 2, 3]), ("", [5])):
        m = PlantState(machine=machine, backend="s" * len(edges), hall_edge_counts=edges,
                       hall_edge_states=list(range(len(edges))), torque_em_nm=-1.25, energy_loss_j=3.5,
                       current_samples_a=[0.5, -2.5] * len(edges), interlock_blanked_count=9, seq=2 ** 40)
        raw = serialize_message(m)
        assert reader.fast(raw) == reader.generic(raw)
        got = dict(zip([p for p, *_ in PLANT_SPEC], reader.fast(raw)))
        assert got["torque_em_nm"] == -1.25 and got["energy_loss_j"] == 3.5 and got["seq"] == 2 ** 40
        assert got["current_samples_a"] == (2.5 if edges else 0.0) and got["interlock_blanked_count"] == 9


def test_repeated_plant_states_count_once(tmp_path):
    s = summarise(write_session_bag(tmp_path / "bag", plant_dups=True))
    assert s["plant_states"] == 1001 and s["plant_state_duplicates"] == 1001
    assert s["plant_state_conflicts"] == 0 and s["warnings"] == []
    check_modes_summary(s)                                  # fault batches not doubled, same powers
    s = summarise(write_session_bag(tmp_path / "bag2", conflict_at=500))
    assert s["plant_state_conflicts"] == 1
    assert any("more than one plant" in w for w in s["warnings"])


def test_report_files_and_progress(tmp_path, capsys, monkeypatch):
    from bike_session import report

    bag = write_session_bag(tmp_path / "bag")
    monkeypatch.setattr(report, "PROGRESS_MIN", 100)
    out = tmp_path / "out"
    assert main([str(bag), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("bike report: ")]
    assert len(lines) == 10 and lines[0].endswith("messages)") and " 10 % " in lines[0] and " 100 % " in lines[-1]
    saved = json.loads((out / "summary.json").read_text())
    assert saved["tracking"]["erg_power"]["rms"] == pytest.approx(SQRT250)
    for name in CHARTS:
        assert (out / name).stat().st_size > 5000, name
    assert (out / "summary.html").read_text().count("<img") == len(CHARTS)
    monkeypatch.setattr(report, "PROGRESS_MIN", 10 ** 9)
    assert main([str(bag)]) == 0
    assert "%" not in capsys.readouterr().err


def test_series_for_the_charts(tmp_path):
    """The binned series behind the charts: ERG target only where ERG rides, isokinetic
    target where that mode rides, cadence from the configured gear ratio, ledger energies."""
    from bike_session.report import analyse, series

    d = analyse(write_session_bag(tmp_path / "bag"))
    assert d.bin_s == 0.01 and d.n_bins == 100
    s = series(d)
    assert len(s["t"]) == 100 and s["t"][0] == pytest.approx(0.005)
    assert np.allclose(s["p_brake"], 100.0) and np.allclose(s["p_rider"], 150.0)
    assert np.allclose(s["cadence"], CADENCE)
    assert np.allclose(s["erg_target"][:20], 90.0) and np.allclose(s["erg_target"][20:40], 120.0)
    assert np.isnan(s["erg_target"][40:]).all()
    assert np.allclose(s["iso_target"][40:70], 90.0) and np.isnan(s["iso_target"][70:]).all()
    assert s["E_bat"][-1] == pytest.approx(80.0) and s["E_res"][49] == pytest.approx(2.5)
    assert np.allclose(s["bat_v"][::1], 50.0) and np.nanmax(s["ipk"]) == 9.0
    coarse = series(d, points=10)
    assert len(coarse["t"]) == 10 and np.allclose(coarse["erg_target"][:2], 90.0)
    assert coarse["E_bat"][-1] == pytest.approx(80.0) and np.allclose(coarse["p_brake"], 100.0)


def test_cadence_target_tracking_wherever_a_command_carries_one(tmp_path):
    """The Commands carry a cadence target of 90 rpm for the first 0.5 s, then none; the crank
    turns at 95.49 rpm (100 rad/s, gear 10): +5.49 rpm over 0.5 s, in any mode."""
    from bike_session.report import analyse
    s = analyse(write_session_bag(tmp_path / "a", cadence=lambda k: 90.0 if k < 500 else 0.0)).summary
    cad = s["tracking"]["cadence_target"]
    assert cad["time_s"] == pytest.approx(0.5) and cad["windows"] == 5
    assert cad["mean"] == pytest.approx(CADENCE - 90.0, rel=1e-9) and cad["mean_target"] == pytest.approx(90.0)
    assert "tracking cadence_target:" in format_summary(s)
    assert "cadence_target" not in analyse(write_session_bag(tmp_path / "b")).summary["tracking"]


def test_power_accuracy_compares_the_trainers_estimate_with_the_riders_ledger(tmp_path):
    """10 s at 100 rad/s: brake 100 W + modelled friction 5 W (B 5e-4) against the ledger's
    150 W rider: -45 W, -30 % over the one 10 s window; a 1 s session has no window."""
    from bike_session.report import analyse
    s = analyse(write_session_bag(tmp_path / "a", n=10001, friction=lambda k: (5.0e-4, 0.0))).summary
    acc = s["power_accuracy"]
    assert acc["windows"] == 1 and acc["window_s"] == pytest.approx(10.0)
    assert acc["mean_w"] == pytest.approx(-45.0, rel=1e-6) and acc["mean_pct"] == pytest.approx(-30.0, rel=1e-6)
    assert "trainer power error:   mean -45.00 W (-30.00 %)" in format_summary(s)
    assert analyse(write_session_bag(tmp_path / "b")).summary["power_accuracy"] is None


@pytest.mark.parametrize("heard_at", [20, 41])
def test_power_accuracy_counts_the_flywheel_from_where_a_drives_ledger_starts(tmp_path, heard_at):
    """A drive on CAN: the plant publishes PlantStates at t = 0 before it hears the drive (speed
    0), then the drive's first speed (100 rad/s) at t = 0 (an ODrive, armed later) or with the
    first batch (a VESC, alive at its first STATUS); the ledger starts there. That step is no
    energy of the rider's: the estimate (100 W brake, steady flywheel) is -50 W against the
    150 W ledger, as without the lead-in (it read ~+7 % in the first window of a CAN ride when
    1/2 J w^2 of the first speed counted)."""
    from bike_session.report import analyse
    s = analyse(write_session_bag(tmp_path / "a", n=10001 + 40, lead=40, heard_at=heard_at)).summary
    acc = s["power_accuracy"]
    assert acc["windows"] == 1
    # (heard with the first batch: its brake power takes the mean of 0 and 100 rad/s, 0.05 J less)
    assert acc["mean_w"] == pytest.approx(-50.0, abs=0.01) and acc["mean_pct"] == pytest.approx(-100.0 / 3.0, abs=0.01)


def emulated_truth(k):
    """An emulated drive's truth at t = k ms (physics time, rider energy): the rider gives 140 W (the
    ledger says 150 W); the emulator's physics ran 3 s before sim time started and runs 2 % faster
    than it (a loaded plant); at 3 s the plant pauses for 2 s of physics (a lost drive: no /clock,
    no sample; the rider spins up meanwhile, 1000 W); at 6 s the emulator restarts (physics and
    energy from 0); its samples start at 0.3 s (when the emulator first heard the plant's /clock) and
    end at 14 s."""
    t = k / 1000.0
    if not 0.3 <= t <= 14.0:
        return None
    if t >= 6.0:
        return 1.02 * (t - 6.0), 140.0 * 1.02 * (t - 6.0)
    physics_s = 3.0 + 1.02 * t + (2.0 if t > 3.0 else 0.0)
    return physics_s, 140.0 * (physics_s - (2.0 if t > 3.0 else 0.0)) + (2000.0 if t > 3.0 else 0.0)


def test_power_accuracy_against_an_emulated_drives_true_power(tmp_path):
    """With a DriveTruth in the bag the trainer's estimate (100 W) is compared with the rider's
    true power (140 W: -40 W, -28.57 %), not with the ledger (150 W: -50 W, the ledger +7.14 % off
    the truth), in the windows the truth covers: the first 10 s from 0.3 s (its pause and the
    emulator's restart left out), not the second (its samples end at 14 s: less than half of it).
    Powers over the physics' own time, so its 2 % faster clock changes nothing."""
    from bike_session.report import analyse
    s = analyse(write_session_bag(tmp_path / "a", n=20001, truth=emulated_truth)).summary
    acc = s["power_accuracy"]
    assert acc["against"] == "drive_truth" and acc["windows"] == 1 and acc["windows_without_truth"] == 1
    assert acc["true_rider_power_w"] == pytest.approx(140.0, rel=1e-9)
    assert acc["mean_w"] == pytest.approx(-40.0, rel=1e-9) and acc["mean_pct"] == pytest.approx(-200.0 / 7.0, rel=1e-9)
    assert acc["ledger"]["mean_w"] == pytest.approx(-50.0, rel=1e-9) and acc["ledger"]["windows"] == 1
    assert acc["ledger_error_pct"] == pytest.approx(50.0 / 7.0, rel=1e-9)
    assert acc["truth_samples"] == 1371 and acc["compared_s"] == pytest.approx(9.7)
    text = format_summary(s)
    assert "trainer power error:   mean -40.00 W (-28.57 %)" in text and "against the rider's true power" in text
    assert "true rider power 140.00 W (drive_truth" in text
    assert "it reads -50.00 W (-33.33 %), the ledger +7.14 % off" in text
    assert "1 window(s) without the truth left out" in text
    # truth that covers no whole window: the ledger's figures, said so
    s = analyse(write_session_bag(tmp_path / "b", n=20001, truth=lambda k: emulated_truth(k) if k >= 6000 else None)
                ).summary
    acc = s["power_accuracy"]
    assert acc["against"] == "ledger" and acc["windows"] == 2 and acc["windows_without_truth"] == 2
    assert acc["mean_w"] == pytest.approx(-50.0, rel=1e-9)
    assert "against the rider's ledger power" in format_summary(s)


def test_power_accuracy_of_a_drive_on_can_says_its_ledger_is_not_the_truth():
    """On CAN the ledger is the plant's own figure from the drive's estimates: the report says so."""
    acc = {"windows": 6, "window_s": 10.0, "mean_w": 0.01, "rms_w": 0.05, "max_abs_w": 0.08, "mean_pct": 0.0}
    assert "drive on CAN" not in format_summary({"power_accuracy": acc})
    text = format_summary({"power_accuracy": dict(acc, ledger_from_drive=True)})
    assert "drive on CAN: the ledger is the plant's, from the drive's torque estimate (kt Iq)" in text
    assert "not the rider's true power" in text


def test_erg_response_times_each_target_step():
    """0.1 s windows: ERG 100 W for 1 s, a step to 200 W that the ERG power reaches within
    5 % after 0.3 s and holds, a step to 150 W at 3 s that it never reaches before ERG ends at
    3.5 s, then resistance mode."""
    from bike_session.report import MODE_ERG, MODE_RESISTANCE, erg_response, format_summary

    n = 40
    target = np.r_[np.full(10, 100.0), np.full(20, 200.0), np.full(5, 150.0), np.full(5, np.nan)]
    power = np.r_[np.full(10, 100.0), [120.0, 150.0, 180.0, 195.0], np.full(16, 200.0), np.full(5, 200.0),
                  np.full(5, 50.0)]
    erg = np.isfinite(target)
    bins = {"dt": np.full(n, 0.1), "e_erg": power * 0.1,
            f"mode_dt{MODE_ERG}": np.where(erg, 0.1, 0.0), f"target_dt{MODE_ERG}": np.where(erg, target * 0.1, 0.0),
            f"mode_dt{MODE_RESISTANCE}": np.where(erg, 0.0, 0.1)}
    r = erg_response(bins, 0.1)
    assert r["steps"] == 2 and r["settled"] == 1
    assert r["settle_s"][0] == pytest.approx(0.3) and r["settle_s"][1] is None
    assert r["median_s"] == pytest.approx(0.3) and r["max_s"] == pytest.approx(0.3)
    assert "erg response:          2 target steps, 1 settled" in format_summary({"erg_response": r})
    bins[f"target_dt{MODE_ERG}"] = np.where(erg, 100.0 * 0.1, 0.0)        # no step: nothing to say
    assert erg_response(bins, 0.1) is None


# ---------------------------------------------------------------- heart rate

def hr_ride(k):
    """The rider's heart rate at t = k ms: none (a strap not yet on) until 0.3 s, 100 bpm until
    0.8 s, 149 until 1.5 s, then 152."""
    return 0.0 if k < 300 else (100.0 if k < 800 else (149.0 if k < 1500 else 152.0))


def hr_erg_ride(path, n=3001, heart=hr_ride, **kw):
    """3 s in ERG: no heart-rate target until 0.5 s, 150 bpm until 2.0 s (15 Commands, one
    stretch), then 120 bpm; the heart as hr_ride()."""
    return write_session_bag(path, n=n, modes=lambda k: (2, 0.2, 0.2 * PMAX, False), heart=heart,
                             hr_target=lambda k: 0.0 if k < 500 else (150.0 if k < 2000 else 120.0), **kw)


# the 10 ms bins of the 150 bpm stretch (0.5-2.0 s) from the first within 3 bpm (0.8 s): 69 bins
# 1 bpm off, the bin with the step to 152 (its last batch at (149 + 152) / 2) 0.85, 50 bins 2 off
HR_MAE_BPM = (69 * 1.0 + 0.85 + 50 * 2.0) / 120


def test_heart_rate_and_heart_rate_erg_stretches(tmp_path):
    from bike_session.report import analyse, series

    d = analyse(hr_erg_ride(tmp_path / "bag"))
    s = d.summary
    # the batches with a heart rate at both ends: 0.3-3.0 s, the steps' batches at their mean
    mean_bpm = (499 * 100.0 + 124.5 + 699 * 149.0 + 150.5 + 1500 * 152.0) / 2700
    assert s["mean_heart_rate_bpm"] == pytest.approx(mean_bpm, rel=1e-9) and s["max_heart_rate_bpm"] == 152.0
    assert d.hr_stretches == [(0.5, 2.0, 150.0), (2.0, math.inf, 120.0)]
    r = s["heart_rate_erg"]
    assert r["stretches"] == 2 and r["settled"] == 1 and r["tolerance_bpm"] == 3.0
    first, second = r["per_stretch"]
    assert first["target_bpm"] == 150.0 and first["start_s"] == pytest.approx(0.5)
    assert first["duration_s"] == pytest.approx(1.5) and first["hr_time_s"] == pytest.approx(1.5)
    assert first["settle_s"] == pytest.approx(0.3)
    assert first["mae_bpm"] == pytest.approx(HR_MAE_BPM, rel=1e-9) and first["max_abs_bpm"] == pytest.approx(2.0)
    assert second["target_bpm"] == 120.0 and second["duration_s"] == pytest.approx(1.0)
    assert second["settle_s"] is None and second["mae_bpm"] is None and second["max_abs_bpm"] is None
    assert r["median_settle_s"] == pytest.approx(0.3) and r["max_settle_s"] == pytest.approx(0.3)
    assert r["mae_bpm"] == pytest.approx(HR_MAE_BPM, rel=1e-9) and r["max_abs_bpm"] == pytest.approx(2.0)
    text = format_summary(s)
    assert f"heart rate:            mean {mean_bpm:.1f} bpm, max 152.0 bpm" in text
    assert "heart-rate ERG:        2 target stretch(es), 1 settled (within 3 bpm) after median 0.3 s" in text
    assert "  150 bpm from 0.5 s (1.5 s): settled after 0.3 s, then mean |error| 1.4 bpm, max 2.0 bpm" in text
    assert "  120 bpm from 2.0 s (1.0 s): never within 3 bpm" in text
    hr = series(d, points=None)["heart_rate"]
    assert np.isnan(hr[:30]).all() and np.allclose(hr[31:79], 100.0) and np.allclose(hr[150:], 152.0)
    json.dumps(s, allow_nan=False)                  # summary.json stays plain JSON


def test_heart_rate_part_absent_without_data_and_targets_only_in_erg(tmp_path):
    """No heart rate and no target: both figures None, nothing printed. A target in a mode other
    than ERG rules nothing (bike_msgs/Command); a target without a heart rate says so."""
    from bike_session.report import analyse

    s = analyse(write_session_bag(tmp_path / "a")).summary
    assert s["mean_heart_rate_bpm"] is None and s["max_heart_rate_bpm"] is None and s["heart_rate_erg"] is None
    assert "heart rate:" not in format_summary(s) and "heart-rate ERG" not in format_summary(s)
    s = analyse(write_session_bag(tmp_path / "b", hr_target=lambda k: 140.0)).summary      # ERG only until 0.4 s
    r = s["heart_rate_erg"]
    assert r["stretches"] == 1 and r["per_stretch"][0]["duration_s"] == pytest.approx(0.4)
    assert r["settled"] == 0 and r["per_stretch"][0]["hr_time_s"] == 0.0
    text = format_summary(s)
    assert "(no heart rate in the bag)" in text and "  140 bpm from 0.0 s (0.4 s): no heart rate" in text
    # a target the controller rejects (outside 40..220 bpm: the whole Command) rules nothing either
    s = analyse(write_session_bag(tmp_path / "c", hr_target=lambda k: 250.0)).summary
    assert s["heart_rate_erg"] is None


def _without_heart_rate(src, dst):
    """The bag ``src`` rewritten as recorded before PlantState and Command had heart_rate_bpm:
    their embedded definitions lack the field, and so do the messages."""
    from bike_session.recorder_node import bike_msgs_msg_dir

    msg_dir = dst.parent / f"{dst.name}_msg"
    msg_dir.mkdir()
    for f in bike_msgs_msg_dir().glob("*.msg"):
        lines = f.read_text().splitlines(keepends=True)
        if f.stem in ("PlantState", "Command"):
            lines = [ln for ln in lines if not ln.startswith("float64 heart_rate_bpm")]
        (msg_dir / f.name).write_text("".join(lines))
    old = build_typestore(msg_dir)
    topics = [(_full(t), m, h, t == "session_info") for t, m, h in TOPICS]
    sink = BagSink(dst, "mcap", old, topics)
    with open_bag(src) as bag:
        for topic, t_ns, raw in bag.messages(raw=True):
            msgtype = bag.topics[topic][0]
            if msgtype in ("bike_msgs/msg/PlantState", "bike_msgs/msg/Command"):
                msg = bag.typestore.deserialize_cdr(raw, msgtype)
                cls = old.types[msgtype]
                fields = {k: getattr(msg, k) for k in cls.__dataclass_fields__ if k != "__msgtype__"
                          and not k.isupper()}
                raw = old.serialize_cdr(cls(**fields), msgtype)
            sink.write(topic, t_ns, raw)
    sink.close()
    return dst


def test_older_bag_without_heart_rate_fields(tmp_path):
    """A bag recorded before heart_rate_bpm: its definitions decode, the report has no heart-rate
    part (the fields' default 0 is "none") and every other number is as before."""
    from bike_session.report import analyse

    bag = _without_heart_rate(hr_erg_ride(tmp_path / "new"), tmp_path / "old")
    with open_bag(bag) as b:
        for name in ("PlantState", "Command"):
            assert "heart_rate_bpm" not in b.typestore.types[f"bike_msgs/msg/{name}"].__dataclass_fields__
    d = analyse(bag)
    assert d.summary["mean_heart_rate_bpm"] is None and d.summary["heart_rate_erg"] is None
    assert d.hr_stretches == []
    assert d.summary["mean_rider_power_w"] == pytest.approx(150.0, rel=1e-9)
    assert "heart rate:" not in format_summary(d.summary) and "heart-rate ERG" not in format_summary(d.summary)


# ---------------------------------------------------------------- a real recorded session

REAL_RUNS: dict = {}


def real_session(kind: str) -> pathlib.Path:
    """A 2 s session ridden in the node graph and recorded (each kind runs once per test
    process; test_compare uses them too): 'resistance' = the default profile, 'erg' = the
    erg_smoke workout. A DDS domain of its own, so other runs on the host do not leak in."""
    if kind not in REAL_RUNS:
        tmp = pathlib.Path(tempfile.mkdtemp(prefix=f"bike_report_{kind}_"))
        atexit.register(shutil.rmtree, tmp, True)
        env = dict(os.environ, ROS_DOMAIN_ID=str(domains.claim()), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        extra = [] if kind == "resistance" else ["--workout", str(ROOT / "test/data/workouts/erg_smoke.erg"),
                                                 "--ftp", "200"]
        result = bike_command("run", *extra, "--duration", "2", "--record", str(tmp), env=env)
        assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
        REAL_RUNS[kind] = (next(p for p in tmp.iterdir() if p.is_dir()), result.stdout)
    return REAL_RUNS[kind][0]


@pytest.mark.slow
def test_report_of_a_real_session(tmp_path):
    bag = real_session("resistance")
    assert "tracking resistance_torque:" in REAL_RUNS["resistance"][1], "./bike run prints the new summary"
    out = tmp_path / "out"
    assert main([str(bag), "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    # independent numbers from the decoded messages
    ps = plant_state_array(bag)
    keep = np.r_[True, (np.diff(ps["time_s"]) != 0) | (np.diff(ps["seq"].astype(float)) != 0)]
    ps = ps[keep]
    dt = np.diff(ps["time_s"])
    p = -ps["torque_em_nm"][1:] * 0.5 * (ps["speed_rad_s"][1:] + ps["speed_rad_s"][:-1])
    assert s["plant_states"] == ps.size and s["duration_s"] == pytest.approx(2.0)
    assert s["mean_braking_power_w"] == pytest.approx(np.sum(p * dt) / 2.0, rel=1e-9)
    assert s["energy_battery_j"] == pytest.approx(ps["energy_battery_j"][-1] - ps["energy_battery_j"][0])
    assert s["peak_phase_current_a"] == pytest.approx(ps["phase_current_peak_a"].max())
    assert s["mean_cadence_rpm"] == pytest.approx(np.sum(0.5 * (ps["speed_rpm"][1:] + ps["speed_rpm"][:-1]) * dt)
                                                  / 2.0 / 35.0, rel=1e-9)
    assert s["machine"] == {"gear_ratio": 35.0, "tmax_nm": 2.941995, "base_speed_rpm": 3300.0, "pmax_w": 1016.68,
                            "source": "session_info config_text", "kind": "bldc"}
    assert s["relay_switch_overs"] == 0 and "relay switch-overs" not in REAL_RUNS["resistance"][1]
    assert s["time_in_mode_s"]["resistance"] == pytest.approx(2.0, abs=0.002)
    # resistance tracking against Eq. 3-4 computed here from the ControllerStatus commands
    status = read_topic(bag, "controller_status")
    st_t = np.array([m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in status])
    cmd = np.array([m.command for m in status])
    idx = np.searchsorted(st_t, ps["time_s"][:-1], side="right") - 1
    rpm = 0.5 * (ps["speed_rpm"][1:] + ps["speed_rpm"][:-1])
    ref = np.where(rpm < 3300.0, cmd[idx] * 2.941995, cmd[idx] * 1016.68 / (rpm / RPM_PER_RAD_S))
    err = -ps["torque_em_nm"][1:] - ref
    tr = s["tracking"]["resistance_torque"]
    assert tr["rms_batch"] == pytest.approx(np.sqrt(np.sum(err ** 2 * dt) / np.sum(dt)), rel=1e-6)
    assert tr["max_abs_batch"] == pytest.approx(np.abs(err).max(), rel=1e-9)
    assert tr["windows"] == 20 and tr["rms"] <= tr["rms_batch"] + 1e-12
    for name in CHARTS:
        assert (out / name).stat().st_size > 5000, name


def test_shift_response_times_the_flywheel_reaching_the_new_gear_and_its_overshoot():
    """A synthetic slope ride at 8 m/s: at t = 1 s an upshift 2.0 -> 2.5, so the slope tracking
    error jumps by 8 x (2.5 / 2.0 - 1) = 2 m/s and then runs as 2.4 exp(-x / 0.1) - 0.4: within
    5 % of the jump (0.1 m/s) after 0.1 ln(4.8) = 0.157 s, and 0.4 m/s past zero (20 % of the
    jump); a downshift at t = 3 s whose error stays at its jump (-1.6 m/s) is never felt."""
    from bike_session.report import MODE_SLOPE, shift_response
    bin_s = 0.01
    t = (np.arange(500) + 0.5) * bin_s
    x = t - 1.0
    err = np.where(t < 1.0, 0.0, np.where(t < 3.0, 2.4 * np.exp(-x / 0.1) - 0.4, -1.6))
    dt = np.full(t.size, bin_s)
    bins = {"dt": dt, "road_m": 8.0 * dt, f"err_dt{MODE_SLOPE}": err * dt, f"trk_dt{MODE_SLOPE}": dt}
    r = shift_response(bins, 0.0, bin_s, [(1.0, 2.0, 2.5, 3), (3.0, 2.5, 2.0, 3)])
    assert r["shifts"] == 2 and r["settled"] == 1 and r["settle_s"][1] is None
    assert r["settle_s"][0] == pytest.approx(0.1 * np.log(4.8), abs=bin_s)
    assert r["overshoot_pct_max"] == pytest.approx(20.0, abs=0.5)
    assert shift_response(bins, 0.0, bin_s, []) is None
    assert shift_response(bins, 0.0, bin_s, [(4.5, 2.0, 2.5, 3)], n_bins=300) is None    # beyond the range


def _refuse_constant(name):
    raise ValueError(f"not standard JSON: {name}")


def test_a_bag_without_a_state_of_charge_reports_na_and_standard_json(tmp_path, monkeypatch, capsys):
    """A drive on CAN has no battery model (PlantState.battery_soc NaN): the summary says n/a,
    and `--json` / summary.json stay standard JSON (a bare NaN there is refused by JSON parsers;
    `./bike report` of a bldc_can.yaml ride printed "final_soc": NaN)."""
    plain = _plant_state

    def without_soc(i):
        m = plain(i)
        m.battery_soc = math.nan
        return m

    monkeypatch.setitem(globals(), "_plant_state", without_soc)
    bag = write_bag(tmp_path / "bag")
    s = summarise(bag)
    assert s["final_soc"] is None
    assert "final battery SOC:     n/a" in format_summary(s)
    assert main([str(bag), "--json"]) == 0
    assert json.loads(capsys.readouterr().out, parse_constant=_refuse_constant)["final_soc"] is None
