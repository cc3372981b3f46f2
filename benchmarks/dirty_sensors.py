"""Per-artefact ablation of the profilers' ``[noise]``: each artefact alone, on a fault-free box.

A 22 x 16 x 8 mm box (10 layers of 0.8 mm, default toolpath, seed 1) is simulated on the twin
and monitored once with only the 0.05 mm range noise, then once per artefact with that
artefact alone at its level in the table below (the "realistic" preset's level,
``[noise] preset = "realistic"``, ``twin.schema.NOISE_PRESETS``), and once with the whole
preset. Printed per case: the reconstruction RMS against the
twin's true surface (the bench's check, :func:`dm2.bench.reconstruction.truth_checks`: the
RMS over layers of each layer's RMS, and the worst layer's), the share of profile points the
pipeline rejected before fusion (:mod:`dm2.fusion.point_filter`), false tracks and wall time.

    .venv/bin/python benchmarks/dirty_sensors.py [--only NAME ...] [--no-filter] [--seed 1]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).parent.resolve()]

import twin  # noqa: E402, F401  (registers the twin's scenario sections)
from dm2.cli.bench_runner import run_scenario, score_scenario_run  # noqa: E402
from dm2.core.config import parse_scenario  # noqa: E402

BASE_NOISE = {"range_sigma_mm": 0.05}
# each artefact alone: the [noise] keys it sets
ARTEFACTS: dict[str, dict] = {
    "none": {},
    "speckle": {"speckle_sigma_mm": 0.02},
    "dropout": {"dropout_prob": 0.02},
    "outliers": {"outlier_prob": 0.002},
    "plume": {"plume_particle_prob": 0.02},
    "ghost lines": {"ghost_line_prob": 0.05},
    "specular": {"specular_run_prob": 0.05},
    "bursts": {"burst_prob": 0.02},
    "jitter+lost": {"clock_jitter_ms": 1.0, "lost_profile_prob": 0.005},
    "drift": {"mount_drift_mm_min": 0.02},
    "realistic": {"preset": "realistic"},
}


def box(noise: dict, seed: int, point_filter: bool) -> dict:
    return {"schema": 1, "name": "dirty_sensors_box", "seed": seed,
            "part": {"generator": "box",
                     "params": {"width_mm": 22.0, "depth_mm": 16.0, "height_mm": 8.0}},
            "noise": {**BASE_NOISE, **noise},
            "monitor": {"point_filter": {"enabled": point_filter}}}


def run_case(noise: dict, seed: int, point_filter: bool) -> dict:
    sc = parse_scenario(box(noise, seed, point_filter), "benchmarks/dirty_sensors.py")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="dm2-dirty-") as tmp:
        run = run_scenario(sc, Path(tmp) / "run", full_report=False)
        score = score_scenario_run(run)
    layer_rms = [v["rms_mm"] for v in run.reconstruction.values()]
    pf = run.report.get("point_filter") or {}
    return {"rms": score["reconstruction_rms_mm"], "worst": max(layer_rms),
            "rejected": pf.get("share", 0.0), "false_tracks": len(score["false_tracks"]),
            "wall_s": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", choices=sorted(ARTEFACTS), help="these cases only")
    ap.add_argument("--no-filter", action="store_true",
                    help="fuse every point ([monitor.point_filter] enabled = false)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    names = args.only or list(ARTEFACTS)
    print(f"box 22 x 16 x 8 mm, 10 layers, seed {args.seed}, point filter "
          f"{'off' if args.no_filter else 'on'}")
    print(f"{'artefact':>12} {'level':>34} {'RMS mm':>7} {'worst':>7} {'rejected':>9} "
          f"{'false tr':>8} {'wall s':>7}")
    for name in names:
        r = run_case(ARTEFACTS[name], args.seed, not args.no_filter)
        level = ", ".join(f"{k}={v}" for k, v in ARTEFACTS[name].items()) or "range noise only"
        print(f"{name:>12} {level[:34]:>34} {r['rms']:7.3f} {r['worst']:7.3f} "
              f"{100 * r['rejected']:8.3f}% {r['false_tracks']:8d} {r['wall_s']:7.1f}",
              flush=True)


if __name__ == "__main__":
    main()
