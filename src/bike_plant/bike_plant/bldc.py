"""Numba kernels of the BLDC machine + 6-switch bridge + battery + shaft (paper 000).

Everything that runs once per 50 us control period lives here, compiled with
the options of :mod:`bike_plant.jit` (``@njit(**JIT)``, inlined: ``JIT_INLINE``); a whole batch of N
periods is one call (:func:`step_batch`), so there is no Python per period. The
controller's predictor calls the same :func:`step_period` on its own state vector
(ARCHITECTURE.md, batched inner loop).

Electrical model (per phase x = a, b, c; terminal voltage v_x w.r.t. DC minus):
    v_x = v_n + R i_x + L_x di_x/dt + i_x dL_x/dt + e_x,   e_x = kph * w_m * f_x(theta_e)
f_x is the 120-degree flat-top trapezoid (paper 000, Fig. 4), optionally blended with a
sinusoid at low speed (section 4.3, Fig. 11: the reason for k < 1). Torque (motoring
positive): T = sum(kph f_x i_x) + 1/2 sum(i_x^2 dL_x/dtheta_m).

Switches and diodes are ideal (no forward drop, no switching loss; r_phase_ohm lumps the
switch on-resistance into the winding): Table 1 gives no device data and Eq. 6 neglects
losses. They would matter at the low end of Fig. 14: with a typical IGBT's ~1.5 V and a
diode's ~1 V in the Q2-D4 loop of Fig. 6(a) no current builds until E_LL = ke n > ~2.5 V,
i.e. below ~460 rpm nothing brakes. So the ledger's losses are copper + friction only, and
the battery's share is at its terminals (its internal resistance's heat included: 4.6 % of
it at 3000 rpm, Command 1).

Integration: per segment of constant switch pattern, one trapezoidal (Crank-Nicolson)
step per phase with the back-EMF held at the mid-period angle:
    g_x = t / (L_x + R_x t / 2),  w_x = v_x - e_x - R_x i0_x,
    v_n = sum(g_x w_x) / sum(g_x) over conducting legs,  i1_x = i0_x + g_x (w_x - v_n).
With copper loss R t ((i0 + i1)/2)^2 the energy balance of a step is exact. A diode-only
leg whose current reaches zero splits the segment at the crossing (secant on the same
step formula) and the topology is re-evaluated.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import jit as _jit
from . import params as P
from .jit import JIT, JIT_COLD, JIT_HOT, JIT_INLINE, KERNEL_FASTMATH, invalidate_stale_numba_cache  # noqa: F401


invalidate_stale_numba_cache(__file__, [P.__file__, _jit.__file__])

# ---- state vector layout ---------------------------------------------------------------
S_IA, S_IB, S_IC = 0, 1, 2
S_THETA_E = 3          # electrical angle, wrapped to [0, 2 pi)
S_OMEGA = 4            # mechanical speed [rad/s]
S_VDC = 5              # DC bus voltage applied during the next period
S_SOC = 6
S_S0 = 7               # brake resistor switch (0/1)
S_VFILT = 8            # S0 comparator input (filtered v_dc)
S_HALL = 9             # 3-bit Hall code
S_PERIODS = 10         # control periods since start (time = periods * dt, exact)
S_CRANK = 11           # crank angle [rad] (rider)
S_EFFORT = 12          # rider effort 0..1
S_RIDER_INT = 13       # rider PI integrator
S_SPEED_TARGET = 14    # prime mover speed [rad/s]
S_IDC = 15             # mean current bridge -> DC node over the last period
S_E_MECH = 16          # ledger, cumulative [J]
S_E_BATT = 17
S_E_RES = 18
S_E_CU = 19
S_E_FRIC = 20
S_E_STORED0 = 21       # kinetic + magnetic energy at start
S_E_CONV = 22          # electrical -> mechanical conversion (diagnostic)
S_INTERLOCK = 23       # blanked leg count
S_FAULTS = 24
S_TEM = 25             # mean T_em of the last period
S_TLOAD = 26           # mean external load torque of the last period
S_IBATT = 27           # mean battery current (charging positive) of the last period
S_OC_TRIPS = 28        # periods blanked by the cycle-by-cycle overcurrent trip (cumulative)
S_IDC_AVG = 29         # S0 on: the bridge current smoothed by the comparator's filter [A]
S_I_CHOP = 30          # S0 on: the current the chopper takes in the next period [A] (v_dc / R_brake at most)
S_SIZE = 32

FAULT_INTERLOCK = 1
FAULT_OVERVOLTAGE = 4
FAULT_OVERCURRENT = 512   # = PlantState.FAULT_OVERCURRENT: a period's gates were blanked by the trip
# = PlantState.FAULT_UNCONTROLLED_GENERATION: the line-to-line back-EMF above the DC bus, so the
# bridge's diodes rectify it whatever the gates do (set by BldcPlant.snapshot, per batch)
FAULT_UNCONTROLLED_GENERATION = 128
# = PlantState.FAULT_PACK_EMPTY: SOC at or below params.PACK_EMPTY_SOC (set by BldcPlant.snapshot, per batch)
FAULT_PACK_EMPTY = 2048
# FAULT_OVERVOLTAGE also while a pack past full takes charge: S0's resistor cannot take the
# regenerated power (a 100 ohm resistor charged the pack to SOC 1.15 with no fault); a real
# pack's BMS opens there. The margin lies beyond the charge a full pack takes with S0 working:
# up to its OCV at s0_on_v, below that at SOC_OVERCHARGE by config (SOC 1.004 for the shipped
# 54.65 V), and while S0 holds the bus at s0_off_v, up to its OCV there (SOC 1.0016)
SOC_OVERCHARGE = P.SOC_OVERCHARGE

# Hall code -> 60-degree sector (sector k spans theta_e in [30 + 60k, 90 + 60k) deg)
HALL_TO_SECTOR = np.array([-1, 0, 2, 1, 4, 5, 3, -1], dtype=np.int64)
SECTOR_TO_HALL = np.array([1, 3, 2, 6, 4, 5], dtype=np.int64)
# phase at +E (p) and at -E (n) in each sector (trapezoid flat tops)
SECTOR_P = np.array([0, 0, 1, 1, 2, 2], dtype=np.int64)
SECTOR_N = np.array([1, 2, 2, 0, 0, 1], dtype=np.int64)

TWO_PI = 2.0 * math.pi
THIRD = 1.0 / 3.0          # v_n of 3 legs: sum * THIRD (a multiply, not a division, on the current path)
SIXTH = math.pi / 3.0
INV_SIXTH = 3.0 / math.pi
TWELFTH = math.pi / 6.0
THIRD_TURN = 1 * (TWO_PI / 3.0)           # x * (2 pi / 3) of phase x = 1, 2, bit for bit
TWO_THIRDS_TURN = 2 * (TWO_PI / 3.0)
MAX_SUBSTEPS = 12
# scratch vector layout (per-period values, kept out of the heap)
W_ACC = 0       # 5 accumulators of the plant step
W_F = 5         # back-EMF shape f_x
W_E = 8         # back-EMF e_x [V]
W_L = 11        # L_x [H]
W_R = 14        # R + dL_x/dt [ohm]
W_RP = 17       # R [ohm]
W_DL = 20       # dL_x/dtheta_m [H/rad]
W_I1 = 23       # step result
W_ACC2 = 26     # 5 accumulators of a trial step
W_TRIAL = 31    # trial currents
W_SYM = 34      # 1: all phases have the same L and R (fast path)
WS_SIZE = 36


@njit(**JIT)
def trapezoid(theta):
    """Unit 120-degree flat-top back-EMF shape of phase a: +1 on [30, 150] deg, -1 on [210, 330]."""
    ph = theta % TWO_PI
    if ph < TWELFTH:
        return ph / TWELFTH
    if ph < 5.0 * TWELFTH:
        return 1.0
    if ph < 7.0 * TWELFTH:
        return 1.0 - (ph - 5.0 * TWELFTH) / TWELFTH
    if ph < 11.0 * TWELFTH:
        return -1.0
    return -1.0 + (ph - 11.0 * TWELFTH) / TWELFTH


@njit(**JIT)
def interp_table(x, xs, ys, n):
    if x <= xs[0]:
        return ys[0]
    for k in range(1, n):
        if x < xs[k]:
            return ys[k - 1] + (ys[k] - ys[k - 1]) * (x - xs[k - 1]) / (xs[k] - xs[k - 1])
    return ys[n - 1]


def _trap_table():
    """EMF_TAB[m] = (a_a, b_a, a_b, b_b, a_c, b_c): on the m-th twelfth of a turn
    (u = theta_e / 30 deg in [m, m + 1)) the trapezoid of phase x is a_x + b_x u, b_x in
    {0, +1, -1}: 1 on [30, 150] deg, -1 on [210, 330], ramps in between (paper 000, Fig. 4)."""
    def piece(m):           # phase a on twelfth m (0..11): (a, b)
        if m == 0:
            return 0.0, 1.0
        if m <= 4:
            return 1.0, 0.0
        if m <= 6:
            return 6.0, -1.0
        if m <= 10:
            return -1.0, 0.0
        return -12.0, 1.0
    tab = np.zeros((12, 6))
    for m in range(12):
        for x in range(3):
            mm = m - 4 * x            # phase x lags a by 120 deg = 4 twelfths: u_x = u - 4x
            a, b = piece(mm % 12)
            # a_x + b_x u with u_x = u - 4x + 12 (if wrapped): a + b (u - 4x + 12 w)
            tab[m, 2 * x] = a + b * (-4.0 * x + (12.0 if mm < 0 else 0.0))
            tab[m, 2 * x + 1] = b
    return tab


EMF_TAB = _trap_table()
INV_TWELFTH = 6.0 / math.pi      # twelfths of a turn per radian


@njit(**JIT_HOT)
def _wrap_twelfths(u, theta_e):
    """u = theta_e * 12 / (2 pi) outside [0, 12): one turn back or on, else the remainder
    (more than one turn off), else 0 (NaN)."""
    if u >= 12.0:
        u -= 12.0
    elif u < 0.0:
        u += 12.0
    if not (0.0 <= u < 12.0):       # more than one turn off, or NaN
        u = (theta_e % TWO_PI) * INV_TWELFTH
        if not (0.0 <= u < 12.0):
            u = 0.0
    return u


@njit(**JIT_INLINE)
def trap3(theta_e):
    """The three phases' unit trapezoids (f_a, f_b, f_c) at theta_e (f_b, f_c lag by 120,
    240 deg), tabulated per twelfth of a turn: exactly one phase is on a ramp there, the
    other two at +-1 (exact). Equals trapezoid(theta_e - x 2 pi / 3) up to round-off on
    the ramp (u - k instead of (theta - k 30 deg) / 30 deg)."""
    u = theta_e * INV_TWELFTH
    if not (0.0 <= u < 12.0):        # one test on the common path; int(u) <= 11 below
        u = _wrap_twelfths(u, theta_e)
    m = int(u)
    return (EMF_TAB[m, 0] + EMF_TAB[m, 1] * u, EMF_TAB[m, 2] + EMF_TAB[m, 3] * u,
            EMF_TAB[m, 4] + EMF_TAB[m, 5] * u)


@njit(**JIT_INLINE)
def emf_f3(theta_e, omega, p):
    """Back-EMF shapes (f_a, f_b, f_c) at angle theta_e (non-ideal blend if enabled)."""
    fa, fb, fc = trap3(theta_e)
    if p[P.P_EMF_NONIDEAL] != 0.0:
        th_b = theta_e - THIRD_TURN
        th_c = theta_e - TWO_THIRDS_TURN
        n = int(p[P.P_NTAB])
        w = interp_table(abs(omega), p[P.P_TAB_X:P.P_TAB_X + 8], p[P.P_TAB_Y:P.P_TAB_Y + 8], n)
        a = (1.0 - w) * p[P.P_SINE_AMP]
        fa = w * fa + a * math.sin(theta_e)
        fb = w * fb + a * math.sin(th_b)
        fc = w * fc + a * math.sin(th_c)
    return fa, fb, fc


@njit(**JIT)
def emf_shape(theta_e, omega, p, f, off):
    """f[off + x] for the 3 phases at angle theta_e (non-ideal blend if enabled)."""
    fa, fb, fc = emf_f3(theta_e, omega, p)
    f[off] = fa
    f[off + 1] = fb
    f[off + 2] = fc


@njit(**JIT)
def sector_of(theta_e):
    return int(((theta_e - TWELFTH) % TWO_PI) // SIXTH) % 6


@njit(**JIT)
def hall_of(theta_e):
    return SECTOR_TO_HALL[sector_of(theta_e)]


@njit(**JIT_INLINE)
def blank_interlock(gates):
    """Hardware interlock (GAL of paper 000, Fig. 10): a leg with both switches on is blanked.

    Returns (applied gates, number of blanked legs)."""
    g = int(gates) & 63
    both = g & (g >> 1) & 0b010101          # bit 2x: leg x has both switches on
    g &= ~(both | (both << 1))
    return g, (both & 1) + ((both >> 2) & 1) + ((both >> 4) & 1)


@njit(**JIT_HOT)
def gate_split_check(ga, gb, sp, gate_limit):  # pragma: no cover - compiled
    """A DriveCommand's arrays in one pass (bike_plant.msgconv.drive_command_problem, every
    batch): 0 valid; 1 / 2 a gates_a / gates_b value >= gate_limit; 3 a non-finite split; 4 a
    split outside [0, 1] (3 wins over 4, as the messages order them)."""
    for i in range(ga.shape[0]):
        if ga[i] >= gate_limit:
            return 1
    for i in range(gb.shape[0]):
        if gb[i] >= gate_limit:
            return 2
    out = 0
    for i in range(sp.shape[0]):
        x = sp[i]
        if not np.isfinite(x):
            return 3
        if x < 0.0 or x > 1.0:
            out = 4
    return out


@njit(**JIT)
def _solve(cur, co, wi, vdc, ws, t):
    """Crank-Nicolson step of the conducting legs (wi[x] > 0) from cur[co:co+3] into
    ws[W_I1:W_I1+3]; open legs get 0. Returns v_n."""
    if ws[W_SYM] != 0.0:
        # symmetric machine (equal L, R in all phases): one g, v_n = mean of w
        r = ws[W_R]
        g = t / (ws[W_L] + 0.5 * r * t)
        sw = 0.0
        nc = 0
        for x in range(3):
            if wi[x] > 0:
                v = vdc if wi[x] == 2 else 0.0
                sw += v - ws[W_E + x] - r * cur[co + x]
                nc += 1
        vn = sw / nc
        for x in range(3):
            if wi[x] > 0:
                v = vdc if wi[x] == 2 else 0.0
                ws[W_I1 + x] = cur[co + x] + g * (v - ws[W_E + x] - r * cur[co + x] - vn)
            else:
                ws[W_I1 + x] = 0.0
        return vn
    sg = 0.0
    sgw = 0.0
    for x in range(3):
        if wi[x] > 0:
            r = ws[W_R + x]
            g = t / (ws[W_L + x] + 0.5 * r * t)
            v = vdc if wi[x] == 2 else 0.0
            sg += g
            sgw += g * (v - ws[W_E + x] - r * cur[co + x])
    vn = sgw / sg
    for x in range(3):
        if wi[x] > 0:
            r = ws[W_R + x]
            g = t / (ws[W_L + x] + 0.5 * r * t)
            v = vdc if wi[x] == 2 else 0.0
            ws[W_I1 + x] = cur[co + x] + g * (v - ws[W_E + x] - r * cur[co + x] - vn)
        else:
            ws[W_I1 + x] = 0.0
    return vn


@njit(**JIT)
def _topology(cur, co, gates, vdc, ws, wi, t):
    """Leg states wi[0:3] (0 open, 1 at 0 V, 2 at v_dc) for pattern `gates` and the
    currents; wi[3:6] = 1 for diode-only legs. Returns True if the conducting legs were
    solved into ws[W_I1:] (False: nothing conducts)."""
    for x in range(3):
        up = (gates >> (2 * x)) & 1
        lo = (gates >> (2 * x + 1)) & 1
        wi[3 + x] = 0
        if up:
            wi[x] = 2
        elif lo:
            wi[x] = 1
        else:
            wi[3 + x] = 1
            ix = cur[co + x]
            if ix > 0.0:
                wi[x] = 1      # lower diode carries current out of the leg into the phase
            elif ix < 0.0:
                wi[x] = 2      # upper diode returns it to the DC bus
            else:
                wi[x] = 0      # discontinuous: leg open
    vn = 0.0
    for _ in range(4):
        ncl = 0
        for x in range(3):
            if wi[x] > 0:
                ncl += 1
        if ncl == 0:
            # all floating: two diodes conduct only if the line-to-line EMF exceeds v_dc
            xmax = 0
            xmin = 0
            for x in range(1, 3):
                if ws[W_E + x] > ws[W_E + xmax]:
                    xmax = x
                if ws[W_E + x] < ws[W_E + xmin]:
                    xmin = x
            if ws[W_E + xmax] - ws[W_E + xmin] > vdc:
                wi[xmax] = 2
                wi[xmin] = 1
                continue
            return False
        if ncl == 1:
            for x in range(3):
                if wi[x] > 0:
                    vn = (vdc if wi[x] == 2 else 0.0) - ws[W_E + x]
        elif ncl == 3 and wi[3] + wi[4] + wi[5] == 0:
            _solve(cur, co, wi, vdc, ws, t)         # all legs switched: nothing floats
            return True
        else:
            vn = _solve(cur, co, wi, vdc, ws, t)
        changed = False
        for x in range(3):
            if wi[x] == 0:
                vt = vn + ws[W_E + x]           # floating terminal (i = 0)
                if vt > vdc:
                    wi[x] = 2
                    changed = True
                elif vt < 0.0:
                    wi[x] = 1
                    changed = True
        if not changed:
            if ncl == 1:
                return False
            # a newly clamped diode leg that would carry current against its diode stays open
            bad = False
            for x in range(3):
                if wi[3 + x] != 0 and cur[co + x] == 0.0 and wi[x] > 0:
                    i1 = ws[W_I1 + x]
                    if (wi[x] == 1 and i1 < 0.0) or (wi[x] == 2 and i1 > 0.0):
                        wi[x] = 0
                        bad = True
            if not bad:
                return True
    ncl = 0
    for x in range(3):
        if wi[x] > 0:
            ncl += 1
    if ncl >= 2:
        _solve(cur, co, wi, vdc, ws, t)
        return True
    return False


@njit(**JIT_INLINE)
def _open_leg(ua, ub, uz0, ez, vdc, r, iz, pos):
    """sym_legs with one leg z open (zero current): u_a, u_b of the conducting legs, z at
    phase position pos (0, 1, 2; sums run in phase order, as _solve's). Returns (w_z, v_n,
    u_z): the 2-leg solution (w_z = 0) if z's terminal v_n + e_z stays inside [0, v_dc], or
    if it clamps to a rail but the clamping diode would then carry current against its
    conducting direction (_topology re-opens the leg); else the 3-leg solution. The diode
    test uses the sign of d_z, which is that of j_z = 0 + g d_z (g > 0) barring underflow."""
    vn2 = (ua + ub) * 0.5                   # == / 2
    vt = vn2 + ez
    hi = vt > vdc
    if not (hi or vt < 0.0):
        return 0, vn2, uz0
    uz = (vdc if hi else 0.0) - ez - r * iz
    if pos == 0:
        vn3 = (uz + ua + ub) * THIRD
    elif pos == 1:
        vn3 = (ua + uz + ub) * THIRD
    else:
        vn3 = (ua + ub + uz) * THIRD
    dz = uz - vn3
    if hi:
        if not (dz > 0.0):       # upper diode: current <= 0
            return 2, vn3, uz
    elif not (dz < 0.0):         # lower diode: current >= 0
        return 1, vn3, uz
    return 0, vn2, uz0


@njit(**JIT_INLINE)
def _leg_guess(code, i):
    """First guess of a leg's state (0 open, 1 at 0 V, 2 at v_dc) from its switch code
    (gates >> 2x) & 3 (0 none, 1 upper, 2 lower, 3 both: treated as upper, as the bit logic
    did) and its current i: with no switch on, the lower diode carries a positive current
    and the upper diode a negative one. Branches, not a table: the pattern and the current
    signs change rarely from one call to the next, so they predict well (fewer
    instructions per period than an indexed look-up)."""
    if code & 1:
        return 2
    if code:
        return 1
    if i > 0.0:
        return 1
    if i < 0.0:
        return 2
    return 0


@njit(**JIT_INLINE)
def sym_legs(i0, i1, i2, gates, vdc, e0, e1, e2, r):
    """_topology + _solve for the symmetric machine (equal L, R in all phases) with >= 2
    conducting legs, as scalars. Returns (ok, w0, w1, w2, d0, d1, d2): leg states as in
    _topology (0 open, 1 at 0 V, 2 at v_dc) and the Crank-Nicolson direction
    d_x = v_x - e_x - R i_x - v_n, so a step of t seconds is i_x + g(t) d_x with
    g(t) = t / (L + R t / 2) (cn_gain); open legs d = 0. ok False (fewer than 2 legs
    conduct): the general iteration is needed.

    _topology's iteration is resolved in closed form (_open_leg), with _solve's sums (v_n
    as sum * 1/3 rather than sum / 3: round-off level), and none of it depends on t: one call serves every
    step length from these currents (the controller's trial and the plant's first segment)."""
    # first guess (as _topology's first pass): a leg is at v_dc through its upper switch or,
    # with no switch on, its upper diode (current < 0); at 0 V through the lower switch or
    # diode (current > 0); open with no switch on and zero current
    w0 = _leg_guess(gates & 3, i0)
    w1 = _leg_guess((gates >> 2) & 3, i1)
    w2 = _leg_guess((gates >> 4) & 3, i2)
    c0 = w0 != 0
    c1 = w1 != 0
    c2 = w2 != 0
    v0 = (vdc if w0 == 2 else 0.0) - e0
    v1 = (vdc if w1 == 2 else 0.0) - e1
    v2 = (vdc if w2 == 2 else 0.0) - e2
    u0 = v0 - r * i0
    u1 = v1 - r * i1
    u2 = v2 - r * i2
    if c0 & c1 & c2:
        # v_n = mean(u) = mean(v_x - e_x) - R mean(i), and the phase currents sum to zero
        # (star point): the R mean(i) term (round-off) is left out, which keeps v_n off the
        # currents' dependency chain; sum(i) then contracts by (1 - g R) per step
        vn = (v0 + v1 + v2) * THIRD
    elif c1 & c2:
        w0, vn, u0 = _open_leg(u1, u2, u0, e0, vdc, r, i0, 0)
        if w0 == 0:
            # two legs in series: d = +-(u_1 - u_2) / 2 (= u - v_n with v_n their mean), two
            # operations after u on the currents' chain, and the two currents stay opposite
            h = (u1 - u2) * 0.5
            return True, w0, w1, w2, 0.0, h, -h
    elif c0 & c2:
        w1, vn, u1 = _open_leg(u0, u2, u1, e1, vdc, r, i1, 1)
        if w1 == 0:
            h = (u0 - u2) * 0.5
            return True, w0, w1, w2, h, 0.0, -h
    elif c0 & c1:
        w2, vn, u2 = _open_leg(u0, u1, u2, e2, vdc, r, i2, 2)
        if w2 == 0:
            h = (u0 - u1) * 0.5
            return True, w0, w1, w2, h, -h, 0.0
    else:
        return False, w0, w1, w2, 0.0, 0.0, 0.0
    return (True, w0, w1, w2, u0 - vn if w0 > 0 else 0.0, u1 - vn if w1 > 0 else 0.0,
            u2 - vn if w2 > 0 else 0.0)


# legs argument of sym_segment: (gates, ok, w0, w1, w2, d0, d1, d2, nx), nx True when a
# whole-period step from these currents was seen to cross no diode leg's zero (then no
# shorter step along the same line does: i + g d keeps its sign on [0, g], rounding being
# monotone); NO_LEGS: none computed yet
NO_LEGS = (-1, False, 0, 0, 0, 0.0, 0.0, 0.0, False)


@njit(**JIT_INLINE)
def cn_gain(t, L, r):
    """g(t) = t / (L + R t / 2) of the Crank-Nicolson step (the expression of _solve)."""
    return t / (L + 0.5 * r * t)


@njit(**JIT)
def _fast_sym(cur, co, gates, vdc, ws, wi, t):
    """sym_legs + the step of t seconds into ws[W_I1:] / wi, the array form electrical_segment
    uses. Returns False (nothing written) when the general iteration is needed."""
    ok, w0, w1, w2, d0, d1, d2 = sym_legs(cur[co], cur[co + 1], cur[co + 2], gates, vdc, ws[W_E], ws[W_E + 1],
                                          ws[W_E + 2], ws[W_R])
    if not ok:
        return False
    g = cn_gain(t, ws[W_L], ws[W_R])
    ws[W_I1] = cur[co] + g * d0 if w0 > 0 else 0.0
    ws[W_I1 + 1] = cur[co + 1] + g * d1 if w1 > 0 else 0.0
    ws[W_I1 + 2] = cur[co + 2] + g * d2 if w2 > 0 else 0.0
    wi[0] = w0
    wi[1] = w1
    wi[2] = w2
    wi[3] = 0 if (gates & 3) else 1
    wi[4] = 0 if (gates & 12) else 1
    wi[5] = 0 if (gates & 48) else 1
    return True


@njit(**JIT)
def electrical_segment(cur, co, gates, t_seg, vdc, ws, wi, kph, acc):
    """Advance the currents cur[co:co+3] (in place) through t_seg seconds of pattern `gates`.

    ws holds the period's e, L, R (period_setup); ws[acc:acc+5] accumulates: [0] energy
    bridge -> machine terminals, [1] charge bridge -> DC node, [2] copper loss,
    [3] electromechanical conversion, [4] torque integral (T dt); acc < 0: no accumulation.
    """
    remaining = t_seg
    for it in range(MAX_SUBSTEPS):
        if remaining <= 0.0:
            break
        t = remaining
        if not (ws[W_SYM] != 0.0 and _fast_sym(cur, co, gates, vdc, ws, wi, t)) and \
                not _topology(cur, co, gates, vdc, ws, wi, t):
            for x in range(3):
                cur[co + x] = 0.0
            break
        # earliest zero crossing of a diode-only leg
        xz = -1
        best = 2.0
        for x in range(3):
            ix = cur[co + x]
            if wi[3 + x] != 0 and wi[x] > 0 and ix != 0.0 and ix * ws[W_I1 + x] <= 0.0:
                fr = ix / (ix - ws[W_I1 + x])
                if fr < best:
                    best = fr
                    xz = x
        last = it == MAX_SUBSTEPS - 1     # out of sub-steps: finish the segment in one step
        if xz >= 0 and not last:
            # regula falsi on the step formula for the crossing time
            ta = 0.0
            fa = cur[co + xz]
            tb = t
            fb = ws[W_I1 + xz]
            tc = t
            for _k in range(4):
                if fa == fb:
                    break
                tc = ta + (tb - ta) * fa / (fa - fb)
                _solve(cur, co, wi, vdc, ws, tc)
                fc = ws[W_I1 + xz]
                if fc * fa > 0.0:
                    ta = tc
                    fa = fc
                else:
                    tb = tc
                    fb = fc
                if abs(fc) < 1e-9:
                    break
            t = tc
            _solve(cur, co, wi, vdc, ws, t)
        for x in range(3):
            if wi[x] > 0 and acc >= 0:
                ia = 0.5 * (cur[co + x] + ws[W_I1 + x])
                dldt = ws[W_R + x] - ws[W_RP + x]
                if wi[x] == 2:
                    ws[acc] += vdc * ia * t
                    ws[acc + 1] -= ia * t
                ws[acc + 2] += ws[W_RP + x] * ia * ia * t
                ws[acc + 3] += (ws[W_E + x] * ia + 0.5 * dldt * ia * ia) * t
                ws[acc + 4] += (kph * ws[W_F + x] * ia + 0.5 * ws[W_DL + x] * ia * ia) * t
        for x in range(3):
            cur[co + x] = ws[W_I1 + x]
        if xz >= 0:
            # exact zero (at the crossing, or a diode that would reverse on the last
            # sub-step); keep sum(i) = 0 by moving the residue to the largest other current
            r = cur[co + xz]
            cur[co + xz] = 0.0
            xm = -1
            for x in range(3):
                if x != xz and wi[x] > 0 and (xm < 0 or abs(cur[co + x]) > abs(cur[co + xm])):
                    xm = x
            if xm >= 0:
                cur[co + xm] += r
        remaining -= t


@njit(**JIT)
def phase_inductance(theta_e, omega, p, ws):
    """ws[W_L+x] = L_x(theta_e); ws[W_R+x] = R + dL_x/dt (i dL/dt acts like a signed
    resistance); ws[W_RP+x] = R; ws[W_DL+x] = dL_x/dtheta_m."""
    L0 = p[P.P_L0]
    eps = p[P.P_EPS]
    r = p[P.P_R]
    pp = p[P.P_POLE_PAIRS]
    for x in range(3):
        if eps != 0.0:
            arg = 2.0 * (theta_e - x * (TWO_PI / 3.0))
            ws[W_L + x] = L0 * (1.0 + eps * math.cos(arg))
            dl_dthe = -2.0 * L0 * eps * math.sin(arg)
            ws[W_DL + x] = dl_dthe * pp
            ws[W_R + x] = r + dl_dthe * pp * omega
        else:
            ws[W_L + x] = L0
            ws[W_DL + x] = 0.0
            ws[W_R + x] = r
        ws[W_RP + x] = r
    ws[W_SYM] = 1.0 if eps == 0.0 else 0.0


@njit(**JIT)
def stored_energy(state, p):
    ws = np.zeros(WS_SIZE)
    phase_inductance(state[S_THETA_E], 0.0, p, ws)
    w = 0.5 * p[P.P_J] * state[S_OMEGA] ** 2
    for x in range(3):
        w += 0.5 * ws[W_L + x] * state[x] ** 2
    return w


@njit(**JIT_INLINE)
def battery_voc(soc, p):
    return p[P.P_V_EMPTY] + (p[P.P_V_FULL] - p[P.P_V_EMPTY]) * soc


@njit(**JIT)
def init_state(state, p, speed_rad_s, soc0):
    state[:] = 0.0
    state[S_OMEGA] = speed_rad_s
    state[S_SPEED_TARGET] = speed_rad_s
    state[S_SOC] = soc0
    voc = battery_voc(soc0, p)
    state[S_VDC] = voc
    state[S_VFILT] = voc
    state[S_HALL] = hall_of(0.0)
    state[S_E_STORED0] = stored_energy(state, p)


@njit(**JIT)
def period_setup(state, p, ws):
    """Back-EMF and inductances of the coming period, evaluated at its mid angle and held."""
    omega = state[S_OMEGA]
    th_mid = state[S_THETA_E] + 0.5 * p[P.P_POLE_PAIRS] * omega * p[P.P_DT]
    emf_shape(th_mid, omega, p, ws, W_F)
    kph = p[P.P_KPH]
    for x in range(3):
        ws[W_E + x] = kph * omega * ws[W_F + x]
    phase_inductance(th_mid, omega, p, ws)


@njit(**JIT)
def trial_currents(state, p, gates, ws, wi):
    """Currents at the end of the coming period if `gates` were held for all of it, into
    ws[W_TRIAL:W_TRIAL+3]; returns the feedback (|ia| + |ib| + |ic|) / 2. No state change.

    Uses the period_setup values already in ws (call period_setup first). This is the
    'model derivative' the hysteresis controller uses to place its switching edge."""
    g, _nb = blank_interlock(gates)
    for x in range(3):
        ws[W_TRIAL + x] = state[x]
    electrical_segment(ws, W_TRIAL, g, p[P.P_DT], state[S_VDC], ws, wi, p[P.P_KPH], -1)   # no ledger
    return 0.5 * (abs(ws[W_TRIAL]) + abs(ws[W_TRIAL + 1]) + abs(ws[W_TRIAL + 2]))


# ---- per-parameter-set constants -------------------------------------------------------
# plant_constants(p) is evaluated once per kernel call, so the period loop multiplies by
# reciprocals instead of dividing by parameters (round-off level differences only).
KC_DT = 0
KC_L0 = 1
KC_R = 2
KC_KPH = 3
KC_PP = 4              # pole pairs
KC_INV_DT = 5          # 1 / dt
KC_INV_RB = 6          # 1 / R_batt
KC_INV_RR = 7          # 1 / R_brake
KC_INV_DEN_S0_OFF = 8  # 1 / (1 / R_batt): DC node with S0 off
KC_S0_ON_RATIO = 9     # R_brake / (R_brake + R_batt): DC node with S0 fully on over that with it off
KC_DT_PER_CAP = 10     # dt / capacity [s / (A s)]: state-of-charge step per ampere
KC_SYM = 11            # 1: no position-dependent L, the scalar fast path (sym_segment) applies
KC_G_DT = 12           # cn_gain(dt, L0, R): the Crank-Nicolson gain of a whole period (no division per trial)
KC_DT_PER_J = 13       # dt / J [s / (kg m^2)]: shaft speed step per N m
KC_INV_GEAR = 14       # 1 / gear ratio (rider: cadence = w / gear, crank torque / gear at the motor)
KC_INV_CADMAX = 15     # 1 / rider maximum cadence [s / rad]
KC_HALF_R_DT = 16      # R dt / 2: a split segment's gain from its fraction s, s dt / (L + (R dt / 2) s)


@njit(**JIT)
def plant_constants(p):
    """Per-parameter-set constants (KC_* layout), a tuple the period loop keeps in registers."""
    dt = p[P.P_DT]
    rb = p[P.P_R_BATT]
    rr = p[P.P_R_BRAKE]
    return (dt, p[P.P_L0], p[P.P_R], p[P.P_KPH], p[P.P_POLE_PAIRS], 1.0 / dt, 1.0 / rb, 1.0 / rr,
            1.0 / (1.0 / rb), rr / (rr + rb), dt / p[P.P_CAP_AS],
            1.0 if p[P.P_EPS] == 0.0 else 0.0, cn_gain(dt, p[P.P_L0], p[P.P_R]), dt / p[P.P_J],
            1.0 / p[P.P_GEAR], 1.0 / p[P.P_RIDER_CADMAX], 0.5 * p[P.P_R] * dt)


@njit(**JIT_INLINE)
def emf_sym(state, p):
    """period_setup's back-EMF as scalars (f_a, f_b, f_c, e_a, e_b, e_c): shape and
    e_x = kph w f_x at the mid-period angle, held for the period."""
    return emf_sym_i(state[S_THETA_E], state[S_OMEGA], p)


@njit(**JIT_INLINE)
def emf_sym_i(theta_e, omega, p):
    """emf_sym at the state's angle theta_e and speed omega."""
    th_mid = theta_e + 0.5 * p[P.P_POLE_PAIRS] * omega * p[P.P_DT]
    f0, f1, f2 = emf_f3(th_mid, omega, p)
    kw = p[P.P_KPH] * omega
    return f0, f1, f2, kw * f0, kw * f1, kw * f2


