"""A recorded session as a FIT activity (`./bike report BAG --fit FILE`, bike_session.fit_export),
read back with Garmin's FIT SDK decoder: per-second records of the rider's power, cadence,
road speed and distance, and the lap / session totals."""
import datetime
import json
import sys

import numpy as np
import pytest

from test_report import CADENCE, W, main, read_topic, real_session, write_session_bag

from bike_session.bags import BagError
from bike_session.fit_export import export_fit


def _decode(path):
    from garmin_fit_sdk import Decoder, Stream
    data = bytearray(path.read_bytes())
    assert Decoder(Stream.from_byte_array(data)).check_integrity(), "header and file CRCs"
    messages, errors = Decoder(Stream.from_byte_array(data)).read()
    assert errors == []
    return messages


def test_a_session_becomes_per_second_records_and_totals(tmp_path):
    # 3 s at 1 kHz: rider 150 W (ledger), motor 100 rad/s; CONFIG_TEXT: gear 10, default wheel and virtual gear
    bag = write_session_bag(tmp_path / "bag", n=3001)
    out = tmp_path / "ride.fit"
    totals = export_fit(bag, out)
    m = _decode(out)
    assert m["file_id_mesgs"][0]["type"] == "activity"
    rec = m["record_mesgs"]
    speed = W * 0.335 * 2.75 / 10.0          # motor rad/s -> crank (gear 10) -> virtual gear 2.75, wheel 0.335 m
    assert len(rec) == 3 and totals["records"] == 3 and totals["laps"] == 1, "no SessionStatus: one lap"
    assert [r["power"] for r in rec] == [150, 150, 150]
    assert [r["cadence"] for r in rec] == [round(CADENCE)] * 3
    assert [r["speed"] for r in rec] == pytest.approx([speed] * 3, abs=1e-3)
    assert [r["distance"] for r in rec] == pytest.approx([speed, 2 * speed, 3 * speed], abs=0.01)
    stamps = [r["timestamp"] for r in rec]
    assert [(b - a).total_seconds() for a, b in zip(stamps, stamps[1:])] == [1.0, 1.0]
    for lap_or_session in (m["lap_mesgs"][0], m["session_mesgs"][0]):
        assert lap_or_session["total_timer_time"] == 3.0 and lap_or_session["total_work"] == 450
        assert lap_or_session["avg_power"] == 150 and lap_or_session["total_distance"] == pytest.approx(3 * speed,
                                                                                                        abs=0.01)
    assert m["session_mesgs"][0]["sport"] == "cycling" and m["session_mesgs"][0]["sub_sport"] == "indoor_cycling"
    assert m["activity_mesgs"][0]["num_sessions"] == 1
    assert [e["event_type"] for e in m["event_mesgs"]] == ["start", "stop_all"]


def test_a_ride_ending_within_a_second_counts_that_second_as_far_as_it_went(tmp_path):
    """2.5 s at 150 W: the last record covers 0.5 s. Counted whole, the FIT totals said 3 s and
    450 J (a 1 ms ride: 1 s, 0.15 kJ); now 2.5 s and 375 J, the mean power still 150 W."""
    bag = write_session_bag(tmp_path / "bag", n=2501)
    out = tmp_path / "ride.fit"
    totals = export_fit(bag, out)
    m = _decode(out)
    rec = m["record_mesgs"]
    assert len(rec) == 3
    stamps = [r["timestamp"] for r in rec]
    assert [(b - a).total_seconds() for a, b in zip(stamps, stamps[1:])] == [1.0, 1.0]     # FIT: whole seconds
    for lap_or_session in (m["lap_mesgs"][0], m["session_mesgs"][0]):
        assert lap_or_session["total_timer_time"] == 2.5 and lap_or_session["total_work"] == 375
        assert lap_or_session["avg_power"] == 150
    assert totals["timer_s"] == pytest.approx(2.5) and totals["elapsed_s"] == pytest.approx(2.5)
    speed = W * 0.335 * 2.75 / 10.0
    assert rec[-1]["distance"] == pytest.approx(2.5 * speed, abs=0.01)


