"""Parameters of the BLDC bike (paper 000): machine, bridge, battery, mechanics, Hall sensors.

Dataclasses in the style of motulator: one small dataclass per physical part, values in
SI units with the unit in the name. They are built from the config dict (the
``/**: ros__parameters`` section, see docs/DESIGN.md) with
:func:`bike_plant.config.build_dataclass`, so a bad value raises ConfigError naming the key.

The numba kernels in :mod:`bike_plant.bldc` do not take dataclasses: :func:`pack_params`
flattens a :class:`PlantParams` into one float64 vector (layout ``P_*`` below).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields
from typing import Mapping

import numpy as np

from .config import ConfigError, build_dataclass, require_positive, section
from .heart import HeartParams

TWO_PI = 2.0 * math.pi
RPM_PER_RAD_S = 60.0 / TWO_PI


@dataclass
class BldcParams:
    """Trapezoidal-EMF BLDC machine + 6-switch bridge (paper 000, Table 1, Fig. 2/6).

    ke_v_per_rpm is the line-to-line back-EMF constant on the flat top, so the phase
    constant is kph = ke * 60 / (2 pi) / 2 [V s/rad] and, with two phases conducting, the
    torque constant is kt = 2 kph = ke * 60 / (2 pi) = 0.05204 N m/A.
    inductance_h is the per-phase effective inductance L - M (117.25 uH, Table 1).
    r_phase_ohm is not in the paper: 6 mOhm per phase (winding + switch on-resistance)
    keeps 2 R I = 0.85 V below E_LL = 1.63 V at 300 rpm, so the ~70 A the paper's
    Tmax / (0.8 kt) needs can still flow at the lowest speed of Fig. 14.
    """
    pole_pairs: int = 2
    ke_v_per_rpm: float = 5.45e-3
    inductance_h: float = 117.25e-6
    r_phase_ohm: float = 0.006
    # non-ideality 1 (paper 000, section 5, reason (1)): L_x = L0 (1 + eps cos(2 (theta_e - 120 deg x)))
    inductance_variation: float = 0.0
    # non-ideality 2 (paper 000, section 4.3 / Fig. 11): back-EMF shape blends from a
    # sinusoid (amplitude emf_sine_amplitude, per unit of the flat top) at low speed to
    # the ideal trapezoid at high speed; weight of the trapezoid from a piecewise-linear table.
    emf_nonideal: bool = False
    emf_sine_amplitude: float = 1.0
    emf_shape_speed_rpm: list = field(default_factory=lambda: [0.0, 4500.0])
    emf_trap_weight: list = field(default_factory=lambda: [1.0, 1.0])
    overvoltage_v: float = 80.0   # FAULT_OVERVOLTAGE threshold of the DC bus
    # cycle-by-cycle overcurrent trip of the bridge (not in the paper; a real inverter's
    # comparator): a period starting with any |phase current| above it has all gates off
    # (FAULT_OVERCURRENT). 150 A = 1.25 x the controller's current_limit_a (120 A), well above
    # its largest command + hysteresis band (121.5 A), so closed-loop operation never trips.
    overcurrent_trip_a: float = 150.0

    def validate(self) -> None:
        require_positive(self, "pole_pairs", "ke_v_per_rpm", "inductance_h", "r_phase_ohm", "overvoltage_v",
                         "overcurrent_trip_a")
        if not 0.0 <= self.inductance_variation < 0.9:
            raise ValueError(f"inductance_variation must be in [0, 0.9), got {self.inductance_variation!r}")
        if not 0.0 < self.emf_sine_amplitude <= 2.0:
            raise ValueError(f"emf_sine_amplitude must be in (0, 2], got {self.emf_sine_amplitude!r}")
        _check_table(self.emf_shape_speed_rpm, self.emf_trap_weight, "emf_shape_speed_rpm", "emf_trap_weight", 0.0, 1.0)

    @property
    def kph_v_s_per_rad(self) -> float:
        """Phase back-EMF constant (flat top), mechanical rad/s."""
        return self.ke_v_per_rpm * RPM_PER_RAD_S / 2.0

    @property
    def kt_nm_per_a(self) -> float:
        """Torque constant with two phases conducting (= ke in V s/rad, line-to-line)."""
        return self.ke_v_per_rpm * RPM_PER_RAD_S


# The state of charge past which a pack taking charge is an overvoltage fault (bike_plant.bldc,
# FAULT_OVERVOLTAGE: a real pack's BMS opens). BatteryParams keeps S0's switch-on voltage at or
# below the pack's OCV at this SOC, so regeneration alone never charges a pack past it.
SOC_OVERCHARGE = 1.005
# The state of charge at and below which either machine's pack is empty: FAULT_PACK_EMPTY in its
# PlantState (bike_plant.sim, bike_plant.spmsm), and the session's EmptyPackGuard
# (bike_controller.session_control) holds assist at zero, as a BMS's undervoltage cut-off would.
# The plant's pack is a model that books energy without bounds (the SPMSM's an ideal source): it
# flags the empty pack, the session keeps assist from it; braking charges it and clears the flag
PACK_EMPTY_SOC = 0.0


@dataclass
class BatteryParams:
    """48 V pack (13S li-ion) + S0 brake resistor (paper 000, Fig. 2, dynamic braking)."""
    v_empty_v: float = 42.0
    v_full_v: float = 54.6
    r_internal_ohm: float = 0.15
    capacity_ah: float = 10.0
    soc0: float = 0.7
    # sized for the regenerated peak (about 1 kW at Command 1, 3000-4500 rpm): 54.6 V^2 / 2.5 ohm = 1.19 kW.
    # The 4 ohm once here took 0.75 kW at most, and a full pack braked at Command 1 at 3000 rpm took the
    # other ~0.2 kW: SOC 1.005, the overcharge fault, within a minute
    r_brake_ohm: float = 2.5
    s0_on_v: float = 54.65        # S0 chopper: on above the full pack's OCV (v_full_v) ...
    s0_off_v: float = 54.62       # ... holds the bus here, above v_full_v, so it never takes the pack's energy
    s0_filter_s: float = 1.0e-3   # RC filter of the S0 comparator input (no bus capacitor in the model)

    def validate(self) -> None:
        require_positive(self, "v_empty_v", "v_full_v", "r_internal_ohm", "capacity_ah", "r_brake_ohm",
                         "s0_on_v", "s0_off_v", "s0_filter_s")
        if self.v_full_v <= self.v_empty_v:
            raise ValueError("v_full_v must be > v_empty_v")
        if not 0.0 <= self.soc0 <= 1.0:
            raise ValueError(f"soc0 must be in [0, 1], got {self.soc0!r}")
        if self.s0_off_v >= self.s0_on_v:
            raise ValueError("s0_off_v must be < s0_on_v (hysteresis)")
        v_top = self.ocv_v(SOC_OVERCHARGE)
        if not self.v_full_v < self.s0_off_v < self.s0_on_v <= v_top:
            # S0 open below the full pack's OCV (54.0 V on the 54.6 V pack): with the pack above
            # SOC 0.95 S0 stayed on and the pack fed the resistor (27.6 J in 0.5 s at SOC 0.99,
            # Command 0.3); S0 closed only above the OCV at SOC_OVERCHARGE: a full pack charged on
            # past it (SOC 1.2 after 10 s of the demo on a 36 V pack with the 48 V pack's 54.6 V)
            raise ValueError(f"s0_off_v and s0_on_v (the brake resistor's switch-off and -on voltages) must lie "
                             f"above v_full_v, the full pack's open-circuit voltage, and at most its OCV at SOC "
                             f"{SOC_OVERCHARGE:g}: {self.v_full_v:g} < s0_off_v < s0_on_v <= {v_top:.5g} V, got "
                             f"s0_off_v {self.s0_off_v:g} V, s0_on_v {self.s0_on_v:g} V: below it S0 drains a nearly "
                             f"full pack into the resistor, above it a full pack charges on past full")

    def ocv_v(self, soc: float) -> float:
        """Open-circuit voltage [V] at state of charge soc (linear, as bike_plant.bldc.battery_voc)."""
        return self.v_empty_v + (self.v_full_v - self.v_empty_v) * soc


# Upper bounds of a friction figure (config, calibration file, spin-down): far above any bike's
# (a spin-down measures B ~1e-4..1e-2 N m s/rad, Tc ~0..0.5 N m at the motor shaft), low enough
# that B w and the virtual bike's figures stay finite (B = 1e300 rode to a distance of 5e202 m
# and an infinite rms without a word).
FRICTION_NMS_MAX = 1.0
DRY_FRICTION_NM_MAX = 10.0


def friction_problem(name: str, value) -> str | None:
    """Why a friction figure (``friction_nms`` [N m s/rad] or ``dry_friction_nm`` [N m]) is
    refused, or None: a finite number in [0, FRICTION_NMS_MAX / DRY_FRICTION_NM_MAX]."""
    top = DRY_FRICTION_NM_MAX if name.startswith("dry") else FRICTION_NMS_MAX
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value)
                                                                              and 0.0 <= value <= top):
        return f"{name} must be a number in [0, {top:g}], got {value!r}"
    return None


@dataclass
class MechParams:
    """Shaft: motor-side inertia (flywheel reflected) and viscous friction."""
    inertia_kgm2: float = 0.01
    friction_nms: float = 1.0e-4
    speed0_rpm: float = 0.0

    def validate(self) -> None:
        require_positive(self, "inertia_kgm2")
        problem = friction_problem("friction_nms", self.friction_nms)
        if problem:
            raise ValueError(problem)


LOAD_KINDS = ("prime_mover", "rider", "none")


@dataclass
class RiderParams:
    """The rider of either machine's ``load`` section (bike_plant.mechanics): crank torque
    T = effort * T0 (1 - cadence/cadence_max) (1 + 0.5 cos(2 crank)), two peaks per crank
    turn, through the load's gear ratio motor/crank; effort from a PI on cadence. His heart
    (bike_plant.heart): resting and maximal rate, steady-state gain, time constant and drift."""
    rider_t0_nm: float = 120.0
    rider_cadence_max_rpm: float = 160.0
    rider_target_cadence_rpm: float = 80.0
    rider_kp: float = 0.57       # mechanics.rider_pi_gains for the BLDC bike's drivetrain
    rider_ki: float = 0.82
    rider_effort0: float = 0.3
    rider_rest_hr_bpm: float = 60.0
    rider_max_hr_bpm: float = 185.0
    rider_hr_gain_bpm_per_w: float = 0.5
    rider_hr_time_constant_s: float = 68.7
    rider_hr_drift_fraction: float = 0.25
    rider_hr_drift_time_constant_s: float = 1800.0

    def validate_rider(self) -> None:
        require_positive(self, "rider_t0_nm", "rider_cadence_max_rpm")
        if not 0.0 < self.rider_target_cadence_rpm < self.rider_cadence_max_rpm:
            # beyond it the rider's torque line is negative (mechanics.rider_pi_gains clamped it)
            raise ValueError(f"rider_target_cadence_rpm must be in (0, rider_cadence_max_rpm = "
                             f"{self.rider_cadence_max_rpm:g}), got {self.rider_target_cadence_rpm!r}")
        if not 0.0 <= self.rider_effort0 <= 1.0:
            raise ValueError("rider_effort0 must be in [0, 1]")
        try:
            self.heart_params().validate()
        except ValueError as exc:
            raise ValueError(f"rider heart: {exc} (load.rider_rest_hr_bpm, rider_max_hr_bpm, "
                             "rider_hr_gain_bpm_per_w, rider_hr_time_constant_s, rider_hr_drift_fraction, "
                             "rider_hr_drift_time_constant_s)") from None

    def heart_params(self) -> HeartParams:
        return HeartParams(rest_bpm=self.rider_rest_hr_bpm, max_bpm=self.rider_max_hr_bpm,
                           gain_bpm_per_w=self.rider_hr_gain_bpm_per_w,
                           time_constant_s=self.rider_hr_time_constant_s,
                           drift_fraction=self.rider_hr_drift_fraction,
                           drift_time_constant_s=self.rider_hr_drift_time_constant_s)

    def rider_fields(self) -> dict:
        """The rider's fields by name (to carry the rider to another load dataclass)."""
        return {f.name: getattr(self, f.name) for f in fields(RiderParams)}


