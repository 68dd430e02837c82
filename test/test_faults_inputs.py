"""Reliability suite: hostile files and security defaults.

Malformed configs, workout files and bags (seeded random truncations, byte flips, random
bytes) give one clear error of the documented class each, never another exception; the
front door (`./bike`) prints one error line and no traceback. No config value is evaluated
as code (YAML python tags refused, no eval / exec / unsafe yaml.load in the sources); the
bag and workout readers stay bounded in memory on hostile sizes and nesting; DDS discovery
is limited to localhost unless configured."""
from __future__ import annotations

import os
import pathlib
import random
import re
import struct
import subprocess
import sys
import textwrap

import pytest

from bike_plant.config import ConfigError, load_config
from bike_session.bags import BagError, open_bag
from bike_session.profiles import ProfileError
from bike_session.recover import recover
from bike_session.workouts import load_workout

ROOT = pathlib.Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config" / "bldc_default.yaml"
WORKOUTS = ROOT / "test" / "data" / "workouts"


def _mutations(data: bytes, seed: int, count: int):
    """Seeded hostile variants of ``data``: truncations, byte flips, inserted junk, random bytes."""
    rng = random.Random(seed)
    out = []
    for i in range(count):
        kind = i % 4
        if kind == 0:
            out.append(data[:rng.randrange(0, len(data))])
        elif kind == 1:
            b = bytearray(data)
            for _ in range(rng.randint(1, 20)):
                b[rng.randrange(len(b))] = rng.randrange(256)
            out.append(bytes(b))
        elif kind == 2:
            pos = rng.randrange(len(data))
            out.append(data[:pos] + bytes(rng.randrange(256) for _ in range(rng.randint(1, 64))) + data[pos:])
        else:
            out.append(bytes(rng.randrange(256) for _ in range(rng.randint(0, 2048))))
    return out


def _build_everything(cfg: dict) -> None:
    """What the nodes build from a config: plant model, controller law (both machines)."""
    from bike_controller.session_control import ModedController
    from bike_plant import params as P
    from bike_plant.node import make_backend

    make_backend("sim", cfg, 0)
    if str(cfg.get("machine", "bldc")) == "bldc":
        ModedController(cfg, P.nominal_params_from_config(cfg))
    else:
        from bike_controller.spmsm_session import ModedSpmsmController
        ModedSpmsmController(cfg)


# ------------------------------------------------------------------ configs
def test_fuzzed_configs_give_one_clear_error_each(tmp_path):
    """60 seeded variants of the default config: load_config and everything the nodes build
    from it either work or raise ConfigError / ValueError with a message; nothing else."""
    data = CONFIG.read_bytes()
    outcomes = {"ok": 0, "error": 0}
    for i, variant in enumerate(_mutations(data, seed=6, count=60)):
        path = tmp_path / f"c{i}.yaml"
        path.write_bytes(variant)
        try:
            cfg = load_config(path)
            _build_everything(cfg)
            outcomes["ok"] += 1
        except (ConfigError, ValueError) as exc:
            assert str(exc).strip(), f"variant {i}: empty error message"
            outcomes["error"] += 1
        except Exception as exc:  # noqa: BLE001 - the point of the test
            pytest.fail(f"variant {i} of the config raised {type(exc).__name__}: {exc}")
    assert outcomes["error"] >= 30, outcomes


HOSTILE_SCALARS = [".nan", ".inf", "-.inf", "-1", "0", "1e308", "-1e308", "abc", "true", "''", "99999999999999999999",
                   "0x7fffffff", "-0.0", "1e-300"]
HOSTILE_SHAPES = ["[]", "{}", "[1, 2]", "null"]


def test_fuzzed_config_values_give_an_error_naming_the_key(tmp_path):
    """The byte-level fuzz above stops early: 45 of its 60 variants end at "not a text file"
    and none reaches a value check. Here each scalar of the default config gets two seeded
    hostile values (NaN, inf, negative, zero, huge, a string, ...; and a list, a map or null), the
    rest of the file intact: each variant works or raises ConfigError / ValueError naming the
    key. (load.rider_preset: [] ended in a TypeError, "unhashable type: 'list'"; command0: -1
    and mode0 were refused as "controller: command must be ...", naming no key the file has.)"""
    lines = CONFIG.read_text().splitlines(keepends=True)
    scalars = [(i, m) for i, line in enumerate(lines)
               if (m := re.match(r"^(\s*)([A-Za-z_][A-Za-z_0-9]*): +[^\s#|>&*\[{]", line))]
    assert len(scalars) > 40
    rng = random.Random(6)
    outcomes, wrong = {"ok": 0, "named": 0}, []
    for n, (i, m) in enumerate(scalars):
        key = m.group(2)
        for value in (rng.choice(HOSTILE_SCALARS), rng.choice(HOSTILE_SHAPES)):
            path = tmp_path / f"v{n}_{len(wrong) + sum(outcomes.values())}.yaml"
            path.write_text("".join(lines[:i] + [f"{m.group(1)}{key}: {value}\n"] + lines[i + 1:]))
            try:
                _build_everything(load_config(path))
                outcomes["ok"] += 1
            except (ConfigError, ValueError) as exc:
                if key in str(exc):
                    outcomes["named"] += 1
                else:
                    wrong.append(f"{key}: {value}: error names no key: {exc}")
            except Exception as exc:  # noqa: BLE001 - the point of the test
                wrong.append(f"{key}: {value}: {type(exc).__name__}: {exc}")
    assert not wrong, "\n".join(wrong)
    assert outcomes["named"] >= len(scalars), outcomes


BAD_VALUES = [("load", "rider_target_cadence_rpm", 1000.0), ("load", "rider_target_cadence_rpm", -90.0),
              ("bldc", "inductance_h", -1.0), ("bldc", "inductance_h", "abc"), ("battery", "soc0", float("nan")),
              ("battery", "r_brake_ohm", 0.0), ("controller", "current_limit_a", float("inf")),
              ("mechanics", "inertia_kgm2", [1, 2]), ("controller", "k_factor", []), ("load", "kind", "dragon")]


@pytest.mark.parametrize("section,key,value", BAD_VALUES)
def test_bad_config_values_are_named(tmp_path, section, key, value):
    import yaml
    doc = yaml.safe_load(CONFIG.read_text())
    doc["/**"]["ros__parameters"][section][key] = value
    if section == "load":
        doc["/**"]["ros__parameters"]["load"]["rider_preset"] = "custom"      # else the preset's value wins
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises((ConfigError, ValueError), match=key.split("_")[0]):
        _build_everything(load_config(path))


def _cli(*args, timeout=120):
    return subprocess.run([str(ROOT / "bike"), *args], capture_output=True, text=True, timeout=timeout,
                          env=dict(os.environ, ROS_DOMAIN_ID=str(random.randint(101, 200))))


def _one_error(run) -> str:
    assert run.returncode == 2, (run.returncode, run.stdout[-2000:], run.stderr[-2000:])
    assert "Traceback" not in run.stderr + run.stdout, run.stderr
    lines = [line for line in run.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "error" in lines[0], run.stderr
    return lines[0]


def _refused_config_file(bike_cli, tmp_path, change) -> str:
    """`./bike run --config` of the default config changed by ``change(params)`` (its profile
    path made absolute): the one error line, which names the file; nothing started."""
    import yaml
    doc = yaml.safe_load(CONFIG.read_text())
    params = doc["/**"]["ros__parameters"]
    change(params)
    params["session"]["profile"] = str(ROOT / "config" / "profiles" / "demo_intervals.yaml")
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(doc))
    run = bike_cli("run", "--config", str(path), "--duration", "0.5", timeout=90)
    line = _one_error(run)
    assert str(path) in line, line
    assert run.stdout == "", run.stdout[-2000:]
    return line


@pytest.mark.parametrize("key,value,words", [
    ("batch_periods", -3, "batch_periods: must be finite and >= 1, got -3"),
    ("batch_periods", "abc", "batch_periods: expected a number, got 'abc'"),
    ("sync_mode", "dragon", "sync_mode: must be 'lockstep' or 'realtime'"),
    ("modes", {"erg_power_max_w": float("nan")}, "erg_power_max_w must be a number >= 0, got nan")])
def test_run_checks_the_config_before_any_node_starts(bike_cli, tmp_path, key, value, words):
    """A value only a node checked (the plant node's batch_periods / sync_mode; the modes section,
    which --set copies were checked for but a --config file was not) started the graph: the
    plant's configuration error among the other nodes' lines, exit 1. Now one error naming the
    file and key, exit 2, nothing started; --set names the config it changed, not its
    temporary copy."""
    line = _refused_config_file(bike_cli, tmp_path, lambda params: params.__setitem__(key, value))
    assert words in line, line
    if not isinstance(value, dict):
        line = _one_error(bike_cli("run", "--set", f"{key}={value}", "--duration", "0.5", timeout=90))
        assert line.startswith("error: --set: ") and str(CONFIG) in line and words in line, line


