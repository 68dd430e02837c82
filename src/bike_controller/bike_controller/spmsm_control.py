"""SPMSM speed and current control of paper 001 (sections 3-5) and an offline closed-loop runner.

Two controller families, selected by ``controller.family``, same telemetry:

* predictive (paper 001, Eq. 7-24 speed, Eq. 25-65 current): incremental one-step models
  from the zero-order-hold discretisation,
      x(k+1) = x(k) + a dx(k) + b du(k),
  one-step cost J = (x*(k+1) - x(k+1))^2 + r du(k)^2, dJ/du = 0 gives
      du(k) = b (x*(k+1) - x(k) - a dx(k)) / (b^2 + r),     u(k) = u(k-1) + du(k).
  Speed loop (1 ms): x = w [rad/s], u = iq* [A], a = exp(-B Ts/J), b = Kt (1 - a)/B.
  Current loops (100 us): x = id, iq [A], u = the decoupled voltages (Eq. 29-30)
      v'd = vd + we Lq iq,   v'q = vq - we (Ld id + lambda),
  a = exp(-R T/L), b = (1 - a)/R; the coupling terms are added back (Eq. 62-63) when the
  voltage is formed. (a, b) come from bike_plant.spmsm.zoh_* with the NOMINAL parameters:
  the predictor's model is the plant's model code.
  With beta = b^2/(b^2 + r) the closed loop (ideal inner loop, a ~ 1) has the poles of
  z^2 - (1 - beta)(1 + a) z + a (1 - beta): beta = 1 (r = 0) is dead-beat, small beta is
  slow AND lightly damped (zeta ~ sqrt(beta)/2: the law is an I-P controller with Kp/Ki =
  a T). Defaults (simulated compromise, see SpmsmControllerParams): beta = 0.6 for the
  speed loop with the reference trajectory below (0.15 without it: its loop also holds the
  speed measurement and the current loop), and beta = 0.7 for the current loops.
  Reference trajectory (``speed_reference_pole_hz`` f > 0, speed loop): the target one
  sample ahead is a point on a first-order path from the present speed towards the command,
      w_t(k+1) = w*(k+1) - alpha (w*(k) - w(k)),   alpha = exp(-2 pi f Ts),
  in place of w*(k+1) (the reference trajectory of predictive functional control). A ramp
  or a sine is still followed without a steady error: the command's next value is kept. The
  closed loop (ideal inner loop, a ~ 1) then has the poles of
      z^2 - ((1 - beta)(1 + a) + alpha beta) z + a (1 - beta),
  real for alpha >= 2 s / (1 + s), s = sqrt(1 - beta). A step still moves the speed by up
  to beta of itself in the sample it is seen (the cost looks one sample ahead, as printed;
  the current limits cut this for large steps); the rest of the error then closes without
  overshoot at the dominant real pole (the paper's "first-order transient responses", Fig.
  11a), where the law as printed rings (zeta = sqrt(beta)/2: 13-63 % overshoot on the
  steps the limits do not shape at beta 0.15). Steps from 50 to 350 r/min then share one
  shape ("similar linear responses", Fig. 14); below, Coulomb friction and cogging shape
  them. A step response without overshoot and a ramp followed without lag cannot both
  come from a causal loop; the anticipation (the command's next value) is what allows it
  here. Defaults: beta_speed = 0.6, f = 10 Hz (alpha = 0.939 >= 0.775; poles 0.936 and
  0.427). f = 0 is the law as printed.
* pi: velocity-form PI controllers on the same discrete plants, tuned by pole placement:
  for x(k+1) = a x(k) + b u(k) and u(k) = u(k-1) + Kp (e(k) - e(k-1)) + Ki T e(k) the
  characteristic polynomial (z - 1)(z - a) + b (Kp (z - 1) + Ki T z) is set to (z - p)^2,
  p = exp(-2 pi f T):  Kp = (a - p^2)/b,  Ki T = (1 - p)^2/b.

Anti-windup (both families): u(k-1) is always the APPLIED (limited) value: the speed loop
integrates onto the iq* the region logic let through, the current loops onto the voltage
the modulator could make (back-computed through the decoupling). The voltage command is
limited along the segment from the steady-state voltage of the present currents
(:func:`limit_voltage`), so saturation never removes the back-EMF compensation; and when
the current loop was voltage limited during a whole speed period, the speed loop continues
from the mean measured iq of that period instead of the reference the current loop could
not deliver (cascade anti-windup; an occasional saturated period, e.g. at a back-EMF
harmonic's peak, does not count: resetting on it would freeze the speed integral; without
the anti-windup the speed loop winds up in flux weakening, where the voltage headroom and
with it the torque slew rate are small, and limit-cycles through MTPV).
Under torque control (the session's assist, the CAN drive emulator) a current loop that was
voltage limited during a whole speed period with id more than EDGE_ID_MISS x Imax off its
reference is stuck at the edge (C_EDGE): :func:`limit_voltage` then gives the increment's share
along the voltage circle priority over its outward share. The region logic's references (Fig.
5-7) are feasible, but with the voltage the model does not know (dead time, the back-EMF's 5th /
7th harmonics: ~3 V peak in dq at 500 r/min) the true edge lies a little inside the planned one,
and there the decoupled PIs both push outward (id* more negative AND iq* higher); cut along their
own direction the currents did not move: at 500 r/min, 1 N m (of the ~1.7 N m the link gives),
id stayed at -8.8 A against the MTPV reference's -11.9 A and the drive made 0.42 N m for good.
Along the edge, id goes down trading some iq, the steady-state voltage falls (-we L per A of id
on the q axis) and iq comes back: 0.98 N m, steady. Speed control never sets C_EDGE.

Operating regions (paper 001, section 5, Fig. 5-7) by :func:`current_reference`, with the
stator resistance kept in the voltage limit (Rs = 6.84 ohm is 6x we L at 180 r/min; the
paper's R-free Eq. 68-71 would be badly wrong here). In the dq current plane (Ld = Lq) the
steady-state voltage limit |(R + j we L) i + j we lambda| <= Vlim is a disc with centre
-j we lambda/(R + j we L) (-> -lambda/Ld, the characteristic current, as R/(we L) -> 0)
and radius Vlim/|R + j we L|; the current limit is the disc |i| <= Imax. For the demanded
iq (torque, Eq. 8) the reference is the point of the feasible set on the line iq = iq*
with id closest to 0:
  constant torque (id = 0 feasible, region 0), flux weakening (id < 0, region 1: the
  advance angle beta = atan(-id/iq) grows with speed, Fig. 7b);
and if iq* is not reachable, the feasible point of extreme iq: the current-limited top of
the current disc (region 0, constant torque at Imax), the intersection of the two circles
(region 1, current and voltage limited: constant power), or the top of the voltage disc
(region 2, MTPV: id fixed by the voltage disc, iq reduced, Fig. 7c). The reference is a
continuous function of (iq*, speed, Vdc) - the extreme point of a strictly convex set moves
continuously - so region boundaries cause no torque step or current spike.
Vlim = voltage_margin * (Vdc/sqrt(3) for SVPWM, Vdc/2 for sine-triangle; 2 Vdc/pi with
``inverter.overmodulation: clamp``, :func:`voltage_limit_factor`) leaves the
current loops headroom; a slow voltage feedback lowers it while the current loop saturates
(dead time and parameter errors cost voltage the model does not know about) and lets it
recover afterwards. ``flux_weakening: false`` keeps id = 0 (paper Fig. 19).

Measurement: phase currents sampled at the period start (carrier valley), Clarke/Park with
the encoder angle (count + 1/2 count, x4 decoding of 2500 lines); optionally
(``current_sensor_lsb_a``) ia and ib quantised to the ADC step and ic = -ia - ib, as a DSP
with two current sensors measures them. ``computation_delay_periods: 1`` applies the duties
computed from the samples of period k in period k + 1 (a DSP that needs the whole period);
the paper's one-step current law is unstable with that delay (its closed loop becomes
z (z - 1)(z - a) + beta ((1 + a) z - a), |z| > 1 for beta >= ~0.07), so the default is the
same-period update the paper's ZOH model assumes. Speed (the paper does not
say how it measured it): by default a speed observer run every 100 us, driven by the encoder
angle error with the measured torque Kt iq fed forward through the nominal J and B (triple
pole at ``observer_pole_hz``; bumpless when the relay switches the feed-forward off / on);
or (``speed_estimator: mt``) the M/T method at 1 ms: counts between the last edges of two
samples over their capture-timer time difference; or (``m``) the counts of the last 1 ms
(6 r/min steps with 10000 counts / turn). The M/T estimate is half a sample old and, below
~20 r/min, arrives every few ms: the paper's one-step speed law (zeta = sqrt(beta)/2, see
above) limit-cycles on it at 2-10 r/min, while the observer holds 2 r/min within 0.02 r/min.
An optional first-order low-pass (``speed_filter_hz``, the usual DSP speed filter) acts on
the speed the speed law sees: with 10-40 Hz the one-step law rings or diverges (its
integral time is one sample), so it is off by default. The observer's pole sets how fast a
load torque is seen and with it the load-step drop and recovery of both families; the
default 5 Hz is calibrated on the paper's Fig. 11b (config comment).

Generating (relay on the rectifier path): the braking torque demand sets the buck duty by
inverting the rectifier's steady state (bike_plant.spmsm.rectifier_steady_state). A switch-over
from the inverter (paper 001, Fig. 2/8) first takes iq towards zero on the inverter, and only then
asks the relay to move (at most ``relay_predrain_s``): the relay's drain then starts from no torque.
"""
from __future__ import annotations

import math
import time

import numpy as np
from numba import njit

from bike_plant import bldc as _bldc
from bike_plant import spmsm as M
from bike_plant.config import ConfigError
from bike_plant.params import RPM_PER_RAD_S, TWO_PI

from .spmsm_params import FAMILIES, SpmsmControllerParams, controller_params_from_config  # noqa: F401

_bldc.invalidate_stale_numba_cache(__file__, [M.__file__, M._jit.__file__])

JIT = M.JIT
JIT_HOT = M.JIT_HOT      # per-period kernels: no array reference counting
JIT_INLINE = M.JIT_INLINE  # ... and inlined into the fused loops
SQRT3 = math.sqrt(3.0)

REGION_CONSTANT_TORQUE = 0
REGION_FLUX_WEAKENING = 1
REGION_MTPV = 2
LIMIT_CURRENT = 1     # torque demand cut by the current limit
LIMIT_VOLTAGE = 2     # ... by the voltage limit
# torque control: |id* - id| beyond this x Imax with the whole speed period voltage limited: the
# current loop is stuck at the voltage edge (speed_loop, C_EDGE)
EDGE_ID_MISS = 0.03


