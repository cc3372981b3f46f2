"""Report stage cost on a tower-sized run: at least 1,000 tracks over 124 layers.

Builds the synthetic run of :func:`dm2.report.synthetic.synthetic_run` (seeded; a 40,401-vertex
mesh per layer, small defect regions living 1-5 layers each, one real-time alarm per ten
tracks), writes the whole report folder ``--runs`` times and prints the median wall time of
:func:`dm2.report.write_report` (goal: at most 20 s). ``--keep DIR`` keeps one such report.

    .venv/bin/python benchmarks/report.py [--layers 124] [--tracks 1000] [--runs 3] [--keep DIR]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).parent.resolve()]
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dm2.report import write_report  # noqa: E402
from dm2.report.synthetic import synthetic_run  # noqa: E402

GOAL_S = 20.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layers", type=int, default=124)
    ap.add_argument("--tracks", type=int, default=1000)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--keep", type=Path, default=None, help="keep the last report here")
    args = ap.parse_args()
    t0 = time.perf_counter()
    results, tracks, realtime = synthetic_run(args.layers, args.tracks)
    print(f"fixture: {len(results)} layers, {len(tracks)} tracks, "
          f"{len(realtime['alarms'])} alarms, {results[0].deviation.n_vertices} vertices per "
          f"layer ({time.perf_counter() - t0:.1f} s to build)")
    times = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.runs):
            t0 = time.perf_counter()
            rep = write_report(Path(tmp) / "report", results, tracks,
                               sections={"realtime": realtime},
                               meta={"scenario": "synthetic", "layers": len(results)})
            times.append(time.perf_counter() - t0)
            print(f"run {k + 1}: {times[-1]:.2f} s ({len(rep['files']['track_plots'])} track "
                  f"plots, {len(rep['files']['deviation_maps'])} maps)")
        if args.keep is not None:
            if args.keep.exists():
                shutil.rmtree(args.keep)
            shutil.copytree(Path(tmp) / "report", args.keep)
    med = statistics.median(times)
    print(f"report stage: median {med:.2f} s over {len(times)} runs (goal <= {GOAL_S:.0f} s: "
          f"{'met' if med <= GOAL_S else 'MISSED'})")


if __name__ == "__main__":
    main()
