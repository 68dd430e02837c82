"""bike_plant.can.torque_map: the drive's torque map, its lookups and its file (no bus)."""
from __future__ import annotations

import numpy as np
import pytest

from bike_plant.can.torque_map import TorqueMap, TorqueMapError, load_torque_map

SETPOINTS = [-3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0]


def _map(**kw) -> TorqueMap:
    """Shaft torque falls behind the estimate with the current (0.97 .. 0.89 at 3 N m) and more
    at the higher speed; the estimate runs 2 % over the setpoint."""
    sp = np.array(SETPOINTS)
    rep = 1.02 * sp
    rows_true = [rep * (1.0 - k * np.abs(sp)) for k in (0.01, 0.035)]
    return TorqueMap([1000.0, 4000.0], sp, [rep, rep], rows_true, **kw)


def test_the_setpoint_for_a_shaft_torque_gives_that_torque():
    m = _map()
    for speed in (1000.0, 1700.0, 2500.0, 4000.0):
        for wanted in (-2.7, -1.3, -0.2, 0.0, 0.4, 2.5):
            sp = m.setpoint_nm_for(speed, wanted)
            # the drive reports ~1.02 x its setpoint: what the map then reads as the shaft's
            reported = float(np.interp(sp, SETPOINTS, 1.02 * np.array(SETPOINTS)))
            assert m.true_nm_at(speed, reported) == pytest.approx(wanted, abs=2e-3)
            assert sp * wanted >= 0.0 and (sp == 0.0) == (wanted == 0.0)
    assert m.outside == 0
    assert m.setpoint_nm_for(4000.0, -2.0) < -2.0 * 1.05         # 7 % short at 4000 rpm: asked for more


def test_lookups_interpolate_in_speed_and_hold_the_edges_counted():
    m = _map()
    lo, hi = m.true_nm_at(1000.0, -2.04), m.true_nm_at(4000.0, -2.04)
    assert lo == pytest.approx(-2.04 * 0.98) and hi == pytest.approx(-2.04 * 0.93)
    assert m.true_nm_at(2500.0, -2.04) == pytest.approx((lo + hi) / 2)
    assert m.true_nm_at(-2500.0, -2.04) == pytest.approx((lo + hi) / 2)   # |speed|
    assert m.outside == 0
    assert m.true_nm_at(6000.0, -2.04) == pytest.approx(hi)              # nearest row
    assert m.outside == 1
    # beyond the largest setpoint: its ratio holds (torque proportional to current)
    assert m.true_nm_at(4000.0, -6.12) == pytest.approx(-6.12 * 0.895)
    assert m.setpoint_nm_for(4000.0, -6.0) == pytest.approx(-6.0 * 3.0 / (3.06 * 0.895))
    assert m.outside == 3


def test_the_file_round_trips_and_bad_maps_are_one_error(tmp_path):
    m = _map(source="unit test")
    path = tmp_path / "m.yaml"
    m.save(path)
    back = load_torque_map(path)
    assert back.source == "unit test" and back.path == str(path)
    for name in ("speed_rpm", "setpoint_nm", "reported_nm", "true_nm"):
        np.testing.assert_allclose(getattr(back, name), getattr(m, name), rtol=1e-6)
    bad = {
        "no inverse": dict(true=[[0.0, 1.0, 0.5]]),
        "opposite sign": dict(true=[[0.5, 0.0, 1.0]], sp=[-1.0, 0.0, 1.0]),
        "no zero": dict(sp=[1.0, 2.0, 3.0]),
        "descending speeds": dict(speed=[2000.0, 1000.0], rep=[[0, 1, 2]] * 2, true=[[0, 1, 2]] * 2),
        "shape": dict(true=[[0.0, 1.0]]),
        "nan": dict(true=[[0.0, np.nan, 2.0]]),
    }
    for why, kw in bad.items():
        args = dict(speed=[1000.0], sp=[0.0, 1.0, 2.0], rep=[[0.0, 1.0, 2.0]], true=[[0.0, 0.9, 1.8]])
        args.update(kw)
        with pytest.raises(TorqueMapError) as err:
            TorqueMap(args["speed"], args["sp"], args["rep"], args["true"], path="x.yaml")
        assert str(err.value).startswith("x.yaml: ") and "\n" not in str(err.value), why
    for text in ("", "drive_torque_map: {speed_rpm: [1]}", "drive_torque_map: {speed_rpm: ['a'], setpoint_nm: [0, 1], "
                 "reported_nm: [0, 1], true_nm: [0, 1]}", "\x00\x01"):
        path.write_text(text)
        with pytest.raises(TorqueMapError, match="m.yaml: "):
            load_torque_map(path)
    path.write_bytes(b"#" * (2 << 20))
    with pytest.raises(TorqueMapError, match="file too large"):
        load_torque_map(path)


