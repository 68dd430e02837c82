"""Configuration files: ROS 2 parameter files read with or without ROS.

A config is a ROS 2 parameter file (the format `--params-file` takes). Every node of the
bike reads the parameters under ``/**: ros__parameters:`` (plus, if present, a section
named after the node), so one file describes one bike. Offline tools (paper figures,
benchmark, tests) read the same file through :func:`load_config`.

Values are never evaluated as code: the file is parsed with ``yaml.safe_load``.
"""
from __future__ import annotations

import copy
import dataclasses
import math
import os
import pathlib
import re
import sys
from typing import Any, Callable, Mapping

import yaml

WILDCARD = "/**"
MAX_CONFIG_BYTES = 1 << 20  # a config is a few kB; refuse anything absurd before parsing


class ConfigError(ValueError):
    """A configuration problem, with the file and key it concerns."""

    def __init__(self, message: str, path: str | os.PathLike | None = None, key: str | None = None):
        where = str(path) if path else "<config>"
        if key:
            where += f": {key}"
        super().__init__(f"{where}: {message}")
        self.path = path
        self.key = key


def default_config_path() -> pathlib.Path:
    """The default bike (BLDC, paper 000), found in the repository's config/ folder."""
    root = os.environ.get("BIKE_ROOT")
    if root:
        return pathlib.Path(root, "config", "bldc_default.yaml")
    here = pathlib.Path(__file__).resolve()
    for parent in here.parents:
        candidate = parent / "config" / "bldc_default.yaml"
        if candidate.is_file():
            return candidate
    raise ConfigError("default config not found; set BIKE_ROOT or pass --config")


class YamlFileError(ValueError):
    """Why a small YAML file could not be read (the reason only: callers add the file)."""


def parse_yaml_text(text: str, check_node: Callable[[yaml.Node], None] | None = None) -> Any:
    """``yaml.safe_load`` of ``text``. YamlFileError with one reason: not valid YAML (line and
    column), nested too deeply. For text that comes from outside (a file, a bag's recorded
    config, a command line), so that none of it ends in a traceback. ``check_node`` sees the
    composed document (its scalars' text and quoting) before it is constructed."""
    # not libyaml's parser (7x faster on the 125 kB torque map): its composer recurses in C
    # and a hostile nesting (a 400 kB file) crashed the process with a segmentation fault
    loader = None
    try:
        loader = yaml.SafeLoader(text)     # its reader refuses an unprintable character here
        # yaml.safe_load's steps, with the check between them (one parse)
        node = loader.get_single_node()
        if node is None:
            return None
        if check_node is not None:
            check_node(node)
        return loader.construct_document(node)
    except yaml.reader.ReaderError as exc:
        # its own text is two lines ('  in "<unicode string>", position 41'): one error line
        at = min(max(int(exc.position), 0), len(text))
        line, column = text.count("\n", 0, at) + 1, at - text.rfind("\n", 0, at)
        raise YamlFileError(f"not valid YAML at line {line}, column {column}: unacceptable character "
                            f"#x{exc.character:04x} ({exc.reason})") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise YamlFileError(f"not valid YAML{line}: {getattr(exc, 'problem', None) or exc}") from None
    except RecursionError:
        # the constructors recurse per level (~300 levels here): an error, not a traceback
        raise YamlFileError("nested too deeply") from None
    finally:
        if loader is not None:
            loader.dispose()


def read_yaml_file(path: pathlib.Path, max_bytes: int, what: str = "it",
                   check_node: Callable[[yaml.Node], None] | None = None) -> Any:
    """:func:`parse_yaml_text` of a file that must be at most ``max_bytes`` (refused before
    parsing: a hostile or mistaken file is not read into memory). YamlFileError with one reason:
    cannot read ``what``, too large, not valid YAML (line and column), nested too deeply, not a
    text file."""
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise YamlFileError(f"cannot read {what} ({exc.strerror or exc})") from None
    if size > max_bytes:
        raise YamlFileError(f"file too large ({size} bytes > {max_bytes})")
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise YamlFileError("not a text file") from None
    except OSError as exc:
        # a directory, or a file stat could see but not read
        raise YamlFileError(f"cannot read {what} ({exc.strerror or exc})") from None
    return parse_yaml_text(text, check_node)


