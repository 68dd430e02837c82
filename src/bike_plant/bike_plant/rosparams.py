"""Declare a node's parameters from a config dict and read them back as one (rclpy helper).

How a node gets its configuration (docs/DESIGN.md, Configuration):

1. The node is started with ``--params-file CONFIG.yaml`` (and maybe ``-p name:=value``).
   rclpy keeps those values as *parameter overrides*; nothing is declared yet.
2. :func:`declare_config` declares ``config_path`` (string, default ``""``). If it is set
   (the launch file sets it), that file is the node's *base config*; otherwise the
   repository's default bike (:func:`bike_plant.config.default_config_path`) is. The base
   config is read with :func:`bike_plant.config.load_config` (validated, node-specific
   sections merged) and gives every parameter its default value and description.
3. Every parameter of the base config (``flatten``: nested keys -> dotted names), every
   node-specific extra (``extra_defaults``) and every override the node was started with
   is declared with a :class:`ParameterDescriptor` (read-only: the nodes build their
   models once at start-up and do not react to later changes). An override wins over the
   default, with its own type (``-p duration_s:=1`` gives an integer; the dataclass
   builders accept integers for floats).
4. :func:`read_config` reads all of them back into the nested dict (``unflatten``) that
   ``plant_params_from_config`` / ``BatchController`` take, with ``_config_path`` set.

We do not use ``automatically_declare_parameters_from_overrides=True``: a parameter file
with an empty list (``schedule_time_s: []``) yields an override of type NOT_SET, which
rclpy refuses to auto-declare. Such parameters are declared with ``dynamic_typing`` and
read back as ``[]``.

No ROS import at module level other than rclpy's parameter types, so the module can be
imported by tools that only inspect the parameter list.
"""
from __future__ import annotations

import array
import math
from typing import Any, Mapping

from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from rclpy.parameter import Parameter

from .config import ConfigError, default_config_path, flatten, load_config, unflatten

CONFIG_PATH_PARAM = "config_path"
# parameters rclpy declares itself or that are not configuration
_ROS_OWNED_PREFIXES = ("qos_overrides.",)
_ROS_OWNED = {"use_sim_time", "start_type_description_service", CONFIG_PATH_PARAM}

DESCRIPTIONS = {
    "machine": "machine model: bldc",
    "sync_mode": "lockstep (plant owns /clock, waits for each DriveCommand; deterministic) | realtime (wall-clock batches)",
    "batch_periods": "N control periods per plant <-> controller exchange",
    "control_period_s": "one control period [s] (50 us for the BLDC bike)",
    "command_timeout_s": "realtime: no DriveCommand for this long [wall s] -> safe state + FAULT_COMMAND_TIMEOUT",
    "duration_s": "simulated seconds of a run; 0 = run until stopped",
    "backend": "plant backend: sim (numba model) | can (a drive over CAN: ODrive CANSimple 0.6, realtime only)",
    "seed": "random seed of the simulated plant",
    "command_wait_s": "lockstep: wall seconds to wait for the Command of a batch before proceeding without it",
    "session.period_s": "Command publishing period of the session [sim s]",
}

_TYPE_NAMES = {
    ParameterType.PARAMETER_BOOL: "bool",
    ParameterType.PARAMETER_INTEGER: "integer",
    ParameterType.PARAMETER_DOUBLE: "double",
    ParameterType.PARAMETER_STRING: "string",
    ParameterType.PARAMETER_BOOL_ARRAY: "bool[]",
    ParameterType.PARAMETER_INTEGER_ARRAY: "integer[]",
    ParameterType.PARAMETER_DOUBLE_ARRAY: "double[]",
    ParameterType.PARAMETER_STRING_ARRAY: "string[]",
}


def _ros_value(value: Any, key: str, path: str | None):
    """A config value as a ROS parameter value (None: not representable statically)."""
    if value is None:
        return None
    if isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (list, tuple)):
        items = list(value)
        if not items:
            return None
        if all(isinstance(v, bool) for v in items):
            return items
        if all(isinstance(v, str) for v in items):
            return items
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in items):
            if all(isinstance(v, int) for v in items):
                return items
            return [float(v) for v in items]       # [1, 2.5] -> a double array
        raise ConfigError(f"a list parameter must hold one type (numbers, strings or booleans), got {items!r}", path, key)
    raise ConfigError(f"unsupported parameter value {value!r}", path, key)


