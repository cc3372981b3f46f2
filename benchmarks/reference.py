"""Benchmark: the near-net reference's integration speed for tilted contour passes on a tall
part against the same passes on the plate.

A tilted spray at the top of a tall wall reaches down to the plate (the rays past the wall's
edge land ``height * tan(tilt)`` farther out), so its footprint's search grows with the part's
height (dm2.reference.tilted_band). Here a 35 degree contour pass runs around the top edge of
a 30 x 30 mm block of ``--height`` mm (the reference's map holds the block) and, as the
baseline in the same run, around the same outline on a bare plate. Both at 250 Hz robot states,
the default process and monitor configuration. Prints, per case, the median over ``--repeats``
of robot states per second and process seconds per wall second, and the ratio of the tall
part's time to the plate's (1.0: height costs nothing).

Run: ``.venv/bin/python benchmarks/reference.py [--height 80] [--repeats 5]``
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_reference import CAL, flange_poses  # noqa: E402

from dm2.core.config import MonitorConfig, ProcessConfig  # noqa: E402
from dm2.reference.model import NearNetReference  # noqa: E402

RATE_HZ = 250.0
SPEED_MM_S = 30.0
TILT_DEG = 35.0
BLOCK_MM = (45.0, 75.0)  # the block's x and y extent [mm, O]: a 30 mm square


def contour_pass() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps, spots (in the block's top plane, z 0) and axes of one contour 1 mm inside the
    block's edge, the spray tilted outwards across the edge by TILT_DEG."""
    lo, hi = BLOCK_MM[0] + 1.0, BLOCK_MM[1] - 1.0
    corners = np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi], [lo, lo]])
    outward = np.array([[0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
    spots, axes = [], []
    step = SPEED_MM_S / RATE_HZ
    t = math.radians(TILT_DEG)
    for k in range(4):
        a, b = corners[k], corners[k + 1]
        n = int(np.linalg.norm(b - a) / step)
        f = np.arange(n)[:, None] / n
        spots.append(a + (b - a) * f)
        axes.append(np.tile([outward[k, 0] * math.sin(t), outward[k, 1] * math.sin(t),
                             -math.cos(t)], (n, 1)))
    xy = np.concatenate(spots)
    stamps = np.arange(xy.shape[0]) / RATE_HZ
    return stamps, np.column_stack([xy, np.zeros(xy.shape[0])]), np.concatenate(axes)


def one_run(height_mm: float, stamps, spots_O, axes_O) -> float:
    """Wall seconds of one reference integrating the pass over the block of ``height_mm``."""
    ref = NearNetReference(ProcessConfig(), MonitorConfig(), CAL)
    n = ref.heights_mm.shape[0]
    c = (np.arange(n) + 0.5) * ref.cell_mm
    inside = ((c >= BLOCK_MM[0]) & (c < BLOCK_MM[1]))
    ref.heights_mm[np.ix_(inside, inside)] = height_mm
    ref.heights_written()
    pts = spots_O.copy()
    pts[:, 2] = height_mm
    poses = flange_poses(pts, axes_O)
    t0 = time.perf_counter()
    ref.add_states(stamps, poses)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--height", type=float, default=80.0, help="the block's height [mm]")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    stamps, spots, axes = contour_pass()
    one_run(args.height, stamps[:50], spots[:50], axes[:50])  # compile outside the timing
    process_s = float(stamps[-1])
    times = {}
    for name, h in (("plate", 0.0), (f"{args.height:g} mm block", args.height)):
        times[name] = statistics.median(one_run(h, stamps, spots, axes)
                                        for _ in range(args.repeats))
        print(f"35 deg contour pass around a 30 mm square, {name}: {stamps.size} states in "
              f"{times[name]:.3f} s (median of {args.repeats}) = {stamps.size / times[name]:,.0f} "
              f"states/s, {process_s / times[name]:.1f} process s per wall s")
    plate, tall = times.values()
    print(f"the tall part's pass against the plate's: {tall / plate:.2f}x the time")


if __name__ == "__main__":
    main()
