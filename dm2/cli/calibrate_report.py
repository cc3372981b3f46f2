"""What ``dm2 calibrate`` prints and writes: the estimates table, calibration.toml with the
provenance of every transform, and the JSON summary."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def estimates_table(result, title: str, truth=None):
    """A rich table of the sensors' estimates (and errors against ``truth``) and the rows
    of the JSON summary."""
    from rich.markup import escape
    from rich.table import Table

    from dm2.core.frames import pose_error

    table = Table(title=title, caption=escape(
        "t: translation [mm], r: rotation [deg], sigma: 1-sigma from the Jacobian, RMS: "
        "residual [mm]; points fitted and rejected (off the spheres or gated out)"))
    table.add_column("sensor")
    if truth is not None:
        table.add_column("t error", justify="right")
        table.add_column("r error", justify="right")
    for col in ("sigma t", "sigma r", "RMS", "profiles", "fitted", "rejected"):
        table.add_column(col, justify="right")
    rows = {}
    for sid, est in result.sensors.items():
        row = {"residual_rms_mm": est.residual_rms_mm, "n_profiles": est.n_profiles,
               "n_points": est.n_points, "n_outliers": est.n_outliers,
               "sigma_translation_mm": est.sigma_translation_mm.tolist(),
               "sigma_rotation_deg": est.sigma_rotation_deg.tolist(),
               "condition": est.condition,
               "per_pose_rms_mm": {str(k): v for k, v in est.per_pose_rms_mm.items()}}
        if est.sigma_z_gain is not None:
            row["z_scale_error"] = est.z_scale_error
            row["sigma_z_scale_error"] = est.sigma_z_gain
        cells = [sid]
        if truth is not None:
            dt, dr = pose_error(est.T_B_S, truth.T_B_S[sid])
            row["translation_error_mm"], row["rotation_error_deg"] = dt, float(np.degrees(dr))
            cells += [f"{dt:.4f}", f"{np.degrees(dr):.4f}"]
        cells += [f"{np.linalg.norm(est.sigma_translation_mm):.4f}",
                  f"{np.linalg.norm(est.sigma_rotation_deg):.4f}",
                  f"{est.residual_rms_mm:.4f}", str(est.n_profiles), str(est.n_points),
                  str(est.n_outliers)]
        table.add_row(*cells)
        rows[sid] = row
    return table, rows


def outcome_summary(outcome, truth=None) -> dict:
    """JSON-ready: provenance, mount, touch-off and held-out check (errors against ``truth``
    for a rehearsal)."""
    from dm2.core.frames import pose_error

    res = outcome.result
    out = {"provenance": outcome.provenance, "mount_estimated": res.mount_estimated,
           "T_F_A": np.asarray(res.T_F_A).tolist(), "holdout": outcome.holdout,
           "dropped_profiles": outcome.dropped}
    if outcome.z_scale is not None:
        out["z_scale_error"] = {sid: {"estimate": v, "sigma": sg}
                                for sid, (v, sg) in outcome.z_scale.items()}
    if outcome.touch_off is not None:
        t = outcome.touch_off
        out["touch_off"] = {"n_touches": t.n_touches, "exit_B_mm": t.exit_B_mm.tolist(),
                            "scatter_mm": t.scatter_mm.tolist(), "sigma_mm": t.sigma_mm.tolist()}
    if truth is not None:
        cal = outcome.calibration
        for name in ("T_F_O", "T_B_N"):
            dt, dr = pose_error(getattr(cal, name), getattr(truth, name))
            out[f"{name}_error"] = {"translation_mm": dt, "rotation_deg": float(np.degrees(dr))}
    return out


def write_outputs(out: Path, outcome, summary: dict, json_name: str) -> tuple[Path, Path]:
    """calibration.toml (with provenance) and the JSON summary in ``out``."""
    import json

    from dm2.core.calibration_io import write_calibration_toml

    out.mkdir(parents=True, exist_ok=True)
    cal_path = out / "calibration.toml"
    write_calibration_toml(outcome.calibration, cal_path, outcome.provenance)
    summary["calibration_toml"] = str(cal_path)
    json_path = out / json_name
    json_path.write_text(json.dumps(summary, indent=2, default=_json_default), encoding="utf-8")
    return cal_path, json_path


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
