"""Parameters of the SPMSM bike (paper 001, section 6) and their loaders from a config:
the machine, inverter, regeneration path, battery, encoder, shaft load. Plain dataclasses, no
numba: what reads a config without simulating (./bike run's checks, the session and FTMS
nodes' mode ranges) loads these without the kernels of :mod:`bike_plant.spmsm`, which
re-exports every name here."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from .config import ConfigError, build_dataclass, require_positive, section
from .params import (LoadParams, MechParams, ShaftLoadParams, friction_problem, load_section_with_preset,
                     negative_config_speed)

MAX_DYNO_POINTS = 16


# =======================================================================================
# parameters
# =======================================================================================
@dataclass
class SpmsmParams:
    """Outer-rotor surface PMSM, 36 slots / 12 poles (paper 001, section 6).

    flux_linkage_vs is the PEAK phase flux linkage [V s/rad electrical] of the amplitude-
    invariant dq model (see the module docstring); inductance_h is Ld = Lq.
    The *_scale factors make the simulated machine differ from the controller's nominal
    model (paper 001, Fig. 23: parameter variation); the nominal copy has them at 1.
    """
    pole_pairs: int = 6
    rs_ohm: float = 6.84
    inductance_h: float = 9.8e-3
    flux_linkage_vs: float = 0.122
    rated_speed_rpm: float = 200.0
    rs_scale: float = 1.0
    inductance_scale: float = 1.0
    flux_scale: float = 1.0
    # non-idealities of the real machine (module docstring "Non-idealities"); 0 = ideal
    emf_harmonic_5: float = 0.0        # 5th harmonic of the phase back-EMF / fundamental
    emf_harmonic_7: float = 0.0        # 7th harmonic / fundamental
    emf_phase_5_deg: float = 0.0       # e_a ~ sin(th) + k5 sin(5 th + phi5) + k7 sin(7 th + phi7)
    emf_phase_7_deg: float = 0.0
    cogging_torque_nm: float = 0.0     # peak cogging torque
    cogging_per_rev: int = 36          # cogging periods per mechanical turn: LCM(36 slots, 12 poles)
    cogging_phase_deg: float = 0.0
    dry_friction_nm: float = 0.0       # Coulomb friction (bearings, belt, coupled brake's idle drag)
    dry_friction_speed_rpm: float = 1.0  # ... smoothed as Tc tanh(w / w_s) below this speed

    def validate(self) -> None:
        require_positive(self, "pole_pairs", "rs_ohm", "inductance_h", "flux_linkage_vs", "rated_speed_rpm",
                         "rs_scale", "inductance_scale", "flux_scale", "cogging_per_rev")
        require_positive(self, "dry_friction_speed_rpm")
        for name in ("emf_harmonic_5", "emf_harmonic_7", "cogging_torque_nm"):
            if not 0.0 <= getattr(self, name) <= (0.5 if name.startswith("emf") else 10.0):
                raise ValueError(f"{name} must be in [0, {0.5 if name.startswith('emf') else 10.0}], "
                                 f"got {getattr(self, name)!r}")
        problem = friction_problem("dry_friction_nm", self.dry_friction_nm)   # the bound of every friction figure
        if problem:
            raise ValueError(problem)

    @property
    def torque_constant_nm_per_a(self) -> float:
        """Kt = 1.5 pp lambda (Eq. 8, Ld = Lq)."""
        return 1.5 * self.pole_pairs * self.flux_linkage_vs

    @property
    def characteristic_current_a(self) -> float:
        """lambda / Ld (paper 001, Eq. 72): the d current that cancels the magnet flux."""
        return self.flux_linkage_vs / self.inductance_h


INVERTER_MODELS = ("average", "switching")
MODULATIONS = ("svpwm", "sine_triangle")
# none: the controller keeps the voltage vector in the modulator's linear range (Vdc/sqrt(3)
# SVPWM, Vdc/2 sine-triangle). clamp: the voltage limit is the six-step fundamental 2 Vdc/pi
# (the most a bridge can make); a vector beyond the linear range is clipped per phase by the
# duty clamp (0 <= d <= 1), which adds 5th / 7th (6k +- 1) voltage harmonics. Used by the
# flux-weakening drives that trade waveform quality for voltage (Holtz, "Pulsewidth
# modulation - a survey", overmodulation; Kwon & Sul, flux weakening into overmodulation). The clamp of a
# min-max-centred reference delivers less than it is asked beyond the linear range: 98.7 % of a 0.6 Vdc
# vector, 95 % of 2 Vdc/pi (14.5 V of 15.3 at 24 V); the controller counts the vector it asked as applied,
# and its current loops and slow voltage feedback (spmsm_control.speed_loop) take up the rest.
OVERMODULATIONS = ("none", "clamp")


@dataclass
class InverterParams:
    """Two-level inverter on the 24 V DC link (the paper's DC supply / battery)."""
    dc_link_v: float = 24.0
    model: str = "average"             # average | switching
    modulation: str = "svpwm"          # svpwm (|v| <= Vdc/sqrt(3)) | sine_triangle (|v| <= Vdc/2)
    overmodulation: str = "none"       # none (linear range only) | clamp (up to 2 Vdc/pi, per-phase duty clamp)
    carrier_multiple: int = 1          # carrier periods per control period (1: 10 kHz carrier)
    dead_time_s: float = 0.0           # switching model only
    diode_drop_v: float = 0.7          # freewheel diodes (gates off)

    def validate(self) -> None:
        require_positive(self, "dc_link_v", "carrier_multiple")
        if self.carrier_multiple > 8:
            raise ValueError(f"carrier_multiple must be <= 8, got {self.carrier_multiple!r}")
        if self.model not in INVERTER_MODELS:
            raise ValueError(f"model must be one of {', '.join(INVERTER_MODELS)}, got {self.model!r}")
        if self.modulation not in MODULATIONS:
            raise ValueError(f"modulation must be one of {', '.join(MODULATIONS)}, got {self.modulation!r}")
        if self.overmodulation not in OVERMODULATIONS:
            raise ValueError(f"overmodulation must be one of {', '.join(OVERMODULATIONS)}, "
                             f"got {self.overmodulation!r}")
        if not 0.0 <= self.dead_time_s < 1e-5:
            raise ValueError(f"dead_time_s must be in [0, 10 us), got {self.dead_time_s!r}")
        if self.diode_drop_v < 0:
            raise ValueError("diode_drop_v must be >= 0")


@dataclass
class RegenParams:
    """Relay + 3-phase diode rectifier + buck (~25 V) + charger (paper 001, Fig. 2/8, 17/18)."""
    buck_output_v: float = 25.0
    link_max_v: float = 60.0           # DC-link (buck input) limit: buck duty >= buck_output_v / link_max_v
    diode_drop_v: float = 0.7
    buck_efficiency: float = 0.95
    charger_efficiency: float = 0.92
    relay_dead_s: float = 2.0e-4       # both paths open; >= one control period
    drain_timeout_s: float = 5.0e-3    # wait this long for zero current before opening anyway
    relay_open_current_a: float = 0.02  # the relay opens once |i| is below this

    def validate(self) -> None:
        require_positive(self, "buck_output_v", "link_max_v", "buck_efficiency", "charger_efficiency",
                         "relay_dead_s", "drain_timeout_s", "relay_open_current_a")
        if self.link_max_v <= self.buck_output_v:
            raise ValueError("link_max_v must be > buck_output_v (a buck steps down)")
        for name in ("buck_efficiency", "charger_efficiency"):
            if getattr(self, name) > 1.0:
                raise ValueError(f"{name} must be in (0, 1]")
        if self.diode_drop_v < 0:
            raise ValueError("diode_drop_v must be >= 0")


@dataclass
class SpmsmBatteryParams:
    """24 V battery set: feeds the inverter, takes the charger's output (paper 001, section 6)."""
    nominal_v: float = 24.0
    capacity_ah: float = 10.0
    soc0: float = 0.7
    dump_above_soc: float = 0.98       # charger off above this: regenerated power goes to the dump resistor

    def validate(self) -> None:
        require_positive(self, "nominal_v", "capacity_ah")
        if not 0.0 <= self.soc0 <= 1.0:
            raise ValueError(f"soc0 must be in [0, 1], got {self.soc0!r}")
        if not 0.0 < self.dump_above_soc <= 1.0:
            raise ValueError("dump_above_soc must be in (0, 1]")


@dataclass
class EncoderParams:
    """Incremental encoder, 2500 pulses/rev (paper 001, section 6), x4 quadrature decoding
    (the F28035 eQEP counts every edge of A and B: 10000 counts/rev); a capture timer stamps
    the last edge for the M/T speed estimate (60 MHz SYSCLK / 32 = 1.875 MHz)."""
    pulses_per_rev: int = 2500
    quadrature: int = 4
    capture_timer_hz: float = 1.875e6

    def validate(self) -> None:
        require_positive(self, "pulses_per_rev", "capture_timer_hz")
        if self.quadrature not in (1, 2, 4):
            raise ValueError(f"quadrature must be 1, 2 or 4, got {self.quadrature!r}")

    @property
    def counts_per_rev(self) -> int:
        return self.pulses_per_rev * self.quadrature


SPMSM_LOAD_KINDS = ("dynamometer", "prime_mover", "rider", "none")
DYNO_MODES = ("brake", "drive")


@dataclass
class SpmsmLoadParams(ShaftLoadParams):
    """External load on the shaft (paper 001, Fig. 9b: dynamometer; ARCHITECTURE.md loads).

    dynamometer: TL(t) piecewise constant, TL = dyno_torque_nm[k] from dyno_time_s[k] on
    (Eq. 3 sign: positive opposes positive rotation). ``dyno_mode`` brake (default): the paper's
    magnetic-powder brake (section 7), passive: TL tanh(w / w_s) opposes the rotation and holds a
    stopped shaft against up to TL (w_s = spmsm.dry_friction_speed_rpm; TL exactly beyond 19 w_s),
    so TL >= 0. drive: a torque source whatever the speed (as before; 1 N m turned a free shaft at
    rest backwards), a negative TL drives. ./bike paper's runs apply TL through their load_fn (a
    torque source, at speed only). prime_mover: speed held at speed_rpm
    (optional schedule). rider: the torque-cadence rider of bike_plant.mechanics
    (:class:`bike_plant.params.RiderParams`) through the gear motor/crank (the outer rotor
    turns ~2.5x the crank). none: free shaft.
    """
    kind: str = "dynamometer"
    dyno_mode: str = "brake"           # brake (passive, TL >= 0) | drive (a torque source, any sign)
    dyno_time_s: list = field(default_factory=lambda: [0.0])
    dyno_torque_nm: list = field(default_factory=lambda: [0.0])
    speed_rpm: float = 200.0
    gear_ratio: float = 2.5

    def validate(self) -> None:
        if self.kind not in SPMSM_LOAD_KINDS:
            raise ValueError(f"kind must be one of {', '.join(SPMSM_LOAD_KINDS)}, got {self.kind!r}")
        for name in ("dyno_time_s", "dyno_torque_nm"):
            if any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in getattr(self, name)):
                raise ValueError(f"{name} entries must be numbers")
        if len(self.dyno_time_s) != len(self.dyno_torque_nm) or not self.dyno_time_s:
            raise ValueError("dyno_time_s and dyno_torque_nm must be non-empty and of equal length")
        if len(self.dyno_time_s) > MAX_DYNO_POINTS:
            raise ValueError(f"at most {MAX_DYNO_POINTS} dynamometer profile points")
        if any(b <= a for a, b in zip(self.dyno_time_s, self.dyno_time_s[1:])):
            raise ValueError("dyno_time_s must be strictly increasing")
        if self.dyno_mode not in DYNO_MODES:
            raise ValueError(f"dyno_mode must be one of {', '.join(DYNO_MODES)}, got {self.dyno_mode!r}")
        if self.kind == "dynamometer" and self.dyno_mode == "brake" and min(self.dyno_torque_nm) < 0.0:
            raise ValueError(f"dyno_torque_nm {min(self.dyno_torque_nm):g} N m: a brake (dyno_mode brake) only "
                             "opposes the rotation; a negative torque drives the shaft: dyno_mode drive")
        self.validate_shaft_load()

    def rider_load_params(self) -> LoadParams:
        """The same rider as bike_plant.params.LoadParams (for bike_plant.mechanics)."""
        return LoadParams(kind="rider", gear_ratio=self.gear_ratio, **self.rider_fields())


