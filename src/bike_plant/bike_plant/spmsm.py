"""SPMSM bike (paper 001): dq machine model, inverter, relay + rectifier/buck/charger path, shaft.

Everything that runs once per 100 us control period is a numba kernel
(``@njit(**JIT)``); the controller's predictor and its region
logic call the same functions with the nominal parameter vector (ARCHITECTURE.md).

Machine (paper 001, Eq. 1-6; section 6 parameters), rotor (dq) frame, motor convention:
    vd = Rs id + Ld did/dt - we Lq iq
    vq = Rs iq + Lq diq/dt + we Ld id + we lambda
    Te = 1.5 pp (lambda iq + (Ld - Lq) id iq),   J dwm/dt = Te - B wm - TL,   we = pp wm
Surface magnets: Ld = Lq = L (one ``inductance_h``), so Te = 1.5 pp lambda iq.

Conventions (documented because the paper does not state them):
- dq is the amplitude-invariant Park transform (dq magnitudes are phase peak values), so
  the 1.5 of Eq. 2 holds and ``flux_linkage_vs`` = 0.122 V s/rad is the PEAK phase flux
  linkage of the magnets per electrical radian. Back-EMF at 200 r/min: 15.3 V phase peak,
  26.6 V line-to-line peak ("near 24 V", section 7 / Fig. 19). Read this way the id = 0
  drive saturates at ~175 r/min with 24 V and SVPWM (|v| <= 24/sqrt(3) = 13.86 V).
- Complex notation i = id + j iq, v = vd + j vq: L di/dt = v - (R + j we L) i - j we lambda.

Discretisation (exact for the linear electrical part): over one period the speed is frozen
at w (see the shaft below) and the inverter output is a constant vector in the STATIONARY
frame (average model: the period's mean; switching model: each switch-state segment), i.e.
v_dq(t) = v0 + V1 exp(-j we t) in the rotor frame. Then, with a = R/L, s = a + j we,
    i(t) = p0 + p1 exp(-j we t) + d exp(-s t),  p0 = (v0 - j we lambda) / (L s),
    p1 = V1 / (L a),  d = i(0) - p0 - p1,
exactly (the zero-order hold / matrix exponential of the dq model at frozen speed, with the
rotation of a stationary voltage vector included). The same closed form gives the exact
integrals of i, |i|^2 and v.i over the segment, so copper loss, terminal energy and
electromechanical energy are evaluated exactly, not by quadrature (:func:`segment`).

Shaft: implicit midpoint. The electrical part is solved at the period's mean speed
w_mid = (w0 + w1) / 2, w1 = w0 + T (mean Te + T_ext - B w_mid) / J, by fixed-point
iteration (contraction ~1e-4 per pass: the electrical coupling over 100 us is weak; the
first guess takes a Taylor step of iq with the period's mean voltage, for the switching model
plus the last period's error of that guess, i.e. the ripple's nearly constant share of the
mean torque; the iteration stops when w_mid moves by less than 1e-11 (1 + |w|) rad/s,
typically after 2 solves; the switching model took 3 from last period's acceleration).
A small inertia makes the pass contract slowly or cycle (it contracts by ~(T/2J)(B + Tc/w_s),
0.48 per pass at J = 1e-4 kg m^2 near standstill): then (P_SHAFT_STIFF) each pass is a
friction-Newton step kept inside a bracket of the root (:func:`_stiff_step`).
Electromechanical energy T Te w_mid then equals the kinetic-energy change minus load and
friction work up to T Te * 1e-11 per period, so the ledger closes to ~1e-12 relative
(round-off level).
Between exact evaluations every 64 periods the rotating phasors exp(j theta_e) and
exp(-j we T) are advanced by small-angle rotations (error ~1e-16 per period): sin/cos are
the expensive part of a period, which is otherwise a short chain of complex arithmetic.

Inverter: (a) average model: the three duty cycles of the period give the mean phase
voltages d_x * Vdc; duties are clipped to [0, 1], so the reachable set is the DC-link
HEXAGON (the controller's modulator keeps to the inscribed circle Vdc/sqrt(3), its linear
range). (b) switching model: centre-aligned triangular carrier, one carrier period per
control period (``carrier_multiple`` carrier periods of equal duty per control period),
sampled at the carrier valley (zero vector) so the sampled current is ripple free; each
constant-switch-state segment is integrated exactly, in the stationary frame where its
voltage is constant and, around the rotating particular solution p0 exp(j theta), the decay
is real (:func:`_solve_switching`: two short series per segment, no libm call, the same
result as the rotor-frame :func:`segment` per segment to ~1e-14); optional dead time (edge
delay by the sign of the phase current at the period start). The bridge is lossless while
its gates run (no conduction or switching loss: the battery's energy is the terminals'); its
diodes' drop (``inverter.diode_drop_v``) counts only with the gates off (path 2 below), so
braking through the inverter books none of the converter loss the rectifier path books.

Non-idealities of the real machine and bridge (``spmsm.*`` / ``inverter.dead_time_s``; the
paper gives none of them, config/spmsm_default.yaml documents the chosen values; 0 = the
paper's ideal Eq. 1-6 machine, which is also the controller's model):
- back-EMF 5th / 7th harmonics (ratios k5, k7 of the phase EMF's fundamental, phases phi5,
  phi7): magnet flux linkage lambda (e^{j th} + k5/5 e^{j phi5} e^{-j5 th} + k7/7 e^{j phi7}
  e^{j7 th}) (amplitude-invariant), i.e. in the rotor frame an EMF j we lambda + we g(th) with
  g = j lambda (k7 e^{j(6 th + phi7)} - k5 e^{j(phi5 - 6 th)}) (:func:`emf_harmonic_shape`) and
  a torque 1.5 pp (lambda iq + Re(g conj(i))). Over a period the harmonic EMF is held at the
  period's mid angle (a constant rotor-frame voltage v0 in :func:`segment`; error ~(6 we T)^2
  / 24, 3e-4 of the harmonic at 200 r/min); the energy it converts is exactly the torque's
  work, so the ledger still closes to round-off.
- cogging torque -Tc sin(N theta_m + phi), N = ``cogging_per_rev`` = LCM(36 slots, 12 poles)
  = 36: a conservative torque with co-energy W = -(Tc / N) cos(N theta_m + phi) (counted in
  the stored energy); the period's mean is the exact change of W over the rotation
  (:func:`cogging_mean_torque`), inside the shaft's midpoint iteration.
- Coulomb friction Tc tanh(w / w_s) (bearings, belt, the coupled brake's idle drag) next to
  the viscous B w (:func:`friction_torque`), booked as friction loss.
- dead time: the switching model delays the turn-on edges by the current's sign; the average
  model applies the same mean error, d_x - sign(i_x) * carrier_multiple * td / T.

Regeneration path (paper 001, Fig. 2/8): a relay connects the machine either to the
inverter (motoring / assist, DC link = 24 V battery) or to a 3-phase diode rectifier ->
DC link -> buck converter (output ~25 V) -> charger -> 24 V battery (generating /
braking), with a dump resistor on the 25 V bus taking the power once the battery is full.
Average model of a diode bridge on a stiff DC voltage Vdc: its phase-voltage fundamental is
a vector of magnitude Vr = (2/pi)(Vdc + 2 Vf) opposing the current (six-step waveform), the
DC current is (3/pi)|i|; it conducts when |we| lambda > Vr. (The real bridge starts
conducting in short pulses at sqrt(3) |we| lambda > Vdc + 2 Vf, ~10 % earlier; the
fundamental model is accurate at the currents that matter.) A buck in continuous conduction
with a regulated output makes its input look like Vlink = Vout / D: the buck duty D sets
the rectifier voltage and with it the braking torque.
Relay switch-over is break-before-make (hardware): the active path first drives the current
to zero (inverter: the controller commands zero current; in the safe state the gates are
off and its diodes freewheel into the battery; rectifier path: buck duty at its minimum,
i.e. the link at ``link_max_v``, the diodes block), the relay opens once |i| is below
``relay_open_current_a`` (or after ``drain_timeout_s``, raising FAULT_RELAY_FORCED: at
speeds where the back-EMF exceeds what the path can oppose, zero current is unreachable),
the magnetic energy left is booked as relay loss, the relay stays open ``relay_dead_s``
with both paths off, then closes onto the requested path. Both paths are never connected
at once (S_OVERLAP counts it: always 0).

Loads (``load.kind``): dynamometer (piecewise-constant torque TL(t) of Eq. 3, positive
opposes positive rotation; the paper's 1 N m step; ``dyno_mode`` brake: the passive powder
brake, TL tanh(w / w_s), which holds a stopped shaft (:func:`brake_torque`), drive: a torque
source at any speed), prime_mover (speed held; schedule),
rider (bike_plant.mechanics rider model through :class:`RiderLoad`, evaluated per batch
and held), none. Any Python callable can be the load hook (:class:`SpmsmPlant` load_hook).
In the state and telemetry ``load_torque_nm`` is the torque the load applies to the shaft,
positive accelerating (the BLDC plant's sign); the dynamometer's TL is its negative.

Energy ledger [J], cumulative: mechanical in (load work) = copper + friction + converter
(diodes, buck, charger, relay) losses + battery + dump resistor + stored (kinetic +
magnetic) change; ``residual_j`` closes to round-off.
The pack is an ideal source at ``battery.nominal_v`` whose SOC books energy / (V Q) without
bounds: above 1 through the inverter it is flagged (FAULT_PACK_OVERCHARGE; the charger's dump
keeps the rectifier path from it); at or below 0 too (FAULT_PACK_EMPTY, PlantState's bit of that
name), but nothing in the plant stops the inverter: the session's EmptyPackGuard holds assist at
0 while the pack is empty (a BMS's undervoltage cut-off); a bare speed loop drains on, flagged. The inverter's link is
``inverter.dc_link_v``, a voltage of the pack (the paper: one 24 V set): the config is refused
unless it lies within 0.875..1.2 x ``battery.nominal_v`` (spmsm_params.link_voltage_problem), and so
is a buck bus ``regen.buck_output_v`` outside that span (the charger's input; buck_voltage_problem).
"""
from __future__ import annotations

import cmath
import dataclasses
import math

import numpy as np
from numba import njit

from . import jit as _jit
from . import mechanics
from .heart import RiderHeart
from .jit import JIT, JIT_COLD, JIT_HOT, JIT_INLINE, invalidate_stale_numba_cache, rmul  # noqa: F401
from .params import PACK_EMPTY_SOC, RPM_PER_RAD_S, TWO_PI
from .spmsm_params import (  # noqa: F401 - re-exported: the parameters live there, without numba
    MAX_DYNO_POINTS, SpmsmParams, INVERTER_MODELS, MODULATIONS, OVERMODULATIONS, InverterParams, RegenParams,
    SpmsmBatteryParams, EncoderParams, SPMSM_LOAD_KINDS, SpmsmLoadParams, SpmsmPlantParams,
    plant_params_from_config, nominal_params_from_config)

# numba options of every kernel (bike_plant.jit: FMA contraction and reciprocal division,
# ~30 % faster on the latency-bound serial chains; IEEE NaN / Inf)
invalidate_stale_numba_cache(__file__, [_jit.__file__])
SQRT3 = math.sqrt(3.0)


