"""A fleet of BLDC bikes in one batched, multi-threaded numba kernel (issue 6, fleet).

Each bike is the whole inner loop of paper 000 (speed estimator Eq. 1, torque command
Eq. 2-5, ktg = k(w) kt Eq. 6-9, hysteresis current control, 6-switch bridge, battery,
S0 + brake resistor, shaft and rider), i.e. exactly :func:`bike_controller.bldc_control.run_fused`
(the per-period closed loop, the controller reading the plant state) with its own plant
state, controller state, parameter vector (rider) and command. The bikes are independent,
so the fleet kernel is a ``prange`` over bikes, each running its periods in chunks of
``chunk_periods`` (the cadence trace is sampled between chunks). Bike b of a fleet is bit
for bit the same as one ``run_fused`` of bike b (test/test_fleet.py).

Throughput: ``bike_seconds_per_wall_s`` = bikes x simulated seconds / wall seconds; it is
also the number of bikes this machine runs in real time (``bikes_in_real_time``).
No rclpy here (physics/control).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from bike_plant import bldc as K
from bike_plant import params as P
from bike_plant.config import machine_config

from . import bldc_control as BC
from . import speed_estimator as _se
from . import bldc_params as _bp
from . import torque_command as _tc

# the fleet kernel compiles run_fused and everything it calls into its own cache entry
K.invalidate_stale_numba_cache(__file__, [BC.__file__, K.__file__, K._jit.__file__, P.__file__, _se.__file__,
                                          _tc.__file__, _bp.__file__])

CHUNK_PERIODS = 1000          # cadence sample every 1000 periods (50 ms at 20 kHz)
BIKES_PER_TASK = 4            # prange work unit (numba parallel chunk size)


@njit(cache=True, parallel=True, error_model="numpy")
def run_fleet_kernel(states, ps, css, qs, n_periods, chunk_periods, speed_trace):
    """Bike b: ``n_periods`` of run_fused(states[b], ps[b], css[b], qs[b]) in chunks of
    ``chunk_periods``; speed_trace[b, j] = shaft speed [rad/s] after chunk j."""
    n_bikes = states.shape[0]
    for b in prange(n_bikes):
        samples = np.zeros((1, 3))
        tem = np.zeros(1)
        state = states[b]
        p = ps[b]
        cs = css[b]
        q = qs[b]
        done = 0
        j = 0
        while done < n_periods:
            n = min(chunk_periods, n_periods - done)
            BC.run_fused(state, p, cs, q, n, samples, 0, tem)
            done += n
            if j < speed_trace.shape[1]:
                speed_trace[b, j] = state[K.S_OMEGA]
            j += 1


@dataclass
class Fleet:
    """Per-bike arrays (row b = bike b): plant state, plant parameters, controller state,
    controller parameters; command/mode/rider values as drawn (for the summary)."""
    states: np.ndarray
    ps: np.ndarray
    css: np.ndarray
    qs: np.ndarray
    command: np.ndarray
    mode: np.ndarray
    speed0_rpm: np.ndarray
    rider_t0_nm: np.ndarray
    rider_target_cadence_rpm: np.ndarray
    gear_ratio: float
    control_period_s: float

    @property
    def n_bikes(self) -> int:
        return self.states.shape[0]


def check_bikes(n_bikes, name: str = "bikes") -> int:
    """The bike count as an int, or ValueError naming ``name`` (the CLI's --bikes)."""
    if isinstance(n_bikes, bool) or not isinstance(n_bikes, (int, np.integer)) or not 1 <= int(n_bikes) <= 1_000_000:
        raise ValueError(f"{name} must be an integer in [1, 1000000], got {n_bikes!r}")
    return int(n_bikes)


def check_seconds(seconds, name: str = "seconds", period_s: float = 0.0) -> float:
    """The simulated time as a float, or ValueError naming ``name`` (the CLI's --seconds); with
    ``period_s`` (the bikes' control period) at least one period: less ran no period and ended in a
    ZeroDivisionError traceback (ns per bike-period)."""
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not math.isfinite(seconds) \
            or not 0.0 < seconds <= 3600.0:
        raise ValueError(f"{name} must be a number in (0, 3600], got {seconds!r}")
    if seconds < period_s:
        raise ValueError(f"{name} must be at least one control period ({period_s:g} s), got {seconds!r}")
    return float(seconds)


def check_seed(seed, name: str = "seed") -> int:
    """The seed as an int, or ValueError naming ``name`` (the CLI's --seed)."""
    # numpy's default_rng said only "expected non-negative integer"
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"{name} must be an integer >= 0, got {seed!r}")
    return int(seed)


