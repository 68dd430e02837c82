"""`./bike run --workout FILE`: a workout file (.erg, .zwo, .fit, a profile) ridden in the node graph
(separate processes, DDS, lockstep), recorded; power targets in ERG mode; a bad file starts nothing."""
import json
import pathlib
import re

import numpy as np
import pytest

from conftest import FAST_BATCHES, bike_command, mean_erg_power_w

from bike_session.bags import read_topic, stamp_s

DATA = pathlib.Path(__file__).resolve().parent / "data" / "workouts"


@pytest.mark.slow
@pytest.mark.parametrize("name, title, text, first_w, target_w", [
    # erg_smoke.erg: 100 W warm-up ramp from t = 0 (FTP header 200 W, rider FTP 200: watts as written)
    ("erg_smoke.erg", "erg-smoke", "Warm up", 100.0, (100.0, 102.0)),
    # sweet_spot.fit (Garmin FIT, written by the FIT SDK): warm-up at 50-60 % FTP of 200 W, ridden at the mean
    ("sweet_spot.fit", "Sweet spot 2x8", "Easy spin to start", 110.0, (110.0, 110.001)),
])
def test_ride_a_workout_file_in_the_node_graph(tmp_path, ros_domain, name, title, text, first_w, target_w):
    result = bike_command("run", "--workout", str(DATA / name), "--ftp", "200", "--duration", "3",
                          "--record", str(tmp_path), *FAST_BATCHES)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert title in result.stdout and text in result.stdout, "workout summary and text event"
    bag = next(p for p in tmp_path.iterdir() if p.is_dir())
    commands = read_topic(bag, "command")
    assert commands and all(c.mode == 2 for c in commands[:-1]), "power targets ride in ERG mode"
    assert commands[0].command == pytest.approx(first_w / 1016.68)
    info = json.loads(read_topic(bag, "session_info")[0].data)
    assert info["workout"]["workout_format"] == name.rsplit(".", 1)[1] and info["profile_name"] == title
    status = read_topic(bag, "controller_status")
    late = [s for s in status if s.header.stamp.sec >= 2]
    assert all(s.mode == 2 and target_w[0] <= s.mode_target < target_w[1] for s in late)
    states = [m for m in read_topic(bag, "plant_state") if m.header.stamp.sec >= 2]
    power = mean_erg_power_w(states)
    assert power == pytest.approx(np.mean([s.mode_target for s in late]), rel=0.05), power


@pytest.mark.parametrize("bad", ["bad_xml.zwo", "decreasing.erg", "entity_bomb.zwo", "workout.txt", "truncated.fit"])
def test_a_bad_workout_file_starts_nothing(bike_cli, tmp_path, bad):
    result = bike_cli("run", "--workout", str(DATA / "bad" / bad), "--duration", "1", "--record", str(tmp_path))
    assert result.returncode == 2
    assert result.stderr.count("error:") == 1 and bad in result.stderr, result.stderr
    assert not any(tmp_path.iterdir()), "no bag, no node started"


@pytest.mark.slow
def test_every_mode_in_the_node_graph(tmp_path, ros_domain):
    """config/profiles/all_modes.yaml: resistance, ERG, slope up, isokinetic, slope down,
    ridden by the rider model through plant, controller and session processes."""
    root = DATA.parents[2]
    result = bike_command("run", "--workout", str(root / "config/profiles/all_modes.yaml"), "--record", str(tmp_path),
                          *FAST_BATCHES)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    bag = next(p for p in tmp_path.iterdir() if p.is_dir())
    states = read_topic(bag, "plant_state")
    status = read_topic(bag, "controller_status")

    def window(msgs, t0, t1):
        return [m for m in msgs if t0 <= m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 < t1]

    modes = [window(status, 4 * k + 3, 4 * k + 4) for k in range(5)]
    assert [{s.mode for s in w} for w in modes] == [{0}, {2}, {3}, {4}, {3}]
    erg = window(states, 7, 8)
    assert mean_erg_power_w(erg) == pytest.approx(180.0, rel=0.05)
    assert modes[2][0].mode_target == pytest.approx(0.04)
    iso = window(states, 15, 16)
    assert np.mean([m.speed_rpm for m in iso]) / 35.0 == pytest.approx(70.0, abs=1.5)
    assert not any(s.mode_saturated for w in modes for s in w)
    assert all(m.faults == 0 for m in states)
    # the summary's slope tracking: the flywheel follows the virtual bike (0.002 m/s measured)
    slope = re.search(r"tracking slope_speed:\s+rms ([0-9.]+) m/s", result.stdout)
    assert slope and float(slope.group(1)) < 0.05, result.stdout[-3000:]


