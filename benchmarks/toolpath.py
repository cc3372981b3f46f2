"""Benchmark: time to plan the full twisted-tower toolpath (124 layers, 62 double layers).

Goal: under 5 s on the project's 2-core machine. Prints the median of 3 runs.
"""

from __future__ import annotations

import statistics
import time

from dm2.core.config import load_scenario
from dm2.toolpath import generate_toolpath
from scenarios import resolve_scenario
from scenarios.parts import build_part
from twin import schema as _twin_schema  # noqa: F401  types the [cell] table read below


def main(runs: int = 3) -> None:
    scenario = load_scenario(resolve_scenario("twisted_tower"))
    mesh = build_part(scenario.part, scenario.cell.plate_size_mm)
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        tp = generate_toolpath(mesh, scenario.toolpath)
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    print(f"twisted tower toolpath: {tp.n_layers} layers, {len(tp)} points")
    print(f"generate_toolpath median of {runs}: {med:.2f} s (goal < 5 s; runs "
          f"{', '.join(f'{t:.2f}' for t in times)})")


if __name__ == "__main__":
    main()