@dataclass
class ShaftLoadParams(RiderParams):
    """What both machines' ``load`` sections share: the rider, the gear motor/crank and the
    prime mover (speed held exactly at speed_rpm, optionally a schedule of (time_s,
    speed_rpm) steps). The defaults of speed and gear are the BLDC's; SpmsmLoadParams redeclares them."""
    speed_rpm: float = 3000.0
    schedule_time_s: list = field(default_factory=list)
    schedule_speed_rpm: list = field(default_factory=list)
    gear_ratio: float = 35.0

    def validate_shaft_load(self) -> None:
        for name in ("schedule_time_s", "schedule_speed_rpm"):
            if any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in getattr(self, name)):
                raise ValueError(f"{name} entries must be numbers")
        if len(self.schedule_time_s) != len(self.schedule_speed_rpm):
            raise ValueError("schedule_time_s and schedule_speed_rpm must have the same length")
        if list(self.schedule_time_s) != sorted(self.schedule_time_s):
            raise ValueError("schedule_time_s must be increasing")
        require_positive(self, "gear_ratio")
        self.validate_rider()


@dataclass
class LoadParams(ShaftLoadParams):
    """External load on the shaft.

    prime_mover: speed held exactly (paper 000, section 5: 'a prime mover is used to
    rotate the BLPMEM at a fixed speed'), optionally a schedule of (time_s, speed_rpm) steps.
    rider: :class:`RiderParams` through gear ratio motor/crank.
    """
    kind: str = "prime_mover"

    def validate(self) -> None:
        if self.kind not in LOAD_KINDS:
            raise ValueError(f"kind must be one of {', '.join(LOAD_KINDS)}, got {self.kind!r}")
        self.validate_shaft_load()