# ---- flat parameter vector for the kernels ---------------------------------------------
P_PP = 0
P_R = 1                 # actual (scaled) values
P_L = 2
P_LAMBDA = 3
P_DT = 4
P_A = 5                 # R / L
P_EAH = 6               # exp(-a T)
P_J = 7
P_B = 8
P_VDC = 9
P_MODEL = 10            # 0 average, 1 switching
P_MODULATION = 11       # 0 svpwm, 1 sine-triangle (the controller's modulator; informational here)
P_CARRIER = 12
P_DEAD_TIME = 13
P_INV_DIODE_V = 14
P_BUCK_V = 15
P_LINK_MAX = 16
P_RECT_DIODE_V = 17
P_ETA_BUCK = 18
P_ETA_CHG = 19
P_RELAY_DEAD_N = 20     # periods
P_DRAIN_N = 21          # periods
P_BATT_V = 22
P_BATT_CAP_J = 23
P_DUMP_SOC = 24
P_LOAD_KIND = 25        # 0 dynamometer (drive), 1 prime mover, 2 rider / hook (S_TEXT), 3 none, 4 dyno brake
P_CPR = 26
P_FCAP = 27
P_DYNO_N = 28
P_DYNO_T = 29
P_DYNO_TQ = P_DYNO_T + MAX_DYNO_POINTS
P_IEA = P_DYNO_TQ + MAX_DYNO_POINTS     # integral of exp(-a tau) over one period
P_IE2A = P_IEA + 1                      # integral of exp(-2 a tau) over one period
P_RELAY_OPEN_I = P_IE2A + 1
P_EMF_ON = P_RELAY_OPEN_I + 1           # 1: back-EMF harmonics present
P_K5_RE = P_EMF_ON + 1                  # j lambda k5 exp(j phi5) (complex, rotor frame)
P_K5_IM = P_K5_RE + 1
P_K7_RE = P_K5_IM + 1                   # j lambda k7 exp(j phi7)
P_K7_IM = P_K7_RE + 1
P_COG_T = P_K7_IM + 1                   # peak cogging torque [N m]
P_COG_N = P_COG_T + 1                   # periods per mechanical turn
P_COG_PHI = P_COG_N + 1                 # phase [rad]
P_DT_DUTY = P_COG_PHI + 1               # average model: dead-time duty error carrier_multiple * td / T
P_DRY_T = P_DT_DUTY + 1                 # Coulomb friction [N m]
P_DRY_WS = P_DRY_T + 1                  # its smoothing speed [rad/s]
P_COG_SIX = P_DRY_WS + 1                # 1: N = 6 pp, exp(j N theta_m) = exp(j 6 theta_e) (no sincos)
P_COG_C = P_COG_SIX + 1                 # cos / sin of the cogging phase
P_COG_S = P_COG_C + 1
P_IBATT_PER_J = P_COG_S + 1              # 1 / (battery V * T): battery energy of a period -> mean current
P_SOC_PER_J = P_IBATT_PER_J + 1         # 1 / battery capacity [1/J]
P_RAD_PER_COUNT = P_SOC_PER_J + 1       # 2 pi / counts per turn (encoder edge estimate)
P_INV_L = P_RAD_PER_COUNT + 1           # 1 / L, 1 / R (the per-period path multiplies; the same
                                        # numbers as before: fastmath arcp already did x * (1/L))
P_INV_R = P_INV_L + 1
P_TEM_K = P_INV_R + 1                   # 1.5 pp / T (prime mover: torque telemetry / ledger only)
P_SOC_PER_A = P_TEM_K + 1               # T Vbatt / battery capacity: SOC per A of a period
P_DRY_W19 = P_SOC_PER_A + 1             # 19 w_s: beyond it the Coulomb friction's tanh is 1
# the shaft's midpoint iteration (step_period) converges at ~ c = (T / 2J) (B + Tc / w_s + Ke') per pass,
# Ke' = 1.5 pp^2 lambda^2 T / (2L) the torque's response to speed within a period; above SHAFT_STIFF_C
# (a small J: 0.048 at 1e-3 kg m^2, 0.48 at 1e-4 with the default friction) it takes
# friction-Newton steps inside a bracket (_stiff_step), else the plain pass (bit for bit as before)
P_SHAFT_STIFF = P_DRY_W19 + 1           # 1: stiff (the safeguarded iteration)
P_HALF_DT_J = P_SHAFT_STIFF + 1         # T / 2J
P_KE_SPEED = P_HALF_DT_J + 1            # Ke' [N m s/rad]
P_SIZE = P_KE_SPEED + 1
SHAFT_STIFF_C = 0.02

LOAD_DYNO, LOAD_PRIME_MOVER, LOAD_HOOK, LOAD_NONE, LOAD_DYNO_BRAKE = 0, 1, 2, 3, 4


def pack_params(p: SpmsmPlantParams) -> np.ndarray:
    """SpmsmPlantParams -> float64 vector for the kernels (layout P_* above)."""
    v = np.zeros(P_SIZE)
    m = p.spmsm
    r = m.rs_ohm * m.rs_scale
    ind = m.inductance_h * m.inductance_scale
    v[P_PP] = m.pole_pairs
    v[P_R] = r
    v[P_L] = ind
    v[P_LAMBDA] = m.flux_linkage_vs * m.flux_scale
    v[P_DT] = p.control_period_s
    v[P_A] = r / ind
    v[P_EAH] = math.exp(-r / ind * p.control_period_s)
    v[P_IEA] = -math.expm1(-r / ind * p.control_period_s) / (r / ind)
    v[P_IE2A] = -math.expm1(-2.0 * r / ind * p.control_period_s) / (2.0 * r / ind)
    v[P_J] = p.mech.inertia_kgm2
    v[P_B] = p.mech.friction_nms
    inv = p.inverter
    v[P_VDC] = inv.dc_link_v
    v[P_MODEL] = INVERTER_MODELS.index(inv.model)
    v[P_MODULATION] = MODULATIONS.index(inv.modulation)
    v[P_CARRIER] = inv.carrier_multiple
    v[P_DEAD_TIME] = inv.dead_time_s
    v[P_INV_DIODE_V] = inv.diode_drop_v
    rg = p.regen
    v[P_BUCK_V] = rg.buck_output_v
    v[P_LINK_MAX] = rg.link_max_v
    v[P_RECT_DIODE_V] = rg.diode_drop_v
    v[P_ETA_BUCK] = rg.buck_efficiency
    v[P_ETA_CHG] = rg.charger_efficiency
    v[P_RELAY_DEAD_N] = max(1, int(math.ceil(rg.relay_dead_s / p.control_period_s - 1e-9)))
    v[P_DRAIN_N] = max(1, int(math.ceil(rg.drain_timeout_s / p.control_period_s - 1e-9)))
    v[P_RELAY_OPEN_I] = rg.relay_open_current_a
    lam = m.flux_linkage_vs * m.flux_scale
    k5 = 1j * lam * m.emf_harmonic_5 * cmath.exp(1j * math.radians(m.emf_phase_5_deg))
    k7 = 1j * lam * m.emf_harmonic_7 * cmath.exp(1j * math.radians(m.emf_phase_7_deg))
    v[P_EMF_ON] = 1.0 if (m.emf_harmonic_5 > 0.0 or m.emf_harmonic_7 > 0.0) else 0.0
    v[P_K5_RE], v[P_K5_IM], v[P_K7_RE], v[P_K7_IM] = k5.real, k5.imag, k7.real, k7.imag
    v[P_COG_T] = m.cogging_torque_nm
    v[P_COG_N] = m.cogging_per_rev
    v[P_COG_PHI] = math.radians(m.cogging_phase_deg)
    v[P_DT_DUTY] = inv.carrier_multiple * inv.dead_time_s / p.control_period_s
    v[P_DRY_T] = m.dry_friction_nm
    v[P_DRY_WS] = m.dry_friction_speed_rpm / RPM_PER_RAD_S
    v[P_DRY_W19] = 19.0 * v[P_DRY_WS]
    v[P_HALF_DT_J] = 0.5 * p.control_period_s / p.mech.inertia_kgm2
    lam_act = m.flux_linkage_vs * m.flux_scale
    v[P_KE_SPEED] = 1.5 * (m.pole_pairs * lam_act) ** 2 * p.control_period_s / (2.0 * ind)
    # the passive dynamometer brake is smoothed over the same speed as the Coulomb friction
    brake_nm = max(p.load.dyno_torque_nm) if p.load.kind == "dynamometer" and p.load.dyno_mode == "brake" else 0.0
    stiff_c = v[P_HALF_DT_J] * (p.mech.friction_nms + (m.dry_friction_nm + brake_nm) / v[P_DRY_WS]
                                + v[P_KE_SPEED])
    v[P_SHAFT_STIFF] = 1.0 if stiff_c > SHAFT_STIFF_C else 0.0
    v[P_COG_SIX] = 1.0 if m.cogging_per_rev == 6 * m.pole_pairs else 0.0
    v[P_COG_C] = math.cos(math.radians(m.cogging_phase_deg))
    v[P_COG_S] = math.sin(math.radians(m.cogging_phase_deg))
    bt = p.battery
    v[P_BATT_V] = bt.nominal_v
    v[P_BATT_CAP_J] = bt.nominal_v * bt.capacity_ah * 3600.0
    v[P_IBATT_PER_J] = 1.0 / (bt.nominal_v * p.control_period_s)
    v[P_SOC_PER_J] = 1.0 / v[P_BATT_CAP_J]
    v[P_SOC_PER_A] = p.control_period_s * bt.nominal_v * v[P_SOC_PER_J]
    v[P_DUMP_SOC] = bt.dump_above_soc
    kind = p.load.kind
    v[P_LOAD_KIND] = {"dynamometer": LOAD_DYNO if p.load.dyno_mode == "drive" else LOAD_DYNO_BRAKE,
                      "prime_mover": LOAD_PRIME_MOVER, "rider": LOAD_HOOK, "none": LOAD_NONE}[kind]
    v[P_CPR] = p.encoder.counts_per_rev
    v[P_RAD_PER_COUNT] = TWO_PI / p.encoder.counts_per_rev
    v[P_INV_L] = 1.0 / ind
    v[P_INV_R] = 1.0 / r
    v[P_TEM_K] = 1.5 * m.pole_pairs / p.control_period_s
    v[P_FCAP] = p.encoder.capture_timer_hz
    v[P_DYNO_N] = len(p.load.dyno_time_s)
    for k, (t, tq) in enumerate(zip(p.load.dyno_time_s, p.load.dyno_torque_nm)):
        v[P_DYNO_T + k] = t
        v[P_DYNO_TQ + k] = tq
    return v


# =======================================================================================
# state vector
# =======================================================================================
S_ID, S_IQ = 0, 1          # rotor-frame currents [A] (authoritative electrical state)
S_IA, S_IB, S_IC = 2, 3, 4  # phase currents at the period boundary (what the ADC samples)
S_THETA_M = 5              # mechanical angle in [0, 2 pi)
S_REV = 6                  # whole revolutions (signed)
S_OMEGA = 7                # mechanical speed [rad/s]
S_PERIODS = 8              # control periods since start (time = periods * T)
S_ACCEL = 9                # mean acceleration of the last period (midpoint guess)
S_COUNT = 10               # encoder count (integer valued, unwrapped)
S_EDGE_TICKS = 11          # capture-timer ticks of the last encoder edge
S_COS_E, S_SIN_E = 12, 13  # cos / sin of the electrical angle now
S_RELAY = 14               # REL_* state
S_RELAY_FROM = 15          # path connected while draining
S_RELAY_TO = 16            # path to connect after the dead interval
S_RELAY_TIMER = 17         # periods in the current relay state
S_OVERLAP = 18             # periods with both paths connected (must stay 0)
S_RELAY_SWITCHES = 19      # completed switch-overs
S_GATES_OFF = 20           # safe state: inverter gates off
S_SOC = 21
S_SPEED_TARGET = 22        # prime mover [rad/s]
S_TEXT = 23                # hook load torque on the shaft [N m], accelerating positive
S_TEM = 24                 # mean Te of the last period
S_TLOAD = 25               # mean external torque of the last period (accelerating positive)
# 26, 27: the bracket (lo, hi) of a stiff shaft's midpoint iteration (_stiff_step; scratch within a
# period, in the state so that the usual iteration carries no values for it)
S_SHAFT_LO, S_SHAFT_HI = 26, 27
S_IBATT = 28               # mean battery current of the last period, charging positive
S_VLINK = 29               # rectifier DC link of the last period
S_FAULTS = 30
S_ITER = 31                # midpoint iterations used in the last period
S_E_MECH = 32              # ---- ledger, cumulative [J]
S_E_BATT = 33              # into the battery (negative: drawn by the inverter)
S_E_RES = 34               # dump resistor
S_E_CU = 35
S_E_FRIC = 36
S_E_CONV = 37              # diodes + buck + charger + relay losses
S_E_STORED0 = 38
S_E_EM = 39                # electromechanical conversion (diagnostic)
S_E_TERM = 40              # into the machine terminals (diagnostic)
S_MID_RESID = 41           # accumulated midpoint residual (diagnostic, ~1e-16 J)
S_E1H_RE, S_E1H_IM = 42, 43  # exp(-j we T) of the last period (start of the next guess)
S_WE_LAST = 44             # the we it belongs to
S_TCOG = 45                # mean cogging torque of the last period (accelerating positive)
S_TG_CORR = 46             # switching model: last period's mean torque minus its Taylor guess
S_SIZE = 48

