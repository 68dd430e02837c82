"""`./bike`: the front door of the testbed.

    ./bike run [--config FILE] [--duration S] [--record DIR]   ride a session in the node graph
          [--workout FILE.zwo|.erg|.mrc|.fit [--ftp W]]         ... riding a workout file
          [--max-hr BPM]                                        ... its heart-rate targets in % of max
          [--ftms [--ftms-host 0.0.0.0]]                        ... as a smart trainer a training app rides
    ./bike shift N [--domain ID]                               press a running bike's virtual shifter
    ./bike trainer [--find] [--host H] [--power W | --grade %] the app's end of FTMS / DIRCON: poke a trainer
    ./bike report BAG [--out DIR] [--fit FILE]                 summarise a recorded session
    ./bike compare BAG_A BAG_B [--out DIR]                     A/B report of two recorded sessions
    ./bike replay BAG [--config OTHER] [--record DIR]          ride a recorded session again
    ./bike bag recover BAG [--out DIR]                         rescue a crashed recording
    ./bike paper NAME --out DIR                                reproduce a figure of a paper
    ./bike bench [--json FILE] [--only SECTION] [--memory-s S] speed / memory figures and ratios, peers
    ./bike fleet [--bikes N | --graph K [--netns bikeK=NS]] [--seconds S]  many bikes: batched kernel or DDS graph
    ./bike torque-map --config FILE --out MAP.yaml             measure the drive's torque map on the emulator
    ./bike torque-map --from-csv DYNO.csv --out MAP.yaml       a real drive's map from a dynamometer's points
"""
from __future__ import annotations

import argparse
import datetime
import math
import os
import pathlib
import re
import sys

PAPERS = {
    "seed1-fig14": "paper 000 Fig. 14: torque-speed curve with Command = 1, prime mover 300..5400 rpm",
    "seed1-current": "paper 000 Fig. 12/13: hysteresis current control at I* = 35 A and 50 A, 3000 rpm",
    "seed1-resistance": "paper 000 Eq. 3-4 at Command 0.2..1: the resistance mode's steady torque, 750..4750 rpm",
    "seed1-k-table": "paper 000 Eq. 7: measure the config machine's k table over speed and Command, then "
                     "check it as seed1-resistance",
    "seed2-table1": "paper 001 Table 1 (Fig. 11-16): predictive vs PI speed/current control of the SPMSM",
}


def repo_root() -> pathlib.Path:
    root = os.environ.get("BIKE_ROOT")
    return pathlib.Path(root) if root else pathlib.Path(__file__).resolve().parents[3]


# lockstep flow control while recording (plant_node recorder_window_batches): small enough that
# a sample lost on the transport is still in the writer's DDS history when it is re-requested
RECORDER_WINDOW_BATCHES = 50


def default_launch_file() -> pathlib.Path:
    return repo_root() / "config" / "launch" / "bike.launch.yaml"


class Parser(argparse.ArgumentParser):
    """argparse with a usage error as one line, "error: ... (./bike fleet --help)": it printed the
    usage (up to 5 lines), then "bike fleet: error: argument --show: invalid int value: 'nan'"."""

    def error(self, message: str):
        sys.stderr.write(f"error: {message} (./{self.prog} --help)\n")
        sys.exit(2)


def namespace_problem(namespace: str) -> str | None:
    """Why ``namespace`` (--namespace, leading / trailing '/' taken off) is no ROS namespace, one line; or None.
    rclpy's message is three lines (the name and a caret under the bad character): its first
    ended in ':', so the name is quoted in front instead."""
    from rclpy.validate_namespace import InvalidNamespaceException, validate_namespace
    try:
        validate_namespace("/" + namespace.strip("/"))
    except InvalidNamespaceException as exc:
        return f"--namespace {namespace!r}: {str(exc).splitlines()[0].rstrip(' :')}"
    return None


