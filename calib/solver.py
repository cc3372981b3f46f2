"""Hand-eye solve of the stationary profilers' poses ``T_B_S`` from sphere-artifact profiles.

Model: a point ``p_S = (x, 0, z)`` of a profile taken at flange pose ``T_B_F`` that lies on
sphere ``k`` satisfies ``| T_A_F T_F_B T_B_S p_S - c_k | = r_k`` (``c_k``, ``r_k`` in the
artifact frame ``A``; ``T_F_A`` known, or co-estimated with ``estimate_mount``).

Steps: associate points with spheres using the prior; closed-form start from circle fits per
profile (each arc gives the sphere centre in ``S``, the robot gives it in ``B``; Kabsch);
degeneracy check on the scaled Jacobian; robust nonlinear least squares (soft-L1) with
re-association and outlier gates shrinking to a multiple of the robust residual scale;
covariance from the Jacobian; per-pose residuals. Parameters are right perturbations
``T = T0 @ [Exp(w), v]``, so uncertainty and weak directions are expressed in ``S`` axes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calib.artifact import Artifact
from calib.checks import (  # the errors are part of this module's API
    CalibrationError,
    DegenerateError,
    NotObservedError,
    check_degenerate,
    check_observed,
)
from calib.fitting import (
    exp_se3,
    kabsch,
    right_jacobian_so3,
    robust_circle_fit,
    sphere_center_from_arc,
    spread_mm,
)
from calib.observations import Observation
from dm2.core.frames import invert

log = logging.getLogger(__name__)

__all__ = ["CalibrationError", "CalibrationResult", "DegenerateError", "ISO9283_RP_PER_SIGMA",
           "NotObservedError", "SensorEstimate", "SolverOptions", "solve_calibration"]

ISO9283_RP_PER_SIGMA = 3.62  # ISO 9283 repeatability RP / per-axis sigma (isotropic Gaussian)

@dataclass(frozen=True)
class SolverOptions:
    estimate_mount: bool = False  # co-estimate T_F_A (T_F_O when the artifact is the plate)
    init_gate_mm: float | None = None  # default: a quarter of the smallest sphere radius
    gate_sigmas: float = 5.0  # later gates: this many robust residual sigmas
    min_gate_mm: float = 0.05
    loss_scale_mm: float = 0.1  # soft-L1 knee
    rounds: int = 3
    min_points: int = 8  # sphere points for a profile to count
    min_profiles: int = 3
    rotation_scale_mm: float = 50.0  # lever arm that makes radians comparable with mm
    min_condition: float = 2e-3  # smallest / largest scaled singular value
    # per-axis sigma of the flange position error at each pose (robot repeatability); > 0
    # adds one nuisance translation per pose, shared by every sensor seeing that pose
    robot_sigma_mm: float = 0.0
    # co-estimate each sensor's range (z_S) scale: reported z = true z * (1 + error); the
    # artifact's known radii make it observable once the spheres are cut across the range
    estimate_z_scale: bool = False
    z_scale_lever_mm: float = 100.0  # range that makes a scale comparable with mm


@dataclass(frozen=True)
class SensorEstimate:
    """One profiler's estimated pose and its quality figures.

    ``sigma_*`` are 1-sigma from the Jacobian (about / along the ``S`` axes); they ignore
    robot repeatability, which is correlated within a pose.
    """

    sensor_id: str
    T_B_S: np.ndarray
    sigma_rotation_deg: np.ndarray
    sigma_translation_mm: np.ndarray
    residual_rms_mm: float
    n_points: int
    n_outliers: int
    n_profiles: int
    condition: float
    per_pose_rms_mm: dict = field(default_factory=dict)
    z_gain: float = 1.0  # true z = reported z * z_gain (1: not estimated)
    sigma_z_gain: float | None = None

    @property
    def z_scale_error(self) -> float:
        """The sensor's range scale error as estimated: reported z / true z - 1."""
        return 1.0 / self.z_gain - 1.0


