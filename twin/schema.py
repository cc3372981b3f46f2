"""The twin's sections of a scenario file, typed: ``[twin_process]``, ``[cell]``, ``[noise]``,
``[[faults]]``, ``[calibration_error]``.

``dm2`` keeps these tables untyped (:class:`dm2.core.config.Scenario`, the monitor's view of a
scenario file); :class:`TwinScenario` types them, and this module registers it with
:func:`dm2.core.config.register_scenario_model` at import (``import twin`` does), so
:func:`dm2.core.config.load_scenario` validates every section and its errors name the twin's
fields (file, field, bad value, nearest key) exactly as the monitor's. Every model rejects
unknown keys; the twin's defaults live here and nowhere else.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from dm2.core.config import (
    MAX_FEED_G_MIN,
    MAX_NOZZLE_EXIT_MM,
    MAX_PACKETS_PER_S,
    MAX_PLUME_SIGMA_MM,
    MAX_POWDER_DENSITY_G_CM3,
    MAX_STANDOFF_MM,
    ProcessConfig,
    Scenario,
    _Model,
    register_scenario_model,
)


class TwinProcessConfig(_Model):
    """``[twin_process]``: the twin's own physics (the monitor keeps the nominal ``[process]``).

    Every ``[process]`` key may be given here; it overrides the nominal value for the twin
    only. The keys below are physics the monitor's near-net model does not have. Their
    defaults make every shipped run carry a modest, plausible model error; set
    ``plume_sigma_factor = 1``, ``efficiency_factor = 1``, ``efficiency_curve = "cos2"``,
    ``plume_exponent = 2``, ``porosity = 0`` and ``standoff_efficiency_per_mm = 0`` for a twin
    that deposits exactly with the nominal model (see ``twin.world.twin_physics``).
    """

    # the [process] bounds hold here too (dm2.core.config: why each)
    feed_g_min: float | None = Field(None, gt=0, le=MAX_FEED_G_MIN)
    standoff_mm: float | None = Field(None, gt=0, le=MAX_STANDOFF_MM)
    nozzle_exit_mm: float | None = Field(None, gt=0, le=MAX_NOZZLE_EXIT_MM)
    powder_density_g_cm3: float | None = Field(None, gt=0, le=MAX_POWDER_DENSITY_G_CM3)
    deposition_efficiency: float | None = Field(None, gt=0, le=1)
    plume_sigma_mm: float | None = Field(None, gt=0, le=MAX_PLUME_SIGMA_MM)
    critical_angle_deg: float | None = Field(None, gt=0, le=90)
    plume_half_angle_deg: float | None = Field(None, ge=0, lt=45)
    packets_per_s: float | None = Field(None, gt=0, le=MAX_PACKETS_PER_S)
    # sigma multiplier on the (overridden) plume sigma: +8 %, what a divergence half-angle of
    # 6 instead of 5 deg gives at 30 mm standoff (+9 %); the half-angle is rarely known better
    plume_sigma_factor: float = Field(1.08, gt=0, le=5)  # 5x: a plume no nozzle gives
    # normal-impact efficiency multiplier: -7 %, a powder-lot / gas-temperature difference of
    # the size cold-spray deposition efficiencies scatter by between nominally equal runs
    efficiency_factor: float = Field(0.93, gt=0, le=2)  # efficiency stays <= 1 (checked)
    # efficiency against impact angle: "cos2" (the nominal cos^2(pi/2 (theta/theta_c)^2)),
    # "cos" (cos theta up to theta_c), "linear" (1 - theta/theta_c) or "plateau" (flat to
    # plateau_angle_deg, then linear to 0 at theta_c). Default "plateau": the shape measured
    # against spray angle in cold-spray impact-angle studies (e.g. Binder et al. 2011,
    # J. Therm. Spray Technol., CP-Ti): nearly constant to about 30 deg off normal, then falling.
    # "logistic": expit(k (phi - phi0)) in the spray angle phi = 90 deg - theta [rad] between
    # jet and surface, 1 at normal impact, no cut at the critical angle (the shape fitted to
    # cold-spray experiments in published deposition simulators); k and phi0 below
    efficiency_curve: Literal["cos2", "cos", "linear", "plateau", "logistic"] = "plateau"
    plateau_angle_deg: float = Field(30.0, ge=0, lt=90)
    logistic_k_per_rad: float = Field(9.0, gt=0, le=100)
    logistic_phi0_rad: float = Field(0.61, gt=0, lt=1.5707963267948966)
    # the twin's curve times cos(theta) to this power (0: the curve alone); the twin's own, so
    # never taken from [process], where it describes the monitor's model of the curve
    efficiency_cos_exponent: float = Field(0.0, ge=0, le=6)
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


# Upper bounds on the twin's errors, each far past a real profiler or robot (a value beyond
# one is a typo: it would empty every profile, or overflow the height field, without a word)
MAX_NOISE_MM = 1.0  # laser profilers' range noise is a few um; 1 mm is 20x the default
MAX_OUTLIER_OFFSET_MM = 50.0  # a ghost farther than the 50 mm measuring range is not seen
MAX_FAULT_HEIGHT_MM = 50.0  # a bump or dent of 50 mm is the whole part; the plate is 6 mm
MAX_FAULT_WIDTH_MM = 200.0  # wider than the 120 mm plate
MAX_FAULT_FACTOR = 10.0  # feed or efficiency multiplier: 10x full feed is no feeder
MAX_STANDOFF_CHANGE_MM = 100.0  # the nozzle would be far off the part's reach
MAX_DWELL_S = 600.0  # ten minutes at one corner


# [noise] preset = "realistic": a cold-spray cell's dirty profilers (docs/dirty-sensors.md
# says where each level comes from); keys given beside the preset override its values
NOISE_PRESETS: dict[str, dict] = {
    "realistic": {
        "range_sigma_mm": 0.05, "speckle_sigma_mm": 0.02, "dropout_prob": 0.02,
        "outlier_prob": 0.002, "plume_particle_prob": 0.02, "ghost_line_prob": 0.05,
        "specular_run_prob": 0.05, "burst_prob": 0.02, "clock_jitter_ms": 1.0,
        "lost_profile_prob": 0.005, "mount_drift_mm_min": 0.02,
    },
}


class NoiseConfig(_Model):
    # a named set of the levels below (NOISE_PRESETS); keys given beside it override it
    preset: Literal["realistic"] | None = None
    range_sigma_mm: float = Field(0.05, ge=0, le=MAX_NOISE_MM)
    speckle_sigma_mm: float = Field(0.0, ge=0, le=MAX_NOISE_MM)
    dropout_prob: float = Field(0.0, ge=0, le=1)
    outlier_prob: float = Field(0.0, ge=0, le=1)
    speckle_length_points: float = Field(4.0, gt=0)  # speckle correlation length along the line
    outlier_offset_mm: tuple[float, float] = (0.5, 5.0)  # ghost lies this far beyond, along ray
    min_intensity: float = Field(0.02, ge=0, lt=1)  # weaker returns (grazing incidence) dropped
    robot_repeatability_mm: float = Field(0.0, ge=0, le=MAX_NOISE_MM)  # IRB 4600: 0.05
    # The artefacts of a cold-spray cell (twin.profiler.artefacts), each off at 0. None of
    # their levels has a published figure for laser-line profilers on a cold-spray cell; the
    # "realistic" preset (scenarios/noise/realistic.toml) says how its levels were chosen.
    # Powder in the plume: a ray crossing the jet returns a particle in front of the surface
    # with this probability per profile where it meets the jet's axis, falling off as a
    # Gaussian of plume_particle_sigma_mm from it, times feed / plume_feed_ref_g_min, while
    # the spray is on.
    plume_particle_prob: float = Field(0.0, ge=0, le=1)
    plume_particle_sigma_mm: float = Field(3.0, gt=0, le=MAX_FAULT_WIDTH_MM)
    plume_feed_ref_g_min: float = Field(26.0, gt=0)
    # Secondary reflections: per profile, the probability of a stretch of ghost_line_points
    # [min, max] points replaced by a second reflection ghost_line_offset_mm behind the
    # surface, its offset growing along the stretch; placed at the profile's sharpest concave
    # kink (a wall foot, a corner) where it has one, else anywhere.
    ghost_line_prob: float = Field(0.0, ge=0, le=1)
    ghost_line_points: tuple[int, int] = (4, 12)
    ghost_line_offset_mm: tuple[float, float] = (0.4, 2.0)
    # Specular dropouts and saturation: per profile, the probability of a run of
    # specular_run_points [min, max] points mirrored into the camera: lost, or (half of the
    # runs) saturated: clipped to full intensity, the peak's centroid biased by
    # saturation_bias_mm along the ray.
    specular_run_prob: float = Field(0.0, ge=0, le=1)
    specular_run_points: tuple[int, int] = (5, 40)
    saturation_bias_mm: float = Field(0.05, ge=0, le=MAX_NOISE_MM)
    # Outlier bursts: per profile, the probability of a stretch of burst_points [min, max]
    # points misread together, burst_offset_mm [min, max] in front of or behind the surface.
    burst_prob: float = Field(0.0, ge=0, le=1)
    burst_points: tuple[int, int] = (3, 12)
    burst_offset_mm: tuple[float, float] = (0.4, 3.0)
    # Clock jitter: each profile's stamp off its exposure by up to +- this (uniform) [ms];
    # lost profiles: this share of profiles never arrives.
    clock_jitter_ms: float = Field(0.0, ge=0, le=50)
    lost_profile_prob: float = Field(0.0, ge=0, lt=1)
    # Slow mount drift: the profiler creeps along its own z_S by this many mm per minute of
    # process time (the mount warms up), each sensor at its share of it (1, -0.6, 0.8).
    mount_drift_mm_min: float = Field(0.0, ge=-1, le=1)

    @model_validator(mode="before")
    @classmethod
    def _preset(cls, data):
        if isinstance(data, dict) and data.get("preset") in NOISE_PRESETS:
            return {**NOISE_PRESETS[data["preset"]], **data}
        return data

    @model_validator(mode="after")
    def _outlier_offsets(self):
        lo, hi = self.outlier_offset_mm
        if not 0 <= lo <= hi <= MAX_OUTLIER_OFFSET_MM:
            raise ValueError(f"outlier_offset_mm must be [min, max] with 0 <= min <= max <= "
                             f"{MAX_OUTLIER_OFFSET_MM:g} (the profilers' measuring range)")
        for name in ("ghost_line_points", "specular_run_points", "burst_points",
                     "ghost_line_offset_mm", "burst_offset_mm"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"{name} must be [min, max] with 0 < min <= max")
        for name in ("ghost_line_offset_mm", "burst_offset_mm"):
            if getattr(self, name)[1] > MAX_OUTLIER_OFFSET_MM:
                raise ValueError(f"{name} must be at most {MAX_OUTLIER_OFFSET_MM:g} mm (the "
                                 "profilers' measuring range)")
        return self

    def dirty(self) -> bool:
        """Whether any artefact of twin.profiler.artefacts is on."""
        return any(getattr(self, k) for k in (
            "plume_particle_prob", "ghost_line_prob", "specular_run_prob", "burst_prob",
            "clock_jitter_ms", "lost_profile_prob", "mount_drift_mm_min"))


class FaultConfig(_Model):
    """One injected fault. Which fields apply depends on ``kind`` (see twin.world.faults)."""

    kind: Literal["feed_step", "feed_drift", "feed_drop", "clog", "efficiency_drift",
                  "standoff_change", "bump", "dent", "corner_dwell"]
    layers: tuple[int, int] | None = None  # inclusive layer window
    time_s: tuple[float, float] | None = None  # process-time window
    # feed or efficiency multiplier at full effect
    factor: float | None = Field(None, ge=0, le=MAX_FAULT_FACTOR)
    per_layer: float | None = Field(None, ge=-1, le=1)  # efficiency drift per layer (fraction)
    # standoff change
    delta_mm: float | None = Field(None, ge=-MAX_STANDOFF_CHANGE_MM, le=MAX_STANDOFF_CHANGE_MM)
    center_O_mm: tuple[float, float] | None = None  # bump / dent
    height_mm: float | None = Field(None, gt=0, le=MAX_FAULT_HEIGHT_MM)
    width_mm: float | None = Field(None, gt=0, le=MAX_FAULT_WIDTH_MM)
    corner_angle_deg: float | None = Field(None, ge=0, le=360)
    extra_dwell_s: float | None = Field(None, gt=0, le=MAX_DWELL_S)

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


class TwinScenario(Scenario):
    """A whole scenario file with the twin's sections typed (see the module docstring)."""

    twin_process: TwinProcessConfig = TwinProcessConfig()
    cell: CellConfig = CellConfig()
    noise: NoiseConfig = NoiseConfig()
    faults: tuple[FaultConfig, ...] = ()
    calibration_error: CalibrationPerturbation | None = None

    @model_validator(mode="after")
    def _twin_plateau(self):
        tp = self.twin_process
        tc = tp.critical_angle_deg or self.process.critical_angle_deg
        if tp.efficiency_curve == "plateau" and tp.plateau_angle_deg >= tc:
            raise ValueError(f"twin_process.plateau_angle_deg {tp.plateau_angle_deg} must be "
                             f"below the twin's critical_angle_deg {tc}")
        return self


register_scenario_model(TwinScenario)