@njit(**JIT)
def _ws_setup_sym(ws, emf, c):
    """What period_setup leaves in ws for the symmetric machine (for the general path)."""
    for x in range(3):
        ws[W_F + x] = emf[x]
        ws[W_E + x] = emf[3 + x]
        ws[W_L + x] = c[KC_L0]
        ws[W_R + x] = c[KC_R]
        ws[W_RP + x] = c[KC_R]
        ws[W_DL + x] = 0.0
    ws[W_SYM] = 1.0


@njit(**JIT_INLINE)
def legs_of(i0, i1, i2, gates, vdc, emf, c):
    """sym_legs tagged with the (interlock-applied) pattern: (gates, ok, w0, w1, w2, d0, d1, d2,
    nx) (nx False: see NO_LEGS). The controller's trial computes this for the pattern the
    plant starts the period with; sym_segment reuses it when the pattern matches (same
    currents, v_dc and EMF)."""
    ok, w0, w1, w2, d0, d1, d2 = sym_legs(i0, i1, i2, gates, vdc, emf[3], emf[4], emf[5], c[KC_R])
    return (gates, ok, w0, w1, w2, d0, d1, d2, False)


@njit(**JIT_INLINE)
def legs_moved(legs, i0, i1, i2, j0, j1, j2, r):
    """legs_of(i0, i1, i2, ...) carried to the currents j0, j1, j2 of the same pattern, v_dc
    and EMF, without a second topology solution: sym_legs' leg states depend on the currents
    only through the signs of the diode-only (no switch on) legs, and its directions are
    d_x = v_x - e_x - R i_x - v_n with v_n free of the currents (3 legs: the mean of
    v - e; 2 legs: the two conducting currents sum to zero), so d_x(j) = d_x(i) - R (j_x - i_x)
    (round-off level apart). When a diode-only leg's current changed sign class (zero,
    positive, negative) the states may differ: returns NO_LEGS' tag (-1), and sym_segment
    solves afresh. Used for a period's second segment: the controller's trial of that
    pattern from the period's start currents is the legs."""
    gates = legs[0]
    if legs[1]:
        if (gates & 3) == 0 and ((i0 > 0.0) != (j0 > 0.0) or (i0 < 0.0) != (j0 < 0.0)):
            gates = -1
        if (gates & 12) == 0 and ((i1 > 0.0) != (j1 > 0.0) or (i1 < 0.0) != (j1 < 0.0)):
            gates = -1
        if (gates & 48) == 0 and ((i2 > 0.0) != (j2 > 0.0) or (i2 < 0.0) != (j2 < 0.0)):
            gates = -1
    return (gates, legs[1], legs[2], legs[3], legs[4], legs[5] - r * (j0 - i0) if legs[2] > 0 else 0.0,
            legs[6] - r * (j1 - i1) if legs[3] > 0 else 0.0, legs[7] - r * (j2 - i2) if legs[4] > 0 else 0.0,
            False)