@pytest.mark.slow
def test_ride_a_zwift_file_in_the_node_graph(tmp_path, ros_domain):
    """A .zwo (Zwift) workout: imported, ridden in ERG mode by the rider model, recorded."""
    result = bike_command("run", "--workout", str(DATA / "over_unders.zwo"), "--ftp", "250", "--duration", "2",
                          "--record", str(tmp_path), *FAST_BATCHES)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    bag = next(p for p in tmp_path.iterdir() if p.is_dir())
    info = json.loads(read_topic(bag, "session_info")[0].data)
    assert info["workout"]["workout_format"] == "zwo"
    commands = read_topic(bag, "command")
    assert commands and all(c.mode == 2 for c in commands[:-1])
    status = [s for s in read_topic(bag, "controller_status") if s.header.stamp.sec >= 1]
    target = np.mean([s.mode_target for s in status])
    states = [m for m in read_topic(bag, "plant_state") if m.header.stamp.sec >= 1]
    assert mean_erg_power_w(states) == pytest.approx(target, rel=0.1)


def test_a_realtime_recording_starts_at_the_first_batch(tmp_path, ros_domain):
    """Realtime (wall-clock batches) with --record: the plant waits for the recorder before its
    first batch, so the bag holds the run from seq 0, not from whenever the recorder matched."""
    import yaml

    cfg = yaml.safe_load((DATA.parents[2] / "config" / "bldc_default.yaml").read_text())
    params = next(iter(cfg.values()))["ros__parameters"]
    params["sync_mode"] = "realtime"
    params["session"]["profile"] = str(DATA.parents[2] / "config" / params["session"]["profile"])
    path = tmp_path / "realtime.yaml"
    path.write_text(yaml.safe_dump(cfg))
    result = bike_command("run", "--config", str(path), "--duration", "1.5", "--record", str(tmp_path / "bags"))
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    bag = next(p for p in (tmp_path / "bags").iterdir() if p.is_dir())
    seqs = [int(m.seq) for m in read_topic(bag, "plant_state")]
    assert seqs[0] == 0, f"the recording starts at seq {seqs[0]}"
    assert seqs == list(range(len(seqs))), "a realtime state is missing from the bag"


@pytest.mark.slow
def test_the_rider_follows_a_zwift_files_cadence_and_erg_holds_the_power_and_a_replay_too(tmp_path, ros_domain):
    """A .zwo at 200 W (0.8 of FTP 250) with Cadence 95, then 65: the Commands carry the cadence,
    the plant's rider pedals at it (through the controller's DriveCommand, so lockstep stays
    exact), ERG's brake holds the power at both; `./bike replay` rides the same, bit for bit."""
    from bike_session.replay import command_timeline
    zwo = tmp_path / "cadence.zwo"
    zwo.write_text('<workout_file><name>cadence drill</name><workout>'
                   '<SteadyState Duration="6" Power="0.8" Cadence="95"/>'
                   '<SteadyState Duration="6" Power="0.8" Cadence="65"/></workout></workout_file>')
    result = bike_command("run", "--workout", str(zwo), "--ftp", "250", "--record", str(tmp_path / "orig"), *FAST_BATCHES)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    bag = next((tmp_path / "orig").iterdir())
    timeline = command_timeline(bag)[0]
    assert {x[5] for x in timeline if x[0] < 6e9} == {95.0} and {x[5] for x in timeline if 6e9 <= x[0] < 12e9} == {65.0}
    states = read_topic(bag, "plant_state")
    # the last 3 s of each step (lockstep: the same every run; the rider is within 0.1 rpm of the
    # cadence 3 s after its change, from 66 rpm at the start and from 95 rpm)
    for t0, cadence in ((3.0, 95.0), (9.0, 65.0)):
        late = [m for m in states if t0 <= m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 < t0 + 3]
        assert np.mean([m.speed_rpm for m in late]) / 35.0 == pytest.approx(cadence, abs=1.5)
        assert mean_erg_power_w(late) == pytest.approx(200.0, rel=0.03)
    replay = bike_command("replay", str(bag), "--record", str(tmp_path / "same"))
    assert replay.returncode == 0, replay.stdout[-2000:] + replay.stderr[-3000:]
    same = next(p for p in (tmp_path / "same").iterdir() if p.is_dir())
    assert command_timeline(same)[0] == timeline
    assert [m.speed_rpm for m in read_topic(same, "plant_state")] == [m.speed_rpm for m in states]