@pytest.mark.parametrize("item,words", [
    ("session.period_s=-1", "session.period_s: must be > 0, got -1"),
    ("session.period_s=abc", "session.period_s: must be a finite number, got 'abc'"),
    ("session.ftp_w=.nan", "session.ftp_w: must be a finite number, got nan"),
    ("controller.current_limit_a=-5", "controller: current_limit_a must be > 0, got -5.0"),
    # the modes section's messages named neither the config nor the section
    ("modes.erg_power_max_w=-1", "modes: erg_power_max_w must be a number >= 0, got -1.0"),
    ("modes.foo=1", ".yaml: modes: unknown key(s) foo"),
    ("session.profile=/nonexistent/p.yaml", "session.profile: /nonexistent/p.yaml: cannot read profile")])
def test_run_checks_the_session_controller_and_profile_before_any_node_starts(bike_cli, tmp_path, item, words):
    """What the session node (period, profile) and the controller node (its parameters) refused
    once the graph had started: one error naming --set, the config and the key, exit 2, nothing
    started; a --config whose profile is missing too."""
    line = _one_error(bike_cli("run", "--set", item, "--duration", "0.5", timeout=90))
    assert line.startswith("error: --set: ") and str(CONFIG) in line and words in line, line
    if item.startswith("session.profile"):
        path = tmp_path / "bad.yaml"
        path.write_text(CONFIG.read_text())          # its relative profile is not beside the copy
        run = bike_cli("run", "--config", str(path), "--duration", "0.5", timeout=90)
        line = _one_error(run)
        assert str(path) in line and "session.profile" in line and "cannot read profile" in line, line
        assert run.stdout == "", run.stdout[-2000:]


@pytest.mark.parametrize("sets,words", [
    (["clock_period_s=0.08"], "clock_period_s: must be at most half of session.period_s = 0.1 s, got 0.08"),
    (["session.period_s=0.01"], "clock_period_s: must be at most half of session.period_s = 0.01 s, got 0.01"),
    # 0.15 s batches against 0.1 s Commands rode the demo with a third of its Commands never applied
    (["batch_periods=3000"], "batch_periods: one batch (3000 x control_period_s 5e-05 s = 0.15 s) must be at most "
                             "half of session.period_s = 0.1 s"),
    # hysteresis control with one edge per period: a 2 ms period braked 53 W for 340 W, no current shown
    (["control_period_s=0.002", "batch_periods=1"], "control_period_s: 0.002 s is too long a period for hysteresis "
                                                    "current control on this machine: the current changes by up to "
                                                    "466 A in one"),
    (["recorder_window_batches=101"], "recorder_window_batches: must be at most 100 (half the loop topics' DDS "
                                      "history), got 101"),
    (["backend=can", "sync_mode=lockstep"], "sync_mode: backend 'can' drives a real drive in real time"),
    (["session.over_range=clamp"], "session.over_range: must be 'warn' or 'error', got 'clamp'"),
    (["session.over_range=5"], "session.over_range: must be 'warn' or 'error', got 5"),
    (["command_wait_s=-1"], "command_wait_s: must be a number > 0, got -1"),
    (["sync_mode=realtime", "busy_wait_s=-1"], "busy_wait_s: must be finite and >= 0.0, got -1"),
])
def test_run_checks_what_the_nodes_check_across_keys_before_any_node_starts(bike_cli, tmp_path, sets, words):
    """Checks a node made once the graph had started, its error among the other nodes' lines
    (exit 1): the plant's clock_period_s against session.period_s (the node's default clock
    period when the config gives none); its recorder_window_batches against the loop topics' DDS
    history (LOOP_QOS, whose depth is config.LOOP_HISTORY_DEPTH); backend can in lockstep; the
    session's over_range (only read with a workout, and then named by the workout file); the
    controller node's own numbers (command_wait_s; busy_wait_s, which it reads in realtime too). Now one error naming --set, the config and the key,
    exit 2, nothing started; a --config file with the values too."""
    import yaml
    line = _one_error(bike_cli("run", *(x for item in sets for x in ("--set", item)), "--duration", "0.5", timeout=90))
    assert line.startswith("error: --set: ") and str(CONFIG) in line and words in line, line

    def change(params):
        for item in sets:
            key, _eq, text = item.partition("=")
            node = params
            *parents, leaf = key.split(".")
            for part in parents:
                node = node.setdefault(part, {})
            node[leaf] = yaml.safe_load(text)
    assert words in _refused_config_file(bike_cli, tmp_path, change)


def test_run_takes_a_lockstep_can_config_with_ftms_which_rides_it_in_real_time(capsys):
    """--ftms rides every config in real time (an overrides file), so the check of backend can
    against lockstep goes by the sync mode the run rides, not the config's alone."""
    from bike_session.cli import _backend_sync_mode_ok
    cfg = dict(load_config(CONFIG), backend="can", sync_mode="lockstep")
    assert _backend_sync_mode_ok(cfg, CONFIG, CONFIG, ftms_on=True)
    assert not _backend_sync_mode_ok(cfg, CONFIG, CONFIG, ftms_on=False)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{CONFIG}: sync_mode: backend 'can'" in err[0], err


def test_run_reads_the_workout_with_the_configs_over_range(tmp_path):
    """session.over_range: error refuses a workout target beyond the machine's range: ./bike run
    read the workout with 'warn' (the targets saturated, a warning) and the session node, which
    reads it with the config's over_range, refused it once the graph had started (exit 1). Now
    one error naming the workout, exit 2, nothing started."""
    workout = tmp_path / "hard.zwo"
    workout.write_text('<workout_file><workout>\n<SteadyState Duration="60" Power="3.0"/>\n</workout></workout_file>\n')
    run = _cli("run", "--set", "session.over_range=error", "--workout", str(workout), "--ftp", "400",
               "--duration", "0.5", timeout=90)
    line = _one_error(run)
    assert str(workout) in line and "exceeds the machine's power range" in line, line
    assert "--set" not in run.stdout and "[bike] config" not in run.stdout, run.stdout[-2000:]


@pytest.mark.parametrize("key,value,words", [
    ("batch_periods", -3, "batch_periods: must be finite and >= 1, got -3"),
    ("command_wait_s", -1, "command_wait_s: must be a number > 0, got -1")])
def test_replay_names_the_given_config_and_leaves_nothing_when_it_refuses_it(tmp_path, monkeypatch, capsys,
                                                                             key, value, words):
    """./bike replay BAG --config BAD: the run it hands the replay's config to refused it naming
    the generated replay_<bag>_config.yaml, and that file and the profile were left in the
    --record folder. Now one error naming --config's file and the key, exit 2, --record as it
    was (not even the folder when the replay made it)."""
    import yaml

    from bike_session import replay
    info = {"duration_s": 1.0, "period_s": 0.1, "config_text": CONFIG.read_text()}
    monkeypatch.setattr(replay, "command_timeline", lambda _bag: ([(0, 0.5, 0, 0.0, None)], info))
    doc = yaml.safe_load(CONFIG.read_text())
    doc["/**"]["ros__parameters"][key] = value
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(doc))
    for record in (tmp_path / "runs", tmp_path / "new" / "runs"):
        record.parent.mkdir(exist_ok=True)
        if record.name == "runs" and record.parent == tmp_path:
            record.mkdir()
        code = replay.main([str(tmp_path / "session_x"), "--config", str(bad), "--record", str(record)])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and err[0].startswith(f"error: {bad}: ") and words in err[0], err
        assert "_config.yaml" not in err[0], err
        assert (list(record.iterdir()) == []) if record.parent == tmp_path else not record.exists()


def test_replay_on_another_machine_keeps_the_recorded_rider_on_that_bikes_drivetrain(tmp_path, monkeypatch):
    """./bike replay of a BLDC ride --config spmsm_default.yaml (--load recorded, the default)
    rode the BLDC's 35:1 gear on the SPMSM: 14 W braking, the pack drawn down. The recorded
    rider (preset, torque-cadence line, heart) rides on, but the gear and the rider's effort
    gains, tuned on the bike's crank inertia, are the other bike's."""
    import yaml

    from bike_plant.config import load_config
    from bike_session import replay
    recorded = yaml.safe_load(CONFIG.read_text())
    recorded["/**"]["ros__parameters"]["load"]["rider_preset"] = "trained"
    info = {"duration_s": 1.0, "period_s": 0.1, "config_text": yaml.safe_dump(recorded)}
    monkeypatch.setattr(replay, "command_timeline", lambda _bag: ([(0, 0.5, 0, 0.0, None)], info))
    spmsm = ROOT / "config" / "spmsm_default.yaml"
    own = load_config(spmsm)["load"]
    prep = replay.prepare(tmp_path / "session_x", tmp_path / "runs", str(spmsm), "recorded")
    load = load_config(prep["config"])["load"]
    assert load["rider_preset"] == "trained" and load["kind"] == "rider"
    for key in replay.BIKE_LOAD_KEYS:
        assert load[key] == own[key], key
    same = replay.prepare(tmp_path / "session_x", tmp_path / "runs2", None, "recorded")
    assert load_config(same["config"])["load"]["gear_ratio"] == recorded["/**"]["ros__parameters"]["load"]["gear_ratio"]
    # a second replay into the same folder keeps the first one's files (its bag names them)
    again = replay.prepare(tmp_path / "session_x", tmp_path / "runs", None, "recorded")
    assert again["config"] != prep["config"] and again["profile"] != prep["profile"]
    assert prep["config"].exists() and prep["profile"].exists() and again["config"].name.endswith("_2_config.yaml")