def check_threads(threads, name: str = "threads") -> int | None:
    """The worker thread count (None: all numba has), or ValueError naming ``name`` (the CLI's --threads)."""
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
        raise ValueError(f"{name} must be an integer >= 1, got {threads!r}")
    return threads


def make_fleet(cfg: dict, n_bikes: int, seed: int = 0, spread: bool = True) -> Fleet:
    """n_bikes rider bikes of config `cfg` (load kind forced to rider). With `spread`, each
    bike draws its own (seeded) start speed, resistance Command and rider: start 1500-3000
    rpm, Command 0.2-1.0 (Eq. 5, resistance mode), crank torque T0 80-200 N m, target
    cadence 70-95 rpm; without it every bike is the config's bike at Command 1."""
    n_bikes = check_bikes(n_bikes)
    seed = check_seed(seed)
    # an SPMSM config said "battery: unknown parameter(s) dump_above_soc, nominal_v", or, with none of
    # those keys, rode the BLDC bike's defaults without a word
    cfg = machine_config(cfg, "bldc", "the offline fleet is the BLDC bike's batched kernel (paper 000)")
    cfg["load"] = dict(cfg.get("load") or {}, kind="rider")
    plant = P.plant_params_from_config(cfg)
    nominal = P.nominal_params_from_config(cfg)
    cp = BC.controller_params_from_config(cfg)
    p0 = P.pack_params(plant)
    q0 = BC.pack_controller(cp, nominal)
    rng = np.random.default_rng(seed)
    if spread:
        speed0 = rng.uniform(1500.0, 3000.0, n_bikes)
        command = rng.uniform(0.2, 1.0, n_bikes)
        t0 = rng.uniform(80.0, 200.0, n_bikes)
        target = rng.uniform(70.0, 95.0, n_bikes)
    else:
        speed0 = np.full(n_bikes, plant.mech.speed0_rpm)
        command = np.ones(n_bikes)
        t0 = np.full(n_bikes, plant.load.rider_t0_nm)
        target = np.full(n_bikes, plant.load.rider_target_cadence_rpm)
    mode = np.zeros(n_bikes, np.int64)             # resistance (generating)
    ps = np.tile(p0, (n_bikes, 1))
    ps[:, P.P_RIDER_T0] = t0
    ps[:, P.P_RIDER_TARGET] = target / P.RPM_PER_RAD_S
    qs = np.tile(q0, (n_bikes, 1))
    states = np.zeros((n_bikes, K.S_SIZE))
    css = np.zeros((n_bikes, BC.C_SIZE))
    for b in range(n_bikes):
        BC.validate_command(float(command[b]), int(mode[b]))
        K.init_state(states[b], ps[b], speed0[b] / P.RPM_PER_RAD_S, plant.battery.soc0)
        states[b, K.S_EFFORT] = plant.load.rider_effort0
        states[b, K.S_RIDER_INT] = plant.load.rider_effort0
        css[b, BC.C_IOVERRIDE] = -1.0
        css[b, BC.C_COMMAND] = command[b]
        css[b, BC.C_MODE] = mode[b]
        BC.update_command(css[b], qs[b])
    return Fleet(states, ps, css, qs, command, mode, speed0, t0, target, plant.load.gear_ratio,
                 plant.control_period_s)


def set_threads(threads: int | None) -> int:
    """numba worker threads for the fleet (None: all numba has); returns the count in use."""
    import numba
    if check_threads(threads) is not None:
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    return numba.get_num_threads()


