"""Bag reading and the session summary, on bags written here with rosbags (no DDS)."""
import json
import shutil

import numpy as np
import pytest

from bike_session.bags import BagError, open_bag, plant_state_array, read_topic, read_topic_stamped
from bike_session.recorder_node import TOPICS, BagSink, build_typestore
from bike_session.report import format_summary, main, summarise

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
    assert s["fault_batches"] == {"interlock": 1, "command_timeout": 2, "overvoltage": 0, "bad_command": 0,
                                  "drive_lost": 0, "recorder_lost": 0}
    assert s["end_of_run"] is True
    assert s["final_soc"] == pytest.approx(0.51)
    assert s["session_state"] == "DONE" and s["profile_name"] == "unit"
    expected = {"/clock": N, "/bike/plant_state": N, "/bike/command": 3, "/bike/session_status": 1,
                "/bike/session_info": 1, "/bike/drive_command": 0, "/bike/controller_status": 0,
                "/bike/battery": 0, "/diagnostics": 0}
    assert s["messages"] == expected
    text = format_summary(s)
    assert "20.00 W" in text and "12.00 J" in text and "7.50 A" in text and "command_timeout 2" in text


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
    with pytest.raises(BagError, match="not closed properly"):
        summarise(unclosed)
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
    assert (out / "session.png").stat().st_size > 1000
