"""Calibration errors, and the checks that refuse to solve what the data cannot determine.

``check_observed``: every sensor must see the artifact in enough profiles.
``check_degenerate``: the Jacobian of each sensor's parameters (and of the joint problem when the
mount is co-estimated), with rotations scaled to millimetres at ``rotation_scale_mm``, must not
be rank-poor; the weakest direction is named in the sensor's own axes.
"""

from __future__ import annotations

import numpy as np

PARAM_NAMES = ("rotation about x_{f}", "rotation about y_{f}", "rotation about z_{f}",
               "translation along x_{f}", "translation along y_{f}", "translation along z_{f}")


class CalibrationError(ValueError):
    """The calibration data cannot give a trustworthy answer; the text says why."""


class NotObservedError(CalibrationError):
    """A sensor saw the artifact in too few profiles."""


class DegenerateError(CalibrationError):
    """The pose set leaves a direction of a sensor's pose (or the mount) unconstrained."""


def describe_direction(v: np.ndarray, frame_names: list[str], n_base: int | None = None) -> str:
    """Name the dominant components of a weak parameter direction (pose blocks of 6, then
    one range scale per sensor from ``n_base`` on)."""
    n_base = len(v) if n_base is None else n_base
    parts = []
    for i in np.argsort(-np.abs(v)):
        if abs(v[i]) < 0.3 and parts:
            break
        if i >= n_base:
            parts.append(f"range scale of {frame_names[int(i) - n_base]} ({abs(v[i]):.2f})")
            continue
        block, j = divmod(int(i), 6)
        parts.append(f"{PARAM_NAMES[j].format(f=frame_names[block])} ({abs(v[i]):.2f})")
    return " + ".join(parts)


def check_observed(prob, inl, opt) -> None:
    for s, sid in enumerate(prob.sensors):
        n_total = sum(o.sensor_id == sid for o in prob.obs)
        seen = 0
        for oi in np.unique(prob.obs_idx[prob.sensor_idx == s]):
            seen += int(np.sum(inl & (prob.obs_idx == oi)) >= opt.min_points)
        if seen < opt.min_profiles:
            raise NotObservedError(
                f"sensor {sid}: the artifact was seen in {seen} of {n_total} profiles (need "
                f">= {opt.min_profiles} with >= {opt.min_points} sphere points); check the "
                "poses, the artifact description and the prior calibration")


def check_degenerate(prob, J: np.ndarray, idx, mount: bool, opt):
    """Raise DegenerateError when a sensor's (or the joint) scaled Jacobian is rank-poor.

    Rotations are scaled by ``opt.rotation_scale_mm``, range scales by
    ``opt.z_scale_lever_mm`` (a scale error of 1e-3 moves a point that far times 1e-3).
    """
    S = len(prob.sensors)
    n_base = 6 * S + (6 if mount else 0)
    n_z = J.shape[1] - n_base
    scale = np.concatenate([np.tile([1.0 / opt.rotation_scale_mm] * 3 + [1.0] * 3,
                                    S + (1 if mount else 0)),
                            np.full(n_z, 1.0 / opt.z_scale_lever_mm)])
    Js = J * scale
    conds = {}
    blocks = [(s, prob.sensor_idx[idx] == s,
               np.r_[6 * s:6 * s + 6, [n_base + s] if n_z else []].astype(int))
              for s in range(S)]
    if mount:
        blocks.append((S, np.ones(len(idx), bool), np.arange(J.shape[1])))
    names = [f"{sid}" for sid in prob.sensors] + ["A (mount)"]
    for b, rows, cols in blocks:
        _, sv, Vt = np.linalg.svd(Js[rows][:, cols] / np.sqrt(max(rows.sum(), 1)),
                                  full_matrices=False)
        cond = float(sv[-1] / sv[0]) if sv[0] > 0 else 0.0
        conds[b] = cond
        if cond < opt.min_condition:
            v = np.zeros(Js.shape[1])
            v[cols] = Vt[-1]
            who = names[b] if b < S else "the sensors and the artifact mount together"
            raise DegenerateError(
                f"{who}: the poses do not constrain "
                f"{describe_direction(v, names, n_base)} "
                f"(condition {cond:.1e} < {opt.min_condition:.0e}); add poses that cut the "
                "spheres off-centre, at several heights, tilts and rotations")
    return conds
