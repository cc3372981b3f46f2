"""Scenario and cell configuration: TOML parsed into typed, versioned models.

Every model rejects unknown keys. Defaults live here and nowhere else. Load with
:func:`load_scenario`; errors are :class:`ConfigError` naming the file and the field.
Angles are degrees in files (``*_deg``) and converted to radians at use.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from dm2.core.config_errors import model_named
from dm2.core.config_uncertainty import UncertaintyConfig

SCHEMA_VERSION = 1


class ConfigError(ValueError):
    """A configuration file is unreadable or invalid; the text names file and field."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class PartConfig(_Model):
    """The part to build: a generator with parameters, or a watertight STL [mm]."""

    generator: Literal["pad", "seven_sided", "twisted_tower", "box"] | None = None
    stl: str | None = None
    params: dict[str, float] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _one_source(self):
        if (self.generator is None) == (self.stl is None):
            raise ValueError("give exactly one of 'generator' or 'stl'")
        return self


class SpeedConfig(_Model):
    infill: float = Field(30.0, gt=0)
    edge: float = Field(30.0, gt=0)
    overhang: float = Field(12.0, gt=0)
    skip: float = Field(50.0, gt=0)


class ToolpathConfig(_Model):
    layer_mm: float = Field(0.8, gt=0)
    line_spacing_mm: float = Field(2.0, gt=0)
    strategy: Literal["double", "single"] = "double"
    contour_angle_deg: float = Field(35.0, ge=0, lt=80)
    # where the tilted edge jet points: "toward_wall" (nozzle leaning out, the jet meets the
    # wall from outside and straightens it, as the paper tilts it) or "away_from_wall"
    contour_jet: Literal["away_from_wall", "toward_wall"] = "away_from_wall"
    contour_inset_mm: float | None = Field(None, ge=0)  # default: half a bead = spacing / 2
    zone_mm: float = Field(1.0, ge=0)
    speed_mm_s: SpeedConfig = SpeedConfig()
    infill_angle_deg: float = 0.0  # first layer's raster direction; alternates by 90 degrees
    overhang_min_mm: float = Field(0.5, ge=0)  # outline beyond the layer below that is overhang
    max_layers: int | None = Field(None, gt=0)


class ProcessConfig(_Model):
    feed_g_min: float = Field(12.0, gt=0)
    standoff_mm: float = Field(30.0, gt=0)
    nozzle_exit_mm: float = Field(6.55, gt=0)
    powder_density_g_cm3: float = Field(4.51, gt=0)
    deposition_efficiency: float = Field(0.5, gt=0, le=1)  # zeta at normal impact
    plume_sigma_mm: float | None = Field(None, gt=0)  # default derived from exit and standoff
    critical_angle_deg: float = Field(75.0, gt=0, le=90)  # zeta(theta) falls to 0 here
    plume_half_angle_deg: float = Field(5.0, ge=0, lt=45)  # jet divergence past the exit
    packets_per_s: float = Field(20000.0, gt=0)  # particle packets drawn per second at full feed


