"""BLDC torque controller of paper 000 (Fig. 7/10) with the batched inner loop.

Per 50 us period: speed estimator (Eq. 1) -> torque command transformer (Eq. 2-5) ->
torque-constant correction ktg = k(w) kt (Eq. 6-9) -> current command I* -> commutation
from the Hall state + hysteresis current control with at most one switching edge per
period (20 kHz PWM) -> gate interlock (in the plant's hardware).

Batched inner loop (ARCHITECTURE.md): :class:`BatchController` answers one PlantState
with N periods of gate decisions. Inside the batch it cannot measure, so it predicts the
fast state with its own copy of the plant kernel (:func:`bike_plant.bldc.step_period`,
nominal parameters, shaft speed held at the measured value, Hall edges predicted with the
same capture-timer quantisation). With a matched model the result equals a per-period
closed loop; with a mismatched one the error is reported (prediction_error_a).

Generating (quadrant II, Fig. 5/6): in a sector with phase p at +E and phase n at -E the
LOW switch of p is modulated: on -> the winding current rises through Q(low p) and the
lower diode of n (boost inductor charging); off -> it flows into the battery through the
upper diode of p. Motoring (quadrant I): upper p modulated, lower n on.
Feedback current = (|ia| + |ib| + |ic|) / 2 (paper 000, Fig. 12b/13b).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from bike_plant import bldc as K
from bike_plant import jit as _jit
from bike_plant import params as P
from bike_plant.config import ConfigError
from bike_plant.jit import JIT, JIT_INLINE, unlikely

from . import bldc_params as _bp
from . import speed_estimator as _se
from . import torque_command as _tc
from .speed_estimator import speed_rpm_from_counts
from .bldc_params import (K_ROWS_MAX, K_TABLE_MAX, ControllerParams, controller_params_from_config,  # noqa: F401
                          validate_command)
from .torque_command import (MODE_MOTORING, MODE_RESISTANCE, k_factor, ktg_nm_per_a, region_of,
                             torque_command_nm)

# the kernels below inline bike_plant.bldc / params code: drop our numba cache if they changed
K.invalidate_stale_numba_cache(__file__, [K.__file__, _jit.__file__, P.__file__, _se.__file__, _tc.__file__,
                                         _bp.__file__])

QUADRANT_MOTORING = 1
QUADRANT_GENERATING = 2


# ---- controller parameter vector / state layout -------------------------------------------
Q_TMAX, Q_WB, Q_PMAX, Q_H, Q_ILIM, Q_KT, Q_PP, Q_FC, Q_KN, Q_KLIN, Q_KCN = range(11)
Q_KX = 11                               # k table speeds
Q_KCX = Q_KX + K_TABLE_MAX              # its Commands (Q_KCN of them; 0: the paper's one row)
Q_KY = Q_KCX + K_ROWS_MAX               # its rows, Q_KN values each
Q_SIZE = Q_KY + K_TABLE_MAX * K_ROWS_MAX

C_ON = 0            # hysteresis comparator memory (switch state)
C_LAST_EDGE = 1     # capture count of the last Hall edge
C_HAVE_EDGE = 2
C_NC = 3            # counts between the last two edges (Eq. 1 nc)
C_SPEED_EST = 4     # rpm, Eq. 1
C_COMMAND = 5
C_MODE = 6
C_IOVERRIDE = 7     # current command override [A] (< 0: none) for the current-control tests
C_TCMD = 8
C_K = 9
C_KTG = 10
C_ICMD = 11
C_REGION = 12
C_QUADRANT = 13
# capture count from which every Hall edge reached the controller (Eq. 1 needs consecutive edges):
# 0 in lockstep; a realtime controller that skipped PlantStates (newest-only reader) lost their edges
C_EDGES_FROM = 14
C_SIZE = 16


def pack_controller(cp: ControllerParams, plant: P.PlantParams) -> np.ndarray:
    q = np.zeros(Q_SIZE)
    q[Q_TMAX] = cp.tmax_nm
    q[Q_WB] = cp.base_speed_rpm
    q[Q_PMAX] = cp.pmax_w
    q[Q_H] = cp.hysteresis_a
    q[Q_ILIM] = cp.current_limit_a
    q[Q_KT] = plant.bldc.kt_nm_per_a
    q[Q_PP] = plant.bldc.pole_pairs
    q[Q_FC] = plant.hall.timer_hz
    xs, cs, ys = cp.k_table()
    q[Q_KN] = len(xs)
    q[Q_KLIN] = 1.0 if cp.k_interp == "linear" else 0.0
    q[Q_KCN] = len(cs)
    q[Q_KX:Q_KX + len(xs)] = xs
    q[Q_KCX:Q_KCX + len(cs)] = cs
    q[Q_KY:Q_KY + len(ys)] = ys
    return q


@njit(**JIT_INLINE)
def _k_of(speed_rpm, command, q):
    """Eq. 7 k from the packed table (bike_controller.bldc_params.k_factor)."""
    return k_factor(speed_rpm, command, q[Q_KX:Q_KCX], q[Q_KY:Q_SIZE], int(q[Q_KN]), q[Q_KLIN] != 0.0,
                    q[Q_KCX:Q_KY], int(q[Q_KCN]))


@njit(**JIT)
def update_command(cs, q):
    """Speed estimate -> Tcmd (Eq. 3-4) -> k, ktg (Eq. 7-9) -> I*."""
    speed = cs[C_SPEED_EST]
    mode = int(cs[C_MODE])
    cs[C_REGION] = region_of(speed, q[Q_WB])
    if mode == MODE_MOTORING:
        tcmd = cs[C_COMMAND] * q[Q_TMAX]
        k = 1.0
        cs[C_QUADRANT] = QUADRANT_MOTORING
    else:
        tcmd = torque_command_nm(cs[C_COMMAND], speed, q[Q_TMAX], q[Q_WB], q[Q_PMAX])
        k = _k_of(speed, cs[C_COMMAND], q)
        cs[C_QUADRANT] = QUADRANT_GENERATING
    ktg = ktg_nm_per_a(k, q[Q_KT])
    icmd = tcmd / ktg
    if cs[C_IOVERRIDE] >= 0.0:
        icmd = cs[C_IOVERRIDE]
    if icmd > q[Q_ILIM]:
        icmd = q[Q_ILIM]
    cs[C_TCMD] = tcmd
    cs[C_K] = k
    cs[C_KTG] = ktg
    cs[C_ICMD] = icmd


@njit(**JIT)
def process_edge(cs, q, count):
    """A captured Hall edge: Eq. 1 with nc = counts since the previous edge. A previous edge
    older than C_EDGES_FROM only starts a new interval: edges between them went unseen, and nc
    over them would be several intervals (the speed a fraction of the true one)."""
    if cs[C_HAVE_EDGE] != 0.0 and count > cs[C_LAST_EDGE] and cs[C_LAST_EDGE] >= cs[C_EDGES_FROM]:
        cs[C_NC] = count - cs[C_LAST_EDGE]
        cs[C_SPEED_EST] = speed_rpm_from_counts(cs[C_NC], q[Q_FC], q[Q_PP])
        update_command(cs, q)
    cs[C_LAST_EDGE] = count
    cs[C_HAVE_EDGE] = 1.0


@njit(**JIT_INLINE)
def _bound_speed(cs, q, model, p):
    """No edge for longer than the last interval: Eq. 1 of the elapsed count bounds the speed.
    Elapsed since the last edge seen or C_EDGES_FROM, whichever is later: before that, edges may
    have gone unseen, so their absence says nothing of the speed."""
    if cs[C_HAVE_EDGE] != 0.0:
        # the plant's timer formula (np.floor: a float floor, no int64 round trip per period)
        now = np.floor(model[K.S_PERIODS] * (p[P.P_TIMER_HZ] * p[P.P_DT]))
        since = cs[C_LAST_EDGE]
        if cs[C_EDGES_FROM] > since:
            since = cs[C_EDGES_FROM]
        elapsed = now - since
        if elapsed > cs[C_NC] and elapsed > 0.0:
            bound = speed_rpm_from_counts(elapsed, q[Q_FC], q[Q_PP])
            if bound < cs[C_SPEED_EST]:
                cs[C_SPEED_EST] = bound
                update_command(cs, q)


@njit(**JIT_INLINE)
def patterns(sector, mode):
    """(on, off) gate patterns of the sector: generating modulates low p; motoring upper p + low n."""
    pp_ = K.SECTOR_P[sector]
    nn = K.SECTOR_N[sector]
    if mode == MODE_MOTORING:
        return (1 << (2 * pp_)) | (1 << (2 * nn + 1)), 1 << (2 * nn + 1)
    return 1 << (2 * pp_ + 1), 0


def _pattern_table() -> np.ndarray:
    """patterns() by (motoring, Hall code): [motoring][hall] = (on, off); (-1, -1) for the
    two codes that are no sector (0, 7). One look-up per period instead of three."""
    tab = np.full((2, 8, 2), -1, dtype=np.int64)
    for motoring, mode in ((0, MODE_RESISTANCE), (1, MODE_MOTORING)):
        for hall in range(8):
            sector = int(K.HALL_TO_SECTOR[hall])
            if sector >= 0:
                tab[motoring, hall] = patterns.py_func(sector, mode)
    return tab


PATTERN_TABLE = _pattern_table()


@njit(**JIT_INLINE)
def _sector_patterns(cs, model):
    """(on, off) gate patterns for the model's Hall code and the commanded mode, from
    PATTERN_TABLE; (-1, -1) when the code is no sector."""
    hall = int(model[K.S_HALL]) & 7
    motoring = 1 if cs[C_MODE] == MODE_MOTORING else 0
    return PATTERN_TABLE[motoring, hall, 0], PATTERN_TABLE[motoring, hall, 1]


@njit(**JIT)
def control_period(cs, q, model, p, ws, wi):
    """Hysteresis current control for one period from the (measured or predicted) state
    `model`; returns (gates_a, gates_b, split). Uses ws/wi as scratch and leaves the
    period's back-EMF / inductances in ws (K.period_setup), so the step that follows
    can skip recomputing them. General form (any machine); control_period_sym is its
    fast specialisation for the symmetric machine."""
    K.period_setup(model, p, ws)
    _bound_speed(cs, q, model, p)
    on_pat, off_pat = _sector_patterns(cs, model)
    icmd = cs[C_ICMD]
    if on_pat < 0 or icmd <= 0.0:
        cs[C_ON] = 0.0
        return 0, 0, 1.0
    i_fb = 0.5 * (abs(model[0]) + abs(model[1]) + abs(model[2]))
    on = _comparator(cs, q, icmd, i_fb, 1.0)
    pat = on_pat if on else off_pat
    # predict the period with the active pattern; toggle where the opposite band edge is crossed
    i_end = K.trial_currents(model, p, pat, ws, wi)
    if _edge_needed(q, icmd, on, i_fb, i_end, 1.0):
        i_other = K.trial_currents(model, p, off_pat if on else on_pat, ws, wi)
        return _place_edge(cs, q, icmd, on, on_pat, off_pat, i_fb, i_end, i_other, 1.0)
    cs[C_ON] = 1.0 if on else 0.0
    return pat, pat, 1.0


@njit(**JIT_INLINE)
def _comparator(cs, q, icmd, i_fb, scale):
    """Hysteresis comparator with memory at the period start: on below I* - h, off above I* + h.
    scale: i_fb is scale x the feedback (|ia| + |ib| + |ic|) / 2 (1 or 2: the symmetric path
    compares the plain sum, one multiply less on the period's serial chain; both scalings
    are exact, so the decisions are the same)."""
    h = q[Q_H]
    on = cs[C_ON] != 0.0
    if on and i_fb >= scale * (icmd + h):
        on = False
    elif (not on) and i_fb <= scale * (icmd - h):
        on = True
    return on


@njit(**JIT_INLINE)
def _edge_needed(q, icmd, on, i_fb, i_end, scale):
    """Does the prediction i_end of the active pattern cross the opposite band edge? (scale as
    _comparator's)"""
    h = q[Q_H]
    if on:
        return i_end > scale * (icmd + h) and i_end > i_fb
    return i_end < scale * (icmd - h) and i_end < i_fb


@njit(**JIT_INLINE)
def _clamp01(s):
    """min(max(s, 0.0), 1.0), bit for bit (numba's max(s, 0.0) is 0.0 if 0.0 > s else s, so a
    NaN passes, as here), as two branches that almost never apply: the edge fractions are
    ratios of band distances inside [0, 1] but for round-off. min / max are selects, whose
    latency lands on the period's serial chain (trial -> split -> plant step -> currents):
    ~3 cycles per period."""
    if unlikely(s < 0.0):
        s = 0.0
    if unlikely(s > 1.0):
        s = 1.0
    return s


@njit(**JIT_INLINE)
def _place_edge(cs, q, icmd, on, on_pat, off_pat, i_fb, i_end, i_other, scale):
    """The period's one switching edge where the prediction i_end (active pattern) crosses the
    band edge; i_other: the prediction with the other pattern for the whole period. Returns
    (gates_a, gates_b, split) and flips the comparator memory. scale as _comparator's: the
    split is a ratio of differences, each exactly scale x the unscaled one, so it is the same."""
    h = q[Q_H]
    upper = scale * (icmd + h)
    lower = scale * (icmd - h)
    if on:
        s = (upper - i_fb) / (i_end - i_fb)
        # one edge per period: never so early that the rest of the period (off) carries the
        # current below the lower band edge (the off slope is steeper than the on slope)
        if i_other < lower:
            s_keep = (lower - i_other) / (i_end - i_other)
            if s_keep > s:
                s = s_keep
        cs[C_ON] = 0.0
        return on_pat, off_pat, _clamp01(s)
    s = (i_fb - lower) / (i_fb - i_end)
    if i_other > upper:
        s_keep = (i_other - upper) / (i_other - i_end)
        if s_keep > s:
            s = s_keep
    cs[C_ON] = 1.0
    return off_pat, on_pat, _clamp01(s)


@njit(**JIT_INLINE)
def control_period_sym(cs, q, model, p, c, ws, wi, fs):
    """control_period for the symmetric machine (c[K.KC_SYM] != 0), from fs =
    K.fast_state(model): the currents, v_dc, speed and angle in registers. Returns (gates_a,
    gates_b, split, emf, legs_a, legs_b): emf the period's back-EMF (K.emf_sym), legs_a /
    legs_b the trials' K.legs_of for gates_a / gates_b (legs_b K.NO_LEGS without an edge),
    which K.step_period_sym_i reuses: with a matched model the controller's prediction IS the
    plant's first step, and its second starts on the trial's line."""
    i0, i1, i2, vdc, omega, theta_e = fs
    # the speed bound first: its (rare) out-of-line update_command call then has no EMF values
    # live across it to spill
    _bound_speed(cs, q, model, p)
    emf = K.emf_sym_i(theta_e, omega, p)
    on_pat, off_pat = _sector_patterns(cs, model)
    icmd = cs[C_ICMD]
    if on_pat < 0 or icmd <= 0.0:
        cs[C_ON] = 0.0
        return 0, 0, 1.0, emf, K.NO_LEGS, K.NO_LEGS
    i_fb = abs(i0) + abs(i1) + abs(i2)        # 2 x the feedback: scale 2 below
    on = _comparator(cs, q, icmd, i_fb, 2.0)
    pat = on_pat if on else off_pat
    i_end, legs = K.trial_sym_i(i0, i1, i2, vdc, pat, emf, K.legs_of(i0, i1, i2, pat, vdc, emf, c), c, ws, wi,
                                False)
    if _edge_needed(q, icmd, on, i_fb, i_end, 2.0):
        other = off_pat if on else on_pat
        i_other, legs_o = K.trial_sym_i(i0, i1, i2, vdc, other, emf, K.legs_of(i0, i1, i2, other, vdc, emf, c), c,
                                        ws, wi, True)
        a, b, s = _place_edge(cs, q, icmd, on, on_pat, off_pat, i_fb, i_end, i_other, 2.0)
        return a, b, s, emf, legs, legs_o
    cs[C_ON] = 1.0 if on else 0.0
    return pat, pat, 1.0, emf, legs, K.NO_LEGS


@njit(**JIT_INLINE)
def closed_loop_period(cs, q, model, p, c, ws, wi, edge_counts, edge_states):
    """One period of control law + step of `model` (the controller's prediction, or in
    run_fused the plant itself), Hall edges fed back to Eq. 1. Returns (gates_a, gates_b,
    split) as sent to the plant."""
    if c[K.KC_SYM] != 0.0:
        a, b, s, _fs = closed_loop_period_sym(cs, q, model, p, c, ws, wi, edge_counts, edge_states,
                                              K.fast_state(model))
        return a, b, s
    return _closed_loop_period_general(cs, q, model, p, c, ws, wi, edge_counts, edge_states)


@njit(**dict(JIT, forceinline=False))
def _closed_loop_period_general(cs, q, model, p, c, ws, wi, edge_counts, edge_states):
    """closed_loop_period for any machine (the position-dependent L), kept out of line: inlined, its
    topology iteration shared the fused loop's registers with the symmetric machine's period."""
    _jit.out_of_line()
    a, b, s = control_period(cs, q, model, p, ws, wi)
    s = np.float64(np.float32(s))
    ne = K.step_period(model, p, c, a, b, s, edge_counts, edge_states, 0, ws, wi, True)
    for j in range(ne):
        process_edge(cs, q, float(edge_counts[j]))
    return a, b, s


@njit(**JIT_INLINE)
def closed_loop_period_sym(cs, q, model, p, c, ws, wi, edge_counts, edge_states, fs):
    """closed_loop_period for the symmetric machine from fs = K.fast_state(model). Returns
    (gates_a, gates_b, split, fs) with fs the fast state after the period (as stored in
    model): run_fused carries it to the next period in registers, so its serial chains
    (currents -> trial -> edge -> step -> currents; v_dc, angle) have no store and reload."""
    a, b, s, emf, legs_a, legs_b = control_period_sym(cs, q, model, p, c, ws, wi, fs)
    s = np.float64(np.float32(s))    # DriveCommand carries split as float32: predict what the plant gets
    ne, fs = K.step_period_sym_i(model, p, c, fs, a, b, s, emf, legs_a, legs_b, edge_counts, edge_states, 0, ws, wi)
    for j in range(ne):
        process_edge(cs, q, float(edge_counts[j]))
    return a, b, s, fs


@njit(**JIT)
def control_batch(cs, q, model, p, ga, gb, sp, edge_counts, edge_states):
    """N periods of control law + prediction with the controller's own plant kernel."""
    ws = np.empty(K.WS_SIZE)
    wi = np.empty(6, np.int64)
    c = K.plant_constants(p)
    n = ga.shape[0]
    for k in range(n):
        a, b, s = closed_loop_period(cs, q, model, p, c, ws, wi, edge_counts, edge_states)
        ga[k] = a
        gb[k] = b
        sp[k] = s


@njit(**JIT)
def run_fused(plant, p, cs, q, n, samples, rec_every, tem_out):
    """Per-period closed loop (N = 1, perfect measurement): the controller reads the plant
    state directly. The fastest form of the inner loop (benchmark); equal to the batched
    loop with a matched model. samples[k // rec_every] = currents, tem_out the same for torque."""
    ws = np.empty(K.WS_SIZE)
    wi = np.empty(6, np.int64)
    ec = np.empty(4, np.uint64)
    es = np.empty(4, np.uint8)
    c = K.plant_constants(p)
    # the next recorded period (k = r * rec_every): one compare per period, not a modulo
    next_rec = 0 if rec_every > 0 else -1
    r = 0
    sym = c[K.KC_SYM] != 0.0
    # symmetric machine: the fast state (currents, v_dc, speed, angle) goes from one period to
    # the next in registers (closed_loop_period_sym returns what it stores in plant)
    fs = K.fast_state(plant)
    for k in range(n):
        if sym:
            _a, _b, _s, fs = closed_loop_period_sym(cs, q, plant, p, c, ws, wi, ec, es, fs)
        else:
            closed_loop_period(cs, q, plant, p, c, ws, wi, ec, es)
        if k == next_rec:
            if r < samples.shape[0]:
                samples[r, 0] = plant[0]
                samples[r, 1] = plant[1]
                samples[r, 2] = plant[2]
                tem_out[r] = plant[K.S_TEM]
            r += 1
            next_rec += rec_every


class BatchController:
    """The controller node's law without ROS (docs/DESIGN.md, Control API)."""

    def __init__(self, cfg: dict, nominal_params: P.PlantParams | None = None, batch_periods: int | None = None):
        self.cfg = cfg
        self.cp = controller_params_from_config(cfg)
        self.nominal = nominal_params if nominal_params is not None else P.nominal_params_from_config(cfg)
        self.p = P.pack_params(self.nominal)
        self.p[P.P_LOAD_KIND] = 0.0            # prediction: shaft speed held at the measured value
        self.q = pack_controller(self.cp, self.nominal)
        n = batch_periods if batch_periods is not None else cfg.get("batch_periods", 20)
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ConfigError(f"must be an integer >= 1, got {n!r}", cfg.get("_config_path"), "batch_periods")
        self.batch_periods = n
        self.cs = np.zeros(C_SIZE)
        self.cs[C_IOVERRIDE] = -1.0
        self.cs[C_COMMAND] = self.cp.command0
        self.cs[C_MODE] = self.cp.mode0
        update_command(self.cs, self.q)
        self.model = None
        self._est_saved = None
        self._next_periods: float | None = None   # period index of the PlantState after the last one decided
        self.skipped_state_gaps = 0               # decides after skipped PlantStates (realtime)
        self.skipped_periods = 0                  # ... and the control periods they covered
        self.command_rejected = False
        self.last_status: dict = {}
        self.seq = 0

    # ---------------------------------------------------------------- commands
    def set_command(self, command: float, mode: int = MODE_RESISTANCE) -> None:
        """Eq. 5 command (0..1) and mode (0 resistance / generating, 1 motoring)."""
        try:
            validate_command(command, mode)
        except ValueError:
            self.command_rejected = True
            raise
        self.command_rejected = False
        self.cs[C_COMMAND] = float(command)
        self.cs[C_MODE] = int(mode)
        update_command(self.cs, self.q)

    def set_current_override(self, current_a: float | None) -> None:
        """Bypass Eq. 2-9 with a fixed current command (paper 000, Fig. 12/13: I* = 35, 50 A)."""
        if current_a is None:
            self.cs[C_IOVERRIDE] = -1.0
        else:
            if not math.isfinite(current_a) or current_a < 0:
                raise ValueError(f"current override must be finite and >= 0, got {current_a!r}")
            self.cs[C_IOVERRIDE] = float(current_a)
        update_command(self.cs, self.q)

    def torque_command_nm(self, speed_rpm: float, command: float = 1.0) -> float:
        """Eq. 3-4 for this controller's Tmax, wb, Pmax."""
        return float(torque_command_nm(command, speed_rpm, self.cp.tmax_nm, self.cp.base_speed_rpm, self.cp.pmax_w))

    def k_factor(self, speed_rpm: float, command: float = 1.0) -> float:
        """Eq. 7 k at this speed and Command."""
        return float(_k_of(float(speed_rpm), float(command), self.q))

    def ktg(self, speed_rpm: float, torque_nm: float | None = None) -> float:
        """Eq. 8-9: ktg = k * kt, k at the Command that asks ``torque_nm`` here (Eq. 3-4; none:
        Command = 1)."""
        command = 1.0 if torque_nm is None else abs(torque_nm) / self.torque_command_nm(speed_rpm)
        return float(ktg_nm_per_a(self.k_factor(speed_rpm, command), self.q[Q_KT]))

    # ---------------------------------------------------------------- the batch
    def _load_model(self, snap: dict) -> float:
        """Overwrite the predictor's state with the measurement; returns the prediction error."""
        cur = np.asarray(snap["phase_current_a"], dtype=np.float64)
        err = 0.0
        if self.model is None:
            self.model = K.new_state(self.p, float(snap["speed_rpm"]), float(snap["battery_soc"]))
            self.model[K.S_VFILT] = float(snap["dc_bus_v"])
        else:
            err = float(np.max(np.abs(cur - self.model[0:3])))
        m = self.model
        m[0:3] = cur
        m[K.S_THETA_E] = float(snap["rotor_angle_elec_rad"])
        m[K.S_OMEGA] = float(snap["speed_rad_s"])
        m[K.S_SPEED_TARGET] = m[K.S_OMEGA]
        m[K.S_VDC] = float(snap["dc_bus_v"])
        m[K.S_SOC] = float(snap["battery_soc"])
        m[K.S_S0] = 1.0 if snap["brake_resistor_on"] else 0.0
        m[K.S_HALL] = float(snap["hall_state"])
        m[K.S_PERIODS] = self._periods_of(snap)
        return err

    def _periods_of(self, snap: dict) -> float:
        """The plant state's period index, from the capture timer (timer = floor(periods * fc * T),
        fc * T >= 1)."""
        fc_dt = self.nominal.hall.timer_hz * self.nominal.control_period_s
        return float(math.ceil(int(snap["timer_count"]) / fc_dt - 1e-9))

    def gap_periods(self, snapshot: dict) -> int:
        """Control periods of the PlantStates skipped before ``snapshot`` (realtime: the plant ran
        them while this controller was descheduled); 0 for the state after the last one decided
        (lockstep, always)."""
        periods = self._periods_of(snapshot)
        if self._next_periods is None or periods <= self._next_periods:
            return 0
        return int(periods - self._next_periods)

    def _note_skipped_states(self, snapshot: dict) -> None:
        """A PlantState later than the one after the last decided (realtime: the controller reads
        the newest only, and skips what came while it was descheduled): the Hall edges of the
        skipped batches are lost. This state carries the edges of the batch before it only, so
        Eq. 1 intervals start again from that batch's start (C_EDGES_FROM). Left as it was, the
        first edge after the gap measured nc over every lost edge: a third of the speed or less
        for a batch or two (ERG's virtual speed, an app's km/h, fell to 2-9 of ~28 km/h)."""
        gap = self.gap_periods(snapshot)
        if gap == 0:
            return
        n_before = int(snapshot.get("batch_periods") or self.batch_periods)
        fc_dt = self.nominal.hall.timer_hz * self.nominal.control_period_s
        self.cs[C_EDGES_FROM] = math.floor(max(self.model[K.S_PERIODS] - n_before, 0.0) * fc_dt)
        self.skipped_state_gaps += 1
        self.skipped_periods += gap

    def decide(self, snapshot: dict, n: int | None = None):
        """N periods of (gates_a, gates_b, split) answering PlantState `snapshot`, + status."""
        n = self.batch_periods if n is None else int(n)
        err = self._load_model(snapshot)
        # measured Hall edges replace the ones predicted during the previous batch
        if self._est_saved is not None:
            self.cs[C_LAST_EDGE:C_SPEED_EST + 1] = self._est_saved
        self._note_skipped_states(snapshot)
        for c in snapshot.get("hall_edge_counts", ()):
            process_edge(self.cs, self.q, float(c))
        update_command(self.cs, self.q)
        _bound_speed(self.cs, self.q, self.model, self.p)
        self._est_saved = self.cs[C_LAST_EDGE:C_SPEED_EST + 1].copy()
        self._next_periods = self.model[K.S_PERIODS] + n
        status = self.status(snapshot.get("seq", 0), err)
        ga = np.zeros(n, np.uint8)
        gb = np.zeros(n, np.uint8)
        sp = np.ones(n, np.float64)
        ec = np.zeros(2 * n + 8, np.uint64)
        es = np.zeros(2 * n + 8, np.uint8)
        control_batch(self.cs, self.q, self.model, self.p, ga, gb, sp, ec, es)
        self.last_status = status
        return ga, gb, sp, status

    def status(self, seq: int = 0, prediction_error_a: float = 0.0) -> dict:
        """ControllerStatus fields (header excluded)."""
        cs = self.cs
        return {
            "seq": int(seq),
            "command": float(cs[C_COMMAND]),
            "mode": int(cs[C_MODE]),
            "command_rejected": bool(self.command_rejected),
            "speed_est_rpm": float(cs[C_SPEED_EST]),
            "torque_cmd_nm": float(cs[C_TCMD]),
            "k_factor": float(cs[C_K]),
            "ktg_nm_per_a": float(cs[C_KTG]),
            "current_cmd_a": float(cs[C_ICMD]),
            "region": int(cs[C_REGION]),
            "quadrant": int(cs[C_QUADRANT]),
            "prediction_error_a": float(prediction_error_a),
        }