REL_INVERTER, REL_RECTIFIER, REL_DRAIN, REL_DEAD = 0, 1, 2, 3
FAULT_RELAY_FORCED = 32      # relay opened under current after the drain timeout
FAULT_OVERSPEED_DIODES = 64  # gates off but the inverter diodes conduct (uncontrolled generation)
FAULT_PACK_OVERCHARGE = 128  # charge into a full pack (SOC > 1) through the inverter: its BMS would open
FAULT_PACK_EMPTY = 256       # SOC at or below params.PACK_EMPTY_SOC (set by SpmsmPlant.snapshot, per batch)

# workspace (switching segments) layout
W_NSEG = 0
W_T = 1                      # 8 * carrier segment durations
W_VA = W_T + 64
W_VB = W_VA + 64
W_PTS = W_VB + 64            # switching_segments: sorted switching instants (<= 8)
WS_SIZE = W_PTS + 8


# =======================================================================================
# model functions shared with the controller
# =======================================================================================
@njit(**JIT)
def zoh_current_coefficients(r_ohm, l_h, dt_s):
    """ZOH discretisation of the decoupled current model L di/dt = -R i + v' (paper 001,
    Eq. 27-47): i(k+1) = a i(k) + b v'(k), a = exp(-R T / L), b = (1 - a) / R."""
    a = math.exp(-r_ohm * dt_s / l_h)
    return a, -math.expm1(-r_ohm * dt_s / l_h) / r_ohm


@njit(**JIT)
def zoh_speed_coefficients(kt_nm_per_a, j_kgm2, b_nms, dt_s):
    """ZOH discretisation of J dw/dt = Kt iq - B w (paper 001, Eq. 7-16, load neglected):
    w(k+1) = a w(k) + b iq(k), a = exp(-B T / J), b = Kt (1 - a) / B (Kt T / J for B = 0)."""
    if b_nms <= 0.0:
        return 1.0, kt_nm_per_a * dt_s / j_kgm2
    a = math.exp(-b_nms * dt_s / j_kgm2)
    return a, -kt_nm_per_a * math.expm1(-b_nms * dt_s / j_kgm2) / b_nms


@njit(**JIT)
def torque_nm(iq_a, p):
    """Eq. 2 with Ld = Lq: Te = 1.5 pp lambda iq."""
    return 1.5 * p[P_PP] * p[P_LAMBDA] * iq_a


@njit(**JIT)
def steady_state_voltage(id_a, iq_a, we, r_ohm, l_h, lam):
    """Eq. 1 at constant current: v = (R + j we L) i + j we lambda (complex dq)."""
    return complex(r_ohm * id_a - we * l_h * iq_a, r_ohm * iq_a + we * (l_h * id_a + lam))


@njit(**JIT)
def rectifier_voltage(vdc, diode_drop_v):
    """Fundamental phase-voltage magnitude of a 6-pulse diode bridge on Vdc: (2/pi)(Vdc + 2 Vf)."""
    return 2.0 / math.pi * (vdc + 2.0 * diode_drop_v)


@njit(**JIT)
def rectifier_steady_state(vr, we, r_ohm, l_h, lam):
    """Steady current (complex dq) of the machine on a diode bridge of fundamental voltage vr:
    0 = -vr u - (R + j we L) i - j we lambda with i = |i| u. Zero unless |we| lambda > vr."""
    e = abs(we) * lam
    if e <= vr:
        return complex(0.0, 0.0)
    z = complex(r_ohm, we * l_h)
    z2 = r_ohm * r_ohm + (we * l_h) ** 2
    disc = (r_ohm * vr) ** 2 - z2 * (vr * vr - e * e)
    mag = (-r_ohm * vr + math.sqrt(max(disc, 0.0))) / z2
    u = complex(0.0, -we * lam) / (z * mag + vr)
    un = abs(u)
    if un > 0.0:
        u = u / un
    return mag * u


@njit(**JIT)
def _one_minus_exp_over(y, t):
    """t (1 - exp(-y)) / y for complex y = s t, series near 0 (no cancellation)."""
    if abs(y) < 0.05:
        # 1 - y/2 + y^2/6 - y^3/24 + y^4/120 - y^5/720 + y^6/5040 - y^7/40320
        s = 1.0 + y * (-1.0 / 2 + y * (1.0 / 6 + y * (-1.0 / 24 + y * (1.0 / 120 + y * (
            -1.0 / 720 + y * (1.0 / 5040 + y * (-1.0 / 40320)))))))
        return t * s
    return t * (1.0 - cmath.exp(-y)) / y


@njit(**JIT_INLINE)
def _cis_neg(x):
    """exp(-j x); Taylor series for |x| < 0.1 (truncation < 1e-24, no libm sincos)."""
    if abs(x) < 0.1:
        x2 = x * x
        c = 1.0 - x2 / 2.0 * (1.0 - x2 / 12.0 * (1.0 - x2 / 30.0 * (1.0 - x2 / 56.0 * (
            1.0 - x2 / 90.0 * (1.0 - x2 / 132.0)))))
        sn = x * (1.0 - x2 / 6.0 * (1.0 - x2 / 20.0 * (1.0 - x2 / 42.0 * (1.0 - x2 / 72.0 * (
            1.0 - x2 / 110.0 * (1.0 - x2 / 156.0))))))
        return complex(c, -sn)
    return complex(math.cos(x), -math.sin(x))


@njit(**JIT_INLINE)
def _int_exp_neg(y, t):
    """t (1 - exp(-y)) / y = integral of exp(-y tau / t) over [0, t] (real y = a t >= 0);
    series for y < 0.05 (no cancellation, truncation < 1e-22)."""
    if y < 0.05:
        return t * (1.0 - y / 2.0 * (1.0 - y / 3.0 * (1.0 - y / 4.0 * (1.0 - y / 5.0 * (1.0 - y / 6.0 * (
            1.0 - y / 7.0 * (1.0 - y / 8.0 * (1.0 - y / 9.0 * (1.0 - y / 10.0)))))))))
    return t * (-math.expm1(-y)) / y


@njit(**JIT_HOT)
def segment(i0, v0, v1, we, t, e1, eat, a, l_h, lam):
    """Exact solution of L di/dt = v0 + v1 exp(-j we tau) - (R + j we L) i - j we lambda over
    [0, t] (speed frozen). e1 = exp(-j we t), eat = exp(-a t) are passed in (callers reuse
    them). Returns (i(t), integral of i, integral of |i|^2, integral of Re(v conj(i)))."""
    p0 = (v0 - complex(0.0, we * lam)) / (l_h * complex(a, we))
    return _segment_p0(i0, v0, p0, v1, we, t, e1, eat, a, l_h)


@njit(**JIT_INLINE)
def _segment_p0(i0, v0, p0, v1, we, t, e1, eat, a, l_h):
    """:func:`segment` with its particular solution p0 = (v0 - j we lambda) / (L s) given
    (constant over a period: the switching model computes it once for all segments)."""
    s = complex(a, we)
    p1 = v1 * (1.0 / (l_h * a))
    d = i0 - p0 - p1
    es = eat * e1
    i1 = p0 + p1 * e1 + d * es
    ie1 = _ie1(we * t, t)                                    # int exp(-j we tau)
    ies = _one_minus_exp_over(s * t, t)                      # int exp(-s tau)
    iea = _int_exp_neg(a * t, t) if a * t > 0.0 else t
    ie2a = _int_exp_neg(2.0 * a * t, t) if a * t > 0.0 else t
    int_i = p0 * t + p1 * ie1 + d * ies
    cp0 = p0.conjugate()
    cp1 = p1.conjugate()
    cd = d.conjugate()
    int_i2 = ((p0.real * p0.real + p0.imag * p0.imag + p1.real * p1.real + p1.imag * p1.imag) * t
              + (d.real * d.real + d.imag * d.imag) * ie2a
              + 2.0 * ((cp0 * p1 * ie1).real + (cp0 * d * ies).real + (cp1 * d).real * iea))
    e_term = (v0 * int_i.conjugate()).real + (v1 * (cp0 * ie1 + cp1 * t + cd * iea)).real
    return i1, int_i, int_i2, e_term


@njit(**JIT_INLINE)
def _rot_small(e1, dx):
    """e1 * exp(-j dx) for |dx| << 1 (series to round-off below 1e-3)."""
    if abs(dx) < 1e-3:
        x2 = dx * dx
        c = 1.0 - 0.5 * x2 + x2 * x2 / 24.0
        s = dx * (1.0 - x2 / 6.0 + x2 * x2 / 120.0)
    else:
        c = math.cos(dx)
        s = math.sin(dx)
    return e1 * complex(c, -s)


@njit(**JIT_INLINE)
def _rot_tel(e1, dx):
    """e1 * exp(-j dx) for the controller's angle compensation: a shorter series below
    0.02 rad (truncation < 1e-18 relative), else :func:`_rot_poly`."""
    if abs(dx) < 0.02:
        x2 = dx * dx
        c = 1.0 - x2 * (0.5 - x2 * (1.0 / 24.0 - x2 * (1.0 / 720.0)))
        s = dx * (1.0 - x2 * (1.0 / 6.0 - x2 * (1.0 / 120.0 - x2 * (1.0 / 5040.0))))
        return e1 * complex(c, -s)
    return _rot_poly(e1, dx)


@njit(**JIT_INLINE)
def _rot_poly(e1, dx):
    """e1 * exp(-j dx) by :func:`_cis_neg` (Taylor below 0.1, no libm sincos): above 0.02 rad
    the controller's angle compensation (spmsm_control.control_period: its
    dx, half a period's electrical angle, is below 0.1 rad up to ~1900 r/min; there the
    series agrees with libm's sincos to the last bit in all but rare cases, and Table 1 of
    `./bike paper seed2-table1` is unchanged; elsewhere the trajectory keeps libm's sincos, a
    last-bit difference grows in the lightly damped predictive loop)."""
    return e1 * _cis_neg(dx)


# =======================================================================================
# inverter
# =======================================================================================
@njit(**JIT)
def duties_to_valphabeta(da, db, dc, vdc):
    """Mean phase voltages d_x Vdc -> amplitude-invariant (alpha, beta) vector (common mode drops)."""
    va = da * vdc
    vb = db * vdc
    vc = dc * vdc
    return complex((2.0 * va - vb - vc) / 3.0, (vb - vc) / SQRT3)


@njit(**JIT)
def _clip01(x):
    if not (x >= 0.0):      # also NaN
        return 0.0
    if x > 1.0:
        return 1.0
    return x


@njit(**JIT_HOT)
def _leg_edges(d, cur, hc, td):
    """Turn-on / turn-off instants (r, f) of one leg within a carrier period of hc, the
    turn-on edge delayed by the dead time td through the diode the current sign picks."""
    r = 0.5 * (1.0 - d) * hc
    f = 0.5 * (1.0 + d) * hc
    if td > 0.0:
        # both switches off for td after each turn-off: the diode picked by the current
        # sign holds the leg (i > 0 out of the leg: low; i < 0: high)
        if cur > 0.0:
            r += td
        elif cur < 0.0:
            f += td
        else:
            r += 0.5 * td
            f += 0.5 * td
        if f > hc:
            # the low pulse, [f, hc) here and [0, r) of the next (identical) carrier, starts late
            # by what runs past this carrier's end: taken off its [0, r) part (the volt-seconds
            # exact, the pulse moved by at most td). Clipped at hc, a duty above 1 - 2 td / hc with
            # i < 0 lost up to td / hc of its dead-time error (0.08 V of a leg's 0.36 V at 0.98)
            r = max(r - (f - hc), 0.0)
            f = hc
    return min(max(r, 0.0), hc), min(max(f, 0.0), hc)


@njit(**JIT_INLINE)
def _sort3(t0, l0, t1, l1, t2, l2):
    """Three (instant, leg) pairs in ascending order of the instant (sorting network)."""
    if t1 < t0:
        t0, l0, t1, l1 = t1, l1, t0, l0
    if t2 < t1:
        t1, l1, t2, l2 = t2, l2, t1, l1
    if t1 < t0:
        t0, l0, t1, l1 = t1, l1, t0, l0
    return t0, l0, t1, l1, t2, l2


@njit(**JIT_INLINE)
def _emit_segment(ws, ns, t, sa, sb, sc, vdc):
    """Append a segment of duration t with leg states (sa, sb, sc) unless it is empty."""
    if t <= 0.0:
        return ns
    ws[W_T + ns] = t
    ws[W_VA + ns] = vdc * (2.0 * sa - sb - sc) / 3.0
    ws[W_VB + ns] = vdc * (sb - sc) / SQRT3
    return ns + 1


