"""The calibration procedure around the solver: a first pass to re-plan from, the solve, the
nozzle touch-off, a held-out check and where every transform of the result came from.

Nothing here knows the truth: the inputs are what a real cell records (profiles, robot
states, touch-off poses) and the prior calibration (the cell file's nominal layout).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from calib.artifact import Artifact
from calib.observations import Observation, observations_from_messages
from calib.solver import (
    CalibrationError,
    CalibrationResult,
    DegenerateError,
    SolverOptions,
    solve_calibration,
)
from calib.touch_off import TouchOffResult, nozzle_exit_from_touches
from dm2.core.frames import apply, invert, pose_error
from dm2.core.messages import Calibration

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CalibrationOutcome:
    """The solved calibration and how it was obtained.

    Attributes
    ----------
    result : the solver's result on every pose
    calibration : Calibration to hand the monitor
    provenance : dict transform name -> text starting with 'estimated' or 'taken'
    touch_off : TouchOffResult or None
    holdout : dict (rms_mm, n_points, n_rejected, poses) of the held-out check, or None
    dropped : dict reason -> count of profiles without a flange pose
    n_observations : int, profiles paired with a flange pose
    z_scale : dict sensor id -> (range scale error, 1-sigma) from a solve that co-estimates
        it (``options.estimate_z_scale``), or None. The poses of ``calibration`` come from a
        solve that leaves the ranges as reported: the monitor takes profiles as reported, so
        the pose that absorbs a range scale error best near the spot serves it best.
    """

    result: CalibrationResult
    calibration: Calibration
    provenance: dict
    touch_off: TouchOffResult | None
    holdout: dict | None
    dropped: dict
    n_observations: int
    z_scale: dict | None = None


def first_pass_refiner(artifact: Artifact, options: SolverOptions | None = None,
                       max_rms_mm: float = 0.1, max_shift_mm: float = 10.0,
                       max_turn_deg: float = 5.0):
    """``refine(messages, prior_T_B_S) -> T_B_S`` solving the first pass of a run.

    The first pass starts from the CAD prior, a few mm off: points are associated with the
    spheres within half the smallest radius (the full solve's default is a quarter). A
    sensor's first-pass pose is kept only when it fits (residual RMS within ``max_rms_mm``)
    and stays within ``max_shift_mm`` / ``max_turn_deg`` of the prior; otherwise the second
    pass is planned on the prior again for that sensor.
    """
    options = options or SolverOptions(init_gate_mm=0.5 * float(artifact.radii_mm.min()))

    def refine(messages, prior_T_B_S):
        obs, _ = observations_from_messages(messages)
        try:
            result = solve_calibration(obs, artifact, prior_T_B_S, options)
        except CalibrationError as exc:
            log.info("first pass not solved (%s); planning on the prior", exc)
            return dict(prior_T_B_S)
        out = {}
        for sid, T in prior_T_B_S.items():
            est = result.sensors.get(sid)
            dt, dr = pose_error(est.T_B_S, T) if est is not None else (np.inf, np.inf)
            ok = (est is not None and est.residual_rms_mm <= max_rms_mm and dt <= max_shift_mm
                  and np.degrees(dr) <= max_turn_deg)
            out[sid] = est.T_B_S if ok else T
            if not ok:
                log.info("first pass: %s not trusted; planning on its prior", sid)
        return out
    return refine


def holdout_residuals(observations: list[Observation], artifact: Artifact,
                      result: CalibrationResult, gate_mm: float = 1.0) -> dict:
    """Distances of held-out profile points to the certified spheres, with ``result``.

    Points farther than ``gate_mm`` from every sphere surface are off the spheres (plate,
    posts); of the rest, those beyond five robust sigmas (at least 0.05 mm) are rejected as
    ghosts. Returns ``rms_mm``, ``n_points``, ``n_rejected``.
    """
    T_A_F = invert(result.T_F_A)
    res = []
    for o in observations:
        est = result.sensors.get(o.sensor_id)
        if est is None or len(o.xz_S) == 0:
            continue
        p_S = np.column_stack([o.xz_S[:, 0], np.zeros(len(o.xz_S)), o.xz_S[:, 1] * est.z_gain])
        q_A = apply(T_A_F @ invert(o.T_B_F) @ est.T_B_S, p_S)
        d = (np.linalg.norm(q_A[:, None] - artifact.centers_A[None], axis=2)
             - artifact.radii_mm[None])
        k = np.argmin(np.abs(d), axis=1)
        r = d[np.arange(len(k)), k]
        res.append(r[np.abs(r) <= gate_mm])
    r = np.concatenate(res) if res else np.zeros(0)
    if r.size == 0:
        return {"rms_mm": float("nan"), "n_points": 0, "n_rejected": 0}
    gate = max(5.0 * 1.4826 * float(np.median(np.abs(r - np.median(r)))), 0.05)
    keep = np.abs(r) <= gate
    return {"rms_mm": float(np.sqrt(np.mean(r[keep] ** 2))), "n_points": int(keep.sum()),
            "n_rejected": int((~keep).sum())}


def solve_run(messages, artifact: Artifact, prior: Calibration, options: SolverOptions,
              touch_T_B_F: np.ndarray | None = None, holdout_every: int = 0,
              prior_source: str = "the cell file") -> CalibrationOutcome:
    """Solve a calibration run; ``holdout_every = k`` also solves without every k-th pose
    and checks those poses' profiles against the certified artifact."""
    art = artifact.with_mount(prior.T_F_O)
    obs, dropped = observations_from_messages(messages)
    z_scale = None
    if options.estimate_z_scale:
        diag = solve_calibration(obs, art, prior.T_B_S, options)
        z_scale = {sid: (e.z_scale_error, e.sigma_z_gain) for sid, e in diag.sensors.items()}
        options = replace(options, estimate_z_scale=False)
    mount_note = ""
    try:
        result = solve_calibration(obs, art, prior.T_B_S, options)
    except DegenerateError as exc:
        if not options.estimate_mount:
            raise
        # the pose set may fix the sensors but not the mount: solve without it, and say so
        options = replace(options, estimate_mount=False)
        result = solve_calibration(obs, art, prior.T_B_S, options)
        mount_note = f" (the mount is not observable from these poses: {exc})"
        log.warning("mount not estimated: %s", exc)
    holdout = None
    if holdout_every > 1:
        held = {o.pose_index for o in obs if o.pose_index % holdout_every == holdout_every - 1}
        fit = solve_calibration([o for o in obs if o.pose_index not in held], art,
                                prior.T_B_S, options)
        holdout = holdout_residuals([o for o in obs if o.pose_index in held], art, fit)
        holdout["poses"] = len(held)
    T_F_O, mount_text = prior.T_F_O, f"taken from {prior_source}{mount_note}"
    if result.mount_estimated and art.work_object:
        T_F_O = result.T_F_A
        mount_text = ("estimated: the sphere artifact's mount (the work object), co-estimated "
                      "with the sensors")
    elif result.mount_estimated:
        mount_text = (f"taken from {prior_source} (the artifact's own mount was estimated; "
                      "the plate's is not observed)")
    touch, T_B_N = None, prior.T_B_N
    nozzle_text = f"taken from {prior_source} (no touch-off)"
    if touch_T_B_F is not None and len(touch_T_B_F):
        if art.touch_mark_A is None:
            raise ValueError(f"artifact {art.name}: touch-off poses given but the artifact has "
                             "no plate.touch_mark_mm")
        touch = nozzle_exit_from_touches(touch_T_B_F, result.T_F_A, art.touch_mark_A,
                                         prior.T_B_N)
        T_B_N = touch.T_B_N
        nozzle_text = (f"estimated: exit position by a nozzle touch-off ({touch.n_touches} "
                       f"touches on the artifact's cone); spray axis taken from {prior_source}")
    n_prof = {sid: e.n_profiles for sid, e in result.sensors.items()}
    provenance = {"T_B_N": nozzle_text, "T_F_O": mount_text}
    for sid, est in result.sensors.items():
        provenance[sid] = (f"estimated: sphere artifact hand-eye solve, {n_prof[sid]} profiles, "
                           f"residual RMS {est.residual_rms_mm:.4f} mm")
    cal = Calibration(T_B_S=result.T_B_S, T_F_O=T_F_O, T_B_N=T_B_N)
    return CalibrationOutcome(result, cal, provenance, touch, holdout, dropped, len(obs),
                              z_scale)
