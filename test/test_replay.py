"""`./bike replay BAG [--config OTHER]`: the recorded Command timeline rides a fresh bike
(real node graph, lockstep) and is recorded again."""
import pathlib

import pytest
import yaml

from conftest import FAST_BATCHES, bike_command

from bike_session.bags import read_topic
from bike_session.replay import command_timeline

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _bag_in(folder: pathlib.Path) -> pathlib.Path:
    bags = [p for p in folder.iterdir() if p.is_dir()]
    assert len(bags) == 1, bags
    return bags[0]


def _values(bag, topic):
    """Decoded field values (CDR padding bytes are not data: they differ between runs)."""
    import dataclasses

    import numpy as np

    def value(v):
        if isinstance(v, np.ndarray):
            return (v.dtype.str, v.tobytes())
        if dataclasses.is_dataclass(v):
            return tuple(value(getattr(v, f.name)) for f in dataclasses.fields(v))
        return v
    return [value(m) for m in read_topic(bag, topic)]


@pytest.mark.slow
def test_replay_same_bike_is_identical_and_other_bike_gets_the_same_commands(tmp_path, ros_domain):
    # a workout with ERG ramps and steps: 2.5 s of it
    res = bike_command("run", "--workout", str(ROOT / "test/data/workouts/mrc_smoke.mrc"), "--ftp", "200",
                       "--duration", "2.5", "--record", str(tmp_path / "orig"))
    assert res.returncode == 0, res.stderr[-3000:]
    orig = _bag_in(tmp_path / "orig")

    res = bike_command("replay", str(orig), "--record", str(tmp_path / "same"))
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    same = _bag_in(tmp_path / "same")
    assert command_timeline(same)[0] == command_timeline(orig)[0]
    a, b = _values(orig, "plant_state"), _values(same, "plant_state")
    assert len(a) == len(b) > 2000 and a == b, "same bike, same rider: bit-identical replay"
    a = read_topic(orig, "plant_state")

    # another controller: half the hysteresis band of the current loop
    cfg = yaml.safe_load((ROOT / "config/bldc_default.yaml").read_text())
    cfg["/**"]["ros__parameters"]["controller"]["hysteresis_a"] = 0.75
    cfg["/**"]["ros__parameters"]["load"]["rider_target_cadence_rpm"] = 100.0     # must NOT be used
    other_cfg = tmp_path / "other.yaml"
    other_cfg.write_text(yaml.safe_dump(cfg))
    res = bike_command("replay", str(orig), "--config", str(other_cfg), "--record", str(tmp_path / "other"))
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    other = _bag_in(tmp_path / "other")
    assert command_timeline(other)[0] == command_timeline(orig)[0], "the same Command timeline"
    c = read_topic(other, "plant_state")
    assert len(c) == len(a) and any(x.speed_rad_s != y.speed_rad_s for x, y in zip(a, c))
    # the recorded rider (target cadence 80 rpm), not the other config's
    written = yaml.safe_load(next((tmp_path / "other").glob("replay_*_config.yaml")).read_text())
    params = written["/**"]["ros__parameters"]
    assert params["load"]["rider_target_cadence_rpm"] == 80.0
    assert params["controller"]["hysteresis_a"] == 0.75


def test_replay_refuses_bad_input_with_one_error(bike_cli, tmp_path):
    res = bike_cli("replay", str(tmp_path / "missing"))
    assert res.returncode == 2 and res.stderr.count("error:") == 1 and "does not exist" in res.stderr
    res = bike_cli("replay", str(ROOT / "config"))
    assert res.returncode == 2 and res.stderr.count("error:") == 1
    res = bike_cli("replay", "--help")
    assert res.returncode == 0 and "--config" in res.stdout and "--load" in res.stdout
    # --load config without --config rode the recorded load (the same either way) without a word
    res = bike_cli("replay", str(tmp_path / "missing"), "--load", "config", "--record", str(tmp_path / "r"))
    assert res.returncode == 2 and res.stderr.count("error:") == 1 and "--load config needs --config" in res.stderr
    assert not (tmp_path / "r").exists()


def test_a_replayed_timeline_keeps_the_road_a_training_app_gave():
    from bike_session.profiles import parse_profile
    from bike_session.replay import profile_from_timeline
    s = 1_000_000_000
    app = (0.004, 0.51, 2.5)
    timeline = [(0, 0.6, 3, 0.0, None), (s, 0.6, 3, 0.0, app), (2 * s, 0.7, 3, 0.0, app), (3 * s, 0.7, 3, 0.0, None)]
    doc = profile_from_timeline(timeline, 4.0, "r")
    assert [seg.get("road") for seg in doc["segments"]] == [
        None, {"crr": 0.004, "cw_kg_m": 0.51, "wind_mps": 2.5}, None, "config"]
    p = parse_profile(doc)
    for t, _c, _m, _g, r in timeline:
        assert p.road_at(t * 1e-9) == r


