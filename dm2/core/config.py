"""Scenario and monitor configuration: TOML parsed into typed, versioned models.

Every model rejects unknown keys. The monitor's defaults live here and nowhere else; the
twin's sections (``[twin_process]``, ``[cell]``, ``[noise]``, ``[[faults]]``,
``[calibration_error]``) are typed in ``twin.schema``, which registers its whole-file model
(:func:`register_scenario_model`). Load with :func:`load_scenario`; errors are
:class:`ConfigError` naming the file and the field.
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
MAX_EFFICIENCY_COS_EXPONENT = 6.0  # [process] efficiency_cos_exponent's upper bound


class ConfigError(ValueError):
    """A configuration file is unreadable or invalid; the text names file and field."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class PartConfig(_Model):
    """The part to build: a generator with parameters, or a watertight STL [mm]."""

    generator: Literal["pad", "seven_sided", "twisted_tower", "box", "cylinder", "ring", "tee",
                       "triangle"] | None = None
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


# Upper bounds on physical values, each well past any cold-spray cell (a value beyond one is a
# typo or a forged file; it would overflow the kernels or empty the run without a word).
MAX_FEED_G_MIN = 1000.0  # powder feeders deliver up to a few hundred g/min
MAX_STANDOFF_MM = 300.0  # standoffs are 10-60 mm; the deposit is gone past a few hundred
MAX_NOZZLE_EXIT_MM = 50.0  # nozzle exits are 2-15 mm across
MAX_POWDER_DENSITY_G_CM3 = 25.0  # the densest element (osmium) is 22.6 g/cm3
MAX_PLUME_SIGMA_MM = 50.0  # a plume this wide deposits no track; the plate is 120 mm
MAX_PACKETS_PER_S = 1e6  # the twin draws each packet: 50x the default at most


class ProcessConfig(_Model):
    feed_g_min: float = Field(12.0, gt=0, le=MAX_FEED_G_MIN)
    standoff_mm: float = Field(30.0, gt=0, le=MAX_STANDOFF_MM)
    nozzle_exit_mm: float = Field(6.55, gt=0, le=MAX_NOZZLE_EXIT_MM)
    powder_density_g_cm3: float = Field(4.51, gt=0, le=MAX_POWDER_DENSITY_G_CM3)
    deposition_efficiency: float = Field(0.5, gt=0, le=1)  # zeta at normal impact
    # default derived from exit and standoff
    plume_sigma_mm: float | None = Field(None, gt=0, le=MAX_PLUME_SIGMA_MM)
    critical_angle_deg: float = Field(75.0, gt=0, le=90)  # zeta(theta) falls to 0 here
    # the cell's curve falls off faster than the model's by cos(theta)**this (0: the model's
    # curve; fitted from a fault-free recording by `dm2 fit-efficiency`)
    efficiency_cos_exponent: float = Field(0.0, ge=0, le=MAX_EFFICIENCY_COS_EXPONENT)
    plume_half_angle_deg: float = Field(5.0, ge=0, lt=45)  # jet divergence past the exit
    # particle packets drawn per second at full feed
    packets_per_s: float = Field(20000.0, gt=0, le=MAX_PACKETS_PER_S)


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


class PointFilterConfig(_Model):
    """``[monitor.point_filter]``: what is not surface, taken out of each profile before fusion
    (:mod:`dm2.fusion.point_filter`)."""

    enabled: bool = True
    # a run of points this far off the line its neighbours agree on is not surface: 6 sigma of
    # the 0.05 mm range noise, so a clean profile loses nothing
    reject_mm: float = Field(0.3, gt=0)
    # the neighbours agree on a line when they lie within this of it
    agree_mm: float = Field(0.15, gt=0)
    # the points around a run lie at most this far apart along the line on average (0.09 mm
    # between the twin's and a scanCONTROL 29xx-50's points at the far end of the range):
    # where a profile comes in fragments, no line is trusted across the gap
    max_step_mm: float = Field(0.3, gt=0)
    max_run_points: int = Field(16, ge=1, le=256)  # the longest run rejected [points]


