"""Garmin FIT workout files (bike_session.fit_workout): steps, repeats, power in % FTP or
watts, free steps, and one WorkoutError for every file or step that cannot be ridden. The
files are written by Garmin's FIT SDK encoder (fit_files.py)."""
import pathlib
import warnings

import pytest

from fit_files import SWEET_SPOT, fit_workout_bytes

from bike_session import fit_workout
from bike_session.profiles import MAX_LEAF_SEGMENTS, MODES
from bike_session.workouts import WorkoutError, WorkoutWarning, load_workout

DATA = pathlib.Path(__file__).resolve().parent / "data" / "workouts"
PMAX = 1016.68


def _power(seconds, lo, hi=None, **extra):
    return dict(duration_type="time", duration_value=int(seconds * 1000), target_type="power", target_value=0,
                custom_target_value_low=lo, custom_target_value_high=lo if hi is None else hi, **extra)


def _repeat(back_to, times):
    return dict(duration_type="repeat_until_steps_cmplt", duration_value=back_to, target_type="open",
                target_value=times)


def _load(tmp_path, steps, name="w.fit", **kw):
    path = tmp_path / name
    path.write_bytes(fit_workout_bytes(steps, **{k: kw.pop(k) for k in ("sport", "file_type", "with_index")
                                                 if k in kw}))
    kw.setdefault("pmax_w", PMAX)
    return load_workout(path, **kw)


def test_the_committed_file_is_what_the_encoder_writes():
    assert (DATA / "sweet_spot.fit").read_bytes() == fit_workout_bytes(SWEET_SPOT, name="Sweet spot 2x8")


def test_a_fit_workout_rides_its_steps_repeats_and_targets():
    w = load_workout(DATA / "sweet_spot.fit", ftp_w=250, pmax_w=PMAX)
    assert w.name == "Sweet spot 2x8" and w.format == "fit" and w.duration_s == pytest.approx(1800.0)
    segs = w.segments
    assert [s.label for s in segs] == ["Warm up", "Sweet spot", "Recover", "Sweet spot", "Recover", "Cool down"]
    assert [s.duration_s for s in segs] == [300.0, 480.0, 120.0, 480.0, 120.0, 300.0]
    # 50-60 % of 250 W: the range's mean; 88-92 %: 225 W; 1150 = 150 W absolute (no FTP scaling)
    assert [s.target_start_w for s in segs[:5]] == pytest.approx([137.5, 225.0, 150.0, 225.0, 150.0])
    assert all(s.target_start_w == s.target_end_w for s in segs[:5])
    assert segs[1].start == pytest.approx(225.0 / PMAX) and segs[1].mode == 2, "power rides in ERG mode"
    assert segs[1].cadence_rpm == pytest.approx(90.0), "the secondary cadence target"
    assert segs[5].target_start_w is None and segs[5].mode == 0 and segs[5].start == pytest.approx(0.2)
    assert "[step 3: 2/2]" in segs[3].path and "[step 3" not in segs[1].path
    assert [(e.time_s, e.message) for e in w.events] == [(0.0, "Easy spin to start")]
    assert w.warnings == []
    assert w.command_at(600.0)[0] == pytest.approx(225.0 / PMAX)
    # the rider's FTP scales the percent steps only
    w200 = load_workout(DATA / "sweet_spot.fit", ftp_w=200, pmax_w=PMAX)
    assert [s.target_start_w for s in w200.segments[:3]] == pytest.approx([110.0, 180.0, 150.0])


def test_nested_repeats_ride_as_on_a_head_unit(tmp_path):
    steps = [_power(10, 1100), _power(20, 1200), _repeat(1, 2), _power(30, 1300), _repeat(0, 3), _power(5, 1050)]
    w = _load(tmp_path, steps, ftp_w=250)
    # (A, B, B, C) three times, then D
    assert [s.target_start_w for s in w.segments] == [100, 200, 200, 300] * 3 + [50]
    assert w.duration_s == pytest.approx((10 + 20 + 20 + 30) * 3 + 5)


