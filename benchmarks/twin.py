"""Twin speed: simulated process seconds per wall second (goal: >= 50x real time).

Runs the default seven-sided scenario for its first ``--process-s`` seconds with all three
profilers, deposition and robot states, three times, and prints the median rates:

- stream: consuming ``Simulation.messages`` (what ``dm2 run`` does in process),
- recorded: the same stream written to MCAP (what ``dm2 simulate`` does),

plus the one-off setup (part, toolpath, executed motion) that precedes the clock.

    .venv/bin/python benchmarks/twin.py [--process-s 20] [--runs 3] [--scenario NAME]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dm2.config import load_scenario  # noqa: E402
from scenarios import DEFAULT_SCENARIO, resolve_scenario  # noqa: E402
from twin.simulate import Simulation, simulate  # noqa: E402


def _stream_once(sim: Simulation) -> tuple[float, Counter]:
    counts: Counter = Counter()
    t0 = time.perf_counter()
    for msg in sim.messages():
        counts[type(msg).__name__] += 1
    return time.perf_counter() - t0, counts


def _record_once(sim: Simulation, scenario, folder: Path) -> float:
    t0 = time.perf_counter()
    simulate(scenario, folder / "bench.mcap", simulation=sim)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default=DEFAULT_SCENARIO)
    ap.add_argument("--process-s", type=float, default=20.0)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()

    scenario = load_scenario(resolve_scenario(args.scenario))
    scenario = scenario.model_copy(update={"duration_s": args.process_s})
    t0 = time.perf_counter()
    sim = Simulation(scenario)
    setup_s = time.perf_counter() - t0
    _stream_once(sim)  # warm-up: numba compilation and caches
    streams, counts = [], Counter()
    for _ in range(args.runs):
        wall, counts = _stream_once(sim)
        streams.append(wall)
    with tempfile.TemporaryDirectory() as tmp:
        records = [_record_once(sim, scenario, Path(tmp)) for _ in range(args.runs)]
        size_mb = (Path(tmp) / "bench.mcap").stat().st_size / 1e6
    process_s = sim.end_s
    print(f"scenario {scenario.name}: {process_s:.1f} s of process, "
          f"{counts['Profile']} profiles, {counts['RobotState']} robot states, "
          f"{counts['LayerMark']} layer marks; setup {setup_s:.2f} s")
    print(f"stream   : {process_s / statistics.median(streams):7.1f} x real time "
          f"(median of {args.runs}: {statistics.median(streams):.2f} s wall)")
    print(f"recorded : {process_s / statistics.median(records):7.1f} x real time "
          f"(median of {args.runs}: {statistics.median(records):.2f} s wall, {size_mb:.1f} MB)")


if __name__ == "__main__":
    main()