def test_replay_of_an_spmsm_ride_on_the_bldc_bike_keeps_the_rider_without_the_dynamometer(tmp_path, monkeypatch):
    """./bike replay of an SPMSM ride --config bldc_default.yaml (--load recorded) was refused:
    "bldc_default.yaml: load: unknown parameter(s) dyno_time_s, dyno_torque_nm", naming a file
    that is fine, for the SPMSM's own dynamometer keys in the recorded load. The recorded rider
    rides the BLDC bike; a key the recorded machine does not know either is still one error."""
    import yaml

    from bike_plant.config import ConfigError, load_config
    from bike_session import replay
    spmsm = ROOT / "config" / "spmsm_default.yaml"
    recorded = yaml.safe_load(spmsm.read_text())
    recorded["/**"]["ros__parameters"]["load"]["rider_preset"] = "trained"
    info = {"duration_s": 1.0, "period_s": 0.1, "config_text": yaml.safe_dump(recorded)}
    monkeypatch.setattr(replay, "command_timeline", lambda _bag: ([(0, 0.5, 0, 0.0, None)], info))
    own = load_config(CONFIG)["load"]
    prep = replay.prepare(tmp_path / "session_x", tmp_path / "runs", str(CONFIG), "recorded")
    load = load_config(prep["config"])["load"]
    assert load["rider_preset"] == "trained" and load["kind"] == "rider" and "dyno_time_s" not in load
    for key in replay.BIKE_LOAD_KEYS:
        assert load[key] == own[key], key
    recorded["/**"]["ros__parameters"]["load"]["rider_t0_nmm"] = 100.0          # a typo stays an error
    info["config_text"] = yaml.safe_dump(recorded)
    with pytest.raises(ConfigError, match="rider_t0_nmm"):
        replay.prepare(tmp_path / "session_x", tmp_path / "runs3", str(CONFIG), "recorded")

def test_replay_leaves_nothing_when_the_run_refuses_it_after_the_config_checks(tmp_path, monkeypatch, capsys):
    """A refusal from ./bike run's checks after the config's (it was a calibration_file under a
    regular file; the replay no longer hands the config's files on, so one of those checks is
    made to refuse here) left the replay's generated profile and config in --record. Now
    --record is as it was, and the run's one error is the only one."""
    from bike_session import cli, replay
    info = {"duration_s": 1.0, "period_s": 0.1, "config_text": CONFIG.read_text()}
    monkeypatch.setattr(replay, "command_timeline", lambda _bag: ([(0, 0.5, 0, 0.0, None)], info))

    def refuse(_cfg, _args, recording):
        print("error: output_file: refused by a check after the config's", file=sys.stderr)
        return False

    monkeypatch.setattr(cli, "_config_launch_args", refuse)
    record = tmp_path / "runs"
    record.mkdir()
    code = replay.main([str(tmp_path / "session_x"), "--config", str(CONFIG), "--record", str(record)])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and err == ["error: output_file: refused by a check after the config's"], err
    assert list(record.iterdir()) == []


def test_run_refuses_a_session_key_no_node_reads(bike_cli, tmp_path, capsys):
    """`--set session.perod_s=0.05` (a typo) or a config's unknown session: key rode the config's
    period without a word: one error naming the section and the key. SESSION_KEYS holds every
    session.* parameter the session node declares (read from its source, so a new one is seen)."""
    import re

    from bike_session import workouts
    from bike_session.cli import _set_run_config
    assert _set_run_config(["session.perod_s=0.05"], CONFIG) is None
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "session: unknown key(s) perod_s; known: profile, period_s" in err[0], err
    line = _refused_config_file(bike_cli, tmp_path, lambda p: p["session"].update(perod_s=0.05))
    assert "unknown key(s) perod_s" in line, line
    source = (ROOT / "src" / "bike_session" / "bike_session" / "session_node.py").read_text()
    declared = set(re.findall(r'"session\.([a-z_0-9]+)"', source))
    assert declared and declared <= set(workouts.SESSION_KEYS), declared - set(workouts.SESSION_KEYS)


def test_run_set_refuses_a_key_no_node_reads(capsys):
    """--set batch_period=5 (a typo) or --set foo=1 was written into the run's config, which no
    node reads: the run went on with batch_periods 20 without a word. One error naming --set
    and the key (with the near one), nothing runs; a key a node reads but the config leaves to
    its default is still taken."""
    from bike_session.cli import _set_run_config
    for item, words in (("batch_period=5", "unknown key 'batch_period'"), ("foo=1", "unknown key 'foo'"),
                        ("nope.x=1", "unknown key 'nope'")):
        assert _set_run_config([item], CONFIG) is None, item
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: --set: ") and words in err[0], (item, err)
    assert "did you mean batch_periods?" in (_set_run_config(["batch_period=5"], CONFIG) or capsys.readouterr().err)
    path, cfg = _set_run_config(["clock_period_s=0.005", "modes.auto_shift=true"], CONFIG)
    assert cfg["clock_period_s"] == 0.005 and cfg["modes"]["auto_shift"] is True


def test_run_set_of_another_machine_is_one_error_naming_it(capsys):
    """--set machine=spmsm on the BLDC config said "battery: unknown parameter(s) r_brake_ohm, ..."
    (the SPMSM loader reading the BLDC bike's sections); --set machine=bldc there changes nothing."""
    from bike_session.cli import _set_run_config
    assert _set_run_config(["machine=spmsm"], CONFIG) is None
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: --set: 'machine=spmsm': the sections of bldc_default.yaml are its 'bldc' bike's; ride "
                   "another machine with --config (config/bldc_default.yaml, config/spmsm_default.yaml)"], err
    path, cfg = _set_run_config(["machine=bldc"], CONFIG)
    assert cfg["machine"] == "bldc"


@pytest.mark.parametrize("map_text, words", [("- 1\n", "expected a mapping 'drive_torque_map:' at the top"),
                                             (None, "cannot read it (No such file or directory)")])
def test_run_refuses_a_torque_map_the_plant_cannot_use_before_any_node_starts(bike_cli, tmp_path, map_text, words):
    """A can.torque_map_file the plant node could not use was its error once the graph (and the drive
    emulator) had started: "[launcher] node 'plant' exited with code 2", exit 1. One error now."""
    bad = tmp_path / "map.yaml"
    if map_text is not None:
        bad.write_text(map_text)
    line = _one_error(bike_cli("run", "--config", str(ROOT / "config" / "bldc_can.yaml"), "--duration", "1",
                           "--set", f"can.torque_map_file={bad}", timeout=90))
    assert line == f"error: --set: {ROOT / 'config' / 'bldc_can.yaml'}: can.torque_map_file: {bad}: {words}", line


@pytest.mark.parametrize("emulator_args, words", [
    ("[--bogus]", "unrecognized arguments: --bogus"),
    ("[--physics, nope]", "argument --physics: invalid choice: 'nope' (choose from 'plant', 'average')"),
    # text on both sides since rcl_scalar_kind, and the emulator refused it only once the graph was up
    ("[--watchdog-s, nan]", "argument --watchdog-s: must be a finite number >= 0, got 'nan'"),
    ("[--heartbeat-ms, '-5']", "argument --heartbeat-ms: must be a finite number >= 0, got '-5'")])
def test_run_refuses_emulator_args_the_drive_emulator_refuses_before_any_node_starts(bike_cli, emulator_args, words):
    """can.emulator_args the emulator's parser refused printed its usage once the graph had started,
    its node exiting. One error naming the key, nothing starts."""
    line = _one_error(bike_cli("run", "--config", str(ROOT / "config" / "bldc_can.yaml"), "--duration", "1",
                           "--set", f"can.emulator_args={emulator_args}", timeout=90))
    assert line == f"error: can.emulator_args: {words} (bike-drive-emulator's options)", line


def test_run_refuses_a_value_ros_types_otherwise_before_any_node_starts(bike_cli, tmp_path):
    """rcl's parameter parser types an unquoted nan, 1e5 or y itself (a number, true/false) where the
    config's loader reads text: [--watchdog-s, nan] passed every check, then each node exited with
    a traceback ('Sequence should be of same type'). One error naming the key and the quoting."""
    line = _refused_config_file(bike_cli, tmp_path, lambda p: p.update(can={"emulator_args": ["--watchdog-s", "nan"]}))
    assert ": can.emulator_args: unquoted 'nan' (line " in line, line
    assert line.endswith(") is text to this config's loader but decimal to ROS 2's parameter parser (the nodes'): "
                         "quote it ('...') if it is text"), line