def test_steps_go_by_their_12_bit_message_index(tmp_path):
    """Written out of order and with the 'selected' flag (0x8000) on one: ridden by index; more
    steps than 12 bits can index is one error."""
    steps = [dict(_power(10, 1200), message_index=1 | 0x8000), dict(_power(20, 1100), message_index=0)]
    assert [s.target_start_w for s in _load(tmp_path, steps).segments] == [100, 200]
    with pytest.raises(WorkoutError, match="more than a FIT workout can index"):
        _load(tmp_path, [_power(1, 1100)] * (fit_workout.MAX_FIT_STEPS + 1))


def test_percent_targets_need_the_riders_ftp(tmp_path):
    with pytest.raises(WorkoutError, match=r"step 0.*ftp_w"):
        _load(tmp_path, [_power(60, 80)])
    assert _load(tmp_path, [_power(60, 1180)]).segments[0].target_start_w == 180.0, "watts need no FTP"


def test_open_steps_and_unmodelled_targets_ride_free_and_say_so(tmp_path):
    steps = [dict(duration_type="open", target_type="power", target_value=0, custom_target_value_low=1100,
                  custom_target_value_high=1100),
             dict(duration_type="time", duration_value=60_000, target_type="speed", target_value=0,
                  custom_target_value_low=8000, custom_target_value_high=9000),
             dict(duration_type="time", duration_value=30_000, target_type="cadence", target_value=0,
                  custom_target_value_low=100, custom_target_value_high=110)]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        w = _load(tmp_path, steps, ftp_w=250)
    assert [s.duration_s for s in w.segments] == [fit_workout.OPEN_STEP_S, 60.0, 30.0]
    assert w.segments[0].target_start_w == 100.0
    assert w.segments[1].target_start_w is None and w.segments[1].mode == 0
    assert w.segments[2].target_start_w is None and w.segments[2].cadence_rpm == pytest.approx(105.0)
    texts = [str(c.message) for c in caught if issubclass(c.category, WorkoutWarning)]
    assert len(texts) == 2 and texts == w.warnings
    assert any("step 0" in t and "lap button" in t for t in texts)
    assert any("step 1" in t and "'speed' targets are not ridden" in t for t in texts)


@pytest.mark.parametrize("steps, kw, match", [
    ([_power(60, 1100)], dict(file_type="activity"), "type 'activity', not a workout"),
    ([_power(60, 1100)], dict(sport="running"), "sport 'running' is not a bike workout"),
    ([dict(duration_type="distance", duration_value=100_000, target_type="open")], {}, r"step 0.*'distance'"),
    ([dict(duration_type="time", duration_value=60_000, target_type="power", target_value=3)], {},
     r"step 0.*power zone 3"),
    ([dict(duration_type="time", duration_value=0, target_type="open")], {}, r"step 0.*duration_value > 0"),
    ([_power(60, 1100), _repeat(1, 2)], {}, r"step 1.*earlier step"),
    ([_power(60, 1100), _repeat(0, 0)], {}, r"step 1.*repeat count"),
    ([_power(60, 1100), dict(duration_type="repeat_until_time", duration_value=600_000, target_type="open")], {},
     r"step 1.*'repeat_until_time'"),
    ([_power(1, 1100), _repeat(0, 1000), _repeat(0, 1000)], {}, f"more than {MAX_LEAF_SEGMENTS} segments"),
    ([_power(60, 1100), _power(60, 1200)], dict(with_index=False), None),
])
def test_what_cannot_be_ridden_is_one_clear_error(tmp_path, steps, kw, match):
    if match is None:        # no message_index at all: file order (a valid file)
        assert [s.target_start_w for s in _load(tmp_path, steps, ftp_w=250, **kw).segments] == [100, 200]
        return
    with pytest.raises(WorkoutError, match=match) as info:
        _load(tmp_path, steps, ftp_w=250, **kw)
    assert "w.fit" in str(info.value)


def test_corrupt_and_foreign_files_are_one_clear_error(tmp_path):
    good = (DATA / "sweet_spot.fit").read_bytes()
    flipped = bytearray(good)
    flipped[40] ^= 0xFF
    cases = {"truncated.fit": good[:100], "flipped.fit": bytes(flipped), "text.fit": b"[COURSE HEADER]\n",
             "random.fit": bytes(range(256)) * 2}
    for name, data in cases.items():
        path = tmp_path / name
        path.write_bytes(data)
        with pytest.raises(WorkoutError) as info:
            load_workout(path, ftp_w=250, pmax_w=PMAX)
        assert name in str(info.value) and ("FIT" in str(info.value)), (name, str(info.value))


