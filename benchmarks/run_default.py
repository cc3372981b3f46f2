"""Benchmark: wall time of the default ``dm2 run`` from a cold start (goal <= 2 min).

Each repeat starts a fresh ``dm2 run`` process (interpreter start, imports, numba cache loads,
twin, pipeline, report), so the figure is what a user waits for. Prints every run and the median.

Run: .venv/bin/python benchmarks/run_default.py [--repeats 3] [--scenario NAME] [--record]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scenario", default=None, help="default: the shipped default scenario")
    ap.add_argument("--record", action="store_true", help="also record run.mcap (dm2 default)")
    args = ap.parse_args()
    dm2 = Path(sys.executable).with_name("dm2")
    walls = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.repeats):
            cmd = [str(dm2), "run", "--out", f"{tmp}/run{k}"]
            cmd += [args.scenario] if args.scenario else []
            cmd += [] if args.record else ["--no-record"]
            t0 = time.perf_counter()
            done = subprocess.run(cmd, capture_output=True, text=True)
            wall = time.perf_counter() - t0
            if done.returncode != 0:
                sys.exit(f"dm2 run failed ({done.returncode}):\n{done.stderr[-2000:]}")
            walls.append(wall)
            print(f"run {k + 1}: {wall:.1f} s")
    med = statistics.median(walls)
    print(f"default dm2 run, cold start: median {med:.1f} s over {len(walls)} runs "
          f"(goal <= 120 s: {'met' if med <= 120 else 'missed'})")


if __name__ == "__main__":
    main()
