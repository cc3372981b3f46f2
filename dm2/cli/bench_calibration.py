"""``dm2 bench --calibration rehearsed``: the chain scored, calibration first, then monitoring.

For each scenario the twin's profilers stand off the scenario's nominal layout by a seeded
few mm and degrees (:func:`twin.stream.rehearsal.as_built_sensor_poses`, seeded by the
scenario's seed). A calibration run is rehearsed on that cell (the twin's own profilers, the
scenario's ``[noise]``, robot repeatability, the artifact within its certificate, a nozzle
touch-off) and solved from the cell file's nominal layout as the prior
(:func:`calib.procedure.solve_run`): the sensors, the work object's mount ``T_F_O`` (the
artifact is the work object, co-estimated) and the nozzle exit (touch-off) are estimated.
The build is then run twice on the same twin: monitored with the solved calibration (the
bench's figures) and with the true one (the reference the figures are set beside).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

REHEARSAL_POSES = 48
AS_BUILT_MM, AS_BUILT_DEG = 2.0, 1.0
ROBOT_REPEATABILITY_MM = 0.02
DEFAULT_ARTIFACT = "four_spheres"


def rehearsed_calibration(sc, artifact_path: Path | None = None):
    """Rehearse and solve the calibration of ``sc``'s twin with its sensors as built.

    Returns
    -------
    true_T_B_S : dict sensor id -> (4, 4), the twin's profilers as built
    outcome : calib.procedure.CalibrationOutcome
    info : dict, JSON-ready errors of the solved calibration against the twin's truth
    """
    from calib.artifact import load_artifact
    from calib.procedure import first_pass_refiner, solve_run
    from calib.solver import ISO9283_RP_PER_SIGMA, SolverOptions
    from dm2.core.frames import pose_error
    from scenarios import scenario_dir
    from twin.stream.rehearsal import (
        RehearsalConfig,
        as_built_sensor_poses,
        rehearse_calibration,
    )

    art = load_artifact(artifact_path or scenario_dir() / "artifacts" /
                        f"{DEFAULT_ARTIFACT}.toml")
    true_T_B_S = as_built_sensor_poses(sc, sc.seed, AS_BUILT_MM, AS_BUILT_DEG)
    cfg = RehearsalConfig(n_poses=REHEARSAL_POSES, seed=sc.seed, true_T_B_S=true_T_B_S,
                          robot_repeatability_mm=ROBOT_REPEATABILITY_MM)
    from twin.cell.cell import CellModel

    nominal = art.with_mount(CellModel.from_scenario(sc).T_F_O)
    sim = rehearse_calibration(sc, art, cfg, refine=first_pass_refiner(nominal))
    options = SolverOptions(estimate_mount=True,
                            robot_sigma_mm=ROBOT_REPEATABILITY_MM / ISO9283_RP_PER_SIGMA)
    outcome = solve_run(sim.messages, art, sim.prior, options, sim.touch_T_B_F)
    errors = {}
    for sid, T in outcome.calibration.T_B_S.items():
        dt, dr = pose_error(T, sim.truth.T_B_S[sid])
        errors[sid] = {"translation_error_mm": dt, "rotation_error_deg": float(np.degrees(dr))}
    for name in ("T_F_O", "T_B_N"):
        dt, dr = pose_error(getattr(outcome.calibration, name), getattr(sim.truth, name))
        errors[name] = {"translation_error_mm": dt, "rotation_error_deg": float(np.degrees(dr))}
    info = {"artifact": art.name, "poses": REHEARSAL_POSES, "seed": sc.seed,
            "as_built_mm": AS_BUILT_MM, "as_built_deg": AS_BUILT_DEG,
            "robot_repeatability_mm": ROBOT_REPEATABILITY_MM, "errors": errors,
            "provenance": outcome.provenance,
            "residual_rms_mm": {sid: e.residual_rms_mm
                                for sid, e in outcome.result.sensors.items()}}
    return true_T_B_S, outcome, info


def run_rehearsed(sc, run_dir: Path, scenario_file, full_report: bool):
    """Calibrate, then run the build monitored with the solved and with the true calibration.

    Returns ``(run_solved, run_true, info)``: the run folders are ``run_dir`` and
    ``run_dir/../<name>.true-calibration``; ``run_dir/calibration.toml`` is the solved file.
    """
    from dm2.cli.bench_runner import run_scenario
    from dm2.core.calibration_io import write_calibration_toml

    true_T_B_S, outcome, info = rehearsed_calibration(sc)
    run_true = run_scenario(sc, run_dir.with_name(run_dir.name + ".true-calibration"),
                            scenario_file=scenario_file, full_report=full_report,
                            true_T_B_S=true_T_B_S)
    run_solved = run_scenario(sc, run_dir, scenario_file=scenario_file,
                              full_report=full_report, calibration=outcome.calibration,
                              true_T_B_S=true_T_B_S)
    write_calibration_toml(outcome.calibration, run_dir / "calibration.toml",
                           outcome.provenance)
    return run_solved, run_true, info


def compare(score_solved: dict, score_true: dict) -> dict:
    """The chain's figures beside the true-calibration run's, for one scenario."""
    def figures(s):
        return {"false_tracks": len(s["false_tracks"]),
                "realtime_false_alarms": s["realtime_false_alarms"],
                "detected": [bool(f["detected"]) for f in s["faults"]],
                "reconstruction_rms_mm": s["reconstruction_rms_mm"]}

    a, b = figures(score_solved), figures(score_true)
    drms = (a["reconstruction_rms_mm"] - b["reconstruction_rms_mm"]
            if a["reconstruction_rms_mm"] is not None and b["reconstruction_rms_mm"] is not None
            else None)
    return {"solved": a, "true": b, "extra_false_tracks": a["false_tracks"] - b["false_tracks"],
            "same_detections": a["detected"] == b["detected"], "rms_difference_mm": drms}


def chain_summary(runs_true: dict, comparisons: dict, targets) -> dict:
    """bench.json's ``calibration`` section: the true-calibration summary and the chain's."""
    from dm2.bench.suite_score import summarize

    true_summary = summarize(runs_true, targets)
    keep = ("f1", "detected_faults", "missed_faults", "false_tracks", "realtime_false_alarms")
    return {"mode": "rehearsed", "true_calibration": {
                "summary": {k: true_summary.get(k) for k in keep}, "runs": runs_true},
            "comparison": comparisons,
            "extra_false_tracks": sum(c["extra_false_tracks"] for c in comparisons.values()),
            "same_detections": all(c["same_detections"] for c in comparisons.values()),
            "max_rms_difference_mm": max((abs(c["rms_difference_mm"]) for c in
                                          comparisons.values()
                                          if c["rms_difference_mm"] is not None),
                                         default=None)}
