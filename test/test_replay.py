"""`./bike replay BAG [--config OTHER]`: the recorded Command timeline rides a fresh bike
(real node graph, lockstep) and is recorded again."""
import pathlib

import pytest
import yaml

from conftest import bike_command

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


def test_replay_refuses_bad_input_with_one_error(tmp_path, ros_domain):
    res = bike_command("replay", str(tmp_path / "missing"))
    assert res.returncode == 2 and res.stderr.count("error:") == 1 and "does not exist" in res.stderr
    res = bike_command("replay", str(ROOT / "config"))
    assert res.returncode == 2 and res.stderr.count("error:") == 1
    res = bike_command("replay", "--help")
    assert res.returncode == 0 and "--config" in res.stdout and "--load" in res.stdout


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
