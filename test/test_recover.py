"""Crash-safe recording: a recorder killed with kill -9 loses at most flush_period_s, and
`./bike bag recover` turns what survived into a normal bag (the original untouched)."""
from __future__ import annotations

import hashlib
import pathlib
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from bike_session.bags import BagError, open_bag, read_topic
from bike_session.recover import recover

ROOT = pathlib.Path(__file__).resolve().parents[1]

# A writer process: records Command messages stamped 1 ms apart in sim time, flushing every
# 0.1 s of sim time, paced at ~2x real time; prints the stamp of each message after writing it.
WRITER = textwrap.dedent("""
    import pathlib, sys, time
    from bike_session.recorder_node import BagSink, build_typestore
    ts = build_typestore()
    sink = BagSink(pathlib.Path(sys.argv[1]), sys.argv[2], ts,
                   [("/bike/command", "bike_msgs/msg/Command", True, False)], flush_period_s=0.1)
    Command = ts.types["bike_msgs/msg/Command"]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    for k in range(100000):
        t_ns = k * 1_000_000
        msg = Command(header=Header(stamp=Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9), frame_id=""),
                      command=0.5, mode=0, virtual_gear_ratio=0.0, road_from_command=False, crr=0.0,
                      cw_kg_m=0.0, wind_mps=0.0, cadence_rpm=0.0, heart_rate_bpm=0.0)
        sink.write("/bike/command", t_ns, ts.serialize_cdr(msg, "bike_msgs/msg/Command"))
        print(t_ns, flush=True)
        time.sleep(0.0005)
""")


def _digest(path: pathlib.Path) -> str:
    h = hashlib.sha256()
    for f in sorted(path.rglob("*")):
        if f.is_file():
            h.update(f.name.encode())
            h.update(f.read_bytes())
    return h.hexdigest()


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_killed_writer_loses_at_most_the_flush_period(tmp_path, storage):
    bag = tmp_path / "crashed"
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(bag), storage], stdout=subprocess.PIPE, text=True)
    last_ns = 0
    t_end = time.monotonic() + 30
    for line in proc.stdout:
        last_ns = int(line)
        if last_ns >= 1_500_000_000 or time.monotonic() > t_end:
            break
    proc.send_signal(signal.SIGKILL)            # no chance to close: metadata.yaml never written
    proc.wait(10)
    assert last_ns >= 1_500_000_000
    assert not (bag / "metadata.yaml").exists()
    with pytest.raises(BagError, match="not closed properly"):
        open_bag(bag)
    before = _digest(bag)
    res = recover(bag)
    assert _digest(bag) == before, "recovery must not modify the crashed bag"
    out = pathlib.Path(res["out"])
    assert out == tmp_path / "crashed.recovered"
    msgs = read_topic(out, "command")
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in msgs]
    # every message up to the recovered end is there, in order, none twice
    assert stamps == [k * 1_000_000 for k in range(len(stamps))]
    # lost: at most the flush period (0.1 s sim) plus what was written after the last printed line
    assert stamps[-1] >= last_ns - 100_000_000 - 1_000_000, (stamps[-1], last_ns)
    assert res["messages"] == len(msgs)
    with open_bag(out) as b:
        assert b.topics["/bike/command"][0] == "bike_msgs/msg/Command"
    # a second recovery to the same place is refused (nothing overwritten)
    with pytest.raises(BagError, match="already exists"):
        recover(bag)