def test_heart_rate_in_the_records_that_have_one_and_in_the_totals(tmp_path):
    """No heart rate in the first second (a strap put on at 1 s), 140 bpm in the second, 150 in
    the third: the first record has no heart_rate field, the others the second's mean; the lap
    and the session their mean and max. Without a heart rate (test above) no record has one."""
    bag = write_session_bag(tmp_path / "bag", n=3001,
                            heart=lambda k: 0.0 if k < 1000 else (140.0 if k < 2000 else 150.0))
    totals = export_fit(bag, tmp_path / "ride.fit")
    m = _decode(tmp_path / "ride.fit")
    rec = m["record_mesgs"]
    assert [r.get("heart_rate") for r in rec] == [None, 140, 150]
    assert [r["power"] for r in rec] == [150, 150, 150], "the other fields as without a heart rate"
    for lap_or_session in (m["lap_mesgs"][0], m["session_mesgs"][0]):
        assert lap_or_session["avg_heart_rate"] == 145 and lap_or_session["max_heart_rate"] == 150
    assert totals["max_heart_rate_bpm"] == pytest.approx(150.0)
    plain = write_session_bag(tmp_path / "plain", n=2001)
    export_fit(plain, tmp_path / "plain.fit")
    m = _decode(tmp_path / "plain.fit")
    assert not any("heart_rate" in r for r in m["record_mesgs"])
    assert "avg_heart_rate" not in m["session_mesgs"][0]


def test_a_lap_per_workout_segment(tmp_path):
    """Segments 0 (0-2 s), 1 (2-3 s), 2 (3-5 s) of the session: three laps, as a head unit
    running the workout would record them, with their own totals."""
    bag = write_session_bag(tmp_path / "bag", n=5001, segment=lambda k: 0 if k < 2000 else (1 if k < 3000 else 2))
    totals = export_fit(bag, tmp_path / "ride.fit")
    m = _decode(tmp_path / "ride.fit")
    laps = m["lap_mesgs"]
    assert totals["laps"] == 3 and m["session_mesgs"][0]["num_laps"] == 3
    assert [lap["wkt_step_index"] for lap in laps] == [0, 1, 2]
    assert [lap["total_timer_time"] for lap in laps] == [2.0, 1.0, 2.0]
    assert [lap["total_work"] for lap in laps] == [300, 150, 300]
    assert sum(lap["total_distance"] for lap in laps) == pytest.approx(m["session_mesgs"][0]["total_distance"],
                                                                      abs=0.02)
    assert [(lap["start_time"] - laps[0]["start_time"]).total_seconds() for lap in laps] == [0.0, 2.0, 3.0]


def test_a_bag_without_plant_states_is_one_error(tmp_path):
    bag = write_session_bag(tmp_path / "bag", n=1)        # one PlantState: no riding second
    with pytest.raises(BagError, match="nothing to export"):
        export_fit(bag, tmp_path / "x.fit")
    assert not (tmp_path / "x.fit").exists()


def test_without_the_fit_sdk_the_export_is_one_clear_error(tmp_path, monkeypatch):
    bag = write_session_bag(tmp_path / "bag", n=2001)
    monkeypatch.setitem(sys.modules, "garmin_fit_sdk", None)                   # import fails
    with pytest.raises(BagError, match="pip install garmin-fit-sdk"):
        export_fit(bag, tmp_path / "x.fit")


@pytest.mark.slow
def test_a_real_session_exports_what_the_report_says(tmp_path, capsys):
    bag = real_session("erg")
    out = tmp_path / "fit" / "ride.fit"
    assert main([str(bag), "--json", "--fit", str(out)]) == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out)
    assert f"wrote {out}: FIT activity, 2 records over 2 s in 1 lap," in captured.err
    m = _decode(out)
    rec = m["record_mesgs"]
    assert len(rec) == 2
    # the records' mean is the report's rider power (whole watts per second)
    assert np.mean([r["power"] for r in rec]) == pytest.approx(summary["mean_rider_power_w"], abs=0.5)
    assert np.mean([r["cadence"] for r in rec]) == pytest.approx(summary["mean_cadence_rpm"], abs=0.5)
    info = json.loads(read_topic(bag, "session_info")[0].data)
    start = datetime.datetime.fromisoformat(info["start_wall_time"])
    assert m["session_mesgs"][0]["start_time"] == start.replace(microsecond=0)
    assert rec[0]["timestamp"] == (start + datetime.timedelta(seconds=1)).replace(microsecond=0)
