"""Rehearse a profiler calibration in the twin: scan the sphere artifact from planned poses.

The twin's cell (:class:`twin.cell.cell.CellModel`) built from the scenario is the cell file:
the nominal (CAD) layout a user starts from, and the prior the calibration is given. The cell
as built differs from it by seeded errors, and the artifact is rendered by the twin's own
profilers (:class:`twin.profiler.sensor.VirtualProfiler` on the analytic solid of
:mod:`twin.profiler.artifact_surface`): the build's fan layout, measuring range, camera
occlusion, grazing-angle intensity floor, range noise, speckle, dropouts and ghosts
(the scenario's ``[noise]``, or ``RehearsalConfig.noise``), then the sensor's intrinsic error
(:mod:`twin.profiler.intrinsics`). What comes out is what a real calibration run records:
robot states and profiles, plus the flange poses of a nozzle touch-off
(:mod:`twin.stream.touch_off`).

Errors, all drawn from ``RehearsalConfig.seed``
-----------------------------------------------
- sensors as built: each true ``T_B_S`` is the cell file's off by ``as_built_error_mm`` and
  ``as_built_error_deg`` (random directions), unless ``true_T_B_S`` gives them;
- the artifact's true mount off its nominal one by ``mount_error_mm`` / ``mount_error_deg``;
  the true nozzle exit off the cell file's by ``nozzle_error_mm``;
- the artifact as built: radii and centres off the certified values, uniform within the
  certificate's uncertainties;
- intrinsic errors per sensor: ``z_scale_error``, ``fan_angle_offset_deg``,
  ``x_distortion_mm`` with random signs;
- robot repeatability ``R`` (ISO 9283 RP = mean + 3 sigma of the distance to the mean
  position): each pose's true flange position is off the reported one by an isotropic
  Gaussian with ``sigma = R / 3.62`` per axis.

Poses are planned by the calibration's own planner (:mod:`calib.planning`) on the prior, as on
the real cell; the profiles are never predicted with the calibration's scan model. The nozzle
body keeps the artifact out (collision) and hides laser and camera rays (``nozzle_occlusion``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from calib.artifact import Artifact
from calib.planning import PlanOptions, PosePlan, plan_poses
from calib.scan_model import FanModel
from calib.solver import ISO9283_RP_PER_SIGMA
from dm2.core.frames import make_T
from dm2.core.messages import Calibration, RobotState
from twin.cell.cell import CellModel
from twin.cell.kinematics import ReachError
from twin.profiler.artifact_surface import SphereArtifactSurface
from twin.profiler.intrinsics import seeded_intrinsic_errors
from twin.profiler.occluders import nozzle_occluder
from twin.profiler.sensor import VirtualProfiler
from twin.schema import NoiseConfig
from twin.stream.touch_off import touch_off_poses

log = logging.getLogger(__name__)

CALIBRATION_NOISE_STREAM = 0xCA1B  # offsets the profiler noise seed of a calibration run


@dataclass(frozen=True)
class RehearsalConfig:
    n_poses: int = 24
    seed: int = 0
    noise: NoiseConfig | None = None  # None: the scenario's [noise]
    robot_repeatability_mm: float = 0.02
    as_built_error_mm: float = 2.0
    as_built_error_deg: float = 1.0
    mount_error_mm: float = 0.0
    mount_error_deg: float = 0.0
    nozzle_error_mm: float = 0.0
    artifact_within_certificate: bool = True
    z_scale_error: float = 0.0
    fan_angle_offset_deg: float = 0.0
    x_distortion_mm: float = 0.0
    first_pass_poses: int = 8  # poses of the first pass (with ``refine``)
    # the first pass aims the laser planes near the sphere centres, so that a prior a few mm
    # off still cuts the spheres
    first_pass_plan: PlanOptions = PlanOptions(cut_height_range=(0.0, 0.45))
    touch_offs: int = 4  # 0: no touch-off (T_B_N stays the cell file's)
    touch_seat_error_mm: float = 0.01
    nozzle_occlusion: bool = True
    hold_s: float = 0.2  # the arm stands still this long at each pose
    plan: PlanOptions = PlanOptions()
    true_T_B_S: dict | None = field(default=None, hash=False, compare=False)

    def __post_init__(self):
        for name in ("robot_repeatability_mm", "as_built_error_mm", "as_built_error_deg",
                     "mount_error_mm", "mount_error_deg", "nozzle_error_mm", "z_scale_error",
                     "fan_angle_offset_deg", "x_distortion_mm", "touch_seat_error_mm"):
            if not np.isfinite(getattr(self, name)) or getattr(self, name) < 0:
                raise ValueError(f"rehearsal: {name} must be finite and >= 0, got "
                                 f"{getattr(self, name)!r}")
        if self.n_poses < 1:
            raise ValueError(f"rehearsal: n_poses must be >= 1, got {self.n_poses}")
        if self.touch_offs == 1 or self.touch_offs < 0:
            raise ValueError(f"rehearsal: touch_offs must be 0 or >= 2, got {self.touch_offs}")


@dataclass(frozen=True)
class Rehearsal:
    """A simulated calibration run and the truth it is judged against.

    Attributes
    ----------
    messages : list of RobotState and Profile in stamp order
    truth : Calibration, the cell as built (sensors, plate / artifact mount, nozzle)
    prior : Calibration, the cell file (nominal CAD layout), never derived from the truth
    true_T_F_A : (4, 4) float64, where the artifact really sits on the flange [mm]
    plan : PosePlan, the planned flange poses
    touch_T_B_F : (n, 4, 4) float64, reported flange poses of the nozzle touch-off
    intrinsics : dict sensor id -> IntrinsicError, the sensors' true intrinsic errors
    surface : SphereArtifactSurface, the artifact as built
    """

    messages: list
    truth: Calibration
    prior: Calibration
    true_T_F_A: np.ndarray
    plan: PosePlan
    touch_T_B_F: np.ndarray
    intrinsics: dict
    surface: SphereArtifactSurface

    @property
    def prior_T_B_S(self) -> dict:
        return self.prior.T_B_S


def perturb(T: np.ndarray, rng: np.random.Generator, mm: float, deg: float) -> np.ndarray:
    """``T @ dT`` with a rotation of ``deg`` about a random axis and a shift of ``mm``."""
    axis, shift = rng.normal(size=3), rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    shift *= mm / np.linalg.norm(shift)
    return T @ make_T(Rotation.from_rotvec(np.radians(deg) * axis), shift)


def as_built_sensor_poses(scenario, seed: int, mm: float, deg: float) -> dict:
    """The sensors' true poses: the cell file's layout off by ``mm`` / ``deg`` (seeded)."""
    rng = np.random.default_rng([int(seed), 0x5E75])
    nominal = CellModel.from_scenario(scenario).T_B_S
    return {sid: perturb(T, rng, mm, deg) for sid, T in sorted(nominal.items())}


def _as_built_artifact(artifact: Artifact, rng, within: bool) -> SphereArtifactSurface:
    k = artifact.n_spheres
    dr = rng.uniform(-1.0, 1.0, k) * artifact.radius_uncertainty_mm if within else np.zeros(k)
    dc = (rng.uniform(-1.0, 1.0, (k, 3)) * artifact.position_uncertainty_mm if within
          else np.zeros((k, 3)))
    return SphereArtifactSurface(artifact.centers_A + dc, artifact.radii_mm + dr,
                                 artifact.post_radii_mm, artifact.plate_size_mm)


def rehearse_calibration(scenario, artifact: Artifact, cfg: RehearsalConfig | None = None,
                         refine=None) -> Rehearsal:
    """Plan poses, move the twin's arm through them and scan the artifact with every profiler.

    With ``refine``, the run has two passes as on a real cell whose sensors sit a few mm off
    their CAD poses: ``cfg.first_pass_poses`` poses planned on the prior, then
    ``refine(messages, prior_T_B_S) -> {sensor id: T_B_S}`` (a first solve, supplied by the
    caller) and the remaining poses planned on that estimate, so that the laser planes cut
    the spheres where the plan meant them to.

    Raises
    ------
    calib.solver.CalibrationError
        when no plan of ``cfg.n_poses`` visible, reachable, collision-free poses exists.
    """
    cfg = cfg or RehearsalConfig()
    cell = CellModel.from_scenario(scenario)
    prior = cell.calibration()
    nominal_art = artifact.with_mount(prior.T_F_O)
    rng = np.random.default_rng(cfg.seed)
    true_T_B_S = (dict(cfg.true_T_B_S) if cfg.true_T_B_S is not None else
                  as_built_sensor_poses(scenario, cfg.seed, cfg.as_built_error_mm,
                                        cfg.as_built_error_deg))
    true_T_F_A = perturb(nominal_art.T_F_A, rng, cfg.mount_error_mm, cfg.mount_error_deg)
    true_T_B_N = perturb(prior.T_B_N, rng, cfg.nozzle_error_mm, 0.0)
    surface = _as_built_artifact(artifact, rng, cfg.artifact_within_certificate)
    intrinsics = seeded_intrinsic_errors(sorted(true_T_B_S), rng, cfg.z_scale_error,
                                         cfg.fan_angle_offset_deg, cfg.x_distortion_mm)
    truth = Calibration(T_B_S=true_T_B_S,
                        T_F_O=true_T_F_A if artifact.work_object else prior.T_F_O,
                        T_B_N=true_T_B_N)
    noise = cfg.noise or scenario.noise
    # the profilers' own noise stream, not the one the build with the same seed draws from
    noise_seed = (int(cfg.seed) * 1_000_003 + CALIBRATION_NOISE_STREAM) & 0xFFFFFFFF
    profilers = {sid: VirtualProfiler(sid, T, scenario.sensors, noise, seed=noise_seed)
                 for sid, T in sorted(true_T_B_S.items())}
    nozzle_prior = nozzle_occluder(prior.T_B_N, scenario.cell)
    nozzle_true = nozzle_occluder(true_T_B_N, scenario.cell)
    occluders = (nozzle_true,) if cfg.nozzle_occlusion else ()

    def reachable(T_B_F: np.ndarray) -> bool:
        try:
            cell.ik(T_B_F, cell.home_joints_rad)
        except ReachError:
            return False
        return True

    def plan(T_B_S: dict, n: int, seed: int, options: PlanOptions) -> PosePlan:
        return plan_poses(nominal_art, T_B_S, FanModel.from_config(scenario.sensors),
                          cell.spot_B, n, reachable,
                          occluders=(nozzle_prior,) if cfg.nozzle_occlusion else (),
                          keep_out=(nozzle_prior,), options=options, seed=seed)

    sigma_robot = cfg.robot_repeatability_mm / ISO9283_RP_PER_SIGMA
    messages: list = []

    def render(poses: PosePlan, first: int) -> None:
        dt_state = 1.0 / cell.robot_state_hz
        for i, T_B_F in enumerate(poses.T_B_F, start=first):
            t0 = i * cfg.hold_s
            joints = cell.ik(T_B_F, cell.home_joints_rad)
            seq = len(messages)
            for t in np.arange(t0, t0 + cfg.hold_s - 0.5 * dt_state, dt_state):
                messages.append(RobotState(float(t), seq, joints, T_B_F))
                seq += 1
            T_true_B_F = make_T(T_B_F[:3, :3], T_B_F[:3, 3] + rng.normal(0.0, sigma_robot, 3))
            T_B_A = T_true_B_F @ true_T_F_A
            for j, (sid, prof) in enumerate(profilers.items()):
                stamp = t0 + 0.5 * cfg.hold_s + j * scenario.sensors.cascade_s
                profile = prof.scan(surface, T_B_A, stamp, i, occluders)
                messages.append(intrinsics[sid].apply(profile, scenario.sensors))

    n_first = cfg.first_pass_poses if refine is not None else 0
    if not 0 <= n_first < cfg.n_poses:
        raise ValueError(f"rehearsal: first_pass_poses {n_first} must lie in [0, n_poses)")
    poses = plan(prior.T_B_S, n_first or cfg.n_poses, cfg.seed,
                 cfg.first_pass_plan if n_first else cfg.plan)
    render(poses, 0)
    if n_first:
        estimate = refine(sorted(messages, key=lambda m: m.stamp_s), prior.T_B_S)
        second = plan(estimate, cfg.n_poses - n_first, cfg.seed + 1, cfg.plan)
        render(second, n_first)
        poses = PosePlan(np.concatenate([poses.T_B_F, second.T_B_F]),
                         np.concatenate([poses.T_B_A, second.T_B_A]),
                         np.concatenate([poses.spheres_seen, second.spheres_seen]),
                         poses.sensor_ids)
    messages.sort(key=lambda m: m.stamp_s)
    touches = np.zeros((0, 4, 4))
    if cfg.touch_offs:
        if artifact.touch_mark_A is None:
            raise ValueError(f"artifact {artifact.name}: no plate.touch_mark_mm for the nozzle "
                             "touch-off (set touch_offs = 0 to skip it)")
        touches = touch_off_poses(artifact.touch_mark_A, true_T_F_A, true_T_B_N, np.eye(3),
                                  cfg.touch_offs, rng, cfg.touch_seat_error_mm, sigma_robot,
                                  reachable)
    log.info("rehearsal: %d poses, %d messages, %d touches", len(poses.T_B_F), len(messages),
             len(touches))
    return Rehearsal(messages, truth, prior, true_T_F_A, poses, touches, intrinsics, surface)


def write_rehearsal_recording(sim: Rehearsal, path) -> None:
    """Record the run to MCAP as the cell would: robot states and profiles, the prior (the
    cell file) as the recording's calibration, the touch-off poses as ``touch_off.toml``.
    Nothing of the truth goes into the file."""
    from calib.touch_off import TOUCH_OFF_ATTACHMENT, touch_off_to_toml
    from dm2.core.calibration_io import calibration_to_toml
    from dm2.io.recording import CALIBRATION_ATTACHMENT
    from dm2.io.recording_writer import RecordingWriter

    atts = {CALIBRATION_ATTACHMENT: calibration_to_toml(sim.prior).encode()}
    if len(sim.touch_T_B_F):
        atts[TOUCH_OFF_ATTACHMENT] = touch_off_to_toml(sim.touch_T_B_F).encode()
    writer = RecordingWriter(path, attachments=atts)
    try:
        writer.write_static_tf(sim.prior)
        for m in sim.messages:
            writer.write(m)
    finally:
        writer.close()
