"""The BLDC controller's parameters (the config's ``controller:`` section, paper 000 section
4-5) and the Command check of Eq. 5, apart from the kernels of bike_controller.bldc_control
(which re-exports them): ./bike run checks a config with them before it starts a node, and
that process then loads no numba (0.3 s and ~60 MB)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from bike_plant import params as P
from bike_plant.config import ConfigError, build_dataclass, require_positive, section

from .modes import MODE_MOTORING, MODE_RESISTANCE

KGF_CM_TO_NM = 9.80665e-2
K_TABLE_MAX = 24                 # k(speed) table points the controller's parameter vector holds
K_ROWS_MAX = 12                  # k table rows over the Command (k_command)
K_ROW_MAX = 2.0                  # a light Command's row may exceed 1: see ControllerParams.k_command


@dataclass
class ControllerParams:
    """controller: section of the config (paper 000, section 4-5)."""
    tmax_nm: float = 30.0 * KGF_CM_TO_NM          # 30 kgf cm = 2.942 N m
    base_speed_rpm: float = 3300.0
    pmax_w: float = 1016.68                        # Eq. 2 (see torque_command.py on 964.68 W)
    k_speed_rpm: list = field(default_factory=lambda: [0.0, 4500.0])
    k_factor: list = field(default_factory=lambda: [0.8, 1.0])
    k_interp: str = "step"                         # step | linear
    # Optional Command axis of the k table. Empty: k_factor is the paper's k(w) (one row, Eq. 7).
    # Given: k_factor holds one row per Command here, row after row (each over k_speed_rpm: a
    # flat list, as a ROS parameter file takes no nested lists), interpolated linearly in the
    # Command (Eq. 5) and clamped at both ends; the row at Command = 1 is the paper's k(w). The
    # paper measured k at Command = 1 only; torque per ampere rises as the current falls (a
    # shorter commutation dip), so that row alone brakes 13-19 % over Eq. 3-4 at Command 0.1-0.4
    # (default machine, 600-3000 rpm).
    k_command: list = field(default_factory=list)
    hysteresis_a: float = 1.5                      # half band h: I* - h .. I* + h
    current_limit_a: float = 120.0
    model: str = "nominal"                         # nominal | actual (see nominal_params_from_config)
    command0: float = 0.0
    mode0: int = 0

    def validate(self) -> None:
        require_positive(self, "tmax_nm", "base_speed_rpm", "pmax_w", "hysteresis_a", "current_limit_a")
        if len(self.k_speed_rpm) > K_TABLE_MAX:
            raise ValueError(f"at most {K_TABLE_MAX} k table points")
        if not isinstance(self.k_command, list) or not self.k_command:
            if self.k_command != []:
                raise ValueError(f"k_command must be a list of Commands, got {self.k_command!r}")
            if isinstance(self.k_factor, list) and isinstance(self.k_speed_rpm, list) \
                    and self.k_speed_rpm and len(self.k_factor) != len(self.k_speed_rpm):
                # --set controller.k_command=[] on the shipped table: "must be ... of equal length"
                # did not say that the 117 values are its 9 Command rows
                raise ValueError(f"with k_command: [] k_factor is the paper's one row over k_speed_rpm and must hold "
                                 f"{len(self.k_speed_rpm)} values, one per speed; got {len(self.k_factor)} (rows "
                                 f"for several Commands need their k_command)")
            P._check_table(self.k_speed_rpm, self.k_factor, "k_speed_rpm", "k_factor", 1e-6, 1.0)
        else:
            self._check_command_rows()
        if self.k_speed_rpm[0] < 0.0:
            # k_factor reads the table at |speed|: a point below 0 was taken and never used
            raise ValueError(f"k_speed_rpm must be speeds >= 0 (k is read at the speed's magnitude), "
                             f"got {self.k_speed_rpm!r}")
        if self.k_interp not in ("step", "linear"):
            raise ValueError(f"k_interp must be 'step' or 'linear', got {self.k_interp!r}")
        if self.model not in ("nominal", "actual"):
            raise ValueError(f"model must be 'nominal' or 'actual', got {self.model!r}")
        try:
            validate_command(self.command0, self.mode0)
        except ValueError as exc:                   # the keys the config has: command0, mode0
            raise ValueError(f"command0 / mode0: {exc}") from None

    def _check_command_rows(self) -> None:
        cs, xs, ys = self.k_command, self.k_speed_rpm, self.k_factor
        if len(cs) > K_ROWS_MAX:
            raise ValueError(f"at most {K_ROWS_MAX} k_command points")
        if any(isinstance(c, bool) or not isinstance(c, (int, float)) or not 0.0 < c <= 1.0 for c in cs) \
                or any(b <= a for a, b in zip(cs, cs[1:])):
            raise ValueError(f"k_command must be strictly increasing Commands in (0, 1], got {cs!r}")
        if len(ys) != len(cs) * len(xs):
            raise ValueError(f"with {len(cs)} k_command points and {len(xs)} k_speed_rpm points k_factor must "
                             f"hold {len(cs) * len(xs)} values, one row of {len(xs)} per Command, row after row; "
                             f"got {len(ys)} (k_command: [] makes k_factor the paper's one row over k_speed_rpm)")
        for r, c in enumerate(cs):
            P._check_table(xs, ys[r * len(xs):(r + 1) * len(xs)], "k_speed_rpm", f"k_factor row of Command {c:g}",
                           1e-6, K_ROW_MAX)

    def k_table(self) -> tuple[list, list, list]:
        """(speeds, Commands, rows one after the other) as :func:`k_factor` takes them: no
        Commands for the paper's k(w)."""
        return ([float(x) for x in self.k_speed_rpm], [float(c) for c in self.k_command],
                [float(y) for y in self.k_factor])