def test_run_set_of_text_rcl_would_type_is_ridden_as_text():
    """--set can.emulator_args=[--heartbeat-ms, 1e2]: text to the --set parser, written quoted into the
    run's config (it was written bare: a double to rcl, each node's mixed-list traceback), so the
    emulator gets the option as text and the run rides."""
    run = _cli("run", "--config", str(ROOT / "config" / "bldc_can.yaml"), "--duration", "0.3",
               "--set", "can.emulator_args=[--heartbeat-ms, 1e2]", timeout=120)
    assert run.returncode == 0, (run.returncode, run.stdout[-2000:], run.stderr[-2000:])
    assert "Traceback" not in run.stderr + run.stdout and "error" not in run.stderr.lower(), run.stderr[-2000:]


def test_run_set_of_a_rider_value_is_ridden_not_overridden_by_the_rider_preset(capsys):
    """The README's `--set load.rider_target_cadence_rpm=90` rode 80 rpm: load.rider_preset
    (recreational in the shipped configs) sets the rider's values over the section's own, so the
    --set value was dropped without a word. It is ridden now, with the preset's other values,
    and a note says so; a --set of another load value leaves the preset alone. A target
    cadence outside (0, rider_cadence_max_rpm), which the preset had hidden, is refused."""
    from bike_plant.params import RIDER_PRESETS, plant_params_from_config

    from bike_session.cli import _set_run_config
    _path, cfg = _set_run_config(["load.rider_target_cadence_rpm=90"], CONFIG)
    load = plant_params_from_config(cfg).load
    assert load.rider_target_cadence_rpm == 90.0
    assert load.rider_t0_nm == RIDER_PRESETS["recreational"]["rider_t0_nm"]
    assert load.rider_max_hr_bpm == RIDER_PRESETS["recreational"]["rider_max_hr_bpm"]
    out = capsys.readouterr().out
    assert "load.rider_preset recreational would override it" in out, out
    _path, cfg = _set_run_config(["load.rider_preset=trained", "load.rider_t0_nm=250"], CONFIG)
    load = plant_params_from_config(cfg).load
    assert load.rider_t0_nm == 250.0 and load.rider_target_cadence_rpm == RIDER_PRESETS["trained"]["rider_target_cadence_rpm"]
    capsys.readouterr()
    for bad in ("1000", "-90"):
        assert _set_run_config([f"load.rider_target_cadence_rpm={bad}"], CONFIG) is None
        err = capsys.readouterr()
        assert "rider_target_cadence_rpm must be in (0, rider_cadence_max_rpm = 160)" in err.err and err.out == ""
    _path, cfg = _set_run_config(["load.gear_ratio=30"], CONFIG)
    assert cfg["load"]["rider_preset"] == "recreational" and plant_params_from_config(cfg).load.gear_ratio == 30.0
    assert capsys.readouterr().out == ""


def test_run_rides_the_configs_values_of_the_parameters_the_launch_file_sets(tmp_path, monkeypatch, capsys):
    """recorder_window_batches, can_log_file and calibration_file are node parameters the
    launch file sets after the config (0, "", ""), so a config's or --set's value was dropped
    without a word (--set recorder_window_batches=10 rode the run's 50). ./bike run now hands
    them to the launch file: a window that paces nothing (no --record) is said, a can log on
    a simulated bike is said, and a file that cannot be written is one error naming its key.
    (launcher.run is replaced: what is checked is what ./bike run hands it.)"""
    from bike_session import cli, launcher

    launched = []
    monkeypatch.setattr(launcher, "run", lambda _launch, args, **_kw: launched.append(dict(args)) or 0)
    monkeypatch.setenv("ROS_DOMAIN_ID", "0")         # no domain lock for a run that starts nothing
    can_config = ROOT / "config" / "bldc_can.yaml"

    def run(*argv):
        launched.clear()
        code = cli.main(["run", "--duration", "1", *argv])
        return code, (launched[0] if launched else None), capsys.readouterr()

    _code, args, out = run("--set", "recorder_window_batches=10", "--record", str(tmp_path / "rec"))
    assert args["recorder_window"] == "10", args
    _code, args, out = run("--record", str(tmp_path / "rec"))
    assert args["recorder_window"] == str(cli.RECORDER_WINDOW_BATCHES)
    code, args, out = run("--set", "recorder_window_batches=10")
    assert code == 0 and "recorder_window" not in args
    assert "recorder_window_batches 10 not used: it paces a recorded run (--record)" in out.out
    code, args, out = run("--set", f"calibration_file={tmp_path / 'cal' / 'bike.yaml'}")
    assert code == 0 and args["calibration"] == str(tmp_path / "cal" / "bike.yaml")
    code, args, out = run("--set", "can_log_file=frames.asc")
    assert code == 0 and "can_log" not in args and "can_log_file frames.asc not used" in out.out
    code, args, out = run("--config", str(can_config), "--set", f"can_log_file={tmp_path / 'frames.asc'}")
    assert code == 0 and args["can_log"] == str(tmp_path / "frames.asc"), (args, out)
    blocker = tmp_path / "file"
    blocker.write_text("")
    for item, message in ((f"calibration_file={blocker / 'cal.yaml'}", "error: calibration_file "),
                          ("can_log_file=frames.txt", "error: can_log_file must end in .asc or .blf"),
                          (f"can_log_file={blocker / 'f.asc'}", "error: can_log_file ")):
        extra = () if item.startswith("calibration") else ("--config", str(can_config))
        code, args, out = run(*extra, "--set", item)
        assert code == 2 and args is None and out.err.startswith(message), (item, out.err)


def test_yaml_python_tags_are_refused_not_run(tmp_path):
    """A config with !!python tags is refused (safe_load) and nothing is executed."""
    marker = tmp_path / "pwned"
    evil = CONFIG.read_text().replace(
        "duration_s: 60.0", f"duration_s: !!python/object/apply:os.system ['touch {marker}']")
    assert evil != CONFIG.read_text()
    path = tmp_path / "evil.yaml"
    path.write_text(evil)
    with pytest.raises(ConfigError):
        load_config(path)
    line = _one_error(_cli("run", "--config", str(path), "--duration", "0.1"))
    assert "evil.yaml" in line
    assert not marker.exists()
    # the launch file is read the same way
    from bike_session.launcher import LaunchError, parse_launch
    launch = tmp_path / "evil.launch.yaml"
    launch.write_text(f"launch:\n- arg: {{name: x, default: !!python/object/apply:os.system ['touch {marker}']}}\n")
    with pytest.raises(LaunchError):
        parse_launch(str(launch))
    assert not marker.exists()


def test_no_config_value_is_evaluated_as_code():
    """No eval / exec / pickle / unsafe yaml.load in the sources. The two execs (the report's
    fast CDR decoder, the loop's CDR codec) compile source built from fixed templates: only
    integers, struct format letters from a fixed table and the installed message classes'
    field names (rosidl identifiers, quoted with repr) are interpolated, never a string from
    a bag, a config or the wire."""
    pattern = re.compile(r"\b(eval|exec)\s*\(|yaml\.load\s*\(|yaml\.unsafe_load|yaml\.full_load|"
                         r"Loader\s*=\s*yaml\.(Full|Unsafe)?Loader|pickle\.loads?\s*\(|marshal\.loads")
    hits = []
    for path in list((ROOT / "src").rglob("*.py")) + list((ROOT / "tools").rglob("*.py")):
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if pattern.search(line) and not line.lstrip().startswith("#"):
                hits.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    allowed = [h for h in hits if (h.startswith("src/bike_session/bike_session/report.py")
                                   and 'exec("\\n".join(src), ns)' in h)
               or (h.startswith("src/bike_plant/bike_plant/cdr.py") and 'exec("\\n".join(src), env)' in h)]
    assert sorted(set(hits) - set(allowed)) == [], hits
    assert len(allowed) <= 2


# ------------------------------------------------------------------ workouts
# the default config's controller.pmax_w: without it every workout file, whatever it held, was
# refused before it was read ("pmax_w ... is required to turn watts into a Command"), so the
# fuzzing and the hostile cases below reached no parser
PMAX_W = 1016.68


def test_fuzzed_workouts_give_one_clear_error_each(tmp_path):
    """40 seeded variants of each real workout file (.zwo, .erg, .mrc, .fit): a workout or one
    ProfileError; never another exception. Some variants parse (a truncation that keeps whole
    steps, a flip inside a comment): the parser is reached."""
    originals = sorted(p for p in WORKOUTS.iterdir() if p.is_file())
    assert {p.suffix for p in originals} >= {".zwo", ".erg", ".mrc", ".fit"}
    for src in originals:                     # the parser is reached: the originals are workouts
        load_workout(src, ftp_w=250.0, pmax_w=PMAX_W)
    errors = parsed = 0
    for src in originals:
        for i, variant in enumerate(_mutations(src.read_bytes(), seed=hash(src.name) & 0xFFFF, count=40)):
            path = tmp_path / f"w{i}{src.suffix}"
            path.write_bytes(variant)
            try:
                load_workout(path, ftp_w=250.0, pmax_w=PMAX_W)
                parsed += 1
            except ProfileError as exc:
                assert str(exc).strip() and "is required" not in str(exc), exc
                errors += 1
            except Exception as exc:  # noqa: BLE001
                pytest.fail(f"{src.name} variant {i} raised {type(exc).__name__}: {exc}")
    assert errors >= 40 and parsed >= 1, (errors, parsed)


