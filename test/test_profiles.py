"""Workout profiles: every segment kind, nesting, purity, and every malformed case."""
import math
import pathlib

import pytest

from bike_session.profiles import (MAX_PROFILE_BYTES, MODES, Profile, ProfileError, load_profile,
                                   parse_profile, parse_profile_text, shifted_gear)

ROOT = pathlib.Path(__file__).resolve().parents[1]


def write(tmp_path, text, name="p.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_mode_table_matches_command_msg():
    msg = (ROOT / "src" / "bike_msgs" / "msg" / "Command.msg").read_text()
    for name, value in MODES.items():
        assert f"MODE_{name.upper()}={value}" in msg
    assert MODES == {"resistance": 0, "motoring": 1, "erg": 2, "slope": 3, "isokinetic": 4, "spindown": 5}
    from bike_session.report import MODE_NAMES as REPORT_MODES
    assert REPORT_MODES == {v: k for k, v in MODES.items()}, "the report names every mode"
    from bike_controller.modes import MODE_NAMES as LAW_MODES
    assert LAW_MODES == {v: k for k, v in MODES.items()}, "the controller's modes are the session's"


def test_demo_profile():
    p = load_profile(ROOT / "config" / "profiles" / "demo_intervals.yaml")
    assert p.name == "demo_intervals"
    assert p.duration_s == 60.0
    assert len(p.segments) == 6
    assert p.command_at(0.0) == (0.2, 0, 0, "warm-up")
    assert p.command_at(5.0)[0] == pytest.approx(0.35)
    assert p.command_at(10.0) == (0.9, 0, 1, "effort")
    assert p.command_at(20.0) == (0.4, 0, 2, "recovery")
    assert p.command_at(30.0) == (0.9, 0, 3, "effort")
    assert p.command_at(45.0) == (0.4, 0, 4, "recovery")
    assert p.command_at(59.999) == (0.3, 0, 5, "cool-down")
    assert p.command_at(60.0) == (0.0, 0, 6, "end")
    assert "demo_intervals" in p.text


def test_step_and_defaults(tmp_path):
    p = load_profile(write(tmp_path, "segments:\n  - {kind: step, duration_s: 2, command: 0.5}\n"))
    assert p.name == "p"                      # file stem
    assert p.command_at(0) == (0.5, MODES["resistance"], 0, "step")
    assert p.command_at(1.999) == (0.5, 0, 0, "step")
    assert p.command_at(2.0) == (0.0, 0, 1, "end")
    assert p.command_at(-1.0) == (0.5, 0, 0, "step")   # before the start: first segment


def test_ramp_is_linear_and_half_open():
    p = parse_profile({"name": "r", "segments": [
        {"kind": "ramp", "duration_s": 4, "start": 0.0, "end": 1.0, "mode": "motoring", "label": "up"},
        {"kind": "ramp", "duration_s": 2, "start": 1.0, "end": 0.0}]})
    assert p.command_at(0.0) == (0.0, 1, 0, "up")
    assert p.command_at(1.0) == (0.25, 1, 0, "up")
    assert p.command_at(3.0) == (0.75, 1, 0, "up")
    assert p.command_at(4.0) == (1.0, 0, 1, "ramp")   # boundary belongs to the next segment
    assert p.command_at(5.0) == (0.5, 0, 1, "ramp")
    assert p.duration_s == 6.0


def test_intervals_yaml_on_off_keys(tmp_path):
    # bare `on:` / `off:` are booleans in YAML 1.1; they must still work
    text = """
name: iv
mode: motoring
segments:
  - kind: intervals
    repeat: 3
    label: block
    on: {duration_s: 1, command: 0.8}
    off: {kind: ramp, duration_s: 2, start: 0.4, end: 0.2, mode: resistance, label: easy}
"""
    p = load_profile(write(tmp_path, text))
    assert p.duration_s == 9.0
    assert len(p.segments) == 6
    assert p.command_at(0.5) == (0.8, 1, 0, "block")
    assert p.command_at(1.0) == (0.4, 0, 1, "easy")
    assert p.command_at(2.0)[0] == pytest.approx(0.3)
    assert p.command_at(3.0) == (0.8, 1, 2, "block")
    assert p.command_at(8.0)[:3] == (pytest.approx(0.3), 0, 5)
    assert [s.path for s in p.segments][:2] == ["segments[0].on (repeat 1/3)", "segments[0].off (repeat 1/3)"]


def test_nested_repeat():
    p = parse_profile({"segments": [
        {"kind": "step", "duration_s": 1, "command": 0.1, "label": "a"},
        {"kind": "repeat", "repeat": 2, "segments": [
            {"kind": "step", "duration_s": 1, "command": 0.2, "label": "b"},
            {"kind": "repeat", "repeat": 3, "mode": "motoring", "segments": [
                {"kind": "step", "duration_s": 0.5, "command": 0.3, "label": "c"},
                {"kind": "intervals", "repeat": 1, "on": {"duration_s": 0.25, "command": 1.0},
                 "off": {"duration_s": 0.25, "command": 0.0}},
            ]},
        ]},
        {"kind": "step", "duration_s": 1, "command": 0.9, "label": "z"},
    ]})
    # 1 + 2 * (1 + 3 * (0.5 + 0.25 + 0.25)) + 1 = 10 s
    assert p.duration_s == pytest.approx(10.0)
    assert len(p.segments) == 1 + 2 * (1 + 3 * 3) + 1
    labels = [s.label for s in p.segments]
    assert labels[:6] == ["a", "b", "c", "step", "step", "c"]
    assert p.command_at(2.0) == (0.3, 1, 2, "c")
    assert p.command_at(2.5) == (1.0, 1, 3, "step")
    assert p.command_at(2.75) == (0.0, 1, 4, "step")
    assert p.command_at(9.5) == (0.9, 0, 21, "z")
    starts = [s.start_s for s in p.segments]
    assert starts == sorted(starts)
    assert all(s.index == i for i, s in enumerate(p.segments))


def test_pure_function_of_time(tmp_path):
    p = load_profile(ROOT / "config" / "profiles" / "demo_intervals.yaml")
    q = load_profile(ROOT / "config" / "profiles" / "demo_intervals.yaml")
    times = [i * 0.37 for i in range(200)]
    forward = [p.command_at(t) for t in times]
    backward = [p.command_at(t) for t in reversed(times)][::-1]
    assert forward == backward == [q.command_at(t) for t in times]
    for cmd, mode, idx, label in forward:
        assert 0.0 <= cmd <= 1.0 and mode in (0, 1) and isinstance(label, str)
    with pytest.raises(ValueError):
        p.command_at(math.nan)


def test_timeline():
    p = parse_profile({"segments": [{"kind": "ramp", "duration_s": 1, "start": 0, "end": 1}]})
    tl = p.timeline(0.25)
    assert [round(t, 9) for t, _, _ in tl] == [0.0, 0.25, 0.5, 0.75, 1.0]
    assert [c for _, c, _ in tl] == pytest.approx([0.0, 0.25, 0.5, 0.75, 0.0])


BAD = [
    # (yaml text, expected element, expected words)
    ("segments:\n  - {kind: step, duration_s: 1}\n", "segments[0]", "missing key 'command'"),
    ("segments:\n  - {duration_s: 1, command: 0.5}\n", "segments[0]", "missing key 'kind'"),
    ("name: x\n", None, "missing key 'segments'"),
    ("segments:\n  - {kind: step, duration_s: 1, command: 1.5}\n", "segments[0].command", "[0, 1]"),
    ("segments:\n  - {kind: step, duration_s: 1, command: -0.1}\n", "segments[0].command", "[0, 1]"),
    ("segments:\n  - {kind: step, duration_s: 1, command: .nan}\n", "segments[0].command", "finite"),
    ("segments:\n  - {kind: step, duration_s: .inf, command: 0.1}\n", "segments[0].duration_s", "finite"),
    ("segments:\n  - {kind: step, duration_s: -1, command: 0.1}\n", "segments[0].duration_s", "> 0"),
    ("segments:\n  - {kind: step, duration_s: 0, command: 0.1}\n", "segments[0].duration_s", "> 0"),
    ("segments:\n  - {kind: sprint, duration_s: 1, command: 0.1}\n", "segments[0].kind", "unknown kind"),
    ("segments:\n  - {kind: step, duration_s: '1', command: 0.1}\n", "segments[0].duration_s", "expected a number"),
    ("segments:\n  - {kind: step, duration_s: true, command: 0.1}\n", "segments[0].duration_s", "expected a number"),
    ("segments:\n  - {kind: step, duration_s: 1, command: 0.1, mode: turbo}\n", "segments[0].mode", "unknown mode"),
    ("segments:\n  - {kind: step, duration_s: 1, command: 0.1, mode: 1}\n", "segments[0].mode", "unknown mode"),
    ("segments:\n  - {kind: step, duration_s: 1, command: 0.1, label: 3}\n", "segments[0].label", "expected a string"),
    ("segments:\n  - {kind: step, duration_s: 1, command: 0.1, gear: 9}\n", "segments[0].gear", "outside [0.3, 8]"),
    ("segments:\n  - {kind: step, duration_s: 1, command: 0.1, gear: -2}\n", "segments[0].gear", "outside [0.3, 8]"),
    ("segments:\n  - {kind: step, duration_s: 1, command: 0.1, gear: .nan}\n", "segments[0].gear", "finite"),
    ("segments:\n  - {kind: step, duration_s: 1, command: 0.1, gear: big}\n", "segments[0].gear", "expected a number"),
    ("segments:\n  - {kind: step, duration_s: 1, command: 0.1, comand: 2}\n", "segments[0]", "unknown key(s) comand"),
    ("segments:\n  - {kind: ramp, duration_s: 1, start: 0.1}\n", "segments[0]", "missing key 'end'"),
    ("segments:\n  - {kind: ramp, duration_s: 1, start: 0.1, end: 2}\n", "segments[0].end", "[0, 1]"),
    ("segments:\n  - {kind: intervals, repeat: 2, on: {duration_s: 1, command: 0.5}}\n", "segments[0]",
     "missing key 'off'"),
    ("segments:\n  - kind: intervals\n    repeat: 2\n    on: {duration_s: 1, command: 0.5}\n"
     "    off: {duration_s: 1, command: 7}\n", "segments[0].off.command", "[0, 1]"),
    ("segments:\n  - kind: intervals\n    repeat: 2\n    on: {duration_s: 1}\n    off: {duration_s: 1, command: 0}\n",
     "segments[0].on", "missing key 'command'"),
    ("segments:\n  - kind: intervals\n    repeat: 2\n    on: 5\n    off: {duration_s: 1, command: 0}\n",
     "segments[0].on", "expected a mapping"),
    ("segments:\n  - kind: intervals\n    repeat: 2\n    on: {kind: repeat, repeat: 1, segments: []}\n"
     "    off: {duration_s: 1, command: 0}\n", "segments[0].on.kind", "must be step or ramp"),
    ("segments:\n  - {kind: intervals, repeat: 0, on: {duration_s: 1, command: 0}, off: {duration_s: 1, command: 0}}\n",
     "segments[0].repeat", "must be in [1"),
    ("segments:\n  - {kind: intervals, repeat: 1.5, on: {duration_s: 1, command: 0}, off: {duration_s: 1, command: 0}}\n",
     "segments[0].repeat", "expected an integer"),
    ("segments:\n  - {kind: repeat, repeat: 2, segments: []}\n", "segments[0].segments", "empty list"),
    ("segments:\n  - {kind: repeat, repeat: 2, segments: {a: 1}}\n", "segments[0].segments", "expected a list"),
    ("segments:\n  - kind: repeat\n    repeat: 2\n    segments:\n      - {kind: step, duration_s: 1, command: 0.2}\n"
     "      - kind: repeat\n        repeat: 2\n        segments:\n          - {kind: step, duration_s: 1, command: 2}\n",
     "segments[0].segments[1].segments[0].command", "[0, 1]"),
    ("segments: []\n", "segments", "empty list"),
    ("segments: 3\n", "segments", "expected a list"),
    ("segments:\n  - 3\n", "segments[0]", "expected a mapping"),
    ("- a\n- b\n", None, "expected a mapping"),
    ("", None, "expected a mapping"),
    ("segments: [\n", None, "not valid YAML"),
    ("name: x\nsegments:\n  - {kind: step, duration_s: 1, command: 0.1}\ncolour: red\n", None, "unknown key(s) colour"),
    ("name: ''\nsegments:\n  - {kind: step, duration_s: 1, command: 0.1}\n", "name", "non-empty string"),
    ("mode: fast\nsegments:\n  - {kind: step, duration_s: 1, command: 0.1}\n", "mode", "unknown mode"),
    ("segments:\n  - {kind: step, duration_s: 1, command: !!python/object:os.system ls}\n", None, "not valid YAML"),
]


@pytest.mark.parametrize("text,where,words", BAD, ids=[f"bad{i}" for i in range(len(BAD))])
def test_malformed_profiles(tmp_path, text, where, words):
    path = write(tmp_path, text, "bad.yaml")
    with pytest.raises(ProfileError) as info:
        load_profile(path)
    msg = str(info.value)
    assert msg.startswith(str(path)), msg
    assert words in msg, msg
    if where:
        assert f": {where}: " in msg, msg
        assert info.value.where == where


def test_repeat_explosion_is_refused():
    seg = {"kind": "step", "duration_s": 1, "command": 0.1}
    for _ in range(3):
        seg = {"kind": "repeat", "repeat": 1000, "segments": [seg]}
    with pytest.raises(ProfileError, match="more than"):
        parse_profile({"segments": [seg]}, source="boom.yaml")


def test_file_errors(tmp_path):
    with pytest.raises(ProfileError, match="cannot read profile"):
        load_profile(tmp_path / "missing.yaml")
    with pytest.raises(ProfileError, match="not a regular file"):
        load_profile(tmp_path)
    big = tmp_path / "big.yaml"
    big.write_text("# " + "x" * MAX_PROFILE_BYTES + "\n")
    with pytest.raises(ProfileError, match="too large") as info:
        load_profile(big)
    assert str(big) in str(info.value)
    binary = tmp_path / "bin.yaml"
    binary.write_bytes(b"\xff\xfe\x00\x01garbage")
    with pytest.raises(ProfileError, match="not a text file"):
        load_profile(binary)


def test_profile_error_is_value_error_and_text_source():
    with pytest.raises(ValueError):
        parse_profile_text("segments: nope", source="inline")
    p = parse_profile_text("segments:\n  - {kind: step, duration_s: 1, command: 0.1}\n")
    assert isinstance(p, Profile) and p.text.startswith("segments")


def test_a_profile_longer_than_the_sim_clock_counts_is_refused():
    """A step of 1e+300 s loaded, and the session node's int(duration * 1e9) ended in an
    OverflowError traceback once the graph had started: ./bike run --workout refuses it now."""
    with pytest.raises(ProfileError, match=r"segments\[1\]: total duration beyond 9.2e\+09 s"):
        parse_profile_text("segments:\n  - {kind: step, duration_s: 1, command: 0.1}\n"
                           "  - {kind: step, duration_s: 1.0e+300, command: 0.1}\n")
    assert parse_profile_text("segments:\n  - {kind: step, duration_s: 9.0e+9, command: 0.1}\n").duration_s == 9e9


def test_targets_in_each_modes_unit(tmp_path):
    from bike_session.profiles import ModeUnits, load_profile

    units = ModeUnits(erg_power_max_w=1000.0, grade_min=-0.2, grade_max=0.2, cadence_min_rpm=20.0,
                      cadence_max_rpm=120.0)
    path = write(tmp_path, name="t.yaml", text="""
segments:
  - {kind: step, duration_s: 1, mode: erg, target: 250}
  - {kind: step, duration_s: 1, mode: slope, target: -5}
  - {kind: ramp, duration_s: 2, mode: isokinetic, start_target: 40, end_target: 90}
  - {kind: step, duration_s: 1, mode: resistance, command: 0.3}
""")
    prof = load_profile(path, units=units)
    assert prof.command_at(0.5)[:2] == (pytest.approx(0.25), MODES["erg"])
    assert prof.command_at(1.5)[:2] == (pytest.approx(0.375), MODES["slope"])       # (-0.05 + 0.2) / 0.4
    assert prof.command_at(2.0)[0] == pytest.approx(0.2) and prof.command_at(3.0)[0] == pytest.approx(0.45)
    assert prof.command_at(4.5)[:2] == (0.3, MODES["resistance"])
    # without the bike's ranges a target cannot be ridden
    with pytest.raises(ProfileError, match=r"segments\[0\]\.target: a target needs the bike's ranges"):
        load_profile(path)
    bad = [("{kind: step, duration_s: 1, mode: erg, target: 1500}", r"segments\[0\]\.target: .*outside .*\[0, 1000\] W"),
           ("{kind: step, duration_s: 1, mode: slope, target: 25}", r"outside .*\[-20, 20\] % grade"),
           ("{kind: step, duration_s: 1, mode: resistance, target: 3}", "no target unit"),
           ("{kind: step, duration_s: 1, mode: erg, target: 100, command: 0.1}", "not both"),
           ("{kind: step, duration_s: 1, mode: erg}", "missing key 'command'")]
    for seg, words in bad:
        p = write(tmp_path, f"segments:\n  - {seg}\n", "bad.yaml")
        with pytest.raises(ProfileError, match=words):
            load_profile(p, units=units)


def test_mode_units_follow_the_config():
    from bike_plant.config import load_config
    from bike_session.profiles import mode_units_from_config

    cfg = load_config(ROOT / "config" / "bldc_default.yaml")
    u = mode_units_from_config(cfg)
    assert u.erg_power_max_w == cfg["controller"]["pmax_w"]
    cfg["modes"] = {"erg_power_max_w": 600.0, "grade_max": 0.1}
    u = mode_units_from_config(cfg)
    assert u.erg_power_max_w == 600.0 and u.grade_max == 0.1
    assert load_profile(ROOT / "config" / "profiles" / "all_modes.yaml", units=u).duration_s == 20.0


def test_virtual_gears_stay_in_force_until_the_next_one_given():
    """``gear`` on any segment (inherited by intervals / repeat children) is the virtual gear
    from its start until a later segment gives another; 0 before any and back to the config's."""
    p = parse_profile({"mode": "slope", "segments": [
        {"kind": "step", "duration_s": 2, "command": 0.5},
        {"kind": "step", "duration_s": 2, "command": 0.6, "gear": 2.1},
        {"kind": "step", "duration_s": 2, "command": 0.6},
        {"kind": "intervals", "repeat": 2, "gear": 3.5, "on": {"duration_s": 1, "command": 0.7},
         "off": {"duration_s": 1, "command": 0.4, "gear": 1.5}},
        {"kind": "step", "duration_s": 1, "command": 0.5, "gear": 0}]})
    gears = [p.gear_at(t + 0.5) for t in range(11)]
    assert gears == [0.0, 0.0, 2.1, 2.1, 2.1, 2.1, 3.5, 1.5, 3.5, 1.5, 0.0]
    assert p.gear_at(100.0) == 0.0 and p.gear_at(-1.0) == 0.0
    assert p.command_at(6.5)[:2] == (0.7, MODES["slope"]), "gears change nothing else"
    assert parse_profile({"segments": [{"kind": "step", "duration_s": 1, "command": 0.1}]}).gear_at(0.5) == 0.0


def test_a_road_stays_in_force_until_the_next_one_and_bad_roads_are_named():
    head = {"crr": 0.005, "cw_kg_m": 0.5, "wind_mps": 6}
    p = parse_profile({"mode": "slope", "segments": [
        {"kind": "step", "duration_s": 2, "command": 0.5},
        {"kind": "step", "duration_s": 2, "command": 0.6, "road": head},
        {"kind": "repeat", "repeat": 2, "road": {"crr": 0.004, "cw_kg_m": 0.3, "wind_mps": -3},
         "segments": [{"kind": "step", "duration_s": 1, "command": 0.7}]},
        {"kind": "step", "duration_s": 1, "command": 0.5, "road": "config"}]})
    roads = [p.road_at(t + 0.5) for t in range(7)]
    assert roads == [None, None, (0.005, 0.5, 6.0), (0.005, 0.5, 6.0), (0.004, 0.3, -3.0), (0.004, 0.3, -3.0), None]
    assert p.command_at(4.5)[:2] == (0.7, MODES["slope"]), "roads change nothing else"
    for bad, why in (({"crr": 0.005, "cw_kg_m": 0.5}, "exactly crr, cw_kg_m, wind_mps"),
                     ({"crr": 0.5, "cw_kg_m": 0.5, "wind_mps": 0}, "road crr 0.5 outside"),
                     ({"crr": 0.005, "cw_kg_m": "x", "wind_mps": 0}, "expected a number"),
                     ("flat", "expected 'config' or a mapping")):
        with pytest.raises(ProfileError, match=why) as info:
            parse_profile({"segments": [{"kind": "step", "duration_s": 1, "command": 0.1, "road": bad}]})
        assert "segments[0].road" in str(info.value)


def test_a_cadence_target_is_its_segments_own_and_bad_ones_are_named():
    p = parse_profile({"mode": "erg", "segments": [
        {"kind": "step", "duration_s": 2, "command": 0.2, "cadence": 95},
        {"kind": "step", "duration_s": 2, "command": 0.2},
        {"kind": "intervals", "repeat": 1, "cadence": 60, "on": {"duration_s": 1, "command": 0.4},
         "off": {"duration_s": 1, "command": 0.1, "cadence": 0}}]})
    assert [p.cadence_at(t + 0.5) for t in range(6)] == [95.0, 95.0, None, None, 60.0, None]
    assert p.cadence_at(100.0) is None
    for bad, why in ((5, "outside"), (300, "outside"), ("fast", "expected a number")):
        with pytest.raises(ProfileError, match=why) as info:
            parse_profile({"segments": [{"kind": "step", "duration_s": 1, "command": 0.1, "cadence": bad}]})
        assert "segments[0].cadence" in str(info.value)


def test_shifted_gear_walks_the_table_and_says_how_far_it_got():
    table = (1.0, 1.5, 2.0, 3.0)
    assert shifted_gear(table, 1.5, 1) == (2.0, 1)
    assert shifted_gear(table, 1.5, -1) == (1.0, -1)
    assert shifted_gear(table, 1.5, 2) == (3.0, 2)
    assert shifted_gear(table, 1.5, 5) == (3.0, 2), "two gears above: two taken"
    assert shifted_gear(table, 3.0, 1) == (3.0, 0), "top gear"
    assert shifted_gear(table, 1.0, -3) == (1.0, 0), "bottom gear"
    assert shifted_gear(table, 1.7, 1) == (2.0, 1) and shifted_gear(table, 1.7, -1) == (1.5, -1), \
        "from a gear off the table: the next one in that direction"
    assert shifted_gear(table, 2.0 * (1 + 1e-9), 1) == (3.0, 1), "round-off is the same gear"


def test_a_spindown_segment_needs_no_value_and_other_modes_still_do():
    p = parse_profile_text("segments:\n  - {kind: step, mode: erg, command: 0.2, duration_s: 3}\n"
                           "  - {kind: step, mode: spindown, duration_s: 60}\n")
    assert [(s.mode, s.start) for s in p.segments] == [(MODES["erg"], 0.2), (MODES["spindown"], 0.0)]
    with pytest.raises(ProfileError, match="missing key 'command'"):
        parse_profile_text("segments:\n  - {kind: step, mode: erg, duration_s: 3}\n")


def test_every_profile_in_config_loads_on_its_bike():
    """The example profiles users start from load with the default bike's ranges (targets in
    W / % / rpm need them); the spin-down example gives the coast room (50 s: ~35 s on the BLDC
    flywheel from 94 to 60 rpm)."""
    from bike_plant.config import load_config
    from bike_session.profiles import mode_units_from_config
    units = mode_units_from_config(load_config(ROOT / "config" / "bldc_default.yaml"))
    names = sorted(p.name for p in (ROOT / "config" / "profiles").glob("*.yaml"))
    assert "spindown.yaml" in names
    for name in names:
        assert load_profile(ROOT / "config" / "profiles" / name, units=units).duration_s > 0, name
    spin = load_profile(ROOT / "config" / "profiles" / "spindown.yaml", units=units)
    assert [s.mode for s in spin.segments] == [MODES["erg"], MODES["spindown"], MODES["erg"]]
    assert spin.segments[1].duration_s >= 50.0
