"""Heart-rate ERG on the session side: a profile's ``heart_rate_bpm``, FIT heart-rate steps (bpm
and % of the rider's maximum, session.max_hr_bpm) and the Commands that carry the target. No
node graph: the session node's Command building runs on a node object without ROS."""
import array
import types
import warnings

import pytest

from fit_files import HEART_RATE_ERG, fit_workout_bytes, heart_rate_step

from bike_session.profiles import MODES, ModeUnits, ProfileError, describe_command, parse_profile
from bike_session.workouts import WorkoutError, WorkoutWarning, describe, load_workout

PMAX = 1016.68
UNITS = ModeUnits(erg_power_max_w=1000.0, grade_min=-0.2, grade_max=0.2, cadence_min_rpm=20.0, cadence_max_rpm=120.0)


def _step(**kw):
    return {"kind": "step", "duration_s": 1, **kw}


def _fit(tmp_path, steps, **kw):
    path = tmp_path / "hr.fit"
    path.write_bytes(fit_workout_bytes(steps))
    kw.setdefault("pmax_w", PMAX)
    return load_workout(path, **kw)


# --------------------------------------------------------------------------- profiles


def test_a_heart_rate_target_is_its_erg_segments_own_and_the_power_may_start_anywhere():
    p = parse_profile({"mode": "erg", "segments": [
        _step(heart_rate_bpm=140),                                   # no power: from the rider's
        _step(command=0.15, heart_rate_bpm=150.5),                   # from 0.15 Pmax
        _step(command=0.2),
        {"kind": "intervals", "repeat": 1, "heart_rate_bpm": 160, "on": {"duration_s": 1},
         "off": {"duration_s": 1, "command": 0.1, "heart_rate_bpm": 0}}]}, units=UNITS)
    assert [p.heart_rate_at(t + 0.5) for t in range(5)] == [140.0, 150.5, None, 160.0, None]
    assert [p.command_at(t + 0.5)[:2] for t in range(5)] == [(0.0, MODES["erg"]), (0.15, MODES["erg"]),
                                                             (0.2, MODES["erg"]), (0.0, MODES["erg"]),
                                                             (0.1, MODES["erg"])]
    assert p.heart_rate_at(-1.0) == 140.0 and p.heart_rate_at(100.0) is None
    target = parse_profile({"mode": "erg", "segments": [_step(target=150, heart_rate_bpm=140)]}, units=UNITS)
    assert target.command_at(0.5)[0] == pytest.approx(0.15), "a power target is where the power starts"


@pytest.mark.parametrize("doc, where, why", [
    ({"segments": [_step(command=0.2, heart_rate_bpm=140)]}, "segments[0]", "needs mode erg"),
    ({"mode": "slope", "segments": [_step(command=0.5, heart_rate_bpm=140)]}, "segments[0]",
     "this segment rides in mode slope"),
    ({"mode": "erg", "segments": [{"kind": "repeat", "repeat": 2, "heart_rate_bpm": 140, "segments": [
        _step(command=0.2), _step(command=0.2, mode="resistance")]}]},
     r"segments\[0\]\.segments\[1\]", r"given at segments\[0\]\.heart_rate_bpm"),
    ({"mode": "erg", "segments": [{"kind": "ramp", "duration_s": 1, "start": 0.1, "end": 0.2,
                                   "heart_rate_bpm": 140}]}, "segments[0]", "on a ramp"),
    ({"mode": "erg", "segments": [_step(heart_rate_bpm=30)]}, "segments[0].heart_rate_bpm", "outside"),
    ({"mode": "erg", "segments": [_step(heart_rate_bpm=221)]}, "segments[0].heart_rate_bpm", "outside"),
    ({"mode": "erg", "segments": [_step(heart_rate_bpm="high")]}, "segments[0].heart_rate_bpm",
     "expected a number"),
    ({"mode": "erg", "segments": [_step(heart_rate_bpm=float("nan"))]}, "segments[0].heart_rate_bpm",
     "must be finite"),
    ({"mode": "erg", "segments": [_step(command=0.2), _step()]}, "segments[1]", "missing key 'command'"),
])
def test_a_bad_heart_rate_target_is_one_error_naming_the_segment(doc, where, why):
    with pytest.raises(ProfileError, match=why) as info:
        parse_profile(doc, source="p.yaml")
    assert str(info.value).startswith("p.yaml: ") and where.replace("\\", "") in str(info.value)