def path_arg(text: str) -> str:
    """argparse type of a file or folder option: an empty value (an unset shell variable) is
    refused, not taken as not given (--record "" rode without recording, --config "" the
    default bike, --calibration "" without the calibration, each without a word)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty path (an unset shell variable?)")
    return text


def output_dir(path, flag: str) -> pathlib.Path | None:
    """Create an output directory before any work; on failure print one error naming the
    option and return None (a run must not end in a traceback, nor work be lost, because
    its output path was bad)."""
    out = pathlib.Path(path)
    if out.exists() and not out.is_dir():
        # mkdir said "cannot create the directory (File exists)"
        print(f"error: {flag} {out}: not a directory (a file is there)", file=sys.stderr)
        return None
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        print(f"error: {flag} {out}: cannot create the directory ({exc.strerror or exc})", file=sys.stderr)
        return None
    if not os.access(out, os.W_OK):
        print(f"error: {flag} {out}: directory not writable", file=sys.stderr)
        return None
    return out


def given_options(opts, attrs) -> list[str]:
    """The options of ``attrs`` (parser attributes whose default is None, or False for a flag)
    given on the command line, as flags: --power 0 is given, though 0 == False."""
    return [f"--{attr.replace('_', '-')}" for attr in attrs
            if getattr(opts, attr) is not None and getattr(opts, attr) is not False]


def remove_if_made_empty(path, made: bool) -> None:
    """A folder an output option made for a command that was then refused: removed when it is
    still empty, so that a refused command leaves nothing behind."""
    if made and pathlib.Path(path).is_dir() and not any(pathlib.Path(path).iterdir()):
        pathlib.Path(path).rmdir()


def output_file_ok(path, flag: str) -> bool:
    """Before any work: a result file can be written at ``path`` (its directory is created;
    the file is opened for appending, and removed again if that created it), else one error
    naming the option."""
    target = pathlib.Path(path)
    if target.is_dir():
        print(f"error: {flag} {target}: is a directory", file=sys.stderr)
        return False
    if output_dir(target.parent, flag) is None:
        return False
    existed = target.exists()
    try:
        with open(target, "a"):
            pass
    except OSError as exc:
        print(f"error: {flag} {target}: cannot write ({exc.strerror or exc})", file=sys.stderr)
        return False
    if not existed:
        target.unlink()
    return True


def output_spares_inputs(path, inputs, flag: str) -> bool:
    """A result file at ``path`` does not replace one of the command's ``inputs`` (files, or
    folders whose files count too: a bag; a new file beside them is fine): else one error naming
    the option. `./bike report BAG --fit BAG/x.mcap` wrote the FIT file over the recording."""
    target = pathlib.Path(path).resolve()
    for given in inputs:
        source = pathlib.Path(given).resolve()
        if target == source or (source.is_dir() and source in target.parents and target.exists()):
            print(f"error: {flag} {path}: would write over the input {given}", file=sys.stderr)
            return False
    return True


def write_output(path, text: str, flag: str) -> bool:
    """Write a result file; a failure (disk full, removed meanwhile) is one error line."""
    try:
        pathlib.Path(path).write_text(text)
    except OSError as exc:
        print(f"error: {flag} {path}: cannot write ({exc.strerror or exc})", file=sys.stderr)
        return False
    return True


def _cmd_run(opts) -> int:
    from bike_plant.config import ConfigError, load_config

    from bike_session import launcher

    if not _run_options_paired(opts):
        return 2
    config = pathlib.Path(opts.config or repo_root() / "config" / "bldc_default.yaml").resolve()
    try:
        cfg = load_config(config)
        if not getattr(opts, "set", None):      # a --set copy is checked as a whole below
            _check_config(cfg)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:
        # checked before any node starts: one error, not the nodes' (and exit 1 after the start)
        print(f"error: {exc}" if str(config) in str(exc) else f"error: {config}: {exc}", file=sys.stderr)
        return 2
    source_config = config
    if getattr(opts, "set", None):
        changed = _set_run_config(opts.set, config)
        if changed is None:
            return 2
        config, cfg = changed
    workout = None
    ftms_on = getattr(opts, "ftms", False)
    if not opts.workout:
        opts.workout = _config_workout(cfg, config)
    if ftms_on and not opts.workout:
        opts.workout = str(repo_root() / "config" / "profiles" / "app_ride.yaml")
    rider_flags = given_options(opts, ("ftp", "max_hr"))
    if rider_flags and not opts.workout:
        # they are read with a workout only: the config's profile rode without them, without a word
        print(f"error: {' / '.join(rider_flags)} needs --workout FILE (or session.workout in the config): only a "
              f"workout's targets are read with it, and the profile of {source_config.name} has none", file=sys.stderr)
        return 2
    if ftms_on and not 0 <= opts.ftms_port <= 65535:
        print(f"error: --ftms-port must be 0..65535, got {opts.ftms_port}", file=sys.stderr)
        return 2
    if ftms_on and not (_ftms_address_ok(opts.ftms_host, opts.ftms_port) and _ftms_host_is_text(opts.ftms_host)):
        return 2
    if opts.workout:
        workout = _load_workout_for_run(opts, cfg)
        if workout is None:
            return 2
    elif not _config_profile_ok(cfg, config, source_config):
        return 2
    if not _backend_sync_mode_ok(cfg, config, source_config, ftms_on):
        return 2
    default_s = workout.duration_s if workout is not None else float(cfg.get("duration_s", 60.0))
    duration_s = opts.duration if opts.duration is not None else default_s
    if not (duration_s > 0 and math.isfinite(duration_s)):
        print(f"error: --duration must be a finite number > 0, got {duration_s}", file=sys.stderr)
        return 2
    from bike_plant.config import MAX_SIM_TIME_S
    if duration_s > MAX_SIM_TIME_S:
        # the session counts its time in int64 nanoseconds: 1e300 was its OverflowError traceback
        print(f"error: --duration must be at most {MAX_SIM_TIME_S:g} s (the ROS clock's int64 nanoseconds), "
              f"got {duration_s:g}", file=sys.stderr)
        return 2
    namespace = opts.namespace.strip("/")
    problem = namespace_problem(opts.namespace)
    if problem:
        # each node would otherwise die in rclpy.init with a traceback (an invalid remap rule)
        print(f"error: {problem}", file=sys.stderr)
        return 2
    from bike_plant.config import yaml_float

    # numbers as the launch file's YAML reads them back (repr's 1e+16 is text to it)
    args = {"config": str(config), "duration": yaml_float(duration_s), "namespace": namespace,
            "overrides": str(repo_root() / "config" / "launch" / "no_overrides.yaml")}
    if getattr(opts, "calibration", None):
        calibrated = _calibration_run_args(opts.calibration, config, cfg, args)
        if calibrated is None:
            return 2
        config, cfg = calibrated
    ftms_port_said = None
    if ftms_on:
        ftms_port_said = _ftms_run_args(opts, cfg, args)
    can_params = None
    if str(cfg.get("backend", "sim")) == "can":
        can_params = _can_run_args(cfg, args)
        if can_params is None:
            return 2
    if workout is not None:
        ftp_w, max_hr_bpm = _rider_figures(opts, cfg)
        args.update(workout=str(pathlib.Path(opts.workout).resolve()), ftp=yaml_float(ftp_w or 0.0))
        if max_hr_bpm:
            # only when given: a --launch file of its own need not declare the argument
            args.update(max_hr=yaml_float(max_hr_bpm))
    bag_path = None
    made_record_dir = bool(opts.record) and not pathlib.Path(opts.record).exists()
    if opts.record:
        record_dir = output_dir(pathlib.Path(opts.record).resolve(), "--record")
        if record_dir is None:
            return 2
        bag_name = "session_" + datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
        bag_path = record_dir / bag_name
        suffix = 1
        while bag_path.exists():
            bag_path = record_dir / f"{bag_name}_{suffix}"
            suffix += 1
        args.update(record="true", record_dir=str(record_dir), bag_name=bag_path.name, storage=opts.storage,
                    recorder_window=str(RECORDER_WINDOW_BATCHES))
        if can_params is not None and can_params.log_format != "none" and not can_params.log_file:
            # the CAN traffic beside the bag, in a format CAN tools read (python-can .asc / .blf)
            args["can_log"] = str(record_dir / f"{bag_path.name}.can.{can_params.log_format}")
    if not _config_launch_args(cfg, args, recording=bag_path is not None):
        remove_if_made_empty(opts.record, made_record_dir)
        return 2
    try:
        # read again to start: here a bad --launch file is the one line printed, before the
        # domain's and the run's [bike] lines (which said the run was starting)
        launcher.parse_launch(str(opts.launch or default_launch_file()), args)
    except launcher.LaunchError as exc:
        print(f"error: {exc}", file=sys.stderr)
        remove_if_made_empty(opts.record, made_record_dir)
        return 2
    # a private DDS domain: two simulations on one host must not ride each other's /clock and
    # commands (an explicit ROS_DOMAIN_ID is always respected)
    from bike_session import domains
    domains.ensure_private_domain("run")
    copy = f" (this run's copy: {config})" if config != source_config else ""
    print(f"[bike] config {source_config}{copy}, {duration_s:g} s simulated, namespace /{namespace}"
          + (f", recording to {bag_path}" if bag_path else ""), flush=True)
    try:
        code = launcher.run(str(opts.launch or default_launch_file()), args, on_line=ftms_port_said)
    except launcher.LaunchError as exc:
        print(f"error: {exc}", file=sys.stderr)
        remove_if_made_empty(opts.record, made_record_dir)
        return 2
    if bag_path is not None and bag_path.exists() and not (bag_path / "metadata.yaml").exists():
        # the recorder did not close the bag (killed): what it flushed is rescued by recover
        print(f"error: the recording at {bag_path} was not closed (recorder killed?); rescue what it "
              f"flushed with: ./bike bag recover {bag_path}", file=sys.stderr)
        code = code or 1
    elif bag_path is not None and bag_path.exists():
        from bike_session import report

        print(f"[bike] bag written: {bag_path}")
        report_code = report.main([str(bag_path)])
        code = code or report_code
    elif bag_path is not None:
        print(f"error: the recorder wrote no bag at {bag_path}", file=sys.stderr)
        code = code or 1
    return code


# options that only mean something beside another, with their defaults (the parser's are None,
# so that a given one is seen): each had been dropped without a word when its partner was missing
RUN_PAIRED_OPTIONS = (("ftms_host", "--ftms-host", "--ftms", "127.0.0.1"),
                      ("ftms_port", "--ftms-port", "--ftms", 36866),
                      ("ftms_advertise", "--ftms-advertise", "--ftms", "auto"),
                      ("storage", "--storage", "--record DIR", "mcap"))


def _run_options_paired(opts) -> bool:
    """--ftms-host / --ftms-port / --ftms-advertise without --ftms, --storage without --record:
    one error (False); otherwise the options not given take their defaults."""
    partners = {"--ftms": getattr(opts, "ftms", False), "--record DIR": getattr(opts, "record", None)}
    for attr, flag, partner, default in RUN_PAIRED_OPTIONS:
        if getattr(opts, attr, None) is None:
            setattr(opts, attr, default)
        elif not partners[partner]:
            print(f"error: {flag} needs {partner}: without it, it changes nothing", file=sys.stderr)
            return False
    return True


def _config_launch_args(cfg: dict, args: dict, recording: bool) -> bool:
    """The config's values of the node parameters the launch file sets after the config
    (recorder_window_batches, can_log_file, calibration_file), put into the launch arguments
    that carry them: the launch file's own values ("0", "") had replaced them without a word
    (--set recorder_window_batches=10 rode the run's 50). The window was checked with the
    config; a file that cannot be written is one error naming its key (False)."""
    window = cfg.get("recorder_window_batches")
    if window is not None and recording:
        args["recorder_window"] = str(int(window))
        if int(window) == 0:
            print("[bike] recorder_window_batches 0: the plant does not wait for the recorder, which may "
                  "fall behind and lose samples in a lockstep run", flush=True)
    elif window is not None and int(window) > 0:
        # a window with no recorder would hold the plant at its start until recorder_timeout_s
        print(f"[bike] recorder_window_batches {int(window)} not used: it paces a recorded run "
              "(--record), and this run records nothing", flush=True)
    files = {"calibration_file": "calibration"}
    can_log = cfg.get("can_log_file")
    if can_log and str(cfg.get("backend", "sim")) != "can":
        print(f"[bike] can_log_file {can_log} not used: this bike's backend is not can", flush=True)
    elif can_log:
        from bike_plant.can.backend import LOG_SUFFIXES
        if pathlib.Path(str(can_log)).suffix.lower() not in LOG_SUFFIXES:
            print(f"error: can_log_file must end in .asc or .blf, got {can_log!r}", file=sys.stderr)
            return False
        files["can_log_file"] = "can_log"
    for key, arg in files.items():
        if cfg.get(key) and not (key == "calibration_file" and args.get(arg)):     # --calibration wins
            path = pathlib.Path(str(cfg[key])).expanduser().resolve()       # the nodes' cwd may differ
            if not output_file_ok(path, key):
                return False
            args[arg] = str(path)
    return True


def _config_copy(config: pathlib.Path, doc: dict, note: str):
    """Write ``doc`` (the parameter file of ``config``, changed) as this run's config: a copy in
    a temporary folder (the bag records its text), with its relative file paths
    (bike_plant.config.RELATIVE_FILE_KEYS: the profile, a CAN drive's torque map) made absolute
    so they are still found. Returns (path, loaded config); ConfigError / ValueError /
    OSError when the copy is not a config the bike takes (checked as far as it can be without
    starting a node: structure, the modes section, the machine's parameters)."""
    import atexit
    import shutil
    import tempfile

    from bike_plant.config import absolute_file_paths, dump_ros_params, load_config

    for body in doc.values():
        params = body.get("ros__parameters") if isinstance(body, dict) else None
        if isinstance(params, dict):
            # as the nodes resolve them, against the original's folder
            absolute_file_paths(params, config.resolve().parent)
    folder = tempfile.mkdtemp(prefix="bike-config-")
    atexit.register(shutil.rmtree, folder, True)
    path = pathlib.Path(folder) / config.name
    path.write_text(f"# {config} {note}; written by ./bike run\n" + dump_ros_params(doc, sort_keys=False))
    try:
        cfg = load_config(path)
        _check_config(cfg)
    except ValueError as exc:
        # named by the config it was made from: the copy is removed at exit
        raise ValueError(str(exc).replace(str(path), str(config))) from None
    return path, cfg


def _check_config(cfg: dict) -> None:
    """What the nodes build first from a config, without building them: ValueError naming the
    key (the plant node's top-level numbers, the session's keys, numbers and over_range, the
    modes section, the friction figures, the machine's plant and controller parameters, the
    controller node's own numbers, a CAN drive's torque map)."""
    from bike_plant.config import ConfigError, check_plant_numbers

    from bike_controller.modes import modes_from_config
    from bike_controller.node_params import controller_node_numbers

    from bike_session.workouts import SESSION_KEYS, over_range_problem, session_number_problem

    check_plant_numbers(cfg)
    session = cfg.get("session") or {}
    unknown = sorted(set(session) - set(SESSION_KEYS)) if isinstance(session, dict) else []
    if unknown:
        # no node reads them: --set session.perod_s=0.05 (a typo) rode the 0.1 s period without a word
        raise ConfigError(f"unknown key(s) {', '.join(unknown)}; known: {', '.join(SESSION_KEYS)}",
                          cfg.get("_config_path"), "session")
    for key, default in (("period_s", 0.1), ("duration_s", 0.0), ("ftp_w", 0.0), ("max_hr_bpm", 0.0)):
        value = session.get(key, default) if isinstance(session, dict) else None
        # the session node's check (it refused them once the graph had started)
        if session_number_problem(f"session.{key}", value):
            raise ConfigError(session_number_problem(f"session.{key}", value), cfg.get("_config_path"),
                              f"session.{key}")
    over_range = session.get("over_range", "warn") if isinstance(session, dict) else "warn"
    if over_range_problem(over_range):
        # the session node's check (it refused it once the graph had started)
        raise ConfigError(over_range_problem(over_range), cfg.get("_config_path"), "session.over_range")
    modes_from_config(cfg)
    if str(cfg.get("machine", "bldc")) == "spmsm":
        from bike_controller.spmsm_params import controller_params_from_config
        from bike_plant.spmsm_params import plant_params_from_config
    else:
        from bike_controller.bldc_params import controller_params_from_config
        from bike_plant.params import plant_params_from_config
    plant_params_from_config(cfg)
    controller_params_from_config(cfg)
    controller_node_numbers(cfg)        # the controller node's own (command_wait_s, ...)
    if str(cfg.get("backend", "sim")) == "can":
        # the plant node's: a map it cannot use was its error once the graph (and the drive emulator) had started
        from bike_plant.can.backend import can_params_from_config, torque_map_of
        torque_map_of(cfg, can_params_from_config(cfg))


# the top-level keys a node reads (besides the config's own): --set of another is a typo that
# would change nothing (--set batch_period=5 rode batch_periods 20 without a word)
RUN_TOP_LEVEL_KEYS = frozenset((
    "use_sim_time", "machine", "backend", "sync_mode", "batch_periods", "control_period_s", "command_timeout_s",
    "duration_s", "republish_s", "end_linger_s", "battery_every", "busy_wait_s", "clock_period_s",
    "diagnostics_period_s", "recorder_window_batches", "recorder_timeout_s", "start_timeout_s", "seed",
    "can_log_file", "command_wait_s", "calibration_file", "session", "modes", "load", "mechanics", "battery",
    "controller", "bldc", "hall", "spmsm", "encoder", "inverter", "regen", "can", "ftms"))


def _set_run_config(sets: list[str], config: pathlib.Path):
    """--set KEY=VALUE ...: this run's config with each dotted KEY under the wildcard section's
    ros__parameters set to VALUE (read as YAML: numbers, true / false, lists, text). Returns
    (config path, loaded config) or None after one error."""
    import yaml
    from bike_plant.config import ConfigError, YamlFileError, parse_yaml_text

    try:
        doc = yaml.safe_load(config.read_text())
        params = doc["/**"]["ros__parameters"]
        for item in sets:
            key, eq, text = item.partition("=")
            parts = key.strip().split(".")
            if not eq or not all(part.strip() for part in parts):
                raise ValueError(f"{item!r}: expected KEY=VALUE with a dotted KEY, e.g. modes.auto_shift=true")
            try:
                value = parse_yaml_text(text)
            except YamlFileError as exc:
                raise ValueError(f"{item!r}: the value is {exc}") from None
            if value is None or isinstance(value, dict):
                raise ValueError(f"{item!r}: give one value (a number, true / false, a list or text)")
            if isinstance(value, str):
                try:
                    value = float(text)      # YAML 1.1 reads 1e-4 (no dot) as text
                except ValueError:
                    pass
            top = parts[0].strip()
            if top == "machine" and value != params.get("machine", "bldc"):
                # the other machine's loader said "battery: unknown parameter(s) r_brake_ohm, ..."
                raise ValueError(f"{item!r}: the sections of {config.name} are its {params.get('machine', 'bldc')!r} "
                                 "bike's; ride another machine with --config (config/bldc_default.yaml, "
                                 "config/spmsm_default.yaml)")
            if top not in params and top not in RUN_TOP_LEVEL_KEYS:
                import difflib
                near = difflib.get_close_matches(top, sorted(RUN_TOP_LEVEL_KEYS | set(params)), n=1)
                raise ValueError(f"{item!r}: unknown key {top!r}: not in {config.name} nor read by a node"
                                 + (f" (did you mean {near[0]}?)" if near else ""))
            node = params
            for i, part in enumerate(parts[:-1]):
                node = node.setdefault(part, {})
                if not isinstance(node, dict):
                    raise ValueError(f"{item!r}: {'.'.join(parts[:i + 1])} is a value, not a section")
            node[parts[-1]] = value
        note = _set_over_rider_preset(params, sets)
        changed = ", ".join(sets)
        copied = _config_copy(config, doc, f"with --set {changed}")
        if note:
            print(note, flush=True)              # once the copy is a config the bike takes
        return copied
    except (ConfigError, ValueError, OSError, KeyError, TypeError) as exc:
        print(f"error: --set: {exc}", file=sys.stderr)
        return None


def _set_over_rider_preset(params: dict, sets: list[str]) -> str | None:
    """A --set of a rider value that load.rider_preset sets (the presets win over the section's
    own values) is ridden, not overridden by the preset without a word (the README's --set
    load.rider_target_cadence_rpm=90 rode 80 rpm): the preset's other values are written into
    the section, the preset becomes custom; returns the note that says so."""
    from bike_plant.params import RIDER_PRESETS

    load = params.get("load")
    preset = load.get("rider_preset", "custom") if isinstance(load, dict) else "custom"
    if not isinstance(preset, str) or preset not in RIDER_PRESETS:
        return None                              # custom, or an unknown preset: its own error follows
    given = [key.strip().split(".")[1] for key, _eq, _v in (item.partition("=") for item in sets)
             if key.strip().split(".")[0] == "load" and len(key.strip().split(".")) == 2]
    overridden = [key for key in given if key in RIDER_PRESETS[preset]]
    if not overridden:
        return None
    for key, value in RIDER_PRESETS[preset].items():
        if key not in overridden:
            load[key] = value
    load["rider_preset"] = "custom"
    return (f"[bike] --set load.{', load.'.join(overridden)}: load.rider_preset {preset} would override "
            f"{'it' if len(overridden) == 1 else 'them'}; riding the {preset} rider with "
            f"{'this change' if len(overridden) == 1 else 'these changes'} (rider_preset custom)")


def _calibration_run_args(path_text: str, config: pathlib.Path, cfg: dict, args: dict):
    """--calibration FILE: ride with the friction of the bike's last spin-down (FILE, when it
    exists) and let the controller write a new one there. The figures go into a copy of the
    config (bike_controller.calibration), so the recorded config carries them. Returns
    (config path, loaded config) or None after one error."""
    import yaml
    from bike_plant.config import ConfigError

    from bike_controller.calibration import CalibrationError, apply_calibration, read_calibration
    from bike_controller.modes import friction_figures

    path = pathlib.Path(path_text).resolve()
    if path.exists() and not path.is_file() and not path.is_dir():
        # a spin-down renames the new calibration over the file: /dev/null would be replaced
        print(f"error: --calibration {path}: not a regular file (a spin-down replaces the file with its "
              f"calibration)", file=sys.stderr)
        return None
    if not output_file_ok(path, "--calibration"):
        return None
    machine = str(cfg.get("machine", "bldc"))
    try:
        old = friction_figures(cfg)
    except ValueError as exc:
        print(f"error: {config}: {exc}", file=sys.stderr)
        return None
    args["calibration"] = str(path)
    if not path.exists() or path.stat().st_size == 0:
        print(f"[bike] no calibration in {path} yet: the config's friction (B {old[0]:.4g} N m s, Tc {old[1]:.4g} N m);"
              " a spin-down writes one there", flush=True)
        return config, cfg
    try:
        calibration = read_calibration(path, machine)
        doc = apply_calibration(yaml.safe_load(config.read_text()), calibration)
        calibrated, calibrated_cfg = _config_copy(config, doc, f"with the spin-down calibration of {path}")
    except (CalibrationError, ConfigError, ValueError, OSError) as exc:
        print(f"error: --calibration: {exc}", file=sys.stderr)
        return None
    print(f"[bike] friction from the calibration {path}: {calibration.describe()}; the config's: "
          f"B {old[0]:.4g} N m s, Tc {old[1]:.4g} N m. A new spin-down replaces it", flush=True)
    args["config"] = str(calibrated)
    return calibrated, calibrated_cfg


def _ftms_address_ok(host: str, port: int) -> bool:
    """--ftms-host / --ftms-port: the bridge can listen there (a trial listen, closed at once),
    else one error naming them: the bridge node found it once the graph had started (its error
    among the other nodes' lines, exit 1)."""
    import socket

    try:
        with socket.create_server((host, port), reuse_port=False):
            pass
    except (OSError, OverflowError) as exc:
        print(f"error: --ftms-host {host} --ftms-port {port}: cannot listen there "
              f"({getattr(exc, 'strerror', None) or exc})", file=sys.stderr)
        return False
    return True


def _ftms_host_is_text(host: str) -> bool:
    """--ftms-host reaches the bridge as its text parameter ftms.host (a launch argument), else one
    error: the C library's short forms of an address (127.1, 0x7f000001, 2130706433 for 127.0.0.1)
    are numbers to the launch file's YAML, and the bridge refused the number once the graph had
    started (its node's error among the others' lines, exit 1)."""
    from bike_session import launcher

    typed = launcher.typed_value(host)
    if typed is None:
        return True
    print(f"error: --ftms-host {host}: a number to the launch file (ROS parameters are typed), not a host "
          "name; write the address in full (e.g. 127.0.0.1)", file=sys.stderr)
    return False


FTMS_LISTENING = re.compile(r"FTMS over DIRCON on (\S+):(\d+) \(service ")     # the bridge node's line


def _ftms_port_said(host: str):
    """--ftms-port 0: a Launcher line watcher that says the port the OS gave the bridge, from the
    bridge node's own line (``ftms``: "FTMS over DIRCON on HOST:PORT (service ..."), as the
    [bike] line a user looks for; once. The mDNS advert carries that port already (the node
    advertises the port it listens on)."""
    said = []

    def watch(node: str, line: str) -> str | None:
        found = FTMS_LISTENING.search(line) if node == "ftms" and not said else None
        if found is None:
            return None
        said.append(found.group(2))
        return f"[bike] FTMS over DIRCON on {host}:{found.group(2)}: connect a training app to it"
    return watch


def _ftms_run_args(opts, cfg, args: dict):
    """--ftms: the bridge node's launch arguments; an app rides on the wall clock, so a lockstep
    config runs in real time (a parameter file every node takes after the config). Returns the
    launcher's line watcher that says the port when the OS picks it (--ftms-port 0), else None."""
    import atexit
    import shutil
    import tempfile

    args.update(ftms="true", ftms_host=opts.ftms_host, ftms_port=str(opts.ftms_port),
                ftms_advertise=opts.ftms_advertise)
    note = ""
    if str(cfg.get("sync_mode", "lockstep")) != "realtime":
        folder = tempfile.mkdtemp(prefix="bike-ftms-")
        atexit.register(shutil.rmtree, folder, True)
        path = pathlib.Path(folder) / "realtime.yaml"
        path.write_text("/**:\n  ros__parameters:\n    sync_mode: realtime\n")
        args["overrides"] = str(path)
        note = "; sync_mode realtime (the config's lockstep overridden: an app rides on the wall clock)"
    if opts.ftms_port == 0:
        # the port is the bridge's to learn when it listens: said then, from its line
        print(f"[bike] FTMS over DIRCON on {opts.ftms_host}, on a port the OS picks (said here once the bridge "
              f"listens){note}", flush=True)
        return _ftms_port_said(opts.ftms_host)
    print(f"[bike] FTMS over DIRCON on {opts.ftms_host}:{opts.ftms_port}: connect a training app to it{note}",
          flush=True)
    return None


def _emulator_args_problem(argv: list[str]) -> str | None:
    """What bike-drive-emulator's parser says of ``argv`` (None: it takes them), without exiting."""
    from bike_controller.drive_emulator import build_arg_parser

    parser = build_arg_parser()

    def refuse(message: str):
        raise ValueError(message)

    parser.error = refuse
    try:
        parser.parse_args(argv)
    except ValueError as exc:
        return str(exc)
    except SystemExit:
        return "--help / --version print and stop: not for a run"
    return None


def _can_run_args(cfg, args: dict):
    """backend can: the emulator launch arguments from the config's can: section (None: error)."""
    import shlex

    from bike_plant.can.backend import can_params_from_config, emulator_args_from_config
    from bike_plant.config import ConfigError

    try:
        params = can_params_from_config(cfg)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None
    if params.emulator:
        # its rider follows what the controller tells the plant's rider (a real one reads a screen),
        # his chest strap sends his heart rate where the plant node reads it, and its physics' truth
        # (the rider's true power) goes where the recorder records it, for the report
        def topic(name: str) -> str:
            return "/" + "/".join(x for x in (args.get("namespace", ""), name) if x)
        rider = ["--rider-topic", topic("drive_command"), "--heart-rate-topic", topic("heart_rate"),
                 "--truth-topic", topic("drive_truth")]
        emulator_args = emulator_args_from_config(cfg) + rider
        problem = _emulator_args_problem(emulator_args)
        if problem:
            # the emulator's usage and error came once the graph had started (its node exited)
            print(f"error: can.emulator_args: {problem} (bike-drive-emulator's options)", file=sys.stderr)
            return None
        args.update(emulator="true", emulator_args=" ".join(shlex.quote(a) for a in emulator_args))
    print(f"[bike] drive on CAN: {params.describe()}"
          + (", started here as bike-drive-emulator" if params.emulator else ", a real drive (can.emulator false)")
          + "; sim time pauses while the drive is not armed", flush=True)
    return params


def _backend_sync_mode_ok(cfg: dict, config: pathlib.Path, source_config: pathlib.Path, ftms_on: bool) -> bool:
    """backend can in the sync mode the run rides (--ftms: realtime, whatever the config says),
    checked as the plant node checks it before anything starts: a lockstep CAN run was the
    plant's error once the graph had started. False after one error (naming the config given,
    and --set when the run rides a changed copy of it)."""
    from bike_plant.config import ConfigError, check_backend_sync_mode

    sync_mode = "realtime" if ftms_on else str(cfg.get("sync_mode", "lockstep"))
    try:
        check_backend_sync_mode(str(cfg.get("backend", "sim")), sync_mode, source_config)
    except ConfigError as exc:
        print(f"error: {'--set: ' if config != source_config else ''}{exc}", file=sys.stderr)
        return False
    return True


def _config_profile_ok(cfg: dict, config: pathlib.Path, source_config: pathlib.Path) -> bool:
    """The config's session.profile (ridden without --workout) read before anything starts, as
    the session node reads it: a missing or bad profile was the session node's error once the
    graph had started. False after one error (naming the config given, and --set when the run
    rides a changed copy of it)."""
    from bike_session.profiles import ProfileError, load_profile, mode_units_from_config
    from bike_session.session_node import resolve_profile_path

    where = f"{'--set: ' if config != source_config else ''}{source_config}: "
    profile = (cfg.get("session") or {}).get("profile") if isinstance(cfg.get("session"), dict) else None
    if not isinstance(profile, str) or not profile:
        print(f"error: {where}session.profile is empty: give a profile in the config or --workout FILE",
              file=sys.stderr)
        return False
    try:
        units = mode_units_from_config(cfg)
    except ValueError:
        units = None                     # as the session node: a profile that needs them says so
    try:
        load_profile(resolve_profile_path(profile, str(config)), units=units)
    except (ProfileError, ValueError) as exc:
        print(f"error: {where}session.profile: {exc}", file=sys.stderr)
        return False
    return True


def _config_workout(cfg: dict, config: pathlib.Path) -> str | None:
    """The config's session.workout (ridden instead of session.profile, as the session node
    does), resolved like session.profile against the config's folder; None when not set. The
    launch file's workout argument ("" without --workout) replaced it: the config's workout
    was never ridden, the profile was, without a word."""
    from bike_plant.config import resolve_config_path

    session = cfg.get("session") if isinstance(cfg.get("session"), dict) else {}
    value = session.get("workout")
    return str(resolve_config_path(value, config)) if isinstance(value, str) and value.strip() else None


def _rider_figures(opts, cfg) -> tuple[float | None, float | None]:
    """The rider's FTP and maximum heart rate for the workout: --ftp / --max-hr, else the config's
    session.ftp_w / session.max_hr_bpm (0 or absent: not given; _check_config has checked them).
    The launch file's ftp / max_hr arguments replace the config's parameters, so the config's
    figures were never ridden, while the error for a missing FTP named session.ftp_w."""
    session = cfg.get("session") if isinstance(cfg.get("session"), dict) else {}
    ftp_w = opts.ftp if opts.ftp is not None else (session.get("ftp_w") or None)
    max_hr = getattr(opts, "max_hr", None)
    max_hr_bpm = max_hr if max_hr is not None else (session.get("max_hr_bpm") or None)
    return ftp_w, max_hr_bpm


def rider_options_problem(ftp_w: float | None, max_hr_bpm: float | None) -> str | None:
    """Why --ftp / --max-hr (None: not given) are no rider's figures, one line; or None
    (./bike run and ./bike trainer, before a workout is read)."""
    from bike_session.workouts import MAX_FTP_W, MAX_HR_BPM
    if ftp_w is not None and not 0 < ftp_w <= MAX_FTP_W:
        return f"--ftp must be in (0, {MAX_FTP_W:g}] W, got {ftp_w}"
    if max_hr_bpm is not None and not 0 < max_hr_bpm <= MAX_HR_BPM:
        return f"--max-hr must be in (0, {MAX_HR_BPM:g}] bpm, got {max_hr_bpm}"
    return None


def _load_workout_for_run(opts, cfg):
    """Read the workout once before anything starts: a bad file is one error, nothing runs."""
    import warnings

    from bike_session.profiles import ProfileError, mode_units_from_config
    from bike_session.workouts import WorkoutWarning, describe, load_workout, pmax_w_from_config

    problem = rider_options_problem(opts.ftp, getattr(opts, "max_hr", None))
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        return None
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", WorkoutWarning)
            # the config's over_range as the session node reads the workout: an error there
            # refuses a target beyond the machine's range now, not once the graph has started
            ftp_w, max_hr_bpm = _rider_figures(opts, cfg)
            workout = load_workout(opts.workout, ftp_w=ftp_w, pmax_w=pmax_w_from_config(cfg),
                                   units=mode_units_from_config(cfg), max_hr_bpm=max_hr_bpm,
                                   over_range=(cfg.get("session") or {}).get("over_range", "warn"))
    except (ProfileError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None
    print(describe(workout), flush=True)
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr, flush=True)
    return workout


def _cmd_report(opts) -> int:
    from bike_session import report

    return report.main([opts.bag] + (["--out", opts.out] if opts.out else []) + (["--json"] if opts.json else [])
                       + (["--fit", opts.fit] if opts.fit else []))


def _cmd_compare(opts) -> int:
    from bike_session import compare

    return compare.main([opts.bag_a, opts.bag_b] + (["--out", opts.out] if opts.out else [])
                        + (["--json"] if opts.json else []))


def _cmd_replay(opts) -> int:
    from bike_session import replay

    return replay.main(opts.args)


def _cmd_bag(opts) -> int:
    from bike_session import recover

    return recover.main([opts.bag] + (["--out", opts.out] if opts.out else []))


def _cmd_paper(opts) -> int:
    from bike_plant.config import ConfigError

    from bike_session import paper

    made_out = not pathlib.Path(opts.out).exists()
    out = output_dir(opts.out, "--out")
    if out is None:
        return 2
    if opts.name == "seed2-table1":
        from bike_session import paper_spmsm
        config = opts.config or str(repo_root() / "config" / "spmsm_default.yaml")
        try:
            result = paper_spmsm.table1(config, str(out))
        except ConfigError as exc:
            print(f"error: {exc}", file=sys.stderr)
            remove_if_made_empty(out, made_out)
            return 2
        print(paper_spmsm.summary(result))
        for path in result["files"]:
            print(f"  wrote {path}")
        return 0 if result["passed"] else 1
    config = opts.config or str(repo_root() / "config" / "bldc_default.yaml")
    runner = {"seed1-fig14": paper.fig14, "seed1-current": paper.current, "seed1-resistance": paper.resistance,
              "seed1-k-table": paper.k_table}[opts.name]
    try:
        result = runner(config, str(out))
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        remove_if_made_empty(out, made_out)
        return 2
    verdict = "PASS" if result.get("passed") else "FAIL"
    print(f"{result['name']}: {len(result['points'])} points, largest error {result['max_error'] * 100:.2f} % "
          f"(target {result['tolerance'] * 100:.0f} %): {verdict}")
    if result.get("skipped_rpm"):
        print(f"  not measured: {', '.join(f'{s:g}' for s in result['skipped_rpm'])} rpm (the back-EMF reaches the "
              "empty pack's voltage there: the bridge diodes brake beyond control)")
    for path in result["files"]:
        print(f"  wrote {path}")
    if result.get("dropped_commands"):
        print(f"  no row for Command {', '.join(f'{c:g}' for c in result['dropped_commands'])}: the machine brakes "
              "nothing there at some speed (the current asked stays inside the hysteresis band)")
    if opts.name == "seed1-k-table":
        print(f"  put the values of {result['files'][0]} into your config's controller: section, then check "
              "Fig. 14 with ./bike paper seed1-fig14 --config <it>")
    return 0 if result.get("passed", False) else 1


def _cmd_bench(opts) -> int:
    from bike_session import bench

    if opts.json and not output_file_ok(opts.json, "--json"):
        return 2
    return bench.main(json_path=opts.json, quick=opts.quick, only=opts.only, memory_s=opts.memory_s)


FLEET_TARGET_BIKES = 1000      # issue 6: the offline batched kernel runs >= 1000 bikes in real time
# ./bike fleet's options of one mode; the parser's defaults are None (False for a flag), so that a
# given one is seen, and these are taken when not given
FLEET_OFFLINE_OPTIONS = ("bikes", "threads", "seed", "show")
FLEET_GRAPH_OPTIONS = ("timeout", "verbose", "launch")
FLEET_DEFAULTS = {"bikes": FLEET_TARGET_BIKES, "threads": 2, "seed": 0, "show": 5, "timeout": 300.0}


def _cmd_fleet(opts) -> int:
    """Offline: N bikes in the batched numba kernel (bike_controller.fleet). --graph K: K
    namespaced bikes in one DDS graph (bike_session.fleet_graph)."""
    import json

    from bike_plant.config import ConfigError

    config = str(pathlib.Path(opts.config or repo_root() / "config" / "bldc_default.yaml").resolve())
    # each option of the other mode was dropped without a word (--graph 2 --bikes 50 rode 2 bikes)
    wrong = given_options(opts, FLEET_OFFLINE_OPTIONS if opts.graph is not None else FLEET_GRAPH_OPTIONS)
    if wrong:
        print(f"error: {', '.join(wrong)}: " + ("for the offline fleet, not with --graph" if opts.graph is not None
                                                 else "only with --graph"), file=sys.stderr)
        return 2
    for attr, default in FLEET_DEFAULTS.items():
        if getattr(opts, attr) is None:
            setattr(opts, attr, default)
    if opts.json and not output_file_ok(opts.json, "--json"):
        return 2
    if opts.graph is not None:
        from bike_session import fleet_graph as FG
        seconds = 1.0 if opts.seconds is None else opts.seconds
        from bike_session import domains
        try:
            placement = FG.check_graph_args(opts.graph, seconds, opts.timeout, FG.parse_placement(opts.netns))
        except FG.FleetError as exc:
            # before the domain's line: a bad argument is the one line printed
            print(f"error: {exc}", file=sys.stderr)
            return 2
        domains.ensure_private_domain("fleet")
        try:
            result = FG.run_graph(opts.graph, config, seconds, placement, launch_file=opts.launch,
                                  timeout_s=opts.timeout, quiet_nodes=not opts.verbose)
        except (FG.FleetError, FG.L.LaunchError, ConfigError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        print(FG.format_graph(result), flush=True)
        if opts.json and not write_output(opts.json, json.dumps(result, indent=2, sort_keys=True), "--json"):
            return 2
        return 0 if result["ok"] else 1
    if opts.netns:
        print("error: --netns places the nodes of a --graph fleet", file=sys.stderr)
        return 2
    if opts.show < 0:
        # it was taken as 0 without a word
        print(f"error: --show must be >= 0 (bikes to print), got {opts.show}", file=sys.stderr)
        return 2
    from bike_controller import fleet as F
    seconds = 2.0 if opts.seconds is None else opts.seconds
    try:
        # the library's checks name the options the user typed (its own name its arguments)
        r = F.fleet_real_time(opts.bikes, seconds, threads=opts.threads, cfg_path=config, seed=opts.seed,
                              summaries=True, names={k: f"--{k}" for k in ("bikes", "seconds", "threads", "seed")})
    except (ValueError, ConfigError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"fleet: {r['bikes']} bikes x {r['sim_s']:g} s simulated on {r['threads']} threads in {r['wall_s']:.2f} s wall "
          f"(JIT/cache load {r['jit_compile_s']:.1f} s, apart)")
    print(f"  real-time factor of the whole fleet: {r['real_time']:.3f}x "
          f"({r['ns_per_bike_period']:.0f} ns per bike-period)")
    print(f"  bikes in real time: {r['bikes_in_real_time']:.0f} "
          f"(target {FLEET_TARGET_BIKES}: ratio {r['bikes_in_real_time'] / FLEET_TARGET_BIKES:.2f})")
    agg = r["aggregate"]
    print("  per bike (mean / min / max over the fleet):")
    for key, label in (("mean_rider_power_w", "rider power [W]"), ("mean_battery_power_w", "battery charging [W]"),
                       ("mean_resistor_power_w", "brake resistor [W]"), ("mean_cadence_rpm", "cadence [rpm]"),
                       ("final_soc", "final SOC"), ("ledger_residual_j", "ledger residual [J]")):
        a = agg[key]
        print(f"    {label:<22}{a['mean']:>11.4g}{a['min']:>11.4g}{a['max']:>11.4g}")
    print(f"    bikes with faults: {agg['bikes_with_faults']}")
    shown = r["per_bike"][:opts.show]
    if shown:
        print(f"  first {len(shown)} bikes: command, rider T0 [N m], target cadence, mean cadence [rpm], rider W, battery W")
        for b in shown:
            print(f"    bike{b['bike']:<5}{b['command']:>6.2f}{b['rider_t0_nm']:>8.0f}{b['target_cadence_rpm']:>7.0f}"
                  f"{b['mean_cadence_rpm']:>8.1f}{b['mean_rider_power_w']:>9.1f}{b['mean_battery_power_w']:>9.1f}")
    if opts.json and not write_output(opts.json, json.dumps(r, indent=2), "--json"):
        return 2
    return 0


# ./bike trainer's options that connect to one trainer (--find connects to none), and those of a
# workout; each was dropped without a word where it means nothing
TRAINER_CONNECTION_OPTIONS = ("host", "port", "power", "grade", "level", "cadence", "crr", "cw", "wind", "difficulty",
                              "workout", "spindown", "ftp", "max_hr", "csv")
TRAINER_WORKOUT_OPTIONS = ("ftp", "max_hr")


def _trainer_options_problem(opts) -> str | None:
    """Why the options given do not go together (None: they do); the parser's --host / --port
    defaults are None, so that a given one is seen, and are set here."""
    if opts.find and given_options(opts, TRAINER_CONNECTION_OPTIONS):
        return (f"{', '.join(given_options(opts, TRAINER_CONNECTION_OPTIONS))}: not with --find, which lists the "
                "trainers announced on the network and connects to none")
    if not opts.workout and given_options(opts, TRAINER_WORKOUT_OPTIONS):
        return (f"{', '.join(given_options(opts, TRAINER_WORKOUT_OPTIONS))}: only with --workout (its targets in % "
                "of them)")
    from bike_session.dircon import DEFAULT_PORT
    opts.host = "127.0.0.1" if opts.host is None else opts.host
    opts.port = DEFAULT_PORT if opts.port is None else opts.port
    return None


def _cmd_trainer(opts) -> int:
    from bike_session import trainer_probe
    problem = _trainer_options_problem(opts)
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        return 2
    if opts.csv and not output_file_ok(opts.csv, "--csv"):
        return 2
    opts.seconds_given = opts.seconds is not None
    if opts.seconds is None:
        opts.seconds = 120.0 if opts.spindown else 5.0
    if not (opts.seconds > 0 and math.isfinite(opts.seconds)):
        print(f"error: --seconds must be a finite number > 0, got {opts.seconds}", file=sys.stderr)
        return 2
    from bike_plant.config import MAX_SIM_TIME_S
    if opts.seconds > MAX_SIM_TIME_S:
        # --find --seconds 1e300 ended in time.sleep's OverflowError traceback
        print(f"error: --seconds must be at most {MAX_SIM_TIME_S:g} (a clock's int64 nanoseconds), "
              f"got {opts.seconds:g}", file=sys.stderr)
        return 2
    return trainer_probe.main(opts)


def _cmd_shift(opts) -> int:
    from bike_session.shifter import press
    return press(opts.gears, opts.namespace, opts.domain)


def _cmd_torque_map(opts) -> int:
    """The drive's torque map (true vs reported torque per speed and setpoint) measured on the drive
    emulator's physics (bike_controller.drive_torque_map), written for can.torque_map_file."""
    from bike_plant.can.torque_map import TorqueMapError, torque_map_from_csv
    from bike_plant.config import ConfigError, load_config

    from bike_controller import drive_torque_map as DTM

    if not output_spares_inputs(opts.out, [x for x in (opts.from_csv, opts.config) if x], "--out"):
        return 2
    emulator_options = given_options(opts, ("config", "speeds_rpm", "setpoints_nm", "settle_s", "window_s"))
    if opts.from_csv and emulator_options:
        # they set up the emulated dyno: with --from-csv they were dropped without a word
        print(f"error: {', '.join(emulator_options)}: not with --from-csv (they set up the emulated dynamometer; "
              "the CSV's points are the map)", file=sys.stderr)
        return 2
    opts.settle_s = DTM.DEFAULT_SETTLE_S if opts.settle_s is None else opts.settle_s
    opts.window_s = DTM.DEFAULT_WINDOW_S if opts.window_s is None else opts.window_s
    if opts.from_csv:
        # a real drive's map: the points a dynamometer with a torque sensor logged
        try:
            tmap = torque_map_from_csv(opts.from_csv)
        except TorqueMapError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        if not output_file_ok(opts.out, "--out"):
            return 2
        print(f"{tmap.describe()}: {tmap.source}")
        return _save_torque_map(tmap, opts.out)
    config = pathlib.Path(opts.config or repo_root() / "config" / "bldc_can.yaml")
    try:
        cfg = load_config(config)
        drive = DTM.DriveModelParams.from_config(cfg)
        kt, limit_a = drive.torque_constant_nm_per_a, drive.current_limit_a
    except (ConfigError, ValueError) as exc:
        print(f"error: {exc}" if str(config) in str(exc) else f"error: {config}: {exc}", file=sys.stderr)
        return 2
    try:
        speeds = DTM.parse_grid(opts.speeds_rpm, "--speeds-rpm") if opts.speeds_rpm else DTM.default_speeds_rpm(cfg)
        setpoints = (DTM.parse_grid(opts.setpoints_nm, "--setpoints-nm") if opts.setpoints_nm
                     else DTM.default_setpoints_nm(DTM.setpoint_top_nm(cfg, kt, limit_a)))
        # the option and the range, not the emulated dyno's config key (load.speed_rpm)
        DTM.check_speeds(speeds, cfg, "--speeds-rpm" if opts.speeds_rpm else
                         f"the default speeds (cadence {DTM.DEFAULT_CADENCE_RPM[0]:g}..{DTM.DEFAULT_CADENCE_RPM[1]:g} "
                         "rpm x load.gear_ratio; give --speeds-rpm)")
        DTM.check_grid(speeds, setpoints, limit_a * kt,    # before the output file is touched
                       ("--speeds-rpm" if opts.speeds_rpm else "the default speeds",
                        "--setpoints-nm" if opts.setpoints_nm else "the default setpoints"))
        DTM.check_times(opts.settle_s, opts.window_s, ("--settle-s", "--window-s"))
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not output_file_ok(opts.out, "--out"):
        return 2
    try:
        m = DTM.measure_grid(cfg, speeds, setpoints, settle_s=opts.settle_s, window_s=opts.window_s)
        problem = m.problem()
        if problem:
            raise ValueError(problem)
        tmap = m.to_map(DTM.describe_source(m, config.name))
    except (ConfigError, ValueError, TorqueMapError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"torque map of {config} ({m.machine}, kt {m.kt_nm_per_a:.5g} N m/A): {m.speed_rpm.size} speeds x "
          f"{m.setpoint_nm.size} setpoints in {m.wall_s:.2f} s (settled within {float(m.settled_s.max()):.3g} s); "
          f"speed held within "
          f"{float(m.speed_spread_rpm.max()):.3g} rpm (mean off by <= {float(abs(m.speed_error_rpm).max()):.3g} rpm)")
    print(DTM.summary_table(m))
    return _save_torque_map(tmap, opts.out)


def _save_torque_map(tmap, out) -> int:
    """Write the map to ``out`` (checked by output_file_ok first); the command's exit code."""
    try:
        tmap.save(out)
    except OSError as exc:
        print(f"error: --out {out}: cannot write ({exc.strerror or exc})", file=sys.stderr)
        return 2
    print(f"  wrote {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="bike", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = sub.add_parser("run", help="start the node graph (plant, controller, session[, recorder]) "
                                     "for a number of simulated seconds")
    run.add_argument("--config", type=path_arg,
                     help="bike config (ROS 2 parameter file); default config/bldc_default.yaml")
    run.add_argument("--duration", type=float, help="simulated seconds (default: duration_s of the config)")
    run.add_argument("--workout", metavar="FILE", type=path_arg,
                     help="ride a workout file (.zwo, .erg, .mrc, .fit or a profile "
                          ".yaml) instead of the config's profile; power targets in "
                          "ERG mode; the run lasts the workout unless --duration is given")
    run.add_argument("--ftp", type=float, metavar="W", help="rider FTP for the workout's relative targets "
                                                            "(default: the file's own FTP when it has one)")
    run.add_argument("--max-hr", type=float, metavar="BPM", help="rider's maximum heart rate for a FIT workout's "
                                                                 "heart-rate targets in %% of it (session.max_hr_bpm)")
    run.add_argument("--record", metavar="DIR", type=path_arg,
                     help="record every topic to an MCAP bag under DIR and summarise it")
    run.add_argument("--storage", choices=["mcap", "sqlite3"], help="bag storage with --record (default mcap)")
    run.add_argument("--namespace", default="bike", help="ROS namespace of the bike (default bike)")
    run.add_argument("--launch", type=path_arg, help="launch description (default config/launch/bike.launch.yaml)")
    run.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                     help="change one config value for this run (repeatable), e.g. --set modes.auto_shift=true or "
                          "--set load.rider_target_cadence_rpm=90: a dotted key under the config's ros__parameters, "
                          "the value read as YAML; the bag records the changed config")
    run.add_argument("--calibration", metavar="FILE", type=path_arg,
                     help="ride with the friction of the bike's last spin-down, kept in FILE, and write the next "
                          "successful spin-down there (as a trainer keeps its calibration)")
    run.add_argument("--ftms", action="store_true",
                     help="serve the bike as a smart trainer (Bluetooth FTMS over Wahoo Direct Connect, TCP) "
                          "for a training app to ride in real time; without --workout the app rides "
                          "config/profiles/app_ride.yaml (2 h, or Ctrl-C)")
    run.add_argument("--ftms-host",
                     help="address the FTMS bridge listens on (default 127.0.0.1, this host only; 0.0.0.0 for "
                          "an app on the network)")
    run.add_argument("--ftms-port", type=int, help="its TCP port (default 36866, DIRCON's)")
    run.add_argument("--ftms-advertise", choices=["auto", "true", "false"],
                     help="announce the bike by mDNS (_wahoo-fitness-tnp._tcp), as apps find DIRCON trainers; "
                          "auto (default): when --ftms-host is not loopback")
    run.set_defaults(func=_cmd_run)

    rep = sub.add_parser("report", help="summarise a recorded bag: duration, power, energy, peak current, faults")
    rep.add_argument("bag")
    rep.add_argument("--out", type=path_arg,
                     help="also write charts (PNG) and summary.txt/.json/.html into this folder")
    rep.add_argument("--json", action="store_true", help="print the summary as JSON")
    rep.add_argument("--fit", metavar="FILE", type=path_arg,
                     help="also write the ride as a FIT activity (power, cadence, speed, "
                          "distance per second) for Garmin Connect, Strava, GoldenCheetah")
    rep.set_defaults(func=_cmd_report)

    cmp = sub.add_parser("compare", help="A/B comparison of two recorded sessions: tracking error, power, "
                                         "energy, current peaks, config differences (on the overlapping time range)")
    cmp.add_argument("bag_a")
    cmp.add_argument("bag_b")
    cmp.add_argument("--out", type=path_arg, help="write compare.txt/.json/.html and overlay charts into this folder")
    cmp.add_argument("--json", action="store_true", help="print the comparison as JSON")
    cmp.set_defaults(func=_cmd_compare)

    rpl = sub.add_parser("replay", add_help=False,
                         help="ride a recorded session's Command timeline again, on the recorded bike or "
                              "--config OTHER, with the recorded rider; records a new bag "
                              "(replay BAG [--config OTHER] [--load recorded|config] [--record DIR])")
    rpl.add_argument("args", nargs=argparse.REMAINDER)
    rpl.set_defaults(func=_cmd_replay)

    bag = sub.add_parser("bag", help="bag tools: `bag recover BAG` turns a crashed recording into a normal bag")
    bag_sub = bag.add_subparsers(dest="bag_command", required=True, metavar="TOOL")
    rec = bag_sub.add_parser("recover", help="rewrite what survived of a crashed recording (no metadata.yaml) "
                                             "into a new bag (BAG.recovered); the original is not modified")
    rec.add_argument("bag")
    rec.add_argument("--out", type=path_arg, help="output bag directory (default BAG.recovered)")
    rec.set_defaults(func=_cmd_bag)

    pap = sub.add_parser("paper", help="reproduce a figure of a paper: " + "; ".join(
        f"{k} ({v})" for k, v in PAPERS.items()))
    pap.add_argument("name", choices=sorted(PAPERS))
    pap.add_argument("--out", required=True, type=path_arg, help="output folder for CSV and PNG")
    pap.add_argument("--config", type=path_arg,
                     help="bike config (default config/bldc_default.yaml; seed2-*: config/spmsm_default.yaml)")
    pap.set_defaults(func=_cmd_paper)

    ben = sub.add_parser("bench", help="print speed figures and ratios (inner loop, node graph, DDS ping-pong)")
    ben.add_argument("--json", type=path_arg, help="also write the figures to this JSON file")
    ben.add_argument("--quick", action="store_true", help="shorter runs (noisier figures)")
    ben.add_argument("--only", action="append", metavar="SECTION",
                     help="run only this section (repeatable, or a comma list): inner, fleet, graph, can, peers, memory")
    ben.add_argument("--memory-s", type=float, metavar="S",
                     help="simulated seconds of the memory run (default 600; 3600 for the full hour)")
    ben.set_defaults(func=_cmd_bench)

    flt = sub.add_parser("fleet", help="many bikes: the offline batched kernel (bikes in real time, per-bike "
                                       "summaries) or, with --graph K, K namespaced bikes in one DDS graph")
    flt.add_argument("--bikes", type=int, help="offline: number of bikes (default 1000)")
    flt.add_argument("--seconds", type=float, help="simulated seconds (default 2 offline, 1 with --graph)")
    flt.add_argument("--threads", type=int, help="offline: numba threads (default 2)")
    flt.add_argument("--seed", type=int, help="offline: seed of the per-bike spread of riders and commands")
    flt.add_argument("--show", type=int, help="offline: print the first N bikes (default 5)")
    flt.add_argument("--graph", type=int, metavar="K", help="start K namespaced bikes (/bike1..) in one DDS graph")
    flt.add_argument("--netns", action="append", metavar="BIKE[/NODE]=NETNS",
                     help="--graph: run a bike's nodes (or one node) in an existing network namespace; repeatable; "
                          "needs ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET")
    flt.add_argument("--timeout", type=float, help="--graph: wall-clock limit in seconds (default 300)")
    flt.add_argument("--verbose", action="store_true", help="--graph: show the nodes' output")
    flt.add_argument("--launch", type=path_arg,
                     help="--graph: launch description of one bike (default config/launch/bike.launch.yaml)")
    flt.add_argument("--config", type=path_arg, help="bike config (default config/bldc_default.yaml)")
    flt.add_argument("--json", type=path_arg, help="also write the figures to this JSON file")
    flt.set_defaults(func=_cmd_fleet)

    shf = sub.add_parser("shift", help="press a running bike's virtual shifter: N gears up, -N down "
                                       "(std_msgs/Int8 on /<namespace>/shift)")
    shf.add_argument("gears", type=int, help="gears to shift: 1 up, -1 down, ...")
    shf.add_argument("--domain", type=int, help="ROS_DOMAIN_ID of the run (`./bike run` prints it; "
                                                "default: $ROS_DOMAIN_ID)")
    shf.add_argument("--namespace", default="bike", help="namespace of the bike (default bike)")
    shf.set_defaults(func=_cmd_shift)

    trn = sub.add_parser("trainer", help="the app's end of FTMS over DIRCON: find trainers on the network, show "
                                         "what one serves, set a target, print its Indoor Bike Data")
    trn.add_argument("--find", action="store_true", help="list the trainers announced by mDNS and stop")
    trn.add_argument("--host", help="trainer address (default 127.0.0.1: ./bike run --ftms)")
    trn.add_argument("--port", type=int, help="its DIRCON port (default 36866)")
    trn.add_argument("--seconds", type=float, help="how long to print Indoor Bike Data (default 5; --find: how "
                                                   "long to listen, default 3)")
    trn.add_argument("--power", type=float, metavar="W", help="take control and set ERG target power")
    trn.add_argument("--grade", type=float, metavar="PCT", help="take control and set the simulation grade")
    trn.add_argument("--level", type=float, metavar="L", help="take control and set the resistance level")
    trn.add_argument("--cadence", type=float, metavar="RPM", help="with a target: also set the rider's cadence "
                                                                "target (FTMS Set Targeted Cadence)")
    trn.add_argument("--crr", type=float, help="the road sent with a grade: rolling resistance "
                                                              "(default 0.004, as Zwift sends)")
    trn.add_argument("--cw", type=float, metavar="KG_PER_M",
                     help="... wind resistance rho CdA in kg/m (default 0.51, as Zwift sends)")
    trn.add_argument("--wind", type=float, metavar="MPS", help="... head wind in m/s (default 0)")
    trn.add_argument("--difficulty", type=float, metavar="PCT",
                     help="send grades as Zwift does at this trainer difficulty: scaled by it, descents halved "
                          "again (Zwift's default 50; default: the grade as it is)")
    trn.add_argument("--workout", metavar="FILE", type=path_arg,
                     help="ride a workout file (.zwo, .erg, .mrc, .fit, profile .yaml) "
                          "on the trainer as an app does, then print how it followed")
    trn.add_argument("--spindown", action="store_true",
                     help="run the trainer's spin-down calibration (FTMS Spin Down Control) and print its "
                          "progress until success or error (within --seconds, default 120)")
    trn.add_argument("--ftp", type=float, metavar="W", help="rider FTP for the workout's relative targets")
    trn.add_argument("--max-hr", type=float, metavar="BPM", help="rider's maximum heart rate for the workout's "
                                                                 "heart-rate targets in %% of it")
    trn.add_argument("--csv", metavar="FILE", type=path_arg,
                     help="with --workout: write every Indoor Bike Data sample here")
    trn.set_defaults(func=_cmd_trainer)

    tqm = sub.add_parser("torque-map", help="measure the drive's torque map (true vs reported torque per speed and "
                                            "setpoint) on the emulated drive: can.torque_map_file")
    tqm.add_argument("--config", type=path_arg, help="bike config (default config/bldc_can.yaml)")
    tqm.add_argument("--out", required=True, type=path_arg, help="map file to write (YAML)")
    tqm.add_argument("--speeds-rpm", nargs="+", metavar="RPM",
                     help="motor speeds: numbers, comma lists or START:STOP:STEP (default: the rider's cadence "
                          "span x the gear on a fine step, e.g. 1050..4375 every 25)")
    tqm.add_argument("--setpoints-nm", nargs="+", metavar="NM",
                     help="torque setpoints, 0 added (default: both signs up to the torque clamp, ~10 a side); "
                          "a range starting with '-' as --setpoints-nm=-3:3:0.5")
    tqm.add_argument("--from-csv", metavar="FILE", type=path_arg,
                     help="a real drive's map instead: a dynamometer's points (columns speed_rpm, setpoint_nm, "
                          "reported_nm, true_nm: the drive's Torque_Estimate and the torque sensor)")
    tqm.add_argument("--settle-s", type=float, help="settling time per point (default 0.05 s)")
    tqm.add_argument("--window-s", type=float,
                     help="averaging window per point, rounded up to whole electrical revolutions (default 0.1 s)")
    tqm.set_defaults(func=_cmd_torque_map)
    return parser


# the commands that start DDS participants in this environment's ROS_DOMAIN_ID (shift checks its own)
DDS_COMMANDS = ("run", "replay", "fleet", "bench")


def _domain_ok(argv: list[str]) -> bool:
    """ROS_DOMAIN_ID, when set, is a domain the nodes can join: else one error (False) before any
    work, not a traceback in every node (or the bench's ping-pong) once they start."""
    from bike_session import domains
    problem = domains.environment_problem() if argv[:1] and argv[0] in DDS_COMMANDS else None
    if problem and not {"-h", "--help"} & set(argv):
        print(f"error: {problem}", file=sys.stderr)
        return False
    return True


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["replay"]:                       # its own parser (--help lists its options)
        from bike_session import replay
        return replay.main(argv[1:]) if _domain_ok(argv) else 2
    opts = build_parser().parse_args(argv)
    return opts.func(opts) if _domain_ok(argv) else 2


if __name__ == "__main__":
    sys.exit(main())