@njit(**JIT_INLINE)
def switching_segments(da, db, dc, ia, ib, ic, p, ws):
    """Constant-switch-state segments of one control period (centre-aligned carrier, dead
    time by current sign) into ws: count, durations, (alpha, beta) voltages. No allocation.

    The common case, every leg switching and every turn-on before every turn-off, takes the
    turn-on and the turn-off instants each through a 3-element sorting network; the rest
    (a leg that stays off, dead time that interleaves the edges of small duties) the general
    merge (:func:`_switching_segments_sorted`). Both give the same segments bit for bit."""
    m = int(p[P_CARRIER])
    hc = p[P_DT] / m
    td = p[P_DEAD_TIME]
    vdc = p[P_VDC]
    tr0, tf0 = _leg_edges(da, ia, hc, td)
    tr1, tf1 = _leg_edges(db, ib, hc, td)
    tr2, tf2 = _leg_edges(dc, ic, hc, td)
    if not (tf0 > tr0 and tf1 > tr1 and tf2 > tr2 and max(tr0, max(tr1, tr2)) <= min(tf0, min(tf1, tf2))):
        return _switching_segments_sorted(tr0, tf0, tr1, tf1, tr2, tf2, hc, m, vdc, ws)
    r0, k0, r1, k1, r2, k2 = _sort3(tr0, 0, tr1, 1, tr2, 2)
    f0, j0, f1, j1, f2, j2 = _sort3(tf0, 0, tf1, 1, tf2, 2)
    ns = _emit_segment(ws, 0, r0, 0.0, 0.0, 0.0, vdc)
    sa = 1.0 if k0 == 0 else 0.0
    sb = 1.0 if k0 == 1 else 0.0
    sc = 1.0 if k0 == 2 else 0.0
    ns = _emit_segment(ws, ns, r1 - r0, sa, sb, sc, vdc)
    sa = 1.0 if k2 != 0 else 0.0                           # two legs on: all but the last
    sb = 1.0 if k2 != 1 else 0.0
    sc = 1.0 if k2 != 2 else 0.0
    ns = _emit_segment(ws, ns, r2 - r1, sa, sb, sc, vdc)
    ns = _emit_segment(ws, ns, f0 - r2, 1.0, 1.0, 1.0, vdc)
    sa = 1.0 if j0 != 0 else 0.0                           # the first leg off
    sb = 1.0 if j0 != 1 else 0.0
    sc = 1.0 if j0 != 2 else 0.0
    ns = _emit_segment(ws, ns, f1 - f0, sa, sb, sc, vdc)
    sa = 1.0 if j2 == 0 else 0.0                           # only the last leg still on
    sb = 1.0 if j2 == 1 else 0.0
    sc = 1.0 if j2 == 2 else 0.0
    ns = _emit_segment(ws, ns, f2 - f1, sa, sb, sc, vdc)
    ns = _emit_segment(ws, ns, hc - f2, 0.0, 0.0, 0.0, vdc)
    return _repeat_carrier(ws, ns, m)


@njit(**JIT_HOT)
def _repeat_carrier(ws, ns, m):
    """The carrier periods of one control period are identical (equal duties): copy the
    first one's ns segments m - 1 times; store and return the count."""
    n1 = ns
    for c in range(1, m):
        for k in range(n1):
            ws[W_T + ns] = ws[W_T + k]
            ws[W_VA + ns] = ws[W_VA + k]
            ws[W_VB + ns] = ws[W_VB + k]
            ns += 1
    ws[W_NSEG] = ns
    return ns


@njit(**JIT_HOT)
def _switching_segments_sorted(tr0, tf0, tr1, tf1, tr2, tf2, hc, m, vdc, ws):
    """:func:`switching_segments` for any edge order: the <= 8 instants sorted in ws[W_PTS:],
    each segment's switch state from its midpoint."""
    on0 = tf0 > tr0
    on1 = tf1 > tr1
    on2 = tf2 > tr2
    n = 0
    ws[W_PTS] = 0.0
    n += 1
    if on0:
        ws[W_PTS + n] = tr0
        ws[W_PTS + n + 1] = tf0
        n += 2
    if on1:
        ws[W_PTS + n] = tr1
        ws[W_PTS + n + 1] = tf1
        n += 2
    if on2:
        ws[W_PTS + n] = tr2
        ws[W_PTS + n + 1] = tf2
        n += 2
    ws[W_PTS + n] = hc
    n += 1
    # insertion sort (<= 8 values)
    for i in range(1, n):
        v = ws[W_PTS + i]
        j = i - 1
        while j >= 0 and ws[W_PTS + j] > v:
            ws[W_PTS + j + 1] = ws[W_PTS + j]
            j -= 1
        ws[W_PTS + j + 1] = v
    ns = 0
    for k in range(n - 1):
        t = ws[W_PTS + k + 1] - ws[W_PTS + k]
        if t <= 0.0:
            continue
        mid = 0.5 * (ws[W_PTS + k] + ws[W_PTS + k + 1])
        sa = 1.0 if (on0 and tr0 <= mid < tf0) else 0.0
        sb = 1.0 if (on1 and tr1 <= mid < tf1) else 0.0
        sc = 1.0 if (on2 and tr2 <= mid < tf2) else 0.0
        ws[W_T + ns] = t
        ws[W_VA + ns] = vdc * (2.0 * sa - sb - sc) / 3.0
        ws[W_VB + ns] = vdc * (sb - sc) / SQRT3
        ns += 1
    return _repeat_carrier(ws, ns, m)


@njit(**JIT_INLINE)
def _solve_switching(i0, ej0, we, p, ws, v0):
    """Exact solution of Eq. 1 through the switching segments in ws (rotor angle exp(j theta0)
    = ej0, speed frozen at we); v0: a rotor-frame voltage held over the period (minus the
    back-EMF harmonics). Returns (i1, integral of i, integral of |i|^2, integral of
    Re(v conj(i))), all in the rotor (dq) frame, like :func:`segment`.

    Solved in the stationary frame, where each segment's inverter voltage v_k is constant:
    with x = i exp(j theta), L dx/dt = v_k - R x + L s P exp(j theta), s = R/L + j we and
    P = (v0 - j we lambda) / (L s) the rotor-frame particular solution. The deviation
    z = x - P exp(j theta) then obeys L dz/dt = v_k - R z: a REAL decay exp(-a tau) per
    segment, so a segment costs two short series (int exp(-a tau), int exp(-j we tau)) and
    no libm call; the rotor-frame integrals follow in closed form from the same two."""
    a = p[P_A]
    inv_l = p[P_INV_L]
    inv_r = p[P_INV_R]
    ns = int(ws[W_NSEG])
    den = a * a + we * we
    inv_s = complex(a / den, -we / den)
    pp0 = complex(v0.real * inv_l, (v0.imag - we * p[P_LAMBDA]) * inv_l) * inv_s
    rot = ej0.conjugate()              # exp(-j theta) at the segment start
    z = (i0 - pp0) * ej0               # stationary deviation from the particular solution
    zi = complex(0.0, 0.0)             # integral of z exp(-j theta)
    z2 = 0.0                           # integral of |z|^2
    et = 0.0                           # integral of Re(v_k conj(x))
    cp = pp0.conjugate()
    t = p[P_DT]
    series = a * t < 0.05 and abs(we) * t < 0.05        # every segment is shorter than t
    for k in range(ns):
        d = ws[W_T + k]
        va = ws[W_VA + k]
        vb = ws[W_VB + k]
        if series:
            # the series of _int_exp_neg and _ie1 written out (truncation < 1e-18 relative at
            # 0.05): without their per-call branch the solve takes ~106 ns, with the calls ~125
            y = a * d
            f1 = d * (1.0 - y * (1.0 / 2 - y * (1.0 / 6 - y * (1.0 / 24 - y * (1.0 / 120 - y * (
                1.0 / 720 - y * (1.0 / 5040 - y * (1.0 / 40320 - y * (1.0 / 362880)))))))))
            x = we * d
            x2 = x * x
            gw = complex(d * (1.0 - x2 * (1.0 / 6 - x2 * (1.0 / 120 - x2 * (1.0 / 5040 - x2 * (1.0 / 362880))))),
                         -d * x * (0.5 - x2 * (1.0 / 24 - x2 * (1.0 / 720 - x2 * (1.0 / 40320)))))
        else:
            f1 = _int_exp_neg(a * d, d)                    # int exp(-a tau)
            gw = _ie1(we * d, d)                           # int exp(-j we tau)
        ea = 1.0 - a * f1                                  # exp(-a d), no cancellation in f1
        jwg = complex(-we * gw.imag, we * gw.real)          # j we gw = 1 - exp(-j we d)
        # int exp(-s tau) = (1 - exp(-a d) exp(-j we d)) / s, the numerator as a f1 + exp(-a d) j we gw
        gs = (a * f1 + ea * jwg) * inv_s
        if va == 0.0 and vb == 0.0:
            # a zero vector (3 of a carrier's 7 segments): z decays freely; the general branch's bits
            # (what its v_k terms add is an exact zero), ~50 fewer operations
            zi += z * (rot * gs)
            z2 += rmul(z.real * z.real + z.imag * z.imag, 0.5 * f1 * (1.0 + ea))
            z = complex(rmul(z.real, ea), rmul(z.imag, ea))
        else:
            # a complex times a float as rmul of each part: the bits of numba's complex * float with
            # half its products (bike_plant.jit.rmul)
            q = complex(rmul(va, inv_r), rmul(vb, inv_r))      # the segment's equilibrium v_k / R
            w = z - q
            rg = rot * gw
            zi += q * rg + w * (rot * gs)
            # integral of x over the segment
            ix = (cp * rg).conjugate() + complex(rmul(q.real, d), rmul(q.imag, d)) + complex(rmul(w.real, f1),
                                                                                           rmul(w.imag, f1))
            et += va * ix.real + vb * ix.imag
            z2 += ((q.real * q.real + q.imag * q.imag) * d + 2.0 * (q.real * w.real + q.imag * w.imag) * f1
                   + (w.real * w.real + w.imag * w.imag) * (0.5 * f1 * (1.0 + ea)))
            c = inv_l * f1
            z = complex(rmul(z.real, ea) + rmul(va, c), rmul(z.imag, ea) + rmul(vb, c))
        rot = rot * (1.0 - jwg)
    i1 = pp0 + z * rot
    int_i = pp0 * t + zi
    int_i2 = (pp0.real * pp0.real + pp0.imag * pp0.imag) * t + 2.0 * (cp * zi).real + z2
    e_term = et + v0.real * int_i.real + v0.imag * int_i.imag
    return i1, int_i, int_i2, e_term


@njit(**JIT)
def _ie1(x, t):
    """t (1 - exp(-j x)) / (j x) = t (sin x / x + j (cos x - 1) / x), series below 0.05."""
    if abs(x) < 0.05:
        x2 = x * x
        re = 1.0 - x2 / 6.0 * (1.0 - x2 / 20.0 * (1.0 - x2 / 42.0 * (1.0 - x2 / 72.0)))
        im = -0.5 * x * (1.0 - x2 / 12.0 * (1.0 - x2 / 30.0 * (1.0 - x2 / 56.0)))
        return complex(t * re, t * im)
    return complex(t * math.sin(x) / x, t * (math.cos(x) - 1.0) / x)


@njit(**JIT_INLINE)
def _avg_eval(i0, v0, v1, we, e1, p):
    """Fast form of :func:`segment` for one full period (average inverter; v0: minus the
    back-EMF harmonics, 0 for a sinusoidal machine):
    the end current and the integral of i (what the midpoint iteration needs), plus the
    closed-form coefficients for :func:`_avg_energy`."""
    a = p[P_A]
    t = p[P_DT]
    den = a * a + we * we
    inv_s = complex(a / den, -we / den)
    inv_l = p[P_INV_L]
    p0 = complex(v0.real * inv_l, (v0.imag - we * p[P_LAMBDA]) * inv_l) * inv_s
    p1 = v1 * p[P_INV_R]                     # v1 / (L a)
    d = i0 - p0 - p1
    es = p[P_EAH] * e1
    i1 = p0 + p1 * e1 + d * es
    ie1 = _ie1(we * t, t)
    ies = (1.0 - es) * inv_s
    int_i = p0 * t + p1 * ie1 + d * ies
    return i1, int_i, p0, p1, d, ie1, ies