@njit(**JIT_INLINE)
def _sym_ledger(i0, i1, i2, j0, j1, j2, w0, w1, w2, t, emf, r, kph, a1, a2, a3, a4):
    """electrical_segment's sums for one step of t seconds (i -> j) of the symmetric machine,
    where dL/dt = dL/dtheta = 0 (exact zeros there), with the mean currents factored:
    ia_x = (i_x + j_x) / 2, so charge = t/2 sum s_x (legs at v_dc), copper = R t/4 sum s_x^2,
    conversion = t/2 sum e_x s_x, T dt = kph t/2 sum f_x s_x with s_x = i_x + j_x (the same
    sums as electrical_segment, regrouped: round-off level). An open leg has i = j = 0 and
    adds exact zeros, so there is no branch on the leg state. a3 (conversion) is passed
    through: with e_x = kph w f_x it is w times the torque integral, which
    step_period_sym forms once per period."""
    f0, f1, f2, e0, e1, e2 = emf
    s0 = i0 + j0
    s1 = i1 + j1
    s2 = i2 + j2
    ht = 0.5 * t
    a1 = a1 - ht * ((s0 if w0 == 2 else 0.0) + (s1 if w1 == 2 else 0.0) + (s2 if w2 == 2 else 0.0))
    a2 = a2 + (0.5 * r * ht) * (s0 * s0 + s1 * s1 + s2 * s2)
    a4 = a4 + kph * (ht * (f0 * s0 + f1 * s1 + f2 * s2))
    return a1, a2, a3, a4