def test_a_replayed_timeline_keeps_the_riders_cadence_targets():
    from bike_session.profiles import parse_profile
    from bike_session.replay import profile_from_timeline
    s = 1_000_000_000
    timeline = [(0, 0.2, 2, 0.0, None, 95.0), (s, 0.2, 2, 0.0, None, 95.0), (2 * s, 0.2, 2, 0.0, None, 0.0),
                (3 * s, 0.3, 2, 0.0, None, 60.0)]
    doc = profile_from_timeline(timeline, 4.0, "r")
    assert [seg.get("cadence") for seg in doc["segments"]] == [95.0, None, 60.0]
    p = parse_profile(doc)
    for t, *_, cad in timeline:
        assert (p.cadence_at(t * 1e-9) or 0.0) == cad


def test_a_replayed_timeline_keeps_its_virtual_gears():
    """profile_from_timeline: a step per change of command, mode or gear; a gear is given where
    it changes (and stays in force), 0 included; the final Command's gear (the run's end, as
    the session sends it) is kept by one step past the end."""
    from bike_session.profiles import parse_profile
    from bike_session.replay import profile_from_timeline
    s = 1_000_000_000
    timeline = [(0, 0.6, 3, 0.0), (s, 0.6, 3, 2.1), (2 * s, 0.6, 3, 2.1), (3 * s, 0.7, 3, 2.1),
                (4 * s, 0.7, 3, 0.0), (5 * s, 0.0, 3, 3.5)]
    doc = profile_from_timeline(timeline, 5.0, "r")
    assert [seg.get("gear") for seg in doc["segments"]] == [None, 2.1, None, 0.0, 3.5]
    p = parse_profile(doc)
    for t, _c, _m, g in timeline:
        assert p.gear_at(t * 1e-9) == g
    assert [p.command_at(t * 1e-9)[0] for t, *_ in timeline[:-1]] == [c for _t, c, *_ in timeline[:-1]]


@pytest.mark.slow
def test_a_profiles_road_brakes_in_the_graph_is_recorded_and_replays(tmp_path, ros_domain):
    """A slope at 3 % on the config's road, then on a road with Zwift's Cw and a 4 m/s head
    wind (as a training app gives it): the brake follows each road's load, the Commands record
    the road, and a replay rides the same timeline, bit for bit."""
    import numpy as np

    from bike_controller.session_control import ModedController
    from bike_plant.config import load_config

    road = (0.006, 0.51, 4.0)
    prof = tmp_path / "windy.yaml"
    prof.write_text(yaml.safe_dump({"name": "windy", "mode": "slope", "segments": [
        {"kind": "step", "duration_s": 8, "target": 3},
        {"kind": "step", "duration_s": 6, "target": 3, "road": dict(zip(("crr", "cw_kg_m", "wind_mps"), road))}]}))
    res = bike_command("run", "--workout", str(prof), "--record", str(tmp_path / "orig"), *FAST_BATCHES)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    orig = _bag_in(tmp_path / "orig")
    timeline = command_timeline(orig)[0]
    assert {x[4] for x in timeline if x[0] < 8e9} == {None} and {x[4] for x in timeline if 8e9 <= x[0] < 14e9} == {road}

    law = ModedController(load_config(ROOT / "config/bldc_default.yaml")).law
    states, status = read_topic(orig, "plant_state"), read_topic(orig, "controller_status")

    def window(msgs, t0, t1):
        return [m for m in msgs if t0 <= m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 < t1]
    # settled: the last 2 s of each (lockstep, the same every run: the brake is within 6 % of the
    # road's per second from 2 s after the change of road on; the first road's takes ~6 s)
    for t0, r in ((6.0, None), (12.0, road)):
        brake = np.mean([-m.torque_em_nm for m in window(states, t0, t0 + 2)])
        v = np.mean([s.virtual_speed_mps for s in window(status, t0, t0 + 2)])
        law.set_road(r)
        expected = law.road_force_n(0.03, v) * law.mps_per_rad_s
        assert brake == pytest.approx(expected, rel=0.1), (r, brake, expected)
    assert law.road_force_n(0.03, 8.0) > 1.3 * ModedController(load_config(ROOT / "config/bldc_default.yaml")).law.road_force_n(0.03, 8.0)

    res = bike_command("replay", str(orig), "--record", str(tmp_path / "same"))
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    same = _bag_in(tmp_path / "same")
    assert command_timeline(same)[0] == timeline
    assert _values(same, "plant_state") == _values(orig, "plant_state")


