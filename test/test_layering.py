"""The packages' layering: bike_plant <- bike_controller <- bike_session, declared in each
package.xml (colcon orders the build by it; a cycle could not be declared), and the physics
and control modules import no rclpy (nodes are thin adapters)."""
from __future__ import annotations

import pathlib
import re
import subprocess
import sys
import xml.etree.ElementTree as ET

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
LAYERS = {"bike_plant": set(), "bike_controller": {"bike_plant"}, "bike_session": {"bike_plant", "bike_controller"}}
IMPORT = re.compile(r"^\s*(?:from|import)\s+(bike_[a-z]+)", re.M)


def test_each_package_imports_only_the_layers_below_it_and_declares_them():
    for pkg, below in LAYERS.items():
        imported = set()
        for path in (ROOT / "src" / pkg / pkg).rglob("*.py"):
            for name in IMPORT.findall(path.read_text()):
                if name in LAYERS and name != pkg:
                    imported.add(name)
                    assert name in below, f"{path.relative_to(ROOT)} imports {name}, a package above {pkg}"
        declared = {e.text for e in ET.parse(ROOT / "src" / pkg / "package.xml").getroot().iter("exec_depend")}
        assert imported <= declared, f"{pkg}/package.xml does not declare {sorted(imported - declared)}"


def test_physics_and_control_modules_import_no_rclpy():
    modules = ["bike_plant.bldc", "bike_plant.spmsm", "bike_plant.sim", "bike_plant.params", "bike_plant.mechanics",
               "bike_plant.can.protocol", "bike_controller.bldc_control", "bike_controller.spmsm_control",
               "bike_controller.session_control", "bike_controller.spmsm_session", "bike_controller.modes",
               "bike_controller.closed_loop", "bike_controller.fleet", "bike_controller.drive_emulator",
               "bike_controller.node_params", "bike_controller.drive_torque_map", "bike_plant.can.torque_map",
               "bike_plant.can.backend"]
    code = ("import importlib, sys\n"
            f"for m in {modules!r}: importlib.import_module(m)\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] == 'rclpy'))\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.strip() == "[]", run.stdout


@pytest.mark.parametrize("config", ["bldc_default.yaml", "spmsm_default.yaml"])
def test_the_session_recorder_and_ftms_nodes_load_no_numba(config):
    """Only the plant and the controller run kernels. numba costs a node 0.4 s of CPU and ~60 MB
    when loaded, and the session loads its message conversions when it publishes its first
    Command, which the run's first batch waits for (the plant, the controller and the recorder
    start on the same 2 cores). What those nodes import and call, numba not among it; nor in
    ./bike run's check of the config before it starts them (its process stays up as the
    launcher for the whole run). On the SPMSM bike the mode ranges came from the kernel
    modules' parameter loaders: the session node peaked at 183 MB against the BLDC's 75 MB
    (bike_plant.spmsm_params and bike_controller.spmsm_params hold them now)."""
    code = ("import importlib, sys\n"
            "for m in ('bike_session.session_node', 'bike_session.recorder_node', 'bike_session.ftms_node',\n"
            "          'bike_session.workouts', 'bike_plant.msgconv', 'bike_plant.loop', 'bike_plant.shm_ports'):\n"
            "    importlib.import_module(m)\n"
            "from bike_plant.config import load_config\n"
            "from bike_controller.modes import mode_params_from_config\n"
            "from bike_session.profiles import mode_units_from_config\n"
            "from bike_session.ftms_node import _bike_figures\n"
            f"cfg = load_config({str(ROOT / 'config' / config)!r})\n"
            "mode_params_from_config(cfg), mode_units_from_config(cfg), _bike_figures(cfg['_config_path'])\n"
            "from bike_session import cli\n"
            "cli._check_config(cfg)\n"
            "assert cli._config_profile_ok(cfg, cfg['_config_path'], cfg['_config_path'])\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('numba', 'llvmlite')))\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.strip() == "[]", run.stdout