def load_config(path: str | os.PathLike | None = None, node_name: str | None = None) -> dict:
    """Read a parameter file and return the merged nested parameter dict.

    Raises ConfigError naming the file (and key) for unreadable, malformed or
    structurally wrong files. The returned dict carries ``_config_path`` so that relative
    paths inside (profiles) resolve against the file's folder.
    """
    path = pathlib.Path(path) if path else default_config_path()
    try:
        doc = read_yaml_file(path, MAX_CONFIG_BYTES, "config", lambda node: check_rcl_scalars(node, path))
    except YamlFileError as exc:
        raise ConfigError(str(exc), path) from None
    if not isinstance(doc, dict):
        raise ConfigError("expected a mapping of node names to 'ros__parameters'", path)
    merged: dict = {}
    sections = [WILDCARD] + ([node_name, f"/**/{node_name}"] if node_name else [])
    found = False
    for section in sections:
        body = doc.get(section)
        if body is None:
            continue
        if not isinstance(body, dict) or not isinstance(body.get("ros__parameters"), dict):
            raise ConfigError("section needs a 'ros__parameters' mapping", path, section)
        _check_ros_lists(body["ros__parameters"], path, "")
        _deep_merge(merged, body["ros__parameters"])
        found = True
    if not found:
        raise ConfigError(f"no '{WILDCARD}: ros__parameters:' section", path)
    merged["_config_path"] = str(path.resolve())
    return merged


def resolve_config_path(value: str, config_path: str | os.PathLike | None) -> pathlib.Path:
    """A file a config names (a profile, a CAN drive's torque map): ``~`` expanded, a relative
    path against the config file's folder (the working directory without a file)."""
    path = pathlib.Path(os.path.expanduser(value))
    if path.is_absolute():
        return path
    base = pathlib.Path(config_path).resolve().parent if config_path else pathlib.Path.cwd()
    return base / path


# parameters naming a file relative to the config's folder: a copy of the config written
# elsewhere (./bike run --set, replay, bench, the CAN latency rig) makes them absolute
RELATIVE_FILE_KEYS = (("session", "profile"), ("session", "workout"), ("can", "torque_map_file"))


def absolute_file_paths(params: dict, base_dir: str | os.PathLike) -> dict:
    """Make the RELATIVE_FILE_KEYS of one ``ros__parameters`` mapping absolute against
    ``base_dir`` (the folder of the config they came from), in place; returns ``params``."""
    for sect, key in RELATIVE_FILE_KEYS:
        body = params.get(sect) if isinstance(params, dict) else None
        value = body.get(key) if isinstance(body, dict) else None
        if isinstance(value, str) and value:
            path = pathlib.Path(os.path.expanduser(value))
            if not path.is_absolute():
                body[key] = str((pathlib.Path(base_dir) / path).resolve())
    return params


def _list_kind(item) -> str | None:
    """The ROS parameter type of one list item (None: none, as a list or mapping)."""
    if isinstance(item, bool):
        return "true/false"
    if isinstance(item, int):
        return "integer"
    if isinstance(item, float):
        return "decimal"
    if isinstance(item, str):
        return "text"
    return None


def _check_ros_lists(params: Mapping, path, prefix: str) -> None:
    """ConfigError naming the key of a list the ROS parameter parser refuses: every node is
    started with the file (--params-file), and rcl takes a list of one type only, so
    [0.8, 1] made each node exit at start with a traceback ('Sequence should be of same
    type') after the config had been checked."""
    for key, value in params.items():
        name = f"{prefix}{key}"
        for item in (value if isinstance(value, list) else [value]):
            if isinstance(item, int) and not isinstance(item, bool) and not -2**63 <= item < 2**63:
                # rcl reads it as a decimal: a list of it and integers was refused as mixed
                raise ConfigError(f"integer {item} outside the 64-bit range of a ROS parameter", path, name)
        if isinstance(value, Mapping):
            _check_ros_lists(value, path, name + ".")
        elif isinstance(value, list):
            kinds = [_list_kind(item) for item in value]
            if None in kinds:
                raise ConfigError(f"a list parameter holds numbers, text or true/false, not "
                                  f"{value[kinds.index(None)]!r}", path, name)
            if len(set(kinds)) > 1:
                hint = " (write whole numbers with a decimal point, e.g. 1.0)" \
                    if set(kinds) == {"integer", "decimal"} else ""
                raise ConfigError(f"a list parameter holds one type, got {' and '.join(sorted(set(kinds)))} "
                                  f"in {value!r}{hint}", path, name)