def pi_gains_pole_placement(a: float, b: float, pole_hz: float, dt_s: float) -> tuple[float, float]:
    """(Kp, Ki*T) of the velocity-form PI for x(k+1) = a x(k) + b u(k), double pole at
    z = exp(-2 pi pole_hz T) (see module docstring)."""
    pz = math.exp(-TWO_PI * pole_hz * dt_s)
    return (a - pz * pz) / b, (1.0 - pz) ** 2 / b


@njit(**JIT)
def predictive_increment(x_ref_next, x, dx, a, b, r):
    """Closed form of min over du of (x* - (x + a dx + b du))^2 + r du^2 (Eq. 22-23, 58-61)."""
    return b * (x_ref_next - x - a * dx) / (b * b + r)


# ---- controller parameter vector / state layout ----------------------------------------
(Q_FAMILY, Q_DT, Q_NS, Q_TS, Q_AC, Q_BC, Q_AS, Q_BS, Q_RC, Q_RS, Q_KPC, Q_KIC, Q_KPS, Q_KIS, Q_PP, Q_R, Q_L,
 Q_LAM, Q_KT, Q_IMAX, Q_VMARGIN, Q_VDC, Q_VMAX_FACTOR, Q_MODULATION, Q_FW, Q_CPR, Q_FCAP, Q_BUCK_V, Q_LINK_MAX,
 Q_RECT_DIODE_V, Q_ANGLE_COMP, Q_GC, Q_GS, Q_FAMILY_CURRENT, Q_DELAY_COMP, Q_OBSERVER, Q_OBS_L1, Q_OBS_L2, Q_OBS_L3,
 Q_JN, Q_BN, Q_SPEED_KF, Q_MMETHOD, Q_DELAY, Q_ILSB) = range(45)
# precomputed for the per-period path (the same numbers the kernel computed each period)
Q_INV_VDC = 45          # 1 / Vdc
Q_VMAX = 46             # voltage_limit_factor * Vdc: the modulator's circle [V]
Q_HALF_DT2 = 47         # T^2 / 2 (observer prediction)
Q_TORQUE_K = 48         # 1.5 pp lambda (nominal Kt, torque estimate)
Q_REF_ALPHA = 49        # reference trajectory: the error kept per speed sample (0: the command itself)
Q_RAD_PER_COUNT = 50    # 2 pi / counts per turn (mechanical rad per encoder count)
Q_INV_JN = 51           # 1 / nominal J
Q_INV_ILSB = 52         # 1 / ADC step (0 without the ADC)
# the observer's gains while it re-acquires after skipped plant states, and for how many periods
Q_OBS_F1, Q_OBS_F2, Q_OBS_F3, Q_OBS_ACQ_N = 53, 54, 55, 56
# a switch-over from the inverter: the periods iq may take to reach zero before the relay is asked
# anyway, the |iq| [A] at which it is asked, and the voltage [V] its id is planned below the drain's
# (control_period)
Q_PREDRAIN_N, Q_PREDRAIN_IQ, Q_PREDRAIN_DV = 57, 58, 59
Q_SIZE = 60

(C_SUB, C_SPEED_EST, C_SPEED_PREV, C_REF_COUNT, C_REF_TICKS, C_HAVE_REF, C_SPEED_REF, C_SPEED_REF_NEXT,
 C_IQ_DEMAND, C_ID_REF, C_IQ_REF, C_IQ_REF_PREV, C_E_SPEED_PREV, C_ID, C_IQ, C_ID_PREV, C_IQ_PREV, C_VDP_PREV,
 C_VQP_PREV, C_ED_PREV, C_EQ_PREV, C_VD, C_VQ, C_REGION, C_LIMITS, C_TORQUE_EST, C_ADVANCE, C_RELAY_REQ,
 C_BUCK_DUTY, C_BRAKE_T, C_DA, C_DB, C_DC, C_CUR_ACTIVE, C_SPEED_ACTIVE, C_THETA_E, C_COS, C_SIN, C_CNT,
 C_HAVE_ANGLE, C_VSAT, C_SPEED_RAW_PREV, C_OBS_TH, C_OBS_W, C_OBS_D, C_OBS_INIT, C_DV, C_SPEED_FILT,
 C_FILT_INIT, C_IQ_SUM, C_IQ_N, C_OBS_IQFF, C_OBS_INV, C_TORQUE_MODE, C_TORQUE_CMD, C_PEND_OK,
 C_ROT_DTH0, C_ROT_C0, C_ROT_S0, C_ROT_DTH1, C_ROT_C1, C_ROT_S1) = range(62)
# the (id*, iq*) of the last speed-loop run: the advance angle (telemetry) is computed from
# them when read (advance_angle_rad), not by an atan2 in the 1 ms loop (C_ADVANCE: unused)
C_ADV_ID, C_ADV_IQ = 62, 63
# 1: no motoring from the speed loop (an empty pack: a BMS takes charge only), braking kept
C_NO_ASSIST = 64
# torque control: the plan's margin learned at the voltage edge [V], and whether the last speed
# period's miss counted (speed_loop)
C_DV_FLOOR_V, C_DV_MISSED = 65, 66
# the encoder angle a re-acquisition of the observer started from (observer_restart)
C_OBS_TH0 = 67
# periods the inverter has held the relay request back while taking iq to zero (control_period)
C_PREDRAIN_N = 68
# torque control: 1 while the current loop was voltage limited during the whole last speed period
# (stuck at the edge): limit_voltage then moves along the edge first (speed_loop, control_period)
C_EDGE = 69
# > 0: the most motoring current the speed loop may ask [A] (a session's modes.assist_max_nm / Kt);
# 0: no cap but the current limit
C_ASSIST_CAP_A = 70
C_SIZE = 71


def pack_controller(cp: SpmsmControllerParams, nominal: M.SpmsmPlantParams) -> np.ndarray:
    """Controller parameters + the nominal model's ZOH coefficients (from bike_plant.spmsm)."""
    q = np.zeros(Q_SIZE)
    m = nominal.spmsm
    dt = nominal.control_period_s
    ts = dt * cp.speed_loop_periods
    r = m.rs_ohm * m.rs_scale
    ind = m.inductance_h * m.inductance_scale
    lam = m.flux_linkage_vs * m.flux_scale
    kt = 1.5 * m.pole_pairs * lam
    ac, bc = M.zoh_current_coefficients(r, ind, dt)
    a_s, b_s = M.zoh_speed_coefficients(kt, nominal.mech.inertia_kgm2, nominal.mech.friction_nms, ts)
    kpc, kic = pi_gains_pole_placement(ac, bc, cp.pi_current_pole_hz, dt)
    kps, kis = pi_gains_pole_placement(a_s, b_s, cp.pi_speed_pole_hz, ts)
    q[Q_FAMILY] = FAMILIES.index(cp.family)            # speed loop
    q[Q_FAMILY_CURRENT] = FAMILIES.index(cp.family)    # current loops (same family; split for studies)
    q[Q_DT] = dt
    q[Q_NS] = cp.speed_loop_periods
    q[Q_TS] = ts
    q[Q_AC], q[Q_BC], q[Q_AS], q[Q_BS] = ac, bc, a_s, b_s
    q[Q_RC], q[Q_RS] = cp.current_weight_r, cp.speed_weight_r
    q[Q_KPC], q[Q_KIC], q[Q_KPS], q[Q_KIS] = kpc, kic, kps, kis
    q[Q_PP], q[Q_R], q[Q_L], q[Q_LAM], q[Q_KT] = m.pole_pairs, r, ind, lam, kt
    q[Q_IMAX] = cp.current_limit_a
    q[Q_VMARGIN] = cp.voltage_margin
    q[Q_VDC] = nominal.inverter.dc_link_v
    q[Q_MODULATION] = M.MODULATIONS.index(nominal.inverter.modulation)
    q[Q_VMAX_FACTOR] = voltage_limit_factor(nominal.inverter)
    q[Q_FW] = 1.0 if cp.flux_weakening else 0.0
    q[Q_CPR] = nominal.encoder.counts_per_rev
    q[Q_FCAP] = nominal.encoder.capture_timer_hz
    q[Q_BUCK_V] = nominal.regen.buck_output_v
    q[Q_LINK_MAX] = nominal.regen.link_max_v
    q[Q_RECT_DIODE_V] = nominal.regen.diode_drop_v
    q[Q_ANGLE_COMP] = 1.0 if cp.angle_compensation else 0.0
    # predictive gains b / (b^2 + r) of the closed form (predictive_increment), precomputed
    q[Q_GC] = bc / (bc * bc + cp.current_weight_r)
    q[Q_GS] = b_s / (b_s * b_s + cp.speed_weight_r)
    q[Q_DELAY_COMP] = 1.0 if cp.speed_delay_compensation else 0.0
    q[Q_OBSERVER] = 1.0 if cp.speed_estimator == "observer" else 0.0
    q[Q_OBS_L1], q[Q_OBS_L2], q[Q_OBS_L3] = observer_gains(cp.observer_pole_hz, dt)
    q[Q_OBS_F1], q[Q_OBS_F2], q[Q_OBS_F3] = observer_gains(cp.observer_reacquire_pole_hz, dt)
    # for 2 / pole (50 ms at 40 Hz: ~12 time constants of the pole, the triple pole's settling)
    q[Q_OBS_ACQ_N] = max(round(2.0 / (cp.observer_reacquire_pole_hz * dt)), 1)
    q[Q_JN] = nominal.mech.inertia_kgm2
    q[Q_BN] = nominal.mech.friction_nms
    q[Q_SPEED_KF] = -math.expm1(-TWO_PI * cp.speed_filter_hz * ts) if cp.speed_filter_hz > 0 else 0.0
    q[Q_REF_ALPHA] = math.exp(-TWO_PI * cp.speed_reference_pole_hz * ts) if cp.speed_reference_pole_hz > 0 else 0.0
    q[Q_RAD_PER_COUNT] = TWO_PI / q[Q_CPR]
    q[Q_INV_JN] = 1.0 / q[Q_JN]
    q[Q_MMETHOD] = 1.0 if cp.speed_estimator == "m" else 0.0
    q[Q_DELAY] = float(cp.computation_delay_periods)
    q[Q_ILSB] = cp.current_sensor_lsb_a
    q[Q_INV_ILSB] = 1.0 / cp.current_sensor_lsb_a if cp.current_sensor_lsb_a > 0.0 else 0.0
    q[Q_INV_VDC] = 1.0 / q[Q_VDC]
    q[Q_VMAX] = q[Q_VMAX_FACTOR] * q[Q_VDC]
    q[Q_HALF_DT2] = 0.5 * dt * dt
    q[Q_TORQUE_K] = 1.5 * q[Q_PP] * q[Q_LAM]
    q[Q_PREDRAIN_N] = round(cp.relay_predrain_s / dt)
    # 1 % of Imax (0.16 N m): above the EMF harmonics' iq ripple at the voltage edge (~0.06 A).
    # (Handed over at 1 A, the drain's 5 ms took the rest on a prime mover, but in a session,
    # the shaft speeding up once the brake went, 0.4-0.5 N m were left at the opening, 0.2 now)
    q[Q_PREDRAIN_IQ] = 0.01 * cp.current_limit_a
    q[Q_PREDRAIN_DV] = 0.2 * q[Q_VMAX]
    return q