@njit(**JIT_INLINE)
def _avg_energy(p0, p1, d, ie1, ies, v1, p):
    """Integral of |i|^2 and of Re(v conj(i)) for the :func:`_avg_eval` solution."""
    t = p[P_DT]
    iea = p[P_IEA]
    cp0 = p0.conjugate()
    cp1 = p1.conjugate()
    int_i2 = ((p0.real * p0.real + p0.imag * p0.imag + p1.real * p1.real + p1.imag * p1.imag) * t
              + (d.real * d.real + d.imag * d.imag) * p[P_IE2A]
              + 2.0 * ((cp0 * p1 * ie1).real + (cp0 * d * ies).real + (cp1 * d).real * iea))
    e_term = (v1 * (cp0 * ie1 + cp1 * t + d.conjugate() * iea)).real
    return int_i2, e_term


# =======================================================================================
# diode bridge (rectifier path, or the inverter's freewheel diodes with the gates off)
# =======================================================================================
@njit(**JIT_HOT)
def _solve_diode_bridge(i0, we, vr, t, p, vh):
    """Machine on a diode bridge of fundamental voltage vr over t (average model, see module
    docstring). The voltage vector -vr u is held over the period with u the current's
    direction at its start (the steady-state direction when starting from zero). If the
    current would reverse against the diodes, the bridge blocks at that instant (bisection on
    the closed form): the current goes to exactly zero and the small magnetic energy left in
    the perpendicular component is returned as loss (diode reverse recovery / snubber).
    vh: minus the back-EMF harmonics, held over the period (added to the bridge voltage).
    Returns (i1, int_i, int_i2, e_term, loss_j)."""
    a = p[P_A]
    lh = p[P_L]
    lam = p[P_LAMBDA]
    conducting = abs(we) * lam > vr
    z0 = complex(0.0, 0.0)
    e1 = complex(math.cos(we * t), -math.sin(we * t))
    eat = math.exp(-a * t)
    if i0.real == 0.0 and i0.imag == 0.0:
        if not conducting:
            return z0, z0, 0.0, 0.0, 0.0
        # conduction starts: the current grows along the EMF-driven transient, not yet along
        # the steady-state direction; take the direction the period ends in (two passes)
        u = rectifier_steady_state(vr, we, p[P_R], lh, lam)
        u = u / abs(u)
        for _ in range(2):
            i1, ii, ii2, et = segment(i0, vh - vr * u, z0, we, t, e1, eat, a, lh, lam)
            if abs(i1) > 0.0:
                u = i1 / abs(i1)
        i1, ii, ii2, et = segment(i0, vh - vr * u, z0, we, t, e1, eat, a, lh, lam)
        return i1, ii, ii2, et, 0.0
    u = i0 / abs(i0)
    v0 = vh - vr * u
    i1, ii, ii2, et = segment(i0, v0, z0, we, t, e1, eat, a, lh, lam)
    cu = u.conjugate()
    if (i1 * cu).real >= 0.0:
        return i1, ii, ii2, et, 0.0
    # the current reverses against the diodes: find the blocking instant
    lo = 0.0
    hi = t
    for _ in range(48):
        mid = 0.5 * (lo + hi)
        e1m = complex(math.cos(we * mid), -math.sin(we * mid))
        im, _a, _b, _c = segment(i0, v0, z0, we, mid, e1m, math.exp(-a * mid), a, lh, lam)
        if (im * cu).real > 0.0:
            lo = mid
        else:
            hi = mid
    tz = lo
    e1z = complex(math.cos(we * tz), -math.sin(we * tz))
    iz, ii, ii2, et = segment(i0, v0, z0, we, tz, e1z, math.exp(-a * tz), a, lh, lam)
    loss = 0.75 * lh * (iz.real * iz.real + iz.imag * iz.imag)
    return z0, ii, ii2, et, loss


# =======================================================================================
# one control period
# =======================================================================================
@njit(**JIT_HOT)
def dyno_torque_nm(t_s, p):
    """TL(t) of the dynamometer profile (piecewise constant; 0 before the first point)."""
    n = int(p[P_DYNO_N])
    tl = 0.0
    for k in range(n):
        if t_s + 1e-12 >= p[P_DYNO_T + k]:
            tl = p[P_DYNO_TQ + k]
    return tl


@njit(**JIT_HOT)
def stored_energy(state, p):
    """Kinetic + magnetic energy: 0.5 J w^2 + 0.75 L |i|^2 (amplitude-invariant dq), plus the
    cogging co-energy W(theta) = -(Tc / N) cos(N theta + phi) (the cogging torque is -dW/dtheta)."""
    e = 0.5 * p[P_J] * state[S_OMEGA] ** 2 + 0.75 * p[P_L] * (state[S_ID] ** 2 + state[S_IQ] ** 2)
    if p[P_COG_T] != 0.0:
        e -= p[P_COG_T] / p[P_COG_N] * math.cos(p[P_COG_N] * state[S_THETA_M] + p[P_COG_PHI])
    return e


@njit(**JIT_HOT)
def emf_harmonic_shape(ej, x, p):
    """g with back-EMF harmonics E_h = we g (rotor frame) at the electrical angle th + x,
    exp(j th) = ej: g = j lambda (k7 exp(j (6 th + phi7)) - k5 exp(j (phi5 - 6 th)))."""
    e2 = ej * ej
    h6 = e2 * e2 * e2 * complex(math.cos(6.0 * x), math.sin(6.0 * x))
    return complex(p[P_K7_RE], p[P_K7_IM]) * h6 - complex(p[P_K5_RE], p[P_K5_IM]) * h6.conjugate()


@njit(**JIT)
def _sixth(ej0, e1h):
    """exp(j 6 th_mid) = exp(j th0)^6 conj(exp(-j we T))^3: the sixth harmonic's phasor at
    the period's mid angle from the phasors the period already has (no sincos)."""
    e2 = ej0 * ej0
    c = e1h.conjugate()
    return e2 * e2 * e2 * (c * c * c)


@njit(**JIT_INLINE)
def _harmonic_g(h6, p):
    """:func:`emf_harmonic_shape` from exp(j 6 th) = h6."""
    return complex(p[P_K7_RE], p[P_K7_IM]) * h6 - complex(p[P_K5_RE], p[P_K5_IM]) * h6.conjugate()


@njit(**JIT)
def _sinc(x):
    if abs(x) < 0.1:
        x2 = x * x
        return 1.0 - x2 / 6.0 * (1.0 - x2 / 20.0 * (1.0 - x2 / 42.0 * (1.0 - x2 / 72.0)))
    return math.sin(x) / x


@njit(**JIT_INLINE)
def _cogging_mean(th_m0, dtheta, h6, p):
    """:func:`cogging_mean_torque`, without sincos when N = 6 pp (h6 = exp(j 6 th_e,mid))."""
    if p[P_COG_SIX] != 0.0:
        sn = h6.real * p[P_COG_S] + h6.imag * p[P_COG_C]          # sin(N th_mid + phi)
        return -p[P_COG_T] * sn * _sinc(0.5 * p[P_COG_N] * dtheta)
    return cogging_mean_torque(th_m0, dtheta, p)


@njit(**JIT_HOT)
def cogging_mean_torque(theta_m0, dtheta, p):
    """Mean cogging torque over the rotation theta_m0 -> theta_m0 + dtheta (exact: the change of
    W over dtheta), T(theta) = -Tc sin(N theta + phi)."""
    n = p[P_COG_N]
    x = 0.5 * n * dtheta
    if abs(x) < 1e-3:
        sinc = 1.0 - x * x / 6.0 * (1.0 - x * x / 20.0)
    else:
        sinc = math.sin(x) / x
    return -p[P_COG_T] * math.sin(n * (theta_m0 + 0.5 * dtheta) + p[P_COG_PHI]) * sinc


@njit(**JIT_INLINE)
def _plus_coulomb(f, w, t_nm, p):
    """f + t_nm tanh(w / w_s): a dry torque of magnitude t_nm opposing the rotation, smoothed
    through standstill over w_s (spmsm.dry_friction_speed_rpm). Beyond 19 w_s it is t_nm:
    tanh(19) = 1 - 6e-17, so no tanh and no division on that path. The sum is taken here so
    that the product and the add stay one fused step (the kernels' bits)."""
    if w > p[P_DRY_W19]:
        return f + t_nm
    if w < -p[P_DRY_W19]:
        return f - t_nm
    return f + t_nm * math.tanh(w / p[P_DRY_WS])


@njit(**JIT_INLINE)
def friction_torque(w, p):
    """Friction opposing the rotation [N m]: viscous B w (paper 001, Eq. 3) + Coulomb
    Tc tanh(w / w_s) (smoothed through standstill)."""
    f = p[P_B] * w
    if p[P_DRY_T] != 0.0:
        f = _plus_coulomb(f, w, p[P_DRY_T], p)
    return f


@njit(**JIT_HOT)
def brake_torque(w, tl, p):
    """The passive dynamometer's torque opposing the rotation [N m] (load.dyno_mode brake: the
    paper's magnetic-powder brake, section 7): TL tanh(w / w_s), the Coulomb friction's shape
    (_plus_coulomb), so it holds a stopped shaft against up to TL and never turns it; beyond
    19 w_s it is TL, the torque source's value."""
    return _plus_coulomb(0.0, w, tl, p)


@njit(**JIT_COLD)
def _stiff_step(state, wg, wn, p):
    """Next guess of the period's mid speed for a stiff shaft (small J: P_SHAFT_STIFF). The
    midpoint map F(wg) = w0 + (T / 2J)(torques at wg) falls with wg (friction, back-EMF), so the
    root lies between wg and F(wg) = wn: the bracket (lo, hi) narrows to it. The step is Newton's
    on the friction's and the EMF's slope, (wn - wg) / (1 + (T / 2J)(B + Tc / w_s sech^2 + Ke')),
    bisected when it leaves the bracket. The plain pass wg <- wn contracts by that factor's
    denominator - 1 and cycled beyond 1: with J = 1e-5 kg m^2 and the default Coulomb friction
    the shaft never settled (|w| 1 rad/s at rest, the ledger 5e-4 J off after 0.2 s). The
    bracket lives in state[S_SHAFT_LO / HI]; out of line, so the usual pass carries none of it."""
    _jit.out_of_line()
    if wn > wg:
        state[S_SHAFT_LO] = wg
    else:
        state[S_SHAFT_HI] = wg
    lo = state[S_SHAFT_LO]
    hi = state[S_SHAFT_HI]
    w = wg
    slope = p[P_B] + p[P_KE_SPEED]
    if p[P_DRY_T] != 0.0 and -p[P_DRY_W19] <= w <= p[P_DRY_W19]:
        th = math.tanh(w / p[P_DRY_WS])
        slope += p[P_DRY_T] / p[P_DRY_WS] * (1.0 - th * th)
    wx = wg + (wn - wg) / (1.0 + p[P_HALF_DT_J] * slope)
    if not (lo < wx < hi):
        wx = 0.5 * (lo + hi)
    return wx


@njit(**JIT)
def _sgn(x):
    if x > 0.0:
        return 1.0
    if x < 0.0:
        return -1.0
    return 0.0


@njit(**JIT_HOT)
def _set_angle_outputs(state, p):
    """cos/sin of the electrical angle and the phase currents from (id, iq)."""
    th = p[P_PP] * state[S_THETA_M]
    _set_phase_currents(state, math.cos(th), math.sin(th))


@njit(**JIT_INLINE)
def _set_phase_currents(state, c, s):
    state[S_COS_E] = c
    state[S_SIN_E] = s
    ial = state[S_ID] * c - state[S_IQ] * s
    ibe = state[S_ID] * s + state[S_IQ] * c
    state[S_IA] = ial
    state[S_IB] = -0.5 * ial + 0.5 * SQRT3 * ibe
    state[S_IC] = -0.5 * ial - 0.5 * SQRT3 * ibe


@njit(**JIT)
def init_state(state, p, speed_rad_s, soc0, theta_m):
    state[:] = 0.0
    state[S_OMEGA] = speed_rad_s
    state[S_SPEED_TARGET] = speed_rad_s
    th = theta_m % TWO_PI
    state[S_THETA_M] = th
    state[S_COUNT] = math.floor(th * p[P_CPR] / TWO_PI)
    state[S_SOC] = soc0
    state[S_RELAY] = REL_INVERTER
    state[S_RELAY_TO] = REL_INVERTER
    _set_angle_outputs(state, p)
    state[S_E_STORED0] = stored_energy(state, p)