# Rider presets (research notes trainers.md section 4: linear torque-cadence model,
# T(c) = T0 (1 - c / Cmax), Pmax = T0 wmax / 4 at c = Cmax / 2). ``load.rider_preset``
# sets these keys (they win over the same keys in the section); ``custom`` (default) uses
# the section's own values.
RIDER_PRESETS = {
    # about 500 W peak (T0 120 N m, Cmax 160 rpm), holds 80 rpm: a recreational rider; his heart:
    # bike_plant.heart.HeartParams' defaults
    "recreational": {"rider_t0_nm": 120.0, "rider_cadence_max_rpm": 160.0, "rider_target_cadence_rpm": 80.0,
                     "rider_rest_hr_bpm": 60.0, "rider_max_hr_bpm": 185.0, "rider_hr_gain_bpm_per_w": 0.5,
                     "rider_hr_drift_fraction": 0.25},
    # about 1200 W peak (T0 200 N m, Cmax 220 rpm; sprinters reach 1600 W), holds 90 rpm; his heart:
    # rests at 50, 90 % of 190 at an FTP of 300 W -> (171 - 50) / 300 = 0.4 bpm/W; half the
    # recreational rider's drift (a good aerobic base: bike_plant.heart)
    "trained": {"rider_t0_nm": 200.0, "rider_cadence_max_rpm": 220.0, "rider_target_cadence_rpm": 90.0,
                "rider_rest_hr_bpm": 50.0, "rider_max_hr_bpm": 190.0, "rider_hr_gain_bpm_per_w": 0.4,
                "rider_hr_drift_fraction": 0.12},
}


