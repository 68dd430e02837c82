"""A/B comparison of two recorded sessions: exact numbers on synthetic bags, the overlap of
sessions of different lengths, config differences, bad input, and two real sessions."""
import json

import pytest

from test_report import (CADENCE, CONFIG_TEXT, ROAD_MPS, SQRT250, hr_erg_ride, real_session,
                         write_session_bag)

from bike_session.compare import compare, main
from bike_session.report import analyse

CHARTS = ("compare_power.png", "compare_cadence.png", "compare_torque.png", "compare_battery_energy.png")


def metric(result, key):
    return next(m for m in result["metrics"] if m["key"] == key)


def test_same_bag_twice_all_deltas_zero(tmp_path, capsys):
    bag = write_session_bag(tmp_path / "bag")
    out = tmp_path / "out"
    assert main([str(bag), str(bag), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    r = json.loads((out / "compare.json").read_text())
    assert len(r["metrics"]) == 10 + 3 * 4 + 4     # 10 session numbers + 4 per tracked mode + ERG response
    assert metric(r, "distance_m")["a"] == pytest.approx(ROAD_MPS * 1.0, rel=1e-3), "1 s at the virtual speed"
    for m in r["metrics"]:
        if m["key"] in ("erg_response.median_s", "erg_response.max_s"):
            assert m["a"] is None and m["b"] is None, m      # its one step (90 -> 120 W) never settles
            continue
        assert m["a"] is not None and m["a"] == m["b"], m
        assert m["delta"] == 0.0, m
    assert metric(r, "mean_braking_power_w")["a"] == pytest.approx(100.0)
    assert metric(r, "tracking.erg_power.rms")["a"] == pytest.approx(SQRT250)
    assert r["overlap"]["truncated"] is False and r["overlap"]["end_s"] == pytest.approx(1.0)
    assert r["config_diff"]["identical_text"] and r["config_diff"]["parameters"] == []
    assert "config: identical config_text" in text and "NOTE" not in text
    for name in CHARTS:
        assert (out / name).stat().st_size > 5000, name
    page = (out / "compare.html").read_text()
    assert page.count("data:image/png;base64,") == len(CHARTS) and "mean braking power" in page
    assert (out / "compare.txt").read_text().startswith("A/B comparison")


def test_different_lengths_compare_on_the_overlap(tmp_path):
    """A: 1 s, ERG targets 90 / 120 W. B: 0.6 s, ERG 100 W (its braking power), Tmax 2.0 N m.
    Compared on 0-0.6 s: A's ERG error is +10 / -20 W there, B's 0."""
    a = write_session_bag(tmp_path / "a")
    config_b = CONFIG_TEXT.replace("tmax_nm: 1.8", "tmax_nm: 2.0")
    b = write_session_bag(tmp_path / "b", n=601, erg_targets=(100.0, 100.0), config_text=config_b)
    r, da, db, n = compare(a, b)
    assert n == 60 and da.n_bins == 100 and db.n_bins == 60
    ov = r["overlap"]
    assert ov["truncated"] is True and ov["end_s"] == pytest.approx(0.6)
    assert "overlapping range 0-0.6 s" in ov["note"] and "the rest of A is not compared" in ov["note"]
    dur = metric(r, "duration_s")
    assert dur["a"] == pytest.approx(0.6) and dur["b"] == pytest.approx(0.6) and dur["delta"] == pytest.approx(0.0)
    assert r["a"]["recorded_duration_s"] == pytest.approx(1.0)
    assert metric(r, "energy_battery_j")["a"] == pytest.approx(48.0)            # 80 W * 0.6 s, not 80 J
    assert metric(r, "energy_resistor_j")["b"] == pytest.approx(3.0)
    assert metric(r, "peak_phase_current_a")["a"] == 9.0
    assert metric(r, "mean_cadence_rpm")["delta"] == pytest.approx(0.0)
    erg = metric(r, "tracking.erg_power.rms")
    assert erg["a"] == pytest.approx(SQRT250) and erg["b"] == pytest.approx(0.0, abs=1e-9)
    assert erg["delta"] == pytest.approx(-SQRT250)
    assert metric(r, "tracking.erg_power.max_abs")["a"] == pytest.approx(20.0)
    iso = metric(r, "tracking.isokinetic_cadence.rms")
    assert iso["a"] == pytest.approx(CADENCE - 90.0) and iso["delta"] == pytest.approx(0.0, abs=1e-9)
    assert metric(r, "tracking.isokinetic_cadence.time_s")["a"] == pytest.approx(0.2)
    assert "resistance_torque" not in r["tracking"], "resistance starts at 0.7 s, after the overlap"
    # A steps 90 -> 120 W at 0.2 s against a constant 100 W braking power: never settles; B has no step
    steps, settled = metric(r, "erg_response.steps"), metric(r, "erg_response.settled")
    assert (steps["a"], steps["b"], settled["a"]) == (1, 0, 0) and metric(r, "erg_response.median_s")["a"] is None
    params = r["config_diff"]["parameters"]
    assert params == [{"key": "controller.tmax_nm", "a": 1.8, "b": 2.0, "only_in": None}]
    assert "-      tmax_nm: 1.8" in r["config_diff"]["text_diff"]
    assert "+      tmax_nm: 2.0" in r["config_diff"]["text_diff"]


def test_compare_text_and_json_cli(tmp_path, capsys):
    a = write_session_bag(tmp_path / "a")
    b = write_session_bag(tmp_path / "b", n=601, config_text=CONFIG_TEXT.replace("gear_ratio: 10.0", "gear_ratio: 12.0"))
    assert main([str(a), str(b)]) == 0
    text = capsys.readouterr().out
    assert "NOTE: compared on the overlapping range 0-0.6 s" in text
    assert "load.gear_ratio: 10.0 -> 12.0" in text and "config_text diff (shortened):" in text
    assert main([str(a), str(b), "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    cad = metric(r, "mean_cadence_rpm")
    assert cad["b"] == pytest.approx(cad["a"] * 10.0 / 12.0)     # cadence through each bag's own gear ratio


def test_bad_input_is_one_error(tmp_path, capsys):
    good = write_session_bag(tmp_path / "good", n=50)
    junk = tmp_path / "junk.txt"
    junk.write_text("no bag")
    empty = write_session_bag(tmp_path / "empty", n=0)
    cases = [([str(tmp_path / "missing"), str(good)], "does not exist"),
             ([str(good), str(junk)], "not a bag"),
             ([str(good), str(empty)], "no PlantState")]
    for argv, reason in cases:
        capsys.readouterr()
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("bike compare: error: ") and err.count("\n") == 1, err
        assert reason in err and "Traceback" not in err
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main([str(good), str(good), "--out", str(blocker / "out")]) == 2
    err = capsys.readouterr().err
    # refused before the bags are read, naming the option (cli.output_dir)
    assert err.startswith(f"error: --out {blocker / 'out'}: cannot create") and err.count("\n") == 1, err


def test_heart_rate_and_heart_rate_erg_side_by_side_on_the_overlap(tmp_path, capsys):
    """A: the report's heart-rate ride (3 s; at 150 bpm: 149 from 0.8 s, 152 from 1.5 s). B:
    1.6 s, 100 bpm until 1.0 s, then 150. Compared on 0-1.6 s: one stretch each (A's 120 bpm
    stretch starts at 2.0 s), settled 0.3 s / 0.5 s after its start."""
    a = hr_erg_ride(tmp_path / "a")
    b = hr_erg_ride(tmp_path / "b", n=1601, heart=lambda k: 0.0 if k < 300 else (100.0 if k < 1000 else 150.0))
    r, *_ = compare(a, b)
    mean = metric(r, "mean_heart_rate_bpm")
    # batches with a heart rate at both ends, 0.3-1.6 s; a step's batch at its ends' mean
    assert mean["a"] == pytest.approx((499 * 100 + 124.5 + 699 * 149 + 150.5 + 100 * 152) / 1300, rel=1e-9)
    assert mean["b"] == pytest.approx((699 * 100 + 125 + 600 * 150) / 1300, rel=1e-9)
    assert (metric(r, "max_heart_rate_bpm")["a"], metric(r, "max_heart_rate_bpm")["b"]) == (152.0, 150.0)
    assert (metric(r, "heart_rate_erg.stretches")["a"], metric(r, "heart_rate_erg.stretches")["b"]) == (1, 1)
    settle = metric(r, "heart_rate_erg.median_settle_s")
    assert settle["a"] == pytest.approx(0.3) and settle["b"] == pytest.approx(0.5)
    assert settle["delta"] == pytest.approx(0.2)
    mae = metric(r, "heart_rate_erg.mae_bpm")
    assert mae["a"] == pytest.approx((69 * 1.0 + 0.85 + 10 * 2.0) / 80, rel=1e-9) and mae["b"] == pytest.approx(0.0)
    assert metric(r, "heart_rate_erg.max_abs_bpm")["a"] == pytest.approx(2.0)
    assert main([str(a), str(b)]) == 0
    text = capsys.readouterr().out
    assert "mean heart rate [bpm]" in text and "HR ERG settle time, median [s]" in text
    # no heart rate on either side: no rows
    plain = write_session_bag(tmp_path / "plain")
    r, *_ = compare(plain, plain)
    assert not [m for m in r["metrics"] if "heart" in m["key"]]


@pytest.mark.slow
def test_two_real_sessions(tmp_path):
    """Resistance (default profile) against ERG (erg_smoke), both 2 s in the node graph: the
    compared numbers are each session's own report numbers (same range), the ERG session
    tracks its 100 W target, and a real bag against itself gives zero deltas."""
    res, erg = real_session("resistance"), real_session("erg")
    out = tmp_path / "out"
    assert main([str(res), str(erg), "--out", str(out)]) == 0
    r = json.loads((out / "compare.json").read_text())
    sa, sb = analyse(res).summary, analyse(erg).summary
    for key in ("mean_braking_power_w", "mean_rider_power_w", "energy_battery_j", "energy_resistor_j",
                "peak_phase_current_a", "mean_cadence_rpm", "duration_s"):
        m = metric(r, key)
        assert m["a"] == pytest.approx(sa[key], rel=1e-9, abs=1e-9) and m["b"] == pytest.approx(sb[key], rel=1e-9,
                                                                                               abs=1e-9), key
    assert sb["time_in_mode_s"] == {"erg": pytest.approx(2.0, abs=0.002)}
    erg_rms = metric(r, "tracking.erg_power.rms")
    assert erg_rms["a"] is None and 0.0 < erg_rms["b"] < 15.0                  # W, against ~100 W
    assert metric(r, "tracking.erg_power.time_s")["b"] == pytest.approx(2.0, abs=0.002)
    assert r["tracking"]["erg_power"]["b"]["mean_target"] == pytest.approx(100.5, abs=1.0)
    assert metric(r, "tracking.resistance_torque.rms")["b"] is None
    assert r["a"]["profile_name"] == "demo_intervals" and r["b"]["profile_name"] == "erg-smoke"
    for name in CHARTS:
        assert (out / name).stat().st_size > 5000, name
    same, *_ = compare(erg, erg)
    assert all(m["delta"] == 0.0 for m in same["metrics"] if m["a"] is not None)


def test_columns_stay_apart_at_any_width(tmp_path):
    """A difference as wide as its column ran into the percentage ('...138.0+13800.0 %'): each
    column now starts after a space."""
    from bike_session.compare import format_compare

    bag = write_session_bag(tmp_path / "bag")
    r = compare(bag, bag)[0]
    m = metric(r, "mean_braking_power_w")
    m.update(a=1.0, b=123456789.0, delta=123456788.0, delta_pct=12345678800.0)
    line = next(x for x in format_compare(r).splitlines() if x.startswith(m["label"]))
    assert line.split()[-5:] == ["1.00", "123456789.00", "123456788.00", "+12345678800.0", "%"], line


def test_a_config_copy_naming_the_same_profile_is_no_difference(tmp_path):
    """./bike run --set rides a copy of the config in a folder of its own, its relative
    session.profile made absolute: compare listed "session.profile: profiles/demo_intervals.yaml
    -> /.../config/profiles/demo_intervals.yaml" between two rides of the same profile. A file
    parameter is read against its config's folder (session_info's config_path); another file
    still differs."""
    import pathlib

    import yaml

    from bike_plant.config import absolute_file_paths
    from bike_session.compare import config_diff

    source = pathlib.Path(__file__).resolve().parents[1] / "config" / "bldc_default.yaml"
    doc = yaml.safe_load(source.read_text())
    absolute_file_paths(doc["/**"]["ros__parameters"], source.parent)
    doc["/**"]["ros__parameters"]["load"]["rider_target_cadence_rpm"] = 90.0
    copy = tmp_path / "bike-config-x" / "bldc_default.yaml"
    copy.parent.mkdir()
    copy.write_text(yaml.safe_dump(doc))
    a = write_session_bag(tmp_path / "a", config_text=source.read_text(), config_path=source)
    b = write_session_bag(tmp_path / "b", config_text=copy.read_text(), config_path=copy)
    changed = compare(a, b)[0]["config_diff"]["parameters"]
    assert [p["key"] for p in changed] == ["load.rider_target_cadence_rpm"], changed
    doc["/**"]["ros__parameters"]["session"]["profile"] = str(source.parent / "profiles" / "all_modes.yaml")
    copy.write_text(yaml.safe_dump(doc))
    d = config_diff(source.read_text(), copy.read_text(), str(source), str(copy))
    assert [p["key"] for p in d["parameters"]] == ["load.rider_target_cadence_rpm", "session.profile"]


def test_a_key_only_one_config_sets_is_not_shown_as_null(tmp_path):
    """compare listed a key that only B's config sets as "modes.virtual_gears: null -> [1.5, 2.75]",
    as if A's config set it to null. Now "(not set)"; a null a config does write stays null."""
    from bike_session.compare import format_compare

    a = write_session_bag(tmp_path / "a")
    text_b = CONFIG_TEXT.replace("    load:\n", "    extra_null: null\n    load:\n      virtual_gears: [1.5, 2.75]\n",
                                 1)
    b = write_session_bag(tmp_path / "b", config_text=text_b)
    r = compare(a, b)[0]
    text = format_compare(r)
    assert "  load.virtual_gears: (not set) -> [1.5, 2.75]" in text, text
    assert "  extra_null: (not set) -> null" in text, text
    text = format_compare(compare(b, a)[0])
    assert "  load.virtual_gears: [1.5, 2.75] -> (not set)" in text, text