@njit(**JIT_INLINE)
def _crossing(gates, i0, i1, i2, j0, j1, j2):
    """Diode-only legs (no switch on) whose current reaches zero within the step i -> j."""
    # short-circuit in the order of rarity: a sign change is the exception
    return ((i0 * j0 <= 0.0 and i0 != 0.0 and (gates & 3) == 0),
            (i1 * j1 <= 0.0 and i1 != 0.0 and (gates & 12) == 0),
            (i2 * j2 <= 0.0 and i2 != 0.0 and (gates & 48) == 0))


@njit(**JIT_INLINE)
def sym_segment(cur, co, i0, i1, i2, gates, t, vdc, emf, legs, c, ledger, a1, a2, a3, a4, ws, wi, g_t=-1.0):
    """electrical_segment for the symmetric machine with the currents in registers.

    One Crank-Nicolson step of the whole segment; or, when a diode-only leg's current
    reaches zero inside it, a step to the crossing, the exact zero (residue to the largest
    other current, as electrical_segment) and a step of the rest. With equal L and R the
    step is i + g(t) d with d independent of t (sym_legs), so the crossing of leg z is
    g* = -i_z / d_z exactly, at t* = g* L / (1 - R g* / 2) (g inverted); electrical_segment
    gets there by regula falsi to 1e-9 A. Anything else (fewer than 2 conducting legs, a
    second crossing, t <= 0) continues in electrical_segment on cur[co:co+3] with ws set up
    as period_setup would. legs: legs_of(i0, i1, i2, ...) if already known, else NO_LEGS.
    ledger: accumulate (a1 -= charge to the DC node, a2 += copper loss, a3 += conversion,
    a4 += T dt) as electrical_segment's ws[acc + 1:acc + 5]; False for the controller's
    trial. Returns (i0, i1, i2, a1, a2, a3, a4) at the end of the segment."""
    e0 = emf[3]
    e1 = emf[4]
    e2 = emf[5]
    r = c[KC_R]
    L0 = c[KC_L0]
    kph = c[KC_KPH]
    nx = False
    if legs[0] == gates:
        ok, w0, w1, w2, d0, d1, d2, nx = legs[1], legs[2], legs[3], legs[4], legs[5], legs[6], legs[7], legs[8]
    else:
        ok, w0, w1, w2, d0, d1, d2 = sym_legs(i0, i1, i2, gates, vdc, e0, e1, e2, r)
    rest = t
    if ok and t > 0.0:
        if g_t > 0.0:         # the caller's gain of this t (split_gains)
            g = g_t
        else:
            g = c[KC_G_DT] if t == c[KC_DT] else cn_gain(t, L0, r)     # the same value, no division
        # an open leg has i = d = 0: i + g d is its exact 0
        j0 = i0 + g * d0
        j1 = i1 + g * d1
        j2 = i2 + g * d2
        if nx:            # t <= dt: the whole-period step crossed nothing, neither does this one
            x0 = x1 = x2 = False
        else:
            x0, x1, x2 = _crossing(gates, i0, i1, i2, j0, j1, j2)
        if not (x0 or x1 or x2):
            if ledger:
                a1, a2, a3, a4 = _sym_ledger(i0, i1, i2, j0, j1, j2, w0, w1, w2, t, emf, r, kph, a1, a2, a3, a4)
            return j0, j1, j2, a1, a2, a3, a4
        # the earliest crossing: smallest g* = -i / d (g grows with t)
        gz = 2.0 * g
        xz = -1
        if x0 and -i0 / d0 < gz:
            gz = -i0 / d0
            xz = 0
        if x1 and -i1 / d1 < gz:
            gz = -i1 / d1
            xz = 1
        if x2 and -i2 / d2 < gz:
            gz = -i2 / d2
            xz = 2
        tz = gz * L0 / (1.0 - 0.5 * r * gz)
        j0 = i0 + gz * d0
        j1 = i1 + gz * d1
        j2 = i2 + gz * d2
        if ledger:
            a1, a2, a3, a4 = _sym_ledger(i0, i1, i2, j0, j1, j2, w0, w1, w2, tz, emf, r, kph, a1, a2, a3, a4)
        # exact zero at the crossing; keep sum(i) = 0 by moving the residue to the largest
        # other conducting current
        res = j0 if xz == 0 else (j1 if xz == 1 else j2)
        j0 = 0.0 if xz == 0 else j0
        j1 = 0.0 if xz == 1 else j1
        j2 = 0.0 if xz == 2 else j2
        xm = -1
        am = 0.0
        if xz != 0 and w0 > 0:
            xm = 0
            am = abs(j0)
        if xz != 1 and w1 > 0 and (xm < 0 or abs(j1) > am):
            xm = 1
            am = abs(j1)
        if xz != 2 and w2 > 0 and (xm < 0 or abs(j2) > am):
            xm = 2
        j0 = j0 + res if xm == 0 else j0
        j1 = j1 + res if xm == 1 else j1
        j2 = j2 + res if xm == 2 else j2
        rest = t - tz
        if not (rest > 0.0):
            return j0, j1, j2, a1, a2, a3, a4
        # the rest of the segment from the new currents
        i0 = j0
        i1 = j1
        i2 = j2
        ok, w0, w1, w2, d0, d1, d2 = sym_legs(i0, i1, i2, gates, vdc, e0, e1, e2, r)
        if ok:
            g = cn_gain(rest, L0, r)
            j0 = i0 + g * d0
            j1 = i1 + g * d1
            j2 = i2 + g * d2
            x0, x1, x2 = _crossing(gates, i0, i1, i2, j0, j1, j2)
            if not (x0 or x1 or x2):
                if ledger:
                    a1, a2, a3, a4 = _sym_ledger(i0, i1, i2, j0, j1, j2, w0, w1, w2, rest, emf, r, kph,
                                                 a1, a2, a3, a4)
                return j0, j1, j2, a1, a2, a3, a4
    if not (rest > 0.0):
        return i0, i1, i2, a1, a2, a3, a4
    return _segment_general(cur, co, i0, i1, i2, gates, rest, vdc, emf, c, ledger, a1, a2, a3, a4, ws, wi)