# ROS 2's parameter file parser (rcl_yaml_param_parser, parse.c get_value) types every scalar that is
# not single- or double-quoted itself, by its own rules, not YAML 1.1's: these words are true / false,
# then C strtol (base 0) and strtod decide, with errno set meaning "not that type"
_RCL_TRUE = frozenset(("Y", "y", "yes", "Yes", "YES", "true", "True", "TRUE", "on", "On", "ON"))
_RCL_FALSE = frozenset(("N", "n", "no", "No", "NO", "false", "False", "FALSE", "off", "Off", "OFF"))
_RCL_DOT_FLOATS = frozenset(sign + dot for sign in ("", "+", "-") for dot in (".inf", ".Inf", ".INF")) | {
    ".nan", ".NaN", ".NAN"}
_YAML_KINDS = {"tag:yaml.org,2002:bool": "true/false", "tag:yaml.org,2002:int": "integer",
               "tag:yaml.org,2002:float": "decimal", "tag:yaml.org,2002:str": "text",
               "tag:yaml.org,2002:null": "null", "tag:yaml.org,2002:timestamp": "date"}
_libc = None
# what C's strtol / strtod can start with (after white space), and numbers they read without a
# range error: decimal integers within 64 bits, decimals of few digits (leading 0: octal, to C)
_C_NUMBER_STARTS = frozenset("+-.0123456789iInN \t\n\v\f\r")
_SHORT_INT = re.compile(r"[-+]?(?:0|[1-9][0-9]{0,17})")
_SHORT_DECIMAL = re.compile(r"[-+]?(?:0|[1-9][0-9]{0,14})(?:\.[0-9]{0,15})?(?:[eE][-+]?[0-9]{1,2})?")


def _c_parses(func: str, text: str) -> bool:
    """Whether C's strtol (base 0) / strtod reads all of ``text`` without errno (the C library rcl uses)."""
    global _libc
    import ctypes
    if _libc is None:
        _libc = ctypes.CDLL(None, use_errno=True)
        _libc.strtol.restype, _libc.strtol.argtypes = ctypes.c_long, [
            ctypes.c_char_p, ctypes.POINTER(ctypes.c_char_p), ctypes.c_int]
        _libc.strtod.restype, _libc.strtod.argtypes = ctypes.c_double, [
            ctypes.c_char_p, ctypes.POINTER(ctypes.c_char_p)]
    raw = text.encode()
    if not raw or b"\0" in raw:
        return False
    buf = ctypes.create_string_buffer(raw)
    end = ctypes.c_char_p()
    ctypes.set_errno(0)
    if func == "strtol":
        _libc.strtol(buf, ctypes.byref(end), 0)
    else:
        _libc.strtod(buf, ctypes.byref(end))
    stop = ctypes.cast(end, ctypes.c_void_p).value - ctypes.addressof(buf)
    return ctypes.get_errno() == 0 and 0 < stop == len(raw)


def rcl_scalar_kind(text: str) -> str:
    """The type ROS 2's parameter file parser gives an unquoted scalar ``text``: true/false,
    integer, decimal or text (``nan``, ``1e5`` and ``y`` are text to yaml.safe_load, not to rcl)."""
    if text in _RCL_TRUE or text in _RCL_FALSE:
        return "true/false"
    # fast answers for the common texts (a ctypes call costs ~10 us, a config has hundreds of values)
    if text[:1] not in _C_NUMBER_STARTS:
        return "text"
    if _SHORT_INT.fullmatch(text):
        return "integer"
    if _SHORT_DECIMAL.fullmatch(text):
        return "decimal"
    if _c_parses("strtol", text):
        return "integer"
    if text in _RCL_DOT_FLOATS or _c_parses("strtod", text):
        return "decimal"
    return "text"


