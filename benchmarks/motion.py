"""Executed-motion throughput on the seven-sided part's toolpath (the default scenario).

Prints (median of 3 runs):
- IK solutions per wall second of the tracking kernel (one branch, seeded by the previous
  sample, 250 Hz poses of the whole build) and its ratio to calling ``ik`` pose by pose;
- executed-motion samples per wall second of ``execute_toolpath`` (path timing, sampling,
  plate poses, IK, FK) and the real-time factor (process seconds per wall second).
The goal is >= 12,500 IK solutions per second (the twin at 50x real time, 250 Hz).

    .venv/bin/python benchmarks/motion.py [--scenario seven_sided] [--runs 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))

import numpy as np  # noqa: E402

from dm2.core.config import load_scenario  # noqa: E402
from dm2.toolpath import generate_toolpath  # noqa: E402
from scenarios import resolve_scenario  # noqa: E402
from scenarios.parts import build_part  # noqa: E402
from twin.cell import kinematics as kin  # noqa: E402
from twin.cell.cell import CellModel  # noqa: E402
from twin.cell.motion import execute_toolpath  # noqa: E402


def _median_time(fn, runs: int) -> float:
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="seven_sided")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()

    sc = load_scenario(resolve_scenario(args.scenario))
    tp = generate_toolpath(build_part(sc.part, sc.cell.plate_size_mm), sc.toolpath)
    cell = CellModel.from_scenario(sc)
    em = execute_toolpath(tp, cell, rate_hz=cell.robot_state_hz)  # warm-up (numba compile)
    T_B_F = np.ascontiguousarray(em.T_B_F)
    m = T_B_F.shape[0]

    t_track = _median_time(lambda: kin.ik_track(T_B_F, cell.home_joints_rad, em.dt_s), args.runs)
    n_single = min(m, 5000)

    def single():
        q = cell.home_joints_rad
        for k in range(n_single):
            q = kin.ik(T_B_F[k], q)

    t_single = _median_time(single, args.runs) / n_single * m
    t_exec = _median_time(lambda: execute_toolpath(tp, cell, rate_hz=cell.robot_state_hz),
                          args.runs)
    print(f"scenario {sc.name}: {len(tp)} toolpath points, {m} samples at "
          f"{cell.robot_state_hz:g} Hz, {em.duration_s:.1f} s of process time")
    print(f"IK tracking kernel: {m / t_track:,.0f} IK solutions/s "
          f"({t_single / t_track:.1f}x pose-by-pose ik(), which does {m / t_single:,.0f}/s)")
    print(f"execute_toolpath: {m / t_exec:,.0f} samples/s, "
          f"{em.duration_s / t_exec:.0f}x real time (median of {args.runs})")


if __name__ == "__main__":
    main()
