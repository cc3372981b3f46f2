"""``dm2 calibrate``: hand-eye calibration of the profilers from a sphere artifact.

Two modes: ``--rehearse`` scans the artifact in the twin from planned poses and judges the
solve against the twin's truth; ``RUN.mcap --artifact A.toml`` solves a recorded calibration
run. Both write ``calibration.toml`` (readable by ``dm2 monitor`` / ``dm2 run``) and a JSON
summary into ``--out``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import typer

from dm2.cli.common import app, bad_input_exits, console

DEFAULT_ARTIFACT = "four_spheres"


def _artifact_path(artifact: str | None) -> Path:
    from scenarios import scenario_dir

    if artifact is None:
        return scenario_dir() / "artifacts" / f"{DEFAULT_ARTIFACT}.toml"
    p = Path(artifact)
    if p.exists():
        return p
    shipped = scenario_dir() / "artifacts" / f"{artifact}.toml"
    if shipped.exists():
        return shipped
    raise FileNotFoundError(f"--artifact {artifact}: neither a file nor a shipped artifact")


def _estimates_table(result, title: str, truth=None):
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
    table.add_column("sigma t", justify="right")
    table.add_column("sigma r", justify="right")
    table.add_column("RMS", justify="right")
    table.add_column("profiles", justify="right")
    table.add_column("fitted", justify="right")
    table.add_column("rejected", justify="right")
    rows = {}
    for sid, est in result.sensors.items():
        row = {"residual_rms_mm": est.residual_rms_mm, "n_profiles": est.n_profiles,
               "n_points": est.n_points, "n_outliers": est.n_outliers,
               "sigma_translation_mm": est.sigma_translation_mm.tolist(),
               "sigma_rotation_deg": est.sigma_rotation_deg.tolist(),
               "condition": est.condition,
               "per_pose_rms_mm": {str(k): v for k, v in est.per_pose_rms_mm.items()}}
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


def _write_outputs(out: Path, result, prior, artifact, summary: dict) -> Path:
    from dm2.core.calibration_io import write_calibration_toml
    from dm2.core.messages import Calibration

    T_F_O = prior.T_F_O
    if result.mount_estimated and artifact.work_object:
        T_F_O = result.T_F_A
    cal = Calibration(T_B_S=result.T_B_S, T_F_O=T_F_O, T_B_N=prior.T_B_N)
    out.mkdir(parents=True, exist_ok=True)
    cal_path = out / "calibration.toml"
    write_calibration_toml(cal, cal_path)
    summary["calibration_toml"] = str(cal_path)
    summary["mount_estimated"] = result.mount_estimated
    summary["T_F_A"] = np.asarray(result.T_F_A).tolist()
    return cal_path


@app.command()
def calibrate(
    source: str = typer.Argument(None, help="MCAP recording of a calibration run; with "
                                 "--rehearse the cell scenario (name or TOML, default: the "
                                 "default scenario)."),
    rehearse: bool = typer.Option(False, "--rehearse", help="Rehearse in the twin instead."),
    artifact: str = typer.Option(None, "--artifact", help="Artifact TOML (or shipped name); "
                                 "default four_spheres."),
    poses: int = typer.Option(24, "--poses", min=1, help="Poses to plan (--rehearse)."),
    noise_mm: float = typer.Option(0.03, "--noise-mm", min=0.0, help="Profile noise sigma."),
    robot_noise_mm: float = typer.Option(0.02, "--robot-noise-mm", min=0.0,
                                         help="Robot repeatability (ISO 9283 RP)."),
    seed: int = typer.Option(0, "--seed", help="Random seed of the rehearsal."),
    max_tilt_deg: float = typer.Option(20.0, "--max-tilt-deg", min=0.0, max=60.0,
                                       help="Largest artifact tilt in the plan."),
    offset_mm: float = typer.Option(None, "--offset-mm", min=0.0,
                                    help="Limit the artifact's offset from the spot to "
                                    "+-this in every axis (default: the planner's box)."),
    mount_error_mm: float = typer.Option(0.0, "--mount-error-mm", min=0.0,
                                         help="Rehearse an artifact mounted this far off."),
    estimate_mount: bool = typer.Option(False, "--estimate-mount",
                                        help="Co-estimate the artifact pose on the flange."),
    prior: Path = typer.Option(None, "--prior", help="Coarse calibration TOML for a "
                               "recording without one."),
    out: Path = typer.Option(Path("calibration"), "--out", "-o", help="Output folder (new, "
                             "or an earlier dm2 output; see `dm2 run --help`)."),
    force: bool = typer.Option(False, "--force", help="Write into a folder holding an earlier "
                               "dm2 output and other files: replace only dm2's files."),
) -> None:
    """Calibrate the three profilers (T_B_S) from profiles of a sphere artifact.

    With `--rehearse [SCENARIO]`, prints per-sensor translation and rotation errors against
    the twin's truth and writes rehearsal.json; otherwise solves the recorded SOURCE and
    writes calibration.json.
    Both write calibration.toml.
    """
    from calib.artifact import load_artifact
    from calib.observations import observations_from_messages
    from calib.solver import ISO9283_RP_PER_SIGMA, SolverOptions, solve_calibration

    if not rehearse and source is None:
        from dm2.cli.common import fail

        fail("give a RECORDING.mcap of a calibration run (with --artifact), or --rehearse")
    from dm2.report.outdir import check_output_dir, clear_outputs, write_manifest

    with bad_input_exits():
        check_output_dir(out, force=force, inputs=[source, prior])
        art = load_artifact(_artifact_path(artifact))
        options = SolverOptions(estimate_mount=estimate_mount,
                                robot_sigma_mm=robot_noise_mm / ISO9283_RP_PER_SIGMA)
        if rehearse:
            sim, prior_cal, truth = _rehearse(source, art, poses, noise_mm, robot_noise_mm,
                                              seed, max_tilt_deg, offset_mm, mount_error_mm)
            messages = sim.messages
            art = art.with_mount(prior_cal.T_F_O)
            prior_T_B_S = sim.prior_T_B_S
        else:
            messages, prior_cal = _recorded(Path(source), prior)
            prior_T_B_S, truth = prior_cal.T_B_S, None
            art = art.with_mount(prior_cal.T_F_O)
        obs, dropped = observations_from_messages(messages)
        result = solve_calibration(obs, art, prior_T_B_S, options)
    title = "rehearsal: estimated vs twin truth" if rehearse else "calibration"
    table, rows = _estimates_table(result, title, truth)
    console.print(table)
    summary = {"artifact": art.name, "sensors": rows, "dropped_profiles": dropped,
               "n_observations": len(obs)}
    if rehearse:
        summary.update({"poses": poses, "noise_mm": noise_mm, "robot_noise_mm": robot_noise_mm,
                        "seed": seed})
    if out.is_dir():
        clear_outputs(out, inputs=[source, prior])
    cal_path = _write_outputs(out, result, prior_cal, art, summary)
    json_path = out / ("rehearsal.json" if rehearse else "calibration.json")
    json_path.write_text(json.dumps(summary, indent=2))
    write_manifest(out, [cal_path.name, json_path.name], command="dm2 calibrate")
    console.print(f"wrote {cal_path} and {json_path}")


def _rehearse(scenario, art, poses, noise_mm, robot_noise_mm, seed, max_tilt_deg, offset_mm,
              mount_error_mm):
    from calib.planning import PlanOptions
    from dm2.core.config import load_scenario
    from scenarios import resolve_scenario
    from twin.stream.rehearsal import RehearsalConfig, rehearse_calibration

    sc = load_scenario(resolve_scenario(scenario))
    plan = PlanOptions(max_tilt_deg=max_tilt_deg)
    if offset_mm is not None:
        plan = PlanOptions(max_tilt_deg=max_tilt_deg, offset_lo_mm=(-offset_mm,) * 3,
                           offset_hi_mm=(offset_mm,) * 3)
    cfg = RehearsalConfig(n_poses=poses, profile_noise_mm=noise_mm,
                          robot_repeatability_mm=robot_noise_mm, seed=seed,
                          mount_error_mm=mount_error_mm,
                          plan=plan)
    sim = rehearse_calibration(sc, art, cfg)
    return sim, sim.truth, sim.truth


def _recorded(recording: Path, prior: Path | None):
    from dm2.core.calibration_io import read_calibration_toml
    from dm2.io.recording import read_recording

    if not recording.exists():
        raise FileNotFoundError(f"{recording}: no such recording")
    rec = read_recording(recording)
    cal = read_calibration_toml(prior) if prior is not None else rec.calibration
    if cal is None:
        raise ValueError(f"{recording}: holds no calibration to start from; give --prior "
                         "CALIBRATION.toml with the sensors' approximate poses")
    return list(rec.messages()), cal