def voltage_limit_factor(inverter: M.InverterParams) -> float:
    """Largest voltage-vector amplitude the controller commands, per volt of DC link: the
    modulator's linear range (1/sqrt(3) SVPWM, 1/2 sine-triangle), or with
    ``inverter.overmodulation: clamp`` the six-step fundamental 2/pi; beyond the linear range
    :func:`modulate` clips the phase duties to [0, 1] (5th / 7th voltage harmonics)."""
    if inverter.overmodulation == "clamp":
        return 2.0 / math.pi
    return 1.0 / SQRT3 if inverter.modulation == "svpwm" else 0.5


def observer_gains(pole_hz: float, dt_s: float) -> tuple[float, float, float]:
    """Gains L of the speed observer (states: angle, speed, disturbance acceleration; the
    measured torque Kt iq is fed forward): x(k|k) = x(k|k-1) + L (theta_enc - theta(k|k-1)),
    x(k+1|k) = F x(k|k) + G Te/J. The error dynamics F (I - L C) get a triple pole at
    z = exp(-2 pi pole_hz T) (Ackermann on the pair (F, C F))."""
    h = dt_s
    f = np.array([[1.0, h, 0.5 * h * h], [0.0, 1.0, h], [0.0, 0.0, 1.0]])
    c = np.array([[1.0, 0.0, 0.0]])
    z = math.exp(-TWO_PI * pole_hz * h)
    # F (I - L C) = F - (F L) C: place the poles of F - K C with K = F L (predictor form)
    obs = np.vstack([c, c @ f, c @ f @ f])
    pf = np.linalg.matrix_power(f - z * np.eye(3), 3)
    k = pf @ np.linalg.solve(obs, np.array([0.0, 0.0, 1.0]))
    gain = np.linalg.solve(f, k)
    return float(gain[0]), float(gain[1]), float(gain[2])


# =======================================================================================
# operating regions (section 5)
# =======================================================================================
@njit(**JIT)
def current_reference(iq_dem, we, vlim, imax, r, l_h, lam, fw):
    """(id*, iq*, region, limits) for the demanded iq at electrical speed we (module doc)."""
    z = complex(r, we * l_h)
    z2 = r * r + (we * l_h) ** 2
    c = complex(0.0, -we * lam) / z          # voltage-disc centre [A]
    rho = vlim / math.sqrt(z2)               # voltage-disc radius [A]
    cd = c.real
    cq = c.imag
    if fw == 0.0:
        # id = 0 only: the chord of the voltage disc on the q axis, within +-Imax
        h2 = rho * rho - cd * cd
        if h2 < 0.0:
            return 0.0, min(max(cq, -imax), imax), REGION_CONSTANT_TORQUE, LIMIT_VOLTAGE
        h = math.sqrt(h2)
        lo = max(-imax, cq - h)
        hi = min(imax, cq + h)
        if lo > hi:
            return 0.0, min(max(cq, -imax), imax), REGION_CONSTANT_TORQUE, LIMIT_VOLTAGE | LIMIT_CURRENT
        iq = min(max(iq_dem, lo), hi)
        lim = 0
        if iq != iq_dem:
            bound = hi if iq_dem > hi else lo
            lim = LIMIT_CURRENT if abs(bound) >= imax else LIMIT_VOLTAGE
        return 0.0, iq, REGION_CONSTANT_TORQUE, lim
    # the line iq = iq* inside both discs: id closest to 0
    if abs(iq_dem) <= imax and abs(iq_dem - cq) <= rho:
        wi = math.sqrt(imax * imax - iq_dem * iq_dem)
        wv = math.sqrt(rho * rho - (iq_dem - cq) ** 2)
        lo = max(-wi, cd - wv)
        hi = min(wi, cd + wv)
        if lo <= hi:
            idr = min(max(0.0, lo), hi)
            return idr, iq_dem, REGION_CONSTANT_TORQUE if idr == 0.0 else REGION_FLUX_WEAKENING, 0
    # not reachable: the feasible point of extreme iq in the demanded direction
    sgn = 1.0 if iq_dem >= 0.0 else -1.0
    dist = abs(c)
    if dist >= imax + rho:
        # the discs do not meet (over speed): least-voltage current within the limit
        if dist > 0.0:
            return cd / dist * imax, cq / dist * imax, REGION_MTPV, LIMIT_VOLTAGE | LIMIT_CURRENT
        return 0.0, 0.0, REGION_MTPV, LIMIT_VOLTAGE | LIMIT_CURRENT
    best_q = -1e300
    bid = 0.0
    biq = 0.0
    breg = REGION_MTPV
    blim = LIMIT_VOLTAGE
    tol = 1e-12 * (1.0 + imax * imax)
    # (1) extreme of the voltage disc (MTPV) if within the current limit
    qv = cq + sgn * rho
    if cd * cd + qv * qv <= imax * imax + tol:
        best_q = sgn * qv
        bid = cd
        biq = qv
        breg = REGION_MTPV
        blim = LIMIT_VOLTAGE
    # (2) extreme of the current disc (constant torque at Imax) if within the voltage limit
    qi = sgn * imax
    if cd * cd + (qi - cq) ** 2 <= rho * rho + tol and sgn * qi > best_q:
        best_q = sgn * qi
        bid = 0.0
        biq = qi
        breg = REGION_CONSTANT_TORQUE
        blim = LIMIT_CURRENT
    # (3) intersections of the circles (current and voltage limited: constant power)
    if dist > abs(imax - rho) and dist > 0.0:
        a = (imax * imax - rho * rho + dist * dist) / (2.0 * dist)
        h = math.sqrt(max(imax * imax - a * a, 0.0))
        ux = cd / dist
        uy = cq / dist
        for sg in (1.0, -1.0):
            px = a * ux - sg * h * uy
            py = a * uy + sg * h * ux
            if sgn * py > best_q:
                best_q = sgn * py
                bid = px
                biq = py
                breg = REGION_FLUX_WEAKENING if px < 0.0 else REGION_CONSTANT_TORQUE
                blim = LIMIT_CURRENT | LIMIT_VOLTAGE
    return bid, biq, breg, blim


def steady_state_max_speed_rpm(q: np.ndarray, load_torque_nm: float = 0.0, flux_weakening: bool = True,
                               voltage_margin: float = 1.0, speed_limit_rpm: float = 5000.0) -> float:
    """Highest speed at which the region logic (same voltage and current limits, steady
    state) still delivers the torque load_torque_nm + B w, with the full modulator voltage
    times voltage_margin. Bisection on the speed; q from :func:`pack_controller`."""
    vlim = voltage_margin * q[Q_VMAX_FACTOR] * q[Q_VDC]

    def feasible(rpm):
        w = rpm / RPM_PER_RAD_S
        need = (load_torque_nm + q[Q_BN] * w) / q[Q_KT]
        _, iq, _, _ = current_reference(need, q[Q_PP] * w, vlim, q[Q_IMAX], q[Q_R], q[Q_L], q[Q_LAM],
                                        1.0 if flux_weakening else 0.0)
        return iq >= need - 1e-9

    lo, hi = 0.0, speed_limit_rpm
    if not feasible(lo):
        return 0.0
    if feasible(hi):
        return hi
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if feasible(mid):
            lo = mid
        else:
            hi = mid
    return lo


@njit(**JIT_HOT)
def brake_torque_nm(vlink, we, q):
    """Braking torque (>= 0 opposes the rotation) of the machine on the rectifier at link vlink."""
    vr = M.rectifier_voltage(vlink, q[Q_RECT_DIODE_V])
    i = M.rectifier_steady_state(vr, we, q[Q_R], q[Q_L], q[Q_LAM])
    te = 1.5 * q[Q_PP] * q[Q_LAM] * i.imag
    return -te if we >= 0.0 else te


BRAKE_ENVELOPE_STEP_RPM = 5.0
BRAKE_ENVELOPE_MAX_RPM = 1500.0      # 375 r/min cadence at gear 4: beyond any rider