@dataclass(frozen=True)
class CalibrationResult:
    sensors: dict  # sensor id -> SensorEstimate
    T_F_A: np.ndarray
    mount_estimated: bool
    sigma_mount_rotation_deg: np.ndarray | None = None
    sigma_mount_translation_mm: np.ndarray | None = None

    @property
    def T_B_S(self) -> dict:
        return {sid: est.T_B_S for sid, est in self.sensors.items()}


class _Problem:
    """Stacked points of all sensors and the residual / Jacobian of the sphere model."""

    def __init__(self, observations: list[Observation], sensors: list[str], artifact: Artifact,
                 z_scale: bool = False):
        self.sensors, self.art, self.z_scale = sensors, artifact, z_scale
        self.z_gain = np.ones(len(sensors))
        self.obs = [o for o in observations if o.sensor_id in sensors]
        sidx = {s: i for i, s in enumerate(sensors)}
        n = [len(o.xz_S) for o in self.obs]
        xz = np.concatenate([o.xz_S for o in self.obs]) if self.obs else np.zeros((0, 2))
        self.p_S = np.column_stack([xz[:, 0], np.zeros(len(xz)), xz[:, 1]])
        self.obs_idx = np.repeat(np.arange(len(self.obs)), n)
        self.sensor_idx = np.repeat([sidx[o.sensor_id] for o in self.obs], n).astype(np.int64)
        T_F_B = invert(np.stack([o.T_B_F for o in self.obs])) if self.obs else np.zeros((0, 4, 4))
        self.R_FB, self.t_FB = T_F_B[:, :3, :3], T_F_B[:, :3, 3]

    def n_base(self, mount: bool) -> int:
        """Index of the first z-scale parameter (after the sensors and the mount)."""
        return 6 * len(self.sensors) + (6 if mount else 0)

    def n_params(self, mount: bool) -> int:
        return self.n_base(mount) + (len(self.sensors) if self.z_scale else 0)

    def p_at(self, idx: np.ndarray, gain: np.ndarray | None = None) -> np.ndarray:
        """Points (m, 3) in S with the range gains applied (``self.z_gain`` by default)."""
        p = self.p_S[idx].copy()
        p[:, 2] *= (self.z_gain if gain is None else gain)[self.sensor_idx[idx]]
        return p

    def points_F(self, T_B_S: list[np.ndarray], idx: np.ndarray, gain=None):
        R = np.stack([T[:3, :3] for T in T_B_S])
        t = np.stack([T[:3, 3] for T in T_B_S])
        si, oi = self.sensor_idx[idx], self.obs_idx[idx]
        p_B = np.einsum("nij,nj->ni", R[si], self.p_at(idx, gain)) + t[si]
        return np.einsum("nij,nj->ni", self.R_FB[oi], p_B) + self.t_FB[oi]

    def associate(self, T_B_S, T_F_A, gate_mm: np.ndarray):
        """Nearest sphere (m,) and inlier mask (m,) with per-point gates [mm]."""
        idx = np.arange(len(self.p_S))
        q_A = (self.points_F(T_B_S, idx) - T_F_A[:3, 3]) @ T_F_A[:3, :3]
        dist = np.abs(np.linalg.norm(q_A[:, None, :] - self.art.centers_A[None], axis=2)
                      - self.art.radii_mm[None])
        k = np.argmin(dist, axis=1)
        return k, dist[idx, k] <= gate_mm

    def residuals(self, T0, T_FA0, x, idx, k, mount: bool, jac: bool = False,
                  with_normals: bool = False):
        S = len(self.sensors)
        Ts = [exp_se3(T0[s], x[6 * s:6 * s + 6]) for s in range(S)]
        T_FA = exp_se3(T_FA0, x[6 * S:6 * S + 6]) if mount else T_FA0
        nb = self.n_base(mount)
        gain = self.z_gain * (1.0 + x[nb:nb + S]) if self.z_scale else self.z_gain
        q_F = self.points_F(Ts, idx, gain)
        c_A = self.art.centers_A[k]
        d = q_F - (c_A @ T_FA[:3, :3].T + T_FA[:3, 3])
        nd = np.linalg.norm(d, axis=1)
        res = nd - self.art.radii_mm[k]
        if not jac:
            return res
        si, oi, p = self.sensor_idx[idx], self.obs_idx[idx], self.p_at(idx, gain)
        u_B = np.einsum("nji,nj->ni", self.R_FB[oi], d / nd[:, None])
        J = np.zeros((len(idx), self.n_params(mount)))
        for s in range(S):
            rows = si == s
            g0 = u_B[rows] @ T0[s][:3, :3]
            g_S = g0 @ Rotation.from_rotvec(x[6 * s:6 * s + 3]).as_matrix()
            J[rows, 6 * s:6 * s + 3] = np.cross(p[rows], g_S) @ right_jacobian_so3(
                x[6 * s:6 * s + 3])
            J[rows, 6 * s + 3:6 * s + 6] = g0
            if self.z_scale:  # d p_S / d x_s = (0, 0, z * gain_s)
                J[rows, nb + s] = g_S[:, 2] * self.p_S[idx][rows, 2] * self.z_gain[s]
        if mount:
            h0 = (d / nd[:, None]) @ T_FA0[:3, :3]
            w = x[6 * S:6 * S + 3]
            h_A = h0 @ Rotation.from_rotvec(w).as_matrix()
            J[:, 6 * S:6 * S + 3] = np.cross(h_A, c_A) @ right_jacobian_so3(w)
            J[:, 6 * S + 3:6 * S + 6] = -h0
        return (res, J, u_B) if with_normals else (res, J)


