"""Numba kernels of the BLDC machine + 6-switch bridge + battery + shaft (paper 000).

Everything that runs once per 50 us control period lives here, compiled with
``@njit(cache=True, error_model="numpy")``; a whole batch of N periods is one call (:func:`step_batch`), so
there is no Python per period. The controller's predictor calls the same
:func:`step_period` on its own state vector (ARCHITECTURE.md, batched inner loop).

Electrical model (per phase x = a, b, c; terminal voltage v_x w.r.t. DC minus):
    v_x = v_n + R i_x + L_x di_x/dt + i_x dL_x/dt + e_x,   e_x = kph * w_m * f_x(theta_e)
f_x is the 120-degree flat-top trapezoid (paper 000, Fig. 4), optionally blended with a
sinusoid at low speed (section 4.3, Fig. 11: the reason for k < 1). Torque (motoring
positive): T = sum(kph f_x i_x) + 1/2 sum(i_x^2 dL_x/dtheta_m).

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

from . import params as P


def invalidate_stale_numba_cache(module_file: str, dependencies) -> int:
    """Delete this module's numba cache files if a module it calls into is newer.

    numba's cache=True keys a compiled function on its own source file only; functions
    here inline code and constants from other modules (params layout, plant kernels), so
    an edit there would otherwise leave a stale, silently wrong cache. Returns the number
    of files removed."""
    import pathlib
    src = pathlib.Path(module_file).resolve()
    cache_dir = src.parent / "__pycache__"
    if not cache_dir.is_dir():
        return 0
    try:
        newest = max(pathlib.Path(d).resolve().stat().st_mtime for d in dependencies)
    except OSError:
        return 0
    removed = 0
    for f in list(cache_dir.glob(src.stem + ".*.nbi")) + list(cache_dir.glob(src.stem + ".*.nbc")):
        try:
            if f.stat().st_mtime < newest:
                f.unlink()
                removed += 1
        except OSError:
            pass
    return removed


invalidate_stale_numba_cache(__file__, [P.__file__])

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
S_SIZE = 32

FAULT_INTERLOCK = 1
FAULT_OVERVOLTAGE = 4

# Hall code -> 60-degree sector (sector k spans theta_e in [30 + 60k, 90 + 60k) deg)
HALL_TO_SECTOR = np.array([-1, 0, 2, 1, 4, 5, 3, -1], dtype=np.int64)
SECTOR_TO_HALL = np.array([1, 3, 2, 6, 4, 5], dtype=np.int64)
# phase at +E (p) and at -E (n) in each sector (trapezoid flat tops)
SECTOR_P = np.array([0, 0, 1, 1, 2, 2], dtype=np.int64)
SECTOR_N = np.array([1, 2, 2, 0, 0, 1], dtype=np.int64)

TWO_PI = 2.0 * math.pi
SIXTH = math.pi / 3.0
TWELFTH = math.pi / 6.0
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


@njit(cache=True, error_model="numpy")
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


@njit(cache=True, error_model="numpy")
def _trap_near(theta):
    """trapezoid() for theta within one turn of [0, 2 pi) (no float modulo)."""
    if theta < 0.0:
        theta += TWO_PI
    elif theta >= TWO_PI:
        theta -= TWO_PI
    if theta < 0.0 or theta >= TWO_PI:
        return trapezoid(theta)
    if theta < TWELFTH:
        return theta / TWELFTH
    if theta < 5.0 * TWELFTH:
        return 1.0
    if theta < 7.0 * TWELFTH:
        return 1.0 - (theta - 5.0 * TWELFTH) / TWELFTH
    if theta < 11.0 * TWELFTH:
        return -1.0
    return -1.0 + (theta - 11.0 * TWELFTH) / TWELFTH


@njit(cache=True, error_model="numpy")
def interp_table(x, xs, ys, n):
    if x <= xs[0]:
        return ys[0]
    for k in range(1, n):
        if x < xs[k]:
            return ys[k - 1] + (ys[k] - ys[k - 1]) * (x - xs[k - 1]) / (xs[k] - xs[k - 1])
    return ys[n - 1]


@njit(cache=True, error_model="numpy")
def emf_shape(theta_e, omega, p, f, off):
    """f[off + x] for the 3 phases at angle theta_e (non-ideal blend if enabled)."""
    for x in range(3):
        f[off + x] = _trap_near(theta_e - x * (TWO_PI / 3.0))
    if p[P.P_EMF_NONIDEAL] != 0.0:
        n = int(p[P.P_NTAB])
        w = interp_table(abs(omega), p[P.P_TAB_X:P.P_TAB_X + 8], p[P.P_TAB_Y:P.P_TAB_Y + 8], n)
        a = (1.0 - w) * p[P.P_SINE_AMP]
        for x in range(3):
            f[off + x] = w * f[off + x] + a * math.sin(theta_e - x * (TWO_PI / 3.0))


@njit(cache=True, error_model="numpy")
def sector_of(theta_e):
    return int(((theta_e - TWELFTH) % TWO_PI) // SIXTH) % 6


@njit(cache=True, error_model="numpy")
def hall_of(theta_e):
    return SECTOR_TO_HALL[sector_of(theta_e)]


@njit(cache=True, error_model="numpy")
def blank_interlock(gates):
    """Hardware interlock (GAL of paper 000, Fig. 10): a leg with both switches on is blanked.

    Returns (applied gates, number of blanked legs)."""
    g = gates & 63
    nb = 0
    for x in range(3):
        m = 3 << (2 * x)
        if (g & m) == m:
            g &= ~m
            nb += 1
    return g, nb


@njit(cache=True, error_model="numpy")
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


@njit(cache=True, error_model="numpy")
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


@njit(cache=True, error_model="numpy")
def _fast_sym(cur, co, gates, vdc, ws, wi, t):
    """Scalar fast path of _topology + _solve for the symmetric machine when the first
    topology guess holds (>= 2 conducting legs, no floating terminal clamps): the same
    floating-point operations in the same order, so bit-identical. Returns False (nothing
    written but wi) when the general iteration is needed."""
    i0 = cur[co]
    i1 = cur[co + 1]
    i2 = cur[co + 2]
    # leg states (as _topology's first pass); d = diode-only leg
    w0 = 2 if (gates & 1) else (1 if (gates & 2) else (1 if i0 > 0.0 else (2 if i0 < 0.0 else 0)))
    w1 = 2 if (gates & 4) else (1 if (gates & 8) else (1 if i1 > 0.0 else (2 if i1 < 0.0 else 0)))
    w2 = 2 if (gates & 16) else (1 if (gates & 32) else (1 if i2 > 0.0 else (2 if i2 < 0.0 else 0)))
    d0 = 0 if (gates & 3) else 1
    d1 = 0 if (gates & 12) else 1
    d2 = 0 if (gates & 48) else 1
    ncl = (w0 > 0) + (w1 > 0) + (w2 > 0)
    if ncl < 2:
        return False
    e0 = ws[W_E]
    e1 = ws[W_E + 1]
    e2 = ws[W_E + 2]
    r = ws[W_R]
    g = t / (ws[W_L] + 0.5 * r * t)
    v0 = vdc if w0 == 2 else 0.0
    v1 = vdc if w1 == 2 else 0.0
    v2 = vdc if w2 == 2 else 0.0
    sw = 0.0
    if w0 > 0:
        sw += v0 - e0 - r * i0
    if w1 > 0:
        sw += v1 - e1 - r * i1
    if w2 > 0:
        sw += v2 - e2 - r * i2
    vn = sw * 0.5 if ncl == 2 else sw / 3.0     # x * 0.5 == x / 2 exactly
    # a floating terminal that would clamp needs the general iteration
    if w0 == 0:
        vt = vn + e0
        if vt > vdc or vt < 0.0:
            return False
    if w1 == 0:
        vt = vn + e1
        if vt > vdc or vt < 0.0:
            return False
    if w2 == 0:
        vt = vn + e2
        if vt > vdc or vt < 0.0:
            return False
    ws[W_I1] = i0 + g * (v0 - e0 - r * i0 - vn) if w0 > 0 else 0.0
    ws[W_I1 + 1] = i1 + g * (v1 - e1 - r * i1 - vn) if w1 > 0 else 0.0
    ws[W_I1 + 2] = i2 + g * (v2 - e2 - r * i2 - vn) if w2 > 0 else 0.0
    wi[0] = w0
    wi[1] = w1
    wi[2] = w2
    wi[3] = d0
    wi[4] = d1
    wi[5] = d2
    return True


@njit(cache=True, error_model="numpy")
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


@njit(cache=True, error_model="numpy")
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


@njit(cache=True, error_model="numpy")
def stored_energy(state, p):
    ws = np.zeros(WS_SIZE)
    phase_inductance(state[S_THETA_E], 0.0, p, ws)
    w = 0.5 * p[P.P_J] * state[S_OMEGA] ** 2
    for x in range(3):
        w += 0.5 * ws[W_L + x] * state[x] ** 2
    return w


@njit(cache=True, error_model="numpy")
def battery_voc(soc, p):
    return p[P.P_V_EMPTY] + (p[P.P_V_FULL] - p[P.P_V_EMPTY]) * soc


@njit(cache=True, error_model="numpy")
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


@njit(cache=True, error_model="numpy")
def period_setup(state, p, ws):
    """Back-EMF and inductances of the coming period, evaluated at its mid angle and held."""
    omega = state[S_OMEGA]
    th_mid = state[S_THETA_E] + 0.5 * p[P.P_POLE_PAIRS] * omega * p[P.P_DT]
    emf_shape(th_mid, omega, p, ws, W_F)
    kph = p[P.P_KPH]
    for x in range(3):
        ws[W_E + x] = kph * omega * ws[W_F + x]
    phase_inductance(th_mid, omega, p, ws)


@njit(cache=True, error_model="numpy")
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


@njit(cache=True, error_model="numpy")
def step_period(state, p, gates_a, gates_b, split, edge_counts, edge_states, n_edges, ws, wi, setup_done):
    """One control period: electrical (2 segments), Hall edges, DC bus, shaft. Returns n_edges.

    ws (float64[WS_SIZE]) and wi (int64[6]) are scratch, so nothing is allocated. Hall
    edges found in the period are appended to edge_counts / edge_states (capacity
    permitting) and the updated n_edges is returned. setup_done: ws already holds
    period_setup(state) (the controller computed it for its prediction).
    """
    dt = p[P.P_DT]
    pp = p[P.P_POLE_PAIRS]
    kph = p[P.P_KPH]
    omega = state[S_OMEGA]
    th0 = state[S_THETA_E]
    we = pp * omega
    if not setup_done:
        period_setup(state, p, ws)
    ga, nba = blank_interlock(gates_a)
    gb, nbb = blank_interlock(gates_b)
    if nba + nbb > 0:
        state[S_INTERLOCK] += nba + nbb
        state[S_FAULTS] = int(state[S_FAULTS]) | FAULT_INTERLOCK
    s = split
    if not (s >= 0.0):      # also catches NaN
        s = 0.0
    if s > 1.0:
        s = 1.0
    for k in range(5):
        ws[W_ACC + k] = 0.0
    vdc = state[S_VDC]
    if s > 0.0:
        electrical_segment(state, 0, ga, s * dt, vdc, ws, wi, kph, W_ACC)
    if s < 1.0:
        electrical_segment(state, 0, gb, (1.0 - s) * dt, vdc, ws, wi, kph, W_ACC)
    t_em = ws[W_ACC + 4] / dt

    # ---- Hall edges (sector boundaries at 30 + 60 k deg), capture-timer quantised
    u0 = (th0 - TWELFTH) / SIXTH
    du = we * dt / SIXTH
    u1 = u0 + du
    fc_dt = p[P.P_TIMER_HZ] * dt
    periods = state[S_PERIODS]
    if du > 0.0:
        k = math.floor(u0) + 1.0
        while k <= u1:
            frac = (k - u0) / du
            if n_edges < edge_counts.shape[0]:
                edge_counts[n_edges] = np.uint64(math.floor((periods + frac) * fc_dt))
                edge_states[n_edges] = SECTOR_TO_HALL[int(k) % 6]
                n_edges += 1
            state[S_HALL] = SECTOR_TO_HALL[int(k) % 6]
            k += 1.0
    elif du < 0.0:
        k = math.ceil(u0) - 1.0
        while k >= u1:
            frac = (k - u0) / du
            if n_edges < edge_counts.shape[0]:
                edge_counts[n_edges] = np.uint64(math.floor((periods + frac) * fc_dt))
                edge_states[n_edges] = SECTOR_TO_HALL[(int(k) - 1) % 6]
                n_edges += 1
            state[S_HALL] = SECTOR_TO_HALL[(int(k) - 1) % 6]
            k -= 1.0

    # ---- DC node: battery (Voc, Rb) || S0 * brake resistor; the bridge injected i_dc
    i_dc = ws[W_ACC + 1] / dt
    s0 = state[S_S0]
    rr = p[P.P_R_BRAKE]
    i_res = s0 * vdc / rr
    i_batt = i_dc - i_res                     # KCL with this period's bridge current
    state[S_E_BATT] += vdc * i_batt * dt
    state[S_E_RES] += vdc * i_res * dt
    state[S_E_CU] += ws[W_ACC + 2]
    state[S_E_CONV] += ws[W_ACC + 3]
    state[S_SOC] += i_batt * dt / p[P.P_CAP_AS]
    state[S_IBATT] = i_batt
    state[S_IDC] = i_dc
    state[S_VFILT] += p[P.P_S0_ALPHA] * (vdc - state[S_VFILT])
    if s0 == 0.0 and state[S_VFILT] > p[P.P_S0_ON]:
        s0 = 1.0
    elif s0 != 0.0 and state[S_VFILT] < p[P.P_S0_OFF]:
        s0 = 0.0
    state[S_S0] = s0
    rb = p[P.P_R_BATT]
    voc = battery_voc(state[S_SOC], p)
    vdc_next = (voc / rb + i_dc) / (1.0 / rb + s0 / rr)
    state[S_VDC] = vdc_next
    if vdc_next > p[P.P_OVERVOLTAGE]:
        state[S_FAULTS] = int(state[S_FAULTS]) | FAULT_OVERVOLTAGE
    else:
        state[S_FAULTS] = int(state[S_FAULTS]) & ~FAULT_OVERVOLTAGE

    # ---- shaft
    J = p[P.P_J]
    B = p[P.P_B]
    kind = int(p[P.P_LOAD_KIND])
    gear = p[P.P_GEAR]
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
            cad = omega / gear
            err = p[P.P_RIDER_TARGET] - cad
            integ = state[S_RIDER_INT] + p[P.P_RIDER_KI] * err * dt
            integ = min(max(integ, -1.0), 1.0)
            state[S_RIDER_INT] = integ
            effort = p[P.P_RIDER_KP] * err + integ
            effort = min(max(effort, 0.0), 1.0)
            state[S_EFFORT] = effort
            line = 1.0 - cad / p[P.P_RIDER_CADMAX]
            if line < 0.0:
                line = 0.0
            t_crank = effort * p[P.P_RIDER_T0] * line * (1.0 + 0.5 * math.cos(2.0 * state[S_CRANK]))
            t_load = t_crank / gear
            state[S_CRANK] = (state[S_CRANK] + cad * dt) % TWO_PI
        w_new = omega + dt * (t_em + t_load - B * omega) / J
        w_avg = 0.5 * (omega + w_new)
        state[S_E_MECH] += t_load * w_avg * dt
        state[S_E_FRIC] += B * omega * w_avg * dt
    state[S_OMEGA] = w_new
    state[S_TEM] = t_em
    state[S_TLOAD] = t_load
    th1 = th0 + we * dt
    if th1 >= TWO_PI:
        th1 -= TWO_PI
    elif th1 < 0.0:
        th1 += TWO_PI
    if not (0.0 <= th1 < TWO_PI):
        th1 = th1 % TWO_PI
    state[S_THETA_E] = th1
    state[S_PERIODS] = periods + 1.0
    return n_edges


@njit(cache=True, error_model="numpy")
def step_batch(state, p, gates_a, gates_b, split, edge_counts, edge_states, samples, sums):
    """N periods. samples[k] = phase currents at the end of period k; sums = [sum T_em,
    sum T_load, sum i_batt] over the periods. Returns the number of Hall edges captured."""
    n = gates_a.shape[0]
    ws = np.empty(WS_SIZE)
    wi = np.empty(6, np.int64)
    n_edges = 0
    sums[0] = 0.0
    sums[1] = 0.0
    sums[2] = 0.0
    for k in range(n):
        n_edges = step_period(state, p, gates_a[k], gates_b[k], split[k], edge_counts, edge_states, n_edges, ws, wi,
                              False)
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
    """Energy ledger [J], cumulative since start. residual = in - out - stored (should be ~0)."""
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