def _fit_file(header: bytes, records: bytes) -> bytes:
    """A FIT file of (mutated) records, its header's data size and both CRCs made right again:
    the decoder then parses the records instead of stopping at a size or a checksum."""
    from garmin_fit_sdk import CrcCalculator
    head = header[:4] + struct.pack("<I", len(records)) + header[8:12]
    head += struct.pack("<H", CrcCalculator.calculate_crc(head, 0, 12))
    body = head + records
    return body + struct.pack("<H", CrcCalculator.calculate_crc(body, 0, len(body)))


def test_fuzzed_fit_records_past_the_checksum_give_one_clear_error_each(tmp_path):
    """200 seeded byte flips and junk insertions inside the records of a real FIT workout, the
    data size and CRCs made right each time (so the FIT SDK's decoder, and then the step rules,
    see the hostile content): a workout or one ProfileError, never another exception."""
    data = (WORKOUTS / "sweet_spot.fit").read_bytes()
    header, records = data[:14], data[14:-2]
    assert _fit_file(header, records) == data
    rng = random.Random(2026)
    outcomes = {"workout": 0, "error": 0}
    for i in range(200):
        b = bytearray(records)
        if i % 2:
            for _ in range(rng.randint(1, 6)):
                b[rng.randrange(len(b))] = rng.randrange(256)
        else:
            pos = rng.randrange(len(b))
            b[pos:pos] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
        path = tmp_path / f"f{i}.fit"
        path.write_bytes(_fit_file(header, bytes(b)))
        try:
            load_workout(path, ftp_w=250.0, pmax_w=1016.68)
            outcomes["workout"] += 1
        except ProfileError as exc:
            assert str(exc).strip() and path.name in str(exc)
            outcomes["error"] += 1
        except Exception as exc:  # noqa: BLE001
            pytest.fail(f"variant {i} raised {type(exc).__name__}: {exc}")
    assert outcomes["error"] >= 20 and outcomes["workout"] >= 1, outcomes
    # a truncated file: what it is, before the SDK's own words (a TypeError of its internals)
    path = tmp_path / "truncated.fit"
    path.write_bytes(data[:len(data) // 2])
    with pytest.raises(ProfileError, match="corrupt FIT file: truncated or damaged"):
        load_workout(path, ftp_w=250.0, pmax_w=1016.68)


def test_hostile_workouts_are_bounded(tmp_path):
    """Deep nesting, many elements, a huge repeat count (ZWO and FIT), a 300 kB FIT file, a sparse
    file claiming 2 GB: one ProfileError each, quickly, without reading the file into memory."""
    cases = {
        "deep.zwo": "<workout_file><workout>" + "<a>" * 100_000 + "</a>" * 100_000 + "</workout></workout_file>",
        # 240 kB, under the size limit (60 000 SteadyStates were 2.3 MB: the size limit took them)
        "wide.zwo": "<workout_file><workout>" + "<a/>" * 60_000 + "</workout></workout_file>",
        "repeat.zwo": '<workout_file><workout><IntervalsT Repeat="1000000000" OnDuration="60" OffDuration="60" '
                      'OnPower="1" OffPower="0.5"/></workout></workout_file>',
        "bomb.zwo": '<?xml version="1.0"?><!DOCTYPE l [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;&a;&a;">]>'
                    "<workout_file><name>&b;</name></workout_file>",
        "long.erg": "[COURSE HEADER]\nMINUTES WATTS\n[END COURSE HEADER]\n[COURSE DATA]\n0 100\n1e12 100\n"
                    "[END COURSE DATA]\n",
    }
    words = {"deep.zwo": "nested deeper", "wide.zwo": "more than 50000 XML elements", "repeat.zwo": "Repeat: must be in",
             "bomb.zwo": "entity declarations are not allowed", "long.erg": "beyond 24 h"}
    for name, text in cases.items():
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(ProfileError) as err:
            load_workout(path, ftp_w=250.0, pmax_w=PMAX_W)
        assert words[name] in str(err.value), (name, str(err.value))
    # FIT: a repeat of 10^9 and a 300 kB file, both with valid CRCs
    from fit_files import fit_workout_bytes
    step = dict(duration_type="time", duration_value=1000, target_type="open")
    repeat = dict(duration_type="repeat_until_steps_cmplt", duration_value=0, target_type="open",
                  target_value=1_000_000_000)
    (tmp_path / "repeat.fit").write_bytes(fit_workout_bytes([step, repeat]))
    (tmp_path / "wide.fit").write_bytes(fit_workout_bytes([step] * 30_000))
    for name in ("repeat.fit", "wide.fit"):
        with pytest.raises(ProfileError, match="repeat count|too large"):
            load_workout(tmp_path / name, ftp_w=250.0, pmax_w=1016.68)
    huge = tmp_path / "huge.zwo"
    with open(huge, "wb") as fh:
        fh.truncate(2 << 30)           # sparse: claims 2 GB, occupies nothing
    with pytest.raises(ProfileError, match="too large"):
        load_workout(huge, ftp_w=250.0, pmax_w=PMAX_W)


# ------------------------------------------------------------------ bags
def _small_bag(path: pathlib.Path, storage: str, count: int = 200, writer=None, compress=None,
               compressor=None) -> None:
    """A bag of ``count`` Commands through the recorder's BagSink; or (``writer``) through a rosbags
    writer that ``compress`` set up and whose chunks ``compressor`` makes."""
    from bike_session.recorder_node import BagSink, build_typestore
    ts = build_typestore()
    Command = ts.types["bike_msgs/msg/Command"]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    if writer is None:
        sink = BagSink(path, storage, ts, [("/bike/command", "bike_msgs/msg/Command", True, False)])
        write, close = (lambda t, data: sink.write("/bike/command", t, data)), sink.close
    else:
        w = writer(path)
        compress(w)
        w.open()
        w.storage.compressor = compressor
        conn = w.add_connection("/bike/command", "bike_msgs/msg/Command", typestore=ts)
        write, close = (lambda t, data: w.write(conn, t, data)), w.close
    for k in range(count):
        msg = Command(header=Header(stamp=Time(sec=0, nanosec=k * 1000), frame_id=""), command=0.5, mode=0,
                      virtual_gear_ratio=0.0, road_from_command=False, crr=0.0, cw_kg_m=0.0, wind_mps=0.0,
                      cadence_rpm=0.0, heart_rate_bpm=0.0)
        write(k * 1000, ts.serialize_cdr(msg, "bike_msgs/msg/Command"))
    close()


def _read_all(path: pathlib.Path) -> int:
    with open_bag(path) as bag:
        return sum(1 for _ in bag.messages())


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_fuzzed_bags_give_one_clear_error_each(tmp_path, storage):
    """30 seeded corruptions of a real bag's data file and of its metadata.yaml: reading and
    recovering give data or one BagError, never another exception."""
    good = tmp_path / "good"
    _small_bag(good, storage)
    data_file = next(p for p in good.iterdir() if p.suffix in (".mcap", ".db3"))
    assert _read_all(good) == 200
    errors = 0
    for i, variant in enumerate(_mutations(data_file.read_bytes(), seed=60 + len(storage), count=30)
                                + _mutations((good / "metadata.yaml").read_bytes(), seed=61, count=10)):
        bag = tmp_path / f"b{i}"
        bag.mkdir()
        meta = (good / "metadata.yaml").read_bytes()
        body = data_file.read_bytes()
        if i < 30:
            body = variant
        else:
            meta = variant
        (bag / data_file.name.replace("good", bag.name)).write_bytes(body)
        (bag / "metadata.yaml").write_bytes(meta.replace(b"good", bag.name.encode()))
        for action in (_read_all, lambda p: (p / "metadata.yaml").unlink() or recover(p)):
            try:
                action(bag)
            except BagError as exc:
                # clear: a length field that claims more than memory holds ended reading with
                # "cannot open bag: MemoryError" (4 of the 30 mcap variants)
                assert str(exc).strip() and "MemoryError" not in str(exc), (i, str(exc))
                errors += 1
            except Exception as exc:  # noqa: BLE001
                pytest.fail(f"bag variant {i} ({action}): {type(exc).__name__}: {exc}")
    assert errors >= 20


def test_cli_on_a_corrupt_bag_prints_one_error(bike_cli, tmp_path):
    bag = tmp_path / "b"
    _small_bag(bag, "mcap")
    data = next(bag.glob("*.mcap"))
    data.write_bytes(data.read_bytes()[: data.stat().st_size // 2])
    for args in (["report", str(bag), "--out", str(tmp_path / "r")], ["bag", "recover", str(tmp_path / "nope")]):
        _one_error(bike_cli(*args))


@pytest.mark.parametrize("duration", ["inf", "nan", "-1", "0", "1e300"])
def test_run_refuses_a_duration_that_is_not_a_finite_positive_number(bike_cli, duration):
    """`--duration inf` passed the CLI's > 0 check; the session node then refused it while the
    plant and the controller had started (a traceback when they were stopped mid-import).
    `--duration 1e300` (beyond the ROS clock's int64 nanoseconds) was the session node's
    OverflowError traceback."""
    assert "--duration" in _one_error(bike_cli("run", "--duration", duration, timeout=60))


@pytest.mark.parametrize("namespace", ["a-b", "9bike", "bike//x", "bike x"])
def test_run_refuses_an_invalid_namespace(bike_cli, namespace):
    """Every node died in rclpy.init with a traceback (an invalid remap rule)."""
    line = _one_error(bike_cli("run", "--duration", "1", "--namespace", namespace, timeout=60))
    assert "--namespace" in line and "Invalid namespace" in line, line
    assert not line.endswith(":"), line            # rclpy's first line led to the two it leaves out


@pytest.mark.parametrize("namespace", ["a b", "9bike", "bike//x"])
def test_shift_refuses_an_invalid_namespace(bike_cli, namespace):
    """`./bike shift 1 --namespace 'a b'` ended in rclpy's InvalidTopicNameException (a traceback)."""
    line = _one_error(bike_cli("shift", "1", "--domain", "7", "--namespace", namespace, timeout=60))
    assert "--namespace" in line and "Invalid namespace" in line, line
    assert not line.endswith(":"), line


@pytest.mark.parametrize("args, words", [
    (["--ftp", "200"], "--ftp needs --workout FILE"), (["--max-hr", "190"], "--max-hr needs --workout FILE"),
    (["--ftms-port", "5000"], "--ftms-port needs --ftms"), (["--ftms-host", "0.0.0.0"], "--ftms-host needs --ftms"),
    (["--ftms-advertise", "true"], "--ftms-advertise needs --ftms"),
    (["--storage", "sqlite3"], "--storage needs --record")])
def test_run_refuses_an_option_its_partner_is_missing_for(bike_cli, args, words):
    """Each rode the config's profile, unrecorded or without FTMS, the option dropped without a
    word (a newcomer's `./bike run --ftp 250` rode the demo's Commands as ever). One error."""
    line = _one_error(bike_cli("run", "--duration", "1", *args, timeout=60))
    assert words in line, line


def test_run_refuses_a_bad_launch_file_before_it_says_anything(bike_cli, tmp_path):
    """A --launch file that is no launch description (or a folder) was refused after the
    domain's and the run's [bike] lines, which read as a run starting. Now the one line."""
    text = tmp_path / "notes.yaml"
    text.write_text("just: notes\n")
    for launch, words in ((text, "expected a top-level 'launch:' list"), (tmp_path, "Is a directory")):
        run = bike_cli("run", "--duration", "1", "--launch", str(launch), "--record", str(tmp_path / "rec"), timeout=60)
        assert words in _one_error(run) and run.stdout == "", run.stdout
        assert not (tmp_path / "rec").exists(), "the --record folder made for the refused run is left"


def test_a_refused_paper_run_leaves_no_out_folder(bike_cli, tmp_path):
    """`./bike paper NAME --out DIR --config BAD` made DIR, then refused the config: an empty
    folder was left, as if a run had written nothing. A folder that was there stays."""
    bad = tmp_path / "bad.yaml"
    bad.write_bytes(b"\xff\xfe\x00")
    for name in ("seed1-fig14", "seed2-table1"):
        line = _one_error(bike_cli("paper", name, "--out", str(tmp_path / "out"), "--config", str(bad)))
        assert "not a text file" in line, line
        assert not (tmp_path / "out").exists()
    (tmp_path / "kept").mkdir()
    _one_error(bike_cli("paper", "seed1-fig14", "--out", str(tmp_path / "kept"), "--config", str(bad)))
    assert (tmp_path / "kept").is_dir()


def test_run_ftms_refuses_an_address_it_cannot_listen_on(bike_cli):
    """--ftms-host 999.1.1.1 or a --ftms-port in use started the graph, and the bridge node's
    'cannot listen' came among the other nodes' lines, exit 1. One error naming both options,
    exit 2, nothing started."""
    import socket
    line = _one_error(bike_cli("run", "--ftms", "--ftms-host", "999.1.1.1", "--duration", "1", timeout=90))
    assert "--ftms-host 999.1.1.1 --ftms-port 36866: cannot listen there" in line, line
    with socket.create_server(("127.0.0.1", 0)) as busy:
        port = busy.getsockname()[1]
        line = _one_error(bike_cli("run", "--ftms", "--ftms-port", str(port), "--duration", "1", timeout=90))
    assert f"--ftms-port {port}: cannot listen there (Address already in use" in line, line


def test_run_ftms_refuses_a_host_the_launch_file_reads_as_a_number():
    """--ftms-host 127.1 (the C library's short form of 127.0.0.1) could be listened on, then
    reached the bridge's text parameter ftms.host as a number: its node's error once the graph had
    started. One error, nothing started."""
    line = _one_error(_cli("run", "--ftms", "--ftms-host", "127.1", "--ftms-port", "0", "--duration", "1",
                           timeout=90))
    assert line == ("error: --ftms-host 127.1: a number to the launch file (ROS parameters are typed), not a host "
                    "name; write the address in full (e.g. 127.0.0.1)"), line


def test_run_with_files_named_y_and_nan_rides(tmp_path):
    """Names rcl types (y: true/false, nan: a number) as a run's --calibration, --record and config
    files: the launch passes them to the nodes' text parameters as text (absolute paths, and
    launcher.ros_param_value quotes text), and the run rides and records."""
    import shutil
    (tmp_path / "y").mkdir()
    config = tmp_path / "y" / "nan"
    shutil.copy(CONFIG, config)
    doc = config.read_text().replace("profiles/", str(ROOT / "config" / "profiles") + "/")
    config.write_text(doc)
    run = subprocess.run([str(ROOT / "bike"), "run", "--config", "y/nan", "--duration", "0.3", "--calibration", "y/y",
                          "--record", "nan"], capture_output=True, text=True, timeout=180, cwd=tmp_path,
                         env=dict(os.environ, ROS_DOMAIN_ID=str(random.randint(101, 200))))
    assert run.returncode == 0, (run.stdout[-2000:], run.stderr[-2000:])
    assert "Traceback" not in run.stdout + run.stderr and "error" not in run.stderr.lower(), run.stderr[-2000:]
    assert f"no calibration in {tmp_path / 'y' / 'y'} yet" in run.stdout
    assert list((tmp_path / "nan").glob("session_*/metadata.yaml")), run.stdout[-2000:]


def test_unwritable_output_paths_give_one_error_before_any_work(bike_cli, tmp_path):
    """An output path that cannot be made (under a regular file) or is a directory where a
    file goes: one error naming the option, exit 2, before the command runs (a bench or a
    fleet run must not end in a traceback after minutes of work)."""
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    bad_dir = str(blocker / "sub")
    cases = [(["paper", "seed2-table1", "--out", bad_dir], "--out"),
             (["run", "--duration", "1", "--record", bad_dir], "--record"),
             (["replay", str(tmp_path / "no_bag"), "--record", bad_dir], "--record"),
             (["bench", "--only", "can", "--json", str(blocker / "b.json")], "--json"),
             (["bench", "--only", "can", "--json", str(tmp_path)], "--json"),
             (["fleet", "--bikes", "2", "--seconds", "0.01", "--json", str(blocker / "f.json")], "--json"),
             (["report", str(tmp_path / "no_bag"), "--fit", str(blocker / "r.fit")], "--fit"),
             (["report", str(tmp_path / "no_bag"), "--fit", str(tmp_path)], "--fit"),
             (["report", str(tmp_path / "no_bag"), "--out", bad_dir], "--out"),
             (["compare", str(tmp_path / "no_bag"), str(tmp_path / "no_bag"), "--out", bad_dir], "--out"),
             # a file where the folder goes: it said "cannot create the directory (File exists)"
             (["run", "--duration", "1", "--record", str(blocker)], "--record"),
             (["report", str(tmp_path / "no_bag"), "--out", str(blocker)], "--out")]
    for args, flag in cases:
        run = bike_cli(*args, timeout=60)
        line = _one_error(run)
        assert flag in line and str(tmp_path) in line, line
        assert "File exists" not in line and (str(blocker) + ":" not in line or "not a directory" in line), line
        assert run.stdout == "", (args, run.stdout[-2000:])   # refused up front: nothing ran, no figures
    assert blocker.read_text() == "" and sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


def test_an_output_file_never_replaces_the_commands_input(bike_cli, tmp_path):
    """`./bike report BAG --fit BAG/BAG.mcap` wrote the FIT activity over the recording (the bag
    no longer opened), `torque-map --from-csv DYNO.csv --out DYNO.csv` its map over the dyno's
    points. One error naming the option; the input unchanged. A new file in the bag's folder is fine."""
    from test_report import write_session_bag
    bag = write_session_bag(tmp_path / "bag", n=3001)      # a ride the FIT export takes
    data = next(bag.glob("*.mcap"))
    csv = tmp_path / "dyno.csv"
    csv.write_text("speed_rpm,setpoint_nm,reported_nm,true_nm\n1000,1,1,0.98\n")
    before = {path: path.read_bytes() for path in (data, bag / "metadata.yaml", csv)}
    for args in (["report", str(bag), "--fit", str(data)], ["report", str(data), "--fit", str(data)],
                 ["report", str(bag), "--fit", str(bag / "metadata.yaml")],
                 ["torque-map", "--from-csv", str(csv), "--out", str(csv)]):
        line = _one_error(bike_cli(*args, timeout=60))
        assert "would write over the input" in line, line
    assert {path: path.read_bytes() for path in before} == before
    from bike_session import cli
    assert cli.output_spares_inputs(bag / "ride.fit", [bag], "--fit")


@pytest.mark.parametrize("argv", [
    ["run", "--record", ""], ["run", "--config", " "], ["run", "--calibration", ""], ["run", "--workout", ""],
    ["report", "b", "--out", ""], ["compare", "a", "b", "--out", ""], ["paper", "seed1-fig14", "--out", ""],
    ["replay", "b", "--record", ""], ["replay", "b", "--config", ""]])
def test_an_empty_path_option_is_refused_not_taken_as_not_given(argv, capsys):
    """--record "" (an unset shell variable) rode without recording, --config "" the default
    bike, --calibration "" without it, --out "" wrote into the working directory: each
    without a word. One argparse error naming the option, exit 2."""
    from bike_session import cli
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("error:") == 1 and f"argument {argv[-2]}: empty path" in err, err


@pytest.mark.parametrize("argv, message", [
    ([], "the following arguments are required: COMMAND (./bike --help)"),
    (["fleet", "--show", "nan"], "argument --show: invalid int value: 'nan' (./bike fleet --help)"),
    (["shift", "nan"], "argument gears: invalid int value: 'nan' (./bike shift --help)"),
    (["paper", "seed2-table1"], "the following arguments are required: --out (./bike paper --help)"),
    (["bag", "nope"], "argument TOOL: invalid choice: 'nope' (choose from 'recover') (./bike bag --help)"),
    (["replay"], "the following arguments are required: bag (./bike replay --help)")])
def test_a_usage_error_is_one_line(argv, message, capsys):
    """argparse printed the usage (up to 5 lines) before "bike fleet: error: ...": one line now,
    "error: ..." as every other bad input, with where the usage is."""
    from bike_session import cli
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    assert info.value.code == 2
    assert capsys.readouterr().err == f"error: {message}\n"


HOSTILE_READER = textwrap.dedent("""
    import resource, sys, pathlib
    # at most 400 MB more address space than the interpreter with its imports already has
    from bike_session.bags import BagError, open_bag
    from bike_session.recover import recover
    import bike_session.report
    with open("/proc/self/status") as fh:
        vm = next(int(l.split()[1]) * 1024 for l in fh if l.startswith("VmSize"))
    resource.setrlimit(resource.RLIMIT_AS, (vm + 400 * 2**20, vm + 400 * 2**20))
    path = pathlib.Path(sys.argv[1])
    for action in ("read", "recover"):
        try:
            if action == "read":
                with open_bag(path) as bag:
                    for _ in bag.messages():
                        pass
            else:
                (path / "metadata.yaml").unlink(missing_ok=True)
                recover(path)
            print(action, "ok")
        except BagError as exc:
            print(action, "BagError", str(exc)[:400])
""")


def _mcap_record(opcode: int, body: bytes, declared: int | None = None) -> bytes:
    return struct.pack("<BQ", opcode, len(body) if declared is None else declared) + body


@pytest.mark.parametrize("declared", [2**31, 2**40, 2**63 - 1])
def test_bag_reader_bounded_on_huge_declared_sizes(tmp_path, declared):
    """An MCAP whose records claim gigabytes (header, then a chunk of `declared` bytes):
    reading and recovery end with one BagError inside a 400 MB address-space limit."""
    good = tmp_path / "good"
    _small_bag(good, "mcap")
    magic = b"\x89MCAP0\r\n"
    data = next(good.glob("*.mcap")).read_bytes()
    # keep the header record, then a chunk record with a hostile length and a little payload
    header_len = struct.unpack_from("<Q", data, len(magic) + 1)[0]
    head = data[: len(magic) + 9 + header_len]
    for name, tail in {"chunk": _mcap_record(0x06, b"\x00" * 64, declared),
                       "string": _mcap_record(0x03, struct.pack("<H", 1) + struct.pack("<I", 0xFFFFFFF0) + b"x" * 32),
                       "schema": _mcap_record(0x03, struct.pack("<HI", 1, 8) + b"x" * 8
                                              + struct.pack("<I", 4) + b"ros2" + struct.pack("<I", 2**31))}.items():
        bag = tmp_path / f"{name}"
        bag.mkdir()
        (bag / f"{name}.mcap").write_bytes(head + tail)
        (bag / "metadata.yaml").write_text((good / "metadata.yaml").read_text().replace("good", name))
        run = subprocess.run([sys.executable, "-c", HOSTILE_READER, str(bag)], capture_output=True, text=True,
                             timeout=120)
        assert run.returncode == 0, (name, run.stdout, run.stderr[-3000:])
        assert "Traceback" not in run.stderr
        lines = run.stdout.splitlines()
        assert [line.split()[0] for line in lines] == ["read", "recover"], run.stdout
        assert all(line.split()[1] == "BagError" for line in lines), run.stdout


def _zstd_zeros_frame(n_bytes: int) -> bytes:
    """A zstd frame of RLE blocks: 4 bytes for each 128 kB of zeros (1 GB in 32 kB), no content
    size in its header (so nothing up front says how much it inflates to)."""
    block = 128 * 1024
    frame = bytearray(struct.pack("<I", 0xFD2FB528) + bytes([0x00, 7 << 3]))      # 128 kB window
    n = n_bytes // block
    for i in range(n):
        frame += struct.pack("<I", (block << 3) | (1 << 1) | (i == n - 1))[:3] + b"\x00"
    return bytes(frame)


def _bomb_bag(path: pathlib.Path, declared: int | None) -> None:
    """A closed MCAP bag of 10 Commands in one zstd chunk that inflates to 1 GB of zeros; the
    chunk (and its index) declare the true records' size, or ``declared``."""
    from rosbags.rosbag2.writer import CompressionFormat, CompressionMode

    from bike_session.recorder_node import new_writer
    _small_bag(path, "mcap", count=10,
               writer=lambda p: new_writer(p, "mcap"),
               compress=lambda w: w.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD),
               compressor=lambda _data: _zstd_zeros_frame(2**30))
    if declared is None:
        return
    data_file = next(path.glob("*.mcap"))
    b = bytearray(data_file.read_bytes())
    pos = 8
    while pos + 9 <= len(b):
        op, length = b[pos], struct.unpack_from("<Q", b, pos + 1)[0]
        if op == 0x06:                               # Chunk: start, end, uncompressed_size
            struct.pack_into("<Q", b, pos + 9 + 16, declared)
        elif op == 0x08:                             # ChunkIndex: ..., compressed, uncompressed size
            struct.pack_into("<Q", b, pos + 9 + length - 8, declared)
        elif op == 0x02:                             # Footer
            break
        pos += 9 + length
    data_file.write_bytes(bytes(b))


BOMB_READER = HOSTILE_READER + textwrap.dedent("""
    try:
        with open_bag(next(path.glob("*.mcap"))) as bag:
            for _ in bag.messages():
                pass
        print("bare ok")
    except BagError as exc:
        print("bare BagError", str(exc)[:400])
""")


@pytest.mark.parametrize("declared", [None, 2**30])
def test_bag_reader_bounded_on_a_decompression_bomb(tmp_path, declared):
    """A 35 kB MCAP bag whose zstd chunk inflates to 1 GB: reading it took 2.1 GB of memory and
    10 s before rosbags found the chunk's size wrong (declared 1 GB: 172 s; the bare .mcap file
    334 s and 1.1 GB), and under the 400 MB limit the MemoryError was what ended it. Reading the
    directory, the bare file and recovery each end with one BagError of the reader's own bound,
    not of running out of memory."""
    bag = tmp_path / "bomb"
    _bomb_bag(bag, declared)
    assert next(bag.glob("*.mcap")).stat().st_size < 64 * 1024
    run = subprocess.run([sys.executable, "-c", BOMB_READER, str(bag)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and "Traceback" not in run.stderr, (run.stdout, run.stderr[-3000:])
    lines = run.stdout.splitlines()
    assert [line.split()[:2] for line in lines] == [["read", "BagError"], ["recover", "BagError"],
                                                   ["bare", "BagError"]], run.stdout
    assert all("Memory" not in line and "allocate" not in line and "chunk" in line and "inflates" in line
               for line in lines), run.stdout


def test_an_mcap_chunk_index_or_chunk_cut_off_is_one_bag_error(tmp_path):
    """The chunk check's own reading of hostile fields: a ChunkIndex whose offsets map claims
    4 GB (it read past the file and raised struct.error out of open_bag), a chunk whose
    compression name runs past the file's end. One BagError each, from reading and recovery."""
    good = tmp_path / "good"
    _small_bag(good, "mcap")
    data = next(good.glob("*.mcap")).read_bytes()
    pos, index_at = 8, None
    while pos + 9 <= len(data):
        opcode, length = data[pos], struct.unpack_from("<Q", data, pos + 1)[0]
        if opcode == 0x08:
            index_at = pos
            break
        pos += 9 + length
    assert index_at is not None
    overrun = bytearray(data)
    struct.pack_into("<I", overrun, index_at + 9 + 32, 0xFFFFFFF0)
    torn_chunk = (b"\x89MCAP0\r\n" + struct.pack("<BQ", 0x06, 40) + struct.pack("<QQQII", 0, 0, 10, 0, 60)
                  + b"\x00" * 8)
    for name, body in {"overrun": bytes(overrun), "torn": torn_chunk}.items():
        bag = tmp_path / name
        bag.mkdir()
        (bag / f"{name}.mcap").write_bytes(body)
        (bag / "metadata.yaml").write_text((good / "metadata.yaml").read_text().replace("good", name))
        with pytest.raises(BagError):
            _read_all(bag)
        with pytest.raises(BagError):
            _read_all(bag / f"{name}.mcap")
        (bag / "metadata.yaml").unlink()
        try:
            recover(bag)
        except BagError:
            pass


# ------------------------------------------------------------------ DDS discovery
def test_discovery_is_limited_to_localhost_unless_configured():
    """tools/env.sh sets ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST unless the user chose a
    range; ./bike run passes it through to every node unchanged (the launcher adds no env)."""
    probe = "echo RANGE=$ROS_AUTOMATIC_DISCOVERY_RANGE"
    env = {k: v for k, v in os.environ.items() if k != "ROS_AUTOMATIC_DISCOVERY_RANGE"}
    out = subprocess.run(["bash", "-c", f"source {ROOT}/tools/env.sh && {probe}"], env=env, capture_output=True,
                         text=True, timeout=60).stdout
    assert "RANGE=LOCALHOST" in out
    out = subprocess.run(["bash", "-c", f"source {ROOT}/tools/env.sh && {probe}"],
                         env=dict(env, ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET"), capture_output=True, text=True,
                         timeout=60).stdout
    assert "RANGE=SUBNET" in out, "a configured range is respected"
    bike = (ROOT / "bike").read_text()
    assert "tools/env.sh" in bike, "./bike must enter the environment through tools/env.sh"
    # the launcher starts nodes with the caller's environment (nothing overrides the range)
    from bike_session.launcher import parse_launch
    for spec in parse_launch(str(ROOT / "config" / "launch" / "bike.launch.yaml"), {"emulator": "true"}):
        assert "ROS_AUTOMATIC_DISCOVERY_RANGE" not in (getattr(spec, "env", {}) or {})
    cli = (ROOT / "src" / "bike_session" / "bike_session" / "cli.py").read_text()
    assert not re.search(r"environ\[[\"']ROS_AUTOMATIC_DISCOVERY_RANGE", cli)


def test_fast_dds_profile_is_selected_and_parses():
    """tools/env.sh points Fast DDS at config/fastdds.xml unless the user chose a profiles file:
    reliable writers ask for acknowledgments every 100 ms (Fast DDS's default, 3 s, held the
    plant's exit for its end_of_run acknowledgment up to 3 s), and participants announce
    themselves often enough that a node started later is matched within 0.5 s (the recorder,
    started first, was matched 2.5-3 s late and held every recorded run). Fast DDS reads the file when
    a participant is made and ignores a malformed one with an XMLPARSER error line only, so
    the test also makes a node with it and checks that nothing was refused."""
    import xml.etree.ElementTree as ET

    probe = "echo PROFILES=$FASTRTPS_DEFAULT_PROFILES_FILE"
    env = {k: v for k, v in os.environ.items() if k != "FASTRTPS_DEFAULT_PROFILES_FILE"}
    out = subprocess.run(["bash", "-c", f"source {ROOT}/tools/env.sh && {probe}"], env=env, capture_output=True,
                         text=True, timeout=60).stdout
    path = pathlib.Path(out.split("PROFILES=")[1].strip())
    assert path == ROOT / "config" / "fastdds.xml"
    out = subprocess.run(["bash", "-c", f"source {ROOT}/tools/env.sh && {probe}"],
                         env=dict(env, FASTRTPS_DEFAULT_PROFILES_FILE="/x.xml"), capture_output=True, text=True,
                         timeout=60).stdout
    assert "PROFILES=/x.xml" in out, "a profiles file of the user's is respected"
    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    writer = ET.parse(path).getroot().find("f:data_writer", ns)
    assert writer.get("is_default_profile") == "true"
    hb = writer.find("f:times/f:heartbeatPeriod", ns)
    assert int(hb.find("f:sec", ns).text) == 0 and int(hb.find("f:nanosec", ns).text) == 100_000_000
    # participants announce themselves for 2 s after start, then every 0.5 s (Fast DDS: 0.5 s,
    # then every 3 s, so a node started later waited up to 3 s for the others)
    participant = ET.parse(path).getroot().find("f:participant", ns)
    assert participant.get("is_default_profile") == "true"
    disc = participant.find("f:rtps/f:builtin/f:discovery_config", ns)

    def seconds(element):
        return int(element.find("f:sec", ns).text) + int(element.find("f:nanosec", ns).text) * 1e-9
    initial = disc.find("f:initialAnnouncements", ns)
    assert int(initial.find("f:count", ns).text) * seconds(initial.find("f:period", ns)) == pytest.approx(2.0)
    assert seconds(disc.find("f:leaseAnnouncement", ns)) == pytest.approx(0.5)
    code = ("import rclpy; rclpy.init(); n = rclpy.create_node('xml_probe'); "
            "from std_msgs.msg import UInt64; n.create_publisher(UInt64, 'probe', 10); n.destroy_node(); "
            "rclpy.shutdown(); print('made')")
    res = subprocess.run([sys.executable, "-c", code], env=dict(os.environ, FASTRTPS_DEFAULT_PROFILES_FILE=str(path)),
                         capture_output=True, text=True, timeout=60)
    assert "made" in res.stdout and "XML" not in res.stdout + res.stderr, res.stdout + res.stderr


def test_a_bags_recorded_config_nested_too_deeply_is_one_error(tmp_path, monkeypatch, capsys):
    """A bag's session_info carries the config as text: nested 2000 levels deep, PyYAML's
    constructors ran out of recursion and the report and the replay ended in a traceback. Now
    one error each: the report's config figures say why, the replay exits 2 with one line."""
    from bike_session import replay
    from bike_session.report import config_params

    deep = "/**:\n  ros__parameters:\n    a: " + "[" * 2000 + "]" * 2000 + "\n"
    with pytest.raises(ValueError, match="^config_text is nested too deeply$"):
        config_params(deep)
    info = {"duration_s": 1.0, "period_s": 0.1, "config_text": deep}
    monkeypatch.setattr(replay, "command_timeline", lambda _bag: ([(0, 0.5, 0, 0.0, None)], info))
    code = replay.main([str(tmp_path / "session_x"), "--record", str(tmp_path / "runs")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "the recorded config is nested too deeply" in err[0], err


def test_a_replay_writes_neither_the_rides_calibration_nor_its_can_log(tmp_path, monkeypatch, capsys):
    """A config that keeps its calibration (calibration_file) or logs its CAN traffic to a file
    (can_log_file) is recorded with them: its replay wrote into those files, the kept calibration
    overwritten by the replay's spin-down (another bike's with --config OTHER), the ride's CAN
    log by the replay's. The replay's config now names neither, and says so."""
    import yaml

    from bike_plant.config import load_config
    from bike_session import replay
    recorded = yaml.safe_load(CONFIG.read_text())
    kept = {"calibration_file": str(tmp_path / "kept_calibration.yaml"), "can_log_file": str(tmp_path / "ride.asc")}
    recorded["/**"]["ros__parameters"].update(kept)
    info = {"duration_s": 1.0, "period_s": 0.1, "config_text": yaml.safe_dump(recorded)}
    monkeypatch.setattr(replay, "command_timeline", lambda _bag: ([(0, 0.5, 0, 0.0, None)], info))
    prep = replay.prepare(tmp_path / "session_x", tmp_path / "runs", None, "recorded")
    cfg = load_config(prep["config"])
    assert not cfg.get("calibration_file") and not cfg.get("can_log_file"), cfg
    assert "calibration_file, can_log_file of the config not written by the replay" in capsys.readouterr().out