@njit(**JIT_COLD)
def _segment_general(cur, co, i0, i1, i2, gates, t, vdc, emf, c, ledger, a1, a2, a3, a4, ws, wi):
    """electrical_segment (topology iteration, sub-steps) for what sym_segment does not do,
    on cur[co:co+3] with ws set up as period_setup would for the symmetric machine."""
    _jit.out_of_line()
    _ws_setup_sym(ws, emf, c)
    cur[co] = i0
    cur[co + 1] = i1
    cur[co + 2] = i2
    ws[W_ACC] = 0.0
    ws[W_ACC + 1] = a1
    ws[W_ACC + 2] = a2
    ws[W_ACC + 3] = a3
    ws[W_ACC + 4] = a4
    electrical_segment(cur, co, gates, t, vdc, ws, wi, c[KC_KPH], W_ACC if ledger else -1)
    return cur[co], cur[co + 1], cur[co + 2], ws[W_ACC + 1], ws[W_ACC + 2], ws[W_ACC + 3], ws[W_ACC + 4]


@njit(**JIT_INLINE)
def trial_sym(state, gates, emf, legs, c, ws, wi, hold_at_zero):
    """trial_currents for the symmetric machine, unhalved: |ia| + |ib| + |ic| at the end of the
    coming period if `gates` (interlock-safe) were held for all of it. No state change.
    legs: legs_of the same currents and pattern. Returns (feedback, legs), the legs marked
    nx when the step crossed no diode leg's zero (a plant segment of this pattern from
    these currents then skips its own crossing test).

    hold_at_zero: a diode leg whose current would cross zero is taken as held at zero, the
    others on their line, instead of the exact split of the step at the crossing. Exact in
    substance for the common case (two diode legs in series reach zero together and the
    bridge blocks): over 7458 crossing trials of generating runs at 300-5000 rpm it was
    within 1e-5 A of the exact split (currents summing to ~100 A; test_bldc_controller).
    The controller uses it for the other pattern's trial, which only guards the edge's
    earliest place, and saves the split's divisions and second bridge solution."""
    return trial_sym_i(state[S_IA], state[S_IB], state[S_IC], state[S_VDC], gates, emf, legs, c, ws, wi,
                       hold_at_zero)