def controller_params_from_config(cfg: dict) -> ControllerParams:
    path = cfg.get("_config_path")
    cp = build_dataclass(ControllerParams, section(cfg, "controller", path), "controller", path)
    bldc = cfg.get("bldc")
    ke = bldc.get("ke_v_per_rpm", P.BldcParams.ke_v_per_rpm) if isinstance(bldc, dict) else None
    if isinstance(ke, (int, float)) and not isinstance(ke, bool) and math.isfinite(ke) and ke > 0:
        # the plant's section is checked with the plant's parameters; here only what it asks of the limit
        kt_nm_per_a = P.BldcParams(ke_v_per_rpm=ke).kt_nm_per_a
        need_a, at_rpm = peak_current_command_a(cp, kt_nm_per_a)
        if need_a > cp.current_limit_a:
            # I* = Tcmd / (k kt) was clamped to the limit without a word (half the default ke:
            # 138 A asked, 120 A commanded); Eq. 3-4 cannot be met there
            raise ConfigError(
                f"Command = 1 asks for {need_a:.1f} A at {at_rpm:g} rpm (Eq. 3-4 torque / (k_factor x kt), "
                f"kt = {kt_nm_per_a:.4g} N m/A from bldc.ke_v_per_rpm) but current_limit_a is "
                f"{cp.current_limit_a:g} A: lower tmax_nm / pmax_w or raise current_limit_a (and "
                "bldc.overcurrent_trip_a above it)", path, "controller.current_limit_a")
    step_problem = current_step_problem(cfg, cp)
    if step_problem:
        raise ConfigError(step_problem, path, "control_period_s")
    trip = bldc.get("overcurrent_trip_a", P.BldcParams.overcurrent_trip_a) if isinstance(bldc, dict) else None
    if isinstance(trip, (int, float)) and not isinstance(trip, bool) and trip <= cp.current_limit_a + cp.hysteresis_a:
        # the bridge's cycle-by-cycle trip inside the controller's own band blanks the gates in
        # closed-loop operation (--set controller.current_limit_a=200 was taken with the 150 A trip)
        raise ConfigError(f"{trip:g} A must be above controller.current_limit_a + hysteresis_a = "
                          f"{cp.current_limit_a + cp.hysteresis_a:g} A: the trip would blank the gates of "
                          "commands the controller makes (the shipped configs: 1.25 x current_limit_a)",
                          path, "bldc.overcurrent_trip_a")
    return cp


# the largest current change one control period may make, as a share of current_limit_a
CURRENT_STEP_MAX_SHARE = 0.4


def current_step_problem(cfg: dict, cp: ControllerParams) -> str | None:
    """Why the control period is too long for hysteresis current control with one switching
    edge per period (paper 000, section 5: 50 us), or None. The current changes by up to
    v_full_v T / (2 L) in a period (two phases in series across the full pack); past
    CURRENT_STEP_MAX_SHARE of current_limit_a the law loses the torque without a word
    (default machine, Command 0.4 at 3000 rpm, against 5e-5 s: within 2 points up to 2e-4 s,
    -20 points at 3e-4 s, -32 at 4e-4 s; a 2e-3 s period braked 53 W for 340 W and showed no
    current at all). The values not numbers here are refused by their own checks."""
    bldc, battery = cfg.get("bldc"), cfg.get("battery")
    inductance_h = bldc.get("inductance_h", P.BldcParams.inductance_h) if isinstance(bldc, dict) else None
    v_full_v = battery.get("v_full_v", P.BatteryParams.v_full_v) if isinstance(battery, dict) else None
    dt_s = cfg.get("control_period_s", 5.0e-5)
    values = (inductance_h, v_full_v, dt_s)
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0
               for v in values):
        return None
    step_a = v_full_v * dt_s / (2.0 * inductance_h)
    if step_a <= CURRENT_STEP_MAX_SHARE * cp.current_limit_a:
        return None
    longest_s = CURRENT_STEP_MAX_SHARE * cp.current_limit_a * 2.0 * inductance_h / v_full_v
    return (f"{dt_s:g} s is too long a period for hysteresis current control on this machine: the current "
            f"changes by up to {step_a:.0f} A in one (v_full_v x T / (2 x bldc.inductance_h)), more than "
            f"{CURRENT_STEP_MAX_SHARE:.0%} of controller.current_limit_a ({cp.current_limit_a:g} A), and the "
            f"torque is lost; at most {longest_s:.3g} s here (the paper's 5e-05 s)")


