"""The controller node's own numbers (its loop's, not the control law's: bldc_params,
spmsm_control), checked without ROS: the node reads them with controller_node_numbers, and
./bike run checks a config's with it before it starts a node (the node found a bad
command_wait_s once the graph had started: its error among the other nodes' lines, exit 1)."""
from __future__ import annotations

import math

from bike_plant.config import ConfigError, number_param

# the node's numbers that must be > 0 (the busy wait may be 0: block at once)
POSITIVE_KEYS = ("command_wait_s", "session.period_s", "diagnostics_period_s")


def positive_number(value, key: str, path) -> float:
    """``value`` as a finite number > 0; ConfigError naming ``key`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ConfigError(f"must be a number > 0, got {value!r}", path, key)
    return float(value)


def controller_node_numbers(cfg: dict, path=None) -> dict[str, float]:
    """The controller node's numbers a config gives (the node's own config has them all, its
    defaults declared), checked as the node takes them: {key: value}; ConfigError naming the
    first bad one. busy_wait_s is checked in realtime too, where the plant does not read it."""
    path = path or cfg.get("_config_path")
    numbers = {}
    for key in POSITIVE_KEYS:
        head, _dot, leaf = key.rpartition(".")
        holder = cfg.get(head) if head else cfg
        if isinstance(holder, dict) and leaf in holder:
            numbers[key] = positive_number(holder[leaf], key, path)
        elif head and holder is not None and not isinstance(holder, dict):
            raise ConfigError(f"expected a mapping, got {holder!r}", path, head)
    if "busy_wait_s" in cfg:
        numbers["busy_wait_s"] = number_param(cfg, "busy_wait_s", float, 0.0, path)
    return numbers