@njit(**JIT_HOT)
def _relay_update(state, p, relay_request):
    """Break-before-make relay sequencing at the period start. Returns the active path:
    0 inverter, 1 rectifier, 2 inverter freewheel (gates off), 3 rectifier draining, 4 open."""
    req = REL_RECTIFIER if relay_request >= 0.5 else REL_INVERTER
    rel = int(state[S_RELAY])
    if (rel == REL_INVERTER or rel == REL_RECTIFIER) and req != rel:
        state[S_RELAY_FROM] = rel
        state[S_RELAY_TO] = req
        state[S_RELAY] = REL_DRAIN
        state[S_RELAY_TIMER] = 0.0
        rel = REL_DRAIN
    if rel == REL_DRAIN:
        state[S_RELAY_TO] = req      # the latest request wins after the dead interval
        i2 = state[S_ID] ** 2 + state[S_IQ] ** 2
        forced = state[S_RELAY_TIMER] >= p[P_DRAIN_N]
        if i2 <= p[P_RELAY_OPEN_I] ** 2 or forced:
            # the relay opens: the contacts / snubber take what magnetic energy is left
            # (exactly zero after a diode drain; ~1e-9 J below the opening current)
            state[S_E_CONV] += 0.75 * p[P_L] * i2
            state[S_ID] = 0.0
            state[S_IQ] = 0.0
            if forced and i2 > p[P_RELAY_OPEN_I] ** 2:
                state[S_FAULTS] = int(state[S_FAULTS]) | FAULT_RELAY_FORCED
            state[S_RELAY] = REL_DEAD
            state[S_RELAY_TIMER] = 0.0
            rel = REL_DEAD
            _set_angle_outputs(state, p)
    if rel == REL_DEAD:
        if state[S_RELAY_TIMER] >= p[P_RELAY_DEAD_N]:
            rel = int(state[S_RELAY_TO]) if state[S_RELAY_TO] == REL_RECTIFIER else REL_INVERTER
            state[S_RELAY] = rel
            state[S_RELAY_TIMER] = 0.0
            state[S_RELAY_SWITCHES] += 1.0
    on_inv = rel == REL_INVERTER or (rel == REL_DRAIN and state[S_RELAY_FROM] == REL_INVERTER)
    on_rect = rel == REL_RECTIFIER or (rel == REL_DRAIN and state[S_RELAY_FROM] == REL_RECTIFIER)
    if on_inv and on_rect:
        state[S_OVERLAP] += 1.0
    if rel == REL_INVERTER:
        return 2 if state[S_GATES_OFF] != 0.0 else 0
    if rel == REL_RECTIFIER:
        return 1
    if rel == REL_DRAIN:
        if state[S_RELAY_FROM] == REL_INVERTER:
            return 2 if state[S_GATES_OFF] != 0.0 else 0     # inverter drives the current to zero
        return 3
    return 4


@njit(**JIT_HOT)
def _electrical(path, i0, ej0, v0, v1, we, e1h, p, ws, vr):
    """Electrical solution of the period on the active path at frozen speed we; v0: minus
    the back-EMF harmonics (rotor frame, held). Returns (i1, int_i, int_i2, e_term, loss_j),
    e_term including v0's share (the caller removes it)."""
    dt = p[P_DT]
    z0 = complex(0.0, 0.0)
    if path == 0:
        if p[P_MODEL] == 0.0:
            i1, ii, ii2, et = segment(i0, v0, v1, we, dt, e1h, p[P_EAH], p[P_A], p[P_L], p[P_LAMBDA])
        else:
            i1, ii, ii2, et = _solve_switching(i0, ej0, we, p, ws, v0)
        return i1, ii, ii2, et, 0.0
    if path == 4:
        return z0, z0, 0.0, 0.0, 0.0
    return _solve_diode_bridge(i0, we, vr, dt, p, v0)


@njit(**JIT_INLINE)
def step_period(state, p, da, db, dc, relay_request, buck_duty, ws):
    """One control period of the plant: relay sequencing, electrical (exact at frozen speed),
    shaft (implicit midpoint), DC side, encoder, ledger. ws: float64[WS_SIZE] scratch."""
    dt = p[P_DT]
    pp = p[P_PP]
    if state[S_RELAY] == REL_INVERTER and relay_request < 0.5:
        path = 2 if state[S_GATES_OFF] != 0.0 else 0       # common case: nothing to sequence
    else:
        path = _relay_update(state, p, relay_request)
    # exact sincos every 64 periods; in between, phasors are rotated (error ~1e-16 per period)
    resync = (int(state[S_PERIODS]) & 63) == 0
    t0 = state[S_PERIODS] * dt
    i0 = complex(state[S_ID], state[S_IQ])
    ej0 = complex(state[S_COS_E], state[S_SIN_E])
    # ---- inputs of the active path
    v1 = complex(0.0, 0.0)
    vr = 0.0
    vlink = 0.0
    if path == 0:
        if p[P_MODEL] == 0.0:
            da = _clip01(da)
            db = _clip01(db)
            dc = _clip01(dc)
            kd = p[P_DT_DUTY]
            if kd > 0.0:
                # mean dead-time error of each leg: the diode picked by the current sign holds
                # the leg for td after every turn-off (as the switching model's edge shift)
                da = _clip01(da - kd * _sgn(state[S_IA]))
                db = _clip01(db - kd * _sgn(state[S_IB]))
                dc = _clip01(dc - kd * _sgn(state[S_IC]))
            vab = duties_to_valphabeta(da, db, dc, p[P_VDC])
            v1 = vab * ej0.conjugate()
        else:
            switching_segments(_clip01(da), _clip01(db), _clip01(dc), state[S_IA], state[S_IB], state[S_IC], p, ws)
            # the period's mean voltage vector (the shaft guess; the solution uses the segments)
            va_s = 0.0
            vb_s = 0.0
            for k in range(int(ws[W_NSEG])):
                va_s += rmul(ws[W_VA + k], ws[W_T + k])        # (numba's complex * float's bits, bike_plant.jit)
                vb_s += rmul(ws[W_VB + k], ws[W_T + k])
            v1 = complex(va_s, vb_s) * ej0.conjugate() * (1.0 / dt)
    elif path == 2:
        vlink = p[P_VDC]
        vr = rectifier_voltage(vlink, p[P_INV_DIODE_V])
    elif path == 1 or path == 3:
        dmin = p[P_BUCK_V] / p[P_LINK_MAX]
        d = buck_duty if path == 1 else dmin
        if not (d >= dmin):
            d = dmin
        if d > 1.0:
            d = 1.0
        vlink = p[P_BUCK_V] / d
        vr = rectifier_voltage(vlink, p[P_RECT_DIODE_V])
    # ---- external torque (accelerating positive)
    kind = int(p[P_LOAD_KIND])
    w0 = state[S_OMEGA]
    J = p[P_J]
    B = p[P_B]
    t_ext = 0.0
    tl_brake = 0.0
    if kind == LOAD_DYNO:
        t_ext = -dyno_torque_nm(t0, p)
    elif kind == LOAD_DYNO_BRAKE:
        # opposes the rotation at the period's mid speed (set again in the iteration below)
        tl_brake = dyno_torque_nm(t0, p)
        t_ext = -brake_torque(w0, tl_brake, p)
    elif kind == LOAD_HOOK:
        t_ext = state[S_TEXT]
    # ---- electrical + shaft (implicit midpoint by fixed-point iteration)
    fast = path == 0 and p[P_MODEL] == 0.0          # average inverter: specialised closed form
    z0 = complex(0.0, 0.0)
    p0 = z0
    p1 = z0
    dd = z0
    ie1 = z0
    ies = z0
    ii2 = 0.0
    et = 0.0
    loss = 0.0
    emf_on = p[P_EMF_ON] != 0.0
    cog_on = p[P_COG_T] != 0.0
    gh = z0
    v0 = z0
    tcog = 0.0
    fr = 0.0
    th_m0 = state[S_THETA_M]
    tem_g_raw = 0.0
    if kind == LOAD_PRIME_MOVER:
        wg = w0
        if pp * wg == state[S_WE_LAST] and (state[S_E1H_RE] != 0.0 or state[S_E1H_IM] != 0.0):
            e1h = complex(state[S_E1H_RE], state[S_E1H_IM])     # same speed: same exp(-j we T)
        else:
            x = pp * wg * dt
            e1h = complex(math.cos(x), -math.sin(x))
        h6 = _sixth(ej0, e1h) if (emf_on or cog_on) else z0
        if emf_on:
            gh = _harmonic_g(h6, p)
            v0 = -pp * wg * gh
        if fast:
            i1, ii, p0, p1, dd, ie1, ies = _avg_eval(i0, v0, v1, pp * wg, e1h, p)
        else:
            i1, ii, ii2, et, loss = _electrical(path, i0, ej0, v0, v1, pp * wg, e1h, p, ws, vr)
        # lambda iq's product rounded first, as compiled so far: LLVM picks the product it fuses into the
        # sum by the code around it, and the switching solver's zero-vector branch moved it (last bit)
        tem = p[P_TEM_K] * (rmul(p[P_LAMBDA], ii.imag) + gh.real * ii.real + gh.imag * ii.imag)
        if cog_on:
            tcog = _cogging_mean(th_m0, wg * dt, h6, p)
        fr = friction_torque(wg, p)
        t_ext = fr - tem - tcog
        wn = wg
        w1 = state[S_SPEED_TARGET]
        n_it = 1
    else:
        if path == 0:
            # first guess of the mean torque from a Taylor step of iq with the period's mean
            # voltage (the previous period's acceleration lags the control by a period)
            we0 = pp * w0
            vq_m = (v1 * _rot_small(complex(1.0, 0.0), 0.5 * we0 * dt)).imag
            g0 = z0
            tg = 0.0
            if emf_on or cog_on:
                # harmonics and cogging at the mid angle of last period's rotation (the guess
                # must be good to ~1e-4 N m for the iteration to stop after two solves)
                h6g = _sixth(ej0, complex(state[S_E1H_RE], state[S_E1H_IM]))
                if emf_on:
                    g0 = _harmonic_g(h6g, p)
                    vq_m -= we0 * g0.imag
                if cog_on:
                    tg = _cogging_mean(th_m0, w0 * dt, h6g, p)
            diq = (vq_m - p[P_R] * i0.imag - we0 * (p[P_L] * i0.real + p[P_LAMBDA])) / p[P_L]
            iq_m = i0.imag + 0.5 * dt * diq
            tem_g = 1.5 * pp * (p[P_LAMBDA] * iq_m + g0.real * i0.real + g0.imag * iq_m) + tg
            tem_g_raw = tem_g
            if not fast:
                # the current ripple's share of the mean torque changes little from period to
                # period: last period's error of this guess (2 solves instead of 3)
                tem_g += state[S_TG_CORR]
            wg = (w0 + 0.5 * dt * (tem_g + t_ext - friction_torque(w0, p) + B * w0) / J) / (1.0 + 0.5 * dt * B / J)
        else:
            wg = w0 + 0.5 * dt * state[S_ACCEL]
        if resync:
            x = pp * wg * dt
            e1h = complex(math.cos(x), -math.sin(x))
        else:
            # rotate last period's exp(-j we T) by the small speed change (no sincos)
            e1h = _rot_small(complex(state[S_E1H_RE], state[S_E1H_IM]), (pp * wg - state[S_WE_LAST]) * dt)
        tol = 1e-11 * (1.0 + abs(w0))      # ledger residual ~1e-11 * T Te per period
        n_it = 0
        h6 = z0
        stiff = p[P_SHAFT_STIFF] != 0.0
        n_max = 8
        if _jit.unlikely(stiff):
            n_max = 64
            state[S_SHAFT_LO] = -math.inf
            state[S_SHAFT_HI] = math.inf
        for it in range(n_max):
            if emf_on or cog_on:
                h6 = _sixth(ej0, e1h)
            if emf_on:
                # harmonics held at the period's mid angle (rotor frame; error ~(6 we T)^2 / 24)
                gh = _harmonic_g(h6, p)
                v0 = -pp * wg * gh
            if fast:
                i1, ii, p0, p1, dd, ie1, ies = _avg_eval(i0, v0, v1, pp * wg, e1h, p)
            else:
                i1, ii, ii2, et, loss = _electrical(path, i0, ej0, v0, v1, pp * wg, e1h, p, ws, vr)
            n_it += 1
            tem = 1.5 * pp * (p[P_LAMBDA] * ii.imag + gh.real * ii.real + gh.imag * ii.imag) / dt
            if cog_on:
                tcog = _cogging_mean(th_m0, wg * dt, h6, p)
            fr = friction_torque(wg, p)
            if kind == LOAD_DYNO_BRAKE:
                t_ext = -brake_torque(wg, tl_brake, p)
            wn = w0 + 0.5 * dt * (tem + tcog + t_ext - fr) / J
            if abs(wn - wg) <= tol or it == n_max - 1:
                break
            if _jit.unlikely(stiff):
                wx = _stiff_step(state, wg, wn, p)
                e1h = _rot_small(e1h, pp * (wx - wg) * dt)
                wg = wx
                continue
            e1h = _rot_small(e1h, pp * (wn - wg) * dt)
            wg = wn
        w1 = w0 + dt * (tem + tcog + t_ext - fr) / J
        if path == 0 and not fast:
            state[S_TG_CORR] = tem + tcog - tem_g_raw
    if fast:
        ii2, et = _avg_energy(p0, p1, dd, ie1, ies, v1, p)    # terminal share only
    elif emf_on:
        et -= v0.real * ii.real + v0.imag * ii.imag            # segment's e_term includes v0's share
    # ---- ledger: electrical side (exact closed-form integrals)
    e_term = 1.5 * et
    e_cu = 1.5 * p[P_R] * ii2
    e_em = tem * wg * dt                                   # = T mean(Te) * w_used
    state[S_E_TERM] += e_term
    state[S_E_CU] += e_cu
    state[S_E_EM] += e_em
    state[S_E_CONV] += loss
    ibatt = 0.0
    if path == 0:
        state[S_E_BATT] -= e_term                          # ideal inverter on the battery
        ibatt = -e_term * p[P_IBATT_PER_J]
    elif path == 2:
        e_out = -e_term                                    # freewheel diodes into the battery
        e_d = e_out * 2.0 * p[P_INV_DIODE_V] / (vlink + 2.0 * p[P_INV_DIODE_V])
        state[S_E_CONV] += e_d
        state[S_E_BATT] += e_out - e_d
        ibatt = (e_out - e_d) * p[P_IBATT_PER_J]
        if e_out > 0.0:
            state[S_FAULTS] = int(state[S_FAULTS]) | FAULT_OVERSPEED_DIODES
    elif path == 1 or path == 3:
        e_out = -e_term
        e_d = e_out * 2.0 * p[P_RECT_DIODE_V] / (vlink + 2.0 * p[P_RECT_DIODE_V])
        e_link = e_out - e_d
        e_bus = p[P_ETA_BUCK] * e_link
        state[S_E_CONV] += e_d + (e_link - e_bus)
        if state[S_SOC] < p[P_DUMP_SOC]:
            e_b = p[P_ETA_CHG] * e_bus
            state[S_E_CONV] += e_bus - e_b
            state[S_E_BATT] += e_b
            ibatt = e_b * p[P_IBATT_PER_J]
        else:
            state[S_E_RES] += e_bus
    state[S_SOC] += ibatt * p[P_SOC_PER_A]                        # (precomputed: no division per period)
    if ibatt > 0.0 and state[S_SOC] > 1.0:
        # the inverter path has no dump: the model books the charge, and says it cannot be
        state[S_FAULTS] = int(state[S_FAULTS]) | FAULT_PACK_OVERCHARGE
    state[S_IBATT] = ibatt
    state[S_VLINK] = vlink
    # ---- ledger: shaft
    w_avg = 0.5 * (w0 + w1)
    if kind == LOAD_PRIME_MOVER:
        state[S_E_MECH] += t_ext * wg * dt
        state[S_E_FRIC] += fr * wg * dt
        if w1 != w0:
            state[S_E_MECH] += 0.5 * J * (w1 * w1 - w0 * w0)   # schedule step: the prime mover supplies it
    else:
        state[S_E_MECH] += t_ext * w_avg * dt
        state[S_E_FRIC] += fr * w_avg * dt
        state[S_MID_RESID] += (tem + tcog) * (wg - w_avg) * dt
    state[S_ITER] = n_it
    state[S_TEM] = tem
    state[S_TCOG] = tcog
    state[S_TLOAD] = t_ext
    state[S_ACCEL] = (w1 - w0) / dt if kind != LOAD_PRIME_MOVER else 0.0
    state[S_OMEGA] = w1
    state[S_ID] = i1.real
    state[S_IQ] = i1.imag
    # ---- angle and encoder (angle linear in time at the frozen speed wg)
    th0 = state[S_THETA_M]
    th1 = th0 + wg * dt
    cpr = p[P_CPR]
    rev = state[S_REV]
    c0 = state[S_COUNT]
    # np.floor: the float directly (math.floor goes through int64 and back: two conversions
    # on the period's longest latency chain)
    c1 = rev * cpr + np.floor(th1 * cpr / TWO_PI)
    if c1 != c0:
        # last edge crossed: position c1 (forward) or c1 + 1 (backward), time by linear motion
        edge = c1 if c1 > c0 else c1 + 1.0
        kf = dt * p[P_FCAP]
        ticks = -1.0
        if wg != 0.0:
            # the tick count is an integer: an estimate of its argument (2 pi / cpr precomputed,
            # one reciprocal of we T shared with the bound) decides unless it lies within a
            # generous bound of its rounding error (~1e-14 / |we T| ticks) from an integer;
            # then the exact form
            inv_wdt = 1.0 / (wg * dt)
            ff = min(max(((edge - rev * cpr) * p[P_RAD_PER_COUNT] - th0) * inv_wdt, 0.0), 1.0)
            y = (state[S_PERIODS] + ff) * kf
            fl = np.floor(y)
            tol = kf * (1e-13 * abs(inv_wdt) + 1e-15 * (2.0 + state[S_PERIODS])) + 1e-15 * abs(y)
            if y - fl > tol and fl + 1.0 - y > tol:
                ticks = fl
        if ticks < 0.0:
            th_edge = (edge - rev * cpr) * TWO_PI / cpr
            frac = (th_edge - th0) / (wg * dt) if wg != 0.0 else 1.0
            frac = min(max(frac, 0.0), 1.0)
            ticks = np.floor((state[S_PERIODS] + frac) * kf)
        state[S_EDGE_TICKS] = ticks
        state[S_COUNT] = c1
    if th1 >= TWO_PI:
        th1 -= TWO_PI
        state[S_REV] = rev + 1.0
    elif th1 < 0.0:
        th1 += TWO_PI
        state[S_REV] = rev - 1.0
    if not (0.0 <= th1 < TWO_PI):
        k = math.floor(th1 / TWO_PI)
        th1 -= k * TWO_PI
        state[S_REV] += k
    state[S_THETA_M] = th1
    state[S_PERIODS] += 1.0
    state[S_RELAY_TIMER] += 1.0
    state[S_E1H_RE] = e1h.real
    state[S_E1H_IM] = e1h.imag
    state[S_WE_LAST] = pp * wg
    if resync:
        _set_angle_outputs(state, p)               # exact resync of the rotating phasor
    else:
        # exp(j theta_e) advanced by exp(j we_used T): the rotation the electrical solution used
        ej1 = ej0 * e1h.conjugate()
        _set_phase_currents(state, ej1.real, ej1.imag)


