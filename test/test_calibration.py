"""Spin-down calibration kept between runs (bike_controller.calibration, ./bike run --calibration):
the file the controller writes, what a run reads from it, and bad files refused with one error.
The node graph's side (a spin-down writes the file, the next run rides with it) is in
test_ftms_graph.py."""
from __future__ import annotations

import os
import pathlib
import random

import pytest
import yaml

from bike_controller import calibration as cal
from bike_controller.calibration import CalibrationError, apply_calibration, read_calibration, write_calibration
from bike_controller.modes import friction_figures
from bike_controller.spindown import SpinDownResult
from bike_plant.config import load_config

ROOT = pathlib.Path(__file__).resolve().parents[1]
RESULT = SpinDownResult(friction_nms=9.87e-5, dry_friction_nm=0.0123, coast_s=34.9, samples=349,
                        rms_residual_rpm=0.4)


def test_the_file_written_after_a_spin_down_reads_back_the_same_figures(tmp_path):
    path = write_calibration(tmp_path / "cal.yaml", "bldc", RESULT, sim_time_s=45.25, config_path="/x/bike.yaml")
    text = path.read_text()
    assert text.startswith("# Spin-down calibration") and "--calibration" in text
    c = read_calibration(path, "bldc")
    assert (c.machine, c.friction_nms, c.dry_friction_nm, c.coast_s) == ("bldc", 9.87e-5, 0.0123, 34.9)
    assert c.written_utc.endswith("Z") and "9.87e-05" in c.describe() and "34.9 s coast" in c.describe()
    assert yaml.safe_load(text)["sim_time_s"] == 45.25
    assert os.listdir(tmp_path) == ["cal.yaml"]                    # no temporary file left beside it


def test_the_file_reads_alike_to_its_loader_and_ros(tmp_path):
    """write_calibration writes through bike_plant.config.dump_ros_params: numbers as 1.0e-05, text
    rcl would type otherwise quoted (a config named 'nan' was written bare: a number to rcl)."""
    from bike_plant.config import check_rcl_scalars, parse_yaml_text
    tiny = SpinDownResult(friction_nms=1e-05, dry_friction_nm=2e-07, coast_s=1e-06, samples=20,
                          rms_residual_rpm=1e-12)
    path = write_calibration(tmp_path / "cal.yaml", "bldc", tiny, sim_time_s=1e-05, config_path="nan")
    text = path.read_text()
    parse_yaml_text(text, lambda node: check_rcl_scalars(node, path))       # ConfigError if not alike
    assert "friction_nms: 1.0e-05" in text and "config: 'nan'" in text
    c = read_calibration(path, "bldc")
    assert (c.friction_nms, c.dry_friction_nm) == (1e-05, 2e-07)
    assert yaml.safe_load(text)["rms_residual_rpm"] == 1e-12


def test_a_calibration_is_never_renamed_over_a_device(tmp_path):
    """The write renames a new file over the old one: as root, --calibration /dev/null replaced
    the device with the calibration. Refused with an OSError, the device untouched."""
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    with pytest.raises(OSError, match="not a regular file"):
        write_calibration(fifo, "bldc", RESULT, sim_time_s=1.0)
    assert fifo.is_fifo() and [p.name for p in tmp_path.iterdir()] == ["pipe"]


def test_a_write_that_fails_leaves_the_previous_calibration_whole(tmp_path, monkeypatch):
    path = write_calibration(tmp_path / "cal.yaml", "bldc", RESULT, sim_time_s=1.0)
    before = path.read_text()

    def disk_full(*_a, **_k):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(cal.os, "fsync", disk_full)
    with pytest.raises(OSError):
        write_calibration(path, "bldc", SpinDownResult(1.0, 1.0, 1.0, 20, 0.0), sim_time_s=2.0)
    assert path.read_text() == before and os.listdir(tmp_path) == ["cal.yaml"]
    with pytest.raises(OSError):
        write_calibration(tmp_path / "no_such_dir" / "cal.yaml", "bldc", RESULT, sim_time_s=1.0)


