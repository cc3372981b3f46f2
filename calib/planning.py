"""Plan flange poses that sweep the sphere artifact through every profiler's laser plane.

The laser planes of the three profilers meet at the deposition spot, so each pose places the
artifact's sphere centroid near the spot (offset within a box) and turns it: yaw over the full
circle, tilt about a horizontal axis up to ``max_tilt_deg``. Samples come from a scrambled
Halton sequence (well spread in all six parameters); a candidate is kept when it is reachable
(a callable, so this module needs no robot model), keeps clear of the keep-out bodies (the
nozzle) and every sensor sees at least one sphere with enough points, occlusions included.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import qmc

from calib.artifact import Artifact
from calib.scan_model import Cylinder, FanModel, scan_artifact
from calib.solver import CalibrationError
from dm2.core.frames import apply, invert, make_T

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PlanOptions:
    max_tilt_deg: float = 20.0
    offset_lo_mm: tuple[float, float, float] = (-20.0, -20.0, -20.0)  # centroid - spot, in B
    offset_hi_mm: tuple[float, float, float] = (20.0, 20.0, 8.0)
    min_points: int = 12  # sphere points a sensor must see in a pose
    # a sighting counts when the laser plane cuts the sphere at this fraction of its radius
    # from the centre: near-centre cuts leave the plane's offset along y_S weakly determined
    cut_height_range: tuple[float, float] = (0.35, 0.9)
    clearance_mm: float = 3.0  # artifact to occluder
    max_candidates_per_pose: int = 40


@dataclass(frozen=True)
class PosePlan:
    """Planned poses and what each sensor is predicted to see.

    Attributes
    ----------
    T_B_F : (n, 4, 4) float64, flange poses [mm]
    T_B_A : (n, 4, 4) float64, artifact poses they give (nominal mount) [mm]
    spheres_seen : (n, s) int64, spheres seen per pose and sensor (``sensor_ids`` order)
    sensor_ids : tuple of str
    """

    T_B_F: np.ndarray
    T_B_A: np.ndarray
    spheres_seen: np.ndarray
    sensor_ids: tuple


def artifact_pose(artifact: Artifact, spot_B: np.ndarray, yaw_rad: float, tilt_axis_rad: float,
                  tilt_rad: float, offset_B: np.ndarray) -> np.ndarray:
    """``T_B_A`` putting the sphere centroid at ``spot_B + offset_B``, plate facing +z_B."""
    axis = np.array([np.cos(tilt_axis_rad), np.sin(tilt_axis_rad), 0.0])
    R = Rotation.from_rotvec(axis * tilt_rad) * Rotation.from_euler("z", yaw_rad)
    centroid_A = artifact.centers_A.mean(axis=0)
    return make_T(R, np.asarray(spot_B) + offset_B - R.apply(centroid_A))


def collides(artifact: Artifact, T_B_A: np.ndarray, occluders, clearance_mm: float) -> bool:
    """True when a sphere or the plate top comes within ``clearance_mm`` of an occluder."""
    Lx, Ly, _ = artifact.plate_size_mm
    gx, gy = np.meshgrid(np.linspace(0, Lx, 9), np.linspace(0, Ly, 9))
    plate_B = apply(T_B_A, np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)]))
    spheres_B = apply(T_B_A, artifact.centers_A)
    for occ in occluders:
        T_B_C = np.asarray(occ.T_B_C, dtype=np.float64)
        a = T_B_C[:3, 2]
        for pts, radii in ((spheres_B, artifact.radii_mm), (plate_B, np.zeros(len(plate_B)))):
            v = pts - T_B_C[:3, 3]
            h = v @ a
            radial = np.linalg.norm(v - np.outer(h, a), axis=1)
            gap = np.hypot(np.maximum(radial - occ.radius_mm, 0.0),
                           np.maximum.reduce([-h, h - occ.length_mm, np.zeros_like(h)]))
            if np.any(gap < radii + clearance_mm):
                return True
    return False


def plan_poses(artifact: Artifact, T_B_S: dict, fan: FanModel, spot_B: np.ndarray,
               n_poses: int, reachable: Callable[[np.ndarray], bool] | None = None,
               occluders: tuple[Cylinder, ...] = (), keep_out: tuple[Cylinder, ...] = (),
               options: PlanOptions | None = None, seed: int = 0) -> PosePlan:
    """Choose ``n_poses`` flange poses from which every sensor sees the artifact.

    Parameters
    ----------
    T_B_S : dict sensor id -> (4, 4), the (prior) sensor poses used to predict visibility
    spot_B : (3,) [mm], where the laser planes meet
    reachable : ``reachable(T_B_F) -> bool``; None accepts every pose
    occluders : bodies that hide the laser or the camera (checked in the predicted profiles)
    keep_out : bodies the artifact must keep ``clearance_mm`` away from (the nozzle)

    Raises
    ------
    CalibrationError
        when too few candidates pass the checks.
    """
    opt = options or PlanOptions()
    if n_poses < 1:
        raise ValueError(f"n_poses must be >= 1, got {n_poses}")
    if artifact.T_F_A is None:
        raise ValueError(f"artifact {artifact.name}: mount unknown; resolve it with "
                         "artifact.with_mount(T_F_O)")
    sensor_ids = tuple(sorted(T_B_S))
    T_A_F = invert(artifact.T_F_A)
    budget = n_poses * opt.max_candidates_per_pose
    samples = qmc.Halton(d=6, scramble=True, seed=seed).random(budget)
    kept_F, kept_A, seen_rows = [], [], []
    rejected = {"unreachable": 0, "collision": 0, "not_seen": 0}
    for u in samples:
        lo, hi = np.asarray(opt.offset_lo_mm), np.asarray(opt.offset_hi_mm)
        offset = lo + u[3:6] * (hi - lo)
        T_B_A = artifact_pose(artifact, spot_B, 2 * np.pi * u[0], 2 * np.pi * u[1],
                              np.radians(opt.max_tilt_deg) * np.sqrt(u[2]), offset)
        T_B_F = T_B_A @ T_A_F
        if keep_out and collides(artifact, T_B_A, keep_out, opt.clearance_mm):
            rejected["collision"] += 1
            continue
        row = []
        for sid in sensor_ids:
            _, feature = scan_artifact(artifact, T_B_A, T_B_S[sid], fan, occluders)
            counts = np.bincount(feature[feature >= 0], minlength=artifact.n_spheres)
            y_S = apply(invert(T_B_S[sid]) @ T_B_A, artifact.centers_A)[:, 1]
            cut = np.abs(y_S) / artifact.radii_mm
            good = (cut >= opt.cut_height_range[0]) & (cut <= opt.cut_height_range[1])
            row.append(int(np.sum((counts >= opt.min_points) & good)))
        if min(row) == 0:
            rejected["not_seen"] += 1
            continue
        if reachable is not None and not reachable(T_B_F):
            rejected["unreachable"] += 1
            continue
        kept_F.append(T_B_F)
        kept_A.append(T_B_A)
        seen_rows.append(row)
        if len(kept_F) == n_poses:
            break
    if len(kept_F) < n_poses:
        raise CalibrationError(
            f"pose planning found {len(kept_F)} of {n_poses} poses in {budget} candidates "
            f"(rejected: {rejected}); the artifact does not pass through every laser plane "
            "from reachable, collision-free poses")
    log.info("planned %d poses (rejected %s)", n_poses, rejected)
    return PosePlan(np.stack(kept_F), np.stack(kept_A), np.array(seen_rows, dtype=np.int64),
                    sensor_ids)
