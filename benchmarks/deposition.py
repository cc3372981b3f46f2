"""Benchmark: SprayModel deposition steps per second at 250 Hz motion samples.

A serpentine raster over a 40 x 40 mm pad on the default 120 x 120 mm plate at 0.25 mm cells,
default process (12 g/min, 20000 packets/s: 80 packets per 4 ms step). Prints the median over
several repeats of steps per second and of simulated process seconds per wall second, for the
per-step call and the batched call, normal infill and 35 degree tilted edge sprays.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

# run as a script, this folder would come first on sys.path and benchmarks/twin.py would shadow
# the twin package
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).parent.resolve()]

from dm2.core.config import ProcessConfig  # noqa: E402
from twin.world.coupon import raster_spots  # noqa: E402
from twin.world.deposition import SprayModel  # noqa: E402
from twin.world.heightfield import HeightField  # noqa: E402

RATE_HZ = 250.0
DT = 1.0 / RATE_HZ


def run(axis, batched: bool, spots) -> float:
    hf = HeightField((120.0, 120.0), 0.25, 6.0)
    model = SprayModel(ProcessConfig(), seed=1)
    axes = np.tile(axis, (len(spots), 1))
    t0 = time.perf_counter()
    if batched:
        for k in range(0, len(spots), 25):  # 25 samples = one 10 Hz scan interval
            model.deposit_samples(hf, spots[k:k + 25], axes[k:k + 25], DT)
    else:
        for k in range(len(spots)):
            model.deposit(hf, spots[k], axes[k], DT)
    return len(spots) / (time.perf_counter() - t0)


def main() -> None:
    spots = raster_spots(40.0, 2.0, 30.0, 60.0)  # the 40 x 40 mm pad at x, y 40-80 mm
    a = math.radians(35.0)
    cases = {"infill (normal)": np.array([0.0, 0.0, -1.0]),
             "edge (35 deg tilt)": np.array([math.sin(a), 0.0, -math.cos(a)])}
    run(cases["infill (normal)"], True, spots[:50])  # compile
    run(cases["edge (35 deg tilt)"], False, spots[:50])
    print(f"{len(spots)} samples per run ({len(spots) * DT:.1f} s of process time)")
    for name, axis in cases.items():
        for batched in (False, True):
            rates = [run(axis, batched, spots) for _ in range(5)]
            r = float(np.median(rates))
            api = "deposit_samples (25/call)" if batched else "deposit (1/call)"
            print(f"{name:20s} {api:26s}: {r:9.0f} steps/s = {1e6 / r:6.1f} us/step = "
                  f"{r / RATE_HZ:6.1f} process s per wall s")


if __name__ == "__main__":
    main()