def run(fleet: Fleet, seconds: float, chunk_periods: int = CHUNK_PERIODS) -> dict:
    """Advance every bike of `fleet` by `seconds` of simulated time (in place); returns
    wall time, throughput and the cadence trace."""
    seconds = check_seconds(seconds, period_s=fleet.control_period_s)
    dt = fleet.control_period_s
    n = int(round(seconds / dt))
    chunk = max(1, min(int(chunk_periods), n))
    trace = np.zeros((fleet.n_bikes, -(-n // chunk)))
    import numba
    # bikes handed out a few at a time: a thread that the OS preempts (a shared machine)
    # does not leave the other idle at the end, as a static split would
    previous = numba.set_parallel_chunksize(BIKES_PER_TASK)
    try:
        t0 = time.perf_counter()
        run_fleet_kernel(fleet.states, fleet.ps, fleet.css, fleet.qs, n, chunk, trace)
        wall = time.perf_counter() - t0
    finally:
        numba.set_parallel_chunksize(previous)
    sim_s = n * dt
    return {"sim_s": sim_s, "wall_s": wall, "periods": n, "speed_trace_rad_s": trace,
            "real_time_factor": sim_s / wall,
            "bike_seconds_per_wall_s": fleet.n_bikes * sim_s / wall,
            "ns_per_bike_period": wall / (n * fleet.n_bikes) * 1e9}


def bike_summaries(fleet: Fleet, sim_s: float, speed_trace: np.ndarray) -> list[dict]:
    """Per-bike figures over the run: mean rider power (mechanical into the shaft), mean
    battery charging power, mean brake-resistor power, mean cadence, final SOC, faults,
    energy-ledger residual."""
    out = []
    for b in range(fleet.n_bikes):
        st = fleet.states[b]
        led = K.ledger_of(st, fleet.ps[b])
        cad = speed_trace[b] * P.RPM_PER_RAD_S / fleet.gear_ratio
        out.append({
            "bike": b + 1,
            "command": float(fleet.command[b]),
            "mode": int(fleet.mode[b]),
            "rider_t0_nm": float(fleet.rider_t0_nm[b]),
            "target_cadence_rpm": float(fleet.rider_target_cadence_rpm[b]),
            "mean_cadence_rpm": float(np.mean(cad)) if cad.size else 0.0,
            "final_speed_rpm": float(st[K.S_OMEGA] * P.RPM_PER_RAD_S),
            "mean_rider_power_w": led["energy_mech_in_j"] / sim_s,
            "mean_battery_power_w": led["energy_battery_j"] / sim_s,
            "mean_resistor_power_w": led["energy_resistor_j"] / sim_s,
            "final_soc": float(st[K.S_SOC]),
            "faults": int(st[K.S_FAULTS]),
            "ledger_residual_j": led["residual_j"],
        })
    return out


def fleet_real_time(n_bikes: int = 1000, seconds: float = 2.0, threads: int | None = 2, cfg_path=None,
                    seed: int = 0, summaries: bool = False, names: dict[str, str] | None = None) -> dict:
    """Compile (or load from cache), then run `n_bikes` for `seconds`: the fleet figures.
    ValueError for a bad argument, naming it as ``names`` says (the CLI: bikes -> --bikes, seconds,
    threads, seed), checked before the config is read (seconds against its control period after).

    Keys: bikes, threads, sim_s, wall_s, real_time (sim s per wall s of the whole fleet),
    bikes_in_real_time (= bike-seconds per wall second), ns_per_bike_period, jit_compile_s,
    and with `summaries` the per-bike list and its aggregate."""
    from bike_plant.config import load_config

    names = {key: (names or {}).get(key, key) for key in ("bikes", "seconds", "threads", "seed")}
    n_bikes = check_bikes(n_bikes, names["bikes"])
    seconds = check_seconds(seconds, names["seconds"])
    seed = check_seed(seed, names["seed"])
    check_threads(threads, names["threads"])
    cfg = load_config(cfg_path)
    used = set_threads(threads)
    t0 = time.perf_counter()
    warm = make_fleet(cfg, min(n_bikes, 2 * max(used, 1)), seed)
    check_seconds(seconds, names["seconds"], warm.control_period_s)
    run(warm, 20 * warm.control_period_s, 10)
    compile_s = time.perf_counter() - t0
    fleet = make_fleet(cfg, n_bikes, seed)
    res = run(fleet, seconds)
    out = {"bikes": n_bikes, "threads": used, "sim_s": res["sim_s"], "wall_s": res["wall_s"],
           "real_time": res["real_time_factor"], "bikes_in_real_time": res["bike_seconds_per_wall_s"],
           "ns_per_bike_period": res["ns_per_bike_period"], "jit_compile_s": compile_s}
    if summaries:
        per_bike = bike_summaries(fleet, res["sim_s"], res["speed_trace_rad_s"])
        out["per_bike"] = per_bike
        out["aggregate"] = aggregate(per_bike)
    return out


def aggregate(per_bike: list[dict]) -> dict:
    """mean / min / max over the fleet of each per-bike figure."""
    keys = ("mean_rider_power_w", "mean_battery_power_w", "mean_resistor_power_w", "mean_cadence_rpm",
            "final_soc", "ledger_residual_j")
    agg = {}
    for key in keys:
        v = np.array([b[key] for b in per_bike])
        agg[key] = {"mean": float(v.mean()), "min": float(v.min()), "max": float(v.max())}
    agg["bikes_with_faults"] = int(sum(1 for b in per_bike if b["faults"]))
    return agg


if __name__ == "__main__":   # pragma: no cover
    import json
    import sys
    r = fleet_real_time(int(sys.argv[1]) if len(sys.argv) > 1 else 1000,
                        float(sys.argv[2]) if len(sys.argv) > 2 else 2.0)
    print(json.dumps(r, indent=2))
