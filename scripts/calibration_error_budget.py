"""Error budget of the hand-eye calibration: what each profiler intrinsic error costs.

Rehearses the calibration run in the twin (its own profilers; range noise, speckle, dropouts,
ghosts, robot repeatability, the artifact within its certificate, sensors as built off the
CAD layout, CAD prior) once per seed and per error case: no intrinsic error, each intrinsic
error alone, all together. The poses are those calibration.toml gets (ranges as reported);
the range scale is co-estimated in a second solve and reported beside. Prints a Markdown
table (worst sensor over the seeds) and writes JSON.

    python scripts/calibration_error_budget.py --seeds 5 --poses 48 --out budget.json
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from calib.artifact import load_artifact
from calib.procedure import first_pass_refiner, solve_run
from calib.solver import ISO9283_RP_PER_SIGMA, SolverOptions
from dm2.core.config import load_scenario
from dm2.core.frames import pose_error
from scenarios import resolve_scenario, scenario_dir
from twin.cell.cell import CellModel
from twin.stream.rehearsal import RehearsalConfig, rehearse_calibration

CASES = {
    "none": {},
    "z scale 0.1 %": {"z_scale_error": 0.001},
    "fan angle 0.05 deg": {"fan_angle_offset_deg": 0.05},
    "x distortion 0.03 mm": {"x_distortion_mm": 0.03},
    "all three": {"z_scale_error": 0.001, "fan_angle_offset_deg": 0.05,
                  "x_distortion_mm": 0.03},
}


def run_case(sc, art, seed: int, poses: int, errors: dict, estimate_z: bool) -> dict:
    noise = sc.noise.model_copy(update={"range_sigma_mm": 0.03, "speckle_sigma_mm": 0.01,
                                        "dropout_prob": 0.02, "outlier_prob": 0.002})
    cfg = RehearsalConfig(n_poses=poses, seed=seed, noise=noise, robot_repeatability_mm=0.02,
                          **errors)
    nominal = art.with_mount(CellModel.from_scenario(sc).T_F_O)
    sim = rehearse_calibration(sc, art, cfg, refine=first_pass_refiner(nominal))
    opt = SolverOptions(robot_sigma_mm=0.02 / ISO9283_RP_PER_SIGMA, estimate_z_scale=estimate_z)
    out = solve_run(sim.messages, art, sim.prior, opt, sim.touch_T_B_F, holdout_every=4)
    zs = out.z_scale or {}
    sensors = {}
    for sid, est in out.result.sensors.items():
        dt, dr = pose_error(est.T_B_S, sim.truth.T_B_S[sid])
        sensors[sid] = {"translation_error_mm": dt, "rotation_error_deg": float(np.degrees(dr)),
                        "residual_rms_mm": est.residual_rms_mm,
                        "true_z_scale_error": sim.intrinsics[sid].z_scale_error,
                        "estimated_z_scale_error": zs[sid][0] if estimate_z else None,
                        "sigma_z_scale_error": zs[sid][1] if estimate_z else None}
    return {"sensors": sensors, "holdout_rms_mm": out.holdout["rms_mm"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--poses", type=int, default=48)
    ap.add_argument("--scenario", default="pad")
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--out", default="calibration_error_budget.json")
    args = ap.parse_args()
    sc = load_scenario(resolve_scenario(args.scenario))
    art = load_artifact(scenario_dir() / "artifacts" / "four_spheres.toml")
    results = {}
    out = sys.stdout
    out.write("| case | worst t error mm | worst r error deg | worst held-out RMS mm | "
              "worst z-scale estimate error (sigma) |\n|---|---|---|---|---|\n")
    for name in args.cases.split(","):
        runs = [run_case(sc, art, s, args.poses, CASES[name], True) for s in range(args.seeds)]
        results[name] = runs
        sens = [v for r in runs for v in r["sensors"].values()]
        zerr = [abs(v["estimated_z_scale_error"] - v["true_z_scale_error"]) for v in sens]
        zsig = max(v["sigma_z_scale_error"] for v in sens)
        out.write(f"| {name} | {max(v['translation_error_mm'] for v in sens):.4f} | "
                  f"{max(v['rotation_error_deg'] for v in sens):.4f} | "
                  f"{max(r['holdout_rms_mm'] for r in runs):.4f} | "
                  f"{max(zerr):.5f} ({zsig:.5f}) |\n")
        out.flush()
    with open(args.out, "w", encoding="utf-8") as f:
        json.dump({"seeds": args.seeds, "poses": args.poses, "results": results}, f, indent=1)


if __name__ == "__main__":
    main()
