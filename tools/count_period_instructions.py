"""Instructions per control period of the fused BLDC inner loop (bike_controller.bldc_control.run_fused),
or with ``--machine spmsm`` of the SPMSM one (bike_controller.spmsm_control.run_kernel: plant,
average inverter, + predictive controller, the benchmark's 200 r/min prime mover).

The VM this project is benchmarked on has no hardware performance counters (``perf stat``
reports none), and the loop is bound by instruction count: this counts the instructions of
``periods`` periods exactly, by single-stepping them under gdb, after a warm-up into steady
operation (the benchmark's scenario: 3000 rpm prime mover, command 1). Deterministic, so two
variants of the kernel compare without the noise of a shared machine.

    source tools/env.sh && python tools/count_period_instructions.py [--periods 40] [--machine spmsm]

Needs gdb (Debian: apt-get install gdb). Takes ~30 s for 40 periods.
"""
from __future__ import annotations

import argparse
import os
import pathlib
import subprocess
import sys
import tempfile

WARMUP_PERIODS = 2000


def _publish_and_stop(dispatcher, addr_file: str) -> None:
    import signal
    cres = dispatcher.overloads[dispatcher.signatures[0]]
    pathlib.Path(addr_file).write_text(hex(cres.library.get_pointer_to_function(cres.fndesc.llvm_func_name)))
    os.kill(os.getpid(), signal.SIGTRAP)        # gdb stops here and sets its breakpoint


def _inferior_spmsm(periods: int, addr_file: str) -> None:
    """As _inferior, for the SPMSM kernel in the bench's scenario (bench.spmsm_inner_loop_real_time)."""
    import numpy as np

    from bike_controller import spmsm_control as C
    from bike_plant import spmsm as M
    from bike_plant.config import load_config
    root = pathlib.Path(__file__).resolve().parents[1]
    cfg = load_config(root / "config" / "spmsm_default.yaml")
    cfg["load"] = dict(cfg.get("load") or {}, kind="prime_mover", speed_rpm=200.0)
    params = M.plant_params_from_config(cfg)
    params.inverter.model = "average"
    plant = M.SpmsmPlant(params)
    ctrl = C.SpmsmController(cfg, None, family="predictive")
    ctrl.reset_from(plant.state)
    n = WARMUP_PERIODS + periods + 100
    ns = int(ctrl.q[C.Q_NS])
    n_speed = n // ns + 3
    ref_w = np.full(n_speed, 200.0 / C.RPM_PER_RAD_S)
    tl = np.full(n_speed, np.nan)
    zeros = np.zeros(n_speed)
    rec = np.zeros((n // 1000 + 2, C.N_REC))
    ws = np.zeros(M.WS_SIZE)
    args = (ref_w, tl, zeros, zeros, rec, 1000, ws)
    C.run_kernel(plant.state, plant.p, ctrl.cs, ctrl.q, 0, WARMUP_PERIODS, *args)
    _publish_and_stop(C.run_kernel, addr_file)
    C.run_kernel(plant.state, plant.p, ctrl.cs, ctrl.q, WARMUP_PERIODS, WARMUP_PERIODS + periods, *args)


def _inferior(periods: int, addr_file: str) -> None:
    """The process gdb runs: warm up, publish run_fused's entry address, stop, run `periods`."""

    import numpy as np

    from bike_controller import bldc_control as C
    from bike_session import bench_kernels as B
    cfg = B.load_config(None)
    cfg["load"] = dict(cfg.get("load") or {}, kind="prime_mover", speed_rpm=3000.0)
    p, state, ctrl = B._setup(cfg)
    C.run_fused(state, p, ctrl.cs, ctrl.q, WARMUP_PERIODS, np.zeros((1, 3)), 0, np.zeros(1))
    _publish_and_stop(C.run_fused, addr_file)
    C.run_fused(state, p, ctrl.cs, ctrl.q, periods, np.zeros((1, 3)), 0, np.zeros(1))


def _gdb_script(addr_file: str) -> None:
    """Runs inside gdb: step from run_fused's entry to its return, print the count."""
    import gdb  # noqa: F401  (only inside gdb)
    gdb.execute("set pagination off")
    gdb.execute("run")
    gdb.execute("break *%d" % int(pathlib.Path(addr_file).read_text(), 16))
    gdb.execute("continue")
    ret = int(gdb.parse_and_eval("*(unsigned long*)$sp"))
    n = 0
    while True:
        gdb.execute("stepi", to_string=True)
        n += 1
        if int(gdb.parse_and_eval("$pc")) == ret:
            break
    print(f"INSTRUCTIONS {n}")
    gdb.execute("kill")


def _count(periods: int, machine: str = "bldc") -> int:
    with tempfile.TemporaryDirectory() as tmp:
        addr = os.path.join(tmp, "addr")
        env = dict(os.environ, COUNT_ADDR_FILE=addr)
        out = subprocess.run(["gdb", "-q", "-batch", "-x", __file__, "--args", sys.executable, __file__,
                              "--machine", machine, "--inferior", str(periods), addr], env=env, capture_output=True,
                             text=True,
                             timeout=1800)
    for line in out.stdout.splitlines():
        if line.startswith("INSTRUCTIONS "):
            return int(line.split()[1])
    raise RuntimeError(f"gdb gave no count:\n{out.stdout[-2000:]}\n{out.stderr[-2000:]}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--periods", type=int, default=40)
    ap.add_argument("--machine", choices=("bldc", "spmsm"), default="bldc")
    ap.add_argument("--inferior", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.inferior:
        (_inferior_spmsm if args.machine == "spmsm" else _inferior)(int(args.inferior[0]), args.inferior[1])
        return 0
    one = _count(1, args.machine)             # entry, set-up and one period
    many = _count(args.periods + 1, args.machine)
    name = "run_kernel (SPMSM)" if args.machine == "spmsm" else "run_fused"
    print(f"{name}: {(many - one) / args.periods:.0f} instructions per period "
          f"(periods {WARMUP_PERIODS + 2}..{WARMUP_PERIODS + args.periods + 1} of the benchmark scenario)")
    return 0


if __name__ == "__main__":
    try:
        import gdb  # noqa: F401
    except ImportError:
        sys.exit(main())
    else:
        _gdb_script(os.environ["COUNT_ADDR_FILE"])
