"""Console entry points of the nodes (setup.py of each package points here).

A node module imports rclpy, numba and its kernels, which takes 1-3 s; a Ctrl-C in that
window (the launcher passes SIGINT to every node) would end the process with a
KeyboardInterrupt traceback from deep in the import machinery. Each entry imports its
module here instead and ends quietly with exit code 130, as a shell reports an interrupted
command. The nodes' own signal handling takes over once their main() runs. Not covered: the
console script's own lines before this module runs (importlib.metadata and the entry-point
lookup, ~0.1 s; longer on a loaded machine), where a Ctrl-C still prints a traceback."""
from __future__ import annotations

import faulthandler
import importlib
import signal
import sys


def start(module: str, func: str = "main"):
    """Import ``module`` and run its ``func``; a KeyboardInterrupt that escapes either is
    exit code 130 without a traceback.

    ``kill -USR1 <pid>`` prints every thread's Python stack to the node's stderr and the node
    runs on: the way to see where a node that went quiet is (blocked, or spinning with nothing
    delivered). Registered before the import, so a hang in it shows too."""
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    try:
        return getattr(importlib.import_module(module), func)()
    except KeyboardInterrupt:
        sys.exit(130)


def plant_node():
    return start("bike_plant.node")


def drive_emulator():
    return start("bike_controller.drive_emulator")


def controller_node():
    return start("bike_controller.node")


def session_node():
    return start("bike_session.session_node")


def recorder_node():
    return start("bike_session.recorder_node")


def ftms_node():
    return start("bike_session.ftms_node")
