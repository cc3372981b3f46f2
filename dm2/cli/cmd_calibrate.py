"""``dm2 calibrate``: hand-eye calibration of the profilers from a sphere artifact.

Two modes: ``--rehearse`` scans the artifact in the twin (its own profilers, seeded as-built,
intrinsic, artifact and robot errors, a prior from the cell file's nominal layout) and judges
the solve against the twin's truth; ``RUN.mcap --artifact A.toml`` solves a recorded
calibration run (``--rehearse --record RUN.mcap`` writes one). Both write ``calibration.toml``
(readable by ``dm2 monitor`` / ``dm2 run``, with the provenance of every transform) and a JSON
summary into ``--out``. The procedure is :func:`calib.procedure.solve_run`.
"""

from __future__ import annotations

from pathlib import Path

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


@app.command()
def calibrate(
    source: str = typer.Argument(None, help="MCAP recording of a calibration run; with "
                                 "--rehearse the cell scenario (name or TOML, default: the "
                                 "default scenario)."),
    rehearse: bool = typer.Option(False, "--rehearse", help="Rehearse in the twin instead."),
    artifact: str = typer.Option(None, "--artifact", help="Artifact TOML (or shipped name); "
                                 "default four_spheres."),
    poses: int = typer.Option(48, "--poses", min=2, help="Poses to plan (--rehearse); with "
                              "0.03 mm noise 24 poses leave up to 0.03 deg per sensor."),
    noise_mm: float = typer.Option(0.03, "--noise-mm", min=0.0,
                                   help="Profiler range noise sigma (--rehearse)."),
    speckle_mm: float = typer.Option(None, "--speckle-mm", min=0.0,
                                     help="Speckle sigma (default: the scenario's)."),
    dropout_prob: float = typer.Option(None, "--dropout-prob", min=0.0, max=1.0,
                                       help="Dropout probability (default: the scenario's)."),
    outlier_prob: float = typer.Option(None, "--outlier-prob", min=0.0, max=1.0,
                                       help="Ghost probability (default: the scenario's)."),
    robot_noise_mm: float = typer.Option(0.02, "--robot-noise-mm", min=0.0,
                                         help="Robot repeatability (ISO 9283 RP)."),
    seed: int = typer.Option(0, "--seed", help="Random seed of the rehearsal."),
    as_built_mm: float = typer.Option(2.0, "--as-built-mm", min=0.0, help="True sensor poses "
                                      "off the cell file's layout by this much (--rehearse)."),
    as_built_deg: float = typer.Option(1.0, "--as-built-deg", min=0.0,
                                       help="... and by this rotation."),
    z_scale_error: float = typer.Option(0.0, "--z-scale-error", min=0.0,
                                        help="Profiler range scale error, e.g. 0.001."),
    fan_angle_deg: float = typer.Option(0.0, "--fan-angle-deg", min=0.0,
                                        help="Profiler fan angle offset [deg]."),
    x_distortion_mm: float = typer.Option(0.0, "--x-distortion-mm", min=0.0,
                                          help="Profiler x-fan distortion at the fan edge."),
    max_tilt_deg: float = typer.Option(20.0, "--max-tilt-deg", min=0.0, max=60.0,
                                       help="Largest artifact tilt in the plan."),
    offset_mm: float = typer.Option(None, "--offset-mm", min=0.0,
                                    help="Limit the artifact's offset from the spot to "
                                    "+-this in every axis (default: the planner's box)."),
    mount_error_mm: float = typer.Option(0.0, "--mount-error-mm", min=0.0,
                                         help="Rehearse an artifact mounted this far off."),
    mount_error_deg: float = typer.Option(0.0, "--mount-error-deg", min=0.0,
                                          help="... and turned this much."),
    nozzle_error_mm: float = typer.Option(0.0, "--nozzle-error-mm", min=0.0,
                                          help="Rehearse a nozzle exit this far off the cell "
                                          "file's."),
    touch_offs: int = typer.Option(4, "--touch-offs", min=0, help="Nozzle touch-offs to "
                                   "rehearse (0: T_B_N is taken from the cell file)."),
    estimate_mount: bool = typer.Option(True, "--estimate-mount/--fixed-mount",
                                        help="Co-estimate the artifact pose on the flange "
                                        "(T_F_O for a work-object artifact); when the poses "
                                        "leave it unobservable it is taken from the prior, "
                                        "and calibration.toml says so."),
    estimate_z_scale: bool = typer.Option(False, "--estimate-z-scale",
                                          help="Co-estimate each profiler's range scale."),
    holdout: int = typer.Option(4, "--holdout", min=0, help="Also check every k-th pose's "
                                "profiles, held out of a second solve (0, 1: no check)."),
    record: Path = typer.Option(None, "--record", help="Write the rehearsal's recording "
                                "(MCAP, as the cell would record it) here."),
    prior: Path = typer.Option(None, "--prior", help="Coarse calibration TOML for a "
                               "recording without one."),
    out: Path = typer.Option(Path("calibration"), "--out", "-o", help="Output folder (new, "
                             "or an earlier dm2 output; see `dm2 run --help`)."),
    force: bool = typer.Option(False, "--force", help="Write into a folder holding an earlier "
                               "dm2 output and other files: replace only dm2's files."),
) -> None:
    """Calibrate the three profilers (T_B_S), the mount (T_F_O, unless --fixed-mount) and
    the nozzle exit (touch-off) from a sphere artifact.

    With `--rehearse [SCENARIO]`, the twin renders the run with its own profilers, starting
    from the cell file's nominal layout, and the errors against the twin's truth are printed
    and written to rehearsal.json; otherwise the recorded SOURCE is solved and
    calibration.json written. Both write calibration.toml, which says for every transform
    whether it was estimated or taken, and from where.
    """
    from calib.artifact import load_artifact
    from calib.procedure import solve_run
    from calib.solver import ISO9283_RP_PER_SIGMA, SolverOptions
    from dm2.cli.calibrate_report import estimates_table, outcome_summary, write_outputs

    if not rehearse and source is None:
        from dm2.cli.common import fail

        fail("give a RECORDING.mcap of a calibration run (with --artifact), or --rehearse")
    from dm2.report.outdir import check_output_dir, clear_outputs, write_manifest

    with bad_input_exits():
        check_output_dir(out, force=force, inputs=[source, prior])
        art = load_artifact(_artifact_path(artifact))
        options = SolverOptions(estimate_mount=estimate_mount,
                                estimate_z_scale=estimate_z_scale,
                                robot_sigma_mm=robot_noise_mm / ISO9283_RP_PER_SIGMA)
        truth = None
        if rehearse:
            from twin.stream.rehearsal import write_rehearsal_recording

            settings = dict(poses=poses, noise_mm=noise_mm, speckle_mm=speckle_mm,
                            dropout_prob=dropout_prob, outlier_prob=outlier_prob,
                            robot_noise_mm=robot_noise_mm, seed=seed, as_built_mm=as_built_mm,
                            as_built_deg=as_built_deg, z_scale_error=z_scale_error,
                            fan_angle_deg=fan_angle_deg, x_distortion_mm=x_distortion_mm,
                            max_tilt_deg=max_tilt_deg, offset_mm=offset_mm,
                            mount_error_mm=mount_error_mm, mount_error_deg=mount_error_deg,
                            nozzle_error_mm=nozzle_error_mm, touch_offs=touch_offs)
            sim = _rehearse(source, art, settings)
            messages, prior_cal, touches, truth = sim.messages, sim.prior, sim.touch_T_B_F, \
                sim.truth
            prior_source = "the cell file"
        else:
            messages, prior_cal, touches, prior_source = _recorded(Path(source), prior)
        outcome = solve_run(messages, art, prior_cal, options, touches, holdout,
                            prior_source)
    title = "rehearsal: estimated vs twin truth" if rehearse else "calibration"
    table, rows = estimates_table(outcome.result, title, truth)
    console.print(table)
    summary = {"artifact": art.name, "sensors": rows,
               "n_observations": outcome.n_observations,
               **outcome_summary(outcome, truth)}
    if rehearse:
        summary["settings"] = settings
        summary["true_intrinsics"] = {sid: vars(e) for sid, e in sim.intrinsics.items()}
        if outcome.z_scale is not None:
            summary["z_scale_error"] = {
                sid: {**summary["z_scale_error"][sid],
                      "true": sim.intrinsics[sid].z_scale_error} for sid in outcome.z_scale}
        if record is not None:
            summary["recording"] = str(record)
    for name in ("T_F_O", "T_B_N"):
        console.print(f"{name}: {outcome.provenance[name]}")
    if outcome.z_scale is not None:
        console.print("range scale errors (reported z / true z - 1, a diagnosis for the "
                      "sensors' own calibration; the poses written assume the ranges as "
                      "reported): " + ", ".join(f"{sid} {v:+.5f} +- {sg:.5f}" for sid, (v, sg)
                                                in outcome.z_scale.items()))
    if outcome.holdout is not None:
        h = outcome.holdout
        console.print(f"held-out poses ({h['poses']}): {h['n_points']} sphere points fit the "
                      f"certified artifact with RMS {h['rms_mm']:.4f} mm")
    if out.is_dir():
        clear_outputs(out, inputs=[source, prior])
    written = []
    if rehearse and record is not None:
        record.parent.mkdir(parents=True, exist_ok=True)
        write_rehearsal_recording(sim, record)
        if record.parent.resolve() == out.resolve():
            written.append(record.name)
    cal_path, json_path = write_outputs(out, outcome, summary,
                                        "rehearsal.json" if rehearse else "calibration.json")
    write_manifest(out, [*written, cal_path.name, json_path.name], command="dm2 calibrate")
    console.print(f"wrote {cal_path} and {json_path}")