BAD_FILES = [
    ("modes: [1, 2\n", "not valid YAML at line"),
    ("- 1\n- 2\n", "expected a mapping with a 'modes:'"),
    ("machine: bldc\n", "expected a mapping with a 'modes:'"),
    ("machine: spmsm\nmodes: {friction_nms: 0.005, dry_friction_nm: 0.1}\n", "'spmsm' bike's calibration"),
    # it said "a None bike's calibration"
    ("modes: {friction_nms: 1.0e-4, dry_friction_nm: 0.0}\n", "no 'machine:' key: the controller writes the bike's "
                                                             "kind (bldc or spmsm) with its spin-down, and this bike "
                                                             "is 'bldc'"),
    ("machine: bldc\nmodes: {friction_nms: -1.0e-4, dry_friction_nm: 0.0}\n", "modes.friction_nms must be"),
    ("machine: bldc\nmodes: {friction_nms: .nan, dry_friction_nm: 0.0}\n", "modes.friction_nms must be"),
    ("machine: bldc\nmodes: {friction_nms: 1.0e-4, dry_friction_nm: .inf}\n", "modes.dry_friction_nm must be"),
    ("machine: bldc\nmodes: {friction_nms: true, dry_friction_nm: 0.0}\n", "modes.friction_nms must be"),
    ("machine: bldc\nmodes: {friction_nms: '1e-4', dry_friction_nm: 0.0}\n", "modes.friction_nms must be"),
    ("machine: bldc\nmodes: {friction_nms: 1.0e-4}\n", "modes.dry_friction_nm must be"),
    # finite but beyond any bike's: B = 1e300 rode to a virtual distance of 5e202 m, an rms of inf
    ("machine: bldc\nmodes: {friction_nms: 1.0e+300, dry_friction_nm: 0.0}\n",
     "friction_nms must be a number in [0, 1]"),
    ("machine: bldc\nmodes: {friction_nms: 1.0e-4, dry_friction_nm: 20.0}\n",
     "dry_friction_nm must be a number in [0, 10]"),
    ("machine: bldc\nmodes: {friction_nms: 1.0e-4, dry_friction_nm: 0, erg_power_max_w: 9}\n", "unknown key"),
    ("machine: bldc\nmodes: !!python/object/apply:os.system ['true']\n", "not valid YAML"),
]


@pytest.mark.parametrize("text,words", BAD_FILES)
def test_a_bad_calibration_file_is_one_error_naming_the_problem(tmp_path, text, words):
    path = tmp_path / "cal.yaml"
    path.write_text(text)
    with pytest.raises(CalibrationError) as err:
        read_calibration(path, "bldc")
    assert words in str(err.value) and str(path) in str(err.value) and "\n" not in str(err.value)


def test_unreadable_binary_and_huge_files_are_refused_unparsed(tmp_path):
    cases = {"missing": None, "binary": bytes(random.Random(3).randrange(256) for _ in range(512)),
             "huge": b"#" * (cal.MAX_CALIBRATION_BYTES + 1)}
    words = {"missing": "cannot read it", "binary": "", "huge": "file too large"}
    for name, data in cases.items():
        path = tmp_path / name
        if data is not None:
            path.write_bytes(data)
        with pytest.raises(CalibrationError) as err:
            read_calibration(path, "bldc")
        assert words[name] in str(err.value), (name, err.value)


def test_a_calibration_becomes_the_configs_modes_friction_and_the_profile_stays_found():
    """Every section that sets the figures takes the calibration (a node's own section wins
    over the wildcard's), the plant's true friction is untouched, and the run's copy of the
    default config (./bike run's, in a folder of its own) still finds its relative profile."""
    from bike_session.cli import _config_copy
    config = ROOT / "config" / "bldc_default.yaml"
    doc = yaml.safe_load(config.read_text())
    doc["controller"] = {"ros__parameters": {"modes": {"friction_nms": 5.0e-5}}}
    out = apply_calibration(doc, cal.Calibration("bldc", 9.87e-5, 0.0123))
    copy_path, _ = _config_copy(config, out, "with a calibration")
    assert copy_path.parent != config.parent
    for node in (None, "controller"):
        loaded = load_config(copy_path, node)
        b, tc, _ = friction_figures(loaded)
        assert (b, tc) == (9.87e-5, 0.0123), node
        assert loaded["mechanics"] == load_config(config)["mechanics"]
    profile = pathlib.Path(load_config(copy_path)["session"]["profile"])
    assert profile.is_absolute() and profile.exists()


