"""The loop nodes compile (or load) their numba kernels before they join the graph.

Before, the plant compiled its batch kernel after publishing seq 0 and the controller its law
at its first PlantState: on a fresh install the demo's first batch waited ~37 s and the
controller reported a stopped plant. Here: after the warm-up, the node's real per-batch path
(a DriveCommand through the CDR view into the plant; a PlantState of a running plant into the
law, in every mode) finds every signature compiled: no dispatcher gains one."""
from __future__ import annotations

import copy
import pathlib
import sys
import time

import numpy as np
import pytest
from numba.core.registry import CPUDispatcher

from bike_plant import msgconv
from bike_plant.config import load_config
from bike_plant.node import make_backend, warm_up_kernels

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _signatures() -> dict:
    """{dispatcher name: number of compiled signatures} over the project's loaded modules."""
    out = {}
    for name, mod in list(sys.modules.items()):
        if name.split(".")[0] in ("bike_plant", "bike_controller", "bike_session"):
            for attr, obj in list(vars(mod).items()):
                if isinstance(obj, CPUDispatcher):
                    out[f"{name}.{attr}"] = len(obj.signatures)
    return out


def _grown(before: dict) -> dict:
    after = _signatures()
    return {k: (before.get(k, 0), v) for k, v in after.items() if v > before.get(k, 0)}


def _in_fresh_process(check: str, config: str) -> None:
    """Run ``check(config)`` of this module in a new interpreter: in the test session other
    tests have compiled (loaded) most signatures already, and a gap would go unseen."""
    import subprocess
    code = f"import sys; sys.path.insert(0, {str(ROOT / 'test')!r}); import test_warm_up as t; t.{check}({config!r})"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-4000:]


@pytest.mark.parametrize("config", ["bldc_default.yaml", "spmsm_default.yaml"])
def test_plant_warm_up_covers_the_batch_path(config):
    _in_fresh_process("check_plant", config)


@pytest.mark.parametrize("config", ["bldc_default.yaml", "spmsm_default.yaml", "bldc_can.yaml", "spmsm_can.yaml"])
def test_controller_warm_up_covers_every_mode(config):
    _in_fresh_process("check_controller", config)


def check_plant(config):
    cfg = load_config(ROOT / "config" / config)
    n = int(cfg["batch_periods"])
    backend = make_backend("sim", cfg, 0)
    start = copy.deepcopy(backend.snapshot())
    backend.warm_up(n)
    after = backend.snapshot()
    assert after.keys() == start.keys() and all(np.array_equal(np.asarray(after[k]), np.asarray(start[k]))
                                                for k in start), "the warm-up runs on a copy: the plant has not moved"
    before = _signatures()
    if cfg.get("machine") == "spmsm":
        raw = msgconv.spmsm_drive_cdr(1, np.tile(np.float32([0.6, 0.4, 0.5]), (n, 1)), np.zeros(n, np.float32),
                                      np.ones(n, np.float32), 0)
    else:
        raw = msgconv.drive_command_cdr(1, np.full(n, 0b100001, np.uint8), np.full(n, 0b000110, np.uint8),
                                        np.full(n, 0.3, np.float32), 0)
    view = msgconv.DriveCommandView(raw)
    assert backend.problem(view, n) is None
    for held in (False, False, True, True):        # fresh, fresh, held twice (realtime)
        backend.apply(view, held=held)
    backend.safe_batch(n)
    backend.snapshot()
    assert backend.time_s > 0
    assert not _grown(before), f"compiled during the run: {_grown(before)}"


def check_controller(config):
    from bike_controller.modes import MODE_NAMES
    from bike_controller.node import warm_up_law
    from bike_plant.params import nominal_params_from_config

    cfg = load_config(ROOT / "config" / config)
    if cfg.get("machine") == "spmsm":
        from bike_controller.spmsm_session import ModedSpmsmController
        make_law = lambda: ModedSpmsmController(cfg)  # noqa: E731
    else:
        from bike_controller.session_control import ModedController
        make_law = lambda: ModedController(cfg, nominal_params_from_config(cfg))  # noqa: E731
    can = cfg.get("backend") == "can"
    n = make_law().batch_periods
    warm_up_law(make_law, cfg, str(cfg.get("machine", "bldc")), n)
    before = _signatures()
    # a running plant's states, as the node gets them, answered in each mode
    backend = make_backend("sim", cfg, 0)
    law = make_law()
    build = msgconv.spmsm_drive_cdr if cfg.get("machine") == "spmsm" else msgconv.drive_command_cdr
    for k, mode in enumerate(sorted(MODE_NAMES) * 3):
        try:
            law.set_command(0.7, mode)
        except ValueError:
            continue
        snap = backend.snapshot()
        snap.update(seq=k, batch_periods=n, backend="sim", measured_by_drive=can, end_of_run=False)
        stamp = msgconv.seconds_to_ns(backend.time_s)
        view = msgconv.PlantStateView(msgconv.plant_state_cdr(snap, stamp))
        a, b, c, status = law.decide(dict(view.snap, stamp_ns=stamp), n)
        assert not can or status["prediction_error_a"] == 0.0, "a drive on CAN: the torque-only answer"
        drive = msgconv.DriveCommandView(build(k, a, b, c, stamp, float(status.get("torque_cmd_nm", 0.0))))
        if backend.problem(drive, n) is None:
            backend.apply(drive)
        else:
            backend.safe_batch(n)
    assert backend.time_s > 0
    assert not _grown(before), f"compiled during the run: {_grown(before)}"