def check_rcl_scalars(root: yaml.Node, path) -> None:
    """ConfigError naming the key of an unquoted value that yaml.safe_load (this loader, every check
    before a node starts) and ROS 2's parameter parser (the nodes, started with the file) read as
    different types: [--watchdog-s, nan] passed every check as text, then each node exited with a
    traceback ('Sequence should be of same type'), and 1e5 was a number to the nodes only."""
    stack: list[tuple[yaml.Node, str]] = [(root, "")]
    seen: set[int] = set()
    while stack:
        node, name = stack.pop()
        if id(node) in seen:
            continue                    # an alias of a node already checked (or of its own parent)
        seen.add(id(node))
        if isinstance(node, yaml.MappingNode):
            for key, value in node.value:
                part = str(key.value) if isinstance(key, yaml.ScalarNode) else "?"
                # named as the other checks name it: dotted below a section's ros__parameters
                stack.append((value, "" if part == "ros__parameters" else f"{name}.{part}".lstrip(".")))
        elif isinstance(node, yaml.SequenceNode):
            stack.extend((item, name) for item in node.value)
        elif isinstance(node, yaml.ScalarNode) and node.style not in ("'", '"') and node.tag in _YAML_KINDS:
            ours = _YAML_KINDS[node.tag]        # (another tag: the constructor's error follows)
            if node.value == "" and ours == "null":
                raise ConfigError(f"no value (line {node.start_mark.line + 1}): ROS 2's parameter parser "
                                  "refuses an empty value; write one", path, name or None)
            theirs = rcl_scalar_kind(node.value)
            if ours == theirs or (ours, theirs) == ("integer", "decimal"):
                continue                # an integer beyond 64 bits: _check_ros_lists names it
            hint = "quote it ('...') if it is text" if theirs != "text" else "quote it ('...') for text"
            if "decimal" in (ours, theirs) and "e" in node.value.lower():
                hint += ", write a number with a point and a signed exponent (1.0e+5)"
            raise ConfigError(f"unquoted {node.value!r} (line {node.start_mark.line + 1}) is {ours} to this "
                              f"config's loader but {theirs} to ROS 2's parameter parser (the nodes'): {hint}",
                              path, name or None)


def yaml_float(value: float) -> str:
    """``value`` as YAML text that this project's loader and ROS 2's parameter parser both read
    as this same float: always a point and a signed exponent (``1.0e-05``, ``1.0e+16``), not
    ``repr``'s ``1e-05`` (text to yaml.safe_load, a number to rcl: a config holding it is refused);
    ``.nan`` / ``.inf`` / ``-.inf`` for the non-finite; a subnormal as 0.0."""
    value = float(value)
    if 0.0 < abs(value) < sys.float_info.min:
        # a subnormal (< 2.2e-308): C's strtod reads it with a range error, text to rcl; 0 to both
        value = math.copysign(0.0, value)
    if math.isnan(value):
        return ".nan"
    if math.isinf(value):
        return ".inf" if value > 0 else "-.inf"
    text = repr(value)      # the shortest text that reads back as this float; its exponent is signed
    if "e" in text and "." not in text:
        text = text.replace("e", ".0e", 1)
    return text


class _RosParamDumper(yaml.SafeDumper):
    """yaml.safe_dump that writes what this project's loader and ROS 2's parameter parser read
    alike: text rcl would read as another type quoted, floats by :func:`yaml_float` (numpy's
    too: a float subclass)."""

    def represent_str(self, data):
        if rcl_scalar_kind(data) != "text":
            return self.represent_scalar("tag:yaml.org,2002:str", data, style="'")
        return super().represent_str(data)

    def represent_float(self, data):
        return self.represent_scalar("tag:yaml.org,2002:float", yaml_float(data))


_RosParamDumper.add_representer(str, _RosParamDumper.represent_str)
_RosParamDumper.add_representer(float, _RosParamDumper.represent_float)
_RosParamDumper.add_multi_representer(float, _RosParamDumper.represent_float)


def dump_ros_params(doc: Any, **kwargs) -> str:
    """``doc`` as YAML that reads back the same through :func:`load_config` (and
    :func:`read_yaml_file`) and ROS 2's parameter parser: yaml.dump with text that rcl would type
    otherwise ('nan', 'y', '1e5') quoted and floats by :func:`yaml_float`. For every YAML file
    the project writes for a config or a loader to read back (params files, a torque map, a
    calibration, a replay's profile)."""
    return yaml.dump(doc, Dumper=_RosParamDumper, **kwargs)