def test_recover_refuses_bad_input_with_one_clear_error(tmp_path):
    with pytest.raises(BagError, match="does not exist"):
        recover(tmp_path / "nope")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(BagError, match="no .mcap or .db3"):
        recover(empty)
    garbage = tmp_path / "garbage"
    garbage.mkdir()
    (garbage / "garbage.mcap").write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 40)
    with pytest.raises(BagError, match="no complete message survived"):
        recover(garbage)
    assert not (tmp_path / "garbage.recovered").exists(), "no half-written output on failure"
    not_sqlite = tmp_path / "notsqlite"
    not_sqlite.mkdir()
    (not_sqlite / "notsqlite.db3").write_bytes(b"this is not a database" * 100)
    with pytest.raises(BagError, match="sqlite3"):
        recover(not_sqlite)
    assert not (tmp_path / "notsqlite.recovered").exists()


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_the_recovered_bag_offers_the_qos_the_crashed_one_recorded(tmp_path, storage):
    """rosbag2 replays a topic with its recorded offered QoS: recovery keeps each topic's (it
    recorded every topic that was not latched as volatile keep_last 1000, /command too)."""
    import yaml

    from bike_session.recorder_node import BagSink, build_typestore

    ts = build_typestore()
    topics = [("/bike/command", "bike_msgs/msg/Command", True, False),
              ("/bike/session_info", "std_msgs/msg/String", False, True),
              ("/clock", "rosgraph_msgs/msg/Clock", True, False)]
    sink = BagSink(tmp_path / "b", storage, ts, topics, durable={"/bike/command"})
    for topic, *_ in topics:
        sink.write(topic, 1, bytes.fromhex("00010000") + bytes(96))     # copied, never decoded here
    sink.flush()                      # then killed: no metadata.yaml
    res = recover(tmp_path / "b")
    meta = yaml.safe_load((pathlib.Path(res["out"]) / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    offered = {t["topic_metadata"]["name"]: [(q["durability"], q["depth"]) for q in
                                             t["topic_metadata"]["offered_qos_profiles"]]
               for t in meta["topics_with_message_count"]}
    assert offered == {"/bike/command": [("transient_local", 1000)], "/bike/session_info": [("transient_local", 1)],
                       "/clock": [("volatile", 1000)]}
    assert res["messages"] == 3


def test_recover_refuses_a_complete_bag(tmp_path):
    from bike_session.recorder_node import BagSink, build_typestore

    ts = build_typestore()
    sink = BagSink(tmp_path / "ok", "mcap", ts, [("/x", "std_msgs/msg/String", False, False)])
    sink.write("/x", 1, ts.serialize_cdr(ts.types["std_msgs/msg/String"](data="hi"), "std_msgs/msg/String"))
    sink.close()
    with pytest.raises(BagError, match="closed properly"):
        recover(tmp_path / "ok")


def _string_bag(path: pathlib.Path, count: int) -> pathlib.Path:
    """A closed MCAP bag at ``path`` of ``count`` std_msgs/String on /x ("m00000" x 50 ...), 1 ms
    apart; its data file."""
    from bike_session.recorder_node import BagSink, build_typestore

    ts = build_typestore()
    sink = BagSink(path, "mcap", ts, [("/x", "std_msgs/msg/String", False, False)], flush_period_s=0.1)
    for k in range(count):
        sink.write("/x", k * 1_000_000, ts.serialize_cdr(ts.types["std_msgs/msg/String"](data=f"m{k:05d}" * 50),
                                             "std_msgs/msg/String"))
    sink.close()
    (data,) = path.glob("*.mcap")
    return data


def test_a_closed_bag_whose_data_file_was_cut_short_is_recovered(tmp_path):
    """A bag copied or kept on a disk that ran out has its metadata.yaml but half its data
    file: opening it says where the rescue is, and recover, which refused it as "closed
    properly", rescues what survived."""
    data = _string_bag(tmp_path / "cut", 2000)
    with open(data, "r+b") as fh:
        fh.truncate(data.stat().st_size // 2)
    with pytest.raises(BagError, match="cannot open bag: .*bike bag recover rescues what survived") as err:
        open_bag(tmp_path / "cut")
    assert "\n" not in str(err.value)
    result = recover(tmp_path / "cut")
    assert 0 < result["messages"] < 2000
    got = read_topic(result["out"], "/x")
    assert [m.data for m in got] == [f"m{k:05d}" * 50 for k in range(len(got))]


def test_a_data_file_cut_inside_its_first_record_says_so(tmp_path):
    """mcap's EndOfFile carries no text: the error ended in "(EndOfFile: )"."""
    data = _string_bag(tmp_path / "cut", 200)
    with open(data, "r+b") as fh:
        fh.truncate(3000)
    (tmp_path / "cut" / "metadata.yaml").unlink()
    with pytest.raises(BagError) as err:
        recover(tmp_path / "cut")
    assert str(err.value).endswith("no complete message survived (stopped at a torn or invalid record "
                                   "(EndOfFile: the data ends inside it))"), err.value


@pytest.mark.parametrize("metadata", ["", "- 1\n", "rosbag2_bagfile_information:\n  version: 5\n"])
def test_a_bag_whose_metadata_is_damaged_says_so_and_is_recovered(tmp_path, metadata):
    """An empty or foreign metadata.yaml read "cannot open bag: Invalid bag metadata: 'NoneType' object
    is not subscriptable; if its data file was cut short, ./bike bag recover ...": the data file was whole."""
    _string_bag(tmp_path / "b", 20)
    (tmp_path / "b" / "metadata.yaml").write_text(metadata)
    with pytest.raises(BagError, match=r"cannot open bag: .*; its metadata\.yaml is damaged: ./bike bag recover "
                                       r"rebuilds the bag from the data files$"):
        open_bag(tmp_path / "b")
    assert recover(tmp_path / "b")["messages"] == 20


def test_a_whole_data_file_without_its_metadata_is_recovered(tmp_path):
    """A recorder killed after its MCAP was closed but before metadata.yaml was written (rosbags
    writes the file first), or a .mcap copied alone: the file's summary repeats the Schema and
    Channel records, and recover failed on the repeat with "cannot write the recovered bag ...
    (--out): WriterError: Connection can only be added once". Every message is recovered; a
    repeated channel id naming another topic is still one error."""
    from bike_session.recorder_node import BagSink, build_typestore

    ts = build_typestore()
    sink = BagSink(tmp_path / "whole", "mcap", ts, [("/x", "std_msgs/msg/String", False, False)])
    for k in range(50):
        sink.write("/x", k * 1_000_000, ts.serialize_cdr(ts.types["std_msgs/msg/String"](data=f"m{k}"),
                                                         "std_msgs/msg/String"))
    sink.close()
    (tmp_path / "whole" / "metadata.yaml").unlink()
    result = recover(tmp_path / "whole")
    assert result["messages"] == 50 and result["topics"] == {"/x": 50}, result
    assert [m.data for m in read_topic(result["out"], "/x")] == [f"m{k}" for k in range(50)]
    (data,) = (tmp_path / "whole").glob("*.mcap")
    body = data.read_bytes()
    at = body.rindex(b"\x02\x00\x00\x00/x")      # the summary's Channel record: its topic string
    other = tmp_path / "other"
    other.mkdir()
    (other / data.name).write_bytes(body[:at] + b"\x02\x00\x00\x00/y" + body[at + 6:])
    with pytest.raises(BagError, match="channel 1 .*'/y'.*'/x'|channel 1 .*'/x'.*'/y'"):
        recover(other)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_failure_to_write_the_recovered_bag_is_not_taken_for_a_torn_recording(tmp_path, monkeypatch, storage):
    """The source readers take any exception inside their loop for the torn tail of the crashed
    recording: an --out under a regular file was "no complete message survived (... NotADirectoryError)",
    and a write failing mid-way (a full disk) ended the copy early yet reported "recovered N
    messages". Either is one BagError naming the new bag and --out, and nothing is left of it."""
    from rosbags.rosbag2 import Writer

    from bike_session.recorder_node import BagSink, build_typestore

    ts = build_typestore()
    sink = BagSink(tmp_path / "b", storage, ts, [("/x", "std_msgs/msg/String", False, False)], flush_period_s=1.0)
    for k in range(50):
        sink.write("/x", k, ts.serialize_cdr(ts.types["std_msgs/msg/String"](data=str(k)), "std_msgs/msg/String"))
    sink.flush()                                 # then the process "dies"
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    with pytest.raises(BagError, match=r"cannot write the recovered bag .*a_file/r \(--out\): NotADirectoryError"):
        recover(tmp_path / "b", blocker / "r")
    real_write, calls = Writer.write, []

    def full_disk(self, *args, **kwargs):
        calls.append(1)
        if len(calls) > 10:
            raise OSError(28, "No space left on device")
        return real_write(self, *args, **kwargs)

    monkeypatch.setattr(Writer, "write", full_disk)
    with pytest.raises(BagError, match=r"cannot write the recovered bag .*r \(--out\): OSError: .*No space left"):
        recover(tmp_path / "b", tmp_path / "r")
    assert not (tmp_path / "r").exists(), "no half-written output on failure"


def test_cli_bag_recover(tmp_path):
    from bike_session.recorder_node import BagSink, build_typestore

    ts = build_typestore()
    sink = BagSink(tmp_path / "b", "mcap", ts, [("/x", "std_msgs/msg/String", False, False)], flush_period_s=1.0)
    for k in range(3):
        sink.write("/x", k, ts.serialize_cdr(ts.types["std_msgs/msg/String"](data=str(k)), "std_msgs/msg/String"))
    sink.flush()                                 # as the node's timer does; then the process "dies"
    run = subprocess.run([str(ROOT / "bike"), "bag", "recover", str(tmp_path / "b"), "--out", str(tmp_path / "r")],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "recovered 3 messages" in run.stdout
    assert [m.data for m in read_topic(tmp_path / "r", "/x")] == ["0", "1", "2"]
    again = subprocess.run([str(ROOT / "bike"), "bag", "recover", str(tmp_path / "b"), "--out", str(tmp_path / "r")],
                           capture_output=True, text=True, timeout=120)
    assert again.returncode == 2 and again.stderr.count("error:") == 1 and "already exists" in again.stderr


@pytest.mark.slow
def test_kill_9_of_the_real_recorder_mid_session(tmp_path):
    """The node graph (plant, controller, session, recorder: separate processes, real DDS),
    the recorder killed with SIGKILL mid-session; the recovered bag holds every batch from
    the start up to at most 1 s of sim time before the kill, plus the session metadata."""
    from node_harness import CONFIG, Collector, NodeProcess, stop_all

    from bike_msgs.msg import PlantState

    from bike_session import domains
    domain = domains.claim()
    col = Collector(domain, {"plant_state": PlantState})
    procs = []
    try:
        rec = NodeProcess("bike_session", "recorder_node", domain,
                          {"record_dir": str(tmp_path), "bag_name": "crash", "flush_period_s": 0.5})
        procs.append(rec)
        procs.append(NodeProcess("bike_plant", "plant_node", domain,
                                 {"duration_s": 60.0, "recorder_window_batches": 50, "recorder_timeout_s": 2.0}))
        # as `./bike run --record` starts it: its first answer waits until the recorder reads
        # its topics (a graph at 2x real time outruns the discovery of a starved machine)
        procs.append(NodeProcess("bike_controller", "controller_node", domain, {"recorder_window_batches": 50}))
        procs.append(NodeProcess("bike_session", "session_node", domain,
                                 {"duration_s": 60.0, "config_path": str(CONFIG)}))
        states = col.data["plant_state"]
        col.wait_for(lambda: states and states[-1].seq >= 2500, 60, "2.5 s of recorded session", procs)
        rec.signal(signal.SIGKILL)
        seq_at_kill = int(states[-1].seq)
        rec.wait(5.0)
        # the plant notices, says why, and goes on unrecorded
        col.wait_for(lambda: states[-1].faults & PlantState.FAULT_RECORDER_LOST, 10, "FAULT_RECORDER_LOST",
                     procs[1:])
    finally:
        stop_all(procs)
        col.close()
    bag = tmp_path / "crash"
    assert not (bag / "metadata.yaml").exists()
    res = recover(bag)
    plant = read_topic(res["out"], "plant_state")
    seqs = [int(m.seq) for m in plant]
    # a state left unanswered (controller still starting) is re-published with the same seq
    seqs = [k for i, k in enumerate(seqs) if i == 0 or k != seqs[i - 1]]
    assert seqs == list(range(len(seqs))), "every batch from the start, none missing"
    batch_s = plant[0].batch_periods * plant[0].control_period_s
    assert seqs[-1] >= seq_at_kill - round(1.0 / batch_s), (seqs[-1], seq_at_kill)
    info = read_topic(res["out"], "session_info")
    assert info and "config_text" in info[0].data and "software_version" in info[0].data
    assert len(read_topic(res["out"], "controller_status")) >= len(seqs) - 60
