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

from dm2.core.config import ProcessConfig, Scenario, _Model, register_scenario_model


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