class TwinProcessConfig(_Model):
    """``[twin_process]``: the twin's own physics (the monitor keeps the nominal ``[process]``).

    Every ``[process]`` key may be given here; it overrides the nominal value for the twin
    only. The keys below are physics the monitor's near-net model does not have. Their
    defaults make every shipped run carry a modest, plausible model error; set
    ``plume_sigma_factor = 1``, ``efficiency_factor = 1``, ``efficiency_curve = "cos2"``,
    ``plume_exponent = 2``, ``porosity = 0`` and ``standoff_efficiency_per_mm = 0`` for a twin
    that deposits exactly with the nominal model (see ``twin.world.twin_physics``).
    """

    feed_g_min: float | None = Field(None, gt=0)
    standoff_mm: float | None = Field(None, gt=0)
    nozzle_exit_mm: float | None = Field(None, gt=0)
    powder_density_g_cm3: float | None = Field(None, gt=0)
    deposition_efficiency: float | None = Field(None, gt=0, le=1)
    plume_sigma_mm: float | None = Field(None, gt=0)
    critical_angle_deg: float | None = Field(None, gt=0, le=90)
    plume_half_angle_deg: float | None = Field(None, ge=0, lt=45)
    packets_per_s: float | None = Field(None, gt=0)
    # sigma multiplier on the (overridden) plume sigma: +8 %, what a divergence half-angle of
    # 6 instead of 5 deg gives at 30 mm standoff (+9 %); the half-angle is rarely known better
    plume_sigma_factor: float = Field(1.08, gt=0)
    # normal-impact efficiency multiplier: -7 %, a powder-lot / gas-temperature difference of
    # the size cold-spray deposition efficiencies scatter by between nominally equal runs
    efficiency_factor: float = Field(0.93, gt=0)
    # efficiency against impact angle: "cos2" (the nominal cos^2(pi/2 (theta/theta_c)^2)),
    # "cos" (cos theta up to theta_c), "linear" (1 - theta/theta_c) or "plateau" (flat to
    # plateau_angle_deg, then linear to 0 at theta_c). Default "plateau": the shape measured
    # against spray angle in cold-spray impact-angle studies (e.g. Binder et al. 2011,
    # J. Therm. Spray Technol., CP-Ti): nearly constant to about 30 deg off normal, then falling
    efficiency_curve: Literal["cos2", "cos", "linear", "plateau"] = "plateau"
    plateau_angle_deg: float = Field(30.0, ge=0, lt=90)
    # radial plume density exp(-(r/a)^p / 2) at equal rms width; 2 = Gaussian. Default 2.4: a
    # slightly flat-topped jet, as single cold-spray tracks are flatter on top than a Gaussian
    plume_exponent: float = Field(2.4, ge=1, le=8)
    # volume fraction of pores in the deposit (it stands taller than its mass at full density):
    # 2 %, within the 0.5-5 % reported for nitrogen-sprayed CP-Ti (e.g. Marrocco et al. 2006)
    porosity: float = Field(0.02, ge=0, lt=0.5)
    # relative efficiency change per mm that the nozzle-to-surface distance exceeds the
    # standoff: -0.3 %/mm, the slow fall of efficiency with spray distance as particles slow
    # past the jet's core (the trend of standoff studies, e.g. Li et al. 2008, Mater. Des.)
    standoff_efficiency_per_mm: float = Field(-0.003, ge=-0.05, le=0.05)

    def overrides(self) -> dict[str, float]:
        """The ``[process]`` keys this section overrides, with their twin values."""
        return {k: v for k, v in self.model_dump().items()
                if k in ProcessConfig.model_fields and v is not None}


class CellConfig(_Model):
    robot: Literal["irb4600"] = "irb4600"
    nozzle_exit_B_mm: tuple[float, float, float] = (1700.0, 0.0, 1300.0)
    nozzle_length_mm: float = Field(268.0, gt=0)
    nozzle_body_diameter_mm: float = Field(40.0, gt=0)
    plate_size_mm: tuple[float, float, float] = (120.0, 120.0, 6.0)
    # plate corner on the flange; the 50 degree bracket puts the plate centre 150 mm out on
    # the flange axis and keeps axis 5 near -64 deg, clear of its limit and singularity
    plate_on_flange_mm: tuple[float, float, float] = (-38.567, -60.0, 104.037)
    plate_on_flange_rpy_deg: tuple[float, float, float] = (0.0, -50.0, 0.0)
    sensor_distance_mm: float = Field(95.0, gt=0)
    sensor_elevation_deg: float = Field(55.0, gt=0, lt=90)
    sensor_azimuth_deg: tuple[float, float, float] = (90.0, 210.0, 330.0)
    robot_state_hz: float = Field(250.0, gt=0)
    accel_mm_s2: float = Field(500.0, gt=0)
    home_joints_deg: tuple[float, float, float, float, float, float] = (0, 24, 1, 0, -64, 0)
    work_yaw_deg: float = 0.0  # plate x axis about z_B when the plate is level
    max_reorient_deg_s: float = Field(90.0, gt=0)  # spray-axis reorientation rate limit
    wrist_singularity_deg: float = Field(5.0, ge=0, lt=90)  # smallest allowed |axis 5|