def rider_preset_overrides(load: Mapping) -> str | None:
    """What the ``load`` section's rider_preset replaces: its own rider values that differ
    from the preset's ("rider_t0_nm 150 -> 120, ..."), or None. The plant node warns with it:
    a value edited beside a preset was otherwise dropped without a word."""
    preset = (load or {}).get("rider_preset", "custom")
    if not isinstance(preset, str) or preset not in RIDER_PRESETS:
        return None
    changed = [f"{key} {load[key]} -> {value:g}" for key, value in RIDER_PRESETS[preset].items()
               if key in load and load[key] != value]
    if not changed:
        return None
    return (f"load.rider_preset {preset} replaces the section's {', '.join(changed)} "
            "(rider_preset: custom rides the section's own)")


def load_section_with_preset(load: Mapping, path=None) -> dict:
    """The ``load`` section with ``rider_preset`` (recreational | trained | custom) applied."""
    load = dict(load or {})
    preset = load.pop("rider_preset", "custom")
    if preset == "custom":
        return load
    if not isinstance(preset, str) or preset not in RIDER_PRESETS:      # a list or map is unhashable
        raise ConfigError(f"unknown rider_preset {preset!r} (custom | {' | '.join(RIDER_PRESETS)})", path,
                          "load.rider_preset")
    load.update(RIDER_PRESETS[preset])
    return load


