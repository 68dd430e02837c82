"""``./bike replay BAG [--config OTHER]``: ride a recorded session again on a fresh bike.

The recorded Command timeline (stamp, value, mode of every ``command`` message) becomes a
profile of steps, so the new session publishes exactly the same Commands at exactly the
same sim times (on a bike of other ranges, ERG / slope / isokinetic Commands that ask for the
recorded targets: :func:`retarget`), up to the session's end or the bag's, if that is earlier
(a recovered bag). The bike is ``--config OTHER`` (another controller, machine, battery ...)
or, without it, the recorded config (``session_info.config_text``). The load:

- ``--load recorded`` (default): the recorded config's ``load`` section (the same rider
  model with the same parameters and seed, or the same prime-mover schedule), so an A/B
  comparison changes only the bike. The rider is a model that reacts to the bike, not a
  torque trace played open loop (that would make the speed run away with another brake).
- ``--load config``: the load of OTHER.

Both files the replay rides are written next to the new bag's folder
(``replay_<bag>_profile.yaml`` and ``..._config.yaml``) and the new bag's session_info
records them, so a replay is itself replayable. With the same config, lockstep replays
are bit-identical to the original recording (tested).
"""
from __future__ import annotations

import json
import pathlib

import yaml

from bike_plant.config import YamlFileError, dump_ros_params, parse_yaml_text
from bike_session.bags import BagError, open_bag
from bike_session.profiles import MODE_NAMES as MODE_TO_NAME

EARLY_NS = 1000


def command_timeline(bag_path) -> tuple[list[tuple[int, float, int, float, tuple | None, float, float]], dict]:
    """Sorted (stamp_ns, command, mode, virtual gear, road, rider cadence, heart rate) of the bag's
    Commands (duplicates dropped; gear 0 = the config's, also in a bag recorded before Commands had
    one; road (crr, cw_kg_m, wind_mps) or None = the config's; cadence and heart rate 0 = none) and
    its session_info (empty dict when absent)."""
    timeline: dict[int, tuple[float, int, float, tuple | None, float, float]] = {}
    info: dict = {}
    with open_bag(bag_path) as bag:
        cmd_topic = bag.resolve("command")
        try:
            info_topic = bag.resolve("session_info")
        except BagError:
            info_topic = None
        topics = [cmd_topic] + ([info_topic] if info_topic else [])
        for topic, _t, msg in bag.messages(topics):
            if topic == info_topic:
                try:
                    info = json.loads(msg.data)
                except (ValueError, TypeError):
                    raise BagError("session_info is not valid JSON", bag_path) from None
                continue
            stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
            # a road the Command gave (a training app's); older bags have no such fields
            road = ((float(msg.crr), float(msg.cw_kg_m), float(msg.wind_mps))
                    if getattr(msg, "road_from_command", False) else None)
            timeline[stamp] = (float(msg.command), int(msg.mode), float(getattr(msg, "virtual_gear_ratio", 0.0)),
                               road, float(getattr(msg, "cadence_rpm", 0.0)),
                               float(getattr(msg, "heart_rate_bpm", 0.0)))
    if not timeline:
        raise BagError("the command topic is empty: nothing to replay", bag_path)
    return [(t, *v) for t, v in sorted(timeline.items())], info


