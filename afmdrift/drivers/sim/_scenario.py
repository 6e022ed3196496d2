"""Simulator scenarios: one pydantic model, loaded from a TOML file.

A scenario describes the instrument (scan geometry and timing), the sample, the
physical drift effects (each switchable and parameterised), the sensors, the
scan artefacts and a schedule of operator actions (offset moves,
manipulations, tip changes). The equations behind every parameter are in
``docs/physics.md`` and in the docstrings of :mod:`afmdrift.drivers.sim._physics`.

Unknown keys and out-of-range values are rejected with a message naming the
key, the value and the allowed range (the same wording as the main
configuration file, :func:`afmdrift.config.describe_validation_error`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal, Self

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from afmdrift.config import describe_validation_error, read_toml
from afmdrift.errors import ConfigError

__all__ = [
    "SCENARIO_DIR",
    "ArtefactsConfig",
    "ChannelPathConfig",
    "ControllerConfig",
    "CreepConfig",
    "ExtraChannelConfig",
    "HeatNetworkConfig",
    "HumidityConfig",
    "HysteresisConfig",
    "LoggedEventConfig",
    "ManipulationConfig",
    "OffsetMoveConfig",
    "PhysicsConfig",
    "RandomWalkConfig",
    "RoomConfig",
    "SampleConfig",
    "ScanConfig",
    "ScanDirectionConfig",
    "Scenario",
    "SensorsConfig",
    "ThermalConfig",
    "TipChangeConfig",
    "TipChangesConfig",
    "WarmupConfig",
    "load_scenario",
    "parse_scenario",
    "resolve_scenario_path",
]

#: ``config/scenarios`` in a source checkout.
SCENARIO_DIR = Path(__file__).resolve().parents[3] / "config" / "scenarios"

Pair = tuple[float, float]
Slope = Annotated[float, Field(ge=-0.2, le=0.2)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# --------------------------------------------------------------------------- scan


class ScanConfig(_Model):
    """Raster geometry and timing of the simulated scanner."""

    pixels: tuple[int, int] = Field((512, 512), description="(cols, rows) of a frame.")
    size_nm: Pair = Field((2048.0, 2048.0), description="Scan size (x, y) in nm.")
    line_rate_hz: float = Field(4.0, gt=0, le=2000, description="Lines per second (trace+retrace).")
    frame_period_s: float | None = Field(
        None,
        gt=0,
        le=86400,
        description="Time between frame starts; default (and minimum) rows / line_rate_hz.",
    )
    directions: Literal["alternate", "up"] = Field(
        "alternate",
        description="'alternate': up and down frames in turn; 'up': up frames only, the "
        "slow axis returning during the rest of the frame period.",
    )
    trace_fraction: float = Field(
        0.5, gt=0, le=1, description="Fraction of the line period spent on the trace."
    )
    start_offset_nm: Pair = Field((0.0, 0.0), description="Commanded XY offset at power-on.")
    autostart: bool = Field(True, description="Scanning starts at power-on.")

    @model_validator(mode="after")
    def _check(self) -> Self:
        check_scan_geometry(self.size_nm, self.pixels, self.line_rate_hz)
        return self


def check_scan_geometry(size_nm: Pair, pixels: tuple[int, int], line_rate_hz: float) -> None:
    """Raise ValueError naming the item when a scan geometry is out of range.

    Limits: 8..4096 pixels per axis, 1 nm..100 µm scan size, line rate
    (0, 2000] Hz.
    """
    for name, v in zip(("cols", "rows"), pixels, strict=True):
        if not 8 <= int(v) <= 4096:
            raise ValueError(f"pixels {name} = {v} is out of range (allowed: 8..4096)")
    for name, s in zip(("x", "y"), size_nm, strict=True):
        if not 1.0 <= float(s) <= 100_000.0:
            raise ValueError(f"size_nm {name} = {s} is out of range (allowed: 1..100000 nm)")
    if not 0.0 < float(line_rate_hz) <= 2000.0:
        raise ValueError(f"line_rate_hz = {line_rate_hz} is out of range (allowed: (0, 2000])")


# --------------------------------------------------------------------------- sample


class GoldParams(_Model):
    """Gold particles on mica (Yang et al. 2008, Fig. 2: 30 nm particles)."""

    particle_diameter_nm: float = Field(30.0, gt=0, le=1000)
    diameter_sigma_nm: float = Field(2.0, ge=0, le=100, description="Spread of diameters.")
    density_per_um2: float = Field(4.0, ge=0, le=1000, description="Particles per µm².")


class GraphiteParams(_Model):
    """HOPG-like terraces: monatomic steps, terraces hundreds of nm wide."""

    step_height_nm: float = Field(0.335, gt=0, le=10, description="Interlayer spacing of HOPG.")
    terrace_width_nm: float = Field(250.0, gt=0, le=10000, description="Typical terrace width.")
    step_direction_deg: float | None = Field(
        None, ge=0, le=180, description="Direction of the step edges; default random."
    )
    meander: float = Field(
        1.0, ge=0, le=20, description="Meandering of the steps, in terrace widths."
    )
    debris_density_per_um2: float = Field(
        0.5, ge=0, le=1000, description="Small particles on the terraces."
    )
    debris_diameter_nm: float = Field(5.0, gt=0, le=200)


class TextureParams(_Model):
    """Any height image used as the sample (made periodic; see docs/physics.md)."""

    path: str = Field(description=".npy (2-D heights in nm) or any file afmdrift.io reads.")
    pixel_size_nm: Pair | None = Field(
        None, description="Texture pixel size (x, y); default: the file's, else grid_nm."
    )


class SampleConfig(_Model):
    """The sample surface (larger than the scan area; periodic)."""

    kind: Literal["gold_on_mica", "graphite", "texture"] = "gold_on_mica"
    grid_nm: float = Field(4.0, gt=0, le=1000, description="Spacing of the height map.")
    map_px: int = Field(2048, ge=64, le=8192, description="Edge of the (periodic) height map.")
    roughness_nm: float = Field(0.1, ge=0, le=100, description="RMS substrate roughness.")
    roughness_corr_nm: float = Field(12.0, gt=0, le=10000, description="Its correlation length.")
    tip_radius_nm: float = Field(10.0, gt=0, le=1000, description="Tip apex radius.")
    edge_sigma_px: float = Field(
        1.0, ge=0.5, le=20, description="Tip smoothing of sharp edges (map px)."
    )
    gold: GoldParams = Field(default_factory=GoldParams)
    graphite: GraphiteParams = Field(default_factory=GraphiteParams)
    texture: TextureParams | None = None

    @model_validator(mode="after")
    def _check(self) -> Self:
        if self.kind == "texture" and self.texture is None:
            raise ValueError("sample.kind = 'texture' needs a [sample.texture] table with 'path'")
        return self


# --------------------------------------------------------------------------- physics


class RoomConfig(_Model):
    """Room (head) temperature: mean, slow trend, air-conditioning cycle, fluctuations."""

    mean_c: float = Field(22.0, ge=-50, le=80)
    trend_k_per_h: float = Field(0.0, ge=-10, le=10)
    ac_amplitude_k: float = Field(0.0, ge=0, le=10, description="Half peak-to-peak of AC cycle.")
    ac_period_s: float = Field(1200.0, gt=0, le=86400)
    ac_shape: Literal["sine", "triangle"] = "sine"
    fluctuation_k: float = Field(0.0, ge=0, le=10, description="Stationary std of OU noise.")
    fluctuation_tau_s: float = Field(600.0, gt=0, le=86400)


class ThermalConfig(_Model):
    """Thermal expansion of the scanner/frame loop, lagging the head temperature."""

    enabled: bool = True
    alpha_nm_per_k: Pair = Field((100.0, 60.0), description="Expansion coefficient per axis.")
    tau_s: float = Field(1800.0, gt=0, le=86400, description="First-order lag of the scanner.")
    initial_offset_k: float = Field(
        0.0, ge=-20, le=20, description="Scanner minus head temperature at power-on."
    )
    z_alpha_nm_per_k: float = Field(0.0, ge=-1000, le=1000, description="Height drift per K.")


class WarmupConfig(_Model):
    """Settling after power-on: A(1 - exp(-t/tau_w))."""

    enabled: bool = False
    amplitude_nm: Pair = Field((0.0, 0.0))
    tau_s: float = Field(3600.0, gt=0, le=86400)


class CreepConfig(_Model):
    """Logarithmic piezo creep after commanded offset moves."""

    enabled: bool = False
    gamma_per_decade: float = Field(0.03, ge=0, le=0.5)
    t0_s: float = Field(1.0, gt=0, le=3600)


class HysteresisConfig(_Model):
    """Play-operator hysteresis of the commanded XY offset."""

    enabled: bool = False
    play_nm: Pair = Field((0.0, 0.0), description="Half-width r of the play operator per axis.")


class ScanDirectionConfig(_Model):
    """Constant offset between up and down frames (up +b/2, down -b/2)."""

    enabled: bool = False
    bias_nm: Pair = Field((0.0, 0.0))


class HumidityConfig(_Model):
    """Relative humidity and its coupling p_h = beta (RH - RH(0))."""

    enabled: bool = False
    mean_pct: float = Field(45.0, ge=0, le=100)
    trend_pct_per_h: float = Field(0.0, ge=-20, le=20)
    amplitude_pct: float = Field(0.0, ge=0, le=50, description="Slow sinusoidal variation.")
    period_s: float = Field(7200.0, gt=0, le=864000)
    fluctuation_pct: float = Field(0.0, ge=0, le=50, description="Stationary std of OU noise.")
    fluctuation_tau_s: float = Field(900.0, gt=0, le=86400)
    beta_nm_per_pct: Pair = Field((0.0, 0.0))


class RandomWalkConfig(_Model):
    """Wiener-process drift, sigma nm per sqrt(s) per axis."""

    enabled: bool = False
    sigma_nm_per_sqrt_s: Pair = Field((0.0, 0.0))


class TipChangeConfig(_Model):
    """One scheduled tip change."""

    t_s: float = Field(ge=0)
    step_nm: Pair = Field((0.0, 0.0), description="Step in apparent position.")
    tip_radius_nm: float | None = Field(None, gt=0, le=1000, description="New tip radius.")


class TipChangesConfig(_Model):
    """Tip changes: scheduled ones plus a Poisson rate of spontaneous ones."""

    enabled: bool = False
    scheduled: list[TipChangeConfig] = Field(default_factory=list)
    rate_per_h: float = Field(0.0, ge=0, le=100)
    step_sigma_nm: float = Field(5.0, ge=0, le=1000, description="Spontaneous step std.")


class ChannelPathConfig(_Model):
    """One path by which a logged channel C moves the sample: g·(C_s − C_s(0)),
    τ·dC_s/dt = C − C_s (``tau_s`` = 0: C_s = C, a direct response)."""

    gain_nm_per_unit: Pair = Field((0.0, 0.0), description="Drift per channel unit, per axis.")
    tau_s: float = Field(0.0, ge=0, le=86400, description="First-order lag; 0 = direct.")


#: Channel names the simulator logs itself.
_BUILTIN_CHANNELS = ("temperature_c", "humidity_pct")


class ExtraChannelConfig(_Model):
    """A logged channel beyond temperature and humidity (pressure, a stage sensor, ...).

    Its true value is ``mean + trend·t/3600 + amplitude·sin(2πt/period) + OU +
    room_gain·(T_room,lag(t) − T_room,lag(0))``: its own slow variation and
    fluctuation, optionally following the room (head) temperature through a
    first-order lag ``room_lag_s``. The sensor adds white ``noise``. ``paths``
    couple it to the drift; none: a distractor that is logged but moves nothing.
    """

    name: str = Field(pattern=r"^[a-z][a-z0-9_]*$", max_length=64)
    mean: float = Field(0.0, ge=-1e6, le=1e6)
    trend_per_h: float = Field(0.0, ge=-1e4, le=1e4)
    amplitude: float = Field(0.0, ge=0, le=1e4, description="Slow sinusoidal variation.")
    period_s: float = Field(7200.0, gt=0, le=864000)
    phase_rad: float = Field(0.0, ge=-10, le=10)
    fluctuation: float = Field(0.0, ge=0, le=1e4, description="Stationary std of OU noise.")
    fluctuation_tau_s: float = Field(900.0, gt=0, le=86400)
    room_gain: float = Field(0.0, ge=-100, le=100, description="Units per K of room temperature.")
    room_lag_s: float = Field(0.0, ge=0, le=86400, description="Lag behind the room; 0 = none.")
    noise: float = Field(0.0, ge=0, le=1e4, description="Sensor noise (std).")
    paths: list[ChannelPathConfig] = Field(default_factory=list)

    @model_validator(mode="after")
    def _check(self) -> Self:
        if self.name in _BUILTIN_CHANNELS:
            raise ValueError(f"channel name {self.name!r} is logged by the simulator already")
        return self


class LoggedEventConfig(_Model):
    """A logged event of any kind and the drift that follows it.

    ``settle``: ``A·(1 − exp(−(t − t_e)/τ))`` after the event (a step that
    settles), ``log``: ``A·log10(1 + (t − t_e)/t0)``, ``none``: logged only
    (a distractor). Each event's amplitude is ``amplitude_nm`` times
    ``1 + amplitude_spread·N(0, 1)``.
    """

    t_s: float = Field(ge=0)
    kind: str = Field(pattern=r"^[a-z][a-z0-9_]*$", max_length=64)
    shape: Literal["settle", "log", "none"] = "settle"
    amplitude_nm: Pair = Field((0.0, 0.0))
    amplitude_spread: float = Field(0.0, ge=0, le=2)
    tau_s: float = Field(600.0, gt=0, le=86400)
    t0_s: float = Field(10.0, gt=0, le=86400)

    @model_validator(mode="after")
    def _check(self) -> Self:
        if self.kind in ("offset_move", "manipulation", "tip_change", "power_on"):
            raise ValueError(
                f"kind {self.kind!r} is logged by the simulator's own actions; "
                "use [[offset_moves]], [[manipulations]] or [physics.tip_changes]"
            )
        return self


class HeatNetworkConfig(_Model):
    """The second physics (``physics.model = "heat_network"``); see docs/physics.md.

    Room air on a thermostat that heats and cools at different rates inside a
    band, a stage and a scanner each lagging the node before them, an
    algebraic warm-up, an unlogged wander of random-phase slow sinusoids, and
    a cross-coupling of the axes.
    """

    air_mean_c: float = Field(22.0, ge=-50, le=80, description="Thermostat set point.")
    band_k: float = Field(0.5, gt=0, le=10, description="Half-width of the thermostat band.")
    heating_k_per_h: float = Field(2.0, gt=0, le=100, description="Air warming rate, heater on.")
    cooling_k_per_h: float = Field(1.0, gt=0, le=100, description="Air cooling rate, heater off.")
    tau_stage_s: float = Field(1200.0, gt=0, le=86400, description="Stage lag behind the air.")
    tau_scanner_s: float = Field(
        2400.0, gt=0, le=86400, description="Scanner lag behind the stage."
    )
    stage_offset_k: float = Field(
        0.0, ge=-20, le=20, description="Stage (and scanner) minus air temperature at power-on."
    )
    air_nm_per_k: Pair = Field((0.0, 0.0), description="Instant response to the air, per axis.")
    stage_nm_per_k: Pair = Field((0.0, 0.0), description="Response to the stage, per axis.")
    scanner_nm_per_k: Pair = Field((0.0, 0.0), description="Response to the scanner, per axis.")
    warmup_nm: Pair = Field((0.0, 0.0), description="Warm-up amplitude A in A·t/(t + τ_w).")
    warmup_tau_s: float = Field(900.0, gt=0, le=86400, description="Warm-up half time τ_w.")
    wander_nm: Pair = Field((0.0, 0.0), description="RMS of the unlogged wander, per axis.")
    wander_periods_s: Pair = Field(
        (240.0, 14400.0), description="Shortest and longest period of the wander's sinusoids."
    )
    wander_terms: int = Field(12, ge=1, le=200, description="Sinusoids per axis.")
    cross_coupling: Pair = Field(
        (0.0, 0.0), description="(k_xy, k_yx): x gets k_xy·y, y gets k_yx·x (dimensionless)."
    )
    humidity_mean_pct: float = Field(45.0, ge=0, le=100, description="Logged RH at the set point.")
    humidity_pct_per_k: float = Field(
        -2.7, ge=-20, le=20, description="Logged RH change per K of air (moves nothing)."
    )

    @model_validator(mode="after")
    def _check(self) -> Self:
        if abs(self.tau_stage_s - self.tau_scanner_s) < 1.0:
            raise ValueError(
                f"tau_scanner_s = {self.tau_scanner_s} must differ from tau_stage_s = "
                f"{self.tau_stage_s} by at least 1 s"
            )
        lo, hi = self.wander_periods_s
        if not 1.0 <= lo < hi <= 864000.0:
            raise ValueError(
                f"wander_periods_s = {self.wander_periods_s} must be (shortest, longest) "
                "with 1 <= shortest < longest <= 864000 s"
            )
        for name, k in zip(("k_xy", "k_yx"), self.cross_coupling, strict=True):
            if abs(k) > 0.9:
                raise ValueError(
                    f"cross_coupling {name} = {k} is out of range (allowed: -0.9..0.9)"
                )
        return self


#: Tables of ``[physics]`` that only the ``effects`` model reads.
_EFFECTS_TABLES = (
    "dt_s",
    "room",
    "thermal",
    "warmup",
    "creep",
    "hysteresis",
    "humidity",
    "random_walk",
    "channels",
    "events",
)


class PhysicsConfig(_Model):
    """All drift effects; see docs/physics.md."""

    model: Literal["effects", "heat_network"] = Field(
        "effects",
        description="'effects': the documented sum of effects (DriftPhysics); "
        "'heat_network': the second physics, parameters in [physics.heat_network].",
    )
    dt_s: float = Field(0.5, gt=0, le=60, description="Time step of the stochastic processes.")
    room: RoomConfig = Field(default_factory=RoomConfig)
    thermal: ThermalConfig = Field(default_factory=ThermalConfig)
    warmup: WarmupConfig = Field(default_factory=WarmupConfig)
    creep: CreepConfig = Field(default_factory=CreepConfig)
    hysteresis: HysteresisConfig = Field(default_factory=HysteresisConfig)
    scan_direction: ScanDirectionConfig = Field(default_factory=ScanDirectionConfig)
    humidity: HumidityConfig = Field(default_factory=HumidityConfig)
    random_walk: RandomWalkConfig = Field(default_factory=RandomWalkConfig)
    tip_changes: TipChangesConfig = Field(default_factory=TipChangesConfig)
    channels: list[ExtraChannelConfig] = Field(default_factory=list)
    events: list[LoggedEventConfig] = Field(default_factory=list)
    heat_network: HeatNetworkConfig = Field(default_factory=HeatNetworkConfig)

    @model_validator(mode="after")
    def _check_channels(self) -> Self:
        names = [c.name for c in self.channels]
        if len(set(names)) != len(names):
            raise ValueError(f"physics.channels: duplicate channel names in {names}")
        return self

    @model_validator(mode="after")
    def _check_model_tables(self) -> Self:
        given = self.model_fields_set
        if self.model == "heat_network":
            stray = [k for k in _EFFECTS_TABLES if k in given]
            if stray:
                raise ValueError(
                    f"physics.model = 'heat_network' does not read physics.{stray[0]} "
                    "(a table of the 'effects' model); its parameters are in "
                    "[physics.heat_network]"
                )
        elif "heat_network" in given:
            raise ValueError(
                f"[physics.heat_network] is read only with physics.model = 'heat_network' "
                f"(physics.model = {self.model!r})"
            )
        return self


class ArtefactsConfig(_Model):
    """Image artefacts that are not lateral drift."""

    noise_nm: float = Field(0.02, ge=0, le=100, description="Detector noise per pixel (std).")
    line_offset_nm: float = Field(0.0, ge=0, le=100, description="Per-line offset (std).")
    z_drift_nm_per_s: float = Field(0.0, ge=-100, le=100, description="Height offset rate.")
    tilt: tuple[Slope, Slope] = Field((0.0, 0.0), description="Sample plane slope (x, y).")


class SensorsConfig(_Model):
    """Sensor noise and the rate at which `sim record` logs channels."""

    temperature_noise_c: float = Field(0.005, ge=0, le=5)
    humidity_noise_pct: float = Field(0.1, ge=0, le=20)
    record_period_s: float = Field(1.0, gt=0, le=3600, description="channels.csv sample period.")
    truth_period_s: float = Field(1.0, gt=0, le=3600, description="truth.csv sample period.")


class OffsetMoveConfig(_Model):
    """A scheduled commanded offset change (absolute XY offset, nm)."""

    t_s: float = Field(ge=0)
    x_nm: float = Field(ge=-1e6, le=1e6)
    y_nm: float = Field(ge=-1e6, le=1e6)


class ManipulationConfig(_Model):
    """A scheduled tip push from (x0, y0) to (x1, y1) in image coordinates (nm)."""

    t_s: float = Field(ge=0)
    x0_nm: float
    y0_nm: float
    x1_nm: float
    y1_nm: float
    snap_to_particle: bool = Field(
        True, description="Start at the particle nearest (x0, y0), keeping the push vector."
    )


class ControllerConfig(_Model):
    """The controller's piezo and drift compensation (``Piezo.DriftCompSet``).

    A controller behaves in one of two ways on switching the compensation off
    and on, and the daemon cannot read which: ``release = "reset"`` returns
    the displacement to zero when it is switched off (on starts from zero);
    ``"keep"`` holds it through off and on. ``drift_comp_gain`` is what the
    piezo applies per velocity asked (1: as asked; 0.5: half; -1: the
    negative, an axis wired or calibrated the wrong way), while the
    controller reports the velocity asked.
    """

    piezo_range_nm: tuple[float, float, float] = Field(
        (10_000.0, 10_000.0, 2_000.0),
        description="Piezo range (x, y, z), nm (Piezo.RangeGet).",
    )
    release: Literal["reset", "keep"] = Field(
        "reset", description="What switching the drift compensation off does to its displacement."
    )
    drift_comp_gain: float = Field(
        1.0, ge=-10.0, le=10.0, description="Displacement applied per displacement asked."
    )

    @model_validator(mode="after")
    def _check(self) -> Self:
        for axis, r in zip("xyz", self.piezo_range_nm, strict=True):
            if not 10.0 <= r <= 1e6:
                raise ValueError(
                    f"piezo_range_nm {axis} = {r} is out of range (allowed: 10..1e6 nm)"
                )
        return self


class Scenario(_Model):
    """Root of a scenario file."""

    name: str = "unnamed"
    description: str = ""
    duration_s: float = Field(3600.0, gt=0, le=30 * 86400, description="Default record length.")
    seed: int = Field(0, ge=0, le=2**63 - 1)
    scan: ScanConfig = Field(default_factory=ScanConfig)
    sample: SampleConfig = Field(default_factory=SampleConfig)
    physics: PhysicsConfig = Field(default_factory=PhysicsConfig)
    controller: ControllerConfig = Field(default_factory=ControllerConfig)
    artefacts: ArtefactsConfig = Field(default_factory=ArtefactsConfig)
    sensors: SensorsConfig = Field(default_factory=SensorsConfig)
    offset_moves: list[OffsetMoveConfig] = Field(default_factory=list)
    manipulations: list[ManipulationConfig] = Field(default_factory=list)

    @model_validator(mode="after")
    def _check(self) -> Self:
        if self.sample.kind == "texture":
            return self  # checked against the texture's own extent when it is loaded
        edge_nm = self.sample.map_px * self.sample.grid_nm
        for axis, size in zip("xy", self.scan.size_nm, strict=True):
            if size > 0.5 * edge_nm:
                raise ValueError(
                    f"scan.size_nm {axis} = {size} is more than half the sample "
                    f"(sample.map_px * sample.grid_nm = {edge_nm} nm); enlarge the sample"
                )
        return self


def parse_scenario(data: dict[str, Any], *, source: str = "<scenario>") -> Scenario:
    """Validate a mapping (as read from TOML) into a :class:`Scenario`.

    Raises
    ------
    ConfigError
        One line per problem, naming the dotted key, the value and the allowed range.
    """

    try:
        return Scenario.model_validate(data)
    except ValidationError as err:
        raise ConfigError(describe_validation_error(err, source=source, root=Scenario)) from None


def resolve_scenario_path(name_or_path: str | Path) -> Path:
    """A scenario file path, or a bare name looked up in ``config/scenarios``."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    candidate = SCENARIO_DIR / (p.name if p.suffix == ".toml" else f"{p.name}.toml")
    if p.parent == Path(".") and candidate.is_file():
        return candidate
    known = sorted(f.stem for f in SCENARIO_DIR.glob("*.toml")) if SCENARIO_DIR.is_dir() else []
    raise ConfigError(
        f"{name_or_path}: scenario file not found (built-in scenarios: {', '.join(known)})"
    )


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario TOML file (a path or a built-in scenario name)."""
    p = resolve_scenario_path(path)
    return parse_scenario(read_toml(p, what="scenario file"), source=str(p))
