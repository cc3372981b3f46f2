"""Benchmark: each scenario open loop and closed loop from the same seed, the final part (and
every layer) scored against the design intent (dm2.bench.intent).

Open loop runs the closed loop's cell program without corrections (``--compensate hold``: the
same pauses between layers, the powder off on the way); closed loop applies them.

Run: .venv/bin/python benchmarks/closed_loop.py SCENARIO.toml [...] [--tolerance 0.4]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

# this folder holds twin.py: take it off the path so `twin` is the package
_here = str(Path(__file__).resolve().parent)
sys.path[:] = [p for p in sys.path if str(Path(p or ".").resolve()) != _here]

import trimesh  # noqa: E402

import twin  # noqa: E402, F401  (the twin's scenario sections)
from dm2.bench.intent import score_top  # noqa: E402
from dm2.cli.bench_runner import run_scenario  # noqa: E402
from dm2.core.config import load_scenario  # noqa: E402
from twin.stream.simulate import Simulation  # noqa: E402

KEYS = ("out_of_tolerance_mm2", "out_of_tolerance_mm3", "max_abs_deviation_mm", "top_error_mm")


def arm(sc, mode: str, tmp: Path, tol: float) -> list[dict]:
    run = run_scenario(sc, tmp / mode, full_report=False, compensate=mode)
    tp = Simulation(sc, layer_pause_s=sc.control.layer_pause_s).toolpath
    scores = []
    for ply in sorted((run.run_dir / "truth").glob("layer_*.ply")):
        layer = int(ply.stem.split("_")[1])
        mesh = trimesh.load(ply, process=False)
        scores.append(score_top(mesh.vertices, tp, layer, sc.toolpath.layer_mm,
                                sc.toolpath.line_spacing_mm, tol))
    return scores


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenarios", nargs="+")
    ap.add_argument("--tolerance", type=float, default=0.4, help="[mm], default the "
                    "monitor's delta_global_mm")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for path in args.scenarios:
            sc = load_scenario(path)
            res = {m: arm(sc, m, Path(tmp) / sc.name, args.tolerance) for m in ("hold", "apply")}
            print(f"\n{sc.name}  (tolerance {args.tolerance} mm, footprint "
                  f"{res['hold'][-1]['footprint_mm2']:.0f} mm^2)")
            print(f"{'layer':>5} {'loop':>6} " + " ".join(f"{k:>22}" for k in KEYS))
            for o, c in zip(res["hold"], res["apply"], strict=False):
                for name, r in (("open", o), ("closed", c)):
                    print(f"{r['layer']:>5} {name:>6} " + " ".join(f"{r[k]:>22.3f}" for k in KEYS))


if __name__ == "__main__":
    main()