class SensorConfig(_Model):
    model: str = "scanCONTROL 29xx-50"
    points: int = Field(640, gt=1)
    rate_hz: float = Field(10.0, gt=0)
    cascade_s: float = Field(0.020, ge=0)
    z_start_mm: float = Field(70.0, gt=0)
    z_end_mm: float = Field(120.0, gt=0)
    x_width_start_mm: float = Field(42.0, gt=0)
    x_width_end_mm: float = Field(58.0, gt=0)
    camera_baseline_mm: float = Field(40.0, gt=0)  # camera offset from the laser along +y_S

    @model_validator(mode="after")
    def _range(self):
        if self.z_end_mm <= self.z_start_mm:
            raise ValueError("z_end_mm must exceed z_start_mm")
        return self


class NoiseConfig(_Model):
    range_sigma_mm: float = Field(0.05, ge=0)
    speckle_sigma_mm: float = Field(0.0, ge=0)
    dropout_prob: float = Field(0.0, ge=0, le=1)
    outlier_prob: float = Field(0.0, ge=0, le=1)
    speckle_length_points: float = Field(4.0, gt=0)  # speckle correlation length along the line
    outlier_offset_mm: tuple[float, float] = (0.5, 5.0)  # ghost lies this far beyond, along ray
    min_intensity: float = Field(0.02, ge=0, lt=1)  # weaker returns (grazing incidence) dropped
    robot_repeatability_mm: float = Field(0.0, ge=0)

    @model_validator(mode="after")
    def _outlier_offsets(self):
        lo, hi = self.outlier_offset_mm
        if not 0 <= lo <= hi:
            raise ValueError("outlier_offset_mm must be [min, max] with 0 <= min <= max")
        return self


class FaultConfig(_Model):
    """One injected fault. Which fields apply depends on ``kind`` (see twin.world.faults)."""

    kind: Literal["feed_step", "feed_drift", "feed_drop", "clog", "efficiency_drift",
                  "standoff_change", "bump", "dent", "corner_dwell"]
    layers: tuple[int, int] | None = None  # inclusive layer window
    time_s: tuple[float, float] | None = None  # process-time window
    factor: float | None = None  # feed or efficiency multiplier at full effect
    per_layer: float | None = None  # efficiency drift per layer (fraction)
    delta_mm: float | None = None  # standoff change
    center_O_mm: tuple[float, float] | None = None  # bump / dent
    height_mm: float | None = Field(None, gt=0)
    width_mm: float | None = Field(None, gt=0)
    corner_angle_deg: float | None = None
    extra_dwell_s: float | None = Field(None, gt=0)

    @model_validator(mode="after")
    def _window(self):
        if self.layers is not None and self.layers[1] < self.layers[0]:
            raise ValueError("layers window [first, last] is reversed")
        if self.time_s is not None and self.time_s[1] < self.time_s[0]:
            raise ValueError("time_s window [start, end] is reversed")
        return self


class CalibrationPerturbation(_Model):
    """Error added to the calibration handed to the pipeline (rehearses miscalibration)."""

    translation_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sensors: tuple[str, ...] = ("S1", "S2", "S3")