def _rehearse(scenario, art, s: dict):
    from calib.planning import PlanOptions
    from calib.procedure import first_pass_refiner
    from dm2.core.config import load_scenario
    from scenarios import resolve_scenario
    from twin.cell.cell import CellModel
    from twin.stream.rehearsal import RehearsalConfig, rehearse_calibration

    sc = load_scenario(resolve_scenario(scenario))
    plan = PlanOptions(max_tilt_deg=s["max_tilt_deg"])
    if s["offset_mm"] is not None:
        plan = PlanOptions(max_tilt_deg=s["max_tilt_deg"], offset_lo_mm=(-s["offset_mm"],) * 3,
                           offset_hi_mm=(s["offset_mm"],) * 3)
    noise = {"range_sigma_mm": s["noise_mm"], "speckle_sigma_mm": s["speckle_mm"],
             "dropout_prob": s["dropout_prob"], "outlier_prob": s["outlier_prob"]}
    noise = sc.noise.model_copy(update={k: v for k, v in noise.items() if v is not None})
    cfg = RehearsalConfig(
        n_poses=s["poses"], noise=noise, robot_repeatability_mm=s["robot_noise_mm"],
        seed=s["seed"], as_built_error_mm=s["as_built_mm"],
        as_built_error_deg=s["as_built_deg"], mount_error_mm=s["mount_error_mm"],
        mount_error_deg=s["mount_error_deg"], nozzle_error_mm=s["nozzle_error_mm"],
        z_scale_error=s["z_scale_error"], fan_angle_offset_deg=s["fan_angle_deg"],
        x_distortion_mm=s["x_distortion_mm"], touch_offs=s["touch_offs"], plan=plan,
        first_pass_poses=min(8, s["poses"] // 3))
    nominal = art.with_mount(CellModel.from_scenario(sc).T_F_O)
    refine = first_pass_refiner(nominal) if cfg.first_pass_poses else None
    return rehearse_calibration(sc, art, cfg, refine)


def _recorded(recording: Path, prior: Path | None):
    from calib.touch_off import TOUCH_OFF_ATTACHMENT, touch_off_from_toml
    from dm2.core.calibration_io import read_calibration_toml
    from dm2.io.recording import read_recording

    if not recording.exists():
        raise FileNotFoundError(f"{recording}: no such recording")
    rec = read_recording(recording)
    cal = read_calibration_toml(prior) if prior is not None else rec.calibration
    if cal is None:
        raise ValueError(f"{recording}: holds no calibration to start from; give --prior "
                         "CALIBRATION.toml with the sensors' approximate poses")
    touches = None
    if TOUCH_OFF_ATTACHMENT in rec.attachments:
        touches = touch_off_from_toml(rec.attachments[TOUCH_OFF_ATTACHMENT].decode(),
                                      f"{recording}: attachment {TOUCH_OFF_ATTACHMENT}")
    source = f"--prior {prior}" if prior is not None else f"the calibration in {recording.name}"
    return list(rec.messages()), cal, touches, source