def _plain(value: Any) -> Any:
    """A parameter value as plain Python (arrays -> lists)."""
    if isinstance(value, array.array):
        return value.tolist()
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
        return value.tolist()
    if isinstance(value, tuple):
        return list(value)
    return value


def base_config(node) -> dict:
    """The config that gives the node's parameters their defaults (see module doc)."""
    if not node.has_parameter(CONFIG_PATH_PARAM):
        node.declare_parameter(CONFIG_PATH_PARAM, "", ParameterDescriptor(
            type=ParameterType.PARAMETER_STRING, read_only=True,
            description="config file (ROS 2 parameter file) giving the defaults of every parameter; "
                        "empty: the repository's config/bldc_default.yaml"))
    path = node.get_parameter(CONFIG_PATH_PARAM).value or ""
    if path:
        return load_config(path, node_name=node.get_name())
    try:
        default = default_config_path()
    except ConfigError:
        return {}
    return load_config(default, node_name=node.get_name())


def declare_config(node, extra_defaults: Mapping[str, Any] | None = None,
                   descriptions: Mapping[str, str] | None = None) -> dict:
    """Declare every parameter of ``node`` (see module doc) and return the nested config.

    ``extra_defaults``: node parameters that may be absent from the config file
    (flat dotted names or nested), e.g. ``{"command_wait_s": 2.0}``.
    Raises ConfigError for a value that cannot be a ROS parameter.
    """
    base = base_config(node)
    path = base.get("_config_path")
    flat = flatten(base)
    for name, value in flatten(dict(extra_defaults or {})).items():
        flat.setdefault(name, value)
    texts = dict(DESCRIPTIONS)
    texts.update(descriptions or {})
    overrides = dict(getattr(node, "_parameter_overrides", {}) or {})
    names = set(flat) | set(overrides)
    for name in sorted(names):
        if name in _ROS_OWNED or name.startswith(_ROS_OWNED_PREFIXES) or node.has_parameter(name):
            continue
        default = flat.get(name)
        text = texts.get(name, f"config parameter (default from {path or 'the node'})")
        if name in overrides:
            value = overrides[name].value
            source = "override"
        else:
            value = _ros_value(default, name, path)
            source = "default"
        if value is None:
            # empty list / null: no static type; a later value may have any type
            node.declare_parameter(name, None, ParameterDescriptor(
                dynamic_typing=True, read_only=True, description=text + " (empty)"))
            continue
        ptype = Parameter.Type.from_parameter_value(value).value
        descriptor = ParameterDescriptor(type=ptype, read_only=True,
                                         description=f"{text} [{_TYPE_NAMES.get(ptype, '?')}, {source}]")
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"must be finite, got {value!r}", path, name)
        node.declare_parameter(name, value, descriptor)
    return read_config(node, flat_defaults=flat, config_path=path)


def read_config(node, flat_defaults: Mapping[str, Any] | None = None, config_path: str | None = None) -> dict:
    """All declared configuration parameters of ``node`` as a nested dict (``unflatten``)."""
    flat_defaults = flat_defaults or {}
    values: dict[str, Any] = {}
    for name, param in node.get_parameters_by_prefix("").items():
        if name in (CONFIG_PATH_PARAM, "start_type_description_service") or name.startswith(_ROS_OWNED_PREFIXES):
            continue
        value = _plain(param.value)
        if value is None:
            default = flat_defaults.get(name)
            value = [] if isinstance(default, (list, tuple)) or default is None else default
        values[name] = value
    cfg = unflatten(values)
    if config_path:
        cfg["_config_path"] = config_path
    return cfg


def parameter_table(node) -> list[tuple[str, str, Any]]:
    """(name, description, value) of every declared parameter, sorted (docs, --help)."""
    rows = []
    for name, param in sorted(node.get_parameters_by_prefix("").items()):
        desc = node.describe_parameter(name)
        rows.append((name, desc.description, _plain(param.value)))
    return rows
