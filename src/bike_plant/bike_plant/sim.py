"""BldcPlant: the simulated bike (machine + bridge + battery + shaft) behind the plant node.

Thin Python shell around the numba kernels of :mod:`bike_plant.bldc`: one call per batch
of N control periods (ARCHITECTURE.md, batched inner loop). No ROS imports.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from . import bldc as K
from . import params as P
from .heart import RiderHeart
from .params import PlantParams

PLANT_STATE_FIELDS = (
    "seq", "batch_periods", "control_period_s", "machine", "backend", "measured_by_drive", "end_of_run",
    "phase_current_a", "rotor_angle_elec_rad", "speed_rad_s", "speed_rpm", "hall_state", "timer_count",
    "dc_bus_v", "brake_resistor_on", "hall_edge_counts", "hall_edge_states", "torque_em_nm",
    "load_torque_nm", "current_samples_a", "battery_ocv_v", "battery_soc", "battery_current_a",
    "energy_mech_in_j", "energy_battery_j", "energy_resistor_j", "energy_loss_j", "energy_stored_j",
    "heart_rate_bpm", "faults", "interlock_blanked_count",
)


@dataclasses.dataclass
class BatchResult:
    """What happened during one batch of N control periods."""
    hall_edge_counts: np.ndarray      # uint64, capture-timer counts of the Hall edges
    hall_edge_states: np.ndarray      # uint8, Hall code after each edge
    torque_em_nm: float               # mean electromagnetic torque (motoring positive)
    load_torque_nm: float             # mean external torque on the shaft
    battery_current_a: float          # mean, charging positive
    current_samples_a: np.ndarray     # (N, 3) phase currents at the end of every period
    faults: int
    interlock_blanked_count: int      # cumulative
    interlock_blanked_in_batch: int


def as_gate_arrays(gates_a, gates_b, split):
    """Validate and convert one batch of gate decisions (raises ValueError)."""
    ga = np.asarray(gates_a)
    gb = np.asarray(gates_b)
    sp = np.asarray(split, dtype=np.float64)
    if ga.ndim != 1 or ga.shape != gb.shape or ga.shape != sp.shape:
        raise ValueError(f"gates_a, gates_b and split must be 1-D of equal length, got {ga.shape}, {gb.shape}, {sp.shape}")
    if ga.size == 0:
        return ga.astype(np.uint8), gb.astype(np.uint8), sp
    for name, g in (("gates_a", ga), ("gates_b", gb)):
        if g.dtype != np.uint8:
            if g.dtype.kind not in "iuf" or not (g.min() >= 0 and g.max() <= 63) or \
                    (g.dtype.kind == "f" and not np.all(g == np.floor(g))):
                raise ValueError(f"{name} entries must be integers in 0..63")
        elif g.max() > 63:
            raise ValueError(f"{name} entries must be integers in 0..63")
    if not (sp.min() >= 0.0 and sp.max() <= 1.0):       # NaN fails both comparisons
        raise ValueError("split entries must be finite and in [0, 1]")
    return ga.astype(np.uint8), gb.astype(np.uint8), sp


def _sector_rotations() -> np.ndarray:
    """ROTATE[k, g]: gate byte g (bit 2i: leg i high, bit 2i + 1: leg i low; legs U, V, W)
    turned k sectors (k x 60 deg electrical) forward. One sector is the legs' states negated
    (high <-> low, 180 deg) and moved one leg back (U takes V's, V takes W's, W takes U's:
    -120 deg): U+ V- -> U+ W-, the next step of the six-step sequence (paper 000, Fig. 6;
    bldc.HALL_TO_SECTOR's sectors 0 -> 1). For odd k a pattern becomes its high / low mirror
    (a freewheel on the low switches becomes one on the high ones): the same voltages on this
    model's symmetric bridge."""
    table = np.zeros((6, 256), np.uint8)
    for g in range(256):
        x = g & 0x3F
        for k in range(6):
            table[k, g] = x
            legs = [((x >> (2 * i)) & 1) << 1 | ((x >> (2 * i + 1)) & 1) for i in range(3)]   # negated
            x = legs[1] | legs[2] << 2 | legs[0] << 4
    return table


ROTATE_SECTORS = _sector_rotations()


class BldcPlant:
    """The authoritative plant model (docs/DESIGN.md, Physics API)."""

    def __init__(self, params: PlantParams, seed: int = 0):
        self.params = params
        self.p = P.pack_params(params)
        self.seed = seed   # the model is deterministic; kept for API symmetry
        load = params.load
        speed0 = load.speed_rpm if load.kind == "prime_mover" else params.mech.speed0_rpm
        if load.kind == "prime_mover" and load.schedule_time_s:
            speed0 = self._scheduled_speed_rpm(0.0, speed0)
        self.state = K.new_state(self.p, speed0, params.battery.soc0)
        if load.kind == "rider":
            self.state[K.S_EFFORT] = load.rider_effort0
            self.state[K.S_RIDER_INT] = load.rider_effort0
        self.heart = RiderHeart(load.heart_params()) if load.kind == "rider" else None
        self.seq = 0
        self.batch_periods = 0
        self.end_of_run = False
        self._last = BatchResult(np.zeros(0, np.uint64), np.zeros(0, np.uint8), 0.0, 0.0, 0.0,
                                 np.zeros((0, 3)), 0, 0, 0)
        self.safe = False
        # the last batch's gate arrays and the Hall sector it began in, for step_held_batch
        # (which keeps them those of the batch it holds)
        self.last_inputs = None

    # ------------------------------------------------------------------ time
    @property
    def time_s(self) -> float:
        return self.state[K.S_PERIODS] * self.params.control_period_s

    @property
    def timer_count(self) -> int:
        # same expression as the kernel's edge capture: floor(periods * (fc * T))
        return int(math.floor(self.state[K.S_PERIODS] * (self.p[P.P_TIMER_HZ] * self.p[P.P_DT])))

    def _scheduled_speed_rpm(self, t, default):
        load = self.params.load
        speed = default
        for ts, sp in zip(load.schedule_time_s, load.schedule_speed_rpm):
            if t + 1e-12 >= ts:
                speed = sp
        return speed

    # ------------------------------------------------------------------ stepping
    def step_batch(self, gates_a, gates_b, split, checked: bool = False) -> BatchResult:
        """Apply N control periods (period k: gates_a[k] for split[k]*T, then gates_b[k]).
        ``checked``: the arrays are uint8, uint8, float64 of one length and already passed
        msgconv.drive_command_problem (the node's path: no second validation per batch)."""
        ga, gb, sp = (gates_a, gates_b, split) if checked else as_gate_arrays(gates_a, gates_b, split)
        n = ga.shape[0]
        if self.safe:
            ga = np.zeros(n, np.uint8)                    # the caller's arrays may be read-only views
            gb = np.zeros(n, np.uint8)
        load = self.params.load
        if load.kind == "prime_mover" and load.schedule_time_s:
            # schedule resolution is one batch: the prime mover's speed steps at batch starts
            self.state[K.S_SPEED_TARGET] = self._scheduled_speed_rpm(self.time_s, load.speed_rpm) / P.RPM_PER_RAD_S
        edge_counts = np.zeros(2 * n + 8, np.uint64)
        edge_states = np.zeros(2 * n + 8, np.uint8)
        samples = np.zeros((n, 3))
        sums = np.zeros(3)
        blanked0 = int(self.state[K.S_INTERLOCK])
        # per-batch fault bits: set again by the kernel if it happens in this batch
        self.state[K.S_FAULTS] = float(int(self.state[K.S_FAULTS]) & ~(K.FAULT_INTERLOCK | K.FAULT_OVERCURRENT))
        self.last_inputs = (ga.copy(), gb.copy(), sp.copy(), self._sector())   # (the caller may reuse them)
        ne = K.step_batch(self.state, self.p, ga, gb, sp, edge_counts, edge_states, samples, sums)
        self.advance_heart()
        self.seq += 1
        self.batch_periods = n
        nn = max(n, 1)
        self._last = BatchResult(
            hall_edge_counts=edge_counts[:ne].copy(), hall_edge_states=edge_states[:ne].copy(),
            torque_em_nm=float(sums[0] / nn), load_torque_nm=float(sums[1] / nn),
            battery_current_a=float(sums[2] / nn), current_samples_a=samples,
            faults=int(self.state[K.S_FAULTS]), interlock_blanked_count=int(self.state[K.S_INTERLOCK]),
            interlock_blanked_in_batch=int(self.state[K.S_INTERLOCK]) - blanked0)
        return self._last

    def step_held_batch(self) -> BatchResult:
        """The last batch's gate decisions once more (realtime: no new command came in time),
        turned by the Hall sectors the rotor has moved since that batch began
        (:data:`ROTATE_SECTORS`): the same decisions relative to the rotor, to a sector. Replayed
        as they were, they switched the phases of a sector long past: a held resistance brake
        of 0.87 N m gave 0.20, a held 0.89 N m assist braked at 1.5 N m (3.8 N m ripple)."""
        if self.last_inputs is None:
            raise ValueError("no batch to hold yet")
        held = self.last_inputs
        ga, gb, sp, sector0 = held
        now = self._sector()
        k = (now - sector0) % 6 if now >= 0 and sector0 >= 0 else 0    # (an invalid Hall code: as it was)
        result = self.step_batch(ROTATE_SECTORS[k][ga], ROTATE_SECTORS[k][gb], sp, checked=True)
        self.last_inputs = held                         # still the held batch's
        return result

    def _sector(self) -> int:
        """The Hall sector the rotor is in (bldc.HALL_TO_SECTOR; -1: an invalid code)."""
        return int(K.HALL_TO_SECTOR[int(self.state[K.S_HALL])])

    def advance_heart(self) -> None:
        """The rider's heart to the plant's time, on the ledger's rider energy (after every
        batch; the CAN drive emulator calls it after its own kernels step the state)."""
        if self.heart is not None:
            # a Python float: the same value, and the heart's arithmetic is not numpy scalars'
            self.heart.advance(float(self.state[K.S_E_MECH]), self.time_s)

    def set_rider_cadence(self, cadence_rpm: float, stop: bool = False) -> None:
        """The rider's cadence target from now on (a workout's; 0: the config's own); ``stop``:
        he stops pedalling (a spin-down's coast; the kernel's rider takes a target of 0 so)."""
        rpm = cadence_rpm if cadence_rpm > 0 else self.params.load.rider_target_cadence_rpm
        self.p[P.P_RIDER_TARGET] = 0.0 if stop else rpm / P.RPM_PER_RAD_S

    def set_safe_state(self) -> None:
        """All gates off until :meth:`clear_safe_state`: the bridge becomes a diode rectifier."""
        self.safe = True

    def clear_safe_state(self) -> None:
        self.safe = False

    def safe_gates(self, n: int):
        """A batch of all-off gate decisions (what the node applies in the safe state)."""
        return np.zeros(n, np.uint8), np.zeros(n, np.uint8), np.ones(n)

    # ------------------------------------------------------------------ outputs
    def ledger(self) -> dict:
        return K.ledger_of(self.state, self.p)

    def snapshot(self) -> dict:
        """PlantState fields (header excluded) at the start of the next batch."""
        s = self.state
        last = self._last
        led = self.ledger()
        soc = float(s[K.S_SOC])
        speed_rpm = float(s[K.S_OMEGA] * P.RPM_PER_RAD_S)
        faults = int(s[K.S_FAULTS])
        if self.params.bldc.ke_v_per_rpm * abs(speed_rpm) > float(s[K.S_VDC]):
            # the diodes brake beyond any Command (4 x the default ke in the demo: 10 N m for 1.2
            # asked, and no word); slow quantities, so a check per batch, off the kernel's path
            faults |= K.FAULT_UNCONTROLLED_GENERATION
        if soc <= P.PACK_EMPTY_SOC:
            # the pack model runs on below empty (its OCV falls below v_empty_v): said, so that the
            # session keeps assist from it and the report counts it
            faults |= K.FAULT_PACK_EMPTY
        return {
            "seq": int(self.seq),
            "batch_periods": int(self.batch_periods),
            "control_period_s": float(self.params.control_period_s),
            "machine": "bldc",
            "backend": "sim",
            "measured_by_drive": False,
            "end_of_run": bool(self.end_of_run),
            "phase_current_a": [float(s[K.S_IA]), float(s[K.S_IB]), float(s[K.S_IC])],
            "rotor_angle_elec_rad": float(s[K.S_THETA_E]),
            "speed_rad_s": float(s[K.S_OMEGA]),
            "speed_rpm": speed_rpm,
            "hall_state": int(s[K.S_HALL]),
            "timer_count": self.timer_count,
            "dc_bus_v": float(s[K.S_VDC]),
            "brake_resistor_on": bool(s[K.S_S0] != 0.0),
            "hall_edge_counts": [int(c) for c in last.hall_edge_counts],
            "hall_edge_states": [int(c) for c in last.hall_edge_states],
            "torque_em_nm": last.torque_em_nm,
            "load_torque_nm": last.load_torque_nm,
            # float32 as the message carries them: one array conversion, not 3 N Python floats
            "current_samples_a": last.current_samples_a.reshape(-1).astype(np.float32),
            "battery_ocv_v": float(K.battery_voc(soc, self.p)),
            "battery_soc": soc,
            "battery_current_a": last.battery_current_a,
            "energy_mech_in_j": led["energy_mech_in_j"],
            "energy_battery_j": led["energy_battery_j"],
            "energy_resistor_j": led["energy_resistor_j"],
            "energy_loss_j": led["energy_loss_j"],
            "energy_stored_j": led["energy_stored_j"],
            "heart_rate_bpm": self.heart.bpm if self.heart is not None else 0.0,
            "faults": faults,
            "interlock_blanked_count": int(s[K.S_INTERLOCK]),
            "overcurrent_trip_count": int(s[K.S_OC_TRIPS]),
        }