def test_describe_command_names_the_heart_rate_target_and_where_the_power_starts():
    erg = MODES["erg"]
    assert describe_command(erg, 0.15, UNITS) == "erg 150 W"
    assert describe_command(erg, 0.15, UNITS, 140) == "erg heart rate 140 bpm, from 150 W"
    assert describe_command(erg, 0.0, UNITS, 140) == "erg heart rate 140 bpm, from the rider's power"
    assert describe_command(erg, 0.15, None, 140) == "erg heart rate 140 bpm, from 0.15"


# --------------------------------------------------------------------------- the session node's Commands


class _Publisher:
    def __init__(self):
        self.sent = []

    def publish(self, msg):
        self.sent.append(msg)

    def get_subscription_count(self):
        return 1


def _session(profile, period_s=0.5):
    """A session node object without rclpy.init: just what its Command building reads."""
    from bike_msgs.msg import Command
    from diagnostic_msgs.msg import DiagnosticStatus
    from bike_session.session_node import _make_node_class

    cls = _make_node_class()
    node = cls.__new__(cls)
    logged = []
    logger = types.SimpleNamespace(info=logged.append, warning=logged.append)
    node.__dict__.update(
        profile=profile, period_ns=int(period_s * 1e9), period_s=period_s,
        duration_ns=int(profile.duration_s * 1e9), live_from_j=[], live_targets=[], live_gear=None, live_leaf=-1,
        sent_gears=array.array("d"), pub_command=_Publisher(), _Command=Command, commands_published=0,
        readers_at_publish=0, done=False, next_j=0, units=UNITS, erg_shift_w=10.0, erg_max_w=1000.0, erg_bumps=0,
        config_gear=2.75, gear_table=(2.0, 2.75, 3.5), shifts=0, live_commands=0, logged=logged,
        sub_live=types.SimpleNamespace(topic_name="live_command"), _DiagnosticStatus=DiagnosticStatus)
    node.get_logger = lambda: logger
    node._publish_diag = lambda *a, **k: None
    return node


def _sent(node, j):
    node._publish_command(j)
    msg = node.pub_command.sent[-1]
    return msg.mode, round(msg.command, 6), msg.heart_rate_bpm, msg.cadence_rpm


def test_the_session_puts_the_segments_heart_rate_in_every_command_it_sends_for_it():
    pytest.importorskip("rclpy")
    p = parse_profile({"mode": "erg", "segments": [
        _step(command=0.2), _step(heart_rate_bpm=140, cadence=90), _step(command=0.15, heart_rate_bpm=150)]})
    node = _session(p)
    assert [_sent(node, j) for j in range(7)] == [
        (2, 0.2, 0.0, 0.0), (2, 0.2, 0.0, 0.0), (2, 0.0, 140.0, 90.0), (2, 0.0, 140.0, 90.0),
        (2, 0.15, 150.0, 0.0), (2, 0.15, 150.0, 0.0), (2, 0.0, 0.0, 0.0)]      # the run's end: none
    assert _sent(node, 3) == (2, 0.0, 140.0, 90.0), "a Command sent again repeats its target"


def test_a_live_command_carries_its_own_heart_rate_and_a_bad_one_changes_nothing():
    pytest.importorskip("rclpy")
    from bike_msgs.msg import Command
    p = parse_profile({"mode": "erg", "segments": [_step(duration_s=10, heart_rate_bpm=140)]})
    node = _session(p)
    node.next_j = 2
    node._on_live_command(Command(mode=Command.MODE_ERG, command=0.2))          # an app's power: 0 bpm
    node.next_j = 4
    node._on_live_command(Command(mode=Command.MODE_ERG, command=0.1, heart_rate_bpm=130.0))
    node.next_j = 6
    node._on_live_command(Command(mode=Command.MODE_SLOPE, command=0.5, heart_rate_bpm=130.0))   # refused
    assert [_sent(node, j)[:3] for j in (1, 2, 4, 6)] == [(2, 0.0, 140.0), (2, 0.2, 0.0), (2, 0.1, 130.0),
                                                          (2, 0.1, 130.0)]
    assert any("live: erg heart rate 130 bpm, from 100 W" in str(t) for t in node.logged)
    assert any("live Command rejected" in str(t) for t in node.logged)


def test_a_shift_press_in_heart_rate_erg_shifts_the_gear_not_the_power():
    pytest.importorskip("rclpy")
    from std_msgs.msg import Int8
    p = parse_profile({"mode": "erg", "segments": [_step(duration_s=2, command=0.2),
                                                   _step(duration_s=2, heart_rate_bpm=140)]})
    node = _session(p)
    node._on_shift(Int8(data=1))                                 # power ERG: +10 W
    assert node.erg_bumps == 1 and _sent(node, 0)[1] == 0.21
    node.next_j = 4
    node._on_shift(Int8(data=1))                                 # heart-rate ERG: a gear
    assert node.erg_bumps == 1 and node.shifts == 1 and node.gear_for(4) == 3.5
    assert _sent(node, 4)[1:3] == (0.0, 140.0)


