"""Bench speed: real-time factor of the monitor (and of monitor + twin) on a bench scenario.

Runs one scenario of a suite ``--runs`` times in process (the same call ``dm2 bench`` makes)
and prints the medians of:

- monitor real-time factor: simulated process seconds per wall second spent in the pipeline
  (fusion, near-net reference, per-layer analysis) — the figure that matters on a real cell;
- end-to-end factor: process seconds per wall second of the whole run, twin included;
- wall seconds per run (report.json only, no pictures).

    .venv/bin/python benchmarks/bench.py [--suite regression] [--scenario feed_step] [--runs 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).parent.resolve()]
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dm2.bench.suites import load_suite_scenario, resolve_suite  # noqa: E402
from dm2.cli.bench_runner import run_scenario, score_scenario_run  # noqa: E402
from scenarios import scenario_dir  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default="regression")
    ap.add_argument("--scenario", default="feed_step")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    _, files = resolve_suite(args.suite, scenario_dir() / "suites")
    (path,) = [f for f in files if f.stem == args.scenario]
    sc = load_suite_scenario(path)
    rtf, e2e, wall = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.runs + 1):  # the first run warms the numba caches
            run = run_scenario(sc, Path(tmp) / f"r{k}", full_report=False)
            score = score_scenario_run(run)
            if k:
                rtf.append(score["realtime_factor"])
                e2e.append(score["realtime_factor_with_twin"])
                wall.append(run.wall_s)
    print(f"{args.suite}/{args.scenario}: {run.process_s:.1f} s of process, "
          f"{score['layers']} layers, median of {args.runs} runs")
    print(f"monitor real-time factor: {statistics.median(rtf):.1f}x")
    print(f"end-to-end (twin + monitor) factor: {statistics.median(e2e):.1f}x")
    print(f"wall per run: {statistics.median(wall):.2f} s")


if __name__ == "__main__":
    main()