@pytest.mark.slow
def test_a_replay_on_a_bike_of_other_ranges_rides_the_recorded_targets(tmp_path, ros_domain):
    """A BLDC ride at ERG 180 W (Command 0.177 of its 1017 W range) replayed with --config
    spmsm_default.yaml (ERG range 345 W) was sent Command 0.177: 61 W. Now the replay rides the
    recorded 180 W on the SPMSM; a recorded target beyond the other bike's range is one error."""
    prof = tmp_path / "erg.yaml"
    prof.write_text(yaml.safe_dump({"name": "erg", "segments": [
        {"kind": "step", "duration_s": 0.6, "target": 180, "mode": "erg"},
        {"kind": "step", "duration_s": 0.6, "target": 4, "mode": "slope"}]}))
    res = bike_command("run", "--workout", str(prof), "--record", str(tmp_path / "orig"), *FAST_BATCHES)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    orig = _bag_in(tmp_path / "orig")
    spmsm = ROOT / "config/spmsm_default.yaml"
    res = bike_command("replay", str(orig), "--config", str(spmsm), "--record", str(tmp_path / "spmsm"))
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    targets = {(s.mode, round(s.mode_target, 6)) for s in read_topic(_bag_in(tmp_path / "spmsm"), "controller_status")}
    assert targets == {(2, 180.0), (3, 0.04)}, targets

    prof.write_text(yaml.safe_dump({"name": "hard", "segments": [
        {"kind": "step", "duration_s": 0.3, "target": 600, "mode": "erg"}]}))
    res = bike_command("run", "--workout", str(prof), "--record", str(tmp_path / "hard"), *FAST_BATCHES)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    res = bike_command("replay", str(_bag_in(tmp_path / "hard")), "--config", str(spmsm),
                       "--record", str(tmp_path / "refused"))
    assert res.returncode == 2 and res.stderr.count("error:") == 1, res.stderr[-2000:]
    assert str(spmsm) in res.stderr and "600" in res.stderr and "t=0 s" in res.stderr, res.stderr
    assert not (tmp_path / "refused").exists()