@dataclass
class HallParams:
    """Hall sensors + capture timer (paper 000, Eq. 1, Fig. 8).

    timer_hz = 1.25 MHz: the TMS320F240's 20 MHz clock with a /16 prescaler. At 5400 rpm
    an edge interval is 1157 counts (0.09 % speed resolution), and a 16-bit capture
    register still covers edge intervals down to 95 rpm.
    """
    timer_hz: float = 1.25e6

    def validate(self) -> None:
        require_positive(self, "timer_hz")


@dataclass
class PlantParams:
    bldc: BldcParams = field(default_factory=BldcParams)
    battery: BatteryParams = field(default_factory=BatteryParams)
    mech: MechParams = field(default_factory=MechParams)
    load: LoadParams = field(default_factory=LoadParams)
    hall: HallParams = field(default_factory=HallParams)
    control_period_s: float = 5.0e-5


def _check_table(xs, ys, xname, yname, lo, hi):
    if len(xs) != len(ys) or len(xs) == 0:
        raise ValueError(f"{xname} and {yname} must be non-empty and of equal length")
    for v in list(xs) + list(ys):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(f"{xname}/{yname} entries must be finite numbers")
    if any(b <= a for a, b in zip(xs, xs[1:])):
        raise ValueError(f"{xname} must be strictly increasing")
    if any(not lo <= y <= hi for y in ys):
        raise ValueError(f"{yname} entries must be in [{lo}, {hi}]")


def plant_params_from_config(cfg: dict) -> PlantParams:
    """The plant's (authoritative) parameters from a loaded config dict."""
    path = cfg.get("_config_path")
    period = cfg.get("control_period_s", 5.0e-5)
    if isinstance(period, bool) or not isinstance(period, (int, float)) or not (0 < period < 1e-2):
        raise ConfigError(f"must be a number in (0, 0.01), got {period!r}", path, "control_period_s")
    params = PlantParams(
        bldc=build_dataclass(BldcParams, section(cfg, "bldc", path), "bldc", path),
        battery=build_dataclass(BatteryParams, _battery_values(cfg, path), "battery", path),
        mech=build_dataclass(MechParams, section(cfg, "mechanics", path), "mechanics", path),
        load=build_dataclass(LoadParams, load_section_with_preset(section(cfg, "load", path), path), "load", path),
        hall=build_dataclass(HallParams, section(cfg, "hall", path), "hall", path),
        control_period_s=float(period),
    )
    if params.hall.timer_hz * params.control_period_s < 1.0:
        # the controller recovers the period index from the timer count of a PlantState
        raise ConfigError(f"the capture timer must tick at least once per control period "
                          f"(timer_hz * control_period_s = {params.hall.timer_hz * params.control_period_s:g})",
                          path, "hall.timer_hz")
    bus_problem = overvoltage_problem(params)
    if bus_problem:
        raise ConfigError(bus_problem, path, "bldc.overvoltage_v")
    emf_problem = riding_emf_problem(params)
    if emf_problem:
        raise ConfigError(emf_problem, path, "bldc.ke_v_per_rpm")
    reverse = reverse_speed_problem(params)
    if reverse:
        raise ConfigError(reverse[1], path, reverse[0])
    return params


def overvoltage_problem(p: PlantParams) -> str | None:
    """Why bldc.overvoltage_v does not fit the pack (a message), or None. The DC bus is the pack
    (its OCV plus Rb i; no link voltage of its own, unlike the SPMSM's inverter.dc_link_v), and
    while braking S0's chopper holds it near battery.s0_on_v, the top of its healthy range: a
    threshold at or below it set FAULT_OVERVOLTAGE on a healthy bus (overvoltage_v 50 V on the
    48 V pack: faulted at rest, the bus at 50.8 V at SOC 0.7)."""
    b, bt = p.bldc, p.battery
    if b.overvoltage_v > bt.s0_on_v:
        return None
    return (f"{b.overvoltage_v:g} V is at or below battery.s0_on_v {bt.s0_on_v:g} V: the DC bus "
            f"is the pack ({bt.v_empty_v:g}..{bt.v_full_v:g} V, battery.v_empty_v..v_full_v), held up to s0_on_v "
            f"by the brake resistor's chopper while braking, so the fault would flag a healthy bus; give an "
            f"overvoltage_v above {bt.s0_on_v:g} V")