def ros_param_text(value: Any) -> str:
    """``value`` as the one-line YAML of a ROS command-line parameter (``-p name:=VALUE``), which
    rcl types by the same rules as a params file: text it would read as another type quoted
    (``'y'``, ``'nan'``), floats by :func:`yaml_float`, lists in flow style."""
    text = dump_ros_params(value, default_flow_style=True, width=2 ** 30, allow_unicode=True)
    return text[:-len("\n...\n")] if text.endswith("\n...\n") else text.rstrip("\n")


def machine_config(cfg_or_path, machine: str, command: str, hint: str = "") -> dict:
    """A deep copy of a loaded config (or the config at a path) of a ``machine`` bike; one
    ConfigError naming the ``machine`` key and what ``command`` needs otherwise (the other
    machine's loader said "battery: unknown parameter(s) ..." or "expected 'spmsm' for this
    loader", neither of which named what was wrong)."""
    cfg = copy.deepcopy(cfg_or_path) if isinstance(cfg_or_path, dict) else load_config(cfg_or_path)
    found = cfg.get("machine", "bldc")
    if found != machine:
        raise ConfigError(f"{command}, and this config is a {found!r} bike{hint}", cfg.get("_config_path"),
                          "machine")
    return cfg


def config_variant(cfg: dict, **sections) -> dict:
    """A deep copy of a loaded config with the given sections' keys updated, e.g.
    config_variant(cfg, load={"kind": "none"}) (experiments and tests derive their cases so)."""
    c = copy.deepcopy(cfg)
    for name, values in sections.items():
        c[name] = dict(c.get(name) or {}, **values)
    return c


def _deep_merge(into: dict, other: Mapping) -> None:
    for key, value in other.items():
        if isinstance(value, Mapping) and isinstance(into.get(key), dict):
            _deep_merge(into[key], value)
        else:
            into[key] = value


def flatten(params: Mapping, prefix: str = "") -> dict[str, Any]:
    """Nested dict -> {'a.b.c': value}, the way ROS 2 names nested parameters."""
    flat: dict[str, Any] = {}
    for key, value in params.items():
        if str(key).startswith("_"):
            continue
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(flatten(value, name + "."))
        else:
            flat[name] = value
    return flat


def unflatten(flat: Mapping[str, Any]) -> dict:
    """{'a.b.c': value} -> nested dict (inverse of :func:`flatten`)."""
    nested: dict = {}
    for name, value in flat.items():
        node = nested
        *parents, leaf = name.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return nested


def section(cfg: Mapping, key: str, path: str | None = None) -> Mapping:
    """A sub-mapping of the config, empty if absent, ConfigError if not a mapping."""
    value = cfg.get(key, {})
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise ConfigError("expected a mapping", path or cfg.get("_config_path"), key)
    return value


def build_dataclass(cls, values: Mapping | None, key: str, path: str | None = None):
    """Instantiate dataclass ``cls`` from ``values`` with type and range checks.

    Unknown keys are an error (a typo must not silently fall back to a default);
    numbers must be finite; bool/int/float/str/list fields are checked by type. The
    dataclass may define ``validate(self) -> None`` raising ValueError for ranges.
    """
    values = dict(values or {})
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ConfigError(f"unknown parameter(s) {', '.join(unknown)}; known: {', '.join(sorted(fields))}", path, key)
    kwargs = {}
    for name, value in values.items():
        field = fields[name]
        if field.default is not dataclasses.MISSING:
            default = field.default
        elif field.default_factory is not dataclasses.MISSING:
            default = field.default_factory()
        else:
            default = None
        kwargs[name] = _check_value(value, default, f"{key}.{name}", path)
    try:
        obj = cls(**kwargs)
        if hasattr(obj, "validate"):
            obj.validate()
    except (TypeError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(str(exc), path, key) from None
    return obj


def _check_value(value, default, key, path):
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"expected true/false, got {value!r}", path, key)
        return value
    if isinstance(default, (int, float)) and not isinstance(default, bool):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"expected a number, got {value!r}", path, key)
        if not math.isfinite(value):
            raise ConfigError(f"must be finite, got {value!r}", path, key)
        if isinstance(default, int) and not isinstance(value, int):
            if float(value).is_integer():
                return int(value)
            raise ConfigError(f"expected an integer, got {value!r}", path, key)
        return type(default)(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(f"expected a string, got {value!r}", path, key)
        return value
    if isinstance(default, (list, tuple)):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"expected a list, got {value!r}", path, key)
        for item in value:
            if isinstance(item, bool) or not isinstance(item, (int, float, str)):
                raise ConfigError(f"list items must be numbers or strings, got {item!r}", path, key)
            if isinstance(item, float) and not math.isfinite(item):
                raise ConfigError(f"list items must be finite, got {item!r}", path, key)
        return list(value)
    return value


