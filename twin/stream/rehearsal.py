"""Rehearse a profiler calibration in the twin: scan the sphere artifact from planned poses.

The twin's cell (:class:`twin.cell.cell.CellModel`) holds the true profiler poses and the arm; the
artifact is cast analytically (spheres, posts, plate) with the fan model of ``[sensors]``.
What comes out is exactly what a real calibration run records: robot states and profiles.

Noise model
-----------
- profile noise: each point moves along its laser ray by ``N(0, profile_noise_mm)``;
  ``scenario.noise.outlier_prob`` of the points jump 1..5 mm along the ray;
- robot repeatability ``R`` (ISO 9283 positional repeatability RP = mean + 3 sigma of the
  distance to the mean position): each pose's true flange position is off the reported one
  by an isotropic Gaussian with ``sigma = R / 3.62`` per axis, which makes RP equal ``R``;
- the prior handed to the solver is the truth off by ``prior_error_mm`` / ``prior_error_deg``
  (a coarse hand-measured setup), the artifact's true mount off its description by
  ``mount_error_mm`` / ``mount_error_deg``.

The nozzle body always keeps the artifact out (collision), and by default it also hides laser
and camera rays as in the cell (``nozzle_occlusion``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from calib.artifact import Artifact
from calib.planning import PlanOptions, PosePlan, plan_poses
from calib.scan_model import FanModel, scan_artifact
from calib.solver import ISO9283_RP_PER_SIGMA
from dm2.core.frames import make_T
from dm2.core.messages import Calibration, Profile, RobotState
from twin.cell.cell import CellModel
from twin.cell.kinematics import ReachError
from twin.profiler.occluders import nozzle_occluder

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RehearsalConfig:
    n_poses: int = 24
    profile_noise_mm: float = 0.03
    robot_repeatability_mm: float = 0.02
    seed: int = 0
    prior_error_mm: float = 2.0
    prior_error_deg: float = 1.0
    mount_error_mm: float = 0.0
    mount_error_deg: float = 0.0
    nozzle_occlusion: bool = True
    hold_s: float = 0.2  # the arm stands still this long at each pose
    plan: PlanOptions = PlanOptions()

    def __post_init__(self):
        for name in ("profile_noise_mm", "robot_repeatability_mm", "prior_error_mm",
                     "prior_error_deg", "mount_error_mm", "mount_error_deg"):
            if not np.isfinite(getattr(self, name)) or getattr(self, name) < 0:
                raise ValueError(f"rehearsal: {name} must be finite and >= 0")
        if self.n_poses < 1:
            raise ValueError(f"rehearsal: n_poses must be >= 1, got {self.n_poses}")


@dataclass(frozen=True)
class Rehearsal:
    """A simulated calibration run and the truth it is judged against.

    Attributes
    ----------
    messages : list of RobotState and Profile in stamp order
    truth : Calibration, the twin's true calibration
    true_T_F_A : (4, 4) float64, where the artifact really sits on the flange [mm]
    prior_T_B_S : dict sensor id -> (4, 4), the coarse poses given to the solver
    plan : PosePlan, the planned flange poses
    """

    messages: list
    truth: Calibration
    true_T_F_A: np.ndarray
    prior_T_B_S: dict
    plan: PosePlan


def _perturb(T: np.ndarray, rng: np.random.Generator, mm: float, deg: float) -> np.ndarray:
    """``T @ dT`` with a rotation of ``deg`` about a random axis and a shift of ``mm``."""
    axis, shift = rng.normal(size=3), rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    shift *= mm / np.linalg.norm(shift)
    return T @ make_T(Rotation.from_rotvec(np.radians(deg) * axis), shift)


def _profile(sensor_id, xz_S, rng, cfg: RehearsalConfig, outlier_prob: float, stamp_s, counter):
    valid = np.isfinite(xz_S[:, 0])
    xz = xz_S.copy()
    rng_mm = np.linalg.norm(xz[valid], axis=1)
    dirs = xz[valid] / rng_mm[:, None]
    jitter = rng.normal(0.0, cfg.profile_noise_mm, valid.sum())
    jump = rng.random(valid.sum()) < outlier_prob
    jitter[jump] += rng.uniform(1.0, 5.0, jump.sum()) * rng.choice([-1.0, 1.0], jump.sum())
    xz[valid] += dirs * jitter[:, None]
    intensity = np.where(valid, 0.8, 0.0).astype(np.float32)
    return Profile(sensor_id, stamp_s, counter, xz, valid, intensity)


def rehearse_calibration(scenario, artifact: Artifact,
                         cfg: RehearsalConfig | None = None) -> Rehearsal:
    """Plan poses, move the twin's arm through them and scan the artifact with every profiler.

    Raises
    ------
    calib.solver.CalibrationError
        when no plan of ``cfg.n_poses`` visible, reachable, collision-free poses exists.
    """
    cfg = cfg or RehearsalConfig()
    cell = CellModel.from_scenario(scenario)
    truth = cell.calibration()
    artifact = artifact.with_mount(truth.T_F_O)
    rng = np.random.default_rng(cfg.seed)
    prior = {sid: _perturb(T, rng, cfg.prior_error_mm, cfg.prior_error_deg)
             for sid, T in sorted(truth.T_B_S.items())}
    true_T_F_A = _perturb(artifact.T_F_A, rng, cfg.mount_error_mm, cfg.mount_error_deg)
    nozzle = nozzle_occluder(cell.T_B_N, scenario.cell)
    fan = FanModel.from_config(scenario.sensors)
    occluders = (nozzle,) if cfg.nozzle_occlusion else ()

    def reachable(T_B_F: np.ndarray) -> bool:
        try:
            cell.ik(T_B_F, cell.home_joints_rad)
        except ReachError:
            return False
        return True

    plan = plan_poses(artifact, prior, fan, cell.spot_B, cfg.n_poses, reachable,
                      occluders=occluders, keep_out=(nozzle,), options=cfg.plan, seed=cfg.seed)
    sigma_robot = cfg.robot_repeatability_mm / ISO9283_RP_PER_SIGMA
    dt_state = 1.0 / cell.robot_state_hz
    messages, seq = [], 0
    for i, T_B_F in enumerate(plan.T_B_F):
        t0 = i * cfg.hold_s
        joints = cell.ik(T_B_F, cell.home_joints_rad)
        for t in np.arange(t0, t0 + cfg.hold_s - 0.5 * dt_state, dt_state):
            messages.append(RobotState(float(t), seq, joints, T_B_F))
            seq += 1
        T_true_B_F = make_T(T_B_F[:3, :3], T_B_F[:3, 3] + rng.normal(0.0, sigma_robot, 3))
        T_B_A = T_true_B_F @ true_T_F_A
        for j, sid in enumerate(sorted(truth.T_B_S)):
            xz, _ = scan_artifact(artifact, T_B_A, truth.T_B_S[sid], fan, occluders)
            stamp = t0 + 0.5 * cfg.hold_s + j * scenario.sensors.cascade_s
            messages.append(_profile(sid, xz, rng, cfg, scenario.noise.outlier_prob, stamp, i))
    messages.sort(key=lambda m: m.stamp_s)
    log.info("rehearsal: %d poses, %d messages", len(plan.T_B_F), len(messages))
    return Rehearsal(messages, truth, true_T_F_A, prior, plan)