# --------------------------------------------------------------------------- FIT workouts


def test_fit_heart_rate_steps_ride_erg_at_the_middle_of_their_range(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error", WorkoutWarning)          # nothing is ridden otherwise than written
        w = _fit(tmp_path, HEART_RATE_ERG, max_hr_bpm=185)
    segs = w.segments
    assert [s.label for s in segs] == ["Warm up", "Zone 2", "Tempo", "Cool down"]
    assert [s.mode for s in segs] == [MODES["erg"]] * 3 + [MODES["resistance"]]
    # 230-240: 130-140 bpm; 80-84 % of 185 bpm: 148-155.4 bpm
    assert segs[0].heart_rate_bpm is None and segs[3].heart_rate_bpm is None
    assert segs[1].heart_rate_bpm == pytest.approx(135.0) and segs[2].heart_rate_bpm == pytest.approx(151.7)
    assert segs[1].start == segs[1].end == 0.0 and segs[1].target_start_w is None, \
        "the controller starts from the rider's present power"
    assert segs[1].cadence_rpm == pytest.approx(90.0), "a secondary cadence target rides along"
    assert segs[0].target_start_w == 120.0 and segs[0].heart_rate_bpm is None
    assert w.heart_rate_at(400.0) == pytest.approx(135.0) and w.heart_rate_at(1600.0) == pytest.approx(151.7)
    assert w.heart_rate_at(0.0) is None and w.heart_rate_at(2300.0) is None and w.heart_rate_at(1e6) is None
    assert w.cadence_at(400.0) == pytest.approx(90.0)
    assert "HR 135 bpm" in describe(w) and "HR 152 bpm" in describe(w)
    assert w.info()["max_hr_bpm"] == 185.0, "session_info records the maximum the targets were scaled with"


def test_fit_heart_rate_steps_repeat_and_ride_erg_whatever_the_power_mode(tmp_path):
    steps = [heart_rate_step(60, 250), dict(duration_type="repeat_until_steps_cmplt", duration_value=0,
                                            target_type="open", target_value=3)]
    w = _fit(tmp_path, steps, mode="resistance")
    assert [(s.mode, s.heart_rate_bpm) for s in w.segments] == [(MODES["erg"], 150.0)] * 3


def test_a_heart_rate_zone_rides_the_middle_of_garmins_default_zone_with_a_warning(tmp_path):
    """FIT zones 1..5 without a zone table in the file: Garmin's default zones in % of the maximum
    (50-60 .. 90-100 %), their middle, and a warning that says so."""
    steps = [dict(duration_type="time", duration_value=60_000, target_type="heart_rate", target_value=zone)
             for zone in (2, 4)]
    with pytest.warns(WorkoutWarning, match="Garmin's default zones"):
        w = _fit(tmp_path, steps, max_hr_bpm=180)
    assert [s.heart_rate_bpm for s in w.segments] == [pytest.approx(117.0), pytest.approx(153.0)]   # 65, 85 %
    assert [s.mode for s in w.segments] == [MODES["erg"]] * 2


def test_percent_of_max_heart_rate_needs_session_max_hr_bpm(tmp_path):
    with pytest.raises(WorkoutError, match=r"hr\.fit: step 0: .*session\.max_hr_bpm"):
        _fit(tmp_path, [heart_rate_step(60, 70, 80)])
    assert _fit(tmp_path, [heart_rate_step(60, 70, 80)], max_hr_bpm=200).segments[0].heart_rate_bpm == 150.0
    assert _fit(tmp_path, [heart_rate_step(60, 240)]).segments[0].heart_rate_bpm == 140.0, "bpm need no maximum"


@pytest.mark.parametrize("step, kw, why", [
    (dict(duration_type="time", duration_value=60_000, target_type="heart_rate", target_value=3), {},
     r"step 0: heart-rate zone 3: give the rider's maximum heart rate \(session\.max_hr_bpm"),
    (dict(duration_type="time", duration_value=60_000, target_type="heart_rate", target_value=6),
     dict(max_hr_bpm=185), r"step 0: heart-rate zone 6: zones 1\.\.5 only"),
    (dict(duration_type="time", duration_value=60_000, target_type="heart_rate", target_value=0), {},
     r"step 0: heart-rate step without custom_target_value_low/high"),
    (heart_rate_step(60, 105), {}, r"step 0: heart-rate target 5.0 bpm outside \[40, 220\]"),
    (heart_rate_step(60, 340), {}, r"step 0: heart-rate target 240.0 bpm outside \[40, 220\]"),
    (heart_rate_step(60, 10), dict(max_hr_bpm=185), r"step 0: heart-rate target 18.5 bpm outside"),
    (heart_rate_step(60, 0), {}, r"step 0: heart-rate value must be a number > 0"),
    (heart_rate_step(60, 250), dict(max_hr_bpm=0), r"parameter max_hr_bpm must be a number > 0"),
    (heart_rate_step(60, 250), dict(max_hr_bpm=400), r"parameter max_hr_bpm must be .*<= 250"),
])
def test_what_a_heart_rate_step_cannot_ride_is_one_clear_error(tmp_path, step, kw, why):
    with pytest.raises(WorkoutError, match=why) as info:
        _fit(tmp_path, [step], **kw)
    assert "hr.fit" in str(info.value)


def test_the_run_passes_the_riders_maximum_heart_rate_to_the_workout(tmp_path, capsys):
    from bike_plant.config import load_config
    from bike_session import cli

    path = tmp_path / "hr.fit"
    path.write_bytes(fit_workout_bytes([heart_rate_step(60, 70, 80)]))
    opts = cli.build_parser().parse_args(["run", "--workout", str(path), "--max-hr", "200"])
    assert opts.max_hr == 200.0
    cfg = load_config(cli.repo_root() / "config" / "bldc_default.yaml")
    assert cli._load_workout_for_run(opts, cfg).segments[0].heart_rate_bpm == 150.0
    opts.max_hr = None
    assert cli._load_workout_for_run(opts, cfg) is None
    assert "session.max_hr_bpm" in capsys.readouterr().err
    opts.max_hr = -1.0
    assert cli._load_workout_for_run(opts, cfg) is None
    assert "--max-hr must be in (0, 250] bpm" in capsys.readouterr().err
    launch = (cli.repo_root() / "config" / "launch" / "bike.launch.yaml").read_text()
    assert "{name: session.max_hr_bpm, value: $(var max_hr)}" in launch


def test_a_replayed_timeline_keeps_its_heart_rate_targets():
    from bike_session.replay import profile_from_timeline
    s = 1_000_000_000
    timeline = [(0, 0.2, 2, 0.0, None, 0.0, 0.0), (s, 0.0, 2, 0.0, None, 0.0, 140.0),
                (2 * s, 0.0, 2, 0.0, None, 0.0, 140.0), (3 * s, 0.0, 2, 0.0, None, 0.0, 150.0)]
    doc = profile_from_timeline(timeline, 4.0, "r")
    assert [seg.get("heart_rate_bpm") for seg in doc["segments"]] == [None, 140.0, 150.0]
    p = parse_profile(doc)
    for t, *_, bpm in timeline:
        assert (p.heart_rate_at(t * 1e-9) or 0.0) == bpm


def test_the_session_status_shows_the_riders_targets_in_force():
    """SessionStatus carries what a head unit shows: the Command in force's gear, cadence target
    and heart-rate target (none once DONE)."""
    pytest.importorskip("rclpy")
    from bike_msgs.msg import SessionStatus
    p = parse_profile({"mode": "erg", "segments": [
        _step(command=0.2, gear=3.5), _step(heart_rate_bpm=140, cadence=90)]})
    node = _session(p)
    node.__dict__.update(_SessionStatus=SessionStatus, pub_status=_Publisher(), duration_s=p.duration_s)
    for j in range(4):
        node._publish_command(j)
    node._publish_status(int(0.6e9), SessionStatus.STATE_RUNNING)      # tau 0.5 s: the first step
    node._publish_status(int(1.2e9), SessionStatus.STATE_RUNNING)      # tau 1.0 s: the second
    node._publish_status(int(2.0e9), SessionStatus.STATE_DONE)
    first, second, done = node.pub_status.sent
    assert (first.virtual_gear_ratio, first.cadence_rpm, first.heart_rate_bpm) == (3.5, 0.0, 0.0)
    assert (second.virtual_gear_ratio, second.cadence_rpm, second.heart_rate_bpm) == (3.5, 90.0, 140.0)
    assert (done.cadence_rpm, done.heart_rate_bpm, done.command) == (0.0, 0.0, 0.0)