def require_positive(obj, *names: str) -> None:
    """Raise ValueError naming the first field of ``obj`` that is not > 0."""
    for name in names:
        value = getattr(obj, name)
        if not value > 0:
            raise ValueError(f"{name} must be > 0, got {value!r}")


# the longest sim time a run counts: the ROS clock is int64 nanoseconds (292 years). A duration or
# period beyond it (--duration 1e300, a profile step of 1e+300 s) ended in the session node's
# OverflowError traceback once the graph had started
MAX_SIM_TIME_S = 9.2e9

# the plant node's top-level numbers: (kind, minimum); the node reads them with plant_number,
# ./bike run checks a config's with check_plant_numbers before it starts a node
PLANT_NUMBERS = {
    "batch_periods": (int, 1), "control_period_s": (float, 1e-9), "duration_s": (float, 0.0),
    "command_timeout_s": (float, 1e-6), "republish_s": (float, 1e-3), "end_linger_s": (float, 0.0),
    "battery_every": (int, 1), "busy_wait_s": (float, 0.0), "clock_period_s": (float, 0.0),
    "diagnostics_period_s": (float, 1e-3), "recorder_window_batches": (int, 0),
    "recorder_timeout_s": (float, 0.1), "start_timeout_s": (float, 0.0), "seed": (int, 0),
}


# the plant node's default /clock period [sim s] (PLANT_DEFAULTS): check_plant_numbers holds a
# config without clock_period_s to it, as the node does
CLOCK_PERIOD_S = 0.01
# ... and its batch_periods and control_period_s, as check_batch_length takes them
BATCH_PERIODS = 20
CONTROL_PERIOD_S = 5.0e-5


def check_clock_period(clock_period_s: float, session_period_s, path) -> None:
    """clock_period_s at most half of session.period_s (when that is a finite number > 0; the
    session's own check names it otherwise): ConfigError naming clock_period_s. The plant node
    and check_plant_numbers both call it."""
    if isinstance(session_period_s, (int, float)) and not isinstance(session_period_s, bool) \
            and 0 < session_period_s < math.inf and clock_period_s > 0.5 * session_period_s:
        # the session sends its Commands one period ahead of the last /clock it saw; a
        # controller at a later batch would wait for Commands that are not sent yet
        raise ConfigError(f"must be at most half of session.period_s = {session_period_s:g} s, got "
                          f"{clock_period_s:g}", path, "clock_period_s")


def check_batch_length(batch_periods: int, control_period_s: float, session_period_s, path) -> None:
    """One batch (batch_periods x control_period_s) at most half of session.period_s, as
    clock_period_s (check_clock_period): the plant's /clock cannot advance within a batch, so
    a longer batch is a longer clock period; and the controller takes one Command per batch.
    ConfigError naming batch_periods. The plant node and check_plant_numbers both call it."""
    batch_s = batch_periods * control_period_s
    if isinstance(session_period_s, (int, float)) and not isinstance(session_period_s, bool) \
            and 0 < session_period_s < math.inf and batch_s > 0.5 * session_period_s:
        # --set batch_periods=3000 (0.15 s batches, 0.1 s Commands) rode the demo with a third of
        # its Commands never applied: braking power 288 W for 340 W, and no word
        raise ConfigError(f"one batch ({batch_periods} x control_period_s {control_period_s:g} s = {batch_s:g} s) "
                          f"must be at most half of session.period_s = {session_period_s:g} s: the controller "
                          f"takes one Command per batch (at most {int(0.5 * session_period_s / control_period_s)} "
                          "periods here)", path, "batch_periods")


# the loop topics' DDS history [samples] (bike_plant.loop.LOOP_QOS depth): here, where checks
# without rclpy (./bike run's, before it starts a node) read it too
LOOP_HISTORY_DEPTH = 200