def _closed_form_start(prob: _Problem, s: int, T_prior, T_F_A, k, inl, opt) -> np.ndarray:
    """``T_B_S`` from per-profile circle fits and Kabsch; the prior when too few arcs."""
    T_S_B = invert(T_prior)
    c_S, c_B = [], []
    for oi in np.unique(prob.obs_idx[(prob.sensor_idx == s) & inl]):
        o = prob.obs[oi]
        for sphere in np.unique(k[(prob.obs_idx == oi) & inl]):
            pts = (prob.obs_idx == oi) & inl & (k == sphere)
            if pts.sum() < opt.min_points:
                continue
            center, rho, rms, _ = robust_circle_fit(o.xz_S[pts[prob.obs_idx == oi]])
            r = prob.art.radii_mm[sphere]
            if rms > 0.5 or rho > 1.05 * r:
                continue
            cb = o.T_B_F[:3, :3] @ (T_F_A[:3, :3] @ prob.art.centers_A[sphere] + T_F_A[:3, 3])
            cb = cb + o.T_B_F[:3, 3]
            y_pred = (T_S_B[:3, :3] @ cb + T_S_B[:3, 3])[1]
            c_S.append(sphere_center_from_arc(center, rho, r, y_pred))
            c_B.append(cb)
    if len(c_S) < 3 or spread_mm(np.array(c_B))[1] < 1.0:
        return T_prior
    return kabsch(np.array(c_S), np.array(c_B))