def profile_from_timeline(timeline, duration_s: float, name: str) -> dict:
    """A profile document of steps reproducing the timeline (equal neighbours merged); entries
    (stamp_ns, command, mode, gear[, road[, cadence[, heart rate]]])."""
    segments = []
    end_ns = int(round(duration_s * 1e9))
    timeline = [tuple(x) + (None, 0.0, 0.0)[len(x) - 4:] for x in timeline]
    points = [x for x in timeline if x[0] < end_ns]
    if not points or points[0][0] > 0:
        points.insert(0, (0, 0.0, points[0][2] if points else 0, points[0][3] if points else 0.0,
                          points[0][4] if points else None, points[0][5] if points else 0.0,
                          points[0][6] if points else 0.0))
    # each step starts EARLY_NS before its stamp: the profile sums float durations, and the
    # session asks for the command exactly at the stamps, so a boundary must never land on one
    def start(i):
        return 0 if i == 0 else max(points[i][0] - EARLY_NS, 0)
    gear_in_force = 0.0
    road_in_force = None
    for i, (_t, c, m, g, r, cad, hr) in enumerate(points):
        t = start(i)
        t_next = start(i + 1) if i + 1 < len(points) else end_ns
        if t_next <= t:
            continue
        mode = MODE_TO_NAME.get(m)
        if mode is None:
            raise BagError(f"recorded Command at t={t * 1e-9:g}s has unknown mode {m}")
        if (segments and segments[-1]["command"] == c and segments[-1]["mode"] == mode and g == gear_in_force
                and r == road_in_force and cad == segments[-1].get("cadence", 0.0)
                and hr == segments[-1].get("heart_rate_bpm", 0.0)):
            segments[-1]["duration_s"] = round(segments[-1]["duration_s"] + (t_next - t) * 1e-9, 9)
            continue
        segments.append({"kind": "step", "duration_s": round((t_next - t) * 1e-9, 9), "command": c,
                         "mode": mode})
        if g != gear_in_force:          # a profile's gear stays in force until the next one given
            segments[-1]["gear"] = gear_in_force = g
        if cad:                         # a cadence target is the step's own
            segments[-1]["cadence"] = cad
        if hr:                          # as is a heart-rate target
            segments[-1]["heart_rate_bpm"] = hr
        if r != road_in_force:          # and so does its road
            segments[-1]["road"] = "config" if r is None else dict(zip(("crr", "cw_kg_m", "wind_mps"), r))
            road_in_force = r
    # the session's final Command (command 0 at the run's end) carries the gear of the profile
    # segment at that time: one more step from there when it differs (the run still ends at
    # duration_s, which the replay passes on)
    final = [(m, g) for t, _c, m, g, *_ in timeline if t >= end_ns]
    if final and final[0][1] != gear_in_force and segments and segments[-1]["duration_s"] > 2 * EARLY_NS * 1e-9:
        segments[-1]["duration_s"] = round(segments[-1]["duration_s"] - EARLY_NS * 1e-9, 9)
        segments.append({"kind": "step", "duration_s": 1.0, "command": 0.0,
                         "mode": MODE_TO_NAME.get(final[0][0], "resistance"), "gear": final[0][1]})
    return {"name": name, "description": "Command timeline replayed from a recorded bag", "segments": segments}


# top-level config keys naming a file the ride writes into (see prepare)
REPLAY_DROPPED_FILE_KEYS = ("calibration_file", "can_log_file")


def _recorded_config(info: dict, bag_path) -> dict:
    text = info.get("config_text")
    if not text:
        raise BagError("the bag has no recorded config (session_info.config_text); give --config", bag_path)
    try:
        doc = parse_yaml_text(text)
    except YamlFileError as exc:
        raise BagError(f"the recorded config is {exc}", bag_path) from None
    if not isinstance(doc, dict) or not isinstance((doc.get("/**") or {}).get("ros__parameters"), dict):
        raise BagError("the recorded config has no '/**: ros__parameters:' section", bag_path)
    return doc


# load: keys that belong to the bike, not to the rider: the motor-to-crank gear and the rider
# model's effort PI, placed on the crank inertia J x gear^2 (bike_plant.mechanics.rider_pi_gains)
BIKE_LOAD_KEYS = ("gear_ratio", "rider_kp", "rider_ki")


def _machine_only_load_keys(recorded_machine, other_machine) -> set:
    """The ``load`` keys the recorded machine knows and the other does not (none for the same
    machine or one that is neither's: its config check names it)."""
    import dataclasses

    from bike_plant.params import LoadParams
    from bike_plant.spmsm_params import SpmsmLoadParams

    classes = {"bldc": LoadParams, "spmsm": SpmsmLoadParams}
    if recorded_machine not in classes or other_machine not in classes:
        return set()
    names = lambda cls: {f.name for f in dataclasses.fields(cls)}       # noqa: E731
    return names(classes[recorded_machine]) - names(classes[other_machine])