@njit(**JIT_INLINE)
def trial_sym_i(i0, i1, i2, vdc, gates, emf, legs, c, ws, wi, hold_at_zero):
    """trial_sym from the currents i0, i1, i2 and v_dc of the state (fast_state)."""
    if legs[1] and legs[0] == gates:
        g = c[KC_G_DT]
        j0 = i0 + g * legs[5]
        j1 = i1 + g * legs[6]
        j2 = i2 + g * legs[7]
        x0, x1, x2 = _crossing(gates, i0, i1, i2, j0, j1, j2)
        if not (x0 or x1 or x2):
            return (abs(j0) + abs(j1) + abs(j2),
                    (legs[0], legs[1], legs[2], legs[3], legs[4], legs[5], legs[6], legs[7], True))
        if hold_at_zero:
            return (0.0 if x0 else abs(j0)) + (0.0 if x1 else abs(j1)) + (0.0 if x2 else abs(j2)), legs
    j0, j1, j2, _a1, _a2, _a3, _a4 = sym_segment(ws, W_TRIAL, i0, i1, i2, gates, c[KC_DT], vdc, emf,
                                                 legs, c, False, 0.0, 0.0, 0.0, 0.0, ws, wi)
    return abs(j0) + abs(j1) + abs(j2), legs


@njit(**JIT_COLD)
def _overcurrent_trip(state):
    """Count a tripped period and set FAULT_OVERCURRENT. Returns the gates of the period (0).

    Kept out of line: the rare path of the hot loop (the check itself costs ~1.5 ns per
    period of the fused loop's ~70 ns)."""
    _jit.out_of_line()
    state[S_OC_TRIPS] += 1.0
    state[S_FAULTS] = int(state[S_FAULTS]) | FAULT_OVERCURRENT
    return 0


@njit(**JIT_INLINE)
def _interlock_and_split(state, p, gates_a, gates_b, split, i0, i1, i2):
    """Interlock (blank shorted legs, count, fault), the overcurrent trip and the clamped
    split of one period.

    Cycle-by-cycle overcurrent protection (a real inverter's comparator on the phase
    currents; not in paper 000): if any |i_x| at the period start exceeds p[P.P_OC_TRIP],
    all six gates are off for the whole period (the diodes return the current to the DC
    link, so it decays), S_OC_TRIPS counts the period and FAULT_OVERCURRENT is set. The
    check runs once per period, so a current can pass the trip by at most one period of
    rise. The trip level sits above the controller's current_limit_a + hysteresis_a:
    closed-loop operation with fresh gate decisions never reaches it. i0, i1, i2: the state's
    phase currents."""
    ga = int(gates_a) & 63
    gb = int(gates_b) & 63
    if ((ga & (ga >> 1)) | (gb & (gb >> 1))) & 0b010101:      # some leg has both switches on (rare)
        ga, nba = blank_interlock(ga)
        gb, nbb = blank_interlock(gb)
        state[S_INTERLOCK] += nba + nbb
        state[S_FAULTS] = int(state[S_FAULTS]) | FAULT_INTERLOCK
    if max(abs(i0), abs(i1), abs(i2)) > p[P.P_OC_TRIP]:
        ga = _overcurrent_trip(state)
        gb = ga
    s = split
    if not (s >= 0.0):      # also catches NaN
        s = 0.0
    if s > 1.0:
        s = 1.0
    return int(ga), int(gb), s


@njit(**JIT_INLINE)
def split_gains(s, c):
    """Crank-Nicolson gains g(t) = t / (L + R t / 2) of a period split at fraction s (t = s dt,
    then (1 - s) dt), formed from s: the denominator L + (R dt / 2) s is one multiply-add
    after s instead of two operations (round-off level from cn_gain(s dt))."""
    dt = c[KC_DT]
    L0 = c[KC_L0]
    hr = c[KC_HALF_R_DT]
    sb = 1.0 - s
    return (s * dt) / (L0 + hr * s), (sb * dt) / (L0 + hr * sb)


@njit(**JIT_INLINE)
def step_period_sym(state, p, c, gates_a, gates_b, split, emf, legs_a, legs_b, edge_counts, edge_states, n_edges,
                    ws, wi):
    """step_period for the symmetric machine (c[KC_SYM] != 0): the currents stay in
    registers through both segments (sym_segment). emf: emf_sym(state, p); legs_a, legs_b:
    legs_of(state currents, interlock-applied gates_a / gates_b, ...) if the controller
    already computed them (its trials), else NO_LEGS. The second segment starts from the
    first one's currents with legs_b carried there (legs_moved). Returns n_edges."""
    n_edges, _fs = step_period_sym_i(state, p, c, fast_state(state), gates_a, gates_b, split, emf, legs_a, legs_b,
                                     edge_counts, edge_states, n_edges, ws, wi)
    return n_edges


@njit(**JIT_INLINE)
def fast_state(state):
    """(i_a, i_b, i_c, v_dc, omega, theta_e) of the state vector: what one period hands the
    next along its serial chains (currents, DC bus, shaft, angle). The fused loop keeps it in
    registers (step_period_sym_i returns the next one), so the next period does not wait on
    a store and reload of values just computed."""
    return (state[S_IA], state[S_IB], state[S_IC], state[S_VDC], state[S_OMEGA], state[S_THETA_E])