@njit(**JIT)
def step_batch(state, p, duties, relay_request, buck_duty, samples, sums):
    """N periods (duties: N x 3, relay_request / buck_duty: N). samples[k] = phase currents
    at the end of period k; sums = [sum Te, sum T_load, sum i_batt] over the periods."""
    ws = np.zeros(WS_SIZE)
    n = duties.shape[0]
    sums[0] = 0.0
    sums[1] = 0.0
    sums[2] = 0.0
    for k in range(n):
        step_period(state, p, duties[k, 0], duties[k, 1], duties[k, 2], relay_request[k], buck_duty[k], ws)
        samples[k, 0] = state[S_IA]
        samples[k, 1] = state[S_IB]
        samples[k, 2] = state[S_IC]
        sums[0] += state[S_TEM]
        sums[1] += state[S_TLOAD]
        sums[2] += state[S_IBATT]


@njit(**JIT_INLINE)
def _in_unit_interval(a):  # pragma: no cover - compiled
    for i in range(a.shape[0]):
        x = a[i]
        if not (x >= 0.0 and x <= 1.0):      # NaN fails too
            return False
    return True


@njit(**JIT_HOT)
def unit_interval_check(duty_abc, relay_request, buck_duty):  # pragma: no cover - compiled
    """An SPMSM DriveCommand's arrays in one pass (bike_plant.msgconv.spmsm_drive_problem, every
    batch): True when every value is finite and in [0, 1]."""
    return _in_unit_interval(duty_abc) and _in_unit_interval(relay_request) and _in_unit_interval(buck_duty)


# =======================================================================================
# Python shell
# =======================================================================================
def new_state(p: np.ndarray, speed_rpm: float, soc0: float, theta_m_rad: float = 0.0) -> np.ndarray:
    s = np.zeros(S_SIZE)
    init_state(s, p, speed_rpm / RPM_PER_RAD_S, soc0, theta_m_rad)
    return s


def ledger_of(state: np.ndarray, p: np.ndarray) -> dict:
    """Energy ledger [J], cumulative. residual = mech in - battery - resistor - losses - stored."""
    e_mech = state[S_E_MECH]
    e_batt = state[S_E_BATT]
    e_res = state[S_E_RES]
    e_loss = state[S_E_CU] + state[S_E_FRIC] + state[S_E_CONV]
    e_stored = stored_energy(state, p) - state[S_E_STORED0]
    return {
        "energy_mech_in_j": float(e_mech),
        "energy_battery_j": float(e_batt),
        "energy_resistor_j": float(e_res),
        "energy_loss_j": float(e_loss),
        "energy_copper_j": float(state[S_E_CU]),
        "energy_friction_j": float(state[S_E_FRIC]),
        "energy_converter_j": float(state[S_E_CONV]),
        "energy_stored_j": float(e_stored),
        "residual_j": float(e_mech - e_batt - e_res - e_loss - e_stored),
    }


class RiderLoad:
    """Load hook: the rider of bike_plant.mechanics (torque-cadence line, two peaks per crank
    turn, effort PI on cadence: the same model and constants as the BLDC plant's rider)
    seen by the SPMSM through ``gear_ratio``. Called once per batch, the torque is held."""

    def __init__(self, load: SpmsmLoadParams):
        self.params = load.rider_load_params()
        self.target_rpm = self.params.rider_target_cadence_rpm      # set_rider_cadence moves it
        self.stopped = False                                         # a spin-down's coast
        self.effort = load.rider_effort0
        self.integ = load.rider_effort0
        self.crank_rad = 0.0

    def __call__(self, t_s: float, speed_rad_s: float, dt_s: float) -> float:
        lp = self.params
        cad = speed_rad_s / lp.gear_ratio
        err = self.target_rpm / RPM_PER_RAD_S - cad
        if self.stopped:
            self.effort = 0.0
        else:
            self.integ, self.effort = mechanics.rider_effort_update(self.integ, err, lp.rider_kp, lp.rider_ki, dt_s)
        torque = mechanics.rider_motor_torque_nm(self.effort, speed_rad_s, self.crank_rad, lp)
        self.crank_rad = (self.crank_rad + cad * dt_s) % TWO_PI
        return torque


def rotate_duties(duties: np.ndarray, angle_rad: float) -> np.ndarray:
    """Leg duties (float64 N x 3) whose phase voltages are the given ones' turned by ``angle_rad``
    (electrical, Clarke / inverse Clarke of the duties without their common mode), centred
    again by min-max common mode (SVPWM's; a sine-triangle modulator's held duties get it too,
    which leaves the line voltages, and so the currents, as they are) and clipped to [0, 1]."""
    # the row means by numpy (its summation order), the rest compiled: the same operations in
    # the same order, rounded alike (_rotate_rows); ~20 numpy calls on N x 3 took 26 us a batch
    d = np.ascontiguousarray(duties, dtype=np.float64)
    out = np.empty_like(d)
    _rotate_rows(d, d.mean(axis=1), math.cos(angle_rad), math.sin(angle_rad), out)
    return out


_INV_SQRT3 = 1.0 / math.sqrt(3.0)
_HALF_SQRT3 = 0.5 * math.sqrt(3.0)