def _mode_units(params: dict):
    """The bike's ranges (bike_session.profiles.ModeUnits) of a config's parameters; None when
    they cannot be derived (the config check that follows names the problem)."""
    import copy

    from bike_session.profiles import mode_units_from_config
    try:
        return mode_units_from_config(copy.deepcopy(params))
    except Exception:  # noqa: BLE001 - a config the replay's check refuses with one error
        return None


def retarget(timeline, recorded_units, other_units) -> list:
    """The timeline with each ERG, slope and isokinetic Command re-expressed on the other bike's
    ranges, so that it rides the recorded target (180 W, 4 %, 70 rpm), not the recorded fraction
    of a range that is not this bike's (a BLDC's ERG 180 W, Command 0.177 of 1017 W, was 61 W on
    the SPMSM's 345 W). ValueError naming the first target outside the other bike's range."""
    if recorded_units is None or other_units is None or recorded_units == other_units:
        return list(timeline)
    out = []
    for t, c, m, *rest in timeline:
        target = recorded_units.target_of(m, c)
        if target is not None:
            try:
                c = other_units.to_command(m, target[0])[0]
            except ValueError as exc:
                raise ValueError(f"the recorded {MODE_TO_NAME.get(m, m)} Command at t={t * 1e-9:g} s: {exc}") from None
        out.append((t, c, m, *rest))
    return out


def _bag_end_s(bag_path) -> float | None:
    """The sim time of the bag's last message (the recorder logs each at its stamp); None when it
    cannot be opened (command_timeline has already said why, or was given the timeline)."""
    try:
        with open_bag(bag_path) as bag:
            # to the microsecond: rosbags' end_time is the last stamp + 1 ns, MCAP's the last stamp
            return round(bag.end_ns * 1e-9, 6) if bag.message_counts() else None
    except BagError:
        return None


