"""The fusion benchmark's growing part: the scene the monitor exists for, fused by ours and by
Open3D's ``VoxelBlockGrid`` (:mod:`open3d_peer`), timed and measured against the final truth.

A 40 x 40 mm block on the plate, its top at 10 mm, rises ``RISE_MM`` (0.8 mm, about what one
pass deposits in the twin) after each of ``PASSES`` passes. Each pass rasters the whole top
(lines along x every 2 mm, the spray spot on the top, as the static scene of
``benchmarks/fusion.py``), so each top is seen, then buried under the next. The truth is the
block at its final height: every top below it is now inside the part, and a vertex still on one
of them is an error of its depth under the final top.

Ours runs with the package defaults (the weights around the spray axis capped as the spot
passes: dm2.fusion.tsdf.deposit; buried free space carved: dm2.fusion.tsdf.carve), with merged
rays, and as a scan with the spray off (no deposit cap, weights averaged up to 1e4 like Open3D's
running mean), which fuses each new top into the old ones.
"""

from __future__ import annotations

import statistics

import numpy as np
import open3d_peer
from test_monitor_scene import Scene, raster_lines, raster_run

PASSES = 6
RISE_MM = 0.8       # per pass
START_MM = 10.0     # the first top's height
FOOTPRINT = ((40.0, 40.0), (80.0, 80.0))  # the block's x, y corners [mm, O]


def block(top_mm: float) -> Scene:
    (x0, y0), (x1, y1) = FOOTPRINT
    return Scene(boxes=[((x0, y0, -1.0), (x1, y1, top_mm))])


def growing_stream(cal, passes: int = PASSES):
    """``(messages in stamp order, the final block)`` of ``passes`` passes over the rising top."""
    msgs, t0, counter = [], 0.0, 0
    for k in range(passes):
        top = START_MM + RISE_MM * k
        m, _ = raster_run(block(top), cal, raster_lines((35, 85), np.arange(35, 86, 2.0), top),
                          step_mm=1.0, noise_mm=0.05, seed=10 + k, t0_s=t0, counter0=counter)
        msgs += m
        t0, counter = m[-1].stamp_s + 0.5, counter + len(m)
    return msgs, block(START_MM + RISE_MM * (passes - 1))


def accuracy(vertices_O: np.ndarray, final: Scene) -> tuple[float, float, int, float]:
    """RMS and p95 [mm] of ``|sdf|`` over all vertices, their number, and the median signed
    distance [mm] (negative: inside the part) of the vertices over the top: more than 1 mm inside
    the block's edges and above the first top less 1 mm, i.e. on the final top or on a buried
    one."""
    v = np.asarray(vertices_O, np.float64)
    rms, p95, n = open3d_peer.surface_error(v, final.sdf)
    (x0, y0), (x1, y1) = FOOTPRINT
    top = (v[:, 0] > x0 + 1) & (v[:, 0] < x1 - 1) & (v[:, 1] > y0 + 1) & (v[:, 1] < y1 - 1) & \
        (v[:, 2] > START_MM - 1)
    signed = float(np.median(final.sdf(v[top]))) if top.any() else float("nan")
    return rms, p95, n, signed


def compare(cal, repeats: int, run_once, configs: dict) -> None:
    """Print, for Open3D and each of ``configs`` (name: MonitorConfig or None for the
    defaults), the points per second on the growing part (median of ``repeats``, interleaved)
    and the accuracy of the last run's surface against the final block; Open3D and the surfaces
    with the package defaults' voxel, truncation, synchronisation and ``min_weight``.
    ``run_once``: the fusion benchmark's replay ``(cal, msgs, measure_latency, cfg=...) ->
    (TsdfFusion, seconds, _)``."""
    from dm2.core.config import MonitorConfig
    from dm2.fusion.surface import SurfaceExtractor

    cfg = MonitorConfig()
    msgs, final = growing_stream(cal)
    profiles = open3d_peer.synced_profiles(cal, msgs, cfg.max_pose_gap_s, cfg.reorder_window_s)
    rates: dict[str, list[float]] = {name: [] for name in ("Open3D", *configs)}
    last_run = {}
    for _ in range(repeats):
        o3d_field, dt = open3d_peer.open3d_run(profiles, cfg.voxel_mm, cfg.truncation_voxels)
        rates["Open3D"].append(o3d_field.points / dt)
        for name, run_cfg in configs.items():
            mon, elapsed, _ = run_once(cal, msgs, False, cfg=run_cfg)
            rates[name].append(mon.points_fused / elapsed)
            last_run[name] = mon
    errors = {name: accuracy(SurfaceExtractor(mon.tsdf, cfg.min_weight).update().vertices_O,
                             final) for name, mon in last_run.items()}
    errors["Open3D"] = accuracy(o3d_field.extract(cfg.min_weight)[0], final)
    o3d_rate = statistics.median(rates["Open3D"])
    print(f"growing part ({PASSES} passes over a 40 x 40 mm top rising {RISE_MM} mm a pass, "
          f"{o3d_field.points} points; accuracy against the final block, |sdf| at all "
          f"vertices, and the median signed error over the top, on the final top or a buried "
          f"one), median of {repeats}, interleaved:")
    for name in rates:
        rate = statistics.median(rates[name])
        rms, p95, n, signed = errors[name]
        print(f"  {name:<28} {rate / 1e6:6.2f} M points/s ({rate / o3d_rate:4.2f}x Open3D), "
              f"RMS {rms:.3f} mm, p95 {p95:.3f} mm, {n} vertices, over the top {signed:+.3f} mm")
