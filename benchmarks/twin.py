"""Twin speed: simulated process seconds per wall second (goal: >= 50x real time).

Runs the default seven-sided scenario for its first ``--process-s`` seconds with all three
profilers, deposition and robot states and prints the median rate over ``--runs`` runs of:

- stream: consuming ``Simulation.messages`` (what ``dm2 run`` does in process): a worker
  thread runs a few chunks ahead, depositing and casting a balanced share of each profiler
  fan, while the calling thread yields states and casts the rest of the fan on a mirror of the
  height field (it gains only where the machine has a core to spare),
- stream, 2 idle cores: the stream's critical path, the larger of the CPU seconds of the
  calling thread and of the worker thread (what two idle cores would take; the wall-clock
  figures depend on what else shares the machine, so the load average is printed first),
- one thread: the same stream with ``scan_thread=False`` (everything on the calling thread),
- per-sample baseline: the same stream from the plain per-sample loop measured in the same
  process (one deposition call, one validated robot state per 250 Hz motion sample, and the
  profilers' numpy path), with the ratio of the two; the baseline is also checked to
  give the same messages, bit for bit,
- recorded: the stream written to MCAP (what ``dm2 simulate`` does),

plus the one-off setup (part, toolpath, executed motion) that precedes the clock.

    .venv/bin/python benchmarks/twin.py [--process-s 20] [--runs 3] [--scenario NAME]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

# run as a script, this folder would come first on sys.path and this file would shadow the
# twin package
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).parent.resolve()]
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dm2.core.config import load_scenario  # noqa: E402
from scenarios import DEFAULT_SCENARIO, resolve_scenario  # noqa: E402
from tests.oracles.simulate_numpy import per_sample_messages  # noqa: E402
from twin.stream.simulate import Simulation, simulate  # noqa: E402


def _same(a, b) -> bool:
    if type(a) is not type(b):
        return False
    for name, va in vars(a).items():
        vb = getattr(b, name)
        same = (np.array_equal(va, vb, equal_nan=va.dtype.kind == "f")
                if isinstance(va, np.ndarray) else va == vb)
        if not same:
            return False
    return True


def _consume(stream) -> tuple[float, float, Counter, float]:
    """Wall and CPU seconds to drain ``stream``, its message counts, and the CPU seconds of
    this (the calling) thread alone."""
    counts: Counter = Counter()
    t0, c0, th0 = time.perf_counter(), time.process_time(), time.thread_time()
    for msg in stream:
        counts[type(msg).__name__] += 1
    return (time.perf_counter() - t0, time.process_time() - c0, counts,
            time.thread_time() - th0)


def _rates(name: str, process_s: float, runs: list[tuple[float, float]]) -> float:
    """Print the median rate against wall time and against CPU time (the single-threaded
    figure on an idle core, whatever else shares the machine); return the wall rate."""
    wall = statistics.median(w for w, _ in runs)
    cpu = statistics.median(c for _, c in runs)
    print(f"{name:20s}: {process_s / wall:7.1f} x real time (median of {len(runs)}: "
          f"{wall:.2f} s wall); {process_s / cpu:7.1f} x per CPU second ({cpu:.2f} s CPU)")
    return process_s / wall


def _record_once(sim: Simulation, scenario, folder: Path) -> float:
    t0 = time.perf_counter()
    simulate(scenario, folder / "bench.mcap", simulation=sim)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default=DEFAULT_SCENARIO)
    ap.add_argument("--process-s", type=float, default=20.0)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--no-baseline", action="store_true", help="skip the per-sample baseline")
    args = ap.parse_args()

    scenario = load_scenario(resolve_scenario(args.scenario))
    scenario = scenario.model_copy(update={"duration_s": args.process_s})
    t0 = time.perf_counter()
    sim = Simulation(scenario)
    setup_s = time.perf_counter() - t0
    if not args.no_baseline:  # warm-up (numba compilation, caches) and the equality check
        mismatch = sum(not _same(a, b) for a, b in zip(sim.messages(), per_sample_messages(sim),
                                                         strict=True))
    else:
        _consume(sim.messages())
    streams, serials, baselines, counts, paths = [], [], [], Counter(), []
    for _ in range(args.runs):  # interleaved, so all see the same machine load
        wall, cpu, counts, calling = _consume(sim.messages())
        streams.append((wall, cpu))
        paths.append((calling, sim.worker_cpu_s, sim.spray_cpu_s, sim.worker_fan_share))
        serials.append(_consume(sim.messages(scan_thread=False))[:2])
        if not args.no_baseline:
            baselines.append(_consume(per_sample_messages(sim))[:2])
    with tempfile.TemporaryDirectory() as tmp:
        records = [_record_once(sim, scenario, Path(tmp)) for _ in range(args.runs)]
        size_mb = (Path(tmp) / "bench.mcap").stat().st_size / 1e6
    process_s = sim.end_s
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())} "
          f"({os.cpu_count()} CPUs)")
    print(f"scenario {scenario.name}: {process_s:.1f} s of process, "
          f"{counts['Profile']} profiles, {counts['RobotState']} robot states, "
          f"{counts['LayerMark']} layer marks; setup {setup_s:.2f} s")
    stream_x = _rates("stream", process_s, streams)
    serial_x = _rates("one thread", process_s, serials)
    print(f"stream / one thread = {stream_x / serial_x:.2f} (wall)")
    calling, worker, spray, share = (statistics.median(p[i] for p in paths) for i in range(4))
    print(f"{'stream, 2 idle cores':20s}: {process_s / max(calling, worker):7.1f} x real time "
          f"(critical path: calling thread {calling:.2f} s CPU, worker thread {worker:.2f} s "
          f"CPU of which deposition {spray:.2f} s; worker's share of each fan at the end "
          f"{share:.2f})")
    if baselines:
        base_x = _rates("per-sample baseline", process_s, baselines)
        print(f"stream / baseline = {stream_x / base_x:.2f} (wall); "
              f"messages differing from the baseline: {mismatch}")
    print(f"{'recorded':20s}: {process_s / statistics.median(records):7.1f} x real time "
          f"(median of {args.runs}: {statistics.median(records):.2f} s wall, {size_mb:.1f} MB)")


if __name__ == "__main__":
    main()