def test_a_spin_down_in_the_node_graph_teaches_the_bike_its_friction(tmp_path, ros_domain):
    """A profile's `mode: spindown` segment ridden in the graph: the controller's friction figure
    is half the flywheel's (modes.friction_nms 5e-5 against 1e-4), the plant's rider is told
    through DriveCommand to spin up (he overshoots to ~94 rpm) and then to stop pedalling, the coast
    (sampled 85 -> 75 rpm, about 23 s in all) gives
    B within 1 %, and the ERG step after it holds the rider's 200 W; the report names the change."""
    import yaml

    from bike_session.report import format_summary, summarise
    doc = yaml.safe_load((DATA.parents[2] / "config" / "bldc_default.yaml").read_text())
    doc["/**"]["ros__parameters"].setdefault("modes", {}).update(friction_nms=5.0e-5, spindown_low_cadence_rpm=75.0)
    config = tmp_path / "bike.yaml"
    config.write_text(yaml.safe_dump(doc, sort_keys=False))
    profile = tmp_path / "spindown.yaml"
    # lockstep, so the same sim times every run: the spin-down is done at 26.4 s (23.4 s into its
    # segment, which was 32 s) and the ERG after it is within 0.1 W of 200 W from 2 s on
    profile.write_text("name: spin-down\nsegments:\n"
                       "  - {kind: step, mode: erg, target: 200, duration_s: 3}\n"
                       "  - {kind: step, mode: spindown, duration_s: 26}\n"
                       "  - {kind: step, mode: erg, target: 200, duration_s: 6}\n")
    result = bike_command("run", "--config", str(config), "--workout", str(profile), "--record", str(tmp_path / "runs"),
                          *FAST_BATCHES)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    bag = next((tmp_path / "runs").iterdir())
    status = read_topic(bag, "controller_status")
    assert status[0].friction_nms == 5.0e-5
    assert status[-1].friction_nms == pytest.approx(1.0e-4, rel=0.01), status[-1].friction_nms
    drive = read_topic(bag, "drive_command")
    stops = [d for d in drive if d.rider_stops_pedalling]
    assert stamp_s(stops[-1]) - stamp_s(stops[0]) > 5.0, "the rider was told to stop pedalling for the coast"
    states = read_topic(bag, "plant_state")
    coast = {d.seq for d in stops}
    assert all(m.load_torque_nm == 0.0 for m in states if m.seq - 1 in coast), "the rider's torque during the coast"
    # the rider's steady power: the brake's + the flywheel's true friction (the default config's 1e-4)
    first = mean_erg_power_w([m for m in states if 1.0 <= stamp_s(m) < 3.0])
    assert first == pytest.approx(204.3, abs=1.0), first
    last = mean_erg_power_w([m for m in states if stamp_s(m) >= 31.0])      # the ERG's last 4 s
    assert last == pytest.approx(200.0, abs=0.5), last
    text = format_summary(summarise(bag))
    assert "spindown 26.00 s" in text and "friction (the laws'): B 5.000e-05 N m s" in text