def recorder_window_batches(cfg: dict, path) -> int:
    """The plant node's recorder_window_batches, checked: at most half the loop topics' DDS
    history (ConfigError naming it). A sample lost on the transport is repaired from the writer's
    history, so the window must not let the history roll over it."""
    window = plant_number(cfg, "recorder_window_batches", path)
    if window > LOOP_HISTORY_DEPTH // 2:
        raise ConfigError(f"must be at most {LOOP_HISTORY_DEPTH // 2} (half the loop topics' DDS history), "
                          f"got {window}", path, "recorder_window_batches")
    return window


def check_backend_sync_mode(backend: str, sync_mode: str, path) -> None:
    """backend can with sync_mode realtime only: ConfigError naming sync_mode otherwise. The
    plant node's make_backend and ./bike run (with the sync mode the run rides: --ftms makes
    it realtime) both call it."""
    if backend == "can" and sync_mode != "realtime":
        raise ConfigError("backend 'can' drives a real drive in real time: set sync_mode: realtime",
                          path, "sync_mode")


def sync_mode_of(cfg: dict, path) -> str:
    """The config's sync_mode (lockstep when absent), checked: ConfigError naming it. The plant
    and controller nodes and check_plant_numbers take it with this."""
    sync_mode = str(cfg.get("sync_mode", "lockstep"))
    if sync_mode not in ("lockstep", "realtime"):
        raise ConfigError(f"must be 'lockstep' or 'realtime', got {sync_mode!r}", path, "sync_mode")
    return sync_mode


def plant_number(cfg: dict, key: str, path):
    """The plant node's parameter ``key`` (PLANT_NUMBERS), checked; ConfigError naming it."""
    kind, minimum = PLANT_NUMBERS[key]
    return number_param(cfg, key, kind, minimum, path, MAX_SIM_TIME_S if key == "duration_s" else math.inf)


def check_plant_numbers(cfg: dict, path=None) -> None:
    """The plant node's top-level numbers and choices a config gives (absent ones take the
    node's defaults), as the node checks them: ConfigError naming the key. For ./bike run
    before it starts anything (a bad batch_periods was otherwise found by the plant node after
    the graph had started: its error, the other nodes' lines, exit 1)."""
    path = path or cfg.get("_config_path")
    sync_mode = sync_mode_of(cfg, path)
    for key in PLANT_NUMBERS:
        if key in cfg and not (key == "busy_wait_s" and sync_mode != "lockstep"):
            plant_number(cfg, key, path)
    if "recorder_window_batches" in cfg:
        recorder_window_batches(cfg, path)
    clock_period_s = plant_number(cfg, "clock_period_s", path) if "clock_period_s" in cfg else CLOCK_PERIOD_S
    session = cfg.get("session")
    check_clock_period(clock_period_s, session.get("period_s") if isinstance(session, dict) else None, path)
    check_batch_length(plant_number(cfg, "batch_periods", path) if "batch_periods" in cfg else BATCH_PERIODS,
                       plant_number(cfg, "control_period_s", path) if "control_period_s" in cfg else CONTROL_PERIOD_S,
                       session.get("period_s") if isinstance(session, dict) else None, path)
    for key, known in (("machine", ("bldc", "spmsm")), ("backend", ("sim", "can"))):
        if key in cfg and str(cfg[key]) not in known:
            raise ConfigError(f"unknown {key} {cfg[key]!r} ({' | '.join(known)})", path, key)


def number_param(cfg: dict, key: str, kind, minimum, path, maximum=math.inf):
    """A node parameter ``cfg[key]`` that must be a finite number >= ``minimum`` and <= ``maximum``
    (``kind`` int: also a whole number); one ConfigError naming the key otherwise."""
    value = cfg.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"expected a number, got {value!r}", path, key)
    if not math.isfinite(value) or value < minimum:
        raise ConfigError(f"must be finite and >= {minimum}, got {value!r}", path, key)
    if value > maximum:
        raise ConfigError(f"must be at most {maximum:g}, got {value!r}", path, key)
    if kind is int:
        if float(value) != int(value):
            raise ConfigError(f"expected an integer, got {value!r}", path, key)
        return int(value)
    return float(value)