def test_an_oversized_fit_file_is_refused_before_decoding(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(fit_workout, "_decode", lambda *a: calls.append(a))
    path = tmp_path / "big.fit"
    path.write_bytes(b"\x0e" * (fit_workout.MAX_FIT_BYTES + 1))
    with pytest.raises(WorkoutError, match="FIT file too large"):
        load_workout(path, ftp_w=250, pmax_w=PMAX)
    assert calls == []


def test_without_the_fit_sdk_a_fit_file_is_one_clear_error(monkeypatch):
    monkeypatch.setitem(__import__("sys").modules, "garmin_fit_sdk", None)      # import fails
    with pytest.raises(WorkoutError, match="pip install garmin-fit-sdk"):
        load_workout(DATA / "sweet_spot.fit", ftp_w=250, pmax_w=PMAX)


def test_a_fit_cadence_range_is_its_mean_and_one_the_rider_cannot_take_is_none():
    from bike_session.fit_workout import _cadence
    assert _cadence(85, 95) == 90.0 and _cadence(5, 95) == 50.0 and _cadence(None, 90) == 90.0
    assert _cadence(3, 5) is None and _cadence(0, 0) is None and _cadence(300, 400) is None


def test_a_power_or_heart_rate_secondary_target_is_ridden_when_the_primary_is_cadence_or_open(tmp_path):
    # Garmin Connect lets the cadence target be the primary one and the power target the
    # secondary: the step was ridden free at freeride_command (its power target lost, no word)
    cadence_power = dict(duration_type="time", duration_value=60_000, target_type="cadence", target_value=0,
                         custom_target_value_low=85, custom_target_value_high=95, secondary_target_type="power",
                         secondary_target_value=0, secondary_custom_target_value_low=1200,
                         secondary_custom_target_value_high=1220)
    open_percent = dict(duration_type="time", duration_value=60_000, target_type="open",
                        secondary_target_type="power", secondary_target_value=0,
                        secondary_custom_target_value_low=80, secondary_custom_target_value_high=90)
    cadence_hr = dict(cadence_power, secondary_target_type="heart_rate", secondary_custom_target_value_low=240,
                      secondary_custom_target_value_high=250)
    speed_power = dict(open_percent, target_type="speed", target_value=0, custom_target_value_low=8000,
                       custom_target_value_high=9000)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        w = _load(tmp_path, [cadence_power, open_percent, cadence_hr, speed_power], ftp_w=200)
    segs = w.segments
    assert segs[0].target_start_w == 210.0 and segs[0].cadence_rpm == pytest.approx(90.0)
    assert segs[0].mode == segs[1].mode == MODES["erg"] and segs[0].start == pytest.approx(210.0 / PMAX)
    assert segs[1].target_start_w == pytest.approx(170.0), "85 % of FTP 200 W"
    assert segs[2].heart_rate_bpm == pytest.approx(145.0) and segs[2].cadence_rpm == pytest.approx(90.0)
    assert segs[3].target_start_w == pytest.approx(170.0)
    texts = [str(c.message) for c in caught if issubclass(c.category, WorkoutWarning)]
    assert texts == [f"{tmp_path / 'w.fit'}: step 3: 'speed' targets are not ridden (no model of them here): the "
                     "step's secondary power target is ridden"]
    with pytest.raises(WorkoutError, match=r"step 0: secondary power zone 3 needs the rider's zone table"):
        _load(tmp_path, [dict(open_percent, secondary_target_value=3)], ftp_w=200)



def test_a_secondary_cadence_target_of_a_free_step_is_kept(tmp_path):
    # an open (lap button or time) step with a secondary cadence target: the rider's cadence was lost
    step = dict(duration_type="time", duration_value=60_000, target_type="open", secondary_target_type="cadence",
                secondary_target_value=0, secondary_custom_target_value_low=100, secondary_custom_target_value_high=110)
    seg = _load(tmp_path, [step]).segments[0]
    assert seg.target_start_w is None and seg.cadence_rpm == pytest.approx(105.0)