@njit(**JIT_INLINE)
def step_period_sym_i(state, p, c, fs, gates_a, gates_b, split, emf, legs_a, legs_b, edge_counts, edge_states,
                      n_edges, ws, wi):
    """step_period_sym from fs = fast_state(state). Returns (n_edges, fast_state(state)) after
    the period (the values it stored)."""
    i0, i1, i2, vdc, omega, theta_e = fs
    ga, gb, s = _interlock_and_split(state, p, gates_a, gates_b, split, i0, i1, i2)
    dt = c[KC_DT]
    a1 = 0.0
    a2 = 0.0
    a3 = 0.0
    a4 = 0.0
    g_a = -1.0
    g_b = -1.0
    if s > 0.0:
        if s < 1.0:
            if legs_b[0] != gb:
                legs_b = legs_of(i0, i1, i2, gb, vdc, emf, c)
            g_a, g_b = split_gains(s, c)
            j0, j1, j2, a1, a2, a3, a4 = sym_segment(state, 0, i0, i1, i2, ga, s * dt, vdc, emf, legs_a, c, True,
                                                     a1, a2, a3, a4, ws, wi, g_a)
            legs_b = legs_moved(legs_b, i0, i1, i2, j0, j1, j2, c[KC_R])
            i0 = j0
            i1 = j1
            i2 = j2
        else:
            i0, i1, i2, a1, a2, a3, a4 = sym_segment(state, 0, i0, i1, i2, ga, dt, vdc, emf, legs_a, c, True,
                                                     a1, a2, a3, a4, ws, wi)
    if s < 1.0:
        i0, i1, i2, a1, a2, a3, a4 = sym_segment(state, 0, i0, i1, i2, gb, (1.0 - s) * dt, vdc, emf, legs_b, c,
                                                 True, a1, a2, a3, a4, ws, wi, g_b)
    state[S_IA] = i0
    state[S_IB] = i1
    state[S_IC] = i2
    # conversion sum(e_x i_x) dt = w sum(kph f_x i_x) dt = w T dt (e_x = kph w f_x, dL = 0)
    n_edges, vdc, omega, theta_e = period_tail_i(state, p, c, omega, theta_e, vdc, a1, a2, omega * a4, a4,
                                                 edge_counts, edge_states, n_edges)
    return n_edges, (i0, i1, i2, vdc, omega, theta_e)


@njit(**JIT)
def step_period(state, p, c, gates_a, gates_b, split, edge_counts, edge_states, n_edges, ws, wi, setup_done):
    """One control period: electrical (2 segments), Hall edges, DC bus, shaft. Returns n_edges.

    General form (any machine; step_period_sym is its fast specialisation). ws
    (float64[WS_SIZE]) and wi (int64[6]) are scratch, so nothing is allocated. Hall
    edges found in the period are appended to edge_counts / edge_states (capacity
    permitting) and the updated n_edges is returned. setup_done: ws already holds
    period_setup(state) (the controller computed it for its prediction).
    """
    dt = c[KC_DT]
    kph = c[KC_KPH]
    if not setup_done:
        period_setup(state, p, ws)
    ga, gb, s = _interlock_and_split(state, p, gates_a, gates_b, split, state[S_IA], state[S_IB], state[S_IC])
    for k in range(5):
        ws[W_ACC + k] = 0.0
    vdc = state[S_VDC]
    if s > 0.0:
        electrical_segment(state, 0, ga, s * dt, vdc, ws, wi, kph, W_ACC)
    if s < 1.0:
        electrical_segment(state, 0, gb, (1.0 - s) * dt, vdc, ws, wi, kph, W_ACC)
    return period_tail(state, p, c, ws[W_ACC + 1], ws[W_ACC + 2], ws[W_ACC + 3], ws[W_ACC + 4],
                       edge_counts, edge_states, n_edges)


@njit(**JIT_HOT)
def _wrap_angle(th):
    """th outside [0, 2 pi): one turn back or on (exact here, Sterbenz), else th % 2 pi."""
    if th >= TWO_PI:
        th -= TWO_PI
    elif th < 0.0:
        th += TWO_PI
    if not (0.0 <= th < TWO_PI):
        th = th % TWO_PI
    return th


@njit(**JIT_INLINE)
def period_tail(state, p, c, a_charge, a_cu, a_conv, a_tdt, edge_counts, edge_states, n_edges):
    """The rest of a period after the electrical segments: Hall edges, DC bus, shaft.

    a_charge: charge DC node -> bridge [C] (negated bridge current integral), a_cu: copper
    loss [J], a_conv: electromechanical conversion [J], a_tdt: torque integral [N m s];
    state still holds the period's start angle, speed and v_dc. Returns n_edges."""
    n_edges, _vdc, _w, _th = period_tail_i(state, p, c, state[S_OMEGA], state[S_THETA_E], state[S_VDC], a_charge, a_cu,
                                           a_conv, a_tdt, edge_counts, edge_states, n_edges)
    return n_edges


@njit(**JIT_INLINE)
def period_tail_i(state, p, c, omega, th0, vdc, a_charge, a_cu, a_conv, a_tdt, edge_counts, edge_states, n_edges):
    """period_tail from the state's start speed omega, angle th0 and v_dc. Returns (n_edges,
    v_dc, omega, theta_e) of the next period, as stored in the state."""
    dt = c[KC_DT]
    we = c[KC_PP] * omega
    t_em = a_tdt * c[KC_INV_DT]

    # ---- Hall edges (sector boundaries at 30 + 60 k deg), capture-timer quantised
    u0 = (th0 - TWELFTH) * INV_SIXTH
    du = we * dt * INV_SIXTH
    u1 = u0 + du
    periods = state[S_PERIODS]
    if du > 0.0:
        k = np.floor(u0) + 1.0       # (np: a float floor, no int64 round trip)
        if k <= u1:
            n_edges = _hall_edges(state, p, k, u0, u1, du, periods, 1.0, edge_counts, edge_states, n_edges)
    elif du < 0.0:
        k = np.ceil(u0) - 1.0
        if k >= u1:
            n_edges = _hall_edges(state, p, k, u0, u1, du, periods, -1.0, edge_counts, edge_states, n_edges)

    # ---- DC node: battery (Voc, Rb) || S0 * brake resistor; the bridge injected i_dc
    i_dc = a_charge * c[KC_INV_DT]
    s0 = state[S_S0]
    i_res = 0.0
    if s0 != 0.0:
        i_res = min(vdc * c[KC_INV_RR], state[S_I_CHOP])     # the chopper's current, at most fully on
        state[S_E_RES] += vdc * i_res * dt
    i_batt = i_dc - i_res                     # KCL with this period's bridge current
    state[S_E_BATT] += vdc * i_batt * dt
    state[S_E_CU] += a_cu
    state[S_E_CONV] += a_conv
    soc = state[S_SOC] + i_batt * c[KC_DT_PER_CAP]
    state[S_SOC] = soc
    state[S_IBATT] = i_batt
    state[S_IDC] = i_dc
    vfilt = state[S_VFILT] + p[P.P_S0_ALPHA] * (vdc - state[S_VFILT])
    state[S_VFILT] = vfilt
    voc = battery_voc(soc, p)
    vdc_next = (voc * c[KC_INV_RB] + i_dc) * c[KC_INV_DEN_S0_OFF]
    if s0 == 0.0:
        if vfilt > p[P.P_S0_ON]:
            s0 = 1.0
            state[S_IDC_AVG] = (vfilt - voc) * c[KC_INV_RB]    # the filtered bus with S0 open is Voc + Rb i
    else:
        state[S_IDC_AVG] += p[P.P_S0_ALPHA] * (i_dc - state[S_IDC_AVG])
    if s0 != 0.0:
        vdc_next, s0 = _s0_chopper(state, p, c, voc, vdc_next)
    state[S_S0] = s0
    state[S_VDC] = vdc_next
    # (unlikely: a branch, not a select added to the period's chain; bike_plant.jit)
    if vdc_next > p[P.P_OVERVOLTAGE] or _jit.unlikely(soc > SOC_OVERCHARGE and i_batt > 0.0):
        state[S_FAULTS] = int(state[S_FAULTS]) | FAULT_OVERVOLTAGE
    elif state[S_FAULTS] != 0.0:
        state[S_FAULTS] = int(state[S_FAULTS]) & ~FAULT_OVERVOLTAGE

    # ---- shaft
    J = p[P.P_J]
    B = p[P.P_B]
    kind = int(p[P.P_LOAD_KIND])
    if kind == 0:
        # prime mover: speed held exactly; it supplies whatever torque that takes
        t_load = B * omega - t_em
        state[S_E_MECH] += t_load * omega * dt
        state[S_E_FRIC] += B * omega * omega * dt
        w_new = state[S_SPEED_TARGET]
        if w_new != omega:
            state[S_E_MECH] += 0.5 * J * (w_new * w_new - omega * omega)
    else:
        t_load = 0.0
        if kind == 1:
            t_load = _rider(state, p, c, omega, dt)
        w_new = omega + (t_em + t_load - B * omega) * c[KC_DT_PER_J]
        w_avg = 0.5 * (omega + w_new)
        state[S_E_MECH] += t_load * w_avg * dt
        state[S_E_FRIC] += B * omega * w_avg * dt
    state[S_OMEGA] = w_new
    state[S_TEM] = t_em
    state[S_TLOAD] = t_load
    th1 = th0 + we * dt
    if not (0.0 <= th1 < TWO_PI):    # one test on the common path
        th1 = _wrap_angle(th1)
    state[S_THETA_E] = th1
    state[S_PERIODS] = periods + 1.0
    return n_edges, vdc_next, w_new, th1