def brake_envelope(q) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The rectifier path's strongest steady braking torque against motor speed: the buck at
    duty 1, so the link sits at the buck's output voltage (:func:`brake_torque_nm` at
    Q_BUCK_V, the steady state of Fig. 8 that the plant's average model also settles to).
    Zero while the line-to-line back-EMF is below the link (about 215 r/min with the paper's
    machine). Returns (motor r/min grid, N m), for the session's mode laws and the report;
    plain Python (the plant's own functions, uncompiled), so a report needs no JIT."""
    steady = M.rectifier_steady_state.py_func
    vr = M.rectifier_voltage.py_func(q[Q_BUCK_V], q[Q_RECT_DIODE_V])
    n = int(round(BRAKE_ENVELOPE_MAX_RPM / BRAKE_ENVELOPE_STEP_RPM))
    rpm = tuple(k * BRAKE_ENVELOPE_STEP_RPM for k in range(n + 1))
    torque = []
    for speed_rpm in rpm:
        we = q[Q_PP] * speed_rpm / RPM_PER_RAD_S
        i = steady(vr, we, q[Q_R], q[Q_L], q[Q_LAM])
        t_nm = -1.5 * q[Q_PP] * q[Q_LAM] * i.imag
        torque.append(t_nm if t_nm > 0.0 else 0.0)
    return rpm, tuple(torque)


@njit(**JIT_HOT)
def buck_duty_for_brake_torque(t_brake, we, q):
    """Buck duty D = Vbus / Vlink that makes the rectifier brake with t_brake (steady state);
    clipped to the range the hardware has (D = 1: strongest braking)."""
    vbus = q[Q_BUCK_V]
    vmax = q[Q_LINK_MAX]
    if t_brake <= 0.0 or brake_torque_nm(vmax, we, q) >= t_brake:
        return vbus / vmax
    if brake_torque_nm(vbus, we, q) <= t_brake:
        return 1.0
    lo = vbus
    hi = vmax
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if brake_torque_nm(mid, we, q) > t_brake:
            lo = mid
        else:
            hi = mid
    return vbus / (0.5 * (lo + hi))


# =======================================================================================
# the control law
# =======================================================================================
@njit(**JIT)
def modulate(valpha, vbeta, vdc, modulation):
    """(alpha, beta) voltage -> duty cycles: SVPWM (min-max common mode) or sine-triangle.
    Each duty is clamped to [0, 1]: a vector beyond the linear range (overmodulation) is
    clipped per phase, as a DSP's PWM compare register saturates."""
    return _modulate_g(valpha, vbeta, 1.0 / vdc, modulation)


@njit(**JIT_INLINE)
def _modulate_g(valpha, vbeta, g, modulation):
    """:func:`modulate` with g = 1 / Vdc given (precomputed: no division per period)."""
    va = valpha
    vb = -0.5 * valpha + 0.5 * SQRT3 * vbeta
    vc = -0.5 * valpha - 0.5 * SQRT3 * vbeta
    off = 0.0
    if modulation == 0.0:
        off = -0.5 * (max(va, vb, vc) + min(va, vb, vc))
    da = min(max(0.5 + (va + off) * g, 0.0), 1.0)
    db = min(max(0.5 + (vb + off) * g, 0.0), 1.0)
    dc = min(max(0.5 + (vc + off) * g, 0.0), 1.0)
    return da, db, dc


@njit(**JIT_HOT)
def limit_voltage(vd, vq, id_a, iq_a, we, vmax, q, along_edge=False):
    """Keep the voltage command inside the modulator's circle |v| <= vmax by shortening it
    along the segment from the steady-state voltage of the present currents,
    v_ss = (R + j we L) i + j we lambda (bike_plant.spmsm.steady_state_voltage), towards the
    command. The back-EMF compensation is kept and only the dynamic part is cut: a plain
    d-axis-first clip would, in flux weakening, leave vq ~ 0 against a 15 V back-EMF and
    drive iq (and the torque) the wrong way. If even v_ss is out of reach, scale radially.

    ``along_edge`` (torque control, the current loop stuck at the voltage edge: C_EDGE, module
    doc): of the dynamic part v - v_ss, the component along the circle |v| = |v_ss| first, then
    as much of the outward (radial) component as fits. Paper 001, section 5 (the voltage limit
    of Eq. 68-71, here with R kept, a circle in the dq voltage plane; Fig. 6-7): along it id and iq trade
    at constant voltage towards the flux-weakening / MTPV reference, where the segment towards
    the command stalls when the model's edge lies outside the machine's."""
    v2 = vd * vd + vq * vq
    if v2 <= vmax * vmax:
        return vd, vq
    vs = M.steady_state_voltage(id_a, iq_a, we, q[Q_R], q[Q_L], q[Q_LAM])
    s2 = vs.real * vs.real + vs.imag * vs.imag
    if s2 >= vmax * vmax:
        g = vmax / math.sqrt(v2)
        return vd * g, vq * g
    dx = vd - vs.real
    dy = vq - vs.imag
    if along_edge:
        # the dynamic part's outward (radial) share last: its component along the edge first,
        # then as much of the radial one as fits (module doc, "Operating regions")
        sn = math.sqrt(s2)
        if sn > 0.0:
            nx = vs.real / sn
            ny = vs.imag / sn
            rad = dx * nx + dy * ny
            if rad > 0.0:
                tx = dx - rad * nx
                ty = dy - rad * ny
                t2 = tx * tx + ty * ty
                room2 = vmax * vmax - s2
                if t2 >= room2:
                    g = math.sqrt(room2 / t2)
                    return vs.real + g * tx, vs.imag + g * ty
                rr = math.sqrt(vmax * vmax - t2) - sn
                return vs.real + tx + rr * nx, vs.imag + ty + rr * ny
    # |vs + alpha (v - vs)| = vmax, alpha in (0, 1)
    a2 = dx * dx + dy * dy
    b1 = vs.real * dx + vs.imag * dy
    alpha = (-b1 + math.sqrt(b1 * b1 + a2 * (vmax * vmax - s2))) / a2
    return vs.real + alpha * dx, vs.imag + alpha * dy


@njit(**JIT_INLINE)
def drain_id_reference(we, vlim, q):
    """id* of a relay drain (iq* = 0): the one closest to zero whose steady-state voltage
    (R + j we L) id + j we lambda is within vlim, at most Imax. Below the base speed 0; above,
    the flux-weakening id of no torque, ~-(lambda - vlim / we) / L: there zero current is out
    of the link's reach, and id* = 0 turned the machine into a generator through the inverter
    until the drain timeout forced the relay open (340 r/min from no torque: -3.5 N m at the
    opening, -1.2 on the 5 ms mean; from a 2 N m assist -3.6; now 0.0). A braking current decays
    only as fast as the voltage left over the back-EMF lets it, so the inverter takes it towards
    zero before it asks for the relay (the pre-drain, :func:`control_period`, with vlim 20 % of
    the modulator's circle lower; -5 N m at 340 r/min was -3.1 N m at the opening, now 0.04).
    With the Imax clip, the link's voltage beyond it (over speed) is the limiter's to share."""
    r = q[Q_R]
    xl = we * q[Q_L]
    e = we * q[Q_LAM]
    # |(r + j xl) id + j e|^2 = vlim^2: (r^2 + xl^2) id^2 + 2 xl e id + e^2 - vlim^2 = 0
    if e * e <= vlim * vlim:
        return 0.0
    a = r * r + xl * xl
    disc = xl * xl * e * e - a * (e * e - vlim * vlim)
    if disc < 0.0:
        idr = -xl * e / a           # iq = 0 beyond the voltage disc: its least-voltage id
    else:
        idr = (-xl * e + math.sqrt(disc)) / a
    return max(idr, -q[Q_IMAX])


@njit(**JIT_HOT)
def speed_sample(cs, q, meas):
    """M/T speed estimate from the encoder count and the last edge's capture time."""
    cpr = q[Q_CPR]
    fcap = q[Q_FCAP]
    cnt = meas[M.S_COUNT]
    et = meas[M.S_EDGE_TICKS]
    now = math.floor(meas[M.S_PERIODS] * (q[Q_DT] * fcap))
    if cs[C_HAVE_REF] == 0.0:
        cs[C_REF_COUNT] = cnt
        cs[C_REF_TICKS] = et if cnt != 0.0 or et != 0.0 else now
        cs[C_HAVE_REF] = 1.0
        return
    if q[Q_MMETHOD] != 0.0:
        # M method: counts in the last speed period over the period
        cs[C_SPEED_EST] = (cnt - cs[C_REF_COUNT]) * TWO_PI / cpr / q[Q_TS]
        cs[C_REF_COUNT] = cnt
        return
    if cnt != cs[C_REF_COUNT] and et > cs[C_REF_TICKS]:
        cs[C_SPEED_EST] = (cnt - cs[C_REF_COUNT]) * TWO_PI / cpr * fcap / (et - cs[C_REF_TICKS])
        cs[C_REF_COUNT] = cnt
        cs[C_REF_TICKS] = et
    else:
        elapsed = now - cs[C_REF_TICKS]
        if elapsed > 0.0:
            bound = TWO_PI / cpr * fcap / elapsed
            if abs(cs[C_SPEED_EST]) > bound:
                cs[C_SPEED_EST] = bound if cs[C_SPEED_EST] > 0.0 else -bound


@njit(**JIT_INLINE)
def observer_update(cs, q, meas, iq_a):
    """Speed observer, once per current period: correct with the encoder angle (count + 1/2
    count), then predict one period with the measured torque Kt iq (nominal Kt, J, B; pass
    iq_a = 0 for a pure tracking filter)."""
    th_meas = (meas[M.S_COUNT] + 0.5) * q[Q_RAD_PER_COUNT]
    l1, l2, l3 = q[Q_OBS_L1], q[Q_OBS_L2], q[Q_OBS_L3]
    if cs[C_OBS_INIT] != 1.0:
        gains = observer_restart(cs, q, th_meas)
        if gains != 0:
            l1, l2, l3 = q[Q_OBS_F1], q[Q_OBS_F2], q[Q_OBS_F3] if gains == 1 else 0.0
    e = th_meas - cs[C_OBS_TH]
    th = cs[C_OBS_TH] + l1 * e
    w = cs[C_OBS_W] + l2 * e
    d = cs[C_OBS_D] + l3 * e
    cs[C_SPEED_EST] = w
    h = q[Q_DT]
    acc = (q[Q_KT] * iq_a - q[Q_BN] * w) * q[Q_INV_JN] + d
    cs[C_OBS_TH] = th + h * w + q[Q_HALF_DT2] * acc
    cs[C_OBS_W] = w + h * acc
    cs[C_OBS_D] = d


@njit(**JIT_HOT)
def observer_restart(cs, q, th_meas):
    """The observer's start (C_OBS_INIT 0: the run's first period) and its re-acquisition after
    skipped plant states (C_OBS_INIT 2 + the periods since, set by
    SpmsmController._bridge_skipped_periods). Re-acquiring: the angle from the encoder count at
    once; one speed sample on (Ns - 1 periods: inside the batch, so the batch's status has it)
    the speed from the counts between (the batch's counts, as the controller's model of the
    plant gives them from the measured speed); and the fast gains (observer_reacquire_pole_hz)
    for Q_OBS_ACQ_N periods, which find the disturbance again (the skipped time may have held a
    command timeout's safe state, and the relay moved). The disturbance itself is kept (a
    stalled controller does not stop the rider) and frozen until the speed is taken: the
    corrections against the gap's mean speed before it put -46 rad/s^2 into it for a 10 rad/s
    start error. Returns the gains of this period: 0 the usual, 1 the fast ones, 2 the fast
    ones with the disturbance frozen."""
    k = cs[C_OBS_INIT]
    if k == 0.0:
        cs[C_OBS_TH] = th_meas
        cs[C_OBS_W] = cs[C_SPEED_EST]
        cs[C_OBS_D] = 0.0
        cs[C_OBS_INIT] = 1.0
        return 0
    if k == 2.0:
        cs[C_OBS_TH0] = th_meas
        cs[C_OBS_TH] = th_meas
    elapsed = k - 2.0
    speed_at = max(q[Q_NS] - 1.0, 1.0)
    if elapsed == speed_at:
        cs[C_OBS_W] = (th_meas - cs[C_OBS_TH0]) / (elapsed * q[Q_DT])
        cs[C_OBS_TH] = th_meas
    cs[C_OBS_INIT] = 1.0 if elapsed >= max(q[Q_OBS_ACQ_N], q[Q_NS]) else k + 1.0
    return 2 if elapsed < speed_at else 1


@njit(**JIT_HOT)
def speed_loop(cs, q):
    """Speed controller (1 ms) + region logic -> (id*, iq*)."""
    w = cs[C_SPEED_EST]
    # the M/T estimate is the mean speed over the last sample, i.e. half a sample old:
    # optionally extrapolate it to now with the last change (delay compensation)
    w_raw = w
    if q[Q_OBSERVER] == 0.0:
        w = w + 0.5 * q[Q_DELAY_COMP] * (w_raw - cs[C_SPEED_RAW_PREV])
    cs[C_SPEED_RAW_PREV] = w_raw
    if q[Q_SPEED_KF] > 0.0:
        # low-pass on the measured speed (DSP speed-calculation filter)
        if cs[C_FILT_INIT] == 0.0:
            cs[C_SPEED_FILT] = w
            cs[C_FILT_INIT] = 1.0
        cs[C_SPEED_FILT] += q[Q_SPEED_KF] * (w - cs[C_SPEED_FILT])
        w = cs[C_SPEED_FILT]
    if cs[C_SPEED_ACTIVE] == 0.0:
        cs[C_IQ_REF_PREV] = 0.0
        cs[C_SPEED_PREV] = w
        cs[C_E_SPEED_PREV] = cs[C_SPEED_REF] - w
        cs[C_SPEED_ACTIVE] = 1.0
    e = cs[C_SPEED_REF] - w
    # voltage feedback on the region logic: while the current loop saturates, the planning
    # voltage drops (0.2 V per fully saturated ms), else it recovers (0.02 V per ms). It
    # absorbs what the model does not know (dead time, parameter error) and keeps the
    # references reachable; it moves slowly, so the references stay continuous.
    # Under torque control (the session's assist) saturation with iq tracked on average over
    # the speed period is the back-EMF harmonics' ripple at the voltage edge, not an
    # unreachable reference: counted, it held the plan 30 % low in deep flux weakening, and the
    # strongest assist at 200-350 r/min was 1.26-0.43 N m where the 24 V link gives 4.46-2.45.
    # (Not so under speed control: there the cascade anti-windup below sets the reference to
    # the delivered iq, which then always reads as tracked.)
    # "Tracked": within 5 % of the reference (the torque asked, to 5 %) plus 1 % of Imax, which
    # covers the ripple's own miss at small references (at most 0.085 A per period, 100-390
    # r/min, Command 0.1-1). It was 5 % of Imax, 0.75 A = 0.82 N m: more than a whole light
    # assist. On the 4 % descent (0.4 N m at ~390 r/min) the plan then ran up to the voltage
    # edge, the current loop stayed saturated and iq slid from +0.49 A to -0.26 A (the assist
    # turned into a brake) before one period counted; the plan then fell to its 30 % floor and
    # crept back over 200 ms: a 4-5 Hz torque cycle, and the virtual bike's speed tracked 0.23
    # m/s rms instead of 0.16.
    vmax_mod = q[Q_VMAX_FACTOR] * q[Q_VDC]
    sat = cs[C_VSAT] / q[Q_NS]
    if cs[C_TORQUE_MODE] != 0.0 and cs[C_IQ_N] > 0.0 \
            and abs(cs[C_IQ_REF_PREV] - cs[C_IQ_SUM] / cs[C_IQ_N]) \
            < 0.05 * abs(cs[C_IQ_REF_PREV]) + 0.01 * q[Q_IMAX]:
        sat = 0.0
    # Under torque control the recovery towards the voltage edge buys torque only while the
    # region logic clips the reference (limits: Command 1 reaches the link's limit at dv = 0).
    # A reachable reference is delivered at any plan, and near dv = 0 (390-430 r/min, light
    # assist) the model's missing dead time (0.36 V) and EMF harmonics leave the current loop
    # no voltage to move id: iq slid to ~0 within ~20 ms, the plan fell to its 30 % floor to
    # free it and crept back for 200 ms, a 4-5 Hz cycle (10 ms torque std 0.12 N m). So, with
    # the reference reachable, the plan creeps back 10x slower, and not below the plan at which
    # a miss last began plus 0.5 V (with the plan held, the light assist is steady from 0.5 V,
    # erratic below 0.3 V): the margin that edge needs, kept while torque control lasts.
    recover = 0.02
    if cs[C_TORQUE_MODE] == 0.0:
        cs[C_DV_FLOOR_V] = 0.0
    elif cs[C_LIMITS] == 0.0:
        recover = 0.002
        if sat > 0.0 and cs[C_DV_MISSED] == 0.0:
            cs[C_DV_FLOOR_V] = cs[C_DV] + 0.5
    cs[C_DV_MISSED] = 1.0 if sat > 0.0 else 0.0
    dv = cs[C_DV] + 0.2 * sat - recover
    if cs[C_TORQUE_MODE] != 0.0 and cs[C_LIMITS] == 0.0 and dv < cs[C_DV_FLOOR_V]:
        dv = max(dv, min(cs[C_DV], cs[C_DV_FLOOR_V]))
    cs[C_DV] = min(max(dv, 0.0), 0.3 * vmax_mod)
    # torque control: a current loop voltage limited the whole speed period with id off its
    # reference is stuck at the edge (limit_voltage then moves along it first)
    cs[C_EDGE] = 1.0 if (cs[C_TORQUE_MODE] != 0.0 and cs[C_VSAT] >= q[Q_NS]
                         and abs(cs[C_ID_REF] - cs[C_ID]) > EDGE_ID_MISS * q[Q_IMAX]) else 0.0
    if cs[C_VSAT] >= q[Q_NS] and cs[C_IQ_N] > 0.0:
        # the current loop was voltage limited during the whole last speed period: continue
        # from the iq it delivered (its mean over the period), not from the reference it could
        # not reach (cascade anti-windup). An occasional saturated period (a noisy speed in the
        # decoupling term, a back-EMF harmonic peak) does not count, and the mean ignores the
        # current ripple: resetting to an instantaneous low would freeze the integral.
        iqm = cs[C_IQ_SUM] / cs[C_IQ_N]
        iqp = cs[C_IQ_REF_PREV]
        if (iqp > iqm and iqp > 0.0) or (iqp < iqm and iqp < 0.0):
            cs[C_IQ_REF_PREV] = iqm
    cs[C_VSAT] = 0.0
    cs[C_IQ_SUM] = 0.0
    cs[C_IQ_N] = 0.0
    if q[Q_FAMILY] == 0.0:
        # predictive_increment(w*(k+1), w, dw, a, b, r) with b / (b^2 + r) precomputed
        # reference trajectory: the error to the command is closed along a first-order path
        # (alpha per sample), the command's own next step is kept (ramps: no lag)
        target = cs[C_SPEED_REF_NEXT] - q[Q_REF_ALPHA] * e
        du = q[Q_GS] * (target - w - q[Q_AS] * (w - cs[C_SPEED_PREV]))
    else:
        du = q[Q_KPS] * (e - cs[C_E_SPEED_PREV]) + q[Q_KIS] * e
    iq_dem = cs[C_IQ_REF_PREV] + du
    if cs[C_TORQUE_MODE] != 0.0:
        # torque control (session modes: assist downhill): the demanded torque replaces the
        # speed controller's output, through the same region logic and limits
        iq_dem = cs[C_TORQUE_CMD] / q[Q_KT]
    if cs[C_NO_ASSIST] != 0.0 and iq_dem * w >= 0.0:
        # the pack is empty: a torque along the rotation (or from rest) would motor; hold it at zero (the
        # reference then restarts from zero: no wind-up while held)
        iq_dem = 0.0
    cap = cs[C_ASSIST_CAP_A]
    if cap > 0.0 and cs[C_TORQUE_MODE] == 0.0 and iq_dem * w >= 0.0 and abs(iq_dem) > cap:
        # speed control: the session's assist limit (modes.assist_max_nm), as the mode law's isokinetic
        # PI holds it (torque control gets its torque from that law, capped there)
        iq_dem = math.copysign(cap, iq_dem)
    vlim = q[Q_VMARGIN] * vmax_mod - cs[C_DV]
    idr, iqr, reg, lim = current_reference(iq_dem, q[Q_PP] * w, vlim, q[Q_IMAX], q[Q_R], q[Q_L], q[Q_LAM],
                                           q[Q_FW])
    cs[C_IQ_DEMAND] = iq_dem
    cs[C_ID_REF] = idr
    cs[C_IQ_REF] = iqr
    cs[C_IQ_REF_PREV] = iqr         # anti-windup: integrate onto what was let through
    cs[C_REGION] = reg
    cs[C_LIMITS] = lim
    cs[C_ADV_ID] = idr              # advance angle: advance_angle_rad(cs) when read
    cs[C_ADV_IQ] = iqr
    cs[C_SPEED_PREV] = w
    cs[C_E_SPEED_PREV] = e


@njit(**JIT_INLINE)
def _rot_counts(cs, e1, dth):
    """e1 * exp(-j dth) for the angle step of a few encoder counts: bike_plant.spmsm._rot_small
    with the last two steps' (cos, sin) kept in cs (the step takes few distinct values, e.g.
    3 or 4 counts per period at constant speed): the same numbers without a sincos per period."""
    if abs(dth) < 1e-3:
        return M._rot_small(e1, dth)
    if dth == cs[C_ROT_DTH0]:
        c = cs[C_ROT_C0]
        s = cs[C_ROT_S0]
    elif dth == cs[C_ROT_DTH1]:
        c = cs[C_ROT_C1]
        s = cs[C_ROT_S1]
    else:
        c = math.cos(dth)
        s = math.sin(dth)
        cs[C_ROT_DTH1] = cs[C_ROT_DTH0]
        cs[C_ROT_C1] = cs[C_ROT_C0]
        cs[C_ROT_S1] = cs[C_ROT_S0]
        cs[C_ROT_DTH0] = dth
        cs[C_ROT_C0] = c
        cs[C_ROT_S0] = s
    return e1 * complex(c, -s)


@njit(**JIT_INLINE)
def control_period(cs, q, meas):
    """One 100 us period of the control law from the measurable part of a plant state vector
    (phase currents, encoder count / edge time, period counter, relay state). Returns
    (da, db, dc, relay_request, buck_duty)."""
    relay = meas[M.S_RELAY]
    # currents in the encoder frame; the angle's sincos is tracked by small rotations as the
    # count moves (exact sincos every 64 periods and on large jumps)
    pp = q[Q_PP]
    cnt = meas[M.S_COUNT]
    # (reciprocals precomputed: a division per use costs the per-period path several ns)
    th = pp * (cnt + 0.5) * q[Q_RAD_PER_COUNT]
    dth = pp * (cnt - cs[C_CNT]) * q[Q_RAD_PER_COUNT]
    if cs[C_HAVE_ANGLE] == 0.0 or (int(meas[M.S_PERIODS]) & 63) == 0 or abs(dth) > 0.5:
        c = math.cos(th)
        s = math.sin(th)
        cs[C_HAVE_ANGLE] = 1.0
    elif dth != 0.0:
        e = _rot_counts(cs, complex(cs[C_COS], -cs[C_SIN]), dth)    # exp(-j th)
        c = e.real
        s = -e.imag
    else:
        c = cs[C_COS]
        s = cs[C_SIN]
    cs[C_COS] = c
    cs[C_SIN] = s
    cs[C_CNT] = cnt
    if q[Q_ILSB] > 0.0:
        # two phase currents through the ADC (quantised to one LSB), the third from their sum
        # (x * (1 / lsb) as fastmath's arcp formed it, the reciprocal precomputed; np.floor
        # stays a float: math.floor's int64 round trip is two conversions on the period's
        # longest latency chain)
        lsb = q[Q_ILSB]
        inv_lsb = q[Q_INV_ILSB]
        ia_m = np.floor(meas[M.S_IA] * inv_lsb + 0.5) * lsb
        ib_m = np.floor(meas[M.S_IB] * inv_lsb + 0.5) * lsb
        ial = ia_m
        ibe = (ia_m + 2.0 * ib_m) * (1.0 / SQRT3)
    else:
        ial = (2.0 * meas[M.S_IA] - meas[M.S_IB] - meas[M.S_IC]) * (1.0 / 3.0)
        ibe = (meas[M.S_IB] - meas[M.S_IC]) * (1.0 / SQRT3)
    idm = ial * c + ibe * s
    iqm = -ial * s + ibe * c
    cs[C_ID] = idm
    cs[C_IQ] = iqm
    cs[C_IQ_SUM] += iqm
    cs[C_IQ_N] += 1.0
    cs[C_THETA_E] = th
    draining = relay == M.REL_DRAIN and meas[M.S_RELAY_FROM] == M.REL_INVERTER
    # Relay path of paper 001, Fig. 2/8: asked to leave the inverter for the rectifier, the
    # inverter first takes iq towards zero (the pre-drain: the drain's references), and passes
    # the request on once |iq| is within Q_PREDRAIN_IQ (or after Q_PREDRAIN_N periods). Passed
    # at once, the relay's 5 ms drain timeout came before a braking current had decayed (only as
    # fast as the voltage left over the back-EMF lets it): -5 N m at 340 r/min was -3.1 N m when
    # the relay was forced open, now 0.04 (forced still: above the base speed id is not zero);
    # at 100 r/min -0.6 forced, now 0.003 and the relay opens on its own
    req = cs[C_RELAY_REQ]
    predrain = False
    if relay != M.REL_INVERTER or req < 0.5:
        cs[C_PREDRAIN_N] = 0.0
    elif cs[C_PREDRAIN_N] < q[Q_PREDRAIN_N] and abs(iqm) > q[Q_PREDRAIN_IQ]:
        predrain = True
        cs[C_PREDRAIN_N] += 1.0
        req = 0.0
    if q[Q_OBSERVER] != 0.0:
        # torque feed-forward only while the inverter controls the machine; on the rectifier
        # path the observer is a pure encoder tracking filter (a stiff prime mover would
        # otherwise make every braking-torque change look like an acceleration)
        inv = relay == M.REL_INVERTER or draining
        iq_ff = iqm if inv else 0.0
        was = cs[C_OBS_INV]                            # 0 off, 1 inverter, 2 draining
        # (not as the observer re-acquires after skipped plant states: the relay may have moved
        # while they were skipped, and the current before them says nothing of now)
        if cs[C_OBS_INIT] != 0.0 and cs[C_OBS_INIT] != 2.0 and inv != (was != 0.0):
            # feed-forward switched on / off (relay): the disturbance state takes over the
            # torque the feed-forward stops (or starts) explaining, so the estimate is bumpless.
            # Not off after a drain: its current (driven to zero, or above the link voltage's
            # speed the back-EMF's through the diodes, 4-6 N m of braking, the relay then
            # forced open) stops with the relay. Carried over, the estimate fell to 0.5x the
            # shaft's in ~50 ms (a command timeout's safe state put the relay on the inverter)
            if inv or was != 2.0:
                cs[C_OBS_D] += q[Q_KT] * (cs[C_OBS_IQFF] - iq_ff) / q[Q_JN]
        cs[C_OBS_IQFF] = iq_ff
        cs[C_OBS_INV] = 2.0 if draining else 1.0 if inv else 0.0
        observer_update(cs, q, meas, iq_ff)
    ns = q[Q_NS]
    if cs[C_SUB] == 0.0:
        if q[Q_OBSERVER] == 0.0:
            speed_sample(cs, q, meas)
        if predrain:
            # (its saturated periods say nothing of the speed loop's plan: counted, each of its
            # saturated ms would take 0.2 V off the plan when the speed loop next ran)
            cs[C_VSAT] = 0.0
            cs[C_IQ_SUM] = 0.0
            cs[C_IQ_N] = 0.0
        elif relay == M.REL_INVERTER:
            speed_loop(cs, q)
        else:
            cs[C_SPEED_ACTIVE] = 0.0
            if relay == M.REL_RECTIFIER:
                cs[C_BUCK_DUTY] = buck_duty_for_brake_torque(cs[C_BRAKE_T], q[Q_PP] * cs[C_SPEED_EST], q)
    sub = cs[C_SUB] + 1.0
    cs[C_SUB] = 0.0 if sub >= ns else sub            # (no integer modulo in the hot path)
    cs[C_TORQUE_EST] = q[Q_TORQUE_K] * iqm
    if draining or predrain:
        # relay switch-over pending: the inverter drives the current to zero first, or, above
        # the base speed, where the link cannot oppose the back-EMF, to no torque (iq = 0 at the
        # flux-weakening id, drain_id_reference) until the relay opens. The pre-drain plans its id
        # with 20 % of the modulator's circle less: what moves iq is the voltage left over the
        # back-EMF, and at the drain's own id a braking current took 2.4x as long (-5 N m at
        # 340 r/min: 28.2 ms to |iq| < 0.15 A, now 11.7 ms; -16 N m: 19.2, now 10.7)
        vlim = q[Q_VMARGIN] * q[Q_VMAX] - (q[Q_PREDRAIN_DV] if predrain else 0.0)
        cs[C_ID_REF] = drain_id_reference(pp * cs[C_SPEED_EST], vlim, q) if q[Q_FW] != 0.0 else 0.0
        cs[C_IQ_REF] = 0.0
        cs[C_SPEED_ACTIVE] = 0.0
    elif relay != M.REL_INVERTER:
        cs[C_CUR_ACTIVE] = 0.0
        cs[C_ID_PREV] = idm
        cs[C_IQ_PREV] = iqm
        cs[C_VD] = 0.0
        cs[C_VQ] = 0.0
        cs[C_DA] = 0.5
        cs[C_DB] = 0.5
        cs[C_DC] = 0.5
        cs[C_PEND_OK] = 0.0
        return 0.5, 0.5, 0.5, cs[C_RELAY_REQ], cs[C_BUCK_DUTY]
    r = q[Q_R]
    lh = q[Q_L]
    we = pp * cs[C_SPEED_EST]
    if cs[C_CUR_ACTIVE] == 0.0:
        # bumpless start: decoupled voltages of the measured steady state, no increments
        cs[C_VDP_PREV] = r * idm
        cs[C_VQP_PREV] = r * iqm
        cs[C_ID_PREV] = idm
        cs[C_IQ_PREV] = iqm
        cs[C_ED_PREV] = cs[C_ID_REF] - idm
        cs[C_EQ_PREV] = cs[C_IQ_REF] - iqm
        cs[C_CUR_ACTIVE] = 1.0
    ed = cs[C_ID_REF] - idm
    eq = cs[C_IQ_REF] - iqm
    if q[Q_FAMILY_CURRENT] == 0.0:
        # predictive_increment(i*, i, di, a, b, r) with b / (b^2 + r) precomputed
        dvd = q[Q_GC] * (ed - q[Q_AC] * (idm - cs[C_ID_PREV]))
        dvq = q[Q_GC] * (eq - q[Q_AC] * (iqm - cs[C_IQ_PREV]))
    else:
        dvd = q[Q_KPC] * (ed - cs[C_ED_PREV]) + q[Q_KIC] * ed
        dvq = q[Q_KPC] * (eq - cs[C_EQ_PREV]) + q[Q_KIC] * eq
    # coupling terms added back (Eq. 62-63): vd = v'd - we L iq, vq = v'q + we (L id + lambda)
    cpl_d = -we * lh * iqm
    cpl_q = we * (lh * idm + q[Q_LAM])
    vd = cs[C_VDP_PREV] + dvd + cpl_d
    vq = cs[C_VQP_PREV] + dvq + cpl_q
    vmax = q[Q_VMAX]
    if vd * vd + vq * vq > vmax * vmax:
        vd, vq = limit_voltage(vd, vq, idm, iqm, we, vmax, q, cs[C_EDGE] != 0.0 and not (draining or predrain))
        cs[C_VSAT] += 1.0
    cs[C_VDP_PREV] = vd - cpl_d          # anti-windup: the applied voltage, decoupled
    cs[C_VQP_PREV] = vq - cpl_q
    cs[C_ID_PREV] = idm
    cs[C_IQ_PREV] = iqm
    cs[C_ED_PREV] = ed
    cs[C_EQ_PREV] = eq
    cs[C_VD] = vd
    cs[C_VQ] = vq
    if q[Q_ANGLE_COMP] != 0.0:
        # exp(j (th + we T (1/2 + delay))): the mid angle of the period the voltage is applied in
        # (a short series below 0.02 rad, ~640 r/min, a longer one below 0.1 rad, ~1900 r/min:
        # no libm sincos per period)
        rot = M._rot_tel(complex(c, -s), -(0.5 + q[Q_DELAY]) * we * q[Q_DT]).conjugate()
        ca = rot.real
        sa = rot.imag
    else:
        ca = c
        sa = s
    da, db, dc = _modulate_g(vd * ca - vq * sa, vd * sa + vq * ca, q[Q_INV_VDC], q[Q_MODULATION])
    if q[Q_DELAY] != 0.0 and cs[C_PEND_OK] != 0.0:
        # one-period computation delay (DSP): the duties computed from the samples of period
        # k reach the PWM compare registers (shadow load) at the start of period k + 1; this
        # period runs on the ones computed in the previous period
        oa = cs[C_DA]
        ob = cs[C_DB]
        oc = cs[C_DC]
    else:
        oa = da
        ob = db
        oc = dc
    cs[C_PEND_OK] = 1.0
    cs[C_DA] = da
    cs[C_DB] = db
    cs[C_DC] = dc
    return oa, ob, oc, req, cs[C_BUCK_DUTY]


def init_controller_state(q: np.ndarray, cp: SpmsmControllerParams, meas: np.ndarray | None = None) -> np.ndarray:
    """Controller memory. With a measured plant state, the drive is taken as already running
    (speed estimate = the true speed, bumpless current loops)."""
    cs = np.zeros(C_SIZE)
    w0 = cp.speed_ref0_rpm / RPM_PER_RAD_S
    cs[C_SPEED_REF] = w0
    cs[C_SPEED_REF_NEXT] = w0
    cs[C_BRAKE_T] = cp.brake_torque0_nm
    cs[C_BUCK_DUTY] = q[Q_BUCK_V] / q[Q_LINK_MAX]
    if meas is not None:
        cs[C_SPEED_EST] = meas[M.S_OMEGA]
    return cs


# telemetry (ControllerStatus-like), identical for both families
STATUS_FIELDS = ("speed_est_rpm", "speed_ref_rpm", "id_a", "iq_a", "id_ref_a", "iq_ref_a", "iq_demand_a", "vd_v",
                 "vq_v", "region", "limits", "torque_est_nm", "advance_angle_rad", "relay_request", "buck_duty")


@njit(**JIT_INLINE)
def advance_angle_rad(cs):
    """Current advance angle beta = atan2(-id*, |iq*|) of the last speed-loop references
    (paper 001, Fig. 7b; 0 before the first run)."""
    idr = cs[C_ADV_ID]
    iqr = cs[C_ADV_IQ]
    return math.atan2(-idr, abs(iqr)) if (idr != 0.0 or iqr != 0.0) else 0.0


def status_of(cs: np.ndarray) -> dict:
    # read from one list of the state's head (Python floats, the same values): fifteen numpy
    # scalar reads and float() calls cost twice as much, once per batch
    c = cs[:_STATUS_SPAN].tolist()
    return {
        "speed_est_rpm": c[C_SPEED_EST] * RPM_PER_RAD_S,
        "speed_ref_rpm": c[C_SPEED_REF] * RPM_PER_RAD_S,
        "id_a": c[C_ID], "iq_a": c[C_IQ],
        "id_ref_a": c[C_ID_REF], "iq_ref_a": c[C_IQ_REF], "iq_demand_a": c[C_IQ_DEMAND],
        "vd_v": c[C_VD], "vq_v": c[C_VQ],
        "region": int(c[C_REGION]), "limits": int(c[C_LIMITS]),
        "torque_est_nm": c[C_TORQUE_EST], "advance_angle_rad": float(advance_angle_rad(cs)),
        "relay_request": int(c[C_RELAY_REQ]), "buck_duty": c[C_BUCK_DUTY],
    }


_STATUS_SPAN = max(C_SPEED_EST, C_SPEED_REF, C_ID, C_IQ, C_ID_REF, C_IQ_REF, C_IQ_DEMAND, C_VD, C_VQ, C_REGION,
                   C_LIMITS, C_TORQUE_EST, C_RELAY_REQ, C_BUCK_DUTY) + 1


@njit(**JIT)
def control_batch(cs, q, model, p_nom, duties, relay, buck, ws):
    """N periods answering one measured state: the control law runs on the state predicted
    with the controller's own copy of the plant kernel (nominal parameters; the caller sets
    the model's load to hold the measured speed), ARCHITECTURE.md batched inner loop."""
    n = duties.shape[0]
    for k in range(n):
        da, db, dc, rr, bd = control_period(cs, q, model)
        duties[k, 0] = da
        duties[k, 1] = db
        duties[k, 2] = dc
        relay[k] = rr
        buck[k] = bd
        M.step_period(model, p_nom, da, db, dc, rr, bd, ws)


class SpmsmController:
    """The SPMSM control law without ROS: per-period kernel + batched prediction."""

    def __init__(self, cfg: dict, nominal_params: M.SpmsmPlantParams | None = None, family: str | None = None,
                 batch_periods: int | None = None):
        cp = controller_params_from_config(cfg)
        if family is not None:
            if family not in FAMILIES:
                raise ValueError(f"family must be one of {', '.join(FAMILIES)}, got {family!r}")
            cp.family = family
        self.cp = cp
        self.nominal = nominal_params if nominal_params is not None else M.nominal_params_from_config(cfg)
        self.q = pack_controller(cp, self.nominal)
        self.p = M.pack_params(self.nominal)
        self.p[M.P_LOAD_KIND] = M.LOAD_PRIME_MOVER     # prediction: shaft speed held at the measured value
        n = batch_periods if batch_periods is not None else cfg.get("batch_periods", cp.speed_loop_periods)
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ConfigError(f"must be an integer >= 1, got {n!r}", cfg.get("_config_path"), "batch_periods")
        self.batch_periods = n
        self.cs = init_controller_state(self.q, cp)
        self.model = None
        self.ws = np.zeros(M.WS_SIZE)
        self._next_periods: float | None = None   # S_PERIODS of the plant state after the last one decided
        self.skipped_state_gaps = 0               # decides after skipped plant states (realtime)
        self.skipped_periods = 0                  # ... and the control periods they covered

    def set_observer_pole(self, pole_hz: float) -> None:
        """The speed observer's triple pole from now on (its angle, speed and disturbance carry
        over, so the switch is bumpless)."""
        q = self.q
        q[Q_OBS_L1], q[Q_OBS_L2], q[Q_OBS_L3] = observer_gains(pole_hz, self.nominal.control_period_s)

    def reset_from(self, plant_state: np.ndarray) -> None:
        """Start as an already running drive at the plant's state (offline runs); the assist cap
        (set_assist_cap, a setting, not a state) is kept."""
        cap = self.cs[C_ASSIST_CAP_A]
        self.cs = init_controller_state(self.q, self.cp, plant_state)
        self.cs[C_ASSIST_CAP_A] = cap
        self._next_periods = None

    def _bridge_skipped_periods(self, periods: int, count: float) -> None:
        """The plant ran ``periods`` control periods this controller never saw (realtime: it reads
        the newest plant state only, and skips what came while it was descheduled).

        Left at the end of the last batch, the observer took the angle the shaft turned in the
        gap as an angle error to its gains (a 5 Hz triple pole): its speed rose to 1.7x the
        shaft's after 30 ms skipped, 5.8x after 200 ms, for ~0.1 s (the mode law's virtual
        speed, an app's km/h, with it). Now it re-acquires (:func:`observer_restart`): the angle
        from the encoder, the speed from the counts of the next speed sample, the gap's mean
        speed until then. A prediction run over the gap (Kt iq fed forward, the disturbance
        held) did for gaps within the plant's command timeout, but past it the plant's safe
        state then (gates off, the relay on the inverter: 5-7 N m of diode braking at 330
        r/min) was a torque the model has no input for: after a 62-75 ms stall under load the
        estimate read 0.26x - 1.33x the shaft's for ~0.1 s (restarted at the gap's mean speed
        with the disturbance zeroed), 0.6x - 3x (predicted, or fitted to the count).

        M method: its count difference would span the gap too (the speed that many times too
        high): the next sample starts afresh and the gap's mean speed stands until the one
        after. M/T needs nothing: its counts and capture ticks span the same time."""
        cs, q = self.cs, self.q
        gap_mean = self.gap_mean_speed_rad_s(periods, count)
        if q[Q_OBSERVER] != 0.0 and cs[C_OBS_INIT] != 0.0:
            cs[C_OBS_W] = gap_mean
            cs[C_OBS_INIT] = 2.0
        if q[Q_MMETHOD] != 0.0:
            cs[C_HAVE_REF] = 0.0
            cs[C_SPEED_EST] = gap_mean

    def gap_mean_speed_rad_s(self, periods: int, count: float) -> float:
        """The shaft's mean speed over ``periods`` skipped control periods and the one before
        them, from the encoder count then (C_CNT: the count of the last period decided) and now."""
        return (count - self.cs[C_CNT]) * self.q[Q_RAD_PER_COUNT] / ((periods + 1) * self.q[Q_DT])

    def set_speed_ref(self, speed_rpm: float, next_speed_rpm: float | None = None) -> None:
        """Speed command; the predictive law's cost uses the reference one speed sample ahead."""
        for v in (speed_rpm, next_speed_rpm):
            if v is not None and not math.isfinite(v):
                raise ValueError(f"speed reference must be finite, got {v!r}")
        self.cs[C_SPEED_REF] = speed_rpm / RPM_PER_RAD_S
        self.cs[C_SPEED_REF_NEXT] = (speed_rpm if next_speed_rpm is None else next_speed_rpm) / RPM_PER_RAD_S

    def set_no_assist(self, hold: bool) -> None:
        """Hold the speed loop's motoring torque at zero (an empty pack), braking kept."""
        self.cs[C_NO_ASSIST] = 1.0 if hold else 0.0

    def set_assist_cap(self, current_a: float) -> None:
        """The most motoring current the speed loop may ask [A] (0: none but the current limit);
        ValueError for a negative or non-finite one."""
        if not (math.isfinite(current_a) and current_a >= 0.0):
            raise ValueError(f"assist cap must be a finite current >= 0 A, got {current_a!r}")
        self.cs[C_ASSIST_CAP_A] = float(current_a)

    def assist_capped(self) -> bool:
        """The speed loop's last demand was held at the assist cap (set_assist_cap)."""
        cs = self.cs
        return bool(cs[C_ASSIST_CAP_A] > 0.0 and cs[C_TORQUE_MODE] == 0.0 and abs(cs[C_IQ_DEMAND]) >= cs[C_ASSIST_CAP_A]
                    and cs[C_IQ_DEMAND] * cs[C_SPEED_EST] >= 0.0)

    def set_relay(self, rectifier: bool) -> None:
        self.cs[C_RELAY_REQ] = 1.0 if rectifier else 0.0

    def set_brake_torque(self, torque_nm: float) -> None:
        if not (math.isfinite(torque_nm) and torque_nm >= 0.0):
            raise ValueError(f"brake torque must be finite and >= 0, got {torque_nm!r}")
        self.cs[C_BRAKE_T] = float(torque_nm)

    def set_torque_command(self, torque_nm: float | None) -> None:
        """Torque control through the inverter (motoring positive, Eq. 8: iq* = T / Kt) in
        place of the speed controller; None returns to speed control (bumpless: the speed
        loop continues from the iq reference in force)."""
        if torque_nm is None:
            self.cs[C_TORQUE_MODE] = 0.0
            self.cs[C_DV_FLOOR_V] = 0.0      # the edge's margin is learned afresh (speed_loop)
            return
        if not math.isfinite(torque_nm):
            raise ValueError(f"torque command must be finite, got {torque_nm!r}")
        self.cs[C_TORQUE_MODE] = 1.0
        self.cs[C_TORQUE_CMD] = float(torque_nm)

    def gap_periods(self, plant_state: np.ndarray) -> int:
        """Control periods of the plant states skipped before ``plant_state`` (realtime: the plant
        ran them while this controller was descheduled); 0 for the state after the last one
        decided (lockstep, always)."""
        periods = float(plant_state[M.S_PERIODS])
        if self._next_periods is None or periods <= self._next_periods:
            return 0
        return int(periods - self._next_periods)

    def decide(self, plant_state: np.ndarray, n: int | None = None):
        """N periods of (duties N x 3, relay request N, buck duty N) answering a measured
        plant state vector (layout bike_plant.spmsm.S_*), + status."""
        n = self.batch_periods if n is None else int(n)
        self.model = np.array(plant_state, dtype=np.float64, copy=True)
        self.model[M.S_SPEED_TARGET] = self.model[M.S_OMEGA]
        # a plant state later than the one after the last decided: the ones between were skipped
        # (lockstep never skips, and a state without a period count never says so)
        periods = float(self.model[M.S_PERIODS])
        gap = self.gap_periods(self.model)
        if gap > 0:
            self._bridge_skipped_periods(gap, float(self.model[M.S_COUNT]))
            self.skipped_state_gaps += 1
            self.skipped_periods += gap
        self._next_periods = periods + n
        duties = np.zeros((n, 3))
        relay = np.zeros(n)
        buck = np.zeros(n)
        control_batch(self.cs, self.q, self.model, self.p, duties, relay, buck, self.ws)
        return duties, relay, buck, status_of(self.cs)

    def status(self) -> dict:
        return status_of(self.cs)


# =======================================================================================
# offline closed loop
# =======================================================================================
REC_FIELDS = ("t", "speed_rpm", "speed_est_rpm", "speed_ref_rpm", "id", "iq", "id_ref", "iq_ref", "iq_demand",
              "vd", "vq", "ia", "ib", "ic", "torque", "torque_est", "load_torque", "region", "limits", "relay",
              "buck_duty", "battery_current", "advance_angle", "iterations", "encoder_count")
(R_T, R_SPEED, R_SPEED_EST, R_SPEED_REF, R_ID, R_IQ, R_ID_REF, R_IQ_REF, R_IQ_DEM, R_VD, R_VQ, R_IA, R_IB, R_IC,
 R_TORQUE, R_TORQUE_EST, R_TLOAD, R_REGION, R_LIMITS, R_RELAY, R_BUCK, R_IBATT, R_ADV, R_ITER,
 R_COUNT) = range(len(REC_FIELDS))
N_REC = len(REC_FIELDS)


@njit(**JIT)
def run_kernel(plant, p, cs, q, k0, k1, ref_w, tl, relay_req, brake_t, rec, rec_every, ws):
    """Closed loop for periods k0..k1-1 (global indices): per speed sample j = k // Ns the
    references ref_w[j] (and ref_w[j+1] for the predictive cost), dynamometer torque tl[j]
    (NaN: the plant's configured load), relay request and brake torque; records one row
    every rec_every periods (the state after the period)."""
    ns = int(q[Q_NS])
    # speed-sample index and phase, record row and phase: counters, not integer division
    j = k0 // ns
    sub = k0 - j * ns
    r = k0 // rec_every if rec_every > 0 else 0
    rsub = k0 - r * rec_every if rec_every > 0 else 1
    for k in range(k0, k1):
        if sub == 0:
            cs[C_SPEED_REF] = ref_w[j]
            cs[C_SPEED_REF_NEXT] = ref_w[j + 1]
            cs[C_RELAY_REQ] = relay_req[j]
            cs[C_BRAKE_T] = brake_t[j]
            if not math.isnan(tl[j]):
                plant[M.S_TEXT] = -tl[j]
        da, db, dc, rr, bd = control_period(cs, q, plant)
        M.step_period(plant, p, da, db, dc, rr, bd, ws)
        sub += 1
        if sub == ns:
            sub = 0
            j += 1
        if rsub == 0:
            if r < rec.shape[0]:
                rec[r, R_T] = plant[M.S_PERIODS] * p[M.P_DT]
                rec[r, R_SPEED] = plant[M.S_OMEGA] * 9.549296585513721
                rec[r, R_SPEED_EST] = cs[C_SPEED_EST] * 9.549296585513721
                rec[r, R_SPEED_REF] = cs[C_SPEED_REF] * 9.549296585513721
                rec[r, R_ID] = plant[M.S_ID]
                rec[r, R_IQ] = plant[M.S_IQ]
                rec[r, R_ID_REF] = cs[C_ID_REF]
                rec[r, R_IQ_REF] = cs[C_IQ_REF]
                rec[r, R_IQ_DEM] = cs[C_IQ_DEMAND]
                rec[r, R_VD] = cs[C_VD]
                rec[r, R_VQ] = cs[C_VQ]
                rec[r, R_IA] = plant[M.S_IA]
                rec[r, R_IB] = plant[M.S_IB]
                rec[r, R_IC] = plant[M.S_IC]
                rec[r, R_TORQUE] = plant[M.S_TEM]
                rec[r, R_TORQUE_EST] = cs[C_TORQUE_EST]
                rec[r, R_TLOAD] = plant[M.S_TLOAD]
                rec[r, R_REGION] = cs[C_REGION]
                rec[r, R_LIMITS] = cs[C_LIMITS]
                rec[r, R_RELAY] = plant[M.S_RELAY]
                rec[r, R_BUCK] = cs[C_BUCK_DUTY]
                rec[r, R_IBATT] = plant[M.S_IBATT]
                rec[r, R_ADV] = advance_angle_rad(cs)
                rec[r, R_ITER] = plant[M.S_ITER]
                rec[r, R_COUNT] = plant[M.S_COUNT]
            r += 1
        if rec_every > 0:
            rsub += 1
            if rsub == rec_every:
                rsub = 0


def _sample_fn(fn, t: np.ndarray, default: float, name: str) -> np.ndarray:
    """Evaluate fn on the sample times: vectorised if fn accepts an array, else per sample."""
    if fn is None:
        return np.full(t.shape, float(default))
    if not callable(fn):
        return np.full(t.shape, float(fn))
    try:
        out = np.asarray(fn(t), dtype=np.float64)
        if out.shape != t.shape:
            raise ValueError
    except Exception:
        out = np.array([float(fn(float(x))) for x in t])
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{name} returned a non-finite value")
    return out


def _relay_value(v) -> float:
    if isinstance(v, str):
        if v not in ("inverter", "rectifier"):
            raise ValueError(f"relay must be 'inverter' or 'rectifier', got {v!r}")
        return 1.0 if v == "rectifier" else 0.0
    return 1.0 if float(v) >= 0.5 else 0.0


def run_spmsm_offline(cfg: dict, duration_s: float, speed_ref_fn=None, load_fn=None, controller: str = "predictive",
                      switching: bool = False, *, relay_fn=None, brake_torque_fn=None, load_hook=None,
                      record_every: int = 1, plant_params: M.SpmsmPlantParams | None = None,
                      nominal_params: M.SpmsmPlantParams | None = None, no_assist: bool = False) -> dict:
    """Plant + controller closed loop without ROS (per-period loop, fused in numba).

    speed_ref_fn(t) -> speed command [r/min] (None: controller.speed_ref0_rpm);
    load_fn(t) -> dynamometer torque TL [N m] of Eq. 3 (positive opposes rotation; None:
    the config's load); both are sampled once per speed-loop period (1 ms), vectorised when
    they accept arrays. relay_fn(t) -> 0 / 'inverter' or 1 / 'rectifier'; brake_torque_fn(t)
    -> braking torque demand [N m] on the rectifier path. load_hook(t, speed_rad_s, dt_s) ->
    torque on the shaft (accelerating positive), state dependent, called every 1 ms.
    controller: 'predictive' | 'pi'; switching: the switching inverter model (else average).
    no_assist: the speed loop may brake but not motor (an empty pack, SpmsmController.set_no_assist).

    Returns a dict of numpy arrays named by REC_FIELDS (one row every `record_every`
    periods), plus 'ledger', 'plant', 'controller', 'wall_s'.
    """
    if not (isinstance(duration_s, (int, float)) and duration_s > 0 and math.isfinite(duration_s)):
        raise ValueError(f"duration_s must be > 0, got {duration_s!r}")
    if controller not in FAMILIES:
        raise ValueError(f"controller must be one of {', '.join(FAMILIES)}, got {controller!r}")
    if load_fn is not None and load_hook is not None:
        raise ValueError("give load_fn (a dynamometer torque profile) or load_hook (state dependent), not both")
    params = plant_params or M.plant_params_from_config(cfg)
    if switching:
        params.inverter.model = "switching"
    elif plant_params is None:
        params.inverter.model = "average"
    plant = M.SpmsmPlant(params, load_hook=load_hook)
    if load_fn is not None:
        plant.p[M.P_LOAD_KIND] = M.LOAD_HOOK
    ctrl = SpmsmController(cfg, nominal_params, family=controller)
    ctrl.reset_from(plant.state)
    ctrl.set_no_assist(no_assist)
    q = ctrl.q
    dt = params.control_period_s
    ns = int(q[Q_NS])
    n_periods = int(math.ceil(duration_s / dt - 1e-9))
    n_speed = n_periods // ns + 2
    ts = np.arange(n_speed + 1) * (dt * ns)
    ref_w = _sample_fn(speed_ref_fn, ts, ctrl.cp.speed_ref0_rpm, "speed_ref_fn") / RPM_PER_RAD_S
    tl = np.full(n_speed + 1, np.nan) if load_fn is None else _sample_fn(load_fn, ts, 0.0, "load_fn")
    if relay_fn is None:
        relay = np.zeros(n_speed + 1)
    else:
        relay = np.array([_relay_value(relay_fn(float(x))) for x in ts])
    brake = _sample_fn(brake_torque_fn, ts, ctrl.cp.brake_torque0_nm, "brake_torque_fn")
    if np.any(brake < 0):
        raise ValueError("brake_torque_fn must return values >= 0")
    record_every = max(int(record_every), 1)
    rec = np.zeros((n_periods // record_every + 1, N_REC))
    ws = np.zeros(M.WS_SIZE)
    t_wall = time.perf_counter()
    if load_hook is None:
        run_kernel(plant.state, plant.p, ctrl.cs, q, 0, n_periods, ref_w, tl, relay, brake, rec, record_every, ws)
    else:
        for k0 in range(0, n_periods, ns):
            plant.before_batch(ns)
            run_kernel(plant.state, plant.p, ctrl.cs, q, k0, min(k0 + ns, n_periods), ref_w, tl, relay, brake, rec,
                       record_every, ws)
    wall = time.perf_counter() - t_wall
    n_rec = (n_periods - 1) // record_every + 1
    out = {name: rec[:n_rec, i].copy() for i, name in enumerate(REC_FIELDS)}
    out["ledger"] = plant.ledger()
    out["plant"] = plant
    out["controller"] = ctrl
    out["wall_s"] = wall
    return out


def harmonic_amplitudes(t_s: np.ndarray, x: np.ndarray, f0_hz: float, n_harmonics: int = 15) -> np.ndarray:
    """Amplitudes of harmonics 1..n of x(t) (uniform samples), by correlation over the
    longest whole number of fundamental periods at the end of the record."""
    t_s = np.asarray(t_s, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    n_per = int(math.floor((t_s[-1] - t_s[0]) * f0_hz + 1e-9))
    if n_per < 1:
        raise ValueError("the record is shorter than one fundamental period")
    sel = t_s >= t_s[-1] - n_per / f0_hz + 0.5 * (t_s[1] - t_s[0])
    tt, xx = t_s[sel], x[sel]
    return np.array([2.0 * abs(np.mean(xx * np.exp(-2j * math.pi * h * f0_hz * tt)))
                     for h in range(1, n_harmonics + 1)])


def thd_percent(t_s: np.ndarray, x: np.ndarray, f0_hz: float, up_to: int = 15) -> float:
    """Total harmonic distortion [%] from the 2nd to the `up_to`-th harmonic (paper 001,
    Fig. 15b/16b: up to the 15th). f0 = pp * speed_rpm / 60 for a phase current."""
    a = harmonic_amplitudes(t_s, x, f0_hz, up_to)
    return float(100.0 * math.sqrt(float(np.sum(a[1:] ** 2))) / a[0])