def _default_mech() -> MechParams:
    return MechParams(inertia_kgm2=0.01, friction_nms=0.005, speed0_rpm=0.0)


@dataclass
class SpmsmPlantParams:
    spmsm: SpmsmParams = field(default_factory=SpmsmParams)
    inverter: InverterParams = field(default_factory=InverterParams)
    regen: RegenParams = field(default_factory=RegenParams)
    battery: SpmsmBatteryParams = field(default_factory=SpmsmBatteryParams)
    mech: MechParams = field(default_factory=_default_mech)
    load: SpmsmLoadParams = field(default_factory=SpmsmLoadParams)
    encoder: EncoderParams = field(default_factory=EncoderParams)
    control_period_s: float = 1.0e-4


# The inverter's DC link is the battery set's terminals (paper 001: one 24 V set feeds the inverter when
# motoring and takes the rectifier + buck (~25 V) + charger's output when generating), so
# inverter.dc_link_v must be a voltage that set has: within the span of a "24 V" set from empty to
# charging, 21-28.8 V (lead-acid, 1.75-2.4 V per 2 V cell), as a share of battery.nominal_v
LINK_PER_NOMINAL = (0.875, 1.2)


def _set_span_problem(volts: float, nominal_v: float, why: str, note: str = "") -> str | None:
    """``volts`` outside the span of a set of ``nominal_v`` (LINK_PER_NOMINAL x nominal_v): the
    message, ``why`` leading to the span; None inside."""
    lo, hi = (share * nominal_v for share in LINK_PER_NOMINAL)
    if lo * (1.0 - 1e-9) <= volts <= hi * (1.0 + 1e-9):       # 1.2 x 24 is 28.799999999999997
        return None
    return (f"{volts:g} V does not fit battery.nominal_v {nominal_v:g} V: {why} "
            f"{LINK_PER_NOMINAL[0]:g}..{LINK_PER_NOMINAL[1]:g} x nominal_v ({lo:.4g}..{hi:.4g} V{note}); "
            "change them together")


