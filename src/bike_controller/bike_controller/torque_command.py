"""Torque command transformer and torque-constant correction (paper 000, section 4.2-4.3).

    Pmax = Tmax * wb                                   (Eq. 2)
    Tcmd = Command * Tmax          for w <  wb         (Eq. 3)
    Tcmd = Command * Pmax / w      for w >= wb         (Eq. 4)
    Command in [0, 1]                                  (Eq. 5)
    T = k(w) * ke * I = ktg * I,   ktg = k * ke        (Eq. 6-9; ke in V s/rad line-to-line = kt)

Pmax: the paper prints 964.68 W, but Eq. 2 with Tmax = 30 kgf cm and wb = 3300 rpm gives
1016.7 W; 964.68 W would put a 5 % step into the curve at wb, so the default config uses
Eq. 2 (pmax_w stays a parameter).
"""
from __future__ import annotations

import math

from numba import njit

from . import bldc_params as _law

RPM_PER_RAD_S = 60.0 / (2.0 * math.pi)
REGION_CONSTANT_TORQUE = 0
REGION_CONSTANT_POWER = 1
MODE_RESISTANCE = 0
MODE_MOTORING = 1


@njit(cache=True, error_model="numpy")
def pmax_w(tmax_nm, base_speed_rpm):
    """Eq. 2 of paper 000."""
    return tmax_nm * base_speed_rpm / RPM_PER_RAD_S


# Eq. 3-4 and the k(w) table, written once in bldc_params (numba-free: the config checks use
# them) and compiled here for the kernels
torque_command_nm = njit(cache=True, error_model="numpy")(_law.torque_command_nm)
k_factor = njit(cache=True, error_model="numpy")(_law.k_factor)


@njit(cache=True, error_model="numpy")
def region_of(speed_rpm, base_speed_rpm):
    return REGION_CONSTANT_TORQUE if abs(speed_rpm) < base_speed_rpm else REGION_CONSTANT_POWER


@njit(cache=True, error_model="numpy")
def ktg_nm_per_a(k, kt):
    """Eq. 8-9 of paper 000: ktg = k * ke (ke taken as the line-to-line constant in V s/rad)."""
    return k * kt