@pytest.mark.slow
def test_a_replay_of_a_bag_that_ends_early_rides_what_was_recorded(tmp_path, ros_domain):
    """A recovered bag (its data file cut short, as by a kill or a full disk) holds the first part
    of the ride, and its session_info the session's whole duration: the replay rode the whole of
    it, the last recorded Command held for the rest (a 2.9 s part of a 6 s ride rode 6 s). Now it
    rides to the bag's end, says so, and what it rides is the recording's part, bit for bit."""
    from bike_session.bags import open_bag
    from bike_session.recover import recover

    res = bike_command("run", "--workout", str(ROOT / "config/profiles/all_modes.yaml"), "--duration", "3",
                       "--record", str(tmp_path / "orig"), *FAST_BATCHES)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    orig = _bag_in(tmp_path / "orig")
    cut = tmp_path / "cut"
    cut.mkdir()
    (data,) = orig.glob("*.mcap")
    (cut / data.name).write_bytes(data.read_bytes()[:data.stat().st_size // 2])
    rescued = pathlib.Path(recover(cut)["out"])
    with open_bag(rescued) as bag:
        end_s = round(bag.end_ns * 1e-9, 6)
    assert 0.5 < end_s < 2.5, end_s
    # its Commands (one per 0.1 s session period) may end before its other topics do: the replay
    # rides as far as they say (once, its states went on 0.2 s past the last Command's period)
    end_s = min(end_s, round(command_timeline(rescued)[0][-1][0] * 1e-9 + 0.1, 6))

    res = bike_command("replay", str(rescued), "--record", str(tmp_path / "again"))
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    assert f" {end_s:g} s, before its session's 3 s" in res.stdout, res.stdout[-2000:]
    last = read_topic(_bag_in(tmp_path / "again"), "plant_state")[-1].header.stamp
    assert last.sec + last.nanosec * 1e-9 == pytest.approx(end_s, abs=1e-9), last
    again = _values(_bag_in(tmp_path / "again"), "plant_state")
    # all but the last, which ends the run (its end-of-run flag set)
    assert len(again) > 100 and again[:-1] == _values(orig, "plant_state")[:len(again) - 1]


@pytest.mark.slow
def test_a_replay_rides_the_recorded_duration_on_a_config_with_a_session_duration(tmp_path, ros_domain):
    """--config OTHER whose session.duration_s (which the session takes before duration_s) was
    shorter than the recording: the replay's session ended at OTHER's 0.5 s and the rest of the
    1.2 s rode the session's final Command, not the recorded ERG step. Now the recorded timeline."""
    prof = tmp_path / "steps.yaml"
    prof.write_text(yaml.safe_dump({"name": "steps", "mode": "erg", "segments": [
        {"kind": "step", "duration_s": 0.4, "target": 100}, {"kind": "step", "duration_s": 0.8, "target": 200}]}))
    res = bike_command("run", "--workout", str(prof), "--record", str(tmp_path / "orig"), *FAST_BATCHES)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    orig = _bag_in(tmp_path / "orig")
    recorded = yaml.safe_load(command_timeline(orig)[1]["config_text"])
    recorded["/**"]["ros__parameters"]["session"]["duration_s"] = 0.5
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump(recorded))
    res = bike_command("replay", str(orig), "--config", str(other), "--record", str(tmp_path / "again"))
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    timeline = command_timeline(_bag_in(tmp_path / "again"))[0]
    assert timeline == command_timeline(orig)[0]
    assert sum(1 for t, c, m, *_ in timeline if t < 1.2e9 and m == 2 and c > 0.15) >= 7     # 200 W from 0.4 s


@pytest.mark.parametrize("last_command_s, replayed_s", [(1.3, 1.4), (1.45, 1.5)],
                         ids=["commands-end-first", "bag-ends-first"])
def test_a_replay_of_an_early_ending_bag_rides_only_as_far_as_its_commands_say(tmp_path, last_command_s, replayed_s):
    """A cut file's topics need not end together (CI, 2026-12-07: a recovered bag's Commands ended at
    1.3 s, its states at 1.5 s, and the replay held 1.3 s's Command to 1.5 s, unlike the ride). Each
    Command holds one session period (0.1 s): the replay ends there, or at the bag's end if earlier."""
    import json

    from bike_session.recorder_node import BagSink, build_typestore
    from bike_session.replay import prepare

    ts = build_typestore()
    Command, Header, Time = (ts.types[t] for t in ("bike_msgs/msg/Command", "std_msgs/msg/Header",
                                                     "builtin_interfaces/msg/Time"))
    Clock, String = ts.types["rosgraph_msgs/msg/Clock"], ts.types["std_msgs/msg/String"]
    config = ROOT / "config/bldc_default.yaml"
    sink = BagSink(tmp_path / "cut", "mcap", ts, [("/bike/command", "bike_msgs/msg/Command", True, False),
                                                  ("/bike/session_info", "std_msgs/msg/String", False, True),
                                                  ("/clock", "rosgraph_msgs/msg/Clock", True, False)])
    info = {"duration_s": 3.0, "period_s": 0.1, "config_text": config.read_text(), "config_path": str(config)}
    sink.write("/bike/session_info", 0, ts.serialize_cdr(String(data=json.dumps(info)), "std_msgs/msg/String"))
    stamps_ns = list(range(0, int(round(last_command_s * 1e9)) + 1, 100_000_000))
    if stamps_ns[-1] != int(round(last_command_s * 1e9)):
        stamps_ns.append(int(round(last_command_s * 1e9)))
    for t_ns in stamps_ns:
        stamp = Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9)
        msg = Command(header=Header(stamp=stamp, frame_id=""), command=0.3, mode=0, virtual_gear_ratio=0.0,
                      road_from_command=False, crr=0.0, cw_kg_m=0.0, wind_mps=0.0, cadence_rpm=0.0,
                      heart_rate_bpm=0.0)
        sink.write("/bike/command", t_ns, ts.serialize_cdr(msg, "bike_msgs/msg/Command"))
    for t_ns in range(0, 1_500_000_001, 50_000_000):                   # the other topics go on to 1.5 s
        clock = Clock(clock=Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9))
        sink.write("/clock", t_ns, ts.serialize_cdr(clock, "rosgraph_msgs/msg/Clock"))
    sink.close()
    prep = prepare(tmp_path / "cut", tmp_path / "out")
    assert prep["shortened_from"] == 3.0 and prep["duration_s"] == pytest.approx(replayed_s, abs=1e-9), prep
    assert prep["bag_end_s"] == 1.5