def link_voltage_problem(params: "SpmsmPlantParams") -> str | None:
    """Why inverter.dc_link_v and battery.nominal_v are no one battery set (a message), or None.
    Before, each was read on its own: a 400 V link on the 24 V set loaded, and its inverter drove
    the machine from a voltage no part of the bike has, while the pack booked the energy at 24 V."""
    return _set_span_problem(params.inverter.dc_link_v, params.battery.nominal_v,
                             "the inverter runs from the battery set (paper 001: one 24 V set, charged through the "
                             "rectifier, buck and charger), so its link is the set's voltage,",
                             ": the set empty to charging")


def buck_voltage_problem(params: "SpmsmPlantParams") -> str | None:
    """Why regen.buck_output_v cannot feed the charger of the battery.nominal_v set (a message), or None.
    Paper 001 (Fig. 2/8): the buck's ~25 V bus feeds the charger of the 24 V set (25/24 = 1.04). The
    plant's charger is one fixed efficiency (regen.charger_efficiency, P_ETA_CHG) whatever the bus: a
    converter for a ratio near one, its input within the set's own span (LINK_PER_NOMINAL, 21..28.8 V
    for 24 V). Before, a 5 V or 60 V bus charged the 24 V set at that efficiency without a word."""
    return _set_span_problem(params.regen.buck_output_v, params.battery.nominal_v,
                             "the buck's bus feeds the set's charger (paper 001: ~25 V into the 24 V set; the "
                             "plant's charger is one efficiency, for a bus near the set's voltage), so it must be")