def reverse_speed_problem(p: PlantParams) -> tuple[str, str] | None:
    """(key, message) of a speed the load would turn the shaft backwards at, or None. The
    controller commutates for forward rotation only (paper 000 brakes in quadrant II and
    assists in quadrant I of Fig. 3; reverse braking, quadrant IV, is not implemented):
    turned backwards, the phase its generating pattern chops is at -E, no current builds and
    nothing brakes, while the status reports the torque commanded (a prime mover at -3000 rpm:
    0 N m and 0 A for 1.47 N m and 30 A asked)."""
    found = negative_config_speed(p.mech, p.load)
    if found is None:
        return None
    key, rpm = found
    return key, (f"{rpm:g} rpm turns the BLDC bike backwards: its controller brakes and assists forward "
                 "rotation only (paper 000, quadrants II and I of Fig. 3), backwards it would brake nothing "
                 "under any Command; give a speed >= 0")


def negative_config_speed(mech: MechParams, load) -> tuple[str, float] | None:
    """(key, r/min) of the first configured shaft speed below zero (the start speed, a prime
    mover's speed and schedule), or None: either machine refuses it (reverse_speed_problem,
    bike_plant.spmsm_params.plant_params_from_config)."""
    speeds = [("mechanics.speed0_rpm", mech.speed0_rpm)]
    if load.kind == "prime_mover":
        speeds += [("load.speed_rpm", load.speed_rpm)] + [
            ("load.schedule_speed_rpm", float(v)) for v in load.schedule_speed_rpm]
    for key, rpm in speeds:
        if rpm < 0.0:
            return key, rpm
    return None


def emf_speed_limit_rpm(p: PlantParams) -> float:
    """The motor speed whose line-to-line back-EMF reaches the empty pack's voltage: above it
    the bridge's diodes rectify whatever the gates do (no Command controls the brake)."""
    return p.battery.v_empty_v / p.bldc.ke_v_per_rpm


def riding_emf_problem(p: PlantParams) -> str | None:
    """The line-to-line back-EMF at the speed the load rides (the rider's target cadence x gear,
    the prime mover's speeds, the start speed) against the empty pack's voltage, or None. Above
    the bus voltage the bridge's diodes rectify whatever the gates do: a braking torque no
    Command controls (4 x the default ke on the 48 V pack: 10 N m at 2800 rpm for 1.2 N m
    asked, the demo's cadence 69 rpm, no fault and 0 % saturation in the summary)."""
    load = p.load
    speeds = [("mechanics.speed0_rpm", abs(p.mech.speed0_rpm))]
    if load.kind == "rider":
        speeds.append(("load.rider_target_cadence_rpm x load.gear_ratio",
                       load.rider_target_cadence_rpm * load.gear_ratio))
    elif load.kind == "prime_mover":
        speeds += [("load.speed_rpm", abs(load.speed_rpm))] + [
            ("load.schedule_speed_rpm", abs(float(v))) for v in load.schedule_speed_rpm]
    name, top = max(speeds, key=lambda item: item[1])
    if top < emf_speed_limit_rpm(p):
        return None
    e_ll = p.bldc.ke_v_per_rpm * top
    return (f"{p.bldc.ke_v_per_rpm:g} V/rpm gives a line-to-line back-EMF of {e_ll:.1f} V at {top:g} motor rpm "
            f"({name}), at or above the empty pack's {p.battery.v_empty_v:g} V (battery.v_empty_v): the bridge "
            f"diodes would rectify it and brake beyond any Command. The machine must stay below "
            f"{emf_speed_limit_rpm(p):.0f} rpm on this pack: a lower ke, a smaller "
            "load.gear_ratio or a higher-voltage pack")


def _battery_values(cfg, path):
    values = dict(section(cfg, "battery", path))
    values.update(section(cfg, "brake_resistor", path))  # DESIGN.md allows a separate section
    return values