def solve_calibration(observations: list[Observation], artifact: Artifact, prior_T_B_S: dict,
                      options: SolverOptions | None = None) -> CalibrationResult:
    """Estimate ``T_B_S`` for every sensor in ``prior_T_B_S`` (and optionally ``T_F_A``).

    Sensors are solved one by one when the mount is known (their problems are independent),
    jointly with the mount when ``options.estimate_mount``.

    Parameters
    ----------
    observations : profiles (valid points only) with the flange pose at their stamp
    artifact : the sphere artifact, its nominal mount ``T_F_A`` used as the starting point
    prior_T_B_S : dict sensor id -> (4, 4), coarse poses (a few mm / degrees) for association

    Raises
    ------
    NotObservedError, DegenerateError
    """
    opt = options or SolverOptions()
    if artifact.T_F_A is None:
        raise ValueError(f"artifact {artifact.name}: mount unknown; resolve it with "
                         "artifact.with_mount(T_F_O)")
    sensors = sorted(prior_T_B_S)
    joint = opt.estimate_mount or opt.robot_sigma_mm > 0
    groups = [sensors] if joint else [[s] for s in sensors]
    estimates, mount_result = {}, None
    for group in groups:
        prob = _Problem(observations, group, artifact, opt.estimate_z_scale)
        result = _summarise(prob, *_solve_group(prob, artifact, prior_T_B_S, opt),
                            opt.estimate_mount)
        estimates.update(result.sensors)
        mount_result = result
    return CalibrationResult(
        sensors=estimates, T_F_A=mount_result.T_F_A if opt.estimate_mount else artifact.T_F_A,
        mount_estimated=opt.estimate_mount,
        sigma_mount_rotation_deg=mount_result.sigma_mount_rotation_deg,
        sigma_mount_translation_mm=mount_result.sigma_mount_translation_mm)


def _solve_group(prob: _Problem, artifact: Artifact, prior_T_B_S: dict, opt: SolverOptions):
    S, mount = len(prob.sensors), opt.estimate_mount
    T0 = [np.asarray(prior_T_B_S[s], dtype=np.float64) for s in prob.sensors]
    T_FA0 = np.asarray(artifact.T_F_A, dtype=np.float64)
    gate = np.full(S, opt.init_gate_mm or 0.25 * float(artifact.radii_mm.min()))
    k, inl = prob.associate(T0, T_FA0, gate[prob.sensor_idx])
    check_observed(prob, inl, opt)
    T0 = [_closed_form_start(prob, s, T0[s], T_FA0, k, inl, opt) for s in range(S)]
    n_par, nb = prob.n_params(mount), prob.n_base(mount)
    for rnd in range(opt.rounds):
        k, inl = prob.associate(T0, T_FA0, gate[prob.sensor_idx])
        idx = np.flatnonzero(inl)
        kk = k[idx]
        if rnd == 0:
            check_observed(prob, inl, opt)
            _, J = prob.residuals(T0, T_FA0, np.zeros(n_par), idx, kk, mount, jac=True)
            check_degenerate(prob, J, idx, mount, opt)
        sigma = None if rnd == 0 else 0.2 * float(np.min(gate))  # gate = 5 robust sigmas
        x = _least_squares(prob, T0, T_FA0, idx, kk, mount, opt, sigma)
        T0 = [exp_se3(T0[s], x[6 * s:6 * s + 6]) for s in range(S)]
        if mount:
            T_FA0 = exp_se3(T_FA0, x[6 * S:6 * S + 6])
        if prob.z_scale:
            prob.z_gain = prob.z_gain * (1.0 + x[nb:nb + S])
        res = prob.residuals(T0, T_FA0, np.zeros(n_par), idx, kk, mount)
        for s in range(S):
            r_s = np.abs(res[prob.sensor_idx[idx] == s])
            gate[s] = max(opt.gate_sigmas * 1.4826 * float(np.median(r_s)), opt.min_gate_mm)
        log.debug("%s round %d: %d inliers, gates %s mm", prob.sensors, rnd, idx.size,
                  np.round(gate, 4))
    res, J = prob.residuals(T0, T_FA0, np.zeros(n_par), idx, kk, mount, jac=True)
    conds = check_degenerate(prob, J, idx, mount, opt)
    return T0, T_FA0, res, J, idx, inl, conds