def plant_params_from_config(cfg: dict) -> SpmsmPlantParams:
    """The plant's (authoritative) parameters from a loaded config (``machine: spmsm``)."""
    path = cfg.get("_config_path")
    machine = cfg.get("machine", "spmsm")
    if machine != "spmsm":
        raise ConfigError(f"expected 'spmsm' for this loader, got {machine!r}", path, "machine")
    period = cfg.get("control_period_s", 1.0e-4)
    if isinstance(period, bool) or not isinstance(period, (int, float)) or not (1e-6 <= period <= 1e-3):
        raise ConfigError(f"must be a number in [1e-6, 1e-3] s, got {period!r}", path, "control_period_s")
    mech_values = dict(inertia_kgm2=0.01, friction_nms=0.005, speed0_rpm=0.0)
    mech_values.update(section(cfg, "mechanics", path))
    params = SpmsmPlantParams(
        spmsm=build_dataclass(SpmsmParams, section(cfg, "spmsm", path), "spmsm", path),
        inverter=build_dataclass(InverterParams, section(cfg, "inverter", path), "inverter", path),
        regen=build_dataclass(RegenParams, section(cfg, "regen", path), "regen", path),
        battery=build_dataclass(SpmsmBatteryParams, section(cfg, "battery", path), "battery", path),
        mech=build_dataclass(MechParams, mech_values, "mechanics", path),
        load=build_dataclass(SpmsmLoadParams, load_section_with_preset(section(cfg, "load", path), path), "load",
                             path),
        encoder=build_dataclass(EncoderParams, section(cfg, "encoder", path), "encoder", path),
        control_period_s=float(period),
    )
    if params.regen.relay_dead_s < params.control_period_s * (1 - 1e-9):
        raise ConfigError(f"must be at least one control period ({params.control_period_s:g} s)", path,
                          "regen.relay_dead_s")
    if params.inverter.dead_time_s * 4 > params.control_period_s / params.inverter.carrier_multiple:
        raise ConfigError("dead time must be < 1/4 of a carrier period", path, "inverter.dead_time_s")
    link_problem = link_voltage_problem(params)
    if link_problem:
        raise ConfigError(link_problem, path, "inverter.dc_link_v")
    buck_problem = buck_voltage_problem(params)
    if buck_problem:
        raise ConfigError(buck_problem, path, "regen.buck_output_v")
    reverse = negative_config_speed(params.mech, params.load)
    if reverse is not None:
        # the dq model and its speed loop run both ways (./bike paper's sine and triangle commands
        # cross zero), but the session's mode laws (bike_controller.modes, shared with the BLDC
        # bike) brake and assist forward rotation: at -300 r/min the resistance mode braked 0 N m
        # for Command 0.5 (0.000 in its status, unflagged), ERG 5.45 N m for 10.3, and the
        # isokinetic loop's brake was reported as motoring (quadrant I)
        key, rpm = reverse
        raise ConfigError(f"{rpm:g} r/min turns the SPMSM bike backwards: its session modes brake and assist "
                          "forward rotation only (backwards the resistance mode brakes nothing under any "
                          "Command); give a speed >= 0", path, key)
    return params


def nominal_params_from_config(cfg: dict) -> SpmsmPlantParams:
    """The controller's copy of the model: the configured machine with the variation scales
    at 1, a sinusoidal back-EMF, no cogging, no Coulomb friction and no dead time (the paper's
    Eq. 1-6 model), unless ``controller.model: actual`` (then the plant's own)."""
    params = plant_params_from_config(cfg)
    ctrl = section(cfg, "controller", cfg.get("_config_path"))
    model = ctrl.get("model", "nominal")
    if model not in ("nominal", "actual"):
        raise ConfigError(f"must be 'nominal' or 'actual', got {model!r}", cfg.get("_config_path"), "controller.model")
    if model == "actual":
        return params
    params.spmsm = dataclasses.replace(params.spmsm, rs_scale=1.0, inductance_scale=1.0, flux_scale=1.0,
                                       emf_harmonic_5=0.0, emf_harmonic_7=0.0, cogging_torque_nm=0.0,
                                       dry_friction_nm=0.0)
    params.inverter = dataclasses.replace(params.inverter, dead_time_s=0.0)
    return params