@njit(**JIT_INLINE)
def _s0_chopper(state, p, c, voc, vdc_free):
    """S0 closed (paper 000, Fig. 2: dynamic braking): a chopper switching faster than the
    period, modelled by its mean current, holds the bus at s0_off_v (above the full pack's OCV,
    BatteryParams). The pack takes what it takes there, (s0_off_v - Voc) / Rb (none once its OCV
    is above), the resistor the rest of the filtered bridge current, at most v_dc / R_brake
    (fully on), so it never takes the pack's energy (a plain switch with its 54.0 V release below
    the OCV took 27.6 J from a pack at SOC 0.99 in 0.5 s at Command 0.3). The period's ripple
    goes to the pack, standing in for the bus capacitor the model lacks. S0 opens once nothing
    is left for the resistor. vdc_free: the bus with S0 open. Returns (v_dc next, s0)."""
    i_chop = state[S_IDC_AVG] - max(p[P.P_S0_OFF] - voc, 0.0) * c[KC_INV_RB]
    if i_chop <= 0.0:
        state[S_I_CHOP] = 0.0
        return vdc_free, 0.0
    state[S_I_CHOP] = i_chop
    # held at Voc + Rb (i_dc - i_chop), or below it fully on
    return max(vdc_free * c[KC_S0_ON_RATIO], vdc_free - i_chop * c[KC_INV_DEN_S0_OFF]), 1.0


@njit(**JIT_COLD)
def _hall_edges(state, p, k, u0, u1, du, periods, direction, edge_counts, edge_states, n_edges):
    """Hall edges k, k +- 1, ... of a period that crosses sector boundaries (u in sixths of
    a turn from 30 deg; direction +1 forward, -1 backward). Returns n_edges."""
    _jit.out_of_line()
    fc_dt = p[P.P_TIMER_HZ] * p[P.P_DT]
    if direction > 0.0:
        while k <= u1:
            frac = (k - u0) / du
            if n_edges < edge_counts.shape[0]:
                edge_counts[n_edges] = np.uint64(math.floor((periods + frac) * fc_dt))
                edge_states[n_edges] = SECTOR_TO_HALL[int(k) % 6]
                n_edges += 1
            state[S_HALL] = SECTOR_TO_HALL[int(k) % 6]
            k += 1.0
    else:
        while k >= u1:
            frac = (k - u0) / du
            if n_edges < edge_counts.shape[0]:
                edge_counts[n_edges] = np.uint64(math.floor((periods + frac) * fc_dt))
                edge_states[n_edges] = SECTOR_TO_HALL[(int(k) - 1) % 6]
                n_edges += 1
            state[S_HALL] = SECTOR_TO_HALL[(int(k) - 1) % 6]
            k -= 1.0
    return n_edges


@njit(**JIT_INLINE)
def cos_poly(x):
    """cos(x) for x in [0, 4 pi] (wider x: math.cos) without a libm call: reduced to
    y = |x - 2 pi k| in [0, pi], then cos(y) = -cos(pi - y) folds it onto [0, pi / 2], where
    an even Taylor polynomial to y^18 is within 1e-14 of cos (deterministic: plain IEEE
    multiplies and adds)."""
    if not (0.0 <= x <= 2.0 * TWO_PI):
        return math.cos(x)
    if x > math.pi:
        x = x - TWO_PI
        if x > math.pi:
            x = x - TWO_PI
    y = abs(x)
    sgn = 1.0
    if y > 0.5 * math.pi:
        y = math.pi - y
        sgn = -1.0
    z = y * y
    # Horner form of sum_k (-1)^k z^k / (2k)!, k = 0..9
    c = -1.0 / 6402373705728000.0
    c = 1.0 / 20922789888000.0 + z * c
    c = -1.0 / 87178291200.0 + z * c
    c = 1.0 / 479001600.0 + z * c
    c = -1.0 / 3628800.0 + z * c
    c = 1.0 / 40320.0 + z * c
    c = -1.0 / 720.0 + z * c
    c = 1.0 / 24.0 + z * c
    c = -0.5 + z * c
    c = 1.0 + z * c
    return sgn * c


@njit(**JIT_INLINE)
def _rider(state, p, c, omega, dt):
    """Rider load (LoadParams): PI effort on cadence, crank torque with two peaks per turn,
    T_crank = effort T0 max(0, 1 - cad / cad_max) (1 + cos(2 crank) / 2) (bike_plant.mechanics).
    Returns the load torque at the motor shaft (T_crank / gear)."""
    inv_gear = c[KC_INV_GEAR]
    cad = omega * inv_gear
    if p[P.P_RIDER_TARGET] <= 0.0:
        # stops pedalling (a spin-down's coast): no effort, the integral holds, the cranks turn on
        effort = 0.0
    else:
        err = p[P.P_RIDER_TARGET] - cad
        integ = state[S_RIDER_INT] + p[P.P_RIDER_KI] * err * dt
        integ = min(max(integ, -1.0), 1.0)
        effort = p[P.P_RIDER_KP] * err + integ
        # conditional integration (bike_plant.mechanics.rider_effort_update): the integral holds
        # while the effort is pinned and the error pushes it further
        if (effort < 0.0 and err < 0.0) or (effort > 1.0 and err > 0.0):
            integ = state[S_RIDER_INT]
            effort = p[P.P_RIDER_KP] * err + integ
        state[S_RIDER_INT] = integ
        effort = min(max(effort, 0.0), 1.0)
    state[S_EFFORT] = effort
    line = 1.0 - cad * c[KC_INV_CADMAX]
    if line < 0.0:
        line = 0.0
    t_crank = effort * p[P.P_RIDER_T0] * line * (1.0 + 0.5 * cos_poly(2.0 * state[S_CRANK]))
    crank = state[S_CRANK] + cad * dt
    if not (0.0 <= crank < TWO_PI):     # wrap to [0, 2 pi) (one add/subtract: exact, = Python's %)
        crank = _wrap_angle(crank)
    state[S_CRANK] = crank
    return t_crank * inv_gear


@njit(**JIT)
def step_batch(state, p, gates_a, gates_b, split, edge_counts, edge_states, samples, sums):
    """N periods. samples[k] = phase currents at the end of period k; sums = [sum T_em,
    sum T_load, sum i_batt] over the periods. Returns the number of Hall edges captured."""
    n = gates_a.shape[0]
    ws = np.empty(WS_SIZE)
    wi = np.empty(6, np.int64)
    c = plant_constants(p)
    sym = c[KC_SYM] != 0.0
    n_edges = 0
    sums[0] = 0.0
    sums[1] = 0.0
    sums[2] = 0.0
    for k in range(n):
        if sym:
            n_edges = step_period_sym(state, p, c, gates_a[k], gates_b[k], split[k], emf_sym(state, p), NO_LEGS,
                                      NO_LEGS, edge_counts, edge_states, n_edges, ws, wi)
        else:
            n_edges = step_period(state, p, c, gates_a[k], gates_b[k], split[k], edge_counts, edge_states, n_edges,
                                  ws, wi, False)
        samples[k, 0] = state[S_IA]
        samples[k, 1] = state[S_IB]
        samples[k, 2] = state[S_IC]
        sums[0] += state[S_TEM]
        sums[1] += state[S_TLOAD]
        sums[2] += state[S_IBATT]
    return n_edges


def new_state(p: np.ndarray, speed_rpm: float, soc0: float) -> np.ndarray:
    s = np.zeros(S_SIZE)
    init_state(s, p, speed_rpm / P.RPM_PER_RAD_S, soc0)
    return s


def ledger_of(state: np.ndarray, p: np.ndarray) -> dict:
    """Energy ledger [J], cumulative since start. residual = in - out - stored (should be ~0).

    energy_battery_j is at the pack's terminals (its internal resistance's heat included);
    energy_loss_j is copper + friction (ideal switches and diodes: module docstring)."""
    e_mech = state[S_E_MECH]
    e_batt = state[S_E_BATT]
    e_res = state[S_E_RES]
    e_loss = state[S_E_CU] + state[S_E_FRIC]
    e_stored = stored_energy(state, p) - state[S_E_STORED0]
    return {
        "energy_mech_in_j": float(e_mech),
        "energy_battery_j": float(e_batt),
        "energy_resistor_j": float(e_res),
        "energy_loss_j": float(e_loss),
        "energy_stored_j": float(e_stored),
        "residual_j": float(e_mech - e_batt - e_res - e_loss - e_stored),
    }