def prepare(bag_path, out_dir, config: str | None = None, load: str = "recorded") -> dict:
    """Write the replay's profile and config into out_dir; returns their paths + facts."""
    from bike_plant.config import ConfigError, absolute_file_paths, load_config

    if load not in ("recorded", "config"):
        raise ValueError(f"load must be 'recorded' or 'config', got {load!r}")
    bag_path = pathlib.Path(bag_path)
    timeline, info = command_timeline(bag_path)
    duration_s = float(info.get("duration_s") or 0.0) or timeline[-1][0] * 1e-9
    # a bag that ends before its session did (recovered after a kill, a realtime ride stopped with
    # Ctrl-C) holds the Commands up to its end only: the replay rides that much, not the session's
    # duration_s with the last Command held for the rest (a 2.9 s recovered part rode 6 s)
    end_s = _bag_end_s(bag_path)
    shortened_from = None
    if end_s is not None and 0 < end_s < duration_s:
        shortened_from, duration_s = duration_s, end_s
        # its Commands may end before its other topics do (a cut file's chunks need not end
        # together: CI, 2026-12-07, Commands to 1.3 s, states to 1.5 s, and the replay held 1.3 s's
        # Command to the end): each holds one session period, and past that the ride is unknown
        period_s = float(info.get("period_s") or 0.0)
        commands_end_s = round(timeline[-1][0] * 1e-9 + period_s, 6)
        if period_s > 0 and commands_end_s < duration_s:
            duration_s = commands_end_s
    recorded = _recorded_config(info, bag_path) if (config is None or load == "recorded") else None
    if recorded is None and info.get("config_text"):
        try:
            recorded = _recorded_config(info, bag_path)     # its ranges, for the recorded targets
        except BagError:
            recorded = None
    recorded_units = (_mode_units(recorded["/**"]["ros__parameters"])
                      if config is not None and recorded is not None else None)
    if config is not None:
        path = pathlib.Path(config).resolve()
        load_config(path)                                 # one clear ConfigError if it is bad
        try:
            doc = yaml.safe_load(path.read_text())
        except (OSError, yaml.YAMLError) as exc:
            raise ConfigError(f"cannot read config: {exc}", path) from None
        base_dir = path.parent
    else:
        doc = recorded
        base_dir = pathlib.Path(info.get("config_path") or ".").parent
    params = doc["/**"]["ros__parameters"]
    if load == "recorded":
        rec_load = recorded["/**"]["ros__parameters"].get("load")
        if rec_load is not None:
            own = params.get("load") if isinstance(params.get("load"), dict) else {}
            params["load"] = dict(rec_load)
            if config is not None:
                # the recorded rider on the other bike's drivetrain: its gear and the rider's
                # effort gains tuned on that bike's crank inertia (the BLDC's 35:1 gear on the
                # SPMSM braked 14 W and drew the pack down)
                for key in BIKE_LOAD_KEYS:
                    params["load"].pop(key, None)
                    if key in own:
                        params["load"][key] = own[key]
                # keys of the recorded machine's load that the other machine has not (the SPMSM's
                # dynamometer, dyno_*): an SPMSM ride on the BLDC bike was refused for them
                for key in _machine_only_load_keys(recorded["/**"]["ros__parameters"].get("machine", "bldc"),
                                                   params.get("machine", "bldc")):
                    params["load"].pop(key, None)
    # relative paths in the config (a CAN drive's torque map), against the config's folder
    absolute_file_paths(params, base_dir)
    params.setdefault("session", {})
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = f"replay_{bag_path.name}"
    suffix = 1
    while (out_dir / f"{stem}_profile.yaml").exists() or (out_dir / f"{stem}_config.yaml").exists():
        # a second replay of the bag into the same folder: the first one's bag names these files
        suffix += 1
        stem = f"replay_{bag_path.name}_{suffix}"
    profile_path = out_dir / f"{stem}_profile.yaml"
    config_path = out_dir / f"{stem}_config.yaml"
    if recorded_units is not None:
        try:
            timeline = retarget(timeline, recorded_units, _mode_units(params))
        except ValueError as exc:
            raise ConfigError(str(exc), path) from None
    profile = profile_from_timeline(timeline, duration_s, f"replay of {bag_path.name}")
    profile_path.write_text(dump_ros_params(profile, sort_keys=False))
    params["session"]["profile"] = str(profile_path.resolve())
    # the recorded Commands are the ride: a workout the recorded config names (./bike run rides a
    # config's session.workout in place of its profile) must not be ridden instead of them
    params["session"].pop("workout", None)
    # files the ride wrote are the ride's: a replay writing into them would overwrite the kept
    # calibration with the replay's spin-down (another bike's with --config OTHER) and the CAN
    # ride's log beside its bag (--record gives the replay a CAN log of its own)
    dropped = [key for key in REPLAY_DROPPED_FILE_KEYS if params.pop(key, None)]
    if dropped:
        print(f"[bike] replay: {', '.join(dropped)} of the config not written by the replay", flush=True)
    if "period_s" in info:
        params["session"]["period_s"] = float(info["period_s"])
    params["duration_s"] = duration_s
    if "duration_s" in params["session"]:
        # the session's own length wins over duration_s: OTHER's session.duration_s 3 ended a 6 s
        # replay's Commands at 3 s (the rest rode the session's final Command)
        params["session"]["duration_s"] = duration_s
    header = (f"# Replay of {bag_path.resolve()} ({'recorded' if config is None else config} bike, "
              f"{load} load); written by ./bike replay\n")
    config_path.write_text(header + dump_ros_params(doc, sort_keys=False))
    try:
        _check_replay_config(config_path)
    except ValueError as exc:
        # refused: nothing of this replay is left in out_dir, and the error names the bike it
        # was asked for (--config, or the bag's recorded one), not the file written from it
        profile_path.unlink(missing_ok=True)
        config_path.unlink(missing_ok=True)
        given = str(path) if config is not None else f"{bag_path} (its recorded config)"
        raise ConfigError(str(exc).replace(f"{config_path.resolve()}: ", "").replace(f"{config_path}: ", ""),
                          given) from None
    return {"profile": profile_path, "config": config_path, "duration_s": duration_s, "shortened_from": shortened_from,
            "bag_end_s": end_s,
            "commands": len(timeline), "segments": len(profile["segments"]), "base_dir": str(base_dir)}


