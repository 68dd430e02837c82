"""Console entry points of the nodes (setup.py of each package points here).

A node module imports rclpy, numba and its kernels, which takes 1-3 s; a Ctrl-C in that
window (the launcher passes SIGINT to every node) would end the process with a
KeyboardInterrupt traceback from deep in the import machinery. Each entry imports its
module here instead and ends quietly with exit code 130, as a shell reports an interrupted
command. The nodes' own signal handling takes over once their main() runs. Not covered: the
console script's own lines before this module runs (importlib.metadata and the entry-point
lookup, ~0.1 s; longer on a loaded machine), where a Ctrl-C still prints a traceback.

Once main() has returned, the node has shut itself down (executor, node, rclpy context, its
bag or CAN log closed): the process then ends at once with main()'s code (exit_now) instead of
finalising the interpreter, whose final garbage collection (numba / LLVM objects of the loaded
kernels; the SIGUSR1 stacks said "Garbage-collecting") held the end of every run while the
launcher waited for it: at load 10, 2.1 s for the plant after its end of run and 3.2 s for
the controller after its SIGINT."""
from __future__ import annotations

import ctypes
import faulthandler
import importlib
import os
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
        code = getattr(importlib.import_module(module), func)()
    except KeyboardInterrupt:
        sys.exit(130)
    exit_now(code)


def exit_now(code) -> None:
    """End the process with ``code`` (as sys.exit takes it: None is 0) without finalising the
    interpreter: Python's and C's buffered output is flushed first; atexit handlers, object
    finalizers and the final garbage collection do not run. Only for a process whose work is
    done and closed (see the module's docstring): nothing of the nodes' runs on them."""
    for stream in (sys.stdout, sys.stderr):
        try:
            if stream is not None:
                stream.flush()
        except (OSError, ValueError):          # a closed pipe or stream: nothing more to say
            pass
    try:
        ctypes.CDLL(None).fflush(None)         # C's stdio buffers (rcutils, Fast DDS) too
    except (OSError, AttributeError):
        pass
    os._exit(code if isinstance(code, int) else 0 if code is None else 1)


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