def _least_squares(prob: _Problem, T0, T_FA0, idx, k, mount: bool, opt: SolverOptions,
                   noise_mm: float | None) -> np.ndarray:
    """Robust solve around ``T0``; returns the sensor (and mount) parameters.

    With ``opt.robot_sigma_mm > 0`` and a noise estimate, each pose gets a translation
    ``e_p`` of the flange (first order: ``r -= u_B . e_p``) with a Gaussian prior of that sigma.
    """
    n_core = prob.n_params(mount)
    pose_of_obs = np.array([o.pose_index for o in prob.obs])
    poses, pose_col = np.unique(pose_of_obs[prob.obs_idx[idx]], return_inverse=True)
    P = poses.size if (opt.robot_sigma_mm > 0 and noise_mm) else 0
    w = (noise_mm / opt.robot_sigma_mm) if P else 0.0
    m = idx.size
    rows = np.repeat(np.arange(m), 3)
    cols = n_core + 3 * np.repeat(pose_col, 3) + np.tile(np.arange(3), m)
    cache: dict = {}

    def evaluate(x):
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            r, J, u_B = prob.residuals(T0, T_FA0, x[:n_core], idx, k, mount, True, True)
            if P:
                e = x[n_core:].reshape(P, 3)
                r = np.concatenate([r - np.einsum("ij,ij->i", u_B, e[pose_col]), w * x[n_core:]])
                nuis = sparse.csr_matrix((-u_B.ravel(), (rows, cols - n_core)), shape=(m, 3 * P))
                J = sparse.bmat([[sparse.csr_matrix(J), nuis],
                                 [None, w * sparse.identity(3 * P, format="csr")]], format="csr")
            cache[key] = (r, J)
        return cache[key]

    sol = least_squares(lambda x: evaluate(x)[0], np.zeros(n_core + 3 * P),
                        jac=lambda x: evaluate(x)[1], loss="soft_l1", f_scale=opt.loss_scale_mm,
                        x_scale="jac", method="trf", tr_solver="lsmr" if P else "exact")
    return sol.x[:n_core]


def _summarise(prob, T, T_FA, res, J, idx, inl, conds, mount) -> CalibrationResult:
    S = len(prob.sensors)
    dof = max(len(res) - J.shape[1], 1)
    s2 = float(res @ res) / dof
    cov = s2 * np.linalg.pinv(J.T @ J)
    sig = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    out = {}
    for s, sid in enumerate(prob.sensors):
        rows = prob.sensor_idx[idx] == s
        r_s, o_s = res[rows], prob.obs_idx[idx][rows]
        per_pose = {}
        for pose in np.unique([prob.obs[o].pose_index for o in np.unique(o_s)]):
            m = np.isin(o_s, [i for i, o in enumerate(prob.obs) if o.pose_index == pose])
            per_pose[int(pose)] = float(np.sqrt(np.mean(r_s[m] ** 2)))
        out[sid] = SensorEstimate(
            sensor_id=sid, T_B_S=T[s],
            sigma_rotation_deg=np.degrees(sig[6 * s:6 * s + 3]),
            sigma_translation_mm=sig[6 * s + 3:6 * s + 6],
            residual_rms_mm=float(np.sqrt(np.mean(r_s ** 2))) if r_s.size else float("nan"),
            n_points=int(rows.sum()),
            n_outliers=int(np.sum((prob.sensor_idx == s) & ~inl)),
            n_profiles=int(np.unique(o_s).size), condition=conds[s], per_pose_rms_mm=per_pose,
            z_gain=float(prob.z_gain[s]),
            sigma_z_gain=(float(sig[prob.n_base(mount) + s] * prob.z_gain[s]) if prob.z_scale
                          else None))
    return CalibrationResult(
        sensors=out, T_F_A=T_FA, mount_estimated=mount,
        sigma_mount_rotation_deg=np.degrees(sig[6 * S:6 * S + 3]) if mount else None,
        sigma_mount_translation_mm=sig[6 * S + 3:6 * S + 6] if mount else None)