@njit(cache=True, error_model="numpy")   # no fastmath: no FMA contraction, numpy's rounding exactly
def _rotate_rows(duties, mean, c, s, out):  # pragma: no cover - compiled
    """rotate_duties' rows, as its numpy expressions were: v = d - mean, alpha = v0, beta =
    (v1 - v2) / sqrt 3, turned by (c, s), back to three legs, min-max centred at 0.5, clipped."""
    for k in range(duties.shape[0]):
        m = mean[k]
        alpha = duties[k, 0] - m
        beta = ((duties[k, 1] - m) - (duties[k, 2] - m)) * _INV_SQRT3
        a2 = alpha * c - beta * s
        b2 = alpha * s + beta * c
        o0 = a2
        o1 = -0.5 * a2 + _HALF_SQRT3 * b2
        o2 = -0.5 * a2 - _HALF_SQRT3 * b2
        shift = 0.5 - 0.5 * (max(o0, max(o1, o2)) + min(o0, min(o1, o2)))
        o0 += shift
        o1 += shift
        o2 += shift
        out[k, 0] = min(max(o0, 0.0), 1.0)
        out[k, 1] = min(max(o1, 0.0), 1.0)
        out[k, 2] = min(max(o2, 0.0), 1.0)


@dataclasses.dataclass
class SpmsmBatchResult:
    torque_em_nm: float
    load_torque_nm: float
    battery_current_a: float
    current_samples_a: np.ndarray
    faults: int


class SpmsmPlant:
    """The authoritative SPMSM plant (counterpart of bike_plant.sim.BldcPlant).

    load_hook(t_s, speed_rad_s, dt_s) -> torque on the shaft [N m, accelerating positive]
    replaces the configured load (a rider, a recorded torque, ...); it is evaluated at each
    batch start and held for the batch. ``load.kind: rider`` installs :class:`RiderLoad`.
    """

    def __init__(self, params: SpmsmPlantParams, load_hook=None):
        self.params = params
        self.p = pack_params(params)
        load = params.load
        if load_hook is None and load.kind == "rider":
            load_hook = RiderLoad(load)
        self.load_hook = load_hook
        if load_hook is not None:
            self.p[P_LOAD_KIND] = LOAD_HOOK
        speed0 = load.speed_rpm if load.kind == "prime_mover" else params.mech.speed0_rpm
        if load.kind == "prime_mover" and load.schedule_time_s:
            speed0 = self._scheduled_speed_rpm(0.0, speed0)
        self.state = new_state(self.p, speed0, params.battery.soc0)
        self.ws = np.zeros(WS_SIZE)
        self.seq = 0
        # mean electromagnetic torque of the last batch (PlantState.torque_em_nm; None: no batch yet)
        self.last_torque_em_nm: float | None = None
        # ... and its mean battery current (PlantState.battery_current_a, charging positive)
        self.last_battery_current_a: float | None = None
        self.heart = RiderHeart(load.heart_params()) if load.kind == "rider" else None
        # the last batch's inputs (duties, relay request, buck duty) and the rotor angle turned
        # at its start, for step_held_batch
        self.last_inputs = None

    @property
    def time_s(self) -> float:
        return float(self.state[S_PERIODS] * self.params.control_period_s)

    @property
    def rotor_turned_rad(self) -> float:
        """The mechanical angle the rotor has turned since the start (unwrapped) [rad]."""
        return float(self.state[S_REV] * TWO_PI + self.state[S_THETA_M])

    def _scheduled_speed_rpm(self, t, default):
        speed = default
        for ts, sp in zip(self.params.load.schedule_time_s, self.params.load.schedule_speed_rpm):
            if t + 1e-12 >= ts:
                speed = sp
        return speed

    def before_batch(self, n_periods: int) -> None:
        """Per-batch inputs: prime-mover schedule, load hook torque."""
        load = self.params.load
        if load.kind == "prime_mover" and load.schedule_time_s:
            self.state[S_SPEED_TARGET] = self._scheduled_speed_rpm(self.time_s, load.speed_rpm) / RPM_PER_RAD_S
        if self.load_hook is not None:
            self.state[S_TEXT] = float(self.load_hook(self.time_s, float(self.state[S_OMEGA]),
                                                      n_periods * self.params.control_period_s))

    def step_batch(self, duties, relay_request=0.0, buck_duty=1.0, checked: bool = False) -> SpmsmBatchResult:
        """Apply N control periods: duties (N x 3, each in [0, 1]), relay request (0 inverter,
        1 rectifier) and buck duty, scalars or length-N arrays. ``checked``: float64 arrays
        (N x 3, N, N) whose values already passed msgconv.spmsm_drive_problem, which the plant
        may keep (the node's path: fresh conversions of the message; no second validation and
        no copies per batch)."""
        if checked:
            d, rr, bd = duties, relay_request, buck_duty
            n = d.shape[0]
        else:
            d = np.asarray(duties, dtype=np.float64)
            if d.ndim != 2 or d.shape[1] != 3:
                raise ValueError(f"duties must be N x 3, got shape {d.shape}")
            if d.size and not (np.all(d >= 0.0) and np.all(d <= 1.0)):     # NaN fails too
                raise ValueError("duties must be finite and in [0, 1]")
            n = d.shape[0]
            rr = np.broadcast_to(np.asarray(relay_request, dtype=np.float64), (n,)).copy()
            bd = np.broadcast_to(np.asarray(buck_duty, dtype=np.float64), (n,)).copy()
            if n and not (np.all(np.isfinite(rr)) and np.all(np.isfinite(bd))):
                raise ValueError("relay_request and buck_duty must be finite")
            d = d.copy()                                # (the caller may reuse d)
        self.before_batch(n)
        self.last_inputs = (d, rr, bd, self.rotor_turned_rad)
        samples = np.zeros((n, 3))
        sums = np.zeros(3)
        state = self.state
        state[S_FAULTS] = 0.0
        step_batch(state, self.p, d, rr, bd, samples, sums)
        self.advance_heart()
        self.seq += 1
        nn = max(n, 1)
        tem, tload, ibatt = sums.tolist()               # Python floats: the same values, cheaper arithmetic
        if n:
            self.last_torque_em_nm = tem / nn
            self.last_battery_current_a = ibatt / nn
        return SpmsmBatchResult(tem / nn, tload / nn, ibatt / nn, samples, int(state[S_FAULTS]))

    def step_held_batch(self) -> SpmsmBatchResult:
        """The last batch's command once more (realtime: no new one came in time): its relay
        request and buck duty, and the rotor-frame voltage its duties asked, i.e. the duties'
        voltage vectors turned by the electrical angle the rotor has turned since that batch
        began (:func:`rotate_duties`). Replayed as they were, fixed in the stator frame while
        the rotor turned, they gave 7-11 N m of torque ripple at 30 Hz and a mean of the wrong
        sign: a 45 ms hold of a 0.4 N m assist at ~730 r/min braked at 3.3 N m (-160 r/min)."""
        if self.last_inputs is None:
            raise ValueError("no batch to hold yet")
        d, rr, bd, turned_rad = self.last_inputs
        held = rotate_duties(d, self.p[P_PP] * (self.rotor_turned_rad - turned_rad))
        # checked: rotate_duties clips to [0, 1], the relay and buck arrays passed when first applied
        result = self.step_batch(held, rr, bd, checked=True)
        self.last_inputs = (d, rr, bd, turned_rad)      # held again: still from the original batch
        return result

    def step_safe_batch(self, n: int) -> SpmsmBatchResult:
        """N periods of the safe state (a lost controller; :meth:`set_safe_state` holds the
        gates off): buck off, and the relay kept on the rectifier path when it is there or on
        its way (the braking modes), where with the buck off no current flows and the rider
        freewheels. Otherwise it goes to the inverter, whose diodes brake the machine above
        the link voltage's speed (uncontrolled generation, flagged). The safe state used to
        take the relay to the inverter from the rectifier too: 4-6 N m of braking at 330
        r/min, the shaft 330 -> 250 r/min in 25 ms, on every command timeout of a ride."""
        s = self.state
        rect = s[S_RELAY] == REL_RECTIFIER or (s[S_RELAY] in (REL_DRAIN, REL_DEAD) and s[S_RELAY_TO] == REL_RECTIFIER)
        return self.step_batch(np.zeros((n, 3)), np.full(n, 1.0 if rect else 0.0), np.zeros(n), checked=True)

    def advance_heart(self) -> None:
        """The rider's heart to the plant's time, on the ledger's rider energy (after every
        batch; the CAN drive emulator calls it after its own kernels step the state)."""
        if self.heart is not None:
            # a Python float: the same value, and the heart's arithmetic is not numpy scalars'
            self.heart.advance(float(self.state[S_E_MECH]), self.time_s)

    def set_rider_cadence(self, cadence_rpm: float, stop: bool = False) -> None:
        """The rider's cadence target from now on (a workout's; 0: the config's own); ``stop``:
        he stops pedalling (a spin-down's coast); no rider (another load): nothing to tell."""
        if isinstance(self.load_hook, RiderLoad):
            self.load_hook.target_rpm = (cadence_rpm if cadence_rpm > 0
                                         else self.load_hook.params.rider_target_cadence_rpm)
            self.load_hook.stopped = bool(stop)

    def set_safe_state(self) -> None:
        """Inverter gates off: the bridge becomes a diode rectifier into the battery."""
        self.state[S_GATES_OFF] = 1.0

    def clear_safe_state(self) -> None:
        self.state[S_GATES_OFF] = 0.0

    def ledger(self) -> dict:
        return ledger_of(self.state, self.p)

    def snapshot(self) -> dict:
        """Measured quantities at the start of the next batch (PlantState names where they exist)."""
        # the state as Python floats in one call: the same values as float(state[i]) each, and
        # the arithmetic below (IEEE double, the same operations) gives the same bits as on numpy
        # scalars; the ledger's figures are ledger_of's (every batch: ~20 numpy scalar reads and
        # a ledger dict cost a tenth of the batch)
        s = self.state.tolist()
        p = self.p
        e_mech = s[S_E_MECH]
        e_loss = s[S_E_CU] + s[S_E_FRIC] + s[S_E_CONV]
        return {
            "seq": int(self.seq),
            "control_period_s": float(self.params.control_period_s),
            "machine": "spmsm",
            "backend": "sim",
            "phase_current_a": [s[S_IA], s[S_IB], s[S_IC]],
            "rotor_angle_elec_rad": (float(p[P_PP]) * s[S_THETA_M]) % TWO_PI,
            # the controller rebuilds its model's angle from it (spmsm_session.model_state_from_snapshot)
            "rotor_angle_mech_rad": s[S_THETA_M],
            "speed_rad_s": s[S_OMEGA],
            "speed_rpm": s[S_OMEGA] * RPM_PER_RAD_S,
            "encoder_count": int(s[S_COUNT]),
            "encoder_edge_ticks": int(s[S_EDGE_TICKS]),
            "dc_bus_v": float(p[P_VDC]),
            "relay_state": int(s[S_RELAY]),
            # the batch's mean, as PlantState.msg and the BLDC plant give it: the last period's
            # torque alone is biased on the inverter path (+0.025 N m in assist at 50 r/min, which
            # the session's torque trim then closed on)
            "torque_em_nm": s[S_TEM] if self.last_torque_em_nm is None else self.last_torque_em_nm,
            "load_torque_nm": s[S_TLOAD],
            # the pack is an ideal source at its nominal voltage (its SOC books energy / (V_nom Q)):
            # its open-circuit voltage. Absent, PlantState carried 0 V, and the report drew it
            "battery_ocv_v": float(p[P_BATT_V]),
            "battery_soc": s[S_SOC],
            # the batch's mean, as PlantState.msg has it: the last period's alone was 1.0 A rms off it
            # on the inverter path (the isokinetic loop at 70 rpm: +7 % on average, up to 13 A)
            "battery_current_a": s[S_IBATT] if self.last_battery_current_a is None else self.last_battery_current_a,
            "energy_mech_in_j": e_mech,
            "energy_battery_j": s[S_E_BATT],
            "energy_resistor_j": s[S_E_RES],
            "energy_loss_j": e_loss,
            "energy_stored_j": stored_energy(self.state, p) - s[S_E_STORED0],
            "heart_rate_bpm": self.heart.bpm if self.heart is not None else 0.0,
            "faults": int(s[S_FAULTS]) | (FAULT_PACK_EMPTY if s[S_SOC] <= PACK_EMPTY_SOC else 0),
        }
