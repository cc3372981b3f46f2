"""Report stage cost on a tower-sized run: at least 1,000 tracks over 124 layers.

Builds the synthetic run of :func:`dm2.report.synthetic.synthetic_run` (seeded; a 58,081-vertex
mesh per layer, the whole 120 mm plate at 0.5 mm, small defect regions living 1-5 layers each,
one real-time alarm per ten tracks), writes the whole report folder ``--runs`` times and prints
the median wall time of :func:`dm2.report.write_report` (goal: at most 20 s), with its CPU time
(the process's own, so comparable on a shared machine) and the load average. ``--keep DIR``
keeps one such report.

    .venv/bin/python benchmarks/report.py [--layers 124] [--tracks 1000] [--size-mm 120] [--runs 3]
        [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).parent.resolve()]
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dm2.report import ReportContent, write_report  # noqa: E402
from dm2.report.synthetic import synthetic_run  # noqa: E402

GOAL_S = 20.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layers", type=int, default=124)
    ap.add_argument("--tracks", type=int, default=1000)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--size-mm", type=float, default=120.0, help="side of the square mesh")
    ap.add_argument("--keep", type=Path, default=None, help="keep the last report here")
    args = ap.parse_args()
    t0 = time.perf_counter()
    results, tracks, realtime = synthetic_run(args.layers, args.tracks, size_mm=args.size_mm)
    print(f"fixture: {len(results)} layers, {len(tracks)} tracks, "
          f"{len(realtime['alarms'])} alarms, {results[0].deviation.n_vertices} vertices per "
          f"layer ({time.perf_counter() - t0:.1f} s to build)")
    times, cpu = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.runs):
            t0, c0 = time.perf_counter(), time.process_time()
            rep = write_report(Path(tmp) / "report", results, tracks,
                               ReportContent(sections={"realtime": realtime},
                                             meta={"scenario": "synthetic",
                                                   "layers": len(results)}))
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            print(f"run {k + 1}: {times[-1]:.2f} s wall, {cpu[-1]:.2f} s CPU "
                  f"({len(rep['files']['track_plots'])} track plots, "
                  f"{len(rep['files']['deviation_maps'])} maps), load average "
                  f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
        if args.keep is not None:
            if args.keep.exists():
                shutil.rmtree(args.keep)
            shutil.copytree(Path(tmp) / "report", args.keep)
    med = statistics.median(times)
    print(f"report stage: median {med:.2f} s wall ({statistics.median(cpu):.2f} s CPU) over "
          f"{len(times)} runs (goal <= {GOAL_S:.0f} s: {'met' if med <= GOAL_S else 'MISSED'})")


if __name__ == "__main__":
    main()