def test_run_refuses_a_bad_or_foreign_calibration_before_anything_starts(bike_cli, tmp_path):
    """One error naming the option and the file, exit 2, nothing started; the file is kept."""
    foreign = write_calibration(tmp_path / "spmsm_cal.yaml", "spmsm", RESULT, sim_time_s=1.0)
    before = foreign.read_text()
    bad = tmp_path / "bad.yaml"
    bad.write_text("machine: bldc\nmodes: {friction_nms: -1, dry_friction_nm: 0}\n")
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    for path, words in ((foreign, "'spmsm' bike's calibration"), (bad, "modes.friction_nms must be"),
                        (blocker / "cal.yaml", "a_file: not a directory (a file is there)"),
                        (pathlib.Path("/dev/null"), "not a regular file")):
        run = bike_cli("run", "--duration", "1", "--calibration", str(path), timeout=60)
        assert run.returncode == 2 and "Traceback" not in run.stderr, run.stderr[-2000:]
        lines = [line for line in run.stderr.splitlines() if line.strip()]
        assert len(lines) == 1 and "--calibration" in lines[0] and words in lines[0], run.stderr
        assert run.stdout == "", run.stdout[-2000:]
    assert foreign.read_text() == before


def test_set_changes_config_values_for_one_run_and_refuses_bad_ones(capsys):
    """`./bike run --set KEY=VALUE`: dotted keys under the wildcard section, values read as YAML,
    a copy of the config that still finds its profile; a malformed item, a value where a
    section is, or a value the bike refuses is one error naming --set and nothing runs."""
    from bike_session.cli import _set_run_config
    config = ROOT / "config" / "bldc_default.yaml"
    path, cfg = _set_run_config(["modes.auto_shift=true", "load.rider_target_cadence_rpm=90",
                                 "modes.virtual_gears=[1.0, 1.2, 1.4]", "modes.friction_nms=1e-4",
                                 "load.kind=rider"], config)
    assert cfg["modes"]["auto_shift"] is True and cfg["load"]["rider_target_cadence_rpm"] == 90
    assert cfg["modes"]["friction_nms"] == 1e-4 and cfg["load"]["kind"] == "rider"
    assert cfg["modes"]["virtual_gears"] == [1.0, 1.2, 1.4]
    assert cfg["battery"] == load_config(config)["battery"]
    assert pathlib.Path(cfg["session"]["profile"]).exists()
    assert "--set modes.auto_shift=true" in path.read_text().splitlines()[0]
    capsys.readouterr()
    bad = {"modes.auto_shift": "expected KEY=VALUE", "=3": "expected KEY=VALUE", "modes..x=1": "expected KEY=VALUE",
           "battery.soc0.x=1": "battery.soc0 is a value, not a section",
           "modes.grade_min=[1": "not valid YAML", "modes.crr=": "give one value",
           "modes.crr=ab\x02": "not valid YAML at line 1, column 3: unacceptable character #x0002",
           "modes.crr=" + "[" * 2000 + "]" * 2000: "nested too deeply",
           "modes.auto_shift=1": "auto_shift must be true or false", "modes.nope=1": "unknown key(s) nope",
           "modes.crr=nan": "crr must be", "load.kind=dragon": "dragon",
           "bldc.inductance_h=-1": "inductance_h", "modes.friction_nms=-1": "friction_nms",
           "modes.friction_nms=1e300": "modes: friction_nms must be a number in [0, 1]",
           "mechanics.friction_nms=1e300": "friction_nms must be a number in [0, 1]",
           # beyond the ROS clock's int64 nanoseconds: the session node's OverflowError traceback
           "duration_s=1e300": "duration_s: must be at most 9.2e+09",
           "session.duration_s=1e300": "session.duration_s: must be at most 9.2e+09 s",
           "session.period_s=1e300": "session.period_s: must be at most 9.2e+09 s"}
    for item, words in bad.items():
        assert _set_run_config([item], config) is None, item
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: --set") and words in err[0], (item, err)