class InputGateConfig(_Model):
    """Plausibility gates on live and replayed input (:mod:`dm2.fusion.gates`); defaults fit an
    IRB 4600-40/2.55 (datasheet joint limits and speeds, reach 2.55 m) with margin."""

    stamp_band_s: float = Field(2.0, gt=0)  # a stamp this far from the source's clock: dropped
    stamp_rate_max: float = Field(2.0, gt=0)  # stamp seconds per host second at most (live)
    stamp_confirm_s: float = Field(1.0, gt=0)  # a clock step lasting this long is re-synced
    stamp_seed: int = Field(3, ge=1, le=64)  # first messages whose median seeds the band
    workspace_B_mm: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        (-3000.0, -3000.0, -1500.0), (3000.0, 3000.0, 3500.0))
    joint_limits_deg: tuple[tuple[float, float], ...] = (
        (-180.0, 180.0), (-90.0, 150.0), (-180.0, 75.0), (-400.0, 400.0), (-125.0, 125.0),
        (-400.0, 400.0))
    max_tcp_speed_mm_s: float = Field(7000.0, gt=0)
    max_joint_speed_deg_s: tuple[float, ...] = (175.0, 175.0, 175.0, 250.0, 250.0, 360.0)
    speed_margin: float = Field(1.5, ge=1.0)  # factor on the speed limits
    max_lost_share: float = Field(0.25, ge=0, le=1)  # a run losing more input fails (exit 1)

    @model_validator(mode="after")
    def _boxes(self):
        lo, hi = self.workspace_B_mm
        if any(a >= b for a, b in zip(lo, hi, strict=True)):
            raise ValueError(f"workspace_B_mm: lower corner {list(lo)} not below upper {list(hi)}")
        if any(a >= b for a, b in self.joint_limits_deg):
            raise ValueError(f"joint_limits_deg: a lower limit is not below its upper limit "
                             f"({[list(j) for j in self.joint_limits_deg]})")
        if len(self.max_joint_speed_deg_s) != len(self.joint_limits_deg):
            raise ValueError(f"max_joint_speed_deg_s: {len(self.max_joint_speed_deg_s)} values "
                             f"for {len(self.joint_limits_deg)} joints")
        return self


class MonitorConfig(_Model):
    voxel_mm: float = Field(0.5, gt=0, le=2.0)
    truncation_voxels: float = Field(3.0, gt=0)
    active_radius_mm: float | None = Field(None, gt=0)  # default: two plume sigmas
    weight_cap: float = Field(8.0, gt=0)
    max_pose_gap_s: float = Field(0.05, gt=0)
    reorder_window_s: float = Field(0.5, ge=0)
    delta_global_mm: float = Field(0.4, gt=0)
    delta_local: float = Field(0.5, gt=0)
    min_weight: float = Field(1.0, ge=0)
    min_region_area_mm2: float = Field(4.0, ge=0)
    # reference clock (dm2.reference.path_clock): "programmed" = path length over programmed
    # speeds (every robot slowdown shows as overbuild); "executed" = controller time while the
    # spot progresses (dwells deposit nothing), as the shipped scenarios set it; see README
    reference_clock: Literal["executed", "programmed"] = "programmed"
    dwell_speed_mm_s: float = Field(1.0, gt=0)
    uncertainty: UncertaintyConfig = UncertaintyConfig()
    # evidence (dm2.defects.track): a track once seen in track_min_observations layers within
    # track_window_layers; local-only regions are early warnings unless track_local_alone
    track_min_observations: int = Field(2, ge=1)
    track_window_layers: int = Field(2, ge=1)
    track_local_alone: bool = False
    min_region_volume_mm3: float = Field(1.0, ge=0)  # area x mean |deviation| floor
    # real-time alarms: a column counts once flagged this long and in this many observations
    realtime_persist_s: float = Field(0.1, ge=0)
    realtime_min_observations: int = Field(2, ge=1)
    # plate deviations this far outside the planned outline: overspray (dm2.defects.footprint)
    overspray_margin_mm: float = Field(2.0, ge=0)
    # the newest layers whose whole deviation stays in memory; older ones wait on disk for the
    # report (dm2.defects.spill), so a tall build's memory does not grow with its layers
    layers_in_memory: int | None = Field(2, ge=1)
    # the reference follows the process (dm2.pipeline.process_fit); None: on with the
    # executed clock only (on the programmed one it would fit the slowdowns' overbuild)
    process_fit: bool | None = None
    process_fit_rate_per_layer: float = Field(0.02, ge=0, le=0.2)
    process_fit_bound: float = Field(0.10, ge=0, lt=0.5)
    process_finding_threshold: float = Field(0.05, gt=0)
    gates: InputGateConfig = InputGateConfig()