class MonitorConfig(_Model):
    voxel_mm: float = Field(0.5, gt=0, le=2.0)
    truncation_voxels: float = Field(3.0, gt=0)
    # consecutive profile points within this many voxels of a run's first (along the line and
    # in range) are fused as one ray of their mean, weighted by their number
    # (dm2.fusion.profile_merge); 0: every point its own ray
    ray_merge_voxels: float = Field(0.0, ge=0, le=1.0)
    active_radius_mm: float | None = Field(None, gt=0)  # default: two plume sigmas
    weight_cap: float = Field(8.0, gt=0)
    # where the spray spot passes, earlier observations are buried: their weight is capped at
    # this many observations (dm2.fusion.tsdf.deposit); None keeps averaging them
    deposit_weight_cap: float | None = Field(1.0, gt=0)
    max_pose_gap_s: float = Field(0.05, gt=0)
    reorder_window_s: float = Field(0.5, ge=0)
    delta_global_mm: float = Field(0.4, gt=0)
    delta_local: float = Field(0.5, gt=0)
    min_weight: float = Field(1.0, ge=0)
    min_region_area_mm2: float = Field(4.0, ge=0)
    # reference clock (dm2.reference.path_clock): "executed" = controller time while the spot
    # progresses (dwells deposit nothing; the robot's slowdowns build the reference too);
    # "programmed" = path length over programmed speeds (every slowdown shows as overbuild)
    reference_clock: Literal["executed", "programmed"] = "executed"
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
    # the reference follows the process (dm2.process.process_fit: the first layer calibrates
    # within 1 +- bound, then rate-limited); None: on with the executed clock only (on the
    # programmed one it would fit the slowdowns' overbuild)
    process_fit: bool | None = None
    process_fit_rate_per_layer: float = Field(0.02, ge=0, le=0.2)
    process_fit_bound: float = Field(0.25, ge=0, lt=0.5)
    process_finding_threshold: float = Field(0.05, gt=0)
    gates: InputGateConfig = InputGateConfig()
    point_filter: PointFilterConfig = PointFilterConfig()

    @model_validator(mode="after")
    def _deposit_cap(self):
        if self.deposit_weight_cap is not None and self.deposit_weight_cap < self.min_weight:
            raise ValueError(f"deposit_weight_cap {self.deposit_weight_cap} must be at least "
                             f"min_weight {self.min_weight} (a capped surface would vanish)")
        return self


class ControlConfig(_Model):
    """The closed loop's correction law (dm2.control): per segment, a traverse-speed factor for
    the next layer from the measured top against the planned near-net top."""

    min_speed_factor: float = Field(0.6, gt=0, le=1.0)  # slowest: this times the programmed speed
    max_speed_factor: float = Field(1.6, ge=1.0)  # fastest: this times the programmed speed
    rate_per_layer: float = Field(0.2, gt=0)  # a spot's factor moves at most this per layer
    gain: float = Field(0.8, gt=0, le=1.0)  # share of the measured height error corrected at once
    accel_mm_s2: float = Field(500.0, gt=0)  # the robot's path acceleration limit
    max_speed_mm_s: float = Field(500.0, gt=0)  # the robot's traverse speed limit
    top_cell_mm: float = Field(1.0, gt=0, le=5.0)  # grid of the measured top map
    sample_sigma_mm: float = Field(1.5, ge=0)  # the top is averaged this wide around a segment
    min_weight: float = Field(1.0, ge=0)  # fused vertices below this weight are not measured
    # the cell waits this long where each layer has been approached, for that layer's program
    # (the monitor closes the layer before after its reorder window)
    layer_pause_s: float = Field(1.5, ge=0)


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
    """A whole scenario file.

    The monitor's sections are typed here. The twin's sections (``[twin_process]``,
    ``[cell]``, ``[noise]``, ``[[faults]]``, ``[calibration_error]``) belong to the twin: here
    they are plain tables, and the twin's subclass (``twin.schema.TwinScenario``, registered
    with :func:`register_scenario_model` when ``twin`` is imported, as every ``dm2`` command
    does) types and validates them. :func:`parse_scenario` and :func:`load_scenario` use the
    registered model, so their errors name the twin's fields as they name the monitor's.
    """

    schema_: int = Field(SCHEMA_VERSION, alias="schema")
    name: str
    description: str = ""
    seed: int = 0
    duration_s: float | None = Field(None, gt=0)  # stop the twin early (process seconds)
    part: PartConfig
    toolpath: ToolpathConfig = ToolpathConfig()
    process: ProcessConfig = ProcessConfig()
    twin_process: dict[str, Any] = Field(default_factory=dict)
    cell: dict[str, Any] = Field(default_factory=dict)
    sensors: SensorConfig = SensorConfig()
    noise: dict[str, Any] = Field(default_factory=dict)
    faults: tuple[dict[str, Any], ...] = ()
    calibration_error: dict[str, Any] | None = None
    monitor: MonitorConfig = MonitorConfig()
    control: ControlConfig = ControlConfig()
    expect: ExpectConfig = ExpectConfig()

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True,
                              allow_inf_nan=False)

    @field_validator("schema_")
    @classmethod
    def _schema(cls, v: int) -> int:
        return check_schema_version(v)

    def to_toml_dict(self) -> dict[str, Any]:
        """The resolved configuration as a TOML-ready dict (None values dropped)."""
        return _drop_none(self.model_dump(by_alias=True, mode="json"))


_scenario_model: type[Scenario] = Scenario


def register_scenario_model(model: type[Scenario]) -> None:
    """Validate every scenario with ``model``, a subclass of :class:`Scenario` that types the
    sections ``dm2`` leaves as plain tables (the twin registers its own at import)."""
    global _scenario_model
    if not (isinstance(model, type) and issubclass(model, Scenario)):
        raise TypeError(f"{model!r} is not a subclass of Scenario")
    _scenario_model = model


def scenario_model() -> type[Scenario]:
    """The model :func:`parse_scenario` validates with (see :func:`register_scenario_model`)."""
    return _scenario_model


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
    model = _scenario_model
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(source, exc, model)) from None


def read_toml(path: str | Path, what: str = "file") -> dict[str, Any]:
    """Parse a TOML file; :class:`ConfigError` naming the file (and ``what`` it is) otherwise."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read {what}: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a {what} (not UTF-8 text: byte {exc.start})") from None
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