def test_a_copy_of_a_can_config_still_finds_its_torque_map(tmp_path):
    """`./bike run --set ...` (and replay, bench, the CAN latency rig) write the config elsewhere:
    the map's path, relative to the original, is made absolute in the copy (as the profile's)."""
    import pathlib

    import yaml
    from bike_plant.config import absolute_file_paths
    from bike_session import cli

    config = pathlib.Path(__file__).resolve().parents[1] / "config" / "bldc_can.yaml"
    doc = yaml.safe_load(config.read_text())
    assert doc["/**"]["ros__parameters"]["can"]["torque_map_file"] == "bldc_can_torque_map.yaml"
    path, cfg = cli._config_copy(config, doc, "test")
    assert path.parent != config.parent
    assert cfg["can"]["torque_map_file"] == str(config.parent / "bldc_can_torque_map.yaml")
    assert cfg["session"]["profile"] == str(config.parent / "profiles" / "demo_intervals.yaml")
    params = {"can": {"torque_map_file": "/abs/m.yaml"}, "session": {"profile": "~/p.yaml"}}
    absolute_file_paths(params, tmp_path)
    assert params["can"]["torque_map_file"] == "/abs/m.yaml"
    assert params["session"]["profile"] == "~/p.yaml"                 # home-relative: the nodes expand it


def test_a_real_drives_map_from_a_dynamometers_points(tmp_path):
    """`./bike torque-map --from-csv`: the points a dynamometer with a torque sensor logged (any
    order, repeated points averaged, extra columns ignored) make the map; a missing point, a
    missing column or a bad number is one error line and no map file."""
    from conftest import bike_command

    rows = ["setpoint_nm,speed_rpm,reported_nm,true_nm,sensor_temp_c"]
    for speed in (1500.0, 3000.0):
        for sp in (-2.0, 0.0, 2.0):
            k = 0.9 if speed > 2000 else 0.95
            rows.append(f"{sp},{speed},{1.01 * sp},{k * 1.01 * sp + 0.001},25")
    rows.append("2.0,1500,2.02,1.921,26")             # a repeat: averaged with 1.9199
    csv_path = tmp_path / "dyno.csv"
    csv_path.write_text("\n".join(rows) + "\n")
    out = tmp_path / "map.yaml"
    result = bike_command("torque-map", "--from-csv", str(csv_path), "--out", str(out), timeout=120)
    assert result.returncode == 0, result.stderr
    m = load_torque_map(out)
    np.testing.assert_allclose(m.speed_rpm, [1500.0, 3000.0])
    np.testing.assert_allclose(m.setpoint_nm, [-2.0, 0.0, 2.0])
    assert m.true_nm[0, 2] == pytest.approx((0.95 * 2.02 + 0.001 + 1.921) / 2)
    assert m.true_nm_at(3000.0, -2.02) == pytest.approx(0.9 * -2.02 + 0.001)
    assert "dyno.csv (7 rows" in m.source
    for name, text, words in (
            ("gap.csv", "\n".join(rows[:-2]) + "\n", "1 missing: 2 N m at 3000 rpm"),
            ("cols.csv", "speed_rpm,setpoint_nm,true_nm\n1,0,0\n", "missing reported_nm"),
            ("nan.csv", rows[0] + "\n0,1500,x,0,1\n", "line 2: not four numbers")):
        (tmp_path / name).write_text(text)
        bad_out = tmp_path / f"{name}.yaml"
        result = bike_command("torque-map", "--from-csv", str(tmp_path / name), "--out", str(bad_out), timeout=120)
        lines = result.stderr.strip().splitlines()
        assert result.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: ") and words in lines[0], \
            result.stderr
        assert not bad_out.exists()
    # the emulated dyno's options mean nothing beside the CSV: they were dropped without a word
    bad_out = tmp_path / "opts.yaml"
    result = bike_command("torque-map", "--from-csv", str(csv_path), "--out", str(bad_out), "--speeds-rpm", "1000",
                          "--settle-s", "1", timeout=120)
    lines = result.stderr.strip().splitlines()
    said = ("error: --speeds-rpm, --settle-s: not with --from-csv (they set up the emulated dynamometer; the CSV's "
            "points are the map)")
    assert result.returncode == 2 and lines == [said], result.stderr
    assert not bad_out.exists()