class ExpectTrack(_Model):
    kind: Literal["overbuild", "underbuild", "local_overbuild", "local_underbuild"]
    near_mm: tuple[float, float] | None = None
    within_mm: float = Field(10.0, gt=0)
    from_layer: int | None = None


class ExpectConfig(_Model):
    tracks: tuple[ExpectTrack, ...] = ()
    absent: tuple[ExpectTrack, ...] = ()  # tracks that must NOT appear (kind, near, from_layer)
    no_tracks: bool = False  # no global over/underbuild track (local ones are early warnings)
    no_local_tracks: bool = False  # no local over/underbuild track either


class Scenario(_Model):
    """A whole scenario file."""

    schema_: int = Field(SCHEMA_VERSION, alias="schema")
    name: str
    description: str = ""
    seed: int = 0
    duration_s: float | None = Field(None, gt=0)  # stop the twin early (process seconds)
    part: PartConfig
    toolpath: ToolpathConfig = ToolpathConfig()
    process: ProcessConfig = ProcessConfig()
    twin_process: TwinProcessConfig = TwinProcessConfig()
    cell: CellConfig = CellConfig()
    sensors: SensorConfig = SensorConfig()
    noise: NoiseConfig = NoiseConfig()
    faults: tuple[FaultConfig, ...] = ()
    calibration_error: CalibrationPerturbation | None = None
    monitor: MonitorConfig = MonitorConfig()
    expect: ExpectConfig = ExpectConfig()

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    @field_validator("schema_")
    @classmethod
    def _schema(cls, v: int) -> int:
        return check_schema_version(v)

    @model_validator(mode="after")
    def _twin_plateau(self):
        tp = self.twin_process
        tc = tp.critical_angle_deg or self.process.critical_angle_deg
        if tp.efficiency_curve == "plateau" and tp.plateau_angle_deg >= tc:
            raise ValueError(f"twin_process.plateau_angle_deg {tp.plateau_angle_deg} must be "
                             f"below the twin's critical_angle_deg {tc}")
        return self

    def to_toml_dict(self) -> dict[str, Any]:
        """The resolved configuration as a TOML-ready dict (None values dropped)."""
        return _drop_none(self.model_dump(by_alias=True, mode="json"))


def _drop_none(obj):
    if isinstance(obj, dict):
        return {k: _drop_none(v) for k, v in obj.items() if v is not None}
    if isinstance(obj, list):
        return [_drop_none(v) for v in obj]
    return obj


def format_validation_error(source: str, exc: ValidationError, model=None) -> str:
    """One line per error naming the field and showing the bad value; an unknown key gets the
    nearest known key of its table as a suggestion (``model``: the validated model class,
    default the one that raised; :mod:`dm2.core.config_errors`)."""
    from dm2.core.config_errors import describe_errors

    return describe_errors(source, exc, model or model_named(_Model, exc.title))


def parse_scenario(data: dict[str, Any], source: str = "<scenario>") -> Scenario:
    """Validate a parsed TOML dict; ``source`` names it in errors."""
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(source, exc)) from None


def read_toml(path: str | Path, what: str = "file") -> dict[str, Any]:
    """Parse a TOML file; :class:`ConfigError` naming the file (and ``what`` it is) otherwise."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read {what}: {exc.strerror}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None


def check_schema_version(version: int) -> int:
    """Pydantic validator body: only this build's ``schema`` version is read."""
    if version != SCHEMA_VERSION:
        raise ValueError(f"unsupported schema version {version} (this build reads "
                         f"{SCHEMA_VERSION})")
    return version


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario TOML file. Raises :class:`ConfigError`."""
    path = Path(path)
    scenario = parse_scenario(read_toml(path, "scenario file"), str(path))
    if scenario.part.stl is not None and not Path(scenario.part.stl).is_absolute():
        stl = (path.parent / scenario.part.stl).resolve()
        scenario = scenario.model_copy(update={"part": scenario.part.model_copy(
            update={"stl": str(stl)})})
    return scenario
