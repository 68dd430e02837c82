"""Config files: ROS 2 parameter-file format, read without ROS, with clear errors."""
import dataclasses
import math

import pytest

from bike_plant.config import ConfigError, build_dataclass, flatten, load_config, unflatten

from conftest import DEFAULT_CONFIG, ros_parameters_of


def test_default_config_loads_with_the_lockstep_defaults():
    cfg = load_config(DEFAULT_CONFIG)
    assert cfg["machine"] == "bldc"
    assert cfg["sync_mode"] == "lockstep"
    assert cfg["batch_periods"] == 20
    assert cfg["control_period_s"] == pytest.approx(50e-6)
    assert cfg["_config_path"].endswith("bldc_default.yaml")


def test_node_section_overrides_the_wildcard(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("/**:\n  ros__parameters:\n    a: 1\n    s: {x: 1, y: 2}\n"
                    "/**/plant:\n  ros__parameters:\n    s: {y: 3}\n")
    assert load_config(path, "plant")["s"] == {"x": 1, "y": 3}
    assert load_config(path)["s"] == {"x": 1, "y": 2}


def test_flatten_roundtrip():
    nested = {"a": 1, "b": {"c": 2.5, "d": {"e": [1, 2]}}, "_private": 0}
    flat = flatten(nested)
    assert flat == {"a": 1, "b.c": 2.5, "b.d.e": [1, 2]}
    assert unflatten(flat) == {"a": 1, "b": {"c": 2.5, "d": {"e": [1, 2]}}}


@pytest.mark.parametrize("text, message", [
    ("a: [", "not valid YAML at line 1"),
    ("- 1\n- 2\n", "expected a mapping"),
    ("/**:\n  x: 1\n", "'ros__parameters' mapping"),
    ("plant:\n  ros__parameters: {}\n", "no '/\\*\\*: ros__parameters:' section"),
    ("!!python/object/apply:os.system ['true']", "not valid YAML"),
    # PyYAML's constructors recurse per level: a RecursionError traceback before
    ("/**:\n  ros__parameters:\n    a: " + "[" * 2000 + "]" * 2000 + "\n", "nested too deeply"),
    # a control character: PyYAML's own text is two lines ('  in "<unicode string>", position 41')
    ("/**:\n  ros__parameters:\n    machine: bldc\x01\n",
     r"not valid YAML at line 3, column 18: unacceptable character #x0001 \(special characters are not allowed\)$"),
])
def test_malformed_config_names_the_file_and_problem(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message) as info:
        load_config(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("value, message", [
    ("[0.8, 1]", r"controller.k_factor: a list parameter holds one type, got decimal and integer .*e.g. 1.0"),
    ("[1, 'a']", r"controller.k_factor: a list parameter holds one type, got integer and text"),
    ("[[0.8], [1.0]]", r"controller.k_factor: a list parameter holds numbers, text or true/false, not \[0.8\]"),
    ("[0, 100000000000000000000]", r"controller.k_factor: integer 100000000000000000000 outside the 64-bit range"),
    # rcl types unquoted scalars itself (parse.c get_value): text to yaml.safe_load, a number or
    # true/false to rcl ([--watchdog-s, nan] passed the checks, then every node refused the mixed list)
    ("[--watchdog-s, nan]", r"controller.k_factor: unquoted 'nan' \(line 4\) is text to this config's loader "
                            r"but decimal to ROS 2's parameter parser \(the nodes'\): quote it"),
    ("[a, y]", r"controller.k_factor: unquoted 'y' .* is text .* but true/false to ROS 2's"),
    ("1e5", r"controller.k_factor: unquoted '1e5' .* is text .* but decimal .* \(1.0e\+5\)"),
    ("1.0e5", r"unquoted '1.0e5' .* is text .* but decimal"),
    ("09", r"unquoted '09' .* is text .* but decimal"),
    # the other way: a number or null to yaml.safe_load, text to rcl
    ("1_000", r"unquoted '1_000' .* is integer to this config's loader but text"),
    ("0b11", r"unquoted '0b11' .* is integer .* but text"),
    ("1.0e+400", r"unquoted '1.0e\+400' .* is decimal .* but text"),
    ("2001-12-14", r"unquoted '2001-12-14' .* is date .* but text"),
    ("~", r"unquoted '~' .* is null .* but text"),
    ("", r"controller.k_factor: no value \(line 4\): ROS 2's parameter parser refuses an empty value"),
])
def test_a_value_the_ros_parameter_parser_refuses_or_types_otherwise_is_one_error(tmp_path, value, message):
    # every node gets the file as --params-file: rcl refused a mixed list at start, a traceback per node
    path = tmp_path / "c.yaml"
    path.write_text(f"/**:\n  ros__parameters:\n    controller:\n      k_factor: {value}\n")
    with pytest.raises(ConfigError, match=message) as info:
        load_config(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_quoted_scalars_and_plain_numbers_are_taken(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("/**:\n  ros__parameters:\n    a: [--watchdog-s, 'nan']\n    b: \"y\"\n    c: 1.0e+5\n"
                    "    d: 0x1F\n    e: [1, 2]\n    f: on\n    g: .inf\n    h: 'x'\n")
    cfg = load_config(path)
    assert cfg["a"] == ["--watchdog-s", "nan"] and cfg["b"] == "y" and cfg["c"] == 1e5 and cfg["d"] == 31
    assert cfg["f"] is True and cfg["g"] == float("inf")


@pytest.mark.parametrize("value, text, back", [
    (1e-05, "1.0e-05", 1e-05), (1e+16, "1.0e+16", 1e+16), (-2.5e-300, "-2.5e-300", -2.5e-300), (0.1, "0.1", 0.1),
    (3.0, "3.0", 3.0), (float("inf"), ".inf", float("inf")), (-float("inf"), "-.inf", -float("inf")),
    (5e-324, "0.0", 0.0),           # a subnormal: a range error to C's strtod (text to rcl)
])
def test_yaml_float_is_the_same_number_to_the_loader_and_rcl(value, text, back):
    """repr's 1e-05 is text to yaml.safe_load and a number to rcl: a config holding it is refused."""
    import numpy as np

    from bike_plant.config import parse_yaml_text, rcl_scalar_kind, yaml_float
    assert yaml_float(value) == text == yaml_float(np.float64(value))
    assert parse_yaml_text(text) == back and rcl_scalar_kind(text) == "decimal"
    nan = yaml_float(float("nan"))
    assert math.isnan(parse_yaml_text(nan)) and rcl_scalar_kind(nan) == "decimal"


def test_rcl_reads_the_types_the_loader_reads_from_a_written_params_file(tmp_path):
    """dump_ros_params quotes the text rcl would type (nan, y, 1e5, 09): a real rclpy node started
    with the file gets the values load_config reads."""
    from bike_plant.config import dump_ros_params, rcl_scalar_kind
    params = {"a": ["--watchdog-s", "nan"], "b": "y", "c": "1e5", "d": "09", "e": "on", "f": "x", "g": 1e5,
              "h": float("inf"), "i": 3, "j": True, "k": [1.5, 2.0], "l": "1:30", "m": "0x10", "n": 1e-05,
              "o": [2.5e+20, -3e-300]}
    path = tmp_path / "p.yaml"
    path.write_text(dump_ros_params({"/**": {"ros__parameters": params}}, sort_keys=False))
    assert rcl_scalar_kind("nan") == "decimal" and rcl_scalar_kind("y") == "true/false"
    assert load_config(path)["a"] == params["a"]
    assert ros_parameters_of(["--ros-args", "--params-file", str(path)], params) == params


def test_missing_and_binary_files(tmp_path):
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(tmp_path)           # a folder: IsADirectoryError, a traceback of ./bike run --config DIR
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(tmp_path / "nope.yaml")
    binary = tmp_path / "bin.yaml"
    binary.write_bytes(b"\xff\xfe\x00\x01" * 10)
    with pytest.raises(ConfigError):
        load_config(binary)


@dataclasses.dataclass
class Example:
    r_ohm: float = 1.0
    n: int = 2
    on: bool = False
    name: str = "x"
    table: list = dataclasses.field(default_factory=lambda: [1.0])

    def validate(self):
        if self.r_ohm <= 0:
            raise ValueError(f"r_ohm must be > 0, got {self.r_ohm}")


def test_build_dataclass_checks_types_ranges_and_unknown_keys():
    obj = build_dataclass(Example, {"r_ohm": 2, "n": 3.0, "table": [1, 2]}, "ex")
    assert obj.r_ohm == 2.0 and isinstance(obj.r_ohm, float) and obj.n == 3 and obj.table == [1, 2]
    for values, message in [({"r_ohm": "a"}, "ex.r_ohm: expected a number"),
                            ({"r_ohm": float("nan")}, "must be finite"),
                            ({"n": 2.5}, "expected an integer"),
                            ({"on": 1}, "expected true/false"),
                            ({"r_hom": 1.0}, "unknown parameter\\(s\\) r_hom"),
                            ({"r_ohm": -1.0}, "r_ohm must be > 0"),
                            ({"table": [1, float("inf")]}, "finite")]:
        with pytest.raises(ConfigError, match=message):
            build_dataclass(Example, values, "ex")


@pytest.mark.parametrize("values, message", [
    ({"kind": "rider", "rider_effort0": 1.5}, "rider_effort0 must be in"),
    ({"kind": "rider", "rider_t0_nm": 0.0}, "rider_t0_nm"),
    ({"schedule_time_s": [0.0, "x"], "schedule_speed_rpm": [1.0, 2.0]}, "schedule_time_s entries must be numbers"),
    ({"schedule_time_s": [1.0, 0.0], "schedule_speed_rpm": [1.0, 2.0]}, "schedule_time_s must be increasing"),
    ({"schedule_time_s": [0.0], "schedule_speed_rpm": []}, "same length"),
    ({"gear_ratio": -1.0}, "gear_ratio"),
])
def test_both_machines_check_the_shared_load_fields_alike(values, message):
    """The rider, gear and prime-mover schedule are one dataclass (params.ShaftLoadParams)
    under both machines' load sections: the same bad value, the same one error."""
    from bike_plant.params import LoadParams
    from bike_plant.spmsm import SpmsmLoadParams

    for cls in (LoadParams, SpmsmLoadParams):
        with pytest.raises(ConfigError, match=message):
            build_dataclass(cls, values, "load")


@pytest.mark.parametrize("values", [
    {"v_empty_v": 30.0, "v_full_v": 42.0},                    # a 36 V pack with the 48 V pack's S0 (54.65 / 54.62 V)
    {"v_empty_v": 60.0, "v_full_v": 84.0, "s0_on_v": 60.0, "s0_off_v": 59.0},   # S0 at the empty pack's voltage
    {"s0_on_v": 54.6, "s0_off_v": 54.0},                      # the old release, below a pack's OCV above SOC 0.95
    {"s0_on_v": 54.65, "s0_off_v": 54.6},                     # release at the full pack's OCV itself
    {"s0_on_v": 54.7, "s0_off_v": 54.62},                     # on above the OCV at SOC 1.005: 54.663 V
])
def test_the_brake_resistor_switch_must_lie_just_above_the_full_pack(values):
    """A 36 V pack whose S0 thresholds stayed at the 48 V pack's: S0 never closed, and the
    demo charged a full pack to SOC 1.2 without a fault. A release voltage at or below the
    full pack's OCV (54.0 V on the 54.6 V pack): the resistor drained a nearly full pack
    (test_faults_kernel). One error naming both thresholds and their range instead."""
    from bike_plant.params import BatteryParams

    with pytest.raises(ConfigError, match=r"battery: s0_off_v and s0_on_v .*must lie above v_full_v, the full "
                                          r"pack's open-circuit voltage.*< s0_off_v < s0_on_v <= "):
        build_dataclass(BatteryParams, values, "battery")
    build_dataclass(BatteryParams, {"v_empty_v": 30.0, "v_full_v": 42.0, "s0_on_v": 42.05, "s0_off_v": 42.02},
                    "battery")
    build_dataclass(BatteryParams, {}, "battery")      # the defaults, as config/bldc_*.yaml


def test_an_overvoltage_threshold_at_the_packs_own_voltage_is_refused():
    """The BLDC's DC bus is its pack (no link voltage of its own): bldc.overvoltage_v at or below
    battery.s0_on_v, the top of the healthy bus while braking, loaded, and 50 V on the 48 V pack
    set FAULT_OVERVOLTAGE at rest (the bus 50.8 V at SOC 0.7). One error naming both keys."""
    from bike_plant.config import config_variant
    from bike_plant.node import SimBackend
    from bike_plant.params import plant_params_from_config

    cfg = load_config(DEFAULT_CONFIG)
    for volts in (50.0, 54.65):
        with pytest.raises(ConfigError, match=rf"bldc\.overvoltage_v: {volts:g} V is at or below battery\.s0_on_v "
                                              r"54\.65 V: the DC bus is the pack \(42\.\.54\.6 V"):
            plant_params_from_config(config_variant(cfg, bldc={"overvoltage_v": volts}))
        with pytest.raises(ConfigError, match=r"bldc\.overvoltage_v"):
            SimBackend(config_variant(cfg, bldc={"overvoltage_v": volts}), 0)
    just_above = SimBackend(config_variant(cfg, bldc={"overvoltage_v": 54.7}), 0)
    just_above.safe_batch(20)
    assert just_above.snapshot()["faults"] == 0


def test_a_back_emf_above_the_pack_at_the_ridden_speed_is_refused():
    """4 x the default ke on the 48 V pack: 61 V line-to-line at the rider's 80 rpm x 35, above
    the pack, so the bridge diodes braked 10 N m for 1.2 N m asked, and the summary said no
    fault, 0 % saturated. One error naming bldc.ke_v_per_rpm; 2 x ke (30.5 V) still rides."""
    from bike_plant.config import config_variant
    from bike_plant.params import plant_params_from_config

    cfg = load_config(DEFAULT_CONFIG)
    with pytest.raises(ConfigError, match=r"bldc.ke_v_per_rpm: 0.0218 V/rpm gives a line-to-line back-EMF of "
                                          r"61.0 V at 2800 motor rpm .* empty pack's 42 V"):
        plant_params_from_config(config_variant(cfg, bldc={"ke_v_per_rpm": 21.8e-3}))
    with pytest.raises(ConfigError, match=r"bldc.ke_v_per_rpm: .* at 9000 motor rpm \(load.speed_rpm\)"):
        plant_params_from_config(config_variant(cfg, load={"kind": "prime_mover", "speed_rpm": 9000.0}))
    plant_params_from_config(config_variant(cfg, bldc={"ke_v_per_rpm": 10.9e-3}))