def _check_replay_config(config_path: pathlib.Path) -> None:
    """The replay's config checked as ./bike run checks a config before it starts a node
    (ValueError naming the key): the run it is handed to refused it naming this generated
    file, and left it behind."""
    from bike_plant.config import check_backend_sync_mode, load_config

    from bike_session import cli

    cfg = load_config(config_path)
    cli._check_config(cfg)
    # a replay rides the config's own sync mode (no --ftms)
    check_backend_sync_mode(str(cfg.get("backend", "sim")), str(cfg.get("sync_mode", "lockstep")), config_path)


def main(argv: list[str]) -> int:
    """``bike replay BAG [--config OTHER] [--load recorded|config] [--record DIR]``."""
    import sys

    from bike_plant.config import ConfigError

    from bike_session.cli import Parser, path_arg

    ap = Parser(prog="bike replay", description=__doc__.split("\n\n")[0])
    ap.add_argument("bag")
    ap.add_argument("--config", type=path_arg, help="the bike to ride it on (default: the recorded config)")
    ap.add_argument("--load", choices=["recorded", "config"], default="recorded",
                    help="rider / load: the recorded one (default; with --config, on that bike's gear_ratio and "
                         "rider_kp / rider_ki) or the one of --config")
    ap.add_argument("--record", default="runs", metavar="DIR", type=path_arg,
                    help="where the new bag goes (default runs/)")
    ap.add_argument("--storage", choices=["mcap", "sqlite3"], default="mcap")
    opts = ap.parse_args(argv)
    if opts.load == "config" and opts.config is None:
        # without OTHER the recorded config's load is ridden either way: it changed nothing, without a word
        print("error: --load config needs --config OTHER (the load of OTHER); without it the replay rides the "
              "recorded config's load", file=sys.stderr)
        return 2
    from bike_session import cli
    made_record_dir = not pathlib.Path(opts.record).exists()
    if cli.output_dir(opts.record, "--record") is None:
        return 2
    try:
        prep = prepare(opts.bag, opts.record, opts.config, opts.load)
    except (BagError, ConfigError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        cli.remove_if_made_empty(opts.record, made_record_dir)    # made for this replay, which did not start
        return 2
    if prep["shortened_from"] is not None:
        ends = (f"the bag ends at t = {prep['bag_end_s']:g} s and its Commands at {prep['duration_s']:g} s"
                if prep["bag_end_s"] > prep["duration_s"] else f"the bag ends at t = {prep['duration_s']:g} s")
        print(f"[bike] {ends}, before its session's {prep['shortened_from']:g} s "
              f"(recovered, or stopped early): the replay rides the {prep['duration_s']:g} s recorded", flush=True)
    print(f"[bike] replaying {prep['commands']} Commands ({prep['segments']} steps, {prep['duration_s']:g} s) "
          f"of {opts.bag} with {prep['config']}", flush=True)
    code = cli.main(["run", "--config", str(prep["config"]), "--duration", repr(prep["duration_s"]),
                     "--record", opts.record, "--storage", opts.storage])
    if code == 2:
        # refused by ./bike run before a node started (its later checks: the CAN bus, a file
        # the config names): as with a refused config, nothing of this replay is left behind
        prep["profile"].unlink(missing_ok=True)
        prep["config"].unlink(missing_ok=True)
        cli.remove_if_made_empty(opts.record, made_record_dir)
    return code