def torque_command_nm(command, speed_rpm, tmax_nm, base_speed_rpm, pmax):
    """Eq. 3-4 of paper 000 (magnitude of the braking torque). Plain Python, for the checks
    here; the controller's kernels run torque_command's njit copy of this very function."""
    w = abs(speed_rpm)
    if w < base_speed_rpm:
        return command * tmax_nm
    return command * pmax / (w / P.RPM_PER_RAD_S)


def k_factor(speed_rpm, command, xs, ys, n, linear, cs, nc):
    """Eq. 7 modification factor k(w) from a table over the speeds xs[:n]: step (value of the
    last point <= w) or linear. With nc >= 2 Commands cs, ys holds nc rows of n (row r at
    ys[r n:]) and k is interpolated linearly between the rows about the Command (clamped at
    the ends); nc <= 1: ys is the one row of the paper. Plain Python; torque_command.k_factor
    is its njit copy (one function: an njit copy cannot call a plain one)."""
    r0, r1, f = 0, 0, 0.0
    if nc >= 2:
        if command >= cs[nc - 1]:
            r0, r1 = nc - 1, nc - 1
        elif command > cs[0]:
            r1 = 1
            while command >= cs[r1]:
                r1 += 1
            r0 = r1 - 1
            f = (command - cs[r0]) / (cs[r1] - cs[r0])
    w = abs(speed_rpm)
    j0, j1, g = n - 1, n - 1, 0.0
    if w <= xs[0]:
        j0, j1 = 0, 0
    else:
        for j in range(1, n):
            if w < xs[j]:
                j0, j1 = j - 1, j - 1
                if linear:
                    j1 = j
                    g = (w - xs[j - 1]) / (xs[j] - xs[j - 1])
                break
    k0 = ys[r0 * n + j0] + (ys[r0 * n + j1] - ys[r0 * n + j0]) * g
    k1 = ys[r1 * n + j0] + (ys[r1 * n + j1] - ys[r1 * n + j0]) * g
    return k0 + (k1 - k0) * f


def peak_current_command_a(cp: ControllerParams, kt_nm_per_a: float) -> tuple[float, float]:
    """(largest current command I* = Tcmd / (k kt) of Command = 1 over the k table's speeds
    and the base speed, the speed where it is asked) of Eq. 3-4 and 6-9, with the law's own
    functions (torque_command_nm, k_factor)."""
    xs, cs, ys = cp.k_table()
    linear = cp.k_interp == "linear"
    wb = cp.base_speed_rpm
    speeds = sorted({*(x for x in xs if x >= 0.0), wb, math.nextafter(wb, 0.0)})
    return max((torque_command_nm(1.0, w, cp.tmax_nm, wb, cp.pmax_w)
                / (k_factor(w, 1.0, xs, ys, len(xs), linear, cs, len(cs)) * kt_nm_per_a), w) for w in speeds)


def validate_command(command, mode) -> None:
    """Eq. 5: Command in [0, 1]; mode 0 (resistance) or 1 (motoring). ValueError otherwise."""
    if isinstance(command, bool) or not isinstance(command, (int, float, np.floating, np.integer)):
        raise ValueError(f"command must be a number in [0, 1], got {command!r}")
    if not math.isfinite(float(command)):
        raise ValueError(f"command must be finite, got {command!r}")
    if not 0.0 <= float(command) <= 1.0:
        raise ValueError(f"command must be in [0, 1] (paper 000, Eq. 5), got {command!r}")
    if isinstance(mode, bool) or int(mode) != mode or int(mode) not in (MODE_RESISTANCE, MODE_MOTORING):
        raise ValueError(f"mode must be 0 (resistance) or 1 (motoring), got {mode!r}")