def nominal_params_from_config(cfg: dict) -> PlantParams:
    """The controller's copy of the model: non-idealities off unless ``controller.model: actual``."""
    params = plant_params_from_config(cfg)
    ctrl = section(cfg, "controller", cfg.get("_config_path"))
    model = ctrl.get("model", "nominal")
    if model not in ("nominal", "actual"):
        raise ConfigError(f"must be 'nominal' or 'actual', got {model!r}", cfg.get("_config_path"), "controller.model")
    if model == "actual":
        return params
    params.bldc = dataclasses.replace(params.bldc, inductance_variation=0.0, emf_nonideal=False)
    return params


# ---------------------------------------------------------------------------------------
# flat parameter vector for the kernels
P_POLE_PAIRS = 0
P_KPH = 1
P_L0 = 2
P_R = 3
P_EPS = 4
P_EMF_NONIDEAL = 5
P_SINE_AMP = 6
P_DT = 7
P_V_EMPTY = 8
P_V_FULL = 9
P_R_BATT = 10
P_CAP_AS = 11
P_R_BRAKE = 12
P_S0_ON = 13
P_S0_OFF = 14
P_S0_ALPHA = 15
P_J = 16
P_B = 17
P_LOAD_KIND = 18         # 0 prime mover, 1 rider, 2 none
P_GEAR = 19
P_RIDER_T0 = 20
P_RIDER_CADMAX = 21      # rad/s crank
P_RIDER_TARGET = 22      # rad/s crank
P_RIDER_KP = 23
P_RIDER_KI = 24
P_TIMER_HZ = 25
P_OVERVOLTAGE = 26
P_NTAB = 27              # number of EMF shape table points (max 8)
P_TAB_X = 28             # 8 speeds [rad/s]
P_TAB_Y = 36             # 8 weights
P_OC_TRIP = 44           # overcurrent trip level [A]
P_SIZE = 45
MAX_TABLE = 8


def pack_params(p: PlantParams) -> np.ndarray:
    """PlantParams -> float64 vector for the numba kernels (layout P_* above)."""
    v = np.zeros(P_SIZE)
    b = p.bldc
    v[P_POLE_PAIRS] = b.pole_pairs
    v[P_KPH] = b.kph_v_s_per_rad
    v[P_L0] = b.inductance_h
    v[P_R] = b.r_phase_ohm
    v[P_EPS] = b.inductance_variation
    v[P_EMF_NONIDEAL] = 1.0 if b.emf_nonideal else 0.0
    v[P_SINE_AMP] = b.emf_sine_amplitude
    v[P_DT] = p.control_period_s
    bt = p.battery
    v[P_V_EMPTY] = bt.v_empty_v
    v[P_V_FULL] = bt.v_full_v
    v[P_R_BATT] = bt.r_internal_ohm
    v[P_CAP_AS] = bt.capacity_ah * 3600.0
    v[P_R_BRAKE] = bt.r_brake_ohm
    v[P_S0_ON] = bt.s0_on_v
    v[P_S0_OFF] = bt.s0_off_v
    v[P_S0_ALPHA] = 1.0 - math.exp(-p.control_period_s / bt.s0_filter_s)
    v[P_J] = p.mech.inertia_kgm2
    v[P_B] = p.mech.friction_nms
    v[P_LOAD_KIND] = LOAD_KINDS.index(p.load.kind)
    v[P_GEAR] = p.load.gear_ratio
    v[P_RIDER_T0] = p.load.rider_t0_nm
    v[P_RIDER_CADMAX] = p.load.rider_cadence_max_rpm / RPM_PER_RAD_S
    v[P_RIDER_TARGET] = p.load.rider_target_cadence_rpm / RPM_PER_RAD_S
    v[P_RIDER_KP] = p.load.rider_kp
    v[P_RIDER_KI] = p.load.rider_ki
    v[P_TIMER_HZ] = p.hall.timer_hz
    v[P_OVERVOLTAGE] = b.overvoltage_v
    v[P_OC_TRIP] = b.overcurrent_trip_a
    xs, ys = list(b.emf_shape_speed_rpm), list(b.emf_trap_weight)
    if len(xs) > MAX_TABLE:
        raise ConfigError(f"at most {MAX_TABLE} points", None, "bldc.emf_shape_speed_rpm")
    v[P_NTAB] = len(xs)
    for k, (x, y) in enumerate(zip(xs, ys)):
        v[P_TAB_X + k] = x / RPM_PER_RAD_S
        v[P_TAB_Y + k] = y
    return v