class ListLog:
    """A node logger that keeps its lines (warnings prefixed WARN)."""

    def __init__(self):
        self.lines = []

    def info(self, text):
        self.lines.append(text)

    def warning(self, text):
        self.lines.append("WARN " + text)


def test_warm_up_log_says_how_long_and_a_slow_one_says_why():
    import time

    log = ListLog()
    lines = log.lines

    took = warm_up_kernels(log, lambda: None)
    # (and, where this process had LLVM's pages mapped, how much of them it dropped: bike_plant.memory)
    assert took < 1.0 and len(lines) == 1 and lines[0].startswith(f"numba kernels ready in {took:.1f} s"), lines
    lines.clear()
    warm_up_kernels(log, lambda: time.sleep(2.3))
    assert lines[0].startswith("compiling the numba kernels") and lines[1].startswith("numba kernels ready in 2.")
    # a failing warm-up is said once and does not stop the node
    lines.clear()
    warm_up_kernels(log, lambda: 1 / 0)
    assert lines == ["WARN numba kernel warm-up failed (ZeroDivisionError: division by zero): they compile at "
                     "first use"]


def _sigint_after(delay_s: float):
    """A real SIGINT to this process after delay_s (the kernel picks the thread that takes it)."""
    import os
    import signal
    import threading

    timer = threading.Timer(delay_s, os.kill, (os.getpid(), signal.SIGINT))
    timer.daemon = True
    timer.start()
    return timer


def test_a_ctrl_c_during_the_compile_stops_the_node_and_never_lands_inside_the_compile(capsys):
    """CI, Python 3.12: a SIGINT that landed in llvmlite's ctypes object-cache callback was
    printed as "Exception ignored ... KeyboardInterrupt" and swallowed; numba then failed or
    compiled on for tens of seconds. Now the compile runs in a worker thread: a real SIGINT
    during it raises KeyboardInterrupt in the waiting main thread at once, and the compile
    (here a loop through a real ctypes callback) is never interrupted."""
    import ctypes
    import threading

    steps = []
    callback = ctypes.CFUNCTYPE(None)(lambda: steps.append(threading.current_thread().name))
    done = threading.Event()

    def compile_through_callbacks():
        for _ in range(100):          # ~1 s
            callback()
            time.sleep(0.01)
        done.set()

    log = ListLog()
    _sigint_after(0.3)
    with pytest.raises(KeyboardInterrupt):
        warm_up_kernels(log, compile_through_callbacks)
    # stopped while the compile still ran (an ordering, not a wall-clock bound: before, the
    # warm-up returned only after its compile)
    assert not done.is_set() and 0 < len(steps) < 100, len(steps)
    assert log.lines == []
    # the compile went on, undisturbed, in its own thread, to its end
    assert done.wait(5.0) and len(steps) == 100 and set(steps) == {"numba-warm-up"}
    err = capsys.readouterr().err
    assert "Exception ignored" not in err and "Traceback" not in err, err
    # the main thread still takes Ctrl-C as before once the warm-up is over
    log = ListLog()
    warm_up_kernels(log, lambda: None)
    assert log.lines[0].startswith("numba kernels ready")


def test_a_node_interrupted_in_its_warm_up_exits_without_waiting_for_the_compile(tmp_path):
    """run_loop_node's exit after a Ctrl-C in the warm-up: the process ends with its code at
    once (exit_if_a_warm_up_is_left), not when the abandoned compile would have finished."""
    import subprocess

    script = tmp_path / "node.py"
    script.write_text(
        "import os, signal, sys, threading, time\n"
        "from bike_plant.node import exit_if_a_warm_up_is_left, warm_up_kernels\n"
        "class Log:\n"
        "    def info(self, text): print(text, flush=True)\n"
        "    warning = info\n"
        "threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT)).start()\n"
        "try:\n"
        "    warm_up_kernels(Log(), lambda: time.sleep(30))\n"
        "except KeyboardInterrupt:\n"
        "    print('interrupted', flush=True)\n"
        "exit_if_a_warm_up_is_left(7)\n"
        "print('not reached')\n")
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60)
    took_s = time.perf_counter() - t0
    assert out.returncode == 7 and out.stdout.strip() == "interrupted", (out.returncode, out.stdout, out.stderr)
    assert "Traceback" not in out.stderr, out.stderr
    assert took_s < 20.0, took_s               # the 30 s warm-up was not waited for
